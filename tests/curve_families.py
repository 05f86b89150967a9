"""Curve families the planner is judged on, built from seeds (shared by tests and the benchmark).

- ``paper``: Table 1 of the paper (configs/curves/paper.yaml).
- ``cusps``: planar cubic B-splines whose control polygon folds back on itself: an exact fold
  (the curve stops and reverses, C'(u) = 0, a cusp) or a fold offset sideways by about 0.7 mm
  (a near-cusp, radius of curvature about 0.02 mm), between free turns.
- ``loops``: cubic B-splines whose polygon keeps turning by 110-150 degrees a step, so the
  curve ties loops, some of them tight, planar or spatial.
- ``free``: free control polygons (points anywhere in a 60 mm box, degrees 1-5, planar or
  spatial, random weights and interior knots), which fold and loop freely.

Besides the families, :func:`walk_curve` builds long curves of any number of spans (smooth or
winding) for the streaming tests and the benchmark's first block and real-time factors.

Units: mm. Pure functions of their seed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from planner.nurbs import NurbsCurve

PAPER = Path(__file__).resolve().parents[1] / "configs" / "curves" / "paper.yaml"
#: Sideways offset of a near fold of a 10 mm polygon leg: radius about 0.019 d² / mm at the tip.
NEAR_FOLD_OFFSET_MM = 0.7


def paper_curve() -> NurbsCurve:
    return NurbsCurve.from_mapping(yaml.safe_load(PAPER.read_text()))


def _uniform_knots(points: int, degree: int) -> np.ndarray:
    inner = np.arange(1, points - degree, dtype=float)
    return np.concatenate([[0.0] * (degree + 1), inner, [float(points - degree)] * (degree + 1)])


def cusp_curve(seed: int, legs: int = 16, degree: int = 3) -> NurbsCurve:
    """A folding polygon: every other leg folds back (exactly, or offset sideways)."""
    rng = np.random.default_rng(seed)
    heading = rng.uniform(0.0, 2.0 * np.pi)
    points = [np.zeros(2)]
    for leg in range(legs):
        length = rng.uniform(8.0, 14.0)
        if leg % 2 == 1:
            heading += np.pi
            normal = np.array([-np.sin(heading), np.cos(heading)])
            exact = rng.uniform() < 0.4
            side = 0.0 if exact else rng.choice([-1.0, 1.0]) * NEAR_FOLD_OFFSET_MM
            # The fold's tip is the last point; the leg back starts beside it.
            points.append(points[-1] + side * normal)
        else:
            heading += rng.normal(0.0, 0.5)
        step = length * np.array([np.cos(heading), np.sin(heading)])
        points.append(points[-1] + step)
    pts = np.array(points)
    return NurbsCurve.from_arrays(degree, pts, _uniform_knots(len(pts), degree))


def loop_curve(seed: int, steps: int = 24, dim: int = 2, degree: int = 3) -> NurbsCurve:
    """A polygon turning by 110-150 degrees a step (alternating sense now and then)."""
    rng = np.random.default_rng(seed)
    heading, sense = 0.0, 1.0
    points = [np.zeros(dim)]
    for _ in range(steps):
        if rng.uniform() < 0.2:
            sense = -sense
        heading += sense * np.radians(rng.uniform(110.0, 150.0))
        step = rng.uniform(4.0, 12.0) * np.array([np.cos(heading), np.sin(heading)])
        if dim == 3:
            step = np.append(step, rng.normal(0.0, 2.0))
        points.append(points[-1] + step)
    pts = np.array(points)
    return NurbsCurve.from_arrays(degree, pts, _uniform_knots(len(pts), degree))


def free_curve(seed: int) -> NurbsCurve:
    """A free control polygon in a 60 mm box, degree 1-5, weights 0.3-3, random knots."""
    rng = np.random.default_rng(seed)
    while True:
        degree = int(rng.integers(1, 6))
        dim = int(rng.choice([2, 3]))
        n = int(rng.integers(degree + 2, degree + 7))
        points = rng.uniform(-30.0, 30.0, (n, dim))
        weights = rng.uniform(0.3, 3.0, n)
        interior = np.sort(rng.uniform(0.05, 0.95, n - degree - 1))
        if np.unique(interior).size == interior.size:
            break
    knots = np.concatenate([[0.0] * (degree + 1), interior, [1.0] * (degree + 1)])
    return NurbsCurve.from_arrays(degree, points, knots, weights)


def walk_curve(spans: int, seed: int, step_mm: float, turn_rad: float) -> NurbsCurve:
    """A planar cubic B-spline of ``spans`` uniform knot spans over a random walk of control
    points ``step_mm`` apart, whose heading turns by a normal deviate of ``turn_rad`` a step."""
    rng = np.random.default_rng(seed)
    n = spans + 3
    heading = np.cumsum(rng.normal(0.0, turn_rad, n))
    points = np.cumsum(np.c_[np.cos(heading), np.sin(heading)] * step_mm, axis=0)
    return NurbsCurve.from_arrays(3, points, _uniform_knots(n, 3))


def family(name: str, seeds: range) -> list[NurbsCurve]:
    """The curves of one family for the given seeds (``paper`` has one curve)."""
    if name == "paper":
        return [paper_curve()]
    build = {"cusps": cusp_curve, "loops": loop_curve, "free": free_curve}[name]
    return [build(seed) for seed in seeds]
