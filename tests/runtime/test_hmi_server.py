"""The HMI server's semantics against a fake machine, mostly with hand-built frames: status
before and after the first snapshot, the status word, commands by sequence counter (every
request its own sequence and result, judged by the machine in queue order, exception 6 only for
a full mailbox), acknowledgements naming the origin, the contiguous holding block and write-time
limits, programs loaded while moving, the staging hold, the program library, access."""

from __future__ import annotations

import math
import multiprocessing
import os
import signal
import socket
import struct
import threading
import time
import zlib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from fake_machine_link import SIM, FakeMachine, hmi_config, serve_fake
from modbus_wire import Wire, WireError, adu, write_pdu

from runtime.commands import CommandCode, CommandOrigin, CommandResult
from runtime.config import ProgramsConfig
from runtime.curves import load_curve_file
from runtime.hmi import HmiError
from runtime.hmi.client import CommandRefused, HmiClient
from runtime.hmi.registers import (
    BLOCKS,
    CORE_END,
    FIELD,
    HOLDING_HEAD_END,
    INPUT_SIZE,
    MAGIC,
    MAP_VERSION,
    STATE_STARTING,
    HmiStatus,
    LibraryState,
    StagingState,
    StatusBit,
    Table,
    decode_status,
    get,
)
from runtime.hmi.server import HmiServer
from runtime.hmi.upload import encode_staging, staging_crc, staging_of
from runtime.status import Fault, FaultKind, MachineState, MotionPhase, WatchdogState

ROOT = Path(__file__).resolve().parents[2]
PAPER_FILE = ROOT / "configs" / "curves" / "paper.yaml"
PAPER = load_curve_file(PAPER_FILE)
S = MachineState
_CODE, _SEQ = FIELD["COMMAND_CODE"].address, FIELD["COMMAND_SEQ"].address


def raw_status(wire: Wire) -> HmiStatus:
    """The whole input image read block by block over the wire, decoded."""
    image = [0] * INPUT_SIZE
    for _title, table, first, end in BLOCKS:
        if table is Table.INPUT:
            image[first:end] = wire.read_input(first, end - first)
    return decode_status(image)


def send(wire: Wire, code: CommandCode, *extra: int) -> int:
    """Write ``code`` with the next sequence value (FC16 from 0); returns that value."""
    seq = (wire.read_holding(_SEQ, 1)[0] + 1) & 0xFFFF
    wire.write(_CODE, [code, seq, *extra])
    return seq


def settled(wire: Wire, seq: int, timeout_s: float = 3.0) -> tuple[int, CommandResult]:
    """(ticket, result) of request ``seq`` once the machine has judged it."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        for request in raw_status(wire).server.requests:
            if request.seq == seq and request.result != CommandResult.PENDING:
                return request.ticket, request.result  # type: ignore[return-value]
        time.sleep(0.01)
    raise AssertionError(f"request seq {seq} not settled in {timeout_s} s")


def wait_state(wire: Wire, state: MachineState, timeout_s: float = 5.0) -> HmiStatus:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        status = raw_status(wire)
        if status.snapshot is not None and status.snapshot.state is state:
            return status
        time.sleep(0.01)
    raise AssertionError(f"machine not {state.name} in {timeout_s} s")


# -- status ---------------------------------------------------------------------------------


def test_before_the_first_snapshot_the_status_says_starting(tmp_path: Path) -> None:
    machine = FakeMachine(tmp_path)
    with HmiServer(machine, hmi_config()) as hmi, Wire(hmi.port) as wire:
        assert wire.read_input(FIELD["MACHINE_STATE"].address, 1) == [STATE_STARTING]
        status = raw_status(wire)
        assert status.snapshot is None
        assert not status.status_word & StatusBit.STATUS_VALID
        first = FIELD["AXIS_COMMANDED"].address
        image = [0] * first + wire.read_input(first, FIELD["AXIS_NAME"].end - first)
        names = [get(image, FIELD["AXIS_NAME"], i) for i in range(3)]
        assert names == ["X", "Y", "Z"]
        nodes = [get(image, FIELD["AXIS_NODE_ID"], i) for i in range(3)]
        assert nodes == [a.node_id for a in SIM.axes]
        assert all(math.isnan(get(image, FIELD["AXIS_ACTUAL"], i)) for i in range(3))
        machine.step()
        status = raw_status(wire)
        assert status.snapshot is not None and status.snapshot.state is S.DISABLED
        assert status.status_word & StatusBit.STATUS_VALID


def test_status_word_statusword_phase_and_programs(fake: FakeMachine, wire: Wire) -> None:
    fake.publish(statusword=0x1237)
    status = raw_status(wire)
    assert [a.statusword for a in status.snapshot.axes] == [0x1237] * 3
    assert status.status_word == StatusBit.STATUS_VALID
    send(wire, CommandCode.SET_OVERRIDE, 100)  # 10 %: slow enough to watch
    send(wire, CommandCode.ENABLE)
    wait_state(wire, S.STANDBY)
    staging = staging_of(PAPER)
    _stage(wire, staging)
    seq = send(wire, CommandCode.LOAD_CURVE)
    assert settled(wire, seq)[1] is CommandResult.DONE
    send(wire, CommandCode.START)
    status = wait_state(wire, S.MOVING)
    snapshot = status.snapshot
    assert snapshot.phase is MotionPhase.APPROACH
    assert status.status_word & StatusBit.APPROACH and status.status_word & StatusBit.MOVING
    assert status.status_word & StatusBit.ENABLED and status.status_word & StatusBit.PROGRAM_LOADED
    # During the approach the path registers measure the approach line, not zeros.
    end = time.monotonic() + 2.0
    while snapshot.path_s_mm == 0.0 and time.monotonic() < end:
        snapshot = raw_status(wire).snapshot
    assert snapshot.phase is MotionPhase.APPROACH
    assert snapshot.path_length_mm == fake.approach_mm and snapshot.path_s_mm > 0
    assert snapshot.progress_permille > 0
    program = snapshot.program
    assert program.crc32 == staging.crc32 and program.name == f"upload {staging.crc32:08X}"
    assert program.length_mm == pytest.approx(173.9, abs=0.5)


def test_message_is_whole_and_ascii(fake: FakeMachine, wire: Wire) -> None:
    text = (
        "error stop: axis Y: following error +1.2345 mm beyond ±1 mm for 6 cycles; "
        "drive 2 reported EMCY 0x8611 (following error) at 12.5 µs after SYNC; later faults: "
        "axis Z stale feedback (no TPDO for 25 cycles), café"
    )
    fake.fault(FaultKind.FOLLOWING_ERROR, text.removeprefix("error stop: "), axis="Y")
    status = raw_status(wire)
    expected = text.replace("±", "+/-").replace("µ", "u").replace("é", "e")
    assert len(text) > 64 and status.snapshot.message == expected
    assert status.snapshot.fault.kind is FaultKind.FOLLOWING_ERROR
    assert status.snapshot.fault.axis == "Y"
    assert status.status_word & StatusBit.FAULT


def test_cycle_count_wraps(fake: FakeMachine, wire: Wire) -> None:
    with fake.paused():
        fake._state.cycles = 2**32 + 5
        fake._snapshot = fake._state.snapshot(fake)
        regs = wire.read_input(FIELD["CYCLE_COUNT"].address, 2)
    assert regs == [0, 5]


def test_a_read_never_mixes_two_snapshots(tmp_path: Path) -> None:
    machine = FakeMachine(tmp_path)
    machine.step()
    stop = threading.Event()

    def publisher() -> None:
        n = 0
        while not stop.is_set():
            n += 1
            machine.publish(cycles=n, path_s_mm=float(n))

    with HmiServer(machine, hmi_config()) as hmi, Wire(hmi.port) as wire:
        thread = threading.Thread(target=publisher)
        thread.start()
        try:
            heartbeat, position = FIELD["HEARTBEAT"].address, FIELD["PATH_POSITION"].address
            for _ in range(300):
                regs = wire.read_input(heartbeat, position + 2 - heartbeat)
                path_s = struct.unpack(">f", struct.pack(">2H", *regs[-2:]))[0]
                assert regs[0] == int(path_s) & 0xFFFF  # both from one snapshot
        finally:
            stop.set()
            thread.join()


# -- commands -------------------------------------------------------------------------------


def test_a_refused_command_is_acknowledged_with_its_result(fake: FakeMachine, wire: Wire) -> None:
    seq = send(wire, CommandCode.START)  # no exception: the write is applied
    assert wire.read_holding(_CODE, 2) == [CommandCode.START, seq]
    ticket, result = settled(wire, seq)
    assert result is CommandResult.REJECTED_STATE and ticket > 0
    last = raw_status(wire).snapshot.last_command
    assert (last.ticket, last.seq, last.origin, last.result) == (
        ticket,
        seq,
        CommandOrigin.HMI,
        CommandResult.REJECTED_STATE,
    )
    assert fake.posted[-1].origin is CommandOrigin.HMI


def test_commands_are_judged_in_queue_order_against_the_state_they_run_in(
    fake: FakeMachine, wire: Wire
) -> None:
    fake.publish(program=_program(fake), override_percent=10.0)
    seq = send(wire, CommandCode.ENABLE)
    assert settled(wire, seq)[1] is CommandResult.DONE
    with fake.paused():  # START and HOLD are judged in the same period, in that order
        start = send(wire, CommandCode.START)
        hold = send(wire, CommandCode.HOLD)
    assert settled(wire, start)[1] is CommandResult.DONE
    assert settled(wire, hold)[1] is CommandResult.DONE
    assert raw_status(wire).snapshot.state is S.HOLDING


def test_every_request_has_its_own_sequence_and_result(wire: Wire) -> None:
    staging = staging_of(PAPER)
    _stage(wire, staging, crc32=staging.crc32 ^ 1)
    seqs = [send(wire, CommandCode.LOAD_CURVE) for _ in range(3)]
    assert len(set(seqs)) == 3
    requests = raw_status(wire).server.requests
    assert [(r.seq, r.ticket, r.result) for r in requests[:3]] == [
        (seq, 0, CommandResult.CURVE_CRC_MISMATCH) for seq in reversed(seqs)
    ]
    status = raw_status(wire)
    assert status.server.upload.seq == seqs[-1]
    assert "CURVE_CRC32" in status.server.request_message


def test_acknowledgements_name_the_origin_after_a_watchdog_hold(
    fake: FakeMachine, wire: Wire
) -> None:
    fake.publish(program=_program(fake), override_percent=10.0)
    send(wire, CommandCode.ENABLE)
    wait_state(wire, S.STANDBY)
    start = send(wire, CommandCode.START)
    start_ticket, _ = settled(wire, start)
    fake.watchdog_trip()
    status = raw_status(wire)
    last, before = status.snapshot.recent_commands[-1], status.snapshot.recent_commands[-2]
    assert (last.origin, last.code, last.seq, last.result) == (
        CommandOrigin.WATCHDOG,
        CommandCode.HOLD,
        0,
        CommandResult.DONE,
    )
    assert (before.ticket, before.origin, before.code) == (
        start_ticket,
        CommandOrigin.HMI,
        CommandCode.START,
    )
    assert wire.read_input(FIELD["COMMAND_SEQ_ACK"].address, 4) == [
        0,
        CommandCode.HOLD,
        CommandOrigin.WATCHDOG,
        CommandResult.DONE,
    ]
    assert status.snapshot.watchdog is WatchdogState.TRIPPED
    assert status.status_word & StatusBit.WATCHDOG_TRIPPED
    assert status.snapshot.message.startswith("hold by watchdog")


def test_a_full_mailbox_answers_6_and_applies_nothing(fake: FakeMachine, wire: Wire) -> None:
    fake.mailbox_size = 0
    before = wire.read_holding(0, HOLDING_HEAD_END)
    assert wire.ask(write_pdu(_CODE, [CommandCode.ENABLE, 9])) == b"\x90\x06"
    assert wire.read_holding(0, HOLDING_HEAD_END) == before
    assert fake.posted == [] and raw_status(wire).server.requests == ()
    fake.mailbox_size = 16  # the same write again is safe and runs once
    wire.write(_CODE, [CommandCode.ENABLE, 9])
    wire.write(_CODE, [CommandCode.ENABLE, 9])
    assert settled(wire, 9)[1] is CommandResult.DONE
    assert len(fake.posted) == 1


def test_same_sequence_value_runs_nothing_and_fc6_seq_runs_the_code(
    fake: FakeMachine, wire: Wire
) -> None:
    wire.write(_CODE, [CommandCode.SET_OVERRIDE, 4, 1234])
    wire.write(_CODE, [CommandCode.SET_OVERRIDE, 4, 1234])
    assert len(fake.posted) == 1 and fake.posted[0].override_percent == 123.4
    wire.write(FIELD["OVERRIDE_SETPOINT"].address, [500])
    assert len(fake.posted) == 1
    assert wire.ask(struct.pack(">BHH", 6, _SEQ, 5)) == struct.pack(">BHH", 6, _SEQ, 5)
    assert settled(wire, 5)[1] is CommandResult.DONE
    assert raw_status(wire).snapshot.override_percent == 50.0


def test_heartbeat_changes_and_accepted_requests_are_activity(
    fake: FakeMachine, wire: Wire
) -> None:
    heartbeat = FIELD["HMI_HEARTBEAT"].address
    wire.write(heartbeat, [1])
    wire.write(heartbeat, [1])  # unchanged: not a sign of life
    assert fake.activity == 1
    send(wire, CommandCode.ENABLE)
    assert fake.activity == 2


# -- holding registers ----------------------------------------------------------------------


def test_holding_registers_are_contiguous_up_to_the_staging_header(wire: Wire) -> None:
    block = wire.read_holding(0, HOLDING_HEAD_END)
    assert block == [0] * HOLDING_HEAD_END
    wire.write(0, block)  # a merged block write carrying the reserved registers unchanged
    with pytest.raises(WireError) as refused:
        wire.write(7, [1])  # reserved: only 0
    assert refused.value.code == 3
    wire.write(FIELD["CURVE_DEGREE"].address, [3, 3, 7, 11])
    assert wire.read_holding(0, HOLDING_HEAD_END)[16:20] == [3, 3, 7, 11]


@pytest.mark.parametrize(
    ("name", "value"),
    [("CURVE_POINTS", 2001), ("CURVE_DEGREE", 8), ("CURVE_DIMENSION", 4), ("CURVE_KNOTS", 2009)],
)
def test_header_limits_are_checked_at_write_time(wire: Wire, name: str, value: int) -> None:
    with pytest.raises(WireError) as refused:
        wire.write(FIELD[name].address, [value])
    assert refused.value.code == 3
    assert wire.read_holding(FIELD[name].address, 1) == [0]


# -- programs -------------------------------------------------------------------------------


def _stage(wire: Wire, staging: object, crc32: int | None = None) -> None:
    crc = staging.crc32 if crc32 is None else crc32  # type: ignore[attr-defined]
    wire.write(FIELD["CURVE_DEGREE"].address, [*staging.header, crc >> 16, crc & 0xFFFF])  # type: ignore[attr-defined]
    for base, registers in (
        (FIELD["POINT_X"].address, staging.points),  # type: ignore[attr-defined]
        (FIELD["KNOT"].address, staging.knots),  # type: ignore[attr-defined]
    ):
        for offset in range(0, len(registers), 120):
            wire.write(base + offset, registers[offset : offset + 120])


def _program(fake: FakeMachine):  # type: ignore[no-untyped-def]
    return fake.programs.add(PAPER, fake.config, name="paper", crc32=1)


def test_upload_round_trip(fake: FakeMachine, client: HmiClient) -> None:
    outcome = client.load_curve(PAPER)
    assert outcome.result is CommandResult.DONE and outcome.ticket > 0
    program = fake.posted[-1].program
    stored = np.load(program.source)
    np.testing.assert_array_equal(stored["control_points"], PAPER.control_points.astype(np.float32))
    np.testing.assert_array_equal(stored["knots"], PAPER.knots.astype(np.float32))
    status = client.status()
    assert status.snapshot.program.crc32 == staging_of(PAPER).crc32
    assert status.server.upload.result is CommandResult.DONE


def test_a_program_committed_while_moving_becomes_the_next_one(
    fake: FakeMachine, client: HmiClient
) -> None:
    client.command(CommandCode.SET_OVERRIDE, override_percent=50.0)
    client.load_curve(PAPER)
    first = client.status().snapshot.program
    client.command(CommandCode.ENABLE)
    client.command(CommandCode.START)
    line = encode_staging(1, [[10.0, 10.0, 5.0], [20.0, 15.0, 5.0]], [0, 0, 1, 1])
    client.load_curve(line)
    status = client.status()
    assert status.snapshot.state is S.MOVING
    assert status.snapshot.program == first
    assert status.snapshot.next_program.crc32 == line.crc32
    assert status.status_word & StatusBit.NEXT_PROGRAM
    # The next program starts when the current one ends.
    status = client.wait_for(
        lambda s: s.snapshot.program.crc32 == line.crc32, 10.0, "the next program to start"
    )
    assert status.snapshot.next_program is None and status.snapshot.state is S.MOVING
    client.wait_for(lambda s: s.snapshot.state is S.STANDBY, 10.0, "the end")
    client.load_curve(line)
    client.command(CommandCode.START)
    client.load_curve(PAPER)
    client.command(CommandCode.CLEAR_NEXT)
    assert client.status().snapshot.next_program is None


def _bad(change: str) -> object:
    degree, points, knots, weights = (
        3,
        PAPER.control_points.copy(),
        PAPER.knots.copy(),
        PAPER.weights.copy(),
    )
    if change == "decreasing knots":
        knots[5] = 0.3
    elif change == "wrong knot count":
        knots = knots[:-1]
    elif change == "weight 0":
        weights[2] = 0.0
    elif change == "NaN":
        points[3, 1] = math.nan
    elif change == "degree too high":
        degree, points, weights = 7, points[:5], weights[:5]
        knots = np.r_[np.zeros(8), np.ones(4)]
    elif change == "outside travel":
        points[-1, 0] = 350.0
    elif change == "not clamped":
        knots[0] = -0.1
    elif change == "zero length":
        points[:] = points[0]
    elif change == "dimension 1 (bad header)":
        staging = encode_staging(degree, points, knots, weights)
        header = (3, 1, *staging.header[2:])
        return replace(
            staging, header=header, crc32=staging_crc(header, staging.points, staging.knots)
        )
    return encode_staging(degree, points, knots, weights)


BAD_UPLOADS = [
    ("decreasing knots", CommandResult.CURVE_KNOTS_DECREASING),
    ("wrong knot count", CommandResult.CURVE_KNOT_COUNT),
    ("weight 0", CommandResult.CURVE_BAD_WEIGHT),
    ("NaN", CommandResult.CURVE_NOT_FINITE),
    ("degree too high", CommandResult.CURVE_DEGREE_TOO_HIGH),
    ("outside travel", CommandResult.CURVE_OUTSIDE_TRAVEL),
    ("not clamped", CommandResult.CURVE_KNOTS_NOT_CLAMPED),
    ("zero length", CommandResult.CURVE_ZERO_LENGTH),
    ("dimension 1 (bad header)", CommandResult.CURVE_BAD_HEADER),
]


@pytest.mark.parametrize(("change", "expected"), BAD_UPLOADS, ids=[b[0] for b in BAD_UPLOADS])
def test_a_bad_upload_gets_its_code_and_keeps_the_loaded_program(
    fake: FakeMachine, client: HmiClient, change: str, expected: CommandResult
) -> None:
    client.load_curve(PAPER)
    loaded = client.status().snapshot.program
    with pytest.raises(CommandRefused) as refused:
        client.load_curve(_bad(change))  # type: ignore[arg-type]
    assert refused.value.result is expected
    assert refused.value.outcome.ticket == 0 and refused.value.outcome.message
    status = client.status()
    assert status.server.upload.result is expected
    assert status.snapshot.program == loaded


# -- staging hold ---------------------------------------------------------------------------


def test_the_staging_area_has_one_holder(fake: FakeMachine, hmi: HmiServer) -> None:
    staging = staging_of(PAPER)
    with Wire(hmi.port) as a, Wire(hmi.port) as b:
        _stage(a, staging)
        status = raw_status(b)
        view = status.server.staging
        assert view.state is StagingState.HELD and status.status_word & StatusBit.STAGING_HELD
        assert view.owner_ip == 0x7F000001 and view.owner_port == a.sock.getsockname()[1]
        assert 0 < view.hold_left_ms <= 30_000
        for address, values in ((FIELD["POINT_X"].address, [0, 0]), (16, [1])):
            with pytest.raises(WireError) as refused:
                b.write(address, values)
            assert refused.value.code == 2
        with pytest.raises(WireError):
            b.write(FIELD["STAGING_CONTROL"].address, [1])
        seq = send(b, CommandCode.LOAD_CURVE)  # B's commit: refused, nothing loaded
        assert settled(b, seq) == (0, CommandResult.STAGING_LOCKED)
        assert "held by 127.0.0.1" in raw_status(b).server.request_message
        seq = send(a, CommandCode.LOAD_CURVE)  # the holder's commit loads and frees it
        assert settled(a, seq)[1] is CommandResult.DONE
        assert raw_status(b).server.staging.state is StagingState.FREE
        _stage(b, staging)  # now B may take it ...
        b.write(FIELD["STAGING_CONTROL"].address, [2])  # ... and abort: header cleared, free
        assert b.read_holding(16, 6) == [0] * 6
        assert raw_status(a).server.staging.state is StagingState.FREE
        a.write(FIELD["STAGING_CONTROL"].address, [1])  # explicit take
        assert raw_status(b).server.staging.owner_port == a.sock.getsockname()[1]
    with Wire(hmi.port) as c:  # A's connection closed: free again
        assert raw_status(c).server.staging.state is StagingState.FREE


def test_a_staging_hold_lapses_after_its_timeout(fake: FakeMachine) -> None:
    hmi = HmiServer(fake, hmi_config(staging_timeout_ms=300))
    with hmi, Wire(hmi.port) as a, Wire(hmi.port) as b:
        a.write(16, [1])
        with pytest.raises(WireError):
            b.write(16, [2])
        time.sleep(0.4)
        b.write(16, [2])
        assert raw_status(a).server.staging.owner_port == b.sock.getsockname()[1]


# -- program library ------------------------------------------------------------------------


@pytest.fixture
def library(tmp_path: Path) -> Path:
    directory = tmp_path / "library"
    directory.mkdir()
    (directory / "a-paper.yaml").write_bytes(PAPER_FILE.read_bytes())
    (directory / "b-bad.yaml").write_text("degree: 3\ncontrol_points: [[0, 0]]\n")
    (directory / "notes.txt").write_text("not a program")
    return directory


def test_the_program_library(tmp_path: Path, library: Path) -> None:
    config = replace(SIM, programs=ProgramsConfig(library_dir=library))
    machine = FakeMachine(tmp_path / "store", config=config).start()
    try:
        with HmiServer(machine, hmi_config()) as hmi, HmiClient(port=hmi.port) as client:
            assert client.status().server.library_count == 2
            entry = client.library_entry(1)
            assert (entry.state, entry.name, entry.points) == (
                LibraryState.VALID,
                "a-paper.yaml",
                7,
            )
            assert entry.crc32 == zlib.crc32(PAPER_FILE.read_bytes())
            assert entry.length_mm == pytest.approx(173.9, abs=0.5)
            bad = client.library_entry(2)
            assert bad.state is LibraryState.INVALID and bad.result is CommandResult.CURVE_INVALID
            assert client.library_entry(3).state is LibraryState.NOT_FOUND
            outcome = client.load_program(1)
            assert outcome.result is CommandResult.DONE
            program = client.status().snapshot.program
            assert (program.name, program.crc32) == ("a-paper.yaml", entry.crc32)
            with pytest.raises(CommandRefused) as refused:
                client.load_program(3)
            assert refused.value.result is CommandResult.NO_SUCH_PROGRAM
            with pytest.raises(CommandRefused) as refused:
                client.load_program(2)
            assert refused.value.result is CommandResult.CURVE_INVALID
            (library / "0-first.yaml").write_bytes(PAPER_FILE.read_bytes())
            assert client.library_count() == 3
            assert client.library_entry(2).name == "a-paper.yaml"
    finally:
        machine.close()


def test_no_library_configured(client: HmiClient) -> None:
    assert client.library_count() == 0
    with pytest.raises(CommandRefused) as refused:
        client.load_program(1)
    assert refused.value.result is CommandResult.NO_SUCH_PROGRAM
    assert "no library configured" in refused.value.outcome.message


# -- access ---------------------------------------------------------------------------------


def test_refuses_peers_outside_allowed_networks(fake: FakeMachine) -> None:
    with HmiServer(fake, hmi_config(allowed_networks=("10.0.0.0/8",))) as hmi:
        client = HmiClient(port=hmi.port, timeout_s=0.5)
        with pytest.raises(HmiError):
            client.connect()
        client.close()


def test_read_only_refuses_every_write_with_2(fake: FakeMachine) -> None:
    with HmiServer(fake, hmi_config(read_only=True)) as hmi, Wire(hmi.port) as wire:
        assert wire.ask(write_pdu(0, [CommandCode.ENABLE, 1])) == b"\x90\x02"
        assert wire.ask(struct.pack(">BHH", 6, 3, 1)) == b"\x86\x02"
        assert raw_status(wire).snapshot.state is S.DISABLED
        assert fake.posted == []


def test_start_refuses_a_busy_port(hmi: HmiServer, fake: FakeMachine) -> None:
    with pytest.raises(HmiError, match="cannot listen"):
        HmiServer(fake, hmi_config(port=hmi.port)).start()


def test_a_fault_shows_kind_axis_and_later_faults(fake: FakeMachine, wire: Wire) -> None:
    fake.fault(FaultKind.DRIVE_FAULT, "node 2: EMCY 0x2310", axis="Y")
    fake.fault(FaultKind.STALE_FEEDBACK, "node 3: no TPDO")
    status = raw_status(wire)
    assert status.snapshot.fault == Fault(
        FaultKind.DRIVE_FAULT, "a drive reported a fault (EMCY or statusword fault bit)", "Y"
    )
    assert status.later_fault_count == 1


def test_serve_hmi_runs_in_its_process_until_sigterm(tmp_path: Path) -> None:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    process = multiprocessing.get_context("spawn").Process(
        target=serve_fake, args=(str(tmp_path), port)
    )
    process.start()
    try:
        end = time.monotonic() + 30.0
        while True:
            try:
                wire = Wire(port)
                break
            except OSError:
                assert time.monotonic() < end and process.is_alive(), "serve_hmi did not listen"
                time.sleep(0.05)
        with wire:
            assert wire.read_input(0, 2) == [MAGIC, MAP_VERSION]
            os.kill(process.pid, signal.SIGTERM)
            assert wire.closed_by_server(timeout_s=10.0)
        process.join(10.0)
        assert process.exitcode == 0
    finally:
        if process.is_alive():
            process.kill()


def test_requests_after_a_commit_wait_for_its_answer(fake: FakeMachine, wire: Wire) -> None:
    _stage(wire, staging_of(PAPER))
    commit = adu(write_pdu(_CODE, [CommandCode.LOAD_CURVE, 40]), tid=41)
    read = adu(struct.pack(">BHH", 3, _SEQ, 1), tid=42)
    wire.send(commit + read)
    assert wire.response() == (41, 1, struct.pack(">BHH", 16, _CODE, 2))
    assert wire.response() == (42, 1, bytes((3, 2)) + struct.pack(">H", 40))
    assert settled(wire, 40)[1] is CommandResult.DONE


def test_the_core_status_is_one_request(fake: FakeMachine, client: HmiClient) -> None:
    fake.publish(statusword=0x0637)
    core = client.core_status()
    assert CORE_END <= 125
    assert core.snapshot.state is S.DISABLED and core.status_word & StatusBit.STATUS_VALID
    assert [(a.name, a.node_id, a.statusword) for a in core.snapshot.axes] == [
        ("X", 1, 0x0637),
        ("Y", 2, 0x0637),
        ("Z", 3, 0x0637),
    ]
    assert core.snapshot.stats.cycles > 0
