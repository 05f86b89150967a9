"""The cycle process: one thread, SCHED_FIFO, locked memory; the bus, the drives, the machine.

Started by the supervisor (:func:`cycle_main`). It attaches the shared memory, opens the CAN bus
(it alone owns it), builds the CiA-402 master and :class:`runtime.cycle.cycle.Cycle`, and runs
the period loop (:class:`runtime.scheduler.CyclicTask`) in its only thread until the cycle's
shutdown is done (a SHUTDOWN command from the supervisor, or SIGTERM: the supervisor is gone).
Log records go to the shared log ring (the supervisor writes them out).

Exit status: 0 after a clean shutdown, 1 when the loop stopped on an error.
"""

from __future__ import annotations

import gc
import logging
import signal
import sys

from drives.errors import DriveError
from planner.braking import BrakingProfile
from runtime.config import MachineConfig
from runtime.cycle.cycle import Cycle
from runtime.drives_setup import build_master, open_master_bus
from runtime.logs import SharedLogHandler, quiet_libraries
from runtime.processes import prepare_child
from runtime.scheduler import CyclicTask
from runtime.shared import SharedState, shared_path

logger = logging.getLogger(__name__)


def cycle_main(config: MachineConfig, run_dir: str, log_level: str, parent_pid: int) -> None:
    """The cycle process's entry point (never returns: exits with its status)."""
    prepare_child(parent_pid=parent_pid)
    names = tuple(axis.name for axis in config.axes)
    shared = SharedState.attach(shared_path(run_dir), names)
    root = logging.getLogger()
    root.handlers[:] = [SharedLogHandler(shared.log)]
    root.setLevel(log_level)
    quiet_libraries(log_level)
    try:
        bus = open_master_bus(config)
    except DriveError as exc:
        logger.error("%s", exc)
        sys.exit(1)
    drives = build_master(config, bus)
    task = CyclicTask(
        config.cycle.period_s,
        lambda tick: cycle.step(tick),
        realtime=config.cycle.realtime,
        overrun_limit=config.cycle.overrun_limit,
        on_overrun_limit=lambda run: cycle.on_overrun_limit(run),
        name="cycle",
        lateness_window_cycles=round(config.cycle.statistics_window_s / config.cycle.period_s),
    )
    cycle = Cycle(
        config,
        shared,
        drives,
        statistics=task.statistics_fast,
        stop_loop=task.stop,
        moving_changed=task.set_moving,
    )
    signal.signal(signal.SIGTERM, lambda signum, frame: cycle.request_shutdown())
    _warm_up(config)
    cycle.start()
    if config.cycle.realtime.gc != "normal":
        # Everything alive now goes to the permanent generation: no later collection scans it.
        gc.collect()
        gc.freeze()
    error = task.run()
    bus.shutdown()
    if error is not None or not cycle.finished:
        logger.error("cycle stopped: %s", error or "loop ended before the shutdown")
        sys.exit(1)
    logger.info("cycle: drives off the bus, exiting")
    sys.exit(0)


def _warm_up(config: MachineConfig) -> None:
    """Run the braking code once before the first period (its first call costs imports)."""
    planner = config.planner
    BrakingProfile.from_state(
        v0_mm_s=planner.vmax_mm_s,
        a0_mm_s2=0.0,
        amax_mm_s2=planner.amax_mm_s2,
        jmax_mm_s3=planner.jmax_mm_s3,
    ).sample(0.01)
