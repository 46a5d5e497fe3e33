"""Checkpoints of decoder training: the training state as msgpack (no pickle), written to a temporary file
and renamed, and read back only under the same trajectory settings (``DecoderTrainConfig.trajectory``).
:mod:`mnerf_jax.reader.train.stages` writes and resumes with them.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import flax.serialization
import jax
import jax.numpy as jnp

from mnerf_jax.core.errors import MnerfError
from mnerf_jax.reader.train.recipe import DecoderTrainConfig

# The parts of the training state that are arrays (and go through the jitted steps); the rest is bookkeeping.
ARRAY_KEYS = ("encoder", "decoder", "opt", "opt_ft", "opt_inf", "opt_ft_dec")
# Trajectory fields added after checkpoints were first written, with the value a checkpoint without them used.
ADDED_FIELDS = {
    "decoder_init": "random",
    "pool_margin": 0,
    "finetune_sizes": [],
    "decoder_from": "",
    "finetune_decoder_lr": 0.0,
    "finetune_decoder_start": 0.25,
    "read_side": 0,
    "encoder_from": "",
}


def save_checkpoint(path: Path, state: dict[str, Any], cfg: DecoderTrainConfig) -> None:
    payload = {
        "config": json.dumps(cfg.to_dict(), sort_keys=True),
        "state": flax.serialization.to_state_dict(jax.device_get(state)),
    }
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(flax.serialization.msgpack_serialize(payload))
    os.replace(tmp, path)


def load_checkpoint(path: Path, template: dict[str, Any], cfg: DecoderTrainConfig) -> dict[str, Any]:
    try:
        payload = flax.serialization.msgpack_restore(path.read_bytes())
    except Exception as err:  # msgpack raises several unrelated types for damaged input
        raise MnerfError(
            f"checkpoint {path} is unreadable ({type(err).__name__}); delete it to start over"
        ) from None
    saved = {**ADDED_FIELDS, **json.loads(payload["config"])}
    current = json.loads(json.dumps(cfg.trajectory()))  # tuples read back as lists
    diffs = [f"{k}: {saved.get(k)} -> {current[k]}" for k in sorted(current) if saved.get(k) != current[k]]
    if diffs:
        raise MnerfError(
            f"checkpoint {path} was written with other settings ({'; '.join(diffs[:3])}); "
            "use the same settings or another --out"
        )
    saved_state = dict(payload["state"])
    for name, value in flax.serialization.to_state_dict(template).items():
        saved_state.setdefault(name, value)  # fields added since the checkpoint was written
    state = flax.serialization.from_state_dict(template, saved_state)
    for name in ARRAY_KEYS:
        state[name] = jax.tree.map(jnp.asarray, state[name])
    state["step"] = int(state["step"])
    state["whitened"] = bool(state["whitened"])
    state["elapsed_s"] = float(state["elapsed_s"])
    state["whitening_report"] = {k: float(v) for k, v in state["whitening_report"].items()}
    return state
