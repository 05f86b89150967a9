"""The HMI server on the wire, with hand-built frames and with mbpoll: framing (pipelined and
split frames, malformed headers), exception responses, unit ids and device identification.

mbpoll must be installed (``scripts/system-packages`` installs it); where it cannot be, set
``SOFTMOTION_NO_MBPOLL=1`` and the mbpoll tests are skipped with that reason.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import struct
import subprocess
import time

import pytest
from fake_machine_link import FakeMachine
from modbus_wire import Wire, WireError, adu, read_pdu, write_pdu

from runtime.commands import CommandCode
from runtime.hmi.registers import FIELD, HOLDING_HEAD_END, INPUT_SIZE, MAGIC, MAP_VERSION
from runtime.hmi.server import HmiServer
from runtime.version import VERSION


def test_identity_block_and_test_patterns(wire: Wire) -> None:
    regs = wire.read_input(0, 16)
    assert regs[0] == MAGIC and regs[1] == MAP_VERSION
    assert regs[2:6] == [0x47F1, 0x2000, 0x1234, 0x5678]
    assert regs[9] == 3


@pytest.mark.parametrize(("function", "count"), [(4, 126), (3, 126), (4, 0), (3, 0), (4, 2000)])
def test_read_counts_outside_1_to_125_answer_3_with_their_function_code(
    wire: Wire, function: int, count: int
) -> None:
    assert wire.ask(read_pdu(0, count, function)) == bytes((function | 0x80, 3))


@pytest.mark.parametrize("function", [0x41, 0x64, 0x00, 0x09, 0x7F, 1, 2, 5, 8, 15, 22, 24])
def test_unknown_functions_answer_1_with_their_function_code(wire: Wire, function: int) -> None:
    assert wire.ask(bytes((function, 0, 0, 0, 1))) == bytes((function | 0x80, 1))
    assert wire.read_input(0, 1) == [MAGIC]  # the connection goes on


def test_write_counts_and_byte_counts_are_checked(wire: Wire) -> None:
    # 124 registers do not fit a 253-byte PDU: the quantity says 124, the data hold 123.
    too_many = struct.pack(">BHHB", 16, 1000, 124, 246) + bytes(246)
    assert wire.ask(too_many) == b"\x90\x03"
    assert wire.ask(struct.pack(">BHHB", 16, 1000, 0, 0)) == b"\x90\x03"
    assert wire.ask(struct.pack(">BHHB2H", 16, 1000, 2, 6, 0, 0)) == b"\x90\x03"  # byte count
    assert wire.ask(struct.pack(">BHHBH", 16, 1000, 2, 4, 0)) == b"\x90\x03"  # short data
    assert wire.ask(struct.pack(">BHH", 3, 0, 1) + b"\0") == b"\x83\x03"  # PDU too long
    rw = struct.pack(">BHHHHB", 23, 0, 1, 1000, 122, 242) + bytes(242)
    assert wire.ask(rw) == b"\x97\x03"


def test_read_write_multiple_writes_then_reads(wire: Wire) -> None:
    pdu = struct.pack(">BHHHHB2H", 23, 1000, 2, 1000, 2, 4, 0x4148, 0)
    assert wire.ask(pdu) == bytes((23, 4)) + struct.pack(">2H", 0x4148, 0)


def test_pipelined_requests_are_all_answered_in_order(wire: Wire) -> None:
    frames = [
        adu(read_pdu(0, 1), tid=11),
        adu(read_pdu(2, 2), tid=12),
        adu(bytes((0x41,)), tid=13),
        adu(read_pdu(0, 126), tid=14),
    ]
    wire.send(b"".join(frames))
    answers = [wire.response() for _ in frames]
    assert [tid for tid, _unit, _pdu in answers] == [11, 12, 13, 14]
    assert answers[0][2] == bytes((4, 2)) + struct.pack(">H", MAGIC)
    assert answers[1][2] == bytes((4, 4, 0x47, 0xF1, 0x20, 0x00))
    assert answers[2][2] == b"\xc1\x01"
    assert answers[3][2] == b"\x84\x03"


def test_frames_split_across_segments_are_reassembled(wire: Wire) -> None:
    first, second = adu(read_pdu(0, 1), tid=21), adu(read_pdu(1, 1), tid=22)
    stream = first + second
    cut = len(first) + len(second) // 2  # one and a half frames, then the rest
    wire.send(stream[:cut])
    time.sleep(0.05)
    wire.send(stream[cut:])
    assert [wire.response()[0] for _ in range(2)] == [21, 22]
    for byte in adu(read_pdu(0, 2), tid=23):  # one byte per segment
        wire.send(bytes((byte,)))
        time.sleep(0.002)
    assert wire.response() == (23, 1, bytes((4, 4)) + struct.pack(">2H", MAGIC, MAP_VERSION))


@pytest.mark.parametrize(
    "bad",
    [
        struct.pack(">HHHB", 5, 1, 6, 1) + read_pdu(0, 1),  # protocol id 1
        struct.pack(">HHHB", 5, 0, 0, 1),  # length 0
        struct.pack(">HHHB", 5, 0, 1, 1) + read_pdu(0, 1),  # length 1
        struct.pack(">HHHB", 5, 0, 300, 1) + bytes(299),  # length 300
        struct.pack(">HHHB", 5, 0, 255, 1) + bytes(254),  # length 255
        b"GET / HTTP/1.1\r\nHost: x\r\n\r\n",  # garbage
    ],
    ids=["protocol 1", "length 0", "length 1", "length 300", "length 255", "garbage"],
)
def test_a_malformed_header_closes_the_connection_after_earlier_answers(
    hmi: HmiServer, bad: bytes, caplog: pytest.LogCaptureFixture
) -> None:
    with Wire(hmi.port) as wire, caplog.at_level(logging.WARNING, "runtime.hmi.server"):
        port = wire.sock.getsockname()[1]
        wire.send(adu(read_pdu(0, 1), tid=31) + bad + adu(read_pdu(0, 1), tid=32))
        assert wire.response()[0] == 31
        assert wire.closed_by_server()
    assert any(f"127.0.0.1:{port}" in r.getMessage() for r in caplog.records)
    with Wire(hmi.port) as again:  # the server itself goes on
        assert again.read_input(0, 1) == [MAGIC]


def test_a_header_cut_short_closes_the_connection(
    fake: FakeMachine, caplog: pytest.LogCaptureFixture
) -> None:
    from fake_machine_link import hmi_config

    server = HmiServer(fake, hmi_config())
    server.frame_timeout_s = 0.3
    with server, Wire(server.port) as wire, caplog.at_level(logging.WARNING):
        wire.send(adu(read_pdu(0, 1))[:4])
        assert wire.closed_by_server(timeout_s=3.0)
    assert any("incomplete frame (4 bytes)" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("unit", [1, 0, 255])
def test_answers_the_configured_unit_and_0_and_255(wire: Wire, unit: int) -> None:
    assert wire.read_input(0, 1, unit=unit) == [MAGIC]


def test_other_unit_ids_answer_11(wire: Wire) -> None:
    assert wire.ask(read_pdu(0, 1), unit=7) == b"\x84\x0b"
    assert wire.ask(bytes((0x41,)), unit=7) == b"\xc1\x0b"


def test_report_server_id(wire: Wire) -> None:
    answer = wire.ask(bytes((17,)))
    data = f"softmotion {VERSION}".encode() + b"\xff"
    assert answer == bytes((17, len(data))) + data


def _objects(answer: bytes) -> dict[int, bytes]:
    count, at, found = answer[6], 7, {}
    for _ in range(count):
        object_id, size = answer[at], answer[at + 1]
        found[object_id] = answer[at + 2 : at + 2 + size]
        at += 2 + size
    assert at == len(answer)
    return found


def test_read_device_identification(wire: Wire) -> None:
    version = VERSION.encode()
    basic = wire.ask(bytes((43, 14, 1, 0)))
    assert basic[:6] == bytes((43, 14, 1, 0x81, 0, 0))
    assert _objects(basic) == {0: b"softmotion", 1: b"softmotion", 2: version}
    assert _objects(wire.ask(bytes((43, 14, 1, 2)))) == {2: version}
    assert _objects(wire.ask(bytes((43, 14, 1, 0x55)))) == _objects(basic)  # restart at 0
    assert _objects(wire.ask(bytes((43, 14, 4, 1)))) == {1: b"softmotion"}
    assert wire.ask(bytes((43, 14, 4, 9))) == b"\xab\x02"
    assert wire.ask(bytes((43, 14, 5, 0))) == b"\xab\x03"
    assert wire.ask(bytes((43, 13, 1, 0))) == b"\xab\x01"


def test_refusals_use_2_3_and_6_never_4(fake: FakeMachine, wire: Wire) -> None:
    assert wire.ask(read_pdu(INPUT_SIZE, 1)) == b"\x84\x02"
    assert wire.ask(read_pdu(INPUT_SIZE - 1, 2)) == b"\x84\x02"
    assert wire.ask(write_pdu(0, [13, 1])) == b"\x90\x03"  # code above the largest
    assert wire.ask(write_pdu(0, [CommandCode.SHUTDOWN, 1])) == b"\x90\x03"
    assert wire.ask(write_pdu(0, [0, 1])) == b"\x90\x03"  # sequence change without a code
    assert wire.ask(write_pdu(2, [1501])) == b"\x90\x03"
    assert wire.ask(write_pdu(1001, [0])) == b"\x90\x03"  # low word of a float
    assert wire.ask(write_pdu(1000, [0, 0, 0])) == b"\x90\x03"  # ends inside a float
    assert wire.ask(write_pdu(22, [0])) == b"\x90\x02"
    assert wire.ask(write_pdu(21016, [0])) == b"\x90\x02"
    assert wire.ask(read_pdu(22, 1, 3)) == b"\x83\x02"
    assert wire.ask(read_pdu(0, HOLDING_HEAD_END + 1, 3)) == b"\x83\x02"
    assert fake.posted == []


def _mbpoll() -> str:
    path = shutil.which("mbpoll")
    if path is None:
        if os.environ.get("SOFTMOTION_NO_MBPOLL"):
            pytest.skip("mbpoll cannot be installed here (SOFTMOTION_NO_MBPOLL is set)")
        pytest.fail("mbpoll is not installed: run scripts/system-packages (apt-get install mbpoll)")
    return path


def _values(text: str) -> list[str]:
    """The values of mbpoll's ``[address]: value`` lines."""
    return re.findall(r"^\[\d+\]:\s+(\S+)", text, re.MULTILINE)


def _run(*argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(argv, capture_output=True, text=True, timeout=30, check=False)


def test_mbpoll_reads_status_and_holding_block_and_writes_a_command(
    fake: FakeMachine, hmi: HmiServer
) -> None:
    base = [_mbpoll(), "-m", "tcp", "-p", str(hmi.port), "-1", "-0"]
    identity = _run(*base, "-a", "255", "-t", "3:hex", "-r", "0", "-c", "6", "127.0.0.1")
    assert identity.returncode == 0, identity.stderr
    assert _values(identity.stdout) == [
        "0x534D",
        f"0x{MAP_VERSION:04X}",
        "0x47F1",
        "0x2000",
        "0x1234",
        "0x5678",
    ]
    test_float = _run(*base, "-t", "3:float", "-B", "-r", "2", "-c", "1", "127.0.0.1")
    assert _values(test_float.stdout) == ["123456"], test_float.stdout
    # Holding registers 0..21 in one FC3 request: the reserved ones read 0.
    block = _run(*base, "-t", "4", "-r", "0", "-c", str(HOLDING_HEAD_END), "127.0.0.1")
    assert block.returncode == 0, block.stderr
    assert _values(block.stdout) == ["0"] * HOLDING_HEAD_END
    # A command: COMMAND_CODE = ENABLE (FC6), then a new COMMAND_SEQ.
    for address, value in ((FIELD["COMMAND_CODE"].address, 1), (FIELD["COMMAND_SEQ"].address, 5)):
        done = _run(*base, "-t", "4", "-r", str(address), "127.0.0.1", str(value))
        assert done.returncode == 0, done.stderr
    fake.wait_periods(2)
    state = _run(
        *base, "-t", "3", "-r", str(FIELD["MACHINE_STATE"].address), "-c", "1", "127.0.0.1"
    )
    assert _values(state.stdout) == ["1"]  # STANDBY
    # A refused write: mbpoll reports the Modbus exception and exits 1.
    refused = _run(*base, "-t", "4", "-r", str(FIELD["CURVE_POINTS"].address), "127.0.0.1", "2001")
    assert refused.returncode == 1
    assert "Illegal data value" in refused.stderr
    coils = _run(*base, "-t", "0", "-r", "0", "-c", "1", "127.0.0.1")
    assert coils.returncode == 1 and "Illegal function" in coils.stderr


def test_mbpoll_sees_exception_2_for_a_gap(hmi: HmiServer) -> None:
    base = [_mbpoll(), "-m", "tcp", "-p", str(hmi.port), "-1", "-0"]
    gap = _run(*base, "-t", "4", "-r", str(HOLDING_HEAD_END), "-c", "1", "127.0.0.1")
    assert gap.returncode == 1 and "Illegal data address" in gap.stderr


def test_unexpected_errors_answer_4_and_the_connection_goes_on(
    hmi: HmiServer, wire: Wire, monkeypatch: pytest.MonkeyPatch
) -> None:
    def broken(address: int, count: int) -> bytes:
        raise RuntimeError("a bug")

    monkeypatch.setattr(hmi.device, "read_input", broken)
    assert wire.ask(read_pdu(0, 1)) == b"\x84\x04"
    assert wire.read_holding(0, 1) == [0]


def test_wire_error_carries_the_code(wire: Wire) -> None:
    with pytest.raises(WireError) as refused:
        wire.write(2, [1501])
    assert refused.value.code == 3
