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

Not modelled here: non-zero acceleration at the ends of a ramp (a start state with acceleration
is first brought to zero acceleration by :func:`settle_phases`; changes between states with
acceleration are :mod:`planner.profiles.transition`).
"""

from __future__ import annotations

import functools
import math

from planner.profiles import CACHE_SIZE, Phase

#: Iterations of the bracketed Newton search for a speed whose ramps fit a distance.
SPEED_SEARCH_STEPS = 100
#: Relative distance tolerance at which such a speed is accepted.
SPEED_SEARCH_RTOL = 1e-12


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


@functools.lru_cache(maxsize=CACHE_SIZE)
def min_ramp_speed(v_start: float, L: float, A: float, J: float) -> float:
    """Lowest feed a ramp down from v_start reaches within distance L (0 if it can stop).

    Used when a start state is too fast for a constraint ahead: the plan then brakes as hard as
    the limits allow instead of meeting the constraint.
    """
    if ramp_distance_mm(v_start, 0.0, A, J) <= L:
        return 0.0
    # ramp_distance(v_start, v_start) = 0 <= L < ramp_distance(v_start, 0)
    return _fitting_speed((v_start,), L, v_start, 0.0, A, J)


@functools.lru_cache(maxsize=CACHE_SIZE)
def fitting_lower_speed(v_start: float, v_end: float, L: float, A: float, J: float) -> float:
    """Highest feed <= v_end that a ramp down from v_start reaches within distance L, when
    stopping fits in L but slowing to v_end does not.

    That happens: the distance of a ramp down from v_start is largest for an end feed between
    0 and v_start (v_start/3, or A²/2J with constant deceleration), because ending higher keeps
    the speed up for longer than the shorter ramp saves.
    """
    # ramp_distance(v_start, 0) <= L < ramp_distance(v_start, v_end), one crossing between.
    return _fitting_speed((v_start,), L, 0.0, v_end, A, J)


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
    bracketing search finds vp; the caller must have ensured ramp_distance(v0, v1) <= L.
    """
    top, bottom = max(v0, v1), min(v0, v1)
    if segment_distance_mm(v0, v_cap, v1, A, J) <= L:
        return v_cap
    feasible = top if v_cap >= top else bottom
    if segment_distance_mm(v0, feasible, v1, A, J) > L:
        return feasible
    return _fitting_speed((v0, v1), L, feasible, v_cap, A, J)


def _fitting_speed(
    ends: tuple[float, ...], L: float, feasible: float, infeasible: float, A: float, J: float
) -> float:
    """The speed x between ``feasible`` and ``infeasible`` where the ramps from each speed in
    ``ends`` to x cover exactly L together, returned on the feasible side (total distance in
    [L - 1e-12 L, L]); the total must be <= L at ``feasible``, > L at ``infeasible`` and
    monotonic between.

    Newton steps in y = sqrt(|x - feasible|), kept inside the bracket (bisection otherwise): a
    ramp's distance grows like sqrt(dv) next to the feasible end, a vertical slope in x, but is
    smooth in y. Started at y = 0, the iterates converge monotonically after the first step
    (from above where the distance is convex in y, from below where it is concave).
    """
    sign = 1.0 if infeasible > feasible else -1.0
    low, high = 0.0, math.sqrt(abs(infeasible - feasible))
    best, y, previous = feasible, 0.0, math.nan
    for _ in range(SPEED_SEARCH_STEPS):
        x = feasible + sign * y * y
        excess = sum(ramp_distance_mm(v, x, A, J) for v in ends) - L
        if excess <= 0.0:
            low, best = y, x
            if excess >= -SPEED_SEARCH_RTOL * L:
                break
        elif excess <= SPEED_SEARCH_RTOL * L or x == previous:
            # On the root to within round-off of L or of x: step back towards the feasible end
            # by doubling ulps until the distance holds.
            back = math.ulp(x)
            while abs(back) < abs(x - feasible):
                if sum(ramp_distance_mm(v, x - sign * back, A, J) for v in ends) <= L:
                    return x - sign * back
                back *= 2.0
            return best
        else:
            high = y
        if (high * high - low * low) <= 4.0 * math.ulp(x):  # x cannot be resolved further
            break
        slope = sum(_ramp_growth(v, x, y, sign, A, J) for v in ends)
        # Aim half a tolerance short of L: iterates coming from the infeasible side then cross
        # into the accepted band instead of creeping towards L from above.
        aim = excess + 0.5 * SPEED_SEARCH_RTOL * L
        step = y - aim / slope if slope > 0.0 and math.isfinite(slope) else math.nan
        y = step if low < step < high else 0.5 * (low + high)
        previous = x
    return best


def _ramp_growth(v_fixed: float, x: float, y: float, sign: float, A: float, J: float) -> float:
    """d/dy of ramp_distance_mm(v_fixed, x) for x = feasible + sign y² (see _fitting_speed).

    d = (v_fixed + x)/2 t(dv) with dv = |x - v_fixed|, so
    dd/dy = sign y t + (v_fixed + x) y t'(dv) sign sign(x - v_fixed), where y t'(dv) is y/A at
    constant acceleration and y / sqrt(J dv) otherwise (1/sqrt(J) where dv = y² -> 0).
    """
    dv = abs(x - v_fixed)
    if dv >= A * A / J:
        y_dt = y / A
    elif dv > 0.0:
        y_dt = y / math.sqrt(J * dv)
    else:
        y_dt = 1.0 / math.sqrt(J) if y == 0.0 else math.inf
    direction = 1.0 if x >= v_fixed else -1.0
    return sign * y * ramp_time_s(dv, A, J) + (v_fixed + x) * y_dt * sign * direction


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
