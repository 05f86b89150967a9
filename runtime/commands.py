"""Machine commands, their result codes, and which command each machine state allows.

After PLCopen (reference/modbus-hmi.md §9): enable ~ MC_Power on, disable ~ MC_Power off,
start ~ a path move, hold ~ MC_Halt (resumable feed hold on the path), stop ~ MC_Stop,
quick stop ~ the drives' quick stop, reset ~ MC_Reset. Commands are immutable records; the HMI
and the command line build them, the cyclic task applies them at the start of a cycle.

The table :data:`ALLOWED` is the single source of truth for "is this command allowed now": the
machine uses it to reject, and the HMI uses it to answer Modbus exception 6 before queueing.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import Any

from runtime.status import MachineState


class CommandCode(IntEnum):
    """What the operator asks for. Values are the HMI's command codes."""

    ENABLE = 1
    DISABLE = 2
    START = 3
    HOLD = 4
    RESUME = 5
    STOP = 6
    QUICK_STOP = 7
    RESET = 8
    SET_OVERRIDE = 9
    LOAD_CURVE = 10


class CommandResult(IntEnum):
    """Outcome of a command or a curve commit, as the HMI sees it (status register)."""

    NONE = 0
    """No command has been executed yet."""
    DONE = 1
    """Executed."""
    PENDING = 2
    """Accepted and queued; executes at the start of the next cycle."""
    REJECTED_STATE = 3
    """Not allowed in the current machine state; nothing changed."""
    INVALID_PARAMETER = 4
    """A parameter is out of range (override outside 0..150 %, unknown command code)."""
    NO_CURVE = 5
    """Start without a loaded curve."""
    DRIVES_NOT_READY = 6
    """Enable or reset while a drive is faulted or missing."""
    CURVE_CRC_MISMATCH = 10
    """The staged data does not match the CRC32 written with it."""
    CURVE_BAD_HEADER = 11
    """Degree, number of points, dimension or number of knots out of range."""
    CURVE_TOO_LARGE = 12
    """More points or knots than the staging area holds."""
    CURVE_KNOT_COUNT = 13
    """Number of knots is not points + degree + 1."""
    CURVE_KNOTS_DECREASING = 14
    """Knots must be non-decreasing."""
    CURVE_KNOTS_NOT_CLAMPED = 15
    """The first and last degree + 1 knots must be equal (clamped curve)."""
    CURVE_BAD_WEIGHT = 16
    """A weight is zero, negative or not finite."""
    CURVE_NOT_FINITE = 17
    """A coordinate or knot is NaN or infinite."""
    CURVE_DEGREE_TOO_HIGH = 18
    """Fewer than degree + 1 control points."""
    CURVE_ZERO_LENGTH = 19
    """The curve has no length."""
    CURVE_OUTSIDE_TRAVEL = 20
    """The curve leaves an axis's travel limits."""
    CURVE_INVALID = 21
    """Any other violation of the curve rules."""


@dataclass(frozen=True)
class Command:
    """One operator command.

    ``override_percent`` is the parameter of SET_OVERRIDE; ``curve`` of LOAD_CURVE (a
    :class:`runtime.curves.LoadedCurve`, prepared outside the cycle); ``seq`` the HMI's sequence
    number, echoed in the status; ``origin`` says who sent it, for the log and the status.
    """

    code: CommandCode
    override_percent: float | None = None
    curve: Any = None
    seq: int | None = None
    origin: str = "operator"


#: Override range in percent (vmax scales with it; amax and jmax do not).
OVERRIDE_MIN_PERCENT = 0.0
OVERRIDE_MAX_PERCENT = 150.0

_S = MachineState
#: Commands each state accepts. Anything else is rejected with REJECTED_STATE and changes nothing.
ALLOWED: dict[MachineState, frozenset[CommandCode]] = {
    _S.DISABLED: frozenset({CommandCode.ENABLE, CommandCode.LOAD_CURVE, CommandCode.SET_OVERRIDE}),
    _S.STANDBY: frozenset(
        {
            CommandCode.DISABLE,
            CommandCode.START,
            CommandCode.LOAD_CURVE,
            CommandCode.SET_OVERRIDE,
        }
    ),
    _S.MOVING: frozenset(
        {
            CommandCode.HOLD,
            CommandCode.STOP,
            CommandCode.QUICK_STOP,
            CommandCode.SET_OVERRIDE,
        }
    ),
    _S.HOLDING: frozenset(
        {
            CommandCode.RESUME,
            CommandCode.STOP,
            CommandCode.QUICK_STOP,
            CommandCode.SET_OVERRIDE,
        }
    ),
    _S.STOPPING: frozenset({CommandCode.QUICK_STOP, CommandCode.SET_OVERRIDE}),
    _S.ERROR_STOP: frozenset({CommandCode.RESET, CommandCode.DISABLE, CommandCode.SET_OVERRIDE}),
}


def check_allowed(state: MachineState, code: CommandCode) -> str | None:
    """Why ``code`` is not allowed in ``state``, or None when it is."""
    if code in ALLOWED[state]:
        return None
    return f"{code.name.lower()} is not allowed in state {state.name}"
