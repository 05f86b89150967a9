"""Cycle lateness benchmark: how late the cyclic thread wakes, bare and with the runtime's work.

Prints one table row per variant: lateness (wake time minus the deadline of the first period
due, see runtime/scheduler.py) p50, p99, p99.9 and max in µs over every executed cycle of a run
of ``--cycles`` periods, the cycles executed and the periods skipped. Variants:

- (a) the bare loop: a :class:`runtime.scheduler.CyclicTask` whose step does nothing, so it only
  sleeps (and spins ``spin_us``) to the same absolute deadlines as the runtime, under the
  default scheduler and under the runtime's real-time settings (SCHED_FIFO 80, mlockall, GIL
  switch interval 0.5 ms); then with a CPU-bound Python thread beside it (a proxy for the
  planner worker) with and without SCHED_FIFO and the 0.5 ms switch interval, to show the GIL.
- (b) the runtime's cycle and (c) the same with the planner worker busy on a long curve, both
  through ``bench/runtime_loop.py`` (the simulated machine running a long curve).
  The ratio p99(b) / p99(a, real-time settings) is printed.

Run: ``.venv/bin/python bench/bench_cycle.py [--cycles 10000] [--period-ms 4]`` (root, or
CAP_SYS_NICE and CAP_IPC_LOCK, for the real-time settings; refused ones are reported). Each
variant takes cycles x period (40 s at the defaults). Figures depend on the kernel, the host
and whatever else runs: this is a measurement, not a test.
"""

from __future__ import annotations

import argparse
import sys
import threading
from dataclasses import dataclass

from runtime.config import RealtimeConfig
from runtime.realtime import SWITCH_INTERVAL_S
from runtime.scheduler import CycleTick, CyclicTask

DEFAULT_SCHEDULER = RealtimeConfig(priority=0, cpu=None, lock_memory=False, gc="normal")
REALTIME = RealtimeConfig(priority=80, cpu=None, lock_memory=True, gc="normal")
PYTHON_SWITCH_INTERVAL_S = 0.005


@dataclass(frozen=True)
class Variant:
    label: str
    realtime: RealtimeConfig
    switch_interval_s: float
    cpu_bound_thread: bool


BARE_VARIANTS = (
    Variant(
        "a  bare, SCHED_OTHER, switch 5 ms", DEFAULT_SCHEDULER, PYTHON_SWITCH_INTERVAL_S, False
    ),
    Variant("a  bare, FIFO 80 + mlockall, switch 0.5 ms", REALTIME, SWITCH_INTERVAL_S, False),
    Variant(
        "a' + CPU thread, SCHED_OTHER, switch 5 ms",
        DEFAULT_SCHEDULER,
        PYTHON_SWITCH_INTERVAL_S,
        True,
    ),
    Variant(
        "a' + CPU thread, SCHED_OTHER, switch 0.5 ms", DEFAULT_SCHEDULER, SWITCH_INTERVAL_S, True
    ),
    Variant(
        "a' + CPU thread, FIFO 80 + mlockall, switch 5 ms", REALTIME, PYTHON_SWITCH_INTERVAL_S, True
    ),
    Variant(
        "a' + CPU thread, FIFO 80 + mlockall, switch 0.5 ms", REALTIME, SWITCH_INTERVAL_S, True
    ),
)

#: The bare variant with the runtime's settings, the reference for the ratio p99(b) / p99(a).
REFERENCE_LABEL = BARE_VARIANTS[1].label


def _burn_cpu(stop: threading.Event) -> None:
    """Pure-Python arithmetic holding the GIL between eval-loop switch points, like planning."""
    total = 0.0
    while not stop.is_set():
        for i in range(1000):
            total += i * 0.5


def run_bare(variant: Variant, cycles: int, period_s: float) -> dict[str, float]:
    done = threading.Event()

    def step(tick: CycleTick) -> None:
        if tick.period_index + 1 >= cycles:
            done.set()

    task = CyclicTask(
        period_s,
        step,
        realtime=variant.realtime,
        overrun_limit=cycles,
        name="bench",
        lateness_window_cycles=cycles,
        switch_interval_s=variant.switch_interval_s,
    )
    stop_burner = threading.Event()
    burner = threading.Thread(target=_burn_cpu, args=(stop_burner,), daemon=True)
    if variant.cpu_bound_thread:
        burner.start()
    try:
        task.start()
        done.wait()
        task.stop()
    finally:
        stop_burner.set()
        if variant.cpu_bound_thread:
            burner.join()
    refused = [line for line in task.realtime_report if "not applied" in line]
    for line in refused:
        print(f"    {variant.label}: {line}", file=sys.stderr)
    figures = task.lateness_percentiles()
    figures["missed_periods"] = task.statistics().missed_periods
    figures["cycles"] = task.statistics().cycles
    return figures


def format_row(label: str, figures: dict[str, float] | None) -> str:
    if figures is None:
        return f"{label:<52} {'not available':>61}"
    return (
        f"{label:<52} {figures['p50']:>9.1f} {figures['p99']:>9.1f} {figures['p99.9']:>10.1f}"
        f" {figures['max']:>10.1f} {int(figures['cycles']):>8d}"
        f" {int(figures['missed_periods']):>8d}"
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=10_000, help="periods per variant")
    parser.add_argument("--period-ms", type=float, default=4.0)
    args = parser.parse_args(argv)
    period_s = args.period_ms / 1000.0

    print(
        f"cycle lateness, {args.cycles} periods of {args.period_ms:g} ms per variant "
        f"(µs; cycles = executed, missed = periods skipped)"
    )
    print(
        f"{'variant':<52} {'p50':>9} {'p99':>9} {'p99.9':>10} {'max':>10} {'cycles':>8}"
        f" {'missed':>8}"
    )
    results: dict[str, dict[str, float] | None] = {}
    for variant in BARE_VARIANTS:
        results[variant.label] = run_bare(variant, args.cycles, period_s)
        print(format_row(variant.label, results[variant.label]), flush=True)

    from runtime_loop import run_runtime_loop

    for label, planner_busy in (
        ("b  runtime loop", False),
        ("c  runtime loop, planner busy", True),
    ):
        figures = run_runtime_loop(args.cycles, planner_busy=planner_busy)
        results[label] = figures
        print(format_row(label, figures), flush=True)

    reference = results[REFERENCE_LABEL]
    runtime_figures = results["b  runtime loop"]
    if reference is not None and runtime_figures is not None and reference["p99"] > 0:
        print(
            f"p99(b) / p99(a, real-time settings) = {runtime_figures['p99'] / reference['p99']:.2f}"
        )
    else:
        print("p99(b) / p99(a, real-time settings): not available")


if __name__ == "__main__":
    main()
