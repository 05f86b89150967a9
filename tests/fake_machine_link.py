"""A small fake machine behind the :class:`runtime.hmi.link.MachineLink` protocol, for HMI tests
and benchmarks.

Like the cycle process, it judges posted commands once per period, in the order posted, against
the state each will run in (:data:`runtime.commands.ALLOWED`), and publishes one snapshot per
period with a :class:`CommandRecord` for every judged command. Its motion is a stand-in: a fixed
approach move, then the program's length at the feed limit times the override, then the next
program if one waits. It stores programs in a real :class:`ProgramStore`.

Threading: a thread of its own steps it every ``period_s`` (``start``/``close``); ``paused()``
holds the steps so that several posted commands are judged in one period; ``step`` may also be
called by hand while it is not running.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

from runtime.commands import (
    OVERRIDE_MAX_PERCENT,
    Command,
    CommandCode,
    CommandOrigin,
    CommandRecord,
    CommandResult,
    check_allowed,
)
from runtime.config import MachineConfig, ModbusConfig, load_config
from runtime.programs import Program, ProgramStore
from runtime.status import (
    AxisStatus,
    Fault,
    FaultKind,
    MachineState,
    MotionPhase,
    ProgramStatus,
    StatusSnapshot,
    WatchdogState,
)

ROOT = Path(__file__).resolve().parents[1]
SIM = load_config(ROOT / "configs" / "sim.yaml")
S = MachineState

#: States a command moves the fake to at once.
_NEXT_STATE = {
    CommandCode.ENABLE: S.STANDBY,
    CommandCode.DISABLE: S.DISABLED,
    CommandCode.HOLD: S.HOLDING,
    CommandCode.RESUME: S.MOVING,
    CommandCode.STOP: S.STOPPING,
    CommandCode.QUICK_STOP: S.STOPPING,
}
#: Records the snapshot keeps (the real cycle's bound may differ).
RECENT = 16


class FakeMachine:
    """A stand-in machine (see the module docstring).

    :param store_dir: the program store's directory.
    :param mailbox_size: commands the mailbox holds before :meth:`post` answers None.
    :param reset_periods: periods a reset takes before the machine leaves ERROR_STOP.
    :param approach_mm: length of every approach move.
    """

    def __init__(
        self,
        store_dir: Path,
        *,
        config: MachineConfig = SIM,
        period_s: float = 0.004,
        mailbox_size: int = 16,
        reset_periods: int = 10,
        approach_mm: float = 5.0,
    ) -> None:
        self.config = config
        self.axis_names = tuple(a.name for a in config.axes)
        self.programs = ProgramStore(store_dir)
        self.period_s = period_s
        self.mailbox_size = mailbox_size
        self.reset_periods = reset_periods
        self.approach_mm = approach_mm
        self.posted: list[Command] = []
        self.activity = 0
        self._mailbox: deque[Command] = deque()
        self._ticket = 0
        self._lock = threading.Lock()
        self._snapshot: StatusSnapshot | None = None
        self._state = _FakeState()
        self._stop = threading.Event()
        self._steps = threading.Lock()
        self._thread: threading.Thread | None = None

    # -- MachineLink --------------------------------------------------------------------------

    def snapshot(self) -> StatusSnapshot | None:
        return self._snapshot

    def post(self, command: Command) -> int | None:
        with self._lock:
            if len(self._mailbox) >= self.mailbox_size:
                return None
            self._ticket += 1
            command = replace(command, ticket=self._ticket)
            self._mailbox.append(command)
            self.posted.append(command)
            return self._ticket

    def note_activity(self) -> None:
        self.activity += 1

    # -- running ------------------------------------------------------------------------------

    def start(self) -> FakeMachine:
        self._thread = threading.Thread(target=self._run, name="fake-machine", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            self.step()

    @contextmanager
    def paused(self) -> Iterator[None]:
        """Hold the periods: commands posted meanwhile are judged together afterwards."""
        with self._steps:
            yield

    def wait_periods(self, count: int = 2) -> None:
        """Block until ``count`` more periods have been published."""
        start = self._state.cycles
        while self._state.cycles < start + count and not self._stop.wait(self.period_s / 4):
            pass

    # -- the machine --------------------------------------------------------------------------

    def step(self) -> None:
        """One period: judge the mailbox in order, move, publish."""
        with self._steps:
            with self._lock:
                commands = list(self._mailbox)
                self._mailbox.clear()
            state = self._state
            for command in commands:
                result = state.judge(command)
                state.record(command.ticket, command.origin, command.seq, command.code, result)
            state.move(self)
            self._snapshot = state.snapshot(self)

    def watchdog_trip(self) -> None:
        """The cycle's HMI link watchdog fires: HOLD with origin WATCHDOG, judged at once."""
        with self._steps:
            state = self._state
            code = CommandCode.HOLD
            result = state.judge(Command(code, origin=CommandOrigin.WATCHDOG))
            self._ticket += 1
            state.record(self._ticket, CommandOrigin.WATCHDOG, 0, code, result)
            state.watchdog = WatchdogState.TRIPPED
            state.message = "hold by watchdog: HMI link silent for 1.0 s"
            self._snapshot = state.snapshot(self)

    def fault(self, kind: FaultKind, text: str, axis: str | None = None) -> None:
        """A fault: the machine stops in ERROR_STOP at once, with ``text`` in its message."""
        with self._steps:
            self._state.fail(Fault(kind, text, axis))
            self._snapshot = self._state.snapshot(self)

    def publish(self, **changes: object) -> None:
        """Set snapshot fields directly (kept until the next period overwrites them)."""
        with self._steps:
            for name, value in changes.items():
                setattr(self._state, name, value)
            self._snapshot = self._state.snapshot(self)


class _FakeState:
    """What the fake machine remembers from period to period."""

    def __init__(self) -> None:
        self.state = S.DISABLED
        self.phase = MotionPhase.IDLE
        self.cycles = 0
        self.override_percent = 100.0
        self.path_s_mm = 0.0
        self.path_length_mm = 0.0
        self.feed_mm_s = 0.0
        self.program: Program | None = None
        self.next_program: Program | None = None
        self.fault: Fault | None = None
        self.later_faults: tuple[Fault, ...] = ()
        self.records: deque[CommandRecord] = deque(maxlen=RECENT)
        self.watchdog = WatchdogState.OFF
        self.message = "disabled"
        self.resetting = 0
        self.statusword = 0x0250

    def record(
        self,
        ticket: int,
        origin: CommandOrigin,
        seq: int,
        code: CommandCode,
        result: CommandResult,
    ) -> None:
        self.records.append(CommandRecord(ticket, origin, seq, code, result))

    def judge(self, command: Command) -> CommandResult:
        code = command.code
        if check_allowed(self.state, code) is not None or (
            code is CommandCode.RESET and self.resetting
        ):
            self.message = f"{code.name.lower()} refused: not allowed in state {self.state.name}"
            return CommandResult.REJECTED_STATE
        if code is CommandCode.START and self.program is None:
            self.message = "start refused: no program loaded"
            return CommandResult.NO_CURVE
        if code is CommandCode.SET_OVERRIDE:
            percent = command.override_percent
            if percent is None or not 0.0 <= percent <= OVERRIDE_MAX_PERCENT:
                return CommandResult.INVALID_PARAMETER
            self.override_percent = percent
        elif code is CommandCode.LOAD_CURVE:
            if self.state in (S.MOVING, S.HOLDING, S.STOPPING):
                self.next_program = command.program
            else:
                self.program = command.program
        elif code is CommandCode.CLEAR_NEXT:
            self.next_program = None
        elif code is CommandCode.START:
            self.state = S.MOVING
            self._approach()
        elif code is CommandCode.RESET:
            self.resetting = 1
        else:
            self.state = _NEXT_STATE.get(code, self.state)
            if code in (CommandCode.HOLD, CommandCode.STOP, CommandCode.QUICK_STOP):
                self.phase = MotionPhase.BRAKING
        self.message = f"{code.name.lower()} by {command.origin.name.lower()}"
        return CommandResult.DONE

    def _approach(self) -> None:
        self.phase = MotionPhase.APPROACH
        self.path_s_mm = 0.0
        self.path_length_mm = 0.0

    def fail(self, fault: Fault) -> None:
        if self.fault is None:
            self.fault = fault
            self.message = f"error stop: {fault.text}"
        else:
            self.later_faults += (fault,)
        self.state = S.ERROR_STOP
        self.phase = MotionPhase.IDLE
        self.feed_mm_s = 0.0

    def move(self, machine: FakeMachine) -> None:
        self.cycles += 1
        if self.resetting:
            self.resetting += 1
            if self.resetting > machine.reset_periods:
                self.resetting = 0
                self.fault, self.later_faults = None, ()
                self.state = S.STANDBY
                self.message = "reset"
            return
        if self.phase is MotionPhase.BRAKING:
            self.phase, self.feed_mm_s = MotionPhase.IDLE, 0.0
            if self.state is S.STOPPING:
                self.state = S.STANDBY
                self.message = "stopped"
            return
        if self.state is not S.MOVING:
            return
        vmax = machine.config.planner.vmax_mm_s
        self.feed_mm_s = vmax * self.override_percent / 100.0
        if self.phase is MotionPhase.APPROACH:
            self.path_length_mm = machine.approach_mm
        elif self.program is not None:
            self.path_length_mm = self.program.length_mm
        self.path_s_mm = min(
            self.path_length_mm, self.path_s_mm + self.feed_mm_s * machine.period_s
        )
        if self.path_s_mm < self.path_length_mm:
            return
        if self.phase is MotionPhase.APPROACH:
            self.phase, self.path_s_mm = MotionPhase.PROGRAM, 0.0
        elif self.next_program is not None:
            self.program, self.next_program = self.next_program, None
            self._approach()
        else:
            self.state, self.phase, self.feed_mm_s = S.STANDBY, MotionPhase.IDLE, 0.0
            self.message = "program done"

    def snapshot(self, machine: FakeMachine) -> StatusSnapshot:
        axes = tuple(
            AxisStatus(
                a.name,
                a.node_id,
                1.5 * i,
                1.5 * i + 0.25,
                4 if self.state else 1,
                0.25,
                statusword=self.statusword,
            )
            for i, a in enumerate(machine.config.axes)
        )
        return StatusSnapshot(
            state=self.state,
            fault=self.fault,
            later_faults=self.later_faults,
            axes=axes,
            phase=self.phase,
            feed_mm_s=self.feed_mm_s,
            path_s_mm=self.path_s_mm,
            path_length_mm=self.path_length_mm,
            in_position=self.state is S.STANDBY,
            program=_status(self.program),
            next_program=_status(self.next_program),
            override_percent=self.override_percent,
            last_command=self.records[-1] if self.records else None,
            recent_commands=tuple(self.records),
            watchdog=self.watchdog,
            heartbeat=self.cycles & 0xFFFF,
            message=self.message,
            stats=replace(StatusSnapshot().stats, cycles=self.cycles),
        )


def _status(program: Program | None) -> ProgramStatus | None:
    if program is None:
        return None
    return ProgramStatus(program.program_id, program.name, program.crc32, program.length_mm)


def hmi_config(**changes: object) -> ModbusConfig:
    """The default ``modbus`` section on a free port, with ``changes``."""
    return replace(ModbusConfig(port=0), **changes)  # type: ignore[arg-type]


def serve_fake(store_dir: str, port: int) -> None:
    """The HMI process's job against a fake machine (a ``multiprocessing`` target)."""
    from runtime.hmi.server import serve_hmi

    serve_hmi(FakeMachine(Path(store_dir)).start(), hmi_config(port=port))
