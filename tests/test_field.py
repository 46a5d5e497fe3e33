"""TensoRF field: MLP_Fea input layout, extra rows, init, density activation, parameter count."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mnerf_jax.core.config import ModelConfig
from mnerf_jax.tensorf import field, grid_volume, grids

CFG = ModelConfig()
SMALL = ModelConfig(density_ranks=(2, 3, 4), appearance_ranks=(3, 2, 5), app_features=6, mlp_width=16)

# Jitted: one compilation per function instead of one per primitive.
density = jax.jit(field.density, static_argnums=2)
colour = jax.jit(field.colour, static_argnums=3)
colour_mlp = jax.jit(field.colour_mlp, static_argnums=3)
appearance_features = jax.jit(field.appearance_features)


def test_positional_encoding_order():
    x = jnp.asarray([[0.3, -1.2]])
    got = np.asarray(field.positional_encoding(x, 2))[0]
    a, b = 0.3, -1.2
    # TensoRF: (x[..., None] * 2^k).reshape -> index d * F + k, then [sin ..., cos ...].
    expected = [
        np.sin(a),
        np.sin(2 * a),
        np.sin(b),
        np.sin(2 * b),
        np.cos(a),
        np.cos(2 * a),
        np.cos(b),
        np.cos(2 * b),
    ]
    np.testing.assert_allclose(got, expected, rtol=1e-6)


def test_mlp_input_widths():
    assert field.mlp_in_features(CFG) == 150  # Blender: 27 + 3 + 108 + 12
    llff = dataclasses.replace(CFG, pe_features=0, pe_view=0)
    assert field.mlp_in_features(llff) == 30
    feats = jnp.ones((4, 27))
    dirs = jnp.ones((4, 3))
    assert field.mlp_inputs(feats, dirs, CFG).shape == (4, 150)
    assert field.mlp_inputs(feats, dirs, llff).shape == (4, 30)


def _numpy_mlp(mlp, x):
    h = np.maximum(x @ mlp["w0"] + mlp["b0"], 0)
    h = np.maximum(h @ mlp["w1"] + mlp["b1"], 0)
    return h, h @ mlp["w2"] + mlp["b2"]


def test_colour_mlp_is_mlp_fea_and_extra_rows_enter_the_last_layer():
    key = jax.random.PRNGKey(0)
    mlp = {k: np.asarray(v) for k, v in field.init_mlp(key, CFG).items()}
    mlp["b2"] = np.asarray([0.1, -0.2, 0.3], np.float32)
    rng = np.random.default_rng(0)
    feats = rng.normal(size=(7, 27)).astype(np.float32)
    dirs = rng.normal(size=(7, 3)).astype(np.float32)
    x = np.asarray(field.mlp_inputs(jnp.asarray(feats), jnp.asarray(dirs), CFG))
    np.testing.assert_allclose(x[:, :27], feats)
    np.testing.assert_allclose(x[:, 27:30], dirs)
    _, logits = _numpy_mlp(mlp, x)
    plain = np.asarray(colour_mlp(mlp, feats, dirs, CFG))
    np.testing.assert_allclose(plain, 1 / (1 + np.exp(-logits)), atol=1e-5)

    extra = rng.normal(size=(7, 5)).astype(np.float32)
    zero_rows = dict(mlp, out_extra=np.zeros((5, 3), np.float32))
    np.testing.assert_allclose(
        np.asarray(colour_mlp(zero_rows, feats, dirs, CFG, extra_last=extra)), plain, atol=1e-6
    )
    rows = rng.normal(size=(5, 3)).astype(np.float32)
    with_rows = dict(mlp, out_extra=rows)
    got = np.asarray(colour_mlp(with_rows, feats, dirs, CFG, extra_last=extra))
    assert np.abs(got - plain).max() > 1e-3
    np.testing.assert_allclose(got, 1 / (1 + np.exp(-(logits + extra @ rows))), atol=1e-5)


def test_extra_first_enters_the_first_layer():
    mlp = {k: np.asarray(v) for k, v in field.init_mlp(jax.random.PRNGKey(1), CFG).items()}
    rng = np.random.default_rng(1)
    feats = rng.normal(size=(5, 27)).astype(np.float32)
    dirs = rng.normal(size=(5, 3)).astype(np.float32)
    extra = rng.normal(size=(5, 4)).astype(np.float32)
    rows = rng.normal(size=(4, CFG.mlp_width)).astype(np.float32)
    got = np.asarray(colour_mlp(dict(mlp, in_extra=rows), feats, dirs, CFG, extra_first=extra))
    x = np.asarray(field.mlp_inputs(jnp.asarray(feats), jnp.asarray(dirs), CFG))
    h = np.maximum(x @ mlp["w0"] + mlp["b0"] + extra @ rows, 0)
    h = np.maximum(h @ mlp["w1"] + mlp["b1"], 0)
    np.testing.assert_allclose(got, 1 / (1 + np.exp(-(h @ mlp["w2"] + mlp["b2"]))), atol=1e-5)
    plain = np.asarray(colour_mlp(mlp, feats, dirs, CFG))
    assert np.abs(got - plain).max() > 1e-3


def test_init_field_shapes_and_torch_init():
    params = field.init_field(jax.random.PRNGKey(2), CFG, (10, 12, 14))
    assert params["basis"].shape == (144, 27)
    assert grids.vm_ranks(params["density"]) == (16, 16, 16)
    assert grids.vm_ranks(params["appearance"]) == (48, 48, 48)
    assert grids.vm_resolution(params["appearance"]) == (10, 12, 14)
    mlp = params["mlp"]
    assert mlp["w0"].shape == (150, 128) and mlp["w1"].shape == (128, 128) and mlp["w2"].shape == (128, 3)
    assert np.all(np.asarray(mlp["b2"]) == 0)
    for name, fan_in in (("w0", 150), ("w1", 128), ("w2", 128), ("b0", 150)):
        bound = 1 / np.sqrt(fan_in)
        vals = np.asarray(mlp[name])
        assert np.abs(vals).max() <= bound and np.abs(vals).max() > 0.8 * bound
    assert np.abs(np.asarray(params["basis"])).max() <= 1 / np.sqrt(144)


def test_density_activation_and_features():
    params = field.init_field(jax.random.PRNGKey(3), SMALL, (5, 6, 7))
    xyz = jax.random.uniform(jax.random.PRNGKey(4), (9, 3), minval=-1, maxval=1)
    feature = jax.jit(grid_volume.sample_vm_sum)(params["density"], xyz)
    sigma = density(params, xyz, SMALL)
    np.testing.assert_allclose(np.asarray(sigma), np.log1p(np.exp(np.asarray(feature) - 10.0)), rtol=1e-5)
    relu_cfg = dataclasses.replace(SMALL, density_activation="relu")
    np.testing.assert_allclose(np.asarray(density(params, xyz, relu_cfg)), np.maximum(np.asarray(feature), 0))
    with pytest.raises(ValueError):
        density(params, xyz, dataclasses.replace(SMALL, density_activation="exp"))
    feats = appearance_features(params, xyz)
    assert feats.shape == (9, 6)
    np.testing.assert_allclose(
        np.asarray(feats),
        np.asarray(jax.jit(grids.sample_vm)(params["appearance"], xyz)) @ np.asarray(params["basis"]),
        rtol=1e-5,
        atol=1e-6,
    )
    rgb = np.asarray(colour(params, xyz, jnp.ones((9, 3)) / np.sqrt(3), SMALL))
    assert rgb.shape == (9, 3) and np.all((rgb > 0) & (rgb < 1))


def test_param_count_matches_tensorf_size():
    small = field.init_field(jax.random.PRNGKey(5), SMALL, (5, 6, 7))
    assert field.param_count(small) == sum(x.size for x in jax.tree_util.tree_leaves(small))
    # VM-192 at 300^3 (shapes only, nothing allocated): TensoRF's ~17.4 M parameters.
    shapes = jax.eval_shape(lambda k: field.init_field(k, CFG, (300, 300, 300)), jax.random.PRNGKey(0))
    n = field.param_count(shapes)
    grid_part = 3 * (300 * 300 + 300) * (16 + 48)
    mlp_part = 150 * 128 + 128 + 128 * 128 + 128 + 128 * 3 + 3
    assert n == grid_part + 144 * 27 + mlp_part
    assert abs(n / 17.4e6 - 1) < 0.01


@settings(max_examples=20, deadline=None)
@given(x=st.lists(st.floats(-30.0, 30.0, width=32), min_size=1, max_size=8), n_freqs=st.integers(1, 6))
def test_positional_encoding_double_angle_matches_direct(x, n_freqs):
    """The double-angle octaves equal sin / cos of x 2^k, within an error that doubles per octave."""
    xs = np.asarray(x, np.float32)[None, :]
    got = np.asarray(jax.jit(field.positional_encoding, static_argnums=1)(jnp.asarray(xs), n_freqs))[0]
    scaled = (xs[0, :, None].astype(np.float64) * 2.0 ** np.arange(n_freqs)).reshape(-1)
    np.testing.assert_allclose(got, np.concatenate([np.sin(scaled), np.cos(scaled)]), atol=2e-7 * 2**n_freqs)


_sincos = jax.jit(field.sincos)
_sincos_grad = jax.jit(jax.grad(lambda v: jnp.sum(2.0 * field.sincos(v)[0] + 3.0 * field.sincos(v)[1])))


@settings(max_examples=30, deadline=None)
@given(x=st.lists(st.floats(-1e4, 1e4, width=32), min_size=1, max_size=16))
def test_sincos_matches_float64_and_differentiates(x):
    """The vectorised sin / cos is within 1e-7 of float64 over |x| <= 1e4; its derivative is (cos, -sin)."""
    xs = np.resize(np.asarray(x, np.float32), 16)  # one shape: one compilation for every example
    sin, cos = _sincos(jnp.asarray(xs))
    np.testing.assert_allclose(np.asarray(sin), np.sin(xs.astype(np.float64)), rtol=0, atol=1e-7)
    np.testing.assert_allclose(np.asarray(cos), np.cos(xs.astype(np.float64)), rtol=0, atol=1e-7)
    grad = _sincos_grad(jnp.asarray(xs))
    np.testing.assert_allclose(np.asarray(grad), 2.0 * np.asarray(cos) - 3.0 * np.asarray(sin), atol=1e-6)
