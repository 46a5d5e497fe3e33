"""The fitted field's colour samples of every training view, computed once
(``watermark.schedule.cache_source``).

With the fitted TensoRF frozen, a watermarked render differs from the clean one only in what the watermark
adds to the colour MLP's last-layer logits (``watermark.film_logits``): the samples, their compositing
weights and the clean logits are the same at every step. So they are computed once per training view (the
density pass, the appearance grid and the MLP's hidden layers), and a step evaluates only the watermark
grid at the cached points, adds the K IDs' FiLM logits and composites (:func:`cached_render`). The embedding
step then holds no ray march, and its graph is a few buffers of the view's coloured samples, so the whole
view is rendered and differentiated at once (no deferred patches).

The samples are those of an evaluation render (no jitter), so a cached render equals
``render.render_rays(train=False)`` of the watermarked field (test). A frozen source is the design of
watermarks that add a branch to a fixed radiance field (CopyRNeRF); MultiNeRF itself lets the source adapt
at ``lr_source_scale`` of its rates.

    cache = build_cache(params, geometry, model_cfg, split.cameras)
    rgb = cached_render(params, cond, cache.view(v), wm_cfg, white_bg)   # [H·W, 3K]
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from mnerf_jax.core.config import ModelConfig, WatermarkConfig
from mnerf_jax.core.xla_cpu import jit_cpu_tuned
from mnerf_jax.data import camera_rays
from mnerf_jax.tensorf import budgets, field, render
from mnerf_jax.tensorf.raymarch import Geometry
from mnerf_jax.watermark import model as watermark
from mnerf_jax.watermark import run

Array = jax.Array

# Buffer sizes are multiples of this (padding rows have weight 0 and land in a discarded row).
_ROUND = 1024


@dataclasses.dataclass(frozen=True)
class SampleCache:
    """Per training view ``v``: ``xyz [V, B, 3]`` normalised points, ``logits [V, B, 3]`` the clean colour
    before its sigmoid, ``weight [V, B]`` compositing weights (0 on padding), ``ray [V, B]`` int32 ray of
    each sample (``R`` on padding), ``acc [V, R]`` each ray's Σ w; ``counts [V]`` real samples per view."""

    xyz: np.ndarray
    logits: np.ndarray
    weight: np.ndarray
    ray: np.ndarray
    acc: np.ndarray
    counts: np.ndarray

    def view(self, v: int) -> dict[str, np.ndarray]:
        """View ``v``'s buffers, as :func:`cached_render` reads them (``cache_*`` keys of a step's batch)."""
        return {
            "cache_xyz": self.xyz[v],
            "cache_logits": self.logits[v],
            "cache_weight": self.weight[v],
            "cache_ray": self.ray[v],
            "cache_acc": self.acc[v],
        }

    @property
    def nbytes(self) -> int:
        return sum(int(a.nbytes) for a in (self.xyz, self.logits, self.weight, self.ray, self.acc))


@jit_cpu_tuned(static_argnums=(0,))
def _clean_logits(model_cfg: ModelConfig, params: Any, xyz: Array, viewdirs: Array) -> Array:
    return field.colour_logits(params, xyz, viewdirs, model_cfg)


def view_samples(
    params: Any,
    geometry: Geometry,
    model_cfg: ModelConfig,
    rays_o: np.ndarray,
    rays_d: np.ndarray,
    sizes: list[int],
) -> dict[str, np.ndarray]:
    """One view's coloured samples (trimmed to their count) and ``acc [R]``. ``sizes``: the density and
    colour buffer sizes, grown in place until no sample is dropped (so the next view rarely recompiles)."""
    fns = render.tensorf_field_fns(model_cfg)
    o, d = jnp.asarray(rays_o), jnp.asarray(rays_d)
    while True:
        out = render.colour_samples(
            fns, params, o, d, geometry, density_budget=sizes[0], colour_budget=sizes[1]
        )
        dropped = int(out["density_overflow"]), int(out["colour_overflow"])
        if not any(dropped):
            break
        sizes[0] = budgets.ladder(int(out["density_count"])) if dropped[0] else sizes[0]
        sizes[1] = budgets.ladder(int(out["colour_count"])) if dropped[1] else sizes[1]
    n = int(out["colour_count"])
    logits = _clean_logits(model_cfg, params, out["xyz"], out["viewdirs"])
    return {
        "xyz": np.asarray(out["xyz"][:n]),
        "logits": np.asarray(logits[:n]),
        "weight": np.asarray(out["weight"][:n]),
        "ray": np.asarray(out["ray"][:n]),
        "acc": np.asarray(out["acc"]),
    }


def build_cache(
    params: Any, geometry: Geometry, model_cfg: ModelConfig, cameras: Any, progress: bool = False
) -> SampleCache:
    """Every view of ``cameras``, padded to one buffer size (static shapes: one compilation of the step)."""
    num_rays = int(np.prod(np.asarray(camera_rays(cameras, 0)[0]).shape[:-1]))
    sizes = [budgets.ladder(num_rays * 8), budgets.ladder(num_rays * 4)]
    views = []
    bar = tqdm(total=len(cameras), disable=not progress, desc="sample cache", unit="view", dynamic_ncols=True)
    try:
        for v in range(len(cameras)):
            o, d = camera_rays(cameras, v)
            views.append(view_samples(params, geometry, model_cfg, o, d, sizes))
            bar.update(1)
    finally:
        bar.close()
    counts = np.asarray([len(s["weight"]) for s in views], np.int64)
    size = max(-(-int(counts.max(initial=1)) // _ROUND) * _ROUND, _ROUND)

    def padded(name: str, fill: float | int) -> np.ndarray:
        first = views[0][name]
        out = np.full((len(views), size, *first.shape[1:]), fill, first.dtype)
        for i, s in enumerate(views):
            out[i, : len(s[name])] = s[name]
        return out

    cache = SampleCache(
        xyz=padded("xyz", 0.0),
        logits=padded("logits", 0.0),
        weight=padded("weight", 0.0),
        ray=padded("ray", num_rays),
        acc=np.stack([s["acc"] for s in views]),
        counts=counts,
    )
    if progress:
        most = int(counts.max(initial=0))
        tqdm.write(
            f"sample cache: {len(views)} views, at most {most:,} coloured samples a view ({size:,} "
            f"slots), {cache.nbytes / 2**20:.0f} MB"
        )
    return cache


def composite(view: dict[str, Array], rgb_s: Array, white_bg: bool) -> Array:
    """Per-sample colours ``rgb_s [B, C]`` of ``view``'s cached samples composited to ``[R, C]`` on the
    background (``C = 3K``: K renders side by side)."""
    weight, ray, acc = view["cache_weight"], view["cache_ray"], view["cache_acc"]
    r = acc.shape[0]
    rgb = render.add_rows(r + 1, ray, weight[:, None] * rgb_s, sorted_indices=True)[:r]
    bg = 1.0 if white_bg else 0.0
    return jnp.clip(rgb + (1.0 - acc)[:, None] * bg, 0.0, 1.0)


def cached_render(
    params: Any, cond: Any, view: dict[str, Array], cfg: WatermarkConfig, white_bg: bool
) -> jax.Array:
    """The view rendered with the K IDs of ``cond`` (:func:`watermark.condition_many`): ``rgb [R, 3K]``
    (ID ``k`` in columns ``3k:3k+3``), differentiable in the watermark's parameters; ``view``: the
    ``cache_*`` buffers of :meth:`SampleCache.view`."""
    xyz = view["cache_xyz"]
    logits = view["cache_logits"][:, None, :] + watermark.film_logits(params, cond, xyz, cfg)  # [B, K, 3]
    return composite(view, jax.nn.sigmoid(logits).reshape(xyz.shape[0], -1), white_bg)


def view_render_fn(
    cfg: WatermarkConfig, white_bg: bool, ids: Array, view: dict[str, Array]
) -> Callable[[Any, Any, Array], tuple[Array, dict[str, Array]]]:
    """The embedding step's render function (``deferred.RenderFn``) for a cached view: the whole view with
    the IDs ``ids [K]``, ``rgb [R, 3K]``; the rays and key it is given are not read (one patch covers the
    view, and the cached samples are not jittered)."""

    def render_fn(params: Any, rays: Any, key: Array) -> tuple[Array, dict[str, Array]]:
        del rays, key
        rgb = cached_render(params, watermark.condition_many(params, ids, cfg), view, cfg, white_bg)
        count = jnp.sum(view["cache_weight"] > 0, dtype=jnp.int32)
        return rgb, {"density_count": jnp.zeros((), jnp.int32), "colour_count": count}

    return render_fn


@functools.partial(jax.jit, static_argnums=(1,))
def _clean_render(view: dict[str, Array], white_bg: bool) -> Array:
    return composite(view, jax.nn.sigmoid(view["cache_logits"]), white_bg)


def clean_renders(cache: SampleCache, white_bg: bool) -> np.ndarray:
    """The fitted field's render of every cached view, ``[V, R, 3]`` float16 (``render_rays`` in
    evaluation mode, as ``embed_inputs.clean_references`` renders them, without a second ray march)."""
    views = [cache.view(v) for v in range(len(cache.counts))]
    return np.stack([np.asarray(_clean_render(v, white_bg)) for v in views]).astype(np.float16)


@functools.partial(jax.jit, static_argnums=(3, 4))
def _id_renders(
    params: Any, ids: Array, view: dict[str, Array], cfg: WatermarkConfig, white_bg: bool
) -> Array:
    return cached_render(params, watermark.condition_many(params, ids, cfg), view, cfg, white_bg)


def every_id_renders(
    cache: SampleCache,
    params: Any,
    cfg: WatermarkConfig,
    num_ids: int,
    white_bg: bool,
    ids_per_render: int = run.IDS_PER_RENDER,
) -> dict[int, np.ndarray]:
    """Every ID's render of every cached view, ``{ID: [V, R, 3]}`` float32, as ``run.render_every_id``
    renders them (evaluation mode) for a field whose source is the cached one, without a ray march."""
    out: dict[int, list[np.ndarray]] = {n: [] for n in range(num_ids)}
    for first in range(0, num_ids, ids_per_render):
        ids = jnp.arange(first, min(first + ids_per_render, num_ids), dtype=jnp.int32)
        for v in range(len(cache.counts)):
            rgb = np.asarray(_id_renders(params, ids, cache.view(v), cfg, white_bg))
            for k, n in enumerate(np.asarray(ids)):
                out[int(n)].append(rgb[:, 3 * k : 3 * k + 3])
    return {n: np.stack(images) for n, images in out.items()}
