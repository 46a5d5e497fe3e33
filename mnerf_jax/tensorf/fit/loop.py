"""TensoRF optimisation: the ``fit`` loop, its schedules and events (the jitted step: ``fit_step``).

What one run does (TensoRF's train.py, step for step):

- rays of every training pixel; rays that miss the aabb are dropped (non-NDC scenes);
- every step: a batch from a random permutation of the rays (reshuffled per epoch), render with one
  jitter per ray, loss = MSE + L1 on the density factors (+ TV on the planes, weights decaying with
  the learning rate); Adam(0.9, 0.99) with grid factors at ``lr_grid`` and basis/MLP at
  ``lr_network``, both multiplied by ``lr_decay_ratio ** (1 / n_iters)`` after every step;
- after step ``u`` in ``alpha_mask_steps``: a new alpha mask; the first also shrinks the aabb to the
  occupied box (cropping the factors and Adam's moments) and switches L1 to ``l1_weight_rest``; the
  second drops training rays that only cross empty space (non-NDC);
- after step ``u`` in ``upsample_steps``: factors resized to the next voxel count of the log-linear
  schedule, a fresh Adam, learning rates back to their initial values.

Determinism: the per-step PRNG key is ``fold_in(key(seed), step)`` and the batch at a step is a
slice of a permutation seeded by ``(seed, ray-set start, epoch)``, so a resumed run repeats an
uninterrupted one exactly.

Static sample budgets: ``render_rays`` evaluates density and colour in fixed-size buffers (static
shapes under jit; each new size is a compilation). ``budgets.SampleBudgets`` sizes them at the start of each
phase (density predicted from the geometry, colour scaled from the last step), grows them when a
step's counts exceed them (that step dropped samples: it is discarded and redone) and shrinks them
at a few refit points. Steps run pipelined: step k+1 is dispatched before step k's counts are read,
so reading them never stalls XLA; the loop pauses only at events and checkpoints.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mnerf_jax.core.checkpoint import CheckpointStore, config_fingerprint
from mnerf_jax.core.config import Config
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.data import Scene
from mnerf_jax.tensorf import alpha_mask, field, grids, raymarch, render
from mnerf_jax.tensorf.budgets import SampleBudgets, estimate_density_count, refit_due
from mnerf_jax.tensorf.fit.checkpoint import checkpoint_tree, restore_state
from mnerf_jax.tensorf.fit.schedule import boundaries, filter_start, next_event, voxel_steps
from mnerf_jax.tensorf.fit.step import GRID_GROUPS, StepHyper, TrainState, make_optimizer, train_step
from mnerf_jax.tensorf.sampler import PermutationSampler, RaySet, training_rays

Array = jax.Array
Params = Any

STATE_VERSION = 1


# --------------------------------------------------------------------------------------------------
# Building states
# --------------------------------------------------------------------------------------------------


def geometry_for(
    config: Config,
    scene_aabb: np.ndarray,
    resolution: tuple[int, int, int],
    *,
    near: float,
    far: float,
    ndc: bool,
    white_bg: bool,
) -> raymarch.Geometry:
    """A fresh geometry (no alpha mask) for ``resolution`` nodes over ``scene_aabb``."""
    return raymarch.make_geometry(
        scene_aabb,
        resolution,
        step_ratio=config.render.step_ratio,
        near=near,
        far=far,
        distance_scale=config.model.distance_scale,
        ndc=ndc,
        white_bg=white_bg,
        max_samples=config.render.max_samples,
    )


def init_state(config: Config, scene: Scene) -> TrainState:
    """Step-0 state: a fresh field at ``n_voxel_init`` over the scene's aabb, fresh Adam."""
    aabb = np.asarray(scene.aabb, np.float32)
    resolution = grids.resolution_from_voxels(aabb, config.train.n_voxel_init)
    key = jax.random.key(config.train.seed)
    params = field.init_field(jax.random.fold_in(key, 0x1417), config.model, resolution)
    geometry = geometry_for(
        config, aabb, resolution, near=scene.near, far=scene.far, ndc=scene.ndc, white_bg=scene.white_bg
    )
    hyper = StepHyper.from_config(config)
    return TrainState(
        params=params,
        opt_state=make_optimizer(hyper).init(params),
        step=jnp.zeros((), jnp.int32),
        lr_base_step=jnp.zeros((), jnp.int32),
        key=jax.random.fold_in(key, 0x7EA1),
        geometry=geometry,
    )


# --------------------------------------------------------------------------------------------------
# Events: alpha mask (+ shrink, + ray filter) and upsampling
# --------------------------------------------------------------------------------------------------


def update_alpha_mask(
    config: Config,
    state: TrainState,
    fns: render.FieldFns,
    mask_resolution: tuple[int, int, int],
    shrink: bool,
) -> TrainState:
    """New alpha mask at ``mask_resolution`` over the current aabb; with ``shrink`` crop to its box.

    Shrinking crops the factors and Adam's moments alike (the optimiser continues; TensoRF only
    shrinks where it also upsamples, which resets Adam anyway). An all-empty mask is not applied.
    """
    geometry = state.geometry
    mask = alpha_mask.compute_alpha_mask(
        fns, state.params, geometry, mask_resolution, threshold=config.render.alpha_mask_threshold
    )
    if not mask.any():
        # Nothing is dense enough yet: an empty mask would leave no sample to train on.
        return state
    old_aabb = np.asarray(geometry.aabb)
    params, opt_state = state.params, state.opt_state
    if shrink:
        new_box = alpha_mask.shrink_box_from_mask(mask, old_aabb)
        params, aligned = alpha_mask.shrink_field(params, old_aabb, new_box)
        opt_state, _ = alpha_mask.shrink_field(opt_state, old_aabb, new_box)
        geometry = geometry_for(
            config,
            aligned,
            grids.vm_resolution(params["density"]),
            near=float(geometry.near),
            far=float(geometry.far),
            ndc=geometry.ndc,
            white_bg=geometry.white_bg,
        )
    geometry = raymarch.with_alpha_mask(geometry, mask, old_aabb)
    return state.replace(params=params, opt_state=opt_state, geometry=geometry)


def upsample(config: Config, state: TrainState, n_voxels: int) -> TrainState:
    """Resize the factors to ``n_voxels`` over the current aabb; fresh Adam, learning rates reset."""
    geometry = state.geometry
    resolution = grids.resolution_from_voxels(np.asarray(geometry.aabb), n_voxels)
    params = dict(state.params)
    for name in GRID_GROUPS:
        params[name] = grids.upsample_vm(params[name], resolution)
    fresh = geometry_for(
        config,
        np.asarray(geometry.aabb),
        resolution,
        near=float(geometry.near),
        far=float(geometry.far),
        ndc=geometry.ndc,
        white_bg=geometry.white_bg,
    )
    fresh = fresh.replace(
        alpha_mask=geometry.alpha_mask, alpha_cells=geometry.alpha_cells, mask_aabb=geometry.mask_aabb
    )
    hyper = StepHyper.from_config(config)
    return state.replace(
        params=params,
        opt_state=make_optimizer(hyper).init(params),
        lr_base_step=state.step,
        geometry=fresh,
    )


# --------------------------------------------------------------------------------------------------
# The fit loop
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class FitResult:
    """What ``fit`` returns: the final state and the run's timing."""

    state: TrainState
    fns: render.FieldFns
    steps: int
    train_seconds: float
    rays: int  # rays processed by applied steps
    compiles: int
    redone_steps: int
    last_metrics: dict[str, float]
    total_train_seconds: float = 0.0  # including earlier sessions of a resumed run
    compile_seconds: float = 0.0  # spent tracing and compiling train steps (within train_seconds)
    step_shapes: tuple[tuple, ...] = ()  # (resolution, samples per ray, density, colour budget) compiled

    @property
    def rays_per_second(self) -> float:
        return self.rays / self.train_seconds if self.train_seconds > 0 else 0.0


LogFn = Callable[[int, dict[str, float]], None]


class Trainer:
    """Host-side loop state: rays, sampler, budgets, event bookkeeping."""

    def __init__(
        self,
        config: Config,
        scene: Scene,
        state: TrainState,
        rays: RaySet,
        fns: render.FieldFns,
        *,
        budgets: SampleBudgets | None = None,
        mask_resolution: tuple[int, int, int] | None = None,
        ray_keep: np.ndarray | None = None,
        phase_start: int = 0,
    ):
        self.config = config
        self.scene = scene
        self.state = state
        self.fns = fns
        self.hyper = StepHyper.from_config(config)
        self.base_rays = rays
        self.ray_keep = None
        self.use_rays(rays, 0)
        if ray_keep is not None:
            if ray_keep.size != len(rays):
                raise MnerfError(
                    f"the checkpoint was trained on {ray_keep.size} rays, the data gives "
                    f"{len(rays)}: is --data the same scene?"
                )
            self.ray_keep = ray_keep
            self.use_rays(rays.select(ray_keep), filter_start(config))
        self.mask_resolution = mask_resolution or state.resolution
        self.phase_start = phase_start
        self.phase_end = next_event(config, phase_start)
        self.budgets = budgets if budgets is not None else SampleBudgets(density=0, colour=0)
        if budgets is None:
            self.start_phase()
        self.shapes_seen: set[tuple] = set()
        self.compile_seconds = 0.0
        self.redone = 0
        self.rays_done = 0
        self.prior_seconds = 0.0  # training time of earlier sessions (resumed runs)
        self.session_start = time.perf_counter()

    def use_rays(self, rays: RaySet, start: int) -> None:
        self.rays = rays
        self.batch = min(self.config.train.batch_size, len(rays))
        self.sampler = PermutationSampler(self.config.train.seed, len(rays), self.batch, start)

    @property
    def cap(self) -> int:
        return self.batch * self.state.geometry.n_samples

    # -- steps ----------------------------------------------------------------------------------

    def dispatch(self, state: TrainState, step: int) -> tuple[TrainState, dict[str, Array]]:
        idx = self.sampler.indices(step)
        budgets = self.budgets.for_step(step)
        shapes = (state.resolution, state.geometry.n_samples, *budgets)
        t0 = time.perf_counter()
        new_state, out = train_step(
            state,
            self.rays.origins[idx],
            self.rays.directions[idx],
            self.rays.rgb[idx],
            fns=self.fns,
            hyper=self.hyper,
            density_budget=budgets[0],
            colour_budget=budgets[1],
        )
        if shapes not in self.shapes_seen:
            # Tracing and compiling happen in this call; execution is asynchronous.
            self.shapes_seen.add(shapes)
            self.compile_seconds += time.perf_counter() - t0
        return new_state, out

    def run_segment(self, stop: int, on_step: LogFn) -> None:
        """Steps from ``state.step`` to ``stop`` (no events in between), pipelined one step deep.

        Step k+1 is dispatched before step k's counts are read, so the read does not stall XLA. If
        step k overflowed a budget, both results are dropped and step k is redone from the state
        before it with grown budgets.
        """
        state = self.state
        k = int(state.step)
        pending = None  # (step, state before, state after, metrics)
        while k < stop or pending is not None:
            nxt = self.dispatch(state, k) if k < stop else None
            if pending is not None:
                pk, before, after, out = pending
                host = jax.device_get(out)
                n_samples = self.state.geometry.n_samples
                if self.budgets.observe(
                    pk, int(host["density_count"]), int(host["colour_count"]), n_samples, self.cap
                ):
                    self.redone += 1
                    state, k, pending = before, pk, None
                    continue
                self.rays_done += self.batch
                self.state = after
                pending = None
                if refit_due(pk + 1, self.phase_start, self.budgets):
                    self.budgets.schedule_refit(pk + 2, self.cap, self.phase_end - (pk + 2))
                on_step(pk, {name: float(v) for name, v in host.items()})
            if nxt is not None:
                pending = (k, state, nxt[0], nxt[1])
                state, k = nxt[0], k + 1
        self.state = state

    # -- events ---------------------------------------------------------------------------------

    def apply_events(self, done_step: int) -> bool:
        """Events due after step ``done_step`` (0-based, just completed). True if any ran."""
        masks = sorted(self.config.train.alpha_mask_steps)
        upsamples = voxel_steps(self.config)
        ran = False
        if done_step in masks:
            shrink = done_step == masks[0]
            self.state = update_alpha_mask(self.config, self.state, self.fns, self.mask_resolution, shrink)
            if len(masks) > 1 and done_step == masks[1] and not self.scene.ndc:
                self.filter_rays(done_step + 1)
            ran = True
        if done_step in upsamples:
            self.state = upsample(self.config, self.state, upsamples[done_step])
            if math.prod(self.state.resolution) < 256**3:
                self.mask_resolution = self.state.resolution
            ran = True
        if ran:
            self.phase_start = done_step + 1
            self.phase_end = next_event(self.config, self.phase_start)
            self.start_phase()
        return ran

    def start_phase(self) -> None:
        """Budgets for the phase beginning now: density predicted, colour scaled from the last step."""
        g = self.state.geometry
        density = estimate_density_count(self.rays, g, self.batch, self.config.train.seed, self.phase_start)
        colour = self.budgets.colour_estimate(g.n_samples)
        # Before any colour count is known (the first phase), colour may need every density sample.
        self.budgets.start_phase(density, density if colour is None else min(colour, density), self.cap)

    def filter_rays(self, start: int) -> None:
        """Keep the training rays that cross an occupied alpha-mask cell (TensoRF's filtering_rays)."""
        g = self.state.geometry
        keep = alpha_mask.filter_rays(
            g,
            self.base_rays.origins,
            self.base_rays.directions,
            chunk=1 << 16,
            n_samples=min(256, g.n_samples),
        )
        if not keep.any():
            keep[:] = True  # nothing occupied: keep training on every ray
        self.ray_keep = keep
        self.use_rays(self.base_rays.select(keep), start)

    # -- checkpoints ----------------------------------------------------------------------------

    def checkpoint_meta(self) -> dict[str, Any]:
        return {
            "kind": "tensorf",
            "version": STATE_VERSION,
            "step": int(self.state.step),
            "fingerprint": config_fingerprint(self.config),
            "config": self.config.to_dict(),
            "resolution": list(self.state.resolution),
            "mask_resolution": list(self.mask_resolution),
            "geometry": raymarch.geometry_meta(self.state.geometry),
            "budgets": self.budgets.to_dict(),
            "phase_start": self.phase_start,
            "ray_keep_count": None if self.ray_keep is None else int(self.ray_keep.sum()),
            "ray_keep_total": None if self.ray_keep is None else int(self.ray_keep.size),
            "n_train_rays": len(self.base_rays),
            "train_seconds": self.prior_seconds + time.perf_counter() - self.session_start,
        }

    def save(self, store: CheckpointStore) -> None:
        store.save(int(self.state.step), checkpoint_tree(self.state, self.ray_keep), self.checkpoint_meta())


def fit(
    config: Config,
    scene: Scene,
    run_dir: str | Path | None = None,
    *,
    resume: bool = False,
    stop_at: int | None = None,
    on_step: LogFn | None = None,
    fns: render.FieldFns | None = None,
) -> FitResult:
    """Train a TensoRF field on ``scene``'s train split.

    Args:
      config: the run's config (``train`` schedule, ``model``, ``render``).
      scene: a loaded scene with a ``train`` split.
      run_dir: where checkpoints go (``run_dir/checkpoints``); None keeps nothing on disk.
      resume: continue from the latest checkpoint in ``run_dir`` (refused if its config differs).
      stop_at: stop after this many steps (default ``train.n_iters``); a checkpoint is written there.
      on_step: called after every applied step with ``(step, {"loss", "mse", "psnr", ...})``.
      fns: field functions (default: plain TensoRF of ``config.model``).

    Returns:
      FitResult with the final state; ``train_seconds`` is this call's loop (compilation included,
      checkpoint writing in the background).
    """
    fns = fns or render.tensorf_field_fns(config.model)
    stop = min(config.train.n_iters if stop_at is None else int(stop_at), config.train.n_iters)
    store = CheckpointStore(run_dir, keep=config.train.keep_checkpoints) if run_dir is not None else None
    try:
        state = init_state(config, scene)
        rays = training_rays(scene, state.geometry)
        extra: dict[str, Any] = {}
        if resume and store is not None and store.latest_step() is not None:
            state, meta, keep = restore_state(config, store)
            extra = {
                "budgets": SampleBudgets(**{k: int(v) for k, v in meta["budgets"].items()}),
                "mask_resolution": tuple(int(v) for v in meta["mask_resolution"]),
                "ray_keep": keep,
                "phase_start": int(meta["phase_start"]),
            }
            prior = float(meta.get("train_seconds", 0.0))
        else:
            prior = 0.0
        trainer = Trainer(config, scene, state, rays, fns, **extra)
        trainer.prior_seconds = prior
        start = int(trainer.state.step)
        last: dict[str, float] = {}

        def record(step: int, metrics: dict[str, float]) -> None:
            last.clear()
            last.update(metrics)
            if on_step is not None:
                on_step(step, metrics)

        t0 = trainer.session_start = time.perf_counter()
        for mark in boundaries(config, start, stop):
            trainer.run_segment(mark, record)
            trainer.apply_events(mark - 1)
            if store is not None and (mark % max(config.train.checkpoint_every, 1) == 0 or mark == stop):
                trainer.save(store)
        jax.block_until_ready(trainer.state.params)
        seconds = time.perf_counter() - t0
        if store is not None:
            store.wait()
        return FitResult(
            state=trainer.state,
            fns=fns,
            steps=int(trainer.state.step),
            train_seconds=seconds,
            rays=trainer.rays_done,
            compiles=len(trainer.shapes_seen),
            redone_steps=trainer.redone,
            last_metrics=last,
            total_train_seconds=prior + seconds,
            compile_seconds=trainer.compile_seconds,
            step_shapes=tuple(sorted(trainer.shapes_seen)),
        )
    finally:
        if store is not None:
            store.close()
