"""SYNC production and the matching of feedback frames to the SYNC they answered."""

from __future__ import annotations

import can
import pytest

from drives.sync import SyncProducer


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def _producer(counter_overflow: int = 0) -> tuple[SyncProducer, list[can.Message], Clock]:
    sent: list[can.Message] = []
    clock = Clock()
    producer = SyncProducer(
        lambda message: sent.append(
            can.Message(
                arbitration_id=message.arbitration_id,
                data=bytes(message.data),
                is_extended_id=False,
                timestamp=clock.now + 0.0001,
            )
        ),
        history=8,
        counter_overflow=counter_overflow,
        wall_clock=clock,
    )
    return producer, sent, clock


def test_sync_frames_without_and_with_counter() -> None:
    producer, sent, _ = _producer()
    producer.transmit()
    assert sent[0].arbitration_id == 0x080 and sent[0].dlc == 0
    counted, sent, _ = _producer(counter_overflow=3)
    for _ in range(5):
        counted.transmit()
    assert [bytes(m.data) for m in sent] == [b"\x01", b"\x02", b"\x03", b"\x01", b"\x02"]


def test_a_frame_answers_the_last_sync_sent_before_it_however_late_it_is_read() -> None:
    producer, _, clock = _producer()
    stamps = []
    for _ in range(4):
        clock.now += 0.004
        producer.transmit()
        stamps.append(clock.now)
    assert producer.answered(stamps[1] + 0.0005) == 2  # read two periods later
    assert producer.answered(stamps[3] + 0.0005) == 4
    assert producer.answered(stamps[0] - 0.001) == 0  # before every SYNC remembered


def test_echo_timestamps_replace_our_clock_once_seen() -> None:
    producer, sent, clock = _producer()
    for _ in range(3):
        clock.now += 0.004
        producer.transmit()
    # An adapter stamping with its own clock, 500 s behind ours.
    for message in sent[:2]:
        message.timestamp -= 500.0
        producer.on_echo(message)
    assert producer.echoes_seen
    assert producer.answered(sent[1].timestamp + 0.001) == 2  # SYNC 3 has no echo yet
    assert producer.answered(sent[0].timestamp + 0.001) == 1


def test_counter_matching_follows_the_receive_order_of_echoes() -> None:
    producer, sent, clock = _producer(counter_overflow=4)
    for _ in range(6):
        clock.now += 0.004
        producer.transmit()
    producer.on_echo(sent[4])  # SYNC 5 (counter 1); earlier echoes were lost
    assert producer.answered(0.0) == 5
    producer.on_echo(sent[4])  # a duplicate changes nothing
    producer.on_echo(sent[5])
    assert producer.answered(0.0) == 6


def test_counter_overflow_range() -> None:
    with pytest.raises(ValueError, match=r"must be 0 or 2\.\.240"):
        SyncProducer(lambda message: None, history=4, counter_overflow=1)


def test_lost_echoes_do_not_shift_later_matches() -> None:
    producer, sent, clock = _producer()
    for _ in range(6):
        clock.now += 0.004
        producer.transmit()
    # An adapter clock 500 s behind ours; the echoes of SYNCs 2 to 4 were lost in a stall.
    for index in (0, 4, 5):
        sent[index].timestamp -= 500.0
        producer.on_echo(sent[index])
    assert producer.answered(sent[4].timestamp + 0.001) == 5
    assert producer.answered(sent[5].timestamp + 0.001) == 6
    clock.now += 0.004
    producer.transmit()
    sent[6].timestamp -= 500.0
    producer.on_echo(sent[6])
    assert producer.answered(sent[6].timestamp + 0.001) == 7
