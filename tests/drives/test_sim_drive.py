"""The simulated CiA 402 drive as a master sees it: a plain canopen RemoteNode on a second
Network, both on one python-can ``virtual`` channel per test."""

from __future__ import annotations

import argparse
import itertools
import signal
import struct
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable

import can
import canopen
import pytest

from drives import emcy, objects
from drives.cia402 import State, controlword_toward_enabled, decode_statusword
from drives.objects import NmtState, build_drive_od
from drives.sim import DriveModel, DriveQuirks, start_simulated_drives
from drives.sim.quirks import OPTIONAL_OBJECTS
from drives.sim.service import add_arguments, quirk_arguments, quirks_from_arguments

NODE = 3
MASTER_NODE = 0x7F
CYCLE_US = 4000
#: Generous SYNC timeout for tests that pace SYNCs from a shared, noisy CPU.
PATIENT = DriveModel(sync_timeout_factor=100.0)
WINDOW_COUNTS = 5_000
#: Longest wait for a frame that is due now, s (the machine is shared; replies take < 1 ms).
REPLY_TIMEOUT_S = 2.0


def _wait_for(predicate: Callable[[], bool], timeout_s: float = REPLY_TIMEOUT_S) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.002)
    return predicate()


class Bench:
    """A master Network with a RemoteNode and a simulated drive set on one virtual channel."""

    def __init__(
        self,
        model: DriveModel = PATIENT,
        quirks: DriveQuirks = DriveQuirks(),  # noqa: B008  (frozen)
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        channel = f"sim-drive-{uuid.uuid4().hex}"
        self.master = canopen.Network()
        self.master.NOTIFIER_CYCLE = 0.05
        self.master.NOTIFIER_SHUTDOWN_TIMEOUT = 0.5
        self.master.connect(interface="virtual", channel=channel, receive_own_messages=False)
        self.frames: list[can.Message] = []
        self.master.notifier.add_listener(self.frames.append)
        self.drive_set = start_simulated_drives(
            "virtual", channel, [NODE], model=model, quirks={NODE: quirks}, clock=clock
        )
        self.drive = self.drive_set.drives[NODE]
        self.node = self.master.add_node(NODE, build_drive_od(NODE))
        self.tpdo1: list[tuple[int, int]] = []
        self.tpdo2: list[tuple[int, int]] = []
        self._tpdo1_seen = threading.Event()
        self._tpdo2_seen = threading.Event()

    def close(self) -> None:
        self.drive_set.close()
        self.master.disconnect()

    def frames_with_id(self, can_id: int) -> list[can.Message]:
        return [frame for frame in list(self.frames) if frame.arbitration_id == can_id]

    def wait_emcy(self, code: int) -> bool:
        return _wait_for(lambda: any(error.code == code for error in self.node.emcy.log))

    def configure_pdos(self) -> None:
        """The CSP set-up of a master: cycle, window, mode, RPDO1 6040/607A, TPDO1 6041/6064,
        TPDO2 6061/60F4, all synchronous (type 1), written by SDO in PRE-OPERATIONAL."""
        sdo = self.node.sdo
        sdo[objects.COMM_CYCLE_PERIOD].raw = CYCLE_US
        sdo[objects.FOLLOWING_ERROR_WINDOW].raw = WINDOW_COUNTS
        sdo[objects.MODES_OF_OPERATION].raw = objects.MODE_CSP
        self.node.rpdo.read()
        self.node.tpdo.read()
        for pdo_map, layout in (
            (self.node.rpdo[1], objects.CSP_RPDO1),
            (self.node.tpdo[1], objects.CSP_TPDO1),
            (self.node.tpdo[2], objects.CSP_TPDO2),
        ):
            pdo_map.clear()
            for index, subindex in layout:
                pdo_map.add_variable(index, subindex)
            pdo_map.trans_type = 1
            pdo_map.enabled = True
        self.node.rpdo.save()
        self.node.tpdo.save()
        self.node.tpdo[1].add_callback(self._on_tpdo1)
        self.node.tpdo[2].add_callback(self._on_tpdo2)

    def _on_tpdo1(self, pdo_map: canopen.pdo.PdoMap) -> None:
        self.tpdo1.append((pdo_map[objects.STATUSWORD].raw, pdo_map[objects.POSITION_ACTUAL].raw))
        self._tpdo1_seen.set()

    def _on_tpdo2(self, pdo_map: canopen.pdo.PdoMap) -> None:
        self.tpdo2.append(
            (
                pdo_map[objects.MODES_OF_OPERATION_DISPLAY].raw,
                pdo_map[objects.FOLLOWING_ERROR_ACTUAL].raw,
            )
        )
        self._tpdo2_seen.set()

    def start(self) -> None:
        self.node.nmt.send_command(objects.NmtCommand.START)
        assert _wait_for(lambda: self.drive.nmt_state is NmtState.OPERATIONAL)

    def cycle(self, controlword: int, target_counts: int) -> tuple[int, int]:
        """One master cycle: RPDO, SYNC, then wait for both TPDOs; return (statusword, 6064)."""
        rpdo = self.node.rpdo[1]
        rpdo[objects.CONTROLWORD].raw = controlword
        rpdo[objects.TARGET_POSITION].raw = target_counts
        self._tpdo1_seen.clear()
        self._tpdo2_seen.clear()
        rpdo.transmit()
        self.master.sync.transmit()
        assert self._tpdo1_seen.wait(REPLY_TIMEOUT_S), "no TPDO1 after SYNC"
        assert self._tpdo2_seen.wait(REPLY_TIMEOUT_S), "no TPDO2 after SYNC"
        return self.tpdo1[-1]

    def enable(self) -> int:
        """Run cycles with the controlword toward OPERATION ENABLED; return the cycles used."""
        target = self.drive.position_actual_counts
        statusword = self.cycle(0x00, target)[0]
        for cycles in range(1, 10):
            state = decode_statusword(statusword)
            if state is State.OPERATION_ENABLED:
                return cycles
            statusword = self.cycle(controlword_toward_enabled(state), target)[0]
        raise AssertionError(f"not enabled, statusword 0x{statusword:04X}")


@pytest.fixture
def bench():
    bench = Bench()
    yield bench
    bench.close()


@pytest.fixture
def running(bench):
    """A drive configured for CSP, OPERATIONAL and OPERATION ENABLED."""
    bench.configure_pdos()
    bench.start()
    bench.enable()
    return bench


def test_boot_up_message_then_pre_operational(bench):
    assert _wait_for(lambda: bench.frames_with_id(0x700 + NODE))
    assert bytes(bench.frames_with_id(0x700 + NODE)[0].data) == b"\x00"
    assert bench.drive.nmt_state is NmtState.PRE_OPERATIONAL
    assert bench.drive.state is State.SWITCH_ON_DISABLED


def test_boot_delay_holds_back_boot_up_and_sdo():
    bench = Bench(quirks=DriveQuirks(boot_delay_s=0.3))
    try:
        bench.node.sdo.RESPONSE_TIMEOUT = 0.05
        with pytest.raises(canopen.SdoCommunicationError):
            bench.node.sdo[objects.DEVICE_TYPE].raw  # noqa: B018
        assert not bench.frames_with_id(0x700 + NODE)
        bench.node.nmt.wait_for_bootup(REPLY_TIMEOUT_S)
        bench.node.sdo.RESPONSE_TIMEOUT = REPLY_TIMEOUT_S
        assert bench.node.sdo[objects.DEVICE_TYPE].raw == objects.DEVICE_TYPE_SERVO_402
    finally:
        bench.close()


def test_sdo_read_and_write(bench):
    sdo = bench.node.sdo
    assert sdo[objects.DEVICE_TYPE].raw == objects.DEVICE_TYPE_SERVO_402
    assert decode_statusword(sdo[objects.STATUSWORD].raw) is State.SWITCH_ON_DISABLED
    sdo[objects.FOLLOWING_ERROR_WINDOW].raw = 1234
    assert sdo[objects.FOLLOWING_ERROR_WINDOW].raw == 1234
    sdo[objects.INTERPOLATION_PERIOD][2].raw = -4
    assert sdo[objects.INTERPOLATION_PERIOD][2].raw == -4
    assert sdo[objects.IDENTITY][4].raw == NODE


@pytest.mark.parametrize(
    ("index", "subindex", "value", "abort_code"),
    [
        (objects.STATUSWORD, 0, b"\x00\x00", 0x0601_0002),  # read-only
        (0x2000, 0, b"\x00", 0x0602_0000),  # no such object
        (objects.IDENTITY, 9, b"\x00\x00\x00\x00", 0x0609_0011),  # no such sub-index
        (objects.CONTROLWORD, 0, b"\x00\x00\x00\x00", 0x0607_0010),  # length
        (objects.QUICK_STOP_OPTION, 0, b"\x09\x00", 0x0609_0030),  # value range
        (objects.MODES_OF_OPERATION, 0, b"\x01", 0x0609_0030),  # PP: not supported
    ],
)
def test_sdo_write_aborts(bench, index, subindex, value, abort_code):
    with pytest.raises(canopen.SdoAbortedError) as error:
        bench.node.sdo.download(index, subindex, value)
    assert error.value.code == abort_code


def test_sdo_read_of_missing_object_aborts(bench):
    with pytest.raises(canopen.SdoAbortedError) as error:
        bench.node.sdo.upload(0x2000, 0)
    assert error.value.code == 0x0602_0000


def test_mapping_a_valid_pdo_aborts(bench):
    bench.configure_pdos()
    with pytest.raises(canopen.SdoAbortedError) as error:
        bench.node.sdo[objects.RPDO_MAP][1].raw = objects.mapping_entry(objects.CONTROLWORD, 0, 16)
    assert error.value.code == 0x0800_0022


def test_mapping_a_non_mappable_object_aborts(bench):
    sdo = bench.node.sdo
    sdo[objects.TPDO_MAP + 2][0].raw = 0
    with pytest.raises(canopen.SdoAbortedError) as error:
        sdo[objects.TPDO_MAP + 2][1].raw = objects.mapping_entry(objects.QUICK_STOP_OPTION, 0, 16)
    assert error.value.code == 0x0604_0041


def test_no_pdos_in_pre_operational(bench):
    bench.configure_pdos()
    for _ in range(5):
        bench.master.sync.transmit()
    bench.node.sdo[objects.DEVICE_TYPE].raw  # noqa: B018  (the drive has handled the SYNCs)
    time.sleep(0.05)
    assert not bench.frames_with_id(objects.tpdo_cob_id(1, NODE))
    assert not bench.tpdo1


def test_tpdo_on_each_sync_in_operational(bench):
    bench.configure_pdos()
    bench.start()
    for _ in range(10):
        bench.cycle(0x00, 0)
    assert len(bench.frames_with_id(objects.tpdo_cob_id(1, NODE))) == 10
    assert len(bench.frames_with_id(objects.tpdo_cob_id(2, NODE))) == 10


def test_stopped_node_sends_no_pdo_and_no_sdo(bench):
    bench.configure_pdos()
    bench.start()
    bench.node.nmt.send_command(objects.NmtCommand.STOP)
    assert _wait_for(lambda: bench.drive.nmt_state is NmtState.STOPPED)
    bench.master.sync.transmit()
    bench.node.sdo.RESPONSE_TIMEOUT = 0.05
    with pytest.raises(canopen.SdoCommunicationError):
        bench.node.sdo[objects.DEVICE_TYPE].raw  # noqa: B018
    assert not bench.frames_with_id(objects.tpdo_cob_id(1, NODE))


def test_enable_sequence_by_rpdo_and_sync(bench):
    bench.configure_pdos()
    bench.start()
    cycles = bench.enable()
    assert cycles == 4  # shutdown (2), switch on (3), enable operation (4), seen
    statusword, _ = bench.tpdo1[-1]
    assert statusword & 0x6F == 0x27
    assert statusword & 0x1000  # CSP: following the target
    assert bench.tpdo2[-1][0] == objects.MODE_CSP
    assert bench.drive.state is State.OPERATION_ENABLED


def test_rpdo_is_applied_at_sync_not_on_reception(running):
    rpdo = running.node.rpdo[1]
    rpdo[objects.CONTROLWORD].raw = 0x0F
    rpdo[objects.TARGET_POSITION].raw = 777
    rpdo.transmit()
    running.node.sdo[objects.DEVICE_TYPE].raw  # noqa: B018  (the RPDO has been received)
    assert running.drive.target_counts == 0
    running.cycle(0x0F, 777)
    assert running.drive.target_counts == 777


def test_csp_follows_a_ramped_target(running):
    step_counts = 200  # 50 000 counts/s at 4 ms
    target = 0
    largest_error = 0
    for _ in range(100):
        target += step_counts
        running.cycle(0x0F, target)
        largest_error = max(largest_error, abs(running.tpdo2[-1][1]))
    for _ in range(3):
        statusword, position = running.cycle(0x0F, target)
    assert position == target
    assert largest_error < WINDOW_COUNTS
    assert decode_statusword(statusword) is State.OPERATION_ENABLED
    assert not running.node.emcy.log


def test_target_step_beyond_the_window_faults_with_emcy_8611(running):
    target = running.drive.position_actual_counts + 20 * WINDOW_COUNTS
    states = []
    for _ in range(15):
        states.append(decode_statusword(running.cycle(0x0F, target)[0]))
    assert running.wait_emcy(emcy.EMCY_FOLLOWING_ERROR)
    assert State.FAULT_REACTION_ACTIVE in states
    assert states[-1] is State.FAULT
    assert states.index(State.FAULT_REACTION_ACTIVE) < states.index(State.FAULT)
    assert running.node.sdo[objects.ERROR_CODE].raw == emcy.EMCY_FOLLOWING_ERROR
    assert running.node.sdo[objects.ERROR_REGISTER].raw & emcy.ERROR_REGISTER_GENERIC


def test_injected_following_error_faults(running):
    running.drive.inject_following_error()
    for _ in range(15):
        running.cycle(0x0F, 0)
    assert running.wait_emcy(emcy.EMCY_FOLLOWING_ERROR)
    assert running.drive.state is State.FAULT


def test_injected_fault_sends_its_emcy_and_ends_in_fault(running):
    running.drive.inject_fault(emcy.EMCY_EXCESS_TEMPERATURE_DEVICE)
    states = [decode_statusword(running.cycle(0x0F, 0)[0]) for _ in range(5)]
    assert running.wait_emcy(emcy.EMCY_EXCESS_TEMPERATURE_DEVICE)
    assert states[0] is State.FAULT_REACTION_ACTIVE
    assert states[-1] is State.FAULT
    register = running.node.sdo[objects.ERROR_REGISTER].raw
    assert register & emcy.ERROR_REGISTER_TEMPERATURE
    assert running.node.sdo[objects.PREDEFINED_ERROR_FIELD][1].raw == 0x4210


def test_fault_reset_only_on_a_rising_edge_of_bit_7(running):
    running.drive.inject_fault()
    for _ in range(5):
        running.cycle(0x80, 0)  # bit 7 already high when the fault came: no edge
    assert running.drive.state is State.FAULT
    running.cycle(0x00, 0)
    assert running.drive.state is State.FAULT
    statusword, _ = running.cycle(0x80, 0)
    assert decode_statusword(statusword) is State.SWITCH_ON_DISABLED
    assert running.wait_emcy(emcy.EMCY_ERROR_RESET)
    assert running.node.sdo[objects.ERROR_CODE].raw == 0
    assert running.enable() > 0


def test_quick_stop_ramps_down_then_switch_on_disabled(running):
    target = 0
    for _ in range(30):  # reach 100 000 counts/s
        target += 400
        running.cycle(0x0F, target)
    states = [decode_statusword(running.cycle(0x02, target)[0]) for _ in range(20)]
    assert states[0] is State.QUICK_STOP_ACTIVE
    assert states[-1] is State.SWITCH_ON_DISABLED
    assert running.drive.position_actual_counts > target - 400  # braked beyond the last demand


def test_quick_stop_option_6_stays_and_allows_transition_16(bench):
    bench.configure_pdos()
    bench.node.sdo[objects.QUICK_STOP_OPTION].raw = 6
    bench.start()
    bench.enable()
    states = [decode_statusword(bench.cycle(0x02, 0)[0]) for _ in range(5)]
    assert states == [State.QUICK_STOP_ACTIVE] * 5
    assert decode_statusword(bench.cycle(0x0F, 0)[0]) is State.OPERATION_ENABLED


def test_stop_answering_silences_heartbeat_and_sdo(bench):
    heartbeat_id = 0x700 + NODE
    bench.node.sdo[objects.PRODUCER_HEARTBEAT].raw = 10
    assert _wait_for(lambda: len(bench.frames_with_id(heartbeat_id)) >= 3)
    bench.drive.stop_answering()
    time.sleep(0.02)
    count = len(bench.frames_with_id(heartbeat_id))
    bench.node.sdo.RESPONSE_TIMEOUT = 0.05
    with pytest.raises(canopen.SdoCommunicationError):
        bench.node.sdo[objects.DEVICE_TYPE].raw  # noqa: B018
    time.sleep(0.1)
    assert len(bench.frames_with_id(heartbeat_id)) == count
    bench.drive.resume_answering()
    assert _wait_for(lambda: len(bench.frames_with_id(heartbeat_id)) > count)


def test_heartbeat_producer_period_and_state(bench):
    heartbeat_id = 0x700 + NODE
    bench.node.sdo[objects.PRODUCER_HEARTBEAT].raw = 20
    time.sleep(0.3)
    bench.start()
    time.sleep(0.1)
    frames = bench.frames_with_id(heartbeat_id)[1:]  # after the boot-up message
    pre_operational = [frame for frame in frames if bytes(frame.data) == b"\x7f"]
    assert len(pre_operational) >= 10
    assert bytes(frames[-1].data) == b"\x05"  # sent at once on the state change, then periodic
    stamps = [frame.timestamp for frame in pre_operational]
    intervals = [b - a for a, b in itertools.pairwise(stamps)]
    mean_interval_s = sum(intervals) / len(intervals)
    assert 0.016 < mean_interval_s < 0.030


def _enable_by_sdo(bench: Bench, cycle_us: int) -> None:
    """Cycle period 0x1006, CSP and the controlwords to OPERATION ENABLED, all by SDO."""
    bench.node.sdo[objects.COMM_CYCLE_PERIOD].raw = cycle_us
    bench.node.sdo[objects.MODES_OF_OPERATION].raw = objects.MODE_CSP
    for controlword in (0x06, 0x07, 0x0F):
        bench.node.sdo[objects.CONTROLWORD].raw = controlword


def test_sync_loss_faults_with_emcy_8100():
    bench = Bench(model=DriveModel(sync_timeout_factor=2.0))
    try:
        _enable_by_sdo(bench, 20_000)  # 20 ms: 40 ms SYNC timeout
        bench.master.sync.transmit()
        assert _wait_for(lambda: bench.drive.state is State.OPERATION_ENABLED)
        assert bench.wait_emcy(emcy.EMCY_COMMUNICATION)
        assert _wait_for(lambda: bench.drive.state is State.FAULT)
        assert bench.drive.error_code == emcy.EMCY_COMMUNICATION
    finally:
        bench.close()


class SteppedClock:
    """A monotonic clock that moves only when the test moves it, s."""

    def __init__(self) -> None:
        self.now_s = 1000.0

    def __call__(self) -> float:
        return self.now_s


#: 0x1006 of the stepped-clock tests, s; their SYNC timeout is 2 periods.
STEPPED_PERIOD_S = 0.02


@pytest.fixture
def stepped():
    """A drive OPERATION ENABLED on a stepped clock, its SYNC supervision started."""
    clock = SteppedClock()
    bench = Bench(model=DriveModel(sync_timeout_factor=2.0), clock=clock)
    try:
        _enable_by_sdo(bench, int(STEPPED_PERIOD_S * 1e6))
        assert bench.drive.state is State.OPERATION_ENABLED
        _sync(bench)
        yield bench, clock
    finally:
        bench.close()


def _sync(bench: Bench) -> None:
    """Send a SYNC and return once the drive has taken it (an SDO answer comes after it)."""
    bench.master.sync.transmit()
    bench.node.sdo.upload(objects.STATUSWORD, 0)


def _advance(bench: Bench, clock: SteppedClock, periods: float) -> None:
    """Move the clock and let the watchdog run on it (it waits on real time otherwise)."""
    clock.now_s += periods * STEPPED_PERIOD_S
    bench.drive._wake.set()
    time.sleep(0.1)


def test_a_watchdog_stalled_with_its_process_gives_waiting_syncs_a_period(stepped):
    """A watchdog run more than a period after the SYNC limit was stalled with its process
    (drives simulated in the master's process stall with it): a SYNC that waited in the receive
    thread meanwhile keeps the drive enabled. On time, the same silence faults at once."""
    bench, clock = stepped
    _advance(bench, clock, 10)  # a stall: 8 periods past the 2-period limit
    assert bench.drive.state is State.OPERATION_ENABLED
    _sync(bench)
    _advance(bench, clock, 1)
    assert bench.drive.state is State.OPERATION_ENABLED
    _advance(bench, clock, 1.5)  # half a period past the limit: the watchdog is on time
    assert bench.wait_emcy(emcy.EMCY_COMMUNICATION)
    assert bench.drive.error_code == emcy.EMCY_COMMUNICATION


def test_a_stalled_watchdog_faults_when_no_sync_follows_within_a_period(stepped):
    bench, clock = stepped
    _advance(bench, clock, 10)
    assert bench.drive.state is State.OPERATION_ENABLED
    _advance(bench, clock, 1)
    assert bench.wait_emcy(emcy.EMCY_COMMUNICATION)
    assert bench.drive.error_code == emcy.EMCY_COMMUNICATION


def test_master_heartbeat_loss_sends_8130_and_faults(bench):
    running = bench
    running.configure_pdos()
    running.node.sdo[objects.CONSUMER_HEARTBEAT][1].raw = MASTER_NODE << 16 | 50
    running.start()
    running.enable()
    producer = running.master.send_periodic(0x700 + MASTER_NODE, b"\x05", 0.01)
    time.sleep(0.05)
    running.cycle(0x0F, running.drive.position_actual_counts)
    producer.stop()
    assert running.wait_emcy(emcy.EMCY_HEARTBEAT)
    assert _wait_for(lambda: running.drive.state is State.FAULT)


def test_leaving_operational_applies_abort_connection_option(running):
    running.node.nmt.send_command(objects.NmtCommand.ENTER_PRE_OPERATIONAL)
    assert running.wait_emcy(emcy.EMCY_COMMUNICATION)  # 0x6007 = 1: fault
    assert _wait_for(lambda: running.drive.state is State.FAULT)


def test_reset_communication_reboots_and_reloads_pdo_parameters(bench):
    bench.configure_pdos()
    bench.node.sdo[objects.FOLLOWING_ERROR_WINDOW].raw = 777
    bench.frames.clear()
    bench.node.nmt.send_command(objects.NmtCommand.RESET_COMMUNICATION)
    assert _wait_for(lambda: bench.frames_with_id(0x700 + NODE))
    assert bytes(bench.frames_with_id(0x700 + NODE)[0].data) == b"\x00"
    assert _wait_for(lambda: bench.drive.nmt_state is NmtState.PRE_OPERATIONAL)
    assert bench.node.sdo[objects.TPDO_COMM][1].raw & objects.COB_ID_INVALID
    assert bench.node.sdo[objects.COMM_CYCLE_PERIOD].raw == 0
    assert bench.node.sdo[objects.FOLLOWING_ERROR_WINDOW].raw == 777  # application object


def test_reset_node_reloads_application_parameters(bench):
    bench.node.sdo[objects.FOLLOWING_ERROR_WINDOW].raw = 777
    bench.node.nmt.send_command(objects.NmtCommand.RESET_NODE)
    bench.node.nmt.wait_for_bootup(REPLY_TIMEOUT_S)
    default = build_drive_od(NODE)[objects.FOLLOWING_ERROR_WINDOW].default
    assert bench.node.sdo[objects.FOLLOWING_ERROR_WINDOW].raw == default


def test_mode_display_follows_mode(bench):
    assert bench.node.sdo[objects.MODES_OF_OPERATION_DISPLAY].raw == objects.MODE_NONE
    bench.node.sdo[objects.MODES_OF_OPERATION].raw = objects.MODE_CSP
    assert bench.node.sdo[objects.MODES_OF_OPERATION_DISPLAY].raw == objects.MODE_CSP


def test_several_drives_share_one_network():
    channel = f"sim-drive-{uuid.uuid4().hex}"
    master = canopen.Network()
    master.NOTIFIER_CYCLE = 0.05
    master.connect(interface="virtual", channel=channel, receive_own_messages=False)
    drive_set = start_simulated_drives("virtual", channel, [1, 2, 3], model=PATIENT)
    try:
        for node_id in (1, 2, 3):
            node = master.add_node(node_id, build_drive_od(node_id))
            assert node.sdo[objects.IDENTITY][4].raw == node_id
        master.nmt.send_command(objects.NmtCommand.START)
        assert _wait_for(
            lambda: all(d.nmt_state is NmtState.OPERATIONAL for d in drive_set.drives.values())
        )
    finally:
        drive_set.close()
        master.disconnect()


def _delivered_ids(bench: Bench) -> set[int]:
    """The identifiers the drives' bus lets through (None: every frame)."""
    filters = bench.drive_set.network.bus.filters
    assert filters is not None, "the drives' bus receives every frame"
    return {entry["can_id"] for entry in filters}


def test_bus_delivers_only_what_the_drive_subscribed_to(bench):
    # NMT, SYNC, SDO request, node guarding request, and the LSS response that canopen's
    # Network subscribes itself.
    booted = {0x000, 0x080, 0x600 + NODE, 0x700 + NODE, 0x7E4}
    assert _delivered_ids(bench) == booted
    bench.configure_pdos()
    assert _delivered_ids(bench) == booted | {0x200 + NODE}  # RPDO1
    bench.node.sdo[objects.CONSUMER_HEARTBEAT][1].raw = MASTER_NODE << 16 | 250
    assert _delivered_ids(bench) == booted | {0x200 + NODE, 0x700 + MASTER_NODE}
    bench.node.sdo[objects.COB_ID_SYNC].raw = 0x81
    assert 0x081 in _delivered_ids(bench) and 0x080 not in _delivered_ids(bench)


def test_frames_for_other_nodes_never_reach_the_drive(running):
    """Another node's RPDO1 and TPDO1 on the bus: the drive neither receives nor acts on them."""
    received: list[int] = []
    running.drive_set.network.notifier.add_listener(
        lambda message: received.append(message.arbitration_id)
    )
    other = NODE + 1
    running.master.send_message(0x200 + other, bytes(6))
    running.master.send_message(0x180 + other, bytes(6))
    running.cycle(0x0F, running.drive.position_actual_counts)
    assert 0x200 + NODE in received and 0x080 in received
    assert not {0x200 + other, 0x180 + other} & set(received)


def test_power_cycle_reboots(bench):
    bench.node.sdo[objects.FOLLOWING_ERROR_WINDOW].raw = 777
    bench.drive.stop()
    assert bench.drive.nmt_state is NmtState.INITIALISING
    bench.frames.clear()
    bench.drive.start()
    assert _wait_for(lambda: bench.frames_with_id(0x700 + NODE))
    assert bench.node.sdo[objects.FOLLOWING_ERROR_WINDOW].raw != 777


def test_sim_drive_process_runs_until_sigterm():
    channel = f"sim-drive-{uuid.uuid4().hex}"
    command = ["-m", "drives.sim", "--node", "5", "--interface", "virtual", "--channel", channel]
    process = subprocess.Popen(
        [sys.executable, *command],
        stderr=subprocess.PIPE,
        text=True,
    )
    watchdog = threading.Timer(30.0, process.kill)  # never hang the suite on a silent child
    watchdog.start()
    try:
        running = False
        for line in process.stderr:
            if "simulated drive node 5 on virtual" in line:
                running = True
                break
        assert running, "the process ended without running the drive"
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=10) == 0
    finally:
        watchdog.cancel()
        if process.poll() is None:
            process.kill()
            process.wait()


# -- quirks: drives of other vendors ---------------------------------------------------------


def _quirky(**quirks: object) -> Bench:
    return Bench(quirks=DriveQuirks(**quirks))  # type: ignore[arg-type]


@pytest.mark.parametrize("index", sorted(OPTIONAL_OBJECTS))
def test_no_optional_objects_aborts_with_object_does_not_exist(index):
    bench = _quirky(no_optional_objects=True)
    try:
        subindex = 1 if index == objects.CONSUMER_HEARTBEAT else 0
        with pytest.raises(canopen.SdoAbortedError) as error:
            bench.node.sdo.upload(index, subindex)
        assert error.value.code == 0x0602_0000
        assert bench.node.sdo[objects.INTERPOLATION_PERIOD][1].raw == 4  # the rest is there
    finally:
        bench.close()


def test_fixed_pdo_mapping_is_read_only_and_sent_in_its_layout():
    bench = _quirky(fixed_pdo_mapping=True)
    try:
        sdo = bench.node.sdo
        with pytest.raises(canopen.SdoAbortedError) as error:
            sdo[objects.TPDO_MAP][0].raw = 0
        assert error.value.code == 0x0601_0002
        assert sdo[objects.TPDO_COMM][1].raw & 0x7FF == 0x280 + NODE
        bench.node.nmt.send_command(objects.NmtCommand.START)
        assert _wait_for(lambda: bench.drive.nmt_state is NmtState.OPERATIONAL)
        bench.master.sync.transmit()
        assert _wait_for(lambda: bench.frames_with_id(0x280 + NODE))
        frame = bench.frames_with_id(0x280 + NODE)[0]
        position, statusword = struct.unpack("<iH", bytes(frame.data))
        assert statusword == bench.drive.statusword and position == 0
        assert bench.frames_with_id(0x380 + NODE)  # TPDO2: 0x60F4, 0x603F
    finally:
        bench.close()


@pytest.mark.parametrize(
    ("subindex", "value", "abort_code"),
    [(1, 21, 0x0609_0031), (1, 0, 0x0609_0032), (2, -4, 0x0609_0030)],
)
def test_interpolation_in_ms_only(subindex, value, abort_code):
    bench = _quirky(interpolation_ms_only=True)
    try:
        period = bench.node.sdo[objects.INTERPOLATION_PERIOD]
        with pytest.raises(canopen.SdoAbortedError) as error:
            period[subindex].raw = value
        assert error.value.code == abort_code
        period[1].raw = 20
        period[2].raw = -3
        assert (period[1].raw, period[2].raw) == (20, -3)
    finally:
        bench.close()


def test_fault_at_power_on_until_a_fault_reset():
    bench = _quirky(fault_at_power_on=True)
    try:
        assert _wait_for(lambda: bench.drive.state is State.FAULT)
        assert bench.node.sdo[objects.ERROR_CODE].raw == emcy.EMCY_HEARTBEAT
        bench.node.sdo[objects.CONTROLWORD].raw = 0x00
        bench.node.sdo[objects.CONTROLWORD].raw = 0x80
        assert bench.drive.state is State.SWITCH_ON_DISABLED
    finally:
        bench.close()


def _guard(bench: Bench) -> int:
    """One node guarding request; return the answer byte."""
    count = len(bench.frames_with_id(0x700 + NODE))
    bench.master.bus.send(
        can.Message(arbitration_id=0x700 + NODE, is_remote_frame=True, dlc=1, is_extended_id=False)
    )
    assert _wait_for(lambda: len(bench.frames_with_id(0x700 + NODE)) > count)
    return bench.frames_with_id(0x700 + NODE)[-1].data[0]


def test_guarding_only_answers_node_guarding_with_a_toggle_and_guards_its_life():
    bench = _quirky(guarding_only=True)
    try:
        with pytest.raises(canopen.SdoAbortedError):
            bench.node.sdo.upload(objects.PRODUCER_HEARTBEAT, 0)
        assert _wait_for(lambda: bench.frames_with_id(0x700 + NODE))  # boot-up
        answers = [_guard(bench) for _ in range(3)]
        assert answers == [0x7F, 0xFF, 0x7F]  # PRE-OPERATIONAL, toggling
        bench.node.sdo[objects.GUARD_TIME].raw = 20
        bench.node.sdo[objects.LIFE_TIME_FACTOR].raw = 3
        _guard(bench)
        assert bench.wait_emcy(emcy.EMCY_HEARTBEAT)  # not guarded for 60 ms
    finally:
        bench.close()


def test_a_drive_with_heartbeat_on_does_not_answer_guarding(bench):
    bench.node.sdo[objects.PRODUCER_HEARTBEAT].raw = 1000
    # Its first heartbeat goes out at once; the next one is a second away.
    assert _wait_for(lambda: len(bench.frames_with_id(0x700 + NODE)) >= 2)  # boot-up, heartbeat
    bench.frames.clear()
    bench.master.bus.send(
        can.Message(arbitration_id=0x700 + NODE, is_remote_frame=True, dlc=1, is_extended_id=False)
    )
    time.sleep(0.1)
    assert [m for m in bench.frames_with_id(0x700 + NODE) if not m.is_remote_frame] == []


def test_slow_sdo_answers_after_the_delay():
    bench = _quirky(sdo_delay_s=(0.15, 0.2))
    try:
        bench.node.sdo.RESPONSE_TIMEOUT = 1.0
        started = time.monotonic()
        assert bench.node.sdo[objects.DEVICE_TYPE].raw == objects.DEVICE_TYPE_SERVO_402
        assert 0.15 <= time.monotonic() - started < 0.6
    finally:
        bench.close()


def test_late_tpdos_carry_the_state_of_an_earlier_sync():
    bench = _quirky(late_tpdo_periods=2)
    try:
        bench.configure_pdos()
        bench.start()
        for controlword in (0x06, 0x07, 0x0F, 0x0F, 0x0F):
            bench.node.rpdo[1][objects.CONTROLWORD].raw = controlword
            bench.node.rpdo[1][objects.TARGET_POSITION].raw = 0
            bench.node.rpdo[1].transmit()
            bench.master.sync.transmit()
            bench.node.sdo.upload(objects.STATUSWORD, 0)  # the SYNC has been handled
        assert bench.drive.state is State.OPERATION_ENABLED
        _wait_for(lambda: len(bench.tpdo1) >= 3)
        states = [decode_statusword(sw) for sw, _ in bench.tpdo1]
        # Five SYNCs, three TPDOs: the first two SYNCs' answers went out at SYNCs 3 and 4.
        assert states[:2] == [State.READY_TO_SWITCH_ON, State.SWITCHED_ON]
    finally:
        bench.close()


def test_sync_of_the_wrong_length_is_not_used_and_raises_8240(bench):
    bench.configure_pdos()
    bench.start()
    bench.master.send_message(0x080, b"\x01")  # a counter the drive was not told of (0x1019 = 0)
    assert bench.wait_emcy(emcy.EMCY_SYNC_LENGTH)
    assert not bench.tpdo1
    with pytest.raises(canopen.SdoAbortedError) as error:
        bench.node.sdo[objects.SYNC_COUNTER_OVERFLOW].raw = 16  # while 0x1006 != 0
    assert error.value.code == 0x0800_0022
    bench.node.sdo[objects.COMM_CYCLE_PERIOD].raw = 0
    bench.node.sdo[objects.SYNC_COUNTER_OVERFLOW].raw = 16
    bench.master.send_message(0x080, b"\x01")
    assert _wait_for(lambda: bench.tpdo1)


def test_quirk_options_of_the_sim_drive_process_round_trip():
    quirks = DriveQuirks(
        no_optional_objects=True,
        fixed_pdo_mapping=True,
        interpolation_ms_only=True,
        fault_at_power_on=True,
        guarding_only=True,
        sdo_delay_s=(0.15, 0.4),
        boot_delay_s=6.0,
        late_tpdo_periods=2,
    )
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["--node", "3", *quirk_arguments(quirks)])
    assert quirks_from_arguments(args) == quirks
    assert quirks_from_arguments(parser.parse_args(["--node", "3"])) == DriveQuirks()
