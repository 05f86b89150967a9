"""Machine commands, their origins and result codes, and which command each machine state allows.

After PLCopen (reference/modbus-hmi.md §9): enable ~ MC_Power on, disable ~ MC_Power off,
start ~ a path move, hold ~ MC_Halt (resumable feed hold on the path), stop ~ MC_Stop,
quick stop ~ the drives' quick stop, reset ~ MC_Reset. Commands are immutable records; the HMI,
the command line and the supervisor post them to the cycle process's mailboxes, and the cycle
judges and applies each one at the start of a period, in the order posted, against the state it
runs in. Every command gets a ticket when posted (one sequence for the whole runtime) and leaves
one :class:`CommandRecord` with its result in the status.

The table :data:`ALLOWED` is the single source of truth for "is this command allowed now".
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import TYPE_CHECKING

from runtime.status import MachineState

if TYPE_CHECKING:
    from runtime.programs import Program


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
    """Load a program: the active one at rest, the next one while moving (see ``Machine``)."""
    CLEAR_NEXT = 11
    """Forget the next program (the running one is untouched)."""
    SHUTDOWN = 12
    """Stop on the path, disable the drives, leave the bus cleanly and end the cycle process
    (the supervisor's, on SIGTERM or at the end of a demo; never from the HMI)."""


class CommandOrigin(IntEnum):
    """Who asked for a command; values are the HMI's origin codes."""

    NONE = 0
    HMI = 1
    """A Modbus client (COMMAND_SEQ write or curve commit)."""
    WATCHDOG = 2
    """The HMI link watchdog (no HMI heartbeat or command within its timeout while moving)."""
    COMMAND_LINE = 3
    """``softmotion run --curve/--demo`` or another local tool through the supervisor."""
    FAULT = 4
    """The machine itself, reacting to a fault."""
    SHUTDOWN = 5
    """The supervisor stopping the runtime (SIGTERM, SIGINT)."""


class CommandResult(IntEnum):
    """Outcome of a command or a curve commit, as the HMI sees it (status registers)."""

    NONE = 0
    """No command has been executed yet."""
    DONE = 1
    """Executed."""
    PENDING = 2
    """Accepted into the mailbox; judged and executed at the start of a coming period."""
    REJECTED_STATE = 3
    """Not allowed in the state the machine was in when the command's turn came; nothing
    changed."""
    INVALID_PARAMETER = 4
    """A parameter is out of range (override outside 0..150 %, unknown command code)."""
    NO_CURVE = 5
    """Start without a loaded curve."""
    DRIVES_NOT_READY = 6
    """Enable or reset while a drive is faulted, missing or still booting."""
    MAILBOX_FULL = 7
    """The cycle's mailbox was full; nothing was queued (safe to send again)."""
    STAGING_LOCKED = 8
    """A commit from the staging area while another client holds it; nothing was loaded."""
    NO_SUCH_PROGRAM = 9
    """No library program has that number (or no library is configured)."""
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

    ``override_percent`` is the parameter of SET_OVERRIDE; ``program`` of LOAD_CURVE (a
    :class:`runtime.programs.Program`, validated and stored outside the cycle); ``seq`` the
    client's own sequence number (the HMI's COMMAND_SEQ, 0 when none), echoed in the status;
    ``ticket`` the runtime-wide number the mailbox gives it when posted (0 before).
    """

    code: CommandCode
    origin: CommandOrigin = CommandOrigin.COMMAND_LINE
    override_percent: float | None = None
    program: Program | None = None
    seq: int = 0
    ticket: int = 0


@dataclass(frozen=True)
class CommandRecord:
    """One command as the cycle judged it: published in the status, newest last."""

    ticket: int
    origin: CommandOrigin
    seq: int
    """The client's sequence number (HMI COMMAND_SEQ), 0 when none."""
    code: CommandCode
    result: CommandResult


#: Override range in percent (vmax scales with it; amax and jmax do not).
OVERRIDE_MIN_PERCENT = 0.0
OVERRIDE_MAX_PERCENT = 150.0

_S = MachineState
_MOTION_LOAD = frozenset({CommandCode.LOAD_CURVE, CommandCode.CLEAR_NEXT, CommandCode.SET_OVERRIDE})
#: Commands each state accepts. Anything else is rejected with REJECTED_STATE and changes nothing.
#: SHUTDOWN is accepted everywhere (the supervisor's, never an HMI's).
ALLOWED: dict[MachineState, frozenset[CommandCode]] = {
    _S.DISABLED: frozenset({CommandCode.ENABLE} | _MOTION_LOAD),
    _S.STANDBY: frozenset({CommandCode.DISABLE, CommandCode.START} | _MOTION_LOAD),
    _S.MOVING: frozenset(
        {CommandCode.HOLD, CommandCode.STOP, CommandCode.QUICK_STOP} | _MOTION_LOAD
    ),
    _S.HOLDING: frozenset(
        {CommandCode.RESUME, CommandCode.STOP, CommandCode.QUICK_STOP} | _MOTION_LOAD
    ),
    _S.STOPPING: frozenset({CommandCode.QUICK_STOP} | _MOTION_LOAD),
    _S.ERROR_STOP: frozenset({CommandCode.RESET, CommandCode.DISABLE} | _MOTION_LOAD),
}


def check_allowed(state: MachineState, code: CommandCode) -> str | None:
    """Why ``code`` is not allowed in ``state``, or None when it is."""
    if code is CommandCode.SHUTDOWN or code in ALLOWED[state]:
        return None
    return f"{code.name.lower()} is not allowed in state {state.name}"
