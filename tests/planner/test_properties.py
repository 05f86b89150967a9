"""Property tests: the setpoint guarantees on random valid curves (seeded hypothesis)."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest
import setpoint_checks as sc
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from planner.errors import CurveError, CurveRule
from planner.nurbs import NurbsCurve
from planner.stream import Path, braking_end_from_rows, plan_setpoints, stream_setpoints
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
    try:
        return NurbsCurve.from_arrays(degree, points, np.sort(knots), weights)
    except CurveError as exc:  # knots closer than the parameter resolves the path
        assume(exc.rule is not CurveRule.KNOT_SPACING)
        raise


def derandomized(max_examples: int) -> settings:
    """The same examples on every run, so that CI is reproducible; plans take their time."""
    return settings(
        max_examples=max_examples,
        deadline=None,
        derandomize=True,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
    )


# derandomize: the same examples on every run, so that CI is reproducible. Control polygons fold
# back and loop freely, so cusps and loops far tighter than delta occur. 400 examples (about
# 25 s): with 60, the curves found by the longer runs below were all missed.
@derandomized(400)
@given(
    curve=curves(), delta=st.sampled_from([1e-4, 1e-3, 1e-2]), vmax=st.sampled_from([20.0, 100.0])
)
def test_random_curves_keep_every_limit(curve, delta, vmax):
    assert_every_limit_holds(curve, delta, vmax)


# Machines other than the paper's: acceleration and jerk limits from a slow, stiff axis
# (A 200 mm/s², J 200,000 mm/s³: the acceleration settles within a period) to a fast, soft
# one. Derandomized, 150 examples (about 15 s). With the paper's limits alone, the chord
# deficit's acceleration went unchecked: 1.03-1.08 A with A 200 and J 200,000 on one curve in
# six (the found case below).
@derandomized(150)
@given(
    curve=curves(),
    delta=st.sampled_from([1e-4, 1e-3, 1e-2]),
    vmax=st.sampled_from([20.0, 100.0, 300.0]),
    amax=st.sampled_from([200.0, 1000.0, 5000.0]),
    jmax=st.sampled_from([5000.0, 20000.0, 200000.0]),
)
def test_random_curves_keep_every_limit_of_other_machines(curve, delta, vmax, amax, jmax):
    assert_every_limit_holds(curve, delta, vmax, amax, jmax)


# Re-plans with the optional limits on (normal acceleration, each axis's feed and
# acceleration), each axis checked on the joined motion too. Derandomized, 100 examples (about
# 40 s); a longer run found a pin on a flat per-axis limit whose segment before it went
# unchecked (5.2 J; the found case below).
@derandomized(100)
@given(
    curve=curves(),
    delta=st.sampled_from([1e-4, 1e-3, 1e-2]),
    normal=st.one_of(st.none(), st.sampled_from([200.0, 1000.0, 5000.0])),
    axis_feed=st.one_of(st.none(), st.floats(10.0, 150.0)),
    axis_accel=st.one_of(st.none(), st.floats(200.0, 2000.0)),
    where=st.floats(0.0, 1.0),
    braking=st.booleans(),
    ratio=st.sampled_from([0.3, 1.0, 1.5]),
)
def test_replans_with_the_optional_limits_keep_every_limit(
    curve, delta, normal, axis_feed, axis_accel, where, braking, ratio
):
    dim = curve.dimension
    limits = Limits(
        vmax_mm_s=100.0,
        amax_mm_s2=1000.0,
        jmax_mm_s3=20000.0,
        chord_error_mm=delta,
        normal_accel_mm_s2=normal,
        axis_vmax_mm_s=None if axis_feed is None else (axis_feed,) * dim,
        axis_amax_mm_s2=None if axis_accel is None else (axis_accel,) * dim,
    )
    position = assert_a_replan_keeps_every_limit(curve, limits, where, braking, ratio)
    axis_feed_mm_s = np.diff(position, axis=0) / T
    if axis_feed is not None:
        assert np.abs(axis_feed_mm_s).max() <= axis_feed * 1.01 + 1e-9
    if axis_accel is not None:
        assert np.abs(np.diff(axis_feed_mm_s, axis=0)).max() / T <= axis_accel * 1.05 + 1e-6


# Found by longer runs of the test above (its examples are fixed: derandomize): each curve with
# the chord error (mm) and vmax (mm/s) it failed at.
FOUND_CASES = {
    # A line turning into a 1 mm radius at a knot: the curvature jumps, and the chord deficit
    # with it, within one step (1.06 J without planner.feed.curvature_jump_feed).
    "curvature jump at a knot": (
        NurbsCurve.from_arrays(
            2,
            np.array(
                [[0, 0, 0], [0, 17, 4], [0, 17, 4], [0, 17, 4], [0, 18, 0], [0, 0, 1], [0, 0, 0]]
            ),
            np.array([0, 0, 0, 0.25, 0.25, 0.5, 0.75, 1, 1, 1]),
        ),
        1e-2,
        100.0,
    ),
    # A tip whose limit is set by the chord-deficit jerk, the feed limit falling from 140 to
    # 15 mm/s within two steps: that limit must reach a whole step (1.055 J at half a step).
    "tip bound by the chord deficit": (
        NurbsCurve.from_arrays(
            2,
            np.array(
                [
                    [0, 0, 0],
                    [0, 0, 0],
                    [0, 0, 0],
                    [7, 0, 0],
                    [1.5, -11, 5],
                    [1, -27, -23],
                    [0, 0, 0],
                ]
            ),
            np.array([0, 0, 0, 0.125, 0.21875, 0.59375, 0.78125, 1, 1, 1]),
            np.array([1, 1, 1, 0.40625, 1.5, 2.75, 1]),
        ),
        1e-2,
        100.0,
    ),
    # The curvature falls from 1/mm to 0 within 0.7 mm, faster than a tip of that radius: the
    # chord deficit changes faster than chord_deficit_feed assumes (1.09 J without
    # planner.feed.chord_deficit_change_feed).
    "curvature falling to 0 within its radius": (
        NurbsCurve.from_arrays(
            3,
            np.array([[0, 3], [0, 0], [5, 0], [0, 0], [0, 0]]),
            np.array([0, 0, 0, 0, 0.0625, 1, 1, 1, 1]),
            np.array([1, 0.5, 2, 1, 1]),
        ),
        1e-2,
        100.0,
    ),
    # Degree 4: a straight line along x, then from the knot at u = 0.75 a curve turning back
    # towards (0, 1). At that knot the curvature is 0 on both sides; its curvature-jump limit
    # was the largest float instead of inf, and the checker's linear interpolation from there to
    # the next sample, 0.23 mm on, overflowed to -inf: the plan's speeds became infinite.
    "a straight stretch meeting a curve at a knot": (
        NurbsCurve.from_arrays(
            4,
            np.array([[0, 0], [0, 0], [0, 0], [0, 0], [0, 0], [14, 0], [0, 1]]),
            np.array([0, 0, 0, 0, 0, 0.05, 0.75, 1, 1, 1, 1, 1]),
        ),
        1e-2,
        20.0,
    ),
    # A tip of 2 mm/s at 0.1 µm inside a grid interval whose ends have alike limits: the
    # interval was not halved, and the limit, concave on either side of the tip, was
    # interpolated linearly over the 0.056 mm from the tip's neighbour to the grid (1.018 delta).
    "a tip inside a grid interval with alike ends": (
        NurbsCurve.from_arrays(
            5,
            np.array(
                [
                    [0, 0],
                    [-1, 12],
                    [-1, 12],
                    [-1.5, 9.9375],
                    [0, 16.5],
                    [-17, 0],
                    [0, 2],
                    [0, 0],
                    [0, 0],
                ]
            ),
            np.array([0, 0, 0, 0, 0, 0, 0.05078125, 0.3046875, 0.3125, 1, 1, 1, 1, 1, 1]),
            np.array([1, 0.3125, 0.3125, 0.3125, 0.3125, 0.3125, 1, 1, 1]),
        ),
        1e-4,
        100.0,
    ),
    # Degree 1: up 4.6 mm and back down, the turn a span of zero length (a repeated control
    # point), where |C'| is round-off (1e-14) at every grid sample. A reversal told apart from
    # a cusp by |C'| against the grid interval's ends, which are inside that span here, was
    # passed at 20 mm/s (9.4 J, 30 delta).
    "a reversal across a span of zero length": (
        NurbsCurve.from_arrays(
            1,
            np.array([[0, 0], [0, 4.64453125], [0, 4.64453125], [0, 0], [0, 0], [0, 0]]),
            np.array([0, 0, 0.208984375, 0.314453125, 0.5, 0.75, 1, 1]),
            np.array([1, 0.3, 2.5390625, 1, 1, 1]),
        ),
        1e-4,
        20.0,
    ),
    # Degree 5, near folds: the first window ended 4 µm before a tip of 1.12 mm/s and released
    # 100 mm/s 7.5 mm before it, enough to stop at the window's end but not to meet the tip at
    # zero acceleration. The next window's braking segment ran over the limit (1.35 delta,
    # 1.56 J) and held 1.12 mm/s to the curve's end, 22 mm on (planner.refine.refine).
    "a window ending just before a tip": (
        NurbsCurve.from_arrays(
            5,
            np.array(
                [
                    [0.0, 0.0],
                    [-7.46010653, -5.99525991],
                    [-7.89860393, -5.44962264],
                    [-1.38181336, -0.21245169],
                    [3.29072198, 6.59190411],
                    [3.86776738, 6.19564838],
                    [-1.83145467, -2.10381471],
                    [-4.67460169, -14.07461615],
                    [-3.99354715, -14.23637125],
                    [-1.51427854, -3.79764541],
                    [3.9714494, 9.0436415],
                ]
            ),
            np.array([0, 0, 0, 0, 0, 0, 1, 2, 3, 4, 5, 6, 6, 6, 6, 6, 6]),
        ),
        1e-3,
        100.0,
    ),
    # Degree 5, spatial: between two grid samples where the curvature rises at both, it peaks
    # at 0.579 /mm and dips after. The peak was not searched for (only intervals rising at
    # their start and falling at their end were), and the feed passed it 1.1 % above the
    # chord-error limit: 1.021 delta (planner.envelope.hermite_peaks).
    "a peak and a dip between two rising samples": (
        NurbsCurve.from_arrays(
            5,
            np.array(
                [
                    [0.0, 0.0, 0.0],
                    [-7.22943599, 7.76727894, -1.19941779],
                    [-7.68595407, 3.13880306, -2.17106057],
                    [-4.7203321, 6.7409649, -1.92103677],
                    [-14.18294903, 9.8864011, -1.84753583],
                    [-4.93214233, 15.4981094, -2.08176389],
                    [-4.16110604, 4.59420415, -1.82585376],
                ]
            ),
            np.array([0, 0, 0, 0, 0, 0, 1, 2, 2, 2, 2, 2, 2]),
        ),
        1e-4,
        100.0,
    ),
    # Degree 5, rational, a control point repeated five times: between two grid samples the
    # curvature rises to 22 /mm, falls to 1 and rises to 10.3 /mm again. The peak search
    # followed the higher peak alone; the other was passed at the feed of a sample 11 µm
    # before it, 1.053 delta (planner.envelope._other_peaks).
    "two curvature peaks between two grid samples": (
        NurbsCurve.from_arrays(
            5,
            np.array(
                [
                    *([19.20088, -21.674313], [-0.561773, 23.770084], [0, 0]),
                    *([-0.561773, 23.770084], [1.5, 1.5], *[[0.99999, 25.652178]] * 5),
                    *([0, 0], [4.530916, 4.0], [0, 0]),
                ]
            ),
            np.array([*[0] * 6, 0.05, 0.3, 0.324822, 0.615552, 0.719095, 0.932763, 0.95, *[1] * 6]),
            np.array(
                [
                    *(2.13659, 0.9, 0.3, 1.5, 1.0, 2.295751, 0.685817),
                    *(2.621505, 2.585795, 1.9, 2.06734, 1.315071, 2.965672),
                ]
            ),
        ),
        1e-4,
        100.0,
    ),
    # Degree 4 up and down the y axis, its last two control points one: C'(1) = 0, and the
    # curve reverses 0.019 mm before its end, inside the grid's last interval. Its tangent
    # was compared with the end's, which has none: the reversal went unseen and was passed at
    # 4 mm/s (1.15 A, 19 J at every limit tried; planner.envelope searches such an interval
    # towards its end now).
    "a reversal just before an end whose control points repeat": (
        NurbsCurve.from_arrays(
            4, np.array([[0, 0], [0, -7], [0, 1], [0, 0], [0, 0]]), np.array([0] * 5 + [1] * 5)
        ),
        1e-3,
        100.0,
    ),
    # The same off the origin and rational: C'(1) is round-off (3e-14), not 0, and its
    # direction is noise.
    "a reversal just before a rational end whose control points repeat": (
        NurbsCurve.from_arrays(
            4,
            np.array([[0.1, 0.2], [0.1, -7], [0.1, 1], [0.1, 0.2], [0.1, 0.2]]),
            np.array([0] * 5 + [1] * 5),
            np.array([1, 2, 1, 1.7, 1.3]),
        ),
        1e-3,
        100.0,
    ),
    # A degree-5 Bézier whose curvature falls from 20.6 /mm at its start to 0.3, rises to
    # 2.85 /mm at u = 0.045 and falls to 1.93 at the first grid sample: both grid ends fall, and
    # the cubic through their shallow slopes too. The samples halved in where the limit changes
    # fast showed the dip and the rise, but no search was run there: the plan crossed the peak
    # at the feed of its neighbours, 1.42 delta (planner.envelope._missed_maxima).
    "a curvature peak the grid's tests do not see": (
        NurbsCurve.from_arrays(
            5,
            np.array([[0, 0], [0, 0.3], [2.319068, 0], [-14.653651, 30], [0.3, 0], [-8.013223, 0]]),
            np.array([0] * 6 + [1] * 6),
            np.array([0.3, 0.3, 0.3, 0.3, 1.268276, 2.578814]),
        ),
        1e-4,
        100.0,
    ),
    # Up the y axis into a control point repeated five times (degree 5) and off to the right:
    # C' at the knot is 5e-30, not 0 (the point is 1e-13 off the origin, the weights differ),
    # and C' x C'' is exactly 0, so the curvature there came out 0 and the limit vmax. The
    # corner between the two straight spans was passed at speed: 8.0 delta, 2.7 J. Shrunk from
    # a random curve (vmax 20, A 5000) that measured 4.3 delta; a still sample is a stop now.
    "a still knot where the curve turns": (
        NurbsCurve.from_arrays(
            5,
            np.array([[0, -26.5], *[[0, 1e-13]] * 5, [6.6, 24.3], [-17.5, 1.5]]),
            np.array([0] * 6 + [0.4, 0.6] + [1] * 6),
            np.array([1, 2.9, 1.9, 3, 1.6, 1.8, 0.3, 1.3]),
        ),
        1e-3,
        100.0,
    ),
    # Degree 2 in space: at the knot u = 0.857 the curvature goes from 0.15 to 0.19 /mm and
    # its normal turns. The chord deficit's change was bounded by the jump of |kappa| alone;
    # a step across the knot has less deficit than either neighbour (the tangent turns two
    # ways), and the setpoints measured 1.065 J (planner.feed.curvature_jump_feed).
    "a knot where the curvature's normal turns": (
        NurbsCurve.from_arrays(
            2,
            np.array(
                [
                    *([0, -28.559, 0.001], [12.94, -27.871, -17.396]),
                    *[[4.411, 0, 2.038]] * 3,
                    *([-1.769, -17.396, 0], [-20.1, -27.871, -19.423], [0, -28.559, 0.001]),
                ]
            ),
            np.array([0, 0, 0, 0.1, 0.429, 0.587, 0.75, 0.857, 1, 1, 1]),
            np.array([2.024, 1.558, 2.025, 2.583, 2.466, 0.75, 0.3, 2.614]),
        ),
        1e-2,
        100.0,
    ),
}


# Found with other machines' limits: each curve with the chord error (mm), vmax (mm/s), amax
# (mm/s²) and jmax (mm/s³) it failed at.
FOUND_CASES_OTHER_MACHINES = {
    # Degree 3 with a double knot, A 200 mm/s² against J 200,000 mm/s³ at delta = 10 µm: the
    # curvature changes within a few steps, and so does the chord deficit, whose change from
    # one step to the next added 4.5 % of A to the chord feed's acceleration
    # (planner.feed.chord_deficit_change_feed now holds it to 1 %).
    "the chord deficit's acceleration": (
        NurbsCurve.from_arrays(
            3,
            np.array([[17, -9], [-6, 16], [-13, -18], [-5, 7], [-15, 15], [-7, -11]]),
            np.array([0, 0, 0, 0, 1, 1, 2, 2, 2, 2]),
            np.array([1, 2, 2, 2, 0.5, 0.5]),
        ),
        1e-2,
        100.0,
        200.0,
        200000.0,
    ),
    # Degree 5 on 2 µm knot spans, two control points 0.3 µm off the line: a tip whose limit
    # dips over a micrometre, narrower than the half-period steps the check samples the plan
    # at. The plan passed it 9 % above the limit between two samples: 1.036 delta
    # (planner.checker.Checker now checks the plan where the limit has such a kink).
    "a tip narrower than the check's samples": (
        NurbsCurve.from_arrays(
            5,
            np.c_[
                np.arange(16) * 0.002,
                np.where(np.arange(16) == 8, 3e-4, np.where(np.arange(16) == 10, -3e-4, 0.0)),
            ],
            np.concatenate([[0.0] * 6, np.arange(1.0, 11.0), [11.0] * 6]),
        ),
        1e-4,
        100.0,
        1000.0,
        200000.0,
    ),
}


@pytest.mark.parametrize("name", FOUND_CASES_OTHER_MACHINES)
def test_curves_found_with_other_machines_keep_every_limit(name):
    assert_every_limit_holds(*FOUND_CASES_OTHER_MACHINES[name])


@pytest.mark.parametrize("name", FOUND_CASES)
def test_curves_found_by_longer_runs_keep_every_limit(name):
    assert_every_limit_holds(*FOUND_CASES[name])


def test_a_reversal_of_a_rational_curve_nearly_on_a_line_is_a_rest():
    # Up the y axis and back, then into z: the reversal lies 8e-8 mm off the line, a tip of
    # 1e-11 mm radius, far too narrow for the search of curvature maxima. Taken for a
    # near-cusp, it was passed at speed on re-plans: 4.7 A and 2.4 delta.
    curve = NurbsCurve.from_arrays(
        3,
        np.array([[0, 0, 0], [0, 0, 0], [0, 6, 0], [0, 0, 0], [0, 0, 1], [0, 0, 0]]),
        np.array([0, 0, 0, 0, 0.1442694, 0.16846702, 1, 1, 1, 1]),
        np.array([1, 2.6875, 1, 2.25, 0.5, 1]),
    )
    limits = Limits(vmax_mm_s=100.0, amax_mm_s2=1000.0, jmax_mm_s3=20000.0, chord_error_mm=1e-4)
    per_axis = replace(limits, axis_vmax_mm_s=(10.0,) * 3, axis_amax_mm_s2=(200.0,) * 3)
    for where, plan_limits in itertools.product((0.0, 0.03125), (limits, per_axis)):
        assert_a_replan_keeps_every_limit(curve, plan_limits, where, braking=False, ratio=0.3)


#: Found by longer runs with per-axis feed limits of 10 mm/s: each curve with the vmax (mm/s)
#: and chord error (mm) it failed at.
AXIS_FEED_CASES = {
    # The tangent turns through -x between two grid samples, where V_x / |t_x| has its minimum,
    # flat; interpolated linearly from the grid, the limit missed it, and the x axis moved at
    # 10.106 mm/s.
    "through -x between two samples": (
        NurbsCurve.from_arrays(
            5,
            np.array([[16, 0], [3, -15], [11, -0.5], [0, 0], [6, 0], [0, -26], [0, 0]]),
            np.array([0, 0, 0, 0, 0, 0, 0.25, 1, 1, 1, 1, 1, 1]),
            np.array([1.5, 0.5625, 2, 0.5, 1, 1, 1]),
        ),
        20.0,
        1e-3,
    ),
    # Through -y between the first two samples; the first sample, with one neighbour, was not
    # searched for that peak: the y axis moved at 10.30 mm/s.
    "through -y between the first two samples": (
        NurbsCurve.from_arrays(
            3,
            np.array(
                [[0, 4], [1, 0], [-3, 0], [-3, 0], [-3, 0], [-3, 0], [0, 0], [0, 0], [0, 0], [0, 0]]
            ),
            np.array([0, 0, 0, 0, 0.25, 0.25, 0.5, 0.5, 0.5, 0.75, 1, 1, 1, 1]),
            np.array([1, 1, 3, 1, 1, 1, 1, 1, 1, 1]),
        ),
        100.0,
        1e-4,
    ),
    # Starting along +z: V_z / |t_z| is lowest at the start and convex there; interpolated
    # linearly over the first grid interval it let the z axis move at 10.13 mm/s.
    "along +z from the start": (
        NurbsCurve.from_arrays(
            4,
            np.array(
                [
                    [0, 0, 0],
                    [0, 0, 5.9191165],
                    [0, 6, 0],
                    [0, -21, 0],
                    [17, 23.28645134, 0],
                    [17, 23.28645134, 0],
                    [17, 23.28645134, 0],
                    [0, 0, 0],
                    [0, 0, 0],
                    [0, 0, 0],
                ]
            ),
            np.array([0, 0, 0, 0, 0, 0.25, 0.25, 0.375, 0.5, 0.5, 1, 1, 1, 1, 1]),
            np.array([0.875, 2, 3, 0.375, 2.5, 1, 1, 1, 1, 1]),
        ),
        100.0,
        1e-4,
    ),
    # Towards +x ever more closely, without a peak of |t_x|: V_x / |t_x| falls convexly
    # towards 10 over samples 4 % apart, and the x axis moved at 10.106 mm/s between them
    # (planner.envelope.TIGHT_CHANGE_OTHER).
    "towards +x without a peak": (
        NurbsCurve.from_arrays(
            3,
            np.array(
                [
                    [0, 0],
                    [-16.3482914, 12.49590683],
                    [-12.81328964, 0],
                    [-18.96088219, 0],
                    [0, 0],
                    [0, 0],
                    [0, 0],
                    [0, 0],
                ]
            ),
            np.array([0, 0, 0, 0, 0.125, 0.28925153, 0.5, 0.70146391, 1, 1, 1, 1]),
            np.array(
                [2.50471486, 1.1, 2.07355835, 0.5475488, 1.70321322, 0.3, 0.88403453, 1.31753092]
            ),
        ),
        100.0,
        1e-3,
    ),
}


@pytest.mark.parametrize("name", AXIS_FEED_CASES)
def test_curves_found_with_axis_feed_limits_keep_them(name):
    curve, vmax_mm_s, chord_error_mm = AXIS_FEED_CASES[name]
    assert fastest_axis_feed_mm_s(curve, vmax_mm_s, chord_error_mm) <= 10.0 * 1.001


def fastest_axis_feed_mm_s(curve: NurbsCurve, vmax_mm_s: float, chord_error_mm: float) -> float:
    """The fastest any axis of ``curve`` moves between setpoints, planned with the paper's A
    and J and a feed limit of 10 mm/s on each axis."""
    limits = Limits(
        vmax_mm_s=vmax_mm_s,
        amax_mm_s2=1000.0,
        jmax_mm_s3=20000.0,
        chord_error_mm=chord_error_mm,
        axis_vmax_mm_s=(10.0,) * curve.dimension,
    )
    block = plan_setpoints(Path(curve, limits, T), limits, T)
    return float(np.abs(np.diff(block.position_mm, axis=0)).max() / T)


def test_a_pin_on_a_flat_limit_is_reached_by_the_segment_before_it():
    # Up 1 mm along z, a corner, then on towards y under per-axis feed limits: the limit is
    # flat there (V / |t_y|), so a point pinned on it has no acceleration, and the scan gave
    # it its cap without checking that the ramp from the corner reaches it. The ramp took
    # 3.7 µm more than its segment: a short step on the setpoints, 5.2 J.
    curve = NurbsCurve.from_arrays(
        2,
        np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 1], [0, 0, 1], [0, 4, 0]]),
        np.array([0, 0, 0, 0.125, 0.25, 0.25, 0.5, 1, 1, 1]),
    )
    limits = Limits(
        vmax_mm_s=100.0,
        amax_mm_s2=1000.0,
        jmax_mm_s3=20000.0,
        chord_error_mm=1e-4,
        axis_vmax_mm_s=(11.0, 11.0, 11.0),
    )
    block = plan_setpoints(Path(curve, limits, T), limits, T)
    fig = sc.measure(curve, block.u, block.position_mm, T)
    assert fig.max_jerk_mm_s3 <= 20000.0 * 1.05 and fig.max_accel_mm_s2 <= 1000.0 * 1.02


def test_a_window_ending_just_before_a_tip_is_followed_by_a_prompt_motion():
    # 63.5 mm: it took 20.96 s, 22 mm of it at the tip's 1.12 mm/s; 1.27 s now.
    assert assert_every_limit_holds(*FOUND_CASES["a window ending just before a tip"]) < 2.0


def test_the_motion_leaves_a_stop_where_a_span_has_zero_length():
    # Degree 1, two equal control points: the curve stops at that point and turns. The
    # envelope used to lower the samples after the stop to their distance from it over a step
    # (a step reaching back across the stop), a limit that vanishes at the stop: the motion
    # crept on at 1e-11 mm/s and never left it.
    point = [28.548673629760742, -1.1754943508222875e-38, 19.638324737548828]
    curve = NurbsCurve.from_arrays(
        1,
        np.array(
            [
                [-21.11032485961914, 9.410981178283691, 0.0],
                [15.672968864440918, 1.8313266038894653, 27.853403091430664],
                [-2.220446049250313e-16, 0.0, 9.999999974752427e-07],
                point,
                point,
                [0.0, 0.0, 17.700315475463867],
            ]
        ),
        np.array(
            [
                0,
                0,
                0.1657242616007682,
                0.17551504928646183,
                0.3482083497902156,
                0.7898909236112747,
                1,
                1,
            ]
        ),
        np.array(
            [
                0.99,
                1.1615268449664282,
                0.7507484827096722,
                0.8438793338861184,
                1.8737976338980022,
                1.5,
            ]
        ),
    )
    assert_the_motion_ends_promptly(curve)


def test_a_row_past_the_end_by_round_off_is_at_the_end_and_a_replan_may_start_there():
    # Found by a longer run of the re-plans: the profile's penultimate row lay 2.4e-9 mm past
    # the curve's end; a re-plan from it (an override change in the last periods) was refused
    # with "start.s_mm ... must be within [0, length]".
    curve = NurbsCurve.from_arrays(
        3,
        np.array(
            [
                [-10.018742561340332, 27.76668357849121],
                [0, 30],
                [-28.343141555786133, 15.745646476745605],
                [4.883784770965576, 0],
            ]
        ),
        np.array([0, 0, 0, 0, 1, 1, 1, 1]),
        np.array([0.3, 0.3, 0.3, 0.3]),
    )
    limits = Limits(vmax_mm_s=100.0, amax_mm_s2=1000.0, jmax_mm_s3=20000.0, chord_error_mm=1e-4)
    path = Path(curve, limits, T)
    first = plan_setpoints(path, limits, T)
    assert first.s_mm.max() <= path.length_mm
    for row in range(len(first) - 4, len(first)):
        end = braking_end_from_rows(first.feed_mm_s[row:], first.accel_mm_s2[row:], T)
        replan = plan_setpoints(
            path,
            limits.with_feed_override(1.2),
            T,
            start=first.state(row),
            braking_end_mm_s=None if end is None else end.feed_mm_s,
        )
        assert np.array_equal(replan.position_mm[-1], curve.end_point)


def test_the_motion_reaches_an_end_that_turns_within_a_hair():
    # Degree 2, the last leg 1e-42 mm long: at the end the curve turns by 90 degrees, the
    # limit there is the singular floor, not a stop. The envelope lowered the samples before it
    # to their distance from it over a step, below the floor: a limit vanishing at the end,
    # which the motion approached for 73 s, or (with more samples there) for ever.
    curve = NurbsCurve.from_arrays(
        2,
        np.array([[1.48117248e-42, 1.48117248e-42], [28.5272999, 1.48117248e-42], [28.5272999, 0]]),
        np.array([0, 0, 0, 1, 1, 1]),
        np.array([0.3, 0.3, 0.3]),
    )
    assert_the_motion_ends_promptly(curve)


def assert_the_motion_ends_promptly(curve: NurbsCurve) -> None:
    """At 0.1 µm and 20 mm/s, the motion ends within 4x the time of a cruise over the path
    (counted as it streams: a motion that creeps fails here rather than run out of memory), and
    every limit holds."""
    limits = Limits(vmax_mm_s=20.0, amax_mm_s2=1000.0, jmax_mm_s3=20000.0, chord_error_mm=1e-4)
    path = Path(curve, limits, T)
    rows = 0
    for block in stream_setpoints(path, limits, T):
        rows += len(block)
        assert rows < 4 * path.length_mm / limits.vmax_mm_s / T
    assert_every_limit_holds(curve, 1e-4, 20.0)


def assert_every_limit_holds(
    curve: NurbsCurve, delta: float, vmax: float, amax: float = 1000.0, jmax: float = 20000.0
) -> float:
    """Plan ``curve`` and check every limit on its 4 ms setpoints (by default the paper's
    amax 1000 mm/s² and jmax 20000 mm/s³); returns the motion time, s."""
    limits = Limits(vmax_mm_s=vmax, amax_mm_s2=amax, jmax_mm_s3=jmax, chord_error_mm=delta)
    block = plan_setpoints(Path(curve, limits, T), limits, T)
    assert np.isfinite(block.position_mm).all() and np.isfinite(block.u).all()
    fig = sc.measure(curve, block.u, block.position_mm, T)
    assert fig.max_feed_mm_s <= vmax * 1.001
    assert fig.max_accel_mm_s2 <= amax * 1.02
    assert fig.max_jerk_mm_s3 <= jmax * 1.05
    assert fig.max_chord_error_mm <= delta * 1.01
    assert fig.end_error_mm <= 1e-6
    assert block.last and block.feed_mm_s[-1] == 0.0
    return fig.motion_time_s


def assert_a_replan_keeps_every_limit(
    curve: NurbsCurve, limits: Limits, where: float, braking: bool, ratio: float
) -> np.ndarray:
    """Plan ``curve``, re-plan it at ``ratio`` of its feed from the row a fraction ``where``
    into its rows (into its braking rows with ``braking``), and check every limit on the
    joined motion; returns the joined positions. With ``braking``, only inside a hypothesis
    test (a plan without braking rows is not an example)."""
    path = Path(curve, limits, T)
    first = plan_setpoints(path, limits, T)
    rows = np.arange(len(first))
    if braking:
        rows = np.flatnonzero(first.accel_mm_s2 < 0.0)
        assume(len(rows) > 0)
    row = int(rows[int(where * (len(rows) - 1))])
    replan = plan_setpoints(
        path,
        limits.with_feed_override(ratio),
        T,
        start=first.state(row),
        braking_end_mm_s=braking_end_from_rows(
            first.feed_mm_s[row:], first.accel_mm_s2[row:], T
        ).feed_mm_s,
    )
    assert_joined_motion_keeps_every_limit(curve, first, row, replan, limits)
    return np.vstack([first.position_mm[: row + 1], replan.position_mm])


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
