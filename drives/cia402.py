"""CiA 402 device control in pure functions: controlword commands, statusword states, transitions.

Source: CiA 402-2 / IEC 61800-7-201, "device control" state machine. Controlword 0x6040 bits:
0 switch on, 1 enable voltage, 2 quick stop (active low), 3 enable operation, 7 fault reset
(rising edge). Statusword 0x6041 bits: 0 ready to switch on, 1 switched on, 2 operation enabled,
3 fault, 4 voltage enabled, 5 quick stop (0 = active), 6 switch on disabled, 7 warning, 9 remote,
10 target reached, 11 internal limit active, 12-13 mode specific (CSP: 12 following the target,
13 following error).

Transitions (numbers as in the standard): 0-1 automatic to SWITCH ON DISABLED; 2 shutdown;
3 switch on; 4 enable operation; 5 disable operation; 6 shutdown; 7 disable voltage or quick stop;
8 shutdown; 9 disable voltage; 10 disable voltage or quick stop; 11 quick stop; 12 quick stop done
(0x605A 0..4) or disable voltage; 13 fault detected (any state); 14 fault reaction done;
15 fault reset (rising edge of bit 7); 16 enable operation from QUICK STOP ACTIVE (0x605A 5..8).

Both sides use this module: the master (decode the statusword, choose the next controlword) and
the simulated drive (decode the controlword, step its state machine, encode its statusword).

Threading: pure functions on integers, no I/O, no state; callable from any thread.
Invariant: every function returns words in 0..0xFFFF and never a transition missing from
:data:`TRANSITIONS`.
Not modelled: mode-specific controlword bits (4-6, 9), halt (bit 8) and vendor bits (11-15).
"""

from __future__ import annotations

from collections.abc import Mapping
from enum import IntEnum
from types import MappingProxyType
from typing import Final


class State(IntEnum):
    """The eight states of the CiA 402 device control state machine."""

    NOT_READY_TO_SWITCH_ON = 0
    SWITCH_ON_DISABLED = 1
    READY_TO_SWITCH_ON = 2
    SWITCHED_ON = 3
    OPERATION_ENABLED = 4
    QUICK_STOP_ACTIVE = 5
    FAULT_REACTION_ACTIVE = 6
    FAULT = 7


class Command(IntEnum):
    """Controlword values of the device control commands (bits 7..0, mode bits clear).

    ``SWITCH_ON`` and ``DISABLE_OPERATION`` are the same word (0x07); the transition it causes
    depends on the state. ``FAULT_RESET`` acts only on the rising edge of bit 7.
    """

    DISABLE_VOLTAGE = 0x00
    QUICK_STOP = 0x02
    SHUTDOWN = 0x06
    SWITCH_ON = 0x07
    DISABLE_OPERATION = 0x07
    ENABLE_OPERATION = 0x0F
    FAULT_RESET = 0x80


# Controlword bits.
CW_SWITCH_ON: Final[int] = 1 << 0
CW_ENABLE_VOLTAGE: Final[int] = 1 << 1
CW_QUICK_STOP: Final[int] = 1 << 2  # active low
CW_ENABLE_OPERATION: Final[int] = 1 << 3
CW_FAULT_RESET: Final[int] = 1 << 7
CW_HALT: Final[int] = 1 << 8

# Statusword bits.
SW_READY_TO_SWITCH_ON: Final[int] = 1 << 0
SW_SWITCHED_ON: Final[int] = 1 << 1
SW_OPERATION_ENABLED: Final[int] = 1 << 2
SW_FAULT: Final[int] = 1 << 3
SW_VOLTAGE_ENABLED: Final[int] = 1 << 4
SW_QUICK_STOP: Final[int] = 1 << 5  # 0 = quick stop active
SW_SWITCH_ON_DISABLED: Final[int] = 1 << 6
SW_WARNING: Final[int] = 1 << 7
SW_REMOTE: Final[int] = 1 << 9
SW_TARGET_REACHED: Final[int] = 1 << 10
SW_INTERNAL_LIMIT: Final[int] = 1 << 11
SW_CSP_FOLLOWING: Final[int] = 1 << 12  # CSP: drive follows the target position
SW_CSP_FOLLOWING_ERROR: Final[int] = 1 << 13  # CSP: following error

#: Statusword (mask, value) per state, as in the CiA 402 table.
STATUSWORD_PATTERNS: Final[Mapping[State, tuple[int, int]]] = MappingProxyType(
    {
        State.NOT_READY_TO_SWITCH_ON: (0x4F, 0x00),
        State.SWITCH_ON_DISABLED: (0x4F, 0x40),
        State.READY_TO_SWITCH_ON: (0x6F, 0x21),
        State.SWITCHED_ON: (0x6F, 0x23),
        State.OPERATION_ENABLED: (0x6F, 0x27),
        State.QUICK_STOP_ACTIVE: (0x6F, 0x07),
        State.FAULT_REACTION_ACTIVE: (0x4F, 0x0F),
        State.FAULT: (0x4F, 0x08),
    }
)

_ACTIVE_STATES: Final = (
    State.NOT_READY_TO_SWITCH_ON,
    State.SWITCH_ON_DISABLED,
    State.READY_TO_SWITCH_ON,
    State.SWITCHED_ON,
    State.OPERATION_ENABLED,
    State.QUICK_STOP_ACTIVE,
)

#: Numbered transitions of the state machine, keyed by (from, to).
TRANSITIONS: Final[Mapping[tuple[State, State], int]] = MappingProxyType(
    {
        (State.NOT_READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED): 1,
        (State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON): 2,
        (State.READY_TO_SWITCH_ON, State.SWITCHED_ON): 3,
        (State.SWITCHED_ON, State.OPERATION_ENABLED): 4,
        (State.OPERATION_ENABLED, State.SWITCHED_ON): 5,
        (State.SWITCHED_ON, State.READY_TO_SWITCH_ON): 6,
        (State.READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED): 7,
        (State.OPERATION_ENABLED, State.READY_TO_SWITCH_ON): 8,
        (State.OPERATION_ENABLED, State.SWITCH_ON_DISABLED): 9,
        (State.SWITCHED_ON, State.SWITCH_ON_DISABLED): 10,
        (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE): 11,
        (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED): 12,
        **{(state, State.FAULT_REACTION_ACTIVE): 13 for state in _ACTIVE_STATES},
        (State.FAULT_REACTION_ACTIVE, State.FAULT): 14,
        (State.FAULT, State.SWITCH_ON_DISABLED): 15,
        (State.QUICK_STOP_ACTIVE, State.OPERATION_ENABLED): 16,
    }
)

#: 0x605A quick stop option codes that end in SWITCH ON DISABLED (transition 12) once stopped;
#: codes 5..8 stay in QUICK STOP ACTIVE, from where transition 16 is allowed.
QUICK_STOP_OPTIONS_TO_DISABLED: Final = frozenset({0, 1, 2, 3, 4})
QUICK_STOP_OPTIONS_STAY_ACTIVE: Final = frozenset({5, 6, 7, 8})

# Bits 7, 3, 2, 1, 0 select the command; bit 7 set means "fault reset" (acts on its edge only).
_COMMAND_BITS: Final[int] = (
    CW_FAULT_RESET | CW_ENABLE_OPERATION | CW_QUICK_STOP | CW_ENABLE_VOLTAGE | CW_SWITCH_ON
)


_TOWARD_ENABLED: Final[Mapping[State, Command]] = MappingProxyType(
    {
        State.NOT_READY_TO_SWITCH_ON: Command.DISABLE_VOLTAGE,
        State.SWITCH_ON_DISABLED: Command.SHUTDOWN,
        State.READY_TO_SWITCH_ON: Command.SWITCH_ON,
        State.SWITCHED_ON: Command.ENABLE_OPERATION,
        State.OPERATION_ENABLED: Command.ENABLE_OPERATION,
        State.QUICK_STOP_ACTIVE: Command.DISABLE_VOLTAGE,
        State.FAULT_REACTION_ACTIVE: Command.DISABLE_VOLTAGE,
        State.FAULT: Command.DISABLE_VOLTAGE,
    }
)


_TOWARD_DISABLED: Final[Mapping[State, Command]] = MappingProxyType(
    {
        State.NOT_READY_TO_SWITCH_ON: Command.DISABLE_VOLTAGE,
        State.SWITCH_ON_DISABLED: Command.DISABLE_VOLTAGE,
        State.READY_TO_SWITCH_ON: Command.DISABLE_VOLTAGE,
        State.SWITCHED_ON: Command.SHUTDOWN,
        State.OPERATION_ENABLED: Command.DISABLE_OPERATION,
        State.QUICK_STOP_ACTIVE: Command.DISABLE_VOLTAGE,
        State.FAULT_REACTION_ACTIVE: Command.DISABLE_VOLTAGE,
        State.FAULT: Command.DISABLE_VOLTAGE,
    }
)


def _state_of_bits(bits: int) -> State | None:
    for state, (mask, value) in STATUSWORD_PATTERNS.items():
        if bits & mask == value:
            return state
    return None


#: Bits 0-3, 5 and 6 decide the state: every value of the low 7 bits, decoded once.
_STATE_BITS: Final[int] = 0x7F
_STATES_BY_BITS: Final = tuple(_state_of_bits(bits) for bits in range(_STATE_BITS + 1))


def state_of_statusword(statusword: int) -> State | None:
    """The device control state shown by a statusword (0x6041), None if it matches none of
    the eight patterns; a table look-up, for the cycle."""
    return _STATES_BY_BITS[statusword & _STATE_BITS]


def decode_statusword(statusword: int) -> State:
    """Return the device control state shown by a statusword (0x6041).

    Bits outside each state's mask (voltage enabled, warning, remote, mode bits...) are ignored.

    :raises ValueError: if the statusword matches none of the eight state patterns.
    """
    state = state_of_statusword(statusword)
    if state is None:
        raise ValueError(
            f"statusword 0x{statusword:04X}: bits 0-3, 5, 6 match no CiA 402 state pattern"
        )
    return state


def encode_statusword(
    state: State,
    *,
    warning: bool = False,
    remote: bool = True,
    target_reached: bool = False,
    internal_limit: bool = False,
    following: bool | None = None,
    following_error: bool = False,
    voltage_enabled: bool | None = None,
) -> int:
    """Return the statusword (0x6041) a drive reports in ``state``.

    :param following: CSP bit 12; ``None`` sets it exactly in OPERATION ENABLED.
    :param voltage_enabled: bit 4; ``None`` sets it in the states where the power stage may carry
        voltage (READY TO SWITCH ON, SWITCHED ON, OPERATION ENABLED, QUICK STOP ACTIVE,
        FAULT REACTION ACTIVE).
    """
    word = STATUSWORD_PATTERNS[state][1]
    if state in (State.SWITCH_ON_DISABLED, State.NOT_READY_TO_SWITCH_ON):
        word |= SW_QUICK_STOP  # quick stop not active; outside the mask, set as drives do
    if voltage_enabled is None:
        voltage_enabled = state in (
            State.READY_TO_SWITCH_ON,
            State.SWITCHED_ON,
            State.OPERATION_ENABLED,
            State.QUICK_STOP_ACTIVE,
            State.FAULT_REACTION_ACTIVE,
        )
    if following is None:
        following = state is State.OPERATION_ENABLED
    for flag, bit in (
        (voltage_enabled, SW_VOLTAGE_ENABLED),
        (warning, SW_WARNING),
        (remote, SW_REMOTE),
        (target_reached, SW_TARGET_REACHED),
        (internal_limit, SW_INTERNAL_LIMIT),
        (following, SW_CSP_FOLLOWING),
        (following_error, SW_CSP_FOLLOWING_ERROR),
    ):
        if flag:
            word |= bit
    return word


def decode_controlword(controlword: int) -> Command:
    """Return the device control command carried by a controlword (0x6040).

    Decoding follows the CiA 402 command table on bits 7, 3, 2, 1, 0: bit 1 clear is
    DISABLE_VOLTAGE; bit 1 set and bit 2 clear is QUICK_STOP; x110 is SHUTDOWN; 0111 is
    SWITCH_ON (= DISABLE_OPERATION); 1111 is ENABLE_OPERATION. Bit 7 set is FAULT_RESET, whose
    effect requires the rising edge (see :func:`is_fault_reset_edge`).
    """
    word = controlword & _COMMAND_BITS
    if word & CW_FAULT_RESET:
        return Command.FAULT_RESET
    if not word & CW_ENABLE_VOLTAGE:
        return Command.DISABLE_VOLTAGE
    if not word & CW_QUICK_STOP:
        return Command.QUICK_STOP
    if not word & CW_SWITCH_ON:
        return Command.SHUTDOWN
    if word & CW_ENABLE_OPERATION:
        return Command.ENABLE_OPERATION
    return Command.SWITCH_ON


def is_fault_reset_edge(previous_controlword: int, controlword: int) -> bool:
    """Return True if bit 7 (fault reset) rose from 0 to 1 between two controlwords."""
    return not previous_controlword & CW_FAULT_RESET and bool(controlword & CW_FAULT_RESET)


def _target_state(state: State, command: Command, quick_stop_option: int) -> State:
    if state is State.NOT_READY_TO_SWITCH_ON:
        return State.SWITCH_ON_DISABLED  # 1: automatic once initialised
    if state is State.SWITCH_ON_DISABLED:
        return State.READY_TO_SWITCH_ON if command is Command.SHUTDOWN else state  # 2
    if state is State.READY_TO_SWITCH_ON:
        if command in (Command.SWITCH_ON, Command.ENABLE_OPERATION):
            return State.SWITCHED_ON  # 3 (ENABLE_OPERATION continues with 4 on the next step)
        if command in (Command.DISABLE_VOLTAGE, Command.QUICK_STOP):
            return State.SWITCH_ON_DISABLED  # 7
        return state
    if state is State.SWITCHED_ON:
        if command is Command.ENABLE_OPERATION:
            return State.OPERATION_ENABLED  # 4
        if command is Command.SHUTDOWN:
            return State.READY_TO_SWITCH_ON  # 6
        if command in (Command.DISABLE_VOLTAGE, Command.QUICK_STOP):
            return State.SWITCH_ON_DISABLED  # 10
        return state
    if state is State.OPERATION_ENABLED:
        if command is Command.DISABLE_OPERATION:
            return State.SWITCHED_ON  # 5
        if command is Command.SHUTDOWN:
            return State.READY_TO_SWITCH_ON  # 8
        if command is Command.DISABLE_VOLTAGE:
            return State.SWITCH_ON_DISABLED  # 9
        if command is Command.QUICK_STOP:
            return State.QUICK_STOP_ACTIVE  # 11
        return state
    if state is State.QUICK_STOP_ACTIVE:
        if command is Command.DISABLE_VOLTAGE:
            return State.SWITCH_ON_DISABLED  # 12
        if (
            command is Command.ENABLE_OPERATION
            and quick_stop_option in QUICK_STOP_OPTIONS_STAY_ACTIVE
        ):
            return State.OPERATION_ENABLED  # 16
        return state
    return state  # FAULT REACTION ACTIVE and FAULT leave by 14 and 15 only


def drive_transition(
    state: State,
    controlword: int,
    *,
    quick_stop_option: int,
    previous_controlword: int = 0,
) -> tuple[State, int | None]:
    """Step the drive's state machine on a received controlword (the drive side).

    Covers transitions 1 (automatic, any controlword), 2-12 by command, 15 (rising edge of
    bit 7 in FAULT) and 16 (ENABLE OPERATION in QUICK STOP ACTIVE, only with 0x605A 5..8).
    One call makes at most one transition: "switch on + enable operation" (0x0F) from READY TO
    SWITCH ON makes 3, and the next call with the same word makes 4. Transitions driven by
    events inside the drive are separate functions: 12 on quick stop completion
    (:func:`quick_stop_complete`), 13 (:func:`fault_detected`) and 14
    (:func:`fault_reaction_complete`).

    :param quick_stop_option: 0x605A value in force.
    :param previous_controlword: the controlword received before this one (the default 0 has
        bit 7 clear), used to detect the fault reset edge.
    :return: the new state and the transition number, or ``(state, None)`` if none applies.
    """
    if state is State.FAULT:
        if is_fault_reset_edge(previous_controlword, controlword):
            return State.SWITCH_ON_DISABLED, TRANSITIONS[(State.FAULT, State.SWITCH_ON_DISABLED)]
        return state, None
    target = _target_state(state, decode_controlword(controlword), quick_stop_option)
    if target is state:
        return state, None
    return target, TRANSITIONS[(state, target)]


def quick_stop_complete(state: State, *, quick_stop_option: int) -> tuple[State, int | None]:
    """Transition once the quick stop ramp has brought the motor to rest (drive side).

    With 0x605A 0..4 the drive leaves QUICK STOP ACTIVE for SWITCH ON DISABLED (12); with 5..8
    it stays in QUICK STOP ACTIVE.
    """
    if state is State.QUICK_STOP_ACTIVE and quick_stop_option in QUICK_STOP_OPTIONS_TO_DISABLED:
        return State.SWITCH_ON_DISABLED, TRANSITIONS[(state, State.SWITCH_ON_DISABLED)]
    return state, None


def fault_detected(state: State) -> tuple[State, int | None]:
    """Transition 13 on a fault detected inside the drive, from any state but FRA and FAULT."""
    if state in (State.FAULT_REACTION_ACTIVE, State.FAULT):
        return state, None
    return State.FAULT_REACTION_ACTIVE, TRANSITIONS[(state, State.FAULT_REACTION_ACTIVE)]


def fault_reaction_complete(state: State) -> tuple[State, int | None]:
    """Transition 14 once the 0x605E fault reaction has finished."""
    if state is State.FAULT_REACTION_ACTIVE:
        return State.FAULT, TRANSITIONS[(state, State.FAULT)]
    return state, None


def controlword_toward_enabled(state: State) -> int:
    """Return the controlword for the next transition from ``state`` toward OPERATION ENABLED.

    SWITCH ON DISABLED -> SHUTDOWN (2); READY TO SWITCH ON -> SWITCH ON (3); SWITCHED ON ->
    ENABLE OPERATION (4); OPERATION ENABLED -> ENABLE OPERATION (hold); QUICK STOP ACTIVE ->
    DISABLE VOLTAGE (12), continuing from SWITCH ON DISABLED; NOT READY TO SWITCH ON, FAULT
    REACTION ACTIVE and FAULT -> DISABLE VOLTAGE (wait; a FAULT is left by the bit 7 edge of
    :func:`fault_reset_controlword`). One transition per word works on every drive, including
    those that refuse 0x0F in READY TO SWITCH ON.
    """
    return int(_TOWARD_ENABLED[state])


def controlword_toward_disabled(state: State) -> int:
    """Return the controlword for the next transition from ``state`` toward SWITCH ON DISABLED.

    Steps down one state at a time so the drive applies its own stop reactions:
    OPERATION ENABLED -> DISABLE OPERATION (5); SWITCHED ON -> SHUTDOWN (6); READY TO SWITCH
    ON -> DISABLE VOLTAGE (7); QUICK STOP ACTIVE -> DISABLE VOLTAGE (12); every other state ->
    DISABLE VOLTAGE (hold).
    """
    return int(_TOWARD_DISABLED[state])


def fault_reset_controlword(cycle_index: int) -> int:
    """Return the controlword of cycle ``cycle_index`` (0, 1, 2, ...) of a fault reset.

    Alternates 0x00 (bit 7 clear) and 0x80 (bit 7 set), so cycles 0-1 make one rising edge and
    each further pair makes another, for a drive whose fault was still present at the first.

    :raises ValueError: if ``cycle_index`` is negative.
    """
    if cycle_index < 0:
        raise ValueError(f"fault reset cycle_index = {cycle_index}, must be >= 0")
    return int(Command.FAULT_RESET) if cycle_index % 2 else int(Command.DISABLE_VOLTAGE)
