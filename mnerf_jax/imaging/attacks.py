"""Attacks on the 8-bit images a verifier receives: real codecs, geometric and photometric edits, noise,
blur and denoisers (Pillow, scikit-image, SciPy), for evaluation only (not differentiable).

Every attack is ``fn(images, rng, **params) -> images`` with ``images`` uint8 ``[B, H, W, 3]`` in and out
(an attack that changes the size returns ``[B, H', W', 3]``, the same size for every image of the batch).
``rng`` is an explicit ``numpy.random.Generator``; random parameters are drawn per image, in batch order, so
that two batches of the same views attacked with generators of the same seed meet the same parameters (every
watermark ID, and the clean model, meets the same attack). Results are rounded to 8 bits, as a file holds.
:mod:`mnerf_jax.imaging.attack_suites` names these with their parameters and groups them into suites.
"""

from __future__ import annotations

import io
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import scipy.ndimage
from PIL import Image, ImageEnhance, ImageFilter, features
from skimage import color, exposure, filters, restoration, transform, util

from mnerf_jax.core.errors import MnerfError

WEBP_SUPPORTED = bool(features.check("webp"))


class AttackError(MnerfError, ValueError):
    """Images an attack cannot take, or an attack (a user's regeneration hook) that returned no images."""


def check_images(images: object, what: str = "attack input") -> np.ndarray:
    """``images`` as a uint8 array ``[B, H, W, 3]`` with sides of at least 4 pixels (what the decoder
    reads); AttackError naming ``what`` otherwise. Nothing is converted: a float array is refused."""
    if not isinstance(images, np.ndarray):
        raise AttackError(f"{what} is a {type(images).__name__}, not a numpy array of uint8 [B, H, W, 3]")
    if images.dtype != np.uint8:
        raise AttackError(f"{what} has dtype {images.dtype}, not uint8 (images [B, H, W, 3] in 0..255)")
    if images.ndim != 4 or images.shape[-1] != 3 or min(images.shape[1:3]) < 4:
        raise AttackError(f"{what} has shape {images.shape}, not [B, H, W, 3] with H, W >= 4")
    return images


def to_uint8(images: np.ndarray) -> np.ndarray:
    """Float images in [0, 1] rounded to 8 bits (as ``data.images.to_uint8``, which this layer may not
    import)."""
    return (np.clip(images, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def _each(
    images: np.ndarray, fn: Callable[..., np.ndarray], per_image: Sequence[Any] | None = None
) -> np.ndarray:
    """``fn(image)`` for every image ``[H, W, 3]`` of ``images [B, H, W, 3]`` (or ``fn(image, p)`` with
    ``per_image [B]``'s parameter ``p`` of that image), stacked."""
    images = check_images(images)
    if per_image is None:
        return np.stack([fn(image) for image in images])
    return np.stack([fn(image, p) for image, p in zip(images, per_image, strict=True)])


def _pil(images: np.ndarray, fn: Callable[[Image.Image], Image.Image]) -> np.ndarray:
    """``fn`` applied to every image as a Pillow RGB image; uint8 ``[B, H', W', 3]``."""
    return _each(images, lambda x: np.asarray(fn(Image.fromarray(x, "RGB")).convert("RGB"), np.uint8))


def _float(
    images: np.ndarray, fn: Callable[..., np.ndarray], per_image: Sequence[Any] | None = None
) -> np.ndarray:
    """:func:`_each` on every image as float64 ``[H, W, 3]`` in [0, 1]; rounded back to uint8."""
    return _each(images, lambda x, *p: to_uint8(fn(util.img_as_float(x), *p)), per_image)


def _signs(rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` random signs ±1 (float64)."""
    return rng.choice(np.array([-1.0, 1.0]), size=n)


# --------------------------------------------------------------------------------------------- codecs


def _encode(image: Image.Image, fmt: str, quality: int) -> Image.Image:
    buffer = io.BytesIO()
    image.save(buffer, format=fmt, quality=int(quality))
    buffer.seek(0)
    with Image.open(buffer) as decoded:
        return decoded.convert("RGB")


def jpeg(images: np.ndarray, rng: np.random.Generator, *, quality: int) -> np.ndarray:
    """JPEG through Pillow's libjpeg at ``quality`` (1..100; Pillow's defaults: 4:2:0 chroma, IJG tables)."""
    del rng  # deterministic
    return _pil(images, lambda x: _encode(x, "JPEG", quality))


def webp(images: np.ndarray, rng: np.random.Generator, *, quality: int) -> np.ndarray:
    """Lossy WebP through Pillow's libwebp at ``quality`` (0..100); AttackError where Pillow lacks WebP."""
    del rng  # deterministic
    if not WEBP_SUPPORTED:
        raise AttackError("this Pillow was built without WebP support")
    return _pil(images, lambda x: _encode(x, "WEBP", quality))


# ------------------------------------------------------------------------------------------ geometric


def crop(images: np.ndarray, rng: np.random.Generator, *, area: float, random: bool = False) -> np.ndarray:
    """Keep ``area`` (0..1] of each image, each side scaled by √area, left at the new size: centred, or
    (``random``) at a position drawn per image."""
    images = check_images(images)
    b, h, w = images.shape[:3]
    if not 0.0 < area <= 1.0:
        raise AttackError(f"a crop keeps a fraction of the area in (0, 1], got {area}")
    ch, cw = (max(4, round(n * float(np.sqrt(area)))) for n in (h, w))
    if random:  # drawn image by image: an image's corner does not depend on the batch's size
        corners = [(rng.integers(0, h - ch + 1), rng.integers(0, w - cw + 1)) for _ in range(b)]
    else:
        corners = [((h - ch) // 2, (w - cw) // 2)] * b
    return np.stack([x[t : t + ch, s : s + cw] for x, (t, s) in zip(images, corners, strict=True)])


def rotate(images: np.ndarray, rng: np.random.Generator, *, degrees: float, fill: int = 0) -> np.ndarray:
    """Rotate each image about its centre by ``degrees``, clockwise or anticlockwise (drawn per image),
    bilinear (scikit-image), kept at its size; the uncovered corners get grey level ``fill`` (0: black, as
    Pillow and torchvision fill)."""
    angles = degrees * _signs(rng, len(check_images(images)))
    return _float(
        images, lambda x, a: transform.rotate(x, a, order=1, mode="constant", cval=fill / 255), angles
    )


def rescale(images: np.ndarray, rng: np.random.Generator, *, scale: float, back: bool = False) -> np.ndarray:
    """Resize by ``scale`` (scikit-image, bilinear, anti-aliased when shrinking), and with ``back`` resize
    the result to the original size again."""
    del rng  # deterministic
    h, w = check_images(images).shape[1:3]
    size = (max(4, round(h * scale)), max(4, round(w * scale)))

    def one(x: np.ndarray) -> np.ndarray:
        y = transform.resize(x, (*size, 3), order=1, anti_aliasing=scale < 1.0)
        return transform.resize(y, (h, w, 3), order=1, anti_aliasing=scale > 1.0) if back else y

    return _float(images, one)


def flip(images: np.ndarray, rng: np.random.Generator, *, vertical: bool = False) -> np.ndarray:
    """Mirror left-right (or, ``vertical``, upside down)."""
    del rng  # deterministic
    images = check_images(images)
    return np.ascontiguousarray(images[:, ::-1] if vertical else images[:, :, ::-1])


def translate(images: np.ndarray, rng: np.random.Generator, *, fraction: float, fill: int = 0) -> np.ndarray:
    """Shift each image by ``fraction`` of its height and of its width, each direction drawn per image; the
    uncovered band gets grey level ``fill``. Hand-written: an integer shift needs no resampling."""
    images = check_images(images)
    b, h, w = images.shape[:3]
    signs = [_signs(rng, 2) for _ in range(b)]  # image by image, as crop draws
    out = np.full_like(images, fill)
    for x, y, (sy, sx) in zip(images, out, signs, strict=True):
        dy, dx = round(sy * fraction * h), round(sx * fraction * w)
        y[max(dy, 0) : h + min(dy, 0), max(dx, 0) : w + min(dx, 0)] = x[
            max(-dy, 0) : h - max(dy, 0), max(-dx, 0) : w - max(dx, 0)
        ]
    return out


# ---------------------------------------------------------------------------------------- photometric


def brightness(images: np.ndarray, rng: np.random.Generator, *, factor: float) -> np.ndarray:
    """Every channel × ``factor`` (Pillow's ImageEnhance.Brightness: a blend with black)."""
    del rng  # deterministic
    return _pil(images, lambda x: ImageEnhance.Brightness(x).enhance(factor))


def contrast(images: np.ndarray, rng: np.random.Generator, *, factor: float) -> np.ndarray:
    """Contrast × ``factor`` about the image's mean grey (Pillow's ImageEnhance.Contrast)."""
    del rng  # deterministic
    return _pil(images, lambda x: ImageEnhance.Contrast(x).enhance(factor))


def saturation(images: np.ndarray, rng: np.random.Generator, *, factor: float) -> np.ndarray:
    """Saturation × ``factor``: a blend with the greyscale image (Pillow's ImageEnhance.Color)."""
    del rng  # deterministic
    return _pil(images, lambda x: ImageEnhance.Color(x).enhance(factor))


def hue(images: np.ndarray, rng: np.random.Generator, *, turns: float) -> np.ndarray:
    """HSV hue rotated by ``turns`` (a fraction of the colour wheel), either way (drawn per image)
    (scikit-image's HSV conversion)."""
    shifts = turns * _signs(rng, len(check_images(images)))

    def one(x: np.ndarray, shift: float) -> np.ndarray:
        hsv = color.rgb2hsv(x)
        hsv[..., 0] = np.mod(hsv[..., 0] + shift, 1.0)
        return color.hsv2rgb(hsv)

    return _float(images, one, shifts)


def gamma(images: np.ndarray, rng: np.random.Generator, *, gamma: float) -> np.ndarray:
    """``x ↦ x^gamma`` in [0, 1] units (scikit-image's adjust_gamma; > 1 darkens the mid-tones)."""
    del rng  # deterministic
    return _each(images, lambda x: exposure.adjust_gamma(x, gamma))


def greyscale(images: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Greyscale (Pillow's ITU-R 601 luma), stored as RGB again."""
    del rng  # deterministic
    return _pil(images, lambda x: x.convert("L"))


# ------------------------------------------------------------------------------------ noise and blur


def gaussian_noise(images: np.ndarray, rng: np.random.Generator, *, sigma: float) -> np.ndarray:
    """``+ N(0, sigma²)`` per pixel and channel, ``sigma`` in [0, 1] units (the peers' σ = 0.1 is 25.5 grey
    levels), clipped (scikit-image's random_noise)."""
    return _float(images, lambda x: util.random_noise(x, mode="gaussian", var=sigma**2, rng=rng))


def salt_and_pepper(images: np.ndarray, rng: np.random.Generator, *, amount: float) -> np.ndarray:
    """``amount`` of the pixel values set to 0 or 1, half each (scikit-image's random_noise)."""
    return _float(images, lambda x: util.random_noise(x, mode="s&p", amount=amount, rng=rng))


def gaussian_blur(images: np.ndarray, rng: np.random.Generator, *, sigma: float) -> np.ndarray:
    """Gaussian blur of ``sigma`` pixels, 4σ truncation, nearest-edge borders (scikit-image)."""
    del rng  # deterministic
    return _float(images, lambda x: filters.gaussian(x, sigma=sigma, channel_axis=-1))


def median_blur(images: np.ndarray, rng: np.random.Generator, *, size: int) -> np.ndarray:
    """Median over ``size × size`` windows (odd), per channel (Pillow's MedianFilter)."""
    del rng  # deterministic
    return _pil(images, lambda x: x.filter(ImageFilter.MedianFilter(size)))


def motion_kernel(length: int, degrees: float) -> np.ndarray:
    """A ``length × length`` (odd) line kernel through the centre at ``degrees``, summing to 1.
    Hand-written (neither Pillow nor scikit-image offers one): the line, ``length`` pixels long, is sampled
    8 times per pixel and each sample splats into its nearest cell (a level line: ``1/length`` each)."""
    if length < 1 or length % 2 == 0:
        raise AttackError(f"a motion-blur length is an odd number of pixels, got {length}")
    half = (length - 1) / 2
    t = (np.arange(8 * length) + 0.5) / 8 - length / 2
    rows = np.round(half - t * np.sin(np.radians(degrees))).astype(int)
    cols = np.round(half + t * np.cos(np.radians(degrees))).astype(int)
    kernel = np.zeros((length, length))
    np.add.at(kernel, (rows, cols), 1.0)
    return kernel / kernel.sum()


def motion_blur(images: np.ndarray, rng: np.random.Generator, *, length: int) -> np.ndarray:
    """Linear motion blur over ``length`` pixels (odd) in a direction drawn per image (uniform in [0°,
    180°)), reflected borders (SciPy's correlate)."""
    angles = rng.uniform(0.0, 180.0, size=len(check_images(images)))
    kernels = [motion_kernel(length, a)[..., None] for a in angles]
    return _float(images, lambda x, k: scipy.ndimage.correlate(x, k, mode="reflect"), kernels)


# ------------------------------------------------------------------- regeneration stand-ins: denoisers


def denoise_tv(images: np.ndarray, rng: np.random.Generator, *, weight: float) -> np.ndarray:
    """Total-variation denoising of ``weight`` (scikit-image's denoise_tv_chambolle, per channel)."""
    del rng  # deterministic
    return _float(images, lambda x: restoration.denoise_tv_chambolle(x, weight=weight, channel_axis=-1))


def denoise_bilateral(
    images: np.ndarray, rng: np.random.Generator, *, sigma_color: float, sigma_spatial: float
) -> np.ndarray:
    """Bilateral filter: ``sigma_color`` in [0, 1] units, ``sigma_spatial`` pixels (scikit-image)."""
    del rng  # deterministic
    return _float(
        images,
        lambda x: restoration.denoise_bilateral(
            x, sigma_color=sigma_color, sigma_spatial=sigma_spatial, channel_axis=-1
        ),
    )


def denoise_wavelet(images: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Wavelet denoising, noise level estimated per image (scikit-image's denoise_wavelet: BayesShrink, soft
    thresholds, in YCbCr)."""
    del rng  # deterministic
    return _float(
        images,
        lambda x: restoration.denoise_wavelet(x, convert2ycbcr=True, rescale_sigma=True, channel_axis=-1),
    )
