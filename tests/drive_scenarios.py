"""Integration scenarios of the CiA 402 master against simulated drives, independent of transport.

:class:`DriveScenarios` holds the scenarios; a subclass provides the transport (how a bus is
opened) and the drives (how they are launched, silenced and faulted), as python-can's back-to-back
tests do: ``tests/drives/test_integration_virtual.py`` runs them on the in-process ``virtual``
bus, ``tests/vcan/test_drives_vcan.py`` on SocketCAN vcan0 with one process per drive.

The cycle is driven by the test. Motion runs faster than real time: after each exchange the loop
waits until every drive has answered that SYNC (the simulated drives step their model once per
SYNC with the period of 0x1006, so simulated time is exact). Heartbeat loss is wall-clock, so
that scenario runs the cycle at its real period. An independent listener bus records every frame
with the number of SYNCs sent when it arrived, to check what the drives actually received.
"""

from __future__ import annotations

import itertools
import math
import struct
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Protocol

import can
import canopen
import pytest

from drives.cia402 import State
from drives.errors import BootTimeout
from drives.master import AxisFeedback, AxisSpec, Cia402Master, FaultKind, MasterSettings
from drives.scaling import AxisScaling

RPDO1 = struct.Struct("<Hi")


class DriveLauncher(Protocol):
    """Simulated drives on some transport."""

    def stop_answering(self, node_id: int) -> None: ...

    def inject_fault(self, node_id: int, emcy_code: int) -> None: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class Recorded:
    frame: can.Message
    syncs_sent: int


class FrameRecorder(can.Listener):
    """Listener bus records: every frame with the master's SYNC count at its arrival."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        self.frames: list[Recorded] = []
        self.master: Cia402Master | None = None
        self._lock = threading.Lock()
        self._notifier = can.Notifier(bus, [self], timeout=0.05)

    def on_message_received(self, msg: can.Message) -> None:
        syncs = self.master.syncs_sent if self.master is not None else 0
        with self._lock:
            self.frames.append(Recorded(msg, syncs))

    def snapshot(self) -> list[Recorded]:
        with self._lock:
            return list(self.frames)

    def ids(self) -> set[int]:
        return {r.frame.arbitration_id for r in self.snapshot()}

    def close(self) -> None:
        self._notifier.stop()
        self.bus.shutdown()


@dataclass
class Rig:
    master: Cia402Master
    network: canopen.Network
    recorder: FrameRecorder
    launcher: DriveLauncher | None


class DriveScenarios:
    """The scenarios; subclasses set the transport hooks and may scale the timing."""

    NODE_IDS: Sequence[int] = (1, 2, 3)
    AXIS_NAMES: Sequence[str] = ("X", "Y", "Z")
    PERIOD_S = 0.004
    #: TPDO age (cycles) before stale feedback is a fault.
    STALE_FEEDBACK_CYCLES = 3
    HEARTBEAT_MS = 100
    #: Multiplies every wait on wall-clock events that the transport can delay.
    TIMEOUT_SCALE = 1.0
    COUNTS_PER_MM = 1000.0
    WINDOW_MM = 1.0
    VMAX_MM_S = 100.0
    AMAX_MM_S2 = 1000.0
    MOTION_S = 10.0

    # -- transport hooks ------------------------------------------------------------------------

    def make_channel(self) -> str:
        raise NotImplementedError

    def open_bus(self, channel: str) -> can.BusABC:
        raise NotImplementedError

    def launch_drives(self, channel: str, node_ids: Sequence[int]) -> DriveLauncher:
        raise NotImplementedError

    # -- fixtures -------------------------------------------------------------------------------

    def settings(self, **overrides: object) -> MasterSettings:
        values: dict[str, object] = {
            "period_s": self.PERIOD_S,
            "heartbeat_ms": self.HEARTBEAT_MS,
            "master_heartbeat_ms": self.HEARTBEAT_MS,
            "boot_timeout_s": 5.0 * self.TIMEOUT_SCALE,
            "sdo_timeout_s": 0.3 * self.TIMEOUT_SCALE,
            "stale_feedback_cycles": self.STALE_FEEDBACK_CYCLES,
        }
        values.update(overrides)
        return MasterSettings(**values)  # type: ignore[arg-type]

    def axes(self) -> list[AxisSpec]:
        return [
            AxisSpec(
                name,
                node_id,
                AxisScaling(self.COUNTS_PER_MM, travel_min_mm=-500.0, travel_max_mm=500.0),
                following_error_window_mm=self.WINDOW_MM,
                following_error_timeout_ms=20,
            )
            for name, node_id in zip(self.AXIS_NAMES, self.NODE_IDS, strict=True)
        ]

    @pytest.fixture
    def channel(self) -> str:
        return self.make_channel()

    def _rig(self, channel: str, drive_ids: Sequence[int], **overrides: object) -> Iterator[Rig]:
        recorder = FrameRecorder(self.open_bus(channel))
        network = canopen.Network(self.open_bus(channel))
        # Short notifier cycles, and a join on disconnect: a notifier still reading when its
        # socketcan bus closes fails with EBADF (seen in the slow VM).
        network.NOTIFIER_CYCLE = 0.05
        network.NOTIFIER_SHUTDOWN_TIMEOUT = 0.5
        network.connect()
        master = Cia402Master(network, self.axes(), self.settings(**overrides))
        recorder.master = master
        launcher = None
        try:
            launcher = self.launch_drives(channel, drive_ids) if drive_ids else None
            self.wait_for_boot_up(recorder, drive_ids)
            yield Rig(master, network, recorder, launcher)
            master.shutdown()
        finally:
            if launcher is not None:
                launcher.close()
            network.disconnect()
            recorder.close()

    def wait_for_boot_up(self, recorder: FrameRecorder, node_ids: Sequence[int]) -> None:
        """Wait until every launched drive has sent its boot-up (a process takes a while)."""
        expected = {0x700 + node_id for node_id in node_ids}
        deadline = time.monotonic() + 30.0 * self.TIMEOUT_SCALE
        while not expected <= recorder.ids():
            assert time.monotonic() < deadline, f"drives {list(node_ids)} never booted"
            time.sleep(0.01)

    @pytest.fixture
    def rig(self, channel: str) -> Iterator[Rig]:
        yield from self._rig(channel, self.NODE_IDS)

    # -- cycle helpers --------------------------------------------------------------------------

    def fast_cycle(
        self, master: Cia402Master, targets: Sequence[float | None] | None = None
    ) -> tuple[AxisFeedback, ...]:
        """One cycle, then wait until every drive answered its SYNC (faster than real time)."""
        feedback = master.read_feedback()
        master.write_targets(targets)
        master.exchange()
        deadline = time.monotonic() + 1.0 * self.TIMEOUT_SCALE
        while not master.feedback_complete:
            if time.monotonic() > deadline:
                break  # the next read_feedback reports the stale axis
            time.sleep(0.0001)
        return feedback

    def enable_all(self, master: Cia402Master) -> None:
        master.request_enable()
        for _ in range(20):
            feedback = self.fast_cycle(master)
            if all(f.enabled for f in feedback):
                return
        pytest.fail(f"not enabled after 20 cycles: {master.read_feedback()}")

    def booted(self, rig: Rig) -> Cia402Master:
        rig.master.boot()
        self.enable_all(rig.master)
        return rig.master

    def motion(self, k: int, start_mm: Sequence[float]) -> list[float]:
        """Smooth per-axis motion p0 + A (1 - cos 2πft): v = A 2πf, a = A (2πf)² within limits."""
        t = k * self.PERIOD_S
        shapes = ((10.0, 1.0), (8.0, 1.5), (6.0, 0.5))  # (A mm, f Hz): vmax 75 mm/s, amax 711
        return [
            p0 + a * (1.0 - math.cos(2.0 * math.pi * f * t))
            for p0, (a, f) in zip(start_mm, shapes, strict=False)
        ]

    def rpdo_targets(self, recorder: FrameRecorder, node_id: int) -> list[tuple[int, int]]:
        """(controlword, target counts) of every RPDO1 of ``node_id`` seen on the bus."""
        values = []
        for record in recorder.snapshot():
            frame = record.frame
            if frame.arbitration_id == 0x200 + node_id:
                assert frame.dlc == 6, f"RPDO1 of node {node_id}: dlc {frame.dlc}"
                values.append(RPDO1.unpack(bytes(frame.data)))
        return values

    def assert_no_target_jump(self, recorder: FrameRecorder, node_id: int) -> None:
        limit = math.ceil(self.VMAX_MM_S * self.PERIOD_S * self.COUNTS_PER_MM) + 1  # + rounding
        targets = [target for _, target in self.rpdo_targets(recorder, node_id)]
        assert targets, f"no RPDO1 of node {node_id} on the bus"
        steps = [abs(b - a) for a, b in itertools.pairwise(targets)]
        assert max(steps, default=0) <= limit, (
            f"node {node_id}: target step {max(steps)} counts > vmax·T = {limit}"
        )

    # -- scenarios ------------------------------------------------------------------------------

    def test_boot_configure_enable_and_stream_motion(self, rig: Rig) -> None:
        master = self.booted(rig)
        start = [f.commanded_mm for f in master.read_feedback()]
        cycles = round(self.MOTION_S / self.PERIOD_S)
        worst = [0.0] * len(start)
        for k in range(cycles):
            feedback = self.fast_cycle(master, self.motion(k + 1, start))
            for i, item in enumerate(feedback):
                assert item.fault is None, str(item.fault)
                assert item.enabled
                worst[i] = max(worst[i], abs(item.following_error_mm))
        assert max(worst) <= self.WINDOW_MM, worst
        final = master.read_feedback()
        expected = self.motion(cycles, start)
        for item, end_mm in zip(final, expected, strict=True):
            assert item.commanded_mm == pytest.approx(end_mm, abs=1e-3)
            assert item.feedback_age_cycles == 0
        for node_id in self.NODE_IDS:
            self.assert_no_target_jump(rig.recorder, node_id)
            controlwords = {cw for cw, _ in self.rpdo_targets(rig.recorder, node_id)}
            assert controlwords == {0x06, 0x07, 0x0F}
        syncs = [r for r in rig.recorder.snapshot() if r.frame.arbitration_id == 0x080]
        assert len(syncs) == master.syncs_sent
        assert all(r.frame.dlc == 0 for r in syncs)

    def test_boot_timeout_names_the_silent_node(self, channel: str) -> None:
        timeout_s = 0.5 * self.TIMEOUT_SCALE
        present = tuple(self.NODE_IDS[:-1])
        silent = self.NODE_IDS[-1]
        rig_iter = self._rig(channel, present, boot_timeout_s=timeout_s)
        rig = next(rig_iter)
        try:
            started = time.monotonic()
            with pytest.raises(BootTimeout) as caught:
                rig.master.boot()
            elapsed = time.monotonic() - started
            assert caught.value.node_id == silent
            assert str(caught.value).startswith(f"node {silent}: no boot-up or heartbeat")
            assert timeout_s <= elapsed <= timeout_s + 0.5 * self.TIMEOUT_SCALE
            time.sleep(0.1 * self.TIMEOUT_SCALE)  # frames in flight reach the recorder
            ids = rig.recorder.ids()
            # Nothing was configured, started or enabled: no SDO, no RPDO, no SYNC, no NMT start.
            assert not ids & {0x600 + n for n in self.NODE_IDS}
            assert not ids & {0x200 + n for n in self.NODE_IDS}
            assert 0x080 not in ids
            nmt = [r.frame for r in rig.recorder.snapshot() if r.frame.arbitration_id == 0]
            assert all(frame.data[0] == 0x82 for frame in nmt)  # only reset communication
            # The present drives booted (boot-up seen) and stay silent otherwise: no TPDO.
            assert {0x700 + n for n in present} <= ids
            assert not ids & {0x180 + n for n in self.NODE_IDS}
        finally:
            rig_iter.close()

    def test_injected_fault_then_reset_and_reenable_without_jump(self, rig: Rig) -> None:
        master = self.booted(rig)
        assert rig.launcher is not None
        faulty_index = 1
        faulty_node = self.NODE_IDS[faulty_index]
        faulty_name = self.AXIS_NAMES[faulty_index]
        start = [f.commanded_mm for f in master.read_feedback()]
        k = 0
        for _ in range(round(0.4 / self.PERIOD_S)):
            k += 1
            self.fast_cycle(master, self.motion(k, start))
        rig.launcher.inject_fault(faulty_node, 0x4210)
        # The fault must be visible within 2 cycles of its EMCY reaching the bus.
        emcy_at: int | None = None
        fault = None
        deadline = time.monotonic() + 5.0 * self.TIMEOUT_SCALE
        while fault is None:
            assert time.monotonic() < deadline, "injected fault never seen"
            k += 1
            targets = self.motion(k, start)
            targets[faulty_index] = None
            feedback = self.fast_cycle(master, targets)
            fault = feedback[faulty_index].fault
            if emcy_at is None:
                emcy_at = next(
                    (
                        r.syncs_sent
                        for r in rig.recorder.snapshot()
                        if r.frame.arbitration_id == 0x80 + faulty_node
                    ),
                    None,
                )
            if emcy_at is not None and fault is None:
                assert master.syncs_sent - emcy_at <= 2, "fault not visible within 2 cycles"
        assert fault.emcy_code == 0x4210
        assert fault.kind is FaultKind.EMCY
        assert str(fault).startswith(f"axis {faulty_name} (node {faulty_node}): EMCY 0x4210")
        assert all(f.fault is None for i, f in enumerate(feedback) if i != faulty_index)
        # Let the fault reaction finish, then reset and re-enable while the others keep moving.
        master.request_fault_reset([faulty_name])
        master.request_enable([faulty_name])
        for _ in range(50):
            k += 1
            targets = self.motion(k, start)
            targets[faulty_index] = None
            feedback = self.fast_cycle(master, targets)
            if feedback[faulty_index].enabled:
                break
        else:
            pytest.fail(f"not re-enabled: {feedback[faulty_index]}")
        item = feedback[faulty_index]
        assert item.fault is None
        # Re-enabled where the drive stands; then move on from there.
        assert item.commanded_mm == pytest.approx(item.position_mm, abs=1.0 / self.COUNTS_PER_MM)
        restart = list(start)
        restart[faulty_index] = item.commanded_mm
        k0 = k
        for _ in range(round(0.4 / self.PERIOD_S)):
            k += 1
            targets = self.motion(k, start)
            targets[faulty_index] = self.motion(k - k0, restart)[faulty_index]
            feedback = self.fast_cycle(master, targets)
            assert all(f.fault is None for f in feedback), [str(f.fault) for f in feedback]
            assert abs(feedback[faulty_index].following_error_mm) <= self.WINDOW_MM
        for node_id in self.NODE_IDS:
            self.assert_no_target_jump(rig.recorder, node_id)
        controlwords = [cw for cw, _ in self.rpdo_targets(rig.recorder, faulty_node)]
        reset_edge = [i for i in range(1, len(controlwords)) if controlwords[i] == 0x80]
        assert reset_edge and controlwords[reset_edge[0] - 1] & 0x80 == 0

    def test_heartbeat_loss_detected_within_three_periods(self, rig: Rig) -> None:
        master = self.booted(rig)
        assert rig.launcher is not None
        lost_index = 2
        lost_node = self.NODE_IDS[lost_index]
        period_s = self.HEARTBEAT_MS / 1000.0
        # Real-time cycle: heartbeats are wall-clock.
        next_cycle = time.monotonic()
        for _ in range(round(2 * period_s / self.PERIOD_S)):
            feedback = master.read_feedback()
            assert all(f.fault is None for f in feedback), [str(f.fault) for f in feedback]
            master.exchange()
            next_cycle += self.PERIOD_S
            time.sleep(max(0.0, next_cycle - time.monotonic()))
        rig.launcher.stop_answering(lost_node)
        silenced_at = time.monotonic()
        while True:
            feedback = master.read_feedback()
            fault = feedback[lost_index].fault
            if fault is not None and fault.kind is FaultKind.HEARTBEAT_LOSS:
                detected_s = time.monotonic() - silenced_at
                break
            assert time.monotonic() - silenced_at < 10 * period_s, "heartbeat loss not detected"
            master.exchange()
            next_cycle = max(next_cycle + self.PERIOD_S, time.monotonic())
            time.sleep(max(0.0, next_cycle - time.monotonic()))
        assert detected_s <= 3 * period_s, f"detected after {detected_s:.3f} s"
        assert feedback[lost_index].heartbeat_age_s <= 3 * period_s
        assert f"axis {self.AXIS_NAMES[lost_index]} (node {lost_node}): no heartbeat" in str(fault)
        others = [f for i, f in enumerate(feedback) if i != lost_index]
        assert all(f.fault is None and f.state is State.OPERATION_ENABLED for f in others), [
            (f.state, str(f.fault)) for f in others
        ]
