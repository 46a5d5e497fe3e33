"""``mnerf fit``: train a TensoRF field on a scene, then evaluate it on the test views."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from mnerf_jax.cli.process import prepare_process
from mnerf_jax.core import rundir
from mnerf_jax.data import view_indices
from mnerf_jax.watermark import run as wm_run

NAME = "fit"
HELP = "Fit a TensoRF radiance field to a scene (checkpoints, TensorBoard, test metrics in --out)."

# Default preset per detected scene layout when --config is not given.
_PRESET_FOR_LAYOUT = {"blender": "blender", "llff": "llff", "nerfstudio": "capture"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, help="scene directory (not needed for the procedural config)")
    parser.add_argument("--out", type=Path, required=True, help="run directory to create (or to --resume)")
    parser.add_argument(
        "--config", help="preset name in configs/ or a TOML path (default: from the scene layout)"
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config field, e.g. --set train.n_iters=2000 (repeatable)",
    )
    parser.add_argument(
        "--resume", action="store_true", help="continue the run in --out from its last checkpoint"
    )
    parser.add_argument(
        "--eval-views",
        type=int,
        default=0,
        metavar="N",
        help="evaluate on N evenly spread test views (default 0: all)",
    )
    parser.add_argument("--no-eval", action="store_true", help="skip the test-set evaluation at the end")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def choose_preset(config_name: str | None, data: Path | None) -> str:
    """The preset to use: ``--config``, else one matching the scene layout, else ``procedural``."""
    if config_name:
        return config_name
    if data is None:
        return "procedural"
    from mnerf_jax.core.errors import MnerfError
    from mnerf_jax.data import detect_dataset

    layout = detect_dataset(Path(data).expanduser())
    if layout not in _PRESET_FOR_LAYOUT:
        raise MnerfError(f"no default preset for a {layout} scene; pass --config")
    return _PRESET_FOR_LAYOUT[layout]


class Progress:
    """tqdm bar (step, loss, PSNR, rays/s) and TensorBoard scalars every ``log_every`` steps."""

    def __init__(self, out: Path, total: int, batch: int, log_every: int, quiet: bool):
        from tensorboardX import SummaryWriter

        self.total, self.batch, self.log_every, self.quiet = total, batch, max(log_every, 1), quiet
        self.writer = SummaryWriter(str(out / "tb"))
        self.bar: Any = None
        self.window: list[dict[str, float]] = []
        self.window_start = time.perf_counter()

    def __call__(self, step: int, metrics: dict[str, float]) -> None:
        if self.bar is None and not self.quiet:
            from tqdm import tqdm

            self.bar = tqdm(total=self.total, initial=step, unit="step", dynamic_ncols=True, file=sys.stderr)
        self.window.append(metrics)
        if self.bar is not None:
            self.bar.update(1)
        if (step + 1) % self.log_every and step + 1 != self.total:
            return
        now = time.perf_counter()
        n = len(self.window)
        mean = {k: sum(m[k] for m in self.window) / n for k in self.window[-1]}
        rays_per_s = n * self.batch / max(now - self.window_start, 1e-9)
        for key in ("loss", "mse", "psnr", "density_count", "colour_count"):
            self.writer.add_scalar(f"train/{key}", mean[key], step + 1)
        self.writer.add_scalar("train/rays_per_s", rays_per_s, step + 1)
        if self.bar is not None:
            self.bar.set_postfix(
                loss=f"{mean['loss']:.4f}",
                psnr=f"{mean['psnr']:.2f}",
                rays_s=f"{rays_per_s:,.0f}",
                refresh=False,
            )
        self.window, self.window_start = [], now

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
        self.writer.flush()
        self.writer.close()


def run(args: argparse.Namespace) -> int:
    prepare_process()
    from mnerf_jax.core.config import load_config

    preset = choose_preset(args.config, args.data)
    config = load_config(preset, args.set)
    summary = fit_run(
        config,
        args.data,
        args.out,
        resume=args.resume,
        evaluate=not args.no_eval,
        eval_views=args.eval_views,
        quiet=args.quiet,
    )
    test = summary.get("test", {})
    line = f"mnerf fit: {summary['steps']} steps in {summary['train_seconds']:.1f} s"
    if test:
        line += f"; test PSNR {test['psnr']:.2f} dB, SSIM {test['ssim']:.4f}, LPIPS {test['lpips']:.4f}"
        line += f" over {test['views']} views"
    print(line + f" -> {args.out / 'metrics.json'}")
    return 0


def fit_run(
    config: Any,
    data: Path | None,
    out: Path,
    *,
    resume: bool = False,
    evaluate: bool = True,
    eval_views: int = 0,
    quiet: bool = False,
) -> dict[str, Any]:
    """Fit ``config`` on the scene at ``data`` into the run directory ``out``; returns metrics.json's dict.

    Everything that can be checked is checked before anything is written: the output directory (see
    ``rundir.prepare_output``) and the scene.
    """
    from mnerf_jax.core.config import ConfigError

    resuming = rundir.prepare_output(out, config, resume=resume)
    if resume and not resuming and not quiet:
        print(f"mnerf fit: {out} holds no run yet; starting a new one", file=sys.stderr)
    procedural = config.data.dataset == "procedural"
    if not procedural and data is None:
        raise ConfigError(f"config {config.name!r} reads a {config.data.dataset} scene: pass --data PATH")

    from mnerf_jax.data import load_scene
    from mnerf_jax.tensorf.fit import loop as train

    scene = load_scene(data, config.data, config.render, ("train", "test"))
    if not resuming:
        rundir.write_run_files(out, config, data=None if procedural else data)
    if scene.transform is not None:
        rundir.write_json_atomic(out / rundir.SCENE_TRANSFORM_FILE, scene.transform.to_dict())

    progress = Progress(out, config.train.n_iters, config.train.batch_size, config.train.log_every, quiet)
    try:
        result = train.fit(config, scene, out, resume=resuming, on_step=progress)
    finally:
        progress.close()

    summary: dict[str, Any] = {
        "steps": result.steps,
        "train_seconds": round(result.total_train_seconds, 2),
        "session_train_seconds": round(result.train_seconds, 2),
        "train_rays_per_s": round(result.rays_per_second, 1),
        "train_psnr": result.last_metrics.get("psnr"),
        "compiles": result.compiles,
        "compile_seconds": round(result.compile_seconds, 1),
        "redone_steps": result.redone_steps,
        "resolution": list(result.state.resolution),
        "config": config.name,
    }
    if evaluate:
        summary["test"] = evaluate_test(out, eval_views, quiet=quiet)
    rundir.write_json_atomic(out / "metrics.json", summary)
    return summary


def evaluate_test(run_dir: Path, max_views: int, quiet: bool = False) -> dict[str, Any]:
    """Evaluate the latest checkpoint of ``run_dir`` on its test split; also writes ``eval-test.json``."""
    from mnerf_jax.tensorf import run as runs

    loaded = wm_run.load_run(run_dir)
    scene = loaded.load_scene(splits=("test",), max_views=max_views)
    split = scene.split("test")
    n = len(view_indices(len(split), max_views))
    bar = None
    if not quiet:
        from tqdm import tqdm

        bar = tqdm(total=n, unit="view", desc="test views", dynamic_ncols=True, file=sys.stderr)
    t0 = time.perf_counter()
    try:
        result = runs.evaluate_split(
            loaded,
            split,
            max_views=max_views,
            on_view=(lambda i, rgb: bar.update(1)) if bar is not None else None,
        )
    finally:
        if bar is not None:
            bar.close()
    result.update(
        {"split": "test", "step": loaded.step, "render_seconds": round(time.perf_counter() - t0, 2)}
    )
    rundir.write_json_atomic(run_dir / "eval-test.json", result)
    return {k: v for k, v in result.items() if k not in ("per_view", "view_names")}
