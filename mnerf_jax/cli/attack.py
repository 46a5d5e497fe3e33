"""``mnerf attack``: a watermarked run's evaluated renders under attack (``wm_attacks.evaluate_attacks``), or
its field under attack (``--model-suite``: ``evaluation.model_attacks``): bit accuracy, identification and
false claims per attack, ``RUN/eval-<split>-[model-]attacks[-<suite>].json``, a table and a bar plot beside
the JSON."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from mnerf_jax.cli import search_options

NAME = "attack"
HELP = (
    "Score a watermarked run's evaluated renders (the 8-bit PNGs mnerf evaluate saved) under attack: a suite "
    "(codecs, geometric, photometric, regen, peers, paper, all), named attacks, or the 14 augmentations at "
    "one strength (the default); or, with --model-suite, attacks on the field itself (noise, quantisation, "
    "pruning, fine-tuning) rendered again; bit accuracy, identification and false claims on the clean "
    "renders per attack; writes RUN/eval-<split>-[model-]attacks[-<suite>].json and .png."
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
        "--codec-model",
        action="append",
        default=[],
        metavar="ARCHITECTURE=WEIGHTS",
        help="add a row for one of CompressAI's learned codecs (bmshj2018-factorized, cheng2020-anchor, "
        "cheng2020-attn) run in JAX from its weights (a torch.save file of the state dict, or .npz), named "
        "ARCHITECTURE-qN; repeatable; alone, with the regen suite's stand-ins",
    )
    parser.add_argument(
        "--views",
        type=int,
        default=0,
        metavar="N",
        help="score N evenly spread evaluated views (with --model-suite: views of --split) (default 0: all)",
    )
    parser.add_argument(
        "--model-suite",
        default=None,
        metavar="NAME",
        help="attack the watermarked field instead of its saved renders: model (all), noise, quantise, prune "
        "or finetune; renders every ID's --views after each attack (no evaluation needed)",
    )
    parser.add_argument(
        "--finetune-steps",
        default="100,500,2000",
        metavar="N,...",
        help="with --model-suite: the fine-tuning rows' step counts (default 100,500,2000)",
    )
    parser.add_argument(
        "--finetune-id",
        type=int,
        default=0,
        metavar="K",
        help="with --model-suite: the ID the fine-tuning attacker holds and renders (default 0)",
    )
    parser.add_argument(
        "--data", type=Path, default=None, help="with --model-suite: the scene directory (default: the run's)"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the attacks' random parameters")
    search_options.add_arguments(parser, "every attack is also scored read with a search (the S: columns): ")
    parser.add_argument("--list", action="store_true", help="list the suites and their attacks, and stop")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from mnerf_jax.core.errors import MnerfError

    if args.list:
        from mnerf_jax.imaging import attack_suites
        from mnerf_jax.watermark import model_attacks

        print(attack_suites.listing())
        print(model_attacks.listing())
        return 0
    if args.run is None:
        raise MnerfError("mnerf attack needs --run WMRUN (or --list)")

    from mnerf_jax.cli.process import prepare_process

    prepare_process()
    if args.model_suite is not None:
        return run_model_suite(args)
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
        codec_models=args.codec_model,
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


def _step_counts(text: str) -> list[int]:
    """``--finetune-steps``: comma-separated positive step counts; one clear line otherwise."""
    from mnerf_jax.core.errors import MnerfError

    try:
        counts = [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        counts = []
    if not counts or min(counts) < 1:
        raise MnerfError(f"--finetune-steps takes step counts ≥ 1 separated by commas, got {text!r}")
    return counts


def run_model_suite(args: argparse.Namespace) -> int:
    """``--model-suite NAME``: the watermarked field attacked, rendered and read
    (``evaluation.model_attacks``); the table and plot as for the image suites."""
    from mnerf_jax.core.errors import MnerfError
    from mnerf_jax.evaluation import attack_report, model_attacks

    others = [
        flag
        for flag, value in (
            ("--suite", args.suite),
            ("--attacks", args.attacks),
            ("--strength", args.strength),
            ("--regen", args.regen),
            ("--codec-model", args.codec_model),
        )
        if value
    ]
    if others:
        raise MnerfError(f"--model-suite attacks the field, not the saved renders: drop {', '.join(others)}")
    t0 = time.perf_counter()
    result = model_attacks.evaluate_model_attacks(
        args.run,
        args.split,
        args.model_suite,
        args.views or None,
        finetune_steps=_step_counts(args.finetune_steps),
        held_id=args.finetune_id,
        seed=args.seed,
        data_path=args.data,
        progress=not args.quiet,
    )
    path = model_attacks.model_attacks_path(args.run, args.split, args.model_suite)
    plot = attack_report.attacks_plot(path.with_suffix(".png"), {args.run.name: result})
    print(attack_report.format_table(result))
    if not result["false_claims_measured"]:
        print(
            "mnerf attack: no clean renders (none saved by mnerf evaluate, and the source run is gone): "
            "false claims left out"
        )
    print(
        f"mnerf attack: {result['num_ids']} IDs × {result['views']} views × {len(result['attacks'])} "
        f"model attacks in {time.perf_counter() - t0:.1f} s -> {path}, {plot}"
    )
    return 0
