"""Watermark keys: ``N`` random ``L``-bit messages, pairwise ≥ ``d`` bits apart, stored as ``keys.json``.

A watermarked run renders ID ``n`` (an integer in ``[0, N)``) with message ``M(n)``. Messages are drawn
uniformly at random (non-random keys inflate bit accuracy) and redrawn until every pair differs in at least
``min_hamming`` bits, so that a decoded message close to one key is far from the others.

Feasibility is checked before any drawing: the number of binary codewords of length ``L`` with minimum
distance ``d``, ``A(L, d)``, is bounded above by the Plotkin bound (``2d > L``) and the Hamming
(sphere-packing) bound; a request for more than that many keys is rejected at once. A feasible request is
drawn key by key (each candidate redrawn until it is far enough from the keys already kept) with a bounded
number of draws, so that a request beyond what random draws reach fails with an error rather than hanging.

``keys.json`` sits beside the watermarked checkpoint::

    {"format": 1, "num_ids": 4, "bits": 16, "min_hamming": 5, "seed": 0,
     "decoder_fingerprint": "3f2a...", "messages": ["0110...", ...]}
"""

from __future__ import annotations

import dataclasses
import json
import math
import numbers
import os
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from mnerf_jax.core.errors import MnerfError

KEYS_FILE = "keys.json"
KEYS_FORMAT = 1

# Default distance: the largest d whose expected number of candidate draws stays below this many per key.
_DEFAULT_DRAWS_PER_KEY = 4.0
# Hard cap on candidate draws per key before giving up (expected draws of the default d are ≤ 4 per key).
_MAX_DRAWS_PER_KEY = 2000
# Fresh starts after a dead end: keys drawn one after another can leave no room for the next (two 8-bit
# keys 7 or 8 apart leave no word ≥ 5 from both), however many candidates are drawn.
_MAX_STARTS = 20


class KeysError(MnerfError):
    """Keys that cannot be made, read or matched to a decoder."""


@dataclasses.dataclass(frozen=True)
class KeySet:
    """``messages [N, L]`` uint8 in {0, 1}: message ``n`` belongs to ID ``n``."""

    messages: np.ndarray
    min_hamming: int
    seed: int
    decoder_fingerprint: str | None = None

    @property
    def num_ids(self) -> int:
        return int(self.messages.shape[0])

    @property
    def bits(self) -> int:
        return int(self.messages.shape[1])

    def message(self, index: int) -> np.ndarray:
        """The ``[L]`` message of ID ``index``; a clear error outside ``[0, N)``."""
        check_id(index, self.num_ids)
        return self.messages[int(index)]

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": KEYS_FORMAT,
            "num_ids": self.num_ids,
            "bits": self.bits,
            "min_hamming": self.min_hamming,
            "seed": self.seed,
            "decoder_fingerprint": self.decoder_fingerprint,
            "messages": ["".join(str(int(b)) for b in row) for row in self.messages],
        }


def check_id(index: Any, num_ids: int) -> int:
    """``index`` as an int in ``[0, num_ids)``, or a KeysError that says which IDs exist."""
    valid = f"valid IDs: 0..{num_ids - 1}"
    if isinstance(index, str) and index.strip().lstrip("-").isdigit():
        index = int(index.strip())
    if isinstance(index, bool) or not isinstance(index, numbers.Integral):
        raise KeysError(f"watermark ID {index!r} is not an integer ({valid})")
    value = int(index)
    if not 0 <= value < num_ids:
        raise KeysError(f"watermark ID {value} is outside [0, {num_ids}) ({valid})")
    return value


# ---------------------------------------------------------------------------------------------- bounds


def hamming_bound(bits: int, distance: int) -> int:
    """Sphere-packing upper bound on ``A(bits, distance)``: ``2^L / Σ_{k≤t} C(L, k)``, ``t = ⌊(d−1)/2⌋``."""
    t = (distance - 1) // 2
    volume = sum(math.comb(bits, k) for k in range(t + 1))
    return (1 << bits) // volume


def plotkin_bound(bits: int, distance: int) -> int | None:
    """Plotkin upper bound on ``A(bits, distance)`` where it applies (``2d ≥ L``), else None.

    Even ``d``: ``2⌊d/(2d−L)⌋`` for ``2d > L`` and ``4d`` for ``2d = L``. Odd ``d`` uses
    ``A(L, d) = A(L+1, d+1)``.
    """
    n, d = bits, distance
    if d % 2:
        n, d = n + 1, d + 1
    if 2 * d > n:
        return 2 * (d // (2 * d - n))
    if 2 * d == n:
        return 4 * d
    return None


def max_codewords(bits: int, distance: int) -> int:
    """An upper bound on how many ``bits``-long binary words can be pairwise ``≥ distance`` apart."""
    if distance <= 1:
        return 1 << bits
    if distance > bits:
        return 1
    bound = hamming_bound(bits, distance)
    plotkin = plotkin_bound(bits, distance)
    return bound if plotkin is None else min(bound, plotkin)


def _pair_close_probability(bits: int, distance: int) -> float:
    """P[two uniform random messages differ in fewer than ``distance`` bits] = P[Bin(L, ½) < d]."""
    return sum(math.comb(bits, k) for k in range(distance)) / float(1 << bits)


def expected_draws(num_ids: int, bits: int, distance: int) -> float:
    """Expected candidate draws for key-by-key rejection, treating pair distances as independent.

    Key ``i`` is accepted with probability about ``(1 − p)^i`` where ``p = P[Bin(L, ½) < d]``.
    """
    p = _pair_close_probability(bits, distance)
    if p >= 1.0:
        return math.inf
    return float(sum((1.0 - p) ** -i for i in range(num_ids)))


def default_min_hamming(num_ids: int, bits: int) -> int:
    """The largest ``d`` that random draws reach quickly (≤ 4 expected draws per key), at least 1.

    For 4 IDs × 16 bits this is 8; for 16 × 16 it is 6; for 50 × 48 it is 18.
    """
    check_sizes(num_ids, bits)
    best = 1
    for d in range(1, bits + 1):
        if num_ids > max_codewords(bits, d):
            break
        if expected_draws(num_ids, bits, d) > _DEFAULT_DRAWS_PER_KEY * num_ids:
            break
        best = d
    return best


def check_sizes(num_ids: int, bits: int) -> None:
    """KeysError unless ``num_ids ≥ 1``, ``bits ≥ 1`` and ``num_ids ≤ 2^bits``."""
    if int(num_ids) < 1:
        raise KeysError(f"the number of IDs must be at least 1, got {num_ids}")
    if int(bits) < 1:
        raise KeysError(f"the message length must be at least 1 bit, got {bits}")
    if bits < 63 and num_ids > (1 << bits):
        raise KeysError(f"{num_ids} distinct IDs need more than {bits} bits (at most {1 << bits} messages)")


# ------------------------------------------------------------------------------------------- drawing


def pairwise_hamming(messages: np.ndarray) -> np.ndarray:
    """``messages [N, L]`` in {0,1} → symmetric ``[N, N]`` int distances (zero diagonal)."""
    m = np.asarray(messages, np.int32)
    return (m[:, None, :] != m[None, :, :]).sum(-1)


def min_pairwise_hamming(messages: np.ndarray) -> int:
    """Smallest distance between two different rows; ``L + 1`` sentinel-free: ``bits`` for one message."""
    m = np.asarray(messages)
    if m.shape[0] < 2:
        return int(m.shape[1])
    dist = pairwise_hamming(m)
    return int(dist[~np.eye(m.shape[0], dtype=bool)].min())


# Up to this many bits the null word is searched among every word; past it among NULL_CANDIDATES random ones.
NULL_EXHAUSTIVE_BITS = 20
NULL_CANDIDATES = 1 << 16


def null_message(messages: np.ndarray) -> np.ndarray:
    """The ``[L]`` word (uint8 0/1) farthest from every key of ``messages [N, L]``: the largest smallest
    Hamming distance to the keys, then the largest mean distance, then the first in order.

    The embedding teaches the decoder to read unwatermarked images as this word (its clean terms' target), so
    that an image without a watermark reads far from every key rather than near whichever the decoder
    drifted to. Deterministic in the keys: every word for ``L`` ≤ :data:`NULL_EXHAUSTIVE_BITS`, else
    :data:`NULL_CANDIDATES` words drawn with a fixed seed (a verifier never needs it).
    """
    keys = np.asarray(messages, np.uint8)
    bits = keys.shape[1]
    weights = np.left_shift(np.uint64(1), np.arange(bits, dtype=np.uint64))
    key_words = (keys.astype(np.uint64) * weights).sum(axis=1)  # [N]: bit b of word = keys[:, b]
    if bits <= NULL_EXHAUSTIVE_BITS:
        candidates = np.arange(1 << bits, dtype=np.uint64)
    else:
        drawn = np.random.default_rng(0).integers(0, 2, (NULL_CANDIDATES, bits), dtype=np.uint8)
        candidates = (drawn.astype(np.uint64) * weights).sum(axis=1)
    best, best_score = 0, -1
    for start in range(0, len(candidates), 1 << 16):  # [C, N] distances a block at a time
        block = candidates[start : start + (1 << 16)]
        distance = np.bitwise_count(block[:, None] ^ key_words[None, :]).astype(np.int64)
        score = distance.min(axis=1) * (keys.shape[0] * bits + 1) + distance.sum(axis=1)
        top = int(np.argmax(score))  # the first of the block's best
        if int(score[top]) > best_score:
            best, best_score = start + top, int(score[top])
    word = int(candidates[best])
    return np.array([(word >> b) & 1 for b in range(bits)], np.uint8)


def generate_keys(
    num_ids: int,
    bits: int,
    min_hamming: int = 0,
    seed: int = 0,
    decoder_fingerprint: str | None = None,
    max_draws_per_key: int = _MAX_DRAWS_PER_KEY,
    max_starts: int = _MAX_STARTS,
) -> KeySet:
    """Draw ``num_ids`` uniform random ``bits``-bit messages pairwise ≥ ``min_hamming`` apart.

    ``min_hamming=0`` picks :func:`default_min_hamming`. Requests beyond the Plotkin / Hamming bounds are
    rejected before drawing; otherwise each key is redrawn at most ``max_draws_per_key`` times, and a set that
    runs into a dead end is started afresh, at most ``max_starts`` times in all (a clear error after that:
    lower the distance). Deterministic in ``seed``; a set found at the first start is the one drawn before
    fresh starts existed.
    """
    num_ids, bits, min_hamming = int(num_ids), int(bits), int(min_hamming)
    check_sizes(num_ids, bits)
    if min_hamming < 0:
        raise KeysError(f"minimum Hamming distance must be ≥ 0, got {min_hamming}")
    distance = default_min_hamming(num_ids, bits) if min_hamming == 0 else min_hamming
    if distance > bits and num_ids > 1:
        raise KeysError(f"a minimum Hamming distance of {distance} is impossible with {bits}-bit messages")
    bound = max_codewords(bits, distance)
    if num_ids > bound:
        raise KeysError(
            f"{num_ids} keys of {bits} bits cannot be pairwise {distance} bits apart "
            f"(Plotkin/Hamming bound: at most {bound}); lower watermark.min_hamming or use more bits"
        )
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), num_ids, bits, distance]))
    if distance <= 1 and bits <= 30:
        # Only distinctness is asked for: sample without replacement (rejection slows near 2^L keys).
        words = rng.choice(1 << bits, size=num_ids, replace=False)
        messages = ((words[:, None] >> np.arange(bits - 1, -1, -1)) & 1).astype(np.uint8)
        return KeySet(messages, distance, int(seed), decoder_fingerprint)
    most, starts = 0, max(1, int(max_starts))
    for _ in range(starts):
        kept = _draw_greedily(rng, num_ids, bits, distance, max_draws_per_key)
        if kept.shape[0] == num_ids:
            return KeySet(kept, distance, int(seed), decoder_fingerprint)
        most = max(most, kept.shape[0])
    raise KeysError(
        f"random draws found only {most} of {num_ids} keys of {bits} bits pairwise {distance} apart "
        f"({max_draws_per_key} tries for each next key, {starts} fresh starts); lower "
        f"watermark.min_hamming (default for these sizes: {default_min_hamming(num_ids, bits)})"
    )


def _draw_greedily(
    rng: np.random.Generator, num_ids: int, bits: int, distance: int, max_draws_per_key: int
) -> np.ndarray:
    """Keys ``[n ≤ num_ids, bits]`` drawn one after another, each ≥ ``distance`` from those before; stops
    short (``n < num_ids``) when ``max_draws_per_key`` candidates in a row fail."""
    kept = np.zeros((0, bits), np.uint8)
    for _ in range(num_ids):
        for _ in range(max_draws_per_key):
            candidate = rng.integers(0, 2, size=bits, dtype=np.uint8)
            if kept.shape[0] == 0 or (kept != candidate).sum(-1).min() >= distance:
                kept = np.concatenate([kept, candidate[None]], axis=0)
                break
        else:
            break  # no candidate fits: a dead end
    return kept


# ---------------------------------------------------------------------------------------------- files


def _write_json_atomic(path: Path, payload: Mapping[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".keys-", suffix=".json", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as handle:
            json.dump(payload, handle, indent=2)
            handle.write("\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def save_keys(run_dir: str | Path, keys: KeySet) -> Path:
    """Write ``run_dir/keys.json`` atomically; returns its path."""
    path = Path(run_dir) / KEYS_FILE
    _write_json_atomic(path, keys.to_dict())
    return path


def keys_from_dict(values: Mapping[str, Any], where: str = KEYS_FILE) -> KeySet:
    """Parse and check the contents of a ``keys.json``."""
    try:
        fmt = int(values.get("format", -1))
        rows = list(values["messages"])
        bits = int(values["bits"])
        num_ids = int(values["num_ids"])
        min_hamming = int(values["min_hamming"])
        seed = int(values.get("seed", 0))
    except (KeyError, TypeError, ValueError) as err:
        raise KeysError(f"{where}: malformed keys file ({err!r})") from None
    if fmt != KEYS_FORMAT:
        raise KeysError(f"{where}: unknown keys format {fmt} (expected {KEYS_FORMAT})")
    if len(rows) != num_ids or num_ids < 1:
        raise KeysError(f"{where}: num_ids is {num_ids} but {len(rows)} messages are stored")
    for n, row in enumerate(rows):
        if not isinstance(row, str) or len(row) != bits or set(row) - {"0", "1"}:
            raise KeysError(f"{where}: message {n} is not a string of {bits} binary digits: {row!r}")
    messages = np.array([[int(c) for c in row] for row in rows], np.uint8)
    actual = min_pairwise_hamming(messages)
    if num_ids > 1 and actual < min_hamming:
        raise KeysError(f"{where}: messages are only {actual} bits apart, below the stored {min_hamming}")
    fingerprint = values.get("decoder_fingerprint")
    return KeySet(messages, min_hamming, seed, None if fingerprint is None else str(fingerprint))


def load_keys(
    run_dir: str | Path,
    decoder_fingerprint: str | None = None,
    expect_bits: int | None = None,
) -> KeySet:
    """Read ``run_dir/keys.json``, checking it against the decoder that will read the renders.

    ``expect_bits``: the decoder's message length; ``decoder_fingerprint``: ``decoder_io.fingerprint`` of
    the decoder's variables (checked only where both it and the file have one). Each mismatch is a
    KeysError.
    """
    path = Path(run_dir) / KEYS_FILE
    if not path.is_file():
        raise KeysError(f"{run_dir} has no {KEYS_FILE}: not a watermarked run (make one with `mnerf embed`)")
    try:
        values = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise KeysError(f"{path}: malformed JSON: {err}") from None
    if not isinstance(values, Mapping):
        raise KeysError(f"{path}: malformed keys file (expected an object)")
    keys = keys_from_dict(values, str(path))
    if expect_bits is not None and keys.bits != int(expect_bits):
        raise KeysError(
            f"{path}: keys have {keys.bits} bits but the decoder reads {int(expect_bits)}; "
            f"use a {keys.bits}-bit decoder (or embed again with --bits {int(expect_bits)})"
        )
    if (
        decoder_fingerprint is not None
        and keys.decoder_fingerprint is not None
        and keys.decoder_fingerprint != decoder_fingerprint
    ):
        raise KeysError(
            f"{path}: keys were embedded for decoder {keys.decoder_fingerprint}, "
            f"not for the given decoder {decoder_fingerprint}"
        )
    return keys


def with_fingerprint(keys: KeySet, decoder_fingerprint: str | None) -> KeySet:
    """The same keys tied to another decoder (the embedding fine-tunes the decoder in phase 2)."""
    return dataclasses.replace(keys, decoder_fingerprint=decoder_fingerprint)
