"""The ``local`` bus: frames between processes, in order, with the sender's timestamps."""

from __future__ import annotations

import multiprocessing
import os
import time
import uuid

import can
import pytest

from drives.bus import open_bus
from drives.localbus import PEER_CHECK_S, channel_directory


@pytest.fixture
def channel() -> str:
    return f"test-{uuid.uuid4().hex[:8]}"


def _send_numbered(channel: str, count: int, ready, go) -> None:
    bus = open_bus("local", channel)
    ready.set()
    go.wait(10)
    time.sleep(2 * PEER_CHECK_S)
    for i in range(count):
        bus.send(can.Message(arbitration_id=0x180 + (i % 3), data=i.to_bytes(4, "little")))
    bus.shutdown()


def test_frames_from_another_process_arrive_in_order_with_their_send_time(channel: str) -> None:
    receiver = open_bus("local", channel)
    context = multiprocessing.get_context("spawn")
    ready, go = context.Event(), context.Event()
    sender = context.Process(target=_send_numbered, args=(channel, 5000, ready, go))
    sender.start()
    try:
        assert ready.wait(30)
        before = time.time()
        go.set()
        sender.join(30)
        received = []
        while (message := receiver.recv(0.2)) is not None:
            received.append(message)
        after = time.time()
    finally:
        receiver.shutdown()
    assert [int.from_bytes(m.data, "little") for m in received] == list(range(5000))
    assert [m.arbitration_id for m in received[:3]] == [0x180, 0x181, 0x182]
    stamps = [m.timestamp for m in received]
    assert stamps == sorted(stamps) and before <= stamps[0] and stamps[-1] <= after


def test_preserved_timestamps_only_when_asked_and_only_where_a_message_has_one(
    channel: str,
) -> None:
    receiver = open_bus("local", channel)
    preserving = open_bus("local", channel, preserve_timestamps=True)
    plain = open_bus("local", channel)
    try:
        time.sleep(2 * PEER_CHECK_S)
        wire_s = time.time() - 1.0
        before = time.time()
        preserving.send(can.Message(arbitration_id=0x181, data=b"\x01", timestamp=wire_s))
        preserving.send(can.Message(arbitration_id=0x182, data=b"\x02"))
        plain.send(can.Message(arbitration_id=0x183, data=b"\x03", timestamp=wire_s))
        received = {m.arbitration_id: m.timestamp for m in (receiver.recv(0.5) for _ in range(3))}
        after = time.time()
    finally:
        for bus in (receiver, preserving, plain):
            bus.shutdown()
    assert received[0x181] == wire_s
    assert before <= received[0x182] <= after and before <= received[0x183] <= after


def test_own_frames_only_when_asked_and_filters_apply(channel: str) -> None:
    plain = open_bus("local", channel)
    own = open_bus("local", channel, receive_own_messages=True)
    filtered = open_bus(
        "local", channel, can_filters=[{"can_id": 0x80, "can_mask": 0x7FF, "extended": False}]
    )
    try:
        time.sleep(2 * PEER_CHECK_S)
        own.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
        own.send(
            can.Message(arbitration_id=0x700, is_remote_frame=True, dlc=1, is_extended_id=False)
        )
        echo = [own.recv(0.5), own.recv(0.5)]
        assert [m.arbitration_id for m in echo] == [0x80, 0x700]
        assert echo[1].is_remote_frame and echo[1].dlc == 1
        assert [plain.recv(0.5).arbitration_id, plain.recv(0.5).arbitration_id] == [0x80, 0x700]
        assert filtered.recv(0.5).arbitration_id == 0x80
        assert filtered.recv(0.1) is None
        plain.send(can.Message(arbitration_id=0x181, data=b"\x01"))
        assert own.recv(0.5).arbitration_id == 0x181
        assert plain.recv(0.1) is None
    finally:
        for bus in (plain, own, filtered):
            bus.shutdown()


def test_a_receiver_that_reads_nothing_loses_frames_not_the_sender(channel: str) -> None:
    sender = open_bus("local", channel)
    stalled = open_bus("local", channel)
    try:
        time.sleep(2 * PEER_CHECK_S)
        begin = time.perf_counter()
        for _ in range(60_000):
            sender.send(can.Message(arbitration_id=0x181, data=b"12345678"))
        assert time.perf_counter() - begin < 30  # never blocked on the full pipe
        assert sender.frames_dropped > 0
        assert stalled.recv(0.1) is not None
    finally:
        sender.shutdown()
        stalled.shutdown()


def test_a_bus_whose_process_died_is_forgotten(channel: str) -> None:
    sender = open_bus("local", channel)
    directory = channel_directory(channel)
    ghost = directory / "999999999-1"
    os.mkfifo(ghost)  # a pipe no process reads: its bus died without removing it
    try:
        time.sleep(2 * PEER_CHECK_S)
        sender.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
        assert not ghost.exists()
    finally:
        sender.shutdown()


def test_frames_sent_together_arrive_together_and_own_ones_are_marked(channel: str) -> None:
    sender = open_bus("local", channel, receive_own_messages=True)
    receiver = open_bus("local", channel)
    try:
        time.sleep(2 * PEER_CHECK_S)
        frames = [can.Message(arbitration_id=0x201 + i, data=bytes([i])) for i in range(3)]
        sender.send_frames([*frames, can.Message(arbitration_id=0x80, data=b"")])
        received = [receiver.recv(0.5) for _ in range(4)]
        echoed = [sender.recv(0.5) for _ in range(4)]
        assert [m.arbitration_id for m in received] == [0x201, 0x202, 0x203, 0x80]
        assert len({m.timestamp for m in received}) == 1 and all(m.is_rx for m in received)
        assert [m.arbitration_id for m in echoed] == [0x201, 0x202, 0x203, 0x80]
        assert not any(m.is_rx for m in echoed)
    finally:
        sender.shutdown()
        receiver.shutdown()
