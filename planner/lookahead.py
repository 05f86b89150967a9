"""Look-ahead feed planning along the arc length: sensitive points, S-curve and cosine segments.

Source: section 2.2 of Wang, Zhao, Lu, Liu, China Mechanical Engineering 23(3), 2012, 299-304.
- Pre-interpolation: the feed limit of eq. (4) (and the optional limits of :mod:`planner.feed`)
  is sampled on a grid of every knot span (:class:`FeedEnvelope`), the curvature maxima refined,
  in place of the paper's step-by-step pre-interpolation at vmax.
- Curvature-rising module: walking forward, a curvature maximum (a local minimum of the feed
  limit below vmax) is a velocity-sensitive point u_end with its limited feed v_end.
- Curvature-falling module: leaving a sensitive point, if a new curvature rise comes before the
  feed limit reaches vmax again, the stretch is a region of frequent speed change, flag
  F_v_plan = 1; such a stretch is re-planned with the cosine profile of eqs. (5)-(13)
  (:mod:`planner.profiles.cosine`) where the S-curve would break the feed limit.
- Between sensitive points, jerk-limited S-curve segments (:mod:`planner.profiles.scurve`),
  zero acceleration at the points.
- Look-ahead distance: at least the S-curve braking distance from vmax (7.5 mm with the
  paper's limits), extended as long as the plan is not final.
Beyond the paper (motion-planning.md §1, §9 row 6): a bidirectional scan with jerk-feasible
speed changes (backward pass: the highest speed from which each next point can still be met;
forward pass: the highest speed reachable), then every segment is checked against the feed
limit on the arc length and refined (peak lowered, cosine re-plan, or a new sensitive point
inserted at the worst violation) until v(s) <= v_limit(s).

Streaming with bounded memory: a window of the path is planned assuming a stop at its end, and
only the part that a longer look-ahead could no longer change is released (its speeds equal
those planned with no stop at the window end); the window then moves on (a rest of the path
shorter than half a window joins the window before it). Only the window's points and the
envelope chunks it touches are held. A stop at the window end is not always the
hardest case: a staircase of points refined beyond it can brake more slowly than one ramp, so
a window whose start is too fast for its staircase merges it into one braking segment
(:func:`_brake_first`).

Units: s in mm, feeds mm/s, A mm/s², J mm/s³, T s. Pure computation; one generator per stream,
not thread-safe.

Not modelled: non-zero acceleration at sensitive points (a conservative choice of the paper);
per-axis jerk.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from planner.arclength import ArcLengthTable
from planner.envelope import MIN_FEED_MM_S, FeedEnvelope
from planner.profiles import Phase, PhaseTrain
from planner.profiles.cosine import cosine_fits, cosine_max_high_speed, cosine_time_s
from planner.profiles.scurve import (
    braking_distance_mm,
    cruise_speed,
    fitting_lower_speed,
    max_ramp_speed,
    min_ramp_speed,
    ramp_distance_mm,
    ramp_phases,
    segment_phases,
    settle_phases,
    settled_speed,
)

#: Window length in braking distances from vmax, and the lower bound of the window, mm.
WINDOW_BRAKING_DISTANCES, MIN_WINDOW_MM = 16.0, 1.0
#: A rest of the path shorter than this fraction of a window joins the window before it.
TAIL_WINDOW_FRACTION = 0.5
#: Refinement rounds, and sensitive points, of one window before the failing segments are
#: flattened under their lowest limit instead.
MAX_REFINEMENTS, MAX_WINDOW_POINTS = 30, 300
#: Relative slack of the feed-limit check.
CHECK_SLACK = 1e-9
#: Relative excess of a ramp over its distance still counted as fitting (round-off).
RAMP_FIT_RTOL = 1e-9
#: Time a failing segment may lose by cruising at its slower end's feed instead of being split,
#: relative to its own (failing) time.
HOLD_SLOWDOWN = 0.02
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


class _Window:
    """Sensitive points of one look-ahead window and the refinement state of its segments."""

    def __init__(self, s: list[float], cap: list[float], fv_plan: list[bool]) -> None:
        self.s = s
        self.cap = cap
        self.fv_plan = fv_plan  # per segment: region of frequent speed change (F_v_plan = 1)
        self.peak_cap = [math.inf] * (len(s) - 1)
        self.cosine = [0] * (len(s) - 1)  # 0: S-curve, 1: cosine, 2: cosine rejected
        self.braking = False  # the first segment brakes from the start state (_brake_first)
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


def _passes(s: list[float], cap: list[float], v_start: float, lim: PlanLimits) -> list[float]:
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


def _segment(
    w: _Window, k: int, v: list[float], lim: PlanLimits
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


def _segment_time_s(w: _Window, k: int, v: list[float], lim: PlanLimits) -> float:
    """Duration of segment k as planned."""
    return sum(phase.duration_s for phase in _segment(w, k, v, lim)[0])


class _Checker:
    """Compares a segment's planned feed with the envelope on the arc length."""

    def __init__(self, s_env: np.ndarray, v_env: np.ndarray, lim: PlanLimits) -> None:
        # A sharp corner's zero is a sensitive point where the plan stops; interpolating towards
        # it would ask for a linear approach to rest, which no jerk-limited stop can follow.
        moving = v_env > 0.0
        if moving.sum() >= 2:
            s_env, v_env = s_env[moving], v_env[moving]
        self.s_env, self.v_env, self.lim = s_env, v_env, lim
        # The limits with a sentinel after the last, so that a range may end at len(v_env).
        self._v_padded = np.append(v_env, np.inf)

    def interior_min(self, s0: float, s1: float) -> float:
        """The lowest limit over [s0, s1]."""
        return float(self._interior_mins(np.array([s0]), np.array([s1]))[0])

    def flat_end_cap(self, s_point: float, s_lo: float, s_hi: float, v_limit: float) -> float:
        """Highest feed at most ``v_limit`` for a sensitive point at s_point between s_lo and
        s_hi, as far as the limit around it allows.

        The plan has zero acceleration at a sensitive point, so a time tau before or after it
        its feed is at least v - drop(tau), where drop is the jerk-limited change from rest
        (J tau²/2, then A tau - A²/2J); where the limit rises towards the point or falls away
        from it faster than that, a point capped at the limit itself would be exceeded next to
        it by every plan. With tau = |s - s_point| / v, the cap is min(limit(s) + drop(tau)),
        which holds as well for the lower cap it gives (drop grows as v falls).
        """
        lo = int(np.searchsorted(self.s_env, s_lo, side="right"))
        hi = int(np.searchsorted(self.s_env, s_hi, side="left"))
        if hi <= lo or v_limit <= 0.0:
            return v_limit
        A, J = self.lim.A, self.lim.J
        tau = np.abs(self.s_env[lo:hi] - s_point) / v_limit
        drop = np.where(tau <= A / J, 0.5 * J * tau * tau, A * tau - 0.5 * A * A / J)
        return float(min(v_limit, np.min(self.v_env[lo:hi] + drop)))

    def worst_of(
        self, segments: list[tuple[float, float, tuple[Phase, ...], float, float]]
    ) -> list[tuple[float, float] | None]:
        """For each segment (s0, v0, phases, v_top, s1): (s, v_limit) of its worst excess of the
        feed limit, or None if it holds.

        Segments whose highest feed is below the lowest limit they span hold at once; the others
        are laid on one time line (a second apart) and sampled together every half period.
        """
        out: list[tuple[float, float] | None] = [None] * len(segments)
        s0, v_top, s1 = (np.array([seg[i] for seg in segments]) for i in (0, 3, 4))
        pending = np.flatnonzero(self._interior_mins(s0, s1) < v_top * (1.0 + CHECK_SLACK))
        train = PhaseTrain(0.0, 0.0, 0.0, 0.0)
        sampled, starts, ends = [], [], []
        for i in pending.tolist():
            s_start, v_start, phases, _, _ = segments[i]
            start = train.t_s + 1.0
            train.restart(start, s_start, v_start, 0.0)
            train.extend(phases)
            if train.t_s > start:  # a segment without motion has nothing to exceed
                sampled.append(i)
                starts.append(start)
                ends.append(train.t_s)
        if not sampled:
            return out
        start, end = np.array(starts), np.array(ends)
        counts = np.clip(np.ceil((end - start) / (0.5 * self.lim.T)), 16, 20_000).astype(int) + 1
        first = np.cumsum(counts) - counts
        # Each segment's times from its start to its end, both included, evenly spaced.
        fraction = (np.arange(counts.sum()) - np.repeat(first, counts)) / np.repeat(
            counts - 1, counts
        )
        times = np.repeat(start, counts) + np.repeat(end - start, counts) * fraction
        s, v, _, _ = train.sample(times)
        limit = np.interp(s, self.s_env, self.v_env)
        excess = v - limit * (1.0 + CHECK_SLACK) - 1e-9
        worst = first + np.array(
            [int(np.argmax(excess[lo : lo + n])) for lo, n in zip(first, counts, strict=True)]
        )
        for i, j in zip(sampled, worst.tolist(), strict=True):
            if excess[j] > 0.0:
                out[i] = (float(s[j]), float(limit[j]))
        return out

    def _interior_mins(self, s0: np.ndarray, s1: np.ndarray) -> np.ndarray:
        """The lowest limit over each [s0, s1]: at its ends or at a sample inside."""
        lowest = np.minimum(
            np.interp(s0, self.s_env, self.v_env), np.interp(s1, self.s_env, self.v_env)
        )
        i0 = np.searchsorted(self.s_env, s0, side="left")
        i1 = np.searchsorted(self.s_env, s1, side="right")
        inner = np.flatnonzero(i1 > i0)
        if inner.size:
            # reduceat over [i0, i1) pairs: the odd entries span the gaps between them.
            bounds = np.stack([i0[inner], i1[inner]], axis=1).ravel()
            inside = np.minimum.reduceat(self._v_padded, bounds)[::2]
            lowest[inner] = np.minimum(lowest[inner], inside)
        return lowest


def _sensitive_points(
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


def _refine(w: _Window, checker: _Checker, v_start: float, lim: PlanLimits) -> list[float]:
    """Refine the window until every segment keeps under the feed limit; returns the speeds.

    Each round checks every segment (last to first, so that splits do not shift the rest) and
    repairs the failing ones; should the rounds run out, every cosine segment becomes an S-curve
    again (its jerk depends on both end speeds, which flattening may change) and the failing
    segments are flattened to the lowest limit they span, which always holds: lowering the end
    speeds of an S-curve segment never raises it anywhere.
    """
    verdicts: dict[tuple, tuple[float, float] | None] = {}
    v = _passes(w.s, w.cap, v_start, lim)
    for flatten in (False, True):
        if flatten:
            w.cosine = [2 if kind == 1 else kind for kind in w.cosine]
            v = _passes(w.s, w.cap, v_start, lim)
        for _ in range(MAX_REFINEMENTS):
            if _brake_first(w, v, checker):
                v = _passes(w.s, w.cap, v_start, lim)
            failing = _failing(w, v, checker, lim, verdicts)
            if not failing:
                return v
            changed = False
            for k, bad in failing:
                if flatten:
                    changed |= _flatten(w, k, checker)
                else:
                    changed |= _repair(w, k, v, bad, checker, lim)
            v = _passes(w.s, w.cap, v_start, lim)
            if not changed or (not flatten and len(w.s) > MAX_WINDOW_POINTS):
                break
    return v


def _flatten(w: _Window, k: int, checker: _Checker) -> bool:
    """Hold segment k, and its end points, under the lowest limit it spans; whether it changed."""
    floor = max(checker.interior_min(w.s[k], w.s[k + 1]), MIN_FEED_MM_S)
    changed = w.peak_cap[k] > floor
    w.peak_cap[k] = min(w.peak_cap[k], floor)
    for i in (k, k + 1):
        if i > 0 and w.cap[i] > floor:
            w.cap[i] = floor
            changed = True
    return changed


def _brake_first(w: _Window, v: list[float], checker: _Checker) -> bool:
    """Merge the first segments into one that brakes at once, if the start is too fast for them.

    Every sensitive point is a point of zero acceleration, so a staircase of them, refined where
    the feed limit keeps falling, can brake only slowly. When the start state (released by the
    previous window, which did not see this stretch) is faster than such a staircase allows,
    the points up to the first one the plan meets again are removed, and the one segment left
    brakes from the start down to the lowest limit it spans and holds it (to the window's end
    if the plan cannot even stop there).
    """
    over = [k for k in range(1, len(w.s)) if v[k] > w.cap[k] * (1.0 + 1e-9) + 1e-12]
    if not over:
        return False
    m = min(over[-1] + 1, len(w.s) - 1)
    if m <= 1:
        return False
    floor = max(checker.interior_min(w.s[0], w.s[m]), MIN_FEED_MM_S)
    w.merge_first(m, floor)
    return True


def _failing(
    w: _Window, v: list[float], checker: _Checker, lim: PlanLimits, verdicts: dict
) -> list[tuple[int, tuple[float, float]]]:
    """Failing segments, last first, with their worst excess (s, v_limit)."""
    keys: dict[int, tuple] = {}
    unchecked: dict[tuple, tuple[float, float, tuple[Phase, ...], float, float]] = {}
    for k in range(len(w.s) - 1):
        keys[k] = key = w.key(k, v)
        if key not in verdicts and key not in unchecked:
            phases, v_top = _segment(w, k, v, lim)
            unchecked[key] = (w.s[k], v[k], phases, v_top, w.s[k + 1])
    verdicts.update(zip(unchecked, checker.worst_of(list(unchecked.values())), strict=True))
    out = []
    for k in range(len(w.s) - 2, -1, -1):
        L = w.s[k + 1] - w.s[k]
        if w.cosine[k] == 1 and not cosine_fits(v[k], v[k + 1], L, lim.A, lim.J):
            out.append((k, (w.s[k], 0.0)))
        elif verdicts[keys[k]] is not None:
            out.append((k, verdicts[keys[k]]))
    return out


def _lower_for_cosine(w: _Window, k: int, v: list[float], lim: PlanLimits) -> bool:
    """Lower the faster end of a cosine segment so that a_act <= A and j_act <= J, eqs. (9)-(10)."""
    L = w.s[k + 1] - w.s[k]
    high = k if v[k] > v[k + 1] else k + 1
    v_high = cosine_max_high_speed(min(v[k], v[k + 1]), L, lim.A, lim.J)
    if high == 0 or min(v[k], v[k + 1]) + v_high <= 0.0:
        w.cosine[k] = 2
    else:
        w.cap[high] = min(w.cap[high], v_high)
    return True


def _repair(
    w: _Window, k: int, v: list[float], bad: tuple[float, float], checker: _Checker, lim
) -> bool:
    """One repair of segment k: cosine re-plan (F_v_plan), a new point, or a lower peak.

    A new sensitive point goes to the worst excess, capped by the feed limit there as far as a
    point of zero acceleration can meet it (:meth:`_Checker.flat_end_cap`); the two halves are
    checked again, so refinement converges to a staircase that follows the limit where it keeps
    changing (capping at the segment's lowest limit instead would hold whole stretches below
    it). Before a split, a segment whose cruise at its slower end's feed costs at most
    ``HOLD_SLOWDOWN`` of its time cruises there instead (towards a minimum of the limit the
    splits would otherwise go on halving the gap). A segment that can no longer be split, or
    whose ends and worst excess are all at its lowest limit (a flat stretch, where halves would
    repeat the problem), is held under that limit by its peak.
    """
    s_bad, v_limit_bad = bad
    L = w.s[k + 1] - w.s[k]
    if w.cosine[k] == 1:
        if not cosine_fits(v[k], v[k + 1], L, lim.A, lim.J):
            return _lower_for_cosine(w, k, v, lim)
        w.cosine[k] = 2
        return True
    failing_s = _segment_time_s(w, k, v, lim)
    if w.cosine[k] == 0 and w.fv_plan[k] and v[k] + v[k + 1] > 0.0:
        # F_v_plan = 1: re-plan this stretch with eqs. (5)-(13), unless that is slower than a
        # staircase of S-curves could be (near a corner both end speeds may be ~0); then the
        # S-curve is repaired at once.
        if cosine_time_s(v[k], v[k + 1], L) <= failing_s:
            w.cosine[k] = 1
            return True
        w.cosine[k] = 2
    floor = checker.interior_min(w.s[k], w.s[k + 1])
    # Ends at the lowest limit of the segment and the excess where the limit is that low
    # (a plateau): a point there would leave both halves the same problem.
    plateau = max(v[k], v[k + 1], v_limit_bad) <= floor * (1.0 + CHECK_SLACK)
    splittable = not (k == 0 and w.braking) and not plateau
    slow = min(v[k], v[k + 1])
    if splittable and w.peak_cap[k] > slow > 0.0:
        # Cruising at the slower end's feed, changing speed next to the faster end, is the
        # shape that stays under a limit falling towards the slower end; where it costs little
        # time against the failing segment, it saves splitting again and again towards it.
        peak_cap, w.peak_cap[k] = w.peak_cap[k], slow
        if _segment_time_s(w, k, v, lim) <= (1.0 + HOLD_SLOWDOWN) * failing_s:
            return True
        w.peak_cap[k] = peak_cap
    if splittable and s_bad - w.s[k] > MIN_POINT_GAP_MM and w.s[k + 1] - s_bad > MIN_POINT_GAP_MM:
        cap = checker.flat_end_cap(s_bad, w.s[k], w.s[k + 1], min(v_limit_bad, lim.vmax_mm_s))
        w.insert(k, s_bad, cap)
        return True
    if max(v[k], v[k + 1]) <= floor * (1.0 + CHECK_SLACK):
        if w.peak_cap[k] > floor * (1.0 + 1e-12):
            w.peak_cap[k] = floor
            return True
        return False
    for i in (k, k + 1):
        if i > 0 and w.cap[i] > floor:
            w.cap[i] = floor
            return True
    return False


def _released(
    w: _Window, v: list[float], upper: list[float], lim: PlanLimits, final: bool
) -> tuple[list[SegmentPlan], int]:
    """Segments a longer look-ahead can no longer change, and the point index they end on."""
    out: list[SegmentPlan] = []
    n = len(w.s)
    k = 0
    while k < n - 1:
        if not final and (k + 1 == n - 1 or abs(v[k + 1] - upper[k + 1]) > 1e-12 * lim.vmax_mm_s):
            break
        phases, _ = _segment(w, k, v, lim)
        out.append(SegmentPlan(phases, w.s[k + 1], v[k + 1]))
        k += 1
    return out, k


def _cruise_cut(w: _Window, k: int, v: list[float], lim: PlanLimits) -> SegmentPlan | None:
    """The first half of segment k when it cruises at a peak the window end does not lower."""
    if w.cosine[k] == 1:
        return None
    v0, v1, L = v[k], v[k + 1], w.s[k + 1] - w.s[k]
    v_cap = min(lim.vmax_mm_s, w.peak_cap[k])
    vp = cruise_speed(v0, v1, L, v_cap, lim.A, lim.J)
    if vp < v_cap * (1.0 - 1e-12) or vp <= 0.0:
        return None
    up_mm = ramp_distance_mm(v0, vp, lim.A, lim.J)
    cruise_mm = L - up_mm - ramp_distance_mm(vp, v1, lim.A, lim.J)
    if cruise_mm <= 2.0 * MIN_POINT_GAP_MM:
        return None
    phases = [*ramp_phases(v0, vp, lim.A, lim.J), Phase(0.5 * cruise_mm / vp, 0.0)]
    return SegmentPlan(tuple(phases), w.s[k] + up_mm + 0.5 * cruise_mm, vp)


def plan_segments(
    envelope: FeedEnvelope,
    arc: ArcLengthTable,
    lim: PlanLimits,
    s_start: float,
    v_start: float,
    a_start: float,
    *,
    stop: bool,
) -> Iterator[list[SegmentPlan]]:
    """Released stretches of the motion from the start state to rest, in order, in the groups
    that each window releases.

    The first stretch brings the start acceleration to zero (jerk-limited); then windows of the
    path are planned and released. With ``stop`` the motion comes to rest as soon as the limits
    allow (the jerk-limited braking distance), or at the curve end if that comes first.
    """
    A, J = lim.A, lim.J
    settle = settle_phases(a_start, J)
    s, v = s_start, v_start
    if settle:
        train = PhaseTrain(0.0, s, v, a_start)
        train.extend(settle)
        s, v = arc.extent_mm(train.s_mm), settled_speed(v_start, a_start, J)
        yield [SegmentPlan(tuple(settle), s, v)]
    window_mm = max(
        WINDOW_BRAKING_DISTANCES * braking_distance_mm(lim.vmax_mm_s, A, J), MIN_WINDOW_MM
    )
    # A hair beyond the braking distance, so that round-off never makes the stop look infeasible.
    brake_mm = braking_distance_mm(v, A, J) * (1.0 + 1e-9) + 1e-9
    stop_at = arc.extent_mm(s + brake_mm) if stop else math.inf
    extra = 0.0
    while True:
        # The curve's end, once it is within reach of this window (the table grows to there).
        horizon = s + window_mm + extra + TAIL_WINDOW_FRACTION * window_mm
        reach = arc.extent_mm(horizon)
        curve_end = reach if reach < horizon else math.inf
        if s >= curve_end or not (s < stop_at or v > 0.0):
            break
        target = min(stop_at, curve_end)
        s_end = s + window_mm + extra
        if target - s_end < TAIL_WINDOW_FRACTION * window_mm:
            s_end = target  # one window to the end rather than a short one after it
        s_end = min(s_end, target)
        final = s_end >= target
        s_env, v_env = envelope.query(s, s_end)
        pts, cap, fv = _sensitive_points(s_env, v_env, s, s_end, lim.vmax_mm_s)
        if s_end - pts[-1] > MIN_POINT_GAP_MM:
            pts.append(s_end)
            cap.append(0.0)
            fv.append(False)
        else:
            cap[-1] = 0.0
        w = _Window(pts, cap, fv)
        checker = _Checker(s_env, v_env, lim)
        v_plan = _refine(w, checker, v, lim)
        if final:
            if v_plan[-1] > 1e-9:
                # Too fast to stop where planned (start beyond the constraints): stop later.
                stop_at = stop_at + braking_distance_mm(v_plan[-1], A, J)
                extra = 0.0
                if s_end < curve_end:
                    continue
            segments, k = _released(w, v_plan, v_plan, lim, final=True)
            yield segments
            return
        upper_caps = list(w.cap)
        upper_caps[-1] = lim.vmax_mm_s
        upper = _passes(w.s, upper_caps, v, lim)
        segments, k = _released(w, v_plan, upper, lim, final=False)
        cut = _cruise_cut(w, k, v_plan, lim) if k < len(w.s) - 1 else None
        if cut is not None:
            segments.append(cut)
        if not segments:
            extra = 2.0 * (extra + window_mm)
            continue
        extra = 0.0
        yield segments
        s, v = segments[-1].s_end_mm, segments[-1].v_end_mm_s
