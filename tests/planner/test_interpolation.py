"""Acceptance on the paper's curve (Table 1), measured on the 4 ms setpoints."""

from __future__ import annotations

from pathlib import Path as FilePath

import numpy as np
import pytest
import setpoint_checks as sc
import yaml

from planner.nurbs import NurbsCurve
from planner.stream import Path, plan_setpoints
from planner.types import Limits, MotionState

T = 0.004
PAPER = FilePath(__file__).resolve().parents[2] / "configs" / "curves" / "paper.yaml"


@pytest.fixture(scope="module")
def curve() -> NurbsCurve:
    return NurbsCurve.from_mapping(yaml.safe_load(PAPER.read_text()))


def paper_limits(delta_mm: float) -> Limits:
    return Limits(vmax_mm_s=100.0, amax_mm_s2=1000.0, jmax_mm_s3=20000.0, chord_error_mm=delta_mm)


@pytest.mark.parametrize("delta_mm", [1e-4, 5e-4, 1e-3])
def test_limits_hold_on_the_setpoints(curve, delta_mm):
    limits = paper_limits(delta_mm)
    block = plan_setpoints(Path(curve, limits, T), limits, T)
    fig = sc.measure(curve, block.u, block.position_mm, T)
    assert fig.max_feed_mm_s <= 100.0 * 1.001
    assert fig.max_accel_mm_s2 <= 1000.0 * 1.02
    assert fig.max_jerk_mm_s3 <= 20000.0 * 1.05
    assert fig.max_chord_error_mm <= delta_mm * 1.01
    assert fig.end_error_mm <= 1e-6
    assert block.last and block.feed_mm_s[-1] == 0.0 and block.accel_mm_s2[-1] == 0.0
    assert np.array_equal(block.position_mm[-1], curve.end_point)
    assert not np.isnan(block.position_mm).any()


@pytest.mark.parametrize("short_of_end_mm", [4e-14, 1e-9, 1e-7])
def test_a_start_at_rest_a_hair_before_the_end_lands_exactly_on_it(curve, short_of_end_mm):
    """A stop can come to rest within round-off of the end; the resume still ends on it."""
    limits = paper_limits(1e-3)
    path = Path(curve, limits, T)
    start = MotionState(path.length_mm - short_of_end_mm)
    block = plan_setpoints(path, limits, T, start=start)
    assert block.last and block.s_mm[-1] == path.length_mm
    assert np.array_equal(block.position_mm[-1], curve.end_point)


def test_corrected_update_follows_the_planned_arc_length(curve):
    limits = paper_limits(1e-3)
    path = Path(curve, limits, T)
    block = plan_setpoints(path, limits, T)
    s_real = path.arc.s_of_u(block.u)
    assert np.abs(s_real - block.s_mm).max() < 1e-8
    planned = np.diff(block.s_mm)
    moving = planned > 1e-3
    fluctuation = np.abs(np.diff(s_real)[moving] / planned[moving] - 1.0)
    assert fluctuation.max() < 1e-6


def test_taylor2_drifts_more_than_corrected(curve):
    limits = paper_limits(1e-3)
    path = Path(curve, limits, T)
    taylor = plan_setpoints(path, limits, T, update="taylor2")
    corrected = plan_setpoints(path, limits, T, update="corrected")
    err_t = np.abs(path.arc.s_of_u(taylor.u[:-1]) - taylor.s_mm[:-1]).max()
    err_c = np.abs(path.arc.s_of_u(corrected.u[:-1]) - corrected.s_mm[:-1]).max()
    assert err_c < err_t


def test_near_time_optimal(curve):
    limits = paper_limits(1e-3)
    block = plan_setpoints(Path(curve, limits, T), limits, T)
    from planner.feed import chord_error_feed

    bound = sc.acceleration_bound_time_s(
        curve, lambda u: chord_error_feed(curve.curvature(u), 1e-3, T), 100.0, 1000.0, 5001
    )
    ratio = (len(block) - 1) * T / bound
    print(f"motion time / acceleration-limited bound = {ratio:.3f}")
    assert 1.0 <= ratio <= 1.10


@pytest.mark.parametrize("delta_mm", [1e-4, 5e-4, 1e-3])
def test_no_lookahead_breaks_the_acceleration_limit(curve, delta_mm):
    limits = paper_limits(delta_mm)
    block = plan_setpoints(Path(curve, limits, T), limits, T, lookahead=False)
    feed = sc.realised_feed(block.position_mm, T)
    accel = np.abs(sc.differences(feed, T))
    # Eq. (4) alone steps the feed at the start and the end; at the curvature maximum in
    # between the chord-error feed changes as fast as the curvature does.
    factor = accel.max() / 1000.0
    inner = accel[2:-2].max() / 1000.0
    print(
        f"no look-ahead, delta {delta_mm} mm: max |a| = {factor:.1f} x amax, {inner:.2f} x inside"
    )
    assert factor > 9.0
    fig = sc.measure(curve, block.u, block.position_mm, T)
    assert fig.max_chord_error_mm <= delta_mm * 1.05
    assert fig.end_error_mm <= 1e-6
