"""Calibrating the decision threshold on clean images: the threshold at which at most ``k`` of ``M`` clean
images are named, and the largest one whose false-claim rate a Clopper–Pearson bound keeps under a stated
rate (``scripts/false_claims.py``).

The decision names an image when the decision statistic, the best-matching key's Bonferroni-corrected
p-value under the run's test (:mod:`identification`), is below the threshold ``T``. On ``M`` clean images the
statistic's empirical distribution (its distinct values ``v_1 < … < v_D`` and their counts) gives, for any
``T``, the count named ``k(T) = #{p < T}``. ``T = v_j`` names exactly the images below ``v_j``, and no larger
``T`` names as few, so the thresholds worth reporting are the ``v_j``. For a stated rate ``r`` the calibrated
threshold is the largest ``v_j`` whose count ``k`` has a one-sided Clopper–Pearson upper bound at
confidence ``c`` (95 %) of at most ``r``: the rate at that threshold is ≤ ``r`` with confidence ``c``. Where
even ``k = 0`` cannot show it (``M`` below about ``3 / r`` images), the calibration says so
(``attained: false``) and keeps the smaller of ``v_1`` (nothing seen is named) and a fallback (the run's
nominal threshold). No read can get below the test's floor (``C·N / 2^L``: every bit of an ``L``-bit key
agreeing, corrected over ``N`` keys and ``C`` reads), so a threshold at or below it names no image at all,
watermarked ones included: where the rate would need one (clean images reading an exact key), the stated rate
cannot be had with keys this short, and the calibration says so (``at_floor``) and keeps the fallback.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from scipy import special

CONFIDENCE = 0.95
NEVER_NAMED = 1.0  # the statistic of an undecided image (a tie between keys): no threshold ≤ 1 names it


def clopper_pearson_upper(named: int, images: int, confidence: float = CONFIDENCE) -> float:
    """One-sided Clopper–Pearson upper bound on a rate seen as ``named`` of ``images`` (at ``confidence``):
    the rate ``R`` with ``P[Bin(images, R) ≤ named] = 1 − confidence``, the ``confidence`` quantile of
    ``Beta(named + 1, images − named)``; 1 when every image was named."""
    k, n = int(named), int(images)
    if n < 1 or not 0 <= k <= n:
        raise ValueError(f"need 0 ≤ named ≤ images and images ≥ 1, got {k} of {n}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    if k == n:
        return 1.0
    return float(special.betaincinv(k + 1, n - k, confidence))


def decision_statistic(best_id: np.ndarray, p_corrected: np.ndarray) -> np.ndarray:
    """``[B]`` the statistic the decision thresholds: the best key's corrected p-value, :data:`NEVER_NAMED`
    where the best match is a tie (undecided under any threshold)."""
    best_id = np.asarray(best_id)
    return np.where(best_id >= 0, np.asarray(p_corrected, np.float64), NEVER_NAMED)


def distribution(statistic: Sequence[float] | np.ndarray) -> dict[str, list]:
    """The empirical distribution of ``statistic [M]``: ``{"values": distinct, ascending; "counts"}``."""
    values, counts = np.unique(np.asarray(statistic, np.float64), return_counts=True)
    return {"values": values.tolist(), "counts": counts.astype(int).tolist()}


def merge(*dists: Mapping[str, Sequence]) -> dict[str, list]:
    """One distribution of the images of several (each as :func:`distribution` gives it)."""
    total: dict[float, int] = {}
    for d in dists:
        for v, c in zip(d["values"], d["counts"], strict=True):
            total[float(v)] = total.get(float(v), 0) + int(c)
    values = sorted(total)
    return {"values": values, "counts": [total[v] for v in values]}


def _arrays(dist: Mapping[str, Sequence]) -> tuple[np.ndarray, np.ndarray, int]:
    """``(values [D], named below each value [D], images M)`` of a distribution."""
    values = np.asarray(dist["values"], np.float64)
    counts = np.asarray(dist["counts"], np.int64)
    if values.size == 0 or values.shape != counts.shape or (np.diff(values) <= 0).any() or (counts < 1).any():
        raise ValueError("a distribution needs ascending distinct values, each with a count ≥ 1")
    below = np.concatenate([[0], np.cumsum(counts)[:-1]])
    return values, below, int(counts.sum())


def named_at(dist: Mapping[str, Sequence], threshold: float) -> int:
    """How many images of ``dist`` the decision names at ``threshold`` (statistic < threshold)."""
    values, _, _ = _arrays(dist)
    counts = np.asarray(dist["counts"], np.int64)
    return int(counts[values < threshold].sum())


def threshold_for_named(dist: Mapping[str, Sequence], most: int) -> float:
    """The largest threshold (a value of ``dist``) at which at most ``most`` of its images are named."""
    values, below, _ = _arrays(dist)
    return float(values[np.flatnonzero(below <= int(most))[-1]])


def threshold_table(
    dist: Mapping[str, Sequence], up_to: int = 20, confidence: float = CONFIDENCE
) -> list[dict[str, Any]]:
    """The thresholds that name at most ``up_to`` images, one row per value of ``dist`` (each names a
    different count): ``{"named": k, "threshold", "rate": k / M, "rate_upper"}`` (Clopper–Pearson at
    ``confidence``). The threshold of a row is the largest that names no more than its ``k``."""
    values, below, m = _arrays(dist)
    return [
        {
            "named": int(k),
            "threshold": float(v),
            "rate": int(k) / m,
            "rate_upper": clopper_pearson_upper(int(k), m, confidence),
        }
        for v, k in zip(values, below, strict=True)
        if k <= up_to
    ]


def threshold_for_rate(
    dist: Mapping[str, Sequence],
    rate: float,
    confidence: float = CONFIDENCE,
    fallback: float | None = None,
    floor: float | None = None,
) -> dict[str, Any]:
    """The calibrated threshold for a stated false-claim ``rate`` (module docstring): ``{"threshold",
    "named", "images", "rate", "rate_upper", "target_rate", "confidence", "attained", "floor",
    "at_floor"}``. Non-decreasing in ``rate``. Not attained (too few images): the smaller of the least value
    and ``fallback``. ``floor`` (None: unknown): the least statistic any read can have; a threshold at or
    below it would name nothing, so ``fallback`` is kept instead (``at_floor``, not attained)."""
    if not 0.0 < rate < 1.0:
        raise ValueError(f"the stated rate must be in (0, 1), got {rate}")
    values, below, m = _arrays(dist)
    ok = np.array([clopper_pearson_upper(int(k), m, confidence) <= rate for k in below])
    if ok.any():
        j = int(np.flatnonzero(ok)[-1])  # the bound grows with the count, the count with j: ok is a prefix
        threshold, named, attained = float(values[j]), int(below[j]), True
    else:
        threshold = float(values[0]) if fallback is None else min(float(values[0]), float(fallback))
        named, attained = 0, False
    at_floor = floor is not None and fallback is not None and threshold <= floor < fallback
    if at_floor:
        threshold, attained = float(fallback), False
        named = named_at(dist, threshold)
    return {
        "threshold": threshold,
        "named": named,
        "images": m,
        "rate": named / m,
        "rate_upper": clopper_pearson_upper(named, m, confidence),
        "target_rate": float(rate),
        "confidence": float(confidence),
        "attained": attained,
        "floor": None if floor is None else float(floor),
        "at_floor": bool(at_floor),
    }


def percent(rate: float) -> str:
    """A rate as a percentage with two significant figures (``0.063 %``)."""
    if rate <= 0 or not math.isfinite(rate):
        return f"{100 * rate:g} %"
    return f"{100 * rate:.2g} %"


def describe(entry: Mapping[str, Any]) -> str:
    """A calibration entry in words: ``calibrated on M clean images: k named, rate ≤ R at 95 %`` (and, where
    ``M`` images cannot show the stated rate, that too)."""
    text = (
        f"calibrated on {entry['images']:,} clean images: {entry['named']} named, "
        f"rate ≤ {percent(entry['rate_upper'])} at {round(100 * entry['confidence'])} %"
    )
    if entry.get("at_floor", False):
        text += (
            f"; {percent(entry['target_rate'])} would need a threshold at the smallest p-value a read can "
            f"give ({entry['floor']:.3g}), which names no image: keys this short cannot show it, so the "
            "nominal threshold is kept"
        )
    elif not entry.get("attained", True):
        text += f"; too few images to show {percent(entry['target_rate'])}"
    return text
