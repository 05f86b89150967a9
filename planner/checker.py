"""The look-ahead's check: a segment's planned feed against the feed limit along the arc length.

Beyond the paper (motion-planning.md §9 row 6): every planned segment is sampled every half
period and compared with the envelope (:mod:`planner.envelope`), linear between its samples;
segments whose highest feed is below the lowest limit they span pass without sampling.

Units: s in mm, feeds mm/s. Pure computation; one checker per window, not thread-safe.
"""

from __future__ import annotations

import numpy as np

from planner.envelope import range_minima
from planner.profiles import PhaseTrain
from planner.window import PlanLimits

#: Relative slack of the feed-limit check.
CHECK_SLACK = 1e-9


class Checker:
    """Compares a segment's planned feed with the envelope on the arc length."""

    def __init__(self, s_env: np.ndarray, v_env: np.ndarray, lim: PlanLimits) -> None:
        # A sharp corner's zero is a sensitive point where the plan stops; interpolating towards
        # it would ask for a linear approach to rest, which no jerk-limited stop can follow.
        moving = v_env > 0.0
        if moving.sum() >= 2:
            s_env, v_env = s_env[moving], v_env[moving]
        self.s_env, self.v_env, self.lim = s_env, v_env, lim
        # The limits with a sentinel after the last, so that a range may end at len(v_env).
        self._v_padded = np.append(v_env, np.inf)

    def interior_min(self, s0: float, s1: float) -> float:
        """The lowest limit over [s0, s1]."""
        return float(self._interior_mins(np.array([s0]), np.array([s1]))[0])

    def slope(self, s_point: float, half_width_mm: float) -> float:
        """Slope dv_limit/ds of the limit at s_point, over +-half_width_mm, in 1/s."""
        h = max(half_width_mm, 1e-6)
        lo, hi = np.interp([s_point - h, s_point + h], self.s_env, self.v_env)
        return float((hi - lo) / (2.0 * h))

    def end_cap(
        self, s_point: float, s_lo: float, s_hi: float, v_limit: float, accel: float = 0.0
    ) -> float:
        """Highest feed at most ``v_limit`` for a point at s_point between s_lo and s_hi where
        the plan has acceleration ``accel``, as far as the limit around it allows.

        A time tau after the point the plan's feed is at least v + a tau - drop, where drop is
        the jerk-limited departure from that line (J tau²/2 while the acceleration falls from
        a to -A, then linear), and tau before it at least v - a tau - drop with A - a in place
        of A + a; where the limit rises towards the point or falls away from it faster than
        that, a point capped at the limit itself would be exceeded next to it by every plan.
        With tau = (s - s_point) / v, the cap is min(limit(s) - a tau + drop(|tau|)), which
        holds as well for the lower cap it gives. With a = 0 this is the cap of a sensitive
        point (zero acceleration).
        """
        lo = int(np.searchsorted(self.s_env, s_lo, side="right"))
        hi = int(np.searchsorted(self.s_env, s_hi, side="left"))
        if hi <= lo or v_limit <= 0.0:
            return v_limit
        A, J = self.lim.A, self.lim.J
        tau = (self.s_env[lo:hi] - s_point) / v_limit
        reach = np.where(tau >= 0.0, A + accel, A - accel)
        span = np.abs(tau)
        drop = np.where(
            span <= reach / J, 0.5 * J * span * span, reach * span - 0.5 * reach * reach / J
        )
        return float(min(v_limit, np.min(self.v_env[lo:hi] - accel * tau + drop)))

    def worst_of(self, segments: list[tuple]) -> list[tuple[float, float, float] | None]:
        """For each segment (s0, v0, phases, v_top, s1[, a0]): (s, v_limit, v_planned) of its
        worst excess of the feed limit, or None if it holds (a0, the start acceleration,
        defaults to 0).

        Segments whose highest feed is below the lowest limit they span hold at once; the others
        are laid on one time line (a second apart) and sampled together every half period.
        """
        out: list[tuple[float, float, float] | None] = [None] * len(segments)
        s0, v_top, s1 = (np.array([seg[i] for seg in segments]) for i in (0, 3, 4))
        pending = np.flatnonzero(self._interior_mins(s0, s1) < v_top * (1.0 + CHECK_SLACK))
        train = PhaseTrain(0.0, 0.0, 0.0, 0.0)
        sampled, starts, ends = [], [], []
        for i in pending.tolist():
            s_start, v_start, phases, _, _, *a_start = segments[i]
            start = train.t_s + 1.0
            train.restart(start, s_start, v_start, a_start[0] if a_start else 0.0)
            train.extend(phases)
            if train.t_s > start:  # a segment without motion has nothing to exceed
                sampled.append(i)
                starts.append(start)
                ends.append(train.t_s)
        if not sampled:
            return out
        start, end = np.array(starts), np.array(ends)
        counts = np.clip(np.ceil((end - start) / (0.5 * self.lim.T)), 16, 20_000).astype(int) + 1
        first = np.cumsum(counts) - counts
        # Each segment's times from its start to its end, both included, evenly spaced.
        fraction = (np.arange(counts.sum()) - np.repeat(first, counts)) / np.repeat(
            counts - 1, counts
        )
        times = np.repeat(start, counts) + np.repeat(end - start, counts) * fraction
        s, v, _, _ = train.sample(times)
        limit = np.interp(s, self.s_env, self.v_env)
        excess = v - limit * (1.0 + CHECK_SLACK) - 1e-9
        # The first sample of each segment where its excess is largest (argmax per segment).
        segment = np.repeat(np.arange(len(counts)), counts)
        at_max = np.flatnonzero(excess == np.maximum.reduceat(excess, first)[segment])
        worst = at_max[np.searchsorted(segment[at_max], np.arange(len(counts)))]
        for i, j in zip(sampled, worst.tolist(), strict=True):
            if excess[j] > 0.0:
                out[i] = (float(s[j]), float(limit[j]), float(v[j]))
        return out

    def _interior_mins(self, s0: np.ndarray, s1: np.ndarray) -> np.ndarray:
        """The lowest limit over each [s0, s1]: at its ends or at a sample inside."""
        lowest = np.minimum(
            np.interp(s0, self.s_env, self.v_env), np.interp(s1, self.s_env, self.v_env)
        )
        i0 = np.searchsorted(self.s_env, s0, side="left")
        i1 = np.searchsorted(self.s_env, s1, side="right")
        inner = np.flatnonzero(i1 > i0)
        if inner.size:
            inside = range_minima(self._v_padded, i0[inner], i1[inner])
            lowest[inner] = np.minimum(lowest[inner], inside)
        return lowest
