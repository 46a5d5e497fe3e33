"""TensoRF vector-matrix (VM) factor grids: init, sampling, resampling, cropping, schedules, regularisers.

A VM grid is the pytree ``{"planes": (P0, P1, P2), "lines": (L0, L1, L2)}``:

========  ===================  ===============
mode m    plane P_m            line L_m
========  ===================  ===============
0         XY: ``[X, Y, C0]``   Z: ``[Z, C0]``
1         XZ: ``[X, Z, C1]``   Y: ``[Y, C1]``
2         YZ: ``[Y, Z, C2]``   X: ``[X, C2]``
========  ===================  ===============

Component ``c`` of mode ``m`` at a point is ``P_m[u, v, c] * L_m[w, c]``. Points are normalised to
[-1, 1] over the aabb; sampling is (bi)linear with ``align_corners=True`` (index ``i`` sits at
``-1 + 2 i / (G - 1)``) and zero padding outside. Resolutions are read from array shapes, so they are
static under ``jax.jit``.

Layout: factors are stored channels-last. A plane ``[Ga, Gb, C]`` is then, without a copy, a table of
``Ga*Gb`` contiguous rows of ``C`` floats, and bilinear sampling is four row gathers plus weights (the
backward pass four row scatter-adds). A channels-first table would read ``C`` strided scalars per
corner instead; this is also faster than ``jax.scipy.ndimage.map_coordinates`` per channel
(``scripts/bench_render.py``).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array
VMGrid = dict[str, tuple[Array, ...]]

# Plane axes and line axis of each mode (TensoRF's matMode / vecMode).
MAT_MODES: tuple[tuple[int, int], ...] = ((0, 1), (0, 2), (1, 2))
VEC_MODES: tuple[int, ...] = (2, 1, 0)


# --------------------------------------------------------------------------------------------------
# Construction and shape queries
# --------------------------------------------------------------------------------------------------


def init_vm(key: Array, resolution: Sequence[int], ranks: Sequence[int], scale: float = 0.1) -> VMGrid:
    """Random VM factors, ``scale * N(0, 1)`` as TensoRF.

    Args:
      key: PRNG key.
      resolution: grid nodes per axis ``(X, Y, Z)``, each >= 2.
      ranks: components per mode ``(C0, C1, C2)``.
      scale: standard deviation of the initial factors.

    Returns:
      ``{"planes": ([X,Y,C0], [X,Z,C1], [Y,Z,C2]), "lines": ([Z,C0], [Y,C1], [X,C2])}`` float32.
    """
    res = tuple(int(r) for r in resolution)
    if len(res) != 3 or min(res) < 2:
        raise ValueError(f"resolution must be 3 sizes >= 2, got {resolution}")
    if len(ranks) != 3:
        raise ValueError(f"ranks must have 3 entries, got {ranks}")
    return _init_vm(key, res, tuple(int(r) for r in ranks), float(scale))


@functools.partial(jax.jit, static_argnums=(1, 2, 3))
def _init_vm(key: Array, res: tuple[int, ...], ranks: tuple[int, ...], scale: float) -> VMGrid:
    shapes = [(res[a], res[b], r) for (a, b), r in zip(MAT_MODES, ranks, strict=True)]
    shapes += [(res[c], r) for c, r in zip(VEC_MODES, ranks, strict=True)]
    # One draw for all factors: a single random-bits kernel compiles much faster than six.
    sizes = [math.prod(s) for s in shapes]
    flat = scale * jax.random.normal(key, (sum(sizes),), jnp.float32)
    parts = jnp.split(flat, np.cumsum(sizes)[:-1].tolist())
    factors = [p.reshape(s) for p, s in zip(parts, shapes, strict=True)]
    return {"planes": tuple(factors[:3]), "lines": tuple(factors[3:])}


def vm_resolution(grid: VMGrid) -> tuple[int, int, int]:
    """Grid nodes per axis ``(X, Y, Z)`` read from the factor shapes."""
    p0, p1, _ = grid["planes"]
    return int(p0.shape[0]), int(p0.shape[1]), int(p1.shape[1])


def vm_ranks(grid: VMGrid) -> tuple[int, ...]:
    """Components per mode ``(C0, C1, C2)``."""
    return tuple(int(p.shape[-1]) for p in grid["planes"])


def normalize_points(xyz: Array, aabb: Array) -> Array:
    """World points ``[..., 3]`` to [-1, 1] over ``aabb [2, 3]`` (TensoRF's normalize_coord)."""
    return (xyz - aabb[0]) * (2.0 / (aabb[1] - aabb[0])) - 1.0


# --------------------------------------------------------------------------------------------------
# Sampling
# --------------------------------------------------------------------------------------------------


def take_rows(table: Array, idx: Array) -> Array:
    """``table[idx]`` along axis 0 for ``idx [B]`` known to be in range: one gather, no index fix-ups.

    (``table[idx]`` would add negative-index wrapping and clamping to every lookup.)
    """
    dnums = jax.lax.GatherDimensionNumbers(
        offset_dims=tuple(range(1, table.ndim)), collapsed_slice_dims=(0,), start_index_map=(0,)
    )
    return jax.lax.gather(
        table,
        idx[:, None],
        dnums,
        slice_sizes=(1, *table.shape[1:]),
        mode=jax.lax.GatherScatterMode.PROMISE_IN_BOUNDS,
    )


def _axis_taps(u: Array, size: int) -> tuple[Array, Array, Array]:
    """Linear-interpolation taps along one axis with align_corners=True and zero padding.

    ``u`` in [-1, 1] (any value allowed) maps to the continuous index ``g = (u + 1) (size - 1) / 2``.
    The taps are the nodes ``i0, i0 + 1`` with ``i0 = clip(floor(g), 0, size - 2)`` and hat weights
    ``max(0, 1 - |g - node|)``: inside the grid these are ``1 - f, f``; just outside, the missing
    neighbour is the zero padding; far outside both weights are 0.

    Returns ``(i0 [P] int32, w0 [P], w1 [P])``.
    """
    g = (u + 1.0) * (0.5 * (size - 1))
    i0 = jnp.clip(jnp.floor(g), 0, size - 2)
    d = g - i0
    w0 = jnp.maximum(0.0, 1.0 - jnp.abs(d))
    w1 = jnp.maximum(0.0, 1.0 - jnp.abs(d - 1.0))
    return i0.astype(jnp.int32), w0, w1


def sample_plane(plane: Array, u: Array, v: Array) -> Array:
    """Bilinear sample of ``plane [Ga, Gb, C]`` at normalised ``(u, v)`` ``[P]`` each -> ``[P, C]``."""
    ga, gb, c = plane.shape
    table = plane.reshape(ga * gb, c)
    ia, wa0, wa1 = _axis_taps(u, ga)
    ib, wb0, wb1 = _axis_taps(v, gb)
    base = ia * gb + ib
    top = take_rows(table, base) * wb0[:, None] + take_rows(table, base + 1) * wb1[:, None]
    bottom = take_rows(table, base + gb) * wb0[:, None] + take_rows(table, base + gb + 1) * wb1[:, None]
    return top * wa0[:, None] + bottom * wa1[:, None]


def sample_line(line: Array, w: Array) -> Array:
    """Linear sample of ``line [G, C]`` at normalised ``w [P]`` -> ``[P, C]``."""
    i0, w0, w1 = _axis_taps(w, line.shape[0])
    return take_rows(line, i0) * w0[:, None] + take_rows(line, i0 + 1) * w1[:, None]


def sample_vm_modes(grid: VMGrid, xyz: Array) -> tuple[Array, ...]:
    """Per-mode component products at normalised points.

    Args:
      grid: VM grid.
      xyz: ``[P, 3]`` points normalised to [-1, 1] over the aabb. No gradient flows to them (as
        TensoRF, which detaches the sampling coordinates).

    Returns:
      ``(F0 [P, C0], F1 [P, C1], F2 [P, C2])`` with ``F_m[:, c] = P_m(u, v)[c] * L_m(w)[c]``.
    """
    xyz = jax.lax.stop_gradient(xyz)
    out = []
    for plane, line, (a, b), c in zip(grid["planes"], grid["lines"], MAT_MODES, VEC_MODES, strict=True):
        out.append(sample_plane(plane, xyz[:, a], xyz[:, b]) * sample_line(line, xyz[:, c]))
    return tuple(out)


def sample_vm(grid: VMGrid, xyz: Array) -> Array:
    """Component products concatenated by mode: ``[P, C0 + C1 + C2]``.

    The density feature is the sum of this over components; the appearance feature is this vector
    (fed to the basis matrix). ``xyz [P, 3]`` is normalised to [-1, 1] over the aabb.
    """
    return jnp.concatenate(sample_vm_modes(grid, xyz), axis=-1)


# --------------------------------------------------------------------------------------------------
# Resampling and cropping
# --------------------------------------------------------------------------------------------------


def _resize_axis(x: Array, axis: int, new_size: int) -> Array:
    """Linear resize along ``axis`` with align_corners=True (new node j sits at old j (G-1)/(G'-1))."""
    old = x.shape[axis]
    if new_size == old:
        return x
    pos = np.linspace(0.0, old - 1.0, new_size) if new_size > 1 else np.zeros(1)
    i0 = np.clip(np.floor(pos), 0, max(old - 2, 0)).astype(np.int32)
    i1 = np.minimum(i0 + 1, old - 1)
    frac = (pos - i0).astype(np.float32)
    shape = [1] * x.ndim
    shape[axis] = new_size
    frac = jnp.asarray(frac).reshape(shape)
    return jnp.take(x, i0, axis=axis) * (1.0 - frac) + jnp.take(x, i1, axis=axis) * frac


def upsample_vm(grid: VMGrid, new_resolution: Sequence[int]) -> VMGrid:
    """Resize every factor to ``new_resolution (X, Y, Z)`` (bilinear/linear, align_corners=True).

    As TensoRF's ``up_sampling_VM``: the field at the old nodes is preserved up to interpolation (and
    exactly where an old node coincides with a new one). Works for shrinking too.
    """
    res = tuple(int(r) for r in new_resolution)
    planes, lines = [], []
    for plane, line, (a, b), c in zip(grid["planes"], grid["lines"], MAT_MODES, VEC_MODES, strict=True):
        planes.append(_resize_axis(_resize_axis(plane, 0, res[a]), 1, res[b]))
        lines.append(_resize_axis(line, 0, res[c]))
    return {"planes": tuple(planes), "lines": tuple(lines)}


def shrink_vm(grid: VMGrid, lo: Sequence[int], hi: Sequence[int]) -> VMGrid:
    """Crop every factor to nodes ``lo[k] <= i < hi[k]`` along axis k (TensoRF's ``shrink``).

    ``lo``, ``hi`` are ``(X, Y, Z)`` node indices (python ints); the cropped grid spans the sub-box
    whose corner nodes are ``lo`` and ``hi - 1``.
    """
    lo = tuple(int(v) for v in lo)
    hi = tuple(int(v) for v in hi)
    planes, lines = [], []
    for plane, line, (a, b), c in zip(grid["planes"], grid["lines"], MAT_MODES, VEC_MODES, strict=True):
        planes.append(plane[lo[a] : hi[a], lo[b] : hi[b]])
        lines.append(line[lo[c] : hi[c]])
    return {"planes": tuple(planes), "lines": tuple(lines)}


def shrink_indices(
    aabb: Array | np.ndarray, resolution: Sequence[int], new_aabb: Array | np.ndarray
) -> tuple[tuple[int, ...], tuple[int, ...], np.ndarray]:
    """Node range covering ``new_aabb`` on a grid over ``aabb`` and the voxel-aligned box it spans.

    As TensoRF's ``shrink``: ``lo = round((min - aabb0) / unit)``, ``hi = min(round((max - aabb0) /
    unit) + 1, G)`` with ``unit = size / (G - 1)``; the returned aabb has its corners exactly on the
    kept nodes (``aabb0 + lo unit``, ``aabb0 + (hi - 1) unit``), so the cropped factors sample the same
    field at the same points.

    Returns ``(lo, hi, aligned_aabb [2, 3] float32)``.
    """
    aabb = np.asarray(aabb, np.float64)
    new_aabb = np.asarray(new_aabb, np.float64)
    res = np.asarray(resolution, np.int64)
    unit = (aabb[1] - aabb[0]) / (res - 1)
    lo = np.clip(np.round((new_aabb[0] - aabb[0]) / unit), 0, res - 2).astype(np.int64)
    hi = np.minimum(np.round((new_aabb[1] - aabb[0]) / unit).astype(np.int64) + 1, res)
    hi = np.maximum(hi, lo + 2)  # keep at least two nodes per axis
    aligned = np.stack([aabb[0] + lo * unit, aabb[0] + (hi - 1) * unit]).astype(np.float32)
    return tuple(int(v) for v in lo), tuple(int(v) for v in hi), aligned


# --------------------------------------------------------------------------------------------------
# Resolution and sampling schedules (TensoRF's utils.N_to_reso, cal_n_samples, train.py schedule)
# --------------------------------------------------------------------------------------------------


def resolution_from_voxels(aabb: Array | np.ndarray | Sequence, n_voxels: int) -> tuple[int, int, int]:
    """Per-axis node count for ``n_voxels`` total, following the aabb's aspect ratio (N_to_reso).

    ``voxel = (prod(size) / n_voxels) ** (1/3)``; ``res = trunc(size / voxel)``. The truncation
    tolerates float rounding (a relative 1e-5), so a cube of ``128**3`` voxels gives 128, as
    TensoRF's float32 arithmetic does.
    """
    aabb = np.asarray(aabb, np.float64).reshape(2, 3)
    size = aabb[1] - aabb[0]
    voxel = (np.prod(size) / float(n_voxels)) ** (1.0 / 3.0)
    res = np.floor(size / voxel * (1.0 + 1e-5)).astype(np.int64)
    return tuple(int(max(r, 2)) for r in res)


def voxel_schedule(n_init: int, n_final: int, steps: Sequence[int]) -> list[int]:
    """Voxel counts after each upsampling step: log-linear from ``n_init`` to ``n_final``.

    TensoRF: ``round(exp(linspace(log(n_init), log(n_final), len(steps) + 1)))[1:]``.
    """
    counts = np.exp(np.linspace(math.log(n_init), math.log(n_final), len(steps) + 1))
    return [int(v) for v in np.round(counts).astype(np.int64)[1:]]


def n_samples_for(resolution: Sequence[int], step_ratio: float = 0.5) -> int:
    """Samples per ray for a grid resolution (TensoRF's cal_n_samples): ``int(|res| / step_ratio)``."""
    return int(np.linalg.norm(np.asarray(resolution, np.float64)) / step_ratio)


def step_size_for(aabb: Array | np.ndarray | Sequence, resolution: Sequence[int], step_ratio: float) -> float:
    """Ray-marching step in world units: ``mean(aabb size / (res - 1)) * step_ratio``."""
    aabb = np.asarray(aabb, np.float64).reshape(2, 3)
    units = (aabb[1] - aabb[0]) / (np.asarray(resolution, np.float64) - 1.0)
    return float(np.mean(units) * step_ratio)


# --------------------------------------------------------------------------------------------------
# Regularisers
# --------------------------------------------------------------------------------------------------


def l1_density(grid: VMGrid) -> Array:
    """TensoRF's density_L1: ``sum over modes of mean|plane| + mean|line|`` (a scalar)."""
    pairs = zip(grid["planes"], grid["lines"], strict=True)
    return sum(jnp.mean(jnp.abs(p)) + jnp.mean(jnp.abs(l)) for p, l in pairs)


def tv_plane(grid: VMGrid, scale: float = 1e-2) -> Array:
    """TensoRF's plane total variation, ``scale * sum over modes of TVLoss(plane)``.

    ``TVLoss(x) = 2 (mean (dx_a)^2 + mean (dx_b)^2)`` with the means over all differences of
    neighbours along each plane axis (and channels). TensoRF's ``TV_loss_density`` / ``TV_loss_app``
    multiply it by 1e-2 inside (the default ``scale``); the line term is not used there.
    """
    total = jnp.zeros((), jnp.float32)
    for p in grid["planes"]:
        da = jnp.mean(jnp.square(p[1:] - p[:-1]))
        db = jnp.mean(jnp.square(p[:, 1:] - p[:, :-1]))
        total = total + 2.0 * (da + db)
    return scale * total
