"""``softmotion run``: start the machine's processes, serve until a signal, shut down cleanly.

The supervisor (:class:`runtime.supervisor.Runtime`) starts the simulated drives (when
configured), the planner, the cycle and the HMI server. ``--curve`` loads a program at start;
``--demo`` (the README's first command) loads the paper's curve, enables, runs it to its end on
the simulated machine and prints a summary. SIGINT or SIGTERM stops the machine on the path,
disables the drives, leaves the bus cleanly and exits 0.

A drive that is missing or faulted does not stop the runtime: it stays up in ErrorStop naming the
node and the cause (reset brings it to Standby once the drive is healthy). ``--demo`` and
``--curve`` report such a start as a message and exit status 1, never a traceback.
"""

from __future__ import annotations

import logging
import signal
import sys
import threading
import time
from pathlib import Path as FilePath
from typing import TextIO

from planner.errors import PlannerError
from runtime.commands import CommandCode
from runtime.config import DEMO_CURVE_PATH, MachineConfig
from runtime.curves import load_curve_file
from runtime.errors import RuntimeFault
from runtime.programs import Program
from runtime.status import MachineState, MotionPhase, StatusSnapshot
from runtime.supervisor import CommandRefused, Runtime

logger = logging.getLogger(__name__)

EXIT_OK = 0
EXIT_FAILURE = 1
#: How long the demo waits for the drives to be enabled (boot included).
ENABLE_TIMEOUT_S = 30.0
#: Longest demo motion before it gives up [s].
DEMO_MOTION_TIMEOUT_S = 120.0


def run_machine(
    config: MachineConfig,
    *,
    demo: bool = False,
    curve_path: FilePath | None = None,
    log_level: str = "INFO",
    out: TextIO | None = None,
) -> int:
    """The body of ``softmotion run``; returns the exit status."""
    out = out or sys.stdout
    stop_requested = threading.Event()
    previous = {
        sig: signal.signal(sig, lambda signum, frame: stop_requested.set())
        for sig in (signal.SIGINT, signal.SIGTERM)
    }
    runtime = Runtime(config, log_level=log_level)
    try:
        runtime.start()
        logger.info(
            "machine running: %d axes on %s/%s, Modbus TCP %s",
            len(config.axes),
            config.can.interface,
            config.can.channel,
            f"{config.modbus.bind}:{config.modbus.port}" if config.modbus.enabled else "off",
        )
        if demo or curve_path is not None:
            path = curve_path or DEMO_CURVE_PATH
            program = runtime.programs.add(
                load_curve_file(path), config, name=FilePath(path).name, crc32=0
            )
            runtime.command(CommandCode.LOAD_CURVE, program=program)
            if demo:
                return _demo(runtime, program, stop_requested, out)
        while not stop_requested.is_set():
            runtime.supervise()
            time.sleep(0.05)
        logger.info("shutting down")
        return EXIT_OK
    except (PlannerError, RuntimeFault, TimeoutError) as exc:
        # A bad curve, a drive that never comes, a dead cycle: say what, no traceback.
        print(f"softmotion: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    finally:
        exitcode = runtime.stop()
        if exitcode not in (0, None):
            print(f"softmotion: cycle process exit status {exitcode}", file=sys.stderr)
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _demo(runtime: Runtime, program: Program, stop_requested: threading.Event, out: TextIO) -> int:
    try:
        runtime.command(CommandCode.ENABLE)
        runtime.wait_for(
            lambda s: s.state in (MachineState.STANDBY, MachineState.ERROR_STOP), ENABLE_TIMEOUT_S
        )
    except CommandRefused:
        # Refused in ERROR_STOP: a drive faulted before the enable was judged (one in FAULT at
        # power-on, on a slow host); the cause, below, says more than the refusal.
        status = runtime.status()
        if status is None or status.state is not MachineState.ERROR_STOP:
            raise
    except TimeoutError as exc:
        raise RuntimeFault(f"drives not enabled: {exc}") from None
    status = runtime.status()
    assert status is not None
    if status.state is MachineState.ERROR_STOP:
        # The fault, not the message: a command judged since (the curve's load) replaces that.
        cause = f"error stop: {status.fault.text}" if status.fault else status.message
        raise RuntimeFault(f"drives not enabled: {cause}")
    started = time.monotonic()
    runtime.command(CommandCode.START)
    print("demo: running the paper's curve", file=out, flush=True)
    last_print = 0.0
    while True:
        runtime.supervise()
        status = runtime.status()
        assert status is not None
        if status.state is not MachineState.MOVING:
            break
        if stop_requested.is_set():
            print("demo: interrupted", file=out)
            return EXIT_OK
        if time.monotonic() - started > DEMO_MOTION_TIMEOUT_S:
            raise RuntimeFault(f"demo: still moving after {DEMO_MOTION_TIMEOUT_S:g} s")
        if time.monotonic() - last_print >= 0.5:
            last_print = time.monotonic()
            phase = "approach" if status.phase is MotionPhase.APPROACH else "curve"
            print(
                f"  {phase:8s} {status.progress_permille / 10:5.1f} %  "
                f"feed {status.feed_mm_s:6.1f} mm/s  "
                + "  ".join(f"{a.name} {a.commanded_mm:8.3f}" for a in status.axes),
                file=out,
                flush=True,
            )
        time.sleep(0.02)
    motion_s = time.monotonic() - started
    # Let the drives settle on the last setpoint before reading their positions.
    time.sleep(0.1)
    runtime.supervise()
    final = runtime.status()
    assert final is not None
    return _summary(runtime, program, final, motion_s, out)


def _summary(
    runtime: Runtime, program: Program, status: StatusSnapshot, motion_s: float, out: TextIO
) -> int:
    ok = status.state is MachineState.STANDBY and status.program is not None
    stats = status.stats
    print("demo summary", file=out)
    print(f"  result              {'curve finished' if ok else status.message}", file=out)
    print(f"  motion time         {motion_s:.3f} s (wall clock, approach included)", file=out)
    for axis in status.axes:
        print(
            f"  max following error {axis.name}: {axis.peak_following_error_mm * 1000:.1f} um",
            file=out,
        )
    end = program.end_mm
    for i, axis in enumerate(status.axes[: len(end)]):
        scale = runtime.config.axes[i].counts_per_mm
        off = round((axis.actual_mm - end[i]) * scale)
        print(
            f"  final {axis.name}: {axis.actual_mm:.4f} mm (curve end {end[i]:.4f}, "
            f"{off:+d} counts)",
            file=out,
        )
    print(
        f"  cycle lateness      p50 {stats.lateness_p50_us:.0f} us, p99 "
        f"{stats.lateness_p99_us:.0f} us, max {stats.lateness_max_us:.0f} us",
        file=out,
    )
    print(f"  missed periods      {stats.missed_periods} of {stats.cycles} periods", file=out)
    return EXIT_OK if ok else EXIT_FAILURE


__all__ = ["CommandRefused", "run_machine"]
