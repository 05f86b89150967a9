"""``softmotion run``: start the machine, serve until a signal, shut down cleanly.

Start-up order: CAN bus and CANopen network, simulated drives (when the configuration asks for
them), the CiA-402 master (boot, SDO configuration, NMT start), the controller and its cyclic
task, then the Modbus TCP server. Shutdown reverses it: a moving machine is stopped on the path,
the drives are disabled and put out of OPERATIONAL, then every thread ends.

``--demo`` (the README's first command) loads a curve, enables, runs it to the end on the
simulated machine and prints a summary.
"""

from __future__ import annotations

import gc
import logging
import signal
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path as FilePath
from typing import TextIO

import canopen

from drives.bus import open_bus
from drives.errors import DriveError
from drives.master import AxisSpec, Cia402Master, MasterSettings
from drives.scaling import AxisScaling
from planner.braking import BrakingProfile
from planner.errors import PlannerError
from planner.nurbs import NurbsCurve
from planner.stream import Path, stream_setpoints
from runtime.commands import Command, CommandCode, CommandResult
from runtime.config import DEMO_CURVE_PATH, MachineConfig
from runtime.controller import Controller
from runtime.curves import limits_for_curve, load_curve_file, planner_limits
from runtime.errors import RuntimeFault
from runtime.priorities import prioritise_threads, restore_main_thread
from runtime.scheduler import CyclicTask
from runtime.status import MachineState, StatusSnapshot

logger = logging.getLogger(__name__)

#: SYNC-loss limit of in-process simulated drives, in periods beyond the longest SYNC gap the
#: cycle's overrun limit tolerates. Real drives use 1.5 to 2 periods; drives simulated in this
#: process share its interpreter lock with the planner worker, so their SYNC callbacks can lag
#: behind a SYNC that went out on time, and the master's own overrun limit is the one that
#: should decide whether a late cycle stops the machine.
SIMULATED_SYNC_MARGIN_PERIODS = 1
_IN_MOTION = (MachineState.MOVING, MachineState.HOLDING, MachineState.STOPPING)
EXIT_OK = 0
EXIT_FAILURE = 1


def simulated_sync_timeout_periods(config: MachineConfig) -> float:
    """SYNC-loss limit of in-process simulated drives, periods: a run of ``overrun_limit``
    missed periods leaves a SYNC gap of ``overrun_limit + 1`` periods, which they tolerate."""
    return float(config.cycle.overrun_limit + 1 + SIMULATED_SYNC_MARGIN_PERIODS)


def master_settings(config: MachineConfig) -> MasterSettings:
    """The CiA-402 master's settings from the machine description."""
    can = config.can
    return MasterSettings(
        period_s=config.cycle.period_s,
        heartbeat_ms=can.heartbeat_ms,
        master_node_id=can.master_node_id,
        master_heartbeat_ms=can.master_heartbeat_ms,
        heartbeat_loss_periods=can.heartbeat_loss_periods,
        boot_timeout_s=can.boot_timeout_s,
        sdo_timeout_s=can.sdo_timeout_s,
        stale_feedback_cycles=can.stale_feedback_cycles,
        sync_window_us=can.sync_window_us,
    )


def axis_specs(config: MachineConfig) -> tuple[AxisSpec, ...]:
    """The master's view of each configured axis."""
    return tuple(
        AxisSpec(
            name=axis.name,
            node_id=axis.node_id,
            scaling=AxisScaling(
                counts_per_mm=axis.counts_per_mm,
                direction=axis.direction,
                travel_min_mm=axis.travel_min_mm,
                travel_max_mm=axis.travel_max_mm,
            ),
            following_error_window_mm=axis.following_error_window_mm,
            following_error_timeout_ms=axis.following_error_timeout_ms,
            eds=axis.eds,
        )
        for axis in config.axes
    )


@dataclass
class RunningMachine:
    """Everything ``softmotion run`` started, for the demo, the tests and the shutdown."""

    config: MachineConfig
    controller: Controller
    master: Cia402Master
    task: CyclicTask
    hmi: object | None = None
    simulated: object | None = None
    """The in-process simulated drives (``drives.sim.drive.SimulatedDriveSet``), if any."""
    _stack: ExitStack = field(default_factory=ExitStack)

    def wait_for(
        self, condition: Callable[[StatusSnapshot], bool], timeout_s: float
    ) -> StatusSnapshot:
        """Poll the status until ``condition`` holds.

        :raises TimeoutError: naming the state it was left in.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            status = self.controller.snapshot()
            if condition(status):
                return status
            if time.monotonic() > deadline:
                raise TimeoutError(
                    f"machine still {status.state.name} after {timeout_s:g} s ({status.message})"
                )
            time.sleep(0.01)

    def command(self, code: CommandCode, **params: object) -> None:
        """Submit a command and wait until the cycle has applied it.

        :raises RuntimeError: if it is refused.
        """
        seq = self.controller.snapshot().last_command_seq + 1
        result = self.controller.submit(Command(code, seq=seq, origin="command line", **params))
        if result is not CommandResult.PENDING:
            raise RuntimeError(f"{code.name.lower()} refused: {result.name}")
        status = self.wait_for(lambda s: s.last_command_seq >= seq, 2.0)
        if status.last_command_result != CommandResult.DONE:
            raise RuntimeError(
                f"{code.name.lower()} failed: {CommandResult(status.last_command_result).name}"
            )

    def stop(self) -> None:
        """Controlled shutdown: stop on the path, disable the drives, end every thread."""
        try:
            state = self.controller.snapshot().state
            if state in (MachineState.MOVING, MachineState.HOLDING):
                self.controller.submit(Command(CommandCode.STOP, origin="shutdown"))
                self.wait_for(lambda s: s.state not in _IN_MOTION, 5.0)
            if self.controller.snapshot().state is not MachineState.DISABLED:
                self.controller.submit(Command(CommandCode.DISABLE, origin="shutdown"))
                self.wait_for(lambda s: s.state is MachineState.DISABLED, 1.0)
        except TimeoutError as exc:
            logger.warning("shutdown: %s", exc)
        finally:
            self._stack.close()


def warm_up_motion(controller: Controller) -> None:
    """Plan, brake and interpolate a short line once, before the cycle starts.

    The first use of each planner code path imports modules and warms numpy's caches, tens of
    milliseconds under the interpreter lock: done here, no cycle waits for it at the first start.
    """
    dimension = min(3, len(controller.config.axes))
    limits = limits_for_curve(planner_limits(controller.config), dimension)
    line = NurbsCurve.from_arrays(1, [[0.0] * dimension, [1.0] * dimension], [0, 0, 1, 1])
    feed = controller.feed
    path = Path(line, limits, feed.period_s)
    for _ in stream_setpoints(
        path,
        limits,
        feed.period_s,
        lookahead=feed.lookahead,
        update=feed.update,
    ):
        pass
    BrakingProfile.from_state(
        v0_mm_s=limits.vmax_mm_s,
        a0_mm_s2=0.0,
        amax_mm_s2=limits.amax_mm_s2,
        jmax_mm_s3=limits.jmax_mm_s3,
    ).sample(0.0)
    path.curve.point(float(path.arc.u_of_s(0.5)[0]))


@contextmanager
def start_machine(config: MachineConfig, *, serve_hmi: bool = True) -> Iterator[RunningMachine]:
    """Start the whole machine; yields it running and shuts it down on exit.

    :raises DriveError: if a drive does not boot or does not accept its configuration.
    """
    stack = ExitStack()
    with stack:
        network = canopen.Network(
            open_bus(config.can.interface, config.can.channel, config.can.bitrate)
        )
        network.connect()
        stack.callback(network.disconnect)
        simulated = None
        if config.simulation.drives:
            from drives.sim.drive import start_simulated_drives
            from drives.sim.dynamics import DriveModel

            simulated = start_simulated_drives(
                config.can.interface,
                config.can.channel,
                [axis.node_id for axis in config.axes],
                model=DriveModel(sync_timeout_factor=simulated_sync_timeout_periods(config)),
                bitrate=config.can.bitrate,
            )
            stack.callback(simulated.close)
        master = Cia402Master(network, axis_specs(config), master_settings(config))
        master.boot()
        stack.callback(master.shutdown)
        task_holder: list[CyclicTask] = []
        controller = Controller(
            config,
            master,
            statistics=lambda: task_holder[0].statistics_fast(),
            set_moving=lambda moving: task_holder[0].set_moving(moving),
        )
        stack.callback(controller.close)
        task = CyclicTask(
            config.cycle.period_s,
            controller.step,
            realtime=config.cycle.realtime,
            overrun_limit=config.cycle.overrun_limit,
            on_overrun_limit=controller.on_overrun_limit,
        )
        task_holder.append(task)
        running = RunningMachine(config, controller, master, task, simulated=simulated)
        if serve_hmi and config.modbus.enabled:
            from runtime.hmi.server import HmiServer

            # Serve before the cycle starts: the server's start-up must not cost cycle periods.
            hmi = HmiServer(config.modbus, controller)
            hmi.start()
            stack.callback(hmi.stop)
            running.hmi = hmi
        # The main thread too: a thread of this process preempted while it holds the
        # interpreter lock keeps the cyclic thread waiting (it only waits and reports).
        if prioritise_threads(config.cycle.realtime.priority, include_main=True):
            stack.callback(restore_main_thread)
        warm_up_motion(controller)
        if config.cycle.realtime.gc != "normal":
            # Everything alive after start-up goes to the permanent generation: no later full
            # collection (in whichever thread allocates, the cyclic one included) scans it.
            gc.collect()
            gc.freeze()
        task.start()
        stack.callback(task.stop)
        running._stack = stack.pop_all()
        try:
            yield running
        finally:
            running.stop()


def run_machine(
    config: MachineConfig,
    *,
    demo: bool = False,
    curve_path: FilePath | None = None,
    out: TextIO | None = None,
) -> int:
    """The body of ``softmotion run``; returns the exit status."""
    import sys

    out = out or sys.stdout
    stop_requested = threading.Event()
    previous = {
        sig: signal.signal(sig, lambda signum, frame: stop_requested.set())
        for sig in (signal.SIGINT, signal.SIGTERM)
    }
    try:
        with start_machine(config) as machine:
            logger.info(
                "machine running: %d axes on %s/%s, Modbus TCP %s",
                len(config.axes),
                config.can.interface,
                config.can.channel,
                f"{config.modbus.bind}:{config.modbus.port}" if config.modbus.enabled else "off",
            )
            if demo or curve_path is not None:
                machine.command(
                    CommandCode.LOAD_CURVE,
                    curve=machine.controller.prepare_curve(
                        load_curve_file(curve_path or DEMO_CURVE_PATH),
                        name=str(curve_path or DEMO_CURVE_PATH),
                    ),
                )
            if demo:
                return _demo(machine, stop_requested, out)
            _log_state_changes(machine, stop_requested)
            logger.info("shutting down")
        return EXIT_OK
    except (DriveError, PlannerError, RuntimeFault) as exc:
        # A drive that does not boot, a bad curve, a port in use: say what, no traceback.
        print(f"softmotion: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _log_state_changes(machine: RunningMachine, stop_requested: threading.Event) -> None:
    last = (None, None)
    while not stop_requested.wait(0.05):
        status = machine.controller.snapshot()
        now = (status.state, status.fault)
        if now != last and status.fault is not None and status.fault != last[1]:
            logger.error("fault: %s", status.fault.text)
        last = now


def _demo(machine: RunningMachine, stop_requested: threading.Event, out: TextIO) -> int:
    controller = machine.controller
    machine.command(CommandCode.ENABLE)
    machine.wait_for(lambda s: s.state is MachineState.STANDBY, 5.0)
    controller.max_following_error_mm = [0.0] * len(machine.config.axes)
    machine.task.reset_statistics()
    started = time.monotonic()
    machine.command(CommandCode.START)
    print("demo: running the paper's curve", file=out, flush=True)
    last_print = 0.0
    while True:
        status = controller.snapshot()
        if status.state is not MachineState.MOVING:
            break
        if stop_requested.is_set():
            print("demo: interrupted", file=out)
            return EXIT_OK
        if time.monotonic() - last_print >= 0.5:
            last_print = time.monotonic()
            print(
                f"  {status.progress_permille / 10:5.1f} %  feed {status.feed_mm_s:6.1f} mm/s  "
                + "  ".join(f"{a.name} {a.commanded_mm:8.3f}" for a in status.axes),
                file=out,
                flush=True,
            )
        time.sleep(0.02)
    motion_s = time.monotonic() - started
    # Let the drives settle on the last setpoint before reading their positions.
    time.sleep(0.1)
    status = controller.snapshot()
    return _summary(machine, status, motion_s, out)


def _summary(machine: RunningMachine, status: StatusSnapshot, motion_s: float, out: TextIO) -> int:
    loaded = machine.controller.machine.loaded
    ok = status.state is MachineState.STANDBY and loaded is not None
    stats = machine.task.statistics()
    percentiles = machine.task.lateness_percentiles()
    print("demo summary", file=out)
    print(f"  result              {'curve finished' if ok else status.message}", file=out)
    print(f"  motion time         {motion_s:.3f} s (wall clock, approach included)", file=out)
    for axis, error in zip(status.axes, machine.controller.max_following_error_mm, strict=True):
        print(f"  max following error {axis.name}: {error * 1000:.1f} um", file=out)
    if loaded is not None:
        end = loaded.curve.end_point
        for i, axis in enumerate(status.axes[: len(end)]):
            scale = machine.config.axes[i].counts_per_mm
            off = round((axis.actual_mm - float(end[i])) * scale)
            print(
                f"  final {axis.name}: {axis.actual_mm:.4f} mm (curve end {float(end[i]):.4f}, "
                f"{off:+d} counts)",
                file=out,
            )
    print(
        f"  cycle lateness      p50 {percentiles['p50']:.0f} us, p99 {percentiles['p99']:.0f} us, "
        f"max {percentiles['max']:.0f} us",
        file=out,
    )
    print(f"  missed periods      {stats.missed_periods} of {stats.cycles} cycles", file=out)
    return EXIT_OK if ok else EXIT_FAILURE
