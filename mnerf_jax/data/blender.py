"""NeRF-Synthetic (Blender) scenes: ``transforms_<split>.json`` + RGBA images.

Each JSON holds ``camera_angle_x`` (horizontal field of view, radians) and ``frames`` with a
``file_path`` (relative, often without its ``.png`` suffix) and a 4x4 OpenGL camera-to-world
``transform_matrix``. Images are composited on the background, then area-downscaled; the focal
length is ``0.5 W / tan(0.5 camera_angle_x)`` with the principal point at the image centre.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mnerf_jax.data.images import image_size, load_images, read_json, resolve_image, scaled_size
from mnerf_jax.data.types import Cameras, DataError, SceneSplit, view_indices


def parse_matrix(value: Any, where: str) -> np.ndarray:
    """A 4x4 (or 3x4) camera-to-world matrix from JSON -> float64 [3, 4]."""
    try:
        m = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{where}: transform_matrix is not a numeric matrix") from None
    if m.shape not in ((4, 4), (3, 4)):
        raise DataError(f"{where}: transform_matrix must be 4x4, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise DataError(f"{where}: transform_matrix has non-finite entries")
    return m[:3]


def number(meta: dict, key: str, where: str, default: float | None = None) -> float | None:
    """A finite number from metadata, ``default`` when absent."""
    if key not in meta or meta[key] is None:
        return default
    value = meta[key]
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise DataError(f"{where}: {key} must be a finite number, got {value!r}")
    return float(value)


def frame_list(meta: Any, json_path: Path) -> list[dict]:
    """The ``frames`` list of a transforms file, checked to be a non-empty list of objects."""
    if not isinstance(meta, dict):
        raise DataError(f"{json_path}: expected a JSON object at the top level")
    frames = meta.get("frames")
    if not isinstance(frames, list):
        raise DataError(f"{json_path}: missing 'frames' list")
    if not frames:
        raise DataError(f"{json_path}: the split is empty ('frames' has no entries)")
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
            raise DataError(f"{json_path}: frame {i} has no 'file_path'")
        if "transform_matrix" not in frame:
            raise DataError(f"{json_path}: frame {i} has no 'transform_matrix'")
    return frames


def blender_focal(meta: dict, width: int, json_path: Path) -> tuple[float, float]:
    """(fx, fy) in pixels at the file's resolution: ``fl_x``/``fl_y`` if given, else from the field
    of view ``camera_angle_x`` (square pixels)."""
    fl_x = number(meta, "fl_x", str(json_path))
    if fl_x is None:
        angle = number(meta, "camera_angle_x", str(json_path))
        if angle is None:
            raise DataError(f"{json_path}: missing camera_angle_x (the horizontal field of view)")
        if not 0.0 < angle < math.pi:
            raise DataError(f"{json_path}: camera_angle_x must be in (0, pi) radians, got {angle}")
        fl_x = 0.5 * width / math.tan(0.5 * angle)
    fl_y = number(meta, "fl_y", str(json_path), fl_x)
    return fl_x, fl_y


def load_blender_split(
    root: Path,
    split: str,
    white_bg: bool,
    downscale: float = 1.0,
    max_views: int | None = None,
) -> SceneSplit:
    """Load ``root/transforms_<split>.json`` and its images.

    downscale: image sides are divided by this (area resampling); intrinsics follow.
    max_views: keep only ``max_views`` evenly spread frames (``types.view_indices``).
    """
    json_path = root / f"transforms_{split}.json"
    if not json_path.is_file():
        raise DataError(f"{json_path}: no such file (split {split!r} is not in this scene)")
    meta = read_json(json_path)
    frames = frame_list(meta, json_path)
    if max_views is not None:
        frames = [frames[i] for i in view_indices(len(frames), max(1, max_views))]
    paths: list[Path] = []
    c2w = []
    for i, frame in enumerate(frames):
        path = resolve_image(root, frame["file_path"])
        if path is None:
            raise DataError(
                f"{json_path}: frame {i} names {frame['file_path']!r}, but no such image exists in {root}"
            )
        paths.append(path)
        c2w.append(parse_matrix(frame["transform_matrix"], f"{json_path}: frame {i}"))
    width, height = image_size(paths[0])
    fx, fy = blender_focal(meta, width, json_path)
    cx = number(meta, "cx", str(json_path), width / 2.0)
    cy = number(meta, "cy", str(json_path), height / 2.0)
    n = len(paths)
    cams = Cameras(
        c2w=np.stack(c2w),
        fx=np.full(n, fx),
        fy=np.full(n, fy),
        cx=np.full(n, cx),
        cy=np.full(n, cy),
        distortion=np.zeros((n, 4)),
        width=width,
        height=height,
    )
    size = scaled_size(width, height, downscale)
    images = load_images(paths, white_bg, size=size, expect=(width, height))
    return SceneSplit(images=images, cameras=cams.scaled(*size), names=[p.stem for p in paths])


def load_blender(
    root: Path,
    splits: Sequence[str],
    white_bg: bool,
    downscale: float = 1.0,
    max_views: int | None = None,
) -> dict[str, SceneSplit]:
    """Load the requested splits of a Blender scene (each must have its transforms file)."""
    return {s: load_blender_split(root, s, white_bg, downscale, max_views) for s in splits}
