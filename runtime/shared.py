"""Everything that crosses a process boundary: the shared-memory layout, its sizes and version.

The runtime's processes (:mod:`runtime.supervisor`) share one memory-mapped file, created by the
supervisor and attached by the cycle, planner and HMI processes. Every structure another process
reads is defined here, with its writer and readers:

================  ===================  ===================  ==================================
channel           writer               readers              what
================  ===================  ===================  ==================================
header            supervisor (once)    all                  magic, version, sizes, axis count
rings[0], [1]     planner              cycle                planned setpoint rows (two rings:
                                                            one followed, one for the next plan)
ring cursors      cycle                planner              rows taken, rows still needed
planner_request   cycle                planner              follow / cancel / change limits
planner_report    planner              cycle                heartbeat, failures, ring offers
cycle_report      cycle                planner              offer answers, position in the rows
hmi_mailbox       HMI                  cycle                commands, in order
local_mailbox     supervisor           cycle                commands (command line, shutdown)
status            cycle                HMI, supervisor      one consistent snapshot per period
hmi_activity      HMI                  cycle                watchdog: heartbeat and commands
supervision       supervisor           cycle                planner restarts
log               cycle                supervisor           log records (never blocks)
================  ===================  ===================  ==================================

Consistency: one writer per field. A record read by another process either lives in a seqlock
(:class:`SeqlockCell`: the writer makes its counter odd, copies the record, makes it even; a
reader copies the record between two equal even reads of the counter, else tries later) or is
published by a counter (:class:`Mailbox`, :class:`SetpointRing`, :class:`LogRing`: the writer
fills slots first and moves its count after; the reader never reads past the count). Counters
are aligned 8-byte integers written and read in one access. This relies on a total store order
(x86-64): stores become visible in program order. No reader ever blocks or waits on a writer: a
record caught mid-write reads as "nothing new", to be read again next time.

Units: mm, s, mm/s; counts are plain integers. Strings are UTF-8, NUL-padded, cut to their field.

Invariants: :data:`LAYOUT_VERSION` changes with any change of a layout below; a process attaching
a file of another version or size refuses it (:class:`LayoutMismatch`).
"""

from __future__ import annotations

import mmap
import os
import struct
import time
from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path as FilePath

import numpy as np

from runtime.commands import Command, CommandCode, CommandOrigin, CommandRecord, CommandResult
from runtime.programs import NAME_BYTES, SOURCE_BYTES, Program
from runtime.status import (
    AxisStatus,
    CycleStatistics,
    Fault,
    FaultKind,
    MachineState,
    MotionPhase,
    ProgramStatus,
    StatusSnapshot,
    WatchdogState,
)

LAYOUT_MAGIC = 0x534D_5348  # "SMSH"
LAYOUT_VERSION = 1
#: Axes a layout has room for (the configuration allows at most this many).
MAX_AXES = 8
#: Setpoint rows per ring: 16 s at a 4 ms period, far more than the planner keeps ahead.
RING_ROWS = 4096
#: Commands a mailbox holds before ``post`` refuses.
MAILBOX_SLOTS = 32
#: Bytes of log records the cycle may queue before it drops (and counts) records.
LOG_BYTES = 1 << 18
MESSAGE_BYTES = 512
FAULT_TEXT_BYTES = 160
AXIS_NAME_BYTES = 16
AXIS_FAULT_BYTES = 128
FAILURE_TEXT_BYTES = 256
#: Faults listed after the first one, until a reset.
LATER_FAULTS = 8
#: Judged commands the status lists.
RECENT_COMMANDS = 16
#: Attempts a reader makes to catch a record between two writes before it gives up for now.
READ_ATTEMPTS = 4
#: Tries to catch a status snapshot between two of the cycle's writes before the last one read
#: stands in, and the pause between them [s] (the cycle's write takes a few µs).
SNAPSHOT_ATTEMPTS, SNAPSHOT_RETRY_S = 50, 0.0001

_CACHE_LINE = 64


def _aligned(size: int, to: int = _CACHE_LINE) -> int:
    return -(-size // to) * to


def _text(value: str, size: int) -> bytes:
    """``value`` as UTF-8 cut to ``size`` bytes on a character boundary (struct pads with NULs)."""
    return value.encode()[:size].decode(errors="ignore").encode()


def _untext(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode(errors="replace")


class LayoutMismatch(RuntimeError):
    """A shared-memory file that is not this runtime's layout (another version, size or axes)."""


class Counter:
    """One aligned 64-bit integer, written by one process (a single store) and read by others."""

    SIZE = 8

    def __init__(self, buf: memoryview, offset: int) -> None:
        self._cell = np.ndarray((1,), np.int64, buf, offset)

    @property
    def value(self) -> int:
        return int(self._cell[0])

    @value.setter
    def value(self, value: int) -> None:
        self._cell[0] = value


class SeqlockCell:
    """A record with one writer and any readers, never read torn (see the module docstring)."""

    def __init__(self, buf: memoryview, offset: int, layout: struct.Struct) -> None:
        self._seq = np.ndarray((1,), np.int64, buf, offset)
        self._data = buf[offset + 8 : offset + 8 + layout.size]
        self._layout = layout
        self._scratch = bytearray(layout.size)

    @staticmethod
    def size(layout: struct.Struct) -> int:
        return _aligned(8 + layout.size)

    @property
    def scratch(self) -> bytearray:
        """The writer's private image: fill it with ``pack_into`` pieces, then :meth:`publish`."""
        return self._scratch

    def publish(self) -> None:
        """Copy the writer's scratch image into the cell."""
        seq = int(self._seq[0])
        self._seq[0] = seq + 1
        self._data[:] = self._scratch
        self._seq[0] = seq + 2

    def write(self, *values: object) -> None:
        """Pack ``values`` with the cell's layout and publish them."""
        self._layout.pack_into(self._scratch, 0, *values)
        self.publish()

    @property
    def written(self) -> bool:
        """Whether the writer has published at least once."""
        return int(self._seq[0]) != 0

    @property
    def version(self) -> int:
        """Changes with every publish (one read: a poller skips the copy while it stands)."""
        return int(self._seq[0])

    def read_bytes(self) -> bytes | None:
        """A consistent copy of the record; None if never written or caught mid-write."""
        for _ in range(READ_ATTEMPTS):
            before = int(self._seq[0])
            if before == 0:
                return None
            if before & 1:
                continue
            copy = bytes(self._data)
            if int(self._seq[0]) == before:
                return copy
        return None

    def read(self) -> tuple | None:
        """The record's values; None if never written or caught mid-write."""
        copy = self.read_bytes()
        return None if copy is None else self._layout.unpack(copy)


# -- setpoint rings ---------------------------------------------------------------------------


class RowFlag(IntEnum):
    """Bits of a setpoint row's ``flags``."""

    LAST_OF_SEGMENT = 1
    """The segment's final row: at rest at its end."""
    LAST_OF_JOB = 2
    """The job's final row: nothing follows."""


ROW_DTYPE = np.dtype(
    [
        ("s_mm", "<f8"),
        ("feed_mm_s", "<f8"),
        ("accel_mm_s2", "<f8"),
        ("position_mm", "<f8", (MAX_AXES,)),
        ("segment", "<i4"),
        ("flags", "<i4"),
    ]
)

# Planner-written ring header.
_RING_JOB, _RING_FIRST_ROW, _RING_WRITE_COUNT = range(3)
# Cycle-written ring cursor.
_CURSOR_NEEDED_FROM, _CURSOR_JOB = range(2)


class SetpointRing:
    """Planned setpoint rows of one job, numbered from the job's first row on.

    The planner :meth:`begin` s a job (or a re-plan of it) from a row number, :meth:`append` s rows
    and moves the write count after them. The cycle reads row ``i`` of the job while
    ``first_row <= i < write_count`` and publishes in its cursor the lowest row it may still read;
    the planner never overwrites a slot holding a row at or after that one.
    """

    def __init__(self, buf: memoryview, offset: int, rows: int = RING_ROWS) -> None:
        self.capacity = rows
        self._header = np.ndarray((3,), np.int64, buf, offset)
        self._cursor = np.ndarray((2,), np.int64, buf, offset + _CACHE_LINE)
        rows_at = offset + 2 * _CACHE_LINE
        self._rows = np.ndarray((rows,), ROW_DTYPE, buf, rows_at)
        self.s_mm = self._rows["s_mm"]
        self.feed_mm_s = self._rows["feed_mm_s"]
        self.accel_mm_s2 = self._rows["accel_mm_s2"]
        self.position_mm = self._rows["position_mm"]
        self.segment = self._rows["segment"]
        self.flags = self._rows["flags"]

    @staticmethod
    def size(rows: int = RING_ROWS) -> int:
        return 2 * _CACHE_LINE + _aligned(rows * ROW_DTYPE.itemsize)

    # -- planner side ----------------------------------------------------------------------

    def begin(self, job: int, first_row: int) -> None:
        """Start writing ``job``'s rows from ``first_row`` (only while the cycle is not reading
        this ring)."""
        self._header[_RING_WRITE_COUNT] = first_row
        self._header[_RING_FIRST_ROW] = first_row
        self._header[_RING_JOB] = job

    def room(self) -> int:
        """Rows :meth:`append` can take now without overwriting a row the cycle may still read."""
        needed_from = int(self._cursor[_CURSOR_NEEDED_FROM])
        if int(self._cursor[_CURSOR_JOB]) != self.job:
            needed_from = self.first_row
        return max(0, needed_from + self.capacity - self.write_count)

    def append(
        self,
        *,
        s_mm: np.ndarray,
        feed_mm_s: np.ndarray,
        accel_mm_s2: np.ndarray,
        position_mm: np.ndarray,
        segment: int,
        flags: np.ndarray | None = None,
    ) -> None:
        """Write rows after the last one and publish them (the caller checked :meth:`room`)."""
        count = len(s_mm)
        first = self.write_count
        slots = self.slots(first, first + count)
        self.s_mm[slots] = s_mm
        self.feed_mm_s[slots] = feed_mm_s
        self.accel_mm_s2[slots] = accel_mm_s2
        dimension = position_mm.shape[1]
        block = np.zeros((count, MAX_AXES))
        block[:, :dimension] = position_mm
        self.position_mm[slots] = block
        self.segment[slots] = segment
        self.flags[slots] = 0 if flags is None else flags
        self._header[_RING_WRITE_COUNT] = first + count

    # -- both sides ------------------------------------------------------------------------

    @property
    def job(self) -> int:
        return int(self._header[_RING_JOB])

    @property
    def first_row(self) -> int:
        return int(self._header[_RING_FIRST_ROW])

    @property
    def write_count(self) -> int:
        return int(self._header[_RING_WRITE_COUNT])

    # -- cycle side ------------------------------------------------------------------------

    def slot(self, row: int) -> int:
        return row % self.capacity

    def slots(self, first_row: int, stop_row: int) -> np.ndarray:
        """The slots of rows ``first_row`` up to ``stop_row`` (excluded), for indexing."""
        return (np.arange(first_row, stop_row) % self.capacity).astype(np.intp)

    def hold_from(self, job: int, row: int) -> None:
        """The cycle may still read ``job``'s rows from ``row`` on (-1 job: none)."""
        self._cursor[_CURSOR_NEEDED_FROM] = row
        self._cursor[_CURSOR_JOB] = job

    def needed_from(self) -> tuple[int, int]:
        """(job, row) the cycle holds (see :meth:`hold_from`)."""
        return int(self._cursor[_CURSOR_JOB]), int(self._cursor[_CURSOR_NEEDED_FROM])


# -- planner requests, reports and the cycle's answers ---------------------------------------


class PlanRequestKind(IntEnum):
    NONE = 0
    FOLLOW = 1
    """Plan the job's segments from ``start`` and offer them in a ring at row 0."""
    CANCEL = 2
    """Stop planning the job."""
    CHANGE_LIMITS = 3
    """Re-plan the rest of the job with the new override, spliced a little ahead."""


class SegmentKind(IntEnum):
    NONE = 0
    LINE = 1
    """A straight line between two points (the approach to a program's start)."""
    PROGRAM = 2
    """A stored program's curve."""


@dataclass(frozen=True)
class SegmentSpec:
    """One segment of a job: a line or a program."""

    kind: SegmentKind
    from_mm: tuple[float, ...] = ()
    to_mm: tuple[float, ...] = ()
    program: Program | None = None


@dataclass(frozen=True)
class PlanRequest:
    """What the cycle asks of the planner (the latest request replaces the previous one)."""

    seq: int
    kind: PlanRequestKind
    job: int
    override_percent: float = 100.0
    segments: tuple[SegmentSpec, ...] = ()
    start_segment: int = 0
    start_s_mm: float = 0.0
    start_v_mm_s: float = 0.0
    start_a_mm_s2: float = 0.0


_AXES_F8 = f"{MAX_AXES}d"
_PROGRAM_FORMAT = f"qId{_AXES_F8}{_AXES_F8}B{NAME_BYTES}s{SOURCE_BYTES}s"
_SEGMENT_FORMAT = f"B{_AXES_F8}{_AXES_F8}B" + _PROGRAM_FORMAT
_MAX_SEGMENTS = 2
_REQUEST_LAYOUT = struct.Struct("<qBqdBBddd" + _SEGMENT_FORMAT * _MAX_SEGMENTS)


def _pack_program(program: Program | None) -> tuple:
    if program is None:
        return (0, 0, 0.0, *([0.0] * MAX_AXES), *([0.0] * MAX_AXES), 0, b"", b"")
    return (
        program.program_id,
        program.crc32,
        program.length_mm,
        *_padded(program.start_mm),
        *_padded(program.end_mm),
        program.dimension,
        _text(program.name, NAME_BYTES),
        _text(program.source, SOURCE_BYTES),
    )


def _unpack_program(values: tuple) -> Program | None:
    program_id, crc32, length_mm = values[:3]
    if program_id == 0:
        return None
    dimension = values[3 + 2 * MAX_AXES]
    start = values[3 : 3 + dimension]
    end = values[3 + MAX_AXES : 3 + MAX_AXES + dimension]
    name, source = values[4 + 2 * MAX_AXES : 6 + 2 * MAX_AXES]
    return Program(
        program_id=program_id,
        source=_untext(source),
        name=_untext(name),
        crc32=crc32,
        length_mm=length_mm,
        start_mm=tuple(start),
        end_mm=tuple(end),
    )


_PROGRAM_FIELDS = 6 + 2 * MAX_AXES
_SEGMENT_FIELDS = 2 + 2 * MAX_AXES + _PROGRAM_FIELDS


def _padded(values: tuple[float, ...]) -> list[float]:
    return [*values, *([0.0] * (MAX_AXES - len(values)))]


def _pack_segment(segment: SegmentSpec | None) -> tuple:
    if segment is None:
        return (0, *([0.0] * (2 * MAX_AXES)), 0, *_pack_program(None))
    return (
        segment.kind,
        *_padded(segment.from_mm),
        *_padded(segment.to_mm),
        len(segment.from_mm),
        *_pack_program(segment.program),
    )


def _unpack_segment(values: tuple) -> SegmentSpec | None:
    kind = SegmentKind(values[0])
    if kind is SegmentKind.NONE:
        return None
    dimension = values[1 + 2 * MAX_AXES]
    return SegmentSpec(
        kind=kind,
        from_mm=tuple(values[1 : 1 + dimension]),
        to_mm=tuple(values[1 + MAX_AXES : 1 + MAX_AXES + dimension]),
        program=_unpack_program(values[2 + 2 * MAX_AXES :]),
    )


class PlannerRequests:
    """The cycle's latest request to the planner (a seqlock cell; the newest one counts)."""

    def __init__(self, buf: memoryview, offset: int) -> None:
        self._cell = SeqlockCell(buf, offset, _REQUEST_LAYOUT)

    @staticmethod
    def size() -> int:
        return SeqlockCell.size(_REQUEST_LAYOUT)

    def post(self, request: PlanRequest) -> None:
        """Publish ``request`` (the cycle; a few µs, no allocation beyond the packing)."""
        if len(request.segments) > _MAX_SEGMENTS:
            raise ValueError(f"a job has at most {_MAX_SEGMENTS} segments")
        segments = [*request.segments, *([None] * (_MAX_SEGMENTS - len(request.segments)))]
        values: list[object] = [
            request.seq,
            request.kind,
            request.job,
            request.override_percent,
            len(request.segments),
            request.start_segment,
            request.start_s_mm,
            request.start_v_mm_s,
            request.start_a_mm_s2,
        ]
        for segment in segments:
            values.extend(_pack_segment(segment))
        self._cell.write(*values)

    @property
    def version(self) -> int:
        """Changes with every posted request (see :attr:`SeqlockCell.version`)."""
        return self._cell.version

    def latest(self) -> PlanRequest | None:
        """The latest request; None if none yet (or caught mid-write)."""
        values = self._cell.read()
        if values is None:
            return None
        count = values[4]
        segments = []
        for i in range(count):
            at = 9 + i * _SEGMENT_FIELDS
            segment = _unpack_segment(values[at : at + _SEGMENT_FIELDS])
            if segment is not None:
                segments.append(segment)
        return PlanRequest(
            seq=values[0],
            kind=PlanRequestKind(values[1]),
            job=values[2],
            override_percent=values[3],
            segments=tuple(segments),
            start_segment=values[5],
            start_s_mm=values[6],
            start_v_mm_s=values[7],
            start_a_mm_s2=values[8],
        )


@dataclass(frozen=True)
class RingOffer:
    """The planner offers the rows of ``job`` in ``ring`` from ``at_row`` on."""

    seq: int
    ring: int
    job: int
    at_row: int
    override_request: int = 0
    """A splice: seq of the newest override change it plans with (0: a job's start)."""
    rest_row: int = -1
    """A splice that had to wait for the old rows' braking to rest (a sharp corner, the
    approach's end): the row at that rest, the one before ``at_row``; else -1."""


@dataclass(frozen=True)
class PlannerReport:
    """What the planner tells the cycle besides the rows themselves."""

    handled_request: int = 0
    """Seq of the last request the planner has taken up."""
    failed_job: int = 0
    """A job the planner could not plan (0: none); ``failure`` says why."""
    failure: str = ""
    offer: RingOffer | None = None


_REPORT_LAYOUT = struct.Struct(f"<qq{FAILURE_TEXT_BYTES}sqqqqqq")


class PlannerReports:
    """The planner's report to the cycle (a seqlock cell) and its heartbeat (a counter)."""

    def __init__(self, buf: memoryview, offset: int) -> None:
        self.heartbeat = Counter(buf, offset)
        self._cell = SeqlockCell(buf, offset + _CACHE_LINE, _REPORT_LAYOUT)

    @staticmethod
    def size() -> int:
        return _CACHE_LINE + SeqlockCell.size(_REPORT_LAYOUT)

    def publish(self, report: PlannerReport) -> None:
        offer = report.offer or RingOffer(0, 0, 0, 0)
        self._cell.write(
            report.handled_request,
            report.failed_job,
            _text(report.failure, FAILURE_TEXT_BYTES),
            offer.seq,
            offer.ring,
            offer.job,
            offer.at_row,
            offer.override_request,
            offer.rest_row,
        )

    def latest(self) -> PlannerReport | None:
        values = self._cell.read()
        if values is None:
            return None
        handled, failed_job, failure, offer_seq, *offer = values
        return PlannerReport(
            handled_request=handled,
            failed_job=failed_job,
            failure=_untext(failure),
            offer=RingOffer(offer_seq, *offer) if offer_seq else None,
        )


@dataclass(frozen=True)
class CycleReport:
    """What the cycle tells the planner: its answer to the last offer and where it reads."""

    offer_answered: int = 0
    """Seq of the last ring offer the cycle judged."""
    offer_accepted: bool = False
    job: int = 0
    """The job the cycle follows (or waits for); 0 when none."""
    ring: int = 0
    """The ring it reads (after the switch it accepted last)."""
    next_row: int = 0
    """The next row of ``job`` it will take."""


_CYCLE_REPORT_LAYOUT = struct.Struct("<q?qqq")


class CycleReports:
    """The cycle's report to the planner (a seqlock cell)."""

    def __init__(self, buf: memoryview, offset: int) -> None:
        self._cell = SeqlockCell(buf, offset, _CYCLE_REPORT_LAYOUT)

    @staticmethod
    def size() -> int:
        return SeqlockCell.size(_CYCLE_REPORT_LAYOUT)

    def publish(self, report: CycleReport) -> None:
        self._cell.write(
            report.offer_answered, report.offer_accepted, report.job, report.ring, report.next_row
        )

    def latest(self) -> CycleReport:
        values = self._cell.read()
        return CycleReport() if values is None else CycleReport(*values)


# -- command mailboxes ------------------------------------------------------------------------

_COMMAND_LAYOUT = struct.Struct("<qBBId" + _PROGRAM_FORMAT)


class Mailbox:
    """Commands from one producer process to the cycle, in order (single producer, single
    consumer). ``post`` never blocks: a full mailbox refuses the command."""

    def __init__(self, buf: memoryview, offset: int, slots: int = MAILBOX_SLOTS) -> None:
        self.capacity = slots
        self._written = Counter(buf, offset)
        self._taken = Counter(buf, offset + _CACHE_LINE)
        self._slots_at = offset + 2 * _CACHE_LINE
        self._buf = buf

    @staticmethod
    def size(slots: int = MAILBOX_SLOTS) -> int:
        return 2 * _CACHE_LINE + _aligned(slots * _COMMAND_LAYOUT.size)

    def post(self, command: Command) -> int | None:
        """Queue ``command``; returns its ticket (1, 2, ... per mailbox), None when full."""
        written = self._written.value
        if written - self._taken.value >= self.capacity:
            return None
        ticket = written + 1
        _COMMAND_LAYOUT.pack_into(
            self._buf,
            self._slot_offset(written),
            ticket,
            command.code,
            command.origin,
            command.seq & 0xFFFF_FFFF,
            0.0 if command.override_percent is None else float(command.override_percent),
            *_pack_program(command.program),
        )
        self._written.value = ticket
        return ticket

    def take(self) -> Command | None:
        """The oldest command not yet taken (the cycle), or None."""
        taken = self._taken.value
        if taken >= self._written.value:
            return None
        values = _COMMAND_LAYOUT.unpack_from(self._buf, self._slot_offset(taken))
        self._taken.value = taken + 1
        ticket, code, origin, seq, override = values[:5]
        command_code = CommandCode(code)
        return Command(
            code=command_code,
            origin=CommandOrigin(origin),
            override_percent=override if command_code is CommandCode.SET_OVERRIDE else None,
            program=_unpack_program(values[5:]),
            seq=seq,
            ticket=ticket,
        )

    @property
    def pending(self) -> int:
        return self._written.value - self._taken.value

    def _slot_offset(self, index: int) -> int:
        return self._slots_at + (index % self.capacity) * _COMMAND_LAYOUT.size


# -- status -----------------------------------------------------------------------------------

_STATUS_HEAD = "IQBBB?BbH" + f"{FAULT_TEXT_BYTES}s" + "dddd" + "QfffffffQHHI" + f"{MESSAGE_BYTES}s"
_PROGRAM_STATUS = f"qId{NAME_BYTES}s"
_LATER_FAULT = f"HbH{FAULT_TEXT_BYTES}s"
_RECORD = "qBIBB"
_AXIS = f"{AXIS_NAME_BYTES}sBddddbHB{AXIS_FAULT_BYTES}s"
_STATUS_LAYOUT = struct.Struct(
    "<"
    + _STATUS_HEAD
    + _PROGRAM_STATUS * 2
    + "B"
    + _LATER_FAULT * LATER_FAULTS
    + "B"
    + _RECORD * RECENT_COMMANDS
    + "B"
    + _AXIS * MAX_AXES
)
_AXIS_FIELDS = 10
_NO_FAULT = (0, -1, 0, b"")
_NO_RECORD = (0, 0, 0, 0, 0)


def _fault_values(fault: Fault | None, axis_names: tuple[str, ...]) -> tuple:
    if fault is None:
        return _NO_FAULT
    axis = axis_names.index(fault.axis) if fault.axis in axis_names else -1
    return (fault.kind, axis, fault.emcy_code & 0xFFFF, _text(fault.text, FAULT_TEXT_BYTES))


def _program_values(program: ProgramStatus | None) -> tuple:
    if program is None:
        return (0, 0, 0.0, b"")
    return (program.program_id, program.crc32, program.length_mm, _text(program.name, NAME_BYTES))


class StatusBoard:
    """The cycle's status snapshot of each period (a seqlock cell).

    The cycle keeps the rarely changing parts (faults, commands, programs, texts) in the cell's
    scratch image and repacks them only when they change (the ``set_*`` methods), packs the rest
    every period (:meth:`publish`). Readers decode a :class:`StatusSnapshot`.
    """

    def __init__(self, buf: memoryview, offset: int, axis_names: tuple[str, ...]) -> None:
        self._cell = SeqlockCell(buf, offset, _STATUS_LAYOUT)
        self.axis_names = axis_names
        self._values: list[object] = list(_STATUS_LAYOUT.unpack(bytes(_STATUS_LAYOUT.size)))
        self._offsets = _status_offsets()
        self._last_read: StatusSnapshot | None = None

    @staticmethod
    def size() -> int:
        return SeqlockCell.size(_STATUS_LAYOUT)

    # -- cycle side ------------------------------------------------------------------------

    def set(self, **fields: object) -> None:
        """Change fields of the image (names as in :func:`status_field_names`)."""
        index = self._offsets
        for name, value in fields.items():
            self._values[index[name]] = value

    def set_fault(self, fault: Fault | None, later: tuple[Fault, ...]) -> None:
        kind, axis, emcy, text = _fault_values(fault, self.axis_names)
        self.set(fault_kind=kind, fault_axis=axis, fault_emcy=emcy, fault_text=text)
        at = self._offsets["later_count"]
        self._values[at] = min(len(later), LATER_FAULTS)
        for i in range(LATER_FAULTS):
            values = _fault_values(later[i], self.axis_names) if i < len(later) else _NO_FAULT
            self._values[at + 1 + 4 * i : at + 5 + 4 * i] = values

    def set_commands(self, records: tuple[CommandRecord, ...]) -> None:
        at = self._offsets["record_count"]
        records = records[-RECENT_COMMANDS:]
        self._values[at] = len(records)
        for i in range(RECENT_COMMANDS):
            values = _NO_RECORD
            if i < len(records):
                r = records[i]
                values = (r.ticket, r.origin, r.seq & 0xFFFF_FFFF, r.code, r.result)
            self._values[at + 1 + 5 * i : at + 6 + 5 * i] = values

    def set_programs(
        self, program: ProgramStatus | None, next_program: ProgramStatus | None
    ) -> None:
        at = self._offsets["program_id"]
        self._values[at : at + 4] = _program_values(program)
        self._values[at + 4 : at + 8] = _program_values(next_program)

    def set_message(self, message: str) -> None:
        self.set(message=_text(message, MESSAGE_BYTES))

    def set_axis(self, index: int, *values: object) -> None:
        """Axis ``index``: name, node id, commanded, actual, following error, its peak, drive
        state, statusword, boot phase, fault text (bytes)."""
        at = self._offsets["axis_count"] + 1 + index * _AXIS_FIELDS
        self._values[at : at + _AXIS_FIELDS] = values

    def publish(self) -> None:
        _STATUS_LAYOUT.pack_into(self._cell.scratch, 0, *self._values)
        self._cell.publish()

    # -- readers ---------------------------------------------------------------------------

    @property
    def published(self) -> bool:
        """Whether the cycle has published a snapshot yet."""
        return self._cell.written

    def snapshot(self) -> StatusSnapshot | None:
        """The last published snapshot; None only before the first.

        A read that meets the cycle mid-write is tried again after a short pause; should the
        cycle be writing at every try (a reader preempted for a while), the snapshot this
        reader got last stands in.
        """
        for _ in range(SNAPSHOT_ATTEMPTS):
            copy = self._cell.read_bytes()
            if copy is not None:
                self._last_read = _decode_status(_STATUS_LAYOUT.unpack(copy), self.axis_names)
                return self._last_read
            if self._last_read is None and not self.published:
                return None
            time.sleep(SNAPSHOT_RETRY_S)
        return self._last_read


_STATUS_HEAD_FIELDS = (
    "heartbeat",
    "cycle_count",
    "state",
    "phase",
    "watchdog",
    "in_position",
    "fault_kind",
    "fault_axis",
    "fault_emcy",
    "fault_text",
    "feed_mm_s",
    "path_s_mm",
    "path_length_mm",
    "override_percent",
    "stats_cycles",
    "lateness_last_us",
    "lateness_p50_us",
    "lateness_p99_us",
    "lateness_p999_us",
    "lateness_max_us",
    "execution_last_us",
    "execution_max_us",
    "missed_periods",
    "override_latency_periods",
    "override_rest_wait_periods",
    "overrides_applied",
    "message",
    "program_id",
)


def _status_offsets() -> dict[str, int]:
    offsets = {name: i for i, name in enumerate(_STATUS_HEAD_FIELDS)}
    at = len(_STATUS_HEAD_FIELDS) - 1 + 8  # two program records of four values
    offsets["later_count"] = at
    at += 1 + 4 * LATER_FAULTS
    offsets["record_count"] = at
    at += 1 + 5 * RECENT_COMMANDS
    offsets["axis_count"] = at
    return offsets


def status_field_names() -> tuple[str, ...]:
    """Names :meth:`StatusBoard.set` accepts."""
    return (*_STATUS_HEAD_FIELDS[:-1], "axis_count")


def _decode_fault(values: tuple, axis_names: tuple[str, ...]) -> Fault | None:
    kind, axis, emcy, text = values
    if kind == FaultKind.NONE:
        return None
    return Fault(
        kind=FaultKind(kind),
        text=_untext(text),
        axis=axis_names[axis] if 0 <= axis < len(axis_names) else None,
        emcy_code=emcy,
    )


def _decode_program(values: tuple) -> ProgramStatus | None:
    program_id, crc32, length_mm, name = values
    if program_id == 0:
        return None
    return ProgramStatus(program_id, _untext(name), crc32, length_mm)


def _decode_status(values: tuple, axis_names: tuple[str, ...]) -> StatusSnapshot:
    offsets = _status_offsets()
    v = dict(zip(_STATUS_HEAD_FIELDS[:-1], values, strict=False))
    at = offsets["program_id"]
    program = _decode_program(values[at : at + 4])
    next_program = _decode_program(values[at + 4 : at + 8])
    at = offsets["later_count"]
    later = tuple(
        fault
        for i in range(values[at])
        if (fault := _decode_fault(values[at + 1 + 4 * i : at + 5 + 4 * i], axis_names)) is not None
    )
    at = offsets["record_count"]
    records = tuple(
        CommandRecord(
            ticket=t,
            origin=CommandOrigin(o),
            seq=s,
            code=CommandCode(c),
            result=CommandResult(r),
        )
        for t, o, s, c, r in (values[at + 1 + 5 * i : at + 6 + 5 * i] for i in range(values[at]))
    )
    at = offsets["axis_count"]
    axes = []
    for i in range(values[at]):
        first = at + 1 + _AXIS_FIELDS * i
        name, node, commanded, actual, error, peak, state, word, phase, fault = values[
            first : first + _AXIS_FIELDS
        ]
        axes.append(
            AxisStatus(
                name=_untext(name),
                node_id=node,
                commanded_mm=commanded,
                actual_mm=actual,
                drive_state=state,
                following_error_mm=error,
                peak_following_error_mm=peak,
                statusword=word,
                boot_phase=phase,
                fault=_untext(fault),
            )
        )
    return StatusSnapshot(
        state=MachineState(v["state"]),
        fault=_decode_fault(
            (v["fault_kind"], v["fault_axis"], v["fault_emcy"], v["fault_text"]), axis_names
        ),
        later_faults=later,
        axes=tuple(axes),
        phase=MotionPhase(v["phase"]),
        feed_mm_s=v["feed_mm_s"],
        path_s_mm=v["path_s_mm"],
        path_length_mm=v["path_length_mm"],
        in_position=bool(v["in_position"]),
        program=program,
        next_program=next_program,
        override_percent=v["override_percent"],
        stats=CycleStatistics(
            cycles=v["stats_cycles"],
            lateness_last_us=v["lateness_last_us"],
            lateness_p50_us=v["lateness_p50_us"],
            lateness_p99_us=v["lateness_p99_us"],
            lateness_p999_us=v["lateness_p999_us"],
            lateness_max_us=v["lateness_max_us"],
            execution_last_us=v["execution_last_us"],
            execution_max_us=v["execution_max_us"],
            missed_periods=v["missed_periods"],
            override_latency_periods=v["override_latency_periods"],
            override_rest_wait_periods=v["override_rest_wait_periods"],
            overrides_applied=v["overrides_applied"],
        ),
        last_command=records[-1] if records else None,
        recent_commands=records,
        watchdog=WatchdogState(v["watchdog"]),
        heartbeat=v["heartbeat"],
        message=_untext(v["message"]),
    )


# -- log records ------------------------------------------------------------------------------

_LOG_RECORD = struct.Struct("<IB")
_LOG_WRAP = 0xFFFF_FFFF


@dataclass(frozen=True)
class LogEntry:
    level: int
    logger: str
    message: str


class LogRing:
    """Log records from the cycle to the supervisor: a byte ring written without blocking (a
    record that does not fit is dropped and counted)."""

    def __init__(self, buf: memoryview, offset: int, capacity: int = LOG_BYTES) -> None:
        self.capacity = capacity
        self._written = Counter(buf, offset)
        self._dropped = Counter(buf, offset + 8)
        self._read = Counter(buf, offset + _CACHE_LINE)
        self._data = buf[offset + 2 * _CACHE_LINE : offset + 2 * _CACHE_LINE + capacity]

    @staticmethod
    def size(capacity: int = LOG_BYTES) -> int:
        return 2 * _CACHE_LINE + capacity

    @property
    def dropped(self) -> int:
        return self._dropped.value

    def write(self, level: int, logger: str, message: str) -> bool:
        """Queue one record; False (and counted) when the ring is full."""
        body = logger.encode()[:255] + b"\0" + message.encode()[: self.capacity // 8]
        need = _LOG_RECORD.size + len(body)
        written = self._written.value
        free = self.capacity - (written - self._read.value)
        at = written % self.capacity
        pad = self.capacity - at if self.capacity - at < need else 0
        if need + pad > free:
            self._dropped.value = self._dropped.value + 1
            return False
        if pad:
            if pad >= _LOG_RECORD.size:
                _LOG_RECORD.pack_into(self._data, at, _LOG_WRAP, 0)
            written += pad
            at = 0
        _LOG_RECORD.pack_into(self._data, at, len(body), level)
        start = at + _LOG_RECORD.size
        self._data[start : start + len(body)] = body
        self._written.value = written + need
        return True

    def read(self) -> list[LogEntry]:
        """Every queued record (the supervisor)."""
        entries = []
        read = self._read.value
        written = self._written.value
        while read < written:
            at = read % self.capacity
            if self.capacity - at < _LOG_RECORD.size:
                read += self.capacity - at
                continue
            length, level = _LOG_RECORD.unpack_from(self._data, at)
            if length == _LOG_WRAP:
                read += self.capacity - at
                continue
            start = at + _LOG_RECORD.size
            body = bytes(self._data[start : start + length])
            name, _, text = body.partition(b"\0")
            entries.append(
                LogEntry(level, name.decode(errors="replace"), text.decode("utf-8", "replace"))
            )
            read += _LOG_RECORD.size + length
        self._read.value = read
        return entries


# -- the whole file ---------------------------------------------------------------------------

_HEADER = struct.Struct("<IIQII")


@dataclass(frozen=True)
class _Offsets:
    rings: tuple[int, int]
    planner_request: int
    planner_report: int
    cycle_report: int
    hmi_mailbox: int
    local_mailbox: int
    status: int
    hmi_activity: int
    supervision: int
    log: int
    size: int


def _layout() -> _Offsets:
    at = _CACHE_LINE
    places: list[int] = []
    for size in (
        SetpointRing.size(),
        SetpointRing.size(),
        PlannerRequests.size(),
        PlannerReports.size(),
        CycleReports.size(),
        Mailbox.size(),
        Mailbox.size(),
        StatusBoard.size(),
        _CACHE_LINE,
        _CACHE_LINE,
        LogRing.size(),
    ):
        places.append(at)
        at += _aligned(size)
    return _Offsets((places[0], places[1]), *places[2:], size=at)


LAYOUT = _layout()


class SharedState:
    """The runtime's shared memory, created by the supervisor or attached by a process.

    :param buf: the whole mapped file (or any buffer of :data:`LAYOUT` size, for tests).
    :param axis_names: the configured axes (the status decodes axis indices into names).
    """

    def __init__(self, buf: memoryview, axis_names: tuple[str, ...], mapping=None) -> None:
        if len(buf) < LAYOUT.size:
            raise LayoutMismatch(f"shared memory of {len(buf)} bytes, layout needs {LAYOUT.size}")
        self._mapping = mapping
        self.buf = buf
        self.rings = (SetpointRing(buf, LAYOUT.rings[0]), SetpointRing(buf, LAYOUT.rings[1]))
        self.planner_requests = PlannerRequests(buf, LAYOUT.planner_request)
        self.planner_reports = PlannerReports(buf, LAYOUT.planner_report)
        self.cycle_reports = CycleReports(buf, LAYOUT.cycle_report)
        self.hmi_mailbox = Mailbox(buf, LAYOUT.hmi_mailbox)
        self.local_mailbox = Mailbox(buf, LAYOUT.local_mailbox)
        self.status = StatusBoard(buf, LAYOUT.status, axis_names)
        self.hmi_activity = Counter(buf, LAYOUT.hmi_activity)
        """+1 for every HMI heartbeat change or accepted command (the watchdog's input)."""
        self.planner_generation = Counter(buf, LAYOUT.supervision)
        """+1 each time the supervisor (re)starts the planner process."""
        self.log = LogRing(buf, LAYOUT.log)

    @classmethod
    def in_memory(cls, axis_names: tuple[str, ...]) -> SharedState:
        """A private instance over ordinary memory (tests, one-process use)."""
        buf = memoryview(bytearray(LAYOUT.size))
        _HEADER.pack_into(buf, 0, LAYOUT_MAGIC, LAYOUT_VERSION, LAYOUT.size, len(axis_names), 0)
        return cls(buf, axis_names)

    @classmethod
    def create(cls, path: str | os.PathLike[str], axis_names: tuple[str, ...]) -> SharedState:
        """Create the file at ``path`` (replacing any) and map it."""
        if len(axis_names) > MAX_AXES:
            raise ValueError(f"{len(axis_names)} axes, the shared layout holds {MAX_AXES}")
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            os.ftruncate(fd, LAYOUT.size)
            mapping = mmap.mmap(fd, LAYOUT.size)
        finally:
            os.close(fd)
        buf = memoryview(mapping)
        _HEADER.pack_into(buf, 0, LAYOUT_MAGIC, LAYOUT_VERSION, LAYOUT.size, len(axis_names), 0)
        return cls(buf, axis_names, mapping)

    @classmethod
    def attach(cls, path: str | os.PathLike[str], axis_names: tuple[str, ...]) -> SharedState:
        """Map the file the supervisor created.

        :raises LayoutMismatch: a file of another layout version, size or axis count.
        """
        fd = os.open(path, os.O_RDWR)
        try:
            size = os.fstat(fd).st_size
            if size != LAYOUT.size:
                raise LayoutMismatch(f"{path}: {size} bytes, this layout has {LAYOUT.size}")
            mapping = mmap.mmap(fd, size)
        finally:
            os.close(fd)
        buf = memoryview(mapping)
        magic, version, _, axes, _ = _HEADER.unpack_from(buf, 0)
        if (magic, version, axes) != (LAYOUT_MAGIC, LAYOUT_VERSION, len(axis_names)):
            buf.release()
            mapping.close()
            raise LayoutMismatch(
                f"{path}: magic 0x{magic:08X} version {version} axes {axes}, expected "
                f"0x{LAYOUT_MAGIC:08X} version {LAYOUT_VERSION} axes {len(axis_names)}"
            )
        return cls(buf, axis_names, mapping)

    def close(self) -> None:
        """Unmap (numpy views into it must be gone: the process is ending)."""
        if self._mapping is not None:
            try:
                self.buf.release()
                self._mapping.close()
            except BufferError:
                pass  # views still alive; the mapping goes with the process


def shared_path(directory: str | os.PathLike[str]) -> FilePath:
    """Where the runtime's shared-memory file lives in its run directory."""
    return FilePath(directory) / "shared.mem"
