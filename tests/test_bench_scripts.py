"""The embedding benchmarks' bookkeeping: ``scripts/bench_embed_step.py``'s step clock, and
``scripts/bench_embed_scale.py``'s figures for every (size, IDs) asked on the tiny procedural fit (the
structure of its output, not its timings)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import load_script


def test_step_clock_medians_leave_each_phase_first_step_out() -> None:
    clock = load_script("bench_embed_step").StepClock(start=0.0)
    for stamp, phase in [(5.0, 1), (6.0, 1), (7.0, 1), (17.0, 2), (19.0, 2), (21.0, 2), (23.0, 2)]:
        clock.stamps.append(stamp)
        clock.phases.append(phase)
    assert clock.per_phase() == {1: [5.0, 1.0, 1.0], 2: [10.0, 2.0, 2.0, 2.0]}
    assert clock.medians() == {1: 1.0, 2: 2.0} and clock.first_steps_extra() == 4.0 + 8.0


def test_growth_exponents_are_log_log_slopes() -> None:
    scale = load_script("bench_embed_scale")
    assert scale.slope([1e4, 4e4, 16e4], [1.0, 4.0, 16.0]) == 1.0
    assert scale.slope([4, 16, 64], [2.0, 2.0, 2.0]) == 0.0
    assert scale.slope([100], [1.0]) is None and scale.slope([1, 2], [None, 3.0]) is None


def test_bench_embed_scale_reports_every_figure(tiny, tmp_path: Path, capsys) -> None:
    scale = load_script("bench_embed_scale")
    out = tmp_path / "scale.json"
    # One configuration (each runs in a process of its own, compiling everything again): the growth lines
    # over several are test_growth_lines_take_every_size_and_every_id_count's.
    argv = ["--run", str(tiny.fit), "--sizes", "24", "--num-ids", "2", "--bits", "8"]
    argv += [
        "--decoder",
        str(tiny.decoder),
        "--steps",
        "2",
        "--phase3-views",
        "2",
        "--json",
        "--out",
        str(out),
    ]
    # Short compilations (phase 2 only, two augmentations); phase 3 and the time budget on, so that every
    # figure is measured.
    sets = (
        "watermark.schedule.phase1_steps=0",
        "watermark.augment.names=gaussian_blur,box_blur",
        "watermark.phase3.steps=40",
        "watermark.phase3.views=6",
        "watermark.time_budget.minutes=5",
        "watermark.phase3.reserve_min=1",
    )
    argv += [arg for s in sets for arg in ("--set", s)]
    assert scale.main(argv) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == json.loads(out.read_text())
    assert printed["sizes"] == [24] and printed["num_ids"] == [2]
    rows = printed["rows"]
    assert [(r["side"], r["num_ids"], r["image"]) for r in rows] == [(24, 2, "24x24")]
    for row in rows:
        assert set(row) == set(scale.ROW_KEYS)
        assert row["cache_source"] and row["cache_mb"] > 0 and row["choice"]["preset"] == "procedural"
        assert row["schedule"] == [0, 3200] and row["phase3_schedule"] == 40 and row["phase3_views"] == 6
        for key in ("startup_s", "cache_s", "field_step_s", "phase3_step_s", "projected_s", "peak_rss_mb"):
            assert row[key] > 0, key
        assert row["field_peak_rss_mb"] <= row["peak_rss_mb"]
    assert printed["growth"] == scale.growth(rows)  # one size, one ID count: every exponent None
    assert printed["growth"]["pixels"]["field_step_s"] == {"2 IDs": None}


def test_growth_lines_take_every_size_and_every_id_count() -> None:
    scale = load_script("bench_embed_scale")
    # Step time ∝ pixels × IDs^0.5, memory ∝ pixels, projection flat; one failed row is left out.
    rows = [
        {
            "side": s,
            "num_ids": n,
            "pixels": s * s,
            "field_step_s": s * s * n**0.5,
            "peak_rss_mb": s * s,
            "projected_s": 7.0,
        }
        for s in (24, 48)
        for n in (1, 4)
    ] + [{"side": 96, "num_ids": 4, "error": "out of memory"}]
    g = scale.growth(rows)
    assert g["pixels"]["field_step_s"] == pytest.approx({"1 IDs": 1.0, "4 IDs": 1.0})
    assert g["ids"]["field_step_s"] == pytest.approx({"24 px": 0.5, "48 px": 0.5})
    assert g["ids"]["peak_rss_mb"] == pytest.approx({"24 px": 0.0, "48 px": 0.0}, abs=1e-12)
    assert g["pixels"]["projected_s"] == pytest.approx({"1 IDs": 0.0, "4 IDs": 0.0}, abs=1e-12)
    assert "96 px" not in g["ids"]["field_step_s"]
