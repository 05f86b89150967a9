"""Smoke tests of the vcan stage: python-can's socketcan interface on a real kernel CAN bus.

Frames sent through ``can.Bus(interface="socketcan", channel="vcan0")`` must reach the
independent raw-socket recorder (tests/vcan/canlisten.py) with exact identifiers and payloads and
a kernel timestamp, and frames sent by another process must reach this one: the kernel's CAN
layer, not a Python object, carries them. Timeouts only bound waiting; they are scaled by
``vcan_timing_factor`` for the emulated VM.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time

import can
from canlisten import CanListener, RecordedFrame

CHANNEL = "vcan0"
#: Seconds to wait for frames already sent (before the timing factor).
RECEIVE_TIMEOUT_S = 2.0
#: Seconds for a fresh Python process to import python-can and send (before the timing factor).
SENDER_PROCESS_TIMEOUT_S = 10.0

_SENDER_SCRIPT = textwrap.dedent(
    """
    import sys
    import can

    channel, cob_id, count = sys.argv[1], int(sys.argv[2], 0), int(sys.argv[3])
    with can.Bus(interface="socketcan", channel=channel) as bus:
        for index in range(count):
            payload = bytes([index & 0xFF, index >> 8, 0xA5])
            bus.send(can.Message(arbitration_id=cob_id, data=payload, is_extended_id=False))
    """
)


def _sent_frames() -> list[can.Message]:
    """Frames covering the shapes CANopen uses: empty, short, full, remote, and one extended."""
    return [
        can.Message(arbitration_id=0x080, data=b"", is_extended_id=False),
        can.Message(arbitration_id=0x000, data=bytes([0x01, 0x05]), is_extended_id=False),
        can.Message(arbitration_id=0x605, data=bytes(range(0x40, 0x48)), is_extended_id=False),
        can.Message(arbitration_id=0x705, is_remote_frame=True, dlc=1, is_extended_id=False),
        can.Message(arbitration_id=0x1ABCDE05, data=b"\xff\x00\xff", is_extended_id=True),
    ]


def _as_recorded(message: can.Message) -> tuple[int, bytes, bool, bool]:
    data = b"" if message.is_remote_frame else bytes(message.data)
    return (message.arbitration_id, data, message.is_extended_id, message.is_remote_frame)


def _shape(frame: RecordedFrame) -> tuple[int, bytes, bool, bool]:
    return (frame.can_id, frame.data, frame.is_extended, frame.is_remote)


def test_python_can_frames_reach_the_raw_listener_exactly(
    vcan_listener: CanListener, vcan_timing_factor: float
) -> None:
    sent = _sent_frames()
    wanted = {message.arbitration_id for message in sent}
    before_ns = time.time_ns()
    with can.Bus(interface="socketcan", channel=CHANNEL) as bus:
        assert type(bus).__name__ == "SocketcanBus"
        for message in sent:
            bus.send(message)
        received = vcan_listener.wait_for(
            lambda frame: frame.can_id in wanted,
            len(sent),
            RECEIVE_TIMEOUT_S * vcan_timing_factor,
        )
    after_ns = time.time_ns()

    assert [_shape(frame) for frame in received] == [_as_recorded(m) for m in sent]
    stamps = [frame.timestamp_ns for frame in received]
    assert stamps == sorted(stamps)
    assert before_ns <= stamps[0] and stamps[-1] <= after_ns
    assert vcan_listener.dropped == 0


def test_kernel_filter_keeps_only_the_chosen_cob_ids(vcan_timing_factor: float) -> None:
    with (
        CanListener(CHANNEL, cob_ids=[0x185, 0x705]) as listener,
        can.Bus(interface="socketcan", channel=CHANNEL) as bus,
    ):
        for cob_id in (0x080, 0x185, 0x205, 0x705, 0x185):
            bus.send(can.Message(arbitration_id=cob_id, data=[cob_id & 0xFF], is_extended_id=False))
        listener.wait_for_count(0x185, 2, RECEIVE_TIMEOUT_S * vcan_timing_factor)
        listener.wait_for_count(0x705, 1, RECEIVE_TIMEOUT_S * vcan_timing_factor)

    assert [(frame.can_id, frame.data) for frame in listener.frames()] == [
        (0x185, b"\x85"),
        (0x705, b"\x05"),
        (0x185, b"\x85"),
    ]


def test_frames_from_another_process_reach_this_process(
    vcan_listener: CanListener, vcan_timing_factor: float
) -> None:
    cob_id, count = 0x18A, 20
    expected = [bytes([index & 0xFF, index >> 8, 0xA5]) for index in range(count)]
    with can.Bus(
        interface="socketcan",
        channel=CHANNEL,
        can_filters=[{"can_id": cob_id, "can_mask": 0x7FF, "extended": False}],
    ) as receiver:
        subprocess.run(
            [sys.executable, "-c", _SENDER_SCRIPT, CHANNEL, hex(cob_id), str(count)],
            check=True,
            timeout=SENDER_PROCESS_TIMEOUT_S * vcan_timing_factor,
        )
        deadline = time.monotonic() + RECEIVE_TIMEOUT_S * vcan_timing_factor
        received: list[bytes] = []
        while len(received) < count and time.monotonic() < deadline:
            message = receiver.recv(timeout=max(0.0, deadline - time.monotonic()))
            if message is not None:
                received.append(bytes(message.data))

    assert received == expected
    recorded = vcan_listener.wait_for_count(cob_id, count, RECEIVE_TIMEOUT_S * vcan_timing_factor)
    assert [frame.data for frame in recorded] == expected
