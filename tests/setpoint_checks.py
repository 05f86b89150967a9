"""Measurements on setpoints: realised feed, tangential acceleration and jerk, chord error.

Shared by the planner and runtime tests and the benchmark. Everything is measured on the
setpoints themselves, as a drive would see them:
- feed f_i = |p(i+1) - p(i)| / T (the chord between consecutive setpoints);
- acceleration a_i = (f(i+1) - f(i)) / T, jerk j_i = (a(i+1) - a(i)) / T;
- chord error of a period: the largest distance between the true curve C(u) for u between the
  two setpoints' parameters (sampled densely) and the chord joining the two setpoints.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planner.nurbs import NurbsCurve

#: Curve samples per period for the chord error.
CHORD_SAMPLES = 32


def realised_feed(position_mm: np.ndarray, period_s: float) -> np.ndarray:
    """Chord feed |p(i+1) - p(i)| / T of every period, mm/s."""
    return np.linalg.norm(np.diff(position_mm, axis=0), axis=1) / period_s


def differences(values: np.ndarray, period_s: float) -> np.ndarray:
    """(x(i+1) - x(i)) / T."""
    return np.diff(values) / period_s


def chord_errors(
    curve: NurbsCurve, u: np.ndarray, position_mm: np.ndarray, samples: int = CHORD_SAMPLES
) -> np.ndarray:
    """Chord error of every period, mm (0 for periods at rest)."""
    frac = np.linspace(0.0, 1.0, samples + 1)[1:-1]
    u0, u1 = u[:-1], u[1:]
    uu = (u0[:, None] + (u1 - u0)[:, None] * frac).ravel()
    pts = curve.evaluate(uu)[0].reshape(len(u0), len(frac), -1)
    a, b = position_mm[:-1, None, :], position_mm[1:, None, :]
    ab = b - a
    length2 = np.sum(ab * ab, axis=2)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.clip(np.sum((pts - a) * ab, axis=2) / length2, 0.0, 1.0)
    t = np.where(length2 > 0.0, t, 0.0)
    dist = np.linalg.norm(pts - (a + t[..., None] * ab), axis=2)
    return dist.max(axis=1) if dist.size else np.zeros(len(u0))


@dataclass(frozen=True)
class SetpointFigures:
    """Extremes measured on a setpoint sequence."""

    max_feed_mm_s: float
    max_accel_mm_s2: float
    max_jerk_mm_s3: float
    max_chord_error_mm: float
    end_error_mm: float
    motion_time_s: float
    rows: int


def measure(curve: NurbsCurve, u: np.ndarray, position_mm: np.ndarray, period_s: float):
    """:class:`SetpointFigures` of a complete setpoint sequence (start to rest)."""
    feed = realised_feed(position_mm, period_s)
    accel = differences(feed, period_s)
    jerk = differences(accel, period_s)
    chord = chord_errors(curve, u, position_mm)
    return SetpointFigures(
        max_feed_mm_s=float(feed.max(initial=0.0)),
        max_accel_mm_s2=float(np.abs(accel).max(initial=0.0)),
        max_jerk_mm_s3=float(np.abs(jerk).max(initial=0.0)),
        max_chord_error_mm=float(chord.max(initial=0.0)),
        end_error_mm=float(np.linalg.norm(position_mm[-1] - curve.end_point)),
        motion_time_s=(len(u) - 1) * period_s,
        rows=len(u),
    )


def acceleration_bound_time_s(
    curve: NurbsCurve, v_limit, vmax: float, amax: float, samples: int = 20001
) -> float:
    """Acceleration-limited lower bound of the motion time (motion-planning.md §7).

    On a fine grid of the arc length: v² = min(v_lim², v_prev² + 2 A ds) forward from rest, the
    same backward from the end, v = min of both; T = sum 2 ds / (v_i + v_i+1).

    :param v_limit: function u -> feed limit (same chord/limits as the plan, without vmax).
    """
    from planner.arclength import ArcLengthTable

    arc = ArcLengthTable(curve)
    s = np.linspace(0.0, arc.length_mm, samples)
    u = arc.u_of_s(s)
    vlim = np.minimum(vmax, v_limit(u))
    ds = np.diff(s)
    fwd = vlim.copy()
    fwd[0] = 0.0
    for i in range(1, len(s)):
        fwd[i] = min(vlim[i], np.sqrt(fwd[i - 1] ** 2 + 2.0 * amax * ds[i - 1]))
    bwd = vlim.copy()
    bwd[-1] = 0.0
    for i in range(len(s) - 2, -1, -1):
        bwd[i] = min(vlim[i], np.sqrt(bwd[i + 1] ** 2 + 2.0 * amax * ds[i]))
    v = np.minimum(fwd, bwd)
    return float(np.sum(2.0 * ds / (v[:-1] + v[1:])))
