"""The machine's status: states, fault kinds, and the snapshot the cyclic task publishes.

The cyclic task builds one :class:`StatusSnapshot` per cycle and publishes it by reference swap;
readers (the HMI server, the command line) always see one complete, consistent cycle.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum


class MachineState(IntEnum):
    """Machine states after PLCopen; values are the HMI's state codes."""

    DISABLED = 0
    """Drives not in operation (power off)."""
    STANDBY = 1
    """Drives enabled, at rest (PLCopen Standstill)."""
    MOVING = 2
    """Following the loaded curve."""
    HOLDING = 3
    """Feed hold: decelerating to rest on the path, or resting there; resumable."""
    STOPPING = 4
    """Stop: decelerating to rest on the path; the program ends."""
    ERROR_STOP = 5
    """A fault stopped the machine; needs reset."""


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


FAULT_TEXTS: dict[FaultKind, str] = {
    FaultKind.NONE: "no fault",
    FaultKind.DRIVE_FAULT: "a drive reported a fault (EMCY or statusword fault bit)",
    FaultKind.HEARTBEAT_LOSS: "a drive stopped sending its heartbeat",
    FaultKind.STALE_FEEDBACK: "a drive's feedback (TPDO) stopped arriving",
    FaultKind.FOLLOWING_ERROR: "an axis's following error exceeded its window",
    FaultKind.BUFFER_UNDERRUN: "the setpoint buffer ran empty during motion",
    FaultKind.CYCLE_OVERRUN: "too many consecutive missed cycle periods",
    FaultKind.HMI_LINK_LOSS: "the HMI heartbeat stopped changing during motion",
    FaultKind.PLANNER_ERROR: "the planner failed while producing setpoints",
    FaultKind.BOOT_FAILURE: "a drive did not boot or configure",
}


@dataclass(frozen=True)
class Fault:
    """An active fault: its kind, the drive's EMCY code if any, the axis and a readable text."""

    kind: FaultKind
    text: str
    axis: str | None = None
    emcy_code: int = 0


@dataclass(frozen=True)
class AxisStatus:
    """One axis as of the last cycle."""

    name: str
    node_id: int
    commanded_mm: float
    actual_mm: float
    drive_state: int
    """CiA 402 state (drives.cia402.State value)."""
    following_error_mm: float
    fault: str = ""


@dataclass(frozen=True)
class CycleStatistics:
    """Timing of the cyclic task since start (or the last statistics reset)."""

    cycles: int = 0
    lateness_last_us: float = 0.0
    lateness_p50_us: float = 0.0
    lateness_p99_us: float = 0.0
    lateness_max_us: float = 0.0
    execution_last_us: float = 0.0
    execution_max_us: float = 0.0
    missed_periods: int = 0


@dataclass(frozen=True)
class StatusSnapshot:
    """Everything an HMI can read, taken at the end of one cycle."""

    state: MachineState = MachineState.DISABLED
    fault: Fault | None = None
    axes: tuple[AxisStatus, ...] = ()
    feed_mm_s: float = 0.0
    path_s_mm: float = 0.0
    path_length_mm: float = 0.0
    override_percent: float = 100.0
    stats: CycleStatistics = field(default_factory=CycleStatistics)
    last_command_seq: int = 0
    last_command_result: int = 0
    curve_id: int = 0
    curve_crc: int = 0
    heartbeat: int = 0
    message: str = ""
    """The last state change's reason, e.g. 'hold: HMI link lost'."""

    @property
    def progress_permille(self) -> int:
        if self.path_length_mm <= 0:
            return 0
        return min(1000, max(0, round(1000 * self.path_s_mm / self.path_length_mm)))
