"""The machine's status: states, fault kinds, and the snapshot the cycle publishes every period.

The cycle process builds one :class:`StatusSnapshot` per period and publishes it in shared
memory (:mod:`runtime.shared`); readers in other processes (the HMI server, the command line)
always decode one complete, consistent period. Before the cycle's first period there is no
snapshot at all: readers get None and say so (the HMI answers that the runtime is starting).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from runtime.commands import CommandRecord


class MachineState(IntEnum):
    """Machine states after PLCopen; values are the HMI's state codes."""

    DISABLED = 0
    """Drives not in operation (power off)."""
    STANDBY = 1
    """Drives enabled, at rest (PLCopen Standstill)."""
    MOVING = 2
    """Following the loaded program (the approach to its start included)."""
    HOLDING = 3
    """Feed hold: decelerating to rest on the path, or resting there; resumable."""
    STOPPING = 4
    """Stop: decelerating to rest on the path; the program ends."""
    ERROR_STOP = 5
    """A fault stopped the machine; needs reset."""


class MotionPhase(IntEnum):
    """What the setpoint is doing; values are the HMI's phase codes."""

    IDLE = 0
    """At rest, no plan being followed."""
    STARTING = 1
    """A plan was asked for; waiting for its first setpoints (the axes stand still)."""
    APPROACH = 2
    """The straight move from where the axes stood to the program's start point."""
    PROGRAM = 3
    """Following the program's curve."""
    BRAKING = 4
    """Braking to rest on the path (hold, stop, fault, override 0)."""


class FaultKind(IntEnum):
    """Why the machine is in ErrorStop; values index the fault texts of the HMI document."""

    NONE = 0
    DRIVE_FAULT = 1
    HEARTBEAT_LOSS = 2
    STALE_FEEDBACK = 3
    FOLLOWING_ERROR = 4
    BUFFER_UNDERRUN = 5
    CYCLE_OVERRUN = 6
    HMI_LINK_LOSS = 7
    PLANNER_ERROR = 8
    BOOT_FAILURE = 9
    PLANNER_LOST = 10


FAULT_TEXTS: dict[FaultKind, str] = {
    FaultKind.NONE: "no fault",
    FaultKind.DRIVE_FAULT: "a drive reported a fault (EMCY or statusword fault bit)",
    FaultKind.HEARTBEAT_LOSS: "a drive stopped sending its heartbeat (or answering node guarding)",
    FaultKind.STALE_FEEDBACK: "a drive's feedback (TPDO) stopped arriving",
    FaultKind.FOLLOWING_ERROR: "an axis's following error exceeded its window",
    FaultKind.BUFFER_UNDERRUN: "the planner fell behind: too few setpoints ahead to go on",
    FaultKind.CYCLE_OVERRUN: "too many consecutive missed cycle periods",
    FaultKind.HMI_LINK_LOSS: "the HMI heartbeat stopped changing during motion",
    FaultKind.PLANNER_ERROR: "the planner failed while producing setpoints",
    FaultKind.BOOT_FAILURE: "a drive did not boot or could not be configured",
    FaultKind.PLANNER_LOST: "the planner process stopped; it is being restarted",
}


class WatchdogState(IntEnum):
    """The HMI link watchdog, as the cycle runs it."""

    OFF = 0
    """No watchdog configured (timeout 0) or the server is read-only."""
    WATCHING = 1
    """Armed: the HMI heartbeat or a command must come within the timeout while moving."""
    TRIPPED = 2
    """It fired (hold or stop); re-armed by the next HMI heartbeat change or command."""


@dataclass(frozen=True)
class Fault:
    """A fault: its kind, the drive's EMCY code if any, the axis and a readable text."""

    kind: FaultKind
    text: str
    axis: str | None = None
    emcy_code: int = 0


@dataclass(frozen=True)
class AxisStatus:
    """One axis as of the last period."""

    name: str
    node_id: int
    commanded_mm: float
    actual_mm: float
    drive_state: int
    """CiA 402 state (drives.cia402.State value), -1 when the statusword matched none."""
    following_error_mm: float
    """Actual position minus the target the drive was given for that instant (its own 0x60F4
    when mapped); for a drive not enabled (faulted, stopped), actual minus the machine's
    setpoint: how far it stands off the path."""
    peak_following_error_mm: float = 0.0
    """Largest |following error| since the last START (or statistics reset)."""
    statusword: int = 0
    """Raw CiA 402 statusword 0x6041 of the last feedback."""
    boot_phase: int = 0
    """drives' boot phase of the node (0 waiting ... ready; see the register map)."""
    fault: str = ""


@dataclass(frozen=True)
class CycleStatistics:
    """Timing of the cycle since start (or the last statistics reset)."""

    cycles: int = 0
    lateness_last_us: float = 0.0
    lateness_p50_us: float = 0.0
    lateness_p99_us: float = 0.0
    lateness_p999_us: float = 0.0
    lateness_max_us: float = 0.0
    execution_last_us: float = 0.0
    execution_max_us: float = 0.0
    missed_periods: int = 0
    override_latency_periods: int = 0
    """Periods from the last feed-override change the cycle switched to (the oldest one a
    re-plan answers) to its first re-planned setpoint."""
    override_rest_wait_periods: int = 0
    """Of ``override_latency_periods``, the periods the plan still braked to a rest it had to
    reach first (a sharp corner, the approach's end): no setpoint before that rest could change."""
    overrides_applied: int = 0
    """Feed-override changes whose re-planned setpoints were reached since start."""


@dataclass(frozen=True)
class ProgramStatus:
    """A program as the status shows it (the active one or the next one)."""

    program_id: int
    name: str
    crc32: int
    length_mm: float


@dataclass(frozen=True)
class StatusSnapshot:
    """Everything an HMI can read, taken at the end of one period."""

    state: MachineState = MachineState.DISABLED
    fault: Fault | None = None
    """The fault that caused the ErrorStop (the first one; it stays until reset)."""
    later_faults: tuple[Fault, ...] = ()
    """Faults reported after the first one until the reset, oldest first (bounded)."""
    axes: tuple[AxisStatus, ...] = ()
    phase: MotionPhase = MotionPhase.IDLE
    feed_mm_s: float = 0.0
    path_s_mm: float = 0.0
    """Distance travelled along the current phase's path: the program's curve, or the approach
    line during APPROACH (then ``path_length_mm`` is the approach's length)."""
    path_length_mm: float = 0.0
    in_position: bool = False
    """At rest with every enabled axis within its following-error window of its target."""
    program: ProgramStatus | None = None
    next_program: ProgramStatus | None = None
    override_percent: float = 100.0
    stats: CycleStatistics = field(default_factory=CycleStatistics)
    last_command: CommandRecord | None = None
    recent_commands: tuple[CommandRecord, ...] = ()
    """The last commands judged, oldest first (bounded), so a client finds its own ticket's
    result even when others came after it."""
    watchdog: WatchdogState = WatchdogState.OFF
    heartbeat: int = 0
    """+1 per period, wraps at 65536."""
    message: str = ""
    """The last state change's reason, e.g. 'hold by watchdog: HMI link silent for 1.0 s'."""

    @property
    def progress_permille(self) -> int:
        if self.path_length_mm <= 0:
            return 0
        return min(1000, max(0, round(1000 * self.path_s_mm / self.path_length_mm)))
