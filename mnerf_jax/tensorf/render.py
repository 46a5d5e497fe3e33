"""Volume rendering of a radiance field: compaction, compositing, colour (ray sampling: ``raymarch``).

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
evaluates densely (the reference path); compaction is several times faster than dense evaluation,
more so with the alpha mask (``scripts/bench_render.py``).

Points reach the field functions normalised to [-1, 1] over ``geometry.aabb``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from mnerf_jax.core.config import ModelConfig
from mnerf_jax.core.xla_cpu import jit_cpu_tuned
from mnerf_jax.tensorf import field, grids
from mnerf_jax.tensorf.raymarch import Geometry, alpha_mask_lookup, inside_box, sample_along_rays

Array = jax.Array
Params = Any

WEIGHT_THRESHOLD = 1e-4  # TensoRF's rayMarch_weight_thres

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


# --------------------------------------------------------------------------------------------------
# Compositing
# --------------------------------------------------------------------------------------------------


def exclusive_cumsum(x: Array, block: int = 16) -> Array:
    """Exclusive prefix sum along the last axis, ``y_i = Σ_{j<i} x_j``, by blocked matrix products.

    Within blocks of ``block`` samples the sum is a product with a strictly upper-triangular matrix,
    and block offsets another one. On XLA:CPU this is several times faster than ``jnp.cumsum`` (lowered
    to an associative scan whose fusion with the surrounding exps recomputes partial sums).
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
    product of ``1 - α + 1e-10`` up to that 1e-10. Forward+backward it is faster than ``composite_scan``
    and than this formula with ``jnp.cumsum`` (``scripts/bench_render.py``); training needs both passes,
    so this is the hot path; the scan is the reference.

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
    sums dominate on CPU).
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
    that need colour, rounded up to a chunk, not for its static budget: the colour count falls steeply
    over the first few hundred steps of a fit (and is 0 at first), while a smaller budget costs a
    compilation. Buffers of at most one chunk, or not a multiple of it, go in one call.
    """
    b = xyz.shape[0]
    if b <= chunk or b % chunk:
        return fns.colour(params, cond, xyz, viewdirs)
    n = b // chunk
    channels = colour_channels(fns, params, cond)

    def body(carry: None, part: tuple[Array, Array, Array]) -> tuple[None, Array]:
        x, v, i = part
        rgb = jax.lax.cond(
            i * chunk < count,
            jax.checkpoint(lambda: fns.colour(params, cond, x, v)),
            lambda: jnp.zeros((chunk, channels), xyz.dtype),
        )
        return carry, rgb

    parts = (xyz.reshape(n, chunk, 3), viewdirs.reshape(n, chunk, 3), jnp.arange(n, dtype=jnp.int32))
    return jax.lax.scan(body, None, parts)[1].reshape(b, channels)


def colour_channels(fns: FieldFns, params: Params, cond: Any) -> int:
    """Width of ``fns.colour``'s output: 3, or ``3K`` for a cond that renders K watermark IDs at once."""
    probe = jnp.zeros((1, 3), jnp.float32)
    return int(jax.eval_shape(lambda: fns.colour(params, cond, probe, probe)).shape[-1])


class Marched(NamedTuple):
    """Samples along rays with their compositing weights (:func:`march`)."""

    t: Array  # [R, N] sample distances
    viewdirs: Array  # [R, 3] unit directions
    weights: Array  # [R, N] compositing weights α·T
    density_count: Array  # samples inside the aabb and the alpha mask
    density_overflow: Array  # of them, dropped by the density budget (0 when none)
    dense_points: Callable[[], Array]  # () -> every sample, normalised, [R·N, 3]
    points_at: Callable[[Array], tuple[Array, Array]]  # flat indices [B] -> (points [B, 3], ray ids [B])


def march(
    fns: FieldFns,
    params: Params,
    rays_o: Array,
    rays_d: Array,
    geometry: Geometry,
    key: Array | None,
    density_budget: int | None,
) -> Marched:
    """Sample the rays (jittered when ``key`` is given), evaluate density where the sample is inside the
    aabb and the alpha mask (in a buffer of ``density_budget`` slots, or densely for ``None``) and
    composite the weights: the first half of :func:`render_rays`, shared with :func:`colour_samples`."""
    r = rays_o.shape[0]
    t, dists, viewdirs = sample_along_rays(rays_o, rays_d, geometry, key)
    n = t.shape[1]
    m = r * n
    xyz = rays_o[:, None, :] + rays_d[:, None, :] * t[..., None]  # [R, N, 3], fused into its uses
    valid = (inside_box(xyz, geometry.aabb) & alpha_mask_lookup(geometry, xyz)).reshape(m)
    scale = 2.0 / (geometry.aabb[1] - geometry.aabb[0])

    def dense_points() -> Array:
        return ((xyz - geometry.aabb[0]) * scale - 1.0).reshape(m, 3)

    def points_at(idx: Array) -> tuple[Array, Array]:
        """Normalised points ``[B, 3]`` and ray ids ``[B]`` of flat sample indices (clamped)."""
        idx = jnp.minimum(idx, m - 1)
        ray = idx // n
        t_s = grids.take_rows(t.reshape(m), idx)
        p = grids.take_rows(rays_o, ray) + grids.take_rows(rays_d, ray) * t_s[:, None]
        return (p - geometry.aabb[0]) * scale - 1.0, ray

    if density_budget is None:
        sigma = jnp.where(valid, fns.density(params, dense_points()), 0.0)
        density_count, density_overflow = jnp.sum(valid, dtype=jnp.int32), jnp.zeros((), jnp.int32)
    else:
        idx, density_count = compact(valid, density_budget)
        sigma_c = fns.density(params, points_at(idx)[0])
        sigma = add_rows(m + 1, idx, sigma_c, sorted_indices=True)[:m]
        density_overflow = jnp.maximum(density_count - density_budget, 0)
    weights, _ = composite_cumsum(sigma.reshape(r, n), dists, geometry.distance_scale)
    return Marched(t, viewdirs, weights, density_count, density_overflow, dense_points, points_at)


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
      ``rgb [R, 3]`` in [0, 1] (``[R, 3K]`` when ``fns.colour`` gives K colours per sample: several
      watermark IDs sharing one geometry pass), ``depth [R]`` (Σ w t), ``acc [R]`` (Σ w), ``density_count``,
      ``colour_count`` (samples that needed each evaluation), ``density_overflow``,
      ``colour_overflow`` (samples beyond the budget that were dropped; 0 when none).
    """
    mk = march(fns, params, rays_o, rays_d, geometry, key if train else None, density_budget)
    r, n = mk.t.shape
    m = r * n
    weights = mk.weights
    acc = jnp.sum(weights, -1)
    depth = jnp.sum(weights * mk.t, -1)
    density_count, density_overflow = mk.density_count, mk.density_overflow
    viewdirs, points_at = mk.viewdirs, mk.points_at
    zero = jnp.zeros((), jnp.int32)

    # Colour where the weight matters.
    significant = jax.lax.stop_gradient(weights > weight_threshold).reshape(m)
    if colour_budget is None:
        xyz_n = mk.dense_points()
        vd = jnp.broadcast_to(viewdirs[:, None, :], (r, n, 3)).reshape(m, 3)
        rgb_s = jnp.where(significant[:, None], fns.colour(params, cond, xyz_n, vd), 0.0)
        rgb = jnp.sum(weights[..., None] * rgb_s.reshape(r, n, -1), axis=1)
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
    if rgb.shape[-1] != bg.shape[-1]:  # K renders of 3 channels each (several watermark IDs at once)
        bg = jnp.tile(bg, (*(1,) * (bg.ndim - 1), rgb.shape[-1] // bg.shape[-1]))
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


@jit_cpu_tuned(static_argnums=(0,), static_argnames=("density_budget", "colour_budget", "weight_threshold"))
def colour_samples(
    fns: FieldFns,
    params: Params,
    rays_o: Array,
    rays_d: Array,
    geometry: Geometry,
    *,
    density_budget: int,
    colour_budget: int,
    weight_threshold: float = WEIGHT_THRESHOLD,
) -> dict[str, Array]:
    """The samples :func:`render_rays` (evaluation mode: no jitter) would colour, for a caller that colours
    them itself (``sample_cache``).

    Returns ``xyz [B, 3]`` (normalised), ``viewdirs [B, 3]``, ``ray [B]`` int32 (``R`` for padding),
    ``weight [B]`` (0 for padding), ``acc [R]`` (Σ w), with ``B = colour_budget``, and the counts and
    overflows of :func:`render_rays`. ``Σ_b weight_b · colour_b`` per ray, plus ``(1 − acc)·bg``, is
    ``render_rays``'s image.
    """
    mk = march(fns, params, rays_o, rays_d, geometry, None, density_budget)
    r, n = mk.t.shape
    m = r * n
    significant = jax.lax.stop_gradient(mk.weights > weight_threshold).reshape(m)
    idx, colour_count = compact(significant, colour_budget)
    xyz, ray = mk.points_at(idx)
    real = idx < m
    return {
        "xyz": xyz,
        "viewdirs": grids.take_rows(mk.viewdirs, ray),
        "ray": jnp.where(real, ray, r).astype(jnp.int32),
        "weight": jnp.where(real, grids.take_rows(mk.weights.reshape(m), jnp.minimum(idx, m - 1)), 0.0),
        "acc": jnp.sum(mk.weights, -1),
        "density_count": mk.density_count,
        "colour_count": colour_count,
        "density_overflow": mk.density_overflow,
        "colour_overflow": jnp.maximum(colour_count - colour_budget, 0),
    }
