"""The HiDDeN encoder of decoder training, at LL2 resolution (``decoder_train`` trains it).

``(LL2(image)/4, message ±1) → LL2-domain pattern``, carried to the image through the adjoint of the LL2
transform and scaled per image to a fixed RMS, so every encoded image has a PSNR of at least the run's
``target_psnr`` against its original. For a reader that downscales what it reads to a fixed side
(``watermark.reading.max_side``), the encoder works on the LL2 of the downscaled image and the adjoint of the
whole read (downscale, then LL2) carries its pattern to the image: a smooth residual at any image size, the
way Video Seal and Watermark Anything embed at a fixed side and upsample the residual.
"""

from __future__ import annotations

import dataclasses
import functools
import json
from pathlib import Path
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from mnerf_jax.core.errors import MnerfError
from mnerf_jax.reader import decoder_io, dwt, read_window
from mnerf_jax.reader.train import informed
from mnerf_jax.reader.train.recipe import DecoderTrainConfig


class ConvBNReLU(nn.Module):
    features: int
    kernel: int = 3

    @nn.compact
    def __call__(self, x: jax.Array, train: bool) -> jax.Array:
        x = nn.Conv(self.features, (self.kernel, self.kernel), padding=self.kernel // 2)(x)
        x = nn.BatchNorm(use_running_average=not train, momentum=0.9, epsilon=1e-3)(x)
        return nn.relu(x)


class LL2Encoder(nn.Module):
    """HiDDeN encoder at LL2 resolution: ``(LL2/4 [B, h, w, 3], bits ±1 [B, L]) → pattern R [B, h, w, 3]``.

    Conv-BN-ReLU features of the image, the message broadcast over space and concatenated to them, two more
    blocks and a 1×1 convolution to three channels.
    """

    channels: int = 32
    depth: int = 3

    @nn.compact
    def __call__(self, ll2_scaled: jax.Array, signs: jax.Array, train: bool) -> jax.Array:
        f = ll2_scaled
        for _ in range(self.depth):
            f = ConvBNReLU(self.channels)(f, train)
        msg = jnp.broadcast_to(signs[:, None, None, :], (*ll2_scaled.shape[:-1], signs.shape[-1]))
        f = jnp.concatenate([msg, f, ll2_scaled], axis=-1)
        f = ConvBNReLU(self.channels)(f, train)
        f = ConvBNReLU(self.channels)(f, train)
        return nn.Conv(3, (1, 1))(f)


def init_encoder(key: jax.Array, bits: int, channels: int = 32, depth: int = 3) -> dict[str, Any]:
    return dict(_compiled_init(bits, channels, depth)(key))


@functools.cache
def _compiled_init(bits: int, channels: int, depth: int) -> Any:
    """One compiled init per architecture, kept (a compilation takes seconds)."""
    module = LL2Encoder(channels=channels, depth=depth)
    return jax.jit(lambda k: module.init(k, jnp.zeros((1, 8, 8, 3)), jnp.zeros((1, bits)), train=False))


def encode(
    enc_vars: dict[str, Any],
    images: jax.Array,
    bits: jax.Array,
    cfg: DecoderTrainConfig,
    train: bool = False,
    psnr: jax.Array | float | None = None,
    max_side: int = 0,
) -> tuple[jax.Array, Any]:
    """Encoded images ``[B, H, W, 3]`` (clipped to [0, 1]) and the encoder's updated batch stats.

    The residual is scaled to the RMS of ``psnr`` dB (default ``cfg.target_psnr``) before clipping.
    ``max_side``: write for a reader that sees each image downscaled to at most that side
    (``read_window.downscaled``; 0: as it is).
    """
    psnr = cfg.target_psnr if psnr is None else psnr
    module = LL2Encoder(channels=cfg.encoder_channels, depth=cfg.encoder_depth)

    def read(x: jax.Array) -> jax.Array:
        return dwt.ll2(read_window.downscaled(x, max_side), cfg.wavelet)

    ll2 = read(images)
    signs = 2.0 * bits.astype(images.dtype) - 1.0
    variables = {"params": enc_vars["params"], "batch_stats": enc_vars["batch_stats"]}
    if train:
        pattern, upd = module.apply(variables, ll2 / 4.0, signs, train=True, mutable=["batch_stats"])
        stats = upd["batch_stats"]
    else:
        pattern, stats = module.apply(variables, ll2 / 4.0, signs, train=False), enc_vars["batch_stats"]
    # The adjoint of the (linear) read carries the pattern to image resolution as a smooth residual.
    adjoint = jax.linear_transpose(read, images)
    (residual,) = adjoint(pattern)
    residual = informed.scale_to_psnr(residual, psnr)
    return jnp.clip(images + residual, 0.0, 1.0), stats


def encode_batch(
    cfg: DecoderTrainConfig,
    enc_vars: dict[str, Any],
    images: np.ndarray,
    bits: np.ndarray,
    max_side: int = 0,
) -> np.ndarray:
    """Encoded images as float32 in [0, 1] (eval mode); ``max_side`` as :func:`encode`'s."""
    return np.asarray(_encode_eval(enc_vars, jnp.asarray(images), jnp.asarray(bits), cfg, max_side))


@functools.partial(jax.jit, static_argnames=("cfg", "max_side"))
def _encode_eval(
    enc_vars: dict[str, Any],
    images: jax.Array,
    bits: jax.Array,
    cfg: DecoderTrainConfig,
    max_side: int = 0,
) -> jax.Array:
    return encode(enc_vars, images, bits, cfg, max_side=max_side)[0]


def save_encoder(path: str | Path, enc_vars: dict[str, Any], cfg: DecoderTrainConfig) -> None:
    """Write the encoder's variables (float32) and the training config atomically, as :func:`load_encoder`
    reads them."""
    flat = decoder_io._flatten({"params": enc_vars["params"], "batch_stats": enc_vars["batch_stats"]})
    arrays = {k: np.asarray(v, np.float32) for k, v in flat.items()}
    decoder_io.write_npz_atomic(path, arrays, {"config": cfg.to_dict()})


def load_encoder(path: str | Path) -> tuple[dict[str, Any], DecoderTrainConfig]:
    """The encoder variables and the training config from an ``encoder.npz`` written by a run."""
    arrays, meta = {}, {}
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: np.array(data[name]) for name in data.files}
        meta = json.loads(arrays.pop("__metadata__").tobytes().decode())
    except (OSError, ValueError, KeyError) as err:
        raise MnerfError(f"encoder file {path} is unreadable ({err})") from None
    known = {f.name for f in dataclasses.fields(DecoderTrainConfig)}
    values = {k: tuple(v) if isinstance(v, list) else v for k, v in meta["config"].items() if k in known}
    return jax.tree.map(jnp.asarray, decoder_io._unflatten(arrays)), DecoderTrainConfig(**values)
