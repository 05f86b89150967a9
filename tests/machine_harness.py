"""Run a :class:`runtime.controller.Controller` cycle by cycle, faster than real time.

Before each cycle the harness waits (wall clock) until the planner worker has a setpoint ready,
so a test stepping thousands of cycles in a tight loop never sees an underrun the real 4 ms
cycle would not see. Time seen by the machine advances exactly one period per cycle.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from runtime.commands import Command, CommandCode, CommandResult
from runtime.config import MachineConfig, load_config
from runtime.controller import Controller
from runtime.curves import load_curve_file
from runtime.motion import FeedMode, Setpoint
from runtime.scheduler import CycleTick
from runtime.status import MachineState, StatusSnapshot

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "configs" / "curves" / "paper.yaml"


def sim_config() -> MachineConfig:
    return load_config(ROOT / "configs" / "sim.yaml")


class Harness:
    def __init__(self, controller: Controller) -> None:
        self.controller = controller
        self.period_s = controller.config.cycle.period_s
        self.index = 0
        self.setpoints: list[Setpoint] = []
        """The feed's setpoint of every cycle stepped."""

    def sent_targets(self) -> np.ndarray:
        """(cycles, axes) targets the controller sent since tracing began."""
        return np.array([t.targets_mm for t in self.controller.trace])

    @property
    def status(self) -> StatusSnapshot:
        return self.controller.snapshot()

    def cycle(self, count: int = 1) -> None:
        feed = self.controller.feed
        for _ in range(count):
            deadline = time.monotonic() + 10.0
            while (
                feed.mode in (FeedMode.STARTING, FeedMode.PLANNED)
                and feed.buffered_periods == 0
                and not feed.planning_done
            ):
                if time.monotonic() > deadline:
                    raise TimeoutError("planner worker produced nothing for 10 s")
                time.sleep(0.0005)
            if feed.splice_pending:
                # Give the worker the time real cycles would while it re-plans.
                time.sleep(self.period_s)
            tick = CycleTick(self.index, self.index, self.index * self.period_s, 0.0, 0)
            self.controller.step(tick)
            self.setpoints.append(feed.current)
            self.index += 1

    def until(self, condition: Callable[[StatusSnapshot], bool], max_cycles: int) -> int:
        """Cycle until ``condition`` holds; returns the cycles it took."""
        for n in range(max_cycles):
            if condition(self.status):
                return n
            self.cycle()
        raise AssertionError(f"condition not met in {max_cycles} cycles: {self.status}")

    def submit(self, code: CommandCode, **params: object) -> CommandResult:
        return self.controller.submit(Command(code, **params))

    def command(self, code: CommandCode, **params: object) -> None:
        """Submit and apply at the next cycle; the command must be accepted and done."""
        result = self.submit(code, **params)
        assert result is CommandResult.PENDING, result
        self.cycle()
        assert self.status.last_command_result == CommandResult.DONE, self.status

    def load_paper(self) -> None:
        loaded = self.controller.prepare_curve(load_curve_file(PAPER))
        self.command(CommandCode.LOAD_CURVE, curve=loaded)

    def enable(self) -> None:
        self.command(CommandCode.ENABLE)
        self.until(lambda s: s.state is MachineState.STANDBY, 50)

    def standby_with_curve(self) -> None:
        self.load_paper()
        self.enable()
