"""LL2 against PyWavelets, and its behaviour under jit, vmap and grad."""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import pywt
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mnerf_jax.reader import dwt

TOL = 1e-5


def _pywt_ll2(x: np.ndarray, wavelet: str, mode: str) -> np.ndarray:
    """PyWavelets' LL2 of ``[H, W, C]``, channel by channel (float64)."""
    with warnings.catch_warnings():
        # PyWavelets warns when level 2 exceeds its "useful" level for tiny sizes; the result is defined.
        warnings.simplefilter("ignore", UserWarning)
        planes = [pywt.wavedec2(x[..., c], wavelet, mode=mode, level=2)[0] for c in range(x.shape[-1])]
    return np.stack(planes, axis=-1)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    h=st.integers(1, 48),
    w=st.integers(1, 48),
    c=st.integers(1, 3),
    wavelet=st.sampled_from(["haar", "bior4.4"]),
    seed=st.integers(0, 2**16),
)
def test_ll2_matches_pywavelets_default_modes(h, w, c, wavelet, seed):
    x = np.random.default_rng(seed).random((h, w, c))
    mode = dwt.DEFAULT_MODE[wavelet]
    ref = _pywt_ll2(x, wavelet, mode)
    out = np.asarray(dwt.ll2(jnp.asarray(x, jnp.float32), wavelet))
    assert out.shape == ref.shape == (*dwt.ll2_shape(h, w, wavelet), c)
    np.testing.assert_allclose(out, ref, atol=TOL, rtol=0)


def test_default_modes_are_waterf_and_pywavelets_defaults():
    assert dwt.DEFAULT_MODE == {"bior4.4": "periodization", "haar": "symmetric"}
    x = np.random.default_rng(0).random((37, 29, 3))
    np.testing.assert_allclose(
        dwt.ll2(jnp.asarray(x, jnp.float32)), _pywt_ll2(x, "bior4.4", "periodization"), atol=TOL
    )


@pytest.mark.parametrize(("wavelet", "mode"), [("haar", "periodization"), ("bior4.4", "symmetric")])
@pytest.mark.parametrize(("h", "w"), [(1, 1), (3, 7), (16, 16), (33, 50)])
def test_ll2_matches_pywavelets_other_modes(wavelet, mode, h, w):
    x = np.random.default_rng(h * w).random((h, w, 2))
    out = np.asarray(dwt.ll2(jnp.asarray(x, jnp.float32), wavelet, mode))
    np.testing.assert_allclose(out, _pywt_ll2(x, wavelet, mode), atol=TOL, rtol=0)
    assert out.shape[:2] == dwt.ll2_shape(h, w, wavelet, mode)


def test_filter_taps_are_pywavelets_dec_lo():
    for name, taps in dwt.DEC_LO.items():
        np.testing.assert_array_equal(np.asarray(taps), np.asarray(pywt.Wavelet(name).dec_lo))


@pytest.mark.parametrize("wavelet", ["haar", "bior4.4"])
def test_constant_image_gives_four_times_the_value(wavelet):
    x = jnp.full((2, 24, 40, 3), 0.6)
    np.testing.assert_allclose(dwt.ll2(x, wavelet), 2.4, atol=1e-5)


def test_batch_dimensions_jit_vmap():
    x = jnp.asarray(np.random.default_rng(1).random((2, 3, 20, 26, 3)), jnp.float32)
    ref = np.stack(
        [
            np.stack([_pywt_ll2(np.asarray(x[i, j]), "bior4.4", "periodization") for j in range(3)])
            for i in range(2)
        ]
    )
    np.testing.assert_allclose(dwt.ll2(x), ref, atol=TOL)
    np.testing.assert_allclose(jax.jit(dwt.ll2)(x), ref, atol=TOL)
    np.testing.assert_allclose(jax.vmap(jax.vmap(dwt.ll2))(x), ref, atol=TOL)
    np.testing.assert_allclose(jax.jit(dwt.ll2, static_argnums=1)(x, "haar"), dwt.ll2(x, "haar"), atol=1e-6)


def _pywt_axis_matrix(n: int, wavelet: str) -> np.ndarray:
    """The 1-D level-2 approximation as a matrix ``[n2, n]``: PyWavelets applied to unit vectors."""
    mode = dwt.DEFAULT_MODE[wavelet]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return np.stack(
            [pywt.wavedec(np.eye(n)[i], wavelet, mode=mode, level=2)[0] for i in range(n)], axis=1
        )


@pytest.mark.parametrize("wavelet", ["haar", "bior4.4"])
def test_gradient_is_the_transposed_analysis(wavelet):
    # d/dx Σ (g ⊙ LL2(x)) = A_hᵀ g A_w per channel, with A built from PyWavelets independently.
    rng = np.random.default_rng(2)
    x = jnp.asarray(rng.random((19, 22, 3)), jnp.float32)
    g = rng.standard_normal((*dwt.ll2_shape(19, 22, wavelet), 3))
    grad = jax.grad(lambda y: jnp.sum(jnp.asarray(g, jnp.float32) * dwt.ll2(y, wavelet)))(x)
    expected = np.einsum("ph,pqc,qw->hwc", _pywt_axis_matrix(19, wavelet), g, _pywt_axis_matrix(22, wavelet))
    np.testing.assert_allclose(grad, expected, atol=1e-5)
    np.testing.assert_allclose(dwt.ll2_matrix(19, wavelet), _pywt_axis_matrix(19, wavelet), atol=1e-6)


def test_unknown_wavelet_or_mode_raises():
    x = jnp.zeros((8, 8, 3))
    with pytest.raises(ValueError, match="wavelet"):
        dwt.ll2(x, "db2")
    with pytest.raises(ValueError, match="mode"):
        dwt.ll2(x, "haar", "zero")
    with pytest.raises(ValueError, match="H, W, C"):
        dwt.ll2(jnp.zeros((8, 8)))
