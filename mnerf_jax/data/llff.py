"""LLFF forward-facing scenes: ``poses_bounds.npy`` + ``images_<factor>/``.

``poses_bounds.npy`` is [N, 17]: a [3, 5] matrix per view (a 3x4 camera-to-world with the axes
[down, right, back], then a column (H, W, focal) at full resolution) followed by the near and far
scene depth. Processing follows TensoRF: axes to [right, up, back], recentre on the average pose,
then scale translations and depths by 1 / (0.75 * nearest depth) so the nearest depth is 4/3.

The average pose here is a proper rotation (x = y' x z); TensoRF's has a reflected x axis, which
mirrors the whole world in x. Rays, images and NDC coordinates agree up to that mirror, and the
scene box is symmetric in x, so fits are equivalent.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mnerf_jax.data.images import image_size, list_images, load_images, scaled_size
from mnerf_jax.data.types import Cameras, DataError, NDCSpace, SceneSplit, view_indices

NEAR_SCALE = 0.75  # nearest depth ends at 1 / 0.75 after rescaling
NDC_AABB = ((-1.5, -1.67, -1.0), (1.5, 1.67, 1.0))  # TensoRF's LLFF box in NDC
NDC_NEAR_FAR = (0.0, 1.0)


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def average_pose(c2w: np.ndarray) -> np.ndarray:
    """[N, 3, 4] -> [3, 4]: mean centre, mean back (z) axis, x = mean up x z, y = z x x."""
    centre = c2w[:, :, 3].mean(0)
    z = _normalize(c2w[:, :, 2].mean(0))
    y_mean = c2w[:, :, 1].mean(0)
    x = _normalize(np.cross(y_mean, z))
    y = np.cross(z, x)
    return np.stack([x, y, z, centre], axis=1)


def recentre(c2w: np.ndarray) -> np.ndarray:
    """Express [N, 3, 4] poses in the frame of their average pose."""
    avg = np.eye(4)
    avg[:3] = average_pose(c2w)
    homo = np.tile(np.eye(4), (c2w.shape[0], 1, 1))
    homo[:, :3] = c2w
    return (np.linalg.inv(avg) @ homo)[:, :3]


def read_poses_bounds(path: Path) -> np.ndarray:
    """Load and check ``poses_bounds.npy`` -> float64 [N, 17]."""
    if not path.is_file():
        raise DataError(f"{path}: no such file")
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError):
        raise DataError(f"{path}: unreadable (not a numeric .npy array)") from None
    if arr.ndim != 2 or arr.shape[1] != 17 or arr.shape[0] == 0:
        raise DataError(f"{path}: expected an array of shape [N, 17] (poses and bounds), got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number) or not np.all(np.isfinite(arr)):
        raise DataError(f"{path}: poses and bounds must be finite numbers")
    arr = arr.astype(np.float64)
    if np.any(arr[:, 15:] <= 0):
        raise DataError(f"{path}: near/far depths must be positive")
    return arr


def process_poses(poses_bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[float, float, float]]:
    """TensoRF's LLFF pose processing.

    poses_bounds: [N, 17]. Returns c2w [N, 3, 4] (OpenGL axes, recentred, rescaled), bounds [N, 2]
    (rescaled near/far depths) and the full-resolution (H, W, focal) of the first view.
    """
    poses = poses_bounds[:, :15].reshape(-1, 3, 5)
    bounds = poses_bounds[:, 15:17].copy()
    h, w, focal = (float(v) for v in poses[0, :, 4])
    # [down, right, back] -> [right, up, back]
    c2w = np.concatenate([poses[:, :, 1:2], -poses[:, :, 0:1], poses[:, :, 2:4]], axis=-1)
    c2w = recentre(c2w)
    scale = bounds.min() * NEAR_SCALE
    bounds /= scale
    c2w[:, :, 3] /= scale
    return c2w, bounds, (h, w, focal)


def holdout_indices(n: int, hold: int) -> tuple[np.ndarray, np.ndarray]:
    """(train, test) indices: every ``hold``-th view (0, hold, 2 hold, ...) is a test view."""
    if hold < 1:
        raise DataError(f"llff_hold must be >= 1, got {hold}")
    test = np.arange(0, n, hold)
    train = np.setdiff1d(np.arange(n), test)
    return train, test


def image_dir(root: Path, factor: int) -> Path:
    """``images_<factor>`` (``images`` for factor 1); a DataError lists the folders there are."""
    name = "images" if factor == 1 else f"images_{factor}"
    path = root / name
    if not path.is_dir():
        found = sorted(p.name for p in root.glob("images*") if p.is_dir())
        raise DataError(
            f"{path}: no such image folder for llff_factor={factor} (found: {', '.join(found) or 'none'})"
        )
    return path


def load_llff(
    root: Path,
    splits: Sequence[str],
    factor: int,
    hold: int,
    white_bg: bool,
    ndc: bool,
    downscale: float = 1.0,
    max_views: int | None = None,
) -> tuple[dict[str, SceneSplit], NDCSpace | None, tuple[float, float]]:
    """Load the requested splits ("train", "test") of an LLFF scene.

    Returns the splits, the NDC space (when ``ndc``) and the rescaled (nearest, farthest) depth.
    """
    unknown = [s for s in splits if s not in ("train", "test")]
    if unknown:
        raise DataError(f"{root}: llff scenes have 'train' and 'test' splits, not {unknown[0]!r}")
    pb_path = root / "poses_bounds.npy"
    poses_bounds = read_poses_bounds(pb_path)
    folder = image_dir(root, factor)
    paths = list_images(folder)
    n = poses_bounds.shape[0]
    if len(paths) != n:
        raise DataError(f"{folder}: {len(paths)} images but {pb_path.name} has {n} poses")
    c2w, bounds, (h_full, w_full, focal_full) = process_poses(poses_bounds)
    width, height = image_size(paths[0])
    size = scaled_size(width, height, downscale)
    # Intrinsics in poses_bounds are for the full-resolution images.
    fx = focal_full * size[0] / w_full
    fy = focal_full * size[1] / h_full
    ndc_space = NDCSpace(focal=fx, width=size[0], height=size[1], near=1.0) if ndc else None
    train, test = holdout_indices(n, hold)
    out: dict[str, SceneSplit] = {}
    for name in splits:
        idx = train if name == "train" else test
        if idx.size == 0:
            raise DataError(f"{root}: the {name} split is empty ({n} views, llff_hold={hold})")
        if max_views is not None:
            idx = idx[view_indices(idx.size, max(1, max_views))]
        k = idx.size
        cams = Cameras(
            c2w=c2w[idx],
            fx=np.full(k, fx),
            fy=np.full(k, fy),
            cx=np.full(k, size[0] / 2.0),
            cy=np.full(k, size[1] / 2.0),
            distortion=np.zeros((k, 4)),
            width=size[0],
            height=size[1],
            ndc=ndc_space,
        )
        split_paths = [paths[i] for i in idx]
        images = load_images(split_paths, white_bg, size=size, expect=(width, height))
        out[name] = SceneSplit(images=images, cameras=cams, names=[p.stem for p in split_paths])
    return out, ndc_space, (float(bounds.min()), float(bounds.max()))
