"""``mnerf compare``: several watermarked runs' evaluations side by side, seeds of a setting summarised."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

NAME = "compare"
HELP = (
    "Tabulate watermarked runs' evaluations (eval-<split>.json), and with --attacks their scores under an "
    "attack suite, grouped by the [watermark] settings they differ in; each setting's runs (seeds) as mean "
    "and range."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "runs",
        nargs="+",
        type=Path,
        metavar="WMRUN",
        help="watermarked run directories, each evaluated with mnerf evaluate",
    )
    parser.add_argument(
        "--split", default="test", help="the evaluation to read: eval-<split>.json (default test)"
    )
    parser.add_argument(
        "--ignore",
        default="",
        metavar="FIELD,...",
        help="more [watermark] fields (or source_run) to fold, as seeds are",
    )
    parser.add_argument(
        "--plot",
        type=Path,
        metavar="FILE.png",
        help="also plot each run's PSNR drop against its bit accuracy",
    )
    which = parser.add_mutually_exclusive_group()
    which.add_argument(
        "--attacks",
        metavar="SUITE",
        help="also tabulate each run's scores under this mnerf attack --suite "
        "(eval-<split>-attacks-SUITE.json)",
    )
    which.add_argument(
        "--model-attacks",
        metavar="SUITE",
        help="also tabulate each run's scores under this mnerf attack --model-suite",
    )
    parser.add_argument("--json", action="store_true", help="print JSON instead of the tables")


def run(args: argparse.Namespace) -> int:
    from mnerf_jax.evaluation import compare

    extra = [f.strip() for f in args.ignore.split(",") if f.strip()]
    attacks = None
    if args.attacks or args.model_attacks:
        attacks = compare.AttackSuite(args.attacks or args.model_attacks, model=bool(args.model_attacks))
    groups = compare.compare_runs(args.runs, args.split, (*compare.IGNORED_BY_DEFAULT, *extra), attacks)
    if args.plot is not None:
        compare.tradeoff_plot(args.plot, groups)
    if args.json:
        print(json.dumps(compare.to_json(groups), indent=2))
        return 0
    print(compare.runs_table(groups))
    print()
    print(compare.summary_table(groups))
    if attacks is not None:
        print()
        print(compare.attack_table(groups))
    if args.plot is not None:
        print(f"\nplot: {args.plot}")
    return 0
