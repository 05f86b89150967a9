"""The shared-memory layout: every channel round-trips its records, never blocks its writer, and a
reader in another process never sees a record half written."""

from __future__ import annotations

import multiprocessing
from pathlib import Path

import numpy as np
import pytest

from runtime.commands import Command, CommandCode, CommandOrigin, CommandRecord, CommandResult
from runtime.programs import Program
from runtime.shared import (
    LOG_BYTES,
    MAILBOX_SLOTS,
    MESSAGE_BYTES,
    RING_ROWS,
    LayoutMismatch,
    PlanRequest,
    PlanRequestKind,
    SegmentKind,
    SegmentSpec,
    SeqlockCell,
    SharedState,
)
from runtime.status import Fault, FaultKind, ProgramStatus

AXES = ("X", "Y", "Z")
PROGRAM = Program(
    program_id=7,
    source="/run/softmotion/program-7.npz",
    name="bracket ±0.1",
    crc32=0xDEADBEEF,
    length_mm=173.5,
    start_mm=(5.0, 5.0, 4.0),
    end_mm=(132.0, 40.0, 41.0),
)


@pytest.fixture
def shared() -> SharedState:
    return SharedState.in_memory(AXES)


def test_mailbox_keeps_order_gives_tickets_and_refuses_when_full(shared: SharedState) -> None:
    box = shared.hmi_mailbox
    commands = [
        Command(CommandCode.SET_OVERRIDE, CommandOrigin.HMI, override_percent=42.5, seq=9),
        Command(CommandCode.LOAD_CURVE, CommandOrigin.HMI, program=PROGRAM, seq=10),
        Command(CommandCode.START, CommandOrigin.HMI, seq=11),
    ]
    assert [box.post(c) for c in commands] == [1, 2, 3]
    taken = [box.take() for _ in commands]
    assert [(c.code, c.seq, c.ticket) for c in taken] == [
        (CommandCode.SET_OVERRIDE, 9, 1),
        (CommandCode.LOAD_CURVE, 10, 2),
        (CommandCode.START, 11, 3),
    ]
    assert taken[0].override_percent == 42.5 and taken[2].override_percent is None
    assert taken[1].program == PROGRAM
    assert box.take() is None
    for _ in range(MAILBOX_SLOTS):
        assert box.post(commands[2]) is not None
    assert box.post(commands[2]) is None
    assert box.take().ticket == 4


def test_status_round_trips_faults_records_programs_axes_and_cuts_text(
    shared: SharedState,
) -> None:
    board = shared.status
    assert board.snapshot() is None
    board.set(state=5, phase=2, axis_count=3, feed_mm_s=12.5, path_s_mm=3.0, path_length_mm=9.0)
    cause = Fault(FaultKind.DRIVE_FAULT, "axis Y: EMCY 0x8611 following error", "Y", 0x8611)
    later = tuple(Fault(FaultKind.HEARTBEAT_LOSS, f"later {i}", "Z") for i in range(12))
    board.set_fault(cause, later)
    records = tuple(
        CommandRecord(i, CommandOrigin.HMI, 100 + i, CommandCode.HOLD, CommandResult.DONE)
        for i in range(1, 20)
    )
    board.set_commands(records)
    board.set_programs(ProgramStatus(3, "first", 1, 10.0), ProgramStatus(4, "next ü", 2, 20.0))
    board.set_message("é" * MESSAGE_BYTES)
    board.set_axis(1, b"Y", 2, 1.5, 1.25, -0.25, 0.5, 4, 0x1237, 4, b"axis fault")
    board.publish()
    status = board.snapshot()
    assert status.fault == cause
    assert len(status.later_faults) == 8 and status.later_faults[0].text == "later 0"
    assert [r.ticket for r in status.recent_commands] == list(range(4, 20))
    assert status.last_command.seq == 119
    assert status.program == ProgramStatus(3, "first", 1, 10.0)
    assert status.next_program.name == "next ü"
    # Cut on a character boundary: 256 two-byte characters.
    assert status.message == "é" * (MESSAGE_BYTES // 2)
    axis = status.axes[1]
    assert (axis.name, axis.node_id, axis.commanded_mm, axis.actual_mm) == ("Y", 2, 1.5, 1.25)
    assert (axis.following_error_mm, axis.peak_following_error_mm) == (-0.25, 0.5)
    assert (axis.statusword, axis.boot_phase, axis.fault) == (0x1237, 4, "axis fault")
    assert status.progress_permille == 333


def test_a_reader_that_meets_the_cycle_mid_write_gets_its_last_snapshot(
    shared: SharedState, monkeypatch: pytest.MonkeyPatch
) -> None:
    board = shared.status
    board.set(state=5, feed_mm_s=12.5)
    board.publish()
    first = board.snapshot()
    assert first.feed_mm_s == 12.5
    board.set(feed_mm_s=20.0)
    board.publish()
    # Every try meets a write in progress (a reader preempted while the cycle writes).
    monkeypatch.setattr(SeqlockCell, "read_bytes", lambda cell: None)
    assert board.snapshot() == first


def test_planner_request_round_trips_segments(shared: SharedState) -> None:
    request = PlanRequest(
        seq=3,
        kind=PlanRequestKind.FOLLOW,
        job=2,
        override_percent=80.0,
        segments=(
            SegmentSpec(SegmentKind.LINE, (0.0, 1.0, 2.0), PROGRAM.start_mm),
            SegmentSpec(SegmentKind.PROGRAM, program=PROGRAM),
        ),
        start_segment=1,
        start_s_mm=12.0,
    )
    shared.planner_requests.post(request)
    assert shared.planner_requests.latest() == request


def test_setpoint_ring_room_follows_what_the_cycle_still_needs(shared: SharedState) -> None:
    ring = shared.rings[0]
    ring.begin(job=1, first_row=0)
    assert ring.room() == RING_ROWS
    rows = 1000
    ring.append(
        s_mm=np.arange(rows, dtype=float),
        feed_mm_s=np.ones(rows),
        accel_mm_s2=np.zeros(rows),
        position_mm=np.ones((rows, 3)),
        segment=1,
    )
    assert ring.write_count == rows and ring.room() == RING_ROWS - rows
    ring.hold_from(1, 600)
    assert ring.room() == RING_ROWS - rows + 600
    # Rows wrap around the ring.
    ring.append(
        s_mm=np.arange(rows, 2 * rows + 3500, dtype=float),
        feed_mm_s=np.ones(rows + 3500),
        accel_mm_s2=np.zeros(rows + 3500),
        position_mm=np.zeros((rows + 3500, 2)),
        segment=1,
    )
    last = ring.write_count - 1
    assert ring.s_mm[ring.slot(last)] == last and ring.slot(last) == last % RING_ROWS


def test_log_ring_wraps_and_drops_when_full(shared: SharedState) -> None:
    log = shared.log
    for i in range(3):
        assert log.write(20, "runtime.cycle", f"message {i}")
    assert [(e.level, e.logger, e.message) for e in log.read()] == [
        (20, "runtime.cycle", f"message {i}") for i in range(3)
    ]
    long = "x" * (LOG_BYTES // 16)
    written = 0
    while log.write(30, "runtime.cycle", long):
        written += 1
    assert log.dropped == 1
    entries = log.read()
    assert len(entries) == written and all(e.message == long for e in entries)
    # After reading, the ring takes records again, across its end.
    for _ in range(written):
        assert log.write(30, "runtime.cycle", long)
    assert len(log.read()) == written


def test_attaching_another_layout_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "shared.mem"
    SharedState.create(path, AXES).close()
    with pytest.raises(LayoutMismatch, match="axes 3, expected"):
        SharedState.attach(path, ("X", "Y"))
    path.write_bytes(b"\0" * 100)
    with pytest.raises(LayoutMismatch, match="100 bytes"):
        SharedState.attach(path, AXES)


def _publish_forever(path: str, ready, stop) -> None:
    shared = SharedState.attach(path, AXES)
    board = shared.status
    board.set(axis_count=3)
    value = 0
    ready.set()
    while not stop.is_set():
        value += 1
        # Every numeric field of the period carries the same value: a torn read would mix two.
        board.set(heartbeat=value & 0xFFFF, cycle_count=value, feed_mm_s=float(value))
        board.set(path_s_mm=float(value), path_length_mm=float(value))
        for i in range(3):
            board.set_axis(i, b"A", 1, float(value), float(value), 0.0, 0.0, 4, 0, 4, b"")
        board.publish()


def test_a_reader_in_another_process_never_sees_a_torn_snapshot(tmp_path: Path) -> None:
    path = tmp_path / "shared.mem"
    shared = SharedState.create(path, AXES)
    context = multiprocessing.get_context("spawn")
    ready, stop = context.Event(), context.Event()
    writer = context.Process(target=_publish_forever, args=(str(path), ready, stop))
    writer.start()
    try:
        assert ready.wait(30)
        seen, values = 0, set()
        while seen < 20_000:
            status = shared.status.snapshot()
            if status is None:
                continue
            seen += 1
            value = status.feed_mm_s
            values.add(value)
            assert status.path_s_mm == value and status.path_length_mm == value
            assert all(a.commanded_mm == value and a.actual_mm == value for a in status.axes)
            assert status.heartbeat == int(value) & 0xFFFF
        assert len(values) > 100  # the writer really was writing meanwhile
    finally:
        stop.set()
        writer.join(10)
        shared.close()
