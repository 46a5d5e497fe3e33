"""``mnerf embed``: embed N keyed watermarks into a fitted TensoRF run (MultiNeRF's two-phase embedding)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from mnerf_jax.core import embed_defaults

NAME = "embed"
HELP = (
    "Embed N keyed watermark messages into a fitted TensoRF run; writes a watermarked run "
    "(checkpoints, keys.json, the fine-tuned decoder)."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--from",
        dest="source",
        type=Path,
        required=True,
        metavar="RUN",
        help="fitted TensoRF run directory (mnerf fit --out RUN)",
    )
    parser.add_argument("--out", type=Path, required=True, metavar="WMRUN", help="watermarked run to create")
    parser.add_argument("--num-ids", type=int, required=True, metavar="N", help="number of watermark IDs")
    parser.add_argument("--bits", type=int, required=True, metavar="L", help="message length in bits")
    parser.add_argument(
        "--config",
        default=embed_defaults.AUTO,
        metavar="PRESET",
        help="the embedding's settings: auto (default: chosen from the fitted run's image size, scene, "
        "number of IDs and the device, printed at the start), paper (the paper's method), run (the "
        "[watermark] section the fitted run recorded), or a preset name or TOML file",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config field, e.g. --set watermark.schedule.phase2_steps=400 (repeatable)",
    )
    parser.add_argument(
        "--decoder",
        type=Path,
        default=None,
        metavar="FILE",
        help="decoder to start from (default: the shipped decoder for --bits); 'fresh': "
        "a random-init decoder whitened on the scene's training images, trained in "
        "phase 2",
    )
    parser.add_argument("--data", type=Path, default=None, help="scene directory (default: the fitted run's)")
    parser.add_argument("--resume", action="store_true", help="continue the embedding in --out")
    parser.add_argument(
        "--time-budget",
        type=float,
        default=None,
        metavar="MIN",
        help="end within MIN minutes of wall time: stop before a step that would not fit "
        "(the run so far is saved; --resume continues it; sets "
        "watermark.time_budget.minutes)",
    )
    parser.add_argument(
        "--steps",
        type=int,
        default=None,
        metavar="K",
        help="stop after K steps in all (a checkpoint is written; --resume continues)",
    )
    parser.add_argument(
        "--eval-views",
        type=int,
        default=-1,
        metavar="V",
        help="afterwards evaluate on V test views (0: all; default -1: no evaluation)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from mnerf_jax.core import xla_cpu
    from mnerf_jax.evaluation import watermarked as wm_eval
    from mnerf_jax.watermark import embed

    if args.config == embed_defaults.FROM_RUN and not args.resume:
        drift = embed.watermark_defaults_drift(args.source, args.set)
        if drift:
            print(
                f"mnerf embed: note: {args.source} recorded [watermark] settings that differ from today's "
                f"defaults of its preset: {'; '.join(drift)}. Embedding with the recorded ones; "
                "--config PRESET or --set watermark.KEY=VALUE to change them.",
                file=sys.stderr,
            )
    overrides = list(args.set)
    if args.time_budget is not None:
        overrides.append(f"watermark.time_budget.minutes={args.time_budget}")
    result = embed.embed(
        args.source,
        args.out,
        args.num_ids,
        args.bits,
        preset=args.config,
        overrides=overrides,
        decoder_path=args.decoder,
        data_path=args.data,
        resume=args.resume,
        stop_at=args.steps,
        progress=not args.quiet,
    )
    last = result.last_metrics
    summary = {
        "out": str(result.run_dir),
        "num_ids": result.keys.num_ids,
        "bits": result.keys.bits,
        "min_hamming": result.keys.min_hamming,
        "steps": int(result.steps),
        "seconds": round(result.seconds, 1),
        "run_seconds": round(result.run_seconds, 1),  # over all its processes, when resumed
        "last_bit_accuracy": last.get("bit_acc"),
        "last_psnr": last.get("psnr"),
    }
    if result.stopped_by_budget:
        summary["stopped_by_budget"] = True
    for name in ("field_steps", "field_scheduled", "phase3_steps", "phase3_scheduled"):  # phase 3 ran
        if name in last:
            summary[name] = int(last[name])
    print(f"mnerf embed: {json.dumps(summary)}")
    if args.eval_views >= 0:
        del result  # the embedding's buffers and compiled steps go before the evaluation compiles its own
        xla_cpu.release_compiled()
        evaluation = wm_eval.evaluate_watermarked_run(
            args.out, "test", args.data, max_views=args.eval_views or None, progress=not args.quiet
        )
        from mnerf_jax.evaluation.report import format_table

        print(format_table(evaluation))
    if summary["steps"] == 0:
        print("mnerf embed: no steps were run", file=sys.stderr)
    return 0
