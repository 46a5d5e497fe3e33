"""The figures of a study's report (PNG, matplotlib with the Agg backend of ``evaluation.plots``).

- the capacity curve: bit accuracy and PSNR against the number of IDs (log2 axis), a line per method at
  the mean over seeds with the seeds' min–max as a band, the paper's figures for the same settings dashed
  in the method's colour;
- robustness: a heat map per attack suite, a row per setting and a column per attack, the mean bit
  accuracy over seeds.
"""

from __future__ import annotations

from collections.abc import Hashable, Mapping, Sequence
from pathlib import Path

import numpy as np

from mnerf_jax.evaluation.plots import plt  # pyplot, the Agg backend chosen
from mnerf_jax.study.report_stats import Row, group, summary_of
from mnerf_jax.study.report_tables import attacks_of, label, paper_figure, settings_key

DPI = 110


def _curve(rows: Sequence[Row], metric: str, scale: float) -> tuple[np.ndarray, ...]:
    """``(ids, mean, low, high, paper_ids, paper)`` of ``metric`` × ``scale`` over the rows' numbers of IDs
    (nan where no cell is done); the paper's where it has a figure."""
    ids = sorted({r["num_ids"] for r in rows})
    stats = [summary_of([r for r in rows if r["num_ids"] == n], metric) for n in ids]
    found = [(n, paper_figure([r for r in rows if r["num_ids"] == n], metric)) for n in ids]
    paper = [(n, f.value) for n, f in found if f is not None]
    return (
        np.asarray(ids, float),
        np.asarray([s.mean for s in stats]) * scale,
        np.asarray([s.low for s in stats]) * scale,
        np.asarray([s.high for s in stats]) * scale,
        np.asarray([n for n, _ in paper], float),
        np.asarray([v for _, v in paper], float) * scale,
    )


def capacity_plot(path: Path, series: Mapping[Hashable, Sequence[Row]], title: str) -> Path:
    """Bit accuracy (%) and PSNR (dB) against the number of IDs, a line per method of ``series``."""
    fig, axes = plt.subplots(1, 2, figsize=(10.0, 3.8))
    for ax, (metric, scale, ylabel) in zip(
        axes, (("bit_acc", 100.0, "bit accuracy (%)"), ("psnr", 1.0, "PSNR (dB)")), strict=True
    ):
        for i, rs in enumerate(series.values()):
            colour = f"C{i}"
            ids, mean, low, high, paper_ids, paper = _curve(rs, metric, scale)
            ax.plot(ids, mean, "o-", color=colour, label=label(rs).replace("`", ""))
            ax.fill_between(ids, low, high, color=colour, alpha=0.2, linewidth=0)
            if paper.size:
                ax.plot(paper_ids, paper, "s--", color=colour, alpha=0.8, label="paper, same setting")
        if metric == "bit_acc":
            ax.axhline(50.0, color="grey", linestyle=":", linewidth=1, label="chance")
        ax.set_xscale("log", base=2)
        all_ids = [r["num_ids"] for rs in series.values() for r in rs]
        ax.set_xlim(min(all_ids) / 1.3, max(all_ids) * 1.3)  # set: a series may have no cell done yet
        ax.set_xlabel("number of IDs")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="lower left")
    fig.suptitle(title + " (band: the seeds' min–max; dashed: the paper's)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def robustness_plot(path: Path, rows: Sequence[Row], suite: str) -> Path:
    """A heat map of the mean bit accuracy (%) under each attack of ``suite``, a row per setting."""
    attacks = attacks_of(rows, suite)
    settings = group(rows, lambda r: settings_key(r, "scene", "method", "num_ids", "bits"))
    names = [f"{s} {label(rs).replace('`', '')} {n} IDs × {b} b" for (s, _, n, b), rs in settings.items()]
    values = np.asarray(
        [
            [summary_of(rs, f"attack_{suite}_{a}_bit_acc").mean * 100 for a in attacks]
            for rs in settings.values()
        ],
        float,
    ).reshape(len(settings), len(attacks))
    fig, ax = plt.subplots(figsize=(2.5 + 0.55 * len(attacks), 1.2 + 0.3 * len(settings)))
    cmap = plt.get_cmap("viridis").with_extremes(bad="lightgrey")
    image = ax.imshow(np.ma.masked_invalid(values), cmap=cmap, vmin=50, vmax=100, aspect="auto")
    if values.size <= 600:
        for (i, j), v in np.ndenumerate(values):
            if np.isfinite(v):
                ax.text(
                    j,
                    i,
                    f"{v:.0f}",
                    ha="center",
                    va="center",
                    fontsize=6,
                    color="white" if v < 75 else "black",
                )
    ax.set_xticks(range(len(attacks)), attacks, rotation=60, ha="right", fontsize=7)
    ax.set_yticks(range(len(names)), names, fontsize=7)
    fig.colorbar(image, ax=ax, label="bit accuracy (%)")
    ax.set_title(f"attack suite {suite}: mean bit accuracy over seeds (grey: not measured)", fontsize=9)
    fig.savefig(path, dpi=DPI, bbox_inches="tight")  # the settings' names set the margin
    plt.close(fig)
    return path
