"""Random real attacks for training a reader: what a platform does to an image, drawn per image.

Phase 3 refits the decoder on fixed renders, so no gradient has to pass through the attack: the images go
through the evaluation attacks themselves (:mod:`mnerf_jax.imaging.attacks`: Pillow's JPEG and WebP,
scikit-image's noise, blur and warps), not differentiable stand-ins. Each image meets one attack, or two in a
row (:data:`SECOND_ATTACK_PROB`), each drawn uniformly from :data:`TRAINING_ATTACKS` with its parameter drawn
over the range the evaluation suites span (``imaging.attack_suites``: the paper's High strength and the
peers' protocol). Only attacks that keep the image's size are drawn (a batch keeps one shape); crops are
read by the geometry search instead.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from mnerf_jax.imaging import attacks as A

Sampler = Callable[[np.random.Generator], Any]

SECOND_ATTACK_PROB = 0.5  # an image meets a second attack after the first with this probability


def _uniform(low: float, high: float) -> Sampler:
    return lambda rng: float(rng.uniform(low, high))


def _log_uniform(low: float, high: float) -> Sampler:
    """A factor uniform in log scale: halving and doubling drawn alike."""
    return lambda rng: float(np.exp(rng.uniform(np.log(low), np.log(high))))


def _integer(low: int, high: int) -> Sampler:
    return lambda rng: int(rng.integers(low, high + 1))


def _one_of(*values: int) -> Sampler:
    return lambda rng: int(rng.choice(values))


# Each attack drawn: (the attack of imaging.attacks, its parameter, how that parameter is drawn).
TRAINING_ATTACKS: dict[str, tuple[Callable[..., np.ndarray], str, Sampler]] = {
    "jpeg": (A.jpeg, "quality", _integer(10, 95)),
    **({"webp": (A.webp, "quality", _integer(10, 95))} if A.WEBP_SUPPORTED else {}),
    "gaussian_noise": (A.gaussian_noise, "sigma", _uniform(0.005, 0.12)),
    "salt_and_pepper": (A.salt_and_pepper, "amount", _uniform(0.002, 0.06)),
    "brightness": (A.brightness, "factor", _log_uniform(0.5, 2.2)),
    "contrast": (A.contrast, "factor", _uniform(0.5, 1.6)),
    "saturation": (A.saturation, "factor", _uniform(0.0, 1.8)),
    "hue": (A.hue, "turns", _uniform(0.0, 0.08)),
    "gamma": (A.gamma, "gamma", _log_uniform(0.5, 2.0)),
    "gaussian_blur": (A.gaussian_blur, "sigma", _uniform(0.1, 2.0)),
    "median_blur": (A.median_blur, "size", _one_of(3, 5)),
    "motion_blur": (A.motion_blur, "length", _one_of(3, 5, 7, 9)),
    "rotate": (A.rotate, "degrees", _uniform(1.0, 30.0)),
    "rescale": (lambda x, rng, scale: A.rescale(x, rng, scale=scale, back=True), "scale", _uniform(0.5, 1.5)),
    "translate": (A.translate, "fraction", _uniform(0.01, 0.1)),
}


def apply(name: str, images: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``images`` (uint8 ``[B, H, W, 3]``) through the training attack ``name``, its parameter drawn from
    ``rng`` once for the batch; the same shape, uint8."""
    attack, parameter, sample = TRAINING_ATTACKS[name]
    return attack(images, rng, **{parameter: sample(rng)})


def random_attacks(images: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Each of ``images`` (uint8 ``[B, H, W, 3]``) through one or two attacks of :data:`TRAINING_ATTACKS`
    drawn for it from ``rng``; uint8 ``[B, H, W, 3]``. Deterministic in ``rng``'s state, image by image."""
    images = A.check_images(images, "images to attack")
    names = list(TRAINING_ATTACKS)
    out = np.empty_like(images)
    for i, image in enumerate(images):
        x = image[None]
        for _ in range(1 + int(rng.random() < SECOND_ATTACK_PROB)):
            x = apply(names[int(rng.integers(len(names)))], x, rng)
        out[i] = x[0]
    return out
