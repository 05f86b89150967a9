"""Re-plans start from the points an earlier plan of the path refined (planner.warmstart)."""

from __future__ import annotations

import curve_families as cf
import numpy as np
import pytest
from test_properties import assert_joined_motion_keeps_every_limit

import planner.refine
from planner.stream import Path, plan_setpoints
from planner.types import Limits, SetpointBlock
from planner.warmstart import RefinedPoints
from planner.window import Window

T = 0.004
LIMITS = Limits(vmax_mm_s=100.0, amax_mm_s2=1000.0, jmax_mm_s3=20000.0, chord_error_mm=1e-3)
#: A row of the paper curve's plan whose re-plan window holds the sharp stretch.
SHARP_ROW = 145


def replan_with_checks_counted(
    path: Path, first: SetpointBlock, row: int, ratio: float, monkeypatch
) -> tuple[SetpointBlock, int]:
    """The re-plan from ``first``'s row with an override, and how many refinement rounds
    checked the segments of its windows."""
    rounds = 0
    failing = planner.refine._failing

    def counted(*args):
        nonlocal rounds
        rounds += 1
        return failing(*args)

    monkeypatch.setattr(planner.refine, "_failing", counted)
    replan = plan_setpoints(path, LIMITS.with_feed_override(ratio), T, start=first.state(row))
    monkeypatch.undo()
    return replan, rounds


def test_a_replan_starts_from_what_the_first_plan_refined(monkeypatch):
    curve = cf.paper_curve()
    warm = Path(curve, LIMITS, T)
    first = plan_setpoints(warm, LIMITS, T)
    assert len(warm.refined) > 0
    warm_replan, warm_rounds = replan_with_checks_counted(warm, first, SHARP_ROW, 1.2, monkeypatch)
    cold = Path(curve, LIMITS, T)
    cold_replan, cold_rounds = replan_with_checks_counted(cold, first, SHARP_ROW, 1.2, monkeypatch)
    assert len(cold.refined) > 0  # a cold path remembers its re-plan, but started from nothing
    assert warm_rounds < cold_rounds
    assert_joined_motion_keeps_every_limit(curve, first, SHARP_ROW, warm_replan, LIMITS)
    # Both plans are found by the same refinement: their motion times agree closely.
    assert warm_replan.t_s[-1] == pytest.approx(cold_replan.t_s[-1], rel=0.02)


def test_a_plan_from_rest_is_the_same_motion_whatever_was_planned_before():
    curve = cf.paper_curve()
    path = Path(curve, LIMITS, T)
    first = plan_setpoints(path, LIMITS, T)
    for row, ratio in ((40, 0.4), (SHARP_ROW, 1.5), (300, 0.7)):
        plan_setpoints(path, LIMITS.with_feed_override(ratio), T, start=first.state(row))
    again = plan_setpoints(path, LIMITS, T)
    assert np.array_equal(again.position_mm, first.position_mm)


def test_points_at_the_vmax_of_either_plan_are_not_offered():
    memory = RefinedPoints()
    refined = Window([0.0, 10.0], [0.0, 0.0], [False])
    refined.insert(0, 3.0, 50.0)  # placed by the limit
    refined.insert(1, 6.0, 99.5)  # at the vmax of the plan that added it
    memory.remember(refined, {0.0, 10.0}, vmax_mm_s=100.0)
    assert len(memory) == 2
    for vmax, kept in ((100.0, [3.0]), (45.0, []), (200.0, [3.0])):
        seeded = Window([0.0, 10.0], [0.0, 0.0], [False])
        memory.seed(seeded, vmax)
        assert seeded.s[1:-1] == kept


def test_a_plan_below_a_point_keeps_it_and_one_that_sees_it_replaces_it():
    memory = RefinedPoints()
    refined = Window([0.0, 10.0], [0.0, 0.0], [False])
    refined.insert(0, 3.0, 50.0)
    memory.remember(refined, {0.0, 10.0}, vmax_mm_s=100.0)
    # A plan of the stretch at 40 % refines nothing there: the point above its vmax stays.
    memory.remember(Window([0.0, 10.0], [0.0, 0.0], [False]), {0.0, 10.0}, vmax_mm_s=40.0)
    seeded = Window([0.0, 10.0], [0.0, 0.0], [False])
    memory.seed(seeded, 100.0)
    assert seeded.s[1:-1] == [3.0]
    # A plan that could have used it and found no need replaces it.
    memory.remember(Window([0.0, 10.0], [0.0, 0.0], [False]), {0.0, 10.0}, vmax_mm_s=100.0)
    assert len(memory) == 0
