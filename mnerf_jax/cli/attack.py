"""``mnerf attack``: a watermarked run's evaluated renders under each of the 14 augmentations
(``wm_attacks.evaluate_attacks``): bit accuracy and identification per attack,
``RUN/eval-<split>-attacks.json`` and a bar plot beside it."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

NAME = "attack"
HELP = (
    "Score a watermarked run's evaluated renders (the 8-bit PNGs mnerf evaluate saved) under each of the "
    "14 augmentations alone: bit accuracy and identification per attack; writes "
    "RUN/eval-<split>-attacks.json and .png."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--run",
        type=Path,
        required=True,
        help="watermarked run directory (mnerf embed), evaluated on --split by mnerf evaluate",
    )
    parser.add_argument("--split", default="test", help="the evaluated split (default test)")
    parser.add_argument(
        "--strength",
        default="low",
        choices=("low", "medium", "high"),
        help="attack strength, the paper's policies (default low)",
    )
    parser.add_argument(
        "--attacks", default="", metavar="NAMES", help="comma-separated augmentation names (default: all 14)"
    )
    parser.add_argument(
        "--views",
        type=int,
        default=0,
        metavar="N",
        help="score N evenly spread evaluated views (default 0: all)",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the attacks' random parameters")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from mnerf_jax.cli.process import prepare_process

    prepare_process()
    from mnerf_jax.evaluation import attacks as wm_attacks

    t0 = time.perf_counter()
    names = [n.strip() for n in args.attacks.split(",") if n.strip()]
    result = wm_attacks.evaluate_attacks(
        args.run,
        args.split,
        args.strength,
        names or None,
        args.views or None,
        args.seed,
        progress=not args.quiet,
    )
    plot = wm_attacks.attacks_plot(Path(args.run) / f"eval-{args.split}-attacks.png", {args.run.name: result})
    print(wm_attacks.format_table(result))
    path = Path(args.run) / f"eval-{args.split}-attacks.json"
    print(
        f"mnerf attack: {result['num_ids']} IDs × {result['views']} views × {len(result['attacks'])} "
        f"attacks in {time.perf_counter() - t0:.1f} s -> {path}, {plot}"
    )
    return 0
