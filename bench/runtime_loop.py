"""The runtime's own cyclic loop under load, for bench_cycle.py.

Starts the simulated machine (configs/sim.yaml: master and three simulated drives on the
virtual bus, no Modbus) and runs a long curve back and forth for the requested number of
periods, then reports the cyclic task's lateness. ``planner_busy`` makes the planner worker plan
the whole long curve ahead instead of keeping two seconds buffered, so it computes throughout.
"""

from __future__ import annotations

import time
import uuid
from dataclasses import replace
from pathlib import Path

import numpy as np

from planner.nurbs import NurbsCurve
from runtime.app import start_machine
from runtime.commands import CommandCode
from runtime.config import load_config
from runtime.status import MachineState

ROOT = Path(__file__).resolve().parents[1]


def long_curve(spans: int = 2000, seed: int = 7) -> NurbsCurve:
    """A smooth cubic wandering inside the simulated machine's travel (about 3 m long)."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, spans + 3)
    points = np.column_stack(
        [
            120 + 100 * np.sin(2 * np.pi * 7 * t) + rng.normal(0, 1.0, t.size),
            90 + 80 * np.sin(2 * np.pi * 5 * t + 0.5) + rng.normal(0, 1.0, t.size),
            40 + 30 * np.sin(2 * np.pi * 3 * t) + rng.normal(0, 0.5, t.size),
        ]
    )
    inner = np.linspace(0.0, 1.0, spans + 1)[1:-1]
    knots = np.concatenate([np.zeros(4), inner, np.ones(4)])
    return NurbsCurve.from_arrays(3, points, knots)


def run_runtime_loop(cycles: int, *, planner_busy: bool) -> dict[str, float]:
    """Lateness of the runtime's cycle over ``cycles`` periods while a curve runs (µs).

    An error stop (too many missed periods on a loaded host) is reset and counted, not fatal.
    """
    config = load_config(ROOT / "configs" / "sim.yaml")
    config = replace(
        config,
        can=replace(config.can, channel=f"bench-{uuid.uuid4().hex[:8]}"),
        modbus=replace(config.modbus, enabled=False),
    )
    with start_machine(config) as machine:
        controller = machine.controller
        if planner_busy:
            controller.feed.buffer_high_periods = 10**9
        loaded = controller.prepare_curve(long_curve())
        machine.command(CommandCode.LOAD_CURVE, curve=loaded)
        machine.command(CommandCode.ENABLE)
        machine.wait_for(lambda s: s.state is MachineState.STANDBY, 5.0)
        machine.task.reset_statistics()
        started = time.monotonic()
        duration_s = cycles * config.cycle.period_s
        error_stops = 0
        while time.monotonic() - started < duration_s:
            status = controller.snapshot()
            if status.state is MachineState.STANDBY:
                machine.command(CommandCode.START)
            elif status.state is MachineState.ERROR_STOP and status.feed_mm_s == 0.0:
                # Measure on: count the stop (e.g. too many missed periods) and carry on.
                error_stops += 1
                print(f"    error stop: {status.message}")
                machine.command(CommandCode.RESET)
                machine.wait_for(lambda s: s.state is MachineState.STANDBY, 5.0)
            time.sleep(0.05)
        figures = machine.task.lateness_percentiles()
        stats = machine.task.statistics()
    figures["cycles"] = stats.cycles
    figures["missed_periods"] = stats.missed_periods
    figures["error_stops"] = error_stops
    return figures
