"""Watermark extraction: batched decoding of images into logits, bits and bit accuracy.

``decode`` runs the decoder in evaluation mode (BatchNorm running statistics) on images ``[B, H, W, 3]`` in
[0, 1]: LL2 sub-band, then the HiDDeN decoder, jitted once per (chunk size, image size). Large batches are cut
into chunks of ``batch_size`` images (the last one padded): memory stays bounded, one shape compiles.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mnerf_jax.core import xla_cpu
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.reader import decoder as dec
from mnerf_jax.reader import decoder_io, dwt, read_window

PIXEL_BUDGET = 1 << 19  # image pixels per decoder call (chunks of 52 images at 100², 1 at 800²)


@xla_cpu.jit_cpu_tuned(static_argnames=("wavelet", "read"))
def _decode_chunk(
    variables: Mapping[str, Any], images: jax.Array, wavelet: str, read: read_window.ReadOptions
) -> jax.Array:
    logits_of = lambda windows: dec.apply_ll2(variables, dwt.ll2(windows, wavelet))  # noqa: E731
    if read.jitter:
        return read_window.jittered_logits(
            logits_of, images, read.window, read.background, read.jitter, read.max_side
        )
    return logits_of(read_window.window_of(images, read))


def check_images(images: Any) -> np.ndarray | jax.Array:
    """Check ``images`` is ``[B, H, W, 3]`` or ``[H, W, 3]``; MnerfError for any other rank or channels."""
    shape = tuple(np.shape(images))
    if len(shape) not in (3, 4):
        raise MnerfError(
            f"expected an image [H, W, 3] or a batch [B, H, W, 3], got an array of shape {shape}"
        )
    if shape[-1] != 3:
        raise MnerfError(f"expected RGB images with 3 channels (last axis), got shape {shape}")
    if min(shape[-3], shape[-2]) < 4:
        raise MnerfError(f"images of {shape[-3]}×{shape[-2]} pixels are too small to decode (at least 4×4)")
    return images


def chunk_size(n: int, height: int, width: int, batch_size: int = 32, reads: int = 1) -> int:
    """Images per decoder call for ``n`` images of ``height × width``: the fewest calls of at most
    ``batch_size`` images and ``PIXEL_BUDGET`` pixels, split as evenly as they go (the last call is padded);
    each image read ``reads`` times (a jittered read: that many windows) counts that many times.

    Large images go a few at a time: per-image speed is flat in the chunk size on CPU (each call already uses
    every core), while activations of ``[chunk, H/4, W/4, 64]`` floats outgrow the caches. Even calls: 32
    images at 200² in calls of 13 decoded 39 (13 + 13 + 6 padded), 22 % more than 3 calls of 11.
    """
    most = max(1, min(batch_size // reads, n, PIXEL_BUDGET // (height * width * reads)))
    calls = -(-n // most)
    return -(-n // calls)


def decode(
    variables: Mapping[str, Any],
    images: Any,
    wavelet: str = "bior4.4",
    batch_size: int = 32,
    read: read_window.ReadOptions = read_window.WHOLE_IMAGE,
) -> jax.Array:
    """Logits of images ``[B, H, W, 3]`` in [0, 1] → ``[B, L]`` (a single ``[H, W, 3]`` → ``[L]``).

    Integer images (uint8) are scaled by 1/255. The work is done in chunks of at most ``batch_size`` images
    and ``PIXEL_BUDGET`` pixels. ``read``: the window, its background, the jitter and the side the decoder
    reads (:class:`read_window.ReadOptions`; a watermarked run's ``watermark.reading``, see
    ``read_window.of_config``); the default reads the whole image once, at its own size.
    """
    images = check_images(images)
    single = np.ndim(images) == 3
    x = jnp.asarray(images)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.float32) / 255.0
    x = x.astype(jnp.float32)
    if single:
        x = x[None]
    n, h, w = x.shape[:3]
    if not read.window:  # the whole image has no room to move
        read = dataclasses.replace(read, jitter=0)
    chunk = chunk_size(n, h, w, batch_size, len(read_window.jitter_offsets(read.jitter)))
    outs = []
    for start in range(0, n, chunk):
        part = x[start : start + chunk]
        if part.shape[0] < chunk:  # pad so that every chunk has the compiled shape
            part = jnp.concatenate([part, jnp.zeros((chunk - part.shape[0], *part.shape[1:]), part.dtype)])
        logits = _decode_chunk(variables, part, wavelet, read)
        outs.append(logits[: min(chunk, n - start)])
    logits = jnp.concatenate(outs) if len(outs) > 1 else outs[0]
    return logits[0] if single else logits


def bits_from_logits(logits: Any) -> np.ndarray:
    """Bits (uint8 0/1) from logits ``[..., L]``: a bit is 1 where its logit is > 0."""
    return (np.asarray(logits) > 0).astype(np.uint8)


def bit_accuracy(logits: Any, bits: Any) -> jax.Array:
    """Fraction of bits decoded right per image: logits ``[B, L]``, bits ``[B, L]`` or ``[L]`` → ``[B]``."""
    logits = jnp.asarray(logits)
    bits = jnp.asarray(bits)
    if logits.shape[-1] != bits.shape[-1]:
        raise MnerfError(f"the decoder gives {logits.shape[-1]} bits but the message has {bits.shape[-1]}")
    return jnp.mean((logits > 0) == (bits > 0.5), axis=-1)


def bits_to_string(bits: Sequence[int] | np.ndarray) -> str:
    return "".join(str(int(b)) for b in np.asarray(bits).reshape(-1))


def load_image(path: str | Path) -> np.ndarray:
    """An image file as ``[H, W, 3]`` float32 in [0, 1]; RGBA is composited on white (as renders are)."""
    import imageio.v3 as iio

    path = Path(path)
    if not path.is_file():
        raise MnerfError(f"image {path} does not exist")
    try:
        image = np.asarray(iio.imread(path))
    except Exception as err:  # imageio raises plugin-specific types for unreadable files
        raise MnerfError(f"cannot read image {path} ({type(err).__name__}: {err})") from None
    if image.ndim == 3 and image.shape[-1] == 4:
        scale = float(np.iinfo(image.dtype).max) if np.issubdtype(image.dtype, np.integer) else 1.0
        rgba = image.astype(np.float32) / scale
        return rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:])
    if image.ndim != 3 or image.shape[-1] != 3:
        raise MnerfError(f"image {path} has shape {image.shape}; the decoder reads RGB (or RGBA) images")
    if np.issubdtype(image.dtype, np.integer):
        return image.astype(np.float32) / float(np.iinfo(image.dtype).max)
    return image.astype(np.float32)


def decode_paths(
    variables: Mapping[str, Any],
    paths: Sequence[str | Path],
    wavelet: str = "bior4.4",
    batch_size: int = 32,
    read: read_window.ReadOptions = read_window.WHOLE_IMAGE,
) -> np.ndarray:
    """Logits ``[N, L]`` of image files, in the given order; images of one size are decoded together
    (``read``: as :func:`decode`)."""
    images = [load_image(p) for p in paths]
    by_size: dict[tuple[int, int], list[int]] = {}
    for i, image in enumerate(images):
        by_size.setdefault(image.shape[:2], []).append(i)
    bits, _, _ = dec.architecture(variables)
    out = np.zeros((len(images), bits), np.float32)
    for indices in by_size.values():
        batch = np.stack([images[i] for i in indices])
        out[indices] = np.asarray(decode(variables, batch, wavelet, batch_size, read))
    return out


def resolve_decoder(path: str | Path | None = None, bits: int | None = None) -> decoder_io.LoadedDecoder:
    """A decoder file given by path, else the shipped decoder for ``bits`` (default 16)."""
    if path is not None:
        return decoder_io.load_decoder(path, expect_bits=bits)
    return decoder_io.load_shipped_decoder(16 if bits is None else bits)
