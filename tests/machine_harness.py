"""The cycle and the planner service in one process, stepped period by period.

Before each period the planner service works until it has nothing left to do, so a test
stepping thousands of periods never sees the planner fall behind unless it asks for that
(``plan=False``). Time seen by the cycle advances exactly one period per step. The shared
memory is a private buffer; the drives are :class:`tests.fake_drives.FakeDrives` unless given.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from fake_drives import FakeDrives

from runtime.commands import Command, CommandCode, CommandOrigin, CommandRecord, CommandResult
from runtime.config import MachineConfig, load_config
from runtime.curves import load_curve_file
from runtime.cycle.cycle import Cycle
from runtime.cycle.feed import Setpoint
from runtime.planning.service import PlannerService
from runtime.programs import Program, ProgramStore
from runtime.shared import SharedState
from runtime.status import MachineState, StatusSnapshot

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "configs" / "curves" / "paper.yaml"
#: Polls of the planner service per period at most (it idles long before).
PLANNER_POLLS = 10_000


def sim_config() -> MachineConfig:
    return load_config(ROOT / "configs" / "sim.yaml")


class Harness:
    """A machine without processes: cycle, planner service, fake drives, private memory."""

    def __init__(
        self, store_dir: Path, config: MachineConfig | None = None, drives: object | None = None
    ) -> None:
        self.config = config or sim_config()
        names = tuple(axis.name for axis in self.config.axes)
        self.shared = SharedState.in_memory(names)
        self.drives = drives or FakeDrives(names)
        self.planner = PlannerService(self.shared, self.config)
        self.period_s = self.config.cycle.period_s
        self.now_s = 0.0
        self.cycle = Cycle(self.config, self.shared, self.drives, clock=lambda: self.now_s)
        self.cycle.start()
        self.programs = ProgramStore(store_dir)
        self.targets: list[tuple[float, ...]] = []
        """The targets the machine gave the drives, one row per period stepped."""
        self.setpoints: list[Setpoint] = []
        """The feed's setpoint of every period stepped."""

    @property
    def status(self) -> StatusSnapshot:
        snapshot = self.shared.status.snapshot()
        assert snapshot is not None
        return snapshot

    @property
    def machine(self):
        return self.cycle.machine

    def period(self, count: int = 1, *, plan: bool = True) -> None:
        for _ in range(count):
            if plan:
                self.plan()
            self.cycle.step()
            self.targets.append(self.cycle.machine.targets)
            self.setpoints.append(self.cycle.feed.current)
            self.now_s += self.period_s

    def plan(self) -> None:
        """Let the planner service work until it idles."""
        for _ in range(PLANNER_POLLS):
            if not self.planner.poll():
                return

    def until(self, condition: Callable[[StatusSnapshot], bool], max_periods: int) -> int:
        """Step until ``condition`` holds; returns the periods it took."""
        for n in range(max_periods):
            self.period()
            if condition(self.status):
                return n + 1
        raise AssertionError(f"condition not met in {max_periods} periods: {self.status}")

    def post(self, code: CommandCode, **params: object) -> int:
        ticket = self.shared.local_mailbox.post(
            Command(code, origin=params.pop("origin", CommandOrigin.COMMAND_LINE), **params)
        )
        assert ticket is not None
        return ticket

    def record_of(self, ticket: int) -> CommandRecord:
        for record in self.status.recent_commands:
            if record.ticket == ticket and record.origin is not CommandOrigin.HMI:
                return record
        raise AssertionError(f"no record of ticket {ticket}: {self.status.recent_commands}")

    def command(self, code: CommandCode, **params: object) -> CommandResult:
        """Post and step one period; returns the command's result."""
        ticket = self.post(code, **params)
        self.period()
        return self.record_of(ticket).result

    def program(self, path: Path = PAPER, name: str = "paper") -> Program:
        return self.programs.add(load_curve_file(path), self.config, name=name, crc32=0)

    def load(self, path: Path = PAPER) -> Program:
        program = self.program(path)
        assert self.command(CommandCode.LOAD_CURVE, program=program) is CommandResult.DONE
        return program

    def enable(self) -> None:
        assert self.command(CommandCode.ENABLE) is CommandResult.DONE
        self.until(lambda s: s.state is MachineState.STANDBY, 50)

    def standby_with_program(self) -> Program:
        program = self.load()
        self.enable()
        return program

    def run_to_standby(self, max_periods: int = 5000) -> int:
        return self.until(lambda s: s.state is not MachineState.MOVING, max_periods)

    def target_array(self) -> np.ndarray:
        return np.array(self.targets)
