"""Phase 3 of the embedding: the decoder alone, refitted on the finished field's renders (decoder_refit)."""

from __future__ import annotations

import dataclasses
import json
import shutil
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from conftest import load_script
from hypothesis import given, settings
from hypothesis import strategies as st

from mnerf_jax.core.config import watermark_from_flat as wm_config
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.data import trajectory
from mnerf_jax.data.types import Cameras, NDCSpace
from mnerf_jax.imaging import augment
from mnerf_jax.reader import decoder as decoder_lib
from mnerf_jax.reader import decoder_io, dwt, read_window
from mnerf_jax.reader import keys as keys_lib
from mnerf_jax.watermark import embed as E
from mnerf_jax.watermark import novel_views, time_budget
from mnerf_jax.watermark import phase3 as decoder_refit
from mnerf_jax.watermark import run as wm_run
from mnerf_jax.watermark.step import phase_of

if TYPE_CHECKING:
    from conftest import TinyRuns  # the `tiny` fixture's type (tests/conftest.py)


def _ring_cameras(n: int = 12) -> Cameras:
    """``n`` cameras at distance 3.5-4.5 and elevation 10-60° around the origin, looking at it (z up)."""
    rng = np.random.default_rng(0)
    theta = rng.uniform(0, 2 * np.pi, n)
    elev = np.radians(rng.uniform(10, 60, n))
    dist = rng.uniform(3.5, 4.5, n)
    unit = np.stack([np.cos(elev) * np.cos(theta), np.cos(elev) * np.sin(theta), np.sin(elev)], 1)
    pos = dist[:, None] * unit
    c2w = np.stack([trajectory.look_at(p, np.zeros(3), np.array([0.0, 0.0, 1.0])) for p in pos])
    ones = np.ones(n, np.float32)
    return Cameras(
        c2w=c2w,
        fx=40 * ones,
        fy=40 * ones,
        cx=16 * ones,
        cy=16 * ones,
        distortion=np.zeros((n, 4), np.float32),
        width=32,
        height=32,
    )


@settings(max_examples=20, deadline=None)
@given(
    count=st.integers(0, 30),
    seed=st.integers(0, 2**31 - 1),
    density=st.sampled_from(["angles", "sphere"]),
    margin=st.sampled_from([0.0, 5.0, 45.0]),
)
def test_novel_views_stay_within_the_cameras_ranges_and_look_at_their_focus(
    count: int, seed: int, density: str, margin: float
) -> None:
    cams = _ring_cameras()
    novel = novel_views.novel_cameras(cams, count, seed, density, margin)
    assert len(novel) == count and (novel.width, novel.height) == (cams.width, cams.height)
    if not count:
        return
    pos = novel.c2w[:, :, 3].astype(np.float64)
    dist = np.linalg.norm(pos, axis=-1)
    elev = np.degrees(np.arcsin(pos[:, 2] / dist))
    given_pos = cams.c2w[:, :, 3].astype(np.float64)
    given_dist = np.linalg.norm(given_pos, axis=-1)
    given_elev = np.degrees(np.arcsin(given_pos[:, 2] / given_dist))
    assert given_dist.min() - 1e-4 <= dist.min() and dist.max() <= given_dist.max() + 1e-4
    low, high = max(given_elev.min() - margin, -90.0), min(given_elev.max() + margin, 90.0)
    assert low - 1e-3 <= elev.min() and elev.max() <= high + 1e-3
    # Every camera looks at the origin (-z axis towards it) with no roll (x axis horizontal).
    forward = -novel.c2w[:, :, 2]
    np.testing.assert_allclose(np.sum(forward * (-pos / dist[:, None]), -1), 1.0, atol=1e-4)
    np.testing.assert_allclose(novel.c2w[:, 2, 0], 0.0, atol=1e-4)
    again = novel_views.novel_cameras(cams, count, seed, density, margin)
    np.testing.assert_array_equal(novel.c2w, again.c2w)
    np.testing.assert_allclose(novel.fx, cams.fx[0])


def test_novel_views_spread_uniformly_in_elevation_or_over_the_spheres_area() -> None:
    # 4,000 views around cameras at 10-60° elevation: "angles" spreads the elevation uniformly, "sphere" its
    # sine (equal areas of the sphere get equal views, so more lie near the horizon); a margin widens the
    # range on both sides.
    cams = _ring_cameras(200)
    pos = cams.c2w[:, :, 3].astype(np.float64)
    given = np.arcsin(pos[:, 2] / np.linalg.norm(pos, axis=-1))
    quartiles = np.array([0.25, 0.5, 0.75])

    def elevations(density: str, margin: float) -> np.ndarray:
        p = novel_views.novel_cameras(cams, 4000, 3, density, margin).c2w[:, :, 3].astype(np.float64)
        return np.arcsin(p[:, 2] / np.linalg.norm(p, axis=-1))

    for margin in (0.0, 5.0):
        low, high = given.min() - np.radians(margin), given.max() + np.radians(margin)
        flat = elevations("angles", margin)
        np.testing.assert_allclose(np.quantile(flat, quartiles), low + quartiles * (high - low), atol=0.02)
        area = np.sin(elevations("sphere", margin))
        expected = np.sin(low) + quartiles * (np.sin(high) - np.sin(low))
        np.testing.assert_allclose(np.quantile(area, quartiles), expected, atol=0.02)
        assert np.median(elevations("sphere", margin)) < np.median(flat) - 0.05  # nearer the horizon
    with pytest.raises(ValueError, match="density"):
        novel_views.novel_cameras(cams, 3, 0, "cube")


def test_novel_views_of_forward_facing_cameras_need_the_scenes_depth_bounds() -> None:
    # Their novel views lie on the spiral render path, whose focus depth comes from the scene's depth bounds
    # (tests/test_llff_ndc.py tests the poses).
    cams = dataclasses.replace(_ring_cameras(), ndc=NDCSpace(focal=40.0, width=32, height=32, near=1.0))
    with pytest.raises(ValueError, match="depth bounds"):
        novel_views.novel_cameras(cams, 3, 0)


# Two of the 14 augmentations for steps whose test is not about them: the step (and its negatives' policy)
# compiles in half the time; test_augment compiles the policy over the whole registry.
FEW_ATTACKS = ("gaussian_noise", "box_blur")


def _two_class_set(bits: int = 8) -> tuple[decoder_refit.RefitSet, dict]:
    """Two IDs whose renders differ by a pattern each (random 32-px images), and a random decoder."""
    rng = np.random.default_rng(1)
    base = rng.uniform(0.2, 0.8, (6, 32, 32, 3)).astype(np.float32)
    # Low-frequency patterns (8-px blocks), as LL2 keeps them.
    blocks = rng.normal(0, 0.1, (2, 1, 4, 4, 3))
    patterns = np.repeat(np.repeat(blocks, 8, axis=2), 8, axis=3).astype(np.float32)
    renders = np.clip(base[None] + patterns, 0, 1)
    messages = rng.integers(0, 2, (2, bits)).astype(np.uint8)
    variables = decoder_lib.init_decoder(jax.random.PRNGKey(0), bits)
    variables = decoder_lib.fit_whitening(variables, [dwt.ll2(renders.reshape(-1, 32, 32, 3))])
    negatives = np.round(base * 255).astype(np.uint8)  # kept as a verifier receives them
    return decoder_refit.RefitSet(renders, messages, negatives, keys_lib.null_message(messages)), variables


def _bit_accuracy(variables: dict, data: decoder_refit.RefitSet) -> float:
    logits = np.stack([np.asarray(decoder_lib.decode_logits(variables, r)) for r in data.renders])
    return float(((logits > 0) == data.messages[:, None].astype(bool)).mean())


def test_the_refit_decoder_learns_the_ids_keys_and_is_deterministic() -> None:
    data, variables = _two_class_set()
    # Two of the 14 augmentations: the random policy stays in the step (and in the determinism below), and
    # the step compiles much faster than with the whole registry; the refit reads these as well as all 14.
    cfg = wm_config(
        phase3_steps=200, phase3_batch=8, phase3_lr=1e-3, seed=3, augment_names=("gaussian_noise", "box_blur")
    )
    before = _bit_accuracy(variables, data)
    refit, metrics = decoder_refit.refit_decoder(cfg, variables, data)
    assert metrics["steps"] == 200 and np.isfinite(metrics["loss"])
    after = _bit_accuracy(refit, data)
    assert after >= 0.9 and before < 0.7
    # Only the weights learn; BatchNorm statistics and whitening stay.
    for name in set(variables) - {"params"}:
        for x, y in zip(jax.tree.leaves(variables[name]), jax.tree.leaves(refit[name]), strict=True):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    again, _ = decoder_refit.refit_decoder(cfg, variables, data)
    for x, y in zip(jax.tree.leaves(refit), jax.tree.leaves(again), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    answers = iter([True] * 5 + [False])
    _, metrics = decoder_refit.refit_decoder(cfg, variables, data, keep_going=answers.__next__)
    assert metrics["steps"] == 5


def test_phase_three_weighs_its_negatives_by_its_own_weight_not_phase_twos() -> None:
    # The loss of one refit step is linear in phase3_lambda_clean (the negatives' BCE against the null word,
    # positive), and phase 2's lambda_clean does not enter it.
    data, variables = _two_class_set()
    arrays = jax.tree.map(jax.numpy.asarray, data)

    def loss(**weights: float) -> float:
        cfg = wm_config(
            phase3_steps=10, phase3_batch=8, augment_prob=0.0, augment_names=FEW_ATTACKS, **weights
        )
        step = decoder_refit.make_refit_step(cfg, variables)
        opt_state = decoder_refit.refit_optimizer(cfg).init(variables["params"])
        return float(step(variables["params"], opt_state, jax.random.key(5), arrays, 0, 10)[2])

    none = loss(phase3_lambda_clean=0.0, lambda_clean=5.0)
    one = loss(phase3_lambda_clean=1.0, lambda_clean=0.0)
    two = loss(phase3_lambda_clean=2.0, lambda_clean=5.0)
    assert one - none > 0
    assert two - none == pytest.approx(2.0 * (one - none), rel=1e-4)


def test_a_run_from_before_a_phase_3_setting_existed_counts_it_at_its_default(tmp_path) -> None:
    # A finished run whose config.json predates phase3_lambda_clean ran it at its default: resuming it under
    # the same settings is the no-op, not a refusal; another phase-3 setting is still refused.
    from mnerf_jax.core.config import Config

    wm = wm_config(phase1_steps=2, phase2_steps=3, phase3_steps=4)
    saved = {f"phase3_{k}": v for k, v in dataclasses.asdict(wm.phase3).items() if k != "lambda_clean"}
    meta = {"step": 9, "config": {"watermark": saved}}
    E.check_phase3_unchanged(meta, Config(watermark=wm), tmp_path)
    with pytest.raises(MnerfError, match="phase 3"):
        E.check_phase3_unchanged(
            meta,
            Config(
                watermark=dataclasses.replace(wm, phase3=dataclasses.replace(wm.phase3, lambda_clean=3.0))
            ),
            tmp_path,
        )


def test_the_refit_schedule_warms_up_then_decays_to_zero() -> None:
    schedule = decoder_refit.refit_schedule(wm_config(phase3_steps=1000, phase3_lr=1e-3))
    assert float(schedule(0)) == 0.0
    assert float(schedule(100)) == pytest.approx(1e-3)
    assert float(schedule(50)) == pytest.approx(5e-4)
    assert float(schedule(1000)) == pytest.approx(0.0, abs=1e-9)


@settings(max_examples=40, deadline=None)
@given(total=st.integers(2, 20_000), where=st.floats(0.0, 1.2))
def test_the_refit_rate_is_optaxs_warmup_cosine_schedule_of_its_length(total: int, where: float) -> None:
    # The rate takes its schedule's length as data (so phase 3 can be sized to the minutes left); at any
    # length it is the schedule phase 3 had as optax's warmup_cosine_decay_schedule.
    cfg = wm_config(phase3_lr=1e-3)
    step = int(where * total)
    reference = optax.warmup_cosine_decay_schedule(0.0, 1e-3, max(total // 10, 1), total)
    expected = pytest.approx(float(reference(step)), abs=2e-9)
    assert float(decoder_refit.refit_rate(cfg, step, total)) == expected
    assert float(decoder_refit.refit_rate(cfg, jnp.int32(step), jnp.int32(total))) == expected


def test_phase_three_sizes_its_schedule_to_the_minutes_left() -> None:
    # With no time left after the timed steps, the schedule ends at the next step (the rate decayed to 0 on
    # it); with all the time it needs, it is the configured schedule, step for step the unbudgeted refit.
    data, variables = _two_class_set()
    cfg = wm_config(phase3_steps=60, phase3_batch=4, augment_prob=0.0, augment_names=FEW_ATTACKS, seed=2)
    plain, plain_metrics = decoder_refit.refit_decoder(cfg, variables, data)
    roomy, roomy_metrics = decoder_refit.refit_decoder(cfg, variables, data, seconds_left=lambda: 1e9)
    assert plain_metrics["scheduled"] == roomy_metrics["scheduled"] == roomy_metrics["steps"] == 60
    for x, y in zip(jax.tree.leaves(plain), jax.tree.leaves(roomy), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    _, short = decoder_refit.refit_decoder(cfg, variables, data, seconds_left=lambda: 0.0)
    assert short["scheduled"] == short["steps"] == time_budget.SIZING_STEPS + 2
    assert float(decoder_refit.refit_rate(cfg, short["steps"] - 1, short["scheduled"])) < 0.05 * cfg.phase3.lr


@pytest.mark.parametrize(("minutes_left", "scheduled"), [((10.0, 1e9), 60), ((1e9, 0.0), 27)])
def test_phase_three_sizes_its_schedule_again_as_it_runs(
    monkeypatch: pytest.MonkeyPatch, minutes_left: tuple[float, float], scheduled: int
) -> None:
    # A clock that reads 1 s more at each call: the timed steps take 1 s each, so the first sizing (10 s
    # left) plans 21 + 9 steps; the next sizing, 5 steps on, sees 0.2 s steps and room for all 60 again.
    # Time that runs out after a roomy start ends the schedule at the step after the next sizing.
    monkeypatch.setattr(time_budget, "RESIZE_EVERY", 5)
    data, variables = _two_class_set()
    cfg = wm_config(phase3_steps=60, phase3_batch=4, augment_prob=0.0, augment_names=FEW_ATTACKS, seed=2)
    ticks = iter(range(10**6))
    answers = iter(minutes_left)
    _, metrics = decoder_refit.refit_decoder(
        cfg,
        variables,
        data,
        seconds_left=lambda: next(answers, minutes_left[-1]),
        clock=lambda: float(next(ticks)),
    )
    assert metrics["scheduled"] == metrics["steps"] == scheduled


def test_phase_three_follows_the_fields_schedule_and_the_budget_keeps_room_for_it() -> None:
    cfg = wm_config(phase1_steps=2, phase2_steps=3, phase3_steps=4)
    assert [phase_of(s, cfg) for s in range(7)] == [1, 1, 2, 2, 2, 3, 3]
    clock = time_budget.BudgetClock(budget_s=100.0, started=0.0, kept_s=30.0)
    clock.record_step(1.0)
    # 1 s step + 5 s checkpoint + 45 s reserve + 30 s kept: the last step starts by t = 19 s.
    assert clock.room_for_a_step(19.0) and not clock.room_for_a_step(19.5)
    assert clock.room_for(0.0, 50.0) and not clock.room_for(0.0, 50.5)


def test_phase_three_settings_are_checked() -> None:
    for bad in (
        {"phase3_steps": -1},
        {"phase3_views": -2},
        {"phase3_batch": 0},
        {"phase3_lr": 0.0},
        {"phase3_reserve_min": -1.0},
        {"phase3_lambda_clean": -0.1},
        {"phase3_view_density": "cube"},
        {"phase3_elevation_margin": -1.0},
        {"phase3_elevation_margin": 91.0},
    ):
        with pytest.raises(MnerfError, match="phase3"):
            wm_config(**bad)


def test_tiny_embed_with_phase_three_and_its_resume(tiny: TinyRuns) -> None:
    # The tiny run's field (2 IDs, 8 bits) gets phase 3 by --resume (its settings are not in the field's
    # fingerprint); the decoder changes, the field does not; keys.json follows the new decoder; a second
    # phase 3 with other settings is refused, one with the same settings is a no-op.
    root = tiny.root
    run = root / "p3"
    shutil.copytree(tiny.wm, run)
    before = wm_run.load_watermarked_run(run)
    phase3 = [
        *tiny.embed_overrides,
        "watermark.phase3.steps=6",
        "watermark.phase3.views=2",
        "watermark.phase3.batch=4",
    ]
    args = dict(decoder_path=tiny.decoder, progress=False, resume=True)
    result = E.embed(tiny.fit, run, 2, 8, overrides=phase3, **args)
    assert result.steps == before.step + 6
    assert result.last_metrics["phase3_steps"] == 6
    after = wm_run.load_watermarked_run(run)
    assert after.step == before.step + 6
    assert json.loads((run / "embed.json").read_text())["phase"] == 3
    assert json.loads((run / "config.json").read_text())["watermark"]["phase3"]["steps"] == 6
    for x, y in zip(jax.tree.leaves(before.params), jax.tree.leaves(after.params), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    dec_before, dec_after = before.extras["decoder"], after.extras["decoder"]
    assert dec_before.fingerprint != dec_after.fingerprint
    assert json.loads((run / "keys.json").read_text())["decoder_fingerprint"] == dec_after.fingerprint
    assert decoder_io.load_decoder(run / "decoder.npz").fingerprint == dec_after.fingerprint
    again = E.embed(tiny.fit, run, 2, 8, overrides=phase3, **args)
    assert again.steps == after.step
    assert wm_run.load_watermarked_run(run).extras["decoder"].fingerprint == dec_after.fingerprint
    with pytest.raises(MnerfError, match="phase 3"):
        E.embed(tiny.fit, run, 2, 8, overrides=[*phase3, "watermark.phase3.steps=7"], **args)


def test_a_field_the_time_budget_ends_still_gets_phase_three(
    tiny: TinyRuns, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Where steps run slow the budget ends the field before its schedule does; phase 3 then runs in the
    # minutes kept for it (here the clock finds no room for a third field step, and all the time phase 3
    # needs). Its checkpoint lies past the field's schedule, so --resume finds the run finished.
    two_steps = lambda self, now: len(self.step_seconds) < 2  # noqa: E731
    monkeypatch.setattr(time_budget.BudgetClock, "room_for_a_step", two_steps)
    run = tiny.root / "p3_cut"
    overrides = [
        *tiny.embed_overrides,
        "watermark.schedule.phase1_steps=2",
        "watermark.schedule.phase2_steps=3",
        "watermark.phase3.steps=4",
        "watermark.phase3.views=2",
        "watermark.phase3.batch=4",
        "watermark.time_budget.minutes=30",
        "watermark.phase3.reserve_min=1",
    ]
    args = dict(decoder_path=tiny.decoder, progress=False)
    result = E.embed(tiny.fit, run, 2, 8, overrides=overrides, **args)
    assert result.stopped_by_budget
    assert (result.last_metrics["field_steps"], result.last_metrics["phase3_steps"]) == (2, 4)
    assert result.steps == 5 + 4 and wm_run.load_watermarked_run(run).step == 9
    assert json.loads((run / "embed.json").read_text())["phase"] == 3
    field = E.embed(
        tiny.fit,
        tiny.root / "p3_cut_field",
        2,
        8,
        stop_at=2,
        overrides=[*overrides, "watermark.phase3.steps=0"],
        **args,
    )
    refit = wm_run.load_watermarked_run(run)
    for x, y in zip(jax.tree.leaves(field.state.params), jax.tree.leaves(refit.params), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-6, atol=1e-7)
    assert (
        refit.extras["decoder"].fingerprint
        != wm_run.load_watermarked_run(tiny.root / "p3_cut_field").extras["decoder"].fingerprint
    )
    monkeypatch.undo()
    again = E.embed(tiny.fit, run, 2, 8, overrides=overrides, resume=True, **args)
    assert again.steps == 9 and not again.stopped_by_budget


def test_the_field_schedule_is_sized_to_the_minutes_the_budget_leaves_it(
    tiny: TinyRuns, monkeypatch: pytest.MonkeyPatch
) -> None:
    # With phase 3 to follow, the field's schedule shrinks to the steps its share of the budget allows, and
    # its quality ramp runs over those steps: the budget is at its final value when the field ends. One
    # timed phase-2 step sizes it here (SIZING_STEPS = 1), and the field's share has room for one more step.
    monkeypatch.setattr(time_budget, "SIZING_STEPS", 1)
    monkeypatch.setattr(time_budget.BudgetClock, "seconds_left", lambda self, now: self.kept_s + 1e-3)
    overrides = [
        *tiny.embed_overrides,
        "watermark.schedule.phase1_steps=2",
        "watermark.schedule.phase2_steps=6",
        "watermark.fidelity.psnr=40",
        "watermark.fidelity.psnr_start=20",
        "watermark.fidelity.ramp=[0.35, 0.6]",
        "watermark.phase3.steps=4",
        "watermark.phase3.views=2",
        "watermark.phase3.batch=4",
        "watermark.time_budget.minutes=30",
        "watermark.phase3.reserve_min=1",
    ]
    budgets: dict[int, float] = {}
    result = E.embed(
        tiny.fit,
        tiny.root / "sized_field",
        2,
        8,
        overrides=overrides,
        decoder_path=tiny.decoder,
        progress=False,
        on_step=lambda step, host: budgets.setdefault(step, host["psnr_budget"]),
    )
    assert result.stopped_by_budget and sorted(budgets) == [0, 1, 2, 3, 4]
    last = result.last_metrics
    assert (last["field_steps"], last["field_scheduled"], last["phase3_steps"]) == (5, 5, 4)
    assert result.steps == 8 + 4  # past the configured field: --resume finds the run finished
    # Sized at step 4 to 5 steps, the ramp (35-60 % of them) has ended: the last field step is at 40 dB;
    # step 3 was still on the configured 8 steps' ramp (20 dB until step 2.8, 40 dB at step 4.8).
    assert budgets[4] == pytest.approx(40.0, abs=1e-3)
    assert budgets[2] == pytest.approx(20.0, abs=1e-3) and budgets[3] == pytest.approx(22.0, abs=1e-3)


def test_a_refit_set_kept_as_its_reads_steps_exactly_as_the_images() -> None:
    # Without augmentations phase 3 keeps each image as its read window at max_side, as it is and rounded to
    # 8 bits (reads_of): the step then reads the very pixels it would have cut from the whole images.
    data, variables = _two_class_set()
    cfg = wm_config(
        phase3_steps=10,
        phase3_batch=8,
        augment_prob=0.0,
        augment_names=FEW_ATTACKS,
        read_window=0.72,
        read_max_side=16,
        lambda_key=0.2,
    )
    assert decoder_refit.keeps_reads_only(cfg)
    assert not decoder_refit.keeps_reads_only(wm_config(augment_prob=0.5))
    images = data.renders[0]
    reads = decoder_refit.reads_of(images, cfg)
    assert reads.shape == (len(images), 2, 16, 16, 3)
    read = read_window.of_config(cfg.reading)
    for kept, image in ((reads[:, 0], images), (reads[:, 1], np.round(images * 255) / 255)):
        expected = read_window.read_window(
            jnp.asarray(image), read.window, read.background, max_side=read.max_side
        )
        np.testing.assert_allclose(kept, np.asarray(expected), atol=1e-6)
    compact = decoder_refit.RefitSet(
        np.stack([decoder_refit.reads_of(r, cfg) for r in data.renders]),
        data.messages,
        data.negatives,  # whole 8-bit images in either layout: each step attacks them
        data.null,
        compact=True,
    )
    step = decoder_refit.make_refit_step(cfg, variables)
    opt_state = decoder_refit.refit_optimizer(cfg).init(variables["params"])
    outs = [
        step(variables["params"], opt_state, jax.random.key(7), jax.tree.map(jnp.asarray, d), 0, 10)
        for d in (data, compact)
    ]
    np.testing.assert_allclose(float(outs[1][2]), float(outs[0][2]), rtol=1e-5)
    for x, y in zip(jax.tree.leaves(outs[0][0]), jax.tree.leaves(outs[1][0]), strict=True):
        np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=1e-4, atol=1e-6)


def test_the_refit_set_reuses_clean_renders_of_the_training_views_it_is_given(tiny: TinyRuns) -> None:
    # The embedding's quality budget has already rendered the training views with the clean model (float16
    # references); phase 3 then renders only the novel views clean, and its set is the same.
    from mnerf_jax.tensorf import run as runs

    wm = wm_run.load_watermarked_run(tiny.wm)
    clean = wm_run.load_run(tiny.fit)
    split = wm.load_scene(None, splits=("train",)).split("train")
    cfg = dataclasses.replace(
        wm.config.watermark, phase3=dataclasses.replace(wm.config.watermark.phase3, views=2)
    )
    rendered = decoder_refit.render_refit_set(wm, split.cameras, cfg, split.images, clean)
    references = np.stack(runs.render_views(clean, split.cameras)).astype(np.float16)
    reused = decoder_refit.render_refit_set(
        wm, split.cameras, cfg, split.images, clean, clean_renders=references
    )
    views = len(split.images)
    negatives = 2 * views + 2 + decoder_refit.generic_count(2 * views + 2)  # and images from elsewhere
    assert reused.negatives.shape == rendered.negatives.shape == (negatives, *split.images.shape[1:])
    assert reused.negatives.dtype == rendered.negatives.dtype == np.uint8  # as a verifier receives them
    # The references are float16: a pixel may round to the next 8-bit level.
    np.testing.assert_allclose(reused.negatives.astype(int), rendered.negatives.astype(int), atol=1)
    np.testing.assert_array_equal(reused.renders, rendered.renders)
    with pytest.raises(ValueError, match="clean renders"):
        decoder_refit.render_refit_set(
            wm, split.cameras, cfg, split.images, clean, clean_renders=references[1:]
        )
    # The time budget's share for novel views ends the set after their first chunk (render_more is asked
    # before each later one), with their clean renders alike.
    many = dataclasses.replace(
        cfg, phase3=dataclasses.replace(cfg.phase3, views=decoder_refit.VIEWS_PER_CHUNK + 2)
    )
    asked = []
    cut = decoder_refit.render_refit_set(
        wm, split.cameras, many, split.images, clean, render_more=lambda: asked.append(1) and False
    )
    chunk = decoder_refit.VIEWS_PER_CHUNK
    assert len(asked) == 1
    scene = 2 * views + chunk
    assert cut.renders.shape[1] == views + chunk
    assert cut.negatives.shape[0] == scene + decoder_refit.generic_count(scene)
    np.testing.assert_array_equal(cut.renders[:, :views], rendered.renders[:, :views])  # training views first


def test_phase_three_attacks_its_negatives_even_when_the_renders_go_untouched(monkeypatch) -> None:
    # A verifier meets clean renders a platform re-encoded or colour-graded: phase 3 reads its negatives
    # through Medium attacks from the run's augmentation names, and its renders through the run's own policy
    # (none here), and decodes the negatives against the null word, far from every key.
    data, variables = _two_class_set()
    seen: list[tuple[str, tuple[str, ...] | None, int]] = []
    real = augment.random_policy

    def spy(key, images, strength="low", k=2, p=0.75, names=None):
        seen.append((strength, None if names is None else tuple(names), images.shape[0]))
        return real(key, images, strength, k, p, names)

    monkeypatch.setattr(augment, "random_policy", spy)
    cfg = wm_config(phase3_steps=10, phase3_batch=8, augment_prob=0.0, augment_names=("hue", "jpeg"))
    step = decoder_refit.make_refit_step(cfg, variables)
    opt_state = decoder_refit.refit_optimizer(cfg).init(variables["params"])
    jax.eval_shape(step, variables["params"], opt_state, jax.random.key(0), data, 0, 10)
    assert seen == [("medium", ("hue", "jpeg"), 8 // decoder_refit.NEGATIVES_PER_BATCH_DIVISOR)]
    assert data.negatives.dtype == np.uint8
    # Two 8-bit keys always leave a word 4 bits from both (flip where they agree, split where they differ).
    assert (data.null[None] != data.messages).sum(axis=1).min() >= 4


def test_phase_three_attacks_its_negatives_once_a_step_when_the_run_names_one_attack(monkeypatch) -> None:
    # Two distinct attacks cannot be drawn from one name: a run trained under JPEG alone still gets phase 3,
    # at the strength phase3.negative_strength sets.
    data, variables = _two_class_set()
    seen: list[tuple[str, int]] = []
    real = augment.random_policy

    def spy(key, images, strength="low", k=2, p=0.75, names=None):
        seen.append((strength, k))
        return real(key, images, strength, k, p, names)

    monkeypatch.setattr(augment, "random_policy", spy)
    cfg = wm_config(
        phase3={"steps": 10, "batch": 8, "negative_strength": "high"},
        augment_prob=0.0,
        augment_names=("jpeg",),
    )
    step = decoder_refit.make_refit_step(cfg, variables)
    opt_state = decoder_refit.refit_optimizer(cfg).init(variables["params"])
    jax.eval_shape(step, variables["params"], opt_state, jax.random.key(0), data, 0, 10)
    assert seen == [("high", 1)]


def test_the_generic_negatives_are_photo_crops_and_textures_of_the_renders_shape() -> None:
    # Non-square renders get images of their own shape; the draw is fixed by its seed; photographs and
    # textures alternate, and none is blank.
    images = decoder_refit.generic_negatives(6, 24, 40)
    assert images.shape == (6, 24, 40, 3) and images.dtype == np.uint8
    np.testing.assert_array_equal(images, decoder_refit.generic_negatives(6, 24, 40))
    assert not np.array_equal(images, decoder_refit.generic_negatives(6, 24, 40, seed=1))
    assert all(image.std() > 1 for image in images)
    assert decoder_refit.generic_count(400) == 133 and decoder_refit.generic_count(1) == 1


def test_phase_three_reads_its_attacked_copies_at_the_configured_share() -> None:
    # phase3.attacked = 1: every render and negative is read from its attacked copy, so the plain images no
    # longer enter the loss; 0: the copies are never read.
    data, variables = _two_class_set()
    cfg_read = wm_config(phase3_steps=10, phase3_batch=8, augment_prob=0.0, read_window=1.0)
    reads = lambda x: np.asarray(read_window.read_window(jnp.asarray(x), 1.0, None, max_side=0))  # noqa: E731
    rng = np.random.default_rng(2)
    attacked = data.replace(
        attacked=np.stack([decoder_refit.attacked_reads(r, cfg_read, rng) for r in data.renders]),
        attacked_negatives=decoder_refit.attacked_reads(data.negatives, cfg_read, rng),
    )
    assert attacked.attacked.shape == data.renders.shape and attacked.attacked.dtype == np.float16
    assert attacked.attacked_negatives.shape == data.negatives.shape
    assert np.abs(attacked.attacked - data.renders).max() > 0.01
    blank = attacked.replace(renders=np.zeros_like(data.renders), negatives=np.zeros_like(data.negatives))
    garbage = data.replace(
        attacked=rng.uniform(0, 1, attacked.attacked.shape).astype(np.float16),
        attacked_negatives=rng.uniform(0, 1, attacked.attacked_negatives.shape).astype(np.float16),
    )
    assert reads(data.renders[0]).shape == data.renders.shape[1:]  # the whole image is the window here

    steps = {}  # one compiled step per share

    def loss(share: float, d: decoder_refit.RefitSet) -> float:
        cfg = wm_config(
            phase3={"steps": 10, "batch": 8, "attacked": share},
            augment_prob=0.0,
            augment_names=FEW_ATTACKS,
            read_window=1.0,
        )
        if share not in steps:
            steps[share] = decoder_refit.make_refit_step(cfg, variables)
        step = steps[share]
        opt_state = decoder_refit.refit_optimizer(cfg).init(variables["params"])
        arrays = jax.tree.map(jnp.asarray, d)
        return float(step(variables["params"], opt_state, jax.random.key(5), arrays, 0, 10)[2])

    assert loss(1.0, attacked) == pytest.approx(loss(1.0, blank), rel=1e-6)
    assert loss(1.0, attacked) != pytest.approx(
        loss(1.0, data.replace(attacked=garbage.attacked, attacked_negatives=garbage.attacked_negatives)),
        rel=1e-3,
    )
    assert loss(0.0, garbage) == pytest.approx(loss(0.0, data), rel=1e-6)


def test_noisy_negatives_add_bounded_noise_to_a_quarter_of_the_images() -> None:
    # Mid-grey images, so that clipping at 0 and 1 is rare at σ ≤ 0.1: each changed image's residual has a
    # standard deviation within the bound, the unchanged ones are exact, and about a quarter change.
    images = jnp.full((800, 16, 16, 3), 0.5, jnp.float32)
    noisy = np.asarray(decoder_refit.noisy_negatives(jax.random.key(0), images, 0.1))
    residual = (noisy - 0.5).reshape(800, -1)
    changed = np.abs(residual).max(axis=1) > 0
    share = decoder_refit.NOISY_NEGATIVES_SHARE
    assert abs(changed.mean() - share) < 4 * np.sqrt(share * (1 - share) / 800)  # binomial, 4 sd
    assert residual[changed].std(axis=1).max() < 0.1 * 1.1 and (residual[~changed] == 0).all()
    assert noisy.min() >= 0.0 and noisy.max() <= 1.0
    assert (
        np.asarray(decoder_refit.noisy_negatives(jax.random.key(0), images, 0.0)).tolist()
        == np.asarray(images).tolist()
    )  # σ bound 0: nothing changes


def test_phase_three_noises_its_negatives_only_when_asked() -> None:
    # negative_noise 0 is today's step draw for draw; above 0 the negatives (and so the loss) change. A
    # batch of 64 has 16 negatives, so some are noised (the threefry draws are the same on every machine).
    data, variables = _two_class_set()

    def loss(**phase3: float) -> float:
        cfg = wm_config(
            phase3={"steps": 10, "batch": 64, **phase3},
            augment_prob=0.0,
            augment_names=FEW_ATTACKS,
            read_window=1.0,
        )
        step = decoder_refit.make_refit_step(cfg, variables)
        opt_state = decoder_refit.refit_optimizer(cfg).init(variables["params"])
        arrays = jax.tree.map(jnp.asarray, data)
        return float(step(variables["params"], opt_state, jax.random.key(5), arrays, 0, 10)[2])

    assert loss(negative_noise=0.0) == loss()
    assert loss(negative_noise=0.5) != pytest.approx(loss(), rel=1e-4)
    with pytest.raises(MnerfError, match="negative_noise"):
        wm_config(phase3={"steps": 10, "negative_noise": 1.5})


def test_the_refit_set_keeps_each_image_read_after_real_attacks_when_asked(tiny: TinyRuns) -> None:
    # Without the clean model's renders (test_the_refit_set_reuses_clean_renders_... has them); without
    # phase3.attacked no copies are kept (tests/test_llff_ndc.py).
    wm = wm_run.load_watermarked_run(tiny.wm)
    split = wm.load_scene(None, splits=("train",)).split("train")
    base = wm.config.watermark
    cfg = dataclasses.replace(base, phase3=dataclasses.replace(base.phase3, views=2, attacked=0.5))
    data = decoder_refit.render_refit_set(wm, split.cameras, cfg, split.images)
    n_ids, n_views = data.renders.shape[:2]
    plain = decoder_refit.reads_of(split.images[:1].astype(np.float32) / 255.0, cfg)[:, 0]
    assert data.attacked.shape == (n_ids, n_views, *plain.shape[1:])
    assert data.attacked_negatives.shape == (len(data.negatives), *plain.shape[1:])
    assert data.attacked.dtype == data.attacked_negatives.dtype == np.float16
    # Read after an attack, not as rendered; and drawn from the run's seed: the same set again.
    if data.compact:
        as_rendered = data.renders[:, :, 0]
    else:
        as_rendered = np.stack([decoder_refit.reads_of(r, cfg)[:, 0] for r in data.renders])
    assert np.abs(data.attacked - as_rendered).mean() > 1e-3
    again = decoder_refit.render_refit_set(wm, split.cameras, cfg, split.images)
    np.testing.assert_array_equal(again.attacked, data.attacked)
    np.testing.assert_array_equal(again.attacked_negatives, data.attacked_negatives)


def test_the_refit_script_redoes_phase_three_into_a_copy(tiny: TinyRuns, tmp_path, capsys) -> None:
    script = load_script("refit_phase3")
    keys_before, decoder_before = wm_run.load_keys_and_decoder(tiny.wm)
    out = tmp_path / "refit"
    phase3 = {"steps": 6, "batch": 4, "views": 2, "attacked": 0.5}
    argv = ["--run", str(tiny.wm), "--out", str(out)]
    argv += [a for k, v in phase3.items() for a in ("--set", f"watermark.phase3.{k}={v}")]
    assert script.main(argv) == 0
    keys, decoder = wm_run.load_keys_and_decoder(out)  # the copy's keys are tied to its new decoder
    assert decoder.fingerprint != decoder_before.fingerprint
    np.testing.assert_array_equal(keys.messages, keys_before.messages)
    assert json.loads((out / "config.json").read_text())["watermark"]["phase3"]["attacked"] == 0.5
    assert wm_run.load_keys_and_decoder(tiny.wm)[1].fingerprint == decoder_before.fingerprint  # untouched
    assert script.main(argv) == 2 and "exists" in capsys.readouterr().err
