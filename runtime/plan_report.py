"""Body of ``softmotion plan``: plan a curve offline, print its figures, write a trace or a plot.

Uses :mod:`planner.stream` on the whole curve, then measures the setpoints the way the planner
tests do (feed from consecutive setpoints, acceleration and jerk by differences, chord error
against the true curve), and compares with the no-look-ahead case of the paper (figures 8-11 of
Wang, Zhao, Lu, Liu, China Mechanical Engineering 23(3), 2012, 299-304).

Units: mm, s. Runs in the caller's thread; writes only to ``out`` and the given files.
"""

from __future__ import annotations

import csv
import time
from pathlib import Path
from typing import TextIO

import numpy as np

from planner.nurbs import NurbsCurve
from planner.stream import Path as PlannerPath
from planner.stream import plan_setpoints
from planner.types import Limits, SetpointBlock

#: Curve samples per period for the chord error.
CHORD_SAMPLES = 16


def _chord_errors(curve: NurbsCurve, u: np.ndarray, position_mm: np.ndarray) -> np.ndarray:
    frac = np.linspace(0.0, 1.0, CHORD_SAMPLES + 1)[1:-1]
    uu = (u[:-1, None] + np.diff(u)[:, None] * frac).ravel()
    pts = curve.evaluate(uu)[0].reshape(len(u) - 1, len(frac), -1)
    a, ab = position_mm[:-1, None, :], np.diff(position_mm, axis=0)[:, None, :]
    length2 = np.sum(ab * ab, axis=2)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(length2 > 0.0, np.clip(np.sum((pts - a) * ab, axis=2) / length2, 0, 1), 0)
    return np.linalg.norm(pts - (a + t[..., None] * ab), axis=2).max(axis=1)


def _measured(curve: NurbsCurve, block: SetpointBlock, period_s: float) -> dict[str, np.ndarray]:
    feed = np.linalg.norm(np.diff(block.position_mm, axis=0), axis=1) / period_s
    accel = np.diff(feed) / period_s
    return {
        "feed": feed,
        "accel": accel,
        "jerk": np.diff(accel) / period_s,
        "chord": _chord_errors(curve, block.u, block.position_mm),
    }


def run_plan(
    curve: NurbsCurve,
    limits: Limits,
    period_s: float,
    *,
    lookahead: bool,
    update: str,
    trace_path: Path | None,
    plot_path: Path | None,
    out: TextIO,
) -> None:
    """Plan ``curve``, print a summary to ``out``, optionally write a CSV trace and a plot.

    The trace has one row per period, header ``t,u,x,y,z,feed`` (no ``z`` for a planar curve;
    feed is the planned feed). The plot draws chord error, feed, acceleration and jerk over time
    with and without look-ahead (the paper's figures 8-11).

    :raises RuntimeError: if a plot is asked for and matplotlib is missing.
    """
    started = time.process_time()
    path = PlannerPath(curve, limits, period_s)
    block = plan_setpoints(path, limits, period_s, lookahead=lookahead, update=update)
    cpu_s = max(time.process_time() - started, 1e-9)
    m = _measured(curve, block, period_s)
    motion_s = (len(block) - 1) * period_s
    planned = np.diff(block.s_mm)
    realised = np.diff(path.arc.s_of_u(block.u))
    moving = planned > 1e-6
    fluctuation = np.abs(realised[moving] / planned[moving] - 1.0) if moving.any() else np.zeros(1)
    lines = [
        f"curve length          {path.length_mm:.3f} mm",
        f"look-ahead            {'on' if lookahead else 'off (eq. (4) alone)'}, update {update}",
        f"motion time           {motion_s:.3f} s ({len(block)} setpoints of {period_s * 1e3:g} ms)",
        f"max feed              {m['feed'].max(initial=0):.3f} mm/s (vmax {limits.vmax_mm_s:g})",
        f"max |tangential acc|  {np.abs(m['accel']).max(initial=0):.1f} mm/s^2 "
        f"(amax {limits.amax_mm_s2:g})",
        f"max |jerk|            {np.abs(m['jerk']).max(initial=0):.0f} mm/s^3 "
        f"(jmax {limits.jmax_mm_s3:g})",
        f"max chord error       {m['chord'].max(initial=0) * 1e3:.4f} um "
        f"(delta {limits.chord_error_mm * 1e3:g} um)",
        f"feed fluctuation      max {fluctuation.max() * 100:.2e} %, "
        f"mean {fluctuation.mean() * 100:.2e} % (arc length between setpoints vs plan)",
        f"planning time         {cpu_s:.3f} s CPU, real-time factor {motion_s / cpu_s:.0f}",
    ]
    out.write("\n".join(lines) + "\n")
    if trace_path is not None:
        _write_trace(trace_path, block, curve.dimension)
    if plot_path is not None:
        other = plan_setpoints(path, limits, period_s, lookahead=not lookahead, update=update)
        with_la, without = (block, other) if lookahead else (other, block)
        _plot(plot_path, curve, limits, period_s, with_la, without)


def _write_trace(trace_path: Path, block: SetpointBlock, dimension: int) -> None:
    axes = ["x", "y", "z"][:dimension]
    with open(trace_path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["t", "u", *axes, "feed"])
        for i in range(len(block)):
            writer.writerow(
                [
                    f"{block.t_s[i]:.6f}",
                    f"{block.u[i]:.12f}",
                    *(f"{x:.9f}" for x in block.position_mm[i]),
                    f"{block.feed_mm_s[i]:.6f}",
                ]
            )


def _plot(
    plot_path: Path,
    curve: NurbsCurve,
    limits: Limits,
    period_s: float,
    with_la: SetpointBlock,
    without: SetpointBlock,
) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise RuntimeError(
            "plot: matplotlib is not installed; install the plot extra "
            "(pip install softmotion[plot])"
        ) from exc
    rows = [
        ("chord error (um)", "chord", 1e3, limits.chord_error_mm * 1e3),
        ("feed (mm/s)", "feed", 1.0, limits.vmax_mm_s),
        ("acceleration (m/s^2)", "accel", 1e-3, limits.amax_mm_s2 * 1e-3),
        ("jerk (m/s^3)", "jerk", 1e-3, limits.jmax_mm_s3 * 1e-3),
    ]
    fig, axes = plt.subplots(4, 2, figsize=(11, 10), sharex="col")
    for col, (title, block) in enumerate(
        (("without look-ahead", without), ("with look-ahead", with_la))
    ):
        m = _measured(curve, block, period_s)
        for row, (label, key, scale, bound) in enumerate(rows):
            ax = axes[row, col]
            values = m[key] * scale
            ax.plot(block.t_s[: len(values)], values, lw=0.8)
            ax.axhline(bound, color="r", lw=0.6, ls="--")
            if key in ("accel", "jerk"):
                ax.axhline(-bound, color="r", lw=0.6, ls="--")
            ax.set_ylabel(label)
            if row == 0:
                ax.set_title(title)
        axes[-1, col].set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(plot_path, dpi=110)
    plt.close(fig)
