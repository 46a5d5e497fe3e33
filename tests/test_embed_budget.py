"""Ending an embedding within a wall-clock budget (embed_budget): the stopping rule; the loop is in
test_embed.py."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from mnerf_jax.watermark import time_budget as B


def test_the_first_step_always_runs_then_steps_are_judged_by_the_recent_ones() -> None:
    clock = B.BudgetClock(budget_s=100.0, started=0.0)
    assert clock.room_for_a_step(now=1_000.0)  # nothing timed yet: a run takes at least one step
    for seconds in (40.0, 1.0, 1.2, 0.9):  # the first step compiled
        clock.record_step(seconds)
    assert clock.expected_step_s() == 1.1
    clock.checkpoint_s = 2.0
    room = 100.0 - 1.1 - 2.0 - B.RESERVE_S
    assert clock.room_for_a_step(now=room)
    assert not clock.room_for_a_step(now=room + 0.01)


def test_a_resumed_run_owes_no_first_step_once_its_earlier_processes_spent_the_budget() -> None:
    # Its clock started at the seconds the checkpoint recorded (here 80 s before this process began at 0).
    spent = B.BudgetClock(budget_s=100.0, started=-80.0, resumed=True)
    assert not spent.room_for_a_step(now=0.0)  # 80 + 5 (a checkpoint) + 45 kept > 100
    roomy = B.BudgetClock(budget_s=1_000.0, started=-80.0, resumed=True, kept_s=30.0)
    assert roomy.room_for_a_step(now=0.0)
    assert not roomy.room_for_a_step(now=1_000.0 - 80.0 - 30.0 - B.FIRST_CHECKPOINT_S - B.RESERVE_S + 0.01)


@settings(max_examples=50, deadline=None)
@given(
    times=st.lists(st.floats(0.01, 100.0), min_size=1, max_size=3 * B.RECENT_STEPS),
    budget=st.floats(60.0, 7_200.0),
    checkpoint=st.floats(0.0, 10.0),
)
def test_a_step_is_let_in_only_when_it_and_the_last_checkpoint_fit(
    times: list[float], budget: float, checkpoint: float
) -> None:
    clock = B.BudgetClock(budget_s=budget, started=10.0)
    for t in times:
        clock.record_step(t)
    assert len(clock.step_seconds) == min(len(times), B.RECENT_STEPS)
    clock.checkpoint_s = checkpoint
    step = B.expected_step_seconds(times[-B.RECENT_STEPS :])
    assert step is not None and clock.expected_step_s() == step
    for elapsed in (0.0, budget / 2, budget - B.RESERVE_S - step - checkpoint, budget):
        now = 10.0 + elapsed
        fits = (now - 10.0) + step + checkpoint + B.RESERVE_S <= budget  # the clock's rounding at the edge
        assert clock.room_for_a_step(now=now) == fits


def test_no_steps_no_estimate() -> None:
    assert B.expected_step_seconds([]) is None
    assert B.expected_step_seconds([3.0, 1.0, 2.0]) == 2.0


@settings(max_examples=50, deadline=None)
@given(
    done=st.integers(0, 10_000),
    left=st.floats(-100.0, 1e5),
    step_s=st.floats(1e-3, 10.0),
    configured=st.integers(1, 20_000),
)
def test_a_sized_schedule_fits_its_margin_of_the_time_and_never_outgrows_the_configured_one(
    done: int, left: float, step_s: float, configured: int
) -> None:
    total = B.steps_that_fit(done, left, step_s, configured)
    assert total >= done + 1  # the step about to run always belongs to it
    if total > done + 1:
        assert total <= configured
        assert (total - done) * step_s <= B.SIZING_MARGIN * left + 1e-6
    if configured > done and (configured - done) * step_s <= B.SIZING_MARGIN * left - step_s:
        assert total == configured  # all the steps fit: the configured schedule


def test_a_sizer_times_its_first_steps_then_sizes_by_the_pace_since_the_last_sizing() -> None:
    # A clock one second on at each call; steps 11..30 timed at 2 s sizes at step 31 to 31 + 0.97 * 100 / 2;
    # RESIZE_EVERY steps later (one clock call: 1 s for 500 steps) the schedule grows back to its length.
    ticks = iter(range(10**6))
    sizer = B.ScheduleSizer(1_000, lambda: 100.0, start=10, clock=lambda: float(next(ticks)))
    assert [s for s in range(40) if sizer.times(s)] == list(range(11, 11 + B.SIZING_STEPS))
    assert not sizer.due(B.SIZING_STEPS + 11)  # nothing timed yet
    for _ in range(B.SIZING_STEPS):
        sizer.record(2.0)
    first = B.SIZING_STEPS + 11
    assert sizer.due(first) and sizer.size(first) == first + int(B.SIZING_MARGIN * 100.0 / 2.0)
    assert not sizer.due(first + 1) and sizer.due(first + B.RESIZE_EVERY)
    assert sizer.size(first + B.RESIZE_EVERY) == 1_000
