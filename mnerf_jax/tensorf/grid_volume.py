"""Fast paths for sums of VM components: the dense volume the factors span, and splatted gradients.

``sample_vm_sum`` (the density feature ``Σ_m Σ_c P_m L_m``) and ``sample_vm_projected`` (features
projected by a basis matrix first) equal gathering the factors (``grids.sample_vm``) and summing; what
differs is the backward pass. Gathering back-propagates ``[P, C]`` cotangents into every plane and line;
here, while the grid is small enough per point, the cotangent is splatted into a dense volume (8 row
scatter-adds) and contracted with the factors by matrix products, which is faster on XLA:CPU
(``scripts/bench_render.py --only density`` compares them).
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp

from mnerf_jax.tensorf.grids import (
    MAT_MODES,
    VEC_MODES,
    _axis_taps,
    sample_vm,
    sample_vm_modes,
    vm_resolution,
)

Array = jax.Array
VMGrid = dict[str, tuple[Array, ...]]


# ``sample_vm_sum`` back-propagates through the dense volume up to this many grid cells per point.
VOLUME_CELLS_PER_POINT = 32


def vm_volume(grid: VMGrid) -> Array:
    """The dense scalar field ``V [X, Y, Z] = Σ_m Σ_c P_m[., ., c] L_m[., c]`` (axes in xyz order)."""
    volume = None
    for plane, line, (a, b), c in zip(grid["planes"], grid["lines"], MAT_MODES, VEC_MODES, strict=True):
        v = jnp.einsum("abr,cr->abc", plane, line, precision=jax.lax.Precision.HIGHEST)
        v = jnp.transpose(v, [(a, b, c).index(axis) for axis in range(3)])
        volume = v if volume is None else volume + v
    return volume


def sample_volume(volume: Array, xyz: Array) -> Array:
    """Trilinear sample of ``volume [X, Y, Z, *F]`` at normalised ``xyz [P, 3]`` -> ``[P, *F]``.

    Same taps and zero padding as ``sample_plane`` / ``sample_line`` per axis; the 2x2x2 corner cube
    is one gather (its transpose one windowed scatter-add). ``F`` are optional trailing channels.
    """
    xyz = jax.lax.stop_gradient(xyz)
    taps = [_axis_taps(xyz[:, axis], volume.shape[axis]) for axis in range(3)]
    start = jnp.stack([t[0] for t in taps], -1)
    channels = volume.shape[3:]
    dnums = jax.lax.GatherDimensionNumbers(
        offset_dims=tuple(range(1, 4 + len(channels))), collapsed_slice_dims=(), start_index_map=(0, 1, 2)
    )
    cube = jax.lax.gather(
        volume,
        start,
        dnums,
        slice_sizes=(2, 2, 2, *channels),
        mode=jax.lax.GatherScatterMode.PROMISE_IN_BOUNDS,
    )  # [P, 2, 2, 2, *F]
    (_, x0, x1), (_, y0, y1), (_, z0, z1) = (
        tuple(w.reshape(w.shape + (1,) * len(channels)) for w in t) for t in taps
    )
    # Written out rather than as an einsum, which XLA:CPU lowers to a batched dot and a transpose.
    out = 0.0
    for i, wx in enumerate((x0, x1)):
        for j, wy in enumerate((y0, y1)):
            out = out + wx * wy * (cube[:, i, j, 0] * z0 + cube[:, i, j, 1] * z1)
    return out


def _gathered_sum(grid: VMGrid, xyz: Array) -> Array:
    return sum(jnp.sum(f, axis=-1) for f in sample_vm_modes(grid, xyz))


def _volume_transpose(grid: VMGrid, d_volume: Array) -> VMGrid:
    """Cotangent of the factors from a cotangent ``[X, Y, Z]`` of ``vm_volume(grid)``."""
    hi = jax.lax.Precision.HIGHEST
    planes, lines = [], []
    for plane, line, (a, b), c in zip(grid["planes"], grid["lines"], MAT_MODES, VEC_MODES, strict=True):
        d = jnp.transpose(d_volume, (a, b, c))
        planes.append(jnp.einsum("abc,cr->abr", d, line, precision=hi))
        lines.append(jnp.einsum("abc,abr->cr", d, plane, precision=hi))
    return {"planes": tuple(planes), "lines": tuple(lines)}


@functools.partial(jax.custom_vjp, nondiff_argnums=(2,))
def _vm_sum(grid: VMGrid, xyz: Array, volume_backward: bool) -> Array:
    return _gathered_sum(grid, xyz)


def _vm_sum_fwd(grid: VMGrid, xyz: Array, volume_backward: bool) -> tuple[Array, tuple[VMGrid, Array]]:
    return _gathered_sum(grid, xyz), (grid, xyz)


def _vm_sum_bwd(volume_backward: bool, res: tuple[VMGrid, Array], cot: Array) -> tuple[VMGrid, Array]:
    grid, xyz = res
    if volume_backward:
        shape = vm_resolution(grid)
        d_volume = splat_volume(cot[:, None], xyz, shape).reshape(shape)
        d_grid = _volume_transpose(grid, d_volume)
    else:
        d_grid = jax.vjp(lambda g: _gathered_sum(g, xyz), grid)[1](cot)[0]
    return d_grid, jnp.zeros_like(xyz)  # coordinates are detached, as in sample_vm_modes


_vm_sum.defvjp(_vm_sum_fwd, _vm_sum_bwd)


def sample_vm_sum(grid: VMGrid, xyz: Array, method: str = "auto") -> Array:
    """Sum of all component products (TensoRF's density feature) at normalised ``xyz [P, 3]``: ``[P]``.

    Exact evaluations, equal up to float rounding in value and gradient:

    - ``"gather"``: per mode, a bilinear plane sample times a linear line sample. Its backward pass
      materialises a ``[P, C]`` cotangent per plane corner and line tap (18 per point): on the CPU,
      bound by memory bandwidth.
    - ``"volume"``: the sum over components is the dense trilinear field ``vm_volume`` (a matrix
      product per mode), sampled once per point. Its backward pass is one scalar splat per point and
      two matrix products per mode: because the per-point cotangent of the density feature is a
      scalar, nothing ``[P, C]``-sized is built.
    - ``"auto"`` (default): the gather forward (faster without a gradient) and, while the grid has
      at most ``VOLUME_CELLS_PER_POINT`` cells per point, the volume's backward pass (its cost follows
      the cells, the gathers' the points). "auto" splats by row scatter-adds (``splat_volume``);
      ``scripts/bench_render.py --only density`` times the three.
    """
    if method == "auto":
        cells = math.prod(vm_resolution(grid))
        return _vm_sum(grid, xyz, cells <= VOLUME_CELLS_PER_POINT * xyz.shape[0])
    if method == "volume":
        return sample_volume(vm_volume(grid), xyz)
    if method == "gather":
        return _gathered_sum(grid, xyz)
    raise ValueError(f"unknown method {method!r} (auto | gather | volume)")


# ``sample_vm_projected`` back-propagates through a dense ``[X, Y, Z, K]`` cotangent volume while the
# grid has at most this many cells per point and the volume fits in ``PROJECTED_VOLUME_BYTES``.
PROJECTED_CELLS_PER_POINT = 4
PROJECTED_VOLUME_BYTES = 1 << 30


def _projected(grid: VMGrid, basis: Array, xyz: Array) -> tuple[Array, Array]:
    features = sample_vm(grid, xyz)
    return features @ basis, features


def splat_volume(values: Array, xyz: Array, resolution: tuple[int, int, int]) -> Array:
    """Trilinear splat (the transpose of ``sample_volume``) of ``values [P, K]`` -> ``[X*Y*Z, K]``.

    Eight row scatter-adds (one per cube corner) of ``P`` rows of ``K`` floats into the flattened
    volume. (XLA:CPU's windowed scatters, ``[2, 2, 2, K]`` as ``jax.linear_transpose`` of
    ``sample_volume`` gives, or ``[2, K]`` over the adjacent z taps, are slower.)
    """
    xyz = jax.lax.stop_gradient(xyz)
    (x0, wx0, wx1), (y0, wy0, wy1), (z0, wz0, wz1) = (
        _axis_taps(xyz[:, axis], resolution[axis]) for axis in range(3)
    )
    _, ny, nz = resolution
    base = (x0 * ny + y0) * nz + z0
    dnums = jax.lax.ScatterDimensionNumbers(
        update_window_dims=(1,), inserted_window_dims=(0,), scatter_dims_to_operand_dims=(0,)
    )
    table = jnp.zeros((math.prod(resolution), values.shape[-1]), values.dtype)
    for dx, wx in ((0, wx0), (1, wx1)):
        for dy, wy in ((0, wy0), (1, wy1)):
            for dz, wz in ((0, wz0), (1, wz1)):
                rows = base + (dx * ny + dy) * nz + dz
                table = jax.lax.scatter_add(
                    table,
                    rows[:, None],
                    (wx * wy * wz)[:, None] * values,
                    dnums,
                    mode=jax.lax.GatherScatterMode.PROMISE_IN_BOUNDS,
                )
    return table


def _projected_volume_transpose(grid: VMGrid, basis: Array, d_volume: Array) -> VMGrid:
    """Factor cotangents from the cotangent ``[X*Y*Z, K]`` of the projected field.

    The projected field is ``V[x, y, z, k] = Σ_m Σ_r P_m[., ., r] L_m[., r] B[o_m + r, k]``. With
    ``D [A*B, C*K]`` the cotangent in mode m's axis order, ``dP_m = D @ M`` where
    ``M[(c, k), r] = L_m[c, r] B[o_m + r, k]``, and ``dL_m[c, r] = Σ_k B[o_m + r, k] (D^T P_m)[(c, k), r]``:
    two matrix products per mode, in the volume's layout.
    """
    hi = jax.lax.Precision.HIGHEST
    res = vm_resolution(grid)
    k = d_volume.shape[-1]
    volume = d_volume.reshape(*res, k)
    planes, lines = [], []
    offset = 0
    for plane, line, (a, b), c in zip(grid["planes"], grid["lines"], MAT_MODES, VEC_MODES, strict=True):
        rank = plane.shape[-1]
        rows = basis[offset : offset + rank]  # [R, K]
        offset += rank
        d = jnp.transpose(volume, (a, b, c, 3)).reshape(res[a] * res[b], res[c] * k)
        m = (line[:, None, :] * rows.T[None]).reshape(res[c] * k, rank)
        planes.append(jnp.dot(d, m, precision=hi).reshape(res[a], res[b], rank))
        t = jnp.dot(d.T, plane.reshape(-1, rank), precision=hi).reshape(res[c], k, rank)
        lines.append(jnp.sum(t * rows.T[None], axis=1))
    return {"planes": tuple(planes), "lines": tuple(lines)}


@functools.partial(jax.custom_vjp, nondiff_argnums=(3,))
def _vm_projected(grid: VMGrid, basis: Array, xyz: Array, volume_backward: bool) -> Array:
    return _projected(grid, basis, xyz)[0]


def _vm_projected_fwd(
    grid: VMGrid, basis: Array, xyz: Array, volume_backward: bool
) -> tuple[Array, tuple[VMGrid, Array, Array, Array]]:
    out, features = _projected(grid, basis, xyz)
    return out, (grid, basis, xyz, features)


def _vm_projected_bwd(
    volume_backward: bool, res: tuple[VMGrid, Array, Array, Array], cot: Array
) -> tuple[VMGrid, Array, Array]:
    grid, basis, xyz, features = res
    d_basis = features.T @ cot
    if volume_backward:
        d_volume = splat_volume(cot, xyz, vm_resolution(grid))
        d_grid = _projected_volume_transpose(grid, basis, d_volume)
    else:
        d_grid = jax.vjp(lambda g: sample_vm(g, xyz), grid)[1](cot @ basis.T)[0]
    return d_grid, d_basis, jnp.zeros_like(xyz)  # coordinates are detached, as in sample_vm_modes


_vm_projected.defvjp(_vm_projected_fwd, _vm_projected_bwd)


def sample_vm_projected(grid: VMGrid, basis: Array, xyz: Array, method: str = "auto") -> Array:
    """Component products through a basis matrix (TensoRF's appearance feature): ``[P, K]``.

    ``sample_vm(grid, xyz) @ basis`` with ``basis [C0 + C1 + C2, K]``. Evaluations equal up to float
    rounding in value and gradient:

    - ``"gather"``: the per-mode gathers and their transposes. The backward pass materialises a
      ``[P, C]`` cotangent per plane corner and line tap (18 per point).
    - ``"auto"`` (default): the same forward pass; while the grid has at most
      ``PROJECTED_CELLS_PER_POINT`` cells per point (and the volume fits in
      ``PROJECTED_VOLUME_BYTES``), the backward pass splats the ``[P, K]`` cotangent trilinearly into
      a dense ``[X, Y, Z, K]`` volume (one windowed scatter-add) and contracts it with the factors and
      the basis, two matrix products per mode (``_projected_volume_transpose``). The projected field
      is trilinear in each cell because the plane's bilinear weights times the line's linear ones are
      the trilinear weights.
    """
    if method == "gather":
        return _projected(grid, basis, xyz)[0]
    if method != "auto":
        raise ValueError(f"unknown method {method!r} (auto | gather)")
    cells = math.prod(vm_resolution(grid))
    fits = cells * basis.shape[-1] * 4 <= PROJECTED_VOLUME_BYTES
    return _vm_projected(grid, basis, xyz, fits and cells <= PROJECTED_CELLS_PER_POINT * xyz.shape[0])
