"""Scenarios of the CiA 402 master against simulated drives, independent of the transport.

:class:`DriveScenarios` holds the scenarios; a subclass provides the transport (how a bus is
opened) and the drives (how they are launched with their quirks, silenced and faulted), as
python-can's back-to-back tests do: ``tests/drives/test_integration_virtual.py`` runs them on the
in-process ``virtual`` bus, ``tests/vcan/test_drives_vcan.py`` on SocketCAN vcan0 with one
process per drive.

The master is stepped by :class:`drive_loop.CycleLoop` the way the cycle process steps it. An
independent listener bus records every frame, to check what the drives actually received.
"""

from __future__ import annotations

import itertools
import logging
import math
import struct
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Protocol

import can
import pytest
from drive_loop import CycleLoop

from drives.cia402 import State
from drives.master import (
    AxisFeedback,
    AxisSpec,
    BootPhase,
    Cia402Master,
    FaultKind,
    MasterSettings,
)
from drives.scaling import AxisScaling
from drives.sim import DriveQuirks
from drives.sim.quirks import OPTIONAL_OBJECTS

RPDO1 = struct.Struct("<Hi")


class DriveLauncher(Protocol):
    """Simulated drives on some transport."""

    def stop_answering(self, node_id: int) -> None: ...

    def inject_fault(self, node_id: int, emcy_code: int) -> None: ...

    def close(self) -> None: ...


class FrameRecorder(can.Listener):
    """Listener bus: every frame, in arrival order."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        self.frames: list[can.Message] = []
        self._lock = threading.Lock()
        self._notifier = can.Notifier(bus, [self], timeout=0.05)

    def on_message_received(self, msg: can.Message) -> None:
        with self._lock:
            self.frames.append(msg)

    def snapshot(self) -> list[can.Message]:
        with self._lock:
            return list(self.frames)

    def with_id(self, can_id: int) -> list[can.Message]:
        return [m for m in self.snapshot() if m.arbitration_id == can_id]

    def ids(self) -> set[int]:
        return {m.arbitration_id for m in self.snapshot()}

    def sdo_downloads(self, node_id: int) -> list[tuple[int, int, bytes]]:
        """(index, subindex, data) of every expedited SDO download to ``node_id``."""
        writes = []
        for message in self.with_id(0x600 + node_id):
            data = bytes(message.data)
            if data[0] & 0xE3 == 0x23:  # initiate download, expedited, size indicated
                size = 4 - (data[0] >> 2 & 0x03)
                index, subindex = struct.unpack_from("<HB", data, 1)
                writes.append((index, subindex, data[4 : 4 + size]))
        return writes

    def sdo_uploads(self, node_id: int) -> list[tuple[int, int]]:
        """(index, subindex) of every SDO upload request to ``node_id``."""
        return [
            struct.unpack_from("<HB", bytes(m.data), 1)
            for m in self.with_id(0x600 + node_id)
            if m.data[0] == 0x40
        ]

    def emcy_codes(self, node_id: int) -> list[int]:
        return [struct.unpack_from("<H", bytes(m.data))[0] for m in self.with_id(0x80 + node_id)]

    def close(self) -> None:
        self._notifier.stop()
        self.bus.shutdown()


@dataclass
class Rig:
    master: Cia402Master
    loop: CycleLoop
    recorder: FrameRecorder
    launcher: DriveLauncher
    bus: can.BusABC


class DriveRigs:
    """Master, drives and recorder on one channel; subclasses set the transport hooks and may
    scale the timing."""

    NODE_IDS: Sequence[int] = (1, 2, 3)
    AXIS_NAMES: Sequence[str] = ("X", "Y", "Z")
    PERIOD_S = 0.004
    HEARTBEAT_MS = 100
    #: Multiplies every wait on wall-clock events that the transport can delay.
    TIMEOUT_SCALE = 1.0
    STALE_FEEDBACK_CYCLES = 3
    COUNTS_PER_MM = 1000.0
    WINDOW_MM = 1.0
    VMAX_MM_S = 100.0
    MOTION_S = 4.0

    # -- transport hooks ------------------------------------------------------------------------

    def make_channel(self) -> str:
        raise NotImplementedError

    def open_bus(self, channel: str, **options: object) -> can.BusABC:
        raise NotImplementedError

    def launch_drives(
        self, channel: str, node_ids: Sequence[int], quirks: Mapping[int, DriveQuirks]
    ) -> DriveLauncher:
        raise NotImplementedError

    # -- rig ------------------------------------------------------------------------------------

    def settings(self, **overrides: object) -> MasterSettings:
        values: dict[str, object] = {
            "period_s": self.PERIOD_S,
            "heartbeat_ms": self.HEARTBEAT_MS,
            "master_heartbeat_ms": self.HEARTBEAT_MS,
            "boot_timeout_s": 5.0 * self.TIMEOUT_SCALE,
            "stale_feedback_cycles": self.STALE_FEEDBACK_CYCLES,
        }
        values.update(overrides)
        return MasterSettings(**values)  # type: ignore[arg-type]

    def axes(self, **overrides: object) -> list[AxisSpec]:
        values: dict[str, object] = {
            "following_error_window_mm": self.WINDOW_MM,
            "following_error_timeout_ms": 20,
        }
        values.update(overrides)
        return [
            AxisSpec(
                name,
                node_id,
                AxisScaling(self.COUNTS_PER_MM, travel_min_mm=-500.0, travel_max_mm=500.0),
                **values,  # type: ignore[arg-type]
            )
            for name, node_id in zip(self.AXIS_NAMES, self.NODE_IDS, strict=True)
        ]

    @pytest.fixture
    def channel(self) -> str:
        return self.make_channel()

    @contextmanager
    def rig(
        self,
        channel: str,
        *,
        quirks: Mapping[int, DriveQuirks] | None = None,
        drive_ids: Sequence[int] | None = None,
        settings: MasterSettings | None = None,
        axes: Sequence[AxisSpec] | None = None,
        realtime: bool = True,
        bus_options: Mapping[str, object] | None = None,
        powered_on: Sequence[int] | None = None,
    ) -> Iterator[Rig]:
        """Recorder, master bus, drives (powered on with the master's bus already open, so
        nothing they send is missed), master and loop; closed in reverse on exit.

        :param powered_on: the drives whose power-on boot-up is awaited before the master is
            made (default: every drive launched); drive processes take a while to start.
        """
        recorder = FrameRecorder(self.open_bus(channel))
        bus = self.open_bus(channel, **(bus_options or {}))
        launcher = None
        try:
            node_ids = self.NODE_IDS if drive_ids is None else drive_ids
            launcher = self.launch_drives(channel, node_ids, quirks or {})
            self.wait_for_boot_up(recorder, node_ids if powered_on is None else powered_on)
            master = Cia402Master(bus, axes or self.axes(), settings or self.settings())
            loop = CycleLoop(
                master, self.PERIOD_S, realtime=realtime, answer_wait_s=0.05 * self.TIMEOUT_SCALE
            )
            yield Rig(master, loop, recorder, launcher, bus)
        finally:
            if launcher is not None:
                launcher.close()
            bus.shutdown()
            recorder.close()

    # -- helpers --------------------------------------------------------------------------------

    def wait_for_boot_up(self, recorder: FrameRecorder, node_ids: Sequence[int]) -> None:
        expected = {0x700 + node_id for node_id in node_ids}
        deadline = time.monotonic() + 30.0 * self.TIMEOUT_SCALE
        while not expected <= {
            m.arbitration_id for m in recorder.snapshot() if m.data[:1] == b"\0"
        }:
            assert time.monotonic() < deadline, f"drives {list(node_ids)} never booted"
            time.sleep(0.01)

    def motion(self, k: int, start_mm: Sequence[float]) -> list[float]:
        """Smooth per-axis motion p0 + A (1 - cos 2πft): v = A 2πf, a = A (2πf)² within limits."""
        t = k * self.PERIOD_S
        shapes = ((10.0, 1.0), (8.0, 1.5), (6.0, 0.5))  # (A mm, f Hz): vmax 75 mm/s, amax 711
        return [
            p0 + a * (1.0 - math.cos(2.0 * math.pi * f * t))
            for p0, (a, f) in zip(start_mm, shapes, strict=False)
        ]

    def stream(self, rig: Rig, periods: int) -> list[float]:
        """Move every axis along :meth:`motion` from where it stands; return the largest
        |following error| per axis, checking no fault appears."""
        start = [f.position_mm for f in rig.loop.feedback]
        worst = [0.0] * len(start)
        for k in range(1, periods + 1):
            feedback = rig.loop.step(self.motion(k, start))
            for i, item in enumerate(feedback):
                assert item.fault is None, str(item.fault)
                assert item.enabled, item
                if not math.isnan(item.following_error_mm):
                    worst[i] = max(worst[i], abs(item.following_error_mm))
        return worst

    def rpdo_targets(self, recorder: FrameRecorder, node_id: int) -> list[tuple[int, int]]:
        """(controlword, target counts) of every RPDO1 of ``node_id`` seen on the bus."""
        values = []
        for frame in recorder.with_id(0x200 + node_id):
            assert frame.dlc == 6, f"RPDO1 of node {node_id}: dlc {frame.dlc}"
            values.append(RPDO1.unpack(bytes(frame.data)))
        return values

    def assert_no_target_jump(self, recorder: FrameRecorder, node_id: int) -> None:
        limit = math.ceil(self.VMAX_MM_S * self.PERIOD_S * self.COUNTS_PER_MM) + 1  # + rounding
        targets = [target for _, target in self.rpdo_targets(recorder, node_id)]
        assert targets, f"no RPDO1 of node {node_id} on the bus"
        steps = [abs(b - a) for a, b in itertools.pairwise(targets)]
        assert max(steps, default=0) <= limit, f"node {node_id}: target step {max(steps)} > {limit}"

    def boot_timeout(self) -> float:
        return 10.0 * self.TIMEOUT_SCALE


class DriveScenarios(DriveRigs):
    """The scenarios every transport runs."""

    def test_boot_configure_enable_stream_and_shut_down(self, channel: str) -> None:
        with self.rig(channel, realtime=False) as rig:
            rig.loop.boot(self.boot_timeout())
            rig.loop.enable()
            worst = self.stream(rig, round(self.MOTION_S / self.PERIOD_S))
            assert max(worst) <= self.WINDOW_MM / 4, worst
            rig.loop.shutdown(self.boot_timeout())
            for node_id in self.NODE_IDS:
                self.assert_no_target_jump(rig.recorder, node_id)
                controlwords = {cw for cw, _ in self.rpdo_targets(rig.recorder, node_id)}
                assert controlwords >= {0x06, 0x07, 0x0F}
            syncs = rig.recorder.with_id(0x080)
            assert len(syncs) == rig.master.syncs_sent
            assert all(frame.dlc == 0 for frame in syncs)
            assert rig.loop.events == []

    def test_optional_objects_missing_are_skipped_with_one_warning(
        self, channel: str, caplog: pytest.LogCaptureFixture
    ) -> None:
        """Issue case 1: a drive without 0x6066, 0x6007, 0x605A, 0x605E, 0x6065, 0x1016 and
        0x1017 boots, supervised by node guarding, its skipped objects in the feedback."""
        bare = self.NODE_IDS[1]
        with (
            caplog.at_level(logging.WARNING, logger="drives.boot"),
            self.rig(
                channel, quirks={bare: DriveQuirks(no_optional_objects=True)}, realtime=False
            ) as rig,
        ):
            feedback = rig.loop.boot(self.boot_timeout())
            assert all(f.fault is None for f in feedback), [str(f.fault) for f in feedback]
            skipped = set(feedback[1].skipped_objects)
            assert skipped == OPTIONAL_OBJECTS - {0x1016}  # 0x1016 follows 0x1017: not tried
            assert feedback[0].skipped_objects == feedback[2].skipped_objects == ()
            warnings = [r.getMessage() for r in caplog.records if "skipped" in r.getMessage()]
            assert len(warnings) == len(skipped)
            assert f"node {bare}: 0x6066:00 following error timeout skipped: abort 0x06020000" in (
                "\n".join(warnings)
            )
            rig.loop.enable()
            self.stream(rig, 50)
            remote = [m for m in rig.recorder.with_id(0x700 + bare) if m.is_remote_frame]
            assert remote, "the bare drive is not node-guarded"

    def test_interpolation_period_written_as_whole_milliseconds(self, channel: str) -> None:
        """Issue case 2: 0x60C2 = (period in ms, -3), e.g. (4, -3) for 4 ms, read back, accepted
        by a drive that takes index -3 only."""
        with self.rig(
            channel, quirks={n: DriveQuirks(interpolation_ms_only=True) for n in self.NODE_IDS}
        ) as rig:
            rig.loop.boot(self.boot_timeout())
            period_ms = round(self.PERIOD_S * 1000)
            for node_id in self.NODE_IDS:
                writes = rig.recorder.sdo_downloads(node_id)
                assert (0x60C2, 1, bytes([period_ms])) in writes
                assert (0x60C2, 2, bytes([0xFD])) in writes  # -3
                uploads = rig.recorder.sdo_uploads(node_id)
                assert (0x60C2, 1) in uploads and (0x60C2, 2) in uploads

    def test_drive_in_fault_at_power_on_boots_reports_and_resets(self, channel: str) -> None:
        """Issue case 3 (drive side): the drive boots in FAULT, is reported per node with the
        cause, and the fault reset brings it to OPERATION ENABLED."""
        faulty = self.NODE_IDS[0]
        with self.rig(channel, quirks={faulty: DriveQuirks(fault_at_power_on=True)}) as rig:
            feedback = rig.loop.boot(self.boot_timeout())
            assert feedback[0].state is State.FAULT
            fault = feedback[0].fault
            assert fault is not None and fault.kind in (FaultKind.EMCY, FaultKind.FAULT_STATE)
            assert "0x8130" in str(fault) and str(fault).startswith(f"axis X (node {faulty})")
            assert feedback[1].fault is None and feedback[2].fault is None
            rig.master.request_fault_reset()
            rig.master.request_enable()
            feedback = rig.loop.run_until(
                lambda fb: all(f.enabled for f in fb), 2.0 * self.TIMEOUT_SCALE, what="enabled"
            )
            assert all(f.fault is None for f in feedback)
            controlwords = [cw for cw, _ in self.rpdo_targets(rig.recorder, faulty)]
            assert 0x80 in controlwords  # the bit 7 edge

    def test_fixed_read_only_mapping_is_used_as_the_drive_has_it(self, channel: str) -> None:
        """Issue case 5: PDOs fixed in a vendor layout (TPDO1 = position, statusword on
        0x280 + node) are read and used; nothing is written to them."""
        fixed = self.NODE_IDS[2]
        with self.rig(
            channel, quirks={fixed: DriveQuirks(fixed_pdo_mapping=True)}, realtime=False
        ) as rig:
            rig.loop.boot(self.boot_timeout())
            pdo_writes = [
                (index, sub)
                for index, sub, _ in rig.recorder.sdo_downloads(fixed)
                if 0x1400 <= index < 0x1C00
            ]
            assert pdo_writes == []
            rig.loop.enable()
            worst = self.stream(rig, 100)
            assert worst[2] <= self.WINDOW_MM / 4
            assert rig.recorder.with_id(0x280 + fixed), "TPDO1 not on the drive's COB-ID"

    def test_guarding_only_drive_is_supervised_by_node_guarding(self, channel: str) -> None:
        """Issue case 7: a drive without heartbeat objects is guarded (0x100C/0x100D, remote
        frames, toggle) and its silence detected within the life time."""
        guarded = self.NODE_IDS[0]
        with self.rig(channel, quirks={guarded: DriveQuirks(guarding_only=True)}) as rig:
            feedback = rig.loop.boot(self.boot_timeout())
            assert feedback[0].skipped_objects == (0x1017,)
            writes = rig.recorder.sdo_downloads(guarded)
            assert (0x100C, 0, struct.pack("<H", 100)) in writes
            assert (0x100D, 0, bytes([3])) in writes
            rig.loop.run_for(0.3)
            answers = [m for m in rig.recorder.with_id(0x700 + guarded) if not m.is_remote_frame]
            toggles = [m.data[0] & 0x80 for m in answers if m.data[0] & 0x7F == 0x05]
            assert len(toggles) >= 2 and all(a != b for a, b in itertools.pairwise(toggles))
            assert rig.loop.events == []
            rig.launcher.stop_answering(guarded)
            silenced = time.monotonic()
            # Stale feedback shows first; the lost node replaces it once the life time is over.
            feedback = rig.loop.run_until(
                lambda fb: fb[0].fault is not None and fb[0].fault.kind is FaultKind.GUARDING,
                2.0 * self.TIMEOUT_SCALE,
                what="guarding loss",
            )
            assert time.monotonic() - silenced <= 0.3 * 1.5 * self.TIMEOUT_SCALE + 0.1
            assert f"axis X (node {guarded}): no node-guarding answer for" in str(feedback[0].fault)

    def test_clean_shutdown_leaves_no_drive_faulted_and_a_second_start_finds_them_healthy(
        self, channel: str
    ) -> None:
        """Issue case 8: the shutdown disarms 0x1016 (and 0x1006) before NMT PRE-OPERATIONAL
        and the end of our heartbeat; drives stay quiet, a second master finds them healthy."""
        with self.rig(channel, realtime=False) as rig:
            rig.loop.boot(self.boot_timeout())
            rig.loop.enable()
            self.stream(rig, 50)
            rig.loop.shutdown(self.boot_timeout())
            for node_id in self.NODE_IDS:
                writes = rig.recorder.sdo_downloads(node_id)
                assert writes[-2:] == [(0x1016, 1, bytes(4)), (0x1006, 0, bytes(4))]
                nmt = [bytes(m.data) for m in rig.recorder.with_id(0x000)]
                assert nmt[-len(self.NODE_IDS) :].count(bytes([0x80, node_id])) == 1
            # Longer than the drives' consumer time (2.5 heartbeats): nothing may fault.
            time.sleep(3 * self.HEARTBEAT_MS / 1000.0)
            assert not any(rig.recorder.emcy_codes(n) for n in self.NODE_IDS)
            second = Cia402Master(self.open_bus(channel), self.axes(), self.settings())
            try:
                loop = CycleLoop(second, self.PERIOD_S)
                feedback = loop.boot(self.boot_timeout())
                loop.run_for(0.2)
                assert all(f.state is State.SWITCH_ON_DISABLED for f in loop.feedback)
                assert all(f.fault is None for f in feedback) and loop.events == []
                loop.shutdown(self.boot_timeout())
            finally:
                second.bus.shutdown()

    def test_late_boot_is_reported_then_configured_when_it_appears(self, channel: str) -> None:
        """Issue case 9: a drive that boots after boot_timeout_s is reported (BOOT, naming the
        node), looked for, configured when it appears; a fault reset then clears it."""
        late = self.NODE_IDS[2]
        timeout_s = 0.5 * self.TIMEOUT_SCALE
        with self.rig(
            channel,
            quirks={late: DriveQuirks(boot_delay_s=2 * timeout_s)},
            settings=self.settings(boot_timeout_s=timeout_s),
            powered_on=[n for n in self.NODE_IDS if n != late],
        ) as rig:
            rig.master.start()
            feedback = rig.loop.run_until(
                lambda fb: fb[2].fault is not None, 4 * timeout_s, what="boot fault"
            )
            fault = feedback[2].fault
            assert fault.kind is FaultKind.BOOT
            assert str(fault) == (
                f"axis Z (node {late}): no boot-up, heartbeat or SDO answer within "
                f"{timeout_s:g} s; looking for the drive"
            )
            assert feedback[2].phase is BootPhase.WAITING
            feedback = rig.loop.run_until(
                lambda fb: all(f.ready for f in fb), self.boot_timeout(), what="late drive ready"
            )
            assert feedback[2].fault is fault  # stays until reset
            rig.master.request_fault_reset()
            rig.loop.step()
            feedback = rig.loop.step()
            assert all(f.fault is None for f in feedback)
            assert [e.kind for e in rig.loop.events] == [FaultKind.BOOT]
            rig.loop.enable()

    def test_heartbeat_loss_detected_within_three_periods(self, channel: str) -> None:
        with self.rig(channel) as rig:
            rig.loop.boot(self.boot_timeout())
            rig.loop.enable()
            rig.loop.run_for(2 * self.HEARTBEAT_MS / 1000.0)
            lost = self.NODE_IDS[2]
            rig.launcher.stop_answering(lost)
            silenced_at = time.monotonic()
            feedback = rig.loop.run_until(
                lambda fb: fb[2].fault is not None,
                10 * self.HEARTBEAT_MS / 1000.0,
                what="heartbeat loss",
            )
            detected_s = time.monotonic() - silenced_at
            period_s = self.HEARTBEAT_MS / 1000.0
            fault = feedback[2].fault
            assert fault.kind in (FaultKind.HEARTBEAT_LOSS, FaultKind.STALE_FEEDBACK)
            feedback = rig.loop.run_until(
                lambda fb: fb[2].fault.kind is FaultKind.HEARTBEAT_LOSS,
                4 * period_s,
                what="heartbeat loss",
            )
            detected_s = time.monotonic() - silenced_at
            assert detected_s <= 3 * period_s + 0.05, f"detected after {detected_s:.3f} s"
            assert f"axis Z (node {lost}): no heartbeat for" in str(feedback[2].fault)
            assert feedback[2].phase is BootPhase.WAITING  # looked for again
            kinds = [e.kind for e in rig.loop.events]
            assert kinds.count(FaultKind.HEARTBEAT_LOSS) == 1
            assert set(kinds) <= {FaultKind.HEARTBEAT_LOSS, FaultKind.STALE_FEEDBACK}, kinds
            others = feedback[:2]
            assert all(f.fault is None and f.enabled for f in others), others

    def test_injected_fault_then_reset_and_reenable_without_jump(self, channel: str) -> None:
        with self.rig(channel, realtime=False) as rig:
            rig.loop.boot(self.boot_timeout())
            rig.loop.enable()
            self.stream(rig, 100)
            faulty = self.NODE_IDS[1]
            rig.launcher.inject_fault(faulty, 0x4210)
            start = [f.position_mm for f in rig.loop.feedback]
            periods = iter(range(1, 1000))

            def targets(feedback: tuple[AxisFeedback, ...]) -> list[float | None]:
                moved: list[float | None] = list(self.motion(next(periods), start))
                moved[1] = None  # the faulted axis holds where it stands
                return moved

            feedback = rig.loop.run_until(
                lambda fb: fb[1].fault is not None and fb[1].fault.kind is FaultKind.EMCY,
                1.0 * self.TIMEOUT_SCALE,
                targets,
                what="EMCY of the injected fault",
            )
            fault = feedback[1].fault
            assert fault.emcy_code == 0x4210
            assert str(fault).startswith(f"axis Y (node {faulty}): EMCY 0x4210")
            assert feedback[0].fault is None and feedback[2].fault is None
            assert rig.loop.events[0] == fault
            rig.master.request_fault_reset(["Y"])
            rig.master.request_enable(["Y"])
            feedback = rig.loop.run_until(
                lambda fb: fb[1].enabled, 1.0 * self.TIMEOUT_SCALE, targets, what="Y re-enabled"
            )
            assert feedback[1].fault is None and not feedback[1].fault_reset_pending
            assert feedback[1].commanded_mm == pytest.approx(feedback[1].position_mm, abs=0.002)
            for node_id in self.NODE_IDS:
                self.assert_no_target_jump(rig.recorder, node_id)
            controlwords = [cw for cw, _ in self.rpdo_targets(rig.recorder, faulty)]
            edge = controlwords.index(0x80)
            assert controlwords[edge - 1] & 0x80 == 0

    def test_every_fault_is_an_event_also_after_the_first(self, channel: str) -> None:
        """Issue case 11: a second and third drive fault, while the first is latched and the
        machine stops, are each reported with axis, kind, EMCY code and text."""
        with self.rig(channel) as rig:
            rig.loop.boot(self.boot_timeout())
            rig.loop.enable()
            rig.loop.run_for(0.1)
            rig.launcher.inject_fault(self.NODE_IDS[0], 0x4210)
            rig.loop.run_until(lambda fb: fb[0].fault is not None, 1.0 * self.TIMEOUT_SCALE)
            rig.master.request_quick_stop()  # the machine stops; the others brake
            rig.launcher.inject_fault(self.NODE_IDS[1], 0x4210)
            rig.launcher.inject_fault(self.NODE_IDS[2], 0x4210)
            rig.loop.run_until(
                lambda fb: all(f.fault is not None and f.fault.emcy_code for f in fb),
                1.0 * self.TIMEOUT_SCALE,
            )
            emcys = [(e.axis, e.emcy_code) for e in rig.loop.events if e.kind is FaultKind.EMCY]
            assert emcys[0] == ("X", 0x4210)
            assert sorted(emcys[1:]) == [("Y", 0x4210), ("Z", 0x4210)]
            texts = {str(e) for e in rig.loop.events if e.kind is FaultKind.EMCY}
            assert (
                f"axis Z (node {self.NODE_IDS[2]}): EMCY 0x4210 excess temperature device "
                "(register 0x09)"
            ) in texts
            assert rig.master.take_fault_events() == ()  # taken by the loop already
