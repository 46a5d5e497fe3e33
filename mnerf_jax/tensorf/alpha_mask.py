"""Alpha mask, bounding-box shrink and ray filtering (TensoRF's updateAlphaMask, shrink, filtering_rays).

The alpha mask is a boolean volume over the aabb: where the field's α at a grid node (dilated by one node) is
above a threshold. ``render.render_rays`` skips samples outside it; the occupied box of the mask becomes the
new aabb (``shrink_box_from_mask``) and every VM grid is cropped to it (``shrink_field``); training rays
that meet no occupied cell are dropped (``filter_rays``).
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mnerf_jax.core.xla_cpu import jit_cpu_tuned
from mnerf_jax.tensorf import grids
from mnerf_jax.tensorf.raymarch import Geometry, aabb_entry_exit, alpha_mask_lookup, sample_along_rays
from mnerf_jax.tensorf.render import Array, FieldFns, Params


@jit_cpu_tuned(static_argnums=(0, 3, 5))
def _dense_alpha_chunk(
    fns: FieldFns,
    params: Params,
    geometry: Geometry,
    resolution: tuple[int, int, int],
    start: Array,
    size: int,
) -> Array:
    """α at grid nodes ``start .. start + size`` (flat x-major index) of a grid over the aabb."""
    flat = start + jnp.arange(size, dtype=jnp.int32)
    res = jnp.asarray(resolution, jnp.int32)
    ijk = jnp.stack([flat // (res[1] * res[2]), (flat // res[2]) % res[1], flat % res[2]], -1)
    s = ijk.astype(jnp.float32) / (res - 1).astype(jnp.float32)
    xyz = geometry.aabb[0] * (1.0 - s) + geometry.aabb[1] * s
    sigma = fns.density(params, grids.normalize_points(xyz, geometry.aabb))
    sigma = jnp.where(alpha_mask_lookup(geometry, xyz), sigma, 0.0)
    return 1.0 - jnp.exp(-sigma * geometry.step_size)


def compute_alpha_mask(
    fns: FieldFns,
    params: Params,
    geometry: Geometry,
    resolution: tuple[int, int, int],
    threshold: float = 1e-4,
    chunk: int = 1 << 18,
) -> np.ndarray:
    """TensoRF's updateAlphaMask volume: ``[X, Y, Z]`` bool on the nodes of a grid over the aabb.

    α = 1 - exp(-σ step_size) at every node (no distance scale, as TensoRF's getDenseAlpha; σ = 0
    where the current alpha mask is empty), dilated by a 3x3x3 max-pool, then ``α >= threshold``.
    """
    resolution = tuple(int(v) for v in resolution)
    total = math.prod(resolution)
    chunk = min(chunk, total)
    parts = [
        _dense_alpha_chunk(fns, params, geometry, resolution, jnp.asarray(s, jnp.int32), chunk)
        for s in range(0, total, chunk)
    ]
    alpha = jnp.concatenate(parts)[:total].reshape(resolution)
    pooled = jax.lax.reduce_window(alpha, -jnp.inf, jax.lax.max, (3, 3, 3), (1, 1, 1), "SAME")
    return np.asarray(pooled >= threshold)


def shrink_box_from_mask(mask: np.ndarray | Array, aabb: np.ndarray | Array) -> np.ndarray:
    """Bounding box ``[2, 3]`` of the occupied nodes of ``mask [X, Y, Z]`` over ``aabb``.

    As TensoRF's updateAlphaMask: the occupied box of the max-pooled mask, which already extends one
    node beyond the occupied space. An empty mask returns ``aabb`` unchanged.
    """
    mask = np.asarray(mask, bool)
    aabb = np.asarray(aabb, np.float64).reshape(2, 3)
    occupied = np.argwhere(mask)
    if occupied.size == 0:
        return aabb.astype(np.float32)
    s = np.stack([occupied.min(0), occupied.max(0)]) / (np.asarray(mask.shape) - 1.0)
    return (aabb[0] * (1.0 - s) + aabb[1] * s).astype(np.float32)


def _is_vm(node: Any) -> bool:
    return isinstance(node, dict) and set(node) == {"planes", "lines"}


def shrink_field(
    params: Params, old_aabb: np.ndarray | Array, new_aabb: np.ndarray | Array
) -> tuple[Params, np.ndarray]:
    """Crop every VM grid in ``params`` to ``new_aabb`` as TensoRF's ``shrink``.

    Node indices ``lo = round((min - old0) / unit)``, ``hi = round((max - old0) / unit) + 1`` (clipped to
    the grid) are kept, and the returned aabb is moved onto those nodes so the cropped factors sample
    exactly the old field. The resolution is read from the grids (all VM grids must share it).

    Returns ``(cropped params, aligned aabb [2, 3])``: use that aabb (and the new resolution) in the
    geometry from now on.
    """
    vms = [p for p in jax.tree_util.tree_leaves(params, is_leaf=_is_vm) if _is_vm(p)]
    if not vms:
        raise ValueError("no VM grid in params")
    resolution = grids.vm_resolution(vms[0])
    lo, hi, aligned = grids.shrink_indices(old_aabb, resolution, new_aabb)

    def crop(node: Any) -> Any:
        if _is_vm(node):
            if grids.vm_resolution(node) != resolution:
                raise ValueError("VM grids of different resolutions cannot be shrunk together")
            return grids.shrink_vm(node, lo, hi)
        return node

    return jax.tree_util.tree_map(crop, params, is_leaf=_is_vm), aligned


@jit_cpu_tuned(static_argnums=(3, 4))
def _filter_chunk(geometry: Geometry, rays_o: Array, rays_d: Array, n_samples: int, bbox_only: bool) -> Array:
    if bbox_only:
        t_in, t_out = aabb_entry_exit(rays_o, rays_d, geometry.aabb)
        return t_out > jnp.clip(t_in, geometry.near, geometry.far)
    t, _, _ = sample_along_rays(rays_o, rays_d, geometry, None, n_samples)
    xyz = rays_o[:, None, :] + rays_d[:, None, :] * t[..., None]
    return jnp.any(alpha_mask_lookup(geometry, xyz), axis=-1)


def filter_rays(
    geometry: Geometry,
    rays_o: Array | np.ndarray,
    rays_d: Array | np.ndarray,
    *,
    chunk: int = 10240 * 5,
    n_samples: int | None = None,
    bbox_only: bool = False,
) -> np.ndarray:
    """``[R]`` bool: rays worth training on (TensoRF's filtering_rays).

    ``bbox_only``: rays whose sampled range (from the aabb entry clamped to [near, far]) meets the
    aabb; TensoRF tested the whole line, which also keeps rays pointing away from the box. Otherwise:
    rays with at least one evaluation-mode
    sample in an occupied alpha-mask cell (``n_samples`` defaults to the geometry's, which spans the
    whole aabb; TensoRF used 256).
    """
    n = geometry.n_samples if n_samples is None else int(n_samples)
    total = rays_o.shape[0]
    chunk = max(1, min(chunk, total))
    keep = []
    for start in range(0, total, chunk):
        sl = np.minimum(np.arange(start, start + chunk), total - 1)
        o = jnp.asarray(np.asarray(rays_o)[sl], jnp.float32)
        d = jnp.asarray(np.asarray(rays_d)[sl], jnp.float32)
        keep.append(np.asarray(_filter_chunk(geometry, o, d, n, bbox_only))[: min(chunk, total - start)])
    return np.concatenate(keep) if keep else np.zeros((0,), bool)
