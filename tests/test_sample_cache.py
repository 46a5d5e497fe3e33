"""The cached source (schedule.cache_source): cached renders equal the ray-marched ones, in value and in the
watermark's gradient; a tiny embed with it leaves the fitted field as it was."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mnerf_jax.core import xla_cpu
from mnerf_jax.core.config import ModelConfig
from mnerf_jax.core.config import watermark_from_flat as wm_config
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.tensorf import field, raymarch, render
from mnerf_jax.tensorf import run as runs
from mnerf_jax.watermark import embed as E
from mnerf_jax.watermark import model as W
from mnerf_jax.watermark import run as wm_run
from mnerf_jax.watermark import sample_cache

if TYPE_CHECKING:
    from conftest import TinyRuns

MODEL = ModelConfig(density_ranks=(2, 2, 2), appearance_ranks=(4, 4, 4), app_features=8, mlp_width=16)
RES = (9, 8, 7)
CFG = wm_config(wm_ranks=(2, 2, 2), cache_source=True, jitter=False)


def _scene(white_bg: bool = True) -> tuple[dict, raymarch.Geometry, jax.Array, jax.Array]:
    k_field, k_wm = jax.random.split(jax.random.PRNGKey(0))
    params = W.add_watermark(k_wm, field.init_field(k_field, MODEL, RES), CFG, 4, extra_scale=2.0)
    params["density"] = jax.tree.map(lambda a: a + 1.0, params["density"])  # dense enough to see colour
    params["wm"]["mod"] = jax.tree.map(lambda a: 10.0 * a, params["wm"]["mod"])  # FiLM away from identity
    # On black: a white background brings rays to exactly 1.0, where the clip's gradient splits a tie (0.5)
    # or not depending on the last bit of the sum, in either renderer.
    geometry = raymarch.make_geometry(np.array([[-1.5] * 3, [1.5] * 3]), RES, n_samples=32, white_bg=white_bg)
    o = jnp.tile(jnp.array([[0.0, 0.0, -4.0]]), (24, 1))
    d = jnp.concatenate([jnp.linspace(-0.7, 0.7, 24)[:, None], jnp.zeros((24, 1)), jnp.ones((24, 1))], -1)
    return params, geometry, o, d / jnp.linalg.norm(d, axis=-1, keepdims=True)


def _cached_view(params: dict, geometry: raymarch.Geometry, o: jax.Array, d: jax.Array) -> dict:
    sizes = [16, 16]  # too small: grown until nothing is dropped
    s = sample_cache.view_samples(params, geometry, MODEL, np.asarray(o), np.asarray(d), sizes)
    assert sizes[1] >= len(s["weight"]) > 16
    return {f"cache_{k}": jnp.asarray(v) for k, v in s.items()}


def test_a_cached_render_equals_the_ray_marched_render_of_every_id() -> None:
    params, geometry, o, d = _scene()
    view = _cached_view(params, geometry, o, d)
    ids = jnp.array([2, 0, 3])
    fns = W.field_fns(MODEL, CFG)
    cond = W.condition_many(params, ids, CFG)
    cached = sample_cache.cached_render(params, cond, view, CFG, geometry.white_bg)
    marched = render.render_rays(
        fns, params, cond, o, d, geometry, None, train=False, density_budget=None, colour_budget=None
    )
    assert cached.shape == (24, 9)
    assert float(jnp.min(marched["acc"])) < 0.99  # background shows on some rays
    np.testing.assert_allclose(np.asarray(cached), np.asarray(marched["rgb"]), rtol=1e-5, atol=1e-6)
    for k in range(3):  # the IDs differ
        a, b = 3 * k, 3 * ((k + 1) % 3)
        assert float(jnp.abs(cached[:, a : a + 3] - cached[:, b : b + 3]).max()) > 1e-3


def test_the_cached_renders_gradient_is_the_watermarks_gradient_through_the_ray_march() -> None:
    params, geometry, o, d = _scene(white_bg=False)
    view = _cached_view(params, geometry, o, d)
    ids = jnp.array([1, 3])
    fns = W.field_fns(MODEL, CFG)
    probe = jax.random.normal(jax.random.PRNGKey(5), (24, 6))

    def cached_loss(p: dict) -> jax.Array:
        rgb = sample_cache.cached_render(p, W.condition_many(p, ids, CFG), view, CFG, geometry.white_bg)
        return jnp.sum(rgb * probe)

    def marched_loss(p: dict) -> jax.Array:
        out = render.render_rays(
            fns,
            p,
            W.condition_many(p, ids, CFG),
            o,
            d,
            geometry,
            None,
            train=False,
            density_budget=None,
            colour_budget=None,
        )
        return jnp.sum(out["rgb"] * probe)

    # Both compiled as the embedding step is (xla_cpu.jit_cpu_tuned): the suite's backend optimisation level 0
    # (tests/conftest.py) puts the ray march's gradient visibly off in some of Emb's entries here.
    g_cached = xla_cpu.jit_cpu_tuned(jax.grad(cached_loss))(params)
    g_marched = xla_cpu.jit_cpu_tuned(jax.grad(marched_loss))(params)
    learnt = [g_cached["wm"], g_cached["mlp"]["out_extra"]], [g_marched["wm"], g_marched["mlp"]["out_extra"]]
    for a, b in zip(*map(jax.tree.leaves, learnt), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-6)
    assert float(jnp.abs(g_cached["wm"]["grid"]["planes"][0]).max()) > 0  # the grid learns
    # The fitted field is a constant of the cache: no gradient reaches it.
    assert all(float(jnp.abs(g).max()) == 0 for g in jax.tree.leaves(g_cached["density"]))


def test_cache_source_needs_a_last_layer_film_variant_and_no_jitter() -> None:
    CFG.check_ids()
    with pytest.raises(MnerfError, match="jitter=false"):
        dataclasses.replace(CFG, schedule=dataclasses.replace(CFG.schedule, jitter=True))
    for variant in ("early", "waterf_mod", "no_film"):
        with pytest.raises(MnerfError, match="cache_source"):
            dataclasses.replace(CFG, variant=variant)


def test_a_tiny_embed_with_a_cached_source_trains_only_the_watermark(tiny: TinyRuns) -> None:
    # No augmentations: a faster compile (the cache does not depend on them).
    overrides = [
        *tiny.embed_overrides,
        "watermark.schedule.phase1_steps=2",
        "watermark.schedule.phase2_steps=3",
        "watermark.schedule.cache_source=true",
        "watermark.schedule.jitter=false",
        "watermark.augment.per_step=0",
    ]
    out = tiny.root / "cached"
    result = E.embed(tiny.fit, out, 2, 8, overrides=overrides, decoder_path=tiny.decoder, progress=False)
    assert result.steps == 5
    from mnerf_jax.watermark import inputs

    # The quality budget's references from the cache are the clean model's renders.
    source = wm_run.load_run(tiny.fit)
    split = source.load_scene(None, splits=("train",)).split("train")
    cache = sample_cache.build_cache(source.params, source.geometry, source.config.model, split.cameras)
    from_cache = sample_cache.clean_renders(cache, source.geometry.white_bg).reshape(split.images.shape)
    rendered = inputs.clean_references(source, split)
    np.testing.assert_allclose(from_cache.astype(np.float32), rendered.astype(np.float32), atol=2e-3)

    wm = wm_run.load_watermarked_run(out)
    for name in ("density", "appearance"):
        for a, b in zip(jax.tree.leaves(source.params[name]), jax.tree.leaves(wm.params[name]), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    for name in ("w0", "b0", "w2", "b2"):
        np.testing.assert_array_equal(source.params["mlp"][name], wm.params["mlp"][name])
    root = jax.random.key(0)
    start = W.add_watermark(jax.random.fold_in(root, 0x3A7), source.params, wm.config.watermark, 2)
    pairs = zip(jax.tree.leaves(start["wm"]), jax.tree.leaves(wm.params["wm"]), strict=True)
    assert max(float(np.abs(np.asarray(a) - np.asarray(b)).max()) for a, b in pairs) > 0  # it learnt
    # Phase 3's training renders from the cache are the watermarked run's renders of every ID.
    from_cache = sample_cache.every_id_renders(
        cache, wm.params, wm.config.watermark, 2, wm.geometry.white_bg, ids_per_render=1
    )
    rendered = wm_run.render_every_id(wm, split.cameras)
    for n in (0, 1):
        np.testing.assert_allclose(from_cache[n].reshape(rendered[n].shape), rendered[n], atol=1e-4)
    # The null column of the same pass is the clean model's render; the IDs' columns are unchanged.
    with_clean, clean = wm_run.render_every_id_and_clean(wm, split.cameras)
    np.testing.assert_allclose(clean, np.stack(runs.render_views(source, split.cameras)), atol=1e-5)
    for n in (0, 1):
        np.testing.assert_allclose(with_clean[n], rendered[n], atol=1e-5)
    with pytest.raises(MnerfError, match="trained"):  # an adapting source: no conditioning renders it
        wm_run.render_every_id_and_clean(wm_run.load_watermarked_run(tiny.wm), split.cameras)
    # Resumed, it is finished; resumed without the switch, it is another config.
    again = E.embed(
        tiny.fit, out, 2, 8, resume=True, overrides=overrides, decoder_path=tiny.decoder, progress=False
    )
    assert again.steps == 5
    plain = [
        *tiny.embed_overrides,
        "watermark.schedule.phase1_steps=2",
        "watermark.schedule.phase2_steps=3",
    ]  # ray-marched
    with pytest.raises(MnerfError, match="cache_source"):
        E.embed(tiny.fit, out, 2, 8, resume=True, overrides=plain, decoder_path=tiny.decoder, progress=False)
