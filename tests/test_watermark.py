"""Watermark module: per-ID colours, variants, initialisation, FiLM, grid resampling."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mnerf_jax.core.config import ModelConfig, WatermarkConfig
from mnerf_jax.core.config import watermark_from_flat as wm_config
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.tensorf import alpha_mask, field, grids, raymarch, render
from mnerf_jax.watermark import model as W

MODEL = ModelConfig(density_ranks=(2, 2, 2), appearance_ranks=(4, 4, 4), app_features=8, mlp_width=16)
RES = (9, 8, 7)


def _params(cfg: WatermarkConfig, num_ids: int = 4, extra_scale: float = 0.5, seed: int = 0) -> dict:
    k_field, k_wm = jax.random.split(jax.random.PRNGKey(seed))
    base = field.init_field(k_field, MODEL, RES)
    return W.add_watermark(k_wm, base, cfg, num_ids, extra_scale=extra_scale)


def _points(n: int = 64, seed: int = 1) -> tuple[jax.Array, jax.Array]:
    k1, k2 = jax.random.split(jax.random.PRNGKey(seed))
    xyz = jax.random.uniform(k1, (n, 3), minval=-1.0, maxval=1.0)
    d = jax.random.normal(k2, (n, 3))
    return xyz, d / jnp.linalg.norm(d, axis=-1, keepdims=True)


def _colour(params: dict, cfg: WatermarkConfig, index: int) -> np.ndarray:
    xyz, d = _points()
    cond = W.condition(params, index, cfg)
    return np.asarray(W.colour(params, cond, xyz, d, MODEL, cfg))


def _strong_film(variant: str) -> tuple[WatermarkConfig, dict]:
    """A small config of ``variant`` and params whose Mod acts like a trained one (FiLM starts near the
    identity, γ ≈ 1, β ≈ 0, by design)."""
    cfg = wm_config(variant=variant, wm_ranks=(2, 2, 2), emb_dim=4, emb_hidden=8)
    params = _params(cfg)
    if "mod" in params["wm"]:
        params["wm"]["mod"] = jax.tree.map(lambda a: 10.0 * a, params["wm"]["mod"])
    return cfg, params


@pytest.mark.parametrize("variant", [v for v in W.VARIANTS if v != "waterf"])
def test_different_ids_give_different_colours_and_the_same_id_the_same(variant: str) -> None:
    cfg, params = _strong_film(variant)
    c0, c0_again, c1, c3 = (_colour(params, cfg, i) for i in (0, 0, 1, 3))
    np.testing.assert_array_equal(c0, c0_again)
    assert np.abs(c0 - c1).max() > 1e-3
    assert np.abs(c1 - c3).max() > 1e-3
    assert c0.shape == (64, 3) and (c0 > 0).all() and (c0 < 1).all()


def test_waterf_has_no_id_and_refuses_several() -> None:
    cfg = wm_config(variant="waterf")
    params = _params(cfg, num_ids=1)
    assert params["wm"] == {} and "out_extra" not in params["mlp"] and "in_extra" not in params["mlp"]
    assert W.condition(params, 0, cfg) is None
    xyz, d = _points()
    plain = np.asarray(field.colour(params, xyz, d, MODEL))
    np.testing.assert_array_equal(np.asarray(W.colour(params, None, xyz, d, MODEL, cfg)), plain)
    with pytest.raises(MnerfError, match="--num-ids 1"):
        _params(cfg, num_ids=3)


def test_fresh_watermark_renders_the_clean_field() -> None:
    # Small out_extra: the untrained watermarked model matches the TensoRF it starts from.
    cfg = wm_config(wm_ranks=(2, 2, 2))
    k_field, k_wm = jax.random.split(jax.random.PRNGKey(3))
    base = field.init_field(k_field, MODEL, RES)
    params = W.add_watermark(k_wm, base, cfg, 4)
    xyz, d = _points()
    clean = np.asarray(field.colour(base, xyz, d, MODEL))
    for i in range(4):
        np.testing.assert_allclose(_colour(params, cfg, i), clean, atol=1.0 / 255)
    # The base params are not modified.
    assert "wm" not in base and "out_extra" not in base["mlp"]


def test_film_is_per_id_from_the_start() -> None:
    cfg = WatermarkConfig()
    params = _params(cfg, num_ids=5)
    conds = [W.condition(params, i, cfg) for i in range(5)]
    gammas = np.stack([np.asarray(c["gamma"]) for c in conds])
    betas = np.stack([np.asarray(c["beta"]) for c in conds])
    assert gammas.shape == (5, 24) and betas.shape == (5, 24)
    assert np.abs(gammas).max() < 1.5 and np.abs(betas).max() < 1.5
    # Distinct IDs get clearly distinct modulations (not one shared FiLM plus a small per-ID part).
    diffs = [np.abs(gammas[i] - gammas[j]).mean() for i in range(5) for j in range(i)]
    assert min(diffs) > 0.01


@pytest.mark.parametrize(
    "variant,where,width",
    [
        ("multinerf", "out_extra", 24),
        ("frozen_geometry", "out_extra", 24),
        ("no_grid", "out_extra", 24),
        ("no_film", "out_extra", 24 + 16),
        ("early", "in_extra", 24),
        ("waterf_mod", "in_extra", 16),
        ("appearance_film", "out_extra", 8),  # the field's appearance features (MODEL)
        ("appearance_concat", "out_extra", 8 + 16),
    ],
)
def test_variant_structure(variant: str, where: str, width: int) -> None:
    cfg = wm_config(variant=variant)
    params = _params(cfg)
    assert params["mlp"][where].shape[0] == width
    assert ("grid" in params["wm"]) == (variant in ("multinerf", "frozen_geometry", "no_film", "early"))
    film = ("multinerf", "frozen_geometry", "no_grid", "early", "appearance_film")
    assert ("mod" in params["wm"]) == (variant in film)
    if "grid" in params["wm"]:
        assert grids.vm_resolution(params["wm"]["grid"]) == RES
        assert grids.vm_ranks(params["wm"]["grid"]) == (8, 8, 8)
    assert W.trains_source(cfg) == (variant != "frozen_geometry")
    assert W.watermark_param_count(params) > 0


def test_every_watermark_part_gets_a_gradient() -> None:
    cfg = wm_config(wm_ranks=(2, 2, 2))
    params = _params(cfg)
    xyz, d = _points()

    def loss(p):
        cond = W.condition(p, 2, cfg)
        return jnp.sum(W.colour(p, cond, xyz, d, MODEL, cfg) ** 2)

    g = jax.grad(loss)(params)
    for name, leaf in jax.tree_util.tree_leaves_with_path(g["wm"]):
        if "emb" in jax.tree_util.keystr(name) and "w0" in jax.tree_util.keystr(name):
            # Only the chosen ID's row of the one-hot layer moves.
            rows = np.abs(np.asarray(leaf)).sum(1)
            assert rows[2] > 0 and np.count_nonzero(rows) == 1
        else:
            assert float(jnp.abs(leaf).max()) > 0, jax.tree_util.keystr(name)
    assert float(jnp.abs(g["mlp"]["out_extra"]).max()) > 0


def test_unknown_variant_and_bad_ranks_are_refused() -> None:
    with pytest.raises(MnerfError, match="watermark.variant"):
        wm_config(variant="bogus")
    with pytest.raises(MnerfError, match="wm_ranks"):
        wm_config(wm_ranks=(0, 0, 0))


def test_the_automatic_schedule_grows_with_the_ids() -> None:
    from mnerf_jax.watermark import step as S

    # -1 (the default): 50 + 200 steps per ID, at least 4 IDs' worth; a value >= 0 is used as it is.
    assert W.phase_steps(wm_config(num_ids=2)) == (200, 800)
    assert W.phase_steps(wm_config(num_ids=4)) == (200, 800)
    assert W.phase_steps(WatermarkConfig(), num_ids=16) == (800, 3200)
    assert W.phase_steps(wm_config(num_ids=16, phase1_steps=0)) == (0, 3200)
    assert W.phase_steps(wm_config(num_ids=16, phase1_steps=3, phase2_steps=0)) == (3, 0)
    cfg = wm_config(num_ids=8)
    assert S.total_steps(cfg) == 2000 and S.phase_of(399, cfg) == 1 and S.phase_of(400, cfg) == 2
    with pytest.raises(MnerfError, match="phase1_steps"):
        wm_config(phase2_steps=-2)


def test_the_cpu_preset_moves_steps_from_phase_1_to_phase_2() -> None:
    from mnerf_jax.core import config

    # `mnerf embed --config embed_cpu` reads the preset's [watermark] section only: today's defaults with
    # a 100 + 2,600 step schedule ended by a 60-minute budget, the field's loss weighted towards the IDs
    # read worst, and the decoder reading a window on the object (the lego protocol on 2 cores).
    cfg = config.load_preset("embed_cpu").watermark
    assert W.phase_steps(cfg, num_ids=16) == (100, 2600) and cfg.time_budget.minutes == 60
    assert cfg.losses.id_loss_power == 1.0 and cfg.reading.window == 0.72 and cfg.reading.background == 1.0
    plain = {
        **config.flat_items(cfg),
        "schedule.phase1_steps": -1,
        "schedule.phase2_steps": -1,
        "time_budget.minutes": 0.0,
        "losses.id_loss_power": 0.0,
        "reading.window": 0.0,
    }
    assert plain == config.flat_items(WatermarkConfig())


def test_the_cpu_quality_preset_is_the_cpu_preset_with_a_cached_source_a_ramp_no_attacks_and_a_phase_3() -> (
    None
):
    from mnerf_jax.core import config
    from mnerf_jax.watermark.deferred import patch_layout
    from mnerf_jax.watermark.objective import fidelity_budget_db

    cfg = config.load_preset("embed_cpu_quality").watermark
    base = config.load_preset("embed_cpu").watermark
    assert W.phase_steps(cfg, num_ids=16) == (100, 7800)  # three times embed_cpu's field steps
    assert {
        **config.flat_items(cfg),
        "fidelity.psnr": 0.0,
        "fidelity.psnr_start": 0.0,
        "fidelity.ramp": (0.0, 0.0),
        "fidelity.over_source": 0.0,
        "augment.prob": 0.75,
        "schedule.patch_size": 64,
        "schedule.phase2_steps": 2600,
        "phase3.steps": 0,
        "phase3.views": 0,
        "phase3.reserve_min": 0.0,
        "phase3.batch": 32,
        "phase3.lambda_clean": 0.3,
        "phase3.attacked": 0.0,
        "reading.jitter": 0,
        "reading.max_side": 64,
        "phase3.view_density": "angles",
        "phase3.elevation_margin": 0.0,
        "schedule.cache_source": False,
        "schedule.jitter": True,
    } == config.flat_items(base)
    assert cfg.augment.prob == 0.0
    # The fitted field frozen and its samples cached (sample_cache.py), which needs unjittered samples.
    assert cfg.schedule.cache_source and not cfg.schedule.jitter
    cfg.check_ids(16)
    # One patch covers a lego 1/8 view (100 px): the deferred path's single-render branch.
    assert patch_layout(100, 100, cfg.schedule.patch_size).num_patches == 1
    # 20 dB until 35 % of the field's 7,900 steps, 41.5 dB from 60 % on.
    total = sum(W.phase_steps(cfg, num_ids=16))
    assert total == 7900
    budget = [float(fidelity_budget_db(cfg, step, total)) for step in (0, 2765, 4740, 7899)]
    assert budget == pytest.approx([20.0, 20.0, 41.5, 41.5], abs=1e-4)
    assert 20.0 < float(fidelity_budget_db(cfg, 3800, total)) < 41.5
    # Then the decoder alone: 24,000 steps of 16 renders on the training views and 200 novel views, its
    # negatives weighed 1, with 35 of the 60 minutes kept for it; the novel views spread over the sphere's
    # area 5° past the training cameras' elevations, half of the renders and negatives read after real
    # attacks; renders are read over the 9 windows within a pixel.
    phase3 = (
        cfg.phase3.steps,
        cfg.phase3.attacked,
        cfg.phase3.batch,
        cfg.phase3.views,
        cfg.phase3.lambda_clean,
        cfg.phase3.reserve_min,
        cfg.time_budget.minutes,
        cfg.phase3.view_density,
        cfg.phase3.elevation_margin,
    )
    assert phase3 == (24000, 0.5, 16, 200, 1.0, 35, 60, "sphere", 5.0) and cfg.reading.jitter == 1
    assert cfg.reading.max_side == 0  # its 72-px window read as it is


def test_watermark_grid_follows_upsampling_and_shrinking() -> None:
    params = _params(wm_config(wm_ranks=(2, 2, 2)))
    up = W.resample_watermark(params, (12, 10, 9))
    assert grids.vm_resolution(up["wm"]["grid"]) == (12, 10, 9)
    up["density"] = grids.upsample_vm(up["density"], (12, 10, 9))
    up["appearance"] = grids.upsample_vm(up["appearance"], (12, 10, 9))
    # Shrinking with the field keeps all grids at one resolution.
    shrunk, _ = alpha_mask.shrink_field(
        up, np.array([[-1.5] * 3, [1.5] * 3]), np.array([[-1.0, -1.0, -1.0], [1.0, 1.2, 1.0]])
    )
    res = grids.vm_resolution(shrunk["density"])
    assert grids.vm_resolution(shrunk["wm"]["grid"]) == res
    box = np.array([[-1.5] * 3, [1.5] * 3])
    lo, hi, _ = grids.shrink_indices(box, (12, 10, 9), np.array([[-1.0] * 3, [1.0] * 3]))
    assert grids.vm_resolution(W.shrink_watermark(up, lo, hi)["wm"]["grid"]) == tuple(
        h - l for l, h in zip(lo, hi, strict=True)
    )


def test_field_fns_render_differs_by_id() -> None:
    cfg = wm_config(wm_ranks=(2, 2, 2))
    params = _params(cfg, extra_scale=2.0)
    # Dense density so that rays see colour.
    params["density"] = jax.tree.map(lambda a: a + 1.0, params["density"])
    fns = W.field_fns(MODEL, cfg)
    assert fns == W.field_fns(MODEL, dataclasses.replace(cfg))  # hashable, equal: shared compilation
    geometry = raymarch.make_geometry(np.array([[-1.5] * 3, [1.5] * 3]), RES, n_samples=32)
    o = jnp.tile(jnp.array([[0.0, 0.0, -4.0]]), (16, 1))
    dirs = jnp.concatenate([jnp.linspace(-0.2, 0.2, 16)[:, None], jnp.zeros((16, 1)), jnp.ones((16, 1))], -1)
    dirs = dirs / jnp.linalg.norm(dirs, axis=-1, keepdims=True)
    outs = [
        render.render_rays(
            fns,
            params,
            W.condition(params, i, cfg),
            o,
            dirs,
            geometry,
            None,
            train=False,
            density_budget=None,
            colour_budget=None,
        )["rgb"]
        for i in (0, 1)
    ]
    assert float(jnp.abs(outs[0] - outs[1]).max()) > 1e-3


@pytest.mark.parametrize("variant", [v for v in W.VARIANTS if v != "waterf"])
def test_several_ids_at_once_equal_each_id_alone(variant: str) -> None:
    # condition_many: K IDs' colours side by side, [P, 3K], each equal to that ID rendered alone.
    cfg, params = _strong_film(variant)
    xyz, d = _points()
    ids = jnp.array([3, 0, 2])
    many = np.asarray(W.colour(params, W.condition_many(params, ids, cfg), xyz, d, MODEL, cfg))
    assert many.shape == (64, 9)
    for k, i in enumerate((3, 0, 2)):
        np.testing.assert_allclose(many[:, 3 * k : 3 * k + 3], _colour(params, cfg, i), rtol=1e-5, atol=1e-6)
    with pytest.raises(MnerfError, match="no IDs"):
        W.condition_many(params, ids, dataclasses.replace(cfg, variant="waterf"))


@pytest.mark.parametrize("variant", ["early", "waterf_mod"])
def test_several_ids_entering_the_first_layer_have_each_ids_gradient(variant: str) -> None:
    # The K first-layer passes run one at a time and are recomputed backwards: the gradient of a loss on the
    # [P, 3K] colours is the sum of each ID's gradient alone.
    cfg, params = _strong_film(variant)
    xyz, d = _points()
    ids = (3, 0, 2)
    weights = jax.random.normal(jax.random.PRNGKey(5), (xyz.shape[0], 3 * len(ids)))

    def many_loss(p: dict) -> jax.Array:
        return jnp.sum(weights * W.colour(p, W.condition_many(p, jnp.array(ids), cfg), xyz, d, MODEL, cfg))

    def one_loss(p: dict, k: int) -> jax.Array:
        rgb = W.colour(p, W.condition(p, ids[k], cfg), xyz, d, MODEL, cfg)
        return jnp.sum(weights[:, 3 * k : 3 * k + 3] * rgb)

    many = jax.grad(many_loss)(params)
    alone = [jax.grad(one_loss)(params, k) for k in range(len(ids))]
    summed = jax.tree.map(lambda *g: sum(g), *alone)
    for got, want in zip(jax.tree.leaves(many), jax.tree.leaves(summed), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)
    assert max(float(jnp.abs(g).max()) for g in jax.tree.leaves(many["wm"])) > 0


@pytest.mark.parametrize("colour_budget", [None, 2 * render.COLOUR_CHUNK])
def test_render_rays_with_several_ids_equals_one_render_per_id(colour_budget: int | None) -> None:
    # One geometry pass for K IDs: rgb [R, 3K] whose columns are the single-ID renders (background included),
    # through the dense path and the chunked colour buffer alike.
    cfg = wm_config(wm_ranks=(2, 2, 2))
    params = _params(cfg, extra_scale=2.0)
    params["density"] = jax.tree.map(lambda a: a + 1.0, params["density"])
    fns = W.field_fns(MODEL, cfg)
    geometry = raymarch.make_geometry(np.array([[-1.5] * 3, [1.5] * 3]), RES, n_samples=32)
    o = jnp.tile(jnp.array([[0.0, 0.0, -4.0]]), (16, 1))
    dirs = jnp.concatenate([jnp.linspace(-0.6, 0.6, 16)[:, None], jnp.zeros((16, 1)), jnp.ones((16, 1))], -1)
    dirs = dirs / jnp.linalg.norm(dirs, axis=-1, keepdims=True)
    budget = None if colour_budget is None else 16 * 32
    kwargs = dict(train=False, density_budget=budget, colour_budget=colour_budget)
    ids = jnp.array([1, 3])
    many = render.render_rays(
        fns, params, W.condition_many(params, ids, cfg), o, dirs, geometry, None, **kwargs
    )
    assert many["rgb"].shape == (16, 6)
    assert float(jnp.min(many["acc"])) < 0.99  # some background shows: its colour is tiled per ID
    for k, i in enumerate((1, 3)):
        one = render.render_rays(fns, params, W.condition(params, i, cfg), o, dirs, geometry, None, **kwargs)
        np.testing.assert_allclose(many["rgb"][:, 3 * k : 3 * k + 3], one["rgb"], rtol=1e-5, atol=1e-6)
        np.testing.assert_array_equal(many["acc"], one["acc"])
