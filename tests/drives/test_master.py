"""Master unit tests: byte-exact RPDO1/SYNC frames, 402 stepping, supervision rules.

A scripted drive (raw frames on a second virtual bus) plays TPDO1 and heartbeats; an independent
listener bus records what the master transmits.
"""

from __future__ import annotations

import contextlib
import math
import struct
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass

import can
import canopen
import pytest

from drives.cia402 import State, encode_statusword
from drives.errors import DriveError
from drives.master import AxisSpec, Cia402Master, MasterSettings, TravelLimitError
from drives.monitor import (
    AxisSupervisor,
    EmcyRecord,
    FaultKind,
    HeartbeatSample,
    SupervisionLimits,
    SyncCounter,
    TpdoSample,
)
from drives.scaling import AxisScaling

RPDO1 = struct.Struct("<Hi")


@dataclass
class Rig:
    master: Cia402Master
    drive_bus: can.BusABC
    listener: can.BusABC


@pytest.fixture
def rig() -> Iterator[Rig]:
    yield from _rig(MasterSettings(period_s=0.004))


def _rig(settings: MasterSettings) -> Iterator[Rig]:
    channel = f"test-master-{uuid.uuid4().hex}"
    network = canopen.Network()
    network.NOTIFIER_SHUTDOWN_TIMEOUT = 0.0
    network.connect(interface="virtual", channel=channel, receive_own_messages=False)
    drive_bus = can.Bus(interface="virtual", channel=channel)
    listener = can.Bus(interface="virtual", channel=channel)
    axes = [
        AxisSpec("X", 1, AxisScaling(1000.0, travel_min_mm=-100.0, travel_max_mm=100.0), 1.0, 20),
        AxisSpec("Y", 2, AxisScaling(1000.0, direction=-1), 1.0, 20),
    ]
    master = Cia402Master(network, axes, settings)
    try:
        yield Rig(master, drive_bus, listener)
    finally:
        network.disconnect()
        drive_bus.shutdown()
        listener.shutdown()


def _tpdo(rig: Rig, node_id: int, state: State, position_counts: int) -> None:
    statusword = encode_statusword(state)
    rig.drive_bus.send(
        can.Message(
            arbitration_id=0x180 + node_id,
            data=RPDO1.pack(statusword, position_counts),
            is_extended_id=False,
        )
    )


def _play(rig: Rig, states: dict[int, tuple[State, int]]) -> None:
    """Send one TPDO1 per node and wait until the master's notifier stored them."""
    for node_id, (state, position) in states.items():
        _tpdo(rig, node_id, state, position)
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline:
        feedback = rig.master.read_feedback()
        if all(
            f.state is states[f.node_id][0] and f.position_counts == states[f.node_id][1]
            for f in feedback
        ):
            return
        time.sleep(0.001)
    raise AssertionError(f"TPDOs not received: {rig.master.read_feedback()}")


def _is_scripted_tpdo(frame: can.Message) -> bool:
    return 0x181 <= frame.arbitration_id <= 0x1FF


def _frames(rig: Rig, count: int) -> list[can.Message]:
    """The next ``count`` frames the master sent (the scripted drive's TPDOs are skipped)."""
    frames: list[can.Message] = []
    while len(frames) < count:
        frame = rig.listener.recv(timeout=1.0)
        assert frame is not None, f"only {len(frames)} of {count} frames"
        if not _is_scripted_tpdo(frame):
            frames.append(frame)
    while (extra := rig.listener.recv(timeout=0.02)) is not None:
        assert _is_scripted_tpdo(extra), f"unexpected frame {extra}"
    return frames


def _exchange_frames(rig: Rig) -> list[tuple[int, bytes]]:
    rig.master.exchange()
    return [(f.arbitration_id, bytes(f.data)) for f in _frames(rig, 3)]


def test_exchange_sends_rpdo1_of_every_axis_then_one_sync(rig: Rig) -> None:
    _play(rig, {1: (State.SWITCH_ON_DISABLED, 1234), 2: (State.SWITCH_ON_DISABLED, -5678)})
    rig.master.exchange()
    frames = _frames(rig, 3)
    assert [f.arbitration_id for f in frames] == [0x201, 0x202, 0x080]
    assert [f.dlc for f in frames] == [6, 6, 0]
    assert not any(f.is_extended_id or f.is_remote_frame for f in frames)
    # Disabled axes: controlword 0x0000 (disable voltage), target = actual position.
    assert bytes(frames[0].data) == bytes.fromhex("0000d2040000")
    assert bytes(frames[1].data) == bytes.fromhex("0000d2e9ffff")
    assert rig.master.syncs_sent == 1


def test_enable_steps_one_transition_per_cycle_from_the_actual_position(rig: Rig) -> None:
    master = rig.master
    _play(rig, {1: (State.SWITCH_ON_DISABLED, 1000), 2: (State.SWITCH_ON_DISABLED, 2000)})
    master.request_enable()
    expected = [
        (State.SWITCH_ON_DISABLED, 0x06),  # transition 2, shutdown
        (State.READY_TO_SWITCH_ON, 0x07),  # 3, switch on
        (State.SWITCHED_ON, 0x0F),  # 4, enable operation
        (State.OPERATION_ENABLED, 0x0F),  # hold
    ]
    for state, controlword in expected:
        _play(rig, {1: (state, 1000), 2: (state, 2000)})
        master.write_targets([50.0, 50.0])  # ignored until OPERATION ENABLED is reported
        frames = _exchange_frames(rig)
        if state is not State.OPERATION_ENABLED:
            assert frames[0] == (0x201, RPDO1.pack(controlword, 1000))
            assert frames[1] == (0x202, RPDO1.pack(controlword, 2000))
        else:
            assert frames[0] == (0x201, RPDO1.pack(0x0F, 50_000))
            assert frames[1] == (0x202, RPDO1.pack(0x0F, -50_000))  # direction -1
        assert frames[2] == (0x080, b"")
    assert master.all_enabled
    assert master.enabled_mask == (True, True)


def test_targets_keep_last_and_are_absolute(rig: Rig) -> None:
    master = rig.master
    _play(rig, {1: (State.OPERATION_ENABLED, 0), 2: (State.OPERATION_ENABLED, 0)})
    master.request_enable()
    master.write_targets([1.0005, -0.0004])
    assert _exchange_frames(rig)[:2] == [
        (0x201, RPDO1.pack(0x0F, 1000)),  # 1000.5 rounds half to even
        (0x202, RPDO1.pack(0x0F, 0)),
    ]
    master.write_targets([None, 2.0])
    assert _exchange_frames(rig)[:2] == [
        (0x201, RPDO1.pack(0x0F, 1000)),
        (0x202, RPDO1.pack(0x0F, -2000)),
    ]
    master.write_targets(None)
    assert _exchange_frames(rig)[1] == (0x202, RPDO1.pack(0x0F, -2000))
    feedback = master.read_feedback()
    assert feedback[1].commanded_mm == pytest.approx(2.0)


def test_late_feedback_is_judged_against_the_target_it_answered() -> None:
    # A stale-feedback limit of 25 cycles: every TPDO younger than that is compared with the
    # target it answered, however far the targets moved since (a fixed history of 16 targets
    # compared it with a newer one, a following error of 1.5 mm here).
    with contextlib.contextmanager(_rig)(
        MasterSettings(period_s=0.004, stale_feedback_cycles=25)
    ) as rig:
        master = rig.master
        _play(rig, {1: (State.OPERATION_ENABLED, 0), 2: (State.OPERATION_ENABLED, 0)})
        master.request_enable()
        for k in range(1, 21):
            master.write_targets([0.1 * k, 0.0])
            master.exchange()
        assert master.read_feedback()[0].following_error_mm == 0.0
        _play(rig, {1: (State.OPERATION_ENABLED, 100), 2: (State.OPERATION_ENABLED, 0)})
        # Fresh: answers SYNC 20, following the target of SYNC 19 (1.9 mm).
        assert master.read_feedback()[0].following_error_mm == pytest.approx(0.1 - 1.9)


def test_write_targets_checks_everything_before_applying(rig: Rig) -> None:
    master = rig.master
    _play(rig, {1: (State.OPERATION_ENABLED, 0), 2: (State.OPERATION_ENABLED, 0)})
    master.request_enable()
    with pytest.raises(TravelLimitError, match=r"node 1: axis X: target 150\.0 mm outside"):
        master.write_targets([150.0, 5.0])
    with pytest.raises(ValueError, match="1 positions for 2 axes"):
        master.write_targets([1.0])
    # Nothing of the rejected cycles was applied.
    assert _exchange_frames(rig)[:2] == [
        (0x201, RPDO1.pack(0x0F, 0)),
        (0x202, RPDO1.pack(0x0F, 0)),
    ]


def test_quick_stop_then_disabled(rig: Rig) -> None:
    master = rig.master
    _play(rig, {1: (State.OPERATION_ENABLED, 10), 2: (State.OPERATION_ENABLED, 20)})
    master.request_enable()
    master.request_quick_stop(["X"])
    frames = _exchange_frames(rig)
    assert frames[0] == (0x201, RPDO1.pack(0x02, 10))
    assert frames[1] == (0x202, RPDO1.pack(0x0F, 20))
    _play(rig, {1: (State.QUICK_STOP_ACTIVE, 15), 2: (State.OPERATION_ENABLED, 20)})
    # While the drive brakes, the target follows the actual position.
    assert _exchange_frames(rig)[0] == (0x201, RPDO1.pack(0x02, 15))
    _play(rig, {1: (State.SWITCH_ON_DISABLED, 16), 2: (State.OPERATION_ENABLED, 20)})
    assert _exchange_frames(rig)[0] == (0x201, RPDO1.pack(0x00, 16))


def test_disable_steps_down(rig: Rig) -> None:
    master = rig.master
    _play(rig, {1: (State.OPERATION_ENABLED, 0), 2: (State.SWITCHED_ON, 0)})
    master.request_disable()
    frames = _exchange_frames(rig)
    assert frames[0] == (0x201, RPDO1.pack(0x07, 0))  # transition 5, disable operation
    assert frames[1] == (0x202, RPDO1.pack(0x06, 0))  # transition 6, shutdown


def test_fault_reset_is_a_bit7_edge_over_two_cycles(rig: Rig) -> None:
    master = rig.master
    _play(rig, {1: (State.FAULT, 300), 2: (State.OPERATION_ENABLED, 0)})
    master.request_enable()
    # A fault drops the enable request of that axis only.
    assert _exchange_frames(rig)[:2] == [
        (0x201, RPDO1.pack(0x00, 300)),
        (0x202, RPDO1.pack(0x0F, 0)),
    ]
    master.request_fault_reset(["X"])
    master.request_enable(["X"])
    assert _exchange_frames(rig)[0] == (0x201, RPDO1.pack(0x00, 300))
    assert _exchange_frames(rig)[0] == (0x201, RPDO1.pack(0x80, 300))
    _play(rig, {1: (State.SWITCH_ON_DISABLED, 301), 2: (State.OPERATION_ENABLED, 0)})
    # Reset done: the kept enable request continues from the actual position.
    assert _exchange_frames(rig)[0] == (0x201, RPDO1.pack(0x06, 301))


def test_unknown_axis_name(rig: Rig) -> None:
    with pytest.raises(ValueError, match="no axis named 'Z'"):
        rig.master.request_enable(["Z"])


def test_duplicate_nodes_are_rejected() -> None:
    network = canopen.Network()
    axes = [
        AxisSpec("X", 1, AxisScaling(1.0), 1.0, 20),
        AxisSpec("Y", 1, AxisScaling(1.0), 1.0, 20),
    ]
    with pytest.raises(ValueError, match="duplicate node_id 1"):
        Cia402Master(network, axes, MasterSettings(period_s=0.004))


def test_settings_validation() -> None:
    with pytest.raises(ValueError, match="period_s"):
        MasterSettings(period_s=0.0)
    with pytest.raises(ValueError, match="heartbeat_loss_periods"):
        MasterSettings(period_s=0.004, heartbeat_loss_periods=3.0)


# -- supervision rules (AxisSupervisor alone, with a fake clock) -------------------------------


class _Clock:
    def __init__(self) -> None:
        self.now_s = 100.0

    def __call__(self) -> float:
        return self.now_s


def _supervisor(clock: _Clock, syncs: SyncCounter) -> AxisSupervisor:
    limits = SupervisionLimits(
        heartbeat_loss_s=0.25,
        stale_feedback_cycles=3,
        following_error_window_mm=1.0,
        following_error_cycles=5,
    )
    return AxisSupervisor("Y", 2, AxisScaling(1000.0), limits, syncs, clock)


def _check(sup: AxisSupervisor, clock: _Clock, syncs: SyncCounter, **kw: object):
    sample = kw.pop("sample", TpdoSample(0x1237, 0, syncs.value))
    heartbeat = kw.pop("heartbeat", HeartbeatSample(0x05, clock.now_s))
    return sup.supervise(
        kw.pop("state", State.OPERATION_ENABLED),
        sample,
        heartbeat,
        kw.pop("emcy", None),
        kw.pop("following_error_mm", 0.0),
        clock.now_s,
    )


def test_heartbeat_loss_after_the_limit() -> None:
    clock, syncs = _Clock(), SyncCounter()
    sup = _supervisor(clock, syncs)
    beat = HeartbeatSample(0x05, clock.now_s)
    clock.now_s += 0.25
    assert _check(sup, clock, syncs, heartbeat=beat) is None
    clock.now_s += 0.001
    fault = _check(sup, clock, syncs, heartbeat=beat)
    assert fault is not None and fault.kind is FaultKind.HEARTBEAT_LOSS
    assert str(fault) == "axis Y (node 2): no heartbeat for 0.251 s (limit 0.250 s)"


def test_stale_feedback_after_n_cycles() -> None:
    clock, syncs = _Clock(), SyncCounter()
    sup = _supervisor(clock, syncs)
    sample = TpdoSample(0x1237, 0, 10)
    syncs.value = 12
    assert _check(sup, clock, syncs, sample=sample) is None
    syncs.value = 13
    fault = _check(sup, clock, syncs, sample=sample)
    assert fault is not None and fault.kind is FaultKind.STALE_FEEDBACK
    assert "no TPDO for 3 cycles" in fault.text


def test_following_error_needs_the_timeout() -> None:
    clock, syncs = _Clock(), SyncCounter()
    sup = _supervisor(clock, syncs)
    for _ in range(5):
        assert _check(sup, clock, syncs, following_error_mm=1.2) is None
    assert _check(sup, clock, syncs, following_error_mm=0.5) is None  # back inside: timer reset
    for _ in range(5):
        assert _check(sup, clock, syncs, following_error_mm=-1.2) is None
    fault = _check(sup, clock, syncs, following_error_mm=-1.2)
    assert fault is not None and fault.kind is FaultKind.FOLLOWING_ERROR


def test_emcy_upgrades_the_fault_state_and_is_acknowledged_by_reset() -> None:
    clock, syncs = _Clock(), SyncCounter()
    sup = _supervisor(clock, syncs)
    fault = _check(sup, clock, syncs, state=State.FAULT, sample=TpdoSample(0x0218, 0, 0))
    assert fault is not None and fault.kind is FaultKind.FAULT_STATE and fault.emcy_code is None
    emcy = EmcyRecord(0x8611, 0x20, clock.now_s, 1)
    sup.emcy = emcy
    fault = _check(sup, clock, syncs, state=State.FAULT, emcy=emcy)
    assert fault is not None and fault.kind is FaultKind.EMCY and fault.emcy_code == 0x8611
    assert str(fault) == "axis Y (node 2): EMCY 0x8611 following error (register 0x20)"
    sup.clear_fault()
    assert _check(sup, clock, syncs, state=State.SWITCH_ON_DISABLED, emcy=emcy) is None
    newer = EmcyRecord(0x4210, 0x08, clock.now_s, 2)
    fault = _check(sup, clock, syncs, state=State.SWITCH_ON_DISABLED, emcy=newer)
    assert fault is not None and fault.emcy_code == 0x4210


def test_nmt_state_other_than_operational() -> None:
    clock, syncs = _Clock(), SyncCounter()
    sup = _supervisor(clock, syncs)
    fault = _check(sup, clock, syncs, heartbeat=HeartbeatSample(0x7F, clock.now_s))
    assert fault is not None and fault.kind is FaultKind.NMT
    assert "PRE_OPERATIONAL" in fault.text


def test_drive_error_message_names_the_node() -> None:
    assert str(DriveError(3, "boom")) == "node 3: boom"
    assert math.isinf(AxisScaling(1.0).travel_max_mm)
