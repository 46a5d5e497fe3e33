"""Differentiable JPEG against Pillow's codec, odd sizes, extreme qualities, gradients."""

from __future__ import annotations

import io

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image
from skimage import data as skdata

from mnerf_jax.imaging.augment import jpeg as augment_jpeg
from mnerf_jax.imaging.jpeg import jpeg, quant_tables, round_cubic

codec = jax.jit(jpeg)
# Gradient of the sum of the output w.r.t. the images and the (traced) quality.
sum_grad = jax.jit(jax.grad(lambda images, quality: jnp.sum(jpeg(images, quality)), argnums=(0, 1)))


def _pillow(image: np.ndarray, quality: int) -> tuple[np.ndarray, dict]:
    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="JPEG", quality=quality, subsampling=2)
    buffer.seek(0)
    decoded = Image.open(buffer)
    return np.asarray(decoded.convert("RGB"), np.float32) / 255.0, decoded.quantization


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10.0 * np.log10(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2)))


@pytest.fixture(scope="module")
def photo() -> np.ndarray:
    """A crop of a natural photograph with sizes that are not multiples of 16 (or even)."""
    return skdata.chelsea()[40:237, 101:332]


@pytest.mark.parametrize("quality", [10, 30, 50, 90])
def test_close_to_pillow(photo, quality):
    ours = np.asarray(codec(jnp.asarray(photo, jnp.float32) / 255.0, quality))
    ref, _ = _pillow(photo, quality)
    assert ours.shape == ref.shape
    agreement = _psnr(ours, ref)
    assert agreement >= 30.0
    # Much closer to the codec than the codec is to the original: the artefacts themselves are reproduced.
    assert agreement > _psnr(ref, photo / 255.0) + 6.0


@pytest.mark.parametrize("quality", [1, 5, 25, 37, 50, 75, 99, 100])
def test_tables_are_libjpegs(quality):
    _, tables = _pillow(np.zeros((8, 8, 3), np.uint8), quality)
    luma, chroma = quant_tables(float(quality))
    np.testing.assert_array_equal(np.asarray(luma), np.reshape(tables[0], (8, 8)))
    np.testing.assert_array_equal(np.asarray(chroma), np.reshape(tables[1], (8, 8)))


@settings(max_examples=8, deadline=None)
@given(h=st.integers(1, 40), w=st.integers(1, 40), seed=st.integers(0, 1000))
def test_any_size(h, w, seed):
    x = jnp.asarray(np.random.default_rng(seed).random((h, w, 3)), jnp.float32)
    out = codec(x, 50.0)
    assert out.shape == x.shape
    assert bool(jnp.all(jnp.isfinite(out))) and float(out.min()) >= 0 and float(out.max()) <= 1


def test_extreme_qualities_are_finite(photo):
    x = jnp.asarray(photo[:40, :56], jnp.float32) / 255.0
    for quality in (0.0, 1.0, 100.0, 150.0):
        out = codec(x, quality)
        grad, _ = sum_grad(x, jnp.float32(quality))
        assert bool(jnp.all(jnp.isfinite(out))) and bool(jnp.all(jnp.isfinite(grad)))
    np.testing.assert_array_equal(codec(x, 0.0), codec(x, 1.0))  # clipped to [1, 100]
    # Quality 100 still subsamples the chroma, so it is close to, not equal to, the original.
    assert _psnr(np.asarray(codec(x, 100.0)), np.asarray(x)) > 40.0


def test_quality_can_be_traced_and_per_image(photo):
    x = jnp.asarray(np.stack([photo[:32, :48], photo[32:64, :48]]), jnp.float32) / 255.0
    per_image = codec(x, jnp.array([20.0, 80.0]))
    np.testing.assert_allclose(per_image[0], codec(x[0], 20.0), atol=1e-6)
    np.testing.assert_allclose(per_image[1], codec(x[1], 80.0), atol=1e-6)
    _, grad_q = sum_grad(x[0], jnp.float32(30.0))
    assert bool(jnp.isfinite(grad_q))


@jax.jit
def _vjp(images: jax.Array, quality: jax.Array, probe: jax.Array) -> jax.Array:
    _, vjp = jax.vjp(lambda y: jpeg(y, quality), images)
    return vjp(probe)[0]


def test_gradient_is_nonzero_and_finite(photo):
    x = jnp.asarray(photo[:48, :64], jnp.float32) / 255.0
    probe = jax.random.normal(jax.random.key(0), x.shape)
    for quality in (5.0, 50.0, 95.0):
        grad = _vjp(x, jnp.float32(quality), probe)
        assert bool(jnp.all(jnp.isfinite(grad)))
        assert float(jnp.linalg.norm(grad)) > 0.01 * float(jnp.linalg.norm(probe))
    # A smooth probe (mostly low frequencies, finely quantised) passes far better than white noise.
    smooth = jnp.ones_like(x)
    assert float(jnp.linalg.norm(_vjp(x, jnp.float32(50.0), smooth))) > 0.3 * float(jnp.linalg.norm(smooth))


def test_round_cubic_forward_is_exact_and_gradient_is_cubic():
    x = jnp.linspace(-3.0, 3.0, 61) + 0.013
    np.testing.assert_array_equal(round_cubic(x), jnp.round(x))
    grad = jax.vmap(jax.grad(round_cubic))(x)
    np.testing.assert_allclose(grad, 3.0 * (x - jnp.round(x)) ** 2, rtol=1e-5, atol=1e-7)
    assert float(grad.max()) > 0.5


def test_reexported_from_augment():
    assert augment_jpeg is jpeg
