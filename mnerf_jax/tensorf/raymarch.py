"""Ray marching: where a ray's samples lie (the scene box, near/far, marching step, alpha mask).

``Geometry`` holds what the renderer needs besides the field: the aabb, the alpha-mask volume and the box
it covers, the marching step and sample count, near/far, and whether the background is white.
``sample_along_rays`` places TensoRF's samples (``sample_ray`` / ``sample_ray_ndc``, one jitter per ray);
``alpha_mask_lookup`` reads the mask at sample positions. ``render.render_rays`` composites them.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from mnerf_jax.tensorf import grids

Array = jax.Array


@flax.struct.dataclass
class Geometry:
    """Where and how rays are sampled (a pytree; the last three fields are static).

    Attributes:
      aabb: ``[2, 3]`` scene box (world units); samples outside it have σ = 0.
      alpha_mask: ``[Xm, Ym, Zm]`` bool occupancy on the nodes of a grid over ``mask_aabb``
        (TensoRF's alpha volume, indexed x, y, z).
      alpha_cells: ``[Xm-1, Ym-1, Zm-1]`` uint8, 1 where any of a cell's 8 corner nodes is occupied:
        the trilinear interpolation of the mask is > 0 inside such a cell (TensoRF's AlphaGridMask
        test ``grid_sample(mask) > 0``), so one gather per sample answers it.
      mask_aabb: ``[2, 3]`` box of the alpha-mask grid.
      step_size: marching step (world units) for bounded scenes.
      near, far: ray range (bounded: clamp of the aabb entry; NDC: sampling range).
      distance_scale: multiplies σ·Δt (TensoRF's 25).
      n_samples: samples per ray (static).
      ndc: forward-facing scene with NDC rays (static).
      white_bg: composite on white, else black (static).
    """

    aabb: Array
    alpha_mask: Array
    alpha_cells: Array
    mask_aabb: Array
    step_size: Array
    near: Array
    far: Array
    distance_scale: Array
    n_samples: int = flax.struct.field(pytree_node=False)
    ndc: bool = flax.struct.field(pytree_node=False, default=False)
    white_bg: bool = flax.struct.field(pytree_node=False, default=True)


def mask_cells(mask: Array | np.ndarray) -> np.ndarray:
    """Cell occupancy ``[X-1, Y-1, Z-1]`` uint8 of a node mask ``[X, Y, Z]`` (max over 2x2x2 corners)."""
    m = np.asarray(mask, bool)
    cells = m[:-1] | m[1:]
    cells = cells[:, :-1] | cells[:, 1:]
    cells = cells[:, :, :-1] | cells[:, :, 1:]
    return cells.astype(np.uint8)


def make_geometry(
    aabb: Array | np.ndarray,
    resolution: tuple[int, int, int],
    *,
    step_ratio: float = 0.5,
    near: float = 2.0,
    far: float = 6.0,
    distance_scale: float = 25.0,
    ndc: bool = False,
    white_bg: bool = True,
    n_samples: int | None = None,
    max_samples: int = 0,
) -> Geometry:
    """Geometry for a grid of ``resolution`` nodes over ``aabb`` with no alpha mask yet (all ones).

    ``step_size = mean(aabb size / (res - 1)) * step_ratio``; ``n_samples`` defaults to TensoRF's
    ``int(|res| / step_ratio)``, capped by ``max_samples`` when that is > 0.
    """
    aabb = np.asarray(aabb, np.float32).reshape(2, 3)
    if n_samples is None:
        n_samples = grids.n_samples_for(resolution, step_ratio)
        if max_samples > 0:
            n_samples = min(n_samples, max_samples)
    ones = np.ones((2, 2, 2), bool)
    f32 = functools.partial(jnp.asarray, dtype=jnp.float32)
    return Geometry(
        aabb=f32(aabb),
        alpha_mask=jnp.asarray(ones),
        alpha_cells=jnp.asarray(mask_cells(ones)),
        mask_aabb=f32(aabb),
        step_size=f32(grids.step_size_for(aabb, resolution, step_ratio)),
        near=f32(near),
        far=f32(far),
        distance_scale=f32(distance_scale),
        n_samples=int(n_samples),
        ndc=bool(ndc),
        white_bg=bool(white_bg),
    )


# A geometry in a checkpoint: its arrays in the tree, its static fields in the meta.
GEOMETRY_ARRAYS = ("aabb", "alpha_mask", "mask_aabb", "step_size", "near", "far", "distance_scale")


def geometry_arrays(g: Geometry) -> dict[str, Array]:
    """The arrays of ``g`` a checkpoint stores (``alpha_cells`` is derived from the mask)."""
    return {k: getattr(g, k) for k in GEOMETRY_ARRAYS}


def geometry_meta(g: Geometry) -> dict[str, Any]:
    """The static fields of ``g`` (JSON)."""
    return {"n_samples": g.n_samples, "ndc": g.ndc, "white_bg": g.white_bg}


def geometry_from_checkpoint(arrays: Mapping[str, Any], meta: Mapping[str, Any]) -> Geometry:
    """The geometry of :func:`geometry_arrays` ``arrays`` and :func:`geometry_meta` ``meta``."""
    mask = np.asarray(arrays["alpha_mask"], bool)
    f32 = functools.partial(jnp.asarray, dtype=jnp.float32)
    return Geometry(
        alpha_mask=jnp.asarray(mask),
        alpha_cells=jnp.asarray(mask_cells(mask)),
        **{k: f32(arrays[k]) for k in GEOMETRY_ARRAYS if k != "alpha_mask"},
        n_samples=int(meta["n_samples"]),
        ndc=bool(meta["ndc"]),
        white_bg=bool(meta["white_bg"]),
    )


def with_alpha_mask(geometry: Geometry, mask: Array | np.ndarray, mask_aabb: Array | np.ndarray) -> Geometry:
    """The geometry with a new alpha mask ``[X, Y, Z]`` (bool) over ``mask_aabb [2, 3]``."""
    mask = np.asarray(mask, bool)
    if mask.ndim != 3 or min(mask.shape) < 2:
        raise ValueError(f"alpha mask must be [X, Y, Z] with sizes >= 2, got {mask.shape}")
    return geometry.replace(
        alpha_mask=jnp.asarray(mask),
        alpha_cells=jnp.asarray(mask_cells(mask)),
        mask_aabb=jnp.asarray(mask_aabb, jnp.float32).reshape(2, 3),
    )


# --------------------------------------------------------------------------------------------------
# Sampling along rays
# --------------------------------------------------------------------------------------------------


def aabb_entry_exit(rays_o: Array, rays_d: Array, aabb: Array) -> tuple[Array, Array]:
    """Slab-test distances ``(t_in [R], t_out [R])`` of rays to ``aabb`` (no near/far clamp).

    Zero direction components are replaced by 1e-6 as TensoRF does; ``t_out > t_in`` iff the ray's
    line meets the box.
    """
    vec = jnp.where(rays_d == 0, 1e-6, rays_d)
    rate_a = (aabb[1] - rays_o) / vec
    rate_b = (aabb[0] - rays_o) / vec
    return jnp.max(jnp.minimum(rate_a, rate_b), -1), jnp.min(jnp.maximum(rate_a, rate_b), -1)


def sample_along_rays(
    rays_o: Array, rays_d: Array, geometry: Geometry, key: Array | None, n_samples: int | None = None
) -> tuple[Array, Array, Array]:
    """Sample distances along rays as TensoRF.

    Bounded scenes: ``t = t_min + step (arange(N) + u)`` with ``t_min`` the aabb entry clamped to
    [near, far] and one ``u ~ U[0, 1)`` per ray when ``key`` is given (training), ``u = 0`` otherwise.
    NDC: ``t = linspace(near, far, N)`` plus, when ``key`` is given, one jitter row ``U[0, 1) (far -
    near) / N`` shared by all rays (TensoRF's sample_ray_ndc); distances are scaled by |d|.

    Returns ``(t [R, N], dists [R, N], viewdirs [R, 3])``: ``dists[i] = t[i+1] - t[i]`` (world
    units, last 0) and unit view directions (non-NDC directions are used as given, which TensoRF
    assumes to be unit).
    """
    n = geometry.n_samples if n_samples is None else n_samples
    r = rays_o.shape[0]
    if geometry.ndc:
        t = jnp.broadcast_to(jnp.linspace(geometry.near, geometry.far, n, dtype=jnp.float32), (1, n))
        if key is not None:
            t = t + jax.random.uniform(key, (1, n)) * ((geometry.far - geometry.near) / n)
        t = jnp.broadcast_to(t, (r, n))
        norm = jnp.linalg.norm(rays_d, axis=-1, keepdims=True)
        dists = jnp.concatenate([t[:, 1:] - t[:, :-1], jnp.zeros((r, 1), t.dtype)], -1) * norm
        return t, dists, rays_d / norm
    t_in, _ = aabb_entry_exit(rays_o, rays_d, geometry.aabb)
    t_min = jnp.clip(t_in, geometry.near, geometry.far)
    steps = jnp.arange(n, dtype=jnp.float32)[None, :]
    if key is not None:
        steps = steps + jax.random.uniform(key, (r, 1))
    t = t_min[:, None] + geometry.step_size * steps
    # Spacing is exactly one step; the last sample has zero length as in TensoRF.
    dists = jnp.broadcast_to(jnp.where(jnp.arange(n) < n - 1, geometry.step_size, 0.0), (r, n))
    return t, dists, rays_d


def inside_box(xyz: Array, aabb: Array) -> Array:
    """``[...]`` bool: point inside (or on) the box ``[2, 3]``."""
    return jnp.all((xyz >= aabb[0]) & (xyz <= aabb[1]), axis=-1)


def alpha_mask_lookup(geometry: Geometry, xyz: Array) -> Array:
    """``[...]`` bool: TensoRF's ``alphaMask.sample_alpha(xyz) > 0`` at world points ``[..., 3]``.

    True inside a mask cell with an occupied corner; False outside the mask box.
    """
    cells = geometry.alpha_cells
    shape = jnp.asarray(cells.shape, jnp.float32)
    lo, hi = geometry.mask_aabb[0], geometry.mask_aabb[1]
    g = (xyz - lo) * (shape / (hi - lo))
    i = jnp.clip(jnp.floor(g), 0, shape - 1).astype(jnp.int32)
    flat = (i[..., 0] * cells.shape[1] + i[..., 1]) * cells.shape[2] + i[..., 2]
    occupied = grids.take_rows(cells.reshape(-1), flat.reshape(-1)).reshape(flat.shape) > 0
    return occupied & inside_box(xyz, geometry.mask_aabb)
