"""Per-pixel rays of pinhole cameras: OpenCV distortion undone, TensoRF's NDC, aabb culling.

Rays are flat and row-major over pixels (row y, then column x): ray ``y * W + x`` goes through the
centre of pixel (x, y), at pixel coordinates (x + 0.5, y + 0.5).
"""

from __future__ import annotations

import numpy as np

from mnerf_jax.data.types import Cameras, Scene, SceneSplit


def distort(x: np.ndarray, y: np.ndarray, distortion: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV radial-tangential model on normalised image coordinates (x right, y down).

    distortion: [4] (k1, k2, p1, p2). Returns the distorted (x_d, y_d), same shapes as x, y.
    """
    k1, k2, p1, p2 = (float(v) for v in np.asarray(distortion, np.float64).reshape(4))
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + k2 * r2)
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


def undistort(
    xd: np.ndarray, yd: np.ndarray, distortion: np.ndarray, iterations: int = 10
) -> tuple[np.ndarray, np.ndarray]:
    """Invert :func:`distort` by Newton's method on the 2x2 system, starting at the distorted point.

    Works in float64; converges quadratically for the mild distortion of real lenses inside the
    region where the model is invertible.
    """
    k1, k2, p1, p2 = (float(v) for v in np.asarray(distortion, np.float64).reshape(4))
    xd = np.asarray(xd, np.float64)
    yd = np.asarray(yd, np.float64)
    x, y = xd.copy(), yd.copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + k2 * r2)
        d_radial = k1 + 2.0 * k2 * r2  # d radial / d r2
        fx = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
        fy = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd
        fx_x = radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x
        fx_y = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
        fy_x = 2.0 * x * y * d_radial + 2.0 * p2 * y + 2.0 * p1 * x
        fy_y = radial + 2.0 * y * y * d_radial + 2.0 * p2 * x + 6.0 * p1 * y
        det = fx_x * fy_y - fx_y * fy_x
        det = np.where(np.abs(det) < 1e-12, 1e-12, det)
        x = x - (fx * fy_y - fy * fx_y) / det
        y = y - (fy * fx_x - fx * fy_x) / det
    return x, y


def pixel_directions(cameras: Cameras, index: int, subpixel: tuple[float, float] = (0.5, 0.5)) -> np.ndarray:
    """Camera-frame ray directions of every pixel of camera ``index``.

    subpixel: where in each pixel the ray passes, (0.5, 0.5) = the centre.
    Returns float32 [H*W, 3] in the OpenGL camera frame with z = -1 (not normalised).
    """
    w, h = cameras.width, cameras.height
    u = np.arange(w, dtype=np.float64) + subpixel[0]
    v = np.arange(h, dtype=np.float64) + subpixel[1]
    uu, vv = np.meshgrid(u, v, indexing="xy")  # [H, W], row-major over pixels
    # Normalised coordinates in the OpenCV image frame (y down): the frame the distortion model uses.
    x = (uu.reshape(-1) - float(cameras.cx[index])) / float(cameras.fx[index])
    y = (vv.reshape(-1) - float(cameras.cy[index])) / float(cameras.fy[index])
    dist = cameras.distortion[index]
    if np.any(dist != 0):
        x, y = undistort(x, y, dist)
    return np.stack([x, -y, -np.ones_like(x)], axis=-1).astype(np.float32)


def world_rays(
    cameras: Cameras,
    index: int,
    normalize: bool = True,
    subpixel: tuple[float, float] = (0.5, 0.5),
) -> tuple[np.ndarray, np.ndarray]:
    """World-space rays of camera ``index`` (no NDC): origins [H*W, 3] (the camera centre) and
    directions [H*W, 3] (unit length when ``normalize``), float32."""
    dirs = pixel_directions(cameras, index, subpixel).astype(np.float64)
    c2w = cameras.c2w[index].astype(np.float64)
    # einsum rather than ``@``: for [P, 3] x [3, 3] it is many times faster than numpy's matmul.
    d = np.einsum("pj,ij->pi", dirs, c2w[:, :3])
    if normalize:
        d /= np.sqrt(np.einsum("pi,pi->p", d, d))[:, None]
    o = np.broadcast_to(c2w[:, 3], d.shape)
    return np.ascontiguousarray(o, np.float32), d.astype(np.float32)


def camera_rays(cameras: Cameras, index: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays of camera ``index`` as the renderer takes them: origins, directions [H*W, 3] float32.

    Unit world directions, or TensoRF's NDC rays when the cameras carry an NDC space.
    """
    if cameras.ndc is None:
        return world_rays(cameras, index, normalize=True)
    o, d = world_rays(cameras, index, normalize=False)
    space = cameras.ndc
    return ndc_rays(o, d, space.focal, space.width, space.height, space.near)


def ndc_rays(
    origins: np.ndarray,
    directions: np.ndarray,
    focal: float,
    width: int,
    height: int,
    near: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """TensoRF's ``ndc_rays_blender``: map world rays of a forward-facing scene to NDC.

    The origin is first moved along the ray to the plane z = -near; then x and y are projected with
    the pinhole (focal, width, height) and depth maps to z_ndc = 1 + 2 near / z, so the NDC origin
    lies at z = -1 and the ray parameter t in [0, 1] covers depths from ``near`` to infinity.
    origins, directions: [R, 3] (directions need not be unit). Returns float32 [R, 3] each.
    """
    o = np.asarray(origins, np.float64)
    d = np.asarray(directions, np.float64)
    t = -(near + o[:, 2]) / d[:, 2]
    o = o + t[:, None] * d
    ax = -2.0 * focal / width
    ay = -2.0 * focal / height
    ox, oy, oz = o[:, 0] / o[:, 2], o[:, 1] / o[:, 2], o[:, 2]
    o_ndc = np.stack([ax * ox, ay * oy, 1.0 + 2.0 * near / oz], axis=-1)
    d_ndc = np.stack(
        [ax * (d[:, 0] / d[:, 2] - ox), ay * (d[:, 1] / d[:, 2] - oy), -2.0 * near / oz], axis=-1
    )
    return o_ndc.astype(np.float32), d_ndc.astype(np.float32)


def all_rays(
    split: SceneSplit | str, scene: Scene | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every ray of a split with its pixel colour, image after image.

    split: a SceneSplit, or a split name looked up in ``scene``.
    Returns origins [N*H*W, 3], directions [N*H*W, 3] and rgb [N*H*W, 3], float32.
    """
    if isinstance(split, str):
        if scene is None:
            raise ValueError("a split name needs the scene")
        split = scene.split(split)
    cams = split.cameras
    per = cams.width * cams.height
    origins = np.empty((len(cams) * per, 3), np.float32)
    directions = np.empty_like(origins)
    for i in range(len(cams)):
        o, d = camera_rays(cams, i)
        origins[i * per : (i + 1) * per] = o
        directions[i * per : (i + 1) * per] = d
    return origins, directions, split.images.reshape(-1, 3)


def ray_aabb_interval(
    origins: np.ndarray, directions: np.ndarray, aabb: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Slab test: the ray parameters (t_enter, t_exit) [R] where each ray is inside ``aabb`` [2, 3].

    A ray that misses the box gets t_enter >= t_exit. Zero direction components are nudged to 1e-6
    (as TensoRF does) so that the division stays finite.
    """
    o = np.asarray(origins, np.float64)
    d = np.asarray(directions, np.float64)
    box = np.asarray(aabb, np.float64).reshape(2, 3)
    d = np.where(d == 0.0, 1e-6, d)
    t_a = (box[1] - o) / d
    t_b = (box[0] - o) / d
    return np.minimum(t_a, t_b).max(axis=-1), np.maximum(t_a, t_b).min(axis=-1)


def ray_aabb_hit(
    origins: np.ndarray, directions: np.ndarray, aabb: np.ndarray, near: float, far: float
) -> np.ndarray:
    """bool [R]: the ray passes through ``aabb`` [2, 3] at some t in [near, far].

    t is in units of the direction's length (unit directions: world distance).
    """
    t_enter, t_exit = ray_aabb_interval(origins, directions, aabb)
    return np.maximum(t_enter, near) < np.minimum(t_exit, far)
