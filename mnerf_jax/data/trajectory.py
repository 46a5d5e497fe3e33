"""Camera paths for videos: an orbit for object-centred scenes, TensoRF's spiral for forward-facing ones."""

from __future__ import annotations

import math

import numpy as np

from mnerf_jax.data.llff import average_pose
from mnerf_jax.data.types import Cameras, DataError, Scene

SPIRAL_ROTATIONS = 2
SPIRAL_FOCUS_WEIGHT = 0.75  # focus depth: harmonic blend of 0.9 x nearest and 5 x farthest depth
SPIRAL_Z_RATE = 0.5


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _all_cameras(scene: Scene) -> tuple[Cameras, np.ndarray]:
    """The first split's cameras (for intrinsics) and every loaded camera's c2w [N, 3, 4] float64."""
    if not scene.splits:
        raise DataError("scene has no splits to derive a camera path from")
    first = scene.splits.get("train") or next(iter(scene.splits.values()))
    c2w = np.concatenate([s.cameras.c2w for s in scene.splits.values()]).astype(np.float64)
    return first.cameras, c2w


def focus_point(c2w: np.ndarray) -> np.ndarray:
    """The point closest (least squares) to every camera's optical axis; [3].

    Falls back to the origin when the axes are (nearly) parallel.
    """
    forward = _unit(-c2w[:, :, 2])
    proj = np.eye(3)[None] - forward[:, :, None] * forward[:, None, :]  # [N, 3, 3]
    a = proj.sum(0)
    b = np.einsum("nij,nj->i", proj, c2w[:, :, 3])
    if np.linalg.cond(a) > 1e6:
        return np.zeros(3)
    return np.linalg.solve(a, b)


def look_at(position: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world [3, 4] at ``position`` looking at ``target`` with ``up`` roughly up."""
    back = _unit(position - target)
    right = _unit(np.cross(up, back))
    return np.stack([right, np.cross(back, right), back, position], axis=1)


def up_axis(c2w: np.ndarray) -> np.ndarray:
    """The world up direction of [N, 3, 4] cameras; [3].

    Cameras without roll keep their x axis horizontal, so up is the direction most nearly
    perpendicular to every camera's x axis (the least eigenvector of sum x x^T), signed to agree
    with the cameras' y axes. Falls back to the mean y axis when the x axes do not pin it down.
    """
    mean_up = _unit(c2w[:, :, 1].mean(0))
    right = c2w[:, :, 0]
    values, vectors = np.linalg.eigh(right.T @ right)
    if values[1] < 1e-3 * max(values[2], 1e-12):  # all x axes (nearly) parallel
        return mean_up
    axis = vectors[:, 0]
    return axis if axis @ mean_up >= 0 else -axis


def orbit_poses(c2w: np.ndarray, n_frames: int) -> np.ndarray:
    """[n_frames, 3, 4] on a circle around the cameras' focus point, at their mean distance and mean
    elevation about the up axis, starting at the first camera's azimuth."""
    centre = focus_point(c2w)
    axis = up_axis(c2w)
    offsets = c2w[:, :, 3] - centre
    radius = float(np.linalg.norm(offsets, axis=-1).mean())
    heights = offsets @ axis
    elevation = float(np.mean(np.arcsin(np.clip(heights / np.linalg.norm(offsets, axis=-1), -1, 1))))
    e1 = offsets[0] - heights[0] * axis
    if np.linalg.norm(e1) < 1e-9:  # first camera on the axis: any perpendicular will do
        e1 = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 = _unit(e1)
    e2 = np.cross(axis, e1)
    theta = 2 * math.pi * np.arange(n_frames) / n_frames
    ring = np.cos(theta)[:, None] * e1 + np.sin(theta)[:, None] * e2
    pos = centre + radius * (math.cos(elevation) * ring + math.sin(elevation) * axis)
    return np.stack([look_at(p, centre, axis) for p in pos])


def spiral_poses(c2w: np.ndarray, depth_bounds: tuple[float, float], n_frames: int) -> np.ndarray:
    """TensoRF's forward-facing spiral: [n_frames, 3, 4] around the average pose.

    Radii are the 90th percentile of |camera translation| per axis; the path turns twice while
    moving in depth at half that rate, always looking at a point at the focus depth in front of
    the average pose.
    """
    angles = np.linspace(0.0, 2 * math.pi * SPIRAL_ROTATIONS, n_frames + 1)[:-1]
    return spiral_poses_at(c2w, depth_bounds, angles)


def spiral_poses_at(c2w: np.ndarray, depth_bounds: tuple[float, float], angles: np.ndarray) -> np.ndarray:
    """The poses of :func:`spiral_poses`' path at the given path angles (radians; the path closes after
    ``2 pi SPIRAL_ROTATIONS``): [len(angles), 3, 4]. ``c2w`` [N, 3, 4] the scene's cameras, ``depth_bounds``
    their (nearest, farthest) scene depth."""
    avg = average_pose(c2w)
    up = _unit(c2w[:, :, 1].sum(0))
    near, far = depth_bounds
    close, infinity = 0.9 * near, 5.0 * far
    w = SPIRAL_FOCUS_WEIGHT
    focus = 1.0 / ((1.0 - w) / close + w / infinity)
    radii = np.percentile(np.abs(c2w[:, :, 3]), 90, axis=0)
    target = avg @ np.array([0.0, 0.0, -focus, 1.0])
    poses = []
    for theta in np.asarray(angles, np.float64).reshape(-1):
        local = np.array([math.cos(theta), -math.sin(theta), -math.sin(theta * SPIRAL_Z_RATE)]) * radii
        pos = avg @ np.append(local, 1.0)
        poses.append(look_at(pos, target, up))
    return np.stack(poses) if poses else np.zeros((0, 3, 4))


# The camera path's name among a scene's splits (``--split path``): novel views, with no ground truth.
PATH_SPLIT = "path"


def camera_path(scene: Scene, n_frames: int = 120) -> Cameras:
    """Cameras along a smooth closed path for a video, with the intrinsics of the first training
    camera (no distortion): a spiral for forward-facing scenes, else an orbit."""
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    ref, c2w = _all_cameras(scene)
    if scene.depth_bounds is not None:
        poses = spiral_poses(c2w, scene.depth_bounds, n_frames)
    else:
        poses = orbit_poses(c2w, n_frames)
    return Cameras(
        c2w=poses,
        fx=np.full(n_frames, ref.fx[0]),
        fy=np.full(n_frames, ref.fy[0]),
        cx=np.full(n_frames, ref.cx[0]),
        cy=np.full(n_frames, ref.cy[0]),
        distortion=np.zeros((n_frames, 4)),
        width=ref.width,
        height=ref.height,
        ndc=ref.ndc,
    )
