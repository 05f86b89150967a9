"""Property tests: the setpoint guarantees on random valid curves (seeded hypothesis)."""

from __future__ import annotations

import numpy as np
import setpoint_checks as sc
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from planner.nurbs import NurbsCurve
from planner.stream import Path, plan_setpoints
from planner.types import Limits, SetpointBlock

T = 0.004


@st.composite
def curves(draw) -> NurbsCurve:
    degree = draw(st.integers(1, 5))
    dim = draw(st.sampled_from([2, 3]))
    n = draw(st.integers(degree + 1, degree + 5))
    coords = st.floats(-30.0, 30.0, allow_nan=False, width=32)
    points = np.array(
        draw(st.lists(st.lists(coords, min_size=dim, max_size=dim), min_size=n, max_size=n))
    )
    if n >= 3 and draw(st.booleans()):
        # A sharp corner: a control point repeated up to degree times.
        i = draw(st.integers(1, n - 2))
        reps = draw(st.integers(1, degree))
        points = np.insert(points, i, np.repeat(points[i : i + 1], reps, axis=0), axis=0)
        n = len(points)
    weights = np.array(draw(st.lists(st.floats(0.3, 3.0), min_size=n, max_size=n)))
    interior = draw(
        st.lists(st.floats(0.05, 0.95), min_size=n - degree - 1, max_size=n - degree - 1)
    )
    knots = np.concatenate([[0.0] * (degree + 1), sorted(interior), [1.0] * (degree + 1)])
    _, repeats = np.unique(knots[degree + 1 : n], return_counts=True)
    assume(repeats.max(initial=0) <= degree)
    assume(np.ptp(points, axis=0).max() > 0.5)
    return NurbsCurve.from_arrays(degree, points, np.sort(knots), weights)


# derandomize: the same examples on every run, so that CI is reproducible. Control polygons fold
# back and loop freely, so cusps and loops far tighter than delta occur.
@settings(
    max_examples=60,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
)
@given(
    curve=curves(), delta=st.sampled_from([1e-4, 1e-3, 1e-2]), vmax=st.sampled_from([20.0, 100.0])
)
def test_random_curves_keep_every_limit(curve, delta, vmax):
    assert_every_limit_holds(curve, delta, vmax)


def assert_every_limit_holds(curve: NurbsCurve, delta: float, vmax: float) -> None:
    """Plan ``curve`` and check every limit on its 4 ms setpoints (amax 1000, jmax 20000)."""
    limits = Limits(vmax_mm_s=vmax, amax_mm_s2=1000.0, jmax_mm_s3=20000.0, chord_error_mm=delta)
    block = plan_setpoints(Path(curve, limits, T), limits, T)
    assert np.isfinite(block.position_mm).all() and np.isfinite(block.u).all()
    fig = sc.measure(curve, block.u, block.position_mm, T)
    assert fig.max_feed_mm_s <= vmax * 1.001
    assert fig.max_accel_mm_s2 <= 1000.0 * 1.02
    assert fig.max_jerk_mm_s3 <= 20000.0 * 1.05
    assert fig.max_chord_error_mm <= delta * 1.01
    assert fig.end_error_mm <= 1e-6
    assert block.last and block.feed_mm_s[-1] == 0.0


def assert_joined_motion_keeps_every_limit(
    curve: NurbsCurve, first: SetpointBlock, row: int, replan: SetpointBlock, limits: Limits
) -> None:
    """Every limit on ``first``'s rows up to ``row`` followed by ``replan``'s rows."""
    u = np.concatenate([first.u[: row + 1], replan.u])
    position = np.vstack([first.position_mm[: row + 1], replan.position_mm])
    fig = sc.measure(curve, u, position, T)
    assert np.isfinite(position).all()
    assert fig.max_accel_mm_s2 <= limits.amax_mm_s2 * 1.02
    assert fig.max_jerk_mm_s3 <= limits.jmax_mm_s3 * 1.05
    assert fig.max_chord_error_mm <= limits.chord_error_mm * 1.01
    assert fig.end_error_mm <= 1e-6
