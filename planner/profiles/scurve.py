"""Jerk-limited (7-phase S-curve) speed changes along the path, in closed form.

Source: the S-curve acceleration and deceleration of the paper's section 2.1-2.2 (Wang, Zhao, Lu,
Liu, China Mechanical Engineering 23(3), 2012, 299-304); the paper gives no formulas for it, the
closed forms below are the standard ones (Ruckig, LinuxCNC ``sp_scurve.c``).

A *ramp* changes the feed from v0 to v1 with zero acceleration at both ends, jerk +-J and
acceleration at most A. With dv = |v1 - v0|:
- dv >= A²/J (constant-acceleration phase reached): time t = dv/A + A/J;
- dv < A²/J: t = 2 sqrt(dv/J).
The profile is point-symmetric, so its distance is the mean speed times its time:
d = (v0 + v1)/2 · t. A *segment* between two sensitive points is ramp(v0 -> vp), cruise at vp,
ramp(vp -> v1). Braking from vmax = 100 mm/s with A = 1000 mm/s², J = 20000 mm/s³ takes 0.150 s
and 7.5 mm (the look-ahead distance of section 2.2).

Units: mm, s; speeds mm/s, A mm/s², J mm/s³. Pure functions on floats; thread-safe.

Not modelled: non-zero acceleration at the ends of a ramp (a start state with acceleration is
first brought to zero acceleration by :func:`settle_phases`).
"""

from __future__ import annotations

import math

from planner.profiles import Phase

#: Bisection steps for the cruise speed of a segment (2^-60 of the speed bracket).
CRUISE_BISECTION_STEPS = 45


def ramp_time_s(dv: float, A: float, J: float) -> float:
    """Duration of a ramp changing the feed by |dv| (zero acceleration at both ends)."""
    dv = abs(dv)
    if dv >= A * A / J:
        return dv / A + A / J
    return 2.0 * math.sqrt(dv / J)


def ramp_distance_mm(v0: float, v1: float, A: float, J: float) -> float:
    """Distance covered by the ramp v0 -> v1: d = (v0 + v1)/2 · t (point-symmetric profile)."""
    return 0.5 * (v0 + v1) * ramp_time_s(v1 - v0, A, J)


def braking_distance_mm(v: float, A: float, J: float) -> float:
    """Distance of the jerk-limited stop from feed v at zero acceleration (7.5 mm at vmax)."""
    return ramp_distance_mm(v, 0.0, A, J)


def max_ramp_speed(v_end: float, L: float, A: float, J: float) -> float:
    """Largest v >= v_end whose ramp to (or from) v_end fits in distance L, in closed form.

    With dv = v - v_end: if dv < A²/J, x = sqrt(dv) solves x³ + 2 v_end x - L sqrt(J) = 0
    (one real root, hyperbolic form of Cardano's formula); otherwise dv solves
    dv² + (2 v_end + A²/J) dv + 2A (v_end A/J - L) = 0.
    """
    if L <= 0.0:
        return v_end
    p = 2.0 * v_end
    q = -L * math.sqrt(J)
    if p > 0.0:
        r = math.sqrt(p / 3.0)
        x = -2.0 * r * math.sinh(math.asinh(1.5 * q / (p * r)) / 3.0)
    else:
        x = (-q) ** (1.0 / 3.0)
    dv = x * x
    if dv >= A * A / J:
        b = 2.0 * v_end + A * A / J
        c = 2.0 * A * (v_end * A / J - L)
        dv = -2.0 * c / (b + math.sqrt(b * b - 4.0 * c)) if c < 0.0 else 0.0
    return v_end + dv


def min_ramp_speed(v_start: float, L: float, A: float, J: float) -> float:
    """Lowest feed a ramp down from v_start reaches within distance L (0 if it can stop).

    Used when a start state is too fast for a constraint ahead: the plan then brakes as hard as
    the limits allow instead of meeting the constraint.
    """
    if ramp_distance_mm(v_start, 0.0, A, J) <= L:
        return 0.0
    lo, hi = 0.0, v_start  # ramp_distance(v_start, lo) > L >= ramp_distance(v_start, hi)
    for _ in range(CRUISE_BISECTION_STEPS):
        mid = 0.5 * (lo + hi)
        if ramp_distance_mm(v_start, mid, A, J) > L:
            lo = mid
        else:
            hi = mid
    return hi


def segment_distance_mm(v0: float, vp: float, v1: float, A: float, J: float) -> float:
    """Distance of ramp(v0 -> vp) followed by ramp(vp -> v1), without cruise."""
    return ramp_distance_mm(v0, vp, A, J) + ramp_distance_mm(vp, v1, A, J)


def cruise_speed(v0: float, v1: float, L: float, v_cap: float, A: float, J: float) -> float:
    """Cruise feed vp of a segment v0 -> vp -> v1 of length L: the highest feasible vp <= v_cap.

    Usually v_cap >= max(v0, v1) and vp is the peak between two sensitive points. A lower cap
    gives a cruise at or below the faster end: with min(v0, v1) <= v_cap the segment cruises at
    the lower speed and changes speed next to the faster end (the shape that stays under a feed
    limit rising towards that end); a start faster than v_cap (a lowered feed override) first
    brakes down to it. The distance is monotonic in vp on each side of the bracket, so a
    bisection finds vp; the caller must have ensured ramp_distance(v0, v1) <= L.
    """
    top, bottom = max(v0, v1), min(v0, v1)
    if v_cap >= top:
        if segment_distance_mm(v0, v_cap, v1, A, J) <= L:
            return v_cap
        feasible, infeasible = top, v_cap
    else:
        if segment_distance_mm(v0, v_cap, v1, A, J) <= L:
            return v_cap
        feasible, infeasible = (top if v_cap > top else bottom), v_cap
    if segment_distance_mm(v0, feasible, v1, A, J) > L:
        return feasible
    for _ in range(CRUISE_BISECTION_STEPS):
        mid = 0.5 * (feasible + infeasible)
        if segment_distance_mm(v0, mid, v1, A, J) <= L:
            feasible = mid
        else:
            infeasible = mid
    return feasible


def ramp_phases(v0: float, v1: float, A: float, J: float) -> list[Phase]:
    """Constant-jerk phases of the ramp v0 -> v1 (2 phases, or 3 with constant acceleration)."""
    dv = v1 - v0
    if dv == 0.0:
        return []
    sign = 1.0 if dv > 0.0 else -1.0
    dv = abs(dv)
    if dv >= A * A / J:
        return [
            Phase(A / J, sign * J),
            Phase(dv / A - A / J, 0.0),
            Phase(A / J, -sign * J),
        ]
    t_j = math.sqrt(dv / J)
    return [Phase(t_j, sign * J), Phase(t_j, -sign * J)]


def segment_phases(v0: float, vp: float, v1: float, L: float, A: float, J: float) -> list[Phase]:
    """Phases of ramp(v0 -> vp), cruise at vp over the rest of L, ramp(vp -> v1)."""
    cruise_mm = L - segment_distance_mm(v0, vp, v1, A, J)
    phases = ramp_phases(v0, vp, A, J)
    if cruise_mm > 0.0 and vp > 0.0:
        phases.append(Phase(cruise_mm / vp, 0.0))
    phases.extend(ramp_phases(vp, v1, A, J))
    return phases


def settle_phases(a0: float, J: float) -> list[Phase]:
    """The phase bringing acceleration a0 to zero at jerk -sign(a0)·J."""
    if a0 == 0.0:
        return []
    return [Phase(abs(a0) / J, -math.copysign(J, a0))]


def settled_speed(v0: float, a0: float, J: float) -> float:
    """Feed once :func:`settle_phases` has brought a0 to zero: v0 + a0|a0| / (2J)."""
    return max(0.0, v0 + a0 * abs(a0) / (2.0 * J))
