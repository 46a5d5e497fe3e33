"""P-values of a decoded message's agreement with a key, under "no watermark".

Both tests rest on one fact, not on a model of the decoder's output: the keys were drawn uniformly at random,
independently of the image and of the decoder. For an unwatermarked image with logits ``ℓ [L]``, the
agreement pattern ``ε_i = +1`` where the decoded bit ``ℓ_i > 0`` equals the key's bit, else ``−1``, is then
``L`` fair coin flips independent of ``|ℓ|``, whatever the decoder does with the image.

That holds for a decoder fixed before the keys were drawn (the shipped one, a ``--decoder`` file). Phase 2 of
the embedding trains the decoder with the keys, and such a decoder can be drawn towards them on clean images
too (its reads of clean images collapse onto a few patterns near the keys): then the p-values are nominal,
and the false claims measured on clean images (``scripts/false_claims.py``) are the figure to trust. The
embedding's clean terms teach it to read clean images as a word far from every key (``keys.null_message``).

- **binomial** (the count of agreeing bits ``k``): ``p = P[Bin(L, ½) ≥ k]``.
- **sign_flip** (the agreement weighted by confidence, ``S = Σ_i w_i ε_i`` with ``w_i ∝ |ℓ_i|``):
  ``p = P[Σ_i w_i η_i ≥ S]`` for fair signs ``η``, computed exactly (:func:`sign_flip_tail`). It is the same
  randomisation test with a statistic that lets a doubtful bit count for less, so a message read right but
  for its least confident bit or two still passes a threshold that the count alone would miss. With equal
  weights it is the binomial test.

Both are exact for one key; over ``N`` keys the caller corrects by Bonferroni (``min(1, N·p)``). Neither can
go below ``2^-L``: with 16 bits and 16 keys the corrected p-value is at least 2.4e-4.
"""

from __future__ import annotations

import math

import numpy as np

ID_TESTS = ("binomial", "sign_flip")
# Largest total weight Σ w_i of the sign-flip statistic: the exact null distribution is an array of
# 2·Σw + 1 probabilities, updated once per bit. Logits are scaled to integers with this much resolution
# (at 16 bits the largest |ℓ| maps to 512); the rounding only changes the statistic, never the test's
# validity, since the weights are still a function of |ℓ| alone.
MAX_TOTAL_WEIGHT = 1 << 13


def binomial_tail(k: int, n: int) -> float:
    """``P[X ≥ k]`` for ``X ~ Bin(n, ½)``, exact (integer arithmetic)."""
    k = max(int(k), 0)
    if k > n:
        return 0.0
    return sum(math.comb(n, j) for j in range(k, n + 1)) / float(1 << n)


def sign_flip_tail(weights: np.ndarray, observed: int) -> float:
    """``P[Σ_i w_i η_i ≥ observed]`` for independent fair signs ``η_i = ±1`` and integer ``weights ≥ 0``.

    Exact: the distribution of the sum is built bit by bit over the integers ``[−Σw, Σw]`` (probabilities
    are multiples of ``2^-L``, exact in float64 up to L = 52).
    """
    w = np.asarray(weights, np.int64).reshape(-1)
    if (w < 0).any():
        raise ValueError(f"sign-flip weights must be ≥ 0, got {w.tolist()}")
    w = w[w > 0]
    total = int(w.sum())
    if observed > total:
        return 0.0
    if observed <= -total:
        return 1.0
    if (w == w[0]).all():  # equal weights: w·(2X − n) ≥ observed with X ~ Bin(n, ½)
        n = len(w)
        return binomial_tail(-((-(observed + n * int(w[0]))) // (2 * int(w[0]))), n)
    dist = np.zeros(2 * total + 1)
    dist[total] = 1.0
    reach = 0  # the distribution is zero outside [total − reach, total + reach]
    for wi in sorted(w.tolist()):
        lo, hi = total - reach, total + reach + 1
        new = np.zeros_like(dist)
        new[lo + wi : hi + wi] += 0.5 * dist[lo:hi]
        new[lo - wi : hi - wi] += 0.5 * dist[lo:hi]
        dist, reach = new, reach + wi
    return float(dist[observed + total :].sum())


def sign_flip_weights(logits: np.ndarray) -> np.ndarray:
    """Integer weights ``[B, L]`` ∝ ``|ℓ|`` per message; the largest is ``MAX_TOTAL_WEIGHT // L`` (≥ 1)."""
    a = np.abs(np.atleast_2d(np.asarray(logits, np.float64)))
    scale = max(1, MAX_TOTAL_WEIGHT // a.shape[-1])
    top = a.max(axis=-1, keepdims=True)
    return np.rint(np.divide(a * scale, top, out=np.zeros_like(a), where=top > 0)).astype(np.int64)


def sign_flip_p_values(logits: np.ndarray, agree: np.ndarray) -> np.ndarray:
    """Sign-flip p-values ``[B]`` of messages ``logits [B, L]`` whose bits agree (``agree [B, L]``, bool)
    with the key each is tested against."""
    weights = sign_flip_weights(logits)
    agree = np.atleast_2d(np.asarray(agree, bool))
    if agree.shape != weights.shape:
        raise ValueError(f"agreement {agree.shape} does not match the logits {weights.shape}")
    observed = np.where(agree, weights, -weights).sum(axis=-1)
    return np.array([sign_flip_tail(w, int(s)) for w, s in zip(weights, observed, strict=True)], np.float64)


def binomial_p_values(agreement: np.ndarray, bits: int) -> np.ndarray:
    """Binomial p-values ``[B]`` of ``agreement [B]`` agreeing bits out of ``bits``."""
    return np.array([binomial_tail(int(k), bits) for k in np.reshape(agreement, -1)], np.float64)


def check_test(name: str) -> str:
    """``name`` if it is one of :data:`ID_TESTS`, else ValueError naming them."""
    if name not in ID_TESTS:
        raise ValueError(f"unknown identification test {name!r} (known: {', '.join(ID_TESTS)})")
    return name
