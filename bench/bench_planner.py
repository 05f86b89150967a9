"""Planner benchmark (not a test): time-optimality, first block, real-time factors, re-plans.

- Motion time per curve family (tests/curve_families.py: the paper's curve, folding
  polygons with cusps and 0.02 mm near-cusps, loops, free control polygons), delta 1 µm and the
  paper's limits, against the acceleration-limited lower bound and against a jerk-limited
  reference (bench/jerk_reference.py: a sequential linear program in v², zero acceleration at
  the curvature maxima like the planner's sensitive points; needs scipy, the ``bench`` extra),
  both on one adaptive grid with cusps and corners as stops. Measured limits on the setpoints.
- The paper's curve at delta 0.1, 0.5, 1 µm against both.
- First block of a 1,000- and a 100,000-span curve in the same run: CPU time from Path() to the
  first block, and the peak of traced memory over it (the curve itself is built before).
- Real-time factor: motion time / CPU time to prepare the path, plan and interpolate every
  setpoint (the fastest of three runs or more, up to a second of CPU time), and the cold single
  plan ``softmotion plan`` prints (one run, Path() and the plan, as it times them); on the
  paper's curve, long smooth and winding random curves, and noisy measured points on 7 µm
  knot spans.
- Re-plan from a mid-path motion state (a feed override splice: s, feed and acceleration
  non-zero): CPU time from the call to the first block, on the paper's curve and on a
  2,000-span curve.
- Feed fluctuation of the parameter update, taylor2 (eq. (2)) against corrected.

Run: .venv/bin/python bench/bench_planner.py  (pip install -e .[bench] for the reference)
"""

from __future__ import annotations

import sys
import time
import tracemalloc
from pathlib import Path as FilePath

import numpy as np
import yaml

ROOT = FilePath(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import curve_families as cf  # noqa: E402
import feed_bound as fb  # noqa: E402
import setpoint_checks as sc  # noqa: E402

from planner.nurbs import NurbsCurve  # noqa: E402
from planner.stream import (  # noqa: E402
    Path,
    braking_end_from_rows,
    plan_setpoints,
    stream_setpoints,
)
from planner.types import Limits, SetpointBlock  # noqa: E402

try:
    import jerk_reference as ref
except ImportError:  # scipy missing: the bound alone
    ref = None

T = 0.004
#: Complete plans timed per real-time factor, at least, and CPU time after which no more are
#: started; the fastest counts (other load only slows a run, and a plan of a few ms is easily
#: hit by it).
REPEATS, REPEAT_BUDGET_S = 3, 1.0


def limits(delta_mm: float) -> Limits:
    return Limits(vmax_mm_s=100.0, amax_mm_s2=1000.0, jmax_mm_s3=20000.0, chord_error_mm=delta_mm)


def paper_curve() -> NurbsCurve:
    return NurbsCurve.from_mapping(yaml.safe_load((ROOT / "configs/curves/paper.yaml").read_text()))


#: Curves per family in the time-optimality table.
FAMILY_SEEDS = range(4)


def random_curve(
    spans: int, seed: int = 7, turn_rad: float = 0.12, step_mm: float = 15.0
) -> NurbsCurve:
    return cf.walk_curve(spans, seed=seed, step_mm=step_mm, turn_rad=turn_rad)


def dense_curve(points: int = 190, length_mm: float = 1.33, noise_mm: float = 5e-4) -> NurbsCurve:
    """Measured points with noise, as a scanner gives them: degree 5 through ``points``
    control points along a line ``length_mm`` long, each off it by Gaussian noise (7 µm knot
    spans, curvature peaks a micrometre wide)."""
    rng = np.random.default_rng(0)
    control = np.c_[np.linspace(0.0, length_mm, points), rng.normal(0.0, noise_mm, points)]
    knots = np.concatenate([[0.0] * 6, np.arange(1, points - 5), [points - 5.0] * 6])
    return NurbsCurve.from_arrays(5, control, knots)


def timed_plan(
    curve: NurbsCurve,
    lim: Limits,
    update: str = "corrected",
    repeats: int = 1,
    budget_s: float = 0.0,
):
    """Path, all setpoints and the CPU time of the fastest of ``repeats`` complete plans, or
    more while their total stays under ``budget_s``."""
    best, total, runs = float("inf"), 0.0, 0
    while runs < repeats or total < budget_s:
        started = time.process_time()
        path = Path(curve, lim, T)
        blocks = list(stream_setpoints(path, lim, T, update=update))
        elapsed = time.process_time() - started
        best, total, runs = min(best, elapsed), total + elapsed, runs + 1
    return path, SetpointBlock.concatenate(blocks), best


def fluctuation(path: Path, block: SetpointBlock) -> tuple[float, float, float, float]:
    planned = np.diff(block.s_mm)
    moving = planned > 1e-3 * T * 100.0
    arc = np.abs(np.diff(path.arc.s_of_u(block.u))[moving] / planned[moving] - 1.0)
    chord = np.linalg.norm(np.diff(block.position_mm, axis=0), axis=1)[moving]
    chord_f = np.abs(chord / planned[moving] - 1.0)
    return arc.max(), arc.mean(), chord_f.max(), chord_f.mean()


def optimality_row(name: str, curve: NurbsCurve, delta: float) -> None:
    _, block, _ = timed_plan(curve, limits(delta))
    fig = sc.measure(curve, block.u, block.position_mm, T)
    limit = fb.feed_limit_curve(curve, 100.0, delta, T)
    bound = fb.acceleration_bound_time_s(limit, 1000.0)
    line = (
        f"{name:14s} {delta * 1e3:5.1f} {fig.motion_time_s:8.3f} {bound:8.3f} "
        f"{fig.motion_time_s / bound:6.3f}"
    )
    if ref is not None:
        reference, _ = ref.jerk_limited_time_s(limit, 1000.0, 20000.0, zero_accel_at_peaks=True)
        line += f" {reference:8.3f} {fig.motion_time_s / reference:6.3f}"
    else:
        line += f" {'-':>8s} {'-':>6s}"
    print(
        f"{line} {fig.max_feed_mm_s:7.2f} {fig.max_accel_mm_s2:7.1f} {fig.max_jerk_mm_s3:8.0f} "
        f"{fig.max_chord_error_mm / delta:6.3f}"
    )


def first_block(curve: NurbsCurve) -> tuple[float, float]:
    """CPU time (s) and peak traced memory (MB) from Path() to the first block."""
    tracemalloc.start()
    started = time.process_time()
    path = Path(curve, limits(1e-3), T)
    next(stream_setpoints(path, limits(1e-3), T))
    elapsed = time.process_time() - started
    peak = tracemalloc.get_traced_memory()[1] / 1e6
    tracemalloc.stop()
    return elapsed, peak


def replan_first_block_s(curve: NurbsCurve, ratio: float = 1.2) -> float:
    """CPU time from a re-plan call at a mid-path state (override) to its first block."""
    lim = limits(1e-3)
    path = Path(curve, lim, T)
    plan = plan_setpoints(path, lim, T)
    # Mid-path, where the motion accelerates (a re-plan never starts on a braking row).
    row = len(plan) // 2 + int(np.argmax(plan.accel_mm_s2[len(plan) // 2 :] > 0.0))
    state = plan.state(row)
    best = float("inf")
    for _ in range(REPEATS):
        started = time.process_time()
        next(stream_setpoints(path, lim.with_feed_override(ratio), T, start=state))
        best = min(best, time.process_time() - started)
    return best


def replan_first_blocks_ms(curves: list[NurbsCurve], lim: Limits, step: int = 40) -> list[float]:
    """CPU times (ms) from re-plan calls at rows of each curve's plan to their first blocks,
    in order along the path, as a feed override knob turned now and then would ask for them
    (each re-plan starts warm from the points the plans before it found). Rows that brake to
    a rest are left out: the planner process re-plans from that rest (a plan of its own)."""
    times_ms = []
    for curve in curves:
        path = Path(curve, lim, T)
        plan = plan_setpoints(path, lim, T)
        for row in range(1, len(plan) - 1, step):
            end = braking_end_from_rows(plan.feed_mm_s[row:], plan.accel_mm_s2[row:], T)
            if end is not None and end.feed_mm_s == 0.0:
                continue
            for ratio in (0.8, 1.2):
                started = time.process_time()
                next(
                    stream_setpoints(
                        path,
                        lim.with_feed_override(ratio),
                        T,
                        start=plan.state(row),
                        braking_end_mm_s=None if end is None else end.feed_mm_s,
                        block_periods=64,
                    )
                )
                times_ms.append((time.process_time() - started) * 1e3)
    return times_ms


def main() -> None:
    curve = paper_curve()
    print("Motion time against the acceleration-limited bound and the jerk-limited reference")
    print("(delta in um; |a|, |j| and chord error / delta measured on the setpoints)")
    print(
        f"{'curve':14s} {'delta':>5s} {'motion':>8s} {'bound':>8s} {'/bound':>6s} "
        f"{'ref':>8s} {'/ref':>6s} {'feed':>7s} {'|a|':>7s} {'|j|':>8s} {'chord':>6s}"
    )
    for delta in (1e-4, 5e-4, 1e-3):
        optimality_row("paper", curve, delta)
    for delta in (1e-3, 1e-4):
        for family in ("cusps", "loops", "free"):
            for seed, c in zip(FAMILY_SEEDS, cf.family(family, FAMILY_SEEDS), strict=True):
                optimality_row(f"{family} {seed}", c, delta)
    print()
    print("First block: CPU time from Path() to the first block, peak traced memory over it")
    print(f"{'spans':>8s} {'curve build s':>14s} {'first block s':>14s} {'peak MB':>8s}")
    figures = {}
    for spans in (1_000, 100_000):
        started = time.process_time()
        c = random_curve(spans, seed=3, turn_rad=0.15, step_mm=2.0)
        built = time.process_time() - started
        figures[spans] = first_block(c)
        print(f"{spans:8d} {built:14.3f} {figures[spans][0]:14.3f} {figures[spans][1]:8.1f}")
    print(
        f"ratio 100,000 / 1,000: time {figures[100_000][0] / figures[1_000][0]:.2f}, "
        f"memory growth {figures[100_000][1] - figures[1_000][1]:+.1f} MB"
    )
    print()
    print("Real-time factor (motion time / CPU time to prepare, plan and interpolate)")
    print(
        f"{'curve':28s} {'spans':>6s} {'length mm':>10s} {'motion s':>9s} {'CPU s':>7s} "
        f"{'RT':>7s} {'cold RT':>8s}"
    )
    for name, c in (
        ("paper, delta 1 um", curve),
        ("random smooth, delta 1 um", random_curve(2000)),
        ("random winding, delta 1 um", random_curve(1000, seed=3, turn_rad=0.5, step_mm=3.0)),
        ("dense noisy points, delta 1 um", dense_curve()),
    ):
        _, _, cold = timed_plan(c, limits(1e-3))
        path, block, cpu = timed_plan(c, limits(1e-3), repeats=REPEATS, budget_s=REPEAT_BUDGET_S)
        motion = (len(block) - 1) * T
        print(
            f"{name:28s} {len(c.breakpoints) - 1:6d} {path.length_mm:10.1f} {motion:9.2f} "
            f"{cpu:7.3f} {motion / cpu:7.0f} {motion / cold:8.0f}"
        )
    print()
    print(
        "Re-plan from a mid-path state (override 120 %): CPU time from the call to the first block"
    )
    for name, c in (("paper", curve), ("random smooth, 2000 spans", random_curve(2000))):
        print(f"{name:28s} {replan_first_block_s(c) * 1e3:7.2f} ms")
    print()
    print(
        "Re-plans from every 40th row of two curves per family (override 80 and 120 %, after "
        "the re-plans before): CPU time to the first block, ms"
    )
    print(
        f"{'family':8s} {'delta':>5s} {'plans':>6s} {'p50':>6s} {'p90':>6s} {'p99':>6s} {'max':>6s}"
    )
    for delta in (1e-3, 1e-4):
        for family in ("cusps", "loops", "free"):
            times_ms = replan_first_blocks_ms(cf.family(family, range(2)), limits(delta))
            p50, p90, p99 = np.percentile(times_ms, [50, 90, 99])
            print(
                f"{family:8s} {delta * 1e3:5.1f} {len(times_ms):6d} {p50:6.2f} {p90:6.2f} "
                f"{p99:6.2f} {max(times_ms):6.2f}"
            )
    print()
    print("Feed fluctuation |realised/planned - 1| on the paper curve, delta 1 um")
    print(
        f"{'update':10s} {'arc max':>10s} {'arc mean':>10s} {'chord max':>10s} {'chord mean':>10s}"
    )
    for update in ("taylor2", "corrected"):
        path, block, _ = timed_plan(curve, limits(1e-3), update)
        a_max, a_mean, c_max, c_mean = fluctuation(path, block)
        print(f"{update:10s} {a_max:10.2e} {a_mean:10.2e} {c_max:10.2e} {c_mean:10.2e}")


if __name__ == "__main__":
    main()
