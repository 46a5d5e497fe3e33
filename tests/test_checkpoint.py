"""Orbax checkpoint store: round trip, keep-last-k, config fingerprints and refusal of other configs."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import optax
import pytest

from mnerf_jax.core import checkpoint, rundir
from mnerf_jax.core.checkpoint import CheckpointError, CheckpointStore, check_compatible, config_fingerprint
from mnerf_jax.core.config import load_config


def _tree(scale: float, size: int = 4):
    params = {"w": jnp.full((size, 3), scale, jnp.float32), "b": jnp.arange(3, dtype=jnp.float32)}
    return {
        "params": params,
        "opt": optax.adam(1e-3).init(params),
        "step": jnp.int32(7),
        "mask": np.ones((2, 2, 2), bool),
    }


def test_fingerprint_ignores_bookkeeping_but_not_the_schedule():
    base = load_config("procedural")
    same = load_config(
        "procedural",
        ["train.checkpoint_every=7", "train.log_every=3", "train.keep_checkpoints=5", "render.chunk=1024"],
    )
    assert config_fingerprint(base) == config_fingerprint(same)
    for override in (
        "train.n_iters=999",
        "model.density_ranks=8,8,8",
        "render.step_ratio=0.25",
        "data.procedural_size=32",
    ):
        assert config_fingerprint(load_config("procedural", [override])) != config_fingerprint(base), override


def test_round_trip_restores_structure_values_and_meta(tmp_path):
    tree = _tree(2.0)
    with CheckpointStore(tmp_path, keep=2) as store:
        store.save(7, tree, {"step": 7, "resolution": [4, 4, 4]})
        store.wait()
        # Restoring takes the structure from the target; shapes come from the checkpoint.
        restored, meta = store.restore(_tree(0.0, size=9))
    assert meta == {"step": 7, "resolution": [4, 4, 4]}
    np.testing.assert_array_equal(restored["params"]["w"], tree["params"]["w"])
    assert isinstance(restored["opt"], type(tree["opt"]))
    assert restored["mask"].dtype == bool and int(restored["step"]) == 7


def test_keeps_only_the_last_checkpoints(tmp_path):
    with CheckpointStore(tmp_path, keep=2) as store:
        for step in (1, 2, 3):
            store.save(step, _tree(float(step)), {"step": step})
        store.wait()
        assert store.all_steps() == [2, 3] and store.latest_step() == 3
        restored, _ = store.restore(_tree(0.0), step=2)
    assert float(restored["params"]["w"][0, 0]) == 2.0


def test_incompatible_config_is_refused_with_the_difference(tmp_path):
    config = load_config("procedural")
    meta = {"fingerprint": config_fingerprint(config), "config": config.to_dict()}
    check_compatible(meta, config, tmp_path)  # same config: accepted
    other = load_config("procedural", ["train.n_iters=1234"])
    with pytest.raises(CheckpointError, match=rf"train\.n_iters: {config.train.n_iters} -> 1234"):
        check_compatible(meta, other, tmp_path)


def test_missing_checkpoints_are_clear_errors(tmp_path):
    with pytest.raises(CheckpointError, match="holds no checkpoints"):
        CheckpointStore(tmp_path / "nothing", create=False)
    with CheckpointStore(tmp_path) as store, pytest.raises(CheckpointError, match="no checkpoint"):
        store.read_meta()


def test_config_differences_lists_changed_fields():
    old = {"train": {"n_iters": 1, "seed": 0}, "model": {"a": 1}}
    new = {"train": {"n_iters": 2, "seed": 0}, "model": {"a": 1}}
    assert checkpoint.config_differences(old, new) == ["train.n_iters: 1 -> 2"]


def test_runs_written_under_an_older_digest_still_load(tmp_path):
    """A checkpoint or run whose stored digest predates a field becoming bookkeeping is accepted when its
    fields agree; a real difference is still refused."""

    config = load_config("procedural")
    meta = {"fingerprint": "0123456789abcdef", "config": config.to_dict()}  # a digest no config gives
    check_compatible(meta, config, tmp_path)
    with pytest.raises(CheckpointError, match="train.n_iters"):
        check_compatible(meta, load_config("procedural", ["train.n_iters=999"]), tmp_path)
    rundir.write_run_files(tmp_path / "r", config, data=None)
    marker = tmp_path / "r" / rundir.RUN_MARKER
    marker.write_text(marker.read_text().replace(config_fingerprint(config), "0123456789abcdef"))
    assert rundir.prepare_output(tmp_path / "r", config, resume=True)
    with pytest.raises(rundir.RunError, match="train.n_iters"):
        rundir.prepare_output(tmp_path / "r", load_config("procedural", ["train.n_iters=999"]), resume=True)


def test_runs_written_before_a_field_was_added_still_load(tmp_path):
    """A saved config without a field added since (here the data section's orientation and centring) reads
    the field at its default; a real difference is still refused."""
    config = load_config("procedural")
    saved = config.to_dict()
    del saved["data"]["orientation"], saved["data"]["centring"]
    meta = {"fingerprint": "0123456789abcdef", "config": saved}
    check_compatible(meta, config, tmp_path)
    with pytest.raises(CheckpointError, match="data.orientation: auto -> pca"):
        check_compatible(meta, load_config("procedural", ["data.orientation=pca"]), tmp_path)
