"""The 14 augmentations: shapes, ranges, gradients, parameters, and the random policy."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from mnerf_jax.imaging import augment, filters
from mnerf_jax.imaging.augment import AUGMENTATION_NAMES, AUGMENTATIONS, PARAMS, STRENGTHS
from mnerf_jax.imaging.jpeg import jpeg


@functools.cache
def _jitted(name: str, strength: str):
    """``apply(name, ·, ·, strength)`` compiled once per test session."""
    return jax.jit(functools.partial(augment.apply, name, strength=strength))


def _images(shape=(2, 17, 20, 3), seed=0) -> jax.Array:
    """Smooth random images with some saturated pixels, in [0, 1]."""
    rng = np.random.default_rng(seed)
    x = ndimage.gaussian_filter(rng.random(shape), sigma=(0, 1.5, 1.5, 0))
    x = (x - x.min()) / (x.max() - x.min()) * 1.2 - 0.1
    return jnp.asarray(np.clip(x, 0.0, 1.0), jnp.float32)


def test_registry_has_the_fourteen_augmentations():
    assert set(AUGMENTATION_NAMES) == {
        "brightness",
        "contrast",
        "color_jiggle",
        "gaussian_blur",
        "gaussian_noise",
        "hue",
        "posterize",
        "rgb_shift",
        "saturation",
        "median_blur",
        "box_blur",
        "motion_blur",
        "sharpness",
        "jpeg",
    }
    for strength in STRENGTHS:
        assert set(PARAMS[strength]) == set(AUGMENTATION_NAMES)


@pytest.mark.parametrize("strength", STRENGTHS)
@pytest.mark.parametrize("name", AUGMENTATION_NAMES)
def test_shape_range_and_gradient(name, strength):
    x = _images()
    probe = jax.random.normal(jax.random.key(7), x.shape)

    @jax.jit
    def run(key, images):
        out, vjp = jax.vjp(lambda y: AUGMENTATIONS[name](key, y, strength), images)
        return out, vjp(probe)[0]

    out, grad = run(jax.random.key(1), x)
    assert out.shape == x.shape and out.dtype == x.dtype
    assert bool(jnp.all(jnp.isfinite(out)))
    assert float(out.min()) >= 0.0 and float(out.max()) <= 1.0
    assert bool(jnp.all(jnp.isfinite(grad)))
    assert float(jnp.linalg.norm(grad)) > 1e-3
    assert float(jnp.abs(out - x).max()) > 0.0  # it did something


def test_single_image_is_accepted():
    x = _images((1, 12, 14, 3))
    key = jax.random.key(3)
    for name in ("hue", "motion_blur"):
        single = _jitted(name, "medium")(key, x[0])
        assert single.shape == x.shape[1:]
        np.testing.assert_allclose(single, _jitted(name, "medium")(key, x)[0], atol=1e-6)


def test_same_key_same_result_and_keys_matter():
    x = _images()
    for name in ("gaussian_noise", "motion_blur", "rgb_shift"):
        a = _jitted(name, "high")(jax.random.key(0), x)
        b = _jitted(name, "high")(jax.random.key(0), x)
        c = _jitted(name, "high")(jax.random.key(1), x)
        np.testing.assert_array_equal(a, b)
        assert float(jnp.abs(a - c).max()) > 1e-4


def test_unknown_name_and_strength_raise():
    x = _images()
    with pytest.raises(augment.AugmentError):
        augment.apply("rotate", jax.random.key(0), x, "low")
    with pytest.raises(augment.AugmentError):
        augment.apply("hue", jax.random.key(0), x, "extreme")


def test_brightness_shift_stays_in_its_range():
    grey = jnp.full((64, 4, 4, 3), 0.5)
    lo, hi = PARAMS["medium"]["brightness"]["factor"]
    out = _jitted("brightness", "medium")(jax.random.key(0), grey)
    shift = np.asarray(out[:, 0, 0, 0]) - 0.5
    assert shift.min() >= lo - 1 - 1e-6 and shift.max() <= hi - 1 + 1e-6
    assert shift.max() - shift.min() > 0.5 * (hi - lo)  # drawn per image


def test_contrast_is_mean_centred():
    x = _images((4, 16, 16, 3)) * 0.5 + 0.25  # far from the clip limits
    out = _jitted("contrast", "high")(jax.random.key(0), x)
    np.testing.assert_allclose(out.mean(axis=(1, 2)), x.mean(axis=(1, 2)), atol=1e-5)


def test_rgb_shift_is_a_per_channel_constant_within_the_limit():
    x = jnp.full((3, 5, 5, 3), 0.5)
    limit = PARAMS["high"]["rgb_shift"]["shift"]
    out = np.asarray(_jitted("rgb_shift", "high")(jax.random.key(2), x))
    shift = out - 0.5
    np.testing.assert_allclose(shift, shift[:, :1, :1, :] * np.ones_like(shift), atol=1e-6)
    assert np.abs(shift).max() <= limit + 1e-6


def test_posterize_values_and_straight_through_gradient():
    x = _images()
    for strength in STRENGTHS:
        bits = PARAMS[strength]["posterize"]["bits"]
        out = np.asarray(_jitted("posterize", strength)(jax.random.key(0), x)) * 255.0
        levels = np.round(out) / 2 ** (8 - bits)
        np.testing.assert_allclose(levels, np.round(levels), atol=1e-3)
        expected = np.floor(np.floor(np.asarray(x) * 255.0) / 2 ** (8 - bits)) * 2 ** (8 - bits)
        np.testing.assert_allclose(out, expected, atol=1e-3)
    grad = jax.grad(lambda y: jnp.sum(augment.posterize(y, 3)))(x)
    np.testing.assert_allclose(grad, np.ones(x.shape), atol=0)


@pytest.mark.parametrize("kernel", [3, 5, 7])
def test_median_and_box_blur_match_scipy(kernel):
    x = np.asarray(_images((1, 15, 18, 3)))
    median = augment.median_blur(jnp.asarray(x), kernel)
    box = augment.box_blur(jnp.asarray(x), kernel)
    # jnp.pad's "reflect" (d c b | a b c d) is scipy's "mirror".
    size = (1, kernel, kernel, 1)
    np.testing.assert_allclose(median, ndimage.median_filter(x, size=size, mode="mirror"), atol=1e-6)
    np.testing.assert_allclose(box, ndimage.uniform_filter(x, size=size, mode="mirror"), atol=1e-5)


@pytest.mark.parametrize("kernel", [3, 5, 7])
def test_gaussian_blur_per_image_equals_dm_pix(kernel):
    # dm-pix's gaussian_blur, per image with its own sigma, on reflect-padded images, is the oracle.
    import dm_pix as pix

    x = jnp.asarray(_images((3, 12, 9, 3)))
    sigma = jnp.asarray([0.1, 0.8, 2.0])
    padded = filters.pad_reflect(x, kernel // 2)
    # Jitted: one compilation each rather than an eager dispatch per operation.
    expected = jax.jit(jax.vmap(lambda im, s: pix.gaussian_blur(im, s, kernel, padding="VALID")))(
        padded, sigma
    )
    got = jax.jit(filters.gaussian_blur_per_image, static_argnums=2)(x, sigma, kernel)
    np.testing.assert_allclose(got, expected, atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 49), st.integers(0, 2**32 - 1), st.booleans())
def test_median_sorting_network_sorts(n, seed, ties):
    # Batcher's network, cut to n values, sorts any input (ties included) by compare-exchanges alone.
    rng = np.random.default_rng(seed)
    values = rng.integers(0, 3, n) if ties else rng.random(n)
    out = list(values)
    for a, b in filters._sorting_network(n):
        assert 0 <= a < b < n
        out[a], out[b] = min(out[a], out[b]), max(out[a], out[b])
    np.testing.assert_array_equal(out, np.sort(values))


@pytest.mark.parametrize("kernel", [3, 5])
def test_median_blur_with_ties_matches_scipy_and_shares_the_gradient(kernel):
    x = np.round(np.asarray(_images((2, 9, 10, 3))) * 4) / 4  # five levels: ties everywhere
    expected = ndimage.median_filter(x, size=(1, kernel, kernel, 1), mode="mirror")
    np.testing.assert_array_equal(augment.median_blur(jnp.asarray(x), kernel), expected)
    grad = np.asarray(jax.grad(lambda y: augment.median_blur(y, kernel)[0, 4, 4, 1])(jnp.asarray(x)))
    near = slice(4 - kernel // 2, 5 + kernel // 2)
    window = x[0, near, near, 1]
    ties = window == np.median(window)
    np.testing.assert_allclose(grad.sum(), 1.0, rtol=1e-6)
    np.testing.assert_allclose(grad[0, near, near, 1], ties / ties.sum(), rtol=1e-6)


def test_median_gradient_reaches_only_the_selected_pixel():
    x = jnp.asarray(np.random.default_rng(0).random((1, 3, 3, 1)), jnp.float32)
    # The centre output's 3x3 neighbourhood is the whole image (no reflection involved).
    grad = np.asarray(jax.grad(lambda y: augment.median_blur(y, 3)[0, 1, 1, 0])(x))
    assert np.count_nonzero(grad) == 1
    assert np.asarray(x).ravel()[np.argmax(grad.ravel())] == np.median(np.asarray(x))


@pytest.mark.parametrize("name", ["gaussian_blur", "median_blur", "box_blur", "motion_blur", "sharpness"])
def test_filters_keep_a_constant_image(name):
    x = jnp.full((2, 13, 11, 3), 0.3)
    out = _jitted(name, "high")(jax.random.key(5), x)
    np.testing.assert_allclose(out, x, atol=1e-5)


def test_motion_blur_kernel():
    kernel = jax.jit(augment.motion_blur_kernel, static_argnums=3)
    k = np.asarray(kernel(jnp.int32(3), 0.0, 0.0, 5))
    expected = np.zeros((5, 5))
    expected[2, 1:4] = 1 / 3
    np.testing.assert_allclose(k, expected, atol=1e-6)
    # One-sided direction: weights fall linearly to zero along the line.
    k = np.asarray(kernel(jnp.int32(5), 0.0, 1.0, 5))
    np.testing.assert_allclose(k[2], np.array([1.0, 0.75, 0.5, 0.25, 0.0]) / 2.5, atol=1e-6)
    # 90 degrees turns the line vertical; sizes smaller than the grid stay inside their own box.
    k = np.asarray(kernel(jnp.int32(3), 90.0, 0.0, 9))
    assert np.count_nonzero(k) == 3 and np.count_nonzero(k[:, 4]) == 3
    # Oblique lines: nearest-neighbour sampling keeps the centre and cells on both sides of it.
    for angle in (-63.0, 17.0, 45.0):
        k = np.asarray(kernel(jnp.int32(7), angle, 0.3, 9))
        assert abs(k.sum() - 1.0) < 1e-5 and k[0].sum() == 0 and k[:, 0].sum() == 0
        assert k[4, 4] > 0 and np.count_nonzero(k[:4]) >= 1 and np.count_nonzero(k[5:]) >= 1


def test_sharpness_factor_semantics():
    x = _images((2, 12, 12, 3))
    np.testing.assert_allclose(augment.sharpness(x, jnp.ones(2)), x, atol=1e-6)
    blurred = np.asarray(augment.sharpness(x, jnp.zeros(2)))
    kernel = np.array([[1, 1, 1], [1, 5, 1], [1, 1, 1]]) / 13.0
    ref = ndimage.correlate(np.asarray(x)[0, :, :, 0], kernel)
    np.testing.assert_allclose(blurred[0, 1:-1, 1:-1, 0], ref[1:-1, 1:-1], atol=1e-5)
    np.testing.assert_allclose(blurred[:, 0], np.asarray(x)[:, 0], atol=1e-6)  # border kept


def test_jpeg_augmentation_is_the_codec_at_the_strength_quality():
    x = _images()
    codec = jax.jit(jpeg)
    for strength in STRENGTHS:
        out = _jitted("jpeg", strength)(jax.random.key(0), x)
        np.testing.assert_allclose(out, codec(x, PARAMS[strength]["jpeg"]["quality"]), atol=1e-6)


def test_policy_choices_are_distinct_at_most_k_and_deterministic():
    seen = set()
    counts = []
    for seed in range(40):
        key = jax.random.key(seed)
        choices = np.asarray(augment.policy_choices(key, k=3, p=0.6))
        np.testing.assert_array_equal(choices, np.asarray(augment.policy_choices(key, k=3, p=0.6)))
        applied = choices[choices >= 0]
        assert choices.shape == (3,) and len(set(applied.tolist())) == len(applied) <= 3
        assert applied.max(initial=0) < len(AUGMENTATION_NAMES)
        counts.append(len(applied))
        seen.update(applied.tolist())
    assert min(counts) < 3 and max(counts) == 3  # the Bernoulli draw skips some slots, not all
    assert len(seen) > len(AUGMENTATION_NAMES) // 2
    assert np.all(np.asarray(augment.policy_choices(jax.random.key(0), k=2, p=0.0)) == -1)
    assert np.all(np.asarray(augment.policy_choices(jax.random.key(0), k=2, p=1.0)) >= 0)


def test_policy_rejects_bad_arguments():
    with pytest.raises(augment.AugmentError):
        augment.policy_choices(jax.random.key(0), k=3, names=["hue", "jpeg"])
    with pytest.raises(augment.AugmentError):
        augment.random_policy(jax.random.key(0), _images(), names=["hue", "blur"])


def test_random_policy_is_one_compiled_function_matching_its_choices():
    names = ("hue", "gaussian_noise", "box_blur", "posterize")
    x = _images()
    traces = []

    @jax.jit
    def policy(key, images):
        traces.append(1)  # runs only while tracing
        return augment.random_policy(key, images, "medium", k=2, p=0.75, names=names)

    applied_counts = set()
    for seed in range(6):
        key = jax.random.key(seed)
        out = policy(key, x)
        np.testing.assert_array_equal(out, policy(key, x))  # deterministic per key
        choices = np.asarray(augment.policy_choices(key, 2, 0.75, names))
        expected = x
        for slot, index in enumerate(choices):
            if index >= 0:
                slot_key = jax.random.fold_in(key, slot + 1)
                expected = _jitted(names[index], "medium")(slot_key, expected)
        np.testing.assert_allclose(out, expected, atol=1e-5)
        applied_counts.add(int((choices >= 0).sum()))
    assert len(traces) == 1
    assert applied_counts - {0}  # some draws applied something


def test_random_policy_accepts_legacy_uint32_keys():
    x = _images((1, 8, 8, 3))
    out = augment.random_policy(jax.random.PRNGKey(0), x, "low", p=1.0, names=("rgb_shift", "brightness"))
    assert out.shape == x.shape


def test_random_policy_over_the_whole_registry_has_a_gradient():
    # One slot keeps the compile to one copy of the registry; two slots are covered above.
    x = _images((1, 16, 16, 3))
    loss = lambda y, key: jnp.sum(augment.random_policy(key, y, "low", k=1, p=1.0) ** 2)
    grad_fn = jax.jit(jax.grad(loss))
    for seed in range(3):
        grad = grad_fn(x, jax.random.key(seed))
        assert bool(jnp.all(jnp.isfinite(grad))) and float(jnp.linalg.norm(grad)) > 0


def test_random_policy_accepts_a_single_image():
    x = _images((1, 16, 16, 3))
    policy = jax.jit(lambda key, y: augment.random_policy(key, y, "low", p=1.0, names=("hue", "box_blur")))
    np.testing.assert_allclose(policy(jax.random.key(4), x[0]), policy(jax.random.key(4), x)[0], atol=1e-6)
