"""Training curves of watermarked runs: bit accuracy of the training renders, and their PSNR against the
clean model's renders with the quality budget of each step, from each run's ``WMRUN/tb`` scalars.

    python scripts/plot_embed_curves.py WMRUN [WMRUN ...] --out curves.png [--labels A,B]

Each point is the mean of 10 steps (``scalar_log.LOG_EVERY``); bit accuracy is read on the un-augmented
training renders by the decoder before that step's update.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mnerf_jax.core.scalar_log import read_scalars

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", nargs="+", type=Path, metavar="WMRUN")
    parser.add_argument("--out", type=Path, required=True, help="PNG to write")
    parser.add_argument("--labels", default=None, help="comma-separated labels, one per run")
    args = parser.parse_args(argv)
    labels = args.labels.split(",") if args.labels else [run.name for run in args.runs]
    if len(labels) != len(args.runs):
        parser.error(f"--labels names {len(labels)} runs, {len(args.runs)} given")

    fig, (ax_bits, ax_psnr) = plt.subplots(1, 2, figsize=(11, 4))
    for run, label in zip(args.runs, labels, strict=True):
        curves = read_scalars(run / "tb")
        if "train/bit_acc" not in curves:
            print(f"{run}: no training curves (tb/ missing or empty)", file=sys.stderr)
            return 1
        steps, bits = np.array(curves["train/bit_acc"]).T
        line = ax_bits.plot(steps, 100 * bits, label=label)[0]
        if "train/psnr_clean" in curves:
            s, p = np.array(curves["train/psnr_clean"]).T
            ax_psnr.plot(s, p, color=line.get_color(), label=f"{label}: renders")
        if "train/psnr_budget" in curves:
            s, b = np.array(curves["train/psnr_budget"]).T
            ax_psnr.plot(s, b, color=line.get_color(), linestyle="--", label=f"{label}: budget")
    ax_bits.set(xlabel="step", ylabel="bit accuracy, training renders (%)", ylim=(40, 101))
    ax_psnr.set(xlabel="step", ylabel="PSNR against the clean model's render (dB)")
    for ax in (ax_bits, ax_psnr):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
