"""Where phase 3's novel views lie: seeded cameras around the training cameras (on their sphere for an
object-centred scene, on the spiral render path for a forward-facing one), with the first camera's
intrinsics."""

from __future__ import annotations

import math
from typing import get_args

import numpy as np

from mnerf_jax.core.watermark_config import ViewDensity
from mnerf_jax.data import trajectory
from mnerf_jax.data.types import Cameras

VIEW_DENSITIES = get_args(ViewDensity)  # novel_cameras' spreads of the elevation


def novel_cameras(
    cameras: Cameras,
    count: int,
    seed: int,
    density: str = "angles",
    margin_deg: float = 0.0,
    depth_bounds: tuple[float, float] | None = None,
) -> Cameras:
    """``count`` novel cameras with the first camera's intrinsics, seeded by ``seed``.

    Object-centred ``cameras``: around them, looking at their focus point (``trajectory.focus_point``):
    azimuth uniform, distance uniform within the given cameras' range, elevation within theirs widened by
    ``margin_deg`` degrees on either side (clipped to ±90°). ``density`` "angles": elevation uniform;
    "sphere": uniform over the sphere's area, i.e. sin(elevation) uniform (how NeRF-Synthetic's cameras are
    drawn, more views near the horizon).
    Forward-facing (NDC) ``cameras``: poses on the render path's spiral around them
    (``trajectory.spiral_poses_at``, its radii and focus from ``cameras`` and ``depth_bounds``, the scene's
    (nearest, farthest) depth), at path angles uniform over the whole path; they keep the cameras' NDC space,
    so their rays are mapped to NDC as the training rays are. ``density`` and ``margin_deg`` do not apply.
    Raises ValueError for NDC cameras without ``depth_bounds``.
    """
    if density not in VIEW_DENSITIES:
        raise ValueError(f"unknown view density {density!r} (known: {VIEW_DENSITIES})")
    if cameras.ndc is not None:
        return _spiral_cameras(cameras, count, seed, depth_bounds)
    c2w = cameras.c2w.astype(np.float64)
    centre, axis = trajectory.focus_point(c2w), trajectory.up_axis(c2w)
    offsets = c2w[:, :, 3] - centre
    radius = np.linalg.norm(offsets, axis=-1)
    elevation = np.arcsin(np.clip(offsets @ axis / radius, -1.0, 1.0))
    e1 = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x3F]))
    theta = rng.uniform(0.0, 2.0 * math.pi, count)
    margin = math.radians(margin_deg)
    low, high = max(elevation.min() - margin, -math.pi / 2), min(elevation.max() + margin, math.pi / 2)
    if density == "sphere":
        elev = np.arcsin(rng.uniform(math.sin(low), math.sin(high), count))
    else:
        elev = rng.uniform(low, high, count)
    dist = rng.uniform(radius.min(), radius.max(), count)
    ring = np.cos(theta)[:, None] * e1 + np.sin(theta)[:, None] * e2
    pos = centre + dist[:, None] * (np.cos(elev)[:, None] * ring + np.sin(elev)[:, None] * axis)
    poses = np.stack([trajectory.look_at(p, centre, axis) for p in pos]) if count else np.zeros((0, 3, 4))
    return _posed_like_the_first(cameras, poses)


def _posed_like_the_first(cameras: Cameras, c2w: np.ndarray) -> Cameras:
    """Cameras at poses ``c2w [N, 3, 4]`` with the first of ``cameras``' intrinsics (and NDC setting)."""
    first = np.zeros(len(c2w), np.int64)
    return Cameras(
        c2w=c2w,
        fx=cameras.fx[first],
        fy=cameras.fy[first],
        cx=cameras.cx[first],
        cy=cameras.cy[first],
        distortion=cameras.distortion[first],
        width=cameras.width,
        height=cameras.height,
        ndc=cameras.ndc,
    )


def _spiral_cameras(
    cameras: Cameras, count: int, seed: int, depth_bounds: tuple[float, float] | None
) -> Cameras:
    """``novel_cameras`` for forward-facing cameras: seeded poses on the spiral render path around them."""
    if depth_bounds is None:
        raise ValueError("novel views of a forward-facing scene need its depth bounds (the spiral's focus)")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5B]))
    angles = rng.uniform(0.0, 2.0 * math.pi * trajectory.SPIRAL_ROTATIONS, count)
    return _posed_like_the_first(
        cameras, trajectory.spiral_poses_at(cameras.c2w.astype(np.float64), depth_bounds, angles)
    )
