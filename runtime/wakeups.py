"""Wake-up latency test: the cycle's wait on absolute deadlines, measured in a child process.

The child applies the configured real-time settings (:func:`runtime.realtime.apply_realtime`:
SCHED_FIFO priority, CPU pinning, mlockall and the malloc policy, the GC policy of motion), then
waits like the cycle process does for every period of the test: it sleeps to ``spin_us`` before
the absolute deadline ``start + k * period`` and spins to it. Lateness is the wake time minus the
deadline of the first period due (stalls count in full, as in the cycle's statistics); a wake-up
later than half a period skips the periods it missed, keeping phase, as the cycle does. Nothing
runs between wake-ups: the figures are the host's, not the runtime's step.

Runs in a process started with ``spawn``: scheduler, affinity and memory lock are the child's
and end with it, and it inherits no thread of the caller. Units: seconds inside, microseconds in
the percentiles (:data:`runtime.latency.PERCENTILES`), KiB for locked memory.
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from runtime.config import RealtimeConfig
from runtime.latency import LatenessRing
from runtime.realtime import GcPolicy, apply_realtime

#: Seconds the child may take beyond the test itself (interpreter start, imports, settings).
CHILD_START_ALLOWANCE_S = 60.0


@dataclass(frozen=True)
class WakeupResult:
    """What the child obtained and measured."""

    report: tuple[str, ...]
    """One line per real-time setting, as :func:`runtime.realtime.apply_realtime` reports it."""
    fifo_priority: int | None
    """SCHED_FIFO priority the child ran at; None under another policy."""
    cpus: tuple[int, ...]
    """CPUs the child was allowed to run on during the test."""
    locked_kib: int
    """Memory locked by the child at the end of the test (VmLck: with MCL_ONFAULT the size of
    the locked mappings, touched or not)."""
    virtual_kib: int
    """The child's virtual size at the end of the test (VmSize): without CAP_IPC_LOCK,
    mlockall(MCL_CURRENT) is refused when it exceeds RLIMIT_MEMLOCK."""
    wakeups: int
    percentiles_us: dict[str, float]
    """p50, p99, p99.9 and max lateness of the wake-ups [us]."""
    missed_periods: int
    """Periods skipped because a wake-up came more than half a period late."""
    longest_miss_run: int
    """Most periods missed in a row (consecutive late wake-ups add up)."""
    steal_ms: float = 0.0
    """CPU time a hypervisor gave to other guests while this machine's CPUs wanted it, during
    the test, all CPUs together [ms]: 0 on bare metal. No setting inside a virtual machine
    protects a process from it."""


def host_steal_s(stat_path: Path = Path("/proc/stat")) -> float:
    """The steal time of all CPUs since boot (/proc/stat) [s]; 0 where the kernel has none."""
    try:
        with stat_path.open() as stat:
            fields = stat.readline().split()
    except OSError:
        return 0.0
    return int(fields[8]) / os.sysconf("SC_CLK_TCK") if len(fields) > 8 else 0.0


def _memory_kib(status_path: Path = Path("/proc/self/status")) -> dict[str, int]:
    """The ``Vm*`` sizes of /proc/self/status [KiB] (VmLck, VmSize, VmRSS, ...)."""
    sizes: dict[str, int] = {}
    try:
        for line in status_path.read_text().splitlines():
            name, _, value = line.partition(":")
            if name.startswith("Vm") and value.strip().endswith("kB"):
                sizes[name] = int(value.split()[0])
    except OSError:
        pass
    return sizes


def _fifo_priority() -> int | None:
    if os.sched_getscheduler(0) != os.SCHED_FIFO:
        return None
    return os.sched_getparam(0).sched_priority


def measure_wakeups(
    period_s: float, spin_s: float, duration_s: float
) -> tuple[LatenessRing, int, int]:
    """Wait for every deadline of ``duration_s`` (at least one period); return the lateness
    ring, the missed periods and the longest run of them. Runs in the calling thread with
    whatever settings it has."""
    periods = max(1, round(duration_s / period_s))
    ring = LatenessRing(periods)
    half_period_s = 0.5 * period_s
    missed_total = run = longest_run = 0
    clock = time.monotonic
    start_s = clock() + period_s
    index = 0
    while index < periods:
        deadline_s = start_s + index * period_s
        now_s = clock()
        if deadline_s - now_s > spin_s:
            time.sleep(deadline_s - spin_s - now_s)
            now_s = clock()
        while now_s < deadline_s:
            now_s = clock()
        lateness_s = now_s - deadline_s
        ring.record(lateness_s)
        missed = (
            math.ceil((lateness_s - half_period_s) / period_s) if lateness_s > half_period_s else 0
        )
        missed_total += missed
        run = run + missed if missed else 0
        longest_run = max(longest_run, run)
        index += 1 + missed
    return ring, missed_total, longest_run


def _child(realtime: RealtimeConfig, period_s: float, duration_s: float) -> WakeupResult:
    # The report comes back as data; the parent prints it.
    logging.getLogger().addHandler(logging.NullHandler())
    applied = apply_realtime(realtime, thread_name="wake-up test")
    GcPolicy(realtime.gc).set_moving(True)
    steal_at_start_s = host_steal_s()
    ring, missed, longest_run = measure_wakeups(period_s, realtime.spin_us * 1e-6, duration_s)
    steal_s = host_steal_s() - steal_at_start_s
    memory_kib = _memory_kib()
    return WakeupResult(
        report=applied.report,
        fifo_priority=_fifo_priority(),
        cpus=tuple(sorted(os.sched_getaffinity(0))),
        locked_kib=memory_kib.get("VmLck", 0),
        virtual_kib=memory_kib.get("VmSize", 0),
        wakeups=len(ring),
        percentiles_us=ring.percentiles_us(),
        missed_periods=missed,
        longest_miss_run=longest_run,
        steal_ms=steal_s * 1000.0,
    )


def run_wakeup_test(realtime: RealtimeConfig, period_s: float, duration_s: float) -> WakeupResult:
    """Apply ``realtime`` in a fresh child process and measure its wake-ups for ``duration_s``
    (at least one period).

    :raises TimeoutError: if the child does not answer within the test plus
        :data:`CHILD_START_ALLOWANCE_S`.
    """
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=1, mp_context=context) as pool:
        future = pool.submit(_child, realtime, period_s, duration_s)
        return future.result(timeout=duration_s + CHILD_START_ALLOWANCE_S)
