"""One look-ahead window: its sensitive points, their speeds, and the segments between them.

Source: section 2.2 of Wang, Zhao, Lu, Liu, China Mechanical Engineering 23(3), 2012, 299-304.
- Curvature-rising module (:func:`sensitive_points`): walking forward, a curvature maximum (a
  local minimum of the feed limit below vmax) is a velocity-sensitive point with its limited
  feed; curvature-falling module: a stretch between two such points whose limit never reaches
  vmax is a region of frequent speed change, flag F_v_plan = 1.
- Between sensitive points, jerk-limited S-curve segments (:mod:`planner.profiles.scurve`) or,
  where flagged and needed, the cosine profile of eqs. (5)-(13); zero acceleration at the points.
Beyond the paper (motion-planning.md §1, §9 row 6): a bidirectional scan with jerk-feasible
speed changes (:func:`passes`: backward, the highest speed from which each next point can still
be met; forward, the highest speed reachable).

Units: s in mm, feeds mm/s, A mm/s², J mm/s³, T s. Pure computation; one window per plan of a
stretch, not thread-safe.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from planner.profiles import Phase
from planner.profiles.cosine import cosine_time_s
from planner.profiles.scurve import (
    braking_distance_mm,
    cruise_speed,
    fitting_lower_speed,
    max_ramp_speed,
    min_ramp_speed,
    ramp_distance_mm,
    segment_phases,
)

#: Relative excess of a ramp over its distance still counted as fitting (round-off).
RAMP_FIT_RTOL = 1e-9
#: Points closer than this are not inserted, mm.
MIN_POINT_GAP_MM = 1e-7


@dataclass(frozen=True)
class PlanLimits:
    """The limits one plan uses: feed cap (vmax), tangential A and J, period T."""

    vmax_mm_s: float
    A: float
    J: float
    T: float


@dataclass(frozen=True)
class SegmentPlan:
    """A released stretch of motion: phases from (s, v, a) at time t, ending at s_end, v_end."""

    phases: tuple[Phase, ...]
    s_end_mm: float
    v_end_mm_s: float


class Window:
    """Sensitive points of one look-ahead window and the refinement state of its segments."""

    def __init__(self, s: list[float], cap: list[float], fv_plan: list[bool]) -> None:
        self.s = s
        self.cap = cap
        self.fv_plan = fv_plan  # per segment: region of frequent speed change (F_v_plan = 1)
        self.peak_cap = [math.inf] * (len(s) - 1)
        self.cosine = [0] * (len(s) - 1)  # 0: S-curve, 1: cosine, 2: cosine rejected
        self.braking = False  # the first segment brakes from the start state (brake_first)
        # Planned phases and top feed of each segment shape met so far (see key).
        self.plans: dict[tuple, tuple[tuple[Phase, ...], float]] = {}

    def key(self, k: int, v: list[float]) -> tuple:
        """What segment k's plan depends on: its ends, end speeds, peak cap and profile kind."""
        return (self.s[k], self.s[k + 1], v[k], v[k + 1], self.peak_cap[k], self.cosine[k])

    def insert(self, k: int, s_new: float, cap_new: float) -> None:
        """Split segment k at s_new with a new sensitive point."""
        self.s.insert(k + 1, s_new)
        self.cap.insert(k + 1, cap_new)
        self.fv_plan.insert(k + 1, self.fv_plan[k])
        self.peak_cap[k : k + 1] = [math.inf, math.inf]
        self.cosine[k : k + 1] = [0, 0]

    def merge_first(self, m: int, peak_cap: float) -> None:
        """Remove the points between the start and point m: one segment, held under peak_cap."""
        del self.s[1:m], self.cap[1:m], self.fv_plan[1:m], self.peak_cap[1:m], self.cosine[1:m]
        self.peak_cap[0] = peak_cap
        self.cosine[0] = 2
        self.braking = True


def passes(s: list[float], cap: list[float], v_start: float, lim: PlanLimits) -> list[float]:
    """Bidirectional scan: backward (can still meet the next point), then forward (reachable)."""
    n = len(s)
    back = list(cap)
    for k in range(n - 2, 0, -1):
        back[k] = min(cap[k], max_ramp_speed(back[k + 1], s[k + 1] - s[k], lim.A, lim.J))
    v = [v_start] + [0.0] * (n - 1)
    for k in range(1, n):
        L = s[k] - s[k - 1]
        v[k] = min(back[k], max_ramp_speed(v[k - 1], L, lim.A, lim.J))
        fits = L * (1.0 + RAMP_FIT_RTOL)
        if v[k] < v[k - 1] and ramp_distance_mm(v[k - 1], v[k], lim.A, lim.J) > fits:
            if braking_distance_mm(v[k - 1], lim.A, lim.J) <= fits:
                # Stopping fits where slowing to v[k] does not: slow down further instead.
                v[k] = fitting_lower_speed(v[k - 1], v[k], L, lim.A, lim.J)
            else:
                # Only a start state faster than the constraints allow gets here: brake hardest.
                v[k] = max(v[k], min_ramp_speed(v[k - 1], L, lim.A, lim.J))
    return v


def segment_plan(
    w: Window, k: int, v: list[float], lim: PlanLimits
) -> tuple[tuple[Phase, ...], float]:
    """Phases of segment k and its highest planned feed (computed once per window and shape)."""
    key = w.key(k, v)
    if key not in w.plans:
        v0, v1, L = v[k], v[k + 1], w.s[k + 1] - w.s[k]
        if w.cosine[k] == 1:
            t_a = cosine_time_s(v0, v1, L)  # eq. (12)
            w.plans[key] = (Phase(t_a, cosine_dv_mm_s=v1 - v0),), max(v0, v1)
        else:
            vp = cruise_speed(v0, v1, L, min(lim.vmax_mm_s, w.peak_cap[k]), lim.A, lim.J)
            w.plans[key] = tuple(segment_phases(v0, vp, v1, L, lim.A, lim.J)), max(v0, vp, v1)
    return w.plans[key]


def segment_time_s(w: Window, k: int, v: list[float], lim: PlanLimits) -> float:
    """Duration of segment k as planned."""
    return sum(phase.duration_s for phase in segment_plan(w, k, v, lim)[0])


def sensitive_points(
    s_env: np.ndarray, v_env: np.ndarray, s0: float, s_end: float, vcap: float
) -> tuple[list[float], list[float], list[bool]]:
    """Curvature-rising module: local minima of the feed limit below vcap in (s0, s_end).

    Returns the points' s and caps, and per stretch between them the curvature-falling flag
    F_v_plan (the limit stays below vcap between two maxima of curvature).
    """
    inside = (s_env > s0 + MIN_POINT_GAP_MM) & (s_env < s_end - MIN_POINT_GAP_MM)
    v = v_env
    prev = np.concatenate([[np.inf], v[:-1]])
    nxt = np.concatenate([v[1:], [np.inf]])
    is_min = (v <= prev) & (v <= nxt) & ~((v == prev) & (v == nxt)) & (v < vcap) & inside
    idx = np.flatnonzero(is_min)
    s = [s0, *s_env[idx].tolist()]
    cap = [0.0, *np.minimum(v[idx], vcap).tolist()]
    bounds = np.searchsorted(s_env, s)
    fv = []
    for a, b in itertools.pairwise(bounds):
        fv.append(bool(b - a > 1 and v[a:b].max() < vcap))
    return s, cap, fv
