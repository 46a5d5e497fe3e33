"""The statistics of a study's report: a figure's spread over seeds, and paired tests between methods.

A setting's figure is summarised over its done cells (one per seed): mean, sample standard deviation
(``ddof=1``), minimum, maximum and count. Two methods are compared on the cells they share, paired by
``(scene, num_ids, bits, seed)``: the paired t-test (``scipy.stats.ttest_rel``) and the Wilcoxon signed-rank
test (``scipy.stats.wilcoxon``, exact for the few pairs a study has), both two-sided. Fewer than two pairs
get no test.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Callable, Hashable, Iterable, Mapping, Sequence
from typing import Any

import numpy as np
from scipy import stats

PAIR_KEYS = ("scene", "num_ids", "bits", "seed")
Row = Mapping[str, Any]


@dataclasses.dataclass(frozen=True)
class Summary:
    """A figure over the done cells of one setting; ``n == 0``: none is done (shown as ``—``)."""

    n: int
    mean: float = math.nan
    std: float = math.nan  # sample standard deviation; nan for one value
    low: float = math.nan
    high: float = math.nan


def finite(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def summarise(values: Iterable[Any]) -> Summary:
    """The summary of the finite numbers among ``values`` (None and nan, a figure not measured, left out)."""
    x = np.asarray([float(v) for v in values if finite(v)], np.float64)
    if x.size == 0:
        return Summary(0)
    std = float(x.std(ddof=1)) if x.size > 1 else math.nan
    return Summary(int(x.size), float(x.mean()), std, float(x.min()), float(x.max()))


def done(rows: Iterable[Row]) -> list[Row]:
    return [r for r in rows if r.get("status") == "done"]


def summary_of(rows: Iterable[Row], metric: str) -> Summary:
    """``metric`` over the done ``rows``."""
    return summarise(r.get(metric) for r in done(rows))


def group(rows: Iterable[Row], key: Callable[[Row], Hashable]) -> dict[Hashable, list[Row]]:
    """``rows`` by ``key(row)``, in first-appearance order (the spec's)."""
    out: dict[Hashable, list[Row]] = {}
    for r in rows:
        out.setdefault(key(r), []).append(r)
    return out


def first_value(rows: Iterable[Row], column: str) -> Any:
    """The first non-missing ``column`` of ``rows`` (the paper's figure is the same on every seed's row)."""
    return next((r[column] for r in rows if r.get(column) is not None), None)


@dataclasses.dataclass(frozen=True)
class PairedTest:
    """``a − b`` over the pairs two methods share: count, mean difference and two-sided p-values (nan:
    no test, fewer than two pairs)."""

    n: int
    mean_diff: float = math.nan
    t_p: float = math.nan  # also nan for equal, non-zero differences (no spread)
    wilcoxon_p: float = math.nan

    @property
    def tested(self) -> bool:
        return self.n >= 2


def paired_differences(
    a: Iterable[Row], b: Iterable[Row], metric: str, keys: Sequence[str] = PAIR_KEYS
) -> np.ndarray:
    """``a``'s ``metric`` minus ``b``'s on the done cells both have at the same ``keys``: ``[pairs]``."""

    def by_key(rows: Iterable[Row]) -> dict[tuple, float]:
        return {tuple(r.get(k) for k in keys): float(r[metric]) for r in done(rows) if finite(r.get(metric))}

    left, right = by_key(a), by_key(b)
    return np.asarray([left[k] - right[k] for k in left if k in right], np.float64)


def paired_test(diffs: Sequence[float] | np.ndarray) -> PairedTest:
    """The paired t-test and Wilcoxon signed-rank test of the differences ``diffs`` (null: centred on 0).

    Differences that are all zero give p = 1 to both. Differences that are equal but not zero have no
    spread: the t-test is undefined (nan; its statistic infinite), while the signed-rank test stays exact.
    """
    d = np.asarray(diffs, np.float64).reshape(-1)
    n = int(d.size)
    if n < 2:
        return PairedTest(n, float(d.mean()) if n else math.nan)
    mean = float(d.mean())
    if np.all(d == 0):
        return PairedTest(n, 0.0, 1.0, 1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # scipy's warnings of a near-zero spread
        t_p = math.nan if np.all(d == d[0]) else float(stats.ttest_rel(d, np.zeros_like(d)).pvalue)
        wilcoxon_p = float(stats.wilcoxon(d).pvalue)
    return PairedTest(n, mean, t_p, wilcoxon_p)
