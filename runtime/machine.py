"""The machine state machine, after PLCopen: commands, motion, faults.

States (:class:`runtime.status.MachineState`): Disabled, Standby, Moving, Holding, Stopping,
ErrorStop. :data:`runtime.commands.ALLOWED` says which command each state accepts; anything else
is rejected with a reason and changes nothing. Motion comes from :class:`runtime.motion.MotionFeed`;
the drives are driven through the non-blocking request API of the CiA-402 master.

Threading: every method runs in the cyclic thread, once per cycle (:meth:`step`) or when a queued
command is applied at the start of a cycle (:meth:`apply`). Nothing here blocks: enabling,
resetting and stopping progress over cycles.

Invariants: the setpoint never jumps: while the drives are not enabled it is their actual
position; motion starts from where the axes stand (a straight approach to the curve's start, then
the curve) and every change of plan brakes or re-plans from the current feed and acceleration.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import Protocol

import numpy as np

from drives.cia402 import State as DriveState
from drives.monitor import AxisFault
from drives.monitor import FaultKind as DriveFaultKind
from planner.nurbs import NurbsCurve
from planner.stream import Path
from planner.types import Limits, MotionState
from runtime.commands import (
    OVERRIDE_MAX_PERCENT,
    OVERRIDE_MIN_PERCENT,
    Command,
    CommandCode,
    CommandResult,
    check_allowed,
)
from runtime.config import MachineConfig
from runtime.curves import LoadedCurve, limits_for_curve, planner_limits
from runtime.motion import FeedEvent, FeedMode, MotionFeed, Segment
from runtime.status import Fault, FaultKind, MachineState

logger = logging.getLogger(__name__)

#: An approach shorter than this is skipped: the axes already stand at the curve's start.
APPROACH_MIN_MM = 1e-6
#: Enabling or resetting the drives must finish within this time, plus twice the boot timeout
#: (a reset may have to configure a restarted drive again).
RECOVERY_TIMEOUT_S = 3.0

_FAULT_KINDS = {
    DriveFaultKind.EMCY: FaultKind.DRIVE_FAULT,
    DriveFaultKind.FAULT_STATE: FaultKind.DRIVE_FAULT,
    DriveFaultKind.HEARTBEAT_LOSS: FaultKind.HEARTBEAT_LOSS,
    DriveFaultKind.STALE_FEEDBACK: FaultKind.STALE_FEEDBACK,
    DriveFaultKind.FOLLOWING_ERROR: FaultKind.FOLLOWING_ERROR,
    DriveFaultKind.BOOT: FaultKind.BOOT_FAILURE,
    DriveFaultKind.NMT: FaultKind.DRIVE_FAULT,
}


class AxisFeedbackLike(Protocol):
    """One axis's feedback as the CiA-402 master reports it each cycle."""

    axis: str
    node_id: int
    state: DriveState | None
    position_mm: float
    following_error_mm: float
    fault: AxisFault | None


class DriveRequests(Protocol):
    """What the machine asks of the drives (the CiA-402 master's non-blocking requests)."""

    def request_enable(self) -> None: ...
    def request_disable(self) -> None: ...
    def request_quick_stop(self) -> None: ...
    def request_fault_reset(self) -> None: ...


class Machine:
    """The machine: state, loaded curve, override, active fault, and the setpoint of each axis."""

    def __init__(self, config: MachineConfig, feed: MotionFeed, drives: DriveRequests) -> None:
        self.config = config
        self.feed = feed
        self.drives = drives
        self.state = MachineState.DISABLED
        self.fault: Fault | None = None
        self.message = "disabled"
        self.override_percent = 100.0
        self.loaded: LoadedCurve | None = None
        self.curve_id = 0
        self.last_command_seq = 0
        self.last_command_result = CommandResult.NONE
        self._limits = planner_limits(config)
        self._period_s = config.cycle.period_s
        self._axis_count = len(config.axes)
        self._targets: tuple[float, ...] = (0.0,) * self._axis_count
        self._actual: tuple[float, ...] = (0.0,) * self._axis_count
        self._held: tuple[float, ...] = self._targets
        self._power_on = False
        """The operator wants the drives enabled (enable, until disable)."""
        self._recovery: MachineState | None = None
        """Enabling or resetting toward this state (STANDBY or DISABLED) over the next cycles."""
        self._recovery_since_s: float | None = None
        self._recovery_timeout_s = RECOVERY_TIMEOUT_S + 2 * config.can.boot_timeout_s
        self._quick_stopping = False
        self._continue = False
        """MOVING wants to follow the job on from where the feed rests, once the override > 0."""
        self._start_segments: tuple[Segment, ...] = ()

    # -- commands --------------------------------------------------------------------------

    def apply(self, command: Command) -> CommandResult:
        """Apply one command at the start of a cycle; records its result for the status."""
        result = self._apply(command)
        if command.seq is not None:
            self.last_command_seq = command.seq
        self.last_command_result = result
        if result is CommandResult.DONE:
            logger.info("%s (%s): %s", command.code.name.lower(), command.origin, self.state.name)
        else:
            logger.warning(
                "%s (%s) rejected: %s", command.code.name.lower(), command.origin, result.name
            )
        return result

    def check(self, command: Command) -> CommandResult | None:
        """Why ``command`` would be rejected now, or None if it is allowed (changes nothing)."""
        if check_allowed(self.state, command.code) is not None:
            return CommandResult.REJECTED_STATE
        if command.code is CommandCode.SET_OVERRIDE:
            value = command.override_percent
            if value is None or not OVERRIDE_MIN_PERCENT <= value <= OVERRIDE_MAX_PERCENT:
                return CommandResult.INVALID_PARAMETER
        if command.code is CommandCode.START and self.loaded is None:
            return CommandResult.NO_CURVE
        if command.code is CommandCode.LOAD_CURVE and not isinstance(command.curve, LoadedCurve):
            return CommandResult.INVALID_PARAMETER
        if command.code is CommandCode.ENABLE and self._recovery is not None:
            return CommandResult.REJECTED_STATE
        return None

    def _apply(self, command: Command) -> CommandResult:
        refused = self.check(command)
        if refused is not None:
            return refused
        code = command.code
        if code is CommandCode.ENABLE:
            self._power_on = True
            self.drives.request_enable()
            self._begin_recovery(MachineState.STANDBY, "enabling drives")
        elif code is CommandCode.DISABLE:
            self._power_on = False
            self._recovery = None
            self.drives.request_disable()
            self.feed.rest_at(self._actual)
            if self.state is MachineState.ERROR_STOP:
                self.message = "drives disabled; reset clears the fault"
            else:
                self._enter(MachineState.DISABLED, "disabled")
        elif code is CommandCode.LOAD_CURVE:
            self.loaded = command.curve
            self.curve_id += 1
            self.message = f"curve {self.curve_id} loaded"
        elif code is CommandCode.START:
            self._start()
        elif code is CommandCode.HOLD:
            self._brake()
            self._enter(MachineState.HOLDING, f"hold by {command.origin}")
        elif code is CommandCode.RESUME:
            self._continue = True
            self._enter(MachineState.MOVING, f"resume by {command.origin}")
        elif code is CommandCode.STOP:
            self._brake()
            self._continue = False
            self._enter(MachineState.STOPPING, f"stop by {command.origin}")
        elif code is CommandCode.QUICK_STOP:
            self._quick_stop()
            self._enter(MachineState.STOPPING, f"quick stop by {command.origin}")
        elif code is CommandCode.RESET:
            self.drives.request_fault_reset()
            if self._power_on:
                self.drives.request_enable()
            target = MachineState.STANDBY if self._power_on else MachineState.DISABLED
            self._begin_recovery(target, "reset: clearing the fault")
        elif code is CommandCode.SET_OVERRIDE:
            self._set_override(float(command.override_percent))
        return CommandResult.DONE

    def drives_reconfigured(self) -> None:
        """Lost drives were configured again during a reset: reset and enable them afresh
        (their old requests did not survive the restart), with the timeout started anew."""
        if self._recovery is None:
            return
        self.drives.request_fault_reset()
        if self._power_on:
            self.drives.request_enable()
        self._recovery_since_s = None

    def raise_fault(
        self, kind: FaultKind, text: str, *, axis: str | None = None, emcy_code: int = 0
    ) -> None:
        """Stop every axis (controlled or quick, by configuration) and enter ErrorStop."""
        if self.state is MachineState.ERROR_STOP and self.fault is not None:
            return
        self.fault = Fault(kind, text, axis, emcy_code)
        logger.error("fault: %s", text)
        self._recovery = None
        self._continue = False
        if self.state is MachineState.DISABLED:
            self.feed.rest_at(self._actual)
        elif self.config.machine.fault_reaction == "quick_stop" or self.feed.current.path is None:
            self._quick_stop()
        else:
            self._brake()
        self._enter(MachineState.ERROR_STOP, f"error stop: {text}")

    # -- cycle -----------------------------------------------------------------------------

    def step(self, feedback: Sequence[AxisFeedbackLike], now_s: float) -> tuple[float, ...]:
        """One cycle: supervise the drives, advance the motion; returns each axis's target."""
        self._actual = tuple(fb.position_mm for fb in feedback)
        # While a reset is in progress, the old faults are expected until the drives clear them.
        resetting = self._recovery is not None and self.state is MachineState.ERROR_STOP
        for fb in feedback:
            if fb.fault is not None and not resetting:
                self._refine_fault(fb)
                self.raise_fault(
                    _FAULT_KINDS[fb.fault.kind],
                    str(fb.fault),
                    axis=fb.axis,
                    emcy_code=fb.fault.emcy_code or 0,
                )
                break
        self._progress_recovery(feedback, now_s)
        if self._quick_stopping:
            self._progress_quick_stop(feedback)
        else:
            self._on_feed_event(self.feed.take())
            self._follow_on()
        return self._compose_targets()

    def _refine_fault(self, fb: AxisFeedbackLike) -> None:
        """Keep the recorded fault up to date with its axis's diagnosis (stale feedback turns
        out to be a lost heartbeat); stopping already happened when it was first seen."""
        fault = self.fault
        if (
            self.state is MachineState.ERROR_STOP
            and fault is not None
            and fault.axis == fb.axis
            and fault.text != str(fb.fault)
        ):
            self.fault = Fault(
                _FAULT_KINDS[fb.fault.kind], str(fb.fault), fb.axis, fb.fault.emcy_code or 0
            )
            self.message = f"error stop: {self.fault.text}"

    def _begin_recovery(self, target: MachineState, message: str) -> None:
        self._recovery = target
        self._recovery_since_s = None
        self.message = message

    def _progress_recovery(self, feedback: Sequence[AxisFeedbackLike], now_s: float) -> None:
        target = self._recovery
        if target is None:
            return
        if self._recovery_since_s is None:
            self._recovery_since_s = now_s
        healthy = all(fb.fault is None for fb in feedback)
        enabled = [fb.state is DriveState.OPERATION_ENABLED for fb in feedback]
        if healthy and (all(enabled) if target is MachineState.STANDBY else not any(enabled)):
            self._recovery = None
            self.fault = None
            self.feed.rest_at(self._actual)
            self._held = self._actual
            self._enter(target, "enabled" if target is MachineState.STANDBY else "reset")
        elif now_s - self._recovery_since_s > self._recovery_timeout_s:
            self._recovery = None
            waiting = [fb.axis for fb, on in zip(feedback, enabled, strict=True) if not on]
            faulted = [str(fb.fault) for fb in feedback if fb.fault is not None]
            text = f"drives not ready within {RECOVERY_TIMEOUT_S:g} s: " + "; ".join(
                faulted or [f"not enabled: {', '.join(waiting)}"]
            )
            if self.state is MachineState.ERROR_STOP:
                self.message = f"reset failed: {text}"
                logger.error(self.message)
            else:
                self.raise_fault(FaultKind.DRIVE_FAULT, text)

    def _progress_quick_stop(self, feedback: Sequence[AxisFeedbackLike]) -> None:
        enabled = (DriveState.OPERATION_ENABLED, DriveState.QUICK_STOP_ACTIVE)
        self.feed.rest_at(self._actual)
        if all(fb.state not in enabled for fb in feedback):
            self._quick_stopping = False
            if self.state is MachineState.STOPPING:
                self._enter(MachineState.DISABLED, "quick stop done, drives disabled")

    def _on_feed_event(self, event: FeedEvent) -> None:
        if event is FeedEvent.FINISHED and self.state is MachineState.MOVING:
            self._continue = False
            self._enter(MachineState.STANDBY, "curve finished")
        elif event is FeedEvent.UNDERRUN:
            self.raise_fault(FaultKind.BUFFER_UNDERRUN, "setpoint buffer underrun during motion")
        elif event is FeedEvent.PLANNER_FAILED:
            self.raise_fault(FaultKind.PLANNER_ERROR, self.feed.failure or "planner failed")
        elif self.state is MachineState.STOPPING and self.feed.mode is FeedMode.IDLE:
            self._enter(MachineState.STANDBY, "stopped")

    def _follow_on(self) -> None:
        """Start or continue the job once the feed rests and the override allows motion."""
        if not (
            self.state is MachineState.MOVING
            and self._continue
            and self.feed.mode is FeedMode.IDLE
            and self.override_percent > 0
        ):
            return
        self._continue = False
        segments = self._start_segments or self.feed.remaining_segments()
        self._start_segments = ()
        if not segments:
            self._enter(MachineState.STANDBY, "curve finished")
            return
        self.feed.follow(segments, self._limits_now(segments[0].path.curve.dimension))

    # -- motion ----------------------------------------------------------------------------

    def _limits_now(self, dimension: int) -> Limits:
        """The path limits with the feed override applied (only called with override > 0)."""
        return limits_for_curve(self._limits, dimension).with_feed_override(
            self.override_percent / 100.0
        )

    def _start(self) -> None:
        loaded = self.loaded
        assert loaded is not None
        curve = loaded.curve
        here = np.array(self._targets[: curve.dimension])
        segments: list[Segment] = []
        if float(np.linalg.norm(curve.start_point - here)) > APPROACH_MIN_MM:
            approach = NurbsCurve.from_arrays(1, [here, curve.start_point], [0, 0, 1, 1])
            limits = limits_for_curve(self._limits, curve.dimension)
            segments.append(Segment(Path(approach, limits, self._period_s), MotionState(0.0)))
        segments.append(Segment(loaded.path, MotionState(0.0)))
        self._held = self._targets
        self.feed.rest_at(self._targets)
        self._start_segments = tuple(segments)
        self._continue = True
        self._enter(MachineState.MOVING, "moving")

    def _set_override(self, percent: float) -> None:
        self.override_percent = percent
        self.message = f"override {percent:g} %"
        if self.state is not MachineState.MOVING:
            return
        if percent == 0.0:
            self._brake()
            self._continue = True
        elif self.feed.mode in (FeedMode.PLANNED, FeedMode.STARTING):
            path = self.feed.current.path
            dimension = path.curve.dimension if path is not None else self._axis_count
            self.feed.change_limits(self._limits_now(dimension))

    def _brake(self) -> None:
        self.feed.brake(amax_mm_s2=self._limits.amax_mm_s2, jmax_mm_s3=self._limits.jmax_mm_s3)

    def _quick_stop(self) -> None:
        self.drives.request_quick_stop()
        self.feed.rest_at(self._actual)
        self._quick_stopping = True

    def _enter(self, state: MachineState, message: str) -> None:
        if state is not self.state:
            logger.info("state %s -> %s (%s)", self.state.name, state.name, message)
        self.state = state
        self.message = message

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
