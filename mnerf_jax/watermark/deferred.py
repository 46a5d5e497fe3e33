"""Deferred back-propagation over square patches (after ARF), for losses on a whole rendered image.

Render the full image without keeping the graph, take the gradient of the image-level loss with respect
to the image (and to ``extra``, e.g. decoder parameters), then re-render each patch under ``jax.vjp`` and
push the cached image gradient (plus a per-patch loss) back into the field parameters, accumulating over
patches.
Peak memory follows the patch size, not the image size. ``direct_objective`` is the reference that keeps
every patch on the graph.

    layout = patch_layout(H, W, S)            # square S×S patches covering the image (overlaps owned once)
    layout = whole_view_layout(H, W)          # or one patch of the whole H×W view (a cached source)
    loss, aux, image, g_params, g_extra = deferred_grad(render_fn, image_loss_fn, patch_loss_fn, params,
                                                        extra, rays, targets, layout.index, layout.owner,
                                                        key, H, W)
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

PyTree = Any
# render_fn(params, rays_patch, key) -> (rgb [R, 3], stats); rays_patch: a pytree of [R, ...] arrays; stats: a
# dict of scalars (sample counts) reduced by max over patches.
RenderFn = Callable[[PyTree, PyTree, jax.Array], tuple[jax.Array, dict[str, jax.Array]]]
# image_loss_fn(image [H, W, 3], extra) -> (loss, aux); extra: what else is differentiated (decoder params).
ImageLossFn = Callable[[jax.Array, PyTree], tuple[jax.Array, Any]]
# patch_loss_fn(rgb [S, S, 3], target [S, S, 3]) -> loss (a whole-view patch: [H, W, 3])
PatchLossFn = Callable[[jax.Array, jax.Array], jax.Array]


# ------------------------------------------------------------------------------------------ patch layout


@dataclasses.dataclass(frozen=True)
class PatchLayout:
    """Square patches covering an image, or one patch that is the whole (possibly non-square) view.

    ``index [P, S·S]`` int32: flat pixel index (``row·W + col``) of each patch pixel, row-major in the patch;
    ``owner [P, S·S]`` float32: 1 where this patch owns the pixel (every pixel has exactly one owner).
    ``size``: the square patches' side, or the shorter side of a whole-view patch (``index [1, H·W]``).
    """

    height: int
    width: int
    size: int
    index: np.ndarray
    owner: np.ndarray

    @property
    def num_patches(self) -> int:
        return int(self.index.shape[0])

    @property
    def rays(self) -> int:
        """Pixels (rays) of one patch."""
        return int(self.index.shape[1])


def _starts(n: int, size: int) -> list[int]:
    starts = list(range(0, n - size + 1, size))
    if starts[-1] + size < n:
        starts.append(n - size)  # last patch ends at the border; overlaps the one before
    return starts


def tiling_patch_size(height: int, width: int, max_size: int, min_size: int = 1) -> int:
    """The patch side ``<= max_size`` that covers ``height × width`` with the fewest square patches and the
    least overlap: ``ceil(n / max_size)`` patches per axis, each as small as that count allows, but not below
    ``min_size`` (a window the patch loss needs) unless ``max_size`` or the image already is.

    Every re-rendered pixel costs a ray march, so overlap is paid twice per step: 64-px patches on a
    100 × 100 image re-render 16,384 rays for 10,000 pixels; this gives 50-px patches (four, no overlap).
    """
    if height < 1 or width < 1 or max_size < 1:
        raise ValueError(f"tiling_patch_size needs positive sizes, got {height}x{width}, patch {max_size}")
    size = min(int(max_size), int(height), int(width))
    rows, cols = -(-height // size), -(-width // size)
    return max(-(-height // rows), -(-width // cols), min(int(min_size), size))


def patch_layout(height: int, width: int, patch_size: int) -> PatchLayout:
    """Cover ``height × width`` with square patches of side ``min(patch_size, height, width)``."""
    if height < 1 or width < 1 or patch_size < 1:
        raise ValueError(f"patch_layout needs positive sizes, got {height}x{width}, patch {patch_size}")
    size = min(int(patch_size), int(height), int(width))
    rows, cols = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
    index, owner = [], []
    owned = np.zeros(height * width, bool)
    for r0 in _starts(height, size):
        for c0 in _starts(width, size):
            flat = ((r0 + rows) * width + (c0 + cols)).reshape(-1)
            mine = ~owned[flat]
            owned[flat] = True
            index.append(flat)
            owner.append(mine)
    assert owned.all()
    return PatchLayout(
        height=int(height),
        width=int(width),
        size=size,
        index=np.stack(index).astype(np.int32),
        owner=np.stack(owner).astype(np.float32),
    )


def whole_view_layout(height: int, width: int) -> PatchLayout:
    """One patch of the whole ``height × width`` view, row-major (a cached source renders a view at once)."""
    if height < 1 or width < 1:
        raise ValueError(f"whole_view_layout needs positive sizes, got {height}x{width}")
    return PatchLayout(
        height=int(height),
        width=int(width),
        size=min(int(height), int(width)),
        index=np.arange(height * width, dtype=np.int32)[None],
        owner=np.ones((1, height * width), np.float32),
    )


def patch_shape(layout_index: jax.Array | np.ndarray, height: int, width: int) -> tuple[int, int]:
    """The (rows, columns) of the patches of ``layout_index [P, R]``: the view's for a whole-view patch
    (``R = H·W``), else square."""
    n, pixels = layout_index.shape
    if n == 1 and pixels == height * width:
        return int(height), int(width)
    side = int(round(pixels**0.5))
    return side, side


def gather_rays(rays: PyTree, index: jax.Array) -> PyTree:
    """Rays of the pixels ``index [...]`` from a pytree of ``[H·W, ...]`` arrays."""
    return jax.tree.map(lambda r: r[index], rays)


def assemble(
    rgb_patches: jax.Array, index: jax.Array, owner: jax.Array, height: int, width: int
) -> jax.Array:
    """``rgb_patches [P, S·S, C]`` → image ``[H, W, C]`` from each pixel's owning patch."""
    channels = rgb_patches.shape[-1]
    flat = jnp.zeros((height * width, channels), rgb_patches.dtype)
    flat = flat.at[index.reshape(-1)].add((rgb_patches * owner[..., None]).reshape(-1, channels))
    return flat.reshape(height, width, channels)


def patch_keys(key: jax.Array, num_patches: int) -> jax.Array:
    """One PRNG key per patch (shared by the graph-free render and the re-render)."""
    return jax.random.split(key, num_patches)


# ------------------------------------------------------------------------------------------- rendering


def materialised(cotangent: jax.Array) -> jax.Array:
    """``cotangent [R, C]`` computed once into memory before a render's pullback reads it. The pullback
    gathers each sample's ray from it; left free, XLA fuses the image loss's whole gradient into that
    per-sample gather and recomputes it for every sample of the ray. XLA:CPU fuses through reductions and
    drops optimisation barriers, but never fuses a matrix product into its consumer: the product with the
    identity (exact for finite values) is the barrier, at ``R·C²`` multiply-adds."""
    return cotangent @ jnp.eye(cotangent.shape[-1], dtype=cotangent.dtype)


def render_patches(
    render_fn: RenderFn, params: PyTree, rays: PyTree, index: jax.Array, keys: jax.Array
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Render every patch, one at a time (``lax.map``): ``([P, S·S, 3], stats [P])``; no graph is kept."""

    def one(args: tuple[jax.Array, jax.Array]) -> tuple[jax.Array, dict[str, jax.Array]]:
        idx, k = args
        return render_fn(params, gather_rays(rays, idx), k)

    return jax.lax.map(one, (index, keys))


def _max_stats(stats: dict[str, jax.Array]) -> dict[str, jax.Array]:
    return {k: jnp.max(v) for k, v in stats.items()}


def render_image(
    render_fn: RenderFn,
    params: PyTree,
    rays: PyTree,
    layout_index: jax.Array,
    layout_owner: jax.Array,
    key: jax.Array,
    height: int,
    width: int,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Graph-free full render ``[H, W, 3]`` through the patch layout (memory of one patch), and the largest
    per-patch render stats."""
    keys = patch_keys(key, layout_index.shape[0])
    rgb, stats = render_patches(render_fn, jax.lax.stop_gradient(params), rays, layout_index, keys)
    return assemble(rgb, layout_index, layout_owner, height, width), _max_stats(stats)


# ------------------------------------------------------------------------------------------ objectives


def _patch_term(
    patch_loss_fn: PatchLossFn | None, rgb: jax.Array, target: jax.Array, shape: tuple[int, int]
) -> jax.Array:
    if patch_loss_fn is None:
        return jnp.zeros((), jnp.float32)
    return patch_loss_fn(rgb.reshape(*shape, -1), target.reshape(*shape, -1))


def direct_objective(
    render_fn: RenderFn,
    image_loss_fn: ImageLossFn,
    patch_loss_fn: PatchLossFn | None,
    params: PyTree,
    extra: PyTree,
    rays: PyTree,
    targets: jax.Array,
    layout_index: jax.Array,
    layout_owner: jax.Array,
    key: jax.Array,
    height: int,
    width: int,
) -> tuple[jax.Array, Any]:
    """``L(θ, φ)`` computed with every patch render on the graph (reference; memory grows with the image).

    ``targets [H·W, 3]``: ground-truth pixels for the patch loss. Returns ``(loss, aux)``.
    """
    n = layout_index.shape[0]
    shape = patch_shape(layout_index, height, width)
    keys = patch_keys(key, n)
    rgb, _ = jax.vmap(lambda idx, k: render_fn(params, gather_rays(rays, idx), k))(layout_index, keys)
    image = assemble(rgb, layout_index, layout_owner, height, width)
    loss_img, aux = image_loss_fn(image, extra)
    patch = jax.vmap(lambda r, idx: _patch_term(patch_loss_fn, r, targets[idx], shape))(rgb, layout_index)
    return loss_img + patch.sum(), aux


def deferred_grad(
    render_fn: RenderFn,
    image_loss_fn: ImageLossFn,
    patch_loss_fn: PatchLossFn | None,
    params: PyTree,
    extra: PyTree,
    rays: PyTree,
    targets: jax.Array,
    layout_index: jax.Array,
    layout_owner: jax.Array,
    key: jax.Array,
    height: int,
    width: int,
) -> tuple[jax.Array, Any, jax.Array, PyTree, PyTree]:
    """``L`` and its gradients by deferred back-propagation; peak memory follows the patch size.

    Args:
      render_fn: ``(params, rays [R, ...], key) -> (rgb [R, 3], stats)``, per-ray independent.
      image_loss_fn: ``(image [H, W, 3], extra) -> (loss, aux)``.
      patch_loss_fn: ``(rgb [S, S, 3], target [S, S, 3]) -> loss`` or None.
      rays: pytree of ``[H·W, ...]`` arrays; targets: ``[H·W, 3]`` ground truth.
      layout_index, layout_owner: ``PatchLayout.index`` / ``.owner`` as arrays.
    Returns:
      ``(loss, aux, image [H, W, 3], grad_params, grad_extra)``; ``aux`` is the image loss's aux plus
      ``"render_stats"`` (largest per-patch render stats).
    """
    n = layout_index.shape[0]
    shape = patch_shape(layout_index, height, width)
    keys = patch_keys(key, n)
    image_grad = jax.value_and_grad(image_loss_fn, argnums=(0, 1), has_aux=True)
    if n == 1:
        # One patch covers the view: the graph-free render would only repeat that patch's forward pass,
        # so render once on the graph and pull the image gradient back through it (the same gradient, one
        # render fewer).
        idx, k = layout_index[0], keys[0]
        render_view = lambda p: render_fn(p, gather_rays(rays, idx), k)
        rgb, pullback, stats = jax.vjp(render_view, params, has_aux=True)  # one patch: its stats are the max
        image = assemble(rgb[None], layout_index, layout_owner, height, width)
        (loss_img, aux), (g_image, g_extra) = image_grad(image, extra)
        cot = g_image.reshape(height * width, -1)[idx] * layout_owner[0][:, None]
        loss_p, g_rgb = jax.value_and_grad(lambda r: _patch_term(patch_loss_fn, r, targets[idx], shape))(rgb)
        (grads,) = pullback(materialised((cot + g_rgb).astype(rgb.dtype)))
        return _deferred_result(loss_img, aux, loss_p, stats, image, grads, g_extra)
    image, stats = render_image(render_fn, params, rays, layout_index, layout_owner, key, height, width)
    (loss_img, aux), (g_image, g_extra) = image_grad(image, extra)
    # The image gradient of a pixel is pushed back once, through its owning patch.
    cotangents = g_image.reshape(height * width, -1)[layout_index] * layout_owner[..., None]

    Carry = tuple[PyTree, jax.Array]

    def body(carry: Carry, xs: tuple[jax.Array, ...]) -> tuple[Carry, None]:
        # One patch: re-render with a graph, pull back the cached image gradient plus the patch loss.
        acc, loss_patches = carry
        idx, cot, k = xs
        target = targets[idx]
        rgb, pullback, _ = jax.vjp(lambda p: render_fn(p, gather_rays(rays, idx), k), params, has_aux=True)
        loss_p, g_rgb = jax.value_and_grad(lambda r: _patch_term(patch_loss_fn, r, target, shape))(rgb)
        (g_params,) = pullback((cot + g_rgb).astype(rgb.dtype))
        return (jax.tree.map(jnp.add, acc, g_params), loss_patches + loss_p), None

    zeros = jax.tree.map(jnp.zeros_like, params)
    (grads, loss_patches), _ = jax.lax.scan(
        body, (zeros, jnp.zeros((), jnp.float32)), (layout_index, cotangents, keys)
    )
    return _deferred_result(loss_img, aux, loss_patches, stats, image, grads, g_extra)


def _deferred_result(
    loss_img: jax.Array,
    aux: Any,
    loss_patches: jax.Array,
    stats: dict[str, jax.Array],
    image: jax.Array,
    grads: PyTree,
    g_extra: PyTree,
) -> tuple[jax.Array, Any, jax.Array, PyTree, PyTree]:
    """``deferred_grad``'s return value: the image loss's aux plus the largest per-patch render stats and
    both loss parts."""
    aux = dict(aux) if isinstance(aux, dict) else {"image_aux": aux}
    aux["render_stats"] = stats
    aux["loss_image"] = loss_img
    aux["loss_patch"] = loss_patches
    return loss_img + loss_patches, aux, image, grads, g_extra


# ==========================================================================================================
