"""The machine state machine in its cycle: every state/command pair, programs, commands judged
in order, faults and their reactions, the watchdog, the planner's supervision, shutdown.

Cycle and planner service in one process with ideal drives (:mod:`machine_harness`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from machine_harness import Harness, sim_config

from drives.cia402 import State
from runtime.commands import ALLOWED, CommandCode, CommandOrigin, CommandResult
from runtime.status import FaultKind, MachineState, MotionPhase, WatchdogState

VMAX_STEP_MM = 100.0 * 0.004 * 1.001


@pytest.fixture
def h(tmp_path: Path) -> Harness:
    harness = Harness(tmp_path)
    harness.period()
    return harness


def reach_moving(h: Harness) -> None:
    h.standby_with_program()
    assert h.command(CommandCode.START) is CommandResult.DONE
    # On the curve itself, past the approach from the origin to its start.
    h.until(lambda s: s.phase is MotionPhase.PROGRAM and s.path_s_mm > 20.0, 2000)


def reach(h: Harness, state: MachineState) -> None:
    if state is MachineState.DISABLED:
        h.load()
    elif state is MachineState.STANDBY:
        h.standby_with_program()
    elif state is MachineState.MOVING:
        reach_moving(h)
    elif state is MachineState.HOLDING:
        reach_moving(h)
        h.command(CommandCode.HOLD)
        h.until(lambda s: s.feed_mm_s == 0.0, 100)
    elif state is MachineState.STOPPING:
        reach_moving(h)
        h.command(CommandCode.STOP)
    elif state is MachineState.ERROR_STOP:
        reach_moving(h)
        h.drives.inject_fault(1)
        h.period()
    assert h.status.state is state


def params_for(code: CommandCode, h: Harness) -> dict[str, object]:
    if code is CommandCode.SET_OVERRIDE:
        return {"override_percent": 50.0}
    if code is CommandCode.LOAD_CURVE:
        return {"program": h.program()}
    return {}


Check = Callable[[Harness], None]


def _effect_checks() -> dict[tuple[MachineState, CommandCode], Check]:
    S, C = MachineState, CommandCode

    def becomes(state: MachineState, within: int = 400) -> Check:
        def check(h: Harness) -> None:
            h.until(lambda s: s.state is state, within)

        return check

    def program_loaded(h: Harness) -> None:
        status = h.status
        assert status.program is not None and status.program.program_id == 2
        assert status.next_program is None

    def next_program_loaded(h: Harness) -> None:
        status = h.status
        assert status.program is not None and status.program.program_id == 1
        assert status.next_program is not None and status.next_program.program_id == 2

    def next_cleared(h: Harness) -> None:
        assert h.status.next_program is None

    def override_set(h: Harness) -> None:
        assert h.status.override_percent == 50.0

    def holds(h: Harness) -> None:
        assert h.status.state is S.HOLDING
        h.until(lambda s: s.feed_mm_s == 0.0, 100)
        assert h.status.state is S.HOLDING

    def quick_stops(h: Harness) -> None:
        assert h.drives.requests[-1] == "quick_stop"
        h.until(lambda s: s.state is S.DISABLED, 20)

    def moves_on(h: Harness) -> None:
        assert h.status.state is S.MOVING
        h.until(lambda s: s.feed_mm_s > 10.0, 200)

    def stops(h: Harness) -> None:
        # Already at rest (a hold that finished braking) stops in the same period.
        assert h.status.state in (S.STOPPING, S.STANDBY)
        h.until(lambda s: s.state is S.STANDBY, 100)

    def disables_keeping_the_fault(h: Harness) -> None:
        # PLCopen: the fault stays latched until a reset, which then leaves the drives off.
        assert h.drives.requests[-1] == "disable"
        h.period(5)
        assert h.status.state is S.ERROR_STOP and h.status.fault is not None
        assert h.command(C.RESET) is CommandResult.DONE
        h.until(lambda s: s.state is S.DISABLED, 50)
        assert h.status.fault is None

    def resets(h: Harness) -> None:
        assert "fault_reset" in h.drives.requests
        h.until(lambda s: s.state is S.STANDBY, 50)
        assert h.status.fault is None

    loads = {
        state: (
            program_loaded
            if state in (S.DISABLED, S.STANDBY, S.ERROR_STOP)
            else next_program_loaded
        )
        for state in S
    }
    effects: dict[tuple[MachineState, CommandCode], Check] = {
        (S.DISABLED, C.ENABLE): becomes(S.STANDBY, 20),
        (S.STANDBY, C.DISABLE): becomes(S.DISABLED, 1),
        (S.STANDBY, C.START): moves_on,
        (S.MOVING, C.HOLD): holds,
        (S.MOVING, C.STOP): stops,
        (S.MOVING, C.QUICK_STOP): quick_stops,
        (S.HOLDING, C.RESUME): moves_on,
        (S.HOLDING, C.STOP): stops,
        (S.HOLDING, C.QUICK_STOP): quick_stops,
        (S.STOPPING, C.QUICK_STOP): quick_stops,
        (S.ERROR_STOP, C.RESET): resets,
        (S.ERROR_STOP, C.DISABLE): disables_keeping_the_fault,
    }
    for state in S:
        effects[state, C.LOAD_CURVE] = loads[state]
        effects[state, C.CLEAR_NEXT] = next_cleared
        effects[state, C.SET_OVERRIDE] = override_set
    return effects


EFFECTS = _effect_checks()
OPERATOR_CODES = [code for code in CommandCode if code is not CommandCode.SHUTDOWN]
PAIRS = [(state, code) for state in MachineState for code in OPERATOR_CODES]


def test_effects_cover_exactly_the_allowed_pairs() -> None:
    allowed = {(state, code) for state, codes in ALLOWED.items() for code in codes}
    assert set(EFFECTS) == allowed


@pytest.mark.parametrize(("state", "code"), PAIRS, ids=[f"{s.name}-{c.name}" for s, c in PAIRS])
def test_state_command_pair(h: Harness, state: MachineState, code: CommandCode) -> None:
    reach(h, state)
    params = params_for(code, h)
    if (state, code) in EFFECTS:
        assert h.command(code, **params) is CommandResult.DONE
        EFFECTS[state, code](h)
        return
    before = h.status
    requests_before = list(h.drives.requests)
    ticket = h.post(code, **params)
    h.period()
    # Refused under its own ticket, and nothing changed.
    assert h.record_of(ticket).result is CommandResult.REJECTED_STATE
    after = h.status
    assert after.state is before.state
    assert after.program == before.program and after.next_program == before.next_program
    assert after.override_percent == before.override_percent
    assert h.drives.requests == requests_before


def test_invalid_parameters_are_refused_under_their_ticket(h: Harness) -> None:
    for value in (-1.0, 150.5):
        assert (
            h.command(CommandCode.SET_OVERRIDE, override_percent=value)
            is CommandResult.INVALID_PARAMETER
        )
    assert h.command(CommandCode.LOAD_CURVE) is CommandResult.INVALID_PARAMETER
    h.enable()
    assert h.command(CommandCode.START) is CommandResult.NO_CURVE
    assert h.status.state is MachineState.STANDBY
    assert h.status.override_percent == 100.0


def test_commands_are_judged_in_queue_order_against_the_state_they_run_in(h: Harness) -> None:
    h.standby_with_program()
    start = h.post(CommandCode.START)
    hold = h.post(CommandCode.HOLD)
    resume = h.post(CommandCode.RESUME)
    h.period()
    assert [h.record_of(t).result for t in (start, hold, resume)] == [CommandResult.DONE] * 3
    assert h.status.state is MachineState.MOVING
    records = h.status.recent_commands[-3:]
    assert [r.ticket for r in records] == [start, hold, resume]
    assert all(r.origin is CommandOrigin.COMMAND_LINE for r in records)


def test_paper_curve_runs_to_its_exact_end(h: Harness) -> None:
    program = h.standby_with_program()
    assert h.command(CommandCode.START) is CommandResult.DONE
    h.until(lambda s: s.state is MachineState.STANDBY, 2000)
    assert h.machine.targets == program.end_mm
    h.period(2)  # sent with the next SYNC, reached by the one after
    assert tuple(a.position_mm for a in h.drives.axes) == program.end_mm
    status = h.status
    assert status.progress_permille == 1000 and status.message == "program finished"
    steps = np.linalg.norm(np.diff(h.target_array(), axis=0), axis=1)
    assert steps.max() <= VMAX_STEP_MM


def test_status_shows_the_approach_then_the_program(h: Harness) -> None:
    program = h.standby_with_program()
    h.command(CommandCode.START)
    h.until(lambda s: s.phase is MotionPhase.APPROACH and s.path_s_mm > 0.5, 200)
    status = h.status
    approach_mm = float(np.linalg.norm(program.start_mm))
    assert status.path_length_mm == pytest.approx(approach_mm)
    assert 0 < status.progress_permille < 1000
    h.until(lambda s: s.phase is MotionPhase.PROGRAM, 400)
    assert h.status.path_length_mm == pytest.approx(program.length_mm)


def test_a_program_loaded_while_moving_runs_when_the_current_one_ends(h: Harness) -> None:
    first = h.standby_with_program()
    h.command(CommandCode.START)
    h.period(10)
    second = h.program()
    assert h.command(CommandCode.LOAD_CURVE, program=second) is CommandResult.DONE
    assert h.status.next_program.program_id == second.program_id
    # The running one is untouched: it ends, then the next one starts from its end point.
    h.until(lambda s: s.program.program_id == second.program_id, 3000)
    status = h.status
    assert status.state is MachineState.MOVING and status.next_program is None
    assert h.machine.targets == first.end_mm  # its last row, exactly
    h.until(lambda s: s.state is MachineState.STANDBY, 3000)
    assert h.machine.targets == second.end_mm
    steps = np.linalg.norm(np.diff(h.target_array(), axis=0), axis=1)
    assert steps.max() <= VMAX_STEP_MM


def test_a_stopped_program_leaves_the_next_one_for_start(h: Harness) -> None:
    reach_moving(h)
    second = h.program()
    h.command(CommandCode.LOAD_CURVE, program=second)
    h.command(CommandCode.STOP)
    h.until(lambda s: s.state is MachineState.STANDBY, 200)
    status = h.status
    assert status.program.program_id == second.program_id and status.next_program is None
    assert h.command(CommandCode.START) is CommandResult.DONE
    h.until(lambda s: s.state is MachineState.STANDBY, 4000)
    assert h.machine.targets == second.end_mm


def test_hold_then_resume_stays_smooth_and_ends_exactly(h: Harness) -> None:
    program = h.standby_with_program()
    h.command(CommandCode.START)
    h.until(lambda s: s.phase is MotionPhase.PROGRAM and s.path_s_mm > 60.0, 2000)
    h.command(CommandCode.HOLD)
    h.until(lambda s: s.feed_mm_s == 0.0, 200)
    held = h.machine.targets
    h.period(20)
    assert h.machine.targets == held and h.status.state is MachineState.HOLDING
    h.command(CommandCode.RESUME)
    h.until(lambda s: s.state is MachineState.STANDBY, 3000)
    assert h.machine.targets == program.end_mm
    steps = np.linalg.norm(np.diff(h.target_array(), axis=0), axis=1)
    assert steps.max() <= VMAX_STEP_MM


def _axis_fault_config(reaction: str):
    config = sim_config()
    return replace(config, machine=replace(config.machine, axis_fault_reaction=reaction))


def test_axis_fault_with_stop_reaction_brakes_every_axis_along_the_path(tmp_path: Path) -> None:
    h = Harness(tmp_path, config=_axis_fault_config("stop"))
    reach_moving(h)
    assert h.status.feed_mm_s > 50
    h.drives.inject_fault(2, emcy_code=0x8611, text="EMCY 0x8611 following error")
    fault_period = len(h.targets)
    h.period()
    status = h.status
    assert status.state is MachineState.ERROR_STOP
    assert status.fault.kind is FaultKind.DRIVE_FAULT and status.fault.emcy_code == 0x8611
    assert status.fault.axis == "Z"
    h.until(lambda s: s.feed_mm_s == 0.0, 60)
    steps = np.linalg.norm(np.diff(h.target_array(), axis=0), axis=1)
    assert steps.max() <= VMAX_STEP_MM
    # Braking began in the period that saw the fault: from there on every step is shorter.
    braking = steps[fault_period - 1 :]
    assert np.all(np.diff(braking) <= 1e-12)
    assert braking[2] < braking[0]
    assert h.command(CommandCode.RESET) is CommandResult.DONE
    h.until(lambda s: s.state is MachineState.STANDBY, 50)


def test_axis_fault_with_quick_stop_reaction_quick_stops_every_drive(h: Harness) -> None:
    reach_moving(h)
    h.drives.inject_fault(0)
    h.period()
    assert h.status.state is MachineState.ERROR_STOP
    assert h.drives.requests[-1] == "quick_stop"
    h.until(lambda s: all(a.drive_state != State.OPERATION_ENABLED for a in s.axes), 20)
    # The reset enables the drives again: the quick stop was the fault's, not the operator's.
    assert h.command(CommandCode.RESET) is CommandResult.DONE
    h.until(lambda s: s.state is MachineState.STANDBY, 50)


def test_later_faults_are_listed_after_the_first(tmp_path: Path) -> None:
    h = Harness(tmp_path, config=_axis_fault_config("stop"))
    reach_moving(h)
    h.drives.inject_fault(0, emcy_code=0x8611, text="EMCY 0x8611 following error")
    h.period()
    h.drives.inject_fault(1, emcy_code=0x8130, text="EMCY 0x8130 heartbeat")
    h.period()
    status = h.status
    assert status.fault.axis == "X" and status.fault.emcy_code == 0x8611
    assert [(f.axis, f.emcy_code) for f in status.later_faults] == [("Y", 0x8130)]
    h.command(CommandCode.RESET)
    h.until(lambda s: s.state is MachineState.STANDBY, 50)
    assert h.status.later_faults == ()


def test_watchdog_holds_once_while_moving_then_rearms(tmp_path: Path) -> None:
    config = sim_config()
    watchdog = replace(config.modbus.watchdog, timeout_ms=100, action="hold")
    h = Harness(tmp_path, config=replace(config, modbus=replace(config.modbus, watchdog=watchdog)))
    h.shared.hmi_activity.value += 1
    h.standby_with_program()
    h.command(CommandCode.START)
    h.until(lambda s: s.state is MachineState.HOLDING, 100)
    assert h.status.state is MachineState.HOLDING
    assert h.status.watchdog is WatchdogState.TRIPPED
    record = h.status.last_command
    assert record.origin is CommandOrigin.WATCHDOG and record.code is CommandCode.HOLD
    assert "watchdog" in h.status.message
    h.shared.hmi_activity.value += 1
    h.period()
    assert h.status.watchdog is WatchdogState.WATCHING


def test_planner_restart_stops_on_the_planned_rows_and_reset_recovers(h: Harness) -> None:
    program = h.standby_with_program()
    h.command(CommandCode.START)
    h.until(lambda s: s.phase is MotionPhase.PROGRAM and s.path_s_mm > 20.0, 2000)
    h.shared.planner_generation.value += 1
    h.period()
    status = h.status
    assert status.state is MachineState.ERROR_STOP
    assert status.fault.kind is FaultKind.PLANNER_LOST
    h.until(lambda s: s.feed_mm_s == 0.0, 200)
    steps = np.linalg.norm(np.diff(h.target_array(), axis=0), axis=1)
    assert steps.max() <= VMAX_STEP_MM
    assert h.command(CommandCode.RESET) is CommandResult.DONE
    h.until(lambda s: s.state is MachineState.STANDBY, 50)
    assert h.command(CommandCode.START) is CommandResult.DONE
    h.until(lambda s: s.state is MachineState.STANDBY, 4000)
    assert h.machine.targets == program.end_mm


def test_a_planner_that_falls_behind_is_an_underrun_and_a_smooth_stop(h: Harness) -> None:
    h.planner.buffer_high_periods = 100  # less than the whole job: rows can run short
    reach_moving(h)
    # The planner stops working: the rows ahead run short of the braking time.
    for _ in range(600):
        h.period(plan=False)
        if h.status.state is MachineState.ERROR_STOP:
            break
    status = h.status
    assert status.fault.kind is FaultKind.BUFFER_UNDERRUN, status
    assert "planner behind" in status.fault.text
    for _ in range(200):
        h.period(plan=False)
    assert h.status.feed_mm_s == 0.0
    steps = np.linalg.norm(np.diff(h.target_array(), axis=0), axis=1)
    assert steps.max() <= VMAX_STEP_MM
    assert np.all(np.isfinite(h.target_array()))


def test_shutdown_stops_on_the_path_disables_and_leaves_the_bus(h: Harness) -> None:
    reach_moving(h)
    h.post(CommandCode.SHUTDOWN, origin=CommandOrigin.SHUTDOWN)
    h.period()
    assert h.status.state is MachineState.STOPPING
    for _ in range(400):
        h.period()
        if h.cycle.finished:
            break
    assert h.cycle.finished and h.drives.shutting_down
    assert h.status.state is MachineState.DISABLED
    steps = np.linalg.norm(np.diff(h.target_array(), axis=0), axis=1)
    assert steps.max() <= VMAX_STEP_MM


def test_a_faulted_axis_shows_how_far_it_stands_off_the_path(tmp_path: Path) -> None:
    h = Harness(tmp_path, config=_axis_fault_config("stop"))
    reach_moving(h)
    h.drives.inject_fault(0)
    h.until(lambda s: s.feed_mm_s == 0.0, 100)
    status = h.status
    x = status.axes[0]
    assert x.drive_state == State.FAULT
    # The others braked on along the path while X stood: its error is the distance to it.
    assert x.following_error_mm == pytest.approx(x.actual_mm - x.commanded_mm)
    assert abs(x.following_error_mm) > 0.5
    assert status.axes[1].following_error_mm == pytest.approx(0.0, abs=1e-9)
