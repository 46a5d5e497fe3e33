"""Figures of the evaluation (matplotlib with the Agg backend: no display needed)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (the backend is chosen before pyplot loads)
import numpy as np  # noqa: E402

RESIDUAL_GAIN = 10.0


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
