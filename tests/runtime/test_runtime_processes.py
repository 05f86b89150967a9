"""The whole runtime as processes: supervisor, cycle, planner and simulated drives on the
``local`` bus, in real time (4 ms).

Limits are checked on the targets the drives received (RPDO1 frames recorded by an independent
listener on the bus, one row per SYNC), by finite differences. Process deaths: a killed planner
stops the machine on the path and is started again; a killed cycle ends the runtime.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
import threading
import time
import uuid
from dataclasses import replace

import numpy as np
import pytest
from bus_recorder import BusRecorder
from machine_harness import PAPER
from machine_process import connect_when_listening
from setpoint_checks import differences, realised_feed
from sim_machine import free_port, sim_document

from drives.sim.quirks import DriveQuirks
from runtime.commands import CommandCode, CommandOrigin
from runtime.config import MachineConfig, parse_config
from runtime.curves import load_curve_file
from runtime.hmi.client import HmiClient
from runtime.simulation import simulation_main
from runtime.status import FaultKind, MachineState, MotionPhase, WatchdogState
from runtime.supervisor import CycleDied, Runtime

T = 0.004
VMAX, AMAX, JMAX = 100.0, 1000.0, 20000.0
pytestmark = pytest.mark.slow


def local_config() -> MachineConfig:
    return parse_config(
        sim_document(
            {"can": {"channel": f"test-{uuid.uuid4().hex[:8]}"}, "modbus": {"enabled": False}}
        )
    )


@pytest.fixture
def runtime():
    config = local_config()
    with BusRecorder(config.can.interface, config.can.channel) as recorder:
        runtime = Runtime(config, log_level="WARNING")
        runtime.recorder = recorder
        try:
            runtime.start()
            yield runtime
        finally:
            runtime.stop()


def load_enable(runtime: Runtime):
    program = runtime.programs.add(load_curve_file(PAPER), runtime.config, name="paper", crc32=0)
    runtime.command(CommandCode.LOAD_CURVE, program=program)
    runtime.command(CommandCode.ENABLE)
    runtime.wait_for(lambda s: s.state is MachineState.STANDBY, 10.0)
    return program


def run_to_standby(runtime: Runtime, timeout_s: float = 20.0) -> None:
    status = runtime.wait_for(lambda s: s.state is not MachineState.MOVING, timeout_s)
    assert status.state is MachineState.STANDBY, status.message


def received_targets_mm(runtime: Runtime) -> np.ndarray:
    nodes = tuple(axis.node_id for axis in runtime.config.axes)
    scale = np.array([axis.counts_per_mm for axis in runtime.config.axes])
    return runtime.recorder.targets_counts(nodes) / scale


def check_limits(positions: np.ndarray, vmax: float) -> None:
    # Targets are whole counts (1 µm): allow the rounding in the differences. Rounding each
    # axis moves a chord's length by up to sum_k |t_k| counts (t its unit direction), at most
    # sqrt(axes): a braking at amax along (0.82, -0.51, 0.26) measured 1,169 mm/s² on the
    # counts, 1,004 fitted over 9 periods.
    feed = realised_feed(positions, T)
    accel = differences(feed, T)
    jerk = differences(accel, T)
    rounding_mm = 0.001 * np.sqrt(positions.shape[1])
    assert feed.max() <= vmax * 1.001 + rounding_mm / T
    assert np.abs(accel).max() <= AMAX * 1.02 + 2 * rounding_mm / T**2
    assert np.abs(jerk).max() <= JMAX * 1.05 + 4 * rounding_mm / T**3


def test_paper_curve_reaches_the_drives_exactly(runtime: Runtime) -> None:
    program = load_enable(runtime)
    runtime.command(CommandCode.START)
    run_to_standby(runtime)
    time.sleep(0.05)
    targets = received_targets_mm(runtime)
    assert tuple(targets[-1]) == program.end_mm
    moving = targets[np.flatnonzero(np.any(np.diff(targets, axis=0) != 0, axis=1))[0] :]
    check_limits(moving, VMAX)
    status = runtime.status()
    assert [round(a.actual_mm * 1000) for a in status.axes] == [
        round(v * 1000) for v in program.end_mm
    ]


def test_hold_and_resume_across_processes(runtime: Runtime) -> None:
    program = load_enable(runtime)
    runtime.command(CommandCode.START)
    runtime.wait_for(lambda s: s.phase is MotionPhase.PROGRAM and s.path_s_mm > 40, 10.0)
    runtime.command(CommandCode.HOLD)
    held = runtime.wait_for(lambda s: s.feed_mm_s == 0.0 and s.phase is MotionPhase.IDLE, 2.0)
    assert held.state is MachineState.HOLDING
    runtime.command(CommandCode.RESUME)
    run_to_standby(runtime)
    time.sleep(0.05)
    targets = received_targets_mm(runtime)
    assert tuple(targets[-1]) == program.end_mm
    check_limits(targets, VMAX)


def test_override_changes_are_spliced_smoothly(runtime: Runtime) -> None:
    program = load_enable(runtime)
    runtime.command(CommandCode.START)
    runtime.wait_for(lambda s: s.phase is MotionPhase.PROGRAM and s.path_s_mm > 10, 10.0)
    runtime.command(CommandCode.SET_OVERRIDE, override_percent=40.0)
    runtime.wait_for(lambda s: 0 < s.feed_mm_s <= 40.5, 2.0)
    runtime.command(CommandCode.SET_OVERRIDE, override_percent=120.0)
    run_to_standby(runtime, 30.0)
    time.sleep(0.05)
    targets = received_targets_mm(runtime)
    assert tuple(targets[-1]) == program.end_mm
    check_limits(targets, VMAX * 1.2)


def test_killed_planner_stops_on_the_path_is_restarted_and_the_next_start_works(
    runtime: Runtime,
) -> None:
    program = load_enable(runtime)
    runtime.command(CommandCode.START)
    runtime.wait_for(lambda s: s.phase is MotionPhase.PROGRAM and s.path_s_mm > 30, 10.0)
    planner = runtime.process("planner")
    os.kill(planner.pid, signal.SIGKILL)
    status = runtime.wait_for(lambda s: s.state is MachineState.ERROR_STOP, 2.0)
    assert status.fault.kind is FaultKind.PLANNER_LOST
    runtime.wait_for(lambda s: s.feed_mm_s == 0.0, 2.0)
    restarted = runtime.process("planner")
    assert restarted.pid != planner.pid and restarted.is_alive()
    time.sleep(0.05)
    check_limits(received_targets_mm(runtime), VMAX)
    runtime.command(CommandCode.RESET)
    runtime.wait_for(lambda s: s.state is MachineState.STANDBY, 5.0)
    runtime.command(CommandCode.START, timeout_s=10.0)
    run_to_standby(runtime)
    assert runtime.status().axes[0].commanded_mm == program.end_mm[0]


def test_killed_cycle_ends_the_runtime_with_a_clear_message(runtime: Runtime) -> None:
    load_enable(runtime)
    cycle = runtime.process("cycle")
    os.kill(cycle.pid, signal.SIGKILL)
    with pytest.raises(CycleDied, match="signal 9"):
        runtime.wait_for(lambda s: False, 5.0)
    runtime.stop()
    for name in ("planner", "simulated-drives"):
        assert not runtime.process(name).is_alive()


def test_a_drive_faulted_at_power_on_is_an_error_stop_and_reset_brings_it_up() -> None:
    config = local_config()
    simulation = replace(config.simulation, quirks={"Y": DriveQuirks(fault_at_power_on=True)})
    with Runtime(replace(config, simulation=simulation), log_level="WARNING") as runtime:
        status = runtime.wait_for(lambda s: s.state is MachineState.ERROR_STOP, 15.0)
        # The drive says why in its EMCY and in 0x603F; the master latches whichever it
        # sees first: the EMCY sent at boot, or the statusword with the error code.
        assert status.fault.axis == "Y" and "0x8130" in status.fault.text
        runtime.command(CommandCode.RESET)
        runtime.wait_for(lambda s: s.state is MachineState.DISABLED and s.fault is None, 10.0)
        program = load_enable(runtime)
        runtime.command(CommandCode.START)
        run_to_standby(runtime)
        assert runtime.status().axes[2].commanded_mm == program.end_mm[2]


def test_a_second_start_after_a_clean_shutdown_finds_every_drive_healthy() -> None:
    """The drives outlive the runtime (a process of their own here, hardware on a machine):
    the shutdown must leave none supervising a master that is gone, so none raises an EMCY
    (0x8130 heartbeat loss) afterwards, and the next start enables them all."""
    config = local_config()
    context = multiprocessing.get_context("spawn")
    drives = context.Process(target=simulation_main, args=(config, "WARNING", os.getpid()))
    drives.start()
    config = replace(config, simulation=replace(config.simulation, drives=False))
    emcy_ids = {0x80 + axis.node_id for axis in config.axes}
    try:
        with BusRecorder(config.can.interface, config.can.channel) as recorder:
            for _ in range(2):
                with Runtime(config, log_level="WARNING") as runtime:
                    load_enable(runtime)
                    runtime.command(CommandCode.START)
                    run_to_standby(runtime)
                left = len(recorder.frames)
                # Longer than the heartbeat the drives consumed (2.5 x 100 ms).
                time.sleep(0.6)
                after = recorder.frames[left:]
                errors = [f for f in after if f.can_id in emcy_ids and f.data[:2] != b"\0\0"]
                assert errors == []
    finally:
        drives.terminate()
        drives.join(10)


def test_killed_hmi_lets_the_watchdog_hold_and_comes_back() -> None:
    config = local_config()
    watchdog = replace(config.modbus.watchdog, timeout_ms=300, action="hold")
    modbus = replace(config.modbus, enabled=True, port=free_port(), watchdog=watchdog)
    with Runtime(replace(config, modbus=modbus), log_level="WARNING") as runtime:
        with Heartbeat(connect_when_listening(modbus.port)):
            load_enable(runtime)
            runtime.command(CommandCode.START)
            runtime.wait_for(lambda s: s.phase is MotionPhase.PROGRAM, 10.0)
            hmi = runtime.process("hmi")
            os.kill(hmi.pid, signal.SIGKILL)
        # Nobody changes the HMI heartbeat any more: the cycle's watchdog holds on the path.
        status = runtime.wait_for(lambda s: s.state is not MachineState.MOVING, 3.0)
        assert status.state is MachineState.HOLDING and status.watchdog is WatchdogState.TRIPPED
        assert status.last_command.origin is CommandOrigin.WATCHDOG
        runtime.wait_for(
            lambda s: runtime.process("hmi").pid != hmi.pid and runtime.process("hmi").is_alive(),
            10.0,
        )
        # The new HMI server answers; its heartbeat re-arms the watchdog and resume goes on.
        with Heartbeat(connect_when_listening(modbus.port)):
            client = connect_when_listening(modbus.port)
            try:
                assert client.core_status().snapshot.state is MachineState.HOLDING
                client.command(CommandCode.RESUME)
                run_to_standby(runtime)
            finally:
                client.close()


class Heartbeat:
    """An HMI client (its own connection: the client is not thread-safe) changing the HMI
    heartbeat every 50 ms from a thread, until the block ends (then the connection closes)."""

    def __init__(self, client: HmiClient) -> None:
        self.client = client
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, daemon=True)

    def _beat(self) -> None:
        while not self._stop.wait(0.05):
            with contextlib.suppress(Exception):  # the server may be killed meanwhile
                self.client.heartbeat()

    def __enter__(self) -> HmiClient:
        self.client.heartbeat()
        self._thread.start()
        return self.client

    def __exit__(self, *exc_info: object) -> None:
        self._stop.set()
        self._thread.join()
        self.client.close()
