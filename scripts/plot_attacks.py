"""Bit accuracy per attack of several watermarked runs side by side, from each run's
``WMRUN/eval-<split>-attacks.json`` (or, with ``--suite S``, ``eval-<split>-attacks-S.json``; written by
``mnerf attack``).

    python scripts/plot_attacks.py WMRUN [WMRUN ...] --out attacks.png [--labels A,B] [--split test]
        [--suite S]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    from mnerf_jax.evaluation.attack_report import attacks_plot
    from mnerf_jax.evaluation.attacks import attacks_path

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", nargs="+", type=Path, metavar="WMRUN")
    parser.add_argument("--out", type=Path, required=True, help="PNG to write")
    parser.add_argument("--labels", default=None, help="comma-separated labels, one per run")
    parser.add_argument("--split", default="test", help="the evaluated split (default test)")
    parser.add_argument("--suite", default=None, help="the suite mnerf attack ran (default: none named)")
    args = parser.parse_args(argv)
    labels = args.labels.split(",") if args.labels else [run.name for run in args.runs]
    if len(labels) != len(args.runs):
        parser.error(f"--labels names {len(labels)} runs, {len(args.runs)} given")
    results = {}
    for run, label in zip(args.runs, labels, strict=True):
        path = attacks_path(run, args.split, args.suite)
        if not path.is_file():
            suite = f" --suite {args.suite}" if args.suite else ""
            parser.error(
                f"{path} not found: run `mnerf attack --run {run} --split {args.split}{suite}` first"
            )
        results[label] = json.loads(path.read_text())
    print(attacks_plot(args.out, results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
