"""The 14 differentiable image augmentations of MultiNeRF's augmentation layer, and the random policy.

Every augmentation has the signature ``fn(key, images, strength) -> images`` with ``images [B, H, W, 3]``
(``[H, W, 3]`` is accepted too) float in [0, 1], ``strength`` one of ``"low" | "medium" | "high"`` (static),
and an explicit ``jax.random`` key; random parameters are drawn per image. Outputs have the input's shape and
lie in [0, 1]. All are jit-able and differentiable w.r.t. the images.

Parameters (low / medium / high) follow MultiNeRF's supplement and kornia's semantics for each operation:

=============  ==========================================================================================
brightness     additive shift ``f − 1``, ``f ~ U(0.9, 1.1) / U(0.75, 1.25) / U(0.5, 1.5)`` (kornia)
contrast       ``f·(x − mean) + mean`` per image and channel, same ``f`` ranges (dm-pix / TF / torchvision
               convention: mean-centred, so a contrast change does not also shift the brightness the way
               kornia's plain ``f·x`` does)
saturation     HSV saturation × ``f``, same ``f`` ranges
hue            HSV hue + ``δ``, ``δ ~ U(±0.01) / U(±0.02) / U(±0.05)`` turns
color_jiggle   brightness, contrast, saturation, hue in a random order with (b, c, s, h) =
               (0.05, 0.05, 0.05, 0.01) / (0.1, 0.1, 0.1, 0.02) / (0.1, 0.1, 0.1, 0.05): factors
               ``U(1 ± b)`` etc., hue ``U(±h)`` (kornia ColorJiggle)
gaussian_blur  kernel 3 / 5 / 7, ``σ ~ U(0.1, 1.0) / U(0.1, 1.5) / U(0.1, 2.0)`` px
gaussian_noise ``+ N(0, σ²)``, ``σ`` = 0.02 / 0.04 / 0.08
posterize      keep 5 / 4 / 3 bits of the 8-bit value (straight-through gradient)
rgb_shift      per-channel additive shift ``U(±0.02) / U(±0.05) / U(±0.10)``
median_blur    kernel 3 / 5 / 7
box_blur       kernel 3 / 5 / 7
motion_blur    odd kernel size in (3, 5) / (3, 7) / (3, 9), angle ``U(±25°) / U(±45°) / U(±90°)``,
               direction ``U(±0.25) / U(±0.5) / U(±1.0)`` (kornia RandomMotionBlur)
sharpness      blend with the 3×3 smoothed image, factor ``U(0, 0.5) / U(0, 1.0) / U(0, 2.5)`` (kornia/PIL)
jpeg           differentiable JPEG at quality 30 / 15 / 5 (:mod:`mnerf_jax.imaging.jpeg`)
=============  ==========================================================================================

Spatial filters extend the image by reflection, and every augmentation ends with :func:`clip_unit` (an
exact clip with an identity gradient); both are in :mod:`mnerf_jax.imaging.filters`, with the reasons.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import Any

import dm_pix as pix
import jax
import jax.numpy as jnp

from mnerf_jax.core.errors import MnerfError
from mnerf_jax.core.watermark_config import AugmentConfig
from mnerf_jax.imaging.filters import (
    box_blur,
    clip_unit,
    filter_per_image,
    gaussian_blur_per_image,
    median_blur,
    motion_blur_kernel,
    posterize,
    sharpness,
)
from mnerf_jax.imaging.jpeg import jpeg

__all__ = [
    "AUGMENTATIONS",
    "AUGMENTATION_NAMES",
    "PARAMS",
    "STRENGTHS",
    "AugmentError",
    "apply",
    "box_blur",
    "clip_unit",
    "jpeg",
    "median_blur",
    "motion_blur_kernel",
    "policy_choices",
    "posterize",
    "random_policy",
    "sharpness",
]

Augmentation = Callable[[jax.Array, jax.Array, str], jax.Array]

STRENGTHS = ("low", "medium", "high")

# Per-strength parameters (see the module docstring for their meaning).
PARAMS: dict[str, dict[str, dict[str, Any]]] = {
    "low": {
        "brightness": {"factor": (0.9, 1.1)},
        "contrast": {"factor": (0.9, 1.1)},
        "saturation": {"factor": (0.9, 1.1)},
        "hue": {"delta": 0.01},
        "color_jiggle": {"bcsh": (0.05, 0.05, 0.05, 0.01)},
        "gaussian_blur": {"kernel": 3, "sigma": (0.1, 1.0)},
        "gaussian_noise": {"std": 0.02},
        "posterize": {"bits": 5},
        "rgb_shift": {"shift": 0.02},
        "median_blur": {"kernel": 3},
        "box_blur": {"kernel": 3},
        "motion_blur": {"kernel": (3, 5), "angle": 25.0, "direction": 0.25},
        "sharpness": {"factor": 0.5},
        "jpeg": {"quality": 30.0},
    },
    "medium": {
        "brightness": {"factor": (0.75, 1.25)},
        "contrast": {"factor": (0.75, 1.25)},
        "saturation": {"factor": (0.75, 1.25)},
        "hue": {"delta": 0.02},
        "color_jiggle": {"bcsh": (0.1, 0.1, 0.1, 0.02)},
        "gaussian_blur": {"kernel": 5, "sigma": (0.1, 1.5)},
        "gaussian_noise": {"std": 0.04},
        "posterize": {"bits": 4},
        "rgb_shift": {"shift": 0.05},
        "median_blur": {"kernel": 5},
        "box_blur": {"kernel": 5},
        "motion_blur": {"kernel": (3, 7), "angle": 45.0, "direction": 0.5},
        "sharpness": {"factor": 1.0},
        "jpeg": {"quality": 15.0},
    },
    "high": {
        "brightness": {"factor": (0.5, 1.5)},
        "contrast": {"factor": (0.5, 1.5)},
        "saturation": {"factor": (0.5, 1.5)},
        "hue": {"delta": 0.05},
        "color_jiggle": {"bcsh": (0.1, 0.1, 0.1, 0.05)},
        "gaussian_blur": {"kernel": 7, "sigma": (0.1, 2.0)},
        "gaussian_noise": {"std": 0.08},
        "posterize": {"bits": 3},
        "rgb_shift": {"shift": 0.10},
        "median_blur": {"kernel": 7},
        "box_blur": {"kernel": 7},
        "motion_blur": {"kernel": (3, 9), "angle": 90.0, "direction": 1.0},
        "sharpness": {"factor": 2.5},
        "jpeg": {"quality": 5.0},
    },
}


class AugmentError(MnerfError, ValueError):
    """An unknown augmentation name or strength."""


# --- shared helpers -------------------------------------------------------------------------------------


def _check_strength(strength: str) -> None:
    if strength not in PARAMS:
        raise AugmentError(f"unknown augmentation strength {strength!r} (known: {', '.join(STRENGTHS)})")


def _params(name: str, strength: str) -> dict[str, Any]:
    _check_strength(strength)
    return PARAMS[strength][name]


def _uniform(key: jax.Array, shape: tuple[int, ...], lo: float, hi: float) -> jax.Array:
    return jax.random.uniform(key, shape, jnp.float32, lo, hi)


def _per_image(values: jax.Array) -> jax.Array:
    """``[B]`` → ``[B, 1, 1, 1]`` to broadcast over ``[B, H, W, C]``."""
    return values[:, None, None, None]


# --- random augmentations: fn(key, images [B, H, W, 3], strength) -> images --------------------------------


def _brightness(key: jax.Array, images: jax.Array, strength: str) -> jax.Array:
    lo, hi = _params("brightness", strength)["factor"]
    f = _uniform(key, images.shape[:1], lo, hi)
    return pix.adjust_brightness(images, _per_image(f) - 1.0)


def _contrast(key: jax.Array, images: jax.Array, strength: str) -> jax.Array:
    lo, hi = _params("contrast", strength)["factor"]
    f = _uniform(key, images.shape[:1], lo, hi)
    return pix.adjust_contrast(images, _per_image(f))


def _saturation(key: jax.Array, images: jax.Array, strength: str) -> jax.Array:
    lo, hi = _params("saturation", strength)["factor"]
    f = _uniform(key, images.shape[:1], lo, hi)
    return pix.adjust_saturation(images, _per_image(f)[..., 0])


def _hue(key: jax.Array, images: jax.Array, strength: str) -> jax.Array:
    delta = _params("hue", strength)["delta"]
    d = _uniform(key, images.shape[:1], -delta, delta)
    return pix.adjust_hue(images, _per_image(d)[..., 0])


def _color_jiggle(key: jax.Array, images: jax.Array, strength: str) -> jax.Array:
    b, c, s, h = _params("color_jiggle", strength)["bcsh"]
    keys = jax.random.split(key, 5)
    n = images.shape[:1]
    fb = _per_image(_uniform(keys[0], n, 1.0 - b, 1.0 + b))
    fc = _per_image(_uniform(keys[1], n, 1.0 - c, 1.0 + c))
    fs = _per_image(_uniform(keys[2], n, 1.0 - s, 1.0 + s))[..., 0]
    fh = _per_image(_uniform(keys[3], n, -h, h))[..., 0]
    ops = (
        lambda x: pix.adjust_brightness(x, fb - 1.0),
        lambda x: pix.adjust_contrast(x, fc),
        lambda x: pix.adjust_saturation(x, fs),
        lambda x: pix.adjust_hue(x, fh),
    )
    # A random order (one per call) as kornia's ColorJiggle; each step clipped as kornia's adjust_* are.
    # A scan over the four positions compiles the four ops once; an unrolled loop of switches compiled them
    # four times each, a compile cost paid by every function that holds the policy.
    order = jax.random.permutation(keys[4], len(ops))
    branches = [lambda y, op=op: clip_unit(op(y)) for op in ops]
    x, _ = jax.lax.scan(lambda y, i: (jax.lax.switch(i, branches, y), None), images, order)
    return x


def _gaussian_blur(key: jax.Array, images: jax.Array, strength: str) -> jax.Array:
    p = _params("gaussian_blur", strength)
    kernel = p["kernel"]
    sigma = _uniform(key, images.shape[:1], *p["sigma"])
    return gaussian_blur_per_image(images, sigma, kernel)  # dm-pix's filter, faster per image (its docstring)


def _gaussian_noise(key: jax.Array, images: jax.Array, strength: str) -> jax.Array:
    std = _params("gaussian_noise", strength)["std"]
    return images + std * jax.random.normal(key, images.shape, images.dtype)


def _posterize(key: jax.Array, images: jax.Array, strength: str) -> jax.Array:
    del key  # deterministic
    return posterize(images, _params("posterize", strength)["bits"])


def _rgb_shift(key: jax.Array, images: jax.Array, strength: str) -> jax.Array:
    limit = _params("rgb_shift", strength)["shift"]
    shift = _uniform(key, (images.shape[0], 1, 1, images.shape[-1]), -limit, limit)
    return images + shift


def _median_blur(key: jax.Array, images: jax.Array, strength: str) -> jax.Array:
    del key  # deterministic
    return median_blur(images, _params("median_blur", strength)["kernel"])


def _box_blur(key: jax.Array, images: jax.Array, strength: str) -> jax.Array:
    del key  # deterministic
    return box_blur(images, _params("box_blur", strength)["kernel"])


def _motion_blur(key: jax.Array, images: jax.Array, strength: str) -> jax.Array:
    p = _params("motion_blur", strength)
    lo, hi = p["kernel"]
    sizes = jnp.arange(lo, hi + 1, 2)
    k_size, k_angle, k_dir = jax.random.split(key, 3)
    n = images.shape[:1]
    size = sizes[jax.random.randint(k_size, n, 0, sizes.size)]
    angle = _uniform(k_angle, n, -p["angle"], p["angle"])
    direction = _uniform(k_dir, n, -p["direction"], p["direction"])
    kernels = jax.vmap(lambda s, a, d: motion_blur_kernel(s, a, d, hi))(size, angle, direction)
    return filter_per_image(images, kernels)


def _sharpness(key: jax.Array, images: jax.Array, strength: str) -> jax.Array:
    factor = _uniform(key, images.shape[:1], 0.0, _params("sharpness", strength)["factor"])
    return sharpness(images, factor)


def _jpeg(key: jax.Array, images: jax.Array, strength: str) -> jax.Array:
    del key  # deterministic
    return jpeg(images, _params("jpeg", strength)["quality"])


def _finish(fn: Augmentation) -> Augmentation:
    """Wrap a ``[B, H, W, 3]`` augmentation: accept ``[H, W, 3]``, keep the dtype, clip to [0, 1]."""

    @functools.wraps(fn)
    def wrapped(key: jax.Array, images: jax.Array, strength: str = "low") -> jax.Array:
        images = jnp.asarray(images)
        if not jnp.issubdtype(images.dtype, jnp.floating):
            images = images.astype(jnp.float32)
        if images.ndim not in (3, 4) or images.shape[-1] != 3:
            raise AugmentError(f"augmentations expect images [B, H, W, 3] or [H, W, 3], got {images.shape}")
        single = images.ndim == 3
        x = images[None] if single else images
        out = clip_unit(fn(key, x, strength).astype(images.dtype))
        return out[0] if single else out

    return wrapped


AUGMENTATIONS: dict[str, Augmentation] = {
    name: _finish(fn)
    for name, fn in (
        ("brightness", _brightness),
        ("contrast", _contrast),
        ("color_jiggle", _color_jiggle),
        ("gaussian_blur", _gaussian_blur),
        ("gaussian_noise", _gaussian_noise),
        ("hue", _hue),
        ("posterize", _posterize),
        ("rgb_shift", _rgb_shift),
        ("saturation", _saturation),
        ("median_blur", _median_blur),
        ("box_blur", _box_blur),
        ("motion_blur", _motion_blur),
        ("sharpness", _sharpness),
        ("jpeg", _jpeg),
    )
}
AUGMENTATION_NAMES: tuple[str, ...] = tuple(AUGMENTATIONS)


def _check_name(name: str) -> None:
    if name not in AUGMENTATIONS:
        raise AugmentError(f"unknown augmentation {name!r} (known: {', '.join(AUGMENTATION_NAMES)})")


def apply(name: str, key: jax.Array, images: jax.Array, strength: str = "low") -> jax.Array:
    """Apply the augmentation ``name`` with ``key`` (same key, same result) at ``strength``."""
    _check_name(name)
    _check_strength(strength)
    return AUGMENTATIONS[name](key, images, strength)


def resolve_names(names: Sequence[str] | None, k: int) -> tuple[str, ...]:
    """The names a policy draws ``k`` distinct augmentations from (default: all 14), or AugmentError."""
    names = AUGMENTATION_NAMES if names is None else tuple(names)
    for name in names:
        _check_name(name)
    if len(set(names)) != len(names):
        raise AugmentError(f"augmentation names repeat: {names}")
    if not 0 <= k <= len(names):
        raise AugmentError(f"cannot draw {k} distinct augmentations from {len(names)}")
    return names


def policy_choices(
    key: jax.Array, k: int = 2, p: float = 0.75, names: Sequence[str] | None = None
) -> jax.Array:
    """The augmentations :func:`random_policy` applies for ``key``: ``[k]`` int32 indices into ``names``
    (default :data:`AUGMENTATION_NAMES`), distinct, in application order, ``-1`` where the Bernoulli(``p``)
    draw skipped that slot."""
    names = resolve_names(names, k)
    k_pick, k_apply = jax.random.split(jax.random.fold_in(key, 0))
    picked = jax.random.choice(k_pick, len(names), (k,), replace=False)
    applied = jax.random.bernoulli(k_apply, p, (k,))
    return jnp.where(applied, picked, -1).astype(jnp.int32)


def draws_any(cfg: AugmentConfig) -> bool:
    """True when a watermark config's ``augment`` section can apply an augmentation (``per_step`` and
    ``prob`` both above 0)."""
    return cfg.per_step > 0 and cfg.prob > 0


def configured_policy(key: jax.Array, images: jax.Array, cfg: AugmentConfig) -> jax.Array:
    """:func:`random_policy` as a watermark config's ``augment`` section sets it (the images unchanged when it
    draws none: :func:`draws_any`)."""
    if not draws_any(cfg):
        return images
    return random_policy(key, images, cfg.strength, k=cfg.per_step, p=cfg.prob, names=cfg.names or None)


def random_policy(
    key: jax.Array,
    images: jax.Array,
    strength: str = "low",
    k: int = 2,
    p: float = 0.75,
    names: Sequence[str] | None = None,
) -> jax.Array:
    """Apply ``k`` distinct augmentations drawn from ``names``, each with probability ``p``.

    ``images [B, H, W, 3]`` or ``[H, W, 3]`` in [0, 1]; the same augmentations for the whole batch, their
    random parameters per image. The choice is :func:`policy_choices` ``(key, k, p, names)``; slot ``i`` runs
    its augmentation with key ``fold_in(key, i + 1)``. One ``lax.switch`` over the registry per slot (the last
    branch is the identity), so a single compiled function covers every choice and only the chosen branch
    runs. (A scan over the slots runs slower and compiles no faster.)
    """
    names = resolve_names(names, k)
    _check_strength(strength)
    choices = policy_choices(key, k, p, names)
    branches = [functools.partial(AUGMENTATIONS[n], strength=strength) for n in names]
    branches.append(lambda _key, x: x)
    x = jnp.asarray(images)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.float32)
    for i in range(k):
        index = jnp.where(choices[i] < 0, len(names), choices[i])
        x = jax.lax.switch(index, branches, jax.random.fold_in(key, i + 1), x)
    return x
