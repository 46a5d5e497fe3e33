"""Sizing phase 2 to a wall-clock budget (embed_budget): the arithmetic; the wiring is in test_embed.py."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mnerf_jax import embed_budget as B


@settings(max_examples=60, deadline=None)
@given(
    budget_min=st.floats(5.0, 240.0),
    elapsed=st.floats(0.0, 120.0),
    phase1=st.integers(0, 400),
    t1=st.floats(0.05, 3.0),
    t2=st.floats(0.05, 3.0),
    save=st.floats(0.0, 5.0),
    every=st.integers(1, 500),
)
def test_the_plan_is_the_longest_phase_two_that_fits(
    budget_min: float, elapsed: float, phase1: int, t1: float, t2: float, save: float, every: int
) -> None:
    budget = budget_min * 60.0
    try:
        plan = B.plan_phase2(budget, elapsed, phase1, t1, t2, save, every, max_phase2_steps=10**9)
    except B.BudgetError as err:
        one_step = B.BudgetPlan(1, budget, elapsed, t1, t2, save)
        assert one_step.projected_s(phase1, every) > budget  # not even one step had room
        assert "holds no phase-2 step" in str(err)
        return
    assert plan.phase2_steps >= 1
    assert plan.projected_s(phase1, every) <= budget + 1e-6
    longer = B.BudgetPlan(plan.phase2_steps + 1, budget, elapsed, t1, t2, save)
    assert longer.projected_s(phase1, every) > budget  # one more step would not fit


def test_the_plan_is_capped_by_the_configured_phase_two() -> None:
    plan = B.plan_phase2(3600.0, 60.0, 100, 1.2, 1.6, 1.0, 100, max_phase2_steps=1500)
    assert plan.phase2_steps == 1500
    uncapped = B.plan_phase2(3600.0, 60.0, 100, 1.2, 1.6, 1.0, 100, max_phase2_steps=10**9)
    # The lego protocol's figures on the 2-core CPU: about 2,000 phase-2 steps in the hour after phase 1.
    assert 1900 < uncapped.phase2_steps < 2100
    assert uncapped.to_dict()["phase2_steps"] == uncapped.phase2_steps


def test_a_budget_without_room_for_phase_two_is_refused_with_its_figures() -> None:
    with pytest.raises(B.BudgetError, match=r"0\.5 min holds no phase-2 step.*100 steps take ~120 s"):
        B.plan_phase2(30.0, 5.0, 100, 1.2, 1.6, 1.0, 100, max_phase2_steps=1000)


def test_probe_times_leave_out_the_compiling_step() -> None:
    assert B.median_step_seconds([40.0, 1.0, 2.0, 3.0]) == 2.0
    assert B.median_step_seconds([40.0]) == 40.0
    with pytest.raises(ValueError):
        B.median_step_seconds([])
