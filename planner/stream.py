"""The public streaming API: setpoints of a curve, block after block, with bounded memory.

Source: the look-ahead interpolator of Wang, Zhao, Lu, Liu, China Mechanical Engineering 23(3),
2012, 299-304 (section 2: eqs. (2)-(13)); beyond the paper: start from any motion state (feed
override, resume), controlled stop on the path (feed hold), exact landing on the end point.

A :class:`Path` holds what is shared by every plan of a curve: the arc-length table and the
feed-limit envelope, both built lazily per chunk of knot spans as the windows reach them, so
preparing a Path is cheap and the first block comes as fast on a long curve as on a short one;
the points refinement added, which re-plans from a motion state start from
(:mod:`planner.warmstart`); and the segment shapes planned so far
(:class:`planner.window.SegmentPlans`). :func:`stream_setpoints` plans a window ahead
(:mod:`planner.lookahead`), samples the released closed-form motion every period (vectorised,
no loop per period) and turns arc length into curve parameters (:mod:`planner.interpolator`).

Units: mm, s; feeds mm/s, accelerations mm/s², jerks mm/s³. Rows are spaced by period_s, their
time t_s counted from the start state. Pure computation: no clock, no thread; a stream is a
generator used by one thread; a Path may be shared by streams used one at a time (its tables
grow as they are used).

Invariants: no NaN in a row; with look-ahead, |a| <= amax and |j| <= jmax in the planned
profile, feed <= vmax (or braking down to it); the final row of a stream that reaches the curve
end is exactly C(last knot), at rest. A stop at a sharp corner (zero feed limit) dwells until a
period boundary, so that the corner itself is a setpoint.

Not modelled: reverse motion along the path; per-axis jerk; a start that brakes without the
earlier plan's braking end (:func:`braking_end_from_rows`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace

import numpy as np

from planner.arclength import ArcLengthTable
from planner.envelope import MAX_OVERRIDE_RATIO, FeedEnvelope
from planner.feed import adaptive_feed, tangential_accel_limit
from planner.interpolator import Interpolator
from planner.lookahead import BRAKING_TOLERANCE_MM_S2, PlanLimits, plan_segments
from planner.nurbs import NurbsCurve
from planner.profiles import Phase, PhaseTrain
from planner.types import Limits, MotionState, SetpointBlock
from planner.warmstart import RefinedPoints
from planner.window import SegmentPlans

#: Relative tolerance when deciding that a time falls on a period boundary.
_TIME_EPS = 1e-9
#: Largest batch of rows whose parameters and positions are computed together.
BATCH_ROWS = 1024


class Path:
    """Geometry prepared once per curve and shared by every re-plan of it.

    :param curve: the tool path.
    :param limits: its chord error, normal-acceleration and per-axis limits shape the feed-limit
        envelope; vmax is applied at plan time (overrides up to 200 % of this vmax).
    :param period_s: interpolation period T.
    :raises ValueError: for a period that is not finite and > 0, or axis limits not matching the
        curve dimension.
    """

    def __init__(self, curve: NurbsCurve, limits: Limits, period_s: float) -> None:
        if not (math.isfinite(period_s) and period_s > 0.0):
            raise ValueError(f"period_s: got {period_s!r}, must be finite and > 0")
        for name in ("axis_vmax_mm_s", "axis_amax_mm_s2"):
            values = getattr(limits, name)
            if values is not None and len(values) != curve.dimension:
                raise ValueError(
                    f"limits: {name}: got {len(values)} values for a curve of dimension "
                    f"{curve.dimension}, must be one per axis"
                )
        self.curve = curve
        self.limits = limits
        self.period_s = float(period_s)
        self.arc = ArcLengthTable(curve)
        self.envelope = FeedEnvelope(curve, self.arc, limits, self.period_s)
        self.refined = RefinedPoints()
        """What refinement found in earlier plans: re-plans start from it."""
        self.segment_plans = SegmentPlans()
        """Segment shapes planned so far, shared by the windows of every plan."""

    @property
    def length_mm(self) -> float:
        """Length of the curve, mm: builds the whole arc-length table on first use (on a
        100,000-span curve about half a second of CPU time and 50 MB); a stream does not need
        it before its first block."""
        return self.arc.length_mm

    def check(self, limits: Limits, period_s: float) -> None:
        """Raise ValueError unless ``limits`` and ``period_s`` fit this path's envelope."""
        if abs(period_s - self.period_s) > _TIME_EPS * self.period_s:
            raise ValueError(
                f"period_s: got {period_s!r}, the path was prepared for {self.period_s!r}"
            )
        if replace(limits, vmax_mm_s=self.limits.vmax_mm_s) != self.limits:
            raise ValueError(
                "limits: chord error, normal or axis limits differ from those the path was "
                "prepared with; prepare a new Path"
            )
        if limits.vmax_mm_s > MAX_OVERRIDE_RATIO * self.limits.vmax_mm_s * (1.0 + 1e-12):
            raise ValueError(
                f"limits: vmax_mm_s: got {limits.vmax_mm_s!r}, must be <= "
                f"{MAX_OVERRIDE_RATIO:g} x the path's {self.limits.vmax_mm_s!r}"
            )


def stream_setpoints(
    path: Path,
    limits: Limits,
    period_s: float,
    *,
    start: MotionState | None = None,
    stop: bool = False,
    lookahead: bool = True,
    update: str = "corrected",
    block_periods: int = 256,
    braking_end_mm_s: float | None = None,
    between_rounds: Callable[[], None] | None = None,
) -> Iterator[SetpointBlock]:
    """Setpoints from ``start`` to the curve end (or to rest with ``stop``), block by block.

    :param path: the prepared curve.
    :param limits: limits of this plan (a feed override scales vmax).
    :param period_s: interpolation period T (the path's).
    :param start: motion state to continue from; the first row is then one period after it.
        Default: at rest at s = 0, and the first row is that start.
    :param braking_end_mm_s: for a start that brakes (required then): the feed the earlier
        plan's braking comes to (:func:`braking_end_from_rows`); the plan brakes to it, or to
        vmax if lower, as quickly as the limits allow, and plans on from there. A start that
        does not brake eases its acceleration off at once.
    :param stop: decelerate to rest as soon as the jerk and acceleration limits allow.
    :param lookahead: False gives the paper's comparison case, eq. (4) alone each period.
    :param update: parameter update, ``"corrected"`` or ``"taylor2"`` (eq. (2)).
    :param block_periods: rows per block (the last block may be shorter).
    :param between_rounds: called between the refinement rounds of the look-ahead's windows:
        a caller planning ahead may do urgent work of its own there, without waiting for the
        block (it must not use this generator meanwhile).
    :raises ValueError: for bad arguments (named), or limits the path was not prepared for.
    """
    path.check(limits, period_s)
    if block_periods < 1:
        raise ValueError(f"block_periods: got {block_periods!r}, must be >= 1")
    fresh = start is None
    state = MotionState(0.0) if start is None else start
    if not (math.isfinite(state.s_mm) and 0.0 <= state.s_mm <= path.arc.extent_mm(state.s_mm)):
        raise ValueError(f"start.s_mm: got {state.s_mm!r}, must be within [0, {path.length_mm}]")
    if not (math.isfinite(state.v_mm_s) and state.v_mm_s >= 0.0 and math.isfinite(state.a_mm_s2)):
        raise ValueError(f"start: got {state!r}, feed must be >= 0 and both finite")
    if state.a_mm_s2 < -BRAKING_TOLERANCE_MM_S2 and braking_end_mm_s is None:
        raise ValueError(
            f"start.a_mm_s2: got {state.a_mm_s2!r}, a start that brakes needs braking_end_mm_s "
            "(the feed its braking comes to): easing the braking off at once would give up "
            "braking the curve ahead may need"
        )
    if braking_end_mm_s is not None and not (
        math.isfinite(braking_end_mm_s) and braking_end_mm_s >= 0.0
    ):
        raise ValueError(f"braking_end_mm_s: got {braking_end_mm_s!r}, must be finite and >= 0")
    interp = Interpolator(path.curve, path.arc, update, state.s_mm)
    rows = (
        _planned_rows(
            path,
            limits,
            state,
            stop=stop,
            fresh=fresh,
            min_rows=block_periods,
            braking_end_mm_s=braking_end_mm_s,
            between_rounds=between_rounds,
        )
        if lookahead
        else _adaptive_rows(path, limits, state, stop=stop, fresh=fresh)
    )
    yield from _blocks(path, interp, rows, block_periods)


@dataclass(frozen=True)
class BrakingEnd:
    """Where an earlier plan's braking ends, found in its rows (:func:`braking_end_from_rows`)."""

    row: int
    """Index of the first row given that does not brake."""
    feed_mm_s: float
    """The feed the braking comes to."""


def braking_end_from_rows(
    feed_mm_s: Sequence[float], accel_mm_s2: Sequence[float], period_s: float
) -> BrakingEnd | None:
    """Where an earlier plan's braking ends, from its rows starting at a braking one, or None
    while every row given brakes.

    The braking ends between the last braking row and the first that does not brake, where the
    acceleration crosses zero; over that period the plan's jerk is taken as constant (a braking
    ends on one jerk phase), which puts the crossing's feed a²T / (2 (a_next - a)) below the last
    braking row's. The feed it comes to is the lower of that and the lowest feed of the rows.

    For a re-plan from a braking row (``stream_setpoints(start=..., braking_end_mm_s=...)``):
    braking as hard as the limits allow to a feed the earlier plan comes down to anyway is never
    faster, at any point of the path, than that plan's braking.
    """
    for k, accel in enumerate(accel_mm_s2):
        if accel >= -BRAKING_TOLERANCE_MM_S2:
            if k == 0:
                return BrakingEnd(0, float(feed_mm_s[0]))
            a, a_next = float(accel_mm_s2[k - 1]), float(accel)
            crossing = float(feed_mm_s[k - 1]) - a * a * period_s / (2.0 * (a_next - a))
            return BrakingEnd(k, max(0.0, min(float(min(feed_mm_s[: k + 1])), crossing)))
    return None


def plan_setpoints(path: Path, limits: Limits, period_s: float, **kwargs) -> SetpointBlock:
    """All setpoints of :func:`stream_setpoints` in one block (for tests and the CLI)."""
    return SetpointBlock.concatenate(list(stream_setpoints(path, limits, period_s, **kwargs)))


_Rows = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def _planned_rows(
    path: Path,
    limits: Limits,
    state: MotionState,
    *,
    stop: bool,
    fresh: bool,
    min_rows: int,
    braking_end_mm_s: float | None,
    between_rounds: Callable[[], None] | None,
) -> Iterator[tuple[_Rows, bool]]:
    """(t, s, v, a, j) rows of the look-ahead plan, at least ``min_rows`` per batch until the
    last, and whether the batch ends the motion."""
    T = path.period_s
    lim = PlanLimits(
        vmax_mm_s=limits.vmax_mm_s,
        A=tangential_accel_limit(limits),
        J=limits.jmax_mm_s3,
        T=T,
    )
    segments = plan_segments(
        path.envelope,
        path.arc,
        lim,
        state.s_mm,
        state.v_mm_s,
        state.a_mm_s2,
        stop=stop,
        braking_end_mm_s=braking_end_mm_s,
        refined=path.refined,
        warm_start=not fresh,
        plans=path.segment_plans,
        between_rounds=between_rounds,
    )
    t, s, v, a = 0.0, state.s_mm, state.v_mm_s, state.a_mm_s2
    k_next = k_end = 0 if fresh else 1
    # What the windows release is sampled together once it holds min_rows rows, before the
    # next window is planned: one vectorised sampling instead of one per segment.
    train = PhaseTrain(t, s, v, a)
    for released in segments:
        for segment in released:
            train.restart(t, s, v, a)  # each segment starts from its exact planned state
            train.extend(segment.phases)
            t_end = train.t_s
            if segment.v_end_mm_s == 0.0:
                # At rest inside the motion (a sharp corner): wait for the next period boundary
                # (or none, where the rest falls on one within round-off).
                t_end = max(math.ceil(t_end / T - _TIME_EPS) * T, t_end)
                train.extend([Phase(t_end - train.t_s, 0.0)])
            k_end = max(k_end, math.ceil(t_end / T - _TIME_EPS))  # rows with k T < t_end
            t, s, v, a = t_end, segment.s_end_mm, segment.v_end_mm_s, segment.a_end_mm_s2
        if k_end - k_next >= min_rows:
            times = np.arange(k_next, k_end) * T
            yield (times, *train.sample(times)), False
            k_next = k_end
            train = PhaseTrain(t, s, v, a)
    times = np.arange(k_next, k_end) * T
    rows = train.sample(times)
    k_last = max(k_end, math.ceil(t / T - _TIME_EPS))
    at_rest = (k_last * T, s, 0.0, 0.0, 0.0)
    yield tuple(np.append(c, end) for c, end in zip((times, *rows), at_rest, strict=True)), True


def _adaptive_rows(
    path: Path, limits: Limits, state: MotionState, *, stop: bool, fresh: bool
) -> Iterator[tuple[_Rows, bool]]:
    """The paper's no-look-ahead case: feed = min(vmax, chord-error feed), eq. (4), each period.

    Sequential by nature (the feed of a period depends on where the previous one ended); no
    acceleration planning, which is the point of the comparison.
    """
    T = path.period_s
    curve, arc = path.curve, path.arc
    s = state.s_mm
    t, v_prev, a_prev = 0.0, state.v_mm_s, state.a_mm_s2
    rows: list[tuple[float, float, float, float, float]] = []
    if fresh:
        rows.append((0.0, s, 0.0, 0.0, 0.0))
    while s < path.length_mm and not stop:
        u = arc.u_of_s(s)
        kappa = curve.curvature(u)
        v = float(adaptive_feed(kappa, limits.vmax_mm_s, limits.chord_error_mm, T)[0])  # eq. (4)
        s = min(s + v * T, path.length_mm)
        t += T
        a = (v - v_prev) / T
        rows.append((t, s, v, a, (a - a_prev) / T))
        v_prev, a_prev = v, a
        if len(rows) >= 256:
            yield tuple(np.array(c) for c in zip(*rows, strict=True)), False  # type: ignore[misc]
            rows = []
    rows.append((t + T, s, 0.0, -v_prev / T, (-v_prev / T - a_prev) / T))
    yield tuple(np.array(c) for c in zip(*rows, strict=True)), True  # type: ignore[misc]


def _blocks(
    path: Path, interp: Interpolator, rows: Iterator[tuple[_Rows, bool]], block_periods: int
) -> Iterator[SetpointBlock]:
    """Group rows into blocks, adding u and positions; the final block has last=True.

    Parameters and positions are computed together for the first block's rows as soon as they
    are planned, then for twice as many, and so on up to ``BATCH_ROWS``: the first block waits
    for its own rows alone (a first window may release several hundred), and later ones share
    the fixed cost of the vectorised curve evaluations.
    """
    pending: list[_Rows] = []
    count = 0
    batch = block_periods
    largest = max(block_periods, BATCH_ROWS)
    for rows_in, done in rows:
        pending.append(rows_in)
        count += len(rows_in[0])
        while count >= batch or (done and count > 0):
            cols = [np.concatenate([p[i] for p in pending]) for i in range(5)]
            n = min(count, batch)
            if not (done and n == count):
                n -= n % block_periods  # whole blocks until the last
            rest = [c[n:] for c in cols]
            big = _block(path, interp, [c[:n] for c in cols], last=done and n == count)
            for start in range(0, n, block_periods):
                yield big.rows(start, start + block_periods)
            pending = [tuple(rest)] if n < count else []  # type: ignore[list-item]
            count -= n
            batch = min(2 * batch, largest)


def _block(path: Path, interp: Interpolator, cols: list[np.ndarray], last: bool) -> SetpointBlock:
    t, s, v, a, j = cols
    u = interp.parameters(s)
    position = path.curve.evaluate(u)[0]
    # Rows on the curve's end (the table is complete once a plan has reached it). A profile
    # may overshoot it by round-off (2e-9 mm): such a row is at the end, and a re-plan from it
    # starts there, within the path.
    at_end = s >= (path.arc.built_mm if path.arc.complete else math.inf)
    if at_end.any():
        s = np.where(at_end, path.arc.built_mm, s)
        u[at_end] = path.curve.domain[1]
        position[at_end] = path.curve.end_point
    return SetpointBlock(
        t_s=t,
        s_mm=s,
        u=u,
        position_mm=position,
        feed_mm_s=v,
        accel_mm_s2=a,
        jerk_mm_s3=j,
        last=last,
    )
