"""Training loop pieces (schedules, sampler, budgets) and resumption on a tiny procedural scene."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from conftest import TINY_SCHEDULE as TINY

from mnerf_jax.core.config import load_config
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.data import load_scene
from mnerf_jax.tensorf import grids, sampler
from mnerf_jax.tensorf.fit import loop as train
from mnerf_jax.tensorf.fit import step as fit_step


@pytest.fixture(scope="module")
def tiny():
    config = load_config("procedural", TINY)
    return config, load_scene(None, config.data, config.render, ("train",))


# -- schedules -------------------------------------------------------------------------------------


def test_learning_rate_decays_to_ratio_and_resets():
    config = load_config("blender")
    hyper = fit_step.StepHyper.from_config(config)
    assert fit_step.learning_rates(hyper, 0, 0) == {"grid": 0.02, "network": 1e-3}
    end = fit_step.learning_rates(hyper, config.train.n_iters, 0)
    assert end["grid"] == pytest.approx(0.002, rel=1e-6) and end["network"] == pytest.approx(1e-4, rel=1e-6)
    # After a reset at step 2001 the rates start again from their initial values.
    assert fit_step.learning_rates(hyper, 2001, 2001)["grid"] == pytest.approx(0.02)
    assert hyper.l1_switch == 2001


def test_param_labels_split_grids_from_networks(tiny):
    config, _ = tiny
    params = train.init_state(config, tiny[1]).params
    labels = jax.tree.leaves(fit_step.param_labels(params))
    assert set(labels) == {"grid", "network"}
    assert fit_step.param_labels(params)["basis"] == "network"
    assert set(jax.tree.leaves(fit_step.param_labels(params)["density"])) == {"grid"}


def test_blender_voxel_schedule_is_log_linear_to_300():
    config = load_config("blender")
    steps = train.voxel_steps(config)
    assert sorted(steps) == [2000, 3000, 4000, 5500, 7000]
    sides = [
        grids.resolution_from_voxels(np.asarray(config.render.aabb).reshape(2, 3), n)[0]
        for n in steps.values()
    ]
    assert sides[-1] == 300 and sides == sorted(sides) and 145 < sides[0] < 160


# -- sampler and budgets ---------------------------------------------------------------------------


def test_sampler_is_a_function_of_seed_and_step():
    a = sampler.PermutationSampler(seed=3, n_rays=1000, batch=128, start=0)
    b = sampler.PermutationSampler(seed=3, n_rays=1000, batch=128, start=0)
    epoch = np.concatenate([a.indices(s) for s in range(a.per_epoch)])
    assert len(np.unique(epoch)) == 128 * 7  # batches of one epoch never repeat a ray
    np.testing.assert_array_equal(a.indices(11), b.indices(11))  # a fresh sampler (resume) agrees
    assert not np.array_equal(a.indices(0), a.indices(a.per_epoch))  # reshuffled every epoch
    c = sampler.PermutationSampler(seed=4, n_rays=1000, batch=128, start=0)
    assert not np.array_equal(a.indices(0), c.indices(0))


def test_budgets_grow_on_overflow_and_refit_two_steps_later():
    b = train.SampleBudgets(density=1 << 18, colour=1 << 17)
    cap = 1 << 22
    assert b.observe(10, density_count=300_000, colour_count=4_000, n_samples=64, cap=cap)  # overflow: redo
    assert b.density >= 300_000 * b.growth and b.for_step(10)[0] == b.density
    assert not b.observe(10, density_count=300_000, colour_count=4_000, n_samples=64, cap=cap)
    before = b.for_step(11)
    b.schedule_refit(12, cap, remaining=1000)  # decided after step 10: step 11 is already in flight
    assert b.for_step(11) == before
    assert b.for_step(12)[1] < before[1]  # colour was barely used: shrunk
    assert b.for_step(12)[1] <= b.for_step(12)[0]  # colour never exceeds density
    # Near the end of a phase a smaller buffer would not repay its compilation ...
    late = train.SampleBudgets(density=1 << 18, colour=1 << 17)
    late.observe(10, density_count=4_000, colour_count=4_000, n_samples=64, cap=cap)
    late.schedule_refit(12, cap, remaining=5)
    assert late.for_step(12) == (1 << 18, 1 << 17)
    # ... nor would freeing a few thousand slots, however many steps are left; the full phase does.
    small = train.SampleBudgets(density=4096, colour=2048)
    small.observe(10, density_count=100, colour_count=100, n_samples=64, cap=cap)
    small.schedule_refit(12, cap, remaining=1000)
    assert small.for_step(12) == (4096, 2048)
    late.observe(11, density_count=4_000, colour_count=4_000, n_samples=64, cap=cap)
    late.schedule_refit(13, cap, remaining=1000)
    freed = sum((1 << 18, 1 << 17)) - sum(late.for_step(13))
    assert freed * 1000 >= late.refit_cost_slot_steps
    # A new phase scales the latest colour count to the new samples per ray.
    assert b.colour_estimate(128) == pytest.approx(4_000 * 2 * b.headroom)


def test_large_budgets_are_refitted_more_often_and_by_smaller_rungs():
    from mnerf_jax.tensorf.budgets import LARGE_BUDGET, REFIT_EVERY_LARGE, ladder, refit_due

    small = train.SampleBudgets(density=4096, colour=4096)
    large = train.SampleBudgets(density=2 * LARGE_BUDGET, colour=2 * LARGE_BUDGET)
    assert not refit_due(REFIT_EVERY_LARGE, 0, small)
    assert refit_due(REFIT_EVERY_LARGE, 0, large)
    # Colour used at 60 %: the small-budget rule (below half) keeps it, the large-budget rule takes the
    # next rung down.
    count = int(0.6 * large.colour)
    large.observe(40, density_count=large.density - 1, colour_count=count, n_samples=64, cap=1 << 24)
    large.schedule_refit(42, 1 << 24, remaining=100)
    assert large.for_step(42) == (large.density, ladder(count * large.headroom))
    assert large.for_step(42)[1] <= 0.75 * large.colour


# -- the loop --------------------------------------------------------------------------------------


def _state_leaves(state: fit_step.TrainState) -> list[np.ndarray]:
    g = state.geometry
    return [np.asarray(x) for x in jax.tree.leaves((state.params, state.opt_state))] + [
        np.asarray(g.aabb),
        np.asarray(g.alpha_mask),
        np.asarray(state.step),
        np.asarray(state.lr_base_step),
    ]


def test_resume_repeats_an_uninterrupted_run_exactly(tiny, tmp_path):
    config, scene = tiny
    full = train.fit(config, scene, tmp_path / "full")
    first = train.fit(config, scene, tmp_path / "split", stop_at=48)
    assert first.steps == 48
    resumed = train.fit(config, scene, tmp_path / "split", resume=True)
    assert resumed.steps == full.steps == config.train.n_iters
    # Every event ran: the aabb shrank, the grid was upsampled, an alpha mask is in place.
    g = full.state.geometry
    assert np.all(np.asarray(g.aabb)[1] - np.asarray(g.aabb)[0] < 3.0 - 1e-3)
    assert full.state.resolution != grids.resolution_from_voxels(scene.aabb, config.train.n_voxel_init)
    assert not np.asarray(g.alpha_mask).all()
    for a, b in zip(_state_leaves(full.state), _state_leaves(resumed.state), strict=True):
        np.testing.assert_array_equal(a, b)
    assert resumed.last_metrics == full.last_metrics


def test_resume_under_another_config_is_refused(tiny, tmp_path):
    config, scene = tiny
    train.fit(config, scene, tmp_path / "run", stop_at=2)
    other = load_config("procedural", [*TINY, "train.lr_grid=0.01"])
    with pytest.raises(MnerfError, match=r"incompatible config \(train\.lr_grid: 0\.02 -> 0\.01\)"):
        train.fit(other, scene, tmp_path / "run", resume=True)
