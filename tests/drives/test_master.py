"""Master unit tests: byte-exact RPDO and SYNC frames, 402 stepping, supervision and events.

The drives are booted as simulated drives, then silenced: from there a script plays their frames
(TPDO1, EMCY) on a bus of its own, and an independent listener records what the master sends.
"""

from __future__ import annotations

import struct
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass

import can
import pytest
from drive_loop import CycleLoop

from drives.bus import open_bus
from drives.cia402 import State, encode_statusword
from drives.master import (
    AxisSpec,
    BootPhase,
    Cia402Master,
    FaultKind,
    MasterSettings,
    TravelLimitError,
)
from drives.scaling import AxisScaling
from drives.sim import DriveModel, start_simulated_drives

TPDO1 = struct.Struct("<Hi")
PERIOD_S = 0.004


@dataclass
class Rig:
    master: Cia402Master
    script: can.BusABC
    listener: can.BusABC
    last_sync_s: float = 0.0
    """Bus timestamp of the last SYNC the master sent."""


def _settings(**overrides: object) -> MasterSettings:
    # A drive heartbeat of 10 s: the silenced drives are not lost while the script plays.
    values: dict[str, object] = {"period_s": PERIOD_S, "heartbeat_ms": 10_000}
    values.update(overrides)
    return MasterSettings(**values)  # type: ignore[arg-type]


def _axes() -> list[AxisSpec]:
    return [
        AxisSpec("X", 1, AxisScaling(1000.0, travel_min_mm=-100.0, travel_max_mm=100.0), 1.0, 20),
        AxisSpec("Y", 2, AxisScaling(1000.0, direction=-1), 1.0, 20),
    ]


@pytest.fixture
def rig() -> Iterator[Rig]:
    yield from _rig(_settings())


def _rig(settings: MasterSettings) -> Iterator[Rig]:
    channel = f"test-master-{uuid.uuid4().hex}"
    bus = open_bus("virtual", channel)
    drives = start_simulated_drives(
        "virtual", channel, [1, 2], model=DriveModel(sync_timeout_factor=1000.0)
    )
    script = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
    listener = can.Bus(interface="virtual", channel=channel)
    try:
        master = Cia402Master(bus, _axes(), settings)
        CycleLoop(master, PERIOD_S, realtime=False).boot()
        for drive in drives.drives.values():
            drive.stop_answering()
        while listener.recv(0.05) is not None:
            pass
        yield Rig(master, script, listener)
    finally:
        drives.close()
        for each in (bus, script, listener):
            each.shutdown()


def _play(rig: Rig, node_id: int, state: State, position: int, timestamp: float = 0.0) -> None:
    rig.script.send(
        can.Message(
            arbitration_id=0x180 + node_id,
            data=TPDO1.pack(encode_statusword(state), position),
            is_extended_id=False,
            timestamp=timestamp or time.time(),
        )
    )


def _cycle(rig: Rig, targets=None, play: dict[int, tuple[State, int]] | None = None):
    """Script frames, then the master's period: receive, update, write_targets, transmit.
    Returns the feedback and the frames the master sent."""
    for node_id, (state, position) in (play or {}).items():
        _play(rig, node_id, state, position)
    master = rig.master
    deadline = time.monotonic() + 2.0
    while True:  # until the scripted frames have reached the master's bus
        master.receive(time.monotonic())
        feedback = master.update(time.monotonic())
        if all(
            f.state is play[f.node_id][0] and f.position_counts == play[f.node_id][1]
            for f in feedback
            if f.node_id in (play or {})
        ):
            break
        assert time.monotonic() < deadline, f"scripted TPDOs not received: {feedback}"
        time.sleep(0.001)
    master.write_targets(targets)
    master.transmit_period()
    frames = []
    while len(frames) < 3:
        frame = rig.listener.recv(timeout=1.0)
        assert frame is not None, f"only {len(frames)} frames"
        if frame.arbitration_id in (0x201, 0x202, 0x080):
            frames.append((frame.arbitration_id, bytes(frame.data)))
        if frame.arbitration_id == 0x080:
            rig.last_sync_s = frame.timestamp
    return feedback, frames


def test_period_sends_the_rpdo_of_every_axis_then_one_sync(rig: Rig) -> None:
    _, frames = _cycle(
        rig, play={1: (State.SWITCH_ON_DISABLED, 1234), 2: (State.SWITCH_ON_DISABLED, -5678)}
    )
    # Not enabled: controlword 0x0000 (disable voltage), target = actual position.
    assert frames == [
        (0x201, bytes.fromhex("0000d2040000")),
        (0x202, bytes.fromhex("0000d2e9ffff")),
        (0x080, b""),
    ]


def test_enable_steps_one_transition_per_period_from_the_actual_position(rig: Rig) -> None:
    master = rig.master
    master.request_enable()
    for state, controlword in (
        (State.SWITCH_ON_DISABLED, 0x06),  # transition 2, shutdown
        (State.READY_TO_SWITCH_ON, 0x07),  # 3, switch on
        (State.SWITCHED_ON, 0x0F),  # 4, enable operation
    ):
        _, frames = _cycle(rig, [50.0, 50.0], play={1: (state, 1000), 2: (state, 2000)})
        assert frames[:2] == [
            (0x201, TPDO1.pack(controlword, 1000)),  # targets ignored until enabled
            (0x202, TPDO1.pack(controlword, 2000)),
        ]
    enabled = State.OPERATION_ENABLED
    _, frames = _cycle(rig, [50.0, 50.0], play={1: (enabled, 1000), 2: (enabled, 2000)})
    assert frames[:2] == [(0x201, TPDO1.pack(0x0F, 50_000)), (0x202, TPDO1.pack(0x0F, -50_000))]
    assert master.all_enabled and master.enabled_mask == (True, True)


def test_targets_keep_the_last_and_are_absolute(rig: Rig) -> None:
    rig.master.request_enable()
    enabled = {1: (State.OPERATION_ENABLED, 0), 2: (State.OPERATION_ENABLED, 0)}
    _, frames = _cycle(rig, [1.0005, -0.0004], play=enabled)
    assert frames[:2] == [(0x201, TPDO1.pack(0x0F, 1000)), (0x202, TPDO1.pack(0x0F, 0))]
    _, frames = _cycle(rig, [None, 2.0], play=enabled)
    assert frames[:2] == [(0x201, TPDO1.pack(0x0F, 1000)), (0x202, TPDO1.pack(0x0F, -2000))]
    feedback, frames = _cycle(rig, None, play=enabled)
    assert frames[1] == (0x202, TPDO1.pack(0x0F, -2000))
    assert feedback[1].commanded_mm == pytest.approx(2.0)


def test_write_targets_checks_everything_before_preparing(rig: Rig) -> None:
    master = rig.master
    master.request_enable()
    enabled = {1: (State.OPERATION_ENABLED, 0), 2: (State.OPERATION_ENABLED, 0)}
    _cycle(rig, [0.0, 0.0], play=enabled)
    with pytest.raises(TravelLimitError, match=r"node 1: axis X: target 150\.0 mm outside"):
        master.write_targets([150.0, 5.0])
    with pytest.raises(ValueError, match="1 positions for 2 axes"):
        master.write_targets([1.0])
    _, frames = _cycle(rig, None, play=enabled)
    assert frames[:2] == [(0x201, TPDO1.pack(0x0F, 0)), (0x202, TPDO1.pack(0x0F, 0))]


def test_quick_stop_then_disabled(rig: Rig) -> None:
    master = rig.master
    master.request_enable()
    _cycle(rig, play={1: (State.OPERATION_ENABLED, 10), 2: (State.OPERATION_ENABLED, 20)})
    master.request_quick_stop(["X"])
    _, frames = _cycle(
        rig, play={1: (State.OPERATION_ENABLED, 10), 2: (State.OPERATION_ENABLED, 20)}
    )
    assert frames[:2] == [(0x201, TPDO1.pack(0x02, 10)), (0x202, TPDO1.pack(0x0F, 20))]
    # While the drive brakes, the target follows the actual position.
    _, frames = _cycle(
        rig, play={1: (State.QUICK_STOP_ACTIVE, 15), 2: (State.OPERATION_ENABLED, 20)}
    )
    assert frames[0] == (0x201, TPDO1.pack(0x02, 15))
    _, frames = _cycle(
        rig, play={1: (State.SWITCH_ON_DISABLED, 16), 2: (State.OPERATION_ENABLED, 20)}
    )
    assert frames[0] == (0x201, TPDO1.pack(0x00, 16))


def test_disable_steps_down(rig: Rig) -> None:
    rig.master.request_disable()
    _, frames = _cycle(rig, play={1: (State.OPERATION_ENABLED, 0), 2: (State.SWITCHED_ON, 0)})
    assert frames[:2] == [
        (0x201, TPDO1.pack(0x07, 0)),  # transition 5, disable operation
        (0x202, TPDO1.pack(0x06, 0)),  # transition 6, shutdown
    ]


def test_fault_reset_is_a_bit7_edge_and_reports_its_outcome(rig: Rig) -> None:
    master = rig.master
    master.request_enable()
    feedback, frames = _cycle(rig, play={1: (State.FAULT, 300), 2: (State.OPERATION_ENABLED, 0)})
    # A fault drops the enable request of that axis only.
    assert frames[:2] == [(0x201, TPDO1.pack(0x00, 300)), (0x202, TPDO1.pack(0x0F, 0))]
    assert feedback[0].fault.kind is FaultKind.FAULT_STATE
    master.request_fault_reset(["X"])
    master.request_enable(["X"])
    faulted = {1: (State.FAULT, 300), 2: (State.OPERATION_ENABLED, 0)}
    feedback, frames = _cycle(rig, play=faulted)
    assert feedback[0].fault_reset_pending and frames[0] == (0x201, TPDO1.pack(0x00, 300))
    _, frames = _cycle(rig, play=faulted)
    assert frames[0] == (0x201, TPDO1.pack(0x80, 300))
    feedback, frames = _cycle(
        rig, play={1: (State.SWITCH_ON_DISABLED, 301), 2: (State.OPERATION_ENABLED, 0)}
    )
    assert not feedback[0].fault_reset_pending and feedback[0].fault is None
    # Reset done: the kept enable request continues from the actual position.
    assert frames[0] == (0x201, TPDO1.pack(0x06, 301))


def test_feedback_is_judged_against_the_target_of_the_sync_it_answered(rig: Rig) -> None:
    master = rig.master
    master.request_enable()
    enabled = {1: (State.OPERATION_ENABLED, 0), 2: (State.OPERATION_ENABLED, 0)}
    _cycle(rig, [0.0, 0.0], play=enabled)
    sync_stamps: dict[int, float] = {}
    for k in range(1, 11):
        time.sleep(0.001)  # SYNCs apart by more than a stamp's jitter, as on a bus
        _cycle(rig, [0.1 * k, 0.0])
        sync_stamps[master.syncs_sent] = rig.last_sync_s
    sent = master.syncs_sent
    # A TPDO that answered the SYNC sent 4 periods ago (it reaches us late): position 0.6 mm.
    # Stamped halfway to the next SYNC: 0.1 ms after it, with the loop's SYNCs 0.16-0.2 ms
    # apart, matched the next SYNC now and then under load.
    answered_s = 0.5 * (sync_stamps[sent - 4] + sync_stamps[sent - 3])
    _play(rig, 1, State.OPERATION_ENABLED, 600, timestamp=answered_s)
    _play(rig, 2, State.OPERATION_ENABLED, 0, timestamp=answered_s)
    deadline = time.monotonic() + 2.0
    while True:
        master.receive(time.monotonic())
        feedback = master.update(time.monotonic())
        if feedback[0].position_counts == 600:
            break
        assert time.monotonic() < deadline
    assert feedback[0].feedback_age_cycles == 4
    # It answered SYNC n - 4, so it follows the target sent with SYNC n - 5 (lag 1): 0.5 mm.
    assert feedback[0].target_mm == pytest.approx(0.5)
    assert feedback[0].following_error_mm == pytest.approx(0.1)


def test_every_emcy_is_an_event_and_the_error_reset_none(rig: Rig) -> None:
    master = rig.master
    for code, register in ((0x4210, 0x09), (0x0000, 0x00), (0x8611, 0x21)):
        rig.script.send(
            can.Message(
                arbitration_id=0x82,
                data=struct.pack("<HB5s", code, register, b""),
                is_extended_id=False,
                timestamp=time.time(),
            )
        )
    deadline = time.monotonic() + 2.0
    events = []
    while len(events) < 2:
        master.receive(time.monotonic())
        feedback = master.update(time.monotonic())
        events += master.take_fault_events()
        assert time.monotonic() < deadline, events
    assert [(e.axis, e.kind, e.emcy_code) for e in events] == [
        ("Y", FaultKind.EMCY, 0x4210),
        ("Y", FaultKind.EMCY, 0x8611),
    ]
    assert str(events[1]) == "axis Y (node 2): EMCY 0x8611 following error (register 0x21)"
    assert feedback[1].fault == events[0]  # the first stays the axis's cause
    assert feedback[1].error_code == 0x8611
    assert master.take_fault_events() == ()


def test_stale_feedback_after_the_limit_on_an_axis_asked_to_enable() -> None:
    for rig in _rig(_settings(stale_feedback_cycles=3)):
        master = rig.master
        _cycle(rig, play={1: (State.SWITCH_ON_DISABLED, 0), 2: (State.SWITCH_ON_DISABLED, 0)})
        age = master.update(time.monotonic())[0].feedback_age_cycles
        # Two SYNCs unanswered (the newest TPDO answers the SYNC three back): within the limit.
        for _ in range(3 - age):
            master.transmit_period()
        master.request_enable(["X"])
        feedback = master.update(time.monotonic())
        assert feedback[0].feedback_age_cycles == 3 and feedback[0].fault is None
        # The third: X, asked to enable, is faulted; Y, left disabled, follows no target, so its
        # late feedback is shown, not a fault.
        master.transmit_period()
        feedback = master.update(time.monotonic())
        assert feedback[0].fault.kind is FaultKind.STALE_FEEDBACK
        assert feedback[0].fault.text == "no TPDO for 3 cycles (limit 3)"
        assert feedback[1].feedback_age_cycles == 4 and feedback[1].fault is None


def test_unknown_axis_name_and_duplicate_nodes() -> None:
    bus = open_bus("virtual", f"test-master-{uuid.uuid4().hex}")
    try:
        master = Cia402Master(bus, _axes(), _settings())
        with pytest.raises(ValueError, match="no axis named 'Z'"):
            master.request_enable(["Z"])
        axes = [
            AxisSpec("X", 1, AxisScaling(1.0), 1.0, 20),
            AxisSpec("Y", 1, AxisScaling(1.0), 1.0, 20),
        ]
        with pytest.raises(ValueError, match="duplicate node_id 1"):
            Cia402Master(bus, axes, _settings())
        assert all(f.phase is BootPhase.WAITING for f in master.update(0.0))
    finally:
        bus.shutdown()


def test_settings_validation() -> None:
    with pytest.raises(ValueError, match="period_s"):
        MasterSettings(period_s=0.0)
    with pytest.raises(ValueError, match="heartbeat_loss_periods"):
        MasterSettings(period_s=0.004, heartbeat_loss_periods=3.0)
    with pytest.raises(ValueError, match="sdo_retries = -1"):
        MasterSettings(period_s=0.004, sdo_retries=-1)
    with pytest.raises(ValueError, match="axis X: feedback_lag_periods = -1, must be >= 0"):
        AxisSpec("X", 1, AxisScaling(1.0), 1.0, 20, feedback_lag_periods=-1)
