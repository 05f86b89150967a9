"""The cyclic task: skip logic on a fake clock, then a few real-time smoke tests."""

from __future__ import annotations

import gc
import itertools
import logging
import threading
import time

import pytest

from runtime.config import RealtimeConfig
from runtime.scheduler import CycleStopTimeout, CycleTick, CyclicTask

#: No privileges needed, nothing process-wide but the switch interval; no spin, so a fake clock
#: that only moves on sleep reaches every deadline exactly.
PLAIN = RealtimeConfig(priority=0, cpu=None, lock_memory=False, gc="normal", spin_us=0.0)

#: A dyadic period, so deadlines on the fake clock are exact floats.
PERIOD_S = 0.25

#: Generous bound for the real-time tests (2 shared cores, noisy CPU).
JOIN_TIMEOUT_S = 5.0


class FakeTime:
    """A clock that moves only when the task sleeps, the step works, or a read costs time."""

    def __init__(self, start_s: float = 1000.0, read_cost_s: float = 0.0) -> None:
        self.now_s = start_s
        self.read_cost_s = read_cost_s
        self.oversleep_s: list[float] = []
        """Extra time added to successive sleeps (the OS waking the thread late)."""
        self.sleeps_s: list[float] = []

    def clock(self) -> float:
        self.now_s += self.read_cost_s
        return self.now_s

    def sleep(self, duration_s: float) -> None:
        assert duration_s > 0
        self.sleeps_s.append(duration_s)
        extra_s = self.oversleep_s.pop(0) if self.oversleep_s else 0.0
        self.now_s += duration_s + extra_s


def run_fake(
    cycles: int,
    work_s: dict[int, float] | None = None,
    *,
    fake: FakeTime | None = None,
    realtime: RealtimeConfig = PLAIN,
    events: list[str] | None = None,
    **task_kwargs: object,
) -> tuple[list[CycleTick], list[float], CyclicTask]:
    """Run ``cycles`` cycles on a fake clock; the step of cycle i works ``work_s[i]`` seconds.

    Returns the ticks, the fake time at which each step started, and the stopped task; each
    step also appends ``step <index>`` to ``events``.
    """
    fake = fake or FakeTime()
    work_s = work_s or {}
    ticks: list[CycleTick] = []
    starts_s: list[float] = []
    done = threading.Event()
    task: CyclicTask

    def step(tick: CycleTick) -> None:
        ticks.append(tick)
        starts_s.append(fake.now_s)
        if events is not None:
            events.append(f"step {tick.index}")
        fake.now_s += work_s.get(tick.index, 0.0)
        if len(ticks) == cycles:
            task.stop()
            done.set()

    task = CyclicTask(
        PERIOD_S, step, realtime=realtime, clock=fake.clock, sleep=fake.sleep, **task_kwargs
    )
    task.start()
    assert done.wait(JOIN_TIMEOUT_S)
    task.stop(JOIN_TIMEOUT_S)
    return ticks, starts_s, task


# -- deterministic logic (fake clock) ---------------------------------------------------------


def test_cycles_run_on_absolute_deadlines() -> None:
    # Steps taking varying fractions of a period do not shift later deadlines (no drift).
    work = {i: PERIOD_S * (i % 4) / 5 for i in range(40)}
    ticks, starts_s, _ = run_fake(40, work)
    start_s = ticks[0].deadline_s
    assert [t.index for t in ticks] == list(range(40))
    assert [t.period_index for t in ticks] == list(range(40))
    assert all(t.deadline_s == start_s + t.period_index * PERIOD_S for t in ticks)
    assert starts_s == [t.deadline_s for t in ticks]
    assert all(t.missed_periods == 0 and t.lateness_s == 0.0 for t in ticks)


def test_sleep_ends_spin_before_the_deadline_and_spin_reaches_it() -> None:
    spin = RealtimeConfig(priority=0, lock_memory=False, gc="normal", spin_us=20_000.0)
    fake = FakeTime(read_cost_s=2.0**-10)
    ticks, starts_s, _ = run_fake(5, fake=fake, realtime=spin)
    # Each sleep stops 20 ms (spin) before the next deadline, less the step and the clock reads.
    assert all(PERIOD_S - 0.030 < s < PERIOD_S - 0.020 for s in fake.sleeps_s)
    for tick, start_s in zip(ticks[1:], starts_s[1:], strict=True):
        assert tick.missed_periods == 0
        assert 0.0 <= tick.lateness_s <= 2 * fake.read_cost_s
        assert start_s >= tick.deadline_s


def test_overrunning_step_skips_whole_periods_keeping_phase() -> None:
    # Cycle 3's step blocks for 3.5 periods: periods 4 and 5 pass unexecuted, period 6 runs
    # half a period late, and period 7 runs on its own deadline: one cycle each, no burst.
    ticks, starts_s, task = run_fake(8, {3: 3.5 * PERIOD_S})
    start_s = ticks[0].deadline_s
    assert [t.period_index for t in ticks] == [0, 1, 2, 3, 6, 7, 8, 9]
    assert [t.missed_periods for t in ticks] == [0, 0, 0, 0, 2, 0, 0, 0]
    assert ticks[4].lateness_s == 0.5 * PERIOD_S
    assert all(t.deadline_s == start_s + t.period_index * PERIOD_S for t in ticks)
    gaps_s = [b - a for a, b in itertools.pairwise(starts_s)]
    assert min(gaps_s) == 0.5 * PERIOD_S
    stats = task.statistics()
    assert stats.missed_periods == 2
    # Statistics lateness counts from the first period due (4): 2.5 periods.
    assert stats.lateness_max_us == pytest.approx(2.5 * PERIOD_S * 1e6)


def test_late_wake_by_the_os_skips_too() -> None:
    fake = FakeTime()
    # The first sleep (before cycle 1) oversleeps by 2.25 periods: periods 1 and 2 are
    # skipped, period 3 runs a quarter of a period late.
    fake.oversleep_s = [2.25 * PERIOD_S]
    ticks, _, _ = run_fake(4, fake=fake)
    assert [(t.period_index, t.missed_periods) for t in ticks] == [(0, 0), (3, 2), (4, 0), (5, 0)]
    assert ticks[1].lateness_s == 0.25 * PERIOD_S


def test_wake_more_than_half_a_period_late_waits_for_the_next_deadline() -> None:
    fake = FakeTime()
    fake.oversleep_s = [0.75 * PERIOD_S]
    ticks, starts_s, task = run_fake(3, fake=fake)
    assert [(t.period_index, t.missed_periods) for t in ticks] == [(0, 0), (2, 1), (3, 0)]
    assert ticks[1].lateness_s == 0.0
    assert starts_s[1] - starts_s[0] == 2 * PERIOD_S
    assert task.statistics().lateness_max_us == pytest.approx(0.75 * PERIOD_S * 1e6)


def test_chronic_overrun_grows_the_run_and_calls_on_overrun_limit_once() -> None:
    # From cycle 2 on every step takes 1.5 periods: cycles alternate between half a period late
    # (not idle before the deadline, so the run goes on) and one period skipped. With limit 3
    # the fourth skipped period calls on_overrun_limit(4), once, before that cycle's step.
    events: list[str] = []
    ticks, _, _ = run_fake(
        13,
        {i: 1.5 * PERIOD_S for i in range(2, 13)},
        events=events,
        overrun_limit=3,
        on_overrun_limit=lambda run: events.append(f"limit {run}"),
    )
    assert [t.missed_periods for t in ticks[:11]] == [0, 0, 0, 0, 1, 0, 1, 0, 1, 0, 1]
    assert [e for e in events if e.startswith("limit")] == ["limit 4"]
    assert events.index("limit 4") == events.index("step 10") - 1


def test_a_single_stall_of_limit_periods_is_tolerated_one_more_trips() -> None:
    calls: list[int] = []
    # Stall of 4 periods (3 missed, = limit): tolerated; stall of 5 (4 missed): trips.
    ticks, _, _ = run_fake(
        8, {1: 4 * PERIOD_S, 4: 5 * PERIOD_S}, overrun_limit=3, on_overrun_limit=calls.append
    )
    assert [t.missed_periods for t in ticks] == [0, 0, 3, 0, 0, 4, 0, 0]
    assert calls == [4]


def test_a_tripping_run_is_logged_with_the_wake_lateness_and_the_step_before(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # A late wake after short steps (the thread kept off the CPU) and a step that overran read
    # differently in the log: the wake lateness against the step time before it.
    fake = FakeTime()
    fake.oversleep_s = [5.25 * PERIOD_S]
    with caplog.at_level(logging.WARNING, logger="runtime.scheduler"):
        run_fake(3, fake=fake, overrun_limit=3)
        run_fake(3, {1: 5.25 * PERIOD_S}, overrun_limit=3)
    kept_off, overran = (r.getMessage() for r in caplog.records if "consecutive" in r.message)
    woke_ms = 5.25 * PERIOD_S * 1e3
    assert f"5 consecutive periods missed (limit 3): woke {woke_ms:.2f} ms after" in kept_off
    assert "the step before took 0.00 ms" in kept_off
    assert f"woke {woke_ms - PERIOD_S * 1e3:.2f} ms after" in overran
    assert f"the step before took {woke_ms:.2f} ms" in overran


def test_on_time_cycle_ends_the_run_so_a_new_run_can_trip_again() -> None:
    calls: list[int] = []
    # Steps of 2 periods on alternate cycles: one skip each, but the cycle after the skip is
    # idle before its deadline and ends the run, so runs of 1 never reach limit 1 + 1. Two
    # separate stalls of 3 periods (2 skipped each) then trip twice.
    work = {i: 2 * PERIOD_S for i in range(0, 10, 2)}
    work.update({12: 3 * PERIOD_S, 14: 3 * PERIOD_S})
    ticks, _, _ = run_fake(17, work, overrun_limit=1, on_overrun_limit=calls.append)
    assert [t.missed_periods for t in ticks[:10]] == [0, 1, 0, 1, 0, 1, 0, 1, 0, 1]
    assert calls == [2, 2]


def test_overrun_limit_zero_trips_on_any_miss() -> None:
    calls: list[int] = []
    run_fake(4, {1: 2.5 * PERIOD_S}, overrun_limit=0, on_overrun_limit=calls.append)
    assert calls == [1]


def test_exception_in_step_is_logged_stops_the_task_and_reaches_on_error(
    caplog: pytest.LogCaptureFixture,
) -> None:
    fake = FakeTime()
    errors: list[BaseException] = []
    calls: list[int] = []
    stopped = threading.Event()

    def step(tick: CycleTick) -> None:
        calls.append(tick.index)
        if tick.index == 2:
            raise ZeroDivisionError("setpoint")

    def on_error(exc: BaseException) -> None:
        errors.append(exc)
        stopped.set()

    task = CyclicTask(
        PERIOD_S, step, realtime=PLAIN, on_error=on_error, clock=fake.clock, sleep=fake.sleep
    )
    with caplog.at_level(logging.ERROR, logger="runtime.scheduler"):
        task.start()
        assert stopped.wait(JOIN_TIMEOUT_S)
        task.stop(JOIN_TIMEOUT_S)
    assert calls == [0, 1, 2]
    assert not task.running
    assert len(errors) == 1 and isinstance(errors[0], ZeroDivisionError)
    [record] = [r for r in caplog.records if r.name == "runtime.scheduler"]
    assert record.exc_info is not None and "stopped by an exception" in record.getMessage()


def test_statistics_fields_and_reset() -> None:
    _, _, task = run_fake(
        6,
        {1: 0.5 * PERIOD_S, 3: 2.5 * PERIOD_S},
        lateness_window_cycles=100,
        percentile_refresh_cycles=2,
    )
    fast = task.statistics_fast()
    full = task.statistics()
    assert full.cycles == fast.cycles == 6
    assert full.missed_periods == 1
    assert full.execution_max_us == pytest.approx(2.5 * PERIOD_S * 1e6)
    assert full.execution_last_us == 0.0
    # Cycle 4 woke 1.5 periods after period 4's deadline and ran for period 5.
    assert full.lateness_max_us == pytest.approx(1.5 * PERIOD_S * 1e6)
    assert full.lateness_last_us == 0.0
    assert full.lateness_p50_us == 0.0
    assert full.lateness_p99_us == pytest.approx(1.5 * PERIOD_S * 1e6)
    # The cached percentiles were refreshed after cycle 6 (every 2 cycles): same samples.
    assert (fast.lateness_p50_us, fast.lateness_p99_us) == (
        full.lateness_p50_us,
        full.lateness_p99_us,
    )
    assert task.lateness_percentiles()["max"] == pytest.approx(1.5 * PERIOD_S * 1e6)
    task.reset_statistics()
    assert task.statistics().cycles == 0
    assert task.statistics().lateness_max_us == 0.0
    assert task.lateness_percentiles() == {"p50": 0.0, "p99": 0.0, "p99.9": 0.0, "max": 0.0}


def test_a_step_longer_than_the_period_is_logged_on_each_new_maximum(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.WARNING, logger="runtime.scheduler")
    run_fake(7, {1: 0.5 * PERIOD_S, 2: 1.5 * PERIOD_S, 4: 1.25 * PERIOD_S, 5: 2.5 * PERIOD_S})
    lines = [r.getMessage() for r in caplog.records if "longest step" in r.getMessage()]
    # The fake clock moves while the step works, not its CPU time: the CPU share is ~0.
    assert len(lines) == 2
    assert lines[0].startswith(
        f"cyclic task cyclic: longest step so far, {1.5 * PERIOD_S * 1e3:.2f} ms (0."
    )
    assert f"{2.5 * PERIOD_S * 1e3:.2f} ms" in lines[1]


def test_statistics_fast_inside_the_step_sees_this_cycle() -> None:
    seen: list[tuple[int, int]] = []
    task: CyclicTask

    def probe_step(tick: CycleTick) -> None:
        stats = task.statistics_fast()
        seen.append((stats.cycles, stats.missed_periods))

    fake = FakeTime()
    task = CyclicTask(PERIOD_S, probe_step, realtime=PLAIN, clock=fake.clock, sleep=fake.sleep)
    fake.oversleep_s = [PERIOD_S]
    task.start()
    deadline = time.monotonic() + JOIN_TIMEOUT_S
    while len(seen) < 3 and time.monotonic() < deadline:
        time.sleep(0.001)
    task.stop(JOIN_TIMEOUT_S)
    assert seen[:3] == [(1, 0), (2, 1), (3, 1)]


def test_gc_policy_freeze_disables_collection_while_moving() -> None:
    freeze = RealtimeConfig(priority=0, lock_memory=False, gc="freeze", spin_us=0.0)
    assert gc.isenabled()
    task = CyclicTask(PERIOD_S, lambda tick: None, realtime=freeze)
    task.set_moving(True)
    try:
        assert not gc.isenabled()
        assert gc.get_freeze_count() > 0
    finally:
        task.set_moving(False)
    assert gc.isenabled()
    # The frozen objects stay frozen at rest: no full collection of the whole heap.
    assert gc.get_freeze_count() > 0
    gc.unfreeze()


def test_constructor_rejects_bad_period_and_limit() -> None:
    with pytest.raises(ValueError, match="period_s"):
        CyclicTask(0.0, lambda tick: None)
    with pytest.raises(ValueError, match="overrun_limit"):
        CyclicTask(0.004, lambda tick: None, overrun_limit=-1)


# -- real time (generous bounds: 2 shared cores) ----------------------------------------------


def test_real_clock_runs_at_the_period_without_drift() -> None:
    period_s = 0.004
    cycles = 100
    ticks: list[CycleTick] = []
    done = threading.Event()

    def step(tick: CycleTick) -> None:
        ticks.append(tick)
        if len(ticks) == cycles:
            done.set()

    task = CyclicTask(period_s, step, realtime=RealtimeConfig(lock_memory=False, gc="normal"))
    began_s = time.monotonic()
    task.start()
    assert done.wait(JOIN_TIMEOUT_S)
    task.stop(JOIN_TIMEOUT_S)
    elapsed_s = ticks[cycles - 1].deadline_s - ticks[0].deadline_s
    # Absolute deadlines: the period index, not the executed count, tracks elapsed time.
    assert ticks[-1].deadline_s - ticks[0].deadline_s == pytest.approx(
        ticks[-1].period_index * period_s, abs=1e-9
    )
    assert cycles * period_s * 0.9 <= time.monotonic() - began_s
    assert elapsed_s < cycles * period_s * 1.5  # a few skipped periods on a loaded machine
    assert ticks[-1].period_index - ticks[-1].index == task.statistics().missed_periods
    assert all(t.lateness_s < period_s for t in ticks)


def test_real_clock_blocking_step_skips_without_burst() -> None:
    period_s = 0.004
    starts_s: list[float] = []
    ticks: list[CycleTick] = []
    done = threading.Event()

    def step(tick: CycleTick) -> None:
        starts_s.append(time.monotonic())
        ticks.append(tick)
        if tick.index == 5:
            time.sleep(3.5 * period_s)
        if tick.index == 15:
            done.set()

    task = CyclicTask(period_s, step, realtime=RealtimeConfig(lock_memory=False, gc="normal"))
    task.start()
    assert done.wait(JOIN_TIMEOUT_S)
    task.stop(JOIN_TIMEOUT_S)
    assert ticks[6].missed_periods >= 2
    assert task.statistics().missed_periods >= 2
    # Never two steps closer than half a period (less the few µs from wake to step): the
    # skipped periods are not replayed.
    gaps_s = [b - a for a, b in itertools.pairwise(starts_s)]
    assert min(gaps_s) > 0.45 * period_s


def test_stop_joins_and_a_blocked_step_times_out() -> None:
    release = threading.Event()
    entered = threading.Event()

    def blocking_step(tick: CycleTick) -> None:
        entered.set()
        release.wait(JOIN_TIMEOUT_S)

    task = CyclicTask(0.004, blocking_step, realtime=PLAIN)
    task.start()
    assert entered.wait(JOIN_TIMEOUT_S)
    with pytest.raises(CycleStopTimeout, match="still running"):
        task.stop(timeout_s=0.05)
    release.set()
    task.stop(JOIN_TIMEOUT_S)
    assert not task.running
    task.start()
    with pytest.raises(RuntimeError, match="already running"):
        task.start()
    task.stop(JOIN_TIMEOUT_S)
