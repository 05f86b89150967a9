"""S-curve closed forms and the cosine profile of eqs. (5)-(13)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from planner.profiles import Phase, PhaseTrain
from planner.profiles.cosine import (
    cosine_fits,
    cosine_max_high_speed,
    cosine_peaks,
    cosine_state,
    cosine_time_s,
)
from planner.profiles.scurve import (
    braking_distance_mm,
    cruise_speed,
    fitting_lower_speed,
    max_ramp_speed,
    min_ramp_speed,
    ramp_distance_mm,
    ramp_phases,
    ramp_time_s,
    segment_distance_mm,
    segment_phases,
)

A, J = 1000.0, 20000.0


def test_braking_from_vmax_is_the_papers_lookahead_distance():
    assert ramp_time_s(100.0, A, J) == pytest.approx(0.150)
    assert braking_distance_mm(100.0, A, J) == pytest.approx(7.5)


def test_short_ramp_without_constant_acceleration():
    dv = 0.5 * A * A / J
    assert ramp_time_s(dv, A, J) == pytest.approx(2.0 * math.sqrt(dv / J))
    assert len(ramp_phases(0.0, dv, A, J)) == 2


@pytest.mark.parametrize("v_end", [0.0, 3.0, 20.0, 80.0])
@pytest.mark.parametrize("L", [1e-4, 0.05, 1.0, 7.5, 40.0])
def test_max_ramp_speed_inverts_the_ramp_distance(v_end, L):
    dv = max_ramp_speed(v_end, L, A, J) - v_end
    # The distance from dv itself: v_end + dv may round away the low digits of a tiny dv.
    assert (v_end + 0.5 * dv) * ramp_time_s(dv, A, J) == pytest.approx(L, rel=1e-6)


@pytest.mark.parametrize(("v0", "v1", "L"), [(0, 0, 20), (10, 60, 4.0), (100, 0, 9), (30, 30, 0.5)])
def test_segment_fills_its_length_and_meets_its_end_speeds(v0, v1, L):
    vp = cruise_speed(v0, v1, L, 100.0, A, J)
    assert max(v0, v1) <= vp <= 100.0
    assert segment_distance_mm(v0, vp, v1, A, J) <= L * (1 + 1e-12)
    train = PhaseTrain(0.0, 0.0, v0, 0.0)
    train.extend(segment_phases(v0, vp, v1, L, A, J))
    assert train.s_mm == pytest.approx(L, rel=1e-9, abs=1e-12)
    assert train.v_mm_s == pytest.approx(v1, abs=1e-9)
    assert train.a_mm_s2 == pytest.approx(0.0, abs=1e-9)
    t = np.linspace(0.0, train.t_s, 2001)
    _, v, a, j = train.sample(t)
    assert v.max() <= vp + 1e-9
    assert np.abs(a).max() <= A * (1 + 1e-12)
    assert np.abs(j).max() <= J


@pytest.mark.parametrize("v_start", [12.77, 40.0, 90.0])
def test_slowing_down_can_take_longer_than_stopping(v_start):
    # The distance of a ramp down peaks at an intermediate end feed: between stopping and that
    # peak there are end feeds that do not fit where a stop does.
    peak = max(np.linspace(0.0, v_start, 401), key=lambda x: ramp_distance_mm(v_start, x, A, J))
    stop_mm = braking_distance_mm(v_start, A, J)
    assert 0.0 < peak < v_start and ramp_distance_mm(v_start, peak, A, J) > stop_mm
    L = 0.5 * (stop_mm + ramp_distance_mm(v_start, peak, A, J))
    x = fitting_lower_speed(v_start, peak, L, A, J)
    assert 0.0 < x < peak
    assert ramp_distance_mm(v_start, x, A, J) == pytest.approx(L, rel=1e-9)
    assert ramp_distance_mm(v_start, x, A, J) <= L
    # Only what is on the far side of the peak fits as the least braking, where a stop does not.
    assert min_ramp_speed(v_start, 0.9 * stop_mm, A, J) > peak


def test_cruise_speed_brakes_a_start_above_the_cap():
    vp = cruise_speed(120.0, 0.0, 50.0, 100.0, A, J)
    assert vp == pytest.approx(100.0)


def test_cosine_equations():
    v_i, v_next, L = 20.0, 60.0, 3.0
    t_a = cosine_time_s(v_i, v_next, L)
    assert t_a == pytest.approx(2 * L / (v_i + v_next))  # eq. (12)
    a_act, j_act = cosine_peaks(v_i, v_next, t_a)
    assert a_act == pytest.approx((v_next - v_i) * math.pi / (2 * t_a))  # eq. (10)
    assert j_act == pytest.approx((v_next - v_i) * math.pi**2 / (2 * t_a**2))  # eq. (9)
    tau = np.linspace(0.0, t_a, 1001)
    s, v, a, j = cosine_state(v_i, v_next - v_i, t_a, tau)
    assert s[-1] == pytest.approx(L)  # eq. (11)
    assert v[0] == pytest.approx(v_i) and v[-1] == pytest.approx(v_next)
    assert np.abs(a).max() == pytest.approx(a_act, rel=1e-5)
    assert np.abs(j).max() == pytest.approx(j_act)
    # eq. (13): deceleration is the same formula with a negative change.
    _, v_dec, _, _ = cosine_state(v_next, v_i - v_next, t_a, tau)
    assert np.allclose(v_dec, v_i + (v_next - v_i) * 0.5 * (1 + np.cos(np.pi * tau / t_a)))


def test_cosine_speeds_are_lowered_to_meet_the_limits():
    L = 0.5
    v_high = cosine_max_high_speed(10.0, L, A, J)
    assert cosine_fits(10.0, v_high, L, A, J)
    assert not cosine_fits(10.0, v_high * 1.01, L, A, J)


def test_phase_train_mixes_constant_jerk_and_cosine():
    train = PhaseTrain(0.0, 0.0, 10.0, 0.0)
    train.extend([Phase(0.1, cosine_dv_mm_s=20.0), Phase(0.05, 0.0)])
    assert train.v_mm_s == pytest.approx(30.0)
    assert train.s_mm == pytest.approx(20.0 * 0.1 + 30.0 * 0.05)
