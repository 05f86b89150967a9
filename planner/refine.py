"""Refinement of a window until every segment keeps under the feed limit.

Beyond the paper (motion-planning.md §9 row 6): each round checks every segment
(:class:`planner.checker.Checker`) and repairs the failing ones: a cosine re-plan where the
stretch is flagged F_v_plan (eqs. (5)-(13)), a cruise at the slower end's feed when that costs
little, a new point at the worst excess, or a lower peak; should the rounds run out,
the failing segments are flattened under the lowest limit they span. A window whose start is
too fast for its staircase of points brakes in one segment instead (:func:`brake_first`), and
deeper where that still exceeds the limit (:func:`_brake_deeper`).

A new point is pinned on the limit (:class:`planner.window.Window`): a shade under it
(``PIN_MARGIN``), with the limit's own slope as its acceleration (v dv_limit/ds, at most
``PIN_ACCEL_FRACTION`` A; where the limit changes faster the point sits lower, where changing
the feed at that rate meets the limit), so that the plan runs along the limit instead of
stopping its acceleration at every point; the segments on either side are general jerk-limited
motions (:mod:`planner.profiles.transition`). A point the scan cannot honour is lowered, then
falls back to zero acceleration under the cap that keeps a zero-acceleration point below the
limit around it (:meth:`planner.checker.Checker.end_cap`); one at that cap already keeps it
with less acceleration first (:meth:`planner.window.Window.speeds`).

Units: s in mm, feeds mm/s. Pure computation; not thread-safe (it edits the window).
"""

from __future__ import annotations

import math
from collections.abc import Callable

from planner.checker import CHECK_SLACK, Checker
from planner.envelope import MIN_FEED_MM_S
from planner.profiles import Phase
from planner.profiles.cosine import cosine_fits, cosine_max_high_speed, cosine_time_s
from planner.profiles.scurve import ramp_distance_mm, settled_speed
from planner.window import (
    MIN_POINT_GAP_MM,
    PlanLimits,
    Window,
    passes,
    segment_plan,
    segment_time_s,
)

#: Refinement rounds, and sensitive points, of one window before the failing segments are
#: flattened under their lowest limit instead; where the points run out, the look-ahead plans
#: a shorter window first (:func:`planner.lookahead.plan_segments`). At a chord error of 0.1 µm
#: the bench's loop curves need 300-1,200 points in a window timed at vmax: flattened, they
#: took 1.071-1.075 of the jerk-limited reference, planned shorter 1.023-1.025.
MAX_REFINEMENTS, MAX_WINDOW_POINTS = 30, 300
#: A point pinned on the feed limit sits this fraction below it (room for the segments on
#: either side, which match the limit's value and slope there but not its curvature). Measured
#: against the bench's jerk-limited reference: 0.005 left more points that the scan could not
#: honour at zero acceleration (loops 1.068-1.103 of the reference, free curves up to 1.036),
#: 0.01 gives loops 1.059-1.082 and free curves 1.018-1.023 at 0.2 % more on the paper's curve.
PIN_MARGIN = 0.01
#: A point is pinned only where the limit's slope asks at most this fraction of A.
PIN_ACCEL_FRACTION = 0.9
#: Time a failing segment may lose by cruising at its slower end's feed instead of being split,
#: relative to its own (failing) time.
HOLD_SLOWDOWN = 0.02
#: Halvings of the range searched for a braking first segment's peak cap (a 64th of the range
#: between the lowest limit it spans and the start feed).
BRAKING_CAP_STEPS = 6
#: A deeper braking (:func:`_brake_deeper`) aims this fraction below the limit at the excess.
#: Aimed at the limit itself, the rounds came to it from above in ever smaller steps: 16 rounds
#: (10 ms) for a re-plan of a loop curve at 1 µm whose excess started at 2.8 %.
BRAKE_DEEPER_MARGIN = 1e-3


def refine(
    w: Window,
    checker: Checker,
    v_start: float,
    lim: PlanLimits,
    between_rounds: Callable[[], None] | None = None,
    *,
    shortenable: bool = False,
) -> list[float] | None:
    """Refine the window until every segment keeps under the feed limit; returns the speeds.

    With ``shortenable``, a window that needs more than :data:`MAX_WINDOW_POINTS` returns
    None instead of being flattened: the caller plans a shorter one.

    Each round checks every segment (last to first, so that splits do not shift the rest) and
    repairs the failing ones; should the rounds run out, every cosine segment becomes an S-curve
    again (its jerk depends on both end speeds, which flattening may change) and the failing
    segments are flattened to the lowest limit they span, which always holds: lowering the end
    speeds of an S-curve segment never raises it anywhere.

    ``between_rounds`` is called after each round: a caller planning ahead in the background
    may do urgent work there (of its own, never with this plan).

    A start too fast for the window's points brakes in one segment (:func:`brake_first`). Where
    the segments still exceed the limit after all rounds, and the window knows where the plan
    that released the start state comes to rest (:attr:`Window.rest_mm`), the motion stops
    there instead, and the window is refined again: that plan, from this state, kept under the
    limit to its rest. Without such a rest (a re-plan's first window), the rounds have the one
    braking segment brake deeper where it exceeds the limit (:func:`_brake_deeper`).
    (Braking to a tip's feed at zero acceleration can take up to A³ / (8 J²) more than
    stopping just before it: a window that ended just before a tip released a state from
    which the tip could not be met, and the braking segment ran over the limit, 1.35 delta and
    1.56 J on the setpoints, then held the tip's feed to the window's end.)
    """
    refined = _refined(w, checker, v_start, lim, between_rounds, shortenable)
    if refined is not None and not refined[1] and w.rest_inside:
        w.rest_first()
        refined = _refined(w, checker, v_start, lim, between_rounds, shortenable)
    return None if refined is None else refined[0]


def _refined(
    w: Window,
    checker: Checker,
    v_start: float,
    lim: PlanLimits,
    between_rounds: Callable[[], None] | None,
    shortenable: bool,
) -> tuple[list[float], bool] | None:
    """The rounds of :func:`refine`: the speeds, and whether every segment holds (None: the
    window is ``shortenable`` and needs more points than it may hold)."""
    verdicts: dict[tuple, tuple[float, float, float] | None] = {}
    v = w.speeds(v_start, lim)
    for flatten in (False, True):
        if flatten:
            w.cosine = [2 if kind == 1 else kind for kind in w.cosine]
            for i in range(len(w.s)):
                w.unpin(i)
            v = w.speeds(v_start, lim)
        for _ in range(MAX_REFINEMENTS):
            if shortenable and not flatten and len(w.s) > MAX_WINDOW_POINTS:
                return None  # crowded (before any round too: a warm start may seed that many)
            if brake_first(w, v, checker, lim):
                v = w.speeds(v_start, lim)
            failing = _failing(w, v, checker, lim, verdicts)
            if not failing:
                return v, True
            changed = False
            for k, bad in failing:
                if flatten:
                    changed |= _flatten(w, k, checker)
                else:
                    changed |= _repair(w, k, v, bad, checker, lim)
            v = w.speeds(v_start, lim)
            if between_rounds is not None:
                between_rounds()
            if not changed or (not flatten and not shortenable and len(w.s) > MAX_WINDOW_POINTS):
                break
    return v, False


def _flatten(w: Window, k: int, checker: Checker) -> bool:
    """Hold segment k, and its end points, under the lowest limit it spans; whether it changed."""
    floor = _floor(w.s[k], w.s[k + 1], checker)
    changed = w.peak_cap[k] > floor
    w.peak_cap[k] = min(w.peak_cap[k], floor)
    for i in (k, k + 1):
        if i > 0 and w.cap[i] > floor:
            w.unpin(i)
            w.cap[i] = floor
            changed = True
    return changed


def brake_first(w: Window, v: list[float], checker: Checker, lim: PlanLimits) -> bool:
    """Merge the first segments into one that brakes, if the start is too fast for them.

    Every sensitive point is a point of zero acceleration, so a staircase of them, refined where
    the feed limit keeps falling, can brake only slowly. When the start state (released by the
    previous window, which did not see this stretch) is faster than such a staircase allows,
    the points up to the first one a braking segment meets are removed (:func:`_braking_cap`).
    Where no point is met so, the points up to the first rest, or past the last one too fast,
    are removed, and the one segment left brakes at once down to the lowest limit it spans and
    holds it (to the window's end if the plan cannot even stop there). Where the segment so
    found holds that lowest limit, it ends instead where braking at once meets the limit,
    when it comes there faster (:func:`_flank_braking`).
    """
    over = _too_fast(v, w.cap)
    if not over:
        return False
    # Never past a rest (the checker does not see its zero): merged away, a fold the plan
    # came to too fast was passed at 44 mm/s (10 A on the setpoints of a re-plan).
    rest = next(k for k in range(1, len(w.s)) if w.cap[k] == 0.0 or k == len(w.s) - 1)
    last = min(over[-1] + 1, rest)
    if last <= 1:
        return False
    for m in range(over[0] + 1, last + 1):
        peak_cap = _braking_cap(w, m, v[0], checker, lim)
        if peak_cap is not None:
            break
    else:
        m, peak_cap = last, _floor(w.s[0], w.s[last], checker)
    if peak_cap <= _floor(w.s[0], w.s[m], checker):
        flank = _flank_braking(w, m, v[0], checker, lim)
        if flank is not None:
            k, s_end, v_end, trial = flank
            merged = w.copy()
            merged.merge_first(m, peak_cap)
            if _time_to(trial, w.s[m], v[0], lim) < _time_to(merged, w.s[m], v[0], lim):
                w.insert(k, s_end, v_end)
                w.merge_first(k + 1, v[0])
                return True
    w.merge_first(m, peak_cap)
    return True


def _time_to(w: Window, s_mm: float, v_start: float, lim: PlanLimits) -> float:
    """Planned time from the start to the point at ``s_mm`` (speeds as the scan finds them)."""
    v, _ = passes(w.s, w.cap, v_start, lim, w.acc, w.pinned)
    return sum(segment_time_s(w, k, v, lim) for k in range(w.s.index(s_mm)))


def _flank_braking(
    w: Window, m: int, v_start: float, checker: Checker, lim: PlanLimits
) -> tuple[int, float, float, Window] | None:
    """Where one segment braking at once from the start can end before point ``m``: the
    segment k to split, the new point's s and its feed, the highest feed (to a 64th of the
    range) with the segment under the limit and every point after it reached at or under its
    cap, and the window so; None if even the lowest limit it spans is too fast.

    A segment to point m that has to brake at once and hold a low feed (the lowest limit over
    it, a tip's) to get there holds it over the flank before the tip: a cold re-plan of a cusp
    curve crept at 0.9 mm/s for 0.6 mm. Ended on the flank, where the braking meets the limit,
    the plan follows the limit down from there.
    """
    s0, s_m = w.s[0], w.s[m]
    found: dict[float, tuple[int, float, float, Window]] = {}

    def braked(v_end: float) -> bool:
        s_end = s0 + ramp_distance_mm(v_start, v_end, lim.A, lim.J)
        if not s0 + MIN_POINT_GAP_MM < s_end < s_m - MIN_POINT_GAP_MM:
            return False
        k = max(j for j in range(m) if w.s[j] < s_end)
        if s_end - w.s[k] <= MIN_POINT_GAP_MM:
            return False
        trial = w.copy()
        trial.insert(k, s_end, v_end)
        trial.merge_first(k + 1, v_start)
        v = _reached(trial, v_start, lim)
        if v is None or not _first_holds(trial, v, checker, lim):
            return False
        found[v_end] = (k, s_end, v_end, trial)
        return True

    low = _floor(s0, s_m, checker)
    if not braked(low):
        return None
    return found[_highest_holding(low, v_start, braked)]


def _too_fast(v: list[float], cap: list[float]) -> list[int]:
    """The points after the start planned faster than their caps."""
    return [k for k in range(1, len(v)) if v[k] > cap[k] * (1.0 + 1e-9) + 1e-12]


def _floor(s0: float, s1: float, checker: Checker) -> float:
    """The lowest limit over [s0, s1] (at least the lowest feed planned)."""
    return max(checker.interior_min(s0, s1), MIN_FEED_MM_S)


def _braking_cap(
    w: Window, m: int, v_start: float, checker: Checker, lim: PlanLimits
) -> float | None:
    """The highest peak cap, at most the start feed, of one segment from the start to point m
    that keeps under the limit with every point after it reached at or under its cap; None if
    even the lowest limit the segment spans (braking at once, then holding it) does not.

    The segment cruises at its peak cap and brakes as late as its end needs; the caps between
    are halved ``BRAKING_CAP_STEPS`` times (a lower cap changes only the feed before the
    braking, so the verdict changes once). Merging every point up to the last one too fast and
    holding its lowest limit held re-plans at a tip's feed, about 1 mm/s, over the staircase
    after the tip or the 14 mm before it: up to 20 s longer than planned at that override.
    """
    trial = w.copy()
    trial.merge_first(m, v_start)
    # The scan does not see the peak cap: one scan serves every cap tried.
    v = _reached(trial, v_start, lim)
    if v is None:
        return None

    def holds(peak_cap: float) -> bool:
        trial.peak_cap[0] = peak_cap
        return _first_holds(trial, v, checker, lim)

    if holds(v_start):
        return v_start
    low = _floor(w.s[0], w.s[m], checker)
    if not holds(low):
        return None
    return _highest_holding(low, v_start, holds)


def _reached(w: Window, v_start: float, lim: PlanLimits) -> list[float] | None:
    """The scan's speeds from ``v_start``, or None where it cannot reach every point at or
    under its cap."""
    v, bad = passes(w.s, w.cap, v_start, lim, w.acc, w.pinned)
    return None if bad is not None or _too_fast(v, w.cap) else v


def _first_holds(w: Window, v: list[float], checker: Checker, lim: PlanLimits) -> bool:
    """Whether the window's first segment, as planned with speeds ``v``, keeps under the limit."""
    plan = segment_plan(w, 0, v, lim)
    return plan is not None and checker.worst_of([_checked(w, 0, v, plan)]) == [None]


def _highest_holding(low: float, high: float, holds: Callable[[float], bool]) -> float:
    """The highest value in [low, high] that ``holds`` (true at ``low``), to a 2^-
    ``BRAKING_CAP_STEPS`` of the range by bisection."""
    for _ in range(BRAKING_CAP_STEPS):
        middle = 0.5 * (low + high)
        low, high = (middle, high) if holds(middle) else (low, middle)
    return low


def _failing(
    w: Window, v: list[float], checker: Checker, lim: PlanLimits, verdicts: dict
) -> list[tuple[int, tuple[float, float, float]]]:
    """Failing segments, last first, with their worst excess (s, v_limit, v_planned)."""
    keys = w.keys(v)
    unchecked: dict[tuple, tuple[float, float, tuple[Phase, ...], float, float, float]] = {}
    for k, key in enumerate(keys):
        if key not in verdicts and key not in unchecked:
            unchecked[key] = _checked(w, k, v, segment_plan(w, k, v, lim))
    verdicts.update(zip(unchecked, checker.worst_of(list(unchecked.values())), strict=True))
    out = []
    for k in range(len(w.s) - 2, -1, -1):
        L = w.s[k + 1] - w.s[k]
        if w.cosine[k] == 1 and not cosine_fits(v[k], v[k + 1], L, lim.A, lim.J):
            out.append((k, (w.s[k], 0.0, v[k])))
        elif verdicts[keys[k]] is not None:
            out.append((k, verdicts[keys[k]]))
    return out


def _checked(
    w: Window, k: int, v: list[float], plan: tuple[tuple[Phase, ...], float]
) -> tuple[float, float, tuple[Phase, ...], float, float, float]:
    """Segment k with its plan (phases, top feed) as :meth:`Checker.worst_of` takes it."""
    phases, v_top = plan
    return (w.s[k], v[k], phases, v_top, w.s[k + 1], w.acc[k])


def _lower_for_cosine(w: Window, k: int, v: list[float], lim: PlanLimits) -> bool:
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
    w: Window, k: int, v: list[float], bad: tuple[float, float, float], checker: Checker, lim
) -> bool:
    """One repair of segment k: cosine re-plan (F_v_plan), a new point, or a lower peak.

    A new sensitive point goes to the worst excess, capped by the feed limit there as far as a
    point of zero acceleration can meet it (:meth:`Checker.end_cap`); the two halves are
    checked again, so refinement converges to a staircase that follows the limit where it keeps
    changing (capping at the segment's lowest limit instead would hold whole stretches below
    it). Before a split, a segment whose cruise at its slower end's feed costs at most
    ``HOLD_SLOWDOWN`` of its time cruises there instead (towards a minimum of the limit the
    splits would otherwise go on halving the gap). A segment that can no longer be split, or
    whose ends and worst excess are all at its lowest limit (a flat stretch, where halves would
    repeat the problem), is held under that limit by its peak.
    """
    s_bad, v_limit_bad, _ = bad
    L = w.s[k + 1] - w.s[k]
    if w.cosine[k] == 1:
        if not cosine_fits(v[k], v[k + 1], L, lim.A, lim.J):
            return _lower_for_cosine(w, k, v, lim)
        w.cosine[k] = 2
        return True
    failing_s = segment_time_s(w, k, v, lim)
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
        if segment_time_s(w, k, v, lim) <= (1.0 + HOLD_SLOWDOWN) * failing_s:
            return True
        w.peak_cap[k] = peak_cap
    if splittable and s_bad - w.s[k] > MIN_POINT_GAP_MM and w.s[k + 1] - s_bad > MIN_POINT_GAP_MM:
        v_point = min(v_limit_bad, lim.vmax_mm_s)
        flat_cap = checker.end_cap(s_bad, w.s[k], w.s[k + 1], v_point)
        pin = v_point * (1.0 - PIN_MARGIN)
        reach = PIN_ACCEL_FRACTION * lim.A
        acc = pin * checker.slope(s_bad, pin * lim.T)
        steep = abs(acc) > reach
        if steep:
            # A limit changing faster than the plan can: the point sits lower, where changing
            # the feed at reach meets the limit (worth it only above the flat cap).
            acc = math.copysign(reach, acc)
            pin = checker.end_cap(s_bad, w.s[k], w.s[k + 1], pin, acc)
        # Braking at a pinned point must be released before the feed reaches zero.
        released = settled_speed(pin, min(acc, 0.0), lim.J) > PIN_MARGIN * pin
        if v_limit_bad < lim.vmax_mm_s and released and not (steep and pin <= flat_cap):
            w.insert(k, s_bad, pin, acc=acc, flat_cap=flat_cap)
        else:
            w.insert(k, s_bad, flat_cap)
        return True
    if max(v[k], v[k + 1]) <= floor * (1.0 + CHECK_SLACK):
        if w.peak_cap[k] > floor * (1.0 + 1e-12):
            w.peak_cap[k] = floor
            return True
        return False
    for i in (k, k + 1):
        if i > 0 and w.cap[i] > floor:
            w.unpin(i)
            w.cap[i] = floor
            return True
    return k == 0 and w.braking and not w.rest_inside and _brake_deeper(w, v, bad, lim)


def _brake_deeper(
    w: Window, v: list[float], bad: tuple[float, float, float], lim: PlanLimits
) -> bool:
    """Lower the feed the braking first segment (:func:`brake_first`) brakes to, where it
    exceeds the limit while its deceleration eases; whether it did.

    Braking down to the lowest limit the segment spans can still be too slow for a limit that
    falls steeply before it: a re-plan from a state accelerating towards a loop's tip, brought to
    zero acceleration first, exceeded the limit by 3 % on the tip's flank. A deeper braking keeps
    its peak deceleration longer and brings the feed down sooner there, so the feed braked to
    is lowered by the ratio of the limit to the planned feed at the excess, and
    ``BRAKE_DEEPER_MARGIN`` more (the next round checks again). Where the deceleration has not
    yet eased, the ramp is the same whatever feed it brakes to: nothing to gain. Called only
    where the window has no rest to stop at instead (:attr:`Window.rest_inside`, a re-plan's
    first window): towards a tip of 1.12 mm/s the rounds lowered the feed to 0.12 mm/s and held
    it over 22 mm (185 s), where stopping at the rest took 1.27 s in all.
    """
    _, v_limit_bad, v_bad = bad
    v_floor = w.peak_cap[0]
    if not 0.0 < v_floor < v[0]:
        return False
    a_peak = min(lim.A, math.sqrt(lim.J * (v[0] - v_floor)))
    # The ramp is point-symmetric: it eases from v_floor + a_peak² / (2J) on.
    if v_bad >= v_floor + a_peak * a_peak / (2.0 * lim.J):
        return False
    w.peak_cap[0] = v_floor * v_limit_bad / v_bad * (1.0 - BRAKE_DEEPER_MARGIN)
    return True
