"""``mnerf evaluate``: PSNR / SSIM / LPIPS of a run's renders on a split (``RUN/eval-<split>.json``)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

NAME = "evaluate"
HELP = "Evaluate a fitted run on a split (PSNR, SSIM, LPIPS); writes RUN/eval-<split>.json."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--run", type=Path, required=True, help="run directory written by mnerf fit")
    parser.add_argument("--split", default="test", help="test | val | train (default test)")
    parser.add_argument(
        "--data", type=Path, help="scene directory holding the split (default: the run's data)"
    )
    parser.add_argument("--views", type=int, default=0, metavar="N",
                        help="evaluate N evenly spread views (default 0: all)")  # fmt: skip
    parser.add_argument(
        "--lpips", choices=("alex", "vgg"), default="alex", help="LPIPS network (default alex)"
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from mnerf_jax.commands.fit import prepare_process

    prepare_process()
    from mnerf_jax import run as runs

    loaded = runs.load_run(args.run)
    split = loaded.load_scene(args.data, splits=(args.split,)).split(args.split)
    n = len(runs.view_indices(len(split), args.views))
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
    result.update({
        "split": args.split,
        "step": loaded.step,
        "data": str(args.data.expanduser().resolve()) if args.data is not None else loaded.data_path,
        "render_seconds": round(time.perf_counter() - t0, 2),
    })  # fmt: skip
    path = Path(args.run) / f"eval-{args.split}.json"
    runs.write_json_atomic(path, result)
    summary = {k: v for k, v in result.items() if k not in ("per_view", "view_names")}
    print(json.dumps(summary, sort_keys=True))
    return 0
