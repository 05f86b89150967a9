"""The HMI Modbus server against a fake machine link, in process on a free port.

Covers the identity block, status encoding, commands once per sequence value, the exception
codes 2/3/6/11, the curve upload with every rejection code, unit ids 0/255, allowed networks,
read-only mode, the watchdog and the ``softmotion hmi`` command line.
"""

from __future__ import annotations

import argparse
import io
import math
import socket
import struct
import threading
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient

from planner.nurbs import NurbsCurve
from runtime.commands import Command, CommandCode, CommandResult, check_allowed
from runtime.config import ModbusConfig, WatchdogConfig, load_config
from runtime.curves import check_travel, load_curve_file
from runtime.hmi import HmiError, cli
from runtime.hmi.client import CommandRefused, HmiClient, ModbusReplyError
from runtime.hmi.registers import FIELD, INPUT_SIZE, MAX_KNOTS, MAX_POINTS, WatchdogState
from runtime.hmi.server import HmiServer
from runtime.hmi.upload import encode_staging, staging_crc, staging_of
from runtime.status import (
    AxisStatus,
    CycleStatistics,
    Fault,
    FaultKind,
    MachineState,
    StatusSnapshot,
)

ROOT = Path(__file__).resolve().parents[2]
SIM = load_config(ROOT / "configs" / "sim.yaml")
PAPER = load_curve_file(ROOT / "configs" / "curves" / "paper.yaml")
S = MachineState
_NEXT_STATE = {
    CommandCode.ENABLE: S.STANDBY,
    CommandCode.DISABLE: S.DISABLED,
    CommandCode.START: S.MOVING,
    CommandCode.HOLD: S.HOLDING,
    CommandCode.RESUME: S.MOVING,
    CommandCode.STOP: S.STANDBY,
    CommandCode.QUICK_STOP: S.STANDBY,
    CommandCode.RESET: S.STANDBY,
}


class FakeLink:
    """A machine that applies each accepted command at once and publishes a new snapshot."""

    axis_names = tuple(a.name for a in SIM.axes)

    def __init__(self) -> None:
        self._snapshot = StatusSnapshot(
            axes=tuple(AxisStatus(a.name, a.node_id, 0.0, 0.0, 1, 0.0) for a in SIM.axes)
        )
        self.applied: list[Command] = []
        self.loaded: object = None
        self._lock = threading.Lock()

    def snapshot(self) -> StatusSnapshot:
        return self._snapshot

    def publish(self, **changes: object) -> None:
        self._snapshot = replace(self._snapshot, **changes)

    def submit(self, command: Command) -> CommandResult:
        with self._lock:
            s = self._snapshot
            if check_allowed(s.state, command.code) is not None:
                return CommandResult.REJECTED_STATE
            if command.code is CommandCode.START and self.loaded is None:
                return CommandResult.NO_CURVE
            self.applied.append(command)
            changes: dict[str, object] = {
                "last_command_seq": command.seq if command.seq is not None else s.last_command_seq,
                "last_command_result": CommandResult.DONE,
                "message": f"{command.code.name.lower()} by {command.origin}",
            }
            if command.code in _NEXT_STATE:
                changes["state"] = _NEXT_STATE[command.code]
            elif command.code is CommandCode.SET_OVERRIDE:
                changes["override_percent"] = command.override_percent
            elif command.code is CommandCode.LOAD_CURVE:
                self.loaded = command.curve
                changes["curve_id"] = s.curve_id + 1
                changes["curve_crc"] = command.curve[1]
            self._snapshot = replace(s, **changes)
            return CommandResult.PENDING

    def prepare_curve(self, curve: NurbsCurve, crc32: int) -> object:
        check_travel(curve, SIM.axes)
        return (curve, crc32)


def _config(**changes: object) -> ModbusConfig:
    return replace(ModbusConfig(port=0), **changes)


@pytest.fixture
def link() -> FakeLink:
    return FakeLink()


@pytest.fixture
def server(link: FakeLink) -> Iterator[HmiServer]:
    with HmiServer(_config(), link) as hmi:
        yield hmi


@pytest.fixture
def client(server: HmiServer) -> Iterator[HmiClient]:
    with HmiClient(port=server.port, timeout_s=2.0) as hmi:
        yield hmi


@pytest.fixture
def raw(server: HmiServer) -> Iterator[ModbusTcpClient]:
    modbus = ModbusTcpClient("127.0.0.1", port=server.port, timeout=2, retries=0)
    assert modbus.connect()
    yield modbus
    modbus.close()


def _exception(reply: object) -> int | None:
    return reply.exception_code if reply.isError() else None  # type: ignore[attr-defined]


def test_identity_block_and_test_patterns(client: HmiClient, raw: ModbusTcpClient) -> None:
    regs = raw.read_input_registers(0, count=16, device_id=1).registers
    assert regs[0] == 0x534D
    assert regs[2:4] == [0x47F1, 0x2000]
    assert regs[4:6] == [0x1234, 0x5678]
    assert regs[9] == 3
    identity = client.identity
    assert identity.test_float == 123456.0
    assert identity.axis_count == 3 and not identity.read_only


def test_status_encodes_the_snapshot(link: FakeLink, client: HmiClient) -> None:
    link.publish(
        state=S.ERROR_STOP,
        fault=Fault(FaultKind.FOLLOWING_ERROR, "x", axis="Y", emcy_code=0x8611),
        axes=(
            AxisStatus("X", 1, 12.5, 12.25, 4, 0.25),
            AxisStatus("Y", 2, -3.0, -2.5, 7, -0.5),
            AxisStatus("Z", 3, 99.0, 98.0, 4, 1.0),
        ),
        feed_mm_s=87.5,
        path_s_mm=43.5,
        path_length_mm=174.0,
        override_percent=120.5,
        stats=CycleStatistics(
            cycles=70000,
            lateness_last_us=12.4,
            lateness_p99_us=801.0,
            lateness_max_us=3100.6,
            missed_periods=2,
        ),
        curve_id=4,
        curve_crc=0xDEADBEEF,
        heartbeat=65537,
        message="error stop: following error on Y",
    )
    s = client.status().snapshot
    assert s.state is S.ERROR_STOP
    assert s.fault == Fault(
        FaultKind.FOLLOWING_ERROR,
        "an axis's following error exceeded its window",
        axis="Y",
        emcy_code=0x8611,
    )
    assert [(a.name, a.node_id, a.commanded_mm, a.actual_mm, a.drive_state) for a in s.axes] == [
        ("X", 1, 12.5, 12.25, 4),
        ("Y", 2, -3.0, -2.5, 7),
        ("Z", 3, 99.0, 98.0, 4),
    ]
    assert s.axes[1].following_error_mm == -0.5
    assert (s.feed_mm_s, s.path_s_mm, s.path_length_mm) == (87.5, 43.5, 174.0)
    assert s.progress_permille == 250
    assert s.override_percent == 120.5
    assert s.stats.cycles == 70000 and s.stats.missed_periods == 2
    assert (s.stats.lateness_last_us, s.stats.lateness_p99_us, s.stats.lateness_max_us) == (
        12.0,
        801.0,
        3101.0,
    )
    assert (s.curve_id, s.curve_crc, s.heartbeat) == (4, 0xDEADBEEF, 1)
    assert s.message == "error stop: following error on Y"


def test_a_read_never_mixes_two_snapshots(link: FakeLink, client: HmiClient) -> None:
    stop = threading.Event()

    def publisher() -> None:
        n = 0
        while not stop.is_set():
            n += 1
            link.publish(heartbeat=n, path_s_mm=float(n), stats=CycleStatistics(cycles=n))

    thread = threading.Thread(target=publisher)
    thread.start()
    try:
        for _ in range(200):
            s = client.status().snapshot
            assert s.heartbeat == s.stats.cycles & 0xFFFF == int(s.path_s_mm) & 0xFFFF
    finally:
        stop.set()
        thread.join()


def test_a_command_runs_once_per_sequence_value(
    link: FakeLink, client: HmiClient, raw: ModbusTcpClient
) -> None:
    assert _exception(raw.write_registers(0, [CommandCode.ENABLE, 7], device_id=1)) is None
    assert [c.code for c in link.applied] == [CommandCode.ENABLE]
    assert link.applied[0].seq == 7 and link.applied[0].origin == "hmi"
    # The same sequence value again: nothing runs (and the write is harmless).
    assert _exception(raw.write_registers(0, [CommandCode.ENABLE, 7], device_id=1)) is None
    assert len(link.applied) == 1
    # A new sequence value alone (FC6) runs the code already in COMMAND_CODE.
    raw.write_register(0, CommandCode.SET_OVERRIDE, device_id=1)
    raw.write_register(2, 1234, device_id=1)
    assert len(link.applied) == 1
    assert _exception(raw.write_register(1, 8, device_id=1)) is None
    assert link.applied[-1] == Command(
        CommandCode.SET_OVERRIDE, override_percent=123.4, seq=8, origin="hmi"
    )
    status = client.status()
    assert status.snapshot.last_command_seq == 8
    assert status.snapshot.override_percent == 123.4
    assert (status.server.request_seq, status.server.request_result) == (8, CommandResult.DONE)


def test_client_command_waits_for_the_machine(link: FakeLink, client: HmiClient) -> None:
    outcome = client.command(CommandCode.ENABLE)
    assert outcome.result is CommandResult.DONE
    assert client.status().snapshot.state is S.STANDBY


def test_wrong_state_answers_6_and_changes_nothing(
    link: FakeLink, client: HmiClient, raw: ModbusTcpClient
) -> None:
    before = raw.read_holding_registers(0, count=4, device_id=1).registers
    reply = raw.write_registers(0, [CommandCode.START, before[1] + 1], device_id=1)
    assert _exception(reply) == 6
    assert raw.read_holding_registers(0, count=4, device_id=1).registers == before
    assert link.applied == []
    with pytest.raises(CommandRefused) as refused:
        client.command(CommandCode.HOLD)
    assert refused.value.result is CommandResult.REJECTED_STATE
    assert refused.value.exception_code == 6
    client.command(CommandCode.ENABLE)
    with pytest.raises(CommandRefused) as refused:
        client.command(CommandCode.START)
    assert (refused.value.result, refused.value.exception_code) == (CommandResult.NO_CURVE, 6)
    assert client.status().snapshot.state is S.STANDBY


@pytest.mark.parametrize(
    ("address", "values", "code"),
    [
        (2, [1501], 3),  # override above 150.0 %
        (0, [11, 1], 3),  # unknown command code
        (0, [0, 1], 3),  # sequence change with no command
        (1001, [0], 3),  # low word of a float alone
        (1000, [0, 0, 0], 3),  # ends inside a float
        (4, [1], 2),  # reserved
        (22, [1, 2], 2),  # between header and data
        (21016, [0], 2),  # beyond the staging area
    ],
)
def test_malformed_and_unmapped_writes(
    link: FakeLink, raw: ModbusTcpClient, address: int, values: list[int], code: int
) -> None:
    before = raw.read_holding_registers(0, count=4, device_id=1).registers
    assert _exception(raw.write_registers(address, values, device_id=1)) == code
    assert raw.read_holding_registers(0, count=4, device_id=1).registers == before
    assert link.applied == []


def test_other_exception_2_cases(raw: ModbusTcpClient) -> None:
    assert _exception(raw.read_input_registers(INPUT_SIZE, count=1, device_id=1)) == 2
    assert _exception(raw.read_input_registers(INPUT_SIZE - 1, count=2, device_id=1)) == 2
    assert _exception(raw.read_holding_registers(4, count=1, device_id=1)) == 2
    assert _exception(raw.read_coils(0, count=1, device_id=1)) == 2
    assert _exception(raw.write_coil(0, True, device_id=1)) == 2


def test_more_than_123_registers_in_one_write_answers_3(server: HmiServer) -> None:
    # The client library refuses to build such a request; send the frame by hand.
    count = 124
    pdu = struct.pack(">BHHB", 16, 1000, count, 2 * count) + bytes(2 * count)
    frame = struct.pack(">HHHB", 1, 0, len(pdu) + 1, 1) + pdu
    with socket.create_connection(("127.0.0.1", server.port), timeout=2) as sock:
        sock.sendall(frame)
        reply = sock.recv(64)
    assert reply[7] == 0x90 and reply[8] == 3


def test_upload_round_trip(link: FakeLink, client: HmiClient) -> None:
    outcome = client.load_curve(PAPER)
    assert outcome.result is CommandResult.DONE
    curve, crc = link.loaded
    assert crc == staging_of(PAPER).crc32
    np.testing.assert_array_equal(curve.control_points, PAPER.control_points.astype(np.float32))
    np.testing.assert_array_equal(curve.knots, PAPER.knots.astype(np.float32))
    np.testing.assert_array_equal(curve.weights, PAPER.weights.astype(np.float32))
    status = client.status()
    assert status.snapshot.curve_crc == crc
    assert status.server.upload_result is CommandResult.DONE
    assert status.server.upload_seq == outcome.seq


def _paper_arrays() -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    return 3, PAPER.control_points.copy(), PAPER.knots.copy(), PAPER.weights.copy()


def _bad(change: str) -> object:
    degree, points, knots, weights = _paper_arrays()
    if change == "decreasing knots":
        knots[5] = 0.3
    elif change == "wrong knot count":
        knots = knots[:-1]
    elif change == "weight 0":
        weights[2] = 0.0
    elif change == "negative weight":
        weights[2] = -1.0
    elif change == "NaN":
        points[3, 1] = math.nan
    elif change == "degree too high":
        degree, points, weights = 7, points[:5], weights[:5]
        knots = np.r_[np.zeros(8), np.ones(4)]
    elif change == "outside travel":
        points[-1, 0] = 350.0  # the end point, on the curve
    elif change == "not clamped":
        knots[0] = -0.1
    elif change == "zero length":
        points[:] = points[0]
    elif change == "dimension 4 (bad header)":
        return "header", [3, 4, 7, 11]
    elif change == "too many points":
        return "header", [3, 3, 2001, 2005]
    elif change == "degree 9 (bad header)":
        return "header", [9, 3, 7, 17]
    return encode_staging(degree, points, knots, weights)


BAD_UPLOADS = [
    ("decreasing knots", CommandResult.CURVE_KNOTS_DECREASING),
    ("wrong knot count", CommandResult.CURVE_KNOT_COUNT),
    ("weight 0", CommandResult.CURVE_BAD_WEIGHT),
    ("negative weight", CommandResult.CURVE_BAD_WEIGHT),
    ("NaN", CommandResult.CURVE_NOT_FINITE),
    ("degree too high", CommandResult.CURVE_DEGREE_TOO_HIGH),
    ("outside travel", CommandResult.CURVE_OUTSIDE_TRAVEL),
    ("not clamped", CommandResult.CURVE_KNOTS_NOT_CLAMPED),
    ("zero length", CommandResult.CURVE_ZERO_LENGTH),
    ("dimension 4 (bad header)", CommandResult.CURVE_BAD_HEADER),
    ("degree 9 (bad header)", CommandResult.CURVE_BAD_HEADER),
    ("too many points", CommandResult.CURVE_TOO_LARGE),
]


def stage_header(client: HmiClient, header: list[int]) -> None:
    """Write ``header`` with the CRC32 of what is then staged (when it fits the staging area)."""
    _degree, _dimension, n, k = header
    crc = 0
    if n <= MAX_POINTS and k <= MAX_KNOTS:
        points = client.read_holding(FIELD["POINT_X"].address, 8 * n)
        knots = client.read_holding(FIELD["KNOT"].address, 2 * k)
        crc = staging_crc(header, points, knots)
    client.write(FIELD["CURVE_DEGREE"].address, [*header, crc >> 16, crc & 0xFFFF])


@pytest.mark.parametrize(("change", "expected"), BAD_UPLOADS, ids=[b[0] for b in BAD_UPLOADS])
def test_bad_upload_gets_its_code_and_keeps_the_loaded_curve(
    link: FakeLink, client: HmiClient, change: str, expected: CommandResult
) -> None:
    client.load_curve(PAPER)
    loaded, crc_before = link.loaded, client.status().snapshot.curve_crc
    bad = _bad(change)
    with pytest.raises(CommandRefused) as refused:
        if isinstance(bad, tuple):
            stage_header(client, bad[1])
            client.command(CommandCode.LOAD_CURVE)
        else:
            client.load_curve(bad)
    assert refused.value.result is expected
    assert refused.value.exception_code == 3
    status = client.status()
    assert status.server.upload_result is expected
    assert link.loaded is loaded and status.snapshot.curve_crc == crc_before


def test_wrong_crc(link: FakeLink, client: HmiClient) -> None:
    staging = staging_of(PAPER)
    client.stage(staging, crc32=staging.crc32 ^ 1)
    with pytest.raises(CommandRefused) as refused:
        client.command(CommandCode.LOAD_CURVE)
    assert refused.value.result is CommandResult.CURVE_CRC_MISMATCH
    assert link.loaded is None
    # The same staged data with its right CRC loads.
    client.write(FIELD["CURVE_CRC32"].address, [staging.crc32 >> 16, staging.crc32 & 0xFFFF])
    assert client.command(CommandCode.LOAD_CURVE).result is CommandResult.DONE


def test_commit_while_moving_answers_6(link: FakeLink, client: HmiClient) -> None:
    client.load_curve(PAPER)
    loaded = link.loaded
    client.command(CommandCode.ENABLE)
    client.command(CommandCode.START)
    with pytest.raises(CommandRefused) as refused:
        client.load_curve(_bad("outside travel"))  # judged on state before its content
    assert (refused.value.result, refused.value.exception_code) == (
        CommandResult.REJECTED_STATE,
        6,
    )
    assert link.loaded is loaded


@pytest.mark.parametrize("unit", [1, 0, 255])
def test_answers_configured_unit_and_0_and_255(raw: ModbusTcpClient, unit: int) -> None:
    assert raw.read_input_registers(0, count=2, device_id=unit).registers[0] == 0x534D


def test_other_unit_ids_answer_0x0b(raw: ModbusTcpClient) -> None:
    assert _exception(raw.read_input_registers(0, count=2, device_id=7)) == 0x0B


def test_refuses_peers_outside_allowed_networks(link: FakeLink) -> None:
    with HmiServer(_config(allowed_networks=("10.0.0.0/8", "::1/128")), link) as hmi:
        client = HmiClient(port=hmi.port, timeout_s=0.5)
        with pytest.raises(HmiError):
            client.connect()
        client.close()


def test_read_only_refuses_every_write_with_2(link: FakeLink) -> None:
    with HmiServer(_config(read_only=True), link) as hmi, HmiClient(port=hmi.port) as client:
        assert client.identity.read_only
        with pytest.raises(ModbusReplyError) as refused:
            client.send(CommandCode.ENABLE)
        assert refused.value.exception_code == 2
        assert client.status().snapshot.state is S.DISABLED
        assert link.applied == []


def test_start_refuses_a_busy_port(server: HmiServer, link: FakeLink) -> None:
    with pytest.raises(HmiError, match="cannot listen"):
        HmiServer(_config(port=server.port), link).start()


def _watchdog_server(link: FakeLink, timeout_ms: int) -> HmiServer:
    return HmiServer(_config(watchdog=WatchdogConfig(timeout_ms=timeout_ms)), link)


def test_watchdog_holds_a_moving_machine_when_the_hmi_is_silent(link: FakeLink) -> None:
    link.loaded = object()
    link.publish(state=S.STANDBY)
    with _watchdog_server(link, 200) as hmi, HmiClient(port=hmi.port) as client:
        assert client.identity.watchdog_timeout_ms == 200
        client.command(CommandCode.START)
        started = time.monotonic()
        status = client.wait_for(lambda s: s.snapshot.state is S.HOLDING, 3.0, "the hold")
        assert time.monotonic() - started < 1.0
        assert link.applied[-1] == Command(CommandCode.HOLD, origin="hmi watchdog")
        assert status.snapshot.message == "hold by hmi watchdog"
        assert status.server.watchdog is WatchdogState.TRIPPED
        # Sent once: the tripped watchdog waits for the HMI to come back.
        time.sleep(0.3)
        assert [c.origin for c in link.applied].count("hmi watchdog") == 1
        client.heartbeat()
        assert client.status().server.watchdog is WatchdogState.WATCHING


def test_watchdog_is_quiet_while_the_heartbeat_changes(link: FakeLink) -> None:
    link.loaded = object()
    link.publish(state=S.STANDBY)
    with _watchdog_server(link, 200) as hmi, HmiClient(port=hmi.port) as client:
        client.command(CommandCode.START)
        end = time.monotonic() + 0.8
        while time.monotonic() < end:
            client.heartbeat()
            time.sleep(0.05)
        assert client.status().snapshot.state is S.MOVING


def _cli(port: int, *argv: str) -> tuple[int, str]:
    parser = argparse.ArgumentParser()
    cli.add_arguments(parser)
    out = io.StringIO()
    return cli.run(parser.parse_args(["--port", str(port), *argv]), out), out.getvalue()


def test_cli_status_commands_and_errors(
    server: HmiServer, link: FakeLink, capsys: pytest.CaptureFixture[str]
) -> None:
    code, text = _cli(server.port, "status")
    assert code == 0 and "machine   DISABLED" in text and "axis X" in text
    code, _ = _cli(server.port, "start")
    assert code == 1
    err = capsys.readouterr().err
    assert "Modbus exception 6" in err and "REJECTED_STATE" in err
    assert _cli(server.port, "enable")[0] == 0
    code, text = _cli(server.port, "load", str(ROOT / "configs" / "curves" / "paper.yaml"))
    assert code == 0 and "7 points" in text
    assert _cli(server.port, "override", "80")[0] == 0
    assert link.snapshot().override_percent == 80.0
    assert _cli(server.port, "override", "151")[0] == 1
    assert "illegal data value" in capsys.readouterr().err
    code, text = _cli(server.port, "watch", "--count", "3", "--interval", "0.01")
    assert code == 0 and len(text.splitlines()) == 3
    code, text = _cli(server.port, "watch", "--until-idle", "--interval", "0.01")
    assert code == 0 and text.startswith("STANDBY")


def test_cli_reports_an_unreachable_machine(capsys: pytest.CaptureFixture[str]) -> None:
    code, _ = _cli(1, "status")
    assert code == 1
    assert "cannot connect" in capsys.readouterr().err
