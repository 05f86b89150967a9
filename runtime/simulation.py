"""The simulated drives' process: the configured axes as simulated CiA-402 drives on the bus.

Started by the supervisor before the cycle when ``simulation.drives`` is on
(:func:`simulation_main`). The drives stand for hardware: they run in a process of their own,
just below the cycle's real-time priority, so a busy planner or HMI never delays their answers.
"""

from __future__ import annotations

import signal
import threading

from drives.sim.drive import start_simulated_drives
from drives.sim.dynamics import DriveModel
from runtime.config import MachineConfig
from runtime.logs import queued_logging
from runtime.processes import (
    freeze_start_up_objects,
    prepare_child,
    realtime_priority,
    simulation_priority,
)

#: SYNC-loss limit of the simulated drives, in periods beyond the longest SYNC gap the cycle's
#: overrun limit tolerates: a run of ``overrun_limit`` missed periods leaves a gap of
#: ``overrun_limit + 1`` periods, which the machine rides through, so its drives do too.
SIMULATED_SYNC_MARGIN_PERIODS = 1


def simulated_sync_timeout_periods(config: MachineConfig) -> float:
    """SYNC-loss limit of the simulated drives, periods."""
    return float(config.cycle.overrun_limit + 1 + SIMULATED_SYNC_MARGIN_PERIODS)


def simulation_main(config: MachineConfig, log_level: str, parent_pid: int) -> None:
    """The simulated drives' entry point: run until SIGTERM."""
    prepare_child(parent_pid=parent_pid)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda signum, frame: stop.set())
    realtime_priority(simulation_priority(config.cycle.realtime.priority), "simulated drives")
    with queued_logging(log_level):
        drives = start_simulated_drives(
            config.can.interface,
            config.can.channel,
            [axis.node_id for axis in config.axes],
            model=DriveModel(sync_timeout_factor=simulated_sync_timeout_periods(config)),
            bitrate=config.can.bitrate,
            quirks={
                axis.node_id: config.simulation.quirks[axis.name]
                for axis in config.axes
                if axis.name in config.simulation.quirks
            },
        )
        freeze_start_up_objects()
        with drives:
            while not stop.wait(0.5):
                pass
