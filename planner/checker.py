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
#: A kink of the limit that dips less than this fraction below the line across a plan's
#: half-period step is left to the plan's samples: a feed that much above the limit there keeps
#: the chord error within 1 % of the envelope's (planner.envelope.CHORD_MARGIN is 3 %).
KINK_DIP_FRACTION = 5e-3


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
        # Between two of the plan's samples, the plan can exceed the limit by more than its
        # samples do only where the limit dips below the line between its values there: at a
        # sample where the limit's slope rises (a kink: its minima among them), by up to that
        # dip. Kinks whose dip across a half-period step at their own limit (or vmax) is below
        # KINK_DIP_FRACTION are left to the samples.
        step = 0.25 * lim.T * np.minimum(v_env, lim.vmax_mm_s)
        with np.errstate(invalid="ignore"):  # inf on a straight stretch: no kink there
            around = np.interp(s_env - step, s_env, v_env) + np.interp(s_env + step, s_env, v_env)
            kink = np.flatnonzero(0.5 * around - v_env > KINK_DIP_FRACTION * v_env)
        self._kink_s, self._kink_v = s_env[kink], v_env[kink]

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
        s, v, a, _ = train.sample(times)
        segment = np.repeat(np.arange(len(counts)), counts)
        limit = np.interp(s, self.s_env, self.v_env)
        excess = v - limit * (1.0 + CHECK_SLACK) - 1e-9
        kink = self._kinks_passed(s, v, a, times, segment, first, counts, v_top[sampled])
        if kink is not None:
            # Each kink where the plan passes it, sampled with the rest.
            owner, kink_t = kink
            s_k, v_k, _, _ = train.sample(kink_t)
            limit_k = np.interp(s_k, self.s_env, self.v_env)
            excess_k = v_k - limit_k * (1.0 + CHECK_SLACK) - 1e-9
            order = np.argsort(np.concatenate([segment, owner]), kind="stable")
            s, v, limit, excess, segment = (
                np.concatenate(pair)[order]
                for pair in (
                    (s, s_k),
                    (v, v_k),
                    (limit, limit_k),
                    (excess, excess_k),
                    (segment, owner),
                )
            )
            first = np.searchsorted(segment, np.arange(len(counts)))
        # The first sample of each segment where its excess is largest (argmax per segment).
        at_max = np.flatnonzero(excess == np.maximum.reduceat(excess, first)[segment])
        worst = at_max[np.searchsorted(segment[at_max], np.arange(len(counts)))]
        for i, j in zip(sampled, worst.tolist(), strict=True):
            if excess[j] > 0.0:
                out[i] = (float(s[j]), float(limit[j]), float(v[j]))
        return out

    def _kinks_passed(
        self,
        s: np.ndarray,
        v: np.ndarray,
        a: np.ndarray,
        times: np.ndarray,
        segment: np.ndarray,
        first: np.ndarray,
        counts: np.ndarray,
        v_top: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """The limit's kinks strictly inside each sampled segment and below its top feed: the
        segment of each and the time the plan passes it (None if there are none), from the
        plan's samples (``s``, ``v``, ``a`` at ``times``; ``first`` and ``counts`` per
        segment): s(t) from the sample before, to second order (the third order is within
        J (T/2)³ / 6 of it, 27 nm with the paper's limits, where a tip's limit rises over
        micrometres).
        """
        last = first + counts - 1
        lo = np.searchsorted(self._kink_s, s[first], side="right")
        hi = np.searchsorted(self._kink_s, s[last], side="left")
        inside = np.maximum(hi - lo, 0)
        if not inside.any():
            return None
        owner = np.repeat(np.arange(len(counts)), inside)
        index = np.arange(inside.sum()) - np.repeat(np.cumsum(inside) - inside, inside)
        index += np.repeat(lo, inside)
        low = self._kink_v[index] < v_top[owner]
        if not low.any():
            return None
        owner, kink_s = owner[low], self._kink_s[index[low]]
        # One key per segment and arc length, ascending along the concatenated samples (the
        # plan's s does not decrease within a segment).
        width = float(self.s_env[-1] - self.s_env[0]) + 1.0
        keys = segment * width + (s - self.s_env[0])
        before = np.searchsorted(keys, owner * width + (kink_s - self.s_env[0])) - 1
        ahead = kink_s - s[before]
        speed = v[before]
        with np.errstate(invalid="ignore", divide="ignore"):
            root = np.sqrt(np.maximum(speed * speed + 2.0 * a[before] * ahead, 0.0))
            tau = np.where(speed + root > 0.0, 2.0 * ahead / (speed + root), 0.0)
        span = times[np.minimum(before + 1, len(times) - 1)] - times[before]
        return owner, times[before] + np.clip(tau, 0.0, span)

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
