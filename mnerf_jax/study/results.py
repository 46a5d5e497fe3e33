"""A study's results as data: one row per cell with every setting and every figure.

Rows are rebuilt from the cells' folders (``DIR/cells/<id>/result.json``, ``error.json``) each time, so the
table of a study filled by several shards holds every shard's cells. ``DIR/results.json`` (a list of rows)
and ``DIR/results.csv`` (the same, one column per key) are written atomically, with ``DIR/results.md``, a
short markdown table that sets the measured figures beside the paper's (``paper_numbers``).

Units: bit accuracies and rates are fractions in [0, 1]; PSNR in dB; parameter counts in millions
(``params_m*``) and sizes in MiB of float32 (``size_mb*``); times in seconds; memory in MiB (the process's
peak resident set, see ``runner``).
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from mnerf_jax.core import config as config_lib
from mnerf_jax.core import rundir
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.evaluation import compare
from mnerf_jax.study import grid, paper_numbers
from mnerf_jax.study.spec import StudySpec

CELLS_DIR = "cells"
FITS_DIR = "fits"
RESULT_FILE = "result.json"
ERROR_FILE = "error.json"
TABLE_NAMES = ("results.json", "results.csv", "results.md")
MIB = float(2**20)

SETTING_COLUMNS = (
    "study",
    "cell_id",
    "status",
    "scene",
    "paper_scene",
    "scene_preset",
    "scene_data",
    "scene_set",
    "fit",
    "method",
    "variant",
    "method_preset",
    "method_set",
    "num_ids",
    "bits",
    "seed",
    "decoder",
    "wm_ranks",
    "wmcom",
    "phase1_steps",
    "phase2_steps",
    "phase3_steps",
    "ids_per_step",
    "cache_source",
    "noised",
    "time_budget_min",
    "split",
    "views",
)
# Figures of the evaluation beyond mnerf compare's (compare.figures_of): results-row name -> eval key.
EVALUATION_EXTRAS = {
    "named": "verified_identification_accuracy",
    "clean_claimed": "clean_false_detection_rate",
    "best_match_png": "identification_accuracy_png",
    "best_match_hard": "identification_accuracy_hard",
    "wrong": "misidentification_rate",
    "ssim": "ssim",
    "psnr_clean_model": "psnr_clean_model",
    "ssim_clean_model": "ssim_clean_model",
    "lpips_clean_model": "lpips_clean_model",
    "clean_psnr": "clean_psnr",
    "clean_ssim": "clean_ssim",
    "clean_lpips": "clean_lpips",
    "clean_bits": "clean_bit_accuracy",
    "views": "views",
}
FIGURE_COLUMNS = (
    "bit_acc",
    "bit_acc_png",
    "bit_acc_worst_id",
    "best_match",
    "best_match_png",
    "best_match_hard",
    "named",
    "named_binomial",
    "named_sign_flip",
    "named_worst_id",
    "wrong",
    "wrong_binomial",
    "wrong_sign_flip",
    "clean_claimed",
    "clean_claimed_binomial",
    "clean_claimed_sign_flip",
    "clean_bits",
    "psnr",
    "ssim",
    "lpips",
    "psnr_drop",
    "psnr_clean_model",
    "ssim_clean_model",
    "lpips_clean_model",
    "clean_psnr",
    "clean_ssim",
    "clean_lpips",
    "params_m",
    "params_m_watermark",
    "params_m_source",
    "size_mb",
    "size_mb_watermark",
    "size_mb_source",
    "embed_steps",
    "embed_stopped_by_budget",
)
# What the machine measures (times, memory): equal runs differ here and nowhere else.
MACHINE_COLUMNS = (
    "fit_s",
    "embed_s",
    "evaluate_s",
    "attack_s",
    "wall_s",
    "peak_rss_mb",
    "peak_rss_before_mb",
    "machine",
)
PAPER_METRICS = (
    "bit_acc",
    "psnr",
    "ssim",
    "lpips",
    "params_m",
    "params_m_watermark",
    "size_mb",
    "size_mb_source",
    "params_m_source",
)
PAPER_COLUMNS = (*(f"paper_{m}" for m in PAPER_METRICS), "paper_tables", "paper_approx")
ATTACK_FIGURES = {
    "bit_acc": "bit_accuracy_mean",
    "bit_acc_worst_id": "bit_accuracy_min",
    "best_match": "identification_accuracy",
    "named": "verified_identification_accuracy",
}


# mnerf compare's names of the bit accuracies; here ``bits`` is the message length, a setting.
RENAMED = {"bits": "bit_acc", "bits_png": "bit_acc_png", "bits_worst_id": "bit_acc_worst_id"}


def evaluation_figures(result: Mapping[str, Any]) -> dict[str, Any]:
    """A results row's figures of one ``eval-<split>.json`` dict (``evaluate_watermarked_run``)."""
    figures: dict[str, Any] = {RENAMED.get(k, k): v for k, v in compare.figures_of(result).items()}
    figures.update({name: result.get(key) for name, key in EVALUATION_EXTRAS.items()})
    figures["id_test"] = (result.get("identification") or {}).get("test")
    return figures


def param_columns(counts: Mapping[str, int]) -> dict[str, float]:
    """Parameter counts (millions) and float32 sizes (MiB) from ``runner.param_counts``: the whole
    watermarked run, its watermark part and the TensoRF's (the rest)."""
    whole, whole_bytes = counts["count"], counts["bytes"]
    wm, wm_bytes = counts["watermark_count"], counts["watermark_bytes"]
    return {
        "params_m": whole / 1e6,
        "params_m_watermark": wm / 1e6,
        "params_m_source": (whole - wm) / 1e6,
        "size_mb": whole_bytes / MIB,
        "size_mb_watermark": wm_bytes / MIB,
        "size_mb_source": (whole_bytes - wm_bytes) / MIB,
    }


def attack_figures(suite: str, result: Mapping[str, Any]) -> dict[str, Any]:
    """Columns of one attack suite (``evaluate_attacks``): the mean over its attacks, each attack's bits."""
    out: dict[str, Any] = {}
    mean = result.get("mean_over_attacks") or {}
    for name, key in ATTACK_FIGURES.items():
        out[f"attack_{suite}_{name}"] = mean.get(key)
    for attack, scores in (result.get("attacks") or {}).items():
        out[f"attack_{suite}_{attack}_bit_acc"] = scores.get("bit_accuracy_mean")
        out[f"attack_{suite}_{attack}_named"] = scores.get("verified_identification_accuracy")
    return out


def read_json(path: Path) -> dict[str, Any] | None:
    """A JSON object from ``path``; None when missing or unreadable (a cell then counts as not done)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    return data if isinstance(data, dict) else None


def cell_dir(out: Path, cell: grid.Cell) -> Path:
    return out / CELLS_DIR / cell.id


def finished_result(out: Path, cell: grid.Cell, measure: Mapping[str, Any]) -> dict[str, Any] | None:
    """The cell's ``result.json`` when it finished under these measurements, else None."""
    result = read_json(cell_dir(out, cell) / RESULT_FILE)
    if result is None or result.get("measure") != dict(measure) or result.get("cell") != cell.settings():
        return None
    return result


def _settings(spec: StudySpec, cell: grid.Cell) -> dict[str, Any]:
    scene, method = cell.scene, cell.method
    return {
        "study": spec.name,
        "cell_id": cell.id,
        "scene": scene.name,
        "paper_scene": paper_numbers.paper_scene(scene.name, scene.paper),
        "scene_preset": scene.preset,
        "scene_data": scene.data,
        "scene_set": " ".join(scene.fit_overrides()) or None,
        "fit": scene.fit,
        "method": method.name,
        "variant": method.variant,
        "method_preset": method.preset,
        "method_set": " ".join(method.set) or None,
        "num_ids": cell.num_ids,
        "bits": cell.bits,
        "seed": cell.seed,
        "decoder": cell.decoder,
        "split": spec.measure.split,
    }


def _resolved(cell: grid.Cell, fits: dict[str, Any]) -> dict[str, Any]:
    """The resolved settings of a cell not yet embedded (from the spec; empty when it cannot resolve)."""
    key = grid.fit_id(cell.scene)
    try:
        if key not in fits:
            fits[key] = grid.fit_config(cell.scene)
        return grid.resolved_settings(grid.embed_config(cell, fits[key]))
    except MnerfError:
        return {}


def _embedded_settings(config: Mapping[str, Any]) -> dict[str, Any]:
    """The resolved settings of the config an embedding recorded (empty for one this version cannot read)."""
    try:
        return grid.resolved_settings(config_lib.from_dict(config))
    except MnerfError:
        return {}


def row(spec: StudySpec, cell: grid.Cell, out: Path, fits: dict[str, Any] | None = None) -> dict[str, Any]:
    """The results row of ``cell``: its settings, status and, when done, every figure (module docstring)."""
    values = _settings(spec, cell)
    result = finished_result(out, cell, spec.measure.to_dict())
    if result is None:
        error = read_json(cell_dir(out, cell) / ERROR_FILE)
        values["status"] = "failed" if error is not None else "pending"
        values["error"] = None if error is None else error.get("error")
        values.update(_resolved(cell, {} if fits is None else fits))
    else:
        embed, evaluate = result["embed"], result["evaluate"]
        attacks = result.get("attacks", {})
        values["status"] = "done"
        values.update(_embedded_settings(embed["config"]))
        values.update(evaluation_figures(evaluate["result"]))
        values.update(param_columns(embed["params"]))
        values["embed_steps"] = embed.get("steps")
        values["embed_stopped_by_budget"] = embed.get("stopped_by_budget")
        for suite, record in attacks.items():
            values.update(attack_figures(suite, record))
        times = {
            "fit_s": result.get("fit", {}).get("seconds"),
            # Over all the embedding's processes where it was resumed (records before run_seconds: its last).
            "embed_s": embed.get("run_seconds", embed.get("seconds")),
            "evaluate_s": evaluate.get("seconds"),
            "attack_s": sum(r.get("seconds", 0.0) for r in attacks.values()) if attacks else None,
        }
        times["wall_s"] = sum(v for k, v in times.items() if k != "fit_s" and v is not None)
        values.update(times)
        values["peak_rss_mb"] = result.get("peak_rss_mb")
        values["peak_rss_before_mb"] = result.get("peak_rss_before_mb")
        values["machine"] = result.get("machine")  # None for a cell finished before it was recorded
    found = paper_numbers.match(values)
    for metric in PAPER_METRICS:
        values[f"paper_{metric}"] = found[metric].value if metric in found else None
    values["paper_tables"] = " ".join(sorted({f.table for f in found.values()})) or None
    values["paper_approx"] = any(f.approx for f in found.values()) if found else None
    return values


def columns_of(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """Every column of ``rows``: the fixed ones in order, then attack columns as they first appear, error."""
    fixed = [*SETTING_COLUMNS, *FIGURE_COLUMNS, "id_test", *MACHINE_COLUMNS]
    extra = [k for r in rows for k in r if k.startswith("attack_") and k not in fixed]
    attack = list(dict.fromkeys(extra))
    return [*fixed, *attack, *PAPER_COLUMNS, "error"]


def to_csv(rows: Sequence[Mapping[str, Any]]) -> str:
    columns = columns_of(rows)
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for r in rows:
        writer.writerow({k: "" if r.get(k) is None else r.get(k) for k in columns})
    return buffer.getvalue()


def _show(value: Any, kind: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "—"
    if kind == "pct":
        return f"{100.0 * value:.1f} %"
    if kind == "db":
        return f"{value:+.2f}"
    return f"{value:.3f}" if isinstance(value, float) else str(value)


def _beside(r: Mapping[str, Any], metric: str, kind: str) -> str:
    measured, paper = _show(r.get(metric), kind), r.get(f"paper_{metric}")
    return measured if paper is None else f"{measured} ({_show(paper, kind)})"


def _status(r: Mapping[str, Any]) -> str:
    """The cell's status, and where the time budget stopped its embedding, at which of its steps: such a
    cell's figures are not those of the study's schedule."""
    if r["status"] != "done" or not r.get("embed_stopped_by_budget"):
        return str(r["status"])
    planned = (r.get("phase1_steps") or 0) + (r.get("phase2_steps") or 0)
    return f"done, stopped by the time budget at step {r.get('embed_steps')} of {planned:,}"


def to_markdown(spec: StudySpec, rows: Sequence[Mapping[str, Any]]) -> str:
    """A short report: every cell's main figures, the paper's in brackets where it has one."""
    head = ["cell", "status", "bit acc. (paper)", "PNG", "worst ID", "named", "clean claimed", "PSNR (paper)"]
    head += ["ΔPSNR", "SSIM (paper)", "LPIPS (paper)", "params M (paper)", "paper tables"]
    lines = [
        f"# Study {spec.name}",
        "",
        "Measured figures, the paper's in brackets where a table holds one for the same setting "
        "(`paper_numbers.toml`; approx: read from the text). Every figure is in results.csv.",
        "",
        "| " + " | ".join(head) + " |",
        "|" + " --- |" * len(head),
    ]
    for r in rows:
        cells = [
            f"`{r['cell_id']}`",
            _status(r),
            _beside(r, "bit_acc", "pct"),
            _show(r.get("bit_acc_png"), "pct"),
            _show(r.get("bit_acc_worst_id"), "pct"),
            _show(r.get("named"), "pct"),
            _show(r.get("clean_claimed"), "pct"),
            _beside(r, "psnr", "num"),
            _show(r.get("psnr_drop"), "db"),
            _beside(r, "ssim", "num"),
            _beside(r, "lpips", "num"),
            _beside(r, "params_m", "num"),
            (r.get("paper_tables") or "—") + (" (approx)" if r.get("paper_approx") else ""),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    failed = [r for r in rows if r["status"] == "failed"]
    if failed:
        lines += ["", "Failed cells:", ""]
        lines += [f"- `{r['cell_id']}`: {r.get('error')}" for r in failed]
    return "\n".join(lines) + "\n"


def write_tables(spec: StudySpec, out: Path) -> list[dict[str, Any]]:
    """Rebuild every cell's row of ``spec`` from ``out``, write the three tables; returns the rows."""
    fits: dict[str, Any] = {}
    rows = [row(spec, cell, out, fits) for cell in grid.expand(spec)]
    columns = columns_of(rows)
    rows = [{c: r.get(c) for c in columns} for r in rows]  # tidy: every row has every column
    rundir.write_json_atomic(out / "results.json", rows)
    rundir.write_text_atomic(out / "results.csv", to_csv(rows))
    rundir.write_text_atomic(out / "results.md", to_markdown(spec, rows))
    return rows
