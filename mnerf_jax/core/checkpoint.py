"""Orbax checkpoints of a run: atomic, keep-last-k, refused when written under an incompatible config.

A checkpoint is ``RUN/checkpoints/<step>/`` with two items:

- ``state``: a pytree of arrays (``flax.serialization.to_state_dict`` of whatever the trainer keeps:
  params, optimizer state, step, PRNG key data, geometry, sample budgets);
- ``meta``: JSON (step, the config, its fingerprint, grid resolution, budgets, anything else small).

Orbax writes each step into a temporary directory and renames it when complete, so a crash mid-save
leaves the previous checkpoint intact. Restoring reads ``meta`` first, checks the fingerprint, then
restores the arrays as saved (shapes come from the checkpoint: grids change size during training) onto
this process's default device (a run checkpointed on a CPU resumes on a GPU, and the reverse), and maps
them back onto the caller's pytree structure with ``flax.serialization.from_state_dict``.
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import flax.serialization
import jax
import orbax.checkpoint as ocp

from mnerf_jax.core.config import Config, ConfigError, from_dict
from mnerf_jax.core.errors import MnerfError

CHECKPOINT_SUBDIR = "checkpoints"

# Fields that only change bookkeeping or how work is chunked, not the trajectory of the optimisation.
_BOOKKEEPING = {"train": ("checkpoint_every", "log_every", "keep_checkpoints"), "render": ("chunk",)}


class CheckpointError(MnerfError):
    """A checkpoint that is missing, unreadable, or from an incompatible config."""


def _without_bookkeeping(values: Mapping[str, Any], sections: tuple[str, ...]) -> dict:
    fields = {name: values.get(name, {}) for name in sections}
    for name, keys in _BOOKKEEPING.items():
        if isinstance(fields.get(name), Mapping):
            fields[name] = {k: v for k, v in fields[name].items() if k not in keys}
    return fields


def fingerprint_fields(
    config: Config, sections: tuple[str, ...] = ("data", "model", "render", "train")
) -> dict:
    """The config fields that decide array shapes and the optimisation trajectory."""
    return _without_bookkeeping(config.to_dict(), sections)


def config_fingerprint(
    config: Config, sections: tuple[str, ...] = ("data", "model", "render", "train")
) -> str:
    """A short hex digest of ``fingerprint_fields``: equal digests mean a checkpoint can be resumed."""
    blob = json.dumps(fingerprint_fields(config, sections), sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def _flatten(values: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in values.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(_flatten(value, name + "."))
        else:
            out[name] = value
    return out


def config_differences(old: Mapping[str, Any], new: Mapping[str, Any], limit: int = 4) -> list[str]:
    """``["train.n_iters: 1500 -> 2000", ...]`` between two nested config dicts."""
    a, b = _flatten(old), _flatten(new)
    diffs = [
        f"{k}: {a.get(k, '<absent>')} -> {b.get(k, '<absent>')}"
        for k in sorted(set(a) | set(b))
        if a.get(k) != b.get(k)
    ]
    if len(diffs) > limit:
        diffs = diffs[:limit] + [f"... ({len(diffs) - limit} more)"]
    return diffs


def fingerprint_differences(
    saved: Mapping[str, Any], config: Config, sections: tuple[str, ...] = ("data", "model", "render", "train")
) -> list[str]:
    """``config_differences`` between a saved config dict and ``config`` over the fingerprinted fields.

    Empty when they agree, even if the saved run's digest was computed under older fingerprint rules, or
    before a field was added (the saved config is read as any config, a field it lacks at its default).
    """
    try:
        saved = from_dict(saved).to_dict()
    except (ConfigError, TypeError, ValueError):
        saved = dict(saved)  # compared as written: the differences name what no longer reads
    return config_differences(_without_bookkeeping(saved, sections), fingerprint_fields(config, sections))


def check_compatible(
    meta: Mapping[str, Any],
    config: Config,
    where: str | Path,
    sections: tuple[str, ...] = ("data", "model", "render", "train"),
) -> None:
    """Raise CheckpointError unless ``meta`` was written under a config with the same fingerprint."""
    if meta.get("fingerprint") == config_fingerprint(config, sections):
        return
    saved = meta.get("config")
    if isinstance(saved, Mapping):
        diffs = "; ".join(fingerprint_differences(saved, config, sections))
        if not diffs:  # equal fields under another digest: written before a field became bookkeeping
            return
    else:
        diffs = "the checkpoint holds no config"
    raise CheckpointError(
        f"checkpoint in {where} was written under an incompatible config ({diffs}); "
        "use the run's own config or a new --out directory"
    )


class CheckpointStore:
    """Save and restore ``(state pytree, meta JSON)`` pairs under ``RUN/checkpoints``.

    Saves are asynchronous (the arrays are immutable, so training continues while they are written);
    ``wait()`` or ``close()`` blocks until the last one is on disk.
    """

    def __init__(self, run_dir: str | Path, keep: int = 2, create: bool = True):
        self.directory = Path(run_dir).resolve() / CHECKPOINT_SUBDIR
        if not create and not self.directory.is_dir():
            raise CheckpointError(f"{Path(run_dir)} holds no checkpoints (expected {self.directory})")
        # Orbax logs every save at INFO; the progress bar says enough.
        logging.getLogger("absl").setLevel(logging.WARNING)
        options = ocp.CheckpointManagerOptions(max_to_keep=max(1, int(keep)), create=create)
        self._manager = ocp.CheckpointManager(self.directory, options=options, item_names=("state", "meta"))

    def latest_step(self) -> int | None:
        """The newest complete checkpoint's step, or None."""
        return self._manager.latest_step()

    def all_steps(self) -> list[int]:
        return sorted(self._manager.all_steps())

    def save(self, step: int, state: Any, meta: Mapping[str, Any]) -> None:
        """Write checkpoint ``step`` (replacing nothing: a step already on disk is skipped)."""
        if step in self._manager.all_steps():
            return
        tree = flax.serialization.to_state_dict(state)
        args = ocp.args.Composite(state=ocp.args.StandardSave(tree), meta=ocp.args.JsonSave(dict(meta)))
        self._manager.save(int(step), args=args, force=True)

    def read_meta(self, step: int | None = None) -> dict[str, Any]:
        """The JSON item of checkpoint ``step`` (default: the latest)."""
        step = self._pick(step)
        try:
            out = self._manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))
        except Exception as err:  # orbax raises assorted types for damaged directories
            raise CheckpointError(f"cannot read checkpoint {step} in {self.directory}: {err}") from None
        return dict(out["meta"])

    def restore(self, target: Any, step: int | None = None) -> tuple[Any, dict[str, Any]]:
        """Restore ``(state, meta)``; ``target`` gives the pytree structure (its shapes are ignored)."""
        step = self._pick(step)
        try:
            abstract = self._abstract_state(step)
            args = ocp.args.Composite(state=ocp.args.StandardRestore(abstract), meta=ocp.args.JsonRestore())
            out = self._manager.restore(step, args=args)
        except Exception as err:
            raise CheckpointError(f"cannot read checkpoint {step} in {self.directory}: {err}") from None
        try:
            state = flax.serialization.from_state_dict(target, out["state"])
        except (KeyError, ValueError, TypeError) as err:
            raise CheckpointError(
                f"checkpoint {step} in {self.directory} does not match this model: {err}"
            ) from None
        return state, dict(out["meta"])

    def _abstract_state(self, step: int) -> Any:
        """The saved arrays' shapes and dtypes, placed on this process's default device.

        Without a target Orbax restores each array onto the device it was saved from, so a checkpoint
        written on a CPU could not be read on a GPU machine ("topology mismatch"), and the reverse.
        """
        meta = ocp.PyTreeCheckpointHandler().metadata(self.directory / str(step) / "state")
        tree = getattr(meta, "tree", meta)
        sharding = jax.sharding.SingleDeviceSharding(jax.devices()[0])
        return jax.tree.map(lambda m: jax.ShapeDtypeStruct(m.shape, m.dtype, sharding=sharding), tree)

    def _pick(self, step: int | None) -> int:
        if step is None:
            step = self.latest_step()
            if step is None:
                raise CheckpointError(f"no checkpoint in {self.directory}")
        elif step not in self._manager.all_steps():
            raise CheckpointError(f"no checkpoint for step {step} in {self.directory}")
        return int(step)

    def wait(self) -> None:
        self._manager.wait_until_finished()

    def close(self) -> None:
        self._manager.wait_until_finished()
        self._manager.close()

    def __enter__(self) -> CheckpointStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
