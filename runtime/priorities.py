"""Real-time priorities of the runtime's helper threads, below the cyclic thread.

Python threads share one interpreter lock. A normal-priority thread of this process that holds
the lock when the OS preempts it for another process keeps the SCHED_FIFO cyclic thread waiting
until it runs again: on a loaded machine, tens of milliseconds. So every helper thread (CAN
receive, Modbus server, simulated drives) runs SCHED_FIFO just below the cyclic thread, and the
CPU-bound planner worker and the log writer (:mod:`runtime.logs`) at the lowest real-time
priority, where every other one preempts them.

Linux only; where SCHED_FIFO is refused, one warning says so and the threads keep their
scheduler.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Collection

from runtime.logs import LOG_WRITER_THREAD

logger = logging.getLogger(__name__)

#: Threads (by name) that compute or write rather than wait for the bus; they get the lowest
#: real-time priority.
BACKGROUND_THREADS = ("planner", LOG_WRITER_THREAD)


def prioritise_threads(
    cycle_priority: int,
    *,
    exclude: Collection[threading.Thread] = (),
    include_main: bool = False,
) -> int:
    """Give every running thread but ``exclude`` (and the main one unless ``include_main``) a
    SCHED_FIFO priority below ``cycle_priority``; returns how many threads were changed.

    The main thread, when included, gets the lowest priority: it only waits and reports.
    """
    if cycle_priority <= 1:
        return 0
    changed = 0
    for thread in threading.enumerate():
        is_main = thread is threading.main_thread()
        if (is_main and not include_main) or thread in exclude or thread.native_id is None:
            continue
        background = is_main or thread.name in BACKGROUND_THREADS
        priority = 1 if background else cycle_priority - 1
        try:
            os.sched_setscheduler(thread.native_id, os.SCHED_FIFO, os.sched_param(priority))
        except (OSError, AttributeError) as exc:
            logger.warning("helper threads keep their scheduler: SCHED_FIFO refused (%s)", exc)
            return changed
        changed += 1
    logger.info("%d helper threads at SCHED_FIFO below the cyclic thread", changed)
    return changed


def restore_main_thread() -> None:
    """Put the main thread back on the normal scheduler (after :func:`prioritise_threads`)."""
    native_id = threading.main_thread().native_id
    if native_id is None:
        return
    try:
        os.sched_setscheduler(native_id, os.SCHED_OTHER, os.sched_param(0))
    except (OSError, AttributeError) as exc:
        logger.warning("main thread keeps its scheduler: %s", exc)
