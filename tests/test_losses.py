"""Losses: BCE at temperature 10, Watson-DCT, LPIPS-VGG, SSIM, total variation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage

from mnerf_jax.imaging import losses
from mnerf_jax.imaging.jpeg import DCT8

watson = jax.jit(losses.watson_dct_loss, static_argnames="chroma")
watson_grads = jax.jit(jax.value_and_grad(losses.watson_dct_loss, argnums=(0, 1)))


def _images(shape=(2, 32, 40, 3), seed=0) -> jax.Array:
    rng = np.random.default_rng(seed)
    x = ndimage.gaussian_filter(rng.random(shape), sigma=(0, 2, 2, 0))
    return jnp.asarray((x - x.min()) / (x.max() - x.min()) * 0.8 + 0.1, jnp.float32)


def test_bce_matches_numpy_reference():
    rng = np.random.default_rng(0)
    logits = rng.normal(scale=0.8, size=(4, 48))
    bits = rng.integers(0, 2, size=(4, 48))
    z = logits * 10.0
    p = 1.0 / (1.0 + np.exp(-z))
    expected = np.mean(-(bits * np.log(p) + (1 - bits) * np.log1p(-p)))
    np.testing.assert_allclose(losses.bce_with_logits(logits, bits), expected, rtol=1e-5)
    np.testing.assert_allclose(
        losses.bce_with_logits(logits, bits, temperature=1.0), _bce_t1(logits, bits), rtol=1e-5
    )


def test_key_cross_entropy_is_the_posterior_over_keys_from_independent_bits():
    # Key j's log-likelihood Σ_b log σ(T·z_b·s_jb), s = 2·key − 1, normalised over the N keys (uniform prior).
    rng = np.random.default_rng(1)
    logits = rng.normal(scale=0.4, size=(5, 12))
    keys = rng.integers(0, 2, size=(7, 12))
    ids = np.array([0, 3, 6, 3, 1])
    signs = 2.0 * keys - 1.0
    log_lik = -np.logaddexp(0.0, -10.0 * logits[:, None, :] * signs[None]).sum(-1)  # [K, N]
    log_post = log_lik - np.logaddexp.reduce(log_lik, axis=-1, keepdims=True)
    expected = -np.mean(log_post[np.arange(5), ids])
    np.testing.assert_allclose(losses.key_cross_entropy(logits, keys, ids), expected, rtol=1e-5)
    # Its gradient lies only on the bits where the own key differs from another: equal keys move nothing.
    same = np.repeat(keys[:1], 7, axis=0)
    grad = jax.grad(losses.key_cross_entropy)(jnp.asarray(logits), same, ids)
    np.testing.assert_allclose(grad, 0.0, atol=1e-7)
    # A render read as its own key with a wide margin costs almost nothing; read as another key, a lot.
    confident = 0.5 * signs[ids]
    assert float(losses.key_cross_entropy(confident, keys, ids)) < 1e-3
    assert float(losses.key_cross_entropy(0.5 * signs[(ids + 1) % 7], keys, ids)) > 5.0


def _bce_t1(logits: np.ndarray, bits: np.ndarray) -> float:
    p = 1.0 / (1.0 + np.exp(-logits))
    return float(np.mean(-(bits * np.log(p) + (1 - bits) * np.log(1 - p))))


def test_bce_is_stable_for_large_logits():
    logits = jnp.array([[100.0, -100.0, 100.0]])
    bits = jnp.array([[1, 0, 0]])
    value = losses.bce_with_logits(logits, bits)
    np.testing.assert_allclose(value, 1000.0 / 3, rtol=1e-5)
    assert bool(jnp.all(jnp.isfinite(jax.grad(losses.bce_with_logits)(logits, bits))))


def test_watson_zero_for_identical_images_with_finite_gradient():
    x = _images()
    value, grads = watson_grads(x, x)
    assert float(value) == 0.0
    assert all(bool(jnp.all(jnp.isfinite(g))) for g in grads)


def test_watson_increases_with_noise_and_has_a_gradient():
    x = _images()
    values = []
    for i, sigma in enumerate((0.002, 0.01, 0.03, 0.1)):
        noise = jax.random.normal(jax.random.key(i), x.shape)
        values.append(float(watson(jnp.clip(x + sigma * noise, 0, 1), x)))
    assert values[0] > 0 and all(b > a for a, b in zip(values, values[1:], strict=False))
    y = jnp.clip(x + 0.03 * jax.random.normal(jax.random.key(9), x.shape), 0, 1)
    _, (grad_test, grad_ref) = watson_grads(y, x)
    for grad in (grad_test, grad_ref):
        assert bool(jnp.all(jnp.isfinite(grad))) and float(jnp.linalg.norm(grad)) > 0


def test_watson_weights_low_frequencies_more():
    # Two errors of the same energy in one 8x8 block of a flat grey image: DCT coefficient (0, 1) vs (7, 7).
    grey = jnp.full((1, 16, 16, 3), 0.5)
    basis = lambda u, v: np.outer(DCT8[u], DCT8[v])  # unit-energy DCT basis image
    low = np.zeros((16, 16))
    high = np.zeros((16, 16))
    low[:8, :8] = basis(0, 1)
    high[:8, :8] = basis(7, 7)
    bump = lambda e: grey + 0.02 * jnp.asarray(e, jnp.float32)[None, :, :, None]
    assert float(losses.watson_dct_loss(bump(low), grey)) > 5 * float(
        losses.watson_dct_loss(bump(high), grey)
    )


def test_watson_contrast_masking():
    # The same error is less visible on a textured reference than on a flat one.
    rng = np.random.default_rng(3)
    flat = jnp.full((1, 32, 32, 3), 0.5)
    texture = jnp.asarray(0.5 + 0.3 * (rng.random((1, 32, 32, 1)) - 0.5), jnp.float32) * jnp.ones(
        (1, 1, 1, 3)
    )
    error = 0.01 * jnp.asarray(rng.standard_normal((1, 32, 32, 1)), jnp.float32)
    assert float(losses.watson_dct_loss(texture + error, texture)) < float(
        losses.watson_dct_loss(flat + error, flat)
    )


def test_watson_chroma_option_and_odd_sizes():
    x = _images((1, 21, 27, 3))
    y = x.at[..., 2].add(0.05)  # a blue shift: mostly chroma
    luma_only = float(watson(y, x))
    with_chroma = float(watson(y, x, chroma=True))
    assert with_chroma > luma_only > 0
    with pytest.raises(ValueError):
        losses.watson_dct_loss(x, x[:, :20])


def test_watson_dark_reference_is_finite():
    black = jnp.zeros((1, 16, 16, 3))
    value, grads = watson_grads(black + 0.01, black)
    assert np.isfinite(float(value)) and float(value) > 0
    assert all(bool(jnp.all(jnp.isfinite(g))) for g in grads)


def test_vgg_perceptual_loss():
    x = _images((1, 32, 32, 3))
    y = jnp.clip(x + 0.05 * jax.random.normal(jax.random.key(0), x.shape), 0, 1)
    params = losses.vgg_params()
    loss = jax.jit(jax.value_and_grad(losses.vgg_perceptual_loss))
    same, _ = loss(x, x, params)
    different, grad = loss(y, x, params)
    assert abs(float(same)) < 1e-6 and float(different) > 1e-3
    assert bool(jnp.all(jnp.isfinite(grad))) and float(jnp.linalg.norm(grad)) > 0


def test_ssim_loss():
    x = _images()
    ssim = jax.jit(jax.value_and_grad(losses.ssim_loss))
    assert abs(float(ssim(x, x)[0])) < 1e-5
    y = jnp.clip(x + 0.05 * jax.random.normal(jax.random.key(0), x.shape), 0, 1)
    value, grad = ssim(y, x)
    assert 0 < float(value) < 2 and bool(jnp.all(jnp.isfinite(grad)))


@pytest.mark.parametrize("shape", [(1, 11, 11), (1, 23, 17), (2, 40, 33)])
def test_ssim_loss_is_dm_pix_ssim(shape):
    # The loss filters with matrix products; dm-pix's own SSIM (its convolutions) is the oracle.
    import dm_pix as pix

    x = _images((*shape, 3))
    y = jnp.clip(x + 0.1 * jax.random.normal(jax.random.key(1), x.shape), 0, 1)
    reference = lambda a: 1.0 - jnp.mean(pix.ssim(a, x, max_val=1.0))  # noqa: E731
    # Jitted: one compilation each instead of an eager dispatch per operation (and per its gradient).
    loss_and_grad = jax.jit(jax.value_and_grad(losses.ssim_loss))
    reference_and_grad = jax.jit(jax.value_and_grad(reference))
    (value, grad), (expected_value, expected) = loss_and_grad(y, x), reference_and_grad(y)
    np.testing.assert_allclose(value, expected_value, atol=2e-5)  # float32 summation order
    expected = np.asarray(expected)
    np.testing.assert_allclose(grad, expected, atol=2e-3 * np.abs(expected).max())


def test_total_variation_matches_numpy_and_is_zero_for_constants():
    x = np.asarray(_images((2, 9, 11, 3)))
    expected = 2 * (np.mean(np.diff(x, axis=1) ** 2) + np.mean(np.diff(x, axis=2) ** 2))
    np.testing.assert_allclose(losses.total_variation(jnp.asarray(x)), expected, rtol=1e-5)
    assert float(losses.total_variation(jnp.full((4, 4, 3), 0.7))) == 0.0
    grad = jax.grad(losses.total_variation)(jnp.asarray(x))
    assert bool(jnp.all(jnp.isfinite(grad))) and float(jnp.linalg.norm(grad)) > 0
