"""The embedding's loss terms: the quality budget and its ramp, the perceptual and patch losses, the message
loss with its per-ID weighting and key cross-entropy, what the decoder reads of a render, and which terms a
config turns on. :mod:`mnerf_jax.watermark.step` assembles them into one step's objective.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from mnerf_jax.core.watermark_config import WatermarkConfig
from mnerf_jax.imaging import losses
from mnerf_jax.imaging import metrics as metrics_lib
from mnerf_jax.reader import read_window
from mnerf_jax.watermark.deferred import PyTree
from mnerf_jax.watermark.run import EmbedError


def uses_fidelity(cfg: WatermarkConfig) -> bool:
    """True when the quality budget (``watermark.fidelity.psnr``) is on."""
    return cfg.fidelity.psnr > 0


def uses_clean_renders(cfg: WatermarkConfig) -> bool:
    """True when a step needs the clean model's render of its view: the quality budget is on, or the clean
    term reads the clean model's renders (``watermark.losses.clean_negative``)."""
    return uses_fidelity(cfg) or (cfg.losses.lambda_clean > 0 and cfg.losses.clean_negative == "clean_model")


def budget_end_db(cfg: WatermarkConfig, source_psnr: float | None) -> float:
    """Where the quality budget ends (dB against the clean model's render): ``fidelity.psnr``, or with
    ``fidelity.over_source`` > 0 and the source's PSNR on its training views ``source_psnr`` (dB against
    their ground truth) at least ``source_psnr + over_source``. A watermark's error adds to the model's own,
    so the loss against the ground truth follows the budget's distance above the source's PSNR."""
    if not cfg.fidelity.over_source or source_psnr is None:
        return float(cfg.fidelity.psnr)
    return max(float(cfg.fidelity.psnr), float(source_psnr) + float(cfg.fidelity.over_source))


def fidelity_budget_db(cfg: WatermarkConfig, step: int, total: int, end_db: float | None = None) -> float:
    """The quality budget (dB of PSNR against the clean model's render) at step ``step`` of a ``total``-step
    schedule: ``end_db`` (default ``fidelity.psnr``; :func:`budget_end_db`), or with ``fidelity.psnr_start``
    > 0 that until the fraction ``fidelity.ramp[0]`` of the steps, then linear in dB up to ``end_db`` at
    ``fidelity.ramp[1]``, then ``end_db``. Host side: the step receives the budget as data, so the ramp
    compiles once."""
    end = float(cfg.fidelity.psnr if end_db is None else end_db)
    if not cfg.fidelity.psnr_start:
        return end
    first, last = (float(f) * max(int(total), 1) for f in cfg.fidelity.ramp)
    if step <= first:
        return float(cfg.fidelity.psnr_start)
    if step >= last:
        return end
    span = end - cfg.fidelity.psnr_start
    return float(cfg.fidelity.psnr_start + span * (step - first) / (last - first))


def fidelity_loss(
    cfg: WatermarkConfig, renders: jax.Array, reference: jax.Array, budget: jax.Array | None = None
) -> tuple[jax.Array, jax.Array]:
    """``(mean over K of relu(MSE_k / MSE_budget − 1), mean MSE)`` of ``renders [K, H, W, 3]`` against the
    clean model's ``reference [H, W, 3]``; ``MSE_budget`` is ``budget`` (a scalar, traced: the ramp's value
    at this step) or ``10^(−fidelity.psnr / 10)``: zero, with no gradient, for renders inside it."""
    mse = jnp.mean(jnp.square(renders - reference[None]), axis=(1, 2, 3))
    if budget is None:
        budget = metrics_lib.psnr_to_mse(cfg.fidelity.psnr)
    return jnp.mean(jax.nn.relu(mse / budget - 1.0)), jnp.mean(mse)


def perceptual_loss(kind: str, image: jax.Array, reference: jax.Array, vgg_params: Any = None) -> jax.Array:
    """Phase 1's perceptual term: Watson-DCT (default) or LPIPS-VGG."""
    if kind == "watson":
        return losses.watson_dct_loss(image, reference, chroma=True)
    if kind == "vgg":
        return losses.vgg_perceptual_loss(image, reference, vgg_params)
    raise EmbedError(f"unknown watermark.losses.perceptual {kind!r} (watson | vgg)")


def split_renders(image: jax.Array) -> jax.Array:
    """``[..., H, W, 3K]`` (K IDs' renders side by side in the channels) → ``[K, ..., H, W, 3]``."""
    k = image.shape[-1] // 3
    return jnp.moveaxis(image.reshape(*image.shape[:-1], k, 3), -2, 0)


def patch_loss(cfg: WatermarkConfig, rgb: jax.Array, target: jax.Array) -> jax.Array:
    """Phase 2's patch loss ``λ_rgb·L1 + λ_TV·TV + λ_SSIM·(1 − SSIM)`` on ``[S, S, 3]`` patches; for K
    renders of one patch (``rgb [S, S, 3K]``) the mean over them."""
    if rgb.shape[-1] != 3:
        return jnp.mean(jax.vmap(lambda r: patch_loss(cfg, r, target))(split_renders(rgb)))
    loss = cfg.losses.lambda_rgb * jnp.mean(jnp.abs(rgb - target))
    if cfg.losses.lambda_tv:
        loss = loss + cfg.losses.lambda_tv * losses.total_variation(rgb)
    if cfg.losses.lambda_ssim:
        loss = loss + cfg.losses.lambda_ssim * losses.ssim_loss(rgb, target)
    return loss


class MessageTerms(NamedTuple):
    """What :func:`message_loss` returns: the term to minimise (a surrogate whose gradients are the weighted
    ones), the mean BCE, the key term, and the renders' logits ``[K, L]`` (no gradient; the step's bit
    accuracy reads them when the decoder saw the renders unaugmented)."""

    term: jax.Array
    bce: jax.Array
    key: jax.Array
    logits: jax.Array


def decode_two_ways(
    decode: Callable[[jax.Array, PyTree], jax.Array],
) -> Callable[[jax.Array, PyTree], tuple[jax.Array, jax.Array]]:
    """``decode`` evaluated once, returned twice: the first copy's cotangent reaches only the decoder's
    parameters, the second's only the renders. The same values and gradients as two passes with
    ``stop_gradient`` on either side, for one forward pass (the two pullbacks each keep half of theirs)."""

    @jax.custom_vjp
    def both(renders: jax.Array, params: PyTree) -> tuple[jax.Array, jax.Array]:
        logits = decode(renders, params)
        return logits, logits

    def forward(renders: jax.Array, params: PyTree) -> tuple[tuple[jax.Array, jax.Array], Any]:
        logits, pullback = jax.vjp(decode, renders, params)
        return (logits, logits), pullback

    def backward(pullback: Any, cotangents: tuple[jax.Array, jax.Array]) -> tuple[jax.Array, PyTree]:
        to_params, to_renders = cotangents
        return pullback(to_renders)[0], pullback(to_params)[1]

    both.defvjp(forward, backward)
    return both


def message_loss(
    cfg: WatermarkConfig,
    decode: Callable[[jax.Array, PyTree], jax.Array],
    renders: jax.Array,
    dec_params: PyTree,
    message: jax.Array,
    keys: jax.Array | None = None,
    ids: jax.Array | None = None,
) -> MessageTerms:
    """The message term, mean BCE, key term and logits of ``decode(renders [K, H, W, 3], dec_params) ->
    logits [K, L]`` against ``message [K, L]`` (BCE at ``bce_temperature``).

    The term is the mean BCE; with ``id_loss_power`` p > 0 and K > 1 its gradient to the renders is that of
    the mean of the K BCEs weighted by ``BCE_k^p`` (held constant; the renders read worst weigh most), while
    the decoder's stays the plain mean's, and so does the term's value. Weighting the decoder's gradient too
    taught it the weak IDs' keys on barely marked renders, so it claimed clean renders. One decoder pass
    serves both sides (:func:`decode_two_ways`).

    The key term (zero unless ``lambda_key`` > 0, which needs every ID's message ``keys [N, L]`` and the
    renders' ``ids [K]``) is :func:`losses.key_cross_entropy` on the same logits, its gradient to both
    the renders and the decoder, unweighted.
    """
    use_key = cfg.losses.lambda_key > 0
    if use_key and (keys is None or ids is None):
        raise ValueError(
            "watermark.losses.lambda_key > 0 needs every ID's message (keys) and the renders' ids"
        )

    def key_term(z: jax.Array) -> jax.Array:
        if not use_key:
            return jnp.zeros((), jnp.float32)
        return losses.key_cross_entropy(z, keys, ids, cfg.losses.bce_temperature)

    if cfg.losses.id_loss_power <= 0 or renders.shape[0] == 1:
        logits = decode(renders, dec_params)
        bce = losses.bce_with_logits(logits, message, cfg.losses.bce_temperature)
        return MessageTerms(bce, bce, key_term(logits), jax.lax.stop_gradient(logits))

    def per_id(z: jax.Array) -> jax.Array:
        return jax.vmap(lambda zk, mk: losses.bce_with_logits(zk, mk, cfg.losses.bce_temperature))(z, message)

    # The decoder's gradient and the value through z_dec (renders held), the renders' through z_field.
    z_dec, z_field = decode_two_ways(decode)(renders, dec_params)
    bce_k = per_id(z_dec)
    weight = jax.lax.stop_gradient(bce_k) ** cfg.losses.id_loss_power
    weight = weight / jnp.maximum(jnp.sum(weight), jnp.finfo(jnp.float32).tiny)
    field_k = per_id(z_field)
    bce = jnp.mean(bce_k)
    field = jnp.sum(weight * field_k)
    key_field = key_term(z_field)
    key = key_term(z_dec) + key_field - jax.lax.stop_gradient(key_field)
    term = bce + field - jax.lax.stop_gradient(field)
    return MessageTerms(term, bce, key, jax.lax.stop_gradient(z_dec))


def windowed(cfg: WatermarkConfig, images: jax.Array) -> jax.Array:
    """What the decoder reads of images ``[B, H, W, 3]``: the run's read window (``watermark.reading.window``;
    after the augmentations, as a verifier reads an attacked image), at most ``watermark.reading.max_side``
    pixels a side."""
    return read_window.window_of(images, read_window.of_config(cfg.reading))
