"""Dilation of a sampled feed limit: each sample lowered to the limits a step from it reaches.

A setpoint's step of w T from s_i (w its feed, T the period) spans [s_i - w T, s_i + w T] at
most; the limits that depend on the steps either side of a setpoint (the chord-deficit jerk,
the accelerations) must hold over it. With the limit f linear between samples, the largest
such w at each sample is the infimum over x >= 0 of max(f(s_i +- x), x / T), found by
bisection over a sparse table of range minima: O(n log n), whatever the number of samples
within a step. Used by :class:`planner.envelope.FeedEnvelope`.

Units: s in mm, feeds in mm/s, reach in s. Pure computation on numpy arrays.
"""

from __future__ import annotations

import numpy as np


def reach_lowered(
    s: np.ndarray, f: np.ndarray, own: np.ndarray, reach_s: float, cap_mm_s: float
) -> np.ndarray:
    """The largest w <= ``own`` at each sample with w <= f(s_i +- x) for every x up to
    w ``reach_s`` (f linear between samples), or inf where nothing within reach is lower;
    a sample's reach is taken at no more than ``cap_mm_s`` (the highest feed any override
    plans).

    That is the infimum over x >= 0, ahead and behind, of max(f(s_i +- x), x / reach_s):
    on each grid interval it is reached at an end or where f crosses x / reach_s. Using
    the samples alone would leave a sawtooth of spurious minima (sensitive points) wherever
    the limit falls steeply. A corner's zero constrains nothing (the plan stops on it).
    """
    ahead = _reachable(s, f, own, reach_s, cap_mm_s)
    behind = _reachable(-s[::-1], f[::-1], own[::-1], reach_s, cap_mm_s)[::-1]
    return np.minimum(ahead, behind)


def _reachable(
    s: np.ndarray, v: np.ndarray, own: np.ndarray, reach_s: float, cap_mm_s: float
) -> np.ndarray:
    """inf over x >= 0 of max(f(s_i + x), x / reach_s) for increasing s, where it is below
    the sample's own limit and the override cap.

    Up to the first crossing x* of f below the line x / reach_s, the value is f itself;
    beyond it, at least x* / reach_s, which f reaches at x*: so it is the lowest sample of
    f before the crossing, or x* / reach_s. The crossing is found by bisection over the
    samples with a sparse table of range minima (:class:`RangeMinima`) of
    f(s_k) - s_k / reach_s, whose minimum over (i, k] falls to -s_i / reach_s or below once
    f has met the line by sample k: O(n log n) whatever the samples within a step (a curve
    of 185 spans in 1.3 mm, 20,000 samples each reaching 12,000 others, took 12 s with
    every pair tried).
    """
    n = len(s)
    masked = np.where(v > 0.0, v, np.inf)
    # Each sample's reach: the samples whose interval starts within reach at its own limit
    # (a longer step exceeds that limit whatever it meets), up to the next stop: the motion
    # rests there, so no step crosses it. (Beyond it, each sample would be held to its
    # distance from the stop over the reach, a limit that vanishes at the stop: the motion
    # could never leave it.)
    reach_mm = reach_s * np.minimum(own, cap_mm_s)
    reach = np.searchsorted(s, s + reach_mm, side="right")
    rows = np.arange(n)
    stops = np.append(np.flatnonzero(v <= 0.0), n - 1)
    next_stop = stops[np.searchsorted(stops, rows, side="right").clip(max=stops.size - 1)]
    last = np.minimum(reach, next_stop)  # the last sample an interval in reach ends on
    out = np.full(n, np.inf)
    # Only the rows that reach a sample below their own limit and the override cap: on
    # smooth stretches no row does, and f stays above the line on the whole reach.
    rows = np.flatnonzero(last > rows)
    if rows.size == 0:
        return out
    longest = int((last[rows] - rows).max())
    masked_minima = RangeMinima(masked, longest)
    lowest = masked_minima.query(rows + 1, last[rows])
    lowers = lowest < np.minimum(own[rows], cap_mm_s)
    rows, lowest = rows[lowers], lowest[lowers]
    if rows.size == 0:
        return out
    threshold = -s[rows] / reach_s
    gap_minima = RangeMinima(masked - s / reach_s, longest)
    crosses = gap_minima.query(rows + 1, last[rows]) <= threshold
    out[rows[~crosses]] = lowest[~crosses]  # f stays above the line on the whole reach
    rows, threshold = rows[crosses], threshold[crosses]
    if rows.size == 0:
        return out
    # The crossing's sample k, the first whose minimum over (row, k] is at the threshold or
    # below: lo < k <= hi.
    lo, hi = rows.copy(), last[rows]
    while True:
        searching = hi - lo > 1
        if not searching.any():
            break
        mid = np.where(searching, (lo + hi) // 2, hi)  # found: hi again, which holds
        met = gap_minima.query(rows + 1, mid) <= threshold
        hi = np.where(met, mid, hi)
        lo = np.where(met, lo, mid)
    k = hi
    j = k - 1  # the interval [s_j, s_k] where f meets the line
    start_gap, end_gap = s[j] - s[rows], s[k] - s[rows]
    value = np.maximum(masked[k], end_gap / reach_s)
    h = s[k] - s[j]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        slope = (v[k] - v[j]) / h
        x = (v[j] - slope * start_gap) / (1.0 / reach_s - slope)  # f(s_i + x) = x / reach
    crossing = (
        (v[j] > 0.0)
        & (v[k] > 0.0)
        & (h > 0.0)
        & (slope < 1.0 / reach_s)
        & (x >= start_gap)
        & (x <= end_gap)
    )
    value = np.where(crossing, np.minimum(value, x / reach_s), value)
    before = j > rows  # samples strictly between the row and the crossing's interval
    if before.any():
        value[before] = np.minimum(value[before], masked_minima.query(rows[before] + 1, j[before]))
    out[rows] = value
    return out


class RangeMinima:
    """Minima of ``values`` over index ranges [lo, hi] up to ``longest`` long, in O(1) per
    range after O(n log longest) (a sparse table: row l holds the minima of the ranges 2^l
    long, inf past the end)."""

    def __init__(self, values: np.ndarray, longest: int) -> None:
        n = len(values)
        levels = max(int(min(longest, n)).bit_length(), 1)
        table = np.full((levels, n), np.inf)
        table[0] = values
        for level in range(1, levels):
            width = 1 << (level - 1)
            table[level, : n - width] = np.minimum(
                table[level - 1, : n - width], table[level - 1, width:]
            )
        self._table = table

    def query(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """min(values[lo:hi + 1]) for each pair, lo <= hi."""
        level = np.log2(hi - lo + 1).astype(int)
        return np.minimum(self._table[level, lo], self._table[level, hi - (1 << level) + 1])
