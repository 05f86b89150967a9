"""Jerk-limited speed changes between states with acceleration: (v0, a0) to (v1, a1).

Not in the paper (its S-curves start and end at zero acceleration, :mod:`planner.profiles.scurve`);
used where the look-ahead pins a point on the feed limit with the limit's own slope. The closed
forms are the standard third-order ones (Ruckig's velocity interface, Berscheid and Kröger,
RSS 2021), written here for one degree of freedom along the path.

- :func:`transition_phases`: the quickest change from (v0, a0) to (v1, a1), the acceleration a
  trapezoid (or triangle) in time: jerk +-J to a peak a_p, a hold at a_p = +-A when the peak is
  clipped, jerk -+J to a1. With dv = v1 - v0 and dv_lin = (a0 + a1) |a1 - a0| / (2J) (a0 to a1
  in one jerk phase): dv > dv_lin needs a peak above both ends, a_p = sqrt(J dv + (a0² + a1²)/2);
  dv < dv_lin a valley below both, a_p = -sqrt(-J dv + (a0² + a1²)/2). Its distance is the
  least any jerk-limited motion between the two states covers.
- :func:`segment_phases_between`: a motion between the two states over a given distance L: the
  quickest transition stretched either through a lower acceleration plateau a_m (an
  accelerating or decelerating run: a0 -> a_m, hold, a_m -> a1, the hold from dv) or through a
  speed plateau v_p at zero acceleration (transition to (v_p, 0), cruise, transition to
  (v1, a1)), whichever fits L; a one-dimensional bracketed search in a_m or v_p, each candidate
  in closed form.

Units: mm, s; speeds mm/s, A mm/s², J mm/s³. Pure functions on floats; thread-safe.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from planner.profiles import CACHE_SIZE, Phase

#: Bisection steps of the plateau searches.
PLATEAU_SEARCH_STEPS = 60
#: Relative distance tolerance of the plateau searches (1e-8 of a 10 mm segment is 0.1 nm).
PLATEAU_RTOL = 1e-8
#: Relative speed tolerance of the searches for a highest speed.
SPEED_RTOL = 1e-10
#: Points per bracket in each round of the acceleration-plateau search.
RUN_SECTIONS = 17


def transition_phases(
    v0: float, a0: float, v1: float, a1: float, A: float, J: float
) -> list[Phase]:
    """Constant-jerk phases of the quickest change from (v0, a0) to (v1, a1) (|a0|, |a1| <= A)."""
    return _phases(_transition_steps(v0, a0, v1, a1, A, J))


def _transition_steps(
    v0: float, a0: float, v1: float, a1: float, A: float, J: float
) -> list[tuple[float, float]]:
    """(duration, jerk) of the phases of :func:`transition_phases`."""
    dv = v1 - v0
    dv_lin = (a0 + a1) * abs(a1 - a0) / (2.0 * J)
    ends_sq = 0.5 * (a0 * a0 + a1 * a1)
    if dv >= dv_lin:
        a_p = math.sqrt(max(J * dv + ends_sq, 0.0))
        a_p = max(a_p, a0, a1)
        hold = 0.0
        if a_p > A:
            a_p = A
            hold = (dv - (2.0 * A * A - a0 * a0 - a1 * a1) / (2.0 * J)) / A
    else:
        a_p = -math.sqrt(max(-J * dv + ends_sq, 0.0))
        a_p = min(a_p, a0, a1)
        hold = 0.0
        if a_p < -A:
            a_p = -A
            hold = (dv - (a0 * a0 + a1 * a1 - 2.0 * A * A) / (2.0 * J)) / -A
    return _steps_through(a0, a_p, max(hold, 0.0), a1, J)


def _steps_through(
    a0: float, a_m: float, hold_s: float, a1: float, J: float
) -> list[tuple[float, float]]:
    """(duration, jerk) of a0 -> a_m (jerk +-J), hold a_m for hold_s, a_m -> a1 (jerk +-J).

    Plain tuples: the searches below try many candidates, and only the chosen one becomes
    :class:`Phase` s."""
    steps = []
    if a_m != a0:
        steps.append((abs(a_m - a0) / J, math.copysign(J, a_m - a0)))
    if hold_s > 0.0:
        steps.append((hold_s, 0.0))
    if a1 != a_m:
        steps.append((abs(a1 - a_m) / J, math.copysign(J, a1 - a_m)))
    return steps


def _phases(steps: list[tuple[float, float]]) -> list[Phase]:
    return [Phase(tau, j) for tau, j in steps]


def _advance_steps(
    v: float, a: float, steps: list[tuple[float, float]]
) -> tuple[float, float, float, float]:
    """(distance, end speed, end acceleration, duration) of ``steps`` from (v, a)."""
    s = t = 0.0
    for tau, j in steps:
        s += v * tau + a * tau * tau / 2.0 + j * tau**3 / 6.0
        v += a * tau + j * tau * tau / 2.0
        a += j * tau
        t += tau
    return s, v, a, t


@functools.lru_cache(maxsize=CACHE_SIZE)
def transition_distance_mm(v0: float, a0: float, v1: float, a1: float, A: float, J: float) -> float:
    """Distance of :func:`transition_phases`: the shortest any motion between the states needs."""
    return _advance_steps(v0, a0, _transition_steps(v0, a0, v1, a1, A, J))[0]


def settle_speed(v: float, a: float, J: float) -> float:
    """Speed reached when acceleration a is brought to 0 at once (jerk -sign(a) J)."""
    return v + a * abs(a) / (2.0 * J)


def segment_phases_between(
    v0: float, a0: float, v1: float, a1: float, L: float, v_cap: float, A: float, J: float
) -> list[Phase] | None:
    """The quickest phases found from (v0, a0) to (v1, a1) covering exactly L, with the speed
    plateau (if any) at most max(v_cap, v0, v1); None if no motion of these shapes fits L (L
    below the quickest transition's distance, which no motion can cover).
    """
    direct = _transition_steps(v0, a0, v1, a1, A, J)
    d_direct = _advance_steps(v0, a0, direct)[0]
    if d_direct * (1.0 - PLATEAU_RTOL) - 1e-12 > L:
        return None
    if d_direct * (1.0 + PLATEAU_RTOL) + 1e-12 >= L:
        return _phases(direct)
    plateau, v_p = _speed_plateau(v0, a0, v1, a1, L, v_cap, A, J)
    if plateau is not None and v_p >= max(v0, v1):
        return _phases(plateau)  # a peak above both ends: quicker than any run between them
    options = [p for p in (_run(v0, a0, v1, a1, L, A, J), plateau) if p is not None]
    if not options:
        return None
    return _phases(min(options, key=lambda steps: sum(tau for tau, _ in steps)))


#: Acceleration plateaus tried by the run search, as fractions of A (denser near 0, where the
#: hold and the distance grow without bound).
_RUN_GRID = np.concatenate(
    [-(np.linspace(1.0, 0.0, 33)[:-1] ** 3), np.linspace(0.0, 1.0, 33)[1:] ** 3]
)


def _run_motion(v0: float, a0: float, a_m, a1: float, dv: float, J: float):
    """Distance, duration and hold of a0 -> a_m, hold, a_m -> a1 changing the speed by dv,
    for a float or an array of a_m (operators and abs only; the hold negative or not finite
    where no such motion exists)."""
    t1 = abs(a_m - a0) / J
    t3 = abs(a1 - a_m) / J
    gain = 0.5 * (a0 + a_m) * t1 + 0.5 * (a_m + a1) * t3
    hold = (dv - gain) / a_m
    w1 = v0 + 0.5 * (a0 + a_m) * t1
    w2 = w1 + a_m * hold
    # A jerk phase of duration t from a to a' covers v t + a t²/2 + (a' - a) t²/6.
    d = (
        v0 * t1
        + a0 * t1**2 / 2.0
        + (a_m - a0) * t1**2 / 6.0
        + w1 * hold
        + a_m * hold**2 / 2.0
        + w2 * t3
        + a_m * t3**2 / 2.0
        + (a1 - a_m) * t3**2 / 6.0
    )
    return d, t1 + hold + t3, hold


def _run(
    v0: float, a0: float, v1: float, a1: float, L: float, A: float, J: float
) -> list[tuple[float, float]] | None:
    """a0 -> a_m (jerk +-J), hold a_m, a_m -> a1, covering L: the quickest a_m found.

    The hold follows from the speed change; the distance, in closed form, is scanned over a
    grid of a_m (vectorised), and each bracket of L solved by regula falsi (Illinois).
    """
    dv = v1 - v0
    grid = A * _RUN_GRID
    with np.errstate(divide="ignore", invalid="ignore"):
        d, _, hold = _run_motion(v0, a0, grid, a1, dv, J)
    excess = np.where((hold >= 0.0) & np.isfinite(hold), d - L, np.nan)
    brackets = np.flatnonzero(
        np.isfinite(excess[:-1]) & np.isfinite(excess[1:]) & (excess[:-1] * excess[1:] <= 0.0)
    )
    best: list[tuple[float, float]] | None = None
    best_t = math.inf
    for i in brackets.tolist():
        a_m = _regula_falsi(
            lambda x: _run_motion(v0, a0, x, a1, dv, J)[0] - L if x != 0.0 else math.inf,
            float(grid[i]),
            float(excess[i]),
            float(grid[i + 1]),
            float(excess[i + 1]),
            PLATEAU_RTOL * L,
        )
        d_m, t_m, hold_m = _run_motion(v0, a0, a_m, a1, dv, J)
        if hold_m >= 0.0 and abs(d_m - L) <= PLATEAU_RTOL * L and t_m < best_t:
            best, best_t = _steps_through(a0, a_m, hold_m, a1, J), t_m
    return best


def _regula_falsi(f, x0: float, f0: float, x1: float, f1: float, tol: float) -> float:
    """A root of f between x0 and x1 (f0 f1 <= 0) to |f| <= tol, by the Illinois method."""
    side = 0
    for _ in range(PLATEAU_SEARCH_STEPS):
        if abs(f0) <= tol:
            return x0
        if abs(f1) <= tol:
            return x1
        x = (x0 * f1 - x1 * f0) / (f1 - f0) if f1 != f0 else 0.5 * (x0 + x1)
        fx = f(x)
        if fx * f1 < 0.0:
            x0, f0 = x1, f1
            side = 0
        elif side == 1:
            f0 *= 0.5
        else:
            side = 1
        x1, f1 = x, fx
    return x1


def _speed_plateau(
    v0: float, a0: float, v1: float, a1: float, L: float, v_cap: float, A: float, J: float
) -> tuple[list[tuple[float, float]] | None, float]:
    """Transition to (v_p, 0), cruise, transition to (v1, a1); v_p the highest that fits.

    Returns the (duration, jerk) steps (None if even the lowest plateau is too long) and v_p."""

    def distance_mm(v_p: float) -> float:
        return transition_distance_mm(v0, a0, v_p, 0.0, A, J) + transition_distance_mm(
            v_p, 0.0, v1, a1, A, J
        )

    low = max(settle_speed(v0, a0, J), settle_speed(v1, -a1, J), 0.0)
    top = max(v_cap, low)
    d_top = distance_mm(top)
    if d_top <= L:
        v_p = top
    else:
        d_low = distance_mm(low)
        if d_low > L:
            return None, low
        v_p = _regula_falsi(
            lambda x: distance_mm(x) - L, low, d_low - L, top, d_top - L, PLATEAU_RTOL * L
        )
    up = _transition_steps(v0, a0, v_p, 0.0, A, J)
    down = _transition_steps(v_p, 0.0, v1, a1, A, J)
    rest_mm = L - distance_mm(v_p)
    cruise = [(rest_mm / v_p, 0.0)] if rest_mm > 0.0 and v_p > 0.0 else []
    return [*up, *cruise, *down], v_p


@functools.lru_cache(maxsize=CACHE_SIZE)
def highest_start_speed(
    v1: float, a1: float, L: float, v_cap: float, A: float, J: float
) -> float | None:
    """Highest v <= v_cap at zero acceleration from which (v1, a1) is reached within L, or None.

    The quickest transition's distance is least from the speed that one jerk phase joins to
    (v1, a1), and grows on either side of it.
    """
    return _highest_speed(
        lambda v: transition_distance_mm(v, 0.0, v1, a1, A, J) <= L,
        max(settle_speed(v1, -a1, J), 0.0),
        v_cap,
    )


@functools.lru_cache(maxsize=CACHE_SIZE)
def highest_end_speed(
    v0: float, a0: float, L: float, v_cap: float, A: float, J: float
) -> float | None:
    """Highest v <= v_cap reached at zero acceleration from (v0, a0) within L, or None."""
    return _highest_speed(
        lambda v: transition_distance_mm(v0, a0, v, 0.0, A, J) <= L,
        max(settle_speed(v0, a0, J), 0.0),
        v_cap,
    )


def _highest_speed(fits, nearest: float, v_cap: float) -> float | None:
    """The highest speed <= v_cap that ``fits``, the fitting set an interval around
    ``nearest`` (where a transition is shortest); None if nothing up to v_cap fits."""
    if fits(v_cap):
        return v_cap
    if nearest >= v_cap or not fits(nearest):
        return None
    return _bisect_speed(fits, nearest, v_cap)


def _bisect_speed(fits, low: float, high: float) -> float:
    """The highest speed in [low, high] that ``fits`` (true at low, false at high)."""
    for _ in range(PLATEAU_SEARCH_STEPS):
        mid = 0.5 * (low + high)
        if fits(mid):
            low = mid
        else:
            high = mid
        if high - low <= SPEED_RTOL * max(high, 1.0):
            break
    return low
