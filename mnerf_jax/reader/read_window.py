"""The read window: the square of an image the watermark decoder reads, centred on the object.

The HiDDeN decoders read patterns anchored to the frame of the image they are given (their zero padding;
``docs/decoders.md``, "The image frame"). On an object-centred scene with an empty background (NeRF-Synthetic:
a white backdrop) the whole view's frame lies on background, which a radiance field cannot colour without
new geometry. Reading a window centred on the object instead puts the frame the decoder reads on the object,
which reads more bits at the same PSNR (``scripts/watermark_bound.py --read-window``; docs/experiments/).

The window's side is ``fraction`` of the image's shorter side; its centre is the centroid of the pixels that
differ from ``background`` (found on a 4×4 box-filtered copy, so that noise attacks do not move it), or the
image's centre where nothing differs. The position is a function of the image, recomputed at every read, so
crops and shifts of a render move the window with the object. Gradients flow through the window's pixels,
not its position.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mnerf_jax.core.errors import MnerfError
from mnerf_jax.core.watermark_config import ReadingConfig, window_side

# Foreground weight ramps from 0 to 1 as a pixel's largest channel difference from the background goes from
# FOREGROUND_LOW to FOREGROUND_HIGH, after a 4×4 box filter (Gaussian noise of σ shrinks to σ/4). Noise
# clipped to [0, 1] on a white backdrop is one-sided: its mean, 0.4·σ, survives the filter, so the ramp starts
# above it (so strong noise attacks barely move the window), yet below most object pixels' distance from
# white.
FOREGROUND_LOW = 0.1
FOREGROUND_HIGH = 0.2
SMOOTHING = 4


def foreground_weight(images: jax.Array, background: float) -> jax.Array:
    """Soft foreground mask ``[B, H, W]`` in [0, 1] of images ``[B, H, W, 3]`` on a ``background`` grey."""
    distance = jnp.max(jnp.abs(images - background), axis=-1)
    pad = SMOOTHING // 2
    smoothed = jax.lax.reduce_window(
        jnp.pad(distance, ((0, 0), (pad, SMOOTHING - 1 - pad), (pad, SMOOTHING - 1 - pad)), mode="edge"),
        0.0,
        jax.lax.add,
        (1, SMOOTHING, SMOOTHING),
        (1, 1, 1),
        "VALID",
    ) / (SMOOTHING * SMOOTHING)
    return jnp.clip((smoothed - FOREGROUND_LOW) / (FOREGROUND_HIGH - FOREGROUND_LOW), 0.0, 1.0)


def window_origin(images: jax.Array, side: int, background: float | None) -> jax.Array:
    """Top-left corners ``[B, 2]`` (int32 row, column) of ``side``-pixel windows of images ``[B, H, W, 3]``.

    Centred on the foreground's centroid (``background`` None: on the image's centre), kept inside the image.
    """
    b, h, w = images.shape[:3]
    centre = jnp.broadcast_to(jnp.asarray([(h - 1) / 2.0, (w - 1) / 2.0]), (b, 2))
    if background is not None:
        weight = foreground_weight(jax.lax.stop_gradient(images), background)
        total = jnp.sum(weight, axis=(1, 2))
        rows = jnp.sum(weight * jnp.arange(h)[None, :, None], axis=(1, 2)) / jnp.maximum(total, 1e-6)
        cols = jnp.sum(weight * jnp.arange(w)[None, None, :], axis=(1, 2)) / jnp.maximum(total, 1e-6)
        found = (total > 1.0)[:, None]  # at least a pixel's worth of foreground
        centre = jnp.where(found, jnp.stack([rows, cols], axis=1), centre)
    corner = jnp.round(centre - (side - 1) / 2.0).astype(jnp.int32)
    return jnp.clip(corner, 0, jnp.asarray([h - side, w - side], jnp.int32))


def downscaled(images: jax.Array, max_side: int) -> jax.Array:
    """Images ``[B, H, W, 3]`` resized (antialiased, linear; differentiable) so that their longer side is
    ``max_side`` pixels, each side a multiple of 4 (the level-2 DWT's), when it is longer; 0: as they are.

    The shipped decoders read the patterns of their training side best (docs/decoders.md): reading every
    image at that side makes the read, and what the embedding writes for it, independent of the render's
    size (and of a rescaling attack)."""
    h, w = images.shape[1:3]
    if not max_side or max(h, w) <= max_side:
        return images
    scale = max_side / max(h, w)
    size = tuple(max(4, 4 * round(n * scale / 4)) for n in (h, w))
    return jax.image.resize(images, (images.shape[0], *size, images.shape[3]), "linear", antialias=True)


def read_window(
    images: jax.Array,
    fraction: float,
    background: float | None = 1.0,
    offsets: jax.Array | None = None,
    max_side: int = 0,
) -> jax.Array:
    """The windows ``[B, S, S, 3]`` the decoder reads of images ``[B, H, W, 3]``; ``fraction`` 0: the images.

    ``S`` = :func:`window_side`; ``background``: the empty backdrop's grey level (1: white, NeRF-Synthetic's
    convention), or None to centre every window on its image. ``offsets [B, 2]`` (int rows, columns): move
    each window by that much from its centred place (still kept inside the image; :func:`jitter_offsets`).
    ``max_side``: the windows (or images) then :func:`downscaled` to at most that side.
    """
    h, w = images.shape[1:3]
    if not fraction or window_side(h, w, fraction) == h == w:
        return downscaled(images, max_side)
    side = window_side(h, w, fraction)
    origin = window_origin(images, side, background)
    if offsets is not None:
        origin = _moved(origin, jnp.asarray(offsets, jnp.int32), h, w, side)
    return downscaled(_cut(images, origin, side), max_side)


def _moved(origin: jax.Array, offset: jax.Array, height: int, width: int, side: int) -> jax.Array:
    """Window corners ``origin [B, 2]`` moved by ``offset`` (``[B, 2]`` or ``[2]``), kept inside the image."""
    return jnp.clip(origin + offset, 0, jnp.asarray([height - side, width - side], jnp.int32))


def _cut(images: jax.Array, origin: jax.Array, side: int) -> jax.Array:
    """The ``side``-pixel squares ``[B, S, S, 3]`` of images ``[B, H, W, 3]`` at corners ``origin [B, 2]``."""
    return jax.vmap(lambda x, o: jax.lax.dynamic_slice(x, (o[0], o[1], 0), (side, side, 3)))(images, origin)


def jittered_logits(
    logits_of: Callable[[jax.Array], jax.Array],
    images: jax.Array,
    fraction: float,
    background: float | None,
    radius: int,
    max_side: int = 0,
) -> jax.Array:
    """Logits ``[B, L]`` of images ``[B, H, W, 3]`` averaged over the windows :func:`jitter_offsets` gives
    (``radius`` 0: the centred window alone). ``logits_of``: windows ``[B', S, S, 3]`` → logits ``[B', L]``,
    given all ``(2r + 1)² · B`` windows in one batch (each :func:`downscaled` to ``max_side``). The object's
    centre is found once per image."""
    offsets = jitter_offsets(radius)
    h, w = images.shape[1:3]
    if not fraction or window_side(h, w, fraction) == h == w:  # the whole image: every read is the same
        return logits_of(downscaled(images, max_side))
    side = window_side(h, w, fraction)
    b = images.shape[0]
    origin = window_origin(images, side, background)
    moved = [_moved(origin, jnp.asarray(o), h, w, side) for o in offsets]
    windows = jnp.concatenate([_cut(images, corner, side) for corner in moved])
    return jnp.mean(logits_of(downscaled(windows, max_side)).reshape(len(offsets), b, -1), axis=0)


def check_jitter(radius: int) -> int:
    """``radius`` when it is a read jitter (an int ≥ 0, pixels); MnerfError otherwise."""
    if isinstance(radius, bool) or int(radius) != radius or radius < 0:
        raise MnerfError(f"the read jitter is a radius in pixels, an integer at least 0, got {radius}")
    return int(radius)


def jitter_offsets(radius: int) -> np.ndarray:
    """Every window offset ``[(2r + 1)², 2]`` (int32 rows, columns) within ``radius`` pixels on each axis,
    ``(0, 0)`` first: the windows a jittered read averages over (``watermark.read_jitter``)."""
    check_jitter(radius)
    steps = np.arange(-radius, radius + 1)
    grid = np.stack(np.meshgrid(steps, steps, indexing="ij"), -1).reshape(-1, 2)
    return np.concatenate([np.zeros((1, 2)), grid[np.any(grid != 0, axis=1)]]).astype(np.int32)


def background_of(read_background: float) -> float | None:
    """The config's ``watermark.read_background`` as :func:`read_window` takes it (< 0: None, no backdrop)."""
    return None if read_background < 0 else float(read_background)


@dataclasses.dataclass(frozen=True)
class ReadOptions:
    """How the decoder reads an image: a ``window`` of that fraction of the shorter side (0: the whole
    image) centred on what differs from ``background`` (None: on the image's centre), its logits averaged
    over the windows moved by up to ``jitter`` pixels, each read at most ``max_side`` pixels a side (0: as it
    is). Hashable, so a jitted reader takes it as one static argument."""

    window: float = 0.0
    background: float | None = 1.0
    jitter: int = 0
    max_side: int = 0


WHOLE_IMAGE = ReadOptions()  # the whole image, read once at its own size


def window_of(images: jax.Array, read: ReadOptions) -> jax.Array:
    """:func:`read_window` of images ``[B, H, W, 3]`` with ``read``'s window, background and side (one read:
    ``read.jitter`` is for :func:`jittered_logits`)."""
    return read_window(images, read.window, read.background, max_side=read.max_side)


def of_config(reading: ReadingConfig) -> ReadOptions:
    """The read options of a watermark config's ``reading`` section."""
    return ReadOptions(
        float(reading.window),
        background_of(float(reading.background)),
        int(reading.jitter),
        int(reading.max_side),
    )


def of_metadata(meta: Mapping[str, Any]) -> ReadOptions:
    """The read options recorded in a decoder file's metadata by ``mnerf embed`` (a file without them reads
    the whole image, once, at its own size)."""
    return ReadOptions(
        float(meta.get("read_window", 0.0)),
        background_of(float(meta.get("read_background", 1.0))),
        int(meta.get("read_jitter", 0)),
        int(meta.get("read_max_side", 0)),
    )
