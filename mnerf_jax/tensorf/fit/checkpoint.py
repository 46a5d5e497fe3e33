"""The fit's checkpoint layout: the tree a TensoRF training state is stored as, its restore target, and
restoring a state (refused when written under another config). ``train.fit`` writes and resumes with it;
``run.load_run`` reads fitted runs through it.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mnerf_jax.core.checkpoint import CheckpointStore, check_compatible
from mnerf_jax.core.config import Config
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.tensorf import field, raymarch
from mnerf_jax.tensorf.fit.step import StepHyper, TrainState, make_optimizer


def checkpoint_tree(state: TrainState, ray_keep: np.ndarray | None) -> dict[str, Any]:
    """The tree a fit checkpoint stores: state, geometry arrays, the ray filter's packed keep-bits."""
    return {
        "params": state.params,
        "opt_state": state.opt_state,
        "step": state.step,
        "lr_base_step": state.lr_base_step,
        "key": jax.random.key_data(state.key),
        "geometry": raymarch.geometry_arrays(state.geometry),
        # Packed keep-bits of the ray filter (training rays after the bbox drop); a placeholder byte
        # before it (orbax cannot store empty arrays).
        "ray_keep": np.packbits(ray_keep) if ray_keep is not None else np.zeros((1,), np.uint8),
    }


def state_target(config: Config, meta: Mapping[str, Any]) -> dict[str, Any]:
    """The checkpoint tree structure (shapes do not matter) for restoring a TensoRF state."""
    resolution = tuple(meta["resolution"])
    params = jax.eval_shape(lambda: field.init_field(jax.random.key(0), config.model, resolution))
    opt_state = jax.eval_shape(make_optimizer(StepHyper.from_config(config)).init, params)
    scalar = jax.ShapeDtypeStruct((), jnp.float32)
    return {
        "params": params,
        "opt_state": opt_state,
        "step": jax.ShapeDtypeStruct((), jnp.int32),
        "lr_base_step": jax.ShapeDtypeStruct((), jnp.int32),
        "key": jax.ShapeDtypeStruct((2,), jnp.uint32),
        "geometry": dict.fromkeys(raymarch.GEOMETRY_ARRAYS, scalar),
        "ray_keep": jax.ShapeDtypeStruct((1,), jnp.uint8),
    }


def state_from_checkpoint(
    tree: Mapping[str, Any], meta: Mapping[str, Any]
) -> tuple[TrainState, np.ndarray | None]:
    """``(TrainState, ray keep-mask or None)`` from a restored checkpoint tree and its meta."""
    geometry = raymarch.geometry_from_checkpoint(tree["geometry"], meta["geometry"])
    as_jnp = functools.partial(jax.tree.map, jnp.asarray)
    state = TrainState(
        params=as_jnp(tree["params"]),
        opt_state=as_jnp(tree["opt_state"]),
        step=jnp.asarray(tree["step"], jnp.int32),
        lr_base_step=jnp.asarray(tree["lr_base_step"], jnp.int32),
        key=jax.random.wrap_key_data(jnp.asarray(tree["key"], jnp.uint32)),
        geometry=geometry,
    )
    keep = None
    if meta.get("ray_keep_count") is not None:
        n = int(meta["ray_keep_total"])
        keep = np.unpackbits(np.asarray(tree["ray_keep"], np.uint8), count=n).astype(bool)
    return state, keep


def restore_state(
    config: Config, store: CheckpointStore, step: int | None = None
) -> tuple[TrainState, dict[str, Any], np.ndarray | None]:
    """``(state, meta, ray keep-mask)`` of a checkpoint, refused if written under another config."""
    meta = store.read_meta(step)
    if meta.get("kind", "tensorf") != "tensorf":
        raise MnerfError(f"checkpoint in {store.directory} holds a {meta.get('kind')!r} model, not tensorf")
    check_compatible(meta, config, store.directory.parent)
    tree, meta = store.restore(state_target(config, meta), meta["step"])
    state, keep = state_from_checkpoint(tree, meta)
    return state, meta, keep
