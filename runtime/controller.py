"""The controller: one cycle of the machine, and the link the HMI and the command line use.

Each cycle, in the cyclic thread (:meth:`Controller.step`): read the drives' feedback, apply the
commands queued since the last cycle, step the machine, write the targets, send RPDOs then SYNC,
and publish one consistent :class:`~runtime.status.StatusSnapshot` by reference swap.

Other threads (Modbus server, command line) call :meth:`Controller.submit`, which checks the
command against the machine's current state at once (so an HMI gets its answer in the same
request) and queues it for the start of the next cycle, and :meth:`Controller.snapshot`, which
returns the last complete snapshot. Heavy work for a curve (validation, travel check, planning
geometry) happens in :meth:`Controller.prepare_curve`, in the caller's thread.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

from drives.errors import DriveError
from drives.master import RECONFIGURE_FAULT_KINDS
from planner.nurbs import NurbsCurve
from runtime.commands import Command, CommandCode, CommandResult
from runtime.config import MachineConfig
from runtime.curves import LoadedCurve, prepare_curve
from runtime.machine import AxisFeedbackLike, DriveRequests, Machine
from runtime.motion import MotionFeed
from runtime.scheduler import CycleTick
from runtime.status import AxisStatus, CycleStatistics, FaultKind, MachineState, StatusSnapshot

logger = logging.getLogger(__name__)

#: Commands applied per cycle at most; the rest wait for the next cycle (bounded work).
COMMANDS_PER_CYCLE = 8
#: Attempts to configure lost or restarted drives again during a reset.
RECOVERY_ATTEMPTS = 3


@dataclass(frozen=True, slots=True)
class CycleTrace:
    """One cycle as traced: the targets sent, the state after the step, any drive fault seen."""

    targets_mm: tuple[float, ...]
    state: MachineState
    drive_fault_seen: bool


class CyclicDrives(DriveRequests, Protocol):
    """The CiA-402 master as the cycle uses it."""

    def read_feedback(self) -> Sequence[AxisFeedbackLike]: ...
    def write_targets(self, positions_mm: Sequence[float | None] | None) -> None: ...
    def exchange(self) -> None: ...
    def recover(self) -> tuple[str, ...]: ...


class Controller:
    """The machine in its cycle, and the thread-safe link to it."""

    def __init__(
        self,
        config: MachineConfig,
        drives: CyclicDrives,
        *,
        statistics: Callable[[], CycleStatistics] = CycleStatistics,
        set_moving: Callable[[bool], None] = lambda moving: None,
    ) -> None:
        self.config = config
        self.drives = drives
        self.feed = MotionFeed(
            period_s=config.cycle.period_s,
            lookahead=config.planner.lookahead,
            update=config.planner.update,
        )
        self.machine = Machine(config, self.feed, drives)
        self.axis_names = tuple(axis.name for axis in config.axes)
        self._statistics = statistics
        self._set_moving = set_moving
        self._commands: queue.SimpleQueue[Command] = queue.SimpleQueue()
        self._snapshot = StatusSnapshot()
        self._heartbeat = 0
        self._moving = False
        self._curve_lock = threading.Lock()
        self._recovery: threading.Thread | None = None
        self._recovered = threading.Event()
        self.max_following_error_mm = [0.0] * len(config.axes)
        self.trace: list[CycleTrace] | None = None
        """When a list, every cycle appends what it saw and sent (tests, diagnostics)."""

    # -- any thread ------------------------------------------------------------------------

    def snapshot(self) -> StatusSnapshot:
        """The status as of the end of the last cycle."""
        return self._snapshot

    def submit(self, command: Command) -> CommandResult:
        """Check ``command`` against the current state and queue it for the next cycle.

        :returns: PENDING when queued; otherwise why it was refused (nothing was queued).
        """
        refused = self.machine.check(command)
        if refused is not None:
            return refused
        self._commands.put(command)
        return CommandResult.PENDING

    def prepare_curve(self, curve: NurbsCurve, crc32: int = 0, name: str = "") -> LoadedCurve:
        """Check a curve against travel and prepare it for planning (outside the cycle).

        :raises planner.errors.CurveError: (``TravelError`` for travel) if it cannot run here.
        """
        with self._curve_lock:
            return prepare_curve(curve, self.config, crc32=crc32, name=name)

    # -- cyclic thread ---------------------------------------------------------------------

    def step(self, tick: CycleTick) -> None:
        """One cycle; see the module docstring."""
        feedback = self.drives.read_feedback()
        if self._recovered.is_set():
            self._recovered.clear()
            self.machine.drives_reconfigured()
        for _ in range(COMMANDS_PER_CYCLE):
            try:
                command = self._commands.get_nowait()
            except queue.Empty:
                break
            result = self.machine.apply(command)
            if command.code is CommandCode.RESET and result is CommandResult.DONE:
                self._recover_lost_drives(feedback)
        targets = self.machine.step(feedback, tick.deadline_s)
        self.drives.write_targets(targets)
        self.drives.exchange()
        if self.trace is not None:
            faulted = any(fb.fault is not None for fb in feedback)
            self.trace.append(CycleTrace(targets, self.machine.state, faulted))
        self._track_moving()
        self._publish(feedback)

    def _recover_lost_drives(self, feedback: Sequence[AxisFeedbackLike]) -> None:
        """Start configuring again, in a thread of its own, drives that were lost or restarted.

        SDO transfers block, so they never run in the cycle; the machine's reset waits for the
        drives to come up healthy meanwhile.
        """
        lost = any(
            fb.fault is not None and fb.fault.kind in RECONFIGURE_FAULT_KINDS for fb in feedback
        )
        if not lost or (self._recovery is not None and self._recovery.is_alive()):
            return
        self._recovery = threading.Thread(target=self._recover, name="drive-recovery", daemon=True)
        self._recovery.start()

    def _recover(self) -> None:
        # A drive that just rebooted may miss an SDO deadline on a busy bus: try again, from its
        # communication reset, before giving up (the operator can reset once more).
        for attempt in range(1, RECOVERY_ATTEMPTS + 1):
            try:
                names = self.drives.recover()
            except DriveError as exc:
                logger.warning("reset: attempt %d: drives not recovered: %s", attempt, exc)
            else:
                logger.info("reset: drives %s configured again", ", ".join(names))
                self._recovered.set()
                return
        logger.error("reset: drives not recovered after %d attempts", RECOVERY_ATTEMPTS)

    def on_overrun_limit(self, consecutive: int) -> None:
        """Called by the cyclic task when too many consecutive periods were missed.

        With the drives disabled nothing moves and nothing needs stopping: the misses are only
        counted (and logged), so a start-up hiccup does not latch a fault.
        """
        if self.machine.state is MachineState.DISABLED:
            logger.warning("%d consecutive cycle periods missed while disabled", consecutive)
            return
        self.machine.raise_fault(
            FaultKind.CYCLE_OVERRUN,
            f"{consecutive} consecutive cycle periods missed "
            f"(limit {self.config.cycle.overrun_limit})",
        )

    def close(self) -> None:
        """Stop the planner worker."""
        self.feed.close()

    def _track_moving(self) -> None:
        moving = self.machine.state in (
            MachineState.MOVING,
            MachineState.HOLDING,
            MachineState.STOPPING,
        )
        if moving != self._moving:
            self._moving = moving
            self._set_moving(moving)

    def _publish(self, feedback: Sequence[AxisFeedbackLike]) -> None:
        machine = self.machine
        self._heartbeat = (self._heartbeat + 1) & 0xFFFF
        axes = []
        for i, (fb, target) in enumerate(zip(feedback, machine.targets, strict=True)):
            error = fb.following_error_mm
            if self._moving and abs(error) > self.max_following_error_mm[i]:
                self.max_following_error_mm[i] = abs(error)
            axes.append(
                AxisStatus(
                    name=fb.axis,
                    node_id=fb.node_id,
                    commanded_mm=target,
                    actual_mm=fb.position_mm,
                    drive_state=-1 if fb.state is None else int(fb.state),
                    following_error_mm=error,
                    fault="" if fb.fault is None else str(fb.fault),
                )
            )
        setpoint = self.feed.current
        loaded = machine.loaded
        on_curve = loaded is not None and setpoint.path is loaded.path
        self._snapshot = StatusSnapshot(
            state=machine.state,
            fault=machine.fault,
            axes=tuple(axes),
            feed_mm_s=setpoint.feed_mm_s,
            path_s_mm=setpoint.s_mm if on_curve else 0.0,
            path_length_mm=loaded.path.length_mm if loaded is not None else 0.0,
            override_percent=machine.override_percent,
            stats=self._statistics(),
            last_command_seq=machine.last_command_seq,
            last_command_result=int(machine.last_command_result),
            curve_id=machine.curve_id,
            curve_crc=loaded.crc32 if loaded is not None else 0,
            heartbeat=self._heartbeat,
            message=machine.message,
        )
