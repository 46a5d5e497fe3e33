"""A study's report: ``DIR/report.md`` and its figures ``DIR/figures/*.png``, from the rows of the table.

The report holds, each where the study's rows form it (``report_tables`` says how they are chosen): the
capacity curve (bit accuracy and PSNR against the number of IDs, the paper's beside), the ablation table,
the #WMCom and bit-length tables, the single-message table, and robustness under each attack suite; each
figure over its seeds (mean ± standard deviation, n), methods compared by paired tests, then the failed
cells with their errors. It is rebuilt whole from the rows each time (``mnerf study`` writes it at the end of
a run, ``--report-only`` alone), so that a study filled by shards reports every shard's cells.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from mnerf_jax.core import rundir
from mnerf_jax.study import report_plots, report_tables
from mnerf_jax.study.report_stats import Row
from mnerf_jax.study.report_tables import METRICS, MISSING, comparisons, seeds_line

REPORT_FILE = "report.md"
FIGURES_DIR = "figures"
TESTED = {m: METRICS[m] for m in ("bit_acc", "psnr")}
NONE = "No rows of this study form this table."


def _figure(out: Path, name: str) -> tuple[Path, str]:
    """The figure's path and its markdown link (relative to the report)."""
    return out / FIGURES_DIR / name, f"![{name}]({FIGURES_DIR}/{name})"


def head(rows: Sequence[Row], name: str, spec: str | None, command: str | None) -> list[str]:
    """The report's title, spec, command, machines, and the cells' statuses."""
    status = {s: sum(r.get("status") == s for r in rows) for s in ("done", "failed", "pending")}
    hosts = {str(r["machine"]) for r in rows if r.get("machine") and r.get("status") == "done"}
    seeds = sorted({r.get("seed") for r in rows if r.get("seed") is not None})
    return [
        f"# Study {name}: report",
        "",
        f"- spec: `{spec or MISSING}`",
        f"- command: `{command or MISSING}`",
        "- machine: " + ("; ".join(sorted(hosts)) if hosts else "not recorded in the cells' rows"),
        f"- cells: {len(rows)}; done {status['done']}, failed {status['failed']}, "
        f"pending {status['pending']}; seeds {', '.join(map(str, seeds)) or MISSING}",
        "",
        "Each figure is the mean ± standard deviation over the setting's done cells (n: how many; one cell a "
        "seed), `—` where none is done. Bit accuracies in percent. `paper`: the paper's figure for the same "
        "setting (`mnerf_jax/study/paper_numbers.toml`; ≈: read from its text), `paper source` its table. "
        "Every cell's figures are in results.csv.",
    ]


def capacity_section(out: Path, rows: Sequence[Row]) -> list[str]:
    lines = ["", "## Capacity: bit accuracy and PSNR against the number of IDs"]
    found = report_tables.capacity_series(rows)
    for (scene, bits), series in found.items():
        members = [r for rs in series.values() for r in rs]
        path, link = _figure(out, f"capacity-{scene}-b{bits}.png")
        report_plots.capacity_plot(path, series, f"{scene}, {bits}-bit messages")
        lines += ["", f"### {scene}, {bits}-bit messages", "", link, "", seeds_line(members), ""]
        lines += report_tables.capacity_table(series)
        lines += comparisons(members, TESTED)
    return lines if found else [*lines, "", NONE]


def ablation_section(rows: Sequence[Row]) -> list[str]:
    lines = ["", "## Ablation (tab:ablation)"]
    found = report_tables.ablation_groups(rows)
    for (scene, n, bits), members in found.items():
        wmcom = members[0].get("wmcom")
        lines += ["", f"### {scene}, {n} IDs × {bits} bits, #WMCom {wmcom}", "", seeds_line(members), ""]
        lines += report_tables.ablation_table(members)
        lines += comparisons(members, TESTED)
    return lines if found else [*lines, "", NONE]


AXIS_WORDS = {
    "scene": "{}",
    "num_ids": "{} IDs",
    "bits": "{} bits",
    "wmcom": "#WMCom {}",
    "noised": "noised: {}",
}


def axis_section(
    rows: Sequence[Row], axis: str, heading: str, title: str, keys: Sequence[str], tag: str
) -> list[str]:
    lines = ["", f"## {heading} ({tag})"]
    metrics = (*report_tables.QUALITY, "params_m_watermark") if axis == "wmcom" else report_tables.QUALITY
    found = report_tables.axis_groups(rows, axis, keys)
    for key, members in found.items():
        where = ", ".join(AXIS_WORDS[k].format(v) for k, v in zip(keys, key, strict=True))
        lines += ["", f"### {where}", "", seeds_line(members), ""]
        lines += report_tables.axis_table(members, axis, title, metrics)
    return lines if found else [*lines, "", NONE]


def single_section(rows: Sequence[Row]) -> list[str]:
    lines = ["", "## Single message: one ID (tab:bit_acc_single)"]
    found = report_tables.single_groups(rows)
    for bits, members in found.items():
        lines += ["", f"### {bits}-bit message", "", seeds_line(members), ""]
        lines += report_tables.single_table(members)
        lines += comparisons(members, TESTED)
    return lines if found else [*lines, "", NONE]


def robustness_section(out: Path, rows: Sequence[Row]) -> list[str]:
    lines = ["", "## Robustness: bit accuracy under the attack suites"]
    suites = report_tables.suites_of(rows)
    if not suites:
        return [*lines, "", "No cell of this study measured an attack suite ([measure] attacks)."]
    attacked = [r for r in rows if any(r.get(f"attack_{s}_bit_acc") is not None for s in suites)]
    lines += ["", seeds_line(attacked), "", *report_tables.robustness_table(attacked, suites)]
    tested = {f"attack_{s}_bit_acc": (f"{s}: bit acc. %", "pct") for s in suites}
    lines += comparisons(attacked, tested)
    for suite in suites:
        if not report_tables.attacks_of(attacked, suite):
            continue  # the suite's mean only, no attack's own figure
        path, link = _figure(out, f"robustness-{suite}.png")
        report_plots.robustness_plot(path, attacked, suite)
        lines += [
            "",
            f"### Suite {suite}",
            "",
            link,
            "",
            "<details><summary>each attack (mean over seeds)</summary>",
        ]
        lines += ["", *report_tables.per_attack_table(attacked, suite), "", "</details>"]
    return lines


def failures_section(rows: Sequence[Row]) -> list[str]:
    failed = [r for r in rows if r.get("status") == "failed"]
    pending = [r for r in rows if r.get("status") == "pending"]
    lines = ["", "## Failed and pending cells", ""]
    if not failed and not pending:
        return [*lines, "Every cell is done."]
    lines += [f"- failed `{r['cell_id']}`: {r.get('error') or MISSING}" for r in failed]
    if pending:
        lines += [
            f"- pending (not run yet): {len(pending)} cells, "
            + ", ".join(f"`{r['cell_id']}`" for r in pending)
        ]
    return lines


def to_markdown(
    out: Path, rows: Sequence[Row], name: str, spec: str | None = None, command: str | None = None
) -> str:
    """The whole report (writing its figures into ``out/figures``)."""
    lines = head(rows, name, spec, command)
    lines += capacity_section(out, rows)
    lines += ablation_section(rows)
    wmcom_keys, bits_keys = ("scene", "num_ids", "bits"), ("scene", "num_ids", "wmcom", "noised")
    lines += axis_section(rows, "wmcom", "#WMCom", "#WMCom", wmcom_keys, "tab:tensor_components_ablation")
    lines += axis_section(rows, "bits", "Bit length", "bits", bits_keys, "tab:ablation_bit_length_sclable")
    lines += single_section(rows)
    lines += robustness_section(out, rows)
    lines += failures_section(rows)
    return "\n".join(lines) + "\n"


def write_report(
    out: str | Path,
    rows: Sequence[Mapping[str, Any]],
    name: str,
    spec: str | None = None,
    command: str | None = None,
) -> Path:
    """Write ``out/report.md`` and ``out/figures/*.png`` from the table's ``rows``; returns the report's
    path. The figures folder holds this report's figures only (older ones are removed)."""
    out = Path(out)
    figures = out / FIGURES_DIR
    figures.mkdir(parents=True, exist_ok=True)
    for old in figures.glob("*.png"):
        old.unlink()
    path = out / REPORT_FILE
    rundir.write_text_atomic(path, to_markdown(out, rows, name, spec, command))
    return path
