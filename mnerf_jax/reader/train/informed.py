"""Informed embedding: a watermark made by following the decoder's own input gradient.

A radiance field fine-tuned toward a key (MultiNeRF's phases 1 and 2) changes its renders along the gradient
of the message loss through the frozen decoder. The same mechanism, applied to an image directly, is an
*informed* encoder: the residual is the gradient of ``−BCE(decoder(LL2(x + δ)), bits)`` with respect to ``δ``,
scaled to a fixed RMS so the encoded image has a fixed PSNR against its original (clipping to [0, 1] only
lowers the error). Several iterations (each re-normalised to the same RMS) give an optimisation-based
embedding in the manner of SSL-watermarking (Fernandez et al. 2022).

Training the decoder *against* this encoder (``informed_step``) teaches it what MultiNeRF needs from it: its
gradients must be distinct per bit, survive the augmentation layer, and reach the message at a small PSNR
cost. A HiDDeN decoder trained only jointly with a feed-forward encoder does not get there on a CPU budget:
behind a global average pool it reads a zero-mean pattern's sign only through higher-order statistics, which
the pair finds slowly (see docs/decoders.md).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from mnerf_jax.imaging import losses


def scale_to_psnr(residual: jax.Array, psnr: jax.Array | float) -> jax.Array:
    """``residual [B, H, W, C]`` rescaled per image to the RMS of ``psnr`` dB (images in [0, 1])."""
    rms = jnp.sqrt(jnp.mean(residual**2, axis=(-3, -2, -1), keepdims=True) + 1e-20)
    return residual * (10.0 ** (-jnp.asarray(psnr, residual.dtype) / 20.0) / rms)


def informed_embed(
    logit_fn: Callable[[jax.Array], jax.Array],
    images: jax.Array,
    bits: jax.Array,
    psnr: jax.Array | float,
    iterations: int = 1,
    mask: jax.Array | None = None,
) -> jax.Array:
    """Images ``[B, H, W, 3]`` in [0, 1] carrying ``bits [B, L]`` (0/1) for the decoder behind ``logit_fn``.

    ``logit_fn(images) -> logits [B, L]``. Each iteration adds the normalised ascent direction of the message
    log-likelihood and rescales the accumulated residual to ``psnr`` dB; the result is clipped to [0, 1], so
    every image's PSNR against its original is at least ``psnr``. Differentiable in the decoder's parameters
    (the decoder's training differentiates through its own gradient). ``mask [B, H, W, 1]`` (0/1), when
    given, confines the residual to its pixels (the PSNR still counts the whole image).
    """

    # BCE at temperature 1: the ascent direction is Σ (b − σ(logit))·∇logit, a signed sum over the bits
    # weighted toward those not yet right.
    def gain(delta: jax.Array) -> jax.Array:
        return -losses.bce_with_logits(logit_fn(jnp.clip(images + delta, 0.0, 1.0)), bits, temperature=1.0)

    delta = jnp.zeros_like(images)
    for _ in range(iterations):
        direction = jax.grad(gain)(delta)
        step = scale_to_psnr(direction if mask is None else direction * mask, psnr)
        delta = scale_to_psnr(delta + step, psnr)
    return jnp.clip(images + delta, 0.0, 1.0)
