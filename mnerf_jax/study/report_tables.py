"""The tables of a study's report, chosen from the rows of ``results.json`` and set beside the paper's.

Each table gathers the rows that differ along one axis at otherwise equal settings, whatever the spec
calls its methods:

- **capacity**: a method's rows at two or more numbers of IDs (per scene and bit length);
- **ablation**: the rows of the MultiNeRF variant and its ablations (``no_grid``, ``no_film``,
  ``frozen_geometry``, ``early``) at one scene, IDs and bits, at the #WMCom most of them share; the
  paper's ablation rows stand in their order, those without a variant here marked so;
- **#WMCom**: the ``multinerf`` rows at two or more #WMCom (per scene, IDs and bits);
- **bit length**: the ``multinerf`` rows at two or more bit lengths (per scene, IDs, #WMCom, noised);
- **single message**: the rows with one ID, per bit length, a column per scene;
- **robustness**: every setting's mean bit accuracy under each attack suite.

A figure is its mean ± standard deviation over the setting's done cells (``n``: how many, one a seed);
``—`` where none is done. The paper's figure is the one ``paper_numbers.match`` gave the rows (``≈``: read
from the paper's text). Methods are compared by the paired tests of ``report_stats``: the first MultiNeRF
method of each setting (else the first method) against each other method, paired by scene, IDs, bits and
seed, the pairs of every setting pooled.
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Iterable, Mapping, Sequence
from typing import Any

from mnerf_jax.imaging import augment
from mnerf_jax.study import paper_numbers
from mnerf_jax.study.report_stats import (
    Row,
    Summary,
    first_value,
    group,
    paired_differences,
    paired_test,
    summary_of,
)

MISSING = "—"
VARIANT_LABELS = {
    "multinerf": "MultiNeRF",
    "waterf_mod": "WateRF-modified",
    "waterf": "WateRF",
    "no_grid": "MN(-GRID)(+MLP)",
    "no_film": "MN(-FiLM)",
    "appearance_film": "MN(-GRID)",
    "appearance_concat": "MN(-FiLM)(-GRID)",
    "frozen_geometry": "MN G_σ frozen",
    "early": "MN(+EARLY)",
}
ABLATION_VARIANTS = (
    "multinerf",
    "no_grid",
    "appearance_concat",
    "no_film",
    "frozen_geometry",
    "early",
    "appearance_film",
)
ABLATION_TABLE = "tab:ablation"
# column -> (header, format)
METRICS: dict[str, tuple[str, str]] = {
    "bit_acc": ("bit acc. %", "pct"),
    "bit_acc_worst_id": ("worst ID %", "pct"),
    "psnr": ("PSNR dB", "db"),
    "ssim": ("SSIM", "num"),
    "lpips": ("LPIPS", "num"),
    "params_m_watermark": ("WM params M", "num"),
}
QUALITY = ("bit_acc", "bit_acc_worst_id", "psnr", "ssim", "lpips")


# ------------------------------------------------------------------------------------------ formatting


def show(value: float | None, kind: str) -> str:
    """One number: ``pct`` (a fraction shown in percent), ``db`` or ``num``; ``—`` when missing."""
    if value is None or not math.isfinite(value):
        return MISSING
    if kind == "pct":
        return f"{100.0 * value:.1f}"
    return f"{value:.2f}" if kind == "db" else f"{value:.3f}"


def show_summary(s: Summary, kind: str) -> str:
    """``mean ± std (n=N)``; ``mean (n=1)``; ``—`` when no cell is done."""
    if s.n == 0:
        return MISSING
    spread = f" ± {show(s.std, kind)}" if s.n > 1 else ""
    return f"{show(s.mean, kind)}{spread} (n={s.n})"


def show_p(p: float) -> str:
    return MISSING if not math.isfinite(p) else (f"{p:.1e}" if p < 1e-3 else f"{p:.3f}")


def paper_figure(rows: Sequence[Row], metric: str) -> paper_numbers.PaperFigure | None:
    """The paper's figure of ``metric`` for the setting of ``rows`` (``paper_numbers.match``, as the table's
    ``paper_*`` columns; a done row's resolved settings before a pending one's)."""
    if not rows:
        return None
    first = next((r for r in rows if r.get("status") == "done"), rows[0])
    return paper_numbers.match(first).get(metric)


def paper_cell(rows: Sequence[Row], metric: str, kind: str) -> str:
    figure = paper_figure(rows, metric)
    if figure is None:
        return MISSING
    return ("≈" if figure.approx else "") + show(figure.value, kind)


def table(head: Sequence[str], body: Iterable[Sequence[str]]) -> list[str]:
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    return lines + ["| " + " | ".join(cells) + " |" for cells in body]


def label(rows: Sequence[Row]) -> str:
    """A setting's name: its method and what the method is (variant, noised)."""
    r = rows[0]
    what = VARIANT_LABELS.get(r.get("variant"), str(r.get("variant")))
    noised = ", noised" if first_value(rows, "noised") else ""
    return f"`{r.get('method')}` ({what}{noised})"


def metric_head(metrics: Sequence[str], paper: Sequence[str]) -> list[str]:
    head = []
    for m in metrics:
        head.append(METRICS[m][0])
        if m in paper:
            head.append("paper")
    return head


def metric_cells(rows: Sequence[Row], metrics: Sequence[str], paper: Sequence[str]) -> list[str]:
    cells = []
    for m in metrics:
        kind = METRICS[m][1]
        cells.append(show_summary(summary_of(rows, m), kind))
        if m in paper:
            cells.append(paper_cell(rows, m, kind))
    return cells


def source(rows: Sequence[Row], metrics: Sequence[str]) -> str:
    """The paper's tables the figures of ``metrics`` come from."""
    tables = {f.table for f in (paper_figure(rows, m) for m in metrics) if f is not None}
    return " ".join(sorted(tables)) or MISSING


def seeds_line(rows: Iterable[Row]) -> str:
    seeds = sorted({r.get("seed") for r in rows if r.get("seed") is not None})
    return f"Seeds: {', '.join(map(str, seeds)) or MISSING}; n: the done cells a figure is over."


# ------------------------------------------------------------------------------------------ selection


def by_method(rows: Iterable[Row]) -> dict[Hashable, list[Row]]:
    return group(rows, lambda r: r.get("method"))


def settings_key(r: Row, *keys: str) -> tuple:
    return tuple(r.get(k) for k in keys)


def capacity_series(rows: Sequence[Row]) -> dict[tuple, dict[Hashable, list[Row]]]:
    """``(scene, bits) -> {method: rows}`` for the methods with rows at two or more numbers of IDs."""
    out: dict[tuple, dict[Hashable, list[Row]]] = {}
    for key, members in group(rows, lambda r: settings_key(r, "scene", "bits")).items():
        series = {m: rs for m, rs in by_method(members).items() if len({r["num_ids"] for r in rs}) > 1}
        if series:
            out[key] = series  # type: ignore[index]
    return out


def _mode(values: Sequence[Any]) -> Any:
    counts: dict[Any, int] = {}
    for v in values:
        counts[v] = counts.get(v, 0) + 1
    return max(counts, key=lambda v: counts[v])  # ties: the first seen


def ablation_groups(rows: Sequence[Row]) -> dict[tuple, list[Row]]:
    """``(scene, num_ids, bits) -> rows`` of the ablation variants at their common #WMCom, where two or more
    variants are present."""
    out = {}
    for key, members in group(rows, lambda r: settings_key(r, "scene", "num_ids", "bits")).items():
        candidates = [r for r in members if r.get("variant") in ABLATION_VARIANTS]
        if not candidates:
            continue
        wmcom = _mode([r.get("wmcom") for r in candidates])
        kept = [r for r in candidates if r.get("wmcom") == wmcom]
        if len({r["variant"] for r in kept}) > 1:
            out[key] = kept
    return out  # type: ignore[return-value]


def axis_groups(rows: Sequence[Row], axis: str, keys: Sequence[str]) -> dict[tuple, list[Row]]:
    """``keys -> rows`` of the ``multinerf`` variant that take two or more values of ``axis``."""
    mn = [r for r in rows if r.get("variant") == "multinerf" and r.get(axis) is not None]
    return {
        k: rs  # type: ignore[misc]
        for k, rs in group(mn, lambda r: settings_key(r, *keys)).items()
        if len({r[axis] for r in rs}) > 1
    }


def single_groups(rows: Sequence[Row]) -> dict[Hashable, list[Row]]:
    """``bits -> rows`` with one ID."""
    return group([r for r in rows if r.get("num_ids") == 1], lambda r: r.get("bits"))


def suites_of(rows: Sequence[Row]) -> list[str]:
    """The attack suites the rows hold figures of (``attack_<suite>_bit_acc``), in the strengths' order."""
    return [s for s in augment.STRENGTHS if any(r.get(f"attack_{s}_bit_acc") is not None for r in rows)]


def attacks_of(rows: Sequence[Row], suite: str) -> list[str]:
    return [
        a
        for a in augment.AUGMENTATION_NAMES
        if any(r.get(f"attack_{suite}_{a}_bit_acc") is not None for r in rows)
    ]


# ---------------------------------------------------------------------------------------------- tests


def reference_method(rows: Sequence[Row]) -> Hashable:
    """The method others are compared with: the first of the MultiNeRF variant, else the first."""
    first = next((r for r in rows if r.get("variant") == "multinerf"), rows[0])
    return first.get("method")


def comparisons(rows: Sequence[Row], metrics: Mapping[str, tuple[str, str]]) -> list[str]:
    """The paired tests' table of ``metrics`` (column -> (header, format)): per setting (IDs, bits) its
    reference method against each other method, the pairs of one (reference, other) pooled over the
    settings."""
    pairs: dict[tuple, dict[str, list[float]]] = {}
    labels: dict[Hashable, str] = {}
    for members in group(rows, lambda r: settings_key(r, "num_ids", "bits")).values():
        methods = by_method(members)
        ref = reference_method(members)
        for m, rs in methods.items():
            labels.setdefault(m, label(rs))
            if m == ref:
                continue
            found = pairs.setdefault((ref, m), {metric: [] for metric in metrics})
            for metric in metrics:
                found[metric] += paired_differences(methods[ref], rs, metric).tolist()
    body = []
    for (ref, other), diffs in pairs.items():
        for metric in metrics:
            test = paired_test(diffs[metric])
            header, kind = metrics[metric]
            mean = show(test.mean_diff, kind)
            if test.tested:
                t_p, w_p = show_p(test.t_p), show_p(test.wilcoxon_p)
                t_p = "no spread" if math.isnan(test.t_p) else t_p
            else:
                t_p = w_p = "n < 2: no test"
            body.append([f"{labels[ref]} − {labels[other]}", header, str(test.n), mean, t_p, w_p])
    if not body:
        return []
    head = ["difference", "figure", "pairs", "mean diff.", "paired t-test p", "Wilcoxon p"]
    intro = (
        "Paired tests (two-sided), each pair a scene, IDs, bits and seed both methods ran; mean diff. in "
        "the figure's unit (percentage points for bit accuracy):"
    )
    return ["", intro, "", *table(head, body)]


# ----------------------------------------------------------------------------------------------- tables


def capacity_table(series: Mapping[Hashable, Sequence[Row]]) -> list[str]:
    """A row per number of IDs, the bit accuracy and PSNR of each method with the paper's beside."""
    ids = sorted({r["num_ids"] for rs in series.values() for r in rs})
    head = ["IDs"]
    for rs in series.values():
        head += [f"{label(rs)} bit acc. %", "paper", "PSNR dB", "paper"]
    body = []
    for n in ids:
        cells = [str(n)]
        for rs in series.values():
            at = [r for r in rs if r["num_ids"] == n]
            cells += metric_cells(at, ("bit_acc", "psnr"), ("bit_acc", "psnr")) if at else [MISSING] * 4
        body.append(cells)
    return table(head, body)


def ablation_table(rows: Sequence[Row]) -> list[str]:
    """A row per method, in the paper's order where it has the row; the paper's rows with no variant here
    too (with the paper's figures) when the rows stand beside the paper's ablation table."""
    methods = by_method(rows)
    metrics, paper = QUALITY, ("bit_acc", "psnr", "ssim", "lpips")
    head = ["paper row", "method", *metric_head(metrics, paper), "paper source"]
    body, shown = [], set()
    if any(ABLATION_TABLE in (r.get("paper_tables") or "").split() for r in rows):
        for name, figs in _paper_rows(ABLATION_TABLE).items():
            variant = figs[0].variant
            ours = [m for m, rs in methods.items() if rs[0].get("variant") == variant and variant]
            if not ours:
                values = {f.metric: f.value for f in figs}
                cells = []
                for m in metrics:
                    cells.append(MISSING)
                    if m in paper:
                        cells.append(show(values.get(m), METRICS[m][1]))
                why = "not implemented here" if variant is None else "not in this study"
                body.append([name, why, *cells, ABLATION_TABLE])
            for m in ours:
                body.append(
                    [
                        name,
                        label(methods[m]),
                        *metric_cells(methods[m], metrics, paper),
                        source(methods[m], paper),
                    ]
                )
                shown.add(m)
    for m, rs in methods.items():
        if m not in shown:
            body.append([MISSING, label(rs), *metric_cells(rs, metrics, paper), source(rs, paper)])
    return table(head, body)


def _paper_rows(table_id: str) -> dict[str, list[paper_numbers.PaperFigure]]:
    out: dict[str, list[paper_numbers.PaperFigure]] = {}
    for f in paper_numbers.figures():
        if f.table == table_id:
            out.setdefault(f.label, []).append(f)
    return out


def axis_table(rows: Sequence[Row], axis: str, title: str, metrics: Sequence[str]) -> list[str]:
    """A row per method and value of ``axis`` (#WMCom, bits) ordered by the value, the paper's beside."""
    paper = tuple(m for m in metrics if m != "bit_acc_worst_id")
    settings = group(rows, lambda r: settings_key(r, "method", axis)).values()
    methods = sorted(settings, key=lambda rs: rs[0][axis])
    head = [title, "method", *metric_head(metrics, paper), "paper source"]
    body = [
        [str(rs[0][axis]), label(rs), *metric_cells(rs, metrics, paper), source(rs, paper)] for rs in methods
    ]
    return table(head, body)


def single_table(rows: Sequence[Row]) -> list[str]:
    """A row per method with one ID, a column of bit accuracy and PSNR per scene, the paper's beside."""
    scenes = list(dict.fromkeys(r.get("scene") for r in rows))
    head = ["method"]
    for scene in scenes:
        head += [f"{scene} bit acc. %", "paper", f"{scene} PSNR dB", "paper"]
    body = []
    for rs in by_method(rows).values():
        cells = [label(rs)]
        for scene in scenes:
            at = [r for r in rs if r.get("scene") == scene]
            cells += metric_cells(at, ("bit_acc", "psnr"), ("bit_acc", "psnr")) if at else [MISSING] * 4
        body.append(cells)
    return table(head, body)


def robustness_table(rows: Sequence[Row], suites: Sequence[str]) -> list[str]:
    """A row per setting (scene, method, IDs, bits): bit accuracy without attack and the mean over each
    suite's attacks, and the share of views named under each suite."""
    head = ["scene", "method", "IDs", "bits", "no attack bit acc. %"]
    for s in suites:
        head += [f"{s}: bit acc. %", f"{s}: named %"]
    body = []
    for (scene, _, n, bits), rs in group(
        rows, lambda r: settings_key(r, "scene", "method", "num_ids", "bits")
    ).items():
        cells = [str(scene), label(rs), str(n), str(bits), show_summary(summary_of(rs, "bit_acc"), "pct")]
        for s in suites:
            cells += [
                show_summary(summary_of(rs, f"attack_{s}_bit_acc"), "pct"),
                show_summary(summary_of(rs, f"attack_{s}_named"), "pct"),
            ]
        body.append(cells)
    return table(head, body)


def per_attack_table(rows: Sequence[Row], suite: str) -> list[str]:
    """A row per setting, a column per attack of ``suite``: the mean bit accuracy over seeds (%)."""
    attacks = attacks_of(rows, suite)
    head = ["scene", "method", "IDs", "bits", *attacks]
    body = []
    for (scene, _, n, bits), rs in group(
        rows, lambda r: settings_key(r, "scene", "method", "num_ids", "bits")
    ).items():
        means = [show(summary_of(rs, f"attack_{suite}_{a}_bit_acc").mean, "pct") for a in attacks]
        body.append([str(scene), label(rs), str(n), str(bits), *means])
    return table(head, body)
