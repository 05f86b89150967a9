"""CiA 402 master: boots and configures the drives, then exchanges CSP process data each cycle.

Source: CiA 301 (NMT, SYNC, PDO, heartbeat, EMCY) and CiA 402 device control in cyclic
synchronous position mode (0x6060 = 8): RPDO1 = controlword 0x6040 + target position 0x607A,
TPDO1 = statusword 0x6041 + position actual value 0x6064, both transmission type 1.

Units: positions in mm at the API, counts (INTEGER32) on the bus; periods in s; heartbeat times in
ms; feedback age in SYNC cycles.

Threading contract:
- Main thread: ``__init__``, :meth:`Cia402Master.boot` and :meth:`Cia402Master.shutdown`. They
  block (SDO, NMT waits) and must not run while the cycle runs.
- Cyclic thread: :meth:`~Cia402Master.read_feedback`, :meth:`~Cia402Master.write_targets`,
  :meth:`~Cia402Master.exchange` once per period in that order, and the ``request_*`` methods.
  They never block, never use SDO, never log in the normal path; O(axes) work each.
- python-can Notifier thread: canopen runs the TPDO, heartbeat and EMCY callbacks of
  :class:`drives.monitor.AxisSupervisor`, which store immutable records by reference swap.

Invariants:
- Per cycle the RPDOs of every axis go out first, then one SYNC (``network.sync.transmit()``;
  never a background SYNC task), so all drives latch one consistent set of targets.
- The 402 state machine advances at most one transition per cycle, chosen from the state the
  drive reported; nothing waits for a transition.
- While an axis is not in OPERATION ENABLED its target is its actual position, so enabling (and
  re-enabling after a fault reset) never makes the drive jump.
- Targets are converted from absolute millimetres every cycle (:class:`AxisScaling`): no drift.

Not done: modes other than CSP, SDO after boot, re-booting a drive that reset (an NMT fault
stays until the machine is booted again), SYNC counter, TPDO2.
"""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from enum import Enum
from pathlib import Path

import can
import canopen

from drives.cia402 import (
    QUICK_STOP_OPTIONS_STAY_ACTIVE,
    Command,
    State,
    controlword_toward_disabled,
    controlword_toward_enabled,
    decode_statusword,
    fault_reset_controlword,
)
from drives.configure import (
    DriveSetup,
    configure_drive,
    enter_pre_operational,
    heartbeat_consumer_entry,
    period_us,
    read_feedback_by_sdo,
)
from drives.errors import BootTimeout, DriveError
from drives.monitor import (
    AxisFault,
    AxisSupervisor,
    FaultKind,
    SupervisionLimits,
    SyncCounter,
    TpdoSample,
)
from drives.objects import (
    HEARTBEAT_COB_ID_BASE,
    NmtCommand,
    NmtState,
    build_drive_od,
    rpdo_cob_id,
    tpdo_cob_id,
)
from drives.scaling import AxisScaling

__all__ = [
    "AxisFault",
    "AxisFeedback",
    "AxisSpec",
    "Cia402Master",
    "FaultKind",
    "MasterSettings",
    "TravelLimitError",
]

#: RPDO1 payload: controlword (U16), target position (I32), little endian.
RPDO1_STRUCT = struct.Struct("<Hi")


#: Faults after which a drive must be configured again (it was lost, restarted or reset).
RECONFIGURE_FAULT_KINDS = frozenset({FaultKind.HEARTBEAT_LOSS, FaultKind.NMT, FaultKind.BOOT})


class AxisRequest(Enum):
    """What the caller asked an axis to do; the master steps the drive toward it."""

    DISABLE = "disable"
    ENABLE = "enable"
    QUICK_STOP = "quick stop"


class TravelLimitError(DriveError, ValueError):
    """A target outside the axis travel range; no target of that cycle was applied."""

    def __init__(self, axis: str, node_id: int, position_mm: float, scaling: AxisScaling) -> None:
        self.axis = axis
        self.position_mm = position_mm
        super().__init__(
            node_id,
            f"axis {axis}: target {position_mm!r} mm outside travel "
            f"[{scaling.travel_min_mm:g}, {scaling.travel_max_mm:g}] mm",
        )


@dataclass(frozen=True)
class AxisSpec:
    """One axis: its drive's node and how its millimetres map to counts."""

    name: str
    node_id: int
    scaling: AxisScaling
    following_error_window_mm: float
    following_error_timeout_ms: int
    eds: Path | None = None
    """EDS of the drive; None uses :func:`drives.objects.build_drive_od`."""

    def __post_init__(self) -> None:
        if not 1 <= self.node_id <= 127:
            raise ValueError(f"axis {self.name}: node_id = {self.node_id}, must be in 1..127")
        if not (
            math.isfinite(self.following_error_window_mm) and self.following_error_window_mm > 0
        ):
            raise ValueError(
                f"axis {self.name}: following_error_window_mm = "
                f"{self.following_error_window_mm!r}, must be finite and > 0"
            )
        if self.following_error_timeout_ms < 0:
            raise ValueError(
                f"axis {self.name}: following_error_timeout_ms = "
                f"{self.following_error_timeout_ms}, must be >= 0"
            )


@dataclass(frozen=True)
class MasterSettings:
    """Bus-wide timing and the drive options written at boot."""

    period_s: float
    heartbeat_ms: int = 100
    """Producer heartbeat time configured on every drive (0x1017)."""
    master_node_id: int = 127
    master_heartbeat_ms: int = 100
    """Our heartbeat, consumed by the drives (0x1016); 0 = neither sent nor consumed."""
    heartbeat_loss_periods: float = 2.5
    """Heartbeat loss after this many heartbeat periods without one (also the drives' 0x1016)."""
    boot_timeout_s: float = 5.0
    sdo_timeout_s: float = 0.3
    stale_feedback_cycles: int = 3
    quick_stop_option: int = 2
    """0x605A: 2 = quick stop ramp, then SWITCH ON DISABLED."""
    fault_reaction_option: int = 2
    """0x605E: 2 = quick stop ramp."""
    abort_connection_option: int = 1
    """0x6007: 1 = fault on heartbeat loss, SYNC loss or leaving OPERATIONAL."""
    sync_window_us: int = 0
    """0x1007; 0 = not written."""
    feedback_lag_cycles: int = 1
    """SYNCs between a target and the TPDO1 reporting the position that follows it, for the
    master's following-error check: 1 for a drive that latches the target at SYNC n, moves during
    the period and reports at SYNC n + 1 after its step (the simulated drive); 2 for a drive that
    samples its position before applying the new SYNC's target."""
    reset_communication: bool = True
    """Send NMT reset communication at boot, so drives that booted earlier send boot-up again."""

    def __post_init__(self) -> None:
        period_us(self.period_s)  # raises ValueError naming the period
        if self.heartbeat_ms <= 0:
            raise ValueError(f"heartbeat_ms = {self.heartbeat_ms}, must be > 0")
        if not 1 <= self.master_node_id <= 127:
            raise ValueError(f"master_node_id = {self.master_node_id}, must be in 1..127")
        if not 1.0 < self.heartbeat_loss_periods < 3.0:
            raise ValueError(
                f"heartbeat_loss_periods = {self.heartbeat_loss_periods}, must be in (1, 3)"
            )
        if self.feedback_lag_cycles < 0:
            raise ValueError(f"feedback_lag_cycles = {self.feedback_lag_cycles}, must be >= 0")
        if self.stale_feedback_cycles < 1:
            raise ValueError(f"stale_feedback_cycles = {self.stale_feedback_cycles}, must be >= 1")

    @property
    def target_history(self) -> int:
        """Targets kept per axis: every TPDO1 the stale-feedback check still accepts is judged
        for following error against the target it answered."""
        return self.stale_feedback_cycles + self.feedback_lag_cycles + 1


@dataclass(frozen=True, slots=True)
class AxisFeedback:
    """One axis as seen at the start of a cycle."""

    axis: str
    node_id: int
    state: State | None
    """Decoded statusword; None if it matched no CiA 402 state (then ``fault`` says so)."""
    statusword: int
    position_counts: int
    position_mm: float
    commanded_mm: float
    """The target sent with the last SYNC (the actual position while not enabled)."""
    following_error_mm: float
    """Actual minus the target the drive was following; 0 while not in OPERATION ENABLED."""
    feedback_age_cycles: int
    """SYNCs sent since the TPDO1 used here answered (0 = answer to the last SYNC)."""
    heartbeat_age_s: float
    """Seconds since the last heartbeat; inf before the first."""
    fault: AxisFault | None

    @property
    def enabled(self) -> bool:
        return self.state is State.OPERATION_ENABLED


class _Axis:
    """Cyclic-thread state of one axis (the Notifier side lives in its supervisor)."""

    def __init__(
        self, spec: AxisSpec, node: canopen.RemoteNode, supervisor: AxisSupervisor, history: int
    ):
        self.spec = spec
        self.node = node
        self.supervisor = supervisor
        self.rpdo_cob_id = rpdo_cob_id(1, spec.node_id)
        self.request = AxisRequest.DISABLE
        self.reset_pending = False
        self.reset_cycle = 0
        self.state: State | None = None
        self.sample: TpdoSample | None = None
        self.target_counts = 0
        self.sent_counts = [0] * history


class Cia402Master:
    """CiA 402 master for a set of CSP axes on one CANopen network.

    :param network: a connected ``canopen.Network`` (its Notifier runs our callbacks).
    :param axes: the axes, in the order of every per-axis sequence of this API.
    :param settings: bus timing and drive options.
    :param clock: monotonic time source in seconds (heartbeat ages).
    :raises ValueError: on duplicate axis names or node ids, or a node id equal to the master's.
    """

    def __init__(
        self,
        network: canopen.Network,
        axes: Sequence[AxisSpec],
        settings: MasterSettings,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        _check_axes(axes, settings)
        self.network = network
        self.settings = settings
        self._clock = clock
        self._syncs = SyncCounter()
        self._heartbeat_task: can.broadcastmanager.CyclicSendTaskABC | None = None
        self._booted = False
        cycle_s = settings.period_s
        self._axes: tuple[_Axis, ...] = tuple(self._add_axis(spec, cycle_s) for spec in axes)
        self._by_name = {axis.spec.name: axis for axis in self._axes}
        self._feedback: tuple[AxisFeedback, ...] = ()

    def _add_axis(self, spec: AxisSpec, cycle_s: float) -> _Axis:
        od = (
            canopen.import_od(str(spec.eds), spec.node_id)
            if spec.eds is not None
            else build_drive_od(spec.node_id)
        )
        node = self.network.add_node(canopen.RemoteNode(spec.node_id, od))
        node.sdo.RESPONSE_TIMEOUT = self.settings.sdo_timeout_s
        limits = SupervisionLimits(
            heartbeat_loss_s=self.settings.heartbeat_loss_periods
            * self.settings.heartbeat_ms
            / 1000.0,
            stale_feedback_cycles=self.settings.stale_feedback_cycles,
            following_error_window_mm=spec.following_error_window_mm,
            following_error_cycles=math.ceil(spec.following_error_timeout_ms / 1000.0 / cycle_s),
        )
        supervisor = AxisSupervisor(
            spec.name, spec.node_id, spec.scaling, limits, self._syncs, self._clock
        )
        node.nmt.add_heartbeat_callback(supervisor.on_heartbeat)
        node.emcy.add_callback(supervisor.on_emcy)
        # Subscribed directly (not through node.tpdo[1]) so the cyclic path decodes one struct
        # and does not depend on the PDO map object being loaded.
        self.network.subscribe(tpdo_cob_id(1, spec.node_id), supervisor.on_tpdo)
        return _Axis(spec, node, supervisor, self.settings.target_history)

    # -- boot and shutdown (main thread, blocking) ----------------------------------------------

    def boot(self) -> None:
        """Wait for every drive, configure it by SDO, start NMT and the master heartbeat.

        Blocking, outside the cycle. If any drive stays silent, nothing is configured or
        started. Afterwards every axis is OPERATIONAL, SWITCH ON DISABLED (or wherever the
        drive was) and requested disabled; its feedback is seeded by an SDO read.

        :raises BootTimeout: a node sent neither boot-up nor heartbeat within boot_timeout_s.
        :raises ConfigurationFailed: an SDO transfer was aborted or timed out.
        :raises ConfigurationMismatch: an object read back differs from what was written.
        :raises DriveError: a node did not report OPERATIONAL after NMT start.
        """
        settings = self.settings
        if settings.reset_communication:
            for axis in self._axes:
                axis.supervisor.alive.clear()
                axis.node.nmt.send_command(NmtCommand.RESET_COMMUNICATION)
        self._wait_alive()
        try:
            self._start_master_heartbeat()
            for axis in self._axes:
                self._configure(axis)
            for axis in self._axes:
                axis.node.nmt.send_command(NmtCommand.START)
            self._wait_operational()
        except BaseException:
            self._stop_master_heartbeat()
            raise
        for axis in self._axes:
            axis.request = AxisRequest.DISABLE
            axis.reset_pending = False
            axis.supervisor.clear_fault()
        self._booted = True

    def recover(self) -> tuple[str, ...]:
        """Bring back drives that were lost or restarted: reset their communication, wait for
        their boot-up, configure them again by SDO and start them.

        Blocking, outside the cycle (a service thread) while the cycle keeps running; the axes
        concerned stay faulted until this returns, then their faults are cleared and their
        enable request (if any) takes them up again from their actual position.

        :returns: the names of the axes recovered (those with a heartbeat, NMT or boot fault).
        :raises BootTimeout: a drive did not come back within boot_timeout_s.
        :raises ConfigurationFailed: an SDO transfer was aborted or timed out.
        :raises ConfigurationMismatch: an object read back differs from what was written.
        :raises DriveError: a drive did not report OPERATIONAL after NMT start.
        """
        lost = [
            axis
            for axis in self._axes
            if axis.supervisor.fault is not None
            and axis.supervisor.fault.kind in RECONFIGURE_FAULT_KINDS
        ]
        for axis in lost:
            axis.supervisor.alive.clear()
            axis.node.nmt.send_command(NmtCommand.RESET_COMMUNICATION)
        self._wait_alive(lost)
        for axis in lost:
            self._configure(axis)
            axis.node.nmt.send_command(NmtCommand.START)
        self._wait_operational(lost)
        for axis in lost:
            # A pending fault reset stays: a drive that kept its FAULT state still needs it.
            axis.supervisor.clear_fault()
        return tuple(axis.spec.name for axis in lost)

    def _wait_alive(self, axes: Sequence[_Axis] | None = None) -> None:
        timeout_s = self.settings.boot_timeout_s
        deadline = time.monotonic() + timeout_s
        silent = [
            axis.spec.node_id
            for axis in (self._axes if axes is None else axes)
            if not axis.supervisor.alive.wait(max(0.0, deadline - time.monotonic()))
        ]
        if silent:
            raise BootTimeout(silent[0], timeout_s, tuple(silent[1:]))

    def _configure(self, axis: _Axis) -> None:
        spec, settings = axis.spec, self.settings
        consumer_ms = round(settings.master_heartbeat_ms * settings.heartbeat_loss_periods)
        setup = DriveSetup(
            cycle_period_us=period_us(settings.period_s),
            heartbeat_producer_ms=settings.heartbeat_ms,
            master_heartbeat_consumer=heartbeat_consumer_entry(
                settings.master_node_id, consumer_ms
            ),
            following_error_window_counts=round(
                spec.following_error_window_mm * spec.scaling.counts_per_mm
            ),
            following_error_timeout_ms=spec.following_error_timeout_ms,
            quick_stop_option=settings.quick_stop_option,
            fault_reaction_option=settings.fault_reaction_option,
            abort_connection_option=settings.abort_connection_option,
            sync_window_us=settings.sync_window_us,
        )
        enter_pre_operational(axis.node)
        configure_drive(axis.node, setup, mode_timeout_s=settings.boot_timeout_s)
        statusword, position_counts = read_feedback_by_sdo(axis.node)
        axis.supervisor.seed(statusword, position_counts)
        axis.sample = axis.supervisor.tpdo
        axis.target_counts = position_counts
        axis.sent_counts = [position_counts] * self.settings.target_history

    def _wait_operational(self, axes: Sequence[_Axis] | None = None) -> None:
        timeout_s = self.settings.boot_timeout_s
        deadline = time.monotonic() + timeout_s
        for axis in self._axes if axes is None else axes:
            while True:
                heartbeat = axis.supervisor.heartbeat
                if heartbeat is not None and heartbeat.nmt_state == NmtState.OPERATIONAL:
                    break
                if time.monotonic() >= deadline:
                    shown = "none" if heartbeat is None else f"0x{heartbeat.nmt_state:02X}"
                    raise DriveError(
                        axis.spec.node_id,
                        f"not OPERATIONAL {timeout_s:g} s after NMT start (heartbeat {shown})",
                    )
                time.sleep(0.005)

    def _start_master_heartbeat(self) -> None:
        settings = self.settings
        if settings.master_heartbeat_ms > 0 and self._heartbeat_task is None:
            self._heartbeat_task = self.network.send_periodic(
                HEARTBEAT_COB_ID_BASE + settings.master_node_id,
                bytes([NmtState.OPERATIONAL]),
                settings.master_heartbeat_ms / 1000.0,
            )

    def _stop_master_heartbeat(self) -> None:
        if self._heartbeat_task is not None:
            self._heartbeat_task.stop()
            self._heartbeat_task = None

    def shutdown(self, timeout_s: float = 1.0) -> None:
        """Disable every axis through the cycle, then NMT PRE-OPERATIONAL and stop our heartbeat.

        Blocking, from the main thread once the cyclic thread has stopped: it runs the cycle
        itself at the configured period until every drive is in SWITCH ON DISABLED (or FAULT,
        or lost), or ``timeout_s`` has passed. Calling it again does nothing.
        """
        if not self._booted:
            self._stop_master_heartbeat()
            return
        self.request_disable()
        deadline = time.monotonic() + timeout_s
        settled = (State.SWITCH_ON_DISABLED, State.NOT_READY_TO_SWITCH_ON, State.FAULT)
        while time.monotonic() < deadline:
            feedback = self.read_feedback()
            # A lost drive (heartbeat) cannot be stepped down; its 0x6007 reaction applies.
            if all(
                item.state in settled
                or (item.fault is not None and item.fault.kind is FaultKind.HEARTBEAT_LOSS)
                for item in feedback
            ):
                break
            self.exchange()
            time.sleep(self.settings.period_s)
        for axis in self._axes:
            axis.node.nmt.send_command(NmtCommand.ENTER_PRE_OPERATIONAL)
        self._stop_master_heartbeat()
        self._booted = False

    # -- cycle (cyclic thread, non-blocking) ----------------------------------------------------

    def read_feedback(self) -> tuple[AxisFeedback, ...]:
        """Snapshot every axis: latest TPDO1, ages, and faults detected up to now.

        A fault (EMCY, statusword fault, heartbeat loss, NMT state, stale feedback, following
        error) stays in ``fault`` until a fault reset clears it.
        """
        now_s = self._clock()
        syncs = self._syncs.value
        feedback = []
        for axis in self._axes:
            supervisor = axis.supervisor
            sample = supervisor.tpdo
            heartbeat = supervisor.heartbeat
            emcy = supervisor.emcy
            if sample is None:
                sample = TpdoSample(0, 0, 0)
            try:
                state: State | None = decode_statusword(sample.statusword)
            except ValueError:
                state = None
            if state in (State.FAULT, State.FAULT_REACTION_ACTIVE) and axis.state not in (
                State.FAULT,
                State.FAULT_REACTION_ACTIVE,
            ):
                # The drive disabled itself: re-enabling takes an explicit request.
                axis.request = AxisRequest.DISABLE
            if axis.request is AxisRequest.QUICK_STOP and state is State.SWITCH_ON_DISABLED:
                axis.request = AxisRequest.DISABLE
            if axis.reset_pending and state not in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                axis.reset_pending = False
                supervisor.clear_fault()
            if state is State.OPERATION_ENABLED and axis.state is not State.OPERATION_ENABLED:
                # Newly enabled (or first seen enabled): hold where the drive is.
                axis.target_counts = sample.position_counts
            axis.state = state
            axis.sample = sample
            scaling = axis.spec.scaling
            position_mm = scaling.to_mm(sample.position_counts)
            followed_sync = sample.sync_count - self.settings.feedback_lag_cycles
            if state is State.OPERATION_ENABLED and syncs - followed_sync < len(axis.sent_counts):
                followed = axis.sent_counts[followed_sync % len(axis.sent_counts)]
                following_error_mm = position_mm - scaling.to_mm(followed)
            else:
                # Not enabled, or feedback older than the stale-feedback limit (that fault
                # stands for it): no target to compare with.
                following_error_mm = 0.0
            fault = (
                supervisor.supervise(state, sample, heartbeat, emcy, following_error_mm, now_s)
                if self._booted
                else supervisor.fault
            )
            feedback.append(
                AxisFeedback(
                    axis=axis.spec.name,
                    node_id=axis.spec.node_id,
                    state=state,
                    statusword=sample.statusword,
                    position_counts=sample.position_counts,
                    position_mm=position_mm,
                    commanded_mm=scaling.to_mm(axis.target_counts),
                    following_error_mm=following_error_mm,
                    feedback_age_cycles=syncs - sample.sync_count,
                    heartbeat_age_s=math.inf if heartbeat is None else now_s - heartbeat.received_s,
                    fault=fault,
                )
            )
        self._feedback = tuple(feedback)
        return self._feedback

    def write_targets(self, positions_mm: Sequence[float | None] | None) -> None:
        """Set the next target of each axis in mm (None, for all or one axis: keep the last).

        Applied only to axes in OPERATION ENABLED (as of the last :meth:`read_feedback`); the
        others follow their actual position. All targets are checked before any is applied.

        :raises ValueError: if the sequence length differs from the number of axes.
        :raises TravelLimitError: a target outside its axis's travel range.
        :raises ScalingError: a target with no INTEGER32 count value.
        """
        if positions_mm is None:
            return
        if len(positions_mm) != len(self._axes):
            raise ValueError(
                f"write_targets: {len(positions_mm)} positions for {len(self._axes)} axes"
            )
        counts: list[int | None] = []
        for axis, position_mm in zip(self._axes, positions_mm, strict=True):
            if position_mm is None or axis.state is not State.OPERATION_ENABLED:
                counts.append(None)
                continue
            scaling = axis.spec.scaling
            if not scaling.within_travel(position_mm):
                raise TravelLimitError(axis.spec.name, axis.spec.node_id, position_mm, scaling)
            counts.append(scaling.to_counts(position_mm))
        for axis, target in zip(self._axes, counts, strict=True):
            if target is not None:
                axis.target_counts = target

    def exchange(self) -> None:
        """Transmit RPDO1 (controlword + target) of every axis, then one SYNC.

        The controlword makes the next transition toward the axis's request; an axis not in
        OPERATION ENABLED gets its actual position as target.
        """
        send = self.network.send_message
        sync_number = self._syncs.value + 1
        slot = sync_number % self.settings.target_history
        for axis in self._axes:
            controlword = self._controlword(axis)
            if axis.state is not State.OPERATION_ENABLED and axis.sample is not None:
                axis.target_counts = axis.sample.position_counts
            axis.sent_counts[slot] = axis.target_counts
            send(axis.rpdo_cob_id, RPDO1_STRUCT.pack(controlword, axis.target_counts))
        # Counted before the SYNC goes out, so a TPDO answering it is stamped with its number.
        self._syncs.value = sync_number
        self.network.sync.transmit()

    def _controlword(self, axis: _Axis) -> int:
        state = axis.state
        if state is None or state is State.FAULT_REACTION_ACTIVE:
            return Command.DISABLE_VOLTAGE
        if state is State.FAULT:
            if not axis.reset_pending:
                return Command.DISABLE_VOLTAGE
            controlword = fault_reset_controlword(axis.reset_cycle)
            axis.reset_cycle += 1
            return controlword
        if state is State.QUICK_STOP_ACTIVE:
            stays = self.settings.quick_stop_option in QUICK_STOP_OPTIONS_STAY_ACTIVE
            if stays and axis.request is AxisRequest.ENABLE:
                return Command.ENABLE_OPERATION  # transition 16
            if stays and axis.request is AxisRequest.DISABLE:
                return Command.DISABLE_VOLTAGE  # transition 12
            return Command.QUICK_STOP  # let the drive finish its ramp
        if axis.request is AxisRequest.ENABLE:
            return controlword_toward_enabled(state)
        if axis.request is AxisRequest.QUICK_STOP and state is not State.SWITCH_ON_DISABLED:
            return Command.QUICK_STOP
        return controlword_toward_disabled(state)

    # -- requests (cyclic thread, non-blocking) -------------------------------------------------

    def request_enable(self, axes: Iterable[str] | None = None) -> None:
        """Step the axes toward OPERATION ENABLED, one transition per cycle, from their actual
        position. An axis in FAULT stays there until a fault reset."""
        for axis in self._select(axes):
            axis.request = AxisRequest.ENABLE

    def request_disable(self, axes: Iterable[str] | None = None) -> None:
        """Step the axes down to SWITCH ON DISABLED (disable operation, shutdown, voltage off)."""
        for axis in self._select(axes):
            axis.request = AxisRequest.DISABLE

    def request_quick_stop(self, axes: Iterable[str] | None = None) -> None:
        """Quick stop (controlword 0x02): the drive brakes per 0x605A; then the axis is disabled."""
        for axis in self._select(axes):
            axis.request = AxisRequest.QUICK_STOP

    def request_fault_reset(self, axes: Iterable[str] | None = None) -> None:
        """Clear the axes' latched faults; a drive in FAULT gets the bit 7 edge (0x00, 0x80, ...)
        until it leaves FAULT. The request (enable or not) is kept: to re-enable after a fault,
        also call :meth:`request_enable`."""
        for axis in self._select(axes):
            axis.reset_pending = True
            axis.reset_cycle = 0

    def _select(self, axes: Iterable[str] | None) -> Iterable[_Axis]:
        if axes is None:
            return self._axes
        if isinstance(axes, str):
            axes = (axes,)
        try:
            return [self._by_name[name] for name in axes]
        except KeyError as exc:
            known = ", ".join(self._by_name)
            raise ValueError(f"no axis named {exc.args[0]!r} (axes: {known})") from None

    # -- state ----------------------------------------------------------------------------------

    @property
    def axis_names(self) -> tuple[str, ...]:
        return tuple(axis.spec.name for axis in self._axes)

    @property
    def enabled_mask(self) -> tuple[bool, ...]:
        """Per axis, whether it was in OPERATION ENABLED at the last :meth:`read_feedback`."""
        return tuple(axis.state is State.OPERATION_ENABLED for axis in self._axes)

    @property
    def all_enabled(self) -> bool:
        return all(self.enabled_mask)

    @property
    def feedback_complete(self) -> bool:
        """Whether every drive has answered the last SYNC (a poll for tests and diagnostics)."""
        syncs = self._syncs.value
        for axis in self._axes:
            sample = axis.supervisor.tpdo
            if sample is None or sample.sync_count != syncs:
                return False
        return True

    @property
    def syncs_sent(self) -> int:
        return self._syncs.value


def _check_axes(axes: Sequence[AxisSpec], settings: MasterSettings) -> None:
    if not axes:
        raise ValueError("at least one axis is required")
    names = [axis.name for axis in axes]
    nodes = [axis.node_id for axis in axes]
    for label, values in (("name", names), ("node_id", nodes)):
        duplicates = sorted({str(v) for v in values if values.count(v) > 1})
        if duplicates:
            raise ValueError(f"axes: duplicate {label} {', '.join(duplicates)}")
    if settings.master_node_id in nodes:
        raise ValueError(f"master_node_id = {settings.master_node_id} is also an axis node_id")
