"""The planner process's work: plan the jobs the cycle asks for into the shared setpoint rings.

A job is up to two segments (the straight approach to a program's start, then the program's
curve), each planned from rest at its start (or from the cycle's motion state for a resume) by
:func:`planner.stream.stream_setpoints`. :meth:`PlannerService.poll` does one unit of work and
returns, so the process loop stays responsive to the cycle's requests:

- a new request (:class:`runtime.shared.PlanRequest`): FOLLOW starts the job in the ring the
  cycle does not read and offers it from row 0; CANCEL drops it; CHANGE_LIMITS marks a splice;
- a splice: the rows are re-planned with the new override from the state of a row ahead of
  the one the cycle takes next (the ring rows carry feed and acceleration), written into the
  other ring from the row after it, and offered; the cycle accepts it if it has not reached
  that row, else it is made again further ahead. A first try starts from the row the cycle
  takes next (:attr:`PlannerService.splice_lead_periods`): to its first block, re-planning costs
  1.5-3 ms on the paper's curve (rarely up to 5) and up to 20 ms where the window ahead holds
  cusps or tight loops (the path's earlier plans seed it, :mod:`planner.warmstart`), so most
  tries are in time. Starting each try as far ahead as the last one took was tried: a slow
  splice then delayed the fast ones after it, and 41 % of the cycle bench's override changes
  came within 2 periods, against about 95 % now.
  A splice from a row that brakes brakes at once, as hard as the limits allow, to the feed the
  old rows' braking comes to (:func:`planner.stream.braking_end_from_rows`): never faster on
  the path than that braking, which the curve ahead needs. One braking to rest (a sharp
  corner, the approach's end) starts at that rest instead, and one in the job's final braking
  is dropped;
- otherwise the next block of the job, up to :attr:`PlannerService.buffer_high_periods` rows
  ahead of the cycle. A block that needs a new window of the look-ahead may take up to 10 ms
  on a hard stretch: an override change that comes meanwhile is spliced between the window's
  refinement rounds (:meth:`PlannerService._between_rounds`), not after the block.

Failures (a program file gone, a curve the planner rejects) are reported for the job; the cycle
turns them into a fault and stops on the rows it has.

Threading: the planner process's main thread; it never blocks on the cycle (it reads what the
cycle published and tries again next poll).
"""

from __future__ import annotations

import logging
import math
from collections import OrderedDict
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from planner.braking import BrakingProfile
from planner.errors import PlannerError
from planner.nurbs import NurbsCurve
from planner.stream import BRAKING_TOLERANCE_MM_S2, Path, braking_end_from_rows, stream_setpoints
from planner.types import Limits, MotionState, SetpointBlock
from runtime.config import MachineConfig
from runtime.curves import limits_for_curve, planner_limits
from runtime.programs import load_program_curve
from runtime.shared import (
    PlannerReport,
    PlanRequest,
    PlanRequestKind,
    RingOffer,
    RowFlag,
    SegmentKind,
    SegmentSpec,
    SetpointRing,
    SharedState,
)

logger = logging.getLogger(__name__)

#: Programs whose planning geometry is kept for re-plans (resume, override, restart).
PATH_CACHE_SIZE = 4
#: Least lead of the next try of a splice the cycle refused, periods.
SPLICE_RETRY_MIN_PERIODS = 2
#: A splice is offered with rows for its stop plus this many periods of planning time.
SPLICE_SLACK_PERIODS = 25


@dataclass(eq=False)
class _Job:
    """A job being planned into ``ring``."""

    job: int
    paths: tuple[Path, ...]
    limits: tuple[Limits, ...]
    """Per segment: the base limits with the job's override."""
    ring: int
    segment: int
    block_periods: int
    """Rows per block of its streams."""
    blocks: Iterator[SetpointBlock] | None = None
    done: bool = False
    offer: RingOffer | None = None
    """The offer waiting for the cycle's answer."""
    live: bool = False
    """The cycle accepted the job (its first offer)."""
    splice_override: float | None = None
    override_request: int = 0
    """Seq of the override change ``splice_override`` (or, for a splice, ``override_percent``)
    comes from."""
    splice_lead: int = 0
    pending_state: tuple[int, MotionState, float | None] | None = None
    """Where the next stream of the job starts when none is open: segment, state, and for a
    splice from a braking row the feed that braking comes to."""
    override_percent: float = 100.0
    candidate: _Job | None = None
    """A splice offered to the cycle: the re-planned rest of the job, in the other ring."""


class PlannerService:
    """Plans the cycle's jobs into the shared rings; see the module docstring."""

    #: Plan this many periods ahead of the cycle before waiting.
    buffer_high_periods = 500
    #: A first try of a splice re-plans from the state of the row the cycle takes next plus this
    #: many (its new rows follow that row): 0 changes the setpoint two periods after the command
    #: when the planner answers within about a period and a half; an offer that comes too late
    #: is refused and made again further ahead (by at least :data:`SPLICE_RETRY_MIN_PERIODS`,
    #: and as far as the refused one took).
    splice_lead_periods = 0
    #: Rows per planned block (the first block of a job or splice comes as soon as it is
    #: planned); a splice's blocks hold the rows its offer needs, where those are more.
    block_periods = 64

    def __init__(self, shared: SharedState, config: MachineConfig) -> None:
        self._shared = shared
        self._config = config
        self._period_s = config.cycle.period_s
        self._limits = planner_limits(config)
        self._lookahead = config.planner.lookahead
        self._update = config.planner.update
        self._paths: OrderedDict[int, Path] = OrderedDict()
        self._job: _Job | None = None
        self._splice_periods = 0
        """Periods the cycle went on while the last splice was planned."""
        self._seen = 0
        self._request_version = -1
        self._extending: _Job | None = None
        """The job whose next block :meth:`_extend` is planning (its stream is running)."""
        self._splicing_between_rounds = False
        # A restarted planner goes on numbering offers after its predecessor's: the cycle
        # ignores an offer whose number it has answered already.
        previous = shared.planner_reports.latest() or PlannerReport()
        self._offer_seq = previous.offer.seq if previous.offer is not None else 0
        self._report = PlannerReport(offer=previous.offer)
        self._shared.planner_reports.publish(self._report)

    # -- the loop ----------------------------------------------------------------------------

    @property
    def has_job(self) -> bool:
        """Whether a job is being planned or followed (else only requests can bring work)."""
        return self._job is not None

    def poll(self) -> bool:
        """One unit of work; False when there was nothing to do (the caller may sleep briefly)."""
        self._shared.planner_reports.heartbeat.value += 1
        unseen = self._unseen_request()
        if unseen is not None:
            self._take(*unseen)
            return True
        job = self._job
        if job is None:
            return False
        if job.offer is not None:
            return self._guarded(job, lambda: self._await_answer(job) or self._extend_offered(job))
        if job.splice_override is not None and self._cycle_reads(job.ring):
            return self._guarded(job, lambda: self._splice(job))
        return self._guarded(job, lambda: self._extend(job))

    def _guarded(self, job: _Job, work: Callable[[], bool]) -> bool:
        """Run a unit of work on ``job``; a failure fails the job (reported to the cycle)."""
        try:
            return work()
        except PlannerError as exc:
            self._fail(job, f"planner: {exc}")
        except Exception as exc:
            logger.exception("planner: job %d failed", job.job)
            self._fail(job, f"planner failed: {exc!r}")
        return True

    def _between_rounds(self) -> None:
        """Between the refinement rounds of a block :meth:`_extend` plans ahead: an override
        change for that job is spliced now, not once the block is done (a window on a hard
        stretch of a curve takes up to 10 ms, more than two periods).

        Other requests wait for the block: they replace or end the job it belongs to. So does
        a splice that needs more of the old plan first (:meth:`_extend_for_splice`), or one
        while another waits for the cycle's answer.
        """
        job = self._extending
        if job is None or job is not self._job or self._splicing_between_rounds:
            return
        unseen = self._unseen_request()
        if unseen is None:
            return
        request = unseen[1]
        if request.kind is not PlanRequestKind.CHANGE_LIMITS or request.job != job.job:
            return
        self._take(*unseen)
        if job.offer is not None or not self._cycle_reads(job.ring):
            return
        self._splicing_between_rounds = True
        try:
            self._guarded(job, lambda: self._splice(job))
        finally:
            self._splicing_between_rounds = False

    # -- requests ----------------------------------------------------------------------------

    def _unseen_request(self) -> tuple[int, PlanRequest] | None:
        """The cycle's newest request and its version, when not handled yet."""
        requests = self._shared.planner_requests
        version = requests.version  # read before the request: a newer one shows next poll
        if version == self._request_version:
            return None
        request = requests.latest()
        if request is None:  # caught mid-write: read it again next poll
            return None
        if request.seq == self._seen:
            self._request_version = version
            return None
        return version, request

    def _take(self, version: int, request: PlanRequest) -> None:
        """Handle a request :meth:`_unseen_request` gave, and report it handled."""
        self._request_version = version
        self._seen = request.seq
        self._handle(request)
        self._publish()

    def _handle(self, request: PlanRequest) -> None:
        self._report = PlannerReport(
            handled_request=request.seq,
            failed_job=self._report.failed_job,
            failure=self._report.failure,
            offer=self._report.offer,
        )
        job = self._job
        if request.kind is PlanRequestKind.FOLLOW:
            self._job = None
            try:
                self._job = self._start(request)
            except PlannerError as exc:
                self._fail_request(request.job, f"planner: {exc}")
            except Exception as exc:
                logger.exception("planner: job %d could not start", request.job)
                self._fail_request(request.job, f"planner failed: {exc!r}")
        elif job is not None and job.job == request.job:
            if request.kind is PlanRequestKind.CANCEL:
                self._job = None
            elif request.kind is PlanRequestKind.CHANGE_LIMITS:
                job.splice_override = request.override_percent
                job.override_request = request.seq
                job.splice_lead = self.splice_lead_periods

    def _start(self, request: PlanRequest) -> _Job:
        paths = tuple(self._path(segment) for segment in request.segments)
        limits = tuple(self._limits_for(path, request.override_percent) for path in paths)
        ring_index = 1 - self._shared.cycle_reports.latest().ring
        ring = self._shared.rings[ring_index]
        ring.begin(request.job, 0)
        job = _Job(
            job=request.job,
            paths=paths,
            limits=limits,
            ring=ring_index,
            segment=request.start_segment,
            block_periods=self.block_periods,
            override_percent=request.override_percent,
        )
        job.pending_state = (
            request.start_segment,
            MotionState(request.start_s_mm, request.start_v_mm_s, request.start_a_mm_s2),
            None,
        )
        self._write_block(job, ring)
        self._offer(job, ring_index, 0)
        return job

    def _path(self, segment: SegmentSpec) -> Path:
        if segment.kind is SegmentKind.LINE:
            curve = NurbsCurve.from_arrays(1, [segment.from_mm, segment.to_mm], [0, 0, 1, 1])
            return self._make_path(curve)
        program = segment.program
        if program is None:
            raise ValueError("a program segment without its program")
        path = self._paths.get(program.program_id)
        if path is None:
            path = self._make_path(load_program_curve(program))
            self._paths[program.program_id] = path
            while len(self._paths) > PATH_CACHE_SIZE:
                self._paths.popitem(last=False)
        self._paths.move_to_end(program.program_id)
        return path

    def _make_path(self, curve: NurbsCurve) -> Path:
        return Path(curve, limits_for_curve(self._limits, curve.dimension), self._period_s)

    def _limits_for(self, path: Path, override_percent: float) -> Limits:
        limits = limits_for_curve(self._limits, path.curve.dimension)
        return limits.with_feed_override(override_percent / 100.0)

    # -- offers ------------------------------------------------------------------------------

    def _offer(self, job: _Job, ring: int, at_row: int, rest_row: int = -1) -> None:
        self._offer_seq += 1
        override_request = job.candidate.override_request if job.candidate else 0
        job.offer = RingOffer(self._offer_seq, ring, job.job, at_row, override_request, rest_row)
        self._report = PlannerReport(
            handled_request=self._report.handled_request,
            failed_job=self._report.failed_job,
            failure=self._report.failure,
            offer=job.offer,
        )
        self._publish()

    def _await_answer(self, job: _Job) -> bool:
        offer = job.offer
        assert offer is not None
        answer = self._shared.cycle_reports.latest()
        if answer.offer_answered < offer.seq:
            return False
        job.offer = None
        if not answer.offer_accepted:
            if not job.live:
                self._job = None  # the cycle moved on to another job
            else:
                self._try_further_ahead(job)
            return True
        job.live = True
        job.ring = offer.ring
        if offer.at_row > 0:
            self._commit_splice(job)
        return True

    def _extend_offered(self, job: _Job) -> bool:
        """While the cycle has not answered a job's first offer, plan on the rows offered (the
        cycle reads them only once it accepts; refused, they are dropped): the more rows ahead
        at the start, the longer the planner may fall behind afterwards.

        A splice waits for the answer instead: its rows cover its stop and
        :data:`SPLICE_SLACK_PERIODS` of planning, the cycle answers within a period or two, and
        its next block is then planned by :meth:`_extend`, where an override change given
        meanwhile is spliced between the refinement rounds (here it would wait for the block).
        """
        if job.candidate is not None:
            return False
        ring = self._shared.rings[job.ring]
        ahead = ring.write_count - ring.first_row
        if job.done or ahead >= self.buffer_high_periods or ring.room() < job.block_periods:
            return False
        self._write_block(job, ring)
        return True

    def _cycle_reads(self, ring: int) -> bool:
        """Whether the cycle has switched to ``ring`` (so the other ring is free)."""
        return self._shared.cycle_reports.latest().ring == ring

    # -- extending ---------------------------------------------------------------------------

    def _extend(self, job: _Job) -> bool:
        if job.done or not job.live:
            return False
        ring = self._shared.rings[job.ring]
        cycle = self._shared.cycle_reports.latest()
        ahead = ring.write_count - (cycle.next_row if cycle.job == job.job else 0)
        if ahead >= self.buffer_high_periods or ring.room() < job.block_periods:
            return False
        self._extending = job
        try:
            self._write_block(job, ring)
        finally:
            self._extending = None
        return True

    def _write_block(self, job: _Job, ring: SetpointRing) -> None:
        """Plan the job's next block and append it to ``ring`` (one block per call)."""
        if job.blocks is None:
            assert job.pending_state is not None
            segment, state, braking_end = job.pending_state
            job.segment = segment
            job.blocks = self._stream(job, segment, state, braking_end)
            job.pending_state = None
        block = next(job.blocks, None)
        if block is None:
            _segment_finished(job)
            return
        self._append(job, ring, block)

    def _stream(
        self, job: _Job, segment: int, state: MotionState, braking_end_mm_s: float | None
    ) -> Iterator[SetpointBlock]:
        return stream_setpoints(
            job.paths[segment],
            job.limits[segment],
            self._period_s,
            start=state,
            braking_end_mm_s=braking_end_mm_s,
            lookahead=self._lookahead,
            update=self._update,
            block_periods=job.block_periods,
            between_rounds=self._between_rounds,
        )

    def _append(self, job: _Job, ring: SetpointRing, block: SetpointBlock) -> None:
        flags = np.zeros(len(block), dtype=np.int32)
        if block.last:
            flags[-1] = RowFlag.LAST_OF_SEGMENT
            if job.segment == len(job.paths) - 1:
                flags[-1] |= RowFlag.LAST_OF_JOB
        ring.append(
            s_mm=block.s_mm,
            feed_mm_s=block.feed_mm_s,
            accel_mm_s2=block.accel_mm_s2,
            position_mm=block.position_mm,
            segment=job.segment,
            flags=flags,
        )
        if block.last:
            _segment_finished(job)

    # -- splicing ----------------------------------------------------------------------------

    def _splice(self, job: _Job) -> bool:
        """Re-plan from a row ahead of the cycle with the new override, into the other ring."""
        ring = self._shared.rings[job.ring]
        cycle = self._shared.cycle_reports.latest()
        row = cycle.next_row + job.splice_lead
        last_planned = ring.write_count - 1
        braking_end = None
        rest_row = -1
        if row <= last_planned and ring.accel_mm_s2[ring.slot(row)] < -BRAKING_TOLERANCE_MM_S2:
            slots = ring.slots(row, last_planned + 1)
            end = braking_end_from_rows(
                ring.feed_mm_s[slots], ring.accel_mm_s2[slots], self._period_s
            )
            if end is None:
                return self._extend_for_splice(job, ring)  # its braking's end is not planned yet
            braking_end = end.feed_mm_s
            if braking_end == 0.0:
                # Braking to rest (a sharp corner, a segment's end): braking harder would stop
                # short of it; the re-plan starts at that rest instead.
                row, braking_end = row + end.row, None
                rest_row = row
        if row > last_planned and not job.done:
            return self._extend_for_splice(job, ring)
        if row > last_planned or self._row_has(ring, row, RowFlag.LAST_OF_JOB):
            job.splice_override = None  # the rest is the braking to the end: nothing to re-plan
            return True
        override = job.splice_override
        assert override is not None
        slot = ring.slot(row)
        segment = int(ring.segment[slot])
        if self._row_has(ring, row, RowFlag.LAST_OF_SEGMENT):
            # At rest at the end of a segment (the approach): the next one from its start.
            segment, state = segment + 1, MotionState(0.0)
        else:
            state = MotionState(
                float(ring.s_mm[slot]), float(ring.feed_mm_s[slot]), float(ring.accel_mm_s2[slot])
            )
        limits = tuple(self._limits_for(path, override) for path in job.paths)
        other_index = 1 - job.ring
        other = self._shared.rings[other_index]
        other.begin(job.job, row + 1)
        # Offered once its rows cover a stop from where it begins, and the time to plan more:
        # the cycle takes them from two periods on, and calls the planner behind when the rows
        # ahead no longer cover its braking. Its blocks hold that many rows, so that the offer
        # waits for one block: a second would wait for the next window.
        cover = self._rows_to_stop(state) + SPLICE_SLACK_PERIODS
        spliced = _Job(
            job=job.job,
            paths=job.paths,
            limits=limits,
            ring=other_index,
            segment=segment,
            block_periods=max(self.block_periods, cover),
            live=True,
            override_percent=override,
            override_request=job.override_request,
        )
        spliced.pending_state = (segment, state, braking_end)
        while other.write_count - other.first_row < cover:
            self._write_block(spliced, other)
            if spliced.done or spliced.pending_state is not None:
                break  # its rows end at rest: nothing to cover beyond them
        now = self._shared.cycle_reports.latest()
        self._splice_periods = max(0, now.next_row - cycle.next_row)  # < 0: a new job began
        job.candidate = spliced
        if now.next_row > row + 1:
            self._try_further_ahead(job)  # the cycle took the first new row meanwhile
        else:
            self._offer(job, other_index, row + 1, rest_row)
        return True

    def _try_further_ahead(self, job: _Job) -> None:
        """The cycle got to the splice's first row first: plan it again as far ahead as this try
        took (the points this try's refinement added seed the next, which plans faster: on the
        cycle bench, p90 of the override latency 7 -> 6 periods against one period further)."""
        job.splice_lead = max(SPLICE_RETRY_MIN_PERIODS, job.splice_lead + 1, self._splice_periods)
        job.candidate = None

    def _rows_to_stop(self, state: MotionState) -> int:
        """Periods a jerk-limited stop from ``state`` takes."""
        braking = BrakingProfile.from_state(
            v0_mm_s=state.v_mm_s,
            a0_mm_s2=state.a_mm_s2,
            amax_mm_s2=self._limits.amax_mm_s2,
            jmax_mm_s3=self._limits.jmax_mm_s3,
        )
        return math.ceil(braking.duration_s / self._period_s)

    def _extend_for_splice(self, job: _Job, ring: SetpointRing) -> bool:
        """The splice row is not planned yet: the old plan goes on meanwhile (not while its
        stream is running: between the rounds of its next block)."""
        if job.done or ring.room() < job.block_periods or self._extending is job:
            return False
        self._write_block(job, ring)
        return True

    @staticmethod
    def _row_has(ring: SetpointRing, row: int, flag: RowFlag) -> bool:
        return bool(ring.flags[ring.slot(row)] & flag)

    def _commit_splice(self, job: _Job) -> None:
        spliced = job.candidate
        assert spliced is not None
        job.paths, job.limits = spliced.paths, spliced.limits
        job.segment, job.blocks, job.done = spliced.segment, spliced.blocks, spliced.done
        job.block_periods = spliced.block_periods
        job.pending_state = spliced.pending_state
        job.override_percent = spliced.override_percent
        if job.override_request == spliced.override_request:
            job.splice_override = None
        job.candidate = None

    # -- reporting ---------------------------------------------------------------------------

    def _fail(self, job: _Job, reason: str) -> None:
        if self._job is job:
            self._job = None
        self._fail_request(job.job, reason)

    def _fail_request(self, job: int, reason: str) -> None:
        logger.error("job %d: %s", job, reason)
        self._report = PlannerReport(
            handled_request=self._report.handled_request,
            failed_job=job,
            failure=reason,
            offer=self._report.offer,
        )
        self._publish()

    def _publish(self) -> None:
        self._shared.planner_reports.publish(self._report)


def _segment_finished(job: _Job) -> None:
    """The job's current segment is fully written: the next one starts from rest, or the job
    is done."""
    job.blocks = None
    if job.segment + 1 < len(job.paths):
        job.pending_state = (job.segment + 1, MotionState(0.0), None)
    else:
        job.done = True
