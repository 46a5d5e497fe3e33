"""Report of a watermarked run: a markdown summary, a PNG grid of each ID's render with its amplified residual
against the clean render, and a bar plot of per-ID bit accuracy (matplotlib, Agg backend: no display needed).

``write_report(out_dir, eval_result, renders_by_id, clean_render)`` reads the dict written by
``wm_eval.evaluate_watermarked_run`` (``eval-<split>.json``) and one view's renders.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from mnerf_jax.evaluation.plots import RESIDUAL_GAIN, bit_accuracy_plot, render_grid

# (label, key, format) rows of the summary table.
SUMMARY_ROWS: tuple[tuple[str, str, str], ...] = (
    ("IDs × bits", "_ids_bits", "{}"),
    ("views", "views", "{}"),
    ("bit accuracy, float render (mean over IDs)", "bit_accuracy_mean", "{:.2%}"),
    ("bit accuracy, float render (worst ID)", "bit_accuracy_min", "{:.2%}"),
    ("bit accuracy, 8-bit PNG (mean over IDs)", "bit_accuracy_png_mean", "{:.2%}"),
    ("identification accuracy (best match)", "identification_accuracy", "{:.2%}"),
    ("identification accuracy (binomial p < threshold)", "_verified_binomial", "{:.2%}"),
    ("identification accuracy (sign-flip p < threshold)", "_verified_sign_flip", "{:.2%}"),
    ("wrong ID named (binomial p < threshold)", "_wrong_binomial", "{:.2%}"),
    ("wrong ID named (sign-flip p < threshold)", "_wrong_sign_flip", "{:.2%}"),
    ("bit accuracy of clean renders (chance: 50 %)", "clean_bit_accuracy", "{:.2%}"),
    ("false detections on clean renders", "clean_false_detection_rate", "{:.2%}"),
    ("PSNR vs ground truth (dB)", "psnr", "{:.2f}"),
    ("PSNR of the clean model vs ground truth (dB)", "clean_psnr", "{:.2f}"),
    ("PSNR vs clean model's render (dB)", "psnr_clean_model", "{:.2f}"),
    ("SSIM vs ground truth", "ssim", "{:.4f}"),
    ("LPIPS vs ground truth", "lpips", "{:.4f}"),
)


def _fmt(fmt: str, value: Any) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    return fmt.format(value)


def weakest_bit(row: Mapping[str, Any]) -> str:
    """``"b10 44.0%"``: the bit an ID reads right on the fewest views; "n/a" for older evaluations."""
    per_bit = row.get("bit_accuracy_per_bit")
    if not per_bit:
        return "n/a"
    i = int(np.argmin(per_bit))
    return f"b{i} {per_bit[i]:.1%}"


def summary_rows(eval_result: Mapping[str, Any]) -> list[tuple[str, str]]:
    """``[(label, formatted value)]`` of the headline figures (missing ones are left out)."""
    values = dict(eval_result)
    values["_ids_bits"] = f"{eval_result.get('num_ids')} × {eval_result.get('bits')}"
    # Evaluations written before the sign-flip test decided by the binomial one and hold only that rate.
    by_test = eval_result.get("verified_identification_accuracy_by_test")
    if by_test is None and "verified_identification_accuracy" in eval_result:
        by_test = {"binomial": eval_result["verified_identification_accuracy"]}
    values.update({f"_verified_{test}": rate for test, rate in (by_test or {}).items()})
    # Evaluations written before this rate was reported leave these rows out.
    values.update(
        {
            f"_wrong_{test}": rate
            for test, rate in (eval_result.get("misidentification_rate_by_test") or {}).items()
        }
    )
    return [(label, _fmt(fmt, values[key])) for label, key, fmt in SUMMARY_ROWS if key in values]


def format_table(eval_result: Mapping[str, Any]) -> str:
    """The summary and per-ID figures as aligned plain text (for the terminal)."""
    rows = summary_rows(eval_result)
    width = max(len(label) for label, _ in rows)
    lines = [f"{label:<{width}}  {value}" for label, value in rows]
    per_id = eval_result.get("per_id") or []
    if per_id:
        mw = max(7, max(len(str(row.get("message", ""))) for row in per_id))
        lines.append("")
        header = (
            f"{'ID':>3}  {'message':<{mw}}  {'bit acc':>8}  {'PNG':>8}  {'identified':>10}  "
            f"{'named':>8}  {'weakest bit':>11}  {'PSNR':>6}"
        )
        lines.append(header)
        for row in per_id:
            lines.append(
                f"{row['id']:>3}  {row['message']:<{mw}}  {_fmt('{:.2%}', row.get('bit_accuracy')):>8}  "
                f"{_fmt('{:.2%}', row.get('bit_accuracy_png')):>8}  "
                f"{_fmt('{:.2%}', row.get('identification_accuracy')):>10}  "
                f"{_fmt('{:.2%}', row.get('verified_identification_accuracy')):>8}  "
                f"{weakest_bit(row):>11}  {_fmt('{:.2f}', row.get('psnr')):>6}"
            )
    return "\n".join(lines)


def markdown(eval_result: Mapping[str, Any], grid_png: str | None, bars_png: str | None) -> str:
    """The report's markdown text."""
    split = eval_result.get("split", "?")
    out = [f"# Watermark report ({split} split)", ""]
    if eval_result.get("variant"):
        decoder = eval_result.get("decoder_fingerprint", "?")
        out += [f"Variant: `{eval_result['variant']}`; decoder `{decoder}`.", ""]
    out += ["| figure | value |", "| --- | --- |"]
    out += [f"| {label} | {value} |" for label, value in summary_rows(eval_result)]
    ident = eval_result.get("identification") or {}
    if ident:
        out += [
            "",
            f"Identification: the best-matching key by soft correlation with the logits; named when its "
            f"Bonferroni-corrected p-value is below {ident.get('threshold')}: the binomial one of its "
            f"agreeing bits, or the sign-flip one of the agreement weighted by confidence (the run decides "
            f"by {ident.get('test', 'binomial').replace('_', '-')}; smallest attainable p-value with these "
            f"sizes: {_fmt('{:.3g}', ident.get('min_attainable_p'))}).",
        ]
    per_id = eval_result.get("per_id") or []
    if per_id:
        out += [
            "",
            "| ID | message | bit accuracy | 8-bit PNG | identified | named | weakest bit | PSNR (dB) |",
            "| --- | --- | --- | --- | --- | --- | --- | --- |",
        ]
        for row in per_id:
            out.append(
                f"| {row['id']} | `{row['message']}` | {_fmt('{:.2%}', row.get('bit_accuracy'))} | "
                f"{_fmt('{:.2%}', row.get('bit_accuracy_png'))} | "
                f"{_fmt('{:.2%}', row.get('identification_accuracy'))} | "
                f"{_fmt('{:.2%}', row.get('verified_identification_accuracy'))} | {weakest_bit(row)} | "
                f"{_fmt('{:.2f}', row.get('psnr'))} |"
            )
    if grid_png:
        caption = f"Renders of one view per ID (top), |render − clean render| × {RESIDUAL_GAIN:g} (bottom):"
        out += ["", caption, "", f"![renders]({grid_png})"]
    if bars_png:
        out += ["", "Bit accuracy per ID:", "", f"![bit accuracy]({bars_png})"]
    return "\n".join(out) + "\n"


def write_report(
    out_dir: str | Path,
    eval_result: Mapping[str, Any],
    renders_by_id: Mapping[int, np.ndarray],
    clean_render: np.ndarray,
) -> dict[str, Path]:
    """Write ``report.md``, ``renders.png`` and ``bit_accuracy.png`` into ``out_dir``; returns their paths.

    Args:
      eval_result: the evaluation dict (``wm_eval.evaluate_watermarked_run``).
      renders_by_id: ``{ID: render [H, W, 3]}`` of one view, float in [0, 1].
      clean_render: ``[H, W, 3]`` the clean (pre-watermark) model's render of that view.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    if renders_by_id:
        paths["grid"] = render_grid(out / "renders.png", renders_by_id, np.asarray(clean_render, np.float32))
    if eval_result.get("per_id"):
        paths["bars"] = bit_accuracy_plot(out / "bit_accuracy.png", eval_result)
    text = markdown(
        eval_result,
        "renders.png" if "grid" in paths else None,
        "bit_accuracy.png" if "bars" in paths else None,
    )
    paths["markdown"] = out / "report.md"
    paths["markdown"].write_text(text)
    return paths
