"""A built-in procedural scene, ray-traced analytically with numpy and written in Blender layout.

Five textured solids on a transparent background: a disc-shaped base with a polar checker, a
sphere with a soft checker, a box with stripes, a cylinder with smooth noise and a small sphere with
colour bands; Lambert shading under two directional lights plus ambient light. Textures are soft
(tanh-smoothed) and every pixel is supersampled 2x2, so a short fit at 64 px reaches a good PSNR.
Cameras sit on a sphere of radius 4 around the origin and look at it, as in NeRF-Synthetic: training
views at random azimuths and elevations in the upper hemisphere, test views on a ring at 30 degrees.
Everything is a deterministic function of the seed.
"""

from __future__ import annotations

import colorsys
import dataclasses
import json
import math
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

from mnerf_jax.data.rays import world_rays
from mnerf_jax.data.trajectory import look_at
from mnerf_jax.data.types import Cameras, DataError

GENERATOR_VERSION = 1  # part of the cache key: bump when the images change
CAMERA_RADIUS = 4.0
CAMERA_ANGLE_X = 0.6911112070083618  # NeRF-Synthetic's field of view
TRAIN_ELEVATION_DEG = (8.0, 72.0)
TEST_ELEVATION_DEG = 30.0
SUPERSAMPLE = ((0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75))
KEY_LIGHT = np.array([0.45, -0.55, 0.75])
FILL_LIGHT = np.array([-0.6, 0.45, 0.3])
AMBIENT, KEY, FILL = 0.32, 0.6, 0.25


@dataclasses.dataclass(frozen=True)
class Hit:
    """Nearest hits of R rays: t [R] (inf on a miss), unit normals [R, 3], object-local points [R, 3]."""

    t: np.ndarray
    normal: np.ndarray
    local: np.ndarray


def _miss(r: int) -> Hit:
    return Hit(np.full(r, np.inf), np.zeros((r, 3)), np.zeros((r, 3)))


def _closer(a: Hit, b: Hit) -> Hit:
    take = b.t < a.t
    return Hit(
        np.where(take, b.t, a.t),
        np.where(take[:, None], b.normal, a.normal),
        np.where(take[:, None], b.local, a.local),
    )


def hit_sphere(o: np.ndarray, d: np.ndarray, centre: np.ndarray, radius: float) -> Hit:
    """Ray/sphere for unit directions d [R, 3]; local point = unit vector from the centre."""
    oc = o - centre
    b = np.einsum("ij,ij->i", oc, d)
    c = np.einsum("ij,ij->i", oc, oc) - radius * radius
    disc = b * b - c
    sq = np.sqrt(np.maximum(disc, 0.0))
    t0, t1 = -b - sq, -b + sq
    t = np.where(t0 > 1e-6, t0, t1)
    t = np.where((disc > 0) & (t > 1e-6), t, np.inf)
    p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
    n = (p - centre) / radius
    return Hit(t, n, n)


def _rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def hit_box(o: np.ndarray, d: np.ndarray, centre: np.ndarray, half: np.ndarray, yaw: float) -> Hit:
    """Ray/box for a box rotated by ``yaw`` about z; local point in the box frame."""
    rot = _rot_z(yaw)
    ol = (o - centre) @ rot  # world -> local is rot^T, applied to row vectors
    dl = d @ rot
    dl = np.where(np.abs(dl) < 1e-12, 1e-12, dl)
    t_a = (half - ol) / dl
    t_b = (-half - ol) / dl
    t_near = np.minimum(t_a, t_b).max(axis=-1)
    t_far = np.maximum(t_a, t_b).min(axis=-1)
    t = np.where(t_near > 1e-6, t_near, t_far)
    t = np.where((t_far >= t_near) & (t > 1e-6), t, np.inf)
    pl = ol + np.where(np.isfinite(t), t, 0.0)[:, None] * dl
    axis = np.argmax(np.abs(pl) / half, axis=-1)
    nl = np.zeros_like(pl)
    nl[np.arange(len(pl)), axis] = np.sign(pl[np.arange(len(pl)), axis])
    return Hit(t, nl @ rot.T, pl)


def hit_cylinder(
    o: np.ndarray, d: np.ndarray, centre_xy: np.ndarray, radius: float, z0: float, z1: float
) -> Hit:
    """Ray/capped cylinder with its axis along z; local point relative to (cx, cy, z0)."""
    base = np.array([centre_xy[0], centre_xy[1], z0])
    oc = o - base
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = oc[:, 0] * d[:, 0] + oc[:, 1] * d[:, 1]
    c = oc[:, 0] ** 2 + oc[:, 1] ** 2 - radius * radius
    a_safe = np.where(a < 1e-12, 1e-12, a)
    disc = b * b - a * c
    sq = np.sqrt(np.maximum(disc, 0.0))
    height = z1 - z0
    best = _miss(len(o))
    for root in ((-b - sq) / a_safe, (-b + sq) / a_safe):
        z = oc[:, 2] + root * d[:, 2]
        ok = (disc > 0) & (a > 1e-12) & (root > 1e-6) & (z >= 0) & (z <= height)
        t = np.where(ok, root, np.inf)
        p = oc + np.where(ok, root, 0.0)[:, None] * d
        n = np.stack([p[:, 0], p[:, 1], np.zeros(len(p))], -1) / radius
        best = _closer(best, Hit(t, n, p))
    dz = np.where(np.abs(d[:, 2]) < 1e-12, 1e-12, d[:, 2])
    for cap_z, sign in ((0.0, -1.0), (height, 1.0)):
        t = (cap_z - oc[:, 2]) / dz
        p = oc + t[:, None] * d
        ok = (t > 1e-6) & (p[:, 0] ** 2 + p[:, 1] ** 2 <= radius * radius)
        n = np.tile([0.0, 0.0, sign], (len(o), 1))
        best = _closer(best, Hit(np.where(ok, t, np.inf), n, p))
    return best


def _soft(x: np.ndarray, sharpness: float = 3.0) -> np.ndarray:
    """Map a signed pattern to [0, 1] with a smooth transition (no aliasing at 64 px)."""
    return 0.5 + 0.5 * np.tanh(sharpness * x)


def _mix(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> np.ndarray:
    return a[None] * (1.0 - w[:, None]) + b[None] * w[:, None]


def _palette(rng: np.random.Generator, n: int) -> list[np.ndarray]:
    """n saturated colours with well-separated hues."""
    start = rng.uniform()
    hues = (start + np.arange(n) / n + rng.uniform(-0.04, 0.04, n)) % 1.0
    rng.shuffle(hues)
    return [np.array(colorsys.hsv_to_rgb(h, rng.uniform(0.55, 0.85), rng.uniform(0.75, 0.95))) for h in hues]


def build_scene(seed: int) -> list[dict]:
    """The objects of scene ``seed``: a list of shape parameters and texture parameters."""
    rng = np.random.default_rng(seed)
    col = _palette(rng, 6)
    cream = np.array([0.93, 0.9, 0.82])
    light = np.array([0.97, 0.95, 0.7])
    jitter = lambda s: rng.uniform(-s, s, 3)  # noqa: E731
    noise_freq = rng.normal(size=(6, 3))
    noise_freq *= rng.uniform(3.0, 6.5, (6, 1)) / np.linalg.norm(noise_freq, axis=1, keepdims=True)
    return [
        {
            "shape": "cylinder",
            "centre": np.zeros(2),
            "radius": 1.0,
            "z": (-0.92, -0.84),
            "texture": "polar",
            "colours": (cream, col[0]),
            "sectors": int(rng.integers(5, 9)),
        },
        {
            "shape": "sphere",
            "centre": np.array([-0.42, -0.32, -0.25]) + jitter(0.08),
            "radius": 0.5,
            "texture": "checker",
            "colours": (col[1], cream),
            "cells": (int(rng.integers(3, 6)), 3),
        },
        {
            "shape": "box",
            "centre": np.array([0.45, 0.42, -0.52]) + jitter(0.06) * [1, 1, 0],
            "half": np.array([0.3, 0.3, 0.3]),
            "yaw": float(rng.uniform(0, math.pi / 2)),
            "texture": "stripes",
            "colours": (col[2], col[3]),
            "axis": rng.normal(size=3),
            "frequency": float(rng.uniform(2.6, 3.4)),
        },
        {
            "shape": "cylinder",
            "centre": np.array([0.42, -0.5]) + rng.uniform(-0.06, 0.06, 2),
            "radius": 0.27,
            "z": (-0.84, float(rng.uniform(0.1, 0.4))),
            "texture": "noise",
            "colours": (col[4], light),
            "frequency": noise_freq,
            "phase": rng.uniform(0, 2 * math.pi, 6),
        },
        {
            "shape": "sphere",
            "centre": np.array([-0.25, 0.55, 0.45]) + jitter(0.08),
            "radius": 0.3,
            "texture": "bands",
            "colours": (col[5], cream),
            "bands": float(rng.uniform(2.0, 3.5)),
        },
    ]


def _intersect(obj: dict, o: np.ndarray, d: np.ndarray) -> Hit:
    if obj["shape"] == "sphere":
        return hit_sphere(o, d, obj["centre"], obj["radius"])
    if obj["shape"] == "box":
        return hit_box(o, d, obj["centre"], obj["half"], obj["yaw"])
    return hit_cylinder(o, d, obj["centre"], obj["radius"], *obj["z"])


def _albedo(obj: dict, local: np.ndarray) -> np.ndarray:
    """[R, 3] surface colour of ``obj`` at object-local points [R, 3]."""
    a, b = obj["colours"]
    kind = obj["texture"]
    if kind == "checker":
        azimuth = np.arctan2(local[:, 1], local[:, 0])
        polar = np.arccos(np.clip(local[:, 2], -1.0, 1.0))
        nu, nv = obj["cells"]
        w = _soft(np.sin(nu * azimuth) * np.sin(2 * nv * polar))
    elif kind == "stripes":
        axis = obj["axis"] / np.linalg.norm(obj["axis"])
        w = _soft(np.sin(2 * math.pi * obj["frequency"] * (local @ axis)))
    elif kind == "noise":
        waves = np.sin(local @ obj["frequency"].T + obj["phase"])  # [R, 6]
        w = np.clip(0.5 + 1.2 * waves.mean(axis=-1), 0.0, 1.0)
    elif kind == "bands":
        w = _soft(np.sin(2 * math.pi * obj["bands"] * local[:, 2]), 2.0)
    else:  # polar checker on the base's top, plain rim
        radius = np.hypot(local[:, 0], local[:, 1])
        angle = np.arctan2(local[:, 1], local[:, 0])
        w = _soft(np.sin(obj["sectors"] * angle) * np.sin(3 * math.pi * radius))
    return _mix(a, b, w)


def shade(objects: list[dict], o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Trace rays (unit d) through the objects -> (rgb [R, 3] straight colour, hit mask [R])."""
    best, owner = _miss(len(o)), np.full(len(o), -1)
    for k, obj in enumerate(objects):
        hit = _intersect(obj, o, d)
        owner = np.where(hit.t < best.t, k, owner)
        best = _closer(best, hit)
    hit_mask = np.isfinite(best.t)
    normal = best.normal * np.where(np.einsum("ij,ij->i", best.normal, d) > 0, -1.0, 1.0)[:, None]
    key, fill = KEY_LIGHT / np.linalg.norm(KEY_LIGHT), FILL_LIGHT / np.linalg.norm(FILL_LIGHT)
    light = AMBIENT + KEY * np.maximum(normal @ key, 0.0) + FILL * np.maximum(normal @ fill, 0.0)
    rgb = np.zeros((len(o), 3))
    for k, obj in enumerate(objects):
        sel = owner == k
        if np.any(sel):
            rgb[sel] = _albedo(obj, best.local[sel])
    return np.clip(rgb * light[:, None], 0.0, 1.0), hit_mask


def _sphere_cameras(azimuth: np.ndarray, elevation: np.ndarray) -> np.ndarray:
    pos = CAMERA_RADIUS * np.stack(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], -1
    )
    up = np.array([0.0, 0.0, 1.0])
    return np.stack([look_at(p, np.zeros(3), up) for p in pos])


def camera_poses(seed: int, n_train: int, n_test: int) -> tuple[np.ndarray, np.ndarray]:
    """(train [n_train, 3, 4], test [n_test, 3, 4]) camera-to-world matrices."""
    rng = np.random.default_rng([seed, 1])
    lo, hi = (math.sin(math.radians(e)) for e in TRAIN_ELEVATION_DEG)
    # Uniform in sin(elevation) = uniform over the area of the spherical band.
    train = _sphere_cameras(rng.uniform(0, 2 * math.pi, n_train), np.arcsin(rng.uniform(lo, hi, n_train)))
    azimuth = rng.uniform(0, 2 * math.pi) + 2 * math.pi * np.arange(n_test) / n_test
    test = _sphere_cameras(azimuth, np.full(n_test, math.radians(TEST_ELEVATION_DEG)))
    return train, test


def render_view(objects: list[dict], c2w: np.ndarray, size: int) -> np.ndarray:
    """One RGBA view (uint8 [size, size, 4], straight alpha) supersampled 2x2 per pixel."""
    focal = 0.5 * size / math.tan(0.5 * CAMERA_ANGLE_X)
    cams = Cameras(
        c2w=c2w[None],
        fx=focal,
        fy=focal,
        cx=size / 2,
        cy=size / 2,
        distortion=np.zeros(4),
        width=size,
        height=size,
    )
    premult = np.zeros((size * size, 3))
    alpha = np.zeros(size * size)
    for sub in SUPERSAMPLE:
        o, d = world_rays(cams, 0, normalize=True, subpixel=sub)
        rgb, hit = shade(objects, o.astype(np.float64), d.astype(np.float64))
        premult += rgb * hit[:, None]
        alpha += hit
    alpha /= len(SUPERSAMPLE)
    premult /= len(SUPERSAMPLE)
    straight = np.where(alpha[:, None] > 0, premult / np.maximum(alpha[:, None], 1e-12), 0.0)
    rgba = np.concatenate([straight, alpha[:, None]], axis=-1).reshape(size, size, 4)
    return np.round(np.clip(rgba, 0.0, 1.0) * 255.0).astype(np.uint8)


def _transforms(poses: np.ndarray, split: str) -> dict:
    frames = []
    for i, c2w in enumerate(poses):
        matrix = np.eye(4)
        matrix[:3] = c2w
        frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": matrix.round(9).tolist()})
    return {"camera_angle_x": CAMERA_ANGLE_X, "frames": frames}


def _check_arguments(size: int, n_train: int, n_test: int) -> None:
    if size < 8 or n_train < 1 or n_test < 1:
        raise DataError(
            "procedural scene needs size >= 8 and at least one view per split, got "
            f"size={size}, n_train={n_train}, n_test={n_test}"
        )


def write_procedural_scene(
    out_dir: str | os.PathLike, seed: int = 0, size: int = 64, n_train: int = 48, n_test: int = 24
) -> Path:
    """Render the scene of ``seed`` and write it in Blender layout to ``out_dir`` (created).

    Writes ``transforms_{train,test}.json`` and ``{train,test}/r_<i>.png`` (RGBA, size x size).
    Same arguments -> identical files. Returns the directory.
    """
    _check_arguments(size, n_train, n_test)
    out = Path(out_dir)
    objects = build_scene(seed)
    train, test = camera_poses(seed, n_train, n_test)
    for split, poses in (("train", train), ("test", test)):
        (out / split).mkdir(parents=True, exist_ok=True)
        for i, c2w in enumerate(poses):
            Image.fromarray(render_view(objects, c2w, size)).save(out / split / f"r_{i}.png")
        text = json.dumps(_transforms(poses, split), indent=2)
        (out / f"transforms_{split}.json").write_text(text + "\n", encoding="utf-8")
    return out


def default_cache_root() -> Path:
    """``$XDG_CACHE_HOME/mnerf-jax/procedural`` (``~/.cache/...`` when unset)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "mnerf-jax" / "procedural"


def procedural_scene_dir(
    seed: int = 0,
    size: int = 64,
    n_train: int = 48,
    n_test: int = 24,
    cache_root: str | os.PathLike | None = None,
) -> Path:
    """The directory of the cached scene, written on first use.

    The scene is rendered into a temporary directory beside the cache entry and renamed into place,
    so a reader never sees a half-written scene and concurrent writers do not collide.
    """
    _check_arguments(size, n_train, n_test)
    root = Path(cache_root) if cache_root is not None else default_cache_root()
    final = root / f"v{GENERATOR_VERSION}-seed{seed}-size{size}-train{n_train}-test{n_test}"
    if (final / "transforms_test.json").is_file():
        return final
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}-", dir=root))
    try:
        write_procedural_scene(tmp, seed, size, n_train, n_test)
        try:
            os.rename(tmp, final)
        except OSError:
            if not (final / "transforms_test.json").is_file():
                raise
            # Another process finished first; its copy is identical.
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return final
