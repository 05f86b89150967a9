"""The planner process: plans the jobs the cycle asks for into the shared rings.

Started (and restarted when it dies) by the supervisor (:func:`planner_main`). Normal scheduling
class, favoured over the HMI server (:mod:`runtime.processes`): it computes while the cycle and
the simulated drives, both real-time, take the CPU whenever they need it. It polls the cycle's
requests between units of work and sleeps when there is nothing to do: :data:`IDLE_SLEEP_S`
while a job runs (an override or hold must reach the ring within a period or two), one period
without a job (a start waits that much longer, and an idle machine costs a quarter of the wake-ups).
"""

from __future__ import annotations

import logging
import signal
import sys
import time

from planner.nurbs import NurbsCurve
from planner.stream import Path, stream_setpoints
from runtime.config import MachineConfig
from runtime.curves import limits_for_curve, planner_limits
from runtime.logs import queued_logging
from runtime.planning.service import PlannerService
from runtime.processes import PLANNER_NICE, favour, freeze_start_up_objects, prepare_child
from runtime.shared import SharedState, shared_path

logger = logging.getLogger(__name__)

#: Sleep between polls while there is nothing to plan [s]: the delay before a new request is
#: taken up.
IDLE_SLEEP_S = 0.001


def planner_main(config: MachineConfig, run_dir: str, log_level: str, parent_pid: int) -> None:
    """The planner process's entry point (never returns)."""
    prepare_child(parent_pid=parent_pid)
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(0))
    with queued_logging(log_level):
        favour(PLANNER_NICE, "planner")
        shared = SharedState.attach(shared_path(run_dir), tuple(axis.name for axis in config.axes))
        _warm_up(config)
        service = PlannerService(shared, config)
        freeze_start_up_objects()
        logger.info("planner ready")
        while True:
            if not service.poll():
                time.sleep(IDLE_SLEEP_S if service.has_job else config.cycle.period_s)


def _warm_up(config: MachineConfig) -> None:
    """Plan a short line once: the first use of each planner code path costs imports and
    numpy's caches, which no job should wait for."""
    dimension = min(3, len(config.axes))
    limits = limits_for_curve(planner_limits(config), dimension)
    line = NurbsCurve.from_arrays(1, [[0.0] * dimension, [1.0] * dimension], [0, 0, 1, 1])
    path = Path(line, limits, config.cycle.period_s)
    for _ in stream_setpoints(path, limits, config.cycle.period_s):
        pass
