"""Volume rendering of a radiance field: ray sampling, alpha mask, compaction, compositing, images.

Pipeline of ``render_rays`` (all shapes static under ``jax.jit``)::

    rays -> samples t [R, N] (TensoRF's sample_ray / sample_ray_ndc)
         -> valid = inside aabb & alpha mask
         -> compact valid samples into a density buffer of ``density_budget`` slots -> σ
         -> weights = α T (cumulative-sum compositing)
         -> compact samples with weight > ``weight_threshold`` into ``colour_budget`` slots -> rgb
         -> rgb, depth, acc per ray (+ background), counters of the budgets' use and overflow

Compaction: JAX needs static shapes, so skipping empty space or negligible samples only saves work if
the surviving samples are gathered into a fixed-size buffer (``compact``: the positions of the True
entries, like ``jnp.nonzero(mask, size=budget)`` but faster on CPU), evaluated there and scattered
back. A budget smaller than the count drops the excess samples (the
last in ray-major order) and reports ``*_overflow > 0``; ``budgets.BudgetPolicy`` and
``chunked.render_rays_exact`` pick budgets that grow on overflow and re-run, so no sample is silently lost.
Whole images: ``chunked.render_image``; the alpha mask itself, the aabb shrink and ray filtering:
``alpha_mask``. A budget of ``None``
evaluates densely (the reference path).

Measured with ``scripts/bench_render.py`` (VM-192 field at 128^3 that is empty except an opaque ball,
4096 rays x 443 samples, 2-core CPU shared with other jobs, best of 3): compaction vs dense evaluation
was 5.5x faster for a training step and 7.7x for evaluation without the alpha mask, and 12x / 20x
with it (where dense evaluation gains nothing from the mask).

Points reach the field functions normalised to [-1, 1] over ``geometry.aabb``.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Mapping
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from mnerf_jax import field, grids
from mnerf_jax.config import ModelConfig

Array = jax.Array
Params = Any

WEIGHT_THRESHOLD = 1e-4  # TensoRF's rayMarch_weight_thres

# XLA:CPU (jax 0.10) hands elementwise+reduce subgraphs to YNNPACK fusions, which materialise every
# gathered [P, C] operand: the density forward of 1 M points took ~1.5 s instead of ~35 ms, and
# evaluation-mode render_rays (4096 rays, 128^3, alpha mask) 440 ms instead of 215 ms; training steps
# were about equally fast either way. Disabling them per compilation restores XLA's own fused loops.
_CPU_OPTIONS = {"xla_cpu_experimental_ynn_fusion_type": ""}


@functools.cache
def xla_compiler_options() -> dict[str, str]:
    """Compiler options for ``jax.jit(..., compiler_options=...)`` of rendering code.

    On CPU, the options that keep XLA from routing sampled-feature arithmetic through YNNPACK
    fusions, if this XLA accepts them; ``{}`` elsewhere. Pass them to the ``jax.jit`` of any function
    that calls ``render_rays`` (the options of an inner jit are ignored when it is inlined).
    """
    if jax.default_backend() != "cpu":
        return {}
    try:
        jax.jit(lambda x: x + 1, compiler_options=_CPU_OPTIONS).lower(jnp.zeros(2)).compile()
    except Exception:  # an XLA without this option: keep its defaults
        return {}
    return dict(_CPU_OPTIONS)


def jit_cpu_tuned(fun: Callable | None = None, **kwargs: Any) -> Any:
    """``jax.jit`` with ``xla_compiler_options()`` when called at top level (chosen at the first call).

    Inside another transformation (arguments are tracers) the plain ``jax.jit`` is used: JAX accepts
    compiler options only on the outermost jit, whose owner should pass ``xla_compiler_options()``.
    """
    if fun is None:
        return functools.partial(jit_cpu_tuned, **kwargs)
    plain = jax.jit(fun, **kwargs)
    top: list[Callable] = []

    @functools.wraps(fun)
    def wrapper(*args: Any, **kw: Any) -> Any:
        if any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves((args, kw))):
            return plain(*args, **kw)
        if not top:
            top.append(jax.jit(fun, compiler_options=xla_compiler_options(), **kwargs))
        return top[0](*args, **kw)

    return wrapper


# --------------------------------------------------------------------------------------------------
# Field functions and geometry
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class FieldFns:
    """The field as two pure functions (static and hashable, so it can be a static jit argument).

    ``density(params, xyz [P, 3]) -> σ [P]`` and ``colour(params, cond, xyz [P, 3], viewdirs [P, 3])
    -> rgb [P, 3]`` with ``xyz`` normalised to [-1, 1] over the aabb and unit ``viewdirs``. ``cond`` is
    any pytree the colour function reads (``None`` for plain TensoRF). Use hashable callables that
    compare by value (frozen dataclasses, module-level functions) so equal fields share compilations.
    """

    density: Callable[[Params, Array], Array]
    colour: Callable[[Params, Any, Array, Array], Array]


@dataclasses.dataclass(frozen=True)
class TensorfDensity:
    """TensoRF's density ``σ(xyz) [P]``; shared by every field (the watermark leaves density alone)."""

    cfg: ModelConfig

    def __call__(self, params: Params, xyz: Array) -> Array:
        return field.density(params, xyz, self.cfg)


@dataclasses.dataclass(frozen=True)
class _TensorfColour:
    cfg: ModelConfig

    def __call__(self, params: Params, cond: Any, xyz: Array, viewdirs: Array) -> Array:
        del cond
        return field.colour(params, xyz, viewdirs, self.cfg)


def tensorf_field_fns(model_cfg: ModelConfig) -> FieldFns:
    """FieldFns of the plain TensoRF backbone (``cond`` is ignored)."""
    return FieldFns(density=TensorfDensity(model_cfg), colour=_TensorfColour(model_cfg))


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


# --------------------------------------------------------------------------------------------------
# Compositing
# --------------------------------------------------------------------------------------------------


def exclusive_cumsum(x: Array, block: int = 16) -> Array:
    """Exclusive prefix sum along the last axis, ``y_i = Σ_{j<i} x_j``, by blocked matrix products.

    Within blocks of ``block`` samples the sum is a product with a strictly upper-triangular matrix,
    and block offsets another one. On XLA:CPU this was 5-10x faster than ``jnp.cumsum`` (lowered to
    an associative scan whose fusion with the surrounding exps recomputes partial sums).
    """
    *lead, n = x.shape
    nb = -(-n // block)
    xb = jnp.pad(x.reshape(-1, n), ((0, 0), (0, nb * block - n))).reshape(-1, nb, block)
    hi = jax.lax.Precision.HIGHEST  # full float32 on accelerators too
    within = jnp.matmul(xb, jnp.triu(jnp.ones((block, block), x.dtype), 1), precision=hi)
    offsets = jnp.matmul(jnp.sum(xb, -1), jnp.triu(jnp.ones((nb, nb), x.dtype), 1), precision=hi)
    return (within + offsets[..., None]).reshape(-1, nb * block)[:, :n].reshape(*lead, n)


def composite_cumsum(sigma: Array, dists: Array, distance_scale: Array | float) -> tuple[Array, Array]:
    """Weights and transmittance from a prefix sum of optical depth (the hot path).

    ``τ = σ Δt s``, ``T_i = exp(-Σ_{j<i} τ_j)``, ``w_i = (1 - exp(-τ_i)) T_i``: TensoRF's cumulative
    product of ``1 - α + 1e-10`` up to that 1e-10. On the 2-core CPU, 4096 x 443 samples,
    forward+backward: 14.5 ms against 56 ms for ``composite_scan`` (forward alone 6.3 vs 3.1 ms), and
    25-40 ms for this formula with ``jnp.cumsum`` (``scripts/bench_render.py``, best of 5 on a shared
    machine). Training needs both passes, so this is the hot path; the scan is the reference.

    Args:
      sigma: ``[R, N]`` densities (>= 0).
      dists: ``[R, N]`` sample lengths (world units).
      distance_scale: scalar factor on σ Δt.

    Returns:
      ``(weights [R, N], transmittance [R, N])``, transmittance before each sample.
    """
    # Capped so an infinite σ cannot turn the block products (0 x inf) into NaN; exp(-1e4) is 0.
    tau = jnp.minimum(sigma * dists * distance_scale, 1e4)
    trans = jnp.exp(-exclusive_cumsum(tau))
    return -jnp.expm1(-tau) * trans, trans


def composite_scan(sigma: Array, dists: Array, distance_scale: Array | float) -> tuple[Array, Array]:
    """Reference compositing with ``lax.scan`` over samples: TensoRF's raw2alpha literally.

    ``α = 1 - exp(-σ Δt s)``, ``T`` = exclusive cumulative product of ``1 - α + 1e-10``, ``w = α T``.
    Same signature and results as ``composite_cumsum``.
    """
    alpha = 1.0 - jnp.exp(-sigma * dists * distance_scale)

    def step(t_acc: Array, a: Array) -> tuple[Array, tuple[Array, Array]]:
        return t_acc * (1.0 - a + 1e-10), (a * t_acc, t_acc)

    t0 = jnp.ones(sigma.shape[:-1], sigma.dtype)
    _, (weights, trans) = jax.lax.scan(step, t0, jnp.moveaxis(alpha, -1, 0))
    return jnp.moveaxis(weights, 0, -1), jnp.moveaxis(trans, 0, -1)


# --------------------------------------------------------------------------------------------------
# Compaction
# --------------------------------------------------------------------------------------------------


def _inclusive_count(mask: Array, block: int = 128) -> Array:
    """``[M]`` int32 inclusive running count of a flat bool mask (blocked, see ``exclusive_cumsum``)."""
    m = mask.shape[0]
    nb = -(-m // block)
    xb = jnp.pad(mask.astype(jnp.float32), (0, nb * block - m)).reshape(nb, block)
    # Counts within a block are small integers: exact in float32.
    within = jnp.matmul(
        xb, jnp.triu(jnp.ones((block, block), jnp.float32)), precision=jax.lax.Precision.HIGHEST
    ).astype(jnp.int32)
    totals = within[:, -1]
    offsets = jnp.cumsum(totals) - totals
    return (within + offsets[:, None]).reshape(-1)[:m]


def add_rows(size: int, idx: Array, updates: Array, sorted_indices: bool = False) -> Array:
    """``zeros([size, ...]).at[idx].add(updates)`` for in-range indices (linear; transpose: a gather)."""
    dnums = jax.lax.ScatterDimensionNumbers(
        update_window_dims=tuple(range(1, updates.ndim)),
        inserted_window_dims=(0,),
        scatter_dims_to_operand_dims=(0,),
    )
    zeros = jnp.zeros((size, *updates.shape[1:]), updates.dtype)
    return jax.lax.scatter_add(
        zeros,
        idx[:, None],
        updates,
        dnums,
        indices_are_sorted=sorted_indices,
        mode=jax.lax.GatherScatterMode.PROMISE_IN_BOUNDS,
    )


def compact(mask: Array, budget: int) -> tuple[Array, Array]:
    """Positions of the True entries of a flat ``mask [M]`` in a static buffer.

    Returns ``(idx [budget] int32, count)``: the first ``budget`` True positions in increasing order,
    padded with ``M`` (one past the end: clamp before gathering, scatter into ``M + 1`` slots), and the
    number of True entries. A running count and one scatter (no ``jnp.nonzero``, whose cumulative
    sums dominated on CPU: ~40 ms vs ~5 ms for 1.8 M entries).
    """
    m = mask.shape[0]
    count = _inclusive_count(mask)
    target = jnp.where(mask, jnp.minimum(count - 1, budget), budget)  # slot `budget` collects the rest
    dnums = jax.lax.ScatterDimensionNumbers(
        update_window_dims=(), inserted_window_dims=(0,), scatter_dims_to_operand_dims=(0,)
    )
    idx = jax.lax.scatter(
        jnp.full((budget + 1,), m, jnp.int32),
        target[:, None],
        jnp.arange(m, dtype=jnp.int32),
        dnums,
        mode=jax.lax.GatherScatterMode.PROMISE_IN_BOUNDS,
    )
    return idx[:budget], count[-1]


# Colour slots per chunk of ``colour_in_chunks``.
COLOUR_CHUNK = 1 << 16


def colour_in_chunks(
    fns: FieldFns,
    params: Params,
    cond: Any,
    xyz: Array,
    viewdirs: Array,
    count: Array,
    chunk: int = COLOUR_CHUNK,
) -> Array:
    """``fns.colour`` over a compacted buffer ``[B, 3]`` whose first ``count`` rows are real samples.

    The buffer is evaluated in chunks of ``chunk`` rows (``lax.scan``), and a chunk past ``count``
    holds only padding: ``lax.cond`` skips it, forward and backward. So a step pays for the samples
    that need colour, rounded up to a chunk, not for its static budget: the colour count falls ~8x
    over the first few hundred steps of a fit (and is 0 for the first ~20), while a smaller budget
    costs a compilation. Buffers of at most one chunk, or not a multiple of it, go in one call.
    """
    b = xyz.shape[0]
    if b <= chunk or b % chunk:
        return fns.colour(params, cond, xyz, viewdirs)
    n = b // chunk

    def body(carry: None, part: tuple[Array, Array, Array]) -> tuple[None, Array]:
        x, v, i = part
        rgb = jax.lax.cond(
            i * chunk < count,
            jax.checkpoint(lambda: fns.colour(params, cond, x, v)),
            lambda: jnp.zeros((chunk, 3), xyz.dtype),
        )
        return carry, rgb

    parts = (xyz.reshape(n, chunk, 3), viewdirs.reshape(n, chunk, 3), jnp.arange(n, dtype=jnp.int32))
    return jax.lax.scan(body, None, parts)[1].reshape(b, 3)


# --------------------------------------------------------------------------------------------------
# render_rays
# --------------------------------------------------------------------------------------------------


@jit_cpu_tuned(
    static_argnums=(0,), static_argnames=("train", "density_budget", "colour_budget", "weight_threshold")
)
def render_rays(
    fns: FieldFns,
    params: Params,
    cond: Any,
    rays_o: Array,
    rays_d: Array,
    geometry: Geometry,
    key: Array | None,
    *,
    train: bool,
    density_budget: int | None,
    colour_budget: int | None,
    bg: Array | None = None,
    weight_threshold: float = WEIGHT_THRESHOLD,
) -> dict[str, Array]:
    """Render rays through the field (differentiable w.r.t. ``params`` and ``cond``).

    Args:
      fns: the field's density and colour functions (static).
      params: field parameters (any pytree ``fns`` reads).
      cond: conditioning pytree passed to ``fns.colour`` (``None`` for TensoRF).
      rays_o, rays_d: ``[R, 3]`` origins and directions (unit for bounded scenes; NDC rays otherwise).
      geometry: aabb, alpha mask, step and sample count.
      key: PRNG key for the per-ray sample jitter; used only when ``train``.
      train: jitter the samples (TensoRF's is_train).
      density_budget: static number of density slots; ``None`` evaluates every sample.
      colour_budget: static number of colour slots; ``None`` evaluates every sample.
      bg: optional background colour, ``[3]`` or per ray ``[R, 3]``; default white or black from
        ``geometry.white_bg``.
      weight_threshold: colour is evaluated only where the weight exceeds this.

    Returns:
      ``rgb [R, 3]`` in [0, 1], ``depth [R]`` (Σ w t), ``acc [R]`` (Σ w), ``density_count``,
      ``colour_count`` (samples that needed each evaluation), ``density_overflow``,
      ``colour_overflow`` (samples beyond the budget that were dropped; 0 when none).
    """
    r = rays_o.shape[0]
    t, dists, viewdirs = sample_along_rays(rays_o, rays_d, geometry, key if train else None)
    n = t.shape[1]
    m = r * n
    xyz = rays_o[:, None, :] + rays_d[:, None, :] * t[..., None]  # [R, N, 3], fused into its uses
    valid = (inside_box(xyz, geometry.aabb) & alpha_mask_lookup(geometry, xyz)).reshape(m)
    scale = 2.0 / (geometry.aabb[1] - geometry.aabb[0])
    zero = jnp.zeros((), jnp.int32)

    def points_at(idx: Array) -> tuple[Array, Array]:
        """Normalised points ``[B, 3]`` and ray ids ``[B]`` of flat sample indices (clamped)."""
        idx = jnp.minimum(idx, m - 1)
        ray = idx // n
        t_s = grids.take_rows(t.reshape(m), idx)
        p = grids.take_rows(rays_o, ray) + grids.take_rows(rays_d, ray) * t_s[:, None]
        return (p - geometry.aabb[0]) * scale - 1.0, ray

    # Density where the sample is inside the aabb and the alpha mask.
    if density_budget is None:
        xyz_n = ((xyz - geometry.aabb[0]) * scale - 1.0).reshape(m, 3)
        sigma = jnp.where(valid, fns.density(params, xyz_n), 0.0)
        density_count, density_overflow = jnp.sum(valid, dtype=jnp.int32), zero
    else:
        idx, density_count = compact(valid, density_budget)
        sigma_c = fns.density(params, points_at(idx)[0])
        sigma = add_rows(m + 1, idx, sigma_c, sorted_indices=True)[:m]
        density_overflow = jnp.maximum(density_count - density_budget, 0)
    weights, _ = composite_cumsum(sigma.reshape(r, n), dists, geometry.distance_scale)
    acc = jnp.sum(weights, -1)
    depth = jnp.sum(weights * t, -1)

    # Colour where the weight matters.
    significant = jax.lax.stop_gradient(weights > weight_threshold).reshape(m)
    if colour_budget is None:
        xyz_n = ((xyz - geometry.aabb[0]) * scale - 1.0).reshape(m, 3)
        vd = jnp.broadcast_to(viewdirs[:, None, :], (r, n, 3)).reshape(m, 3)
        rgb_s = jnp.where(significant[:, None], fns.colour(params, cond, xyz_n, vd), 0.0)
        rgb = jnp.sum(weights[..., None] * rgb_s.reshape(r, n, 3), axis=1)
        colour_count, colour_overflow = jnp.sum(significant, dtype=jnp.int32), zero
    else:
        idx, colour_count = compact(significant, colour_budget)
        xyz_c, ray = points_at(idx)
        rgb_c = colour_in_chunks(fns, params, cond, xyz_c, grids.take_rows(viewdirs, ray), colour_count)
        w_c = jnp.where(idx < m, grids.take_rows(weights.reshape(m), jnp.minimum(idx, m - 1)), 0.0)
        ray = jnp.where(idx < m, ray, r)  # padding slots land in a discarded row
        rgb = add_rows(r + 1, ray, w_c[:, None] * rgb_c, sorted_indices=True)[:r]
        colour_overflow = jnp.maximum(colour_count - colour_budget, 0)

    if bg is None:
        bg = jnp.ones((3,), rgb.dtype) if geometry.white_bg else jnp.zeros((3,), rgb.dtype)
    rgb = jnp.clip(rgb + (1.0 - acc)[:, None] * bg, 0.0, 1.0)
    return {
        "rgb": rgb,
        "depth": depth,
        "acc": acc,
        "density_count": density_count,
        "colour_count": colour_count,
        "density_overflow": density_overflow,
        "colour_overflow": colour_overflow,
    }
