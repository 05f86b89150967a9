"""Speed profiles along the path: a motion made of closed-form phases, sampled in time.

A :class:`PhaseTrain` is a sequence of :class:`Phase` s: constant-jerk phases (the S-curve,
:mod:`planner.profiles.scurve`) or cosine speed changes (eqs. (5)-(13),
:mod:`planner.profiles.cosine`). It integrates its state (s, v, a) in closed form from phase to
phase and evaluates s, v, a, j at any array of times, vectorised (no loop per period).

Units: t in s, s in mm, v in mm/s, a in mm/s², j in mm/s³. Not thread-safe while being built;
pure computation.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from planner.profiles.cosine import cosine_state

#: Results kept by each cache of the profile searches (pure functions of their floats): the
#: look-ahead's scan repeats most of them, round after round, with the same arguments.
CACHE_SIZE = 1 << 14


@dataclass(frozen=True)
class Phase:
    """One phase of a motion: constant jerk, or a cosine change of the feed by cosine_dv_mm_s."""

    duration_s: float
    jerk_mm_s3: float = 0.0
    cosine_dv_mm_s: float | None = None


class PhaseTrain:
    """Phases laid end to end from a start state, with their start states in closed form."""

    def __init__(self, t_s: float, s_mm: float, v_mm_s: float, a_mm_s2: float) -> None:
        self.t_s, self.s_mm, self.v_mm_s, self.a_mm_s2 = t_s, s_mm, v_mm_s, a_mm_s2
        # One row per phase: start t, s, v, a, jerk, cosine dv (nan for constant jerk), duration.
        self._rows: list[tuple[float, float, float, float, float, float, float]] = []
        self._table: np.ndarray | None = None  # the rows as an array, once sampled

    def __len__(self) -> int:
        return len(self._rows)

    def extend(self, phases: Sequence[Phase]) -> None:
        """Append phases, advancing the end state exactly (constant jerk: cubic in time)."""
        self._table = None
        for phase in phases:
            tau = phase.duration_s
            if tau <= 0.0:
                continue
            t, s, v, a = self.t_s, self.s_mm, self.v_mm_s, self.a_mm_s2
            if phase.cosine_dv_mm_s is None:
                j = phase.jerk_mm_s3
                self._rows.append((t, s, v, a, j, np.nan, tau))
                self.s_mm = s + v * tau + a * tau**2 / 2.0 + j * tau**3 / 6.0
                self.v_mm_s = max(0.0, v + a * tau + j * tau**2 / 2.0)
                self.a_mm_s2 = a + j * tau
            else:
                dv = phase.cosine_dv_mm_s
                self._rows.append((t, s, v, 0.0, 0.0, dv, tau))
                self.s_mm = s + (v + 0.5 * dv) * tau  # eq. (11)
                self.v_mm_s = max(0.0, v + dv)
                self.a_mm_s2 = 0.0
            self.t_s = t + tau

    def restart(self, t_s: float, s_mm: float, v_mm_s: float, a_mm_s2: float) -> None:
        """Continue from a new state at a later time ``t_s`` (the phases after it start there);
        lets unrelated motions share one vectorised sampling."""
        if t_s < self.t_s:
            raise ValueError(f"t_s: got {t_s!r}, must be >= the train's end {self.t_s!r}")
        self.t_s, self.s_mm, self.v_mm_s, self.a_mm_s2 = t_s, s_mm, v_mm_s, a_mm_s2

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """s, v, a, j at times ``t`` (each within the train; later times hold the end state)."""
        t = np.asarray(t, dtype=np.float64)
        if not self._rows:
            full = np.full(t.shape, self.s_mm)
            return full, np.full(t.shape, self.v_mm_s), np.zeros(t.shape), np.zeros(t.shape)
        if self._table is None:
            # Kept until the train grows: the look-ahead's check samples it more than once.
            self._table = np.array(self._rows)
        t0, s0, v0, a0, j0, dv, dur = self._table.T
        k = np.clip(np.searchsorted(t0, t, side="right") - 1, 0, len(self._rows) - 1)
        tau = np.clip(t - t0[k], 0.0, dur[k])
        s = s0[k] + v0[k] * tau + a0[k] * tau**2 / 2.0 + j0[k] * tau**3 / 6.0
        v = v0[k] + a0[k] * tau + j0[k] * tau**2 / 2.0
        a = a0[k] + j0[k] * tau
        j = j0[k].copy()
        cos_rows = ~np.isnan(dv[k])
        if cos_rows.any():
            kc = k[cos_rows]
            sc, vc, ac, jc = cosine_state(v0[kc], dv[kc], dur[kc], tau[cos_rows])
            s[cos_rows] = s0[kc] + sc
            v[cos_rows], a[cos_rows], j[cos_rows] = vc, ac, jc
        after = t >= self.t_s
        s[after], v[after], a[after], j[after] = self.s_mm, self.v_mm_s, self.a_mm_s2, 0.0
        return s, np.maximum(v, 0.0), a, j
