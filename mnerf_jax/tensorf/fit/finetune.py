"""Continuing the photometric fit of a finished field for a few steps (``mnerf attack --model-suite``'s
fine-tuning attack: the holder of a field fits it again to the training images).

The continuation is the fit's own loop (:class:`loop.Trainer`: the jitted ``train_step``, its sample budgets
grown on overflow, its ray sampler) started where a fit ends: the step counter at ``train.n_iters``, so the
learning rates are the fit's times ``train.lr_decay_ratio`` and keep decaying as the fit's would (as if it
had run on without a reset), the L1 weight is ``l1_weight_rest`` and the TV weights have decayed alike. A
fresh Adam; no events (no upsampling, no alpha-mask update): the field keeps its resolution and geometry.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp

from mnerf_jax.core.config import Config
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.data import Scene
from mnerf_jax.tensorf import raymarch, render
from mnerf_jax.tensorf.fit.loop import Trainer
from mnerf_jax.tensorf.fit.step import StepHyper, TrainState, make_optimizer
from mnerf_jax.tensorf.sampler import training_rays

Params = Any
SEED_SALT = 0xF17E  # the continuation's PRNG stream, apart from the fit's


def continue_fit(
    config: Config,
    scene: Scene,
    params: Params,
    geometry: raymarch.Geometry,
    fns: render.FieldFns,
    snapshots: Sequence[int],
    *,
    seed: int = 0,
    on_step: Callable[[int, dict[str, float]], None] | None = None,
) -> dict[int, Params]:
    """``{n: params after n more steps}`` for every ``n`` in ``snapshots`` (one trajectory: the snapshot at
    500 steps is the one a continuation of exactly 500 steps ends with).

    Args:
      config: the field's config (``train`` gives the loss, batch, rates; ``render`` the sample weights).
      scene: a scene with a ``train`` split (the training images).
      params: the field's params, any layout ``fns`` reads (a watermarked field's too); every leaf trains:
        ``density`` and ``appearance`` at ``train.lr_grid``, the rest at ``train.lr_network``.
      geometry: the field's geometry (aabb, alpha mask, marching step), kept as it is.
      fns: field functions; ``fns.colour`` is called with ``cond=None`` (a conditioned field must fix its
        condition inside, e.g. ``watermark.model.held_id_field_fns``).
      snapshots: step counts ≥ 1.
      seed: the continuation's rays and jitter.
      on_step: called after each step with ``(steps done, {"loss", "mse", "psnr", ...})``.
    """
    marks = sorted({int(n) for n in snapshots})
    if not marks or marks[0] < 1:
        raise MnerfError(f"fine-tuning needs step counts of at least 1, got {list(snapshots)}")
    hyper = StepHyper.from_config(config)
    start = int(config.train.n_iters)
    state = TrainState(
        params=params,
        opt_state=make_optimizer(hyper).init(params),
        step=jnp.asarray(start, jnp.int32),
        lr_base_step=jnp.zeros((), jnp.int32),
        key=jax.random.fold_in(jax.random.key(seed), SEED_SALT),
        geometry=geometry,
    )
    # Committed to the device as the step's outputs are: the second step then reuses the first's executable
    # (jit compiles again for arguments whose placement differs, and a fresh state's scalars are uncommitted).
    state = jax.device_put(state, jax.devices()[0])
    trainer = Trainer(config, scene, state, training_rays(scene, geometry), fns, phase_start=start)
    trainer.phase_end = start + marks[-1]  # budgets may shrink while enough steps remain

    def record(step: int, metrics: dict[str, float]) -> None:
        if on_step is not None:
            on_step(step + 1 - start, metrics)

    out = {}
    for n in marks:
        trainer.run_segment(start + n, record)
        out[n] = trainer.state.params
    return out
