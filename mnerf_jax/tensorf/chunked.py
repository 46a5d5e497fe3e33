"""Rendering whole images (and ray sets) chunk by chunk with sample budgets that grow on overflow.

``render.render_rays`` compacts samples into static buffers that may drop samples when too small; here
every call takes its budgets from a ``budgets.BudgetPolicy`` and is re-run with grown budgets until nothing is
dropped, so evaluation renders are exact.
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import numpy as np

from mnerf_jax.tensorf.budgets import BudgetPolicy
from mnerf_jax.tensorf.raymarch import Geometry
from mnerf_jax.tensorf.render import Array, FieldFns, Params, render_rays


def render_rays_exact(
    fns: FieldFns,
    params: Params,
    cond: Any,
    rays_o: Array,
    rays_d: Array,
    geometry: Geometry,
    key: Array | None,
    *,
    train: bool,
    policy: BudgetPolicy,
    site: str = "render",
    bg: Array | None = None,
) -> dict[str, Array]:
    """``render_rays`` with budgets from ``policy``, re-run with grown budgets until nothing is dropped."""
    n_rays, n_samples = rays_o.shape[0], geometry.n_samples
    while True:
        db, cb = policy.budgets(site, n_rays, n_samples)
        out = render_rays(
            fns,
            params,
            cond,
            rays_o,
            rays_d,
            geometry,
            key,
            train=train,
            density_budget=db,
            colour_budget=cb,
            bg=bg,
        )
        if not policy.update(site, out, n_rays, n_samples):
            return out


def render_image(
    fns: FieldFns,
    params: Params,
    cond: Any,
    rays_o: Array,
    rays_d: Array,
    geometry: Geometry,
    height: int,
    width: int,
    *,
    chunk: int = 4096,
    policy: BudgetPolicy | None = None,
    bg: Array | None = None,
) -> dict[str, np.ndarray]:
    """Render ``height x width`` rays (``[H*W, 3]`` each, row-major) in evaluation mode, chunk by chunk.

    Each chunk of ``chunk`` rays is one jitted call with static shapes (the last chunk is padded by
    repeating its last ray); no gradient is built. Overflowing chunks are re-rendered with grown
    budgets, so no sample is dropped.

    Returns numpy ``rgb [H, W, 3]`` (``[H, W, 3K]`` for a cond of K watermark IDs), ``depth [H, W]``,
    ``acc [H, W]``.
    """
    policy = BudgetPolicy() if policy is None else policy
    total = rays_o.shape[0]
    if total != height * width:
        raise ValueError(f"{total} rays for a {height}x{width} image")
    chunk = min(chunk, total)
    rays_o = jnp.asarray(rays_o, jnp.float32)
    rays_d = jnp.asarray(rays_d, jnp.float32)
    bg_arr = None if bg is None else jnp.asarray(bg, jnp.float32)
    per_ray_bg = bg_arr is not None and bg_arr.ndim == 2
    outs: dict[str, list[np.ndarray]] = {"rgb": [], "depth": [], "acc": []}
    for start in range(0, total, chunk):
        stop = min(start + chunk, total)
        sl = np.minimum(np.arange(start, start + chunk), stop - 1)  # pad by repeating the last ray
        o, d = rays_o[sl], rays_d[sl]
        b = bg_arr[sl] if per_ray_bg else bg_arr
        out = render_rays_exact(
            fns, params, cond, o, d, geometry, None, train=False, policy=policy, site="render_image", bg=b
        )
        for name in outs:
            outs[name].append(np.asarray(out[name])[: stop - start])
    return {
        "rgb": np.concatenate(outs["rgb"]).reshape(height, width, -1),
        "depth": np.concatenate(outs["depth"]).reshape(height, width),
        "acc": np.concatenate(outs["acc"]).reshape(height, width),
    }
