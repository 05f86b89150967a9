"""The drive-side cases that need the drives in this process (their EDS, their models, a late
adapter, a stalled host), on python-can's ``virtual`` bus. The transport-independent ones are in
``tests/drive_scenarios.py``."""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import canopen
import pytest
from drive_loop import CycleLoop
from drive_scenarios import DriveRigs, Rig
from late_bus import LateDeliveryBus
from test_integration_virtual import InProcessDrives, VirtualTransport

from drives.boot import interpolation_period
from drives.cia402 import State
from drives.master import AxisSpec, BootPhase, Cia402Master, FaultKind, Supervision
from drives.objects import (
    ERROR_CODE,
    FOLLOWING_ERROR_ACTUAL,
    POSITION_ACTUAL,
    STATUSWORD,
)
from drives.pdo import AxisPdoSpec, MappingPolicy, PdoSpec
from drives.sim import DriveModel, DriveQuirks
from drives.sim.quirks import OPTIONAL_OBJECTS, served_od

#: A path at 100 mm/s: cosine ramp up in RAMP_S, then constant speed.
SPEED_MM_S = 100.0
RAMP_S = 0.2


def _path_mm(t_s: float) -> float:
    if t_s < RAMP_S:
        # v = V (1 - cos(pi t / T)) / 2: integral
        return SPEED_MM_S / 2 * (t_s - RAMP_S / math.pi * math.sin(math.pi * t_s / RAMP_S))
    return SPEED_MM_S / 2 * RAMP_S + SPEED_MM_S * (t_s - RAMP_S)


class Cases(VirtualTransport, DriveRigs):
    """Rigs of the scenarios, on the virtual bus."""

    def export_eds(self, tmp_path: Path, node_id: int, quirks: DriveQuirks) -> Path:
        path = tmp_path / f"node{node_id}.eds"
        od = served_od(node_id, quirks)
        od.node_id = None
        canopen.export_od(od, str(path), doc_type="eds")
        return path

    def with_axis(self, index: int, **changes: object) -> list[AxisSpec]:
        axes = self.axes()
        values = {**axes[index].__dict__, **changes}
        axes[index] = AxisSpec(**values)  # type: ignore[arg-type]
        return axes

    def ramp(self, rig: Rig, duration_s: float) -> list[tuple]:
        """Move every axis along the 100 mm/s path; return every period's feedback."""
        start = [f.position_mm for f in rig.loop.feedback]
        history = []
        for k in range(1, round(duration_s / self.PERIOD_S) + 1):
            position = _path_mm(k * self.PERIOD_S)
            history.append(rig.loop.step([p0 + position for p0 in start]))
        return history


# -- case 1: an EDS decides beforehand what exists ------------------------------------------------


class TestOptionalObjectsFromTheEds(Cases):
    def test_objects_absent_from_the_eds_are_never_asked_for(
        self, channel: str, tmp_path: Path, caplog: pytest.LogCaptureFixture
    ) -> None:
        bare = DriveQuirks(no_optional_objects=True)
        eds = self.export_eds(tmp_path, 2, bare)
        with (
            caplog.at_level(logging.WARNING, logger="drives.boot"),
            self.rig(channel, quirks={2: bare}, axes=self.with_axis(1, eds=eds)) as rig,
        ):
            feedback = rig.loop.boot(self.boot_timeout())
            assert set(feedback[1].skipped_objects) == OPTIONAL_OBJECTS - {0x1016}
            asked = {index for index, _, _ in rig.recorder.sdo_downloads(2)}
            asked |= {index for index, _ in rig.recorder.sdo_uploads(2)}
            assert not asked & OPTIONAL_OBJECTS
            assert (
                f"node 2: 0x6007:00 abort connection option code skipped: not in the EDS {eds}"
                in (caplog.text)
            )


# -- case 2: 0x60C2 -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("period_us", "expected"),
    [(4000, (4, -3)), (1000, (1, -3)), (100_000, (100, -3)), (2500, (25, -4)), (500, (5, -4))],
)
def test_interpolation_period_is_whole_ms_with_index_minus_3(period_us, expected) -> None:
    assert interpolation_period(period_us) == expected


class TestInterpolationPeriodOutOfRange(Cases):
    PERIOD_S = 0.025  # 25 ms: beyond the 1..20 ms the drive takes

    def test_refused_value_names_node_object_value_and_range(self, channel: str) -> None:
        quirks = {n: DriveQuirks(interpolation_ms_only=True) for n in self.NODE_IDS}
        with self.rig(channel, quirks=quirks) as rig:
            rig.master.start()
            feedback = rig.loop.run_until(
                lambda fb: all(f.phase is BootPhase.FAILED for f in fb), 5.0, what="boot failed"
            )
            assert str(feedback[0].fault) == (
                "axis X (node 1): 0x60C2:01 interpolation time period value = 25 refused: "
                "abort 0x06090031 (value of parameter written too high); the drive's maximum "
                "is below 25"
            )
            assert [e.kind for e in rig.loop.events] == [FaultKind.BOOT] * 3

    def test_with_an_eds_the_range_is_known_before_writing(
        self, channel: str, tmp_path: Path
    ) -> None:
        quirks = DriveQuirks(interpolation_ms_only=True)
        eds = self.export_eds(tmp_path, 1, quirks)
        with self.rig(channel, quirks={1: quirks}, axes=self.with_axis(0, eds=eds)) as rig:
            rig.master.start()
            feedback = rig.loop.run_until(
                lambda fb: fb[0].phase is BootPhase.FAILED, 5.0, what="boot failed"
            )
            assert str(feedback[0].fault) == (
                f"axis X (node 1): 0x60C2:01 interpolation time period value = 25 outside the "
                f"drive's range 1..20 (EDS {eds})"
            )
            assert (0x60C2, 1) not in {(i, s) for i, s, _ in rig.recorder.sdo_downloads(1)}


# -- case 5: PDO mapping ------------------------------------------------------------------------


class TestPdoMapping(Cases):
    def test_read_only_mapping_without_what_is_needed_names_the_missing_objects(
        self, channel: str
    ) -> None:
        pdo = AxisPdoSpec(tpdos=(PdoSpec(3, (STATUSWORD, POSITION_ACTUAL)),))
        with self.rig(
            channel,
            quirks={1: DriveQuirks(fixed_pdo_mapping=True)},
            axes=self.with_axis(0, pdo=pdo),
        ) as rig:
            rig.master.start()
            feedback = rig.loop.run_until(
                lambda fb: fb[0].phase is BootPhase.FAILED and fb[1].ready and fb[2].ready,
                5.0,
                what="X failed, the others ready",
            )
            text = feedback[0].fault.text
            assert text.startswith("TPDO3 on 0x181 (type 1, not valid): 0x606C: lacks ")
            assert "lacks 0x6041 statusword, 0x6064 position actual value" in text
            assert "mapping fixed: abort 0x06010002 (attempt to write a read only object)" in text

    def test_drive_mapping_with_following_error_and_error_code_is_used(self, channel: str) -> None:
        pdo = AxisPdoSpec(
            tpdos=(
                PdoSpec(1, (STATUSWORD, POSITION_ACTUAL)),
                PdoSpec(2, (FOLLOWING_ERROR_ACTUAL, ERROR_CODE)),
            )
        )
        with self.rig(
            channel,
            quirks={1: DriveQuirks(fixed_pdo_mapping=True)},
            axes=self.with_axis(0, pdo=pdo),
        ) as rig:
            rig.loop.boot(self.boot_timeout())
            rig.loop.enable()
            history = self.ramp(rig, 0.4)
            assert all(f[0].fault is None for f in history)
            assert rig.recorder.with_id(0x381), "TPDO2 (0x60F4, 0x603F) not used"

    def test_write_policy_maps_in_the_configured_order(self, channel: str) -> None:
        pdo = AxisPdoSpec(
            mapping=MappingPolicy.WRITE, tpdos=(PdoSpec(1, (POSITION_ACTUAL, STATUSWORD)),)
        )
        with self.rig(channel, axes=self.with_axis(2, pdo=pdo)) as rig:
            rig.loop.boot(self.boot_timeout())
            writes = rig.recorder.sdo_downloads(3)
            mapping = [(i, s, v) for i, s, v in writes if i == 0x1A00]
            assert mapping == [
                (0x1A00, 0, b"\x00"),
                (0x1A00, 1, (0x6064_0020).to_bytes(4, "little")),
                (0x1A00, 2, (0x6041_0010).to_bytes(4, "little")),
                (0x1A00, 0, b"\x02"),
            ]
            rig.loop.enable()
            self.ramp(rig, 0.2)


# -- case 6: SDO timeout and retries --------------------------------------------------------------


class TestSlowSdo(Cases):
    @pytest.mark.slow
    def test_a_slow_drive_boots_with_the_default_timeout_beside_fast_ones(
        self, channel: str
    ) -> None:
        slow = DriveQuirks(sdo_delay_s=(0.15, 0.25))
        with self.rig(channel, quirks={3: slow}, settings=self.settings()) as rig:
            rig.master.start()
            started = time.monotonic()
            rig.loop.run_until(lambda fb: fb[0].ready and fb[1].ready, 2.0, what="fast ready")
            fast_s = time.monotonic() - started
            feedback = rig.loop.run_until(lambda fb: fb[2].ready, 20.0, what="slow drive ready")
            assert time.monotonic() - started > 10 * 0.15 > fast_s
            assert rig.loop.events == [], [str(e) for e in rig.loop.events]
            assert all(f.fault is None for f in feedback)
            rig.loop.enable()

    def test_a_timeout_shorter_than_the_drive_reports_it_and_keeps_trying(
        self, channel: str
    ) -> None:
        slow = DriveQuirks(sdo_delay_s=(0.15, 0.15))
        with self.rig(
            channel,
            quirks={3: slow},
            settings=self.settings(sdo_timeout_s=0.05, sdo_retries=1),
        ) as rig:
            rig.master.start()
            feedback = rig.loop.run_until(
                lambda fb: fb[2].fault is not None, 3.0, what="slow drive reported"
            )
            assert feedback[2].fault.kind is FaultKind.BOOT
            assert "no SDO answer within 0.05 s (2 attempts); looking for the drive" in str(
                feedback[2].fault
            )
            assert feedback[2].phase is BootPhase.WAITING


# -- case 7: guarding chosen by configuration ------------------------------------------------------


class TestGuardingByConfiguration(Cases):
    def test_guarding_configured_on_a_drive_with_heartbeat(self, channel: str) -> None:
        axes = self.with_axis(1, supervision=Supervision.GUARDING, guard_time_ms=50)
        with self.rig(channel, axes=axes) as rig:
            rig.loop.boot(self.boot_timeout())
            writes = rig.recorder.sdo_downloads(2)
            assert (0x1017, 0, b"\x00\x00") in writes  # heartbeat off: the drive guards
            assert (0x100C, 0, b"\x32\x00") in writes
            rig.loop.run_for(0.3)
            assert len([m for m in rig.recorder.with_id(0x702) if m.is_remote_frame]) >= 4
            assert rig.loop.events == []
            rig.loop.shutdown()
            time.sleep(0.3)  # life time 150 ms: disarmed, the drive stays quiet
            assert rig.recorder.emcy_codes(2) == []


# -- case 8: what leaving without the clean shutdown does -----------------------------------------


class TestLeavingWithoutShutdown(Cases):
    def test_a_master_that_just_stops_makes_the_drives_raise_8130(self, channel: str) -> None:
        """The control for the clean shutdown scenario: the drives do supervise us."""
        with self.rig(channel) as rig:
            rig.loop.boot(self.boot_timeout())
            rig.loop.run_for(0.1)
            time.sleep(0.5)  # no more heartbeat from us
            assert all(0x8130 in rig.recorder.emcy_codes(n) for n in self.NODE_IDS)


# -- case 9: drives that reboot or vanish while running -------------------------------------------


class TestDriveComesBack(Cases):
    def test_a_drive_that_reboots_while_running_is_configured_again(self, channel: str) -> None:
        with self.rig(channel) as rig:
            rig.loop.boot(self.boot_timeout())
            rig.loop.enable()
            drive = rig.launcher.drive_set.drives[2]
            drive.stop()
            drive.start()
            feedback = rig.loop.run_until(
                lambda fb: fb[1].fault is not None and fb[1].fault.kind is FaultKind.NMT,
                2.0,
                what="reboot seen",
            )
            assert "drive rebooted" in str(feedback[1].fault)
            feedback = rig.loop.run_until(lambda fb: fb[1].ready, 3.0, what="ready again")
            assert feedback[1].state is State.SWITCH_ON_DISABLED
            assert feedback[1].fault is not None  # until reset
            rig.master.request_fault_reset()
            rig.loop.enable()
            assert all(f.fault is None for f in rig.loop.feedback)

    def test_a_reset_while_the_drive_is_configured_again_applies_once_it_is_ready(
        self, channel: str
    ) -> None:
        with self.rig(channel) as rig:
            rig.loop.boot(self.boot_timeout())
            drive = rig.launcher.drive_set.drives[2]
            drive.stop()
            rig.loop.run_until(lambda fb: fb[1].fault is not None, 5.0, what="drive lost")
            drive.quirks = DriveQuirks(sdo_delay_s=(0.02, 0.02))  # a configuration to wait for
            drive.start()
            rig.loop.run_until(
                lambda fb: fb[1].phase is BootPhase.CONFIGURING, 3.0, what="configured again"
            )
            rig.master.request_fault_reset()
            feedback = rig.loop.run_until(
                lambda fb: fb[1].ready and fb[1].fault is None, 5.0, what="reset once ready"
            )
            assert feedback[1].state is State.SWITCH_ON_DISABLED
            rig.loop.enable()

    def test_a_lost_drive_is_looked_for_and_configured_when_it_answers_again(
        self, channel: str
    ) -> None:
        with self.rig(channel) as rig:
            rig.loop.boot(self.boot_timeout())
            drive = rig.launcher.drive_set.drives[1]
            drive.stop_answering()
            rig.loop.run_until(
                lambda fb: fb[0].phase is BootPhase.WAITING, 2.0, what="lost drive looked for"
            )
            drive.resume_answering()
            feedback = rig.loop.run_until(lambda fb: fb[0].ready, 5.0, what="found again")
            assert feedback[0].fault.kind is FaultKind.HEARTBEAT_LOSS
            rig.master.request_fault_reset()
            rig.loop.enable()


# -- case 10: feedback matched to its SYNC ---------------------------------------------------------


class TestLateAdapter(Cases):
    WINDOW_MM = 0.5  # ipc-example.yaml's window

    @pytest.mark.parametrize("counter", [0, 16])
    def test_frames_handed_over_a_period_late_do_not_shift_the_following_error(
        self, channel: str, counter: int
    ) -> None:
        # The adapter's period of delay comes out of the stale-feedback margin: one more.
        settings = self.settings(
            sync_counter_overflow=counter, stale_feedback_cycles=self.STALE_FEEDBACK_CYCLES + 1
        )
        with self.rig(
            channel, settings=settings, bus_options={"receive_own_messages": bool(counter)}
        ) as rig:
            late = LateDeliveryBus(rig.bus)
            rig.master.bus = late
            rig.loop.boot(self.boot_timeout())
            rig.loop.enable()
            history = self.ramp(rig, 0.6)
            steady = history[round(RAMP_S / self.PERIOD_S) + 10 :]
            assert all(f.fault is None for fb in history for f in fb), rig.loop.events
            assert max(abs(f.following_error_mm) for fb in steady for f in fb) < 0.01
            # Read by arrival (the TPDO taken for an answer to the SYNC before the last), the
            # same positions would lag their targets by a period: 0.4 mm at 100 mm/s.
            assert min(fb[0].feedback_age_cycles for fb in steady) == 2
            by_arrival = [
                fb[0].position_mm - (fb[0].target_mm + SPEED_MM_S * self.PERIOD_S) for fb in steady
            ]
            assert max(abs(e) for e in by_arrival) == pytest.approx(0.4, abs=0.01)

    def test_feedback_lag_per_axis_for_a_drive_that_sends_late(self, channel: str) -> None:
        late = DriveQuirks(late_tpdo_periods=2)
        axes = self.with_axis(1, feedback_lag_periods=3)
        with self.rig(
            channel,
            quirks={2: late, 3: late},
            axes=axes,
            settings=self.settings(stale_feedback_cycles=5),
        ) as rig:
            rig.loop.boot(self.boot_timeout())
            rig.loop.enable()
            history = self.ramp(rig, 0.5)
            steady = history[round(RAMP_S / self.PERIOD_S) + 10 :]
            fitted = max(abs(fb[1].following_error_mm) for fb in steady)
            default = max(abs(fb[2].following_error_mm) for fb in steady)
            assert fitted < 0.01
            assert default == pytest.approx(2 * SPEED_MM_S * self.PERIOD_S, abs=0.01)
            # An event, not necessarily the axis's first fault: a host that stalls this process
            # for 20 ms leaves five SYNCs unanswered, stale feedback, before the window trips.
            assert (
                "Z",
                FaultKind.FOLLOWING_ERROR,
            ) in {(event.axis, event.kind) for event in rig.loop.events}


# -- case 11: drive faults during a stop after a host stall ---------------------------------------


class TestHostStall(Cases):
    def test_every_drive_fault_after_a_stall_is_reported(self, channel: str) -> None:
        model = DriveModel(sync_timeout_factor=5.0)  # 20 ms without SYNC: fault 0x8100
        with self.rig(channel) as rig:
            rig.launcher.close()
            rig.launcher = InProcessDrives(channel, self.NODE_IDS, {}, model=model)
            rig.loop.boot(self.boot_timeout())
            rig.loop.enable()
            self.ramp(rig, 0.3)
            time.sleep(0.2)  # the host stalls: no SYNC for 200 ms
            rig.loop.run_until(lambda fb: all(f.state is State.FAULT for f in fb), 1.0)
            rig.loop.run_for(0.3)
            for axis in ("X", "Y", "Z"):
                codes = [e.emcy_code for e in rig.loop.events if e.axis == axis and e.emcy_code]
                # SYNC loss first; the heartbeat gap of the stall follows on some drives.
                assert codes[0] == 0x8100 and set(codes) <= {0x8100, 0x8130}, codes


# -- case 12: the following error is the drive's, not zero by construction -----------------------


class TestFollowingError(Cases):
    WINDOW_MM = 20.0

    def test_following_error_of_a_drive_that_cannot_keep_up(self, channel: str) -> None:
        """Drives limited to 80 mm/s, asked for 100: the error grows, the master's own value
        (X) and the drive's 0x60F4 (Y) agree, and both are the actual position against the
        target of that instant."""
        pdo = AxisPdoSpec(
            tpdos=(
                PdoSpec(1, (STATUSWORD, POSITION_ACTUAL)),
                PdoSpec(2, (FOLLOWING_ERROR_ACTUAL,)),
            )
        )
        model = DriveModel(sync_timeout_factor=50.0, max_velocity_counts_s=80_000.0)
        with self.rig(channel, axes=self.with_axis(1, pdo=pdo)) as rig:
            rig.launcher.close()
            rig.launcher = InProcessDrives(channel, self.NODE_IDS, {}, model=model)
            rig.loop.boot(self.boot_timeout())
            rig.loop.enable()
            history = self.ramp(rig, 0.6)
            last = history[-1]
            assert last[0].following_error_mm < -1.0
            assert last[1].following_error_mm == pytest.approx(last[0].following_error_mm, abs=0.01)
            x = last[0]
            assert x.following_error_mm == pytest.approx(x.position_mm - x.target_mm)
            assert not math.isnan(x.target_mm) and x.target_mm > x.position_mm


class TestNoDrives(Cases):
    def test_drives_that_never_answer_are_reported_never_raised(self, channel: str) -> None:
        bus = self.open_bus(channel)
        try:
            master = Cia402Master(bus, self.axes(), self.settings(boot_timeout_s=0.2))
            loop = CycleLoop(master, self.PERIOD_S)
            master.start()
            feedback = loop.run_until(
                lambda fb: all(f.fault is not None for f in fb), 2.0, what="boot reported"
            )
            assert all(f.phase is BootPhase.WAITING for f in feedback)
            assert [e.kind for e in loop.events] == [FaultKind.BOOT] * 3
            loop.shutdown()
        finally:
            bus.shutdown()
