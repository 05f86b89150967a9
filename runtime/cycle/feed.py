"""The cycle's side of the planned setpoints: ask for plans, follow their rows, brake on them.

The planner process writes setpoint rows into the shared rings (:mod:`runtime.shared`); each
period the cycle takes the next row of the job it follows (:meth:`SetpointFeed.take`). Changes of
plan keep the stream smooth:

- A job (start, resume, the next program) is asked for with :meth:`SetpointFeed.follow`; the
  planner offers its rows in the ring the cycle does not read, from row 0, and the motion starts
  once :attr:`SetpointFeed.start_lead_periods` rows are there (or the whole job is).
- A feed-override change (:meth:`SetpointFeed.change_override`) is planned by the planner from a
  row a little ahead of the cycle and offered in the other ring from the row after it; the cycle
  accepts the offer if it has not reached that row yet and switches rings there. Refused offers
  are made again further ahead.
- Hold, stop and fault stops brake at once, here in the cycle, with the closed-form jerk-limited
  :class:`planner.braking.BrakingProfile` from the current feed and acceleration, along the
  rows already planned ahead. A jerk-limited stop never travels farther in a given time than
  any plan with the same limits, so those rows always reach past the stopping point; positions
  between two rows are interpolated on a cubic through them (:meth:`SetpointFeed._on_rows`),
  within a small fraction of the chord error of the curve. So no planner is needed to stop,
  and a dead or late planner never makes the path jump.
- A resume starts where the stop came to rest, a hair off the curve its rows start on: the
  setpoint first moves onto the curve, at rest (:meth:`SetpointFeed._settled_onto_rows`).
- Underrun: while following a plan, the rows planned ahead must always cover the braking time
  from the current feed and acceleration plus :data:`UNDERRUN_MARGIN_PERIODS`; when they no longer
  do (the planner fell behind), :meth:`take` reports UNDERRUN once, and the machine stops on the
  rows it still has. Rows that end at rest (the end of a segment) need nothing beyond them; at
  rest (the end of the approach, a sharp corner) nothing needs braking: the setpoint waits for
  the next rows, up to :data:`REST_WAIT_LIMIT_S`.

Units: mm, mm/s, mm/s², periods. Threading: the cycle process's single thread; every call is
O(1) (a braking step advances a cursor over rows it passes once). Nothing here blocks or
allocates beyond small records.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

import numpy as np

from planner.braking import BrakingProfile
from runtime.shared import (
    CycleReport,
    PlannerReport,
    PlanRequest,
    PlanRequestKind,
    RingOffer,
    RowFlag,
    SegmentSpec,
    SetpointRing,
    SharedState,
)

#: A resume whose rows start closer than this to where the setpoint rests starts at once [mm].
SETTLE_NEGLIGIBLE_MM = 1e-9
#: Largest |third derivative| of the septic smoothstep 35x⁴ - 84x⁵ + 70x⁶ - 20x⁷ on [0, 1].
SMOOTHSTEP_PEAK_JERK = 52.5
#: Rows beyond the braking time the planner must keep ahead while moving.
UNDERRUN_MARGIN_PERIODS = 2
#: At rest between two segments the feed waits this long for the next rows before it calls the
#: planner behind [s].
REST_WAIT_LIMIT_S = 10.0


class FeedMode(Enum):
    """What the feed is doing."""

    IDLE = "idle"
    """At rest; no plan is being followed."""
    STARTING = "starting"
    """A job was asked for; waiting for its first rows (the setpoint stays put)."""
    PLANNED = "planned"
    """Following planned rows."""
    BRAKING = "braking"
    """Braking to rest along the planned rows."""


class FeedEvent(Enum):
    """What happened in this period, for the machine to act on."""

    NONE = "none"
    FINISHED = "finished"
    """The job's last row was taken: at rest at the end of its last segment."""
    STOPPED = "stopped"
    """Braking reached rest on the path."""
    UNDERRUN = "underrun"
    """Too few rows ahead to go on (the planner fell behind); see :attr:`SetpointFeed.problem`."""
    PLANNER_FAILED = "planner failed"
    """The planner could not plan the job; see :attr:`SetpointFeed.problem`."""


@dataclass(frozen=True)
class Setpoint:
    """The setpoint of one period."""

    position_mm: tuple[float, ...]
    s_mm: float = 0.0
    """Arc length along the current segment."""
    feed_mm_s: float = 0.0
    accel_mm_s2: float = 0.0
    segment: int = -1
    """Index of the job's segment (-1: not on a job's path)."""


@dataclass
class _Settle:
    """The setpoint's move onto the curve before a resume's rows (see
    :meth:`SetpointFeed._settled_onto_rows`)."""

    from_mm: np.ndarray
    to_mm: np.ndarray
    periods: int
    taken: int = 0


@dataclass(frozen=True)
class _OverrideChange:
    """An override change waiting for the splice that answers it."""

    request: int
    """Seq of its CHANGE_LIMITS request."""
    row: int
    """The row the cycle took next when it was commanded."""


@dataclass(frozen=True)
class JobStart:
    """Where a job starts: a segment index and the motion state on it."""

    segment: int = 0
    s_mm: float = 0.0
    v_mm_s: float = 0.0
    a_mm_s2: float = 0.0


class SetpointFeed:
    """Planned setpoints for the cycle; see the module docstring.

    :param shared: the runtime's shared memory (rings, planner requests and reports).
    :param period_s: the cycle period [s].
    :param amax_mm_s2, jmax_mm_s3: the path's braking limits.
    """

    #: Motion starts once this many rows are planned (or the whole job is): a head start that
    #: lets the planner fall behind for a while without the rows running short.
    start_lead_periods = 50

    def __init__(
        self, shared: SharedState, *, period_s: float, amax_mm_s2: float, jmax_mm_s3: float
    ) -> None:
        self._shared = shared
        self._rings = shared.rings
        self._period_s = period_s
        self._amax = amax_mm_s2
        self._jmax = jmax_mm_s3
        self.mode = FeedMode.IDLE
        self.current = Setpoint(())
        self.problem = ""
        """Why the last UNDERRUN or PLANNER_FAILED happened."""
        self.override_latency_periods = 0
        """Periods from the oldest override change the last splice answers to its first row."""
        self.override_rest_wait_periods = 0
        """Of those, the periods the old rows still braked to a rest the splice starts at."""
        self.overrides_applied = 0
        """Override changes whose re-planned setpoints have been reached."""
        self._override_changes: list[_OverrideChange] = []
        """Changes of the followed job no splice has answered yet, oldest first."""
        self._rest_row = -1
        """The rest the last splice that waited for one started at."""
        self._segments: tuple[SegmentSpec, ...] = ()
        self._job_start = JobStart()
        self._settle: _Settle | None = None
        self._dimension = 0
        self._first_offer_taken = False
        self._job = 0
        self._request_seq = 0
        self._override_percent = 100.0
        self._ring = 0
        self._next_row = 0
        self._switch: RingOffer | None = None
        """An accepted offer whose row the cycle has not reached yet."""
        self._answered = 0
        self._accepted = False
        self._underrun_reported = False
        self._failure_seen = 0
        self._waiting_periods = 0
        self._rest_wait_limit = math.ceil(REST_WAIT_LIMIT_S / period_s)
        # Braking.
        self._braking: BrakingProfile | None = None
        self._braking_s0 = 0.0
        self._braking_t_s = 0.0
        self._cursor = 0
        self._hold_row = -1

    # -- requests --------------------------------------------------------------------------

    @property
    def job(self) -> int:
        """The job followed or waited for (0: none yet)."""
        return self._job

    def follow(
        self, segments: tuple[SegmentSpec, ...], start: JobStart, override_percent: float
    ) -> None:
        """Ask for a job through ``segments`` from ``start`` and follow it once planned.

        Until its first rows come the setpoint stays where it is (mode STARTING).
        """
        self._job += 1
        self._segments = segments
        self._job_start = start
        self._dimension = _dimension(segments)
        self._first_offer_taken = False
        self._override_percent = override_percent
        self._switch = None
        self._hold_row = -1
        self._underrun_reported = False
        self._settle = None
        self._forget_override_changes()
        self._post(
            PlanRequestKind.FOLLOW,
            segments=segments,
            start_segment=start.segment,
            start_s_mm=start.s_mm,
            start_v_mm_s=start.v_mm_s,
            start_a_mm_s2=start.a_mm_s2,
        )
        self.mode = FeedMode.STARTING

    def change_override(self, override_percent: float) -> None:
        """Re-plan the rest of the job with a new feed override (> 0), spliced ahead."""
        self._override_percent = override_percent
        if self.mode is FeedMode.STARTING:
            self.follow(self._segments, self._job_start, override_percent)
        elif self.mode is FeedMode.PLANNED:
            self._post(PlanRequestKind.CHANGE_LIMITS)
            self._override_changes.append(_OverrideChange(self._request_seq, self._next_row))

    def brake(self) -> None:
        """Brake to rest along the planned rows from the current feed and acceleration, now.

        Already braking: the stop in progress is the quickest one, it goes on.
        """
        if self.mode is FeedMode.BRAKING:
            return
        self._cancel_job()
        now = self.current
        self.mode = FeedMode.BRAKING
        if self._hold_row < 0 or (now.feed_mm_s <= 0.0 and now.accel_mm_s2 <= 0.0):
            self._braking = None  # nothing to brake: at rest next period
            return
        self._braking = BrakingProfile.from_state(
            v0_mm_s=now.feed_mm_s,
            a0_mm_s2=now.accel_mm_s2,
            amax_mm_s2=self._amax,
            jmax_mm_s3=self._jmax,
        )
        self._braking_s0 = now.s_mm
        self._braking_t_s = 0.0
        self._cursor = self._hold_row

    def rest_at(self, position_mm: tuple[float, ...]) -> None:
        """Forget any plan and rest at ``position_mm`` (e.g. the drives' actual position)."""
        self._cancel_job()
        self._braking = None
        self._hold_row = -1
        self.mode = FeedMode.IDLE
        self.current = Setpoint(tuple(position_mm))
        self._publish()

    def awaited(self) -> tuple[tuple[SegmentSpec, ...], JobStart] | None:
        """The job asked for whose first rows have not come yet (mode STARTING), or None."""
        if self.mode is not FeedMode.STARTING:
            return None
        return self._segments, self._job_start

    def remaining(self) -> tuple[tuple[SegmentSpec, ...], JobStart] | None:
        """The rest of the last job from where the setpoint rests (for a resume), or None when
        the setpoint is not on a job's path."""
        now = self.current
        if now.segment < 0 or not self._segments:
            return None
        return self._segments, JobStart(now.segment, now.s_mm)

    # -- per period ------------------------------------------------------------------------

    def take(self) -> FeedEvent:
        """Advance one period; the new setpoint is :attr:`current`."""
        event = FeedEvent.NONE
        report = self._shared.planner_reports.latest()
        if report is not None:
            event = self._judge(report)
        if event is FeedEvent.NONE:
            if self.mode is FeedMode.BRAKING:
                event = self._take_braking()
            elif self.mode is FeedMode.STARTING:
                if self._started() and self._settled_onto_rows():
                    self.mode = FeedMode.PLANNED
                    event = self._take_planned()
            elif self.mode is FeedMode.PLANNED:
                event = self._take_planned()
        self._publish()
        return event

    @property
    def rows_ahead(self) -> int:
        """Planned rows not yet taken (0 when not following a plan)."""
        if self.mode is not FeedMode.PLANNED:
            return 0
        return max(0, self._available_end() - self._next_row)

    # -- offers and failures -----------------------------------------------------------------

    def _judge(self, report: PlannerReport) -> FeedEvent:
        if (
            report.failed_job == self._job
            and self._failure_seen != self._job
            and self.mode in (FeedMode.STARTING, FeedMode.PLANNED)
        ):
            self._failure_seen = self._job
            self.problem = report.failure
            return FeedEvent.PLANNER_FAILED
        offer = report.offer
        if offer is None or offer.seq <= self._answered:
            return FeedEvent.NONE
        self._answered = offer.seq
        self._accepted = self._acceptable(offer)
        if self._accepted:
            if self.mode is FeedMode.STARTING:
                self._first_offer_taken = True
                self._ring = offer.ring
                self._next_row = 0
            else:
                self._switch = offer
        return FeedEvent.NONE

    def _acceptable(self, offer: RingOffer) -> bool:
        if offer.job != self._job or offer.ring not in (0, 1):
            return False
        if self.mode is FeedMode.STARTING:
            return offer.at_row == 0 and not self._first_offer_taken
        return (
            self.mode is FeedMode.PLANNED
            and offer.ring != self._ring
            and self._switch is None
            and offer.at_row >= self._next_row
        )

    # -- following ---------------------------------------------------------------------------

    def _ring_of(self, row: int) -> SetpointRing:
        switch = self._switch
        if switch is not None and row >= switch.at_row:
            return self._rings[switch.ring]
        return self._rings[self._ring]

    def _available_end(self) -> int:
        switch = self._switch
        if switch is not None:
            return self._rings[switch.ring].write_count
        return self._rings[self._ring].write_count

    def _last_row_flags(self) -> int:
        end = self._available_end()
        if end <= 0:
            return 0
        ring = self._ring_of(end - 1)
        return int(ring.flags[ring.slot(end - 1)])

    def _job_complete(self) -> bool:
        return bool(self._last_row_flags() & RowFlag.LAST_OF_JOB)

    def _rows_end_at_rest(self) -> bool:
        """Whether the rows planned ahead end at rest (a segment's end): the plan itself stops
        there, so a stop from now never needs more rows than there are."""
        return bool(self._last_row_flags() & RowFlag.LAST_OF_SEGMENT)

    def _started(self) -> bool:
        if not self._first_offer_taken:
            return False
        return self._available_end() >= self.start_lead_periods or self._job_complete()

    def _settled_onto_rows(self) -> bool:
        """Whether the setpoint is where the job's rows start; else it moves there one step.

        A stop comes to rest between two rows, on the cubic through them, a hair off the curve
        a resume's rows start on (up to 8 nm in the operator-sequence tests; on the chords
        braking once followed, up to the chord error). Taken at once, a step is a jerk of
        step / T³ on top of the start's own: 15,600 mm/s³ for 1 µm at 4 ms. So the setpoint
        first moves onto the curve at rest, along a septic smoothstep (no step in feed,
        acceleration or jerk) at no more than half of jmax, whatever the step.
        """
        settle = self._settle
        if settle is None:
            target = self._curve_point_at_rest()
            if target is None:
                return True
            here = np.array(self.current.position_mm)
            offset_mm = float(np.linalg.norm(target - here))
            if offset_mm <= SETTLE_NEGLIGIBLE_MM:
                return True
            duration_s = (2.0 * SMOOTHSTEP_PEAK_JERK * offset_mm / self._jmax) ** (1.0 / 3.0)
            settle = self._settle = _Settle(
                here, target, max(2, math.ceil(duration_s / self._period_s))
            )
        settle.taken += 1
        now = self.current
        if settle.taken >= settle.periods:
            position = tuple(settle.to_mm.tolist())
            self._settle = None
        else:
            x = settle.taken / settle.periods
            weight = x**4 * (35.0 - 84.0 * x + 70.0 * x * x - 20.0 * x**3)
            position = tuple((settle.from_mm + weight * (settle.to_mm - settle.from_mm)).tolist())
        self.current = Setpoint(position, now.s_mm, 0.0, 0.0, now.segment)
        return False

    def _curve_point_at_rest(self) -> np.ndarray | None:
        """For a resume on the path, the curve point where the setpoint rests, from the job's
        first two rows (a start from rest: extrapolated back over a step a seventh of the
        next, to a few nanometres on the tightest curves); None for any other start."""
        now = self.current
        if now.segment < 0 or self._available_end() < 2:
            return None
        if self._row_segment(0) != now.segment or self._row_segment(1) != now.segment:
            return None
        p0, s0 = self._row_point(0)
        if s0 <= now.s_mm:
            return p0.copy()
        p1, s1 = self._row_point(1)
        if s1 <= s0:
            return None
        return p0 - (p1 - p0) * ((s0 - now.s_mm) / (s1 - s0))

    def _take_planned(self) -> FeedEvent:
        row = self._next_row
        if row >= self._available_end():
            if self._at_rest() and self._waiting_periods < self._rest_wait_limit:
                # At rest between two segments (or at a corner): nothing to brake, the
                # setpoint stays where it is until the next rows come.
                self._waiting_periods += 1
                return FeedEvent.NONE
            self.problem = "planner behind: no setpoint planned for this period"
            return self._underrun()
        self._waiting_periods = 0
        switch = self._switch
        if switch is not None and row >= switch.at_row:
            self._ring = switch.ring
            self._switch = None
            self._count_override_changes(switch, row)
        ring = self._rings[self._ring]
        self._set_current(ring, row)
        self._hold_row = row
        self._next_row = row + 1
        # int() first: a numpy scalar & an IntEnum takes numpy's slow path (~13 µs).
        if int(ring.flags[ring.slot(row)]) & RowFlag.LAST_OF_JOB:
            self._cancel_job()
            self.mode = FeedMode.IDLE
            return FeedEvent.FINISHED
        return self._check_underrun()

    def _count_override_changes(self, splice: RingOffer, row: int) -> None:
        """The splice's first row ``row`` is taken: the changes it answers are in effect."""
        if splice.rest_row >= 0:
            self._rest_row = splice.rest_row
        changes = self._override_changes
        answered = 0
        while answered < len(changes) and changes[answered].request <= splice.override_request:
            answered += 1
        if answered == 0:
            return
        oldest = changes[0].row
        del changes[:answered]
        self.override_latency_periods = row - oldest
        # A change that came meanwhile waits for the same rest, even when its own splice
        # (after that rest) did not.
        self.override_rest_wait_periods = max(0, self._rest_row - oldest)
        self.overrides_applied += answered

    def _at_rest(self) -> bool:
        now = self.current
        return now.feed_mm_s == 0.0 and now.accel_mm_s2 == 0.0

    def _check_underrun(self) -> FeedEvent:
        if self._underrun_reported or self._at_rest() or self._rows_end_at_rest():
            return FeedEvent.NONE
        now = self.current
        braking = BrakingProfile.from_state(
            v0_mm_s=now.feed_mm_s,
            a0_mm_s2=now.accel_mm_s2,
            amax_mm_s2=self._amax,
            jmax_mm_s3=self._jmax,
        )
        needed = math.ceil(braking.duration_s / self._period_s) + UNDERRUN_MARGIN_PERIODS
        ahead = self._available_end() - self._next_row
        if ahead >= needed:
            return FeedEvent.NONE
        self.problem = (
            f"planner behind: {ahead} setpoints ({ahead * self._period_s * 1000:.0f} ms) planned "
            f"ahead at {now.feed_mm_s:.1f} mm/s, braking needs {needed}"
        )
        return self._underrun()

    def _underrun(self) -> FeedEvent:
        self._underrun_reported = True
        return FeedEvent.UNDERRUN

    def _set_current(self, ring: SetpointRing, row: int) -> None:
        slot = ring.slot(row)
        dimension = self._dimension
        self.current = Setpoint(
            tuple(ring.position_mm[slot, :dimension].tolist()),
            float(ring.s_mm[slot]),
            float(ring.feed_mm_s[slot]),
            float(ring.accel_mm_s2[slot]),
            int(ring.segment[slot]),
        )

    # -- braking -----------------------------------------------------------------------------

    def _take_braking(self) -> FeedEvent:
        profile = self._braking
        if profile is None:
            # At rest already: it stays where it is on the path (a resume goes on from there).
            now = self.current
            self.mode = FeedMode.IDLE
            self.current = Setpoint(now.position_mm, now.s_mm, 0.0, 0.0, now.segment)
            return FeedEvent.STOPPED
        self._braking_t_s += self._period_s
        distance, feed, accel = profile.sample(self._braking_t_s)
        s = self._braking_s0 + distance
        segment = self.current.segment
        end = self._available_end()
        cursor = self._cursor
        while cursor + 1 < end:
            ring = self._ring_of(cursor + 1)
            slot = ring.slot(cursor + 1)
            if int(ring.segment[slot]) != segment or float(ring.s_mm[slot]) > s:
                break
            cursor += 1
        self._cursor = cursor
        position, s = self._on_rows(cursor, s, segment, end)
        at_rest = self._braking_t_s >= profile.duration_s
        if at_rest:
            feed, accel = 0.0, 0.0
        self.current = Setpoint(position, s, feed, accel, segment)
        if not at_rest:
            return FeedEvent.NONE
        self._braking = None
        self.mode = FeedMode.IDLE
        return FeedEvent.STOPPED

    def _on_rows(
        self, row: int, s: float, segment: int, end: int
    ) -> tuple[tuple[float, ...], float]:
        """The point at arc length ``s`` between row ``row`` and the next one of ``segment``,
        clamped to the last row available.

        On the cubic Hermite curve through the two rows, in arc length, with tangents from
        their neighbouring rows: braking is slower than the plan at every point of the path,
        so its steps are shorter than the planned ones, and a point on the curve keeps its
        chord within the chord error. Points on the chord between the rows (the sagitta of a
        planned step inside the curve already, up to the chord error) measured up to 1.6 times
        it across a row on the paper's curve. Where the rows turn by more than a right angle (a
        corner or cusp, where the plan comes to rest and its steps are tiny) it is that chord.
        """
        here, s_here = self._row_point(row)
        after = self._row_of_segment(row + 1, segment, end)
        if after is None:
            return tuple(here.tolist()), s_here
        there, s_next = after
        if s_next <= s_here:
            return tuple(here.tolist()), s_here
        s = max(s_here, min(s, s_next))
        x = (s - s_here) / (s_next - s_here)
        chord = there - here
        point = here + x * chord
        step_mm = s_next - s_here
        # Each row read once: the two rows and their neighbours give both tangents.
        start = _row_tangent(
            self._row_of_segment(row - 1, segment, end), (here, s_here), after, chord
        )
        finish = _row_tangent(
            (here, s_here) if self._row_segment(row) == segment else None,
            after,
            self._row_of_segment(row + 2, segment, end),
            chord,
        )
        if start is not None and finish is not None:
            # Hermite basis, as corrections to the chord's linear blend.
            point += (x * (1.0 - x) ** 2) * (step_mm * start - chord) - (x * x * (1.0 - x)) * (
                step_mm * finish - chord
            )
        return tuple(point.tolist()), s

    def _row_point(self, row: int) -> tuple[np.ndarray, float]:
        ring = self._ring_of(row)
        slot = ring.slot(row)
        return ring.position_mm[slot, : self._dimension], float(ring.s_mm[slot])

    def _row_segment(self, row: int) -> int:
        ring = self._ring_of(row)
        return int(ring.segment[ring.slot(row)])

    def _row_of_segment(self, row: int, segment: int, end: int) -> _RowPoint | None:
        """Position and arc length of ``row`` when it is a row of ``segment`` before ``end``."""
        if row < 0 or row >= end or self._row_segment(row) != segment:
            return None
        return self._row_point(row)

    # -- bookkeeping -------------------------------------------------------------------------

    def _cancel_job(self) -> None:
        if self.mode in (FeedMode.STARTING, FeedMode.PLANNED):
            self._post(PlanRequestKind.CANCEL)
        self._switch = None
        self._settle = None
        self._forget_override_changes()

    def _forget_override_changes(self) -> None:
        """No splice of the job followed so far will answer them (its rows count anew)."""
        self._override_changes.clear()
        self._rest_row = -1

    def _post(self, kind: PlanRequestKind, **fields: object) -> None:
        self._request_seq += 1
        if kind is not PlanRequestKind.FOLLOW:
            fields.setdefault("segments", self._segments)
        self._shared.planner_requests.post(
            PlanRequest(
                seq=self._request_seq,
                kind=kind,
                job=self._job,
                override_percent=self._override_percent,
                **fields,  # type: ignore[arg-type]
            )
        )

    def _publish(self) -> None:
        """Tell the planner where the cycle reads and which rows it may still need."""
        following = self.mode in (FeedMode.PLANNED, FeedMode.STARTING, FeedMode.BRAKING)
        job = self._job if following else 0
        # From the row before the one braking starts or goes on from: a tangent's neighbour.
        held = max(0, (self._cursor if self.mode is FeedMode.BRAKING else self._next_row - 1) - 1)
        for index, ring in enumerate(self._rings):
            in_use = following and (
                index == self._ring or (self._switch is not None and index == self._switch.ring)
            )
            ring.hold_from(job if in_use else -1, held)
        self._shared.cycle_reports.publish(
            CycleReport(
                offer_answered=self._answered,
                offer_accepted=self._accepted,
                job=job,
                ring=self._ring,
                next_row=self._next_row,
            )
        )


_RowPoint = tuple[np.ndarray, float]


def _row_tangent(
    before: _RowPoint | None, at: _RowPoint, after: _RowPoint | None, chord: np.ndarray
) -> np.ndarray | None:
    """The unit tangent at row ``at`` (position, arc length), from the rows either side of
    the same segment (second order on their uneven steps; one side, None, at a segment's or
    the rows' end). Unit: the rows lie on the curve in arc length, and a shorter one slows the
    cubic between rows (a tangent from the chords' mean measured 0.3 % feed ripple, 5 % of
    jmax while braking). None where the rows turn by more than a right angle there or do not
    move."""
    here, s_here = at
    p_before, s_before = before if before is not None else at
    p_after, s_after = after if after is not None else at
    back_mm, ahead_mm = s_here - s_before, s_after - s_here
    if back_mm > 0.0 and ahead_mm > 0.0:
        behind, ahead = here - p_before, p_after - here
        if float(np.dot(behind, ahead)) <= 0.0:
            return None
        tangent = back_mm * back_mm * ahead + ahead_mm * ahead_mm * behind
    elif back_mm > 0.0 or ahead_mm > 0.0:
        tangent = p_after - p_before
    else:
        return None
    length = float(np.linalg.norm(tangent))
    if length == 0.0 or float(np.dot(tangent, chord)) <= 0.0:
        return None
    return tangent / length


def _dimension(segments: tuple[SegmentSpec, ...]) -> int:
    """Coordinates of a job's points (all its segments share them)."""
    for segment in segments:
        if segment.from_mm:
            return len(segment.from_mm)
        if segment.program is not None:
            return segment.program.dimension
    return 0
