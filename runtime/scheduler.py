"""The cyclic task: calls one step per period on absolute deadlines, in its own real-time thread.

Timing (reference modbus-hmi.md §8; LinuxCNC and OpenPLC use the same absolute deadlines):

- Period ``k`` has the deadline ``start + k * period_s`` on ``clock`` (``time.monotonic``), computed
  by multiplication, so there is no drift however long the task runs. The thread sleeps
  (``time.sleep``, which is ``clock_nanosleep`` since Python 3.11) until ``spin_us`` before the
  deadline, then busy-waits to it.
- Overrun policy: skip, never catch up. A cycle runs only within half a period after a deadline.
  When the thread gets to run later than that after the deadline of the next period due (the
  step overran, or the OS woke it late), the periods in between are skipped keeping phase: the
  cycle runs for the latest deadline at most half a period ago, or, if there is none, sleeps to
  the next deadline. ``missed_periods`` says how many periods were skipped just before it. The
  step never runs twice back-to-back to catch up: two steps always start at least half a period
  apart, so drives never see a burst of setpoints.
- Consecutive misses: a run of misses is the number of periods skipped since the last on-time
  cycle, one that skipped nothing and whose thread was idle before its deadline (the previous
  cycle finished within its period). Every cycle that skips adds its skipped periods to the run;
  a cycle that skips nothing but was delayed by the previous step's overrun leaves it unchanged,
  so a step that chronically needs more than a period keeps the run growing. When the run first
  exceeds ``overrun_limit``, ``on_overrun_limit(run)`` is called once, just before the step of
  that cycle (so the step can already react, e.g. go to ErrorStop), after a warning that gives
  how late the thread woke and how long the step before it took, on the clock and on the CPU.
  A single stall costing ``overrun_limit`` periods is tolerated; one more trips.

Numbering: ``CycleTick.index`` counts executed cycles (0, 1, 2, ... with no gaps);
``CycleTick.period_index`` counts periods since start including skipped ones, so
``deadline_s == start + period_index * period_s`` and ``period_index - index`` is the total of
skipped periods.

Lateness: ``CycleTick.lateness_s`` is the wake time minus the cycle's own deadline, in
``[0, period_s / 2]``. The statistics record the first wake time minus the deadline of the first
period due: how late the thread got to run, stalls included (a 100 ms stall counts 100 ms, not
its remainder modulo the period), the figure the reference's latency tables give. Execution time
is ``clock`` read around the step; a step longer than the period that is the longest so far is
logged with the thread's CPU time over it (``time.thread_time``), which tells computing apart
from waiting for the CPU.

Statistics cost: per cycle, O(1) (counters, maxima, one sample into the
:class:`runtime.latency.LatenessRing`'s histogram). The percentiles (bounded, whatever the
window) are refreshed by the cyclic thread every ``percentile_refresh_cycles`` cycles (default:
once a second), after the step, in the idle time before the next sleep (about 35 µs); the step
reads them cheaply through :meth:`CyclicTask.statistics_fast`. :meth:`CyclicTask.statistics` and
:meth:`CyclicTask.lateness_percentiles` compute fresh percentiles for callers outside the cycle.

Threading: :meth:`start` and :meth:`stop` are called from a control thread; the step,
``on_overrun_limit`` and ``on_error`` run in the cyclic thread and must not block. Real-time
settings (:mod:`runtime.realtime`) are applied inside the cyclic thread before the first cycle
and the process-wide ones are undone when it ends. An exception from the step (or from
``on_overrun_limit``) is logged with its traceback, stops the task and is passed to
``on_error``.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from runtime.config import RealtimeConfig
from runtime.errors import RuntimeFault
from runtime.latency import LatenessRing
from runtime.realtime import SWITCH_INTERVAL_S, GcPolicy, apply_realtime
from runtime.status import CycleStatistics

logger = logging.getLogger(__name__)

DEFAULT_REALTIME = RealtimeConfig()


class CycleStopTimeout(RuntimeFault, TimeoutError):
    """The cyclic thread did not end within the stop timeout (its step is blocked)."""

    def __init__(self, name: str, timeout_s: float) -> None:
        self.name = name
        self.timeout_s = timeout_s
        super().__init__(f"cyclic task {name}: thread still running {timeout_s:g} s after stop")


@dataclass(frozen=True, slots=True)
class CycleTick:
    """What the step learns about the cycle it runs in."""

    index: int
    """Executed cycles before this one since start (no gaps)."""
    period_index: int
    """Periods since start, skipped ones included: ``deadline_s = start + period_index * T``."""
    deadline_s: float
    """This cycle's deadline on the task's clock (``time.monotonic``)."""
    lateness_s: float
    """Wake time minus ``deadline_s``; in ``[0, period_s / 2]``."""
    missed_periods: int
    """Periods skipped just before this cycle (0 normally)."""


class CyclicTask:
    """Runs ``step(tick)`` once per period in its own thread; see the module docstring.

    :param period_s: the cycle period [s], > 0.
    :param step: called once per cycle in the cyclic thread; O(1), never blocking.
    :param realtime: scheduler, affinity, memory lock, GC policy and spin before each deadline.
    :param overrun_limit: a run of more consecutive missed periods than this calls
        ``on_overrun_limit(run)``.
    :param on_error: called in the cyclic thread with the exception that stopped the task.
    :param clock: monotonic time source [s]; ``sleep`` sleeps a relative time [s]. Both are
        injectable so the timing logic can be tested with a fake clock.
    :param lateness_window_cycles: samples held for the lateness percentiles.
    :param percentile_refresh_cycles: cycles between refreshes of the cached percentiles that
        :meth:`statistics_fast` returns; default: the cycles in one second.
    :param switch_interval_s: GIL switch interval applied while the task runs; None leaves it.
    :raises ValueError: for a period that is not a positive finite number, a negative
        ``overrun_limit`` or a window or refresh interval below 1.
    """

    def __init__(
        self,
        period_s: float,
        step: Callable[[CycleTick], None],
        *,
        realtime: RealtimeConfig = DEFAULT_REALTIME,
        overrun_limit: int = 3,
        on_overrun_limit: Callable[[int], None] | None = None,
        on_error: Callable[[BaseException], None] | None = None,
        name: str = "cyclic",
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
        lateness_window_cycles: int = 2500,
        percentile_refresh_cycles: int | None = None,
        switch_interval_s: float | None = SWITCH_INTERVAL_S,
    ) -> None:
        if not (math.isfinite(period_s) and period_s > 0):
            raise ValueError(f"cyclic task {name}: period_s = {period_s!r}, must be > 0")
        if overrun_limit < 0:
            raise ValueError(f"cyclic task {name}: overrun_limit = {overrun_limit}, must be >= 0")
        if percentile_refresh_cycles is None:
            percentile_refresh_cycles = max(1, round(1.0 / period_s))
        if percentile_refresh_cycles < 1:
            raise ValueError(
                f"cyclic task {name}: percentile_refresh_cycles = {percentile_refresh_cycles}, "
                "must be >= 1"
            )
        self.period_s = period_s
        self.name = name
        self._step = step
        self._realtime = realtime
        self._spin_s = realtime.spin_us * 1e-6
        self._overrun_limit = overrun_limit
        self._on_overrun_limit = on_overrun_limit
        self._on_error = on_error
        self._clock = clock
        self._sleep = sleep
        self._refresh_cycles = percentile_refresh_cycles
        self._switch_interval_s = switch_interval_s
        self._gc = GcPolicy(realtime.gc)
        self._ring = LatenessRing(lateness_window_cycles)
        self._thread: threading.Thread | None = None
        self._running = False
        self._looping = False
        self._ready = threading.Event()
        self.realtime_report: tuple[str, ...] = ()
        """One line per real-time setting: applied, or why not. Filled by :meth:`start`."""
        self._clear_statistics()

    # -- control (control thread) ---------------------------------------------------------

    @property
    def running(self) -> bool:
        """True from :meth:`start` (or :meth:`run`) until the loop ends (stop, or an error in
        the step)."""
        return self._thread is not None and self._thread.is_alive() and self._looping

    def run(self) -> BaseException | None:
        """Run the loop in the calling thread (the cycle process's only thread) until
        :meth:`stop`; returns the exception that stopped it, if any.

        :raises RuntimeError: if the task is already running.
        """
        if self.running:
            raise RuntimeError(f"cyclic task {self.name}: already running")
        self._running = True
        self._ready.clear()
        self._thread = threading.current_thread()
        return self._run()

    def start(self) -> None:
        """Run the loop in a thread of its own; returns once its real-time settings are
        applied (benchmarks and tests; the runtime uses :meth:`run`).

        :raises RuntimeError: if the task is already running.
        """
        if self.running:
            raise RuntimeError(f"cyclic task {self.name}: already running")
        self._running = True
        self._ready.clear()
        self._looping = True
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()
        self._ready.wait()

    def stop(self, timeout_s: float = 2.0) -> None:
        """Stop after the current cycle and join the thread.

        From the step itself it only requests the stop (the loop ends after this cycle).

        :raises CycleStopTimeout: if the thread is still running after ``timeout_s``.
        """
        self._running = False
        thread = self._thread
        if thread is None or thread is threading.current_thread():
            return
        thread.join(timeout_s)
        if thread.is_alive():
            raise CycleStopTimeout(self.name, timeout_s)

    def set_moving(self, moving: bool) -> None:
        """Apply the GC policy for motion or rest (process-wide, O(1); any thread)."""
        self._gc.set_moving(moving)

    # -- statistics -----------------------------------------------------------------------

    def statistics_fast(self) -> CycleStatistics:
        """Counters, last and max values, and the percentiles of the last refresh. O(1).

        Meant for the step's per-cycle status snapshot; inside the step the execution figures
        are those of the previous cycle.
        """
        return CycleStatistics(
            cycles=self._cycles,
            lateness_last_us=self._lateness_last_s * 1e6,
            lateness_p50_us=self._percentiles_us["p50"],
            lateness_p99_us=self._percentiles_us["p99"],
            lateness_p999_us=self._percentiles_us["p99.9"],
            lateness_max_us=self._lateness_max_s * 1e6,
            execution_last_us=self._execution_last_s * 1e6,
            execution_max_us=self._execution_max_s * 1e6,
            missed_periods=self._missed_total,
        )

    def statistics(self) -> CycleStatistics:
        """Like :meth:`statistics_fast` with fresh percentiles. O(window): not from the step."""
        percentiles_us = self._ring.percentiles_us()
        fast = self.statistics_fast()
        return CycleStatistics(
            cycles=fast.cycles,
            lateness_last_us=fast.lateness_last_us,
            lateness_p50_us=percentiles_us["p50"],
            lateness_p99_us=percentiles_us["p99"],
            lateness_p999_us=percentiles_us["p99.9"],
            lateness_max_us=fast.lateness_max_us,
            execution_last_us=fast.execution_last_us,
            execution_max_us=fast.execution_max_us,
            missed_periods=fast.missed_periods,
        )

    def lateness_percentiles(self) -> dict[str, float]:
        """p50, p99, p99.9 and max lateness [µs] over the window. O(window): not from the step."""
        return self._ring.percentiles_us()

    def reset_statistics(self) -> None:
        """Zero the statistics (not the overrun run, which is protection, not statistics).

        Call it from the step (e.g. when applying the HMI's reset at cycle start) or while the
        task is stopped; from another thread a sample of the current cycle may survive it.
        """
        self._clear_statistics()

    def _clear_statistics(self) -> None:
        self._cycles = 0
        self._missed_total = 0
        self._lateness_last_s = 0.0
        self._lateness_max_s = 0.0
        self._execution_last_s = 0.0
        self._execution_last_cpu_s = 0.0
        self._execution_max_s = 0.0
        self._ring.clear()
        self._percentiles_us = self._ring.percentiles_us()

    # -- the cyclic thread ------------------------------------------------------------------

    def _run(self) -> BaseException | None:
        applied = None
        self._looping = True
        error: BaseException | None = None
        try:
            applied = apply_realtime(
                self._realtime, thread_name=self.name, switch_interval_s=self._switch_interval_s
            )
            self.realtime_report = applied.report
            self._ready.set()
            self._loop()
        except Exception as exc:
            error = exc
            self._running = False
            logger.exception("cyclic task %s: stopped by an exception in its cycle", self.name)
            if self._on_error is not None:
                try:
                    self._on_error(exc)
                except Exception:
                    logger.exception("cyclic task %s: on_error raised", self.name)
        finally:
            self._looping = False
            self._ready.set()
            self._gc.restore()
            if applied is not None:
                applied.restore()
        return error

    def _wait_until(self, deadline_s: float) -> float:
        """Sleep to ``spin`` before ``deadline_s``, spin to it; return the wake time."""
        clock = self._clock
        now_s = clock()
        if deadline_s - now_s > self._spin_s:
            self._sleep(deadline_s - self._spin_s - now_s)
            now_s = clock()
        while now_s < deadline_s:
            now_s = clock()
        return now_s

    def _loop(self) -> None:
        clock = self._clock
        step = self._step
        period_s = self.period_s
        half_period_s = 0.5 * period_s
        start_s = clock()
        index = 0
        period_index = 0
        miss_run = 0
        run_reported = False
        while self._running:
            first_due_index = period_index
            deadline_s = start_s + period_index * period_s
            idle = clock() < deadline_s
            now_s = self._wait_until(deadline_s)
            wake_lateness_s = now_s - deadline_s
            lateness_s = wake_lateness_s
            while lateness_s > half_period_s:
                period_index += math.ceil((lateness_s - half_period_s) / period_s)
                deadline_s = start_s + period_index * period_s
                if deadline_s > now_s:
                    now_s = self._wait_until(deadline_s)
                lateness_s = now_s - deadline_s
            missed = period_index - first_due_index
            tick = CycleTick(index, period_index, deadline_s, lateness_s, missed)

            self._record_lateness(wake_lateness_s, missed)
            if missed == 0 and idle:
                miss_run = 0
                run_reported = False
            elif missed:
                miss_run += missed
                if miss_run > self._overrun_limit and not run_reported:
                    run_reported = True
                    self._report_overrun_run(miss_run, wake_lateness_s)
                    if self._on_overrun_limit is not None:
                        self._on_overrun_limit(miss_run)

            begin_s = clock()
            begin_cpu_s = time.thread_time()
            step(tick)
            self._record_execution(clock() - begin_s, time.thread_time() - begin_cpu_s)
            index += 1
            period_index += 1
            if index % self._refresh_cycles == 0:
                self._percentiles_us = self._ring.percentiles_us()

    def _record_lateness(self, lateness_s: float, missed: int) -> None:
        self._cycles += 1
        self._missed_total += missed
        self._lateness_last_s = lateness_s
        if lateness_s > self._lateness_max_s:
            self._lateness_max_s = lateness_s
        self._ring.record(lateness_s)

    def _report_overrun_run(self, run: int, wake_lateness_s: float) -> None:
        # Both figures, so the log tells a thread kept off the CPU (a late wake after a short
        # step: a higher priority or the host) from a step that overran (on the CPU or blocked).
        logger.warning(
            "cyclic task %s: %d consecutive periods missed (limit %d): woke %.2f ms after the "
            "first deadline due; the step before took %.2f ms (%.2f ms of it on the CPU)",
            self.name,
            run,
            self._overrun_limit,
            wake_lateness_s * 1e3,
            self._execution_last_s * 1e3,
            self._execution_last_cpu_s * 1e3,
        )

    def _record_execution(self, execution_s: float, cpu_s: float) -> None:
        self._execution_last_s = execution_s
        self._execution_last_cpu_s = cpu_s
        if execution_s <= self._execution_max_s:
            return
        self._execution_max_s = execution_s
        if execution_s > self.period_s:
            # Logged on a new maximum only: a chronic overrun must not flood the log.
            logger.warning(
                "cyclic task %s: longest step so far, %.2f ms (%.2f ms of it on the CPU), "
                "longer than the period",
                self.name,
                execution_s * 1e3,
                cpu_s * 1e3,
            )
