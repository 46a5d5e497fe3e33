"""The jitted steps of decoder training: joint encoder+decoder, informed (decoder against its own gradient
watermark) and encoder-only through the frozen whitened decoder. Each is ``(state, images, bits, key, ...) →
(state, metrics)`` and skips itself when a gradient is not finite."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import optax

from mnerf_jax.core import xla_cpu
from mnerf_jax.imaging import losses
from mnerf_jax.reader import decoder as dec
from mnerf_jax.reader import dwt, read_window
from mnerf_jax.reader.train import informed
from mnerf_jax.reader.train.evaluation import policy
from mnerf_jax.reader.train.hidden_encoder import encode
from mnerf_jax.reader.train.recipe import DecoderTrainConfig


def _message_loss(logits: jax.Array, bits: jax.Array, temperature: float) -> jax.Array:
    return losses.bce_with_logits(logits, bits, temperature=temperature)


def _bit_acc(logits: jax.Array, bits: jax.Array) -> jax.Array:
    return jnp.mean((logits > 0) == (bits > 0.5))


def _psnr(a: jax.Array, b: jax.Array) -> jax.Array:
    mse = jnp.mean((a - b) ** 2, axis=(-3, -2, -1))
    return jnp.mean(-10.0 * jnp.log10(jnp.maximum(mse, 1e-12)))


def random_windows(key: jax.Array, images: jax.Array, size: int) -> jax.Array:
    """A random ``size × size`` window of each image ``[B, H, W, C]`` (one offset per image).

    The decoder then never sees the encoder's image borders at a fixed place, so a watermark that leans on
    them (zero padding tells a small network where the border is) does not survive: the watermark has to be
    stationary, and it then decodes at any image size.
    """
    b, h, w, c = images.shape
    if (h, w) == (size, size):
        return images
    ky, kx = jax.random.split(key)
    ys = jax.random.randint(ky, (b,), 0, h - size + 1)
    xs = jax.random.randint(kx, (b,), 0, w - size + 1)
    crop = lambda image, y, x: jax.lax.dynamic_slice(image, (y, x, 0), (size, size, c))
    return jax.vmap(crop)(images, ys, xs)


def _all_finite(tree: Any) -> jax.Array:
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree.leaves(tree)]))


def _unless_finite(grads: Any, new: dict[str, Any], old: dict[str, Any]) -> dict[str, Any]:
    """``new`` where every gradient is finite, else ``old`` (the step is skipped).

    A rare batch can give a non-finite gradient through an augmentation (e.g. Gaussian blur followed by the
    HSV saturation change); one such step must not poison the weights.
    """
    ok = _all_finite(grads)
    return jax.tree.map(lambda n, o: jnp.where(ok, n, o), new, old)


def _metrics(loss: jax.Array, aux: dict[str, Any], grads: Any) -> dict[str, jax.Array]:
    skipped = 1.0 - _all_finite(grads).astype(jnp.float32)
    return {"loss": loss, "acc": aux["acc"], "psnr": aux["psnr"], "skipped": skipped}


def _update_part(
    tx: optax.GradientTransformation, state: dict[str, Any], part: str, opt_key: str, grads: Any, stats: Any
) -> dict[str, Any]:
    """``state`` with one network (``part``: encoder or decoder) stepped by ``tx`` on ``grads`` and its batch
    statistics replaced by ``stats``; unchanged if a gradient is not finite."""
    params = state[part]["params"]
    updates, opt = tx.update(grads, state[opt_key], params)
    new = dict(state)
    new[part] = {**state[part], "params": optax.apply_updates(params, updates), "batch_stats": stats}
    new[opt_key] = opt
    return _unless_finite(grads, new, state)


def make_joint_step(cfg: DecoderTrainConfig, tx: optax.GradientTransformation, augmented: bool) -> Callable:
    """Jitted joint step: ``(state, images, bits, key, psnr) → (state, metrics)``."""
    augment_fn = policy(cfg) if augmented else None

    def loss_fn(params, state, images, bits, key, psnr):
        enc = {"params": params["encoder"], "batch_stats": state["encoder"]["batch_stats"]}
        encoded, enc_stats = encode(enc, images, bits, cfg, train=True, psnr=psnr)
        k_crop, k_aug = jax.random.split(key)
        seen = random_windows(k_crop, encoded, cfg.size)
        seen = augment_fn(k_aug, seen) if augment_fn is not None else seen
        dec_vars = {**state["decoder"], "params": params["decoder"]}
        logits, dec_stats = dec.apply_ll2_train(dec_vars, dwt.ll2(seen, cfg.wavelet))
        loss = _message_loss(logits, bits, cfg.temperature)
        aux = {
            "enc_stats": enc_stats,
            "dec_stats": dec_stats,
            "acc": _bit_acc(logits, bits),
            "psnr": _psnr(encoded, images),
        }
        return loss, aux

    def step(state, images, bits, key, psnr):
        params = {"encoder": state["encoder"]["params"], "decoder": state["decoder"]["params"]}
        (loss, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(params, state, images, bits, key, psnr)
        updates, opt = tx.update(grads, state["opt"], params)
        params = optax.apply_updates(params, updates)
        new = dict(state)
        new["encoder"] = {"params": params["encoder"], "batch_stats": aux["enc_stats"]}
        new["decoder"] = {**state["decoder"], "params": params["decoder"], "batch_stats": aux["dec_stats"]}
        new["opt"] = opt
        return _unless_finite(grads, new, state), _metrics(loss, aux, grads)

    return xla_cpu.jit_cpu_tuned(step, donate_argnums=0)


def make_finetune_step(
    cfg: DecoderTrainConfig,
    tx: optax.GradientTransformation,
    tx_decoder: optax.GradientTransformation | None = None,
) -> Callable:
    """Jitted encoder step through the eval-mode, whitened decoder: frozen, or also stepped by ``tx_decoder``.

    Half of the steps see the augmented encoded images, unless the run never augments (``clean_fraction`` 1).
    A learning decoder keeps its BatchNorm running statistics and its whitening layer (the rotation the
    encoder writes for): only its convolutions, BatchNorm affine parameters and first linear layer move.
    """
    augment_fn = policy(cfg) if cfg.clean_fraction < 1.0 else (lambda key, images: images)

    def loss_fn(params, state, images, bits, key):
        enc = {"params": params["encoder"], "batch_stats": state["encoder"]["batch_stats"]}
        encoded, enc_stats = encode(enc, images, bits, cfg, train=True, max_side=cfg.read_side)
        k_apply, k_aug, k_crop = jax.random.split(key, 3)
        window = random_windows(k_crop, encoded, encoded.shape[1] - cfg.crop_margin)  # sides take turns
        # Half the steps see the clean encoded image: the no-attack accuracy matters as much as robustness.
        seen = jnp.where(jax.random.uniform(k_apply) < 0.5, augment_fn(k_aug, window), window)
        seen = read_window.downscaled(seen, cfg.read_side)  # the read the encoder writes for (0: as is)
        logits = dec.apply_ll2({**state["decoder"], "params": params["decoder"]}, dwt.ll2(seen, cfg.wavelet))
        loss = _message_loss(logits, bits, cfg.temperature)
        return loss, {"enc_stats": enc_stats, "acc": _bit_acc(logits, bits), "psnr": _psnr(encoded, images)}

    def step(state, images, bits, key, psnr):
        del psnr  # always the target
        dec_params = state["decoder"]["params"]
        if tx_decoder is None:
            grad_fn = lambda p: loss_fn({"encoder": p, "decoder": dec_params}, state, images, bits, key)
            (loss, aux), grads = jax.value_and_grad(grad_fn, has_aux=True)(state["encoder"]["params"])
            new = _update_part(tx, state, "encoder", "opt_ft", grads, aux["enc_stats"])
            return new, _metrics(loss, aux, grads)
        params = {"encoder": state["encoder"]["params"], "decoder": dec_params}
        (loss, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(params, state, images, bits, key)
        new = _update_part(tx, state, "encoder", "opt_ft", grads["encoder"], aux["enc_stats"])
        stats = state["decoder"]["batch_stats"]  # eval mode: the running statistics stay
        new = _update_part(tx_decoder, new, "decoder", "opt_ft_dec", grads["decoder"], stats)
        whitening = state["decoder"]["params"]["whiten"]  # fixed: weight decay would move it too
        new["decoder"] = {**new["decoder"], "params": {**new["decoder"]["params"], "whiten": whitening}}
        return _unless_finite(grads, new, state), _metrics(loss, aux, grads)

    return xla_cpu.jit_cpu_tuned(step, donate_argnums=0)


def make_informed_step(
    cfg: DecoderTrainConfig, tx: optax.GradientTransformation, augmented: bool
) -> Callable:
    """Jitted decoder step against the informed encoder: ``(state, images, bits, key, psnr)``.

    The watermark is the decoder's own (train-mode) message gradient scaled to ``psnr`` dB
    (``informed.informed_embed``, one iteration); the decoder then reads the encoded images, through the
    augmentation layer if ``augmented``, and both uses of the decoder are differentiated. With
    ``informed_margin`` the decoder reads a random window of each encoded image, ``informed_margin`` smaller.
    """
    augment_fn = policy(cfg) if augmented else (lambda key, images: images)

    def loss_fn(params, state, images, bits, key, psnr):
        stats = state["decoder"]["batch_stats"]
        read = lambda x: dec.apply_ll2_train(
            {**state["decoder"], "params": params, "batch_stats": stats}, dwt.ll2(x, cfg.wavelet)
        )
        encoded = informed.informed_embed(lambda x: read(x)[0], images, bits, psnr)
        k_crop, k_aug = jax.random.split(key)
        window = random_windows(k_crop, encoded, images.shape[1] - cfg.informed_margin)
        logits, dec_stats = read(augment_fn(k_aug, window))
        loss = _message_loss(logits, bits, cfg.temperature)
        return loss, {"dec_stats": dec_stats, "acc": _bit_acc(logits, bits), "psnr": _psnr(encoded, images)}

    def step(state, images, bits, key, psnr):
        params = state["decoder"]["params"]
        (loss, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(params, state, images, bits, key, psnr)
        new = _update_part(tx, state, "decoder", "opt_inf", grads, aux["dec_stats"])
        return new, _metrics(loss, aux, grads)

    return xla_cpu.jit_cpu_tuned(step, donate_argnums=0)
