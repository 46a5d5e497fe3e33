"""Sizing phase 2 to a wall-clock budget (``watermark.time_budget_min``).

A step's cost depends on the machine and the day (the lego protocol's phase-2 step took 1.57-1.71 s on
the same 2-core CPU on different days), so a fixed step count either overruns an hour or leaves part of it
unused. With a budget, ``mnerf embed`` times a few steps of each phase before its first real step (their
results are discarded, so the trajectory is the one a fixed schedule of the chosen length gives: re-running
with ``watermark.phase2_steps`` set to it and the budget off repeats the run) and one checkpoint, then gives
phase 2 as many steps as the rest of the budget holds, at most ``watermark.phase2_steps``. Phase 1 keeps
its count. The learning rates decay over the chosen schedule from the first step (the compiled step takes
the schedule's length as an argument, so timing it costs no extra compilation).
"""

from __future__ import annotations

import dataclasses
import statistics
from collections.abc import Sequence

# Steps timed per phase before the first real step; the first of them also compiles and is not counted.
PROBE_STEPS = 3
# Seconds kept free of steps: the process's start before the budget's clock (imports, loading the run)
# and its end after the loop (the last checkpoint's wait, the decoder file).
RESERVE_S = 30.0
# Step times drift while a long run goes on (other work on the machine, clock and thermal changes): the
# plan assumes steps this much slower than the probes measured.
SLOWDOWN = 0.03


class BudgetError(ValueError):
    """The budget cannot hold the schedule's fixed part."""


@dataclasses.dataclass(frozen=True)
class BudgetPlan:
    """The chosen phase-2 length and the figures it came from (recorded in the run's ``embed.json``)."""

    phase2_steps: int
    budget_s: float
    elapsed_s: float
    phase1_step_s: float
    phase2_step_s: float
    checkpoint_s: float

    def projected_s(self, phase1_steps: int, checkpoint_every: int) -> float:
        """Wall seconds the plan expects from the budget's start to the end of the loop."""
        return self.elapsed_s + _loop_seconds(self, phase1_steps, self.phase2_steps, checkpoint_every)

    def to_dict(self) -> dict[str, float]:
        return {k: round(v, 3) if isinstance(v, float) else v for k, v in dataclasses.asdict(self).items()}


def median_step_seconds(seconds: Sequence[float]) -> float:
    """The median of probe step times, the first (compilation) left out when there are others."""
    timed = list(seconds[1:]) if len(seconds) > 1 else list(seconds)
    if not timed:
        raise ValueError("no probe steps were timed")
    return float(statistics.median(timed))


def _loop_seconds(plan: BudgetPlan, phase1_steps: int, phase2_steps: int, checkpoint_every: int) -> float:
    steps = phase1_steps + phase2_steps
    saves = steps // max(checkpoint_every, 1) + 2  # every checkpoint_every steps, phase 1's end, the last
    work = phase1_steps * plan.phase1_step_s + phase2_steps * plan.phase2_step_s
    return work * (1.0 + SLOWDOWN) + saves * plan.checkpoint_s + RESERVE_S


def plan_phase2(
    budget_s: float,
    elapsed_s: float,
    phase1_steps: int,
    phase1_step_s: float,
    phase2_step_s: float,
    checkpoint_s: float,
    checkpoint_every: int,
    max_phase2_steps: int,
) -> BudgetPlan:
    """The most phase-2 steps (``≤ max_phase2_steps``) that end the loop within ``budget_s`` seconds.

    Args:
      budget_s: the whole budget; ``elapsed_s`` of it are spent (loading, the probes).
      phase1_steps: phase-1 steps still to run; ``phase1_step_s``, ``phase2_step_s``: seconds a step.
      checkpoint_s: seconds a checkpoint takes; one every ``checkpoint_every`` steps.
    Raises:
      BudgetError: not even one phase-2 step fits after phase 1 (with the figures, for the message).
    """
    plan = BudgetPlan(0, float(budget_s), float(elapsed_s), float(phase1_step_s), float(phase2_step_s),
                      float(checkpoint_s))  # fmt: skip

    def fits(n: int) -> bool:
        return elapsed_s + _loop_seconds(plan, phase1_steps, n, checkpoint_every) <= budget_s

    if not fits(1):
        raise BudgetError(
            f"a budget of {budget_s / 60:.1f} min holds no phase-2 step: {elapsed_s:.0f} s are spent, "
            f"phase 1's {phase1_steps} steps take ~{phase1_steps * phase1_step_s:.0f} s at "
            f"{phase1_step_s:.2f} s a step and a phase-2 step {phase2_step_s:.2f} s; raise "
            "watermark.time_budget_min or lower watermark.phase1_steps"
        )
    # The count from the mean cost of a step (checkpoints spread over steps), then corrected to the last
    # count that fits (checkpoints come whole).
    per_step = phase2_step_s * (1.0 + SLOWDOWN) + checkpoint_s / max(checkpoint_every, 1)
    spare = budget_s - elapsed_s - _loop_seconds(plan, phase1_steps, 0, checkpoint_every)
    n = max(1, min(int(spare / per_step) if per_step > 0 else max_phase2_steps, max_phase2_steps))
    while n > 1 and not fits(n):
        n -= 1
    while n < max_phase2_steps and fits(n + 1):
        n += 1
    return dataclasses.replace(plan, phase2_steps=int(n))
