"""Feed limits: eqs. (3)-(4), normal acceleration and per-axis limits."""

from __future__ import annotations

import math

import numpy as np
import pytest

from planner.feed import (
    CHORD_JERK_FRACTION,
    adaptive_feed,
    chord_deficit_change_feed,
    chord_deficit_feed,
    chord_error_feed,
    curvature_jump_feed,
    geometric_feed_limits,
    normal_accel_feed,
    normal_cosine,
    tangential_accel_limit,
)
from planner.types import Limits

T = 0.004


def test_chord_error_feed_is_eq_3():
    rho, delta = 10.5, 1e-3
    v = chord_error_feed(np.array([1 / rho]), delta, T)[0]
    assert v == pytest.approx(2 / T * math.sqrt(rho**2 - (rho - delta) ** 2))
    # The step V T has sagitta delta on the circle of radius rho.
    half = v * T / 2
    assert rho - math.sqrt(rho**2 - half**2) == pytest.approx(delta)


def test_full_feed_needs_20_mm_radius_at_1_micron():
    assert chord_error_feed(np.array([1 / 20.0]), 1e-3, T)[0] == pytest.approx(100.0, rel=1e-4)


def test_corner_and_straight_line():
    v = chord_error_feed(np.array([math.inf, 0.0]), 1e-3, T)
    assert v[0] == 0.0 and v[1] == math.inf
    assert adaptive_feed(np.array([0.0]), 100.0, 1e-3, T)[0] == 100.0  # eq. (4)


def test_chord_deficit_change_lowers_the_limit_only_where_the_curvature_changes_faster():
    # A tip kappa(s) = 1 / (1 + s²): chord_deficit_feed takes (kappa²)'' = 4 kappa⁴, exact at
    # the peak; on the flanks, |s| > 0.63, |(kappa²)''| = |20 s² - 4| kappa⁴ is larger, and the
    # limit of the deficit's change from step to step binds there. A circle keeps its limit.
    limits = Limits(100.0, 1000.0, 20000.0, 1e-3)
    s = np.linspace(-5.0, 5.0, 20001)
    kappa = 1.0 / (1.0 + s * s)
    v = chord_deficit_feed(kappa, limits.jmax_mm_s3, T)
    lowered = chord_deficit_change_feed(s, kappa, v, 200.0, limits, T)
    assert np.array_equal(lowered[np.abs(s) < 0.6], v[np.abs(s) < 0.6])
    assert np.all(lowered <= v)
    assert lowered[np.argmin(np.abs(s - 1.5))] < 0.8 * v[np.argmin(np.abs(s - 1.5))]
    arc = np.linspace(0.0, 20.0, 2001)
    circle = np.full(arc.size, 0.5)
    v_circle = chord_deficit_feed(circle, limits.jmax_mm_s3, T)
    assert np.array_equal(
        chord_deficit_change_feed(arc, circle, v_circle, 200.0, limits, T), v_circle
    )


def test_no_curvature_jump_leaves_the_feed_unlimited():
    # inf, not the largest float: interpolating from that to a neighbour overflows to -inf.
    limits = Limits(100.0, 1000.0, 20000.0, 1e-3)
    feed = curvature_jump_feed(np.array([0.0, 0.5]), np.array([0.0, 0.5]), limits, T)
    assert np.all(feed == math.inf)
    assert curvature_jump_feed(np.array([0.0]), np.array([1.0]), limits, T)[0] == pytest.approx(
        (24 * CHORD_JERK_FRACTION * 20000.0) ** (1 / 3)
    )


def test_an_s_bend_at_a_knot_limits_the_feed_without_a_jump_of_the_curvature():
    # Radius 2 mm either side, normals opposite (a planar S): the chord deficit of a step across
    # the knot is a quarter of its neighbours', so the deficit still changes within a step.
    limits = Limits(100.0, 1000.0, 20000.0, 1e-3)
    kappa = np.array([0.5])
    same_side = curvature_jump_feed(kappa, kappa, limits, T, np.array([1.0]))
    s_bend = curvature_jump_feed(kappa, kappa, limits, T, np.array([-1.0]))
    assert same_side[0] == math.inf
    assert s_bend[0] == pytest.approx((24 * CHORD_JERK_FRACTION * 20000.0 / 0.375) ** (1 / 3))
    # A planar S from the derivatives: the normals of y = x² and y = -x² at the origin.
    tangent, up, down = np.array([[1.0, 0.0]]), np.array([[0.0, 2.0]]), np.array([[0.0, -2.0]])
    assert normal_cosine(tangent, up, tangent, down)[0] == pytest.approx(-1.0)
    assert normal_cosine(tangent, up, tangent, np.zeros((1, 2)))[0] == 1.0  # a straight side


def test_normal_acceleration_limit():
    assert normal_accel_feed(np.array([1 / 10.5]), 1000.0)[0] == pytest.approx(math.sqrt(10500.0))


def test_optional_limits_are_off_by_default_and_apply_when_set():
    d1 = np.array([[3.0, 4.0]])
    d2 = np.array([[-4.0, 3.0]])  # circle of radius 5 at this point
    paper = Limits(100.0, 1000.0, 20000.0, 1e-3)
    kappa, v_chord, v_other = geometric_feed_limits(d1, d2, paper, T)
    v = np.minimum(v_chord, v_other)
    assert kappa[0] == pytest.approx(1 / 5)
    assert v[0] == pytest.approx(chord_error_feed(kappa, 1e-3, T)[0])
    strict = Limits(
        100.0,
        1000.0,
        20000.0,
        1e-3,
        normal_accel_mm_s2=500.0,
        axis_vmax_mm_s=(10.0, 50.0),
        axis_amax_mm_s2=(800.0, 800.0),
    )
    _, v2_chord, v2_other = geometric_feed_limits(d1, d2, strict, T)
    v2 = np.minimum(v2_chord, v2_other)
    tangent = np.array([0.6, 0.8])
    expected = min(v[0], math.sqrt(500.0 * 5), 10.0 / tangent[0], math.sqrt(400.0 / (0.2 * 0.8)))
    assert v2[0] == pytest.approx(expected)
    assert tangential_accel_limit(strict) == 400.0
    assert tangential_accel_limit(paper) == 1000.0


def test_limits_validation_names_the_field():
    with pytest.raises(ValueError, match="jmax_mm_s3"):
        Limits(100.0, 1000.0, -1.0, 1e-3)
    with pytest.raises(ValueError, match=r"axis_vmax_mm_s\[1\]"):
        Limits(100.0, 1000.0, 20000.0, 1e-3, axis_vmax_mm_s=(1.0, math.nan))
    lim = Limits(100.0, 1000.0, 20000.0, 1e-3).with_feed_override(0.5)
    assert (lim.vmax_mm_s, lim.amax_mm_s2, lim.jmax_mm_s3) == (50.0, 1000.0, 20000.0)
