"""The fit / render / evaluate / demo commands on a tiny procedural run, and their refusals."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import TINY_SCHEDULE as TINY
from hypothesis import given
from hypothesis import strategies as st

from mnerf_jax import cli
from mnerf_jax.cli import demo
from mnerf_jax.core import rundir

# The schedule of tests/test_train.py (same static shapes: its compilations are reused here).


def _sets(overrides: list[str]) -> list[str]:
    return [arg for item in overrides for arg in ("--set", item)]


def _snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    """A fitted tiny procedural run (fit -> metrics.json, eval-test.json)."""
    run = tmp_path_factory.mktemp("cli") / "run"
    code = cli.main(["fit", "--out", str(run), *_sets(TINY), "--eval-views", "2", "--quiet"])
    assert code == 0
    return run


def test_fit_writes_the_documented_files(tiny_run):
    for name in ("run.json", "config.json", "metrics.json", "eval-test.json", "checkpoints", "tb"):
        assert (tiny_run / name).exists(), name
    marker = json.loads((tiny_run / "run.json").read_text())
    assert marker["kind"] == "tensorf" and marker["version"] == 1 and marker["data"] is None
    metrics = json.loads((tiny_run / "metrics.json").read_text())
    assert metrics["steps"] == 60 and metrics["train_seconds"] > 0
    assert {"psnr", "ssim", "lpips", "views"} <= set(metrics["test"]) and metrics["test"]["views"] == 2
    assert any((tiny_run / "tb").iterdir())


def test_render_test_split_and_path(tiny_run, tmp_path, mnerf):
    code, out, _ = mnerf(
        "render", "--run", tiny_run, "--split", "test", "--out", tmp_path / "t", "--views", "2", "--quiet"
    )
    assert code == 0 and sorted(p.name for p in (tmp_path / "t").iterdir()) == ["r_0.png", "r_3.png"]
    code, _, _ = mnerf(
        "render", "--run", tiny_run, "--split", "path", "--out", tmp_path / "p", "--frames", "3", "--quiet"
    )
    assert code == 0 and (tmp_path / "p" / "path.gif").stat().st_size > 0
    assert len(list((tmp_path / "p").glob("frame_*.png"))) == 3
    # Rendering again over the same files is refused unless asked for.
    before = _snapshot(tmp_path / "t")
    code, _, err = mnerf(
        "render", "--run", tiny_run, "--split", "test", "--out", tmp_path / "t", "--views", "2", "--quiet"
    )
    assert code == 2 and "--overwrite" in err and _snapshot(tmp_path / "t") == before


def test_evaluate_writes_and_prints_metrics(tiny_run, mnerf):
    code, out, _ = mnerf("evaluate", "--run", tiny_run, "--views", "2", "--quiet")
    assert code == 0
    printed = json.loads(out.strip().splitlines()[-1])
    saved = json.loads((tiny_run / "eval-test.json").read_text())
    for result in (printed, saved):
        assert {"psnr", "ssim", "lpips", "views", "split"} <= set(result) and result["views"] == 2
    assert saved["psnr"] == pytest.approx(printed["psnr"])


def test_fit_into_another_runs_directory_is_refused_and_changes_nothing(tiny_run, mnerf):
    before = _snapshot(tiny_run)
    code, _, err = mnerf("fit", "--out", tiny_run, *_sets([*TINY, "train.n_iters=61"]), "--quiet")
    assert code == 2 and "holds another run" in err and "train.n_iters: 60 -> 61" in err
    code, _, err = mnerf("fit", "--out", tiny_run, *_sets(TINY), "--quiet")
    assert code == 2 and "pass --resume" in err
    assert _snapshot(tiny_run) == before


def test_fit_into_a_non_run_directory_is_refused(tmp_path, mnerf):
    (tmp_path / "notes.txt").write_text("keep me")
    code, _, err = mnerf("fit", "--out", tmp_path, *_sets(TINY), "--quiet")
    assert code == 2 and "holds no mnerf run" in err
    assert _snapshot(tmp_path) == {"notes.txt": b"keep me"}


def test_unknown_set_key_is_one_clear_line(tmp_path, mnerf):
    code, _, err = mnerf("fit", "--out", tmp_path / "x", "--set", "train.n_iterz=5")
    assert code == 2 and err.strip().count("\n") == 0 and "unknown config key config.train.n_iterz" in err
    assert not (tmp_path / "x").exists()


def test_missing_data_and_missing_checkpoint_are_clear_errors(tmp_path, mnerf):
    code, _, err = mnerf("fit", "--config", "quick", "--data", tmp_path / "nope", "--out", tmp_path / "r")
    assert code == 2 and "no such scene directory" in err and not (tmp_path / "r").exists()
    # A run directory whose fit never reached a checkpoint.
    from mnerf_jax.core.config import load_config

    rundir.write_run_files(tmp_path / "empty", load_config("procedural", TINY), data=None)
    for command in ("render", "evaluate"):
        extra = ["--out", str(tmp_path / "o")] if command == "render" else []
        code, _, err = mnerf(command, "--run", tmp_path / "empty", *extra)
        assert code == 2 and "no checkpoint" in err, command
    code, _, err = mnerf("evaluate", "--run", tmp_path / "missing")
    assert code == 2 and "no such directory" in err


@given(
    minutes=st.floats(0.5, 30.0),
    reserve=st.floats(0.0, 10.0),
    elapsed=st.floats(0.0, 1200.0, allow_nan=False),
)
def test_the_demo_gives_its_embedding_what_is_left_of_its_ten_minutes(
    minutes: float, reserve: float, elapsed: float
) -> None:
    sets = dict(item.split("=") for item in demo.embedding_budget(minutes, reserve, elapsed))
    left = (demo.DEMO_MINUTES * 60 - elapsed - demo.FINISH_ALLOWANCE_S) / 60
    if left >= minutes:
        assert not sets  # the preset's budget fits: unchanged
        return
    budget = float(sets["watermark.time_budget.minutes"])
    assert min(minutes, demo.MIN_EMBED_MINUTES) - 1e-3 <= budget <= minutes + 1e-3
    if budget > demo.MIN_EMBED_MINUTES + 1e-3:  # the whole demo then ends within its ten minutes
        assert elapsed + budget * 60 + demo.FINISH_ALLOWANCE_S <= demo.DEMO_MINUTES * 60 + 0.1
    # phase 3 keeps the preset's share of the budget
    assert float(sets["watermark.phase3.reserve_min"]) == pytest.approx(reserve * budget / minutes, abs=2e-3)


def test_the_demo_leaves_an_embedding_without_a_time_budget_alone() -> None:
    assert demo.embedding_budget(0.0, 3.0, 590.0) == ()
    assert demo.embedding_budget(7.0, 3.0, 60.0) == ()  # 10 - 1 - 1 minutes left: the preset's 7 fit
    assert demo.embedding_budget(7.0, 3.0, 240.0) == (
        "watermark.time_budget.minutes=5.000",
        "watermark.phase3.reserve_min=2.143",
    )


def test_demo_into_a_folder_that_is_not_a_demos_is_refused(tmp_path, mnerf):
    # (tests/test_wm_cli.py runs the whole demo on the tiny fitted run.)
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "x").write_text("x")
    code, _, err = mnerf("demo", "--out", tmp_path / "other", *_sets(TINY), "--quiet")
    assert code == 2 and "not a demo folder" in err
