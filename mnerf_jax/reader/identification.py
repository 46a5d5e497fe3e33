"""Identification of a watermark ID from decoded logits: the best-matching key, its p-values, the decision.

A decoded message (``L`` logits ``ℓ``, bits ``b = ℓ > 0``) is compared with every key
``m_n``. The best match is the key with the largest soft correlation ``Σ_i ℓ_i (2 m_n,i − 1)``
(:func:`identify_logits`, what evaluation and ``mnerf extract`` use): soft-decision decoding, the
maximum-likelihood key when the logits are equally scaled noisy readings of ``±1`` (the decoder's whitening
layer scales them alike), so a confident bit outweighs a doubtful one; counting agreeing bits alone
(:func:`identify`, hard decisions) throws that away and leaves ties. With ``k`` the agreeing bits of the
chosen key, under the null hypothesis (no watermark: decoded bits are fair coin flips independent of the
keys) the agreement with one fixed key is ``X ~ Bin(L, ½)``, so

    p = P[X ≥ k] = Σ_{j≥k} C(L, j) / 2^L

and, as one of ``N`` keys was picked, the Bonferroni-corrected ``p_N = min(1, N·p)`` bounds the chance
that *any* key agrees this well by luck (the chosen key agrees at most as well as the best-agreeing one, so
picking it by soft correlation keeps the bound). The decision rule: report the best-matching ID when
``p_N < threshold`` (default :data:`DEFAULT_THRESHOLD` = 1e-3, i.e. at most one false claim per thousand
unwatermarked images while the decoder does not know the keys; one fine-tuned with them in phase 2 can claim
more, which evaluation measures on the clean renders), otherwise "no watermark" (ID −1). A tie between two
keys at the best score is undecided (−1) too. An image read C times (a geometry search's candidates,
:func:`identify_best_read`) keeps its best (read, key) pair, corrected over the C·N pairs: ``min(1, C·N·p)``.

The decision may use the sign-flip test instead (``test="sign_flip"``, `significance.py`): the same null
hypothesis, the agreement weighted by each bit's confidence, so a match wrong only in its most doubtful bits
still passes. Both p-values are always reported.

The smallest attainable ``p_N`` is ``N / 2^L`` (all bits agree): with short messages and many IDs the
threshold may be out of reach whatever the accuracy (4 IDs × 8 bits: 0.0156). Results therefore report both
the *best-match* identification accuracy (the argmax is the rendered ID) and the *verified* one (argmax
correct and ``p_N < threshold``), plus ``min_attainable_p`` so a reader can tell the two apart.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from mnerf_jax.reader import significance

DEFAULT_THRESHOLD = 1e-3
NO_WATERMARK = -1


# ---------------------------------------------------------------------------------------------- bits


def logits_to_bits(logits: np.ndarray) -> np.ndarray:
    """Decoded bits ``[..., L]`` uint8: 1 where the logit is > 0."""
    return (np.asarray(logits) > 0).astype(np.uint8)


def bit_accuracy(bits: np.ndarray, message: np.ndarray) -> np.ndarray:
    """Fraction of matching bits ``[...]`` between decoded ``bits [..., L]`` and ``message [..., L]``."""
    return np.mean(np.asarray(bits, np.uint8) == np.asarray(message, np.uint8), axis=-1)


# ----------------------------------------------------------------------------------------- identification


@dataclasses.dataclass(frozen=True)
class Identification:
    """Identification of a batch of ``B`` decoded messages against ``N`` keys.

    best_id [B]                 the best-matching key (−1 on a tie)
    agreement [B]               agreeing bits with that key
    bit_accuracy [B]            agreement / L
    p_value [B]                 binomial: P[Bin(L, ½) ≥ agreement]
    p_corrected [B]             min(1, C·N·p_value)
    p_value_sign_flip [B]       the sign-flip test's p-value of the same match (significance.py)
    p_corrected_sign_flip [B]   min(1, C·N·p_value_sign_flip)
    decision [B]                best_id where ``test``'s corrected p-value < threshold, else −1 (no watermark)

    ``reads`` (C, default 1): how many reads of each image the match was chosen among by its p-value
    (:func:`identify_best_read`, a geometry search's candidates); Bonferroni then corrects over C·N pairs.
    """

    best_id: np.ndarray
    agreement: np.ndarray
    p_value: np.ndarray
    p_value_sign_flip: np.ndarray
    threshold: float
    test: str
    bits: int
    num_ids: int
    reads: int = 1

    @property
    def bit_accuracy(self) -> np.ndarray:
        return self.agreement / self.bits

    @property
    def comparisons(self) -> int:
        """The (read, key) pairs the best match was chosen among: the Bonferroni factor C·N."""
        return self.reads * self.num_ids

    @property
    def p_corrected(self) -> np.ndarray:
        return np.minimum(1.0, self.comparisons * self.p_value)

    @property
    def p_corrected_sign_flip(self) -> np.ndarray:
        return np.minimum(1.0, self.comparisons * self.p_value_sign_flip)

    @property
    def min_attainable_p(self) -> float:
        return min_attainable_p(self.comparisons, self.bits)

    @property
    def decision(self) -> np.ndarray:
        return self.decision_by(self.test)

    def decision_by(self, test: str) -> np.ndarray:
        """Decisions ``[B]`` had ``test`` judged the same best matches at the same threshold."""
        p = self.p_corrected if significance.check_test(test) == "binomial" else self.p_corrected_sign_flip
        return np.where(p < self.threshold, self.best_id, NO_WATERMARK).astype(np.int64)


def min_attainable_p(comparisons: int, bits: int) -> float:
    """The smallest corrected p-value a read can give: every bit of a ``bits``-bit key agreeing, corrected
    over ``comparisons`` (read, key) pairs (both tests: the sign-flip p-value is at least 2^-L too)."""
    return min(1.0, comparisons / float(1 << bits))


def identify(
    decoded: np.ndarray, messages: np.ndarray, threshold: float = DEFAULT_THRESHOLD, test: str = "binomial"
) -> Identification:
    """Best-matching key by agreeing bits (hard decisions), its p-values and the decision.

    Args:
      decoded: ``[B, L]`` decoded bits (or ``[L]``).
      messages: ``[N, L]`` keys.
      threshold: decision threshold on the Bonferroni-corrected p-value of ``test``.
      test: ``binomial`` or ``sign_flip`` (with hard bits every weight is equal: the same p-value).
    """
    messages = np.asarray(messages, np.uint8)
    bits = np.atleast_2d(np.asarray(decoded, np.uint8))
    agree = _agreement(bits, messages)
    return _identification(agree, agree, 2.0 * bits - 1.0, messages, threshold, test)


def identify_logits(
    logits: np.ndarray, messages: np.ndarray, threshold: float = DEFAULT_THRESHOLD, test: str = "binomial"
) -> Identification:
    """Best-matching key by soft correlation ``Σ ℓ_i (2 m_i − 1)`` (module docstring), its p-values (binomial
    on its agreeing bits ``ℓ > 0``; sign-flip on the agreement weighted by ``|ℓ|``) and the decision.

    Args:
      logits: ``[B, L]`` decoder logits (or ``[L]``).
      messages: ``[N, L]`` keys.
      threshold: decision threshold on the Bonferroni-corrected p-value of ``test``.
      test: ``binomial`` (default) or ``sign_flip``.
    """
    logits = np.atleast_2d(np.asarray(logits, np.float64))
    messages = np.asarray(messages, np.uint8)
    agree = _agreement(logits_to_bits(logits), messages)
    signs = 2.0 * messages.astype(np.float64) - 1.0
    return _identification(logits @ signs.T, agree, logits, messages, threshold, test)


def identify_best_read(
    logits: np.ndarray, messages: np.ndarray, threshold: float = DEFAULT_THRESHOLD, test: str = "binomial"
) -> tuple[Identification, np.ndarray]:
    """The best-supported (read, key) pair of each image among ``C`` reads of it, and the read chosen.

    Each read is matched as :func:`identify_logits` does; the read kept is the one whose best match has the
    smallest p-value under ``test`` (then under the other test; a tie between keys counts last; then the
    first read). Under "no watermark" each read's p-value is valid for each key, so the smallest over
    C·N pairs is below ``t`` with probability at most ``C·N·t`` (Bonferroni, whatever the reads'
    dependence): the result's ``reads`` = C puts that factor into every corrected p-value.

    Args:
      logits: ``[B, C, L]`` decoder logits of C reads of each of B images.
      messages: ``[N, L]`` keys.
      threshold, test: as :func:`identify_logits`.

    Returns:
      ``(identification of the chosen reads [B], chosen read per image [B] int64)``.
    """
    logits = np.asarray(logits, np.float64)
    if logits.ndim != 3:
        raise ValueError(f"expected logits [B, C, L] of C reads per image, got shape {logits.shape}")
    b, c, bits = logits.shape
    every = identify_logits(logits.reshape(b * c, bits), messages, threshold, test)
    first, second = (
        (every.p_value, every.p_value_sign_flip)
        if significance.check_test(test) == "binomial"
        else (every.p_value_sign_flip, every.p_value)
    )
    image, read = np.repeat(np.arange(b), c), np.tile(np.arange(c), b)
    # np.lexsort sorts by its last key first: by image, then the smallest p, the other test's, a tie between
    # keys last, the read's order; each image's C rows stay together, its chosen one first.
    ranked = np.lexsort((read, every.best_id < 0, second, first, image))
    chosen = read[ranked[::c]].astype(np.int64)
    pick = ranked[::c]
    ident = dataclasses.replace(
        every,
        best_id=every.best_id[pick],
        agreement=every.agreement[pick],
        p_value=every.p_value[pick],
        p_value_sign_flip=every.p_value_sign_flip[pick],
        reads=c,
    )
    return ident, chosen


def _agreement(bits: np.ndarray, messages: np.ndarray) -> np.ndarray:
    """Agreeing bits ``[B, N]`` of decoded ``bits [B, L]`` with each key of ``messages [N, L]``."""
    if bits.shape[-1] != messages.shape[-1]:
        raise ValueError(f"decoded messages have {bits.shape[-1]} bits, the keys {messages.shape[-1]}")
    return (bits[:, None, :] == messages[None, :, :]).sum(-1)


def _identification(
    scores: np.ndarray,
    agree: np.ndarray,
    logits: np.ndarray,
    messages: np.ndarray,
    threshold: float,
    test: str,
) -> Identification:
    """The key of highest ``scores [B, N]`` (−1 on a tie), judged by its agreeing bits ``agree [B, N]`` and by
    the agreement of ``logits [B, L]`` with it weighted by confidence."""
    significance.check_test(test)
    n_ids, bits = messages.shape
    top = scores.max(axis=1)
    best_id = scores.argmax(axis=1)
    tie = (scores == top[:, None]).sum(axis=1) > 1
    best = np.take_along_axis(agree, best_id[:, None], axis=1)[:, 0]
    p_flip = significance.sign_flip_p_values(logits, logits_to_bits(logits) == messages[best_id])
    best_id = np.where(tie, NO_WATERMARK, best_id)  # a tie is undecided under either test
    return Identification(
        best_id=best_id.astype(np.int64),
        agreement=best.astype(np.int64),
        p_value=significance.binomial_p_values(best, bits),
        p_value_sign_flip=p_flip,
        threshold=float(threshold),
        test=test,
        bits=int(bits),
        num_ids=int(n_ids),
    )


def confusion_matrix(true_ids: Sequence[int], predicted: Sequence[int], num_ids: int) -> np.ndarray:
    """``[N, N + 1]`` counts: row = rendered ID, column = predicted ID, last column = none / undecided."""
    out = np.zeros((num_ids, num_ids + 1), np.int64)
    for t, p in zip(true_ids, predicted, strict=True):
        out[int(t), int(p) if 0 <= int(p) < num_ids else num_ids] += 1
    return out


def _fraction(mask: np.ndarray) -> float:
    """Mean of a boolean array; NaN when it is empty."""
    return float(mask.mean()) if mask.size else math.nan


def _by_test(ident: Identification, rate: Callable[[np.ndarray], float]) -> dict[str, float]:
    """``rate`` of the decisions each test makes of the same best matches at the same threshold."""
    return {test: rate(ident.decision_by(test)) for test in significance.ID_TESTS}


def identification_summary(true_ids: Sequence[int], ident: Identification) -> dict[str, Any]:
    """Identification accuracies and the confusion matrices (best match and decision) as plain data."""
    true = np.asarray(true_ids, np.int64)

    def named_right(decision: np.ndarray) -> float:
        return _fraction(decision == true)

    def named_wrong(decision: np.ndarray) -> float:
        # A render named as another key: the costly error (a licensee accused of another's copy), unlike a
        # render left as "no watermark".
        return _fraction((decision >= 0) & (decision != true))

    return {
        "identification_accuracy": _fraction(ident.best_id == true),
        "verified_identification_accuracy": named_right(ident.decision),  # by ident.test
        "verified_identification_accuracy_by_test": _by_test(ident, named_right),
        "misidentification_rate": named_wrong(ident.decision),
        "misidentification_rate_by_test": _by_test(ident, named_wrong),
        "test": ident.test,
        "detection_rate": _fraction(ident.decision >= 0),
        "threshold": ident.threshold,
        "min_attainable_p": ident.min_attainable_p,
        "median_p_corrected": float(np.median(ident.p_corrected)) if true.size else math.nan,
        "confusion_best_match": confusion_matrix(true, ident.best_id, ident.num_ids).tolist(),
        "confusion_decision": confusion_matrix(true, ident.decision, ident.num_ids).tolist(),
    }


def false_detection_summary(ident: Identification, num_ids: int = 0) -> dict[str, Any]:
    """How often unwatermarked images are claimed (decision ≠ −1): should be ≤ the threshold; and how many
    were claimed as each of the ``num_ids`` keys (a decoder biased towards some keys claims those)."""

    def claimed_rate(decision: np.ndarray) -> float:
        return _fraction(decision >= 0)

    return {
        "false_detection_rate": claimed_rate(ident.decision),
        "false_detection_rate_by_test": _by_test(ident, claimed_rate),
        "mean_best_agreement": float(ident.bit_accuracy.mean()) if ident.decision.size else math.nan,
        "claimed_per_id": np.bincount(ident.decision[ident.decision >= 0], minlength=num_ids).tolist(),
    }
