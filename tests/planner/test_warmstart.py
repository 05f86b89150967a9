"""Re-plans start from the points an earlier plan of the path refined (planner.warmstart)."""

from __future__ import annotations

import curve_families as cf
import numpy as np
import pytest
import setpoint_checks as sc
from hypothesis import given
from hypothesis import strategies as st
from test_families import family_curves, family_settings

import planner.refine
from planner.nurbs import NurbsCurve
from planner.stream import Path, plan_setpoints
from planner.types import Limits, SetpointBlock
from planner.warmstart import RefinedPoints

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


def assert_joined_motion_keeps_every_limit(
    curve: NurbsCurve, first: SetpointBlock, row: int, replan: SetpointBlock, limits: Limits
) -> None:
    u = np.concatenate([first.u[: row + 1], replan.u])
    position = np.vstack([first.position_mm[: row + 1], replan.position_mm])
    fig = sc.measure(curve, u, position, T)
    assert np.isfinite(position).all()
    assert fig.max_accel_mm_s2 <= limits.amax_mm_s2 * 1.02
    assert fig.max_jerk_mm_s3 <= limits.jmax_mm_s3 * 1.05
    assert fig.max_chord_error_mm <= limits.chord_error_mm * 1.01
    assert fig.end_error_mm <= 1e-6


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
    from planner.window import Window

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


@family_settings(40)
@given(
    curve=family_curves(),
    delta=st.sampled_from([1e-4, 1e-3, 1e-2]),
    where=st.floats(0.05, 0.9),
    ratio=st.sampled_from([0.3, 0.8, 1.5]),
)
def test_warm_replans_of_the_curve_families_keep_every_limit(curve, delta, where, ratio):
    limits = Limits(vmax_mm_s=100.0, amax_mm_s2=1000.0, jmax_mm_s3=20000.0, chord_error_mm=delta)
    path = Path(curve, limits, T)
    first = plan_setpoints(path, limits, T)
    row = int(where * (len(first) - 1))
    while first.accel_mm_s2[row] < 0.0:
        row += 1  # a re-plan starts where the motion does not brake, as the runtime's splices
    replan = plan_setpoints(path, limits.with_feed_override(ratio), T, start=first.state(row))
    assert_joined_motion_keeps_every_limit(curve, first, row, replan, limits)
    assert replan.feed_mm_s[-1] == 0.0
