"""The machine state machine: every state/command pair, motion, faults, with ideal drives."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from fake_drives import FakeDrives
from machine_harness import PAPER, Harness, sim_config

from runtime.commands import ALLOWED, Command, CommandCode, CommandResult
from runtime.controller import Controller
from runtime.curves import load_curve_file
from runtime.status import FaultKind, MachineState


@pytest.fixture
def rig():
    drives = FakeDrives()
    controller = Controller(sim_config(), drives)
    controller.trace = []
    harness = Harness(controller)
    harness.cycle()
    yield harness, drives
    controller.close()


def reach_moving(h: Harness) -> None:
    h.standby_with_curve()
    h.command(CommandCode.START)
    # On the curve itself, past the approach from the origin to its start.
    h.until(lambda s: s.path_s_mm > 20.0, 2000)


def reach(h: Harness, drives: FakeDrives, state: MachineState) -> None:
    if state is MachineState.DISABLED:
        h.load_paper()
    elif state is MachineState.STANDBY:
        h.standby_with_curve()
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
        drives.inject_fault(1)
        h.cycle()
    assert h.status.state is state


def params_for(code: CommandCode, h: Harness) -> dict[str, object]:
    if code is CommandCode.SET_OVERRIDE:
        return {"override_percent": 50.0}
    if code is CommandCode.LOAD_CURVE:
        return {"curve": h.controller.prepare_curve(load_curve_file(PAPER))}
    return {}


def _effect_checks() -> dict[
    tuple[MachineState, CommandCode], Callable[[Harness, FakeDrives], None]
]:
    S, C = MachineState, CommandCode

    def becomes(state: MachineState, within: int = 400) -> Callable[[Harness, FakeDrives], None]:
        def check(h: Harness, drives: FakeDrives) -> None:
            h.until(lambda s: s.state is state, within)

        return check

    def curve_reloaded(h: Harness, drives: FakeDrives) -> None:
        assert h.status.curve_id == 2

    def override_set(h: Harness, drives: FakeDrives) -> None:
        assert h.status.override_percent == 50.0

    def holds(h: Harness, drives: FakeDrives) -> None:
        assert h.status.state is S.HOLDING
        h.until(lambda s: s.feed_mm_s == 0.0, 100)
        assert h.status.state is S.HOLDING

    def quick_stops(h: Harness, drives: FakeDrives) -> None:
        assert drives.requests[-1] == "quick_stop"
        h.until(lambda s: s.state is S.DISABLED, 20)

    def moves_on(h: Harness, drives: FakeDrives) -> None:
        assert h.status.state is S.MOVING
        h.until(lambda s: s.feed_mm_s > 10.0, 200)

    def stops(h: Harness, drives: FakeDrives) -> None:
        # Already at rest (a hold that finished braking) stops in the same cycle.
        assert h.status.state in (S.STOPPING, S.STANDBY)
        h.until(lambda s: s.state is S.STANDBY, 100)

    def disables_keeping_the_fault(h: Harness, drives: FakeDrives) -> None:
        # PLCopen: the fault stays latched until a reset, which then leaves the drives off.
        assert drives.requests[-1] == "disable"
        h.cycle(5)
        assert h.status.state is S.ERROR_STOP and h.status.fault is not None
        h.command(C.RESET)
        h.until(lambda s: s.state is S.DISABLED, 50)
        assert h.status.fault is None

    def resets(h: Harness, drives: FakeDrives) -> None:
        assert "fault_reset" in drives.requests
        h.until(lambda s: s.state is S.STANDBY, 50)
        assert h.status.fault is None

    return {
        (S.DISABLED, C.ENABLE): becomes(S.STANDBY, 20),
        (S.DISABLED, C.LOAD_CURVE): curve_reloaded,
        (S.DISABLED, C.SET_OVERRIDE): override_set,
        (S.STANDBY, C.DISABLE): becomes(S.DISABLED, 1),
        (S.STANDBY, C.START): moves_on,
        (S.STANDBY, C.LOAD_CURVE): curve_reloaded,
        (S.STANDBY, C.SET_OVERRIDE): override_set,
        (S.MOVING, C.HOLD): holds,
        (S.MOVING, C.STOP): stops,
        (S.MOVING, C.QUICK_STOP): quick_stops,
        (S.MOVING, C.SET_OVERRIDE): override_set,
        (S.HOLDING, C.RESUME): moves_on,
        (S.HOLDING, C.STOP): stops,
        (S.HOLDING, C.QUICK_STOP): quick_stops,
        (S.HOLDING, C.SET_OVERRIDE): override_set,
        (S.STOPPING, C.QUICK_STOP): quick_stops,
        (S.STOPPING, C.SET_OVERRIDE): override_set,
        (S.ERROR_STOP, C.RESET): resets,
        (S.ERROR_STOP, C.DISABLE): disables_keeping_the_fault,
        (S.ERROR_STOP, C.SET_OVERRIDE): override_set,
    }


EFFECTS = _effect_checks()
PAIRS = [(state, code) for state in MachineState for code in CommandCode]


def test_effects_cover_exactly_the_allowed_pairs() -> None:
    allowed = {(state, code) for state, codes in ALLOWED.items() for code in codes}
    assert set(EFFECTS) == allowed


@pytest.mark.parametrize(("state", "code"), PAIRS, ids=[f"{s.name}-{c.name}" for s, c in PAIRS])
def test_state_command_pair(rig, state: MachineState, code: CommandCode) -> None:
    h, drives = rig
    reach(h, drives, state)
    params = params_for(code, h)
    if (state, code) in EFFECTS:
        h.command(code, **params)
        EFFECTS[state, code](h, drives)
        return
    before = h.status
    requests_before = list(drives.requests)
    assert h.submit(code, **params) is CommandResult.REJECTED_STATE
    # The same command reaching the cycle anyway (state changed after the check) changes nothing.
    machine = h.controller.machine
    assert machine.apply(Command(code, **params)) is CommandResult.REJECTED_STATE
    assert machine.state is before.state
    assert machine.curve_id == before.curve_id
    assert machine.override_percent == before.override_percent
    assert drives.requests == requests_before


def test_invalid_parameters_are_refused(rig) -> None:
    h, _ = rig
    for value in (-1.0, 150.5, None):
        assert (
            h.submit(CommandCode.SET_OVERRIDE, override_percent=value)
            is CommandResult.INVALID_PARAMETER
        )
    assert h.submit(CommandCode.LOAD_CURVE, curve="not prepared") is CommandResult.INVALID_PARAMETER
    h.enable()
    assert h.submit(CommandCode.START) is CommandResult.NO_CURVE
    assert h.status.state is MachineState.STANDBY


def test_paper_curve_runs_to_its_exact_end(rig) -> None:
    h, drives = rig
    h.standby_with_curve()
    h.command(CommandCode.START)
    h.until(lambda s: s.state is MachineState.STANDBY, 2000)
    end = h.controller.machine.loaded.curve.end_point
    assert h.controller.machine.targets == tuple(end)
    h.cycle()
    assert [a.position_mm for a in drives.axes] == list(end)
    assert h.status.progress_permille == 1000
    targets = h.sent_targets()
    steps = np.linalg.norm(np.diff(targets, axis=0), axis=1)
    assert steps.max() <= 100.0 * 0.004 * 1.001


def test_fault_mid_curve_stops_every_axis_without_jump(rig) -> None:
    h, drives = rig
    reach_moving(h)
    feed_before = h.status.feed_mm_s
    assert feed_before > 50
    drives.inject_fault(2, emcy_code=0x8611, text="EMCY 0x8611 following error")
    fault_cycle = len(h.controller.trace)
    h.cycle()
    status = h.status
    assert status.state is MachineState.ERROR_STOP
    assert status.fault.kind is FaultKind.DRIVE_FAULT and status.fault.emcy_code == 0x8611
    assert status.fault.axis == "Z"
    h.until(lambda s: s.feed_mm_s == 0.0, 60)
    targets = h.sent_targets()
    steps = np.linalg.norm(np.diff(targets, axis=0), axis=1)
    assert steps.max() <= 100.0 * 0.004 * 1.001
    # Braking began in the cycle that saw the fault: from there on every step is shorter.
    braking = steps[fault_cycle - 1 :]
    assert np.all(np.diff(braking) <= 1e-12)
    assert braking[2] < braking[0]
    assert steps[-1] > 0 and h.status.feed_mm_s == 0.0
    h.command(CommandCode.RESET)
    h.until(lambda s: s.state is MachineState.STANDBY, 50)
