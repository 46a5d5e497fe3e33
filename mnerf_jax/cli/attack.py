"""``mnerf attack``: a watermarked run's evaluated renders under attack (``wm_attacks.evaluate_attacks``):
bit accuracy, identification and false claims per attack, ``RUN/eval-<split>-attacks[-<suite>].json``, a
table and a bar plot beside the JSON."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from mnerf_jax.cli import search_options

NAME = "attack"
HELP = (
    "Score a watermarked run's evaluated renders (the 8-bit PNGs mnerf evaluate saved) under attack: a suite "
    "(codecs, geometric, photometric, regen, peers, paper, all), named attacks, or the 14 augmentations at "
    "one strength (the default); bit accuracy, identification and false claims on the clean renders per "
    "attack; writes RUN/eval-<split>-attacks[-<suite>].json and .png."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--run",
        type=Path,
        help="watermarked run directory (mnerf embed), evaluated on --split by mnerf evaluate",
    )
    parser.add_argument("--split", default="test", help="the evaluated split (default test)")
    parser.add_argument(
        "--suite",
        default=None,
        metavar="NAME",
        help="a suite of attacks: codecs, geometric, photometric, regen, peers, paper, all "
        "(--list names them)",
    )
    parser.add_argument(
        "--attacks",
        default="",
        metavar="NAMES",
        help="comma-separated attack names instead of a suite (a+b composes); the 14 augmentation names "
        "take --strength",
    )
    parser.add_argument(
        "--strength",
        default=None,
        choices=("low", "medium", "high"),
        help="without --suite: the augmentations' strength, the paper's policies (default low)",
    )
    parser.add_argument(
        "--regen",
        default=None,
        metavar="MODULE:FUNCTION",
        help="add a row for your own regeneration model: a function taking and returning uint8 images "
        "[B, H, W, 3] (module importable, or path/to/file.py); alone, with the regen suite's stand-ins",
    )
    parser.add_argument(
        "--views",
        type=int,
        default=0,
        metavar="N",
        help="score N evenly spread evaluated views (default 0: all)",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the attacks' random parameters")
    search_options.add_arguments(parser, "every attack is also scored read with a search (the S: columns): ")
    parser.add_argument("--list", action="store_true", help="list the suites and their attacks, and stop")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from mnerf_jax.core.errors import MnerfError

    if args.list:
        from mnerf_jax.imaging import attack_suites

        print(attack_suites.listing())
        return 0
    if args.run is None:
        raise MnerfError("mnerf attack needs --run WMRUN (or --list)")

    from mnerf_jax.cli.process import prepare_process

    prepare_process()
    from mnerf_jax.evaluation import attack_report
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
        suite=args.suite,
        regen=args.regen,
        **search_options.of_args(args),
    )
    path = wm_attacks.attacks_path(args.run, args.split, result["suite"])
    plot = attack_report.attacks_plot(path.with_suffix(".png"), {args.run.name: result})
    print(attack_report.format_table(result))
    if not result["false_claims_measured"]:
        print(
            f"mnerf attack: no clean renders saved under {args.run / f'eval-{args.split}' / 'clean'} "
            "(run mnerf evaluate again to save them): false claims left out"
        )
    print(
        f"mnerf attack: {result['num_ids']} IDs × {result['views']} views × {len(result['attacks'])} "
        f"attacks in {time.perf_counter() - t0:.1f} s -> {path}, {plot}"
    )
    return 0
