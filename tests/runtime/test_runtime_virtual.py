"""The whole machine on python-can's virtual bus: master, three simulated drives, cyclic task.

Real time (4 ms cycle in its own thread). Limits are checked on the targets the controller sent
each cycle, by finite differences, as the drives receive them.
"""

from __future__ import annotations

import time
import uuid
from dataclasses import replace

import numpy as np
import pytest
from machine_harness import PAPER, sim_config
from setpoint_checks import chord_errors, differences, realised_feed

from runtime.app import RunningMachine, start_machine
from runtime.commands import CommandCode
from runtime.config import MachineConfig
from runtime.curves import load_curve_file
from runtime.status import FaultKind, MachineState

T = 0.004
VMAX, AMAX, JMAX, DELTA = 100.0, 1000.0, 20000.0, 0.001
pytestmark = pytest.mark.slow


def virtual_config() -> MachineConfig:
    config = sim_config()
    return replace(
        config,
        can=replace(config.can, channel=f"test-{uuid.uuid4().hex[:8]}"),
        modbus=replace(config.modbus, enabled=False),
    )


@pytest.fixture
def machine():
    with start_machine(virtual_config()) as running:
        running.controller.trace = []
        yield running


def run_to_standby(m: RunningMachine, timeout_s: float = 20.0) -> None:
    m.wait_for(lambda s: s.state is not MachineState.MOVING, timeout_s)
    status = m.controller.snapshot()
    assert status.state is MachineState.STANDBY, status.message


def load_enable_start(m: RunningMachine) -> None:
    m.command(CommandCode.LOAD_CURVE, curve=m.controller.prepare_curve(load_curve_file(PAPER)))
    m.command(CommandCode.ENABLE)
    m.wait_for(lambda s: s.state is MachineState.STANDBY, 5.0)
    m.command(CommandCode.START)


def sent(m: RunningMachine) -> np.ndarray:
    return np.array([t.targets_mm for t in m.controller.trace])


def check_limits(positions: np.ndarray, vmax: float) -> None:
    feed = realised_feed(positions, T)
    accel = differences(feed, T)
    jerk = differences(accel, T)
    assert feed.max() <= vmax * 1.001
    assert np.abs(accel).max() <= AMAX * 1.02
    assert np.abs(jerk).max() <= JMAX * 1.05


def check_curve_rows_and_end(m: RunningMachine, positions: np.ndarray) -> None:
    curve = m.controller.machine.loaded.curve
    end = curve.end_point
    # The targets from the first one equal to the curve's start on are on the curve.
    start = int(
        np.flatnonzero(np.all(np.isclose(positions, curve.start_point, rtol=0, atol=1e-9), 1))[0]
    )
    rows = positions[start:]
    arc = m.controller.machine.loaded.path.arc
    lengths = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(rows, axis=0), axis=1))])
    u = arc.u_of_s(np.clip(lengths, 0, arc.length_mm))
    # Positions are on the curve: each is C(u) for the u nearest in arc length (chords are
    # shorter than arcs by < 1e-6 mm here, so the u found is close; refine by projection).
    for _ in range(3):
        d = curve.evaluate(u, order=1)
        diff = rows - d[0]
        u = np.clip(u + np.sum(diff * d[1], 1) / np.sum(d[1] * d[1], 1), *curve.domain)
    assert np.abs(curve.evaluate(u)[0] - rows).max() < 1e-6
    assert chord_errors(curve, u, rows).max() <= DELTA * 1.01
    assert np.array_equal(rows[-1], end)


def test_paper_curve_end_to_end(machine: RunningMachine) -> None:
    load_enable_start(machine)
    run_to_standby(machine)
    time.sleep(0.1)  # let the drives settle on the last target
    status = machine.controller.snapshot()
    end = machine.controller.machine.loaded.curve.end_point
    for axis, target, config in zip(status.axes, end, machine.config.axes, strict=True):
        counts_off = abs(axis.actual_mm - target) * config.counts_per_mm
        assert counts_off <= 1.0, (axis.name, axis.actual_mm, target)
    positions = sent(machine)
    check_limits(positions, VMAX)
    check_curve_rows_and_end(machine, positions)


def test_hold_then_resume(machine: RunningMachine) -> None:
    load_enable_start(machine)
    machine.wait_for(lambda s: s.path_s_mm > 60.0, 10.0)
    machine.command(CommandCode.HOLD)
    held = machine.wait_for(lambda s: s.feed_mm_s == 0.0, 2.0)
    assert held.state is MachineState.HOLDING
    time.sleep(0.1)
    assert machine.controller.snapshot().path_s_mm == held.path_s_mm
    machine.command(CommandCode.RESUME)
    run_to_standby(machine)
    positions = sent(machine)
    check_limits(positions, VMAX)
    check_curve_rows_and_end(machine, positions)


def test_override_30_then_150(machine: RunningMachine) -> None:
    load_enable_start(machine)
    machine.wait_for(lambda s: s.path_s_mm > 20.0, 10.0)
    machine.command(CommandCode.SET_OVERRIDE, override_percent=30.0)
    time.sleep(0.6)
    recent = realised_feed(sent(machine)[-50:], T)
    assert recent.max() <= 30.0 * 1.001
    machine.command(CommandCode.SET_OVERRIDE, override_percent=150.0)
    run_to_standby(machine)
    positions = sent(machine)
    check_limits(positions, 150.0)
    check_curve_rows_and_end(machine, positions)


def test_drive_fault_stops_every_axis_then_reset(machine: RunningMachine) -> None:
    load_enable_start(machine)
    machine.wait_for(lambda s: s.path_s_mm > 40.0 and s.feed_mm_s > 50.0, 10.0)
    machine.simulated.drives[2].inject_fault(0x4210)
    status = machine.wait_for(lambda s: s.state is MachineState.ERROR_STOP, 1.0)
    assert status.fault.kind is FaultKind.DRIVE_FAULT
    assert status.fault.emcy_code == 0x4210 and status.fault.axis == "Y"
    machine.wait_for(lambda s: s.feed_mm_s == 0.0, 1.0)
    trace = machine.controller.trace
    first_seen = next(i for i, t in enumerate(trace) if t.drive_fault_seen)
    stopped = next(i for i, t in enumerate(trace) if t.state is MachineState.ERROR_STOP)
    assert stopped - first_seen <= 1  # the cycle that sees the fault (at most the next) stops
    steps = np.linalg.norm(np.diff(sent(machine), axis=0), axis=1)
    assert steps.max() <= VMAX * T * 1.001  # no jump
    assert np.all(np.diff(steps[stopped:]) <= 1e-9)  # only braking after the fault
    machine.command(CommandCode.RESET)
    machine.wait_for(lambda s: s.state is MachineState.STANDBY, 5.0)
    assert machine.controller.snapshot().fault is None
    before_restart = len(trace)
    machine.command(CommandCode.START)
    run_to_standby(machine)
    steps = np.linalg.norm(np.diff(sent(machine)[before_restart - 1 :], axis=0), axis=1)
    assert steps.max() <= VMAX * T * 1.001


def test_lost_drive_stops_every_axis_and_reset_configures_it_again(
    machine: RunningMachine,
) -> None:
    load_enable_start(machine)
    machine.wait_for(lambda s: s.path_s_mm > 40.0, 10.0)
    drive = machine.simulated.drives[3]
    drive.stop_answering()
    status = machine.wait_for(lambda s: s.state is MachineState.ERROR_STOP, 1.0)
    assert status.fault.kind in (FaultKind.STALE_FEEDBACK, FaultKind.HEARTBEAT_LOSS)
    assert status.fault.axis == "Z"
    machine.wait_for(lambda s: s.feed_mm_s == 0.0, 1.0)
    steps = np.linalg.norm(np.diff(sent(machine), axis=0), axis=1)
    assert steps.max() <= VMAX * T * 1.001
    # Heartbeat loss: 2.5 heartbeat periods of 100 ms.
    lost = machine.wait_for(lambda s: "heartbeat" in s.axes[2].fault, 1.0)
    assert lost.state is MachineState.ERROR_STOP
    drive.resume_answering()
    machine.command(CommandCode.RESET)
    machine.wait_for(lambda s: s.state is MachineState.STANDBY, 10.0)
    machine.command(CommandCode.START)
    run_to_standby(machine)
    end = machine.controller.machine.loaded.curve.end_point
    assert np.array_equal(sent(machine)[-1], end)
