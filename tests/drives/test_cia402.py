"""CiA 402 codec: the drive-side state machine transition by transition, statusword decoding,
the master's controlword choice and the fault reset edge, against the CiA 402 tables."""

from __future__ import annotations

import pytest

from drives.cia402 import (
    TRANSITIONS,
    Command,
    State,
    controlword_toward_disabled,
    controlword_toward_enabled,
    decode_controlword,
    decode_statusword,
    drive_transition,
    encode_statusword,
    fault_detected,
    fault_reaction_complete,
    fault_reset_controlword,
    is_fault_reset_edge,
    quick_stop_complete,
)

S = State

# The CiA 402 transition table: (number, from, to, controlword that causes it, 0x605A in force).
COMMAND_TRANSITIONS = [
    (2, S.SWITCH_ON_DISABLED, S.READY_TO_SWITCH_ON, 0x06, 2),
    (3, S.READY_TO_SWITCH_ON, S.SWITCHED_ON, 0x07, 2),
    (3, S.READY_TO_SWITCH_ON, S.SWITCHED_ON, 0x0F, 2),  # switch on + enable operation, first step
    (4, S.SWITCHED_ON, S.OPERATION_ENABLED, 0x0F, 2),
    (5, S.OPERATION_ENABLED, S.SWITCHED_ON, 0x07, 2),
    (6, S.SWITCHED_ON, S.READY_TO_SWITCH_ON, 0x06, 2),
    (7, S.READY_TO_SWITCH_ON, S.SWITCH_ON_DISABLED, 0x00, 2),
    (7, S.READY_TO_SWITCH_ON, S.SWITCH_ON_DISABLED, 0x02, 2),
    (8, S.OPERATION_ENABLED, S.READY_TO_SWITCH_ON, 0x06, 2),
    (9, S.OPERATION_ENABLED, S.SWITCH_ON_DISABLED, 0x00, 2),
    (10, S.SWITCHED_ON, S.SWITCH_ON_DISABLED, 0x00, 2),
    (10, S.SWITCHED_ON, S.SWITCH_ON_DISABLED, 0x02, 2),
    (11, S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE, 0x02, 2),
    (11, S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE, 0x0B, 2),
    (12, S.QUICK_STOP_ACTIVE, S.SWITCH_ON_DISABLED, 0x00, 2),
    (12, S.QUICK_STOP_ACTIVE, S.SWITCH_ON_DISABLED, 0x00, 6),
    (16, S.QUICK_STOP_ACTIVE, S.OPERATION_ENABLED, 0x0F, 5),
    (16, S.QUICK_STOP_ACTIVE, S.OPERATION_ENABLED, 0x0F, 8),
]


@pytest.mark.parametrize(
    ("number", "source", "target", "controlword", "qs_option"), COMMAND_TRANSITIONS
)
def test_command_transition_matches_the_table(number, source, target, controlword, qs_option):
    assert TRANSITIONS[(source, target)] == number
    assert drive_transition(source, controlword, quick_stop_option=qs_option) == (target, number)


@pytest.mark.parametrize("mode_bits", [0x0000, 0x0070, 0x0100, 0xF800])
@pytest.mark.parametrize(
    ("number", "source", "target", "controlword", "qs_option"), COMMAND_TRANSITIONS
)
def test_mode_halt_and_vendor_bits_do_not_change_the_command(
    number, source, target, controlword, qs_option, mode_bits
):
    result = drive_transition(source, controlword | mode_bits, quick_stop_option=qs_option)
    assert result == (target, number)


def test_transition_1_is_automatic():
    assert drive_transition(S.NOT_READY_TO_SWITCH_ON, 0x00, quick_stop_option=2) == (
        S.SWITCH_ON_DISABLED,
        1,
    )


def test_enable_from_ready_takes_transition_3_then_4():
    state, first = drive_transition(S.READY_TO_SWITCH_ON, 0x0F, quick_stop_option=2)
    state, second = drive_transition(state, 0x0F, quick_stop_option=2, previous_controlword=0x0F)
    assert (first, second, state) == (3, 4, S.OPERATION_ENABLED)


@pytest.mark.parametrize("qs_option", [0, 1, 2, 3, 4])
def test_transition_16_refused_when_quick_stop_option_leaves_the_state(qs_option):
    assert drive_transition(S.QUICK_STOP_ACTIVE, 0x0F, quick_stop_option=qs_option) == (
        S.QUICK_STOP_ACTIVE,
        None,
    )


# Commands that the table does not define for a state leave it unchanged.
NO_TRANSITION = [
    (S.SWITCH_ON_DISABLED, [0x00, 0x02, 0x07, 0x0F]),
    (S.READY_TO_SWITCH_ON, [0x06]),
    (S.SWITCHED_ON, [0x07]),
    (S.OPERATION_ENABLED, [0x0F]),
    (S.QUICK_STOP_ACTIVE, [0x02, 0x06, 0x07]),
    (S.FAULT_REACTION_ACTIVE, [0x00, 0x02, 0x06, 0x07, 0x0F, 0x80]),
    (S.FAULT, [0x00, 0x02, 0x06, 0x07, 0x0F]),
]


@pytest.mark.parametrize(("state", "controlwords"), NO_TRANSITION)
def test_undefined_commands_keep_the_state(state, controlwords):
    for controlword in controlwords:
        assert drive_transition(state, controlword, quick_stop_option=6) == (state, None)


def test_bit_7_held_is_no_command():
    for state in (S.SWITCH_ON_DISABLED, S.READY_TO_SWITCH_ON, S.OPERATION_ENABLED):
        result = drive_transition(state, 0x86, quick_stop_option=2, previous_controlword=0x80)
        assert result == (state, None)


def test_transition_15_needs_a_rising_edge_of_bit_7():
    assert drive_transition(S.FAULT, 0x80, quick_stop_option=2, previous_controlword=0x00) == (
        S.SWITCH_ON_DISABLED,
        15,
    )
    assert drive_transition(S.FAULT, 0x80, quick_stop_option=2, previous_controlword=0x80) == (
        S.FAULT,
        None,
    )
    assert drive_transition(S.FAULT, 0x8F, quick_stop_option=2, previous_controlword=0x0F) == (
        S.SWITCH_ON_DISABLED,
        15,
    )


@pytest.mark.parametrize(
    "state",
    [
        S.NOT_READY_TO_SWITCH_ON,
        S.SWITCH_ON_DISABLED,
        S.READY_TO_SWITCH_ON,
        S.SWITCHED_ON,
        S.OPERATION_ENABLED,
        S.QUICK_STOP_ACTIVE,
    ],
)
def test_transition_13_from_every_state(state):
    assert fault_detected(state) == (S.FAULT_REACTION_ACTIVE, 13)


def test_no_transition_13_while_already_faulted():
    assert fault_detected(S.FAULT_REACTION_ACTIVE) == (S.FAULT_REACTION_ACTIVE, None)
    assert fault_detected(S.FAULT) == (S.FAULT, None)


def test_transition_14_ends_the_fault_reaction():
    assert fault_reaction_complete(S.FAULT_REACTION_ACTIVE) == (S.FAULT, 14)
    assert fault_reaction_complete(S.OPERATION_ENABLED) == (S.OPERATION_ENABLED, None)


@pytest.mark.parametrize(
    ("qs_option", "expected"), [(0, 12), (2, 12), (4, 12), (5, None), (8, None)]
)
def test_quick_stop_completion_follows_605a(qs_option, expected):
    state, transition = quick_stop_complete(S.QUICK_STOP_ACTIVE, quick_stop_option=qs_option)
    assert transition == expected
    assert state is (S.SWITCH_ON_DISABLED if expected else S.QUICK_STOP_ACTIVE)


def test_every_numbered_transition_is_covered():
    numbers = {number for number, *_ in COMMAND_TRANSITIONS} | {1, 12, 13, 14, 15}
    assert numbers == set(range(1, 17))
    assert set(TRANSITIONS.values()) == set(range(1, 17))


STATUSWORDS = [
    (S.NOT_READY_TO_SWITCH_ON, 0x0000),
    (S.SWITCH_ON_DISABLED, 0x0040),
    (S.READY_TO_SWITCH_ON, 0x0021),
    (S.SWITCHED_ON, 0x0023),
    (S.OPERATION_ENABLED, 0x0027),
    (S.QUICK_STOP_ACTIVE, 0x0007),
    (S.FAULT_REACTION_ACTIVE, 0x000F),
    (S.FAULT, 0x0008),
]


@pytest.mark.parametrize(("state", "word"), STATUSWORDS)
def test_statusword_decoding(state, word):
    assert decode_statusword(word) is state


@pytest.mark.parametrize(("state", "word"), STATUSWORDS)
@pytest.mark.parametrize("other_bits", [0x0010, 0x0080, 0x0200, 0x0400, 0x0800, 0x1000, 0xF000])
def test_statusword_decoding_ignores_unrelated_bits(state, word, other_bits):
    assert decode_statusword(word | other_bits) is state


def test_statusword_decoding_ignores_quick_stop_bit_where_masked():
    assert decode_statusword(0x0060) is S.SWITCH_ON_DISABLED
    assert decode_statusword(0x0028) is S.FAULT
    assert decode_statusword(0x002F) is S.FAULT_REACTION_ACTIVE


def test_statusword_without_state_pattern_is_rejected():
    with pytest.raises(ValueError, match="0x0001"):
        decode_statusword(0x0001)


@pytest.mark.parametrize("state", list(State))
def test_encoded_statusword_decodes_to_its_state(state):
    assert decode_statusword(encode_statusword(state)) is state
    assert decode_statusword(encode_statusword(state, warning=True, following_error=True)) is state


def test_encoded_statusword_of_operation_enabled_in_csp():
    # bits 0, 1, 2 (state), 4 voltage enabled, 5 no quick stop, 9 remote, 12 following
    assert encode_statusword(S.OPERATION_ENABLED) == 0x1237
    assert encode_statusword(S.QUICK_STOP_ACTIVE) == 0x0217
    assert encode_statusword(S.OPERATION_ENABLED, following_error=True) & 0x2000


@pytest.mark.parametrize(
    ("controlword", "command"),
    [
        (0x00, Command.DISABLE_VOLTAGE),
        (0x04, Command.DISABLE_VOLTAGE),
        (0x0D, Command.DISABLE_VOLTAGE),
        (0x02, Command.QUICK_STOP),
        (0x0B, Command.QUICK_STOP),
        (0x06, Command.SHUTDOWN),
        (0x0E, Command.SHUTDOWN),
        (0x07, Command.SWITCH_ON),
        (0x0F, Command.ENABLE_OPERATION),
        (0x80, Command.FAULT_RESET),
    ],
)
def test_controlword_command_table(controlword, command):
    assert decode_controlword(controlword) is command


TOWARD_ENABLED = [
    (S.NOT_READY_TO_SWITCH_ON, 0x00),
    (S.SWITCH_ON_DISABLED, 0x06),
    (S.READY_TO_SWITCH_ON, 0x07),
    (S.SWITCHED_ON, 0x0F),
    (S.OPERATION_ENABLED, 0x0F),
    (S.QUICK_STOP_ACTIVE, 0x00),
    (S.FAULT_REACTION_ACTIVE, 0x00),
    (S.FAULT, 0x00),
]


@pytest.mark.parametrize(("state", "controlword"), TOWARD_ENABLED)
def test_controlword_toward_enabled(state, controlword):
    assert controlword_toward_enabled(state) == controlword


@pytest.mark.parametrize("start", [S.SWITCH_ON_DISABLED, S.READY_TO_SWITCH_ON, S.QUICK_STOP_ACTIVE])
def test_master_and_drive_reach_operation_enabled(start):
    state, previous = start, 0
    for _ in range(5):
        controlword = controlword_toward_enabled(state)
        state, _ = drive_transition(
            state, controlword, quick_stop_option=2, previous_controlword=previous
        )
        previous = controlword
    assert state is S.OPERATION_ENABLED


@pytest.mark.parametrize(
    "start", [S.OPERATION_ENABLED, S.SWITCHED_ON, S.READY_TO_SWITCH_ON, S.QUICK_STOP_ACTIVE]
)
def test_master_and_drive_reach_switch_on_disabled(start):
    state = start
    numbers = []
    for _ in range(4):
        state, number = drive_transition(
            state, controlword_toward_disabled(state), quick_stop_option=2
        )
        numbers.append(number)
    assert state is S.SWITCH_ON_DISABLED
    assert (
        numbers[0]
        == {
            S.OPERATION_ENABLED: 5,
            S.SWITCHED_ON: 6,
            S.READY_TO_SWITCH_ON: 7,
            S.QUICK_STOP_ACTIVE: 12,
        }[start]
    )


def test_fault_reset_sequence_makes_rising_edges_and_resets_the_drive():
    words = [fault_reset_controlword(k) for k in range(4)]
    assert words == [0x00, 0x80, 0x00, 0x80]
    assert is_fault_reset_edge(words[0], words[1])
    assert not is_fault_reset_edge(words[1], words[1])
    state, previous = S.FAULT, 0x0F
    for word in words[:2]:
        state, _ = drive_transition(state, word, quick_stop_option=2, previous_controlword=previous)
        previous = word
    assert state is S.SWITCH_ON_DISABLED


def test_fault_reset_cycle_index_must_not_be_negative():
    with pytest.raises(ValueError, match="cycle_index = -1"):
        fault_reset_controlword(-1)
