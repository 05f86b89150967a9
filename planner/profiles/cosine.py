"""Cosine (trigonometric) speed change for regions of frequent speed change, eqs. (5)-(13).

Source: Wang, Zhao, Lu, Liu, China Mechanical Engineering 23(3), 2012, 299-304, section 2.1:
- (5) f_a(tau) = ½(1 - cos(pi tau)), (13) f_d(tau) = ½(1 + cos(pi tau));
- (6) v(t) = v_i + (v_{i+1} - v_i) f_a(t / t_a); with v_{i+1} < v_i this is
  v_{i+1} + (v_i - v_{i+1}) f_d(t / t_a), eq. (13), so one formula serves both directions;
- (7), (8) a(t) = dv·pi/(2 t_a)·sin(pi t/t_a), j(t) = dv·pi²/(2 t_a²)·cos(pi t/t_a);
- (9), (10) peaks j_act = |dv|·pi²/(2 t_a²), a_act = |dv|·pi/(2 t_a);
- (11), (12) the distance L_i between the two points is kept: L_i = ½(v_i + v_{i+1}) t_a, so
  t_a = 2 L_i / (v_i + v_{i+1}).

Units: mm, s. Pure functions; thread-safe. The acceleration is zero at both ends, the jerk is
not (it steps by at most j_act at each end).
"""

from __future__ import annotations

import math

import numpy as np

#: Bisection steps for the highest end feed meeting the jerk limit.
JERK_BISECTION_STEPS = 60


def cosine_time_s(v_i: float, v_next: float, L: float) -> float:
    """Actual acceleration time t_a = 2 L / (v_i + v_{i+1}), eq. (12); inf when both are 0."""
    total = v_i + v_next
    return 2.0 * L / total if total > 0.0 else math.inf


def cosine_peaks(v_i: float, v_next: float, t_a: float) -> tuple[float, float]:
    """Peak (a_act, j_act) of the cosine change, eqs. (10) and (9)."""
    dv = abs(v_next - v_i)
    return dv * math.pi / (2.0 * t_a), dv * math.pi**2 / (2.0 * t_a**2)


def cosine_fits(v_i: float, v_next: float, L: float, A: float, J: float) -> bool:
    """Whether the cosine change over L keeps a_act <= A and j_act <= J."""
    t_a = cosine_time_s(v_i, v_next, L)
    if not math.isfinite(t_a):
        return False
    a_act, j_act = cosine_peaks(v_i, v_next, t_a)
    return a_act <= A and j_act <= J


def cosine_max_high_speed(v_low: float, L: float, A: float, J: float) -> float:
    """Highest v_high >= v_low for which the cosine change v_low <-> v_high over L fits A and J.

    With t_a from eq. (12), a_act <= A is (v_h - v_l)(v_h + v_l) <= 4 L A / pi, so
    v_h <= sqrt(v_l² + 4 L A / pi); j_act <= J is (v_h - v_l)(v_h + v_l)² <= 8 L² J / pi², which
    grows with v_h and is solved by bisection. This is how speeds are lowered where the cosine
    change would break the limits.
    """
    v_acc = math.sqrt(v_low * v_low + 4.0 * L * A / math.pi)
    bound = 8.0 * L * L * J / math.pi**2
    if (v_acc - v_low) * (v_acc + v_low) ** 2 <= bound:
        return v_acc
    lo, hi = v_low, v_acc
    for _ in range(JERK_BISECTION_STEPS):
        mid = 0.5 * (lo + hi)
        if (mid - v_low) * (mid + v_low) ** 2 <= bound:
            lo = mid
        else:
            hi = mid
    return lo


def cosine_state(
    v_i: float | np.ndarray, dv: float | np.ndarray, t_a: float | np.ndarray, tau: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Distance, feed, acceleration and jerk at time tau into the change, eqs. (6)-(8), (13).

    s(tau) = v_i tau + dv/2 (tau - t_a/pi sin(pi tau/t_a)), the integral of eq. (6).
    """
    phase = np.pi * tau / t_a
    sin, cos = np.sin(phase), np.cos(phase)
    s = v_i * tau + 0.5 * dv * (tau - t_a / np.pi * sin)
    v = v_i + 0.5 * dv * (1.0 - cos)  # eq. (6), eq. (13) when dv < 0
    a = dv * np.pi / (2.0 * t_a) * sin  # eq. (7)
    j = dv * np.pi**2 / (2.0 * t_a**2) * cos  # eq. (8)
    return s, v, a, j
