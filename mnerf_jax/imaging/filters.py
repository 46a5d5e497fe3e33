"""Deterministic, differentiable image filters on ``[B, H, W, C]`` floats, the building blocks of
:mod:`mnerf_jax.imaging.augment`'s random augmentations.

Spatial filters extend the image by reflection (kornia's default border), not by zeros, so borders do not
darken. :func:`clip_unit` is an exact clip to [0, 1] in the forward pass with an identity gradient: a plain
clip would zero the gradient of every pixel pushed past 0 or 1 (e.g. the white background of a synthetic
scene under a brightness increase or noise) although the decoder still sees those pixels change when the
renderer changes them.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np


def clip_unit(x: jax.Array) -> jax.Array:
    """Clip to [0, 1] in the forward pass; the gradient is the identity (see the module docstring)."""
    return x + jax.lax.stop_gradient(jnp.clip(x, 0.0, 1.0) - x)


def pad_reflect(images: jax.Array, radius: int) -> jax.Array:
    """Reflect-pad the two spatial axes of ``[B, H, W, C]`` by ``radius`` pixels."""
    if radius == 0:
        return images
    mode = "reflect" if min(images.shape[1:3]) > 1 else "edge"  # reflect needs two samples per axis
    return jnp.pad(images, ((0, 0), (radius, radius), (radius, radius), (0, 0)), mode=mode)


def filter_per_image(images: jax.Array, kernels: jax.Array) -> jax.Array:
    """Correlate each image ``[B, H, W, C]`` with its own kernel ``[B, k, k]`` (odd k), reflect borders.

    3×3 kernels: a sum of 9 shifted images, each scaled per image. Larger ones: one depthwise convolution
    with the batch folded into the channels: shifted sums are the faster for 3×3, but XLA:CPU does not fuse
    their backward well beyond a few terms.
    """
    b, h, w, c = images.shape
    k = kernels.shape[-1]
    if k <= 3:
        weights = kernels.astype(images.dtype).reshape(b, k * k, 1, 1, 1)
        return sum(v * weights[:, n] for n, v in enumerate(_neighbours(images, k)))
    x = pad_reflect(images, k // 2)
    x = x.transpose(1, 2, 0, 3).reshape(1, h + k - 1, w + k - 1, b * c)
    rhs = jnp.repeat(kernels.astype(images.dtype), c, axis=0).transpose(1, 2, 0)[:, :, None, :]
    out = jax.lax.conv_general_dilated(
        x,
        rhs,
        (1, 1),
        "VALID",
        feature_group_count=b * c,
        dimension_numbers=("NHWC", "HWIO", "NHWC"),
        precision=jax.lax.Precision.HIGHEST,
    )
    return out.reshape(h, w, b, c).transpose(2, 0, 1, 3)


def gaussian_blur_per_image(images: jax.Array, sigma: jax.Array, kernel: int) -> jax.Array:
    """Blur each image ``[B, H, W, C]`` with its own Gaussian ``sigma [B]`` (px): dm-pix's separable
    ``kernel``-tap filter (``exp(−t²/2σ²)``, normalised), reflect borders.

    Separable sums of shifted images, each scaled per image. dm-pix's ``gaussian_blur`` vmapped over the batch
    (per-image depthwise convolutions) computes the same, far more slowly on XLA:CPU; it remains the test
    oracle.
    """
    r = kernel // 2
    taps = jnp.arange(-r, r + 1, dtype=images.dtype)
    weights = jnp.exp(-(taps[None] ** 2) / (2.0 * jnp.asarray(sigma, images.dtype)[:, None] ** 2))
    return _separable(images, weights / jnp.sum(weights, axis=-1, keepdims=True))


def _separable(images: jax.Array, taps: jax.Array) -> jax.Array:
    """Filter ``[B, H, W, C]`` along H, then W, with the 1-D ``taps [B, k]`` (per image) or ``[1, k]`` (odd
    k), reflect borders: sums of shifted images, which XLA fuses."""
    h, w = images.shape[1:3]
    k = taps.shape[-1]
    weights = jnp.asarray(taps, images.dtype)[:, :, None, None, None]  # [B or 1, k, 1, 1, 1]
    x = pad_reflect(images, k // 2)
    x = sum(x[:, i : i + h] * weights[:, i] for i in range(k))
    return sum(x[:, :, j : j + w] * weights[:, j] for j in range(k))


def _neighbours(images: jax.Array, kernel: int) -> list[jax.Array]:
    """``kernel²`` arrays ``[B, H, W, C]``: each pixel's reflect-padded neighbour at one offset."""
    h, w = images.shape[1:3]
    x = pad_reflect(images, kernel // 2)
    return [x[:, i : i + h, j : j + w] for i in range(kernel) for j in range(kernel)]


@functools.cache
def _sorting_network(n: int) -> tuple[tuple[int, int], ...]:
    """Compare-exchange pairs ``(i, j)``, ``i < j``, of Batcher's odd-even merge sort of ``n`` values.

    Built for the next power of two; pairs that reach past ``n`` are dropped (as if the missing values were
    +inf, for which they are no-ops).
    """
    size = 1 << max(n - 1, 0).bit_length()
    pairs = []
    p = 1
    while p < size:
        k = p
        while k >= 1:
            for j in range(k % p, size - k, 2 * k):
                for i in range(min(k, size - j - k)):
                    a, b = i + j, i + j + k
                    if a // (2 * p) == b // (2 * p) and b < n:
                        pairs.append((a, b))
            k //= 2
        p *= 2
    return tuple(pairs)


def box_blur(images: jax.Array, kernel: int) -> jax.Array:
    """Mean over ``kernel × kernel`` neighbourhoods of ``[B, H, W, C]`` (separable, reflect borders)."""
    return _separable(images, jnp.full((1, kernel), 1.0 / kernel))


def median_blur(images: jax.Array, kernel: int) -> jax.Array:
    """Median over ``kernel × kernel`` neighbourhoods of ``[B, H, W, C]`` (odd ``kernel``, reflect borders).

    The value comes from a sorting network of elementwise min / max over the ``kernel²`` shifted images (XLA
    keeps only the comparators the middle output needs); the gradient reaches the neighbour(s) equal to the
    median (shared among ties) through a mask. ``jnp.sort`` over stacked patches, with its own derivative
    (a gather and a scatter of the permutation), is far slower, forward and backward.
    """
    views = _neighbours(images, kernel)
    values = list(views)
    for a, b in _sorting_network(len(values)):
        values[a], values[b] = jnp.minimum(values[a], values[b]), jnp.maximum(values[a], values[b])
    median = jax.lax.stop_gradient(values[len(values) // 2])
    chosen = [jax.lax.stop_gradient(v == median).astype(images.dtype) for v in views]
    count = sum(chosen)
    # Exactly the median in value; d(out)/d(neighbour) = chosen / count.
    moved = sum((v - jax.lax.stop_gradient(v)) * c for v, c in zip(views, chosen, strict=True))
    return median + moved / count


def posterize(images: jax.Array, bits: int) -> jax.Array:
    """Keep the top ``bits`` bits of each 8-bit value (``floor(255x)`` masked), straight-through gradient."""
    step = 2.0 ** (8 - bits)
    quantised = jnp.floor(jnp.floor(jnp.clip(images, 0.0, 1.0) * 255.0) / step) * step / 255.0
    return images + jax.lax.stop_gradient(quantised - images)


_SHARPNESS_KERNEL = np.array([[1, 1, 1], [1, 5, 1], [1, 1, 1]], np.float32) / 13.0


def sharpness(images: jax.Array, factor: jax.Array) -> jax.Array:
    """PIL/kornia sharpness: ``blur + factor·(x − blur)`` with a 3×3 smoothing kernel; borders unchanged.

    ``factor [B]``: 0 gives the smoothed image, 1 the original, above 1 sharpens. ``images [B, H, W, C]``.
    """
    b, h, w, _ = images.shape
    if h < 3 or w < 3:
        return images
    kernels = jnp.broadcast_to(jnp.asarray(_SHARPNESS_KERNEL), (b, 3, 3))
    blurred = filter_per_image(images, kernels)
    interior = jnp.zeros((h, w), bool).at[1:-1, 1:-1].set(True)[None, :, :, None]
    blurred = jnp.where(interior, blurred, images)  # as PIL: the one-pixel border keeps the original
    return blurred + factor[:, None, None, None] * (images - blurred)


def motion_blur_kernel(size: jax.Array, angle: jax.Array, direction: jax.Array, max_size: int) -> jax.Array:
    """One motion-blur kernel ``[max_size, max_size]`` (sums to 1), kornia's ``get_motion_kernel2d``.

    A horizontal line of odd length ``size`` (≤ ``max_size``) through the centre, weights going linearly from
    ``d`` to ``1 − d`` with ``d = (direction + 1)/2`` (direction 0: uniform; ±1: one-sided), rotated by
    ``angle`` degrees with nearest-neighbour sampling and renormalised. Scalars may be traced.
    """
    radius = max_size // 2
    coords = jnp.arange(-radius, radius + 1, dtype=jnp.float32)
    yy, xx = jnp.meshgrid(coords, coords, indexing="ij")
    theta = jnp.deg2rad(angle)
    cos, sin = jnp.cos(theta), jnp.sin(theta)
    # Inverse-rotate each kernel cell onto the unrotated line and take the nearest line sample.
    xs = jnp.round(cos * xx + sin * yy)
    ys = jnp.round(-sin * xx + cos * yy)
    r = (size // 2).astype(jnp.float32)
    d = (jnp.clip(direction, -1.0, 1.0) + 1.0) / 2.0
    weight = d + (1.0 - 2.0 * d) * (xs + r) / jnp.maximum(2.0 * r, 1.0)
    inside = (ys == 0) & (jnp.abs(xs) <= r) & (jnp.abs(xx) <= r) & (jnp.abs(yy) <= r)
    kernel = jnp.where(inside, weight, 0.0)
    return kernel / jnp.sum(kernel)
