"""Node guarding and the master's heartbeat producer, on a stepped clock."""

from __future__ import annotations

import can
import pytest

from drives.guarding import NodeGuard, heartbeat_producer


def test_guard_requests_every_guard_time_without_bursts() -> None:
    sent: list[can.Message] = []
    guard = NodeGuard(3, sent.append, guard_time_s=0.1, life_time_factor=3)
    guard.start(now_s=10.0)
    for now_s in (10.0, 10.05, 10.1, 10.35):  # 10.35: late; one request, then 10.45
        guard.poll(now_s)
    guard.poll(10.4)
    guard.poll(10.45)
    assert len(sent) == 4
    assert all(m.is_remote_frame and m.arbitration_id == 0x703 and m.dlc == 1 for m in sent)


def test_guard_answers_toggle_and_life_time() -> None:
    guard = NodeGuard(3, lambda message: None, guard_time_s=0.1, life_time_factor=3)
    guard.start(now_s=0.0)
    assert guard.on_answer(0x85, now_s=0.01)  # first answer: any toggle
    assert guard.on_answer(0x05, now_s=0.11)
    assert not guard.on_answer(0x05, now_s=0.21)  # toggle did not alternate
    assert guard.nmt_state == 0x05
    assert guard.life_time_s == pytest.approx(0.3)
    assert guard.silence_s(0.5) == pytest.approx(0.29)


def test_heartbeat_producer() -> None:
    sent: list[can.Message] = []
    producer = heartbeat_producer(127, sent.append, period_s=0.1)
    producer.poll(0.0)
    assert sent == []  # not started
    producer.start()
    for now_s in (0.0, 0.05, 0.1, 0.2, 0.55, 0.6, 0.65):
        producer.poll(now_s)
    assert [bytes(m.data) for m in sent] == [b"\x05"] * 5
    assert sent[0].arbitration_id == 0x77F
