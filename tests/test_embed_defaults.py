"""``mnerf embed`` without ``--config``: the settings chosen from the fitted run and the machine
(``core.embed_defaults``), recorded in the run and replayed on ``--resume``; ``--config paper``."""

from __future__ import annotations

import itertools
import json
import shutil

import pytest
from conftest import TinyRuns

from mnerf_jax.core import config as config_lib
from mnerf_jax.core import embed_defaults as auto
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.watermark import embed as E

GIB = 2**30


def facts(**changes: object) -> auto.SceneFacts:
    """Lego at 1/8 (100 training views of 100²) with 16 IDs on a CPU with 16 GiB free, then ``changes``."""
    values: dict[str, object] = dict(
        fit_preset="quick",
        height=100,
        width=100,
        views=100,
        backdrop=1.0,
        num_ids=16,
        backend="cpu",
        memory_bytes=16 * GIB,
    )
    values.update(changes)
    return auto.SceneFacts(**values)  # type: ignore[arg-type]


def chosen(choice: auto.Choice) -> config_lib.Config:
    return config_lib.apply_overrides(config_lib.load_preset(choice.preset), choice.settings)


def test_lego_at_100_gets_the_method_preset_as_it_is() -> None:
    choice = auto.choose(facts())
    assert choice == auto.Choice(auto.METHOD_PRESET)
    assert chosen(choice).watermark == config_lib.load_preset(auto.METHOD_PRESET).watermark


def test_a_fit_preset_with_its_own_embedding_keeps_it() -> None:
    assert auto.preset_ships_embedding("procedural") and not auto.preset_ships_embedding("quick")
    assert auto.choose(facts(fit_preset="procedural", height=64, width=64)) == auto.Choice("procedural")
    assert not auto.preset_ships_embedding("no-such-preset")


def test_the_time_budget_grows_with_pixels_up_to_twice_and_the_reserve_with_it() -> None:
    base = config_lib.load_preset(auto.METHOD_PRESET).watermark
    budgets = []
    for side in (50, 100, 120, 141, 200, 400, 800):
        cfg = chosen(auto.choose(facts(height=side, width=side))).watermark
        budgets.append(cfg.time_budget.minutes)
        share = cfg.phase3.reserve_min / cfg.time_budget.minutes
        assert share == pytest.approx(base.phase3.reserve_min / base.time_budget.minutes, rel=1e-2)
    assert budgets == sorted(budgets)
    assert budgets[0] == budgets[1] == base.time_budget.minutes
    assert budgets[-1] == auto.MAX_BUDGET_FACTOR * base.time_budget.minutes
    on_gpu = chosen(auto.choose(facts(height=800, width=800, backend="gpu"))).watermark
    assert on_gpu.time_budget.minutes == auto.GPU_MINUTES


def test_more_ids_than_a_step_renders_lengthen_the_field() -> None:
    base = config_lib.load_preset(auto.METHOD_PRESET).watermark.schedule.phase2_steps
    steps = {
        n: chosen(auto.choose(facts(num_ids=n))).watermark.schedule.phase2_steps for n in (1, 16, 17, 64)
    }
    assert steps == {1: base, 16: base, 17: 2 * base, 64: 4 * base}


def test_the_window_centres_on_the_image_without_a_backdrop() -> None:
    assert chosen(auto.choose(facts(backdrop=None))).watermark.reading.background < 0
    assert chosen(auto.choose(facts(backdrop=0.0))).watermark.reading.background == 0.0
    assert auto.backdrop_of("blender", True) == 1.0 and auto.backdrop_of("blender", False) == 0.0
    assert auto.backdrop_of("llff", False) is None and auto.backdrop_of("nerfstudio", True) is None


def test_a_read_close_to_the_decoders_side_stays_as_it_is_and_a_larger_one_is_downscaled() -> None:
    base = config_lib.load_preset(auto.METHOD_PRESET).watermark.reading
    assert base.max_side == 0 and base.window == 0.72
    sides = {}
    for side in (64, 100, 133, 135, 200, 800):
        sides[side] = chosen(auto.choose(facts(height=side, width=side))).watermark.reading.max_side
    # 0.72 of the side: 96 px at 133² is within 1.5 × 64, 97 px at 135² is not.
    assert sides == {64: 0, 100: 0, 133: 0, 135: 64, 200: 64, 800: 64}
    assert auto.read_side(facts(height=100, width=150), 0.0) == 150
    assert auto.read_side(facts(height=100, width=150), 0.72) == 72


def test_the_source_is_cached_only_when_its_samples_fit_in_memory() -> None:
    roomy = chosen(auto.choose(facts())).watermark.schedule
    assert roomy.cache_source
    tight = facts(memory_bytes=auto.cache_bytes(facts()))  # twice what half of it holds
    schedule = chosen(auto.choose(tight)).watermark.schedule
    assert not schedule.cache_source and schedule.patch_size == auto.UNCACHED_PATCH


def test_every_choice_is_a_valid_config_with_a_reason_per_setting() -> None:
    grid = itertools.product((64, 100, 333, 800), (1, 16, 40), ("cpu", "gpu"), (1.0, None), (GIB, 64 * GIB))
    for side, n, backend, backdrop, memory in grid:
        choice = auto.choose(
            facts(
                height=side,
                width=side + 7,
                num_ids=n,
                backend=backend,
                backdrop=backdrop,
                memory_bytes=memory,
            )
        )
        assert len(choice.reasons) == len(choice.settings)
        assert auto.Choice.from_dict(json.loads(json.dumps(choice.to_dict()))) == choice
        chosen(choice).watermark.check_ids(n)  # parses, validates (e.g. the cache without jitter)
        assert choice.describe().count("\n") == len(choice.settings)


def test_the_paper_preset_is_the_papers_method() -> None:
    cfg = config_lib.load_preset(auto.PAPER).watermark
    assert cfg.schedule.ids_per_step == 1 and not cfg.schedule.cache_source and cfg.schedule.jitter
    assert cfg.optim.lr_source_scale == 1.0
    assert (cfg.losses.lambda_message, cfg.losses.lambda_perceptual) == (0.95, 0.05)
    assert (cfg.losses.lambda_rgb, cfg.losses.lambda_tv, cfg.losses.lambda_ssim) == (0.1, 0.02, 0.2)
    assert cfg.losses.lambda_key == cfg.losses.lambda_clean == cfg.losses.id_loss_power == 0
    assert (cfg.augment.per_step, cfg.augment.prob) == (2, 1.0)
    assert cfg.reading.window == 0 and cfg.fidelity.psnr == 0 and cfg.phase3.steps == 0


def test_auto_is_recorded_and_replayed_on_resume(tiny: TinyRuns, monkeypatch: pytest.MonkeyPatch) -> None:
    # The tiny procedural fit as if its preset shipped no embedding: the method preset, tiny's steps on top.
    monkeypatch.setattr(auto, "preset_ships_embedding", lambda name: False)
    out = tiny.root / "auto_wm"
    shutil.rmtree(out, ignore_errors=True)
    args = dict(decoder_path=tiny.decoder, progress=False)
    overrides = [
        *tiny.embed_overrides,
        *("watermark.fidelity.psnr_start=0", "watermark.phase3.steps=0", "watermark.time_budget.minutes=0"),
    ]
    E.embed(tiny.fit, out, 2, 8, preset=auto.AUTO, overrides=overrides, stop_at=1, **args)
    record = json.loads((out / "run.json").read_text())[E.AUTO_RECORD]
    assert record["preset"] == auto.METHOD_PRESET
    config = json.loads((out / "config.json").read_text())["watermark"]
    method = config_lib.load_preset(auto.METHOD_PRESET).watermark
    assert config["reading"]["window"] == method.reading.window  # the method preset's, not the run's
    # A resume replays the recorded choice: with no memory the choice made now would differ.
    monkeypatch.setattr(auto, "free_memory_bytes", lambda: 1)
    resumed = E.embed(
        tiny.fit, out, 2, 8, preset=auto.AUTO, overrides=overrides, stop_at=2, resume=True, **args
    )
    assert resumed.steps == 2
    explicit = tiny.root / "explicit_wm"
    shutil.rmtree(explicit, ignore_errors=True)
    E.embed(tiny.fit, explicit, 2, 8, overrides=overrides, stop_at=1, **args)
    # A run embedded with the fitted run's section (or before --config auto) resumes with that section.
    again = E.embed(
        tiny.fit, explicit, 2, 8, preset=auto.AUTO, overrides=overrides, stop_at=2, resume=True, **args
    )
    assert again.steps == 2 and E.AUTO_RECORD not in json.loads((explicit / "run.json").read_text())
    with pytest.raises(MnerfError, match="incompatible config"):  # another preset's settings
        E.embed(tiny.fit, explicit, 2, 8, preset=auto.METHOD_PRESET, overrides=overrides, resume=True, **args)
