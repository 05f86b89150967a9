"""One period of the cycle process: drives, commands, machine, setpoints, status.

Per period, in this order (:meth:`Cycle.step`):

1. the RPDOs computed last period go out, then SYNC (``transmit_period``): nothing runs before
   them, so the SYNC's jitter on the wire is the wake-up jitter alone;
2. the frames received since the last period are drained and the drives' supervision and
   background work (boot, configuration, heartbeat) advance one step (``receive``, ``update``);
3. drive faults that happened are reported; commands from the mailboxes are judged and applied
   in order (at most :data:`COMMANDS_PER_PERIOD`); the HMI link watchdog and the planner's
   supervision run;
4. the machine steps (its setpoint comes from the rings the planner fills) and the next targets
   are prepared (``write_targets``);
5. the status snapshot is published.

A SHUTDOWN command stops the motion on the path, disables the drives, leaves the bus cleanly
(``begin_shutdown``) and then ends the loop (:attr:`Cycle.finished`).

Threading: the cycle process's single thread. Every call is O(axes + commands), never blocks;
log records go to the shared log ring (:mod:`runtime.cycle.logring`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from enum import Enum
from typing import Protocol

from drives.cia402 import State as DriveState
from drives.errors import DriveError
from drives.monitor import FaultKind as DriveFaultKind
from runtime.commands import Command, CommandCode, CommandOrigin, CommandResult
from runtime.config import MachineConfig
from runtime.cycle.feed import SetpointFeed
from runtime.cycle.machine import AxisFeedbackLike, DriveFault, Machine
from runtime.shared import AXIS_FAULT_BYTES, SharedState
from runtime.status import (
    CycleStatistics,
    FaultKind,
    MachineState,
    ProgramStatus,
    WatchdogState,
)

logger = logging.getLogger(__name__)

#: Commands applied per period at most; the rest wait for the next period (bounded work).
COMMANDS_PER_PERIOD = 8
#: The drives must be stopped and disabled within this time of a shutdown request, and off the
#: bus within the drives' own shutdown.
SHUTDOWN_TIMEOUT_S = 10.0

#: Drive states with the power stage on (a drive in them is not yet disabled).
_POWERED = frozenset(
    {DriveState.OPERATION_ENABLED, DriveState.QUICK_STOP_ACTIVE, DriveState.SWITCHED_ON}
)

FAULT_KINDS = {
    DriveFaultKind.EMCY: FaultKind.DRIVE_FAULT,
    DriveFaultKind.FAULT_STATE: FaultKind.DRIVE_FAULT,
    DriveFaultKind.HEARTBEAT_LOSS: FaultKind.HEARTBEAT_LOSS,
    DriveFaultKind.GUARDING: FaultKind.HEARTBEAT_LOSS,
    DriveFaultKind.STALE_FEEDBACK: FaultKind.STALE_FEEDBACK,
    DriveFaultKind.FOLLOWING_ERROR: FaultKind.FOLLOWING_ERROR,
    DriveFaultKind.BOOT: FaultKind.BOOT_FAILURE,
    DriveFaultKind.NMT: FaultKind.DRIVE_FAULT,
}


class CycleDrives(Protocol):
    """The CiA-402 master as the cycle drives it (see drives.master)."""

    def start(self) -> None: ...
    def transmit_period(self) -> None: ...
    def receive(self, now_s: float) -> None: ...
    def update(self, now_s: float) -> Sequence[AxisFeedbackLike]: ...
    def take_fault_events(self) -> Sequence[DriveFault]: ...
    def write_targets(self, positions_mm: Sequence[float | None] | None) -> None: ...
    def request_enable(self) -> None: ...
    def request_disable(self) -> None: ...
    def request_quick_stop(self) -> None: ...
    def request_fault_reset(self) -> None: ...
    def begin_shutdown(self) -> None: ...

    @property
    def shutdown_done(self) -> bool: ...


class ShutdownStep(Enum):
    NONE = "none"
    STOPPING = "stopping"
    """Braking on the path."""
    DISABLING = "disabling"
    """Stepping every drive down to SWITCH ON DISABLED."""
    LEAVING = "leaving"
    """Drives disabled; the master leaves the bus (heartbeat consumers disarmed, NMT)."""
    DONE = "done"


class HmiWatchdog:
    """The HMI link watchdog: the HMI process counts heartbeat changes and accepted commands;
    when the count stands still for the timeout while the machine moves, it fires once."""

    def __init__(self, timeout_ms: int, enabled: bool) -> None:
        self.timeout_s = timeout_ms / 1000.0
        self.state = WatchdogState.WATCHING if enabled and timeout_ms > 0 else WatchdogState.OFF
        self._count = 0
        self._since_s: float | None = None

    def check(self, count: int, now_s: float, moving: bool) -> bool:
        """Whether it fires now."""
        if self.state is WatchdogState.OFF:
            return False
        if count != self._count or self._since_s is None:
            self._count = count
            self._since_s = now_s
            self.state = WatchdogState.WATCHING
            return False
        if self.state is WatchdogState.TRIPPED or not moving:
            return False
        if now_s - self._since_s < self.timeout_s:
            return False
        self.state = WatchdogState.TRIPPED
        return True


class Cycle:
    """The machine in its period; see the module docstring.

    :param statistics: the cycle loop's timing figures (O(1)), published in the status.
    :param stop_loop: ends the period loop once the shutdown is done.
    :param moving_changed: told when the machine starts or stops moving (the garbage
        collector's policy follows it).
    """

    def __init__(
        self,
        config: MachineConfig,
        shared: SharedState,
        drives: CycleDrives,
        *,
        statistics: Callable[[], CycleStatistics] = CycleStatistics,
        stop_loop: Callable[[], None] = lambda: None,
        moving_changed: Callable[[bool], None] = lambda moving: None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.config = config
        self.shared = shared
        self.drives = drives
        self._statistics = statistics
        self._stop_loop = stop_loop
        self._moving_changed = moving_changed
        self._moving = False
        self._shutdown_asked = False
        self._clock = clock
        planner = config.planner
        self.feed = SetpointFeed(
            shared,
            period_s=config.cycle.period_s,
            amax_mm_s2=planner.amax_mm_s2,
            jmax_mm_s3=planner.jmax_mm_s3,
        )
        self.machine = Machine(config, self.feed, drives, fault_kind_of=FAULT_KINDS)
        modbus = config.modbus
        self.watchdog = HmiWatchdog(
            modbus.watchdog.timeout_ms, modbus.enabled and not modbus.read_only
        )
        self._watchdog_action = (
            CommandCode.STOP if modbus.watchdog.action == "stop" else CommandCode.HOLD
        )
        self._mailboxes = (shared.local_mailbox, shared.hmi_mailbox)
        self._planner_generation = shared.planner_generation.value
        self.shutdown = ShutdownStep.NONE
        self._shutdown_since_s = 0.0
        self._heartbeat = 0
        self._cycles = 0
        self._published_version = -1
        self._axis_faults: list[object] = [None] * len(config.axes)
        self._axis_fault_texts = [b""] * len(config.axes)
        self._peak_errors_mm = [0.0] * len(config.axes)
        self._windows_mm = tuple(axis.following_error_window_mm for axis in config.axes)
        status = shared.status
        status.set(axis_count=len(config.axes))
        self._axis_names = tuple(axis.name.encode() for axis in config.axes)

    @property
    def finished(self) -> bool:
        return self.shutdown is ShutdownStep.DONE

    def start(self) -> None:
        """Begin booting the drives (non-blocking; they come up over the next periods)."""
        self.drives.start()

    # -- the period ------------------------------------------------------------------------

    def step(self, tick: object = None) -> None:
        """One period; see the module docstring."""
        drives = self.drives
        drives.transmit_period()
        now_s = self._clock()
        drives.receive(now_s)
        feedback = drives.update(now_s)
        machine = self.machine
        for fault in drives.take_fault_events():
            machine.drive_fault(fault)
        self._apply_commands()
        if self._shutdown_asked:
            self._shutdown_asked = False
            machine.apply(Command(CommandCode.SHUTDOWN, origin=CommandOrigin.SHUTDOWN))
            self._begin_shutdown()
        self._supervise_planner()
        if self.watchdog.check(self.shared.hmi_activity.value, now_s, machine.moving):
            self._watchdog_fired()
        self._progress_shutdown(feedback, now_s)
        targets = machine.step(feedback, now_s)
        try:
            drives.write_targets(targets)
        except DriveError as exc:
            machine.raise_fault(FaultKind.DRIVE_FAULT, str(exc))
            drives.write_targets(None)
        if machine.moving != self._moving:
            self._moving = machine.moving
            self._moving_changed(self._moving)
        self._publish(feedback)

    def on_overrun_limit(self, consecutive: int) -> None:
        """Called by the period loop when too many consecutive periods were missed.

        With the drives disabled nothing moves and nothing needs stopping: the misses are only
        logged, so a start-up hiccup does not latch a fault.
        """
        limit = self.config.cycle.overrun_limit
        if self.machine.state is MachineState.DISABLED:
            logger.warning("%d consecutive periods missed while disabled", consecutive)
            return
        self.machine.raise_fault(
            FaultKind.CYCLE_OVERRUN, f"{consecutive} consecutive periods missed (limit {limit})"
        )

    # -- inputs ------------------------------------------------------------------------------

    def _apply_commands(self) -> None:
        applied = 0
        for mailbox in self._mailboxes:
            while applied < COMMANDS_PER_PERIOD:
                command = mailbox.take()
                if command is None:
                    break
                applied += 1
                if command.code is CommandCode.SHUTDOWN:
                    self._begin_shutdown()
                result = self.machine.apply(command)
                if command.code is CommandCode.START and result is CommandResult.DONE:
                    self._peak_errors_mm = [0.0] * len(self._peak_errors_mm)

    def request_shutdown(self) -> None:
        """Shut down as if the supervisor had asked (a signal handler may call it)."""
        self._shutdown_asked = True

    def _watchdog_fired(self) -> None:
        timeout_s = self.watchdog.timeout_s
        logger.warning("HMI link silent for %.1f s while moving", timeout_s)
        self.machine.apply(Command(self._watchdog_action, origin=CommandOrigin.WATCHDOG))
        self.machine.say(
            f"{self._watchdog_action.name.lower()} by watchdog: HMI link silent for {timeout_s:g} s"
        )

    def _supervise_planner(self) -> None:
        generation = self.shared.planner_generation.value
        if generation == self._planner_generation:
            return
        self._planner_generation = generation
        if self.machine.moving and self.machine.state is not MachineState.ERROR_STOP:
            self.machine.raise_fault(
                FaultKind.PLANNER_LOST,
                "planner process stopped; stopping on the planned path, restarting it",
            )

    # -- shutdown ----------------------------------------------------------------------------

    def _begin_shutdown(self) -> None:
        if self.shutdown is ShutdownStep.NONE:
            self.shutdown = ShutdownStep.STOPPING
            self._shutdown_since_s = self._clock()
            logger.info("shutdown: stopping on the path, then disabling the drives")

    def _progress_shutdown(self, feedback: Sequence[AxisFeedbackLike], now_s: float) -> None:
        step = self.shutdown
        if step in (ShutdownStep.NONE, ShutdownStep.DONE):
            return
        machine = self.machine
        late = now_s - self._shutdown_since_s > SHUTDOWN_TIMEOUT_S
        if step is ShutdownStep.STOPPING:
            if machine.state is MachineState.STOPPING and not late:
                return
            if machine.state is not MachineState.DISABLED:
                machine.apply(Command(CommandCode.DISABLE, origin=CommandOrigin.SHUTDOWN))
            self.shutdown = ShutdownStep.DISABLING
        elif step is ShutdownStep.DISABLING:
            if any(fb.state in _POWERED for fb in feedback) and not late:
                return
            self.drives.begin_shutdown()
            self.shutdown = ShutdownStep.LEAVING
        elif step is ShutdownStep.LEAVING and (self.drives.shutdown_done or late):
            if late:
                logger.warning(
                    "shutdown: drives not all left cleanly within %g s", SHUTDOWN_TIMEOUT_S
                )
            self.shutdown = ShutdownStep.DONE
            self._stop_loop()

    # -- status ------------------------------------------------------------------------------

    def _publish(self, feedback: Sequence[AxisFeedbackLike]) -> None:
        machine = self.machine
        status = self.shared.status
        if machine.version != self._published_version:
            self._published_version = machine.version
            status.set_fault(machine.fault, machine.later_faults)
            status.set_commands(tuple(machine.records))
            status.set_programs(
                _program_status(machine.program), _program_status(machine.next_program)
            )
            status.set_message(machine.message)
        self._heartbeat = (self._heartbeat + 1) & 0xFFFF
        self._cycles += 1
        in_position = not machine.moving and machine.state is not MachineState.DISABLED
        for i, (fb, target) in enumerate(zip(feedback, machine.targets, strict=True)):
            error = fb.following_error_mm
            if fb.state is not DriveState.OPERATION_ENABLED:
                # The master gives a drive that is not enabled its own position as target; how
                # far it stands off the machine's setpoint (the path) is what matters then.
                error = fb.position_mm - target
            if not abs(error) <= self._windows_mm[i]:  # NaN: not known yet, not in position
                in_position = False
            if abs(error) > self._peak_errors_mm[i]:
                self._peak_errors_mm[i] = abs(error)
            fault = fb.fault
            if fault is not self._axis_faults[i]:
                self._axis_faults[i] = fault
                self._axis_fault_texts[i] = b"" if fault is None else fault.text.encode()
            status.set_axis(
                i,
                self._axis_names[i],
                fb.node_id,
                target,
                fb.position_mm,
                error,
                self._peak_errors_mm[i],
                -1 if fb.state is None else int(fb.state),
                fb.statusword,
                int(fb.phase),
                self._axis_fault_texts[i][:AXIS_FAULT_BYTES],
            )
        stats = self._statistics()
        s_mm, length_mm = machine.path_position()
        setpoint = self.feed.current
        status.set(
            heartbeat=self._heartbeat,
            cycle_count=self._cycles,
            state=machine.state,
            phase=machine.phase,
            watchdog=self.watchdog.state,
            in_position=in_position,
            feed_mm_s=setpoint.feed_mm_s,
            path_s_mm=s_mm,
            path_length_mm=length_mm,
            override_percent=machine.override_percent,
            stats_cycles=stats.cycles,
            lateness_last_us=stats.lateness_last_us,
            lateness_p50_us=stats.lateness_p50_us,
            lateness_p99_us=stats.lateness_p99_us,
            lateness_p999_us=stats.lateness_p999_us,
            lateness_max_us=stats.lateness_max_us,
            execution_last_us=stats.execution_last_us,
            execution_max_us=stats.execution_max_us,
            missed_periods=stats.missed_periods,
            override_latency_periods=min(self.feed.override_latency_periods, 0xFFFF),
            override_rest_wait_periods=min(self.feed.override_rest_wait_periods, 0xFFFF),
            overrides_applied=self.feed.overrides_applied & 0xFFFF_FFFF,
        )
        status.publish()


def _program_status(program: object) -> ProgramStatus | None:
    if program is None:
        return None
    return ProgramStatus(program.program_id, program.name, program.crc32, program.length_mm)
