"""``mnerf evaluate``: PSNR / SSIM / LPIPS of a run's renders on a split (``RUN/eval-<split>.json``).

On a watermarked run (``mnerf embed``) it evaluates every ID instead (``wm_eval.evaluate_watermarked_run``:
bit accuracy, identification, quality against the ground truth and the clean model) and prints the table.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from mnerf_jax.core import rundir
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.data import PATH_SPLIT, view_indices
from mnerf_jax.watermark import run as wm_run

NAME = "evaluate"
HELP = (
    "Evaluate a fitted run on a split (PSNR, SSIM, LPIPS), or a watermarked run (also bit accuracy and "
    "identification of every ID); writes RUN/eval-<split>.json."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--run", type=Path, required=True, help="run directory written by mnerf fit or mnerf embed"
    )
    parser.add_argument(
        "--split",
        default="test",
        help="test | val | train, or path for a watermarked run: --views N views (default 30) along the "
        "render path, read and compared with the clean model's renders (default test)",
    )
    parser.add_argument(
        "--data", type=Path, help="scene directory holding the split (default: the run's data)"
    )
    parser.add_argument(
        "--views",
        type=int,
        default=0,
        metavar="N",
        help="evaluate N evenly spread views (default 0: all)",
    )
    parser.add_argument(
        "--lpips", choices=("alex", "vgg"), default="alex", help="LPIPS network (default alex)"
    )
    parser.add_argument(
        "--read-jitter",
        type=int,
        default=None,
        metavar="R",
        help="watermarked runs: average the decoder's logits over the read windows moved by "
        "up to R pixels (default: the run's watermark.reading.jitter)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from mnerf_jax.cli.process import prepare_process

    prepare_process()
    from mnerf_jax.tensorf import run as runs

    marker = rundir.read_marker(args.run) if args.run.is_dir() else None
    if marker is not None and marker.get("kind") == rundir.WATERMARK_KIND:
        return evaluate_watermarked(args)
    loaded = wm_run.load_run(args.run)
    if args.split == PATH_SPLIT:
        raise MnerfError(
            f"--split {PATH_SPLIT} has no ground truth: it evaluates watermarked runs only "
            f"(mnerf render --split {PATH_SPLIT} renders a fitted run's path)"
        )
    split = loaded.load_scene(args.data, splits=(args.split,), max_views=args.views).split(args.split)
    n = len(view_indices(len(split), args.views))
    bar = None
    if not args.quiet:
        from tqdm import tqdm

        bar = tqdm(total=n, unit="view", desc=f"evaluate {args.split}", dynamic_ncols=True, file=sys.stderr)
    t0 = time.perf_counter()
    try:
        result = runs.evaluate_split(
            loaded,
            split,
            max_views=args.views,
            lpips_net=args.lpips,
            on_view=(lambda i, rgb: bar.update(1)) if bar is not None else None,
        )
    finally:
        if bar is not None:
            bar.close()
    result.update(
        {
            "split": args.split,
            "step": loaded.step,
            "data": str(args.data.expanduser().resolve()) if args.data is not None else loaded.data_path,
            "render_seconds": round(time.perf_counter() - t0, 2),
        }
    )
    path = Path(args.run) / f"eval-{args.split}.json"
    rundir.write_json_atomic(path, result)
    summary = {k: v for k, v in result.items() if k not in ("per_view", "view_names")}
    print(json.dumps(summary, sort_keys=True))
    return 0


def evaluate_watermarked(args: argparse.Namespace) -> int:
    """Every ID of a watermarked run on ``args.split``: writes ``RUN/eval-<split>.json`` (and the PNGs it
    decodes, ``RUN/eval-<split>/id<K>/``), prints the summary table."""
    from mnerf_jax.evaluation import report
    from mnerf_jax.evaluation import watermarked as wm_eval

    t0 = time.perf_counter()
    result = wm_eval.evaluate_watermarked_run(
        args.run,
        args.split,
        args.data,
        max_views=args.views or None,
        lpips_net=args.lpips,
        progress=not args.quiet,
        read_jitter=args.read_jitter,
    )
    print(report.format_table(result))
    path = Path(args.run) / f"eval-{args.split}.json"
    print(
        f"mnerf evaluate: {result['num_ids']} IDs × {result['views']} views in "
        f"{time.perf_counter() - t0:.1f} s -> {path}"
    )
    return 0
