"""When the fit's events happen: TensoRF's log-linear upsampling schedule, the next event after a step, where
the filtered ray set starts, and the step counts at which the loop pauses (events, checkpoints, the end).
"""

from __future__ import annotations

from mnerf_jax.core.config import Config
from mnerf_jax.tensorf import grids


def voxel_steps(config: Config) -> dict[int, int]:
    """``{upsample step: voxel count after it}`` (TensoRF's log-linear schedule)."""
    t = config.train
    steps = sorted(t.upsample_steps)
    return dict(zip(steps, grids.voxel_schedule(t.n_voxel_init, t.n_voxel_final, steps), strict=True))


def next_event(config: Config, step: int) -> int:
    """The first step count after ``step`` at which an event runs (``n_iters`` when none)."""
    t = config.train
    marks = [u + 1 for u in (*t.upsample_steps, *t.alpha_mask_steps) if u + 1 > step]
    return min(marks, default=t.n_iters)


def filter_start(config: Config) -> int:
    """The step from which training samples the alpha-filtered ray set."""
    masks = sorted(config.train.alpha_mask_steps)
    return masks[1] + 1 if len(masks) > 1 else 0


def boundaries(config: Config, start: int, stop: int) -> list[int]:
    """Step counts at which the loop pauses: after events, at checkpoints, at ``stop``."""
    t = config.train
    marks = {u + 1 for u in (*t.upsample_steps, *t.alpha_mask_steps)}
    every = max(t.checkpoint_every, 1)
    marks |= set(range(every, stop, every))
    marks.add(stop)
    return sorted(m for m in marks if start < m <= stop)
