"""Differentiable JPEG: a baseline JFIF codec round trip whose gradient w.r.t. the image is non-zero.

The forward pass follows what libjpeg (and so Pillow) does with 4:2:0 chroma subsampling:

1. pad ``H × W`` to a multiple of 16 by repeating the last row and column (libjpeg's edge expansion);
2. RGB → YCbCr (JFIF/BT.601 full range, on the 0–255 scale);
3. Cb and Cr averaged over 2×2 pixels (libjpeg's ``h2v2_downsample``);
4. level shift −128 and an orthonormal 8×8 DCT-II (as a matrix; the orthonormal DCT is JPEG's scaling);
5. quantisation with the IJG luminance / chrominance tables scaled by quality
   (``s = floor(5000/q)`` for ``q < 50`` else ``200 − 2q``, ``Q = floor((T·s + 50)/100)`` clipped to
   [1, 255]: libjpeg's tables for integer qualities);
   rounding is exact in the forward pass and has the derivative of ``round(x) + (x − round(x))³``
   (Shin & Song 2017) in the backward pass, so the gradient is neither zero (``jnp.round``) nor the identity;
6. dequantisation, inverse DCT, +128;
7. chroma upsampling with libjpeg's default "fancy" (triangular) filter: each full-resolution sample is
   ¾ of the nearest chroma sample plus ¼ of the next one along each axis, edges replicated. This is bilinear
   interpolation with centred chroma siting, which is what libjpeg-based decoders produce by default;
8. YCbCr → RGB, /255, crop back to ``H × W``, clip to [0, 1].

The output is not rounded to 8 bits (that adds at most 0.5/255 and would only zero more of the gradient).
libjpeg's integer DCT and fixed-point colour conversion differ from this float pipeline by a fraction of
a grey level per coefficient; ``scripts/check_jpeg.py`` measures the distance to Pillow's codec.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

# IJG standard quantisation tables (ITU-T T.81 Annex K, tables K.1 and K.2), row-major in (v, u).
LUMA_TABLE = np.array(
    [
        [16, 11, 10, 16, 24, 40, 51, 61],
        [12, 12, 14, 19, 26, 58, 60, 55],
        [14, 13, 16, 24, 40, 57, 69, 56],
        [14, 17, 22, 29, 51, 87, 80, 62],
        [18, 22, 37, 56, 68, 109, 103, 77],
        [24, 35, 55, 64, 81, 104, 113, 92],
        [49, 64, 78, 87, 103, 121, 120, 101],
        [72, 92, 95, 98, 112, 100, 103, 99],
    ],
    np.float32,
)
CHROMA_TABLE = np.array(
    [
        [17, 18, 24, 47, 99, 99, 99, 99],
        [18, 21, 26, 66, 99, 99, 99, 99],
        [24, 26, 56, 99, 99, 99, 99, 99],
        [47, 66, 99, 99, 99, 99, 99, 99],
        [99, 99, 99, 99, 99, 99, 99, 99],
        [99, 99, 99, 99, 99, 99, 99, 99],
        [99, 99, 99, 99, 99, 99, 99, 99],
        [99, 99, 99, 99, 99, 99, 99, 99],
    ],
    np.float32,
)

# JFIF RGB -> YCbCr (rows Y, Cb, Cr); the +128 chroma offset is applied separately.
RGB_TO_YCBCR = np.array(
    [
        [0.299, 0.587, 0.114],
        [-0.168735892, -0.331264108, 0.5],
        [0.5, -0.418687589, -0.081312411],
    ],
    np.float32,
)
YCBCR_TO_RGB = np.linalg.inv(RGB_TO_YCBCR.astype(np.float64)).astype(np.float32)


def _dct_matrix(n: int = 8) -> np.ndarray:
    """Orthonormal DCT-II matrix ``C [u, x] = α(u)·cos((2x + 1)uπ / 2n)``."""
    u = np.arange(n)[:, None]
    x = np.arange(n)[None, :]
    c = np.sqrt(2.0 / n) * np.cos((2 * x + 1) * u * np.pi / (2 * n))
    c[0] /= np.sqrt(2.0)
    return c.astype(np.float32)


DCT8 = _dct_matrix(8)


@jax.custom_jvp
def round_cubic(x: jax.Array) -> jax.Array:
    """``round(x)`` whose derivative is that of ``round(x) + (x − round(x))³``, i.e. ``3(x − round(x))²``."""
    return jnp.round(x)


@round_cubic.defjvp
def _round_cubic_jvp(primals: tuple[jax.Array], tangents: tuple[jax.Array]) -> tuple[jax.Array, jax.Array]:
    (x,), (t,) = primals, tangents
    r = jnp.round(x)
    return r, t * 3.0 * jnp.square(x - r)


def quality_scale(quality: jax.Array | float) -> jax.Array:
    """IJG quality → table scale in percent; quality is clipped to [1, 100] first (0 would divide by 0).

    ``5000/q`` is floored as libjpeg's integer division does, so integer qualities give libjpeg's tables.
    """
    q = jnp.clip(jnp.asarray(quality, jnp.float32), 1.0, 100.0)
    return jnp.where(q < 50.0, jnp.floor(5000.0 / q), 200.0 - 2.0 * q)


def quant_tables(quality: jax.Array | float) -> tuple[jax.Array, jax.Array]:
    """Luma and chroma tables ``[..., 8, 8]`` for ``quality [...]`` (float, traced OK), baseline-clipped."""
    s = quality_scale(quality)[..., None, None]
    luma = jnp.clip(jnp.floor((LUMA_TABLE * s + 50.0) / 100.0), 1.0, 255.0)
    chroma = jnp.clip(jnp.floor((CHROMA_TABLE * s + 50.0) / 100.0), 1.0, 255.0)
    return luma, chroma


def _blocks(x: jax.Array) -> jax.Array:
    """``[N, H, W]`` (H, W multiples of 8) → ``[N, H/8, W/8, 8, 8]``."""
    n, h, w = x.shape
    return x.reshape(n, h // 8, 8, w // 8, 8).transpose(0, 1, 3, 2, 4)


def _unblocks(x: jax.Array) -> jax.Array:
    n, bh, bw, _, _ = x.shape
    return x.transpose(0, 1, 3, 2, 4).reshape(n, bh * 8, bw * 8)


def _codec_plane(plane: jax.Array, table: jax.Array) -> jax.Array:
    """Level shift, DCT, quantise, dequantise, inverse DCT of one plane ``[N, H, W]`` (0–255 scale).

    ``table [N, 8, 8]`` is the quantisation table of each image.
    """
    c = jnp.asarray(DCT8)
    hi = jax.lax.Precision.HIGHEST
    blocks = _blocks(plane - 128.0)
    coef = jnp.einsum("ux,nijxy,vy->nijuv", c, blocks, c, precision=hi)
    table = table[:, None, None]
    coef = round_cubic(coef / table) * table
    blocks = jnp.einsum("ux,nijuv,vy->nijxy", c, coef, c, precision=hi)
    return _unblocks(blocks) + 128.0


def _upsample2_fancy(x: jax.Array, axis: int) -> jax.Array:
    """Double ``axis`` with libjpeg's triangular filter, edges replicated.

    ``out[2i] = ¾·x[i] + ¼·x[i−1]`` and ``out[2i+1] = ¾·x[i] + ¼·x[i+1]``.
    """
    n = x.shape[axis]
    prev = jnp.concatenate(
        [jax.lax.slice_in_dim(x, 0, 1, axis=axis), jax.lax.slice_in_dim(x, 0, n - 1, axis=axis)], axis=axis
    )
    nxt = jnp.concatenate(
        [jax.lax.slice_in_dim(x, 1, n, axis=axis), jax.lax.slice_in_dim(x, n - 1, n, axis=axis)], axis=axis
    )
    even = 0.75 * x + 0.25 * prev
    odd = 0.75 * x + 0.25 * nxt
    out = jnp.stack([even, odd], axis=axis + 1)
    shape = list(x.shape)
    shape[axis] = 2 * n
    return out.reshape(shape)


def _clip_unit(x: jax.Array) -> jax.Array:
    """Clip to [0, 1] in the forward pass, identity gradient (ringing past 0 or 1 keeps its gradient)."""
    return x + jax.lax.stop_gradient(jnp.clip(x, 0.0, 1.0) - x)


def jpeg(images: jax.Array, quality: jax.Array | float) -> jax.Array:
    """JPEG-compress and decompress ``images [..., H, W, 3]`` in [0, 1] at ``quality`` (1–100, float).

    ``quality`` is a scalar or has the images' leading shape ``[...]`` (one quality per image); it may be
    traced. Any ``H × W`` works. Returns ``[..., H, W, 3]`` in [0, 1], differentiable w.r.t. the images.
    """
    images = jnp.asarray(images)
    if images.ndim < 3 or images.shape[-1] != 3:
        raise ValueError(f"jpeg expects images [..., H, W, 3], got shape {images.shape}")
    if not jnp.issubdtype(images.dtype, jnp.floating):
        images = images.astype(jnp.float32)
    lead, (h, w) = images.shape[:-3], images.shape[-3:-1]
    x = images.reshape((-1, h, w, 3))
    n = x.shape[0]
    q = jnp.broadcast_to(jnp.asarray(quality, jnp.float32), lead).reshape(n)
    luma_q, chroma_q = quant_tables(q)

    hp, wp = -(-h // 16) * 16, -(-w // 16) * 16
    x = jnp.pad(x, ((0, 0), (0, hp - h), (0, wp - w), (0, 0)), mode="edge")
    hi = jax.lax.Precision.HIGHEST  # accelerators would otherwise round float32 operands of products
    ycc = jnp.einsum("nhwc,kc->nhwk", x * 255.0, jnp.asarray(RGB_TO_YCBCR, x.dtype), precision=hi)
    y = ycc[..., 0]
    chroma = ycc[..., 1:].reshape(n, hp // 2, 2, wp // 2, 2, 2).mean(axis=(2, 4)) + 128.0

    y = _codec_plane(y, luma_q)
    cb = _codec_plane(chroma[..., 0], chroma_q)
    cr = _codec_plane(chroma[..., 1], chroma_q)
    chroma = jnp.stack([cb, cr], axis=-1)
    chroma = _upsample2_fancy(_upsample2_fancy(chroma, 1), 2) - 128.0

    ycc = jnp.concatenate([y[..., None], chroma], axis=-1)
    rgb = jnp.einsum("nhwk,ck->nhwc", ycc, jnp.asarray(YCBCR_TO_RGB, x.dtype), precision=hi) / 255.0
    rgb = rgb[:, :h, :w]
    return _clip_unit(rgb).reshape(images.shape)
