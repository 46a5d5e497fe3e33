"""Configs as data: the watermark's sections, their checks, their metadata, and config.json files written
before the sections."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from mnerf_jax.core import config
from mnerf_jax.core.errors import ConfigError
from mnerf_jax.core.watermark_config import WatermarkConfig, normalised


def test_a_config_round_trips_through_json(tmp_path: Path) -> None:
    cfg = config.load_config("embed_cpu_quality", ["watermark.reading.id_test=sign_flip"])
    (tmp_path / "config.json").write_text(cfg.to_json())
    assert config.load_json(tmp_path / "config.json") == cfg


def test_a_flat_config_json_from_before_the_sections_loads_as_today(tmp_path: Path) -> None:
    nested = config.load_preset("embed_cpu_quality")
    # fidelity.over_source came after the sections: no flat file has it, so it loads at its default.
    wm_now = nested.watermark
    nested = dataclasses.replace(
        nested,
        watermark=dataclasses.replace(wm_now, fidelity=dataclasses.replace(wm_now.fidelity, over_source=0.0)),
    )
    flat = nested.to_dict()
    wm = flat.pop("watermark")
    old_names = {
        "augment": "augment_{}",
        "reading": "read_{}",
        "fidelity": "fidelity_{}",
        "phase3": "phase3_{}",
    }
    legacy: dict = {k: v for k, v in wm.items() if not isinstance(v, dict)}
    for section, values in ((k, v) for k, v in wm.items() if isinstance(v, dict)):
        for name, value in values.items():
            if (section == "reading" and name.startswith("search")) or name == "over_source":
                continue  # added after the sections (at their defaults here): no flat file has them
            key = old_names.get(section, "{}").format(name)
            key = {
                "read_wavelet": "wavelet",
                "read_id_threshold": "id_threshold",
                "read_id_test": "id_test",
                "fidelity_weight": "lambda_fidelity",
                "minutes": "time_budget_min",
            }.get(key, key)
            legacy[key] = value
    legacy.update(emb_activation="relu", budget_sizes_field=False)  # removed, at the values this version runs
    (tmp_path / "config.json").write_text(json.dumps({**flat, "watermark": legacy}))
    assert config.load_json(tmp_path / "config.json") == nested


def test_a_removed_switch_at_another_value_is_refused_with_one_line() -> None:
    for key, value in (("emb_activation", "silu"), ("budget_sizes_field", True)):
        with pytest.raises(ConfigError, match=f"watermark.{key} = .* was removed") as err:
            config.from_dict({"watermark": {key: value}})
        assert "\n" not in str(err.value)


def test_a_runs_config_with_the_removed_anchor_term_loads_when_it_was_off() -> None:
    # losses.lambda_anchor / anchor_images were deleted (the null word does better): a run written with the
    # term off loads as today's default; one that ran it is refused in one line.
    off = config.from_dict(
        {"watermark": {"losses": {"lambda_anchor": 0.0, "anchor_images": 4, "lambda_key": 0.1}}}
    )
    assert off.watermark.losses == dataclasses.replace(config.Config().watermark.losses, lambda_key=0.1)
    with pytest.raises(ConfigError, match=r"watermark.losses.lambda_anchor = 1.0 was removed") as err:
        config.from_dict({"watermark": {"losses": {"lambda_anchor": 1.0}}})
    assert "\n" not in str(err.value)


def test_choices_and_ranges_are_checked_when_the_config_is_built() -> None:
    bad = [
        "watermark.variant=bogus",
        "watermark.losses.perceptual=lpips",
        "watermark.augment.strength=extreme",
        "watermark.reading.id_test=fisher",
        "watermark.phase3.view_density=cube",
        "watermark.losses.lambda_key=-1",
        "watermark.schedule.phase1_steps=-2",
        "watermark.module.wm_ranks=0,0,0",
        "watermark.fidelity.psnr=-1",
    ]
    for item in bad:
        with pytest.raises(ConfigError, match=item.split("=")[0].split(".")[-1]):
            config.load_config("procedural", [item])
    with pytest.raises(ConfigError, match="unknown config key config.watermark.schedule.nope"):
        config.load_config("procedural", ["watermark.schedule.nope=1"])


def test_field_metadata_decides_what_the_step_and_the_fingerprint_ignore() -> None:
    cfg = config.watermark_from_flat(
        seed=5, phase1_steps=3, phase3_steps=9, time_budget_min=10.0, read_jitter=2, lambda_key=0.5
    )
    host = normalised(cfg, "host")
    assert (host.seed, host.schedule.phase1_steps, host.phase3, host.time_budget, host.reading.jitter) == (
        0,
        -1,
        WatermarkConfig().phase3,
        WatermarkConfig().time_budget,
        0,
    )
    assert host.losses.lambda_key == 0.5  # the step reads it
    trajectory = normalised(cfg, "trajectory")
    assert trajectory.seed == 5 and trajectory.schedule.phase1_steps == 3  # they change the trajectory
    assert trajectory.phase3 == WatermarkConfig().phase3 and trajectory.reading.jitter == 0
    assert dataclasses.replace(trajectory, seed=0) != cfg


def test_flat_items_name_every_leaf_with_its_section() -> None:
    items = config.flat_items(WatermarkConfig())
    assert items["phase3.steps"] == 0 and items["reading.window"] == 0.0 and items["num_ids"] == 4
    assert all(not isinstance(v, dict) for v in items.values())
