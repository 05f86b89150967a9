"""The machine state machine, after PLCopen: commands, programs, motion, faults.

States (:class:`runtime.status.MachineState`): Disabled, Standby, Moving, Holding, Stopping,
ErrorStop. Commands are judged when their turn comes, in mailbox order, against the state the
machine is in then (:data:`runtime.commands.ALLOWED` plus their parameters); a refused command
changes nothing and leaves its refusal in its :class:`~runtime.commands.CommandRecord`.

Programs: LOAD_CURVE at rest makes the program the active one; while the machine moves it
becomes the next program (the running one is untouched), which runs as soon as the current one
ends (or on START, if the current one was stopped). START moves in a straight jerk-limited line
from where the axes stand to the program's start (the approach), then follows its curve to its
exact end point.

Faults: the first fault is the cause of the ErrorStop and stays until a reset; every later fault
(a second drive faulting while the machine stops, say) is listed after it. The stop itself
follows the configured reaction for the case: a fault of an axis's drive (EMCY, fault state,
lost drive) ``machine.axis_fault_reaction``, any other fault ``machine.fault_reaction``:
``stop`` brakes every axis along the path (the path is kept by every axis that can still
follow it), ``quick_stop`` asks every drive for its quick stop (each axis stops on its own ramp:
the quickest stop, off the path by what the ramps differ).

Threading: every method runs in the cycle process's thread, once per period (:meth:`step`) or
when a command is applied at the start of a period. Nothing here blocks: enabling, resetting
and stopping progress over periods.

Invariants: the setpoint never jumps: while the drives are not enabled it is their actual
position; motion starts from where the axes stand and every change of plan brakes or re-plans
from the current feed and acceleration.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Sequence
from typing import Protocol

from drives.cia402 import State as DriveState
from runtime.commands import (
    OVERRIDE_MAX_PERCENT,
    OVERRIDE_MIN_PERCENT,
    Command,
    CommandCode,
    CommandRecord,
    CommandResult,
    check_allowed,
)
from runtime.config import MachineConfig
from runtime.cycle.feed import FeedEvent, FeedMode, JobStart, SetpointFeed
from runtime.programs import Program
from runtime.shared import LATER_FAULTS, RECENT_COMMANDS, SegmentKind, SegmentSpec
from runtime.status import Fault, FaultKind, MachineState, MotionPhase

logger = logging.getLogger(__name__)

#: An approach shorter than this is skipped: the axes already stand at the program's start.
APPROACH_MIN_MM = 1e-6
#: Enabling or resetting the drives must finish within this time, plus twice the boot timeout
#: (a reset may wait for a restarted drive to be configured again).
RECOVERY_TIMEOUT_S = 3.0
#: A job whose first setpoints do not come within this time is a planner fault.
PLAN_START_TIMEOUT_S = 10.0


class DriveFault(Protocol):
    """A fault of one axis's drive as the CiA-402 master reports it."""

    axis: str
    kind: object
    emcy_code: int | None
    text: str


class AxisFeedbackLike(Protocol):
    """One axis's feedback as the CiA-402 master reports it each period."""

    axis: str
    node_id: int
    state: DriveState | None
    statusword: int
    phase: int
    position_mm: float
    following_error_mm: float
    fault: DriveFault | None


class DriveRequests(Protocol):
    """What the machine asks of the drives (the CiA-402 master's non-blocking requests)."""

    def request_enable(self) -> None: ...
    def request_disable(self) -> None: ...
    def request_quick_stop(self) -> None: ...
    def request_fault_reset(self) -> None: ...


class Machine:
    """The machine: state, programs, override, faults, and the setpoint of each axis."""

    def __init__(
        self,
        config: MachineConfig,
        feed: SetpointFeed,
        drives: DriveRequests,
        *,
        fault_kind_of: dict[object, FaultKind],
    ) -> None:
        self.config = config
        self.feed = feed
        self.drives = drives
        self.state = MachineState.DISABLED
        self.fault: Fault | None = None
        self.later_faults: tuple[Fault, ...] = ()
        self.message = "disabled"
        self.override_percent = 100.0
        self.program: Program | None = None
        self.next_program: Program | None = None
        self.records: deque[CommandRecord] = deque(maxlen=RECENT_COMMANDS)
        self.version = 0
        """+1 whenever something the status shows beside the motion changes (fault, records,
        programs, message), so the publisher repacks those parts only then."""
        self._fault_kind_of = fault_kind_of
        self._axis_count = len(config.axes)
        self._targets: tuple[float, ...] = (0.0,) * self._axis_count
        self._actual: tuple[float, ...] = (0.0,) * self._axis_count
        self._held: tuple[float, ...] = self._targets
        self._power_on = False
        """The operator wants the drives enabled (enable, until disable)."""
        self._recovery: MachineState | None = None
        """Enabling or resetting toward this state (STANDBY or DISABLED) over the next periods."""
        self._recovery_since_s: float | None = None
        self._recovery_timeout_s = RECOVERY_TIMEOUT_S + 2 * config.can.boot_timeout_s
        self._quick_stopping = False
        self._continue = False
        """MOVING wants to follow the job on from where the feed rests, once the override > 0."""
        self._start_job: tuple[tuple[SegmentSpec, ...], JobStart] | None = None
        self._approach_mm = 0.0
        self._starting_since_s: float | None = None

    # -- commands --------------------------------------------------------------------------

    def apply(self, command: Command) -> CommandResult:
        """Judge and apply one command at the start of a period; records its result."""
        result = self._judge(command)
        if result is CommandResult.DONE:
            self._execute(command)
            logger.info(
                "%s (%s): %s",
                command.code.name.lower(),
                command.origin.name.lower(),
                self.state.name,
            )
        else:
            logger.warning(
                "%s (%s) refused: %s",
                command.code.name.lower(),
                command.origin.name.lower(),
                result.name,
            )
        self.record(command, result)
        return result

    def record(self, command: Command, result: CommandResult) -> None:
        """Publish the judgement of ``command`` (also for commands the cycle makes itself)."""
        self.records.append(
            CommandRecord(command.ticket, command.origin, command.seq, command.code, result)
        )
        self.version += 1

    def _judge(self, command: Command) -> CommandResult:
        code = command.code
        if check_allowed(self.state, code) is not None:
            return CommandResult.REJECTED_STATE
        if code is CommandCode.SET_OVERRIDE:
            value = command.override_percent
            if value is None or not OVERRIDE_MIN_PERCENT <= value <= OVERRIDE_MAX_PERCENT:
                return CommandResult.INVALID_PARAMETER
        if code is CommandCode.START and self.program is None and self.next_program is None:
            return CommandResult.NO_CURVE
        if code is CommandCode.LOAD_CURVE:
            program = command.program
            if program is None or program.dimension > self._axis_count:
                return CommandResult.INVALID_PARAMETER
        if code is CommandCode.ENABLE and self._recovery is not None:
            return CommandResult.REJECTED_STATE
        return CommandResult.DONE

    def _execute(self, command: Command) -> None:
        code = command.code
        by = command.origin.name.lower().replace("_", " ")
        if code is CommandCode.ENABLE:
            self._power_on = True
            self.drives.request_enable()
            self._begin_recovery(MachineState.STANDBY, "enabling drives")
        elif code is CommandCode.DISABLE:
            self._disable()
        elif code is CommandCode.LOAD_CURVE:
            self._load(command.program)
        elif code is CommandCode.CLEAR_NEXT:
            self.next_program = None
            self.say("next program cleared")
        elif code is CommandCode.START:
            if self.program is None:
                self._promote_next()
            self._start()
        elif code is CommandCode.HOLD:
            self._brake()
            self._enter(MachineState.HOLDING, f"hold by {by}")
        elif code is CommandCode.RESUME:
            self._continue = True
            self._enter(MachineState.MOVING, f"resume by {by}")
        elif code is CommandCode.STOP:
            self._brake()
            self._continue = False
            self._start_job = None
            self._enter(MachineState.STOPPING, f"stop by {by}")
        elif code is CommandCode.QUICK_STOP:
            self._start_job = None
            self._quick_stop()
            self._enter(MachineState.STOPPING, f"quick stop by {by}")
        elif code is CommandCode.RESET:
            self.drives.request_fault_reset()
            if self._power_on:
                self.drives.request_enable()
            target = MachineState.STANDBY if self._power_on else MachineState.DISABLED
            self._begin_recovery(target, "reset: clearing the fault")
        elif code is CommandCode.SET_OVERRIDE:
            self._set_override(float(command.override_percent or 0.0))
        elif code is CommandCode.SHUTDOWN:
            self._shutdown()

    def _load(self, program: Program | None) -> None:
        assert program is not None
        if self.state in (MachineState.MOVING, MachineState.HOLDING, MachineState.STOPPING):
            self.next_program = program
            self.say(f"program {program.program_id} ({program.name}) loaded as next program")
        else:
            self.program = program
            self.say(f"program {program.program_id} ({program.name}) loaded")

    def _promote_next(self) -> None:
        if self.next_program is not None:
            self.program, self.next_program = self.next_program, None
            self.version += 1

    def _disable(self) -> None:
        self._power_on = False
        self._recovery = None
        self.drives.request_disable()
        self.feed.rest_at(self._actual)
        if self.state is MachineState.ERROR_STOP:
            self.say("drives disabled; reset clears the fault")
        else:
            self._enter(MachineState.DISABLED, "disabled")

    def _shutdown(self) -> None:
        if self.state in (MachineState.MOVING, MachineState.HOLDING):
            self._brake()
            self._continue = False
            self._start_job = None
            self._enter(MachineState.STOPPING, "stop for shutdown")

    def raise_fault(
        self,
        kind: FaultKind,
        text: str,
        *,
        axis: str | None = None,
        emcy_code: int = 0,
        axis_fault: bool = False,
    ) -> None:
        """Report a fault: the first one stops every axis (by the configured reaction for the
        case) and enters ErrorStop; later ones are listed beside it."""
        fault = Fault(kind, text, axis, emcy_code)
        if self.state is MachineState.ERROR_STOP and self.fault is not None:
            if fault != self.fault and fault not in self.later_faults:
                self.later_faults = (*self.later_faults, fault)[-LATER_FAULTS:]
                self.version += 1
                logger.error("further fault: %s", text)
            return
        self.fault = fault
        self.later_faults = ()
        logger.error("fault: %s", text)
        self._recovery = None
        self._continue = False
        self._start_job = None
        reaction = (
            self.config.machine.axis_fault_reaction
            if axis_fault
            else self.config.machine.fault_reaction
        )
        if self.state is MachineState.DISABLED:
            self.feed.rest_at(self._actual)
        elif reaction == "quick_stop" or self.feed.current.segment < 0:
            self._quick_stop()
        else:
            self._brake()
        self._enter(MachineState.ERROR_STOP, f"error stop: {text}")

    def drive_fault(self, fault: DriveFault) -> None:
        """A drive reported a fault (as an event, when it happened)."""
        self.raise_fault(
            self._fault_kind_of.get(fault.kind, FaultKind.DRIVE_FAULT),
            f"axis {fault.axis}: {fault.text}",
            axis=fault.axis,
            emcy_code=fault.emcy_code or 0,
            axis_fault=True,
        )

    # -- period ----------------------------------------------------------------------------

    def step(self, feedback: Sequence[AxisFeedbackLike], now_s: float) -> tuple[float, ...]:
        """One period: supervise, advance the motion; returns each axis's target [mm]."""
        self._actual = tuple(fb.position_mm for fb in feedback)
        self._progress_recovery(feedback, now_s)
        if self._quick_stopping:
            self._progress_quick_stop(feedback)
        else:
            self._on_feed_event(self.feed.take(), now_s)
            self._follow_on(now_s)
        return self._compose_targets()

    def _begin_recovery(self, target: MachineState, message: str) -> None:
        self._recovery = target
        self._recovery_since_s = None
        self.say(message)

    def _progress_recovery(self, feedback: Sequence[AxisFeedbackLike], now_s: float) -> None:
        target = self._recovery
        if target is None:
            return
        if self._recovery_since_s is None:
            self._recovery_since_s = now_s
        healthy = all(fb.fault is None for fb in feedback)
        enabled = [fb.state is DriveState.OPERATION_ENABLED for fb in feedback]
        if target is MachineState.STANDBY and not all(enabled):
            # A drive still booting (or configured again after a restart) starts from a
            # disable request: ask again until every drive is up.
            self.drives.request_enable()
        if healthy and (all(enabled) if target is MachineState.STANDBY else not any(enabled)):
            self._recovery = None
            self.fault = None
            self.later_faults = ()
            self.feed.rest_at(self._actual)
            self._held = self._actual
            self._enter(target, "enabled" if target is MachineState.STANDBY else "reset")
        elif now_s - self._recovery_since_s > self._recovery_timeout_s:
            self._recovery = None
            waiting = [fb.axis for fb, on in zip(feedback, enabled, strict=True) if not on]
            faulted = [f"axis {fb.axis}: {fb.fault.text}" for fb in feedback if fb.fault]
            text = f"drives not ready within {self._recovery_timeout_s:g} s: " + "; ".join(
                faulted or [f"not enabled: {', '.join(waiting)}"]
            )
            if self.state is MachineState.ERROR_STOP:
                self.say(f"reset failed: {text}")
                logger.error(self.message)
            else:
                self.raise_fault(FaultKind.DRIVE_FAULT, text)

    def _progress_quick_stop(self, feedback: Sequence[AxisFeedbackLike]) -> None:
        stopping = (DriveState.OPERATION_ENABLED, DriveState.QUICK_STOP_ACTIVE)
        self.feed.rest_at(self._actual)
        if all(fb.state not in stopping for fb in feedback):
            self._quick_stopping = False
            if self.state is MachineState.STOPPING:
                # The operator's quick stop ends with the power off; a fault's keeps the
                # operator's wish, so the reset enables the drives again.
                self._power_on = False
                self._enter(MachineState.DISABLED, "quick stop done, drives disabled")

    def _on_feed_event(self, event: FeedEvent, now_s: float) -> None:
        if event is FeedEvent.FINISHED and self.state is MachineState.MOVING:
            self._continue = False
            if self.next_program is not None:
                self._promote_next()
                self._start()
                self.say(f"program finished; next program {self.program.program_id} started")
            else:
                self._enter(MachineState.STANDBY, "program finished")
        elif event is FeedEvent.UNDERRUN:
            self.raise_fault(FaultKind.BUFFER_UNDERRUN, self.feed.problem)
        elif event is FeedEvent.PLANNER_FAILED:
            self.raise_fault(FaultKind.PLANNER_ERROR, self.feed.problem or "planner failed")
        elif self.state is MachineState.STOPPING and self.feed.mode is FeedMode.IDLE:
            self._promote_next()
            self._enter(MachineState.STANDBY, "stopped")
        if self.feed.mode is FeedMode.STARTING:
            if self._starting_since_s is None:
                self._starting_since_s = now_s
            elif now_s - self._starting_since_s > PLAN_START_TIMEOUT_S:
                self.raise_fault(
                    FaultKind.PLANNER_ERROR,
                    f"planner: no setpoints within {PLAN_START_TIMEOUT_S:g} s of the request",
                )
        else:
            self._starting_since_s = None

    def _follow_on(self, now_s: float) -> None:
        """Start or continue the job once the feed rests and the override allows motion."""
        if not (
            self.state is MachineState.MOVING
            and self._continue
            and self.feed.mode is FeedMode.IDLE
            and self.override_percent > 0
        ):
            return
        self._continue = False
        job = self._start_job or self.feed.remaining()
        self._start_job = None
        if job is None:
            self._enter(MachineState.STANDBY, "program finished")
            return
        segments, start = job
        self.feed.follow(segments, start, self.override_percent)

    # -- motion ----------------------------------------------------------------------------

    def _start(self) -> None:
        program = self.program
        assert program is not None
        # From the setpoint just taken: a program that finished this period ends on its last
        # row, which the targets of the period before do not hold yet.
        here = self._compose_targets()[: program.dimension]
        segments: list[SegmentSpec] = []
        approach_mm = math.dist(here, program.start_mm)
        if approach_mm > APPROACH_MIN_MM:
            segments.append(SegmentSpec(SegmentKind.LINE, here, program.start_mm))
        segments.append(SegmentSpec(SegmentKind.PROGRAM, program=program))
        self._approach_mm = approach_mm if len(segments) == 2 else 0.0
        self._held = self._targets
        self.feed.rest_at(here)
        self._start_job = (tuple(segments), JobStart())
        self._continue = True
        self._enter(MachineState.MOVING, f"moving: program {program.program_id}")

    def _set_override(self, percent: float) -> None:
        self.override_percent = percent
        self.say(f"override {percent:g} %")
        if self.state is not MachineState.MOVING:
            return
        if percent == 0.0:
            self._brake()
            self._continue = True
        elif self.feed.mode in (FeedMode.PLANNED, FeedMode.STARTING):
            self.feed.change_override(percent)

    def _brake(self) -> None:
        """Brake on the path now (a job asked for but not begun stays pending for a resume)."""
        self._start_job = self.feed.awaited() or self._start_job
        self.feed.brake()

    def _quick_stop(self) -> None:
        self.drives.request_quick_stop()
        self.feed.rest_at(self._actual)
        self._quick_stopping = True

    def _enter(self, state: MachineState, message: str) -> None:
        if state is not self.state:
            logger.info("state %s -> %s (%s)", self.state.name, state.name, message)
        self.state = state
        self.say(message)

    def say(self, message: str) -> None:
        """Set the status message (the reason of the last change)."""
        self.message = message
        self.version += 1

    # -- status ----------------------------------------------------------------------------

    @property
    def phase(self) -> MotionPhase:
        mode = self.feed.mode
        if mode is FeedMode.BRAKING:
            return MotionPhase.BRAKING
        if mode is FeedMode.STARTING or (
            mode is FeedMode.IDLE and self._start_job is not None and self._continue
        ):
            return MotionPhase.STARTING
        segment = self.feed.current.segment
        if mode is FeedMode.IDLE or segment < 0:
            return MotionPhase.IDLE
        return MotionPhase.APPROACH if self._on_approach(segment) else MotionPhase.PROGRAM

    def _on_approach(self, segment: int) -> bool:
        return self._approach_mm > 0.0 and segment == 0

    def path_position(self) -> tuple[float, float]:
        """(distance travelled, length) of the current phase's path [mm]."""
        segment = self.feed.current.segment
        if segment >= 0 and self._on_approach(segment):
            return self.feed.current.s_mm, self._approach_mm
        length = self.program.length_mm if self.program is not None else 0.0
        s = self.feed.current.s_mm if segment >= 0 else 0.0
        return s, length

    # -- targets ---------------------------------------------------------------------------

    def _compose_targets(self) -> tuple[float, ...]:
        if self.state is MachineState.DISABLED or self._quick_stopping:
            self._targets = self._actual
            return self._targets
        position = self.feed.current.position_mm
        if not position:
            return self._targets
        self._targets = tuple(
            position[i] if i < len(position) else self._held[i] for i in range(self._axis_count)
        )
        if not all(math.isfinite(v) for v in self._targets):
            raise FloatingPointError(f"non-finite setpoint {self._targets}")
        return self._targets

    @property
    def targets(self) -> tuple[float, ...]:
        return self._targets

    @property
    def moving(self) -> bool:
        return self.state in (MachineState.MOVING, MachineState.HOLDING, MachineState.STOPPING)
