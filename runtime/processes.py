"""What every child process of the runtime does first, and the priorities of the processes.

The supervisor (:mod:`runtime.supervisor`) starts the children with multiprocessing's ``spawn``
(a fresh interpreter each: nothing inherited from the supervisor's threads). Each child:

- dies with the supervisor (``PR_SET_PDEATHSIG``: SIGTERM when the supervisor ends, however);
- ignores SIGINT: Ctrl-C on a terminal reaches the whole process group, and the supervisor alone
  decides how the machine stops (it asks the cycle to stop on the path, disable the drives and
  leave the bus, then ends the others);
- takes its scheduling class: the cycle SCHED_FIFO at ``cycle.realtime.priority``; simulated
  drives (standing for hardware that never waits for the host) just below it; the planner at the
  normal class but favoured (nice :data:`PLANNER_NICE`), because a planner that falls behind
  stops the machine; the HMI server and the supervisor at the normal class. A real-time HMI
  server was tried: ten clients reading the whole status at 20 Hz then kept the planner from the
  CPU on two cores until the setpoints ran short. Threads a process starts later inherit its
  class;
- once set up, hands what it built to the collector's permanent generation
  (:func:`freeze_start_up_objects`), so a full collection never walks it again.

Linux only (prctl, sched_setscheduler); where a setting is refused, one warning says so and the
process goes on without it.
"""

from __future__ import annotations

import ctypes
import gc
import logging
import os
import signal

logger = logging.getLogger(__name__)

PR_SET_PDEATHSIG = 1
#: Simulated drives run this far below the cycle's SCHED_FIFO priority.
SIMULATION_PRIORITY_BELOW_CYCLE = 5
#: Nice value of the planner process: more CPU share than the HMI server and the supervisor.
PLANNER_NICE = -5


def prepare_child(*, parent_pid: int) -> None:
    """Die with the supervisor and leave SIGINT to it (call first thing in a child)."""
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    if os.getppid() != parent_pid:
        # The supervisor ended before the request took effect: nothing will signal us.
        os._exit(1)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def realtime_priority(priority: int, role: str) -> bool:
    """SCHED_FIFO at ``priority`` for this process's calling thread (0: leave it); whether it
    was applied."""
    if priority <= 0:
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (PermissionError, OSError) as exc:
        logger.warning("%s: SCHED_FIFO %d refused (%s); normal scheduling", role, priority, exc)
        return False
    return True


def simulation_priority(cycle_priority: int) -> int:
    """SCHED_FIFO priority of the simulated drives (0 when the cycle has none)."""
    return max(0, cycle_priority - SIMULATION_PRIORITY_BELOW_CYCLE) if cycle_priority else 0


def favour(nice: int, role: str) -> bool:
    """Lower this process's nice value to ``nice`` (needs CAP_SYS_NICE below 0); whether it
    was applied."""
    try:
        os.setpriority(os.PRIO_PROCESS, 0, nice)
    except OSError as exc:
        logger.warning("%s: nice %d refused (%s); default share of the CPU", role, nice, exc)
        return False
    return True


def freeze_start_up_objects() -> None:
    """Move every object alive now out of the garbage collector's reach (``gc.freeze``).

    What a process builds at start-up (modules, CANopen object dictionaries, the Modbus
    register map) lives as long as the process, yet a full collection walks all of it: 9 ms
    in the simulated drives' process on a 2-core host, over two periods without an answer to
    SYNC. Frozen, a full collection there takes about 15 µs. Start-up's own cyclic garbage is
    collected first, so none of it is kept for good.
    """
    gc.collect()
    gc.freeze()
