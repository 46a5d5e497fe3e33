"""nerfstudio / instant-ngp scenes: one ``transforms.json``.

Intrinsics ``fl_x, fl_y, cx, cy, w, h`` (or ``camera_angle_x``/``camera_angle_y``) and OpenCV
distortion ``k1, k2, p1, p2`` may be global or given per frame (a frame's own values win). Frame
matrices are OpenGL camera-to-world.

Images are loaded upright: a JPEG's EXIF Orientation tag is applied. A frame's camera describes its
image as stored (the pixels COLMAP and nerfstudio read) unless its ``w``, ``h`` match only the upright
size; a camera of the stored pixels is re-expressed for the upright image, every pixel keeping its ray
(``capture.upright_camera``). Without ``w``/``h`` a frame's size is its file's as stored.

Sizes: the scene's images have the first frame's upright size (frames sorted by file path) divided by
``downscale``. A frame of another size is resampled to it, its intrinsics scaled with it, when the frame
states its own ``w`` and ``h``; otherwise it is refused with one line naming its file.

Poses: with ``orientation`` "up" or "pca" they are normalised (``capture.normalising_transform``:
rotated, centred by ``centring``, scaled so that every camera lies in [-1, 1]^3), by a transform
computed over every frame that has an image (so every split and ``max_views`` get the same) and returned
with the splits. "auto" keeps the file's frame for files that define one of their own (instant-ngp's
``aabb_scale``, or intrinsics given only as ``camera_angle_x``, NeRF-Synthetic's way), and is "up" for
the rest: captures processed by nerfstudio, COLMAP or Polycam. "none" keeps the file's frame.

Splits: ``train_filenames``/``val_filenames``/``test_filenames`` lists, else a per-frame ``split``
entry, else every ``hold``-th frame (frames sorted by file path, missing ones dropped first) is a
test frame. Frames whose image file is missing are skipped with one warning.

Scene box (the file's frame only): instant-ngp maps a point p of the file to ``p * scale + offset``
(defaults 0.33 and 0.5) and renders inside the cube of side ``aabb_scale`` centred on 0.5. The same box
in the file's coordinates is ``[(0.5 - aabb_scale / 2 - offset) / scale, (0.5 + aabb_scale / 2 - offset)
/ scale]`` per axis, i.e. ``+-1.5 * aabb_scale`` with the defaults. Files without ``aabb_scale``, and
normalised captures, use the configured box.
"""

from __future__ import annotations

import dataclasses
import math
import os
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mnerf_jax.data import capture
from mnerf_jax.data.blender import number, parse_matrix
from mnerf_jax.data.images import image_header, load_images, read_json, resolve_image, scaled_size
from mnerf_jax.data.types import Cameras, DataError, DataWarning, SceneSplit, SceneTransform, view_indices

# Normalised captures (cameras in [-1, 1]^3) when no render config is given: the capture preset's box,
# which leaves room beyond the cameras for the background, and its near/far.
CAPTURE_AABB = ((-1.5, -1.5, -1.5), (1.5, 1.5, 1.5))
CAPTURE_NEAR_FAR = (0.05, 6.0)
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
    """(fx, fy, cx, cy, (k1, k2, p1, p2), (w, h)) of one frame, in pixels of the size (w, h) its
    intrinsics state (``image_wh`` where they state none)."""
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
    """Split name -> indices into ``frames`` (already sorted and filtered).

    Where the file names a held-out split as only one of "val" and "test", the other name gives the same
    frames (a fit evaluates on "test"); every ``hold``-th frame answers to both.
    """
    lists = {s: meta.get(f"{s}_filenames") for s in ("train", "val", "test")}
    out: dict[str, list[int]] = {}
    if any(v is not None for v in lists.values()):
        keys = [_key(f["file_path"]) for f in frames]
        for split, names in lists.items():
            if names is None:
                continue
            if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
                raise DataError(f"{json_path}: {split}_filenames must be a list of file names")
            wanted = {_key(n) for n in names}
            out[split] = [i for i, k in enumerate(keys) if k in wanted]
    elif any("split" in f for f in frames):
        for i, f in enumerate(frames):
            out.setdefault(str(f.get("split", "train")), []).append(i)
    else:
        if hold < 1:
            raise DataError(f"llff_hold must be >= 1, got {hold}")
        out["test"] = list(range(0, len(frames), hold))
        out["train"] = [i for i in range(len(frames)) if i % hold != 0]
    for name, other in (("test", "val"), ("val", "test")):
        if name not in out and other in out:
            out[name] = out[other]
    return out


def resolve_orientation(meta: dict, orientation: str) -> str:
    """``orientation`` with "auto" decided for this file: "none" when it has ``aabb_scale`` or no
    ``fl_x`` anywhere (intrinsics as ``camera_angle_x``), else "up"."""
    if orientation not in capture.ORIENTATIONS:
        raise DataError(
            f"data.orientation {orientation!r}: expected one of {', '.join(capture.ORIENTATIONS)}"
        )
    if orientation != "auto":
        return orientation
    frames = meta.get("frames", [])
    focal = "fl_x" in meta or any(isinstance(f, dict) and "fl_x" in f for f in frames)
    return "none" if "aabb_scale" in meta or not focal else "up"


@dataclasses.dataclass(frozen=True)
class CaptureFrame:
    """A frame that has an image, its camera re-expressed for the upright image.

    c2w: [3, 4] float64; intrinsics: (fx, fy, cx, cy) in pixels of ``size``; distortion: (k1, k2, p1, p2);
    size: (width, height) of the upright image; own_size: the frame states its own ``w`` and ``h``.
    """

    file_path: str
    path: Path
    c2w: np.ndarray
    intrinsics: tuple[float, float, float, float]
    distortion: tuple[float, float, float, float]
    size: tuple[int, int]
    own_size: bool


def read_frame(meta: dict, frame: dict, path: Path, where: str) -> CaptureFrame:
    """One frame's camera for its upright image (see the module docstring for whose size ``w``, ``h`` are)."""
    stored, tag = image_header(path)
    upright = capture.upright_size(tag, *stored)
    merged = {
        **{k: meta[k] for k in ("w", "h") if k in meta},
        **{k: frame[k] for k in ("w", "h") if k in frame},
    }
    w, h = number(merged, "w", where), number(merged, "h", where)
    stated = (stored[0] if w is None else int(w), stored[1] if h is None else int(h))
    if stated == stored:
        described = "stored"
    elif stated == upright:
        described = "upright"
    else:
        turned = f" ({upright[0]}x{upright[1]} upright)" if upright != stored else ""
        raise DataError(
            f"{path}: intrinsics say {stated[0]}x{stated[1]} but the image is {stored[0]}x{stored[1]}{turned}"
        )
    fx, fy, cx, cy, dist, _ = frame_intrinsics(meta, frame, where, stated)
    c2w = parse_matrix(frame["transform_matrix"], where)
    intrinsics = (fx, fy, cx, cy)
    if described == "stored" and tag != 1:
        intrinsics, dist, c2w = capture.upright_camera(tag, *stored, intrinsics, dist, c2w)
    own = "w" in frame and "h" in frame
    return CaptureFrame(frame["file_path"], path, c2w, intrinsics, tuple(dist), upright, own)


def load_nerfstudio(
    root: Path,
    splits: Sequence[str],
    white_bg: bool,
    hold: int,
    downscale: float = 1.0,
    max_views: int | None = None,
    orientation: str = "none",
    centring: str = "focus",
) -> tuple[dict[str, SceneSplit], np.ndarray | None, SceneTransform | None]:
    """Load the requested splits of ``root/transforms.json``.

    orientation: "auto" | "up" | "pca" | "none"; centring: "focus" | "poses" | "none" (normalised
    captures only). Returns the splits, the file's instant-ngp box (None when it defines none or the
    poses were normalised) and the normalisation applied (None in the file's frame).
    """
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
    orientation = resolve_orientation(meta, orientation)
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
    cams = [
        read_frame(meta, f, path, f"{json_path}: frame {f['file_path']!r}")
        for f, path in zip(present, paths, strict=True)
    ]
    first = cams[0]
    for cam in cams[1:]:
        if cam.size != first.size and not cam.own_size:
            raise DataError(
                f"{cam.path}: image is {cam.size[0]}x{cam.size[1]} but {first.path.name} is "
                f"{first.size[0]}x{first.size[1]}; a frame of another size needs its own w and h "
                f"in {json_path.name}"
            )
    transform = None
    if orientation != "none":
        transform = capture.normalising_transform(np.stack([c.c2w for c in cams]), orientation, centring)
        cams = [dataclasses.replace(c, c2w=transform.apply(c.c2w)) for c in cams]
    assignment = assign_splits(meta, present, hold, json_path)
    size = scaled_size(*first.size, downscale)
    out: dict[str, SceneSplit] = {}
    for split in splits:
        idx = assignment.get(split)
        if idx is None:
            raise DataError(f"{json_path}: no {split!r} split (has: {', '.join(sorted(assignment))})")
        if not idx:
            raise DataError(f"{json_path}: the {split} split is empty")
        if max_views is not None:
            idx = [idx[i] for i in view_indices(len(idx), max(1, max_views))]
        out[split] = _load_split([cams[i] for i in idx], white_bg, size)
    box = ngp_aabb(meta, str(json_path)) if transform is None else None
    return out, box, transform


def _load_split(frames: list[CaptureFrame], white_bg: bool, size: tuple[int, int]) -> SceneSplit:
    """The frames' upright images resampled to ``size`` (width, height), their intrinsics scaled with them."""
    sx = np.array([size[0] / f.size[0] for f in frames])
    sy = np.array([size[1] / f.size[1] for f in frames])
    intr = np.array([f.intrinsics for f in frames], np.float64)
    cams = Cameras(
        c2w=np.stack([f.c2w for f in frames]),
        fx=intr[:, 0] * sx,
        fy=intr[:, 1] * sy,
        cx=intr[:, 2] * sx,
        cy=intr[:, 3] * sy,
        distortion=np.array([f.distortion for f in frames]),
        width=size[0],
        height=size[1],
    )
    paths = [f.path for f in frames]
    images = load_images(paths, white_bg, size=size, expect=[f.size for f in frames], upright=True)
    return SceneSplit(images=images, cameras=cams, names=[p.stem for p in paths])
