"""Planner benchmark (not a test): prints real-time factors, time-optimality and feed fluctuation.

- Real-time factor: motion time / CPU time to prepare the path, plan and interpolate every
  setpoint (target >= 1000; the fastest of three runs or more, up to a second of CPU time),
  on the paper's curve, on a long smooth random curve and on a winding one whose feed limit
  keeps changing. The paper's curve moves for under 2 s, so the fixed cost of a plan
  (arc-length table, envelope, look-ahead, and the arc-length inversion of each batch of rows)
  dominates there.
- Motion time / acceleration-limited lower bound (forward-backward v² pass on a fine arc grid
  with the same vmax, chord-error and amax limits; motion-planning.md §7), per chord error.
  What separates the plan from the bound: the jerk limit (every speed change takes A/J longer,
  most visible at the start and end), and zero acceleration at sensitive points, so that where
  the feed limit keeps changing the plan follows it as a staircase of S-curves below it.
- Feed fluctuation of the parameter update, taylor2 (eq. (2)) against corrected: max and mean
  |realised / planned - 1|, with the realised step the arc length between consecutive setpoints
  (arc-based) and the chord between them (chord-based, shorter by (kappa L)²/24).

Run: .venv/bin/python bench/bench_planner.py
"""

from __future__ import annotations

import sys
import time
from pathlib import Path as FilePath

import numpy as np
import yaml

ROOT = FilePath(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import setpoint_checks as sc  # noqa: E402

from planner.feed import chord_error_feed  # noqa: E402
from planner.nurbs import NurbsCurve  # noqa: E402
from planner.stream import Path, stream_setpoints  # noqa: E402
from planner.types import Limits, SetpointBlock  # noqa: E402

T = 0.004
#: Complete plans timed per real-time factor, at least, and CPU time after which no more are
#: started; the fastest counts (other load only slows a run, and a plan of a few ms is easily
#: hit by it).
REPEATS, REPEAT_BUDGET_S = 3, 1.0


def limits(delta_mm: float) -> Limits:
    return Limits(vmax_mm_s=100.0, amax_mm_s2=1000.0, jmax_mm_s3=20000.0, chord_error_mm=delta_mm)


def paper_curve() -> NurbsCurve:
    return NurbsCurve.from_mapping(yaml.safe_load((ROOT / "configs/curves/paper.yaml").read_text()))


def random_curve(
    spans: int, seed: int = 7, turn_rad: float = 0.12, step_mm: float = 15.0
) -> NurbsCurve:
    rng = np.random.default_rng(seed)
    n = spans + 3
    heading = np.cumsum(rng.normal(0.0, turn_rad, n))
    points = np.cumsum(np.c_[np.cos(heading), np.sin(heading)] * step_mm, axis=0)
    knots = np.concatenate([[0.0] * 4, np.arange(1, n - 3), [n - 3.0] * 4])
    return NurbsCurve.from_arrays(3, points, knots)


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


def main() -> None:
    curve = paper_curve()
    print("Real-time factor (motion time / CPU time to prepare, plan and interpolate)")
    print(
        f"{'curve':32s} {'spans':>6s} {'length mm':>10s} {'motion s':>9s} {'CPU s':>7s} {'RT':>7s}"
    )
    for name, c in (
        ("paper, delta 1 um", curve),
        ("random smooth, delta 1 um", random_curve(2000)),
        ("random winding, delta 1 um", random_curve(1000, seed=3, turn_rad=0.5, step_mm=3.0)),
    ):
        path, block, cpu = timed_plan(c, limits(1e-3), repeats=REPEATS, budget_s=REPEAT_BUDGET_S)
        motion = (len(block) - 1) * T
        print(
            f"{name:32s} {len(c.breakpoints) - 1:6d} {path.length_mm:10.1f} {motion:9.2f} "
            f"{cpu:7.3f} {motion / cpu:7.0f}"
        )
    print()
    print("Paper curve: motion time / acceleration-limited bound (same vmax, chord, amax)")
    print(
        f"{'delta um':>8s} {'motion s':>9s} {'bound s':>8s} {'ratio':>6s} "
        f"{'feed':>7s} {'|a|':>7s} {'|j|':>8s} {'chord um':>9s}"
    )
    for delta in (1e-4, 5e-4, 1e-3):
        _, block, _ = timed_plan(curve, limits(delta))
        fig = sc.measure(curve, block.u, block.position_mm, T)
        bound = sc.acceleration_bound_time_s(
            curve, lambda u, d=delta: chord_error_feed(curve.curvature(u), d, T), 100.0, 1000.0
        )
        print(
            f"{delta * 1e3:8.1f} {fig.motion_time_s:9.3f} {bound:8.3f} "
            f"{fig.motion_time_s / bound:6.3f} {fig.max_feed_mm_s:7.2f} "
            f"{fig.max_accel_mm_s2:7.1f} {fig.max_jerk_mm_s3:8.0f} "
            f"{fig.max_chord_error_mm * 1e3:9.4f}"
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
