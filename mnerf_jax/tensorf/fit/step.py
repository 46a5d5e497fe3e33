"""The jitted TensoRF train step: its hyper-parameters, optimiser, state and loss (``train`` runs it).

One step renders a batch of rays with one jitter per ray and takes one Adam step on
``MSE + l1 · L1(density factors) + TV(planes)``, grid factors at ``lr_grid`` and basis/MLP at
``lr_network``, both decayed by ``lr_factor`` per step since the last reset (``lr_base_step``). The TV
weights decay with the learning rate, as TensoRF's do.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import optax

from mnerf_jax.core import xla_cpu
from mnerf_jax.core.config import Config
from mnerf_jax.tensorf import grids, raymarch, render

Array = jax.Array
Params = Any

GRID_GROUPS = ("density", "appearance")  # params entries trained at lr_grid; the rest at lr_network


# --------------------------------------------------------------------------------------------------
# Optimiser and schedules
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class StepHyper:
    """The hyper-parameters a train step reads (static under jit: hashable and compared by value)."""

    lr_grid: float
    lr_network: float
    lr_factor: float  # per-step decay: lr_decay_ratio ** (1 / n_iters)
    adam_b1: float
    adam_b2: float
    l1_initial: float
    l1_rest: float
    l1_switch: int  # steps >= this use l1_rest (the first alpha-mask step + 1; huge when none)
    tv_density: float
    tv_app: float
    random_background: bool
    weight_threshold: float  # colour only where the compositing weight exceeds this

    @classmethod
    def from_config(cls, config: Config) -> StepHyper:
        t = config.train
        masks = sorted(t.alpha_mask_steps)
        return cls(
            lr_grid=t.lr_grid,
            lr_network=t.lr_network,
            lr_factor=lr_factor(t.lr_decay_ratio, t.n_iters),
            adam_b1=t.adam_b1,
            adam_b2=t.adam_b2,
            l1_initial=t.l1_weight_initial,
            l1_rest=t.l1_weight_rest,
            l1_switch=masks[0] + 1 if masks else 2**31 - 1,
            tv_density=t.tv_weight_density,
            tv_app=t.tv_weight_app,
            random_background=t.random_background,
            weight_threshold=config.render.weight_threshold,
        )


def lr_factor(decay_ratio: float, n_iters: int) -> float:
    """Per-step learning-rate multiplier that reaches ``decay_ratio`` after ``n_iters`` steps."""
    return float(decay_ratio ** (1.0 / max(int(n_iters), 1)))


def param_labels(params: Params) -> dict[str, Any]:
    """``"grid"`` for the VM factor entries of ``params``, ``"network"`` for everything else."""
    return {
        k: jax.tree.map(lambda _, k=k: "grid" if k in GRID_GROUPS else "network", v)
        for k, v in params.items()
    }


def make_optimizer(hyper: StepHyper) -> optax.GradientTransformation:
    """Adam with per-group base learning rates (the per-step decay is applied by the train step)."""
    return optax.chain(
        optax.scale_by_adam(b1=hyper.adam_b1, b2=hyper.adam_b2, eps=1e-8),
        optax.multi_transform(
            {"grid": optax.scale(-hyper.lr_grid), "network": optax.scale(-hyper.lr_network)}, param_labels
        ),
    )


def learning_rates(hyper: StepHyper, step: int, lr_base_step: int) -> dict[str, float]:
    """The learning rates used by step ``step`` (0-based) after a reset at ``lr_base_step``."""
    scale = hyper.lr_factor ** (step - lr_base_step)
    return {"grid": hyper.lr_grid * scale, "network": hyper.lr_network * scale}


# --------------------------------------------------------------------------------------------------
# Train state and step
# --------------------------------------------------------------------------------------------------


@flax.struct.dataclass
class TrainState:
    """Everything the jitted step reads and writes.

    Attributes:
      params: field params (``field.init_field`` layout).
      opt_state: optax state of ``make_optimizer``.
      step: ``[]`` int32, steps completed.
      lr_base_step: ``[]`` int32, step at which the learning rates were last reset.
      key: PRNG key of the run; step ``s`` uses ``fold_in(key, s)``.
      geometry: aabb, alpha mask, marching step, samples per ray (``raymarch.Geometry``).
    """

    params: Params
    opt_state: Any
    step: Array
    lr_base_step: Array
    key: Array
    geometry: raymarch.Geometry

    @property
    def resolution(self) -> tuple[int, int, int]:
        return grids.vm_resolution(self.params["density"])


def step_key(state: TrainState) -> Array:
    """The PRNG key of the state's next step."""
    return jax.random.fold_in(state.key, state.step)


def _loss_fn(
    params: Params,
    state: TrainState,
    rays_o: Array,
    rays_d: Array,
    rgb: Array,
    key: Array,
    fns: render.FieldFns,
    hyper: StepHyper,
    density_budget: int,
    colour_budget: int,
) -> tuple[Array, dict[str, Array]]:
    k_jitter, k_bg = jax.random.split(key)
    bg = None
    if hyper.random_background and not state.geometry.white_bg:
        # TensoRF composites a black-background scene on white in half of the training steps.
        bg = jnp.where(jax.random.uniform(k_bg) < 0.5, 1.0, 0.0) * jnp.ones((3,), jnp.float32)
    out = render.render_rays(
        fns,
        params,
        None,
        rays_o,
        rays_d,
        state.geometry,
        k_jitter,
        train=True,
        bg=bg,
        density_budget=density_budget,
        colour_budget=colour_budget,
        weight_threshold=hyper.weight_threshold,
    )
    mse = jnp.mean(jnp.square(out["rgb"] - rgb))
    loss = mse
    l1_weight = jnp.where(state.step >= hyper.l1_switch, hyper.l1_rest, hyper.l1_initial)
    if hyper.l1_initial > 0 or hyper.l1_rest > 0:
        loss = loss + l1_weight * grids.l1_density(params["density"])
    # TensoRF multiplies the TV weights by the lr factor before each use: w0 * f^(step + 1).
    tv_decay = hyper.lr_factor ** (state.step.astype(jnp.float32) + 1.0)
    if hyper.tv_density > 0:
        loss = loss + hyper.tv_density * tv_decay * grids.tv_plane(params["density"])
    if hyper.tv_app > 0:
        loss = loss + hyper.tv_app * tv_decay * grids.tv_plane(params["appearance"])
    aux = {
        "loss": loss,
        "mse": mse,
        "density_count": out["density_count"],
        "colour_count": out["colour_count"],
    }
    return loss, aux


# The top-level step takes xla_cpu.xla_compiler_options() (XLA:CPU fusion settings).
@xla_cpu.jit_cpu_tuned(static_argnames=("fns", "hyper", "density_budget", "colour_budget"))
def train_step(
    state: TrainState,
    rays_o: Array,
    rays_d: Array,
    rgb: Array,
    key: Array | None = None,
    *,
    fns: render.FieldFns,
    hyper: StepHyper,
    density_budget: int,
    colour_budget: int,
) -> tuple[TrainState, dict[str, Array]]:
    """One optimisation step on a batch of rays.

    Args:
      state: the train state (its ``step`` selects the learning rates).
      rays_o, rays_d, rgb: ``[B, 3]`` ray origins, directions and target colours in [0, 1].
      key: PRNG key of this step (sample jitter, background coin); default ``step_key(state)``,
        which makes a run a function of its seed.
      fns: the field functions (static).
      hyper: step hyper-parameters (static).
      density_budget, colour_budget: static sample buffer sizes (see ``render.render_rays``).

    Returns:
      ``(new state, metrics)`` with scalar ``loss``, ``mse``, ``psnr``, ``density_count``,
      ``colour_count``. If a count exceeds its budget, samples were dropped: discard the new state.
    """
    key = step_key(state) if key is None else key
    grads, aux = jax.grad(_loss_fn, has_aux=True)(
        state.params, state, rays_o, rays_d, rgb, key, fns, hyper, density_budget, colour_budget
    )
    tx = make_optimizer(hyper)
    updates, opt_state = tx.update(grads, state.opt_state, state.params)
    lr_scale = jnp.power(jnp.float32(hyper.lr_factor), (state.step - state.lr_base_step).astype(jnp.float32))
    updates = jax.tree.map(lambda u: u * lr_scale, updates)
    params = optax.apply_updates(state.params, updates)
    new_state = state.replace(params=params, opt_state=opt_state, step=state.step + 1)
    aux["psnr"] = -10.0 * jnp.log10(jnp.maximum(aux["mse"], 1e-12))
    return new_state, aux
