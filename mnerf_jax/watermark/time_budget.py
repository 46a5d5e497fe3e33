"""Ending an embedding within a wall-clock budget (``watermark.time_budget.minutes``, ``mnerf embed
--time-budget``).

A step's cost depends on the machine and the day, and grows during a run as the sample buffers grow to the
largest view's counts, so a step count fixed in advance either overruns the time or leaves part of it unused.
With a budget, the loop runs the configured schedule and, before each step, stops when that step and the last
checkpoint would no longer end inside the budget, judging a step's cost by the steps just run. Without
phase 3 the schedule is not resized: a field the budget stops after N steps is exactly the first N steps of
the unbudgeted run (``--steps N`` repeats it), and ``--resume`` with a larger budget, or none, continues it.
The budget is the run's, not the process's: a resumed run's clock starts at the seconds its checkpoint
recorded, so a killed run resumed ends about where it would have ended uninterrupted. With phase 3
(``watermark.phase3.steps``) the loop keeps ``phase3.reserve_min`` of the budget for it, and sizes the field's
schedule to the steps its share allows (:class:`ScheduleSizer`, ``field_scheduled`` in the run's metrics):
the quality budget's ramp is laid over them, so that it has tightened when the field ends, while the
learning rates still decay over the configured length (where every step fits, nothing changes). Phase 3
runs on whatever field the budget left, its own schedule sized to the time left (``phase3.refit_decoder``):
where steps run slower the budget then ends with a shorter field and a shorter phase 3, not without phase 3.
"""

from __future__ import annotations

import dataclasses
import statistics
import time
from collections.abc import Callable, Sequence

# Seconds kept free: the process's start before the budget's clock (imports, loading the run), the end after
# the loop, and one recompilation (sample buffers grown after an overflow).
RESERVE_S = 45.0
# Recent steps whose median is the next step's expected cost.
RECENT_STEPS = 10
# A checkpoint's expected cost before one has been timed.
FIRST_CHECKPOINT_S = 5.0
# Steps timed one by one (after the first, which compiles) before a schedule is sized to the time left, by
# their median (robust to one that compiles again or meets a busy moment).
SIZING_STEPS = 20
# The share of the seconds left a sized schedule plans for (steps vary; the budget ends an overrun).
SIZING_MARGIN = 0.97
# Steps between re-sizings, each by the mean step of the steps since the last: a busy moment at the start
# shortens the schedule only until the steps run at their pace again (up to the configured length).
RESIZE_EVERY = 500


@dataclasses.dataclass
class BudgetClock:
    """The budget and what the loop has timed so far (seconds, ``time.perf_counter`` based)."""

    budget_s: float
    started: float
    step_seconds: list[float] = dataclasses.field(default_factory=list)
    checkpoint_s: float = FIRST_CHECKPOINT_S
    kept_s: float = 0.0  # kept free by the field's steps for what follows them (phase 3)
    # ``started`` includes a resumed run's earlier processes: the first step is taken only if time is left.
    resumed: bool = False

    def record_step(self, seconds: float) -> None:
        self.step_seconds = [*self.step_seconds, float(seconds)][-RECENT_STEPS:]

    def expected_step_s(self) -> float | None:
        """The median of the recent steps; None before the first one."""
        return expected_step_seconds(self.step_seconds)

    def room_for_a_step(self, now: float) -> bool:
        """True while one more step and the final checkpoint end within the budget; before the first step has
        been timed, always for a fresh run (a run takes at least one step), and for a resumed one while the
        budget has any time left."""
        step_s = self.expected_step_s()
        if step_s is None:
            return not self.resumed or self.room_for(self.kept_s, now)
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


def steps_that_fit(done: int, seconds_left: float, step_s: float, configured: int) -> int:
    """The length of a schedule ``done`` steps into it that ends within :data:`SIZING_MARGIN` of
    ``seconds_left`` at ``step_s`` seconds a step: at most ``configured``, at least ``done + 1``."""
    fits = done + int(SIZING_MARGIN * max(seconds_left, 0.0) / max(step_s, 1e-9))
    return max(min(int(configured), fits), done + 1)


@dataclasses.dataclass
class ScheduleSizer:
    """Sizes a schedule of ``configured`` steps (those from ``start`` on are timed) to ``seconds_left()``.

    The steps ``start + 1 .. start + SIZING_STEPS`` are timed (the first compiles); before step ``start +
    SIZING_STEPS + 1`` the schedule is sized by their median, then every :data:`RESIZE_EVERY` steps by the
    mean wall time per step since the last sizing (``clock``, seconds), never beyond ``configured``. The
    caller asks :meth:`due` before each step, then :meth:`size`; it times the steps :meth:`times` names.
    """

    configured: int
    seconds_left: Callable[[], float]
    start: int = 0
    clock: Callable[[], float] = time.perf_counter
    timed: list[float] = dataclasses.field(default_factory=list, init=False)
    last_sized: tuple[int, float] | None = dataclasses.field(default=None, init=False)

    def times(self, step: int) -> bool:
        """True for the steps whose times the first sizing uses."""
        return self.start + 1 <= step <= self.start + SIZING_STEPS

    def record(self, seconds: float) -> None:
        self.timed.append(float(seconds))

    def due(self, step: int) -> bool:
        """True when the schedule is to be sized before ``step``."""
        if self.last_sized is None:
            return step == self.start + SIZING_STEPS + 1 and bool(self.timed)
        return step - self.last_sized[0] == RESIZE_EVERY

    def size(self, step: int) -> int:
        """Size the schedule before ``step`` (see :meth:`due`); returns its new length."""
        now = self.clock()
        if self.last_sized is None:
            step_s = float(statistics.median(self.timed))
        else:
            step_s = (now - self.last_sized[1]) / max(step - self.last_sized[0], 1)
        self.last_sized = (step, now)
        return steps_that_fit(step, self.seconds_left(), step_s, self.configured)
