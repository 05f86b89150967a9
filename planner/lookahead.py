"""Look-ahead feed planning along the arc length: windows of the path, planned and released.

Source: section 2.2 of Wang, Zhao, Lu, Liu, China Mechanical Engineering 23(3), 2012, 299-304.
The stages, one module each:
- :mod:`planner.envelope`: the feed limit along the arc length (pre-interpolation), each sample
  lowered to the limits a step from it reaches (:mod:`planner.dilation`);
- :mod:`planner.window`: sensitive points (curvature-rising and -falling modules, F_v_plan),
  the bidirectional scan of their speeds and the S-curve or cosine segment between two points;
- :mod:`planner.checker`: a segment's planned feed against the limit;
- :mod:`planner.refine`: repairs until every segment keeps under the limit;
- here: the windows. Look-ahead distance: at least the S-curve braking distance from vmax
  (7.5 mm with the paper's limits), extended as long as the plan is not final. The first window
  is only as long as a first block needs (:data:`FIRST_WINDOW_PERIODS`; a re-plan's is timed on
  the feed limit ahead, shorter where that is low).

Streaming with bounded memory: a window of the path is planned assuming a stop at its end, and
only the part that a longer look-ahead could no longer change is released (its speeds equal
those planned with no stop at the window end); the window then moves on (a rest of the path
shorter than half a window joins the window before it). Only the window's points and the
envelope and arc-length chunks it reaches are built, so the first stretch comes as fast on a
curve of 100,000 knot spans as on a short one. A window whose refinement needs more points than
:data:`planner.refine.MAX_WINDOW_POINTS` (tight loops and cusps at a chord error of 0.1 µm) is
planned shorter rather than flattened under its lowest limits, and the windows after it are
sized to the points it held.

Units: s in mm, feeds mm/s, A mm/s², J mm/s³, T s. Pure computation; one generator per stream,
not thread-safe.

Not modelled: non-zero acceleration at the paper's sensitive points (the curvature maxima: a
conservative choice of the paper, kept; points the refinement adds may carry one); per-axis
jerk.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

import numpy as np

from planner.arclength import ArcLengthTable
from planner.checker import Checker
from planner.envelope import FeedEnvelope
from planner.errors import StartTooFast
from planner.profiles import Phase, PhaseTrain
from planner.profiles.scurve import (
    braking_distance_mm,
    cruise_speed,
    ramp_distance_mm,
    ramp_phases,
    settle_phases,
    settled_speed,
)
from planner.profiles.transition import transition_phases
from planner.refine import MAX_WINDOW_POINTS, refine
from planner.warmstart import RefinedPoints
from planner.window import (
    MIN_POINT_GAP_MM,
    PlanLimits,
    SegmentPlan,
    SegmentPlans,
    Window,
    segment_plan,
    sensitive_points,
)

#: A start decelerating by less than this is not braking (round-off at the end of a braking).
BRAKING_TOLERANCE_MM_S2 = 1e-6
#: Window length in braking distances from vmax, and the lower bound of the window, mm. A
#: window costs a fixed share (the envelope query, the checks, the sampling) besides its
#: points: against 16, 24 took the smooth random curve's planning CPU time down about 12 %, with
#: every bench curve's motion time the same to the period. Longer windows also make each
#: refinement round, between which the planner process answers the cycle, longer.
WINDOW_BRAKING_DISTANCES, MIN_WINDOW_MM = 24.0, 1.0
#: The first window covers this many periods at vmax (at the start feed, when above it) plus
#: this many braking distances from there, when that is shorter than a whole window: a first
#: block (the planner process asks for 64 rows) then waits for the refinement of what it needs,
#: not of a whole window. Measured on re-plans' first blocks against whole first windows: cusps
#: median 12.2 -> 3.5 ms, loops 14.0 -> 8.1 ms, the paper's curve's as before. Where windows
#: end moves what refinement finds: of the bench's 12 family curves, 9 keep their motion time
#: to the period, loops 0 and 3 take 5 and 3 periods more (+0.6 %, +0.3 %), free 3 one less;
#: the paper's curve keeps its own.
FIRST_WINDOW_PERIODS, FIRST_WINDOW_BRAKING_DISTANCES = 65, 2.0
#: A re-plan's first window timed on the feed limit is taken only when shorter than this
#: fraction of the one timed at vmax: a little shorter, the window may end too close after the
#: last point a release can end on. On the paper's curve one 50.0 mm long against 51.6 mm
#: released nothing, and the re-plan's first block took 1.05 ms against 0.86 ms.
LIMIT_TIMED_WINDOW_FRACTION = 0.75
#: Times a window too crowded to refine is planned shorter before a release, at most; then it
#: is flattened under its lowest limits (as when the refinement rounds run out).
MAX_SHORTENINGS = 6
#: A crowded window is shortened only while that moves its length by at least this many stops
#: from its highest feed (halfway towards the longest window that released nothing); a longer
#: window that released nothing is grown by the same rule towards the crowded one.
CROWDED_STEP_BRAKING_DISTANCES = 2.0
#: A rest of the path shorter than this fraction of a window joins the window before it.
TAIL_WINDOW_FRACTION = 0.5


def _released(
    w: Window, v: list[float], upper: list[float], lim: PlanLimits, final: bool
) -> tuple[list[SegmentPlan], int]:
    """Segments a longer look-ahead can no longer change, and the point index they end on."""
    out: list[SegmentPlan] = []
    n = len(w.s)
    k = 0
    while k < n - 1:
        if not final and (k + 1 == n - 1 or abs(v[k + 1] - upper[k + 1]) > 1e-12 * lim.vmax_mm_s):
            break
        phases, _ = segment_plan(w, k, v, lim)
        out.append(SegmentPlan(phases, w.s[k + 1], v[k + 1], w.acc[k + 1]))
        k += 1
    # The next window starts at zero acceleration: a release ends on an unpinned point.
    while out and out[-1].a_end_mm_s2 != 0.0:
        out.pop()
        k -= 1
    return out, k


def _first_window_on_limit_mm(
    envelope: FeedEnvelope, s: float, v: float, longest_mm: float, lim: PlanLimits
) -> float:
    """A re-plan's first window, up to ``longest_mm`` (timed at vmax): as long as
    :data:`FIRST_WINDOW_PERIODS` at the feed limit ahead take, plus
    :data:`FIRST_WINDOW_BRAKING_DISTANCES` from the highest feed on the way.

    The feed is at most the limit (or the start feed, above a lowered override's vmax): the
    rows of a first block never get farther. Timed on the limit's samples with 2 h / (v0 + v1),
    never longer than along the limit interpolated between them, so the window rather comes
    out long. Where the limit is low (tight loops, a small chord error) the window is that much
    shorter, and so is the refinement an override change waits for. Plans from rest keep the
    window timed at vmax: where windows end moves what refinement finds (on two of the bench's
    loop curves this one took 2 and 4 periods longer).
    """
    s_env, v_env = envelope.query(s, s + longest_mm)
    feed = np.minimum(v_env, max(v, lim.vmax_mm_s))
    with np.errstate(divide="ignore"):
        t_s = np.concatenate([[0.0], np.cumsum(2.0 * np.diff(s_env) / (feed[:-1] + feed[1:]))])
    t_start_s = float(np.interp(s, s_env, t_s))  # the first sample lies at or before s
    covered = int(np.searchsorted(t_s, t_start_s + FIRST_WINDOW_PERIODS * lim.T, side="right"))
    if covered >= len(s_env):
        return longest_mm  # (at least MIN_WINDOW_MM)
    v_high = max(v, float(feed[: covered + 1].max()))
    window_mm = (
        s_env[covered]
        - s
        + FIRST_WINDOW_BRAKING_DISTANCES * braking_distance_mm(v_high, lim.A, lim.J)
    )
    if window_mm > LIMIT_TIMED_WINDOW_FRACTION * longest_mm:
        return longest_mm
    return max(window_mm, MIN_WINDOW_MM)


def _cruise_cut(w: Window, k: int, v: list[float], lim: PlanLimits) -> SegmentPlan | None:
    """Segment k up to where its cruise ends, when it cruises at a peak the window end does not
    lower: a longer look-ahead moves only the ramp after the cruise (the first window of a plan
    at vmax then releases 33.5 of its 41 mm with the paper's limits, where half the cruise was
    20.5 mm, and a 64-row first block no longer waits for a second window)."""
    if w.cosine[k] == 1 or w.acc[k] != 0.0 or w.acc[k + 1] != 0.0:
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
    cut_mm = cruise_mm - 2.0 * MIN_POINT_GAP_MM
    phases = [*ramp_phases(v0, vp, lim.A, lim.J), Phase(cut_mm / vp, 0.0)]
    return SegmentPlan(tuple(phases), w.s[k] + up_mm + cut_mm, vp)


def plan_segments(
    envelope: FeedEnvelope,
    arc: ArcLengthTable,
    lim: PlanLimits,
    s_start: float,
    v_start: float,
    a_start: float,
    *,
    stop: bool,
    braking_end_mm_s: float | None = None,
    refined: RefinedPoints | None = None,
    warm_start: bool = False,
    plans: SegmentPlans | None = None,
    between_rounds: Callable[[], None] | None = None,
) -> Iterator[list[SegmentPlan]]:
    """Released stretches of the motion from the start state to rest, in order, in the groups
    that each window releases.

    The first stretch brings the start acceleration to zero (jerk-limited): at once, or for a
    start that brakes with ``braking_end_mm_s`` given, as quickly as the limits allow at the
    lower of that feed and vmax. Then windows of the path are planned and released. With
    ``stop`` the motion comes to rest as soon as the limits allow (the jerk-limited braking
    distance), or at the curve end if that comes first.

    Each refined window is remembered in ``refined`` when given; with ``warm_start`` its
    points seed the windows first (:mod:`planner.warmstart`). The first window is shorter
    (:data:`FIRST_WINDOW_PERIODS`), so that the first stretch comes sooner. The windows share
    the segment plans of ``plans`` when given. ``between_rounds`` is called between the
    refinement rounds of each window (:func:`planner.refine.refine`).
    """
    A, J = lim.A, lim.J
    s, v = s_start, v_start
    first, v_first = settle_phases(a_start, J), settled_speed(v, a_start, J)
    # Not below -BRAKING_TOLERANCE_MM_S2: a row at the zero acceleration of a pin read back as
    # -2.8e-14 mm/s².
    if a_start < -BRAKING_TOLERANCE_MM_S2 and braking_end_mm_s is not None:
        # Easing off at once ends the braking at the highest feed any plan from this state can
        # come to zero acceleration at: the braking end is never above it. Not at a lower vmax
        # (a lowered override): the windows brake down to it with the path ahead in view. Brought
        # to zero acceleration at the new vmax first, re-plans at 30 % could no longer stop at a
        # rest or the curve's end a few millimetres on: 22 delta, 1.4 A; 5 A.
        v_first = min(max(braking_end_mm_s, 0.0), v_first)
        first = transition_phases(v, a_start, v_first, 0.0, A, J)
    if first:
        train = PhaseTrain(0.0, s, v, a_start)
        train.extend(first)
        s, v = arc.extent_mm(train.s_mm), v_first
        yield [SegmentPlan(tuple(first), s, v)]
    full_window_mm = max(
        WINDOW_BRAKING_DISTANCES * braking_distance_mm(lim.vmax_mm_s, A, J), MIN_WINDOW_MM
    )
    # From above vmax (a lowered override) the first block brakes down to it first.
    v_top = max(v, lim.vmax_mm_s)
    first_window_mm = FIRST_WINDOW_PERIODS * lim.T * v_top + (
        FIRST_WINDOW_BRAKING_DISTANCES * braking_distance_mm(v_top, A, J)
    )
    first_window_mm = max(min(full_window_mm, first_window_mm), MIN_WINDOW_MM)
    window_mm = first_window_mm
    if warm_start:
        window_mm = _first_window_on_limit_mm(envelope, s, v, first_window_mm, lim)
    # A hair beyond the braking distance, so that round-off never makes the stop look infeasible.
    brake_mm = braking_distance_mm(v, A, J) * (1.0 + 1e-9) + 1e-9
    stop_at = arc.extent_mm(s + brake_mm) if stop else math.inf
    extra = 0.0
    crowded = False  # a window was planned shorter for its points (MAX_WINDOW_POINTS)
    # Since the last release: the longest window that released nothing, the shortest one too
    # crowded to refine, and how many were.
    barren_mm, crowded_mm, shortenings = 0.0, math.inf, 0
    released_s = 0.0  # motion time released so far
    crowded_points = RefinedPoints()  # what refining such a window found: seeds for the next
    rest_mm = None  # where the plan that released s comes to rest (the last window's end)
    while True:
        # The curve's end, once it is within reach of this window (the table grows to there).
        horizon = s + window_mm + extra + TAIL_WINDOW_FRACTION * window_mm
        reach = arc.extent_mm(horizon)
        curve_end = reach if reach < horizon else math.inf
        if v == 0.0 and 0.0 < curve_end - s <= MIN_POINT_GAP_MM:
            # At rest a hair before the end (a stop came to rest there): no window fits, and
            # the motion still ends exactly on the end point.
            yield [SegmentPlan((), curve_end, 0.0)]
            break
        if s >= curve_end or not (s < stop_at or v > 0.0):
            break
        target = min(stop_at, curve_end)
        s_end = s + window_mm + extra
        if target - s_end < TAIL_WINDOW_FRACTION * window_mm and target - s < crowded_mm:
            s_end = target  # one window to the end rather than a short one after it
        s_end = min(s_end, target)
        final = s_end >= target
        s_env, v_env = envelope.query(s, s_end)
        pts, cap, fv = sensitive_points(s_env, v_env, s, s_end, lim.vmax_mm_s)
        if s_end - pts[-1] > MIN_POINT_GAP_MM:
            pts.append(s_end)
            cap.append(0.0)
            fv.append(False)
        else:
            cap[-1] = 0.0
        w = Window(pts, cap, fv, None if plans is None else plans.for_limits(lim), rest_mm)
        initial_s = frozenset(w.s)
        if refined is not None and warm_start:
            refined.seed(w, lim.vmax_mm_s)
        crowded_points.seed(w, lim.vmax_mm_s)
        checker = Checker(s_env, v_env, lim)
        # A window too crowded to refine (MAX_WINDOW_POINTS) is planned shorter, halfway to
        # the longest one that released nothing, while that is a step away.
        length_mm = s_end - s
        v_high = max(v, min(float(v_env.max()), lim.vmax_mm_s))
        step_mm = max(
            MIN_WINDOW_MM, CROWDED_STEP_BRAKING_DISTANCES * braking_distance_mm(v_high, A, J)
        )
        shortenable = shortenings < MAX_SHORTENINGS and 0.5 * (length_mm - barren_mm) >= step_mm
        v_plan = refine(w, checker, v, lim, between_rounds, shortenable=shortenable)
        if v_plan is None:
            crowded_points.remember(w, initial_s, lim.vmax_mm_s)
            crowded, crowded_mm, shortenings = True, length_mm, shortenings + 1
            window_mm, extra = 0.5 * (barren_mm + length_mm), 0.0
            continue
        if refined is not None:
            refined.remember(w, initial_s, lim.vmax_mm_s)
        if final:
            if v_plan[-1] > 1e-9:
                # Too fast to stop where planned (start beyond the constraints): stop later.
                if s_end >= curve_end:
                    raise StartTooFast(s_start, v_start, a_start, curve_end, v_plan[-1])
                stop_at = stop_at + braking_distance_mm(v_plan[-1], A, J)
                extra = 0.0
                continue
            segments, k = _released(w, v_plan, v_plan, lim, final=True)
            yield segments
            return
        upper_caps = list(w.cap)
        upper_caps[-1] = lim.vmax_mm_s
        upper = w.speeds(v, lim, caps=upper_caps)
        segments, k = _released(w, v_plan, upper, lim, final=False)
        cut = _cruise_cut(w, k, v_plan, lim) if k < len(w.s) - 1 else None
        if cut is not None:
            segments.append(cut)
        if not segments:
            barren_mm = length_mm
            if math.isfinite(crowded_mm) and crowded_mm - length_mm >= 2.0 * step_mm:
                extra = 0.5 * (length_mm + crowded_mm) - window_mm
            else:
                crowded_mm = math.inf  # none, or no room below the crowded one: grow past it
                extra = 2.0 * (extra + window_mm)
            continue
        extra, barren_mm, crowded_mm, shortenings = 0.0, 0.0, math.inf, 0
        released_s += sum(phase.duration_s for segment in segments for phase in segment.phases)
        yield segments
        s, v = segments[-1].s_end_mm, segments[-1].v_end_mm_s
        rest_mm = s_end
        if warm_start and released_s < FIRST_WINDOW_PERIODS * lim.T:
            # Still short of a first block: the next window is timed on the limit too.
            window_mm = _first_window_on_limit_mm(envelope, s, v, first_window_mm, lim)
        elif crowded:
            # The path ahead of a crowded stretch is likely as crowded: the next window is as
            # long as half the points this one had room for would take.
            density_per_mm = len(w.s) / (w.s[-1] - w.s[0])
            window_mm = min(full_window_mm, 0.5 * MAX_WINDOW_POINTS / density_per_mm)
            crowded = window_mm < full_window_mm
        else:
            window_mm = full_window_mm
