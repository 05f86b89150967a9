"""One look-ahead window: its sensitive points, their speeds, and the segments between them.

Source: section 2.2 of Wang, Zhao, Lu, Liu, China Mechanical Engineering 23(3), 2012, 299-304.
- Curvature-rising module (:func:`sensitive_points`): walking forward, a curvature maximum (a
  local minimum of the feed limit below vmax) is a velocity-sensitive point with its limited
  feed; curvature-falling module: a stretch between two such points whose limit never reaches
  vmax is a region of frequent speed change, flag F_v_plan = 1.
- Between sensitive points, jerk-limited S-curve segments (:mod:`planner.profiles.scurve`) or,
  where flagged and needed, the cosine profile of eqs. (5)-(13); zero acceleration at the points.
Beyond the paper: points the refinement pins on the limit carry the limit's slope as their
acceleration, and the segments touching them are general jerk-limited motions between
(v0, a0) and (v1, a1) (:mod:`planner.profiles.transition`); the paper's sensitive points keep
zero acceleration.
Beyond the paper (motion-planning.md §1, §9 row 6): a bidirectional scan with jerk-feasible
speed changes (:func:`passes`: backward, the highest speed from which each next point can still
be met; forward, the highest speed reachable).

Units: s in mm, feeds mm/s, A mm/s², J mm/s³, T s. Pure computation; one window per plan of a
stretch, not thread-safe.
"""

from __future__ import annotations

import bisect
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
from planner.profiles.transition import (
    highest_end_speed,
    highest_start_speed,
    segment_phases_between,
    transition_distance_mm,
)

#: Relative excess of a ramp over its distance still counted as fitting (round-off).
RAMP_FIT_RTOL = 1e-9
#: Times the scan lowers a pinned point it cannot honour before unpinning it.
PIN_RETRIES = 3
#: Points closer than this are not inserted, mm.
MIN_POINT_GAP_MM = 1e-7
#: A segment's feed cap at least this fraction above the highest feed it can reach binds
#: nothing (room for round-off, :func:`segment_cap`).
REACH_MARGIN = 1e-6


@dataclass(frozen=True)
class PlanLimits:
    """The limits one plan uses: feed cap (vmax), tangential A and J, period T."""

    vmax_mm_s: float
    A: float
    J: float
    T: float


@dataclass(frozen=True)
class SegmentPlan:
    """A released stretch of motion: phases from (s, v, a) at time t, ending at s_end, v_end
    and a_end."""

    phases: tuple[Phase, ...]
    s_end_mm: float
    v_end_mm_s: float
    a_end_mm_s2: float = 0.0


_Plans = dict[tuple, "tuple[tuple[Phase, ...], float] | None"]


class SegmentPlans:
    """Planned phases of segment shapes, shared by the windows of a path's plans.

    A shape's plan depends on its key (:meth:`Window.key`, which holds the feed cap the
    segment plans under) and the plan's A and J alone, so the windows of every plan of one path
    with the same A and J share one table, whatever their feed override: where the override's
    vmax is above what a segment can reach, its cap is that reach (:func:`segment_cap`).
    Consecutive windows overlap, and a re-plan from a motion state (a feed override, a resume)
    meets again most shapes that earlier plans of the stretch met: on the bench's re-plans the
    median first block of a cusped curve drops from 3.8 to 3.4 ms and of a curve with loops
    from 8.4 to 7.4 ms. Bounded: the tables are emptied when they hold ``max_shapes`` shapes
    together.
    """

    def __init__(self, max_shapes: int = 8192) -> None:
        self.max_shapes = max_shapes
        self._by_limits: dict[tuple[float, float], _Plans] = {}

    def __len__(self) -> int:
        return sum(len(plans) for plans in self._by_limits.values())

    def for_limits(self, lim: PlanLimits) -> _Plans:
        """The table of plans with the A and J of ``lim`` (for the next window)."""
        if len(self) >= self.max_shapes:
            self._by_limits.clear()
        return self._by_limits.setdefault((lim.A, lim.J), {})


class Window:
    """Sensitive points of one look-ahead window and the refinement state of its segments.

    A point has zero acceleration (the paper's sensitive points, the start, the window end,
    and the points refinement adds where the limit cannot be followed), or is *pinned* on the
    feed limit: its speed is its cap and its acceleration the limit's own slope there, so that
    the plan runs along the limit instead of stopping its acceleration at every point. A pinned
    point the scan cannot honour falls back to zero acceleration under ``flat_cap``.
    """

    def __init__(
        self,
        s: list[float],
        cap: list[float],
        fv_plan: list[bool],
        plans: _Plans | None = None,
        rest_mm: float | None = None,
    ) -> None:
        self.s = s
        self.cap = cap
        self.fv_plan = fv_plan  # per segment: region of frequent speed change (F_v_plan = 1)
        self.acc = [0.0] * len(s)
        self.pinned = [False] * len(s)
        self.flat_cap = list(cap)  # cap of a point at zero acceleration
        self.peak_cap = [math.inf] * (len(s) - 1)
        self.cosine = [0] * (len(s) - 1)  # 0: S-curve, 1: cosine, 2: cosine rejected
        self.braking = False  # the first segment brakes from the start state (brake_first)
        # Where the plan that released the start state comes to rest (the previous window's
        # end), if known: from the start state, a stop there keeps under the limit.
        self.rest_mm = rest_mm
        # Planned phases and top feed of each segment shape met so far (see key), in this window
        # or, given ``plans`` (:meth:`SegmentPlans.for_limits`), in any with the same A and J.
        self.plans: _Plans = {} if plans is None else plans

    def key(self, k: int, v: list[float], cap: float) -> tuple:
        """What segment k's plan depends on besides A and J: its ends, end states, feed cap
        (:func:`segment_cap`; within one window, whose limits are fixed, its peak cap will do)
        and profile kind."""
        return (
            self.s[k],
            self.s[k + 1],
            v[k],
            v[k + 1],
            self.acc[k],
            self.acc[k + 1],
            cap,
            self.cosine[k],
        )

    def keys(self, v: list[float]) -> list[tuple]:
        """:meth:`key` of every segment with its peak cap, in order (one pass, no call per
        segment: a refinement round keys every segment of its window)."""
        s, acc = self.s, self.acc
        return list(
            zip(
                s[:-1],
                s[1:],
                v[:-1],
                v[1:],
                acc[:-1],
                acc[1:],
                self.peak_cap,
                self.cosine,
                strict=True,
            )
        )

    def insert(
        self,
        k: int,
        s_new: float,
        cap_new: float,
        *,
        acc: float = 0.0,
        flat_cap: float | None = None,
    ) -> None:
        """Split segment k at s_new with a new point (pinned when ``flat_cap`` is given)."""
        self.s.insert(k + 1, s_new)
        self.cap.insert(k + 1, cap_new)
        self.acc.insert(k + 1, acc if flat_cap is not None else 0.0)
        self.pinned.insert(k + 1, flat_cap is not None)
        self.flat_cap.insert(k + 1, cap_new if flat_cap is None else flat_cap)
        self.fv_plan.insert(k + 1, self.fv_plan[k])
        self.peak_cap[k : k + 1] = [math.inf, math.inf]
        self.cosine[k : k + 1] = [2, 2] if flat_cap is not None else [0, 0]

    def unpin(self, k: int) -> None:
        """Point k back to zero acceleration, under its flat cap."""
        self.pinned[k] = False
        self.acc[k] = 0.0
        self.cap[k] = min(self.cap[k], self.flat_cap[k])

    def _shapeless(
        self, v: list[float], acc: list[float], pinned: list[bool], lim: PlanLimits
    ) -> int | None:
        """The pinned end of the first segment with no motion of the shapes tried, or None.

        Every segment touching a pin is tried, a pin without acceleration (on a flat limit)
        too: the scan gives a pin its cap whether or not the segment before reaches it. Such a
        segment is an S-curve (:func:`segment_plan`), which needs its ramp to fit.
        """
        for k in range(len(self.s) - 1):
            if acc[k] != 0.0 or acc[k + 1] != 0.0:
                shapeless = _shape(self, self.s, k, v, acc, lim) is None
            elif pinned[k] or pinned[k + 1]:
                L = self.s[k + 1] - self.s[k]
                shapeless = ramp_distance_mm(v[k], v[k + 1], lim.A, lim.J) > L * (
                    1.0 + RAMP_FIT_RTOL
                )
            else:
                continue
            if shapeless:
                return k + 1 if pinned[k + 1] else k
        return None

    @property
    def rest_inside(self) -> bool:
        """Whether :attr:`rest_mm` is known and inside the window (a stop the plan may fall
        back on, :meth:`rest_first`)."""
        return self.rest_mm is not None and self.s[0] < self.rest_mm < self.s[-1]

    def rest_first(self) -> None:
        """Replace the points up to :attr:`rest_mm` with a stop there (see
        :func:`planner.refine.refine`)."""
        m = bisect.bisect_right(self.s, self.rest_mm)
        self.merge_first(m, math.inf)
        self.insert(0, self.rest_mm, 0.0)
        self.braking = False

    def copy(self) -> Window:
        """A copy whose points and segments may be edited apart from this window's (the table
        of plans is shared)."""
        twin = Window(list(self.s), list(self.cap), list(self.fv_plan), self.plans, self.rest_mm)
        twin.acc, twin.pinned = list(self.acc), list(self.pinned)
        twin.flat_cap, twin.peak_cap = list(self.flat_cap), list(self.peak_cap)
        twin.cosine = list(self.cosine)
        twin.braking = self.braking
        return twin

    def merge_first(self, m: int, peak_cap: float) -> None:
        """Remove the points between the start and point m: one segment, held under peak_cap."""
        for column in (self.s, self.cap, self.acc, self.pinned, self.flat_cap, self.fv_plan):
            del column[1:m]
        del self.peak_cap[1:m], self.cosine[1:m]
        self.peak_cap[0] = peak_cap
        self.cosine[0] = 2
        self.braking = True

    def speeds(
        self, v_start: float, lim: PlanLimits, caps: list[float] | None = None
    ) -> list[float]:
        """Speeds of the points by :func:`passes`, lowering the pinned points it cannot honour
        (halfway to their flat cap ``PIN_RETRIES`` times, then halving their acceleration as
        often, as a pin just before the limit's minimum needs; then unpinned, which tends to
        refuse the pins before it in turn; each lowering is scanned again only as far as it
        reaches, :class:`SpeedScan`); with other ``caps`` (a look at the plan without the stop
        at the window end) the window is left as it is."""
        keep = caps is not None
        caps = list(self.cap if caps is None else caps)
        acc, pinned = list(self.acc), list(self.pinned)
        tries = [0] * len(self.s)
        scan = SpeedScan(self.s, caps, v_start, lim, acc, pinned)
        bad = scan.scan()
        while True:
            if bad is None:
                bad = self._shapeless(scan.v, acc, pinned, lim)
            if bad is None:
                return scan.v
            if tries[bad] < PIN_RETRIES and caps[bad] > self.flat_cap[bad]:
                # Lower, along the limit's slope: the acceleration scales with the feed.
                lower = 0.5 * (caps[bad] + self.flat_cap[bad])
                acc[bad] *= lower / caps[bad]
                caps[bad] = lower
                tries[bad] += 1
            elif tries[bad] < 2 * PIN_RETRIES:
                # At (or lowered towards) its flat cap: settle sooner. The bench's loops
                # measured 1.038-1.050 of their reference with these pins unpinned at once,
                # 1.032-1.040 with them kept.
                acc[bad] *= 0.5
                tries[bad] += 1
            else:
                pinned[bad], acc[bad] = False, 0.0
                caps[bad] = min(caps[bad], self.flat_cap[bad])
            if not keep:
                self.cap[bad], self.acc[bad], self.pinned[bad] = caps[bad], acc[bad], pinned[bad]
            bad = scan.scan(bad)


class SpeedScan:
    """The bidirectional scan of :func:`passes`, kept between changes to one point at a time.

    :meth:`Window.speeds` lowers the pins the scan cannot honour one by one, and a re-plan's
    window at a chord error of 0.1 µm may lower hundreds: one re-plan of a loop curve ran 370
    full scans, 90 % of its CPU time. A change at one point reaches the backward speeds before
    it and the forward speeds after it only as far as they change: where a speed computed again
    equals the one before, the rest of that pass is as it was (the same inputs give the same
    speeds), so the scan stops there.

    ``cap``, ``acc`` and ``pinned`` are the caller's lists, read at every scan.
    """

    def __init__(
        self,
        s: list[float],
        cap: list[float],
        v_start: float,
        lim: PlanLimits,
        acc: list[float],
        pinned: list[bool],
    ) -> None:
        self.s, self.cap, self.acc, self.pinned, self.lim = s, cap, acc, pinned, lim
        n = len(s)
        self.back = list(cap)  # highest speed from which each next point can still be met
        self.v = [v_start] + [0.0] * (n - 1)  # highest speed reachable
        self._back_from = n - 1  # back[k] is scanned for k >= _back_from
        self._forward_to = 0  # v[k] is scanned for k <= _forward_to

    @property
    def backward_done(self) -> bool:
        """Whether the backward pass reached the start (no point before it failed)."""
        return self._back_from <= 1

    def scan(self, changed: int | None = None) -> int | None:
        """Scan again after point ``changed`` had its cap, acceleration or pin changed (None:
        the first scan); returns the first pinned point that cannot be met and left, as
        :func:`passes` does, or None."""
        n = len(self.s)
        resumable = changed is not None and self.backward_done and self._forward_to == n - 1
        top = n - 2
        if changed is not None:
            self.back[changed] = self.cap[changed]
            if changed >= self._back_from - 1:  # the speeds after it are scanned
                top = min(changed, n - 2)
        first_new, bad = self._backward(top, changed if resumable else None)
        if bad is not None:
            return bad
        return self._forward(first_new if resumable else 1, changed if resumable else None)

    def _backward(self, top: int, changed: int | None) -> tuple[int, int | None]:
        """Backward speeds from point ``top`` down; with ``changed`` (the last scan complete),
        only as far as they differ from the last scan's. Returns the lowest point whose speed
        may differ, and the pin that cannot be met and left (or None)."""
        s, cap, acc, pinned, back = self.s, self.cap, self.acc, self.pinned, self.back
        A, J = self.lim.A, self.lim.J
        for k in range(top, 0, -1):
            before = back[k]
            L = s[k + 1] - s[k]
            if pinned[k]:
                if pinned[k + 1]:
                    fits = transition_distance_mm(
                        cap[k], acc[k], back[k + 1], acc[k + 1], A, J
                    ) <= L * (1.0 + RAMP_FIT_RTOL)
                else:
                    # A point of zero acceleration next may be met at any speed up to its own:
                    # a pin just before a minimum of the limit settles below it.
                    fits = highest_end_speed(cap[k], acc[k], L, back[k + 1], A, J) is not None
                if not fits:
                    # Of two pins too far apart in feed, the faster one gives way.
                    self._back_from, self._forward_to = k + 1, 0
                    return k, k + 1 if pinned[k + 1] and cap[k + 1] > cap[k] else k
            elif acc[k + 1] == 0.0:
                back[k] = min(cap[k], max_ramp_speed(back[k + 1], L, A, J))
            else:
                start = highest_start_speed(back[k + 1], acc[k + 1], L, cap[k], A, J)
                if start is None:
                    self._back_from, self._forward_to = k + 1, 0
                    return k, k + 1
                back[k] = start
            if changed is not None and k < changed and back[k] == before:
                return k + 1, None
        self._back_from = 1
        return 1, None

    def _forward(self, start: int, changed: int | None) -> int | None:
        """Forward speeds from point ``start`` on (from the first unscanned one, if earlier);
        with ``changed`` (the last scan complete), only as far as they differ from the last
        scan's. Returns the first point that cannot be left, or None."""
        s, cap, acc, pinned, back, v = self.s, self.cap, self.acc, self.pinned, self.back, self.v
        A, J = self.lim.A, self.lim.J
        n = len(s)
        for k in range(min(start, self._forward_to + 1), n):
            before = v[k]
            L = s[k] - s[k - 1]
            if pinned[k]:
                v[k] = cap[k]
            elif acc[k - 1] != 0.0:
                end = highest_end_speed(v[k - 1], acc[k - 1], L, back[k], A, J)
                if end is None:
                    self._forward_to = k - 1
                    return k - 1
                v[k] = end
            else:
                v[k] = min(back[k], max_ramp_speed(v[k - 1], L, A, J))
                fits = L * (1.0 + RAMP_FIT_RTOL)
                if v[k] < v[k - 1] and ramp_distance_mm(v[k - 1], v[k], A, J) > fits:
                    # Stopping fits where slowing to v[k] does not: slow down further instead.
                    # Within the points' resolution: a re-plan from a row of a plan's hardest
                    # braking took 1.3e-8 mm more to stop (its start state is sampled), and
                    # braking hardest instead came to the curve's end at 44 mm/s, the lowest
                    # feed that ramps there at zero acceleration.
                    if braking_distance_mm(v[k - 1], A, J) <= fits + MIN_POINT_GAP_MM:
                        v[k] = fitting_lower_speed(v[k - 1], v[k], L, A, J)
                    else:
                        # Only a start state faster than the constraints allow gets here:
                        # brake hardest.
                        v[k] = max(v[k], min_ramp_speed(v[k - 1], L, A, J))
            if changed is not None and k > changed and v[k] == before:
                return None
        self._forward_to = n - 1
        return None


def passes(
    s: list[float],
    cap: list[float],
    v_start: float,
    lim: PlanLimits,
    acc: list[float] | None = None,
    pinned: list[bool] | None = None,
) -> tuple[list[float], int | None] | list[float]:
    """Bidirectional scan: backward (can still meet the next point), then forward (reachable).

    Without ``acc`` every point has zero acceleration and the speeds are returned. With it
    (and ``pinned``), a pinned point keeps its cap and acceleration where it can be met and
    left; returns the speeds and the first pinned point that cannot (or None).
    """
    n = len(s)
    scan = SpeedScan(
        s,
        cap,
        v_start,
        lim,
        [0.0] * n if acc is None else acc,
        [False] * n if pinned is None else pinned,
    )
    bad = scan.scan()
    if acc is None:
        return scan.v
    return (scan.v if scan.backward_done else scan.back), bad


def _shape(
    w: Window, s: list[float], k: int, v: list[float], acc: list[float], lim: PlanLimits
) -> tuple[tuple[Phase, ...], float] | None:
    """Phases and top feed of a segment with an end of non-zero acceleration (cached)."""
    v_cap = segment_cap(w, s, k, v, lim)
    key = (s[k], s[k + 1], v[k], v[k + 1], acc[k], acc[k + 1], v_cap, 2)
    if key not in w.plans:
        phases = segment_phases_between(
            v[k], acc[k], v[k + 1], acc[k + 1], s[k + 1] - s[k], v_cap, lim.A, lim.J
        )
        low, top = (-1.0, math.inf) if phases is None else _speed_range(v[k], acc[k], phases)
        # A transition may overshoot its ends: above the feed cap, or backwards, it is no
        # motion of this plan.
        fits = low >= 0.0 and top <= max(v_cap, v[k], v[k + 1]) * (1.0 + RAMP_FIT_RTOL)
        w.plans[key] = (tuple(phases), top) if fits else None
    return w.plans[key]


def segment_cap(w: Window, s: list[float], k: int, v: list[float], lim: PlanLimits) -> float:
    """The feed cap segment k plans under: the lowest of vmax, its peak cap and the highest
    feed any motion between its ends can reach (with |a| <= A, v² <= A L + (v0² + v1²) / 2;
    not below the faster end, which an infeasible segment keeps as before).

    A cap above that reach binds nothing, so the segment's plan is the same under any feed
    override whose vmax is above it (:class:`SegmentPlans`)."""
    v0, v1 = v[k], v[k + 1]
    reach = math.sqrt(lim.A * (s[k + 1] - s[k]) + 0.5 * (v0 * v0 + v1 * v1))
    return min(lim.vmax_mm_s, w.peak_cap[k], max(reach * (1.0 + REACH_MARGIN), v0, v1))


def _speed_range(v: float, a: float, phases: list[Phase]) -> tuple[float, float]:
    """Lowest and highest feed of constant-jerk phases from (v, a): at their ends or where the
    acceleration crosses zero."""
    low = high = v
    for phase in phases:
        tau, j = phase.duration_s, phase.jerk_mm_s3
        if j != 0.0 and 0.0 < -a / j < tau:  # a crosses zero inside: a speed extremum
            t0 = -a / j
            extremum = v + a * t0 + j * t0 * t0 / 2.0
            low, high = min(low, extremum), max(high, extremum)
        v += a * tau + j * tau * tau / 2.0
        a += j * tau
        low, high = min(low, v), max(high, v)
    return low, high


def segment_plan(
    w: Window, k: int, v: list[float], lim: PlanLimits
) -> tuple[tuple[Phase, ...], float] | None:
    """Phases of segment k and its highest planned feed (computed once per window and shape);
    None where an end is pinned and no motion between the ends stays under the peak cap (the
    scan unpins such ends, so only a trial of a lower peak cap meets it)."""
    if w.acc[k] != 0.0 or w.acc[k + 1] != 0.0:
        return _shape(w, w.s, k, v, w.acc, lim)
    key = w.key(k, v, segment_cap(w, w.s, k, v, lim))
    if key not in w.plans:
        v0, v1, L = v[k], v[k + 1], w.s[k + 1] - w.s[k]
        if w.cosine[k] == 1:
            t_a = cosine_time_s(v0, v1, L)  # eq. (12)
            w.plans[key] = (Phase(t_a, cosine_dv_mm_s=v1 - v0),), max(v0, v1)
        else:
            vp = cruise_speed(v0, v1, L, key[6], lim.A, lim.J)
            w.plans[key] = tuple(segment_phases(v0, vp, v1, L, lim.A, lim.J)), max(v0, vp, v1)
    return w.plans[key]


def segment_time_s(w: Window, k: int, v: list[float], lim: PlanLimits) -> float:
    """Duration of segment k as planned (inf where it has no motion, see segment_plan)."""
    plan = segment_plan(w, k, v, lim)
    return math.inf if plan is None else sum(phase.duration_s for phase in plan[0])


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
