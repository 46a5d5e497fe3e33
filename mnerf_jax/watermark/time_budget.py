"""Ending an embedding within a wall-clock budget (``watermark.time_budget.minutes``, ``mnerf embed
--time-budget``).

A step's cost depends on the machine and the day, and grows during a run as the sample buffers grow to the
largest view's counts, so a step count fixed in advance either overruns the time or leaves part of it unused.
With a budget, the loop runs the configured schedule and, before each step, stops when that step and the last
checkpoint would no longer end inside the budget, judging a step's cost by the steps just run. The field's
schedule is not resized: the learning rates decay over the configured length, so a field the budget stops
after N steps is exactly the first N steps of the unbudgeted run (``--steps N`` repeats it), and without phase
3 ``--resume`` continues it. With phase 3 (``watermark.phase3.steps``) the loop keeps ``phase3.reserve_min``
of the budget for it and phase 3 runs on whatever field the budget left, its own schedule sized to the time
left (``phase3.refit_decoder``): where steps run slower the budget then ends with a shorter field and a
shorter phase 3, not without phase 3.
"""

from __future__ import annotations

import dataclasses
import statistics
from collections.abc import Sequence

# Seconds kept free: the process's start before the budget's clock (imports, loading the run), the end after
# the loop, and one recompilation (sample buffers grown after an overflow).
RESERVE_S = 45.0
# Recent steps whose median is the next step's expected cost.
RECENT_STEPS = 10
# A checkpoint's expected cost before one has been timed.
FIRST_CHECKPOINT_S = 5.0


@dataclasses.dataclass
class BudgetClock:
    """The budget and what the loop has timed so far (seconds, ``time.perf_counter`` based)."""

    budget_s: float
    started: float
    step_seconds: list[float] = dataclasses.field(default_factory=list)
    checkpoint_s: float = FIRST_CHECKPOINT_S
    kept_s: float = 0.0  # kept free by the field's steps for what follows them (phase 3)

    def record_step(self, seconds: float) -> None:
        self.step_seconds = [*self.step_seconds, float(seconds)][-RECENT_STEPS:]

    def expected_step_s(self) -> float | None:
        """The median of the recent steps; None before the first one."""
        return expected_step_seconds(self.step_seconds)

    def room_for_a_step(self, now: float) -> bool:
        """True while one more step and the final checkpoint end within the budget (always before the first
        step has been timed: a run takes at least one step)."""
        step_s = self.expected_step_s()
        if step_s is None:
            return True
        return self.room_for(step_s + self.kept_s, now)

    def room_for(self, seconds: float, now: float) -> bool:
        """True while ``seconds`` more and the final checkpoint end within the budget."""
        # The sum, not seconds_left's difference: the same rounding at the edge as the steps were judged by.
        return (now - self.started) + seconds + self.checkpoint_s + RESERVE_S <= self.budget_s

    def seconds_left(self, now: float) -> float:
        """Seconds of the budget left at ``now`` for work before the final checkpoint (negative: overrun)."""
        return self.budget_s - (now - self.started) - self.checkpoint_s - RESERVE_S


def expected_step_seconds(recent: Sequence[float]) -> float | None:
    """The median of ``recent`` step times (robust to one step that compiled), None when empty."""
    return float(statistics.median(recent)) if recent else None
