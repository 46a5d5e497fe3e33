"""``mnerf render``: render a run's views (a data split, or a camera path with a video) to PNGs."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from mnerf_jax.core import rundir
from mnerf_jax.data import PATH_SPLIT
from mnerf_jax.watermark import run as wm_run

NAME = "render"
HELP = (
    "Render a fitted or watermarked run: the views of a split, or an orbit/spiral camera path with a GIF "
    "or MP4; --id K picks the watermark ID of a watermarked run."
)

VIDEO_FORMATS = ("gif", "mp4")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--run", type=Path, required=True, help="run directory written by mnerf fit or mnerf embed"
    )
    parser.add_argument(
        "--id",
        type=int,
        default=None,
        metavar="K",
        help="watermark ID to render, 0..N-1 (watermarked runs only; default 0)",
    )
    parser.add_argument("--split", default="test", help="test | train | val | path (default test)")
    parser.add_argument("--out", type=Path, required=True, help="output directory for the PNGs (and video)")
    parser.add_argument("--data", type=Path, help="scene directory (default: the one the run was fitted on)")
    parser.add_argument(
        "--views",
        type=int,
        default=0,
        metavar="N",
        help="render N evenly spread views of the split (default 0: all)",
    )
    parser.add_argument("--frames", type=int, default=120, help="frames of the camera path (--split path)")
    parser.add_argument("--fps", type=int, default=30, help="video frame rate (--split path)")
    parser.add_argument("--format", choices=VIDEO_FORMATS, default="gif", help="video format (--split path)")
    parser.add_argument("--overwrite", action="store_true", help="replace files already in --out")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def check_targets(out: Path, names: list[str], overwrite: bool) -> None:
    """Refuse (MnerfError, nothing written) to write into a run directory or over existing files."""

    if out.exists() and not out.is_dir():
        raise rundir.RunError(f"--out {out} is a file, not a directory")
    if rundir.read_marker(out) is not None:
        raise rundir.RunError(
            f"--out {out} is a run directory; render into a subdirectory such as {out / 'renders'}"
        )
    if overwrite:
        return
    clash = [n for n in names if (out / n).exists()]
    if clash:
        raise rundir.RunError(
            f"--out {out} already holds {clash[0]} (and {len(clash) - 1} more of the files "
            "to write); pass --overwrite or choose another directory"
        )


def write_video(path: Path, frames: list[np.ndarray], fps: int) -> None:
    """Write uint8 ``[H, W, 3]`` frames as a looping GIF or an MP4 (needs imageio-ffmpeg)."""
    import imageio.v3 as iio

    from mnerf_jax.core.errors import MnerfError

    if path.suffix == ".gif":
        iio.imwrite(path, np.stack(frames), extension=".gif", duration=1000.0 / max(fps, 1), loop=0)
        return
    try:
        iio.imwrite(path, np.stack(frames), extension=".mp4", fps=fps, codec="libx264")
    except Exception as err:  # imageio raises assorted errors when no ffmpeg plugin is installed
        raise MnerfError(
            f"cannot write {path.name} ({err}); install imageio-ffmpeg or use --format gif"
        ) from None


def render_to(
    run: Any,
    split_name: str,
    out: Path,
    *,
    data: Path | None = None,
    views: int = 0,
    frames: int = 120,
    fps: int = 30,
    video_format: str = "gif",
    overwrite: bool = False,
    quiet: bool = False,
) -> dict[str, Any]:
    """Render ``split_name`` (or ``path``) of a loaded run into ``out``; returns what was written."""
    import imageio.v3 as iio

    from mnerf_jax.data.images import to_uint8
    from mnerf_jax.tensorf import run as runs

    on_path = split_name == PATH_SPLIT
    cameras, indices, stems, _ = run.split_views(split_name, data, frames if on_path else views)
    names = [f"{stem}.png" for stem in stems]
    video = f"path.{video_format}" if on_path else None
    targets = [*names, video] if video else names
    check_targets(out, targets, overwrite)
    out.mkdir(parents=True, exist_ok=True)

    bar = None
    if not quiet:
        from tqdm import tqdm

        bar = tqdm(
            total=len(indices), unit="view", desc=f"render {split_name}", dynamic_ncols=True, file=sys.stderr
        )
    lookup = dict(zip(indices, names, strict=True))
    written: list[np.ndarray] = []

    def save(i: int, rgb: np.ndarray) -> None:
        image = to_uint8(rgb)
        iio.imwrite(out / lookup[i], image)
        written.append(image)
        if bar is not None:
            bar.update(1)

    try:
        runs.render_views(run, cameras, indices, on_view=save)
    finally:
        if bar is not None:
            bar.close()
    result: dict[str, Any] = {"split": split_name, "views": len(indices), "out": str(out), "images": names}
    if video is not None:
        write_video(out / video, written, fps)
        result["video"] = video
    return result


def load_for_render(run_dir: Path, wm_id: int | None = None) -> Any:
    """``wm_run.load_run(run_dir)``, set to render watermark ID ``wm_id`` when given.

    MnerfError (nothing written) for an ID on a run without watermarks or outside ``[0, N)``.
    """
    loaded = wm_run.load_run(run_dir)
    return loaded if wm_id is None else wm_run.with_id(loaded, wm_id)


def run(args: argparse.Namespace) -> int:
    from mnerf_jax.cli.process import prepare_process

    prepare_process()
    loaded = load_for_render(args.run, args.id)
    result = render_to(
        loaded,
        args.split,
        args.out,
        data=args.data,
        views=args.views,
        frames=args.frames,
        fps=args.fps,
        video_format=args.format,
        overwrite=args.overwrite,
        quiet=args.quiet,
    )
    extra = f" and {result['video']}" if "video" in result else ""
    wm_id = loaded.extras.get("id")
    which = f" of watermark ID {wm_id}" if wm_id is not None else ""
    print(f"mnerf render: {result['views']} images{extra}{which} -> {args.out}")
    return 0
