"""The motion feed: a planner worker filling a setpoint buffer, and braking on the path.

The cyclic task takes one setpoint per period from :class:`MotionFeed` (O(1): an index into a
buffered block). A worker thread runs :func:`planner.stream.stream_setpoints` ahead of it and
appends blocks to the buffer, up to :attr:`MotionFeed.buffer_high_periods` periods ahead.

Changes of plan keep the setpoint stream smooth:

- hold, stop and fault stops brake at once in the cyclic thread with the closed-form
  jerk-limited :class:`planner.braking.BrakingProfile` from the current feed and acceleration,
  staying on the path (one arc-length inversion and one curve point per period);
- resume re-plans from rest where the path stopped;
- a feed-override change is spliced: the worker plans from the state of a row a little ahead of
  the cyclic task (``splice_lead_periods``) with the new limits and replaces the rows after it;
  if the cyclic task got there first, it tries again further ahead.

Threads: the cyclic thread calls every public method except those marked otherwise; the worker
thread only plans and appends. They share the buffer under one lock held for O(1) work.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from enum import Enum

from planner.braking import BrakingProfile
from planner.errors import PlannerError
from planner.stream import Path, stream_setpoints
from planner.types import Limits, MotionState, SetpointBlock

logger = logging.getLogger(__name__)


class FeedMode(Enum):
    """What the feed is doing."""

    IDLE = "idle"
    """At rest; no path is being followed."""
    STARTING = "starting"
    """A plan was asked for; waiting for its first block (the setpoint stays put)."""
    PLANNED = "planned"
    """Following buffered planned setpoints."""
    BRAKING = "braking"
    """Braking to rest on the path."""


class FeedEvent(Enum):
    """What happened in this period, for the machine to act on."""

    NONE = "none"
    FINISHED = "finished"
    """The last setpoint of the job was taken: at rest at the end of its last segment."""
    STOPPED = "stopped"
    """Braking reached rest on the path."""
    UNDERRUN = "underrun"
    """The buffer ran empty while following a plan."""
    PLANNER_FAILED = "planner failed"


@dataclass(frozen=True)
class Segment:
    """One path of a job, followed from ``start`` to the end of the path."""

    path: Path
    start: MotionState


@dataclass(frozen=True, eq=False)
class _Chunk:
    """A planned block and the segment it belongs to."""

    segment: int
    path: Path
    block: SetpointBlock
    last_of_job: bool


@dataclass(frozen=True)
class Setpoint:
    """The setpoint of one period, in curve coordinates."""

    position_mm: tuple[float, ...]
    s_mm: float
    feed_mm_s: float
    accel_mm_s2: float
    path: Path | None
    segment: int


@dataclass(eq=False)
class _Job:
    """What the worker plans; mutated by the worker only, except ``splice_limits``."""

    segments: tuple[Segment, ...]
    limits: Limits
    segment: int = 0
    """The segment being planned."""
    blocks: Iterator[SetpointBlock] | None = None
    """The planner stream of that segment, once started."""
    done: bool = False
    """Everything up to the end of the last segment is in the buffer."""
    splice_limits: Limits | None = None
    """A feed-override change to splice in (set by the cyclic thread under the lock)."""
    splice_lead: int = 0
    """Periods ahead of the cyclic task where the splice is tried next."""


class MotionFeed:
    """Setpoints for the cyclic task: planned ahead by a worker, braked on the path at once."""

    #: Plan this many periods ahead of the cyclic task before the worker waits.
    buffer_high_periods = 500
    #: An override change takes effect about this many periods ahead (time for the worker).
    splice_lead_periods = 25
    #: Motion starts once this many periods are planned (or the whole job is): a head start
    #: that lets the worker fall behind for a while without the buffer running empty.
    start_lead_periods = 50

    def __init__(
        self,
        *,
        period_s: float,
        lookahead: bool = True,
        update: str = "corrected",
        block_periods: int = 128,
    ) -> None:
        self.period_s = period_s
        self.lookahead = lookahead
        self.update = update
        self.block_periods = block_periods
        self.mode = FeedMode.IDLE
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._job: _Job | None = None
        self._segments: tuple[Segment, ...] = ()
        # Buffer, shared with the worker under the lock.
        self._chunks: deque[_Chunk] = deque()
        self._chunk: _Chunk | None = None
        self._row = 0
        self._taken = 0
        self._buffered_rows = 0
        self._failure: str | None = None
        # Braking, cyclic thread only.
        self._braking: BrakingProfile | None = None
        self._braking_from = MotionState(0.0)
        self._braking_t_s = 0.0
        self._braking_u = 0.0
        self._current = Setpoint((), 0.0, 0.0, 0.0, None, 0)
        self._stopping = False
        self._worker = threading.Thread(target=self._work, name="planner", daemon=True)
        self._worker.start()

    # -- cyclic thread --------------------------------------------------------------------

    @property
    def current(self) -> Setpoint:
        """The setpoint taken last (or where the feed rests)."""
        return self._current

    def rest_at(self, position_mm: tuple[float, ...]) -> None:
        """Forget any plan and rest at ``position_mm`` (e.g. the drives' actual position)."""
        with self._lock:
            self._cancel_locked()
        self._segments = ()
        self.mode = FeedMode.IDLE
        self._current = Setpoint(tuple(position_mm), 0.0, 0.0, 0.0, None, 0)

    def follow(self, segments: tuple[Segment, ...], limits: Limits) -> None:
        """Plan ``segments`` one after the other with ``limits`` and follow them (non-blocking).

        Until the first block is planned the setpoint stays where it is (mode STARTING).
        """
        with self._lock:
            self._cancel_locked()
            self._job = _Job(segments, limits)
            self._wake.notify_all()
        self._segments = segments
        self.mode = FeedMode.STARTING

    def change_limits(self, limits: Limits) -> None:
        """Re-plan the rest of the job with ``limits`` (a feed override), spliced ahead."""
        if self.mode is FeedMode.STARTING:
            self.follow(self._segments, limits)
            return
        with self._lock:
            job = self._job
            if self.mode is FeedMode.PLANNED and job is not None:
                job.splice_limits = limits
                job.splice_lead = self.splice_lead_periods
                self._wake.notify_all()

    @property
    def splice_pending(self) -> bool:
        """Whether a feed-override change is waiting to be spliced into the plan."""
        job = self._job
        return job is not None and job.splice_limits is not None

    def brake(self, *, amax_mm_s2: float, jmax_mm_s3: float) -> None:
        """Brake to rest on the current path from the current feed and acceleration, now."""
        with self._lock:
            self._cancel_locked()
        now = self._current
        self.mode = FeedMode.BRAKING
        self._braking = None
        if now.path is None or (now.feed_mm_s == 0.0 and now.accel_mm_s2 == 0.0):
            return
        self._braking = BrakingProfile.from_state(
            v0_mm_s=now.feed_mm_s,
            a0_mm_s2=now.accel_mm_s2,
            amax_mm_s2=amax_mm_s2,
            jmax_mm_s3=jmax_mm_s3,
        )
        self._braking_from = MotionState(now.s_mm, now.feed_mm_s, now.accel_mm_s2)
        self._braking_t_s = 0.0
        self._braking_u = float(now.path.arc.u_of_s(now.s_mm)[0])

    @property
    def failure(self) -> str | None:
        """Why the planner worker failed on the current job, if it did."""
        return self._failure

    @property
    def buffered_periods(self) -> int:
        """Planned setpoints waiting in the buffer (0 when not following a plan)."""
        return self._buffered_rows

    @property
    def planning_done(self) -> bool:
        """Whether the current plan is buffered to its end (or there is none to plan)."""
        job = self._job
        return job is None or job.done

    def take(self) -> FeedEvent:
        """Advance one period; the new setpoint is :attr:`current`."""
        if self.mode is FeedMode.BRAKING:
            return self._take_braking()
        if self.mode in (FeedMode.PLANNED, FeedMode.STARTING):
            return self._take_planned()
        return FeedEvent.NONE

    def remaining_segments(self) -> tuple[Segment, ...]:
        """The rest of the last job from the current setpoint on, starting from rest there."""
        now = self._current
        if now.path is None or not self._segments:
            return ()
        return (Segment(now.path, MotionState(now.s_mm)), *self._segments[now.segment + 1 :])

    def close(self) -> None:
        """Stop the worker thread."""
        with self._lock:
            self._stopping = True
            self._cancel_locked()
        self._worker.join(timeout=2.0)

    def _cancel_locked(self) -> None:
        self._job = None
        self._chunks = deque()
        self._chunk = None
        self._row = 0
        self._taken = 0
        self._buffered_rows = 0
        self._failure = None
        self._wake.notify_all()

    def _take_planned(self) -> FeedEvent:
        with self._lock:
            if self._failure is not None:
                return FeedEvent.PLANNER_FAILED
            if self.mode is FeedMode.STARTING and not self._started_locked():
                return FeedEvent.NONE
            chunk = self._chunk
            if chunk is None or self._row >= len(chunk.block):
                if not self._chunks:
                    return FeedEvent.UNDERRUN
                chunk = self._chunk = self._chunks.popleft()
                self._row = 0
            block, i = chunk.block, self._row
            self._row += 1
            self._taken += 1
            self._buffered_rows -= 1
            self._wake.notify_all()
            finished = chunk.last_of_job and self._row == len(block)
        self.mode = FeedMode.PLANNED
        self._current = Setpoint(
            tuple(block.position_mm[i].tolist()),
            float(block.s_mm[i]),
            float(block.feed_mm_s[i]),
            float(block.accel_mm_s2[i]),
            chunk.path,
            chunk.segment,
        )
        if not finished:
            return FeedEvent.NONE
        with self._lock:
            self._cancel_locked()
        self.mode = FeedMode.IDLE
        return FeedEvent.FINISHED

    def _started_locked(self) -> bool:
        job = self._job
        return self._buffered_rows >= self.start_lead_periods or (job is not None and job.done)

    def _take_braking(self) -> FeedEvent:
        profile = self._braking
        now = self._current
        if profile is None or now.path is None:
            self.mode = FeedMode.IDLE
            return FeedEvent.STOPPED
        self._braking_t_s += self.period_s
        distance, feed, accel = profile.sample(self._braking_t_s)
        path = now.path
        s = min(self._braking_from.s_mm + distance, path.length_mm)
        u = float(path.arc.u_of_s(s, u_guess=self._braking_u)[0])
        self._braking_u = u
        at_rest = self._braking_t_s >= profile.duration_s or s >= path.length_mm
        if at_rest:
            feed, accel = 0.0, 0.0
        position = tuple(path.curve.point(u).tolist())
        self._current = Setpoint(position, s, feed, accel, path, now.segment)
        if not at_rest:
            return FeedEvent.NONE
        self._braking = None
        self.mode = FeedMode.IDLE
        return FeedEvent.STOPPED

    # -- worker thread --------------------------------------------------------------------

    def _has_work(self) -> bool:
        job = self._job
        if job is None:
            return False
        if job.splice_limits is not None:
            return True
        return not job.done and self._buffered_rows < self.buffer_high_periods

    def _work(self) -> None:
        while True:
            with self._lock:
                while not self._stopping and not self._has_work():
                    self._wake.wait()
                if self._stopping:
                    return
                job = self._job
                splice = job.splice_limits
            try:
                if splice is not None:
                    self._splice(job, splice)
                else:
                    self._extend(job)
            except PlannerError as exc:
                self._fail(job, f"planner: {exc}")
            except Exception as exc:
                logger.exception("planner worker failed")
                self._fail(job, f"planner worker failed: {exc!r}")

    def _fail(self, job: _Job, reason: str) -> None:
        with self._lock:
            if self._job is job:
                self._failure = reason
                job.done = True
                job.splice_limits = None

    def _blocks(self, segment: Segment, limits: Limits) -> Iterator[SetpointBlock]:
        return stream_setpoints(
            segment.path,
            limits,
            self.period_s,
            start=segment.start,
            lookahead=self.lookahead,
            update=self.update,
            block_periods=self.block_periods,
        )

    def _make_chunk(self, job: _Job, segment: int, path: Path, block: SetpointBlock) -> _Chunk:
        return _Chunk(segment, path, block, block.last and segment == len(job.segments) - 1)

    def _extend(self, job: _Job) -> None:
        """Plan the job's next block and append it (the worker's step while nothing else waits)."""
        if job.blocks is None:
            job.blocks = self._blocks(job.segments[job.segment], job.limits)
        block = next(job.blocks, None)
        with self._lock:
            if self._job is not job:
                return
            if block is None:
                job.blocks = None
                job.segment += 1
                job.done = job.segment == len(job.segments)
                return
            self._chunks.append(
                self._make_chunk(job, job.segment, job.segments[job.segment].path, block)
            )
            self._buffered_rows += len(block)
            self._wake.notify_all()

    def _splice(self, job: _Job, limits: Limits) -> None:
        """Re-plan from a buffered row a little ahead of the cyclic task with ``limits``.

        The old plan keeps feeding the buffer until the new one is cut in, so the cyclic task
        never waits for the re-plan; if it took the chosen row meanwhile, try further ahead.
        """
        with self._lock:
            found = self._splice_point(self._taken + job.splice_lead)
        if found is None:
            if not job.done:
                self._extend(job)  # the row is not planned yet: the old plan goes on meanwhile
                return
            with self._lock:
                # Fewer rows left than the lead: the motion is already braking to its end.
                if job.splice_limits is limits:
                    job.splice_limits = None
            return
        row, segment, state = found
        path = job.segments[segment].path
        blocks = self._blocks(Segment(path, state), limits)
        first = next(blocks)
        with self._lock:
            if self._job is not job or job.splice_limits is not limits:
                return
            if row < self._taken:
                job.splice_lead *= 2
                return
            # Cut and append under one lock: the cyclic task never sees a gap.
            self._cut_after(row)
            self._chunks.append(self._make_chunk(job, segment, path, first))
            self._buffered_rows += len(first)
            job.limits = limits
            job.segment = segment
            job.blocks = blocks
            job.done = False
            job.splice_limits = None
            self._wake.notify_all()

    def _pending(self) -> Iterator[tuple[int, _Chunk, int]]:
        """(absolute row, chunk, row in chunk) of the first pending row of every chunk."""
        index = self._taken
        if self._chunk is not None and self._row < len(self._chunk.block):
            yield index, self._chunk, self._row
            index += len(self._chunk.block) - self._row
        for chunk in self._chunks:
            yield index, chunk, 0
            index += len(chunk.block)

    def _splice_point(self, wanted: int) -> tuple[int, int, MotionState] | None:
        """The row ``wanted`` with its segment and state, if it is buffered (lock held).

        Never a segment's final row (the motion rests there; nothing to re-plan).
        """
        for first, chunk, offset in self._pending():
            last = first + len(chunk.block) - offset - 1
            if chunk.block.last:
                last -= 1
            if first <= wanted <= last:
                return wanted, chunk.segment, chunk.block.state(offset + wanted - first)
        return None

    def _cut_after(self, row: int) -> None:
        """Drop every buffered row after ``row`` (lock held)."""
        kept: deque[_Chunk] = deque()
        for first, chunk, offset in list(self._pending()):
            n = len(chunk.block) - offset
            if row >= first + n - 1:
                if chunk is not self._chunk:
                    kept.append(chunk)
                continue
            end = offset + row - first + 1
            if chunk is self._chunk:
                self._chunk = _slice(chunk, end)
            elif row >= first:
                kept.append(_slice(chunk, end))
            break
        self._chunks = kept
        self._buffered_rows = row - self._taken + 1


def _slice(chunk: _Chunk, stop: int) -> _Chunk:
    """The rows of ``chunk`` before ``stop``, no longer marked as an end."""
    b = chunk.block
    part = SetpointBlock(
        t_s=b.t_s[:stop],
        s_mm=b.s_mm[:stop],
        u=b.u[:stop],
        position_mm=b.position_mm[:stop],
        feed_mm_s=b.feed_mm_s[:stop],
        accel_mm_s2=b.accel_mm_s2[:stop],
        jerk_mm_s3=b.jerk_mm_s3[:stop],
        last=False,
    )
    return _Chunk(chunk.segment, chunk.path, part, False)
