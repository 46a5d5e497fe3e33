"""The host side of ``mnerf embed``: the loop that chooses IDs and views, dispatches the jitted step
(``wm_step.embed_step``), grows the sample buffers, checkpoints, reports, and ends the run early when a
time budget (``embed_budget``) has no room for another step. ``embed.embed`` sets it up.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from mnerf_jax.core import rundir
from mnerf_jax.core.checkpoint import CheckpointStore, config_fingerprint
from mnerf_jax.core.config import Config
from mnerf_jax.core.scalar_log import ScalarLog
from mnerf_jax.imaging import metrics as metrics_lib
from mnerf_jax.reader import decoder_io
from mnerf_jax.reader import keys as keys_lib
from mnerf_jax.tensorf import budgets, grids, raymarch
from mnerf_jax.watermark import model as watermark
from mnerf_jax.watermark import run as wm_run
from mnerf_jax.watermark import sample_cache
from mnerf_jax.watermark import time_budget as embed_budget
from mnerf_jax.watermark.deferred import PatchLayout
from mnerf_jax.watermark.inputs import step_batch, step_choice
from mnerf_jax.watermark.objective import fidelity_budget_db, uses_fidelity
from mnerf_jax.watermark.run import DECODER_FILE, META_FILE, STATE_VERSION, WM_KIND, EmbedError
from mnerf_jax.watermark.step import EmbedState, StepSpec, embed_step, phase_of, step_config, total_steps

# The sample-buffer site of the embedding's patch renders (budgets.BudgetPolicy).
BUDGET_SITE = "embed_patch"


# ------------------------------------------------------------------------------------- checkpoints


def checkpoint_tree(state: EmbedState, geometry: raymarch.Geometry) -> dict[str, Any]:
    return {
        "params": state.params,
        "decoder": state.decoder,
        "opt_state": state.opt_state,
        "step": state.step,
        "key": jax.random.key_data(state.key),
        "geometry": raymarch.geometry_arrays(geometry),
    }


def checkpoint_meta(
    config: Config,
    state: EmbedState,
    geometry: raymarch.Geometry,
    keys: keys_lib.KeySet,
    budgets: tuple[int, int],
    run_seconds: float,
) -> dict[str, Any]:
    """The checkpoint's meta; ``run_seconds``: the run's wall time to this checkpoint over all its processes
    (a resumed run's clock, and so its time budget, goes on from there)."""
    step = int(state.step)
    return {
        "kind": WM_KIND,
        "version": STATE_VERSION,
        "step": step,
        "phase": phase_of(max(step - 1, 0), config.watermark),
        "fingerprint": config_fingerprint(wm_run.fingerprint_config(config), wm_run.SECTIONS),
        "config": config.to_dict(),
        "resolution": list(grids.vm_resolution(state.params["density"])),
        "geometry": raymarch.geometry_meta(geometry),
        "num_ids": keys.num_ids,
        "bits": keys.bits,
        "budgets": [int(b) for b in budgets],
        "run_seconds": round(float(run_seconds), 2),
    }


@dataclasses.dataclass
class EmbedResult:
    """What :func:`embed` returns."""

    run_dir: Path
    keys: keys_lib.KeySet
    steps: int
    seconds: float
    last_metrics: dict[str, float]
    redone_steps: int
    stopped_by_budget: bool = False  # watermark.time_budget.minutes ended it before its schedule did
    # Wall time of the whole run: this process's, and its earlier processes' to the checkpoint it resumed.
    run_seconds: float = 0.0
    state: EmbedState | None = None  # the state it ended with


def seed_budgets(policy: budgets.BudgetPolicy, n_rays: int, n_samples: int, budgets: Sequence[int]) -> None:
    """Start ``policy`` at the budgets a checkpoint recorded (no overflow-and-redo after a resume)."""
    policy.budgets(BUDGET_SITE, n_rays, n_samples)
    site = policy._sites[(BUDGET_SITE, n_rays * n_samples)]  # noqa: SLF001
    site.density, site.colour = int(budgets[0]), int(budgets[1])


# A step's new state and its metrics on the host.
StepOutcome = tuple[EmbedState, dict[str, float]]


@dataclasses.dataclass
class EmbedLoop:
    """Host side of the embedding: choose ID and view, dispatch steps, grow budgets, checkpoint, report."""

    config: Config
    split: Any
    keys: keys_lib.KeySet
    layout: PatchLayout
    geometry: raymarch.Geometry
    policy: budgets.BudgetPolicy
    store: CheckpointStore
    out: Path
    progress: bool
    on_step: Callable[[int, dict[str, float]], None] | None
    vgg: Any
    references: np.ndarray | None = None  # clean renders of the training views (objective.uses_clean_renders)
    clock: embed_budget.BudgetClock | None = None  # watermark.time_budget.minutes, when set
    cache: sample_cache.SampleCache | None = (
        None  # watermark.schedule.cache_source: the fitted field's samples
    )
    budget_end_db: float | None = None  # where the quality budget ends (objective.budget_end_db)
    # When the run began on time.perf_counter's scale: this process's start less the seconds its earlier
    # processes ran to the checkpoint it resumed from.
    run_started: float = dataclasses.field(default_factory=time.perf_counter)

    def __post_init__(self) -> None:
        # What every step passes unchanged, made once rather than per step.
        cfg = self.config.watermark
        self._messages = self.keys.messages.astype(np.float32)
        self._null = keys_lib.null_message(self.keys.messages)
        self._index, self._owner = jnp.asarray(self.layout.index), jnp.asarray(self.layout.owner)
        self._step_cfg = step_config(cfg)
        self._horizon = total_steps(cfg)  # the quality ramp's length (field_sizer may shorten it)
        self._total = jnp.asarray(total_steps(cfg), jnp.int32)  # the rates decay over the configured steps
        self._ids_per_step = watermark.ids_per_step_of(cfg, self.keys.num_ids)

    def field_sizer(self, start: int) -> embed_budget.ScheduleSizer | None:
        """With a time budget and phase 3 to follow, the sizer of the field's schedule from step ``start``
        (phase 2's steps are timed: phase 1 renders whole images, at another pace); None otherwise. The
        sized schedule ends the field, and the quality ramp runs over it so that the budget has tightened
        by then; the rates keep decaying over the configured steps (sizing them too read far less:
        docs/experiments/2026-11-26-slower-machine.md)."""
        cfg, clock = self.config.watermark, self.clock
        if clock is None or not clock.kept_s or not cfg.schedule.phase2_steps:
            return None

        def seconds_left() -> float:
            return clock.seconds_left(time.perf_counter()) - clock.kept_s

        return embed_budget.ScheduleSizer(
            total_steps(cfg), seconds_left, start=max(int(cfg.schedule.phase1_steps), start)
        )

    def budgets(self) -> tuple[int, int]:
        return self.policy.budgets(BUDGET_SITE, self.layout.rays, self.geometry.n_samples)

    def save(self, state: EmbedState) -> None:
        """Checkpoint, then the decoder as it is now, then keys.json tied to that decoder, then progress."""
        step = int(state.step)
        tick = time.perf_counter()
        run_seconds = tick - self.run_started
        meta = checkpoint_meta(self.config, state, self.geometry, self.keys, self.budgets(), run_seconds)
        self.store.save(step, checkpoint_tree(state, self.geometry), meta)
        self.store.wait()
        wm = self.config.watermark
        dec_meta = decoder_io.save_decoder(
            self.out / DECODER_FILE,
            state.decoder,
            {
                "embed_step": step,
                "read_window": wm.reading.window,
                "read_background": wm.reading.background,
                "read_jitter": wm.reading.jitter,
                "read_max_side": wm.reading.max_side,
            },
            wavelet=wm.reading.wavelet,
        )
        self.keys = keys_lib.with_fingerprint(self.keys, dec_meta["fingerprint"])
        keys_lib.save_keys(self.out, self.keys)
        rundir.write_json_atomic(
            self.out / META_FILE,
            {
                "steps_done": step,
                "phase": meta["phase"],
                "run_seconds": meta["run_seconds"],
                "decoder_fingerprint": dec_meta["fingerprint"],
                **({"quality_budget_db": self.budget_end_db} if self.budget_end_db is not None else {}),
            },
        )
        if self.clock is not None:
            self.clock.checkpoint_s = time.perf_counter() - tick

    def dispatch(self, state: EmbedState, step: int, phase: int) -> StepOutcome | None:
        """Step ``step`` (its IDs and view from the seed) in ``phase``: the new state and host metrics, or
        None when samples overflowed the buffers (grown now: redo it)."""
        cfg = self.config.watermark
        ids, view = step_choice(cfg.seed, step, self.keys.num_ids, len(self.split.images), self._ids_per_step)
        batch = step_batch(self.split, view, self._messages, ids, self.references, self._null)
        if self.cache is not None:
            batch.update({k: jnp.asarray(v) for k, v in self.cache.view(view).items()})
        if uses_fidelity(cfg):  # the budget as data: its ramp (fidelity_budget_db) compiles once
            budget = metrics_lib.psnr_to_mse(fidelity_budget_db(cfg, step, self._horizon, self.budget_end_db))
            batch["fidelity_mse"] = np.float32(budget)
        db, cb = self.budgets() if self.cache is None else (0, 0)  # a cached render marches no ray
        spec = StepSpec(
            model=self.config.model,
            wm=self._step_cfg,
            adam_b1=self.config.train.adam_b1,
            adam_b2=self.config.train.adam_b2,
            phase=phase,
            height=self.layout.height,
            width=self.layout.width,
            density_budget=db,
            colour_budget=cb,
        )
        new_state, metrics = embed_step(
            state,
            self.geometry,
            batch,
            self._index,
            self._owner,
            self.vgg,
            self._total,
            spec=spec,
        )
        host = {k: float(v) for k, v in jax.device_get(metrics).items()}
        counts = {k: int(host[k]) for k in ("density_count", "colour_count")}
        if self.cache is None and self.policy.update(
            BUDGET_SITE, counts, self.layout.rays, self.geometry.n_samples
        ):
            return None
        host.update(phase=float(phase), id=float(ids[0]), view=float(view))
        return new_state, host

    def run(self, state: EmbedState, stop_at: int | None) -> EmbedResult:
        """Steps from ``state.step`` to the schedule's end (or ``stop_at``), or until the time budget (its
        clock started at :attr:`run_started`, so a resumed run's earlier processes count) has no room for
        another step; with phase 3 to follow, the schedule is sized to the steps the budget allows
        (:meth:`field_sizer`)."""
        cfg = self.config.watermark
        t0 = time.perf_counter()
        if cfg.time_budget.minutes > 0:
            kept = cfg.phase3.reserve_min * 60.0 if cfg.phase3.steps else 0.0
            self.clock = embed_budget.BudgetClock(
                cfg.time_budget.minutes * 60.0, self.run_started, kept_s=kept, resumed=int(state.step) > 0
            )
        total = total_steps(cfg)
        stop = total if stop_at is None else min(int(stop_at), total)
        start = step = int(state.step)
        sizer = self.field_sizer(start)
        self._horizon = total
        every = max(int(cfg.checkpoint_every), 1)
        bar = tqdm(
            total=stop,
            initial=start,
            disable=not self.progress,
            desc="embed",
            unit="step",
            dynamic_ncols=True,
        )
        recent: list[tuple[float, float, float]] = []
        last: dict[str, float] = {}
        redone = 0
        stopped_by_budget = False
        log = ScalarLog(self.out)
        try:
            while step < stop:
                if sizer is not None and sizer.due(step):
                    self._horizon = sizer.size(step)
                    bar.total = min(stop, self._horizon)
                    bar.refresh()
                if step >= self._horizon:  # the sized schedule has ended
                    stopped_by_budget = True
                    break
                tick = time.perf_counter()
                if self.clock is not None and not self.clock.room_for_a_step(tick):
                    stopped_by_budget = True
                    break
                out = self.dispatch(state, step, phase_of(step, cfg))
                if out is None:
                    redone += 1  # samples were dropped: redo the step with the grown budgets
                    continue
                if self.clock is not None:
                    self.clock.record_step(time.perf_counter() - tick)
                if sizer is not None and sizer.times(step):
                    sizer.record(time.perf_counter() - tick)
                new_state, host = out
                if not all(np.isfinite(v) for v in host.values()):
                    raise EmbedError(
                        f"step {step}: the loss is not finite ({host['loss']}); lower the "
                        "learning rates (watermark.lr_*)"
                    )
                state, step = new_state, step + 1
                last = host
                recent = [*recent, (host["bit_acc"], host["psnr"], host.get("psnr_clean", np.nan))][-20:]
                bar.update(1)
                shown = {
                    "phase": int(host["phase"]),
                    "bit_acc": f"{np.mean([r[0] for r in recent]):.3f}",
                    "psnr": f"{np.mean([r[1] for r in recent]):.2f}",
                }
                if "psnr_clean" in host:  # against the clean model's render (the quality budget)
                    shown["psnr_clean"] = f"{np.mean([r[2] for r in recent]):.2f}"
                    shown["budget"] = f"{host['psnr_budget']:.1f}"
                bar.set_postfix(shown)
                log.add(step - 1, host, last=step == stop)
                if self.on_step is not None:
                    self.on_step(step - 1, host)
                if step % every == 0 or step == stop or step == cfg.schedule.phase1_steps:
                    self.save(state)
        finally:
            bar.close()
            log.close()
        if stopped_by_budget and self.progress:
            after = (
                "phase 3 follows in the minutes kept for it"
                if self.clock and self.clock.kept_s
                else "--resume with a larger --time-budget, or none, continues it"
            )
            tqdm.write(
                f"embed: the time budget ({cfg.time_budget.minutes:g} min) ends the field at step {step} "
                f"of {total} (its schedule sized to {self._horizon}); {after}"
            )
        saved_there = step % every == 0 or step == cfg.schedule.phase1_steps
        if (stopped_by_budget and not saved_there) or not (self.out / DECODER_FILE).is_file():
            self.save(state)
        return EmbedResult(
            run_dir=self.out,
            keys=self.keys,
            steps=int(state.step),
            seconds=time.perf_counter() - t0,
            last_metrics={**last, "field_scheduled": float(self._horizon)} if sizer is not None else last,
            redone_steps=redone,
            stopped_by_budget=stopped_by_budget,
            run_seconds=time.perf_counter() - self.run_started,
            state=state,
        )
