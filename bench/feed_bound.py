"""The feed limit of a curve on an adaptive arc-length grid, and the acceleration-limited bound.

For the benchmark (numpy only): the feed limit min(vmax, chord-error feed of eq. (3)) sampled on
a grid refined where it is low or changes fast and geometrically towards rest (the ends, cusps
and corners, where the tangent turns at once and the feed must be 0); the acceleration-limited
lower bound of the motion time on it (forward and backward v² passes, motion-planning.md §7).
The jerk-limited reference (bench/jerk_reference.py) solves on the same grid.

Units: mm, s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planner.arclength import ArcLengthTable
from planner.feed import chord_error_feed
from planner.nurbs import NurbsCurve

#: Grid spacing where the feed limit is high, mm, and the finest spacing, mm.
COARSE_MM, FINEST_MM = 0.1, 0.001
#: Grid spacing at most this fraction of a period's step at the local feed limit.
STEP_FRACTION = 0.5
#: Relative change of the feed limit across a grid interval above which it is halved.
LIMIT_CHANGE = 0.05


@dataclass(frozen=True)
class FeedLimitCurve:
    """The feed limit min(vmax, eq. (3)) sampled on an adaptive arc-length grid."""

    s_mm: np.ndarray
    v_limit_mm_s: np.ndarray
    curvature_peak: np.ndarray  # bool per node: a local maximum of curvature under vmax


def feed_limit_curve(
    curve: NurbsCurve, vmax: float, delta: float, period_s: float
) -> FeedLimitCurve:
    """Sample the feed limit on a grid refined where it is low or changes fast."""
    arc = ArcLengthTable(curve)

    def limit(s: np.ndarray) -> np.ndarray:
        kappa = curve.curvature(arc.u_of_s(s))
        return np.minimum(vmax, chord_error_feed(kappa, delta, period_s))

    s = np.linspace(0.0, arc.length_mm, int(np.ceil(arc.length_mm / COARSE_MM)) + 1)
    s = np.union1d(s, _stops_mm(curve, arc))
    v = limit(s)
    for _ in range(12):
        h = np.diff(s)
        low = np.minimum(v[:-1], v[1:])
        coarse = (h > FINEST_MM) & (
            (h > STEP_FRACTION * np.maximum(low, 1e-3) * period_s)
            | (np.abs(np.diff(v)) > LIMIT_CHANGE * np.maximum(low, 1e-3))
        )
        if not coarse.any():
            break
        mid = 0.5 * (s[:-1] + s[1:])[coarse]
        s = np.concatenate([s, mid])
        order = np.argsort(s)
        s = s[order]
        v = np.concatenate([v, limit(mid)])[order]
    v[np.isin(s, _stops_mm(curve, arc))] = 0.0
    # Rest (the ends, cusps): the motion leaves and meets it with the jerk limit over a few
    # micrometres, so the grid shrinks geometrically towards it.
    rest = np.flatnonzero(v < 1e-6 * vmax)
    rest = np.unique(np.concatenate([[0], rest, [len(s) - 1]]))
    offsets = COARSE_MM * 0.5 ** np.arange(1, 14)
    extra = np.concatenate([s[rest][:, None] - offsets, s[rest][:, None] + offsets]).ravel()
    extra = extra[(extra > 0.0) & (extra < s[-1])]
    s = np.concatenate([s, extra])
    order = np.argsort(s)
    s = s[order]
    v = np.concatenate([v, limit(extra)])[order]
    keep = np.concatenate([[True], np.diff(s) > 1e-9])
    s, v = s[keep], v[keep]
    v[np.isin(s, _stops_mm(curve, arc))] = 0.0
    inner = (v[1:-1] < v[:-2]) & (v[1:-1] <= v[2:]) & (v[1:-1] < vmax)
    peak = np.concatenate([[False], inner, [False]])
    return FeedLimitCurve(s, v, peak)


def _stops_mm(curve: NurbsCurve, arc: ArcLengthTable) -> np.ndarray:
    """Arc lengths where the tangent reverses or turns at once (cusps, corners): feed 0 there.

    Found where the tangents of neighbouring samples (4096 per knot span) turn by more than
    90 degrees; located by ternary search of the smallest |C'| between them.
    """
    breaks = curve.breakpoints
    u = np.unique(np.linspace(breaks[:-1], breaks[1:], 4097).ravel())
    d1 = curve.evaluate(u, order=1)[1]
    turn = np.flatnonzero(np.sum(d1[:-1] * d1[1:], axis=1) < 0.0)
    lo, hi = u[turn], u[turn + 1]
    for _ in range(80):
        a, b = lo + (hi - lo) / 3.0, hi - (hi - lo) / 3.0
        speed = np.linalg.norm(curve.evaluate(np.concatenate([a, b]), order=1)[1], axis=1)
        left = speed[: a.size] < speed[a.size :]
        lo, hi = np.where(left, lo, a), np.where(left, b, hi)
    return arc.s_of_u(0.5 * (lo + hi))


def time_s(s: np.ndarray, b: np.ndarray) -> float:
    v = np.sqrt(np.maximum(b, 0.0))
    mean = v[:-1] + v[1:]
    with np.errstate(divide="ignore"):
        return float(np.sum(np.where(mean > 0.0, 2.0 * np.diff(s) / mean, np.inf)))


def acceleration_bound_time_s(limit: FeedLimitCurve, amax: float) -> float:
    """Acceleration-limited lower bound on the same grid: forward and backward v² passes."""
    s, vlim = limit.s_mm, limit.v_limit_mm_s
    b = vlim**2
    two_a_s = 2.0 * amax * s
    # b_f(i) = min over j <= i of (b_j + 2A (s_i - s_j)), from rest at s_0: a running minimum.
    b[0] = b[-1] = 0.0
    forward = two_a_s + np.minimum.accumulate(b - two_a_s)
    backward = -two_a_s + np.minimum.accumulate((b + two_a_s)[::-1])[::-1]
    return time_s(s, np.minimum(forward, backward))
