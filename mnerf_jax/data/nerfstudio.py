"""nerfstudio / instant-ngp scenes: one ``transforms.json``.

Intrinsics ``fl_x, fl_y, cx, cy, w, h`` (or ``camera_angle_x``/``camera_angle_y``) and OpenCV
distortion ``k1, k2, p1, p2`` may be global or given per frame (a frame's own values win). Frame
matrices are OpenGL camera-to-world, used as they are (no re-orientation or re-scaling).

Splits: ``train_filenames``/``val_filenames``/``test_filenames`` lists, else a per-frame ``split``
entry, else every ``hold``-th frame (frames sorted by file path, missing ones dropped first) is a
test frame. Frames whose image file is missing are skipped with one warning.

Scene box: instant-ngp maps a point p of the file to ``p * scale + offset`` (defaults 0.33 and 0.5)
and renders inside the cube of side ``aabb_scale`` centred on 0.5. The same box in the file's
coordinates is ``[(0.5 - aabb_scale / 2 - offset) / scale, (0.5 + aabb_scale / 2 - offset) / scale]``
per axis, i.e. ``+-1.5 * aabb_scale`` with the defaults. Files without ``aabb_scale`` use the
configured box.
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mnerf_jax.data.blender import number, parse_matrix
from mnerf_jax.data.images import image_size, load_images, read_json, resolve_image, scaled_size
from mnerf_jax.data.types import Cameras, DataError, DataWarning, SceneSplit

NGP_SCALE = 0.33
NGP_OFFSET = (0.5, 0.5, 0.5)
SUPPORTED_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")
INTRINSIC_KEYS = (
    "fl_x",
    "fl_y",
    "cx",
    "cy",
    "w",
    "h",
    "k1",
    "k2",
    "p1",
    "p2",
    "k3",
    "k4",
    "camera_angle_x",
    "camera_angle_y",
    "camera_model",
)


def _key(file_path: str) -> str:
    """Frame identity for matching split lists: the normalised relative path without suffix."""
    norm = os.path.normpath(file_path.replace("\\", "/"))
    return os.path.splitext(norm)[0]


def frame_intrinsics(meta: dict, frame: dict, where: str, image_wh: tuple[int, int]) -> tuple:
    """(fx, fy, cx, cy, (k1, k2, p1, p2), (w, h)) of one frame at its file's resolution."""
    merged = {k: meta[k] for k in INTRINSIC_KEYS if k in meta}
    merged.update({k: frame[k] for k in INTRINSIC_KEYS if k in frame})
    model = merged.get("camera_model")
    if model is not None and model not in SUPPORTED_MODELS:
        known = ", ".join(SUPPORTED_MODELS)
        raise DataError(f"{where}: camera_model {model!r} is not supported (use one of {known})")
    for extra in ("k3", "k4"):
        if number(merged, extra, where, 0.0) != 0.0:
            raise DataError(f"{where}: distortion coefficient {extra} is not supported (only k1, k2, p1, p2)")
    w = number(merged, "w", where)
    h = number(merged, "h", where)
    w = image_wh[0] if w is None else int(w)
    h = image_wh[1] if h is None else int(h)
    fx = number(merged, "fl_x", where)
    if fx is None:
        angle_x = number(merged, "camera_angle_x", where)
        if angle_x is None:
            raise DataError(f"{where}: missing intrinsics (fl_x or camera_angle_x)")
        fx = 0.5 * w / math.tan(0.5 * angle_x)
    fy = number(merged, "fl_y", where)
    if fy is None:
        angle_y = number(merged, "camera_angle_y", where)
        fy = fx if angle_y is None else 0.5 * h / math.tan(0.5 * angle_y)
    if fx <= 0 or fy <= 0:
        raise DataError(f"{where}: focal lengths must be positive, got fl_x={fx}, fl_y={fy}")
    cx = number(merged, "cx", where, w / 2.0)
    cy = number(merged, "cy", where, h / 2.0)
    dist = tuple(number(merged, k, where, 0.0) for k in ("k1", "k2", "p1", "p2"))
    return fx, fy, cx, cy, dist, (w, h)


def ngp_aabb(meta: dict, where: str) -> np.ndarray | None:
    """The instant-ngp render box in the file's coordinates ([2, 3]), None without ``aabb_scale``."""
    aabb_scale = number(meta, "aabb_scale", where)
    if aabb_scale is None:
        return None
    scale = number(meta, "scale", where, NGP_SCALE)
    offset = np.asarray(meta.get("offset", NGP_OFFSET), np.float64).reshape(-1)
    if offset.shape != (3,) or aabb_scale <= 0 or not scale:
        raise DataError(f"{where}: aabb_scale, scale and offset must be positive numbers and a 3-vector")
    lo = (0.5 - aabb_scale / 2.0 - offset) / scale
    hi = (0.5 + aabb_scale / 2.0 - offset) / scale
    return np.stack([np.minimum(lo, hi), np.maximum(lo, hi)])


def assign_splits(meta: dict, frames: list[dict], hold: int, json_path: Path) -> dict[str, list[int]]:
    """Split name -> indices into ``frames`` (already sorted and filtered)."""
    lists = {s: meta.get(f"{s}_filenames") for s in ("train", "val", "test")}
    if any(v is not None for v in lists.values()):
        keys = [_key(f["file_path"]) for f in frames]
        out: dict[str, list[int]] = {}
        for split, names in lists.items():
            if names is None:
                continue
            if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
                raise DataError(f"{json_path}: {split}_filenames must be a list of file names")
            wanted = {_key(n) for n in names}
            out[split] = [i for i, k in enumerate(keys) if k in wanted]
        return out
    if any("split" in f for f in frames):
        out = {}
        for i, f in enumerate(frames):
            out.setdefault(str(f.get("split", "train")), []).append(i)
        return out
    if hold < 1:
        raise DataError(f"llff_hold must be >= 1, got {hold}")
    test = list(range(0, len(frames), hold))
    train = [i for i in range(len(frames)) if i % hold != 0]
    return {"train": train, "test": test}


def load_nerfstudio(
    root: Path,
    splits: Sequence[str],
    white_bg: bool,
    hold: int,
    downscale: float = 1.0,
    max_views: int | None = None,
) -> tuple[dict[str, SceneSplit], np.ndarray | None]:
    """Load the requested splits of ``root/transforms.json``; returns the splits and the file's
    instant-ngp box (None when it defines none)."""
    json_path = root / "transforms.json"
    meta = read_json(json_path)
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        raise DataError(f"{json_path}: missing 'frames' list")
    frames = meta["frames"]
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
            raise DataError(f"{json_path}: frame {i} has no 'file_path'")
        if "transform_matrix" not in frame:
            raise DataError(f"{json_path}: frame {i} has no 'transform_matrix'")
    frames = sorted(frames, key=lambda f: f["file_path"])
    present, paths, missing = [], [], []
    for frame in frames:
        path = resolve_image(root, frame["file_path"])
        if path is None:
            missing.append(frame["file_path"])
        else:
            present.append(frame)
            paths.append(path)
    if missing:
        warnings.warn(
            f"{json_path}: skipped {len(missing)} frame(s) whose image is missing (first: {missing[0]})",
            DataWarning,
            stacklevel=3,
        )
    if not present:
        raise DataError(
            f"{json_path}: none of the {len(frames)} frames has an image file (first: {missing[0]})"
        )
    assignment = assign_splits(meta, present, hold, json_path)
    out: dict[str, SceneSplit] = {}
    for split in splits:
        idx = assignment.get(split)
        if idx is None:
            raise DataError(f"{json_path}: no {split!r} split (has: {', '.join(sorted(assignment))})")
        if not idx:
            raise DataError(f"{json_path}: the {split} split is empty")
        if max_views is not None:
            idx = idx[: max(1, max_views)]
        out[split] = _load_split(
            json_path, meta, [present[i] for i in idx], [paths[i] for i in idx], white_bg, downscale
        )
    return out, ngp_aabb(meta, str(json_path))


def _load_split(
    json_path: Path, meta: dict, frames: list[dict], paths: list[Path], white_bg: bool, downscale: float
) -> SceneSplit:
    first_wh = image_size(paths[0])
    rows = []
    for frame, path in zip(frames, paths, strict=True):
        where = f"{json_path}: frame {frame['file_path']!r}"
        fx, fy, cx, cy, dist, wh = frame_intrinsics(meta, frame, where, first_wh)
        if wh != first_wh:
            raise DataError(
                f"{path}: intrinsics say {wh[0]}x{wh[1]} but {paths[0].name} is {first_wh[0]}x{first_wh[1]}; "
                "all images of a split must share one size"
            )
        rows.append((parse_matrix(frame["transform_matrix"], where), fx, fy, cx, cy, dist))
    width, height = first_wh
    cams = Cameras(
        c2w=np.stack([r[0] for r in rows]),
        fx=np.array([r[1] for r in rows]),
        fy=np.array([r[2] for r in rows]),
        cx=np.array([r[3] for r in rows]),
        cy=np.array([r[4] for r in rows]),
        distortion=np.array([r[5] for r in rows]),
        width=width,
        height=height,
    )
    size = scaled_size(width, height, downscale)
    images = load_images(paths, white_bg, size=size, expect=first_wh)
    return SceneSplit(images=images, cameras=cams.scaled(*size), names=[p.stem for p in paths])
