"""Held-out evaluation of a decoder training run: the encoder's images and informed embeddings, with no attack
and under the run's augmentation policy, and their PSNR."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mnerf_jax.imaging import augment
from mnerf_jax.reader import decoder as dec
from mnerf_jax.reader import read_window
from mnerf_jax.reader.train import informed
from mnerf_jax.reader.train.cover_images import EVAL_SEED, heldout_images, heldout_messages
from mnerf_jax.reader.train.hidden_encoder import encode, encode_batch
from mnerf_jax.reader.train.recipe import DecoderTrainConfig


def policy(cfg: DecoderTrainConfig) -> Callable[[jax.Array, jax.Array], jax.Array]:
    """The run's augmentation layer: ``augment.random_policy`` at its strength, count and probability."""

    def apply(key: jax.Array, images: jax.Array) -> jax.Array:
        return augment.random_policy(
            key, images, strength=cfg.augment_strength, k=cfg.augment_k, p=cfg.augment_p
        )

    return apply


def reader(
    cfg: DecoderTrainConfig, dec_vars: dict[str, Any], max_side: int = 0
) -> Callable[[jax.Array], jax.Array]:
    """``images [B, H, W, 3] -> logits [B, L]``: the decoder reading each image downscaled to at most
    ``max_side`` pixels a side (``read_window.downscaled``; 0: as it is)."""
    return lambda images: dec.decode_logits(dec_vars, read_window.downscaled(images, max_side), cfg.wavelet)


def evaluate(
    cfg: DecoderTrainConfig,
    enc_vars: dict[str, Any],
    dec_vars: dict[str, Any],
    images: np.ndarray,
    bits: np.ndarray,
    batch: int = 32,
    max_side: int = 0,
) -> dict[str, float]:
    """Bit accuracy with no attack and under the augmentation policy (several draws), and PSNR, on a set.

    ``max_side``: the decoder reads each image downscaled to at most that side, and the encoder writes for
    that read (``hidden_encoder.encode``); 0: both at the image's own size."""
    draws = cfg.eval_augment_draws
    augment_fn = policy(cfg) if draws > 0 else None

    # The variables are arguments, not closed-over constants (XLA would fold them at length).
    @jax.jit
    def run(enc_vars, dec_vars, x, m, key):
        read = reader(cfg, dec_vars, max_side)
        encoded, _ = encode(enc_vars, x, m, cfg, train=False, max_side=max_side)
        acc_clean = jnp.mean((read(encoded) > 0) == (m > 0.5), axis=-1)
        if augment_fn is None:
            acc_low = jnp.full_like(acc_clean, jnp.nan)
        else:
            # lax.map, not vmap: a batched policy index would run every augmentation branch.
            attacked = jax.lax.map(lambda k: read(augment_fn(k, encoded)), jax.random.split(key, draws))
            acc_low = jnp.mean((attacked > 0) == (m > 0.5)[None], axis=(0, -1))
        mse = jnp.mean((encoded - x) ** 2, axis=(-3, -2, -1))
        return acc_clean, acc_low, -10.0 * jnp.log10(jnp.maximum(mse, 1e-12))

    acc_clean, acc_low, psnr = [], [], []
    for i in range(0, len(images), batch):
        a, b, p = run(
            enc_vars,
            dec_vars,
            jnp.asarray(images[i : i + batch]),
            jnp.asarray(bits[i : i + batch]),
            jax.random.fold_in(jax.random.PRNGKey(EVAL_SEED), i),
        )
        acc_clean.append(np.asarray(a))
        acc_low.append(np.asarray(b))
        psnr.append(np.asarray(p))
    acc_clean, acc_low, psnr = map(np.concatenate, (acc_clean, acc_low, psnr))
    low = float(acc_low.mean())
    return {
        "bit_acc_none": float(acc_clean.mean()),
        "bit_acc_low": None if math.isnan(low) else low,
        "psnr_mean": float(psnr.mean()),
        "psnr_min": float(psnr.min()),
        "images": int(len(images)),
        "informed": {
            f"{n}_iterations": evaluate_informed(cfg, dec_vars, images, bits, n, batch, max_side)
            for n in cfg.eval_informed_iterations
        },
    }


def evaluate_informed(
    cfg: DecoderTrainConfig,
    dec_vars: dict[str, Any],
    images: np.ndarray,
    bits: np.ndarray,
    iterations: int,
    batch: int = 32,
    max_side: int = 0,
) -> dict[str, float | None]:
    """Bit accuracy (no attack, Low) and PSNR of informed embeddings (``informed.informed_embed``) of a set.

    This is how a radiance field carries the watermark (it follows the decoder's gradient), so these figures
    predict MultiNeRF's; the encoder's figures (``evaluate``) are the HiDDeN protocol. ``max_side``: the
    decoder reads each image downscaled to at most that side (``read_window.downscaled``; 0: as it is).
    """
    draws = cfg.eval_augment_draws
    augment_fn = policy(cfg) if draws > 0 else None

    @jax.jit
    def run(dec_vars, x, m, key):
        read = reader(cfg, dec_vars, max_side)
        encoded = informed.informed_embed(read, x, m, cfg.target_psnr, iterations)
        acc_clean = jnp.mean((read(encoded) > 0) == (m > 0.5), axis=-1)
        if draws > 0:
            attacked = jax.lax.map(lambda k: read(augment_fn(k, encoded)), jax.random.split(key, draws))
            acc_low = jnp.mean((attacked > 0) == (m > 0.5)[None], axis=(0, -1))
        else:  # no attacked read: the policy over all 14 augmentations is not compiled for nothing
            acc_low = jnp.full_like(acc_clean, jnp.nan)
        mse = jnp.mean((encoded - x) ** 2, axis=(-3, -2, -1))
        return acc_clean, acc_low, -10.0 * jnp.log10(jnp.maximum(mse, 1e-12))

    parts = [
        run(
            dec_vars,
            jnp.asarray(images[i : i + batch]),
            jnp.asarray(bits[i : i + batch]),
            jax.random.fold_in(jax.random.PRNGKey(EVAL_SEED), i),
        )
        for i in range(0, len(images), batch)
    ]
    acc_clean, acc_low, psnr = (np.concatenate([np.asarray(p[j]) for p in parts]) for j in range(3))
    return {
        "bit_acc_none": float(acc_clean.mean()),
        "bit_acc_low": float(acc_low.mean()) if draws > 0 else None,
        "psnr_mean": float(psnr.mean()),
        "psnr_min": float(psnr.min()),
    }


def evaluate_sizes(
    cfg: DecoderTrainConfig, enc_vars: dict[str, Any], dec_vars: dict[str, Any]
) -> dict[str, Any]:
    """Held-out figures at every side in ``cfg.eval_sizes``: ``{"64px": {...}, "256px": {...}}``, each read
    at ``cfg.read_side``."""
    out = {}
    for size in cfg.eval_sizes:
        images = heldout_images(cfg.eval_images, size)
        messages = heldout_messages(cfg.eval_images, cfg.bits)
        out[f"{size}px"] = evaluate(cfg, enc_vars, dec_vars, images, messages, max_side=cfg.read_side)
    return out


def clean_accuracy(
    cfg: DecoderTrainConfig,
    enc_vars: dict[str, Any],
    dec_vars: dict[str, Any],
    images: np.ndarray,
    bits: np.ndarray,
) -> float:
    encoded = encode_batch(cfg, enc_vars, images, bits)
    logits = dec.decode_logits(dec_vars, jnp.asarray(encoded), cfg.wavelet)
    return float(jnp.mean((logits > 0) == (jnp.asarray(bits) > 0.5)))


def sized_batch(size: int, pixels_of: tuple[int, int] = (32, 64)) -> int:
    """Images per batch at side ``size``: about as many pixels as ``pixels_of[0]`` images of
    ``pixels_of[1]``² (so memory stays flat as the side grows), at least one."""
    count, side = pixels_of
    return max(1, round(count * (side / size) ** 2))


def clean_bit_balance(
    dec_vars: dict[str, Any], images: np.ndarray, wavelet: str, batch: int, max_side: int = 0
) -> dict[str, float]:
    """How a decoder reads images without a watermark: ``ones_mean`` (share of 1 bits), ``bias_max`` (the
    largest ``|P[bit = 1] − ½|`` over the bits) and ``bias_mean`` (its mean over the bits). A decoder whose
    clean reads are fair has biases near 0 (within about ``1 / √images``). ``max_side``: as
    :func:`evaluate_informed`."""
    logits = np.concatenate(
        [
            np.asarray(
                dec.decode_logits(
                    dec_vars, read_window.downscaled(jnp.asarray(images[i : i + batch]), max_side), wavelet
                )
            )
            for i in range(0, len(images), batch)
        ]
    )
    ones = (logits > 0).mean(axis=0)
    bias = np.abs(ones - 0.5)
    return {"ones_mean": float(ones.mean()), "bias_max": float(bias.max()), "bias_mean": float(bias.mean())}


def evaluate_across_sizes(
    cfg: DecoderTrainConfig,
    dec_vars: dict[str, Any],
    sizes: tuple[int, ...],
    images: int,
    iterations: tuple[int, ...] = (1, 10),
    enc_vars: dict[str, Any] | None = None,
    progress: Callable[[str], None] | None = None,
    max_side: int = 0,
) -> dict[str, Any]:
    """A decoder's held-out figures at each image side in ``sizes`` (pixels): ``{"64px": {...}, ...}``.

    Per side, on ``images`` held-out images (never trained on) and their messages: the informed embeddings
    after each count of ``iterations`` (how a radiance field carries the watermark: it follows the decoder's
    gradient), the HiDDeN encoder's images when ``enc_vars`` is given, each with no attack and under the
    Low policy (``cfg.eval_augment_draws`` draws; 0: no attacked read), every image at ≥ ``cfg.target_psnr``
    dB; and the clean images' bit balance (:func:`clean_bit_balance`). ``max_side``: every read sees each
    image downscaled to at most that side, and the encoder writes for that read.
    """
    out: dict[str, Any] = {}
    for size in sizes:
        if progress is not None:
            progress(f"{size}px")
        x = heldout_images(images, size)
        m = heldout_messages(images, cfg.bits)
        batch = sized_batch(size)
        row: dict[str, Any] = {
            "images": int(images),
            "informed": {
                f"{n}_iterations": evaluate_informed(cfg, dec_vars, x, m, n, batch, max_side)
                for n in iterations
            },
            "clean": clean_bit_balance(dec_vars, x, cfg.wavelet, batch, max_side),
        }
        if enc_vars is not None:
            encoded = evaluate(
                dataclasses.replace(cfg, eval_informed_iterations=()),
                enc_vars,
                dec_vars,
                x,
                m,
                batch,
                max_side,
            )
            row["encoder"] = {k: v for k, v in encoded.items() if k != "informed"}
        out[f"{size}px"] = row
    return out
