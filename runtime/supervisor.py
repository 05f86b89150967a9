"""The supervisor: starts the runtime's processes, watches them, restarts them, stops them.

``softmotion run`` is this process. It creates the run directory (shared memory, stored
programs) and starts, as fresh interpreters (multiprocessing ``spawn``):

- the simulated drives, when configured (:mod:`runtime.simulation`);
- the planner (:mod:`runtime.planning.process`);
- the cycle (:mod:`runtime.cycle.process`), which owns the bus and the drives;
- the HMI server (:mod:`runtime.hmi.process`), when Modbus is enabled.

Then it supervises (:meth:`Runtime.supervise`, every :data:`SUPERVISE_PERIOD_S`): it writes out
the cycle's log records, and when a child dies:

- planner: the cycle is told (the planner generation counter), stops on the rows it has and
  enters ErrorStop; the planner is started again at once;
- HMI: started again; meanwhile the HMI link watchdog (run by the cycle) applies;
- simulated drives: reported (like hardware that lost power, they do not come back alone);
- cycle: the runtime ends (:class:`CycleDied`); the drives stop on SYNC and heartbeat loss.

:meth:`Runtime.stop` (SIGTERM, SIGINT, the end of a demo) asks the cycle to stop on the path,
disable the drives and leave the bus, waits for it to exit, then ends the other processes.

Threading: the supervisor's main thread only.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import shutil
import socket
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing.process import BaseProcess
from pathlib import Path

from runtime.commands import Command, CommandCode, CommandOrigin, CommandRecord, CommandResult
from runtime.config import MachineConfig
from runtime.errors import RuntimeFault
from runtime.logs import forward_shared_log
from runtime.programs import ProgramStore
from runtime.shared import SharedState, shared_path
from runtime.status import StatusSnapshot

logger = logging.getLogger(__name__)

#: Run directories are named after this and the supervisor's pid.
RUN_DIR_PREFIX = "softmotion-run-"
#: How often the supervisor looks at its children and the log ring [s].
SUPERVISE_PERIOD_S = 0.02
#: The cycle's first status must come within this time of its start (plus the boot timeout).
START_TIMEOUT_S = 30.0
#: A child restarted more often than this within RESTART_WINDOW_S waits RESTART_BACKOFF_S.
RESTART_BURST = 3
RESTART_WINDOW_S = 10.0
RESTART_BACKOFF_S = 2.0


class CycleDied(RuntimeFault):
    """The cycle process ended without being asked to."""

    def __init__(self, exitcode: int | None) -> None:
        self.exitcode = exitcode
        how = f"signal {-exitcode}" if exitcode is not None and exitcode < 0 else f"exit {exitcode}"
        super().__init__(f"cycle process died ({how}); the drives stop on SYNC and heartbeat loss")


class CommandRefused(RuntimeFault):
    """A command the cycle judged and refused (or that it did not judge in time)."""

    def __init__(self, code: CommandCode, result: CommandResult | None, message: str) -> None:
        self.code = code
        self.result = result
        what = "not judged in time" if result is None else f"refused: {result.name}"
        super().__init__(f"{code.name.lower()} {what} ({message})")


@dataclass
class _Child:
    name: str
    start: Callable[[], BaseProcess]
    restart: bool
    process: BaseProcess | None = None
    starts: list[float] = field(default_factory=list)
    gone: bool = False


class Runtime:
    """The running machine, seen from the supervisor; a context manager that stops it.

    :param config: the machine.
    :param log_level: for every process.
    :param serve_hmi: start the HMI process (when ``config.modbus.enabled``).
    """

    def __init__(self, config: MachineConfig, *, log_level: str = "INFO", serve_hmi: bool = True):
        self.config = config
        self.log_level = log_level
        self.serve_hmi = serve_hmi and config.modbus.enabled
        self.axis_names = tuple(axis.name for axis in config.axes)
        base = _run_base()
        _remove_stale_run_dirs(base)
        self.run_dir = Path(tempfile.mkdtemp(prefix=f"{RUN_DIR_PREFIX}{os.getpid()}-", dir=base))
        self.shared = SharedState.create(shared_path(self.run_dir), self.axis_names)
        self.programs = ProgramStore(self.run_dir / "programs")
        self._context = multiprocessing.get_context("spawn")
        self._children: dict[str, _Child] = {}
        self._stopping = False

    # -- lifecycle ---------------------------------------------------------------------------

    def start(self) -> Runtime:
        """Start every process; returns once the cycle publishes its status.

        :raises CycleDied: if the cycle process ends during start-up.
        :raises TimeoutError: if it publishes nothing within the start timeout.
        """
        from runtime.cycle.process import cycle_main
        from runtime.planning.process import planner_main

        if self.serve_hmi:
            _check_port(self.config.modbus.bind, self.config.modbus.port)
        run_dir, level, me = str(self.run_dir), self.log_level, os.getpid()
        if self.config.simulation.drives:
            from runtime.simulation import simulation_main

            self._add("simulated-drives", simulation_main, (self.config, level, me), restart=False)
        self._add("planner", planner_main, (self.config, run_dir, level, me), restart=True)
        self._add("cycle", cycle_main, (self.config, run_dir, level, me), restart=False)
        if self.serve_hmi:
            from runtime.hmi.process import hmi_main

            self._add("hmi", hmi_main, (self.config, run_dir, level, me), restart=True)
        self.wait_for(lambda status: True, START_TIMEOUT_S + 2 * self.config.can.boot_timeout_s)
        return self

    def __enter__(self) -> Runtime:
        return self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.stop()

    def _add(self, name: str, target: Callable[..., None], args: tuple, *, restart: bool) -> None:
        def start() -> BaseProcess:
            if name == "planner":
                self.shared.planner_generation.value += 1
            process = self._context.Process(target=target, args=args, name=name)
            process.start()
            return process

        child = _Child(name, start, restart)
        self._children[name] = child
        self._launch(child)

    def _launch(self, child: _Child) -> None:
        now = time.monotonic()
        child.starts = [t for t in child.starts if now - t < RESTART_WINDOW_S] + [now]
        child.process = child.start()

    def stop(self, timeout_s: float = 15.0) -> int | None:
        """Stop the machine and every process; returns the cycle's exit status."""
        if self._stopping:
            return None
        self._stopping = True
        cycle = self._children.get("cycle")
        exitcode = None
        if cycle is not None and cycle.process is not None and cycle.process.is_alive():
            self.shared.local_mailbox.post(
                Command(CommandCode.SHUTDOWN, origin=CommandOrigin.SHUTDOWN)
            )
            deadline = time.monotonic() + timeout_s
            while cycle.process.is_alive() and time.monotonic() < deadline:
                forward_shared_log(self.shared.log)
                cycle.process.join(SUPERVISE_PERIOD_S)
            if cycle.process.is_alive():
                logger.error("cycle did not end within %g s of the shutdown; killing it", timeout_s)
                cycle.process.kill()
                cycle.process.join(2.0)
            exitcode = cycle.process.exitcode
        forward_shared_log(self.shared.log)
        for child in self._children.values():
            process = child.process
            if process is not None and process.is_alive():
                process.terminate()
        for child in self._children.values():
            if child.process is not None:
                child.process.join(5.0)
                if child.process.is_alive():
                    child.process.kill()
                    child.process.join(2.0)
        self.shared.close()
        shutil.rmtree(self.run_dir, ignore_errors=True)
        return exitcode

    # -- supervision -------------------------------------------------------------------------

    def supervise(self) -> None:
        """One pass: write out the cycle's log records, handle children that died.

        :raises CycleDied: if the cycle process ended.
        """
        forward_shared_log(self.shared.log)
        if self._stopping:
            return
        for child in self._children.values():
            process = child.process
            if process is None or process.is_alive() or child.gone:
                continue
            code = process.exitcode
            if child.name == "cycle":
                child.gone = True
                raise CycleDied(code)
            if not child.restart:
                child.gone = True
                logger.error("%s process ended (exit %s)", child.name, code)
                continue
            if len(child.starts) >= RESTART_BURST and time.monotonic() - child.starts[-1] < (
                RESTART_BACKOFF_S
            ):
                continue
            logger.error("%s process ended (exit %s); starting it again", child.name, code)
            self._launch(child)

    def process(self, name: str) -> BaseProcess | None:
        """A child process by role name (simulated-drives, planner, cycle, hmi)."""
        child = self._children.get(name)
        return None if child is None else child.process

    # -- the machine -------------------------------------------------------------------------

    def status(self) -> StatusSnapshot | None:
        """The cycle's last published status; None only before its first."""
        return self.shared.status.snapshot()

    def wait_for(
        self, condition: Callable[[StatusSnapshot], bool], timeout_s: float
    ) -> StatusSnapshot:
        """Supervise until the status satisfies ``condition``.

        :raises TimeoutError: naming the state it was left in.
        :raises CycleDied: if the cycle process ends meanwhile.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            self.supervise()
            status = self.status()
            if status is not None and condition(status):
                return status
            if time.monotonic() > deadline:
                shown = (
                    "no status yet" if status is None else f"{status.state.name}: {status.message}"
                )
                raise TimeoutError(f"machine not as expected after {timeout_s:g} s ({shown})")
            time.sleep(SUPERVISE_PERIOD_S)

    def post(self, command: Command) -> int:
        """Queue ``command`` in the supervisor's mailbox; returns its ticket.

        :raises RuntimeFault: if the mailbox is full.
        """
        ticket = self.shared.local_mailbox.post(command)
        if ticket is None:
            raise RuntimeFault("the cycle's mailbox is full")
        return ticket

    def command(self, code: CommandCode, timeout_s: float = 5.0, **params: object) -> CommandRecord:
        """Post a command and wait for the cycle's judgement of it.

        :raises CommandRefused: if it was refused (or not judged within ``timeout_s``).
        """
        ticket = self.post(Command(code, origin=CommandOrigin.COMMAND_LINE, **params))
        try:
            status = self.wait_for(lambda s: _record(s, ticket) is not None, timeout_s)
        except TimeoutError:
            status = self.status()
            raise CommandRefused(code, None, status.message if status else "no status") from None
        record = _record(status, ticket)
        assert record is not None
        if record.result is not CommandResult.DONE:
            raise CommandRefused(code, record.result, status.message)
        return record


def _record(status: StatusSnapshot, ticket: int) -> CommandRecord | None:
    for record in status.recent_commands:
        if record.ticket == ticket and record.origin is CommandOrigin.COMMAND_LINE:
            return record
    return None


def _check_port(bind: str, port: int) -> None:
    """Fail early, with the address, when the HMI process could not listen on it.

    :raises RuntimeFault: naming the address and the reason.
    """
    family = socket.AF_INET6 if ":" in bind else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((bind, port))
        except OSError as exc:
            raise RuntimeFault(f"modbus: cannot listen on {bind}:{port}: {exc.strerror}") from None


def _remove_stale_run_dirs(base: str | None) -> None:
    """Remove the run directories of supervisors that are gone (killed without a shutdown)."""
    for entry in Path(base or tempfile.gettempdir()).glob(f"{RUN_DIR_PREFIX}*-*"):
        pid = entry.name[len(RUN_DIR_PREFIX) :].split("-", 1)[0]
        if pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(entry, ignore_errors=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # another user's process: alive all the same
    return True


def _run_base() -> str | None:
    """Where run directories go: memory-backed /dev/shm when there is one."""
    with contextlib.suppress(OSError):
        if os.access("/dev/shm", os.W_OK):
            return "/dev/shm"
    return None
