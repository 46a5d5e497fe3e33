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

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

RESIDUAL_GAIN = 10.0

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
    values.update({f"_wrong_{test}": rate
                   for test, rate in (eval_result.get("misidentification_rate_by_test") or {}).items()})
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
        header = (f"{'ID':>3}  {'message':<{mw}}  {'bit acc':>8}  {'PNG':>8}  {'identified':>10}  "
                  f"{'named':>8}  {'weakest bit':>11}  {'PSNR':>6}")
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
        out += ["", "| ID | message | bit accuracy | 8-bit PNG | identified | named | weakest bit "
                    "| PSNR (dB) |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
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


def residual(render: np.ndarray, clean: np.ndarray, gain: float = RESIDUAL_GAIN) -> np.ndarray:
    """``clip(|render − clean| × gain, 0, 1)``: ``[H, W, 3]``."""
    return np.clip(np.abs(np.asarray(render, np.float32) - np.asarray(clean, np.float32)) * gain, 0.0, 1.0)


def render_grid(path: Path, renders_by_id: Mapping[int, np.ndarray], clean_render: np.ndarray) -> Path:
    """PNG grid: top row the clean render and each ID's render; bottom row the amplified residuals."""
    ids = sorted(renders_by_id)
    cols = len(ids) + 1
    fig, axes = plt.subplots(2, cols, figsize=(2.2 * cols, 4.6), squeeze=False)
    axes[0, 0].imshow(np.clip(clean_render, 0, 1))
    axes[0, 0].set_title("clean", fontsize=9)
    axes[1, 0].imshow(np.zeros_like(clean_render))
    axes[1, 0].set_title(f"residual ×{RESIDUAL_GAIN:g}", fontsize=9)
    for j, n in enumerate(ids, start=1):
        img = np.asarray(renders_by_id[n])
        axes[0, j].imshow(np.clip(img, 0, 1))
        axes[0, j].set_title(f"ID {n}", fontsize=9)
        res = residual(img, clean_render)
        axes[1, j].imshow(res)
        axes[1, j].set_title(f"max |Δ| = {np.abs(img - clean_render).max():.3f}", fontsize=8)
    for ax in axes.ravel():
        ax.set_axis_off()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def bit_accuracy_plot(path: Path, eval_result: Mapping[str, Any]) -> Path:
    """Bar plot of per-ID bit accuracy (float render and 8-bit PNG) with the 50 % chance line."""
    per_id = list(eval_result.get("per_id") or [])
    ids = [row["id"] for row in per_id]
    acc = [row.get("bit_accuracy", math.nan) for row in per_id]
    png = [row.get("bit_accuracy_png", math.nan) for row in per_id]
    x = np.arange(len(ids))
    fig, ax = plt.subplots(figsize=(max(4.0, 0.6 * len(ids) + 2.0), 3.2))
    ax.bar(x - 0.2, np.asarray(acc, float) * 100, width=0.4, label="float render")
    ax.bar(x + 0.2, np.asarray(png, float) * 100, width=0.4, label="8-bit PNG")
    ax.axhline(50.0, color="grey", linestyle="--", linewidth=1, label="chance")
    ax.set_xticks(x, [str(i) for i in ids])
    ax.set_xlabel("watermark ID")
    ax.set_ylabel("bit accuracy (%)")
    ax.set_ylim(0, 100)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


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
    text = markdown(eval_result, "renders.png" if "grid" in paths else None,
                    "bit_accuracy.png" if "bars" in paths else None)
    paths["markdown"] = out / "report.md"
    paths["markdown"].write_text(text)
    return paths


def demo_watermark(
    run_dir: str | Path,
    out_dir: str | Path,
    *,
    num_ids: int = 4,
    bits: int = 16,
    overrides: tuple[str, ...] | list[str] = (),
    decoder_path: str | Path | None = None,
    eval_views: int | None = None,
    quiet: bool = False,
) -> dict[str, Any]:
    """The demo's watermark part: embed ``num_ids × bits`` into the fitted run, evaluate, write the report.

    Writes ``out_dir/wm`` (the watermarked run; an earlier, unfinished one is resumed and a finished one
    reused) and ``out_dir/report`` (``report.md``, ``renders.png``, ``bit_accuracy.png``). Returns
    ``{"eval": ..., "report": {name: path}, "rows": [(label, value)], "table": str}``.
    """
    from mnerf_jax import embed, wm_eval
    from mnerf_jax import run as runs

    out = Path(out_dir)
    wm_dir = out / "wm"
    marker = runs.read_marker(wm_dir) if wm_dir.is_dir() else None
    resume = marker is not None and marker.get("kind") == embed.WM_KIND
    embed.embed(run_dir, wm_dir, num_ids, bits, overrides=overrides, decoder_path=decoder_path, resume=resume,
                progress=not quiet)  # fmt: skip
    result = wm_eval.evaluate_watermarked_run(wm_dir, "test", max_views=eval_views, progress=not quiet,
                                              keep_renders=True)  # fmt: skip
    renders = {n: r[0] for n, r in result.pop("_renders").items()}
    clean = result.pop("_clean")
    result.pop("_gt")
    reference = clean[0] if clean is not None else next(iter(renders.values()))
    paths = write_report(out / "report", result, renders, reference)
    return {"eval": result, "report": paths, "rows": summary_rows(result), "table": format_table(result)}
