"""Time-optimal jerk-limited braking from any path motion state to rest, in closed form.

Used for feed hold, stop and fault stops: the moment one is asked for, the cyclic task brakes
from the current feed ``v0`` and tangential acceleration ``a0`` along the path, so the stop
begins in the same cycle and no planner round trip delays it.

The profile has three phases (not in the paper; the standard jerk-limited stop, e.g. Ruckig's
velocity interface with target 0):

1. jerk ``-J`` until the acceleration reaches the braking peak ``a_p`` (< 0),
2. constant acceleration ``a_p`` (only when ``|a_p|`` would exceed ``A``),
3. jerk ``+J`` until acceleration and feed reach 0 together.

Velocity balance with phase 2 absent: ``v0 + (a0² - a_p²)/(2J) - a_p²/(2J) = 0``, so
``a_p = -sqrt(J·v0 + a0²/2)``; when that exceeds ``A`` in magnitude, ``a_p = -A`` and phase 2
lasts ``t2 = (v0 + (a0² - 2A²)/(2J)) / A``.

Units: mm, s. Pure computation, no state beyond the frozen record.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class BrakingProfile:
    """Feed, acceleration and distance of a jerk-limited stop, as functions of time.

    ``t_phase_s`` are the durations of the three phases; ``v0_mm_s`` and ``a0_mm_s2`` the state
    braking starts from; ``jerk_mm_s3`` the jerk magnitude used.
    """

    v0_mm_s: float
    a0_mm_s2: float
    jerk_mm_s3: float
    t_phase_s: tuple[float, float, float]

    @classmethod
    def from_state(
        cls, *, v0_mm_s: float, a0_mm_s2: float, amax_mm_s2: float, jmax_mm_s3: float
    ) -> BrakingProfile:
        """The quickest stop from feed ``v0_mm_s`` and acceleration ``a0_mm_s2``.

        A state that cannot stop without the feed dipping below zero (strong deceleration at
        almost no feed, which no jerk-limited plan produces) brakes with phase 3 alone and is
        clamped at rest by :meth:`sample`.
        """
        v0 = max(0.0, v0_mm_s)
        a0 = min(max(a0_mm_s2, -amax_mm_s2), amax_mm_s2)
        J = jmax_mm_s3
        A = amax_mm_s2
        if v0 == 0.0 and a0 == 0.0:
            return cls(v0, a0, J, (0.0, 0.0, 0.0))
        peak_sq = J * v0 + 0.5 * a0 * a0
        if a0 < 0 and peak_sq < a0 * a0:
            # Already braking harder than needed: release the acceleration at once.
            return cls(v0, a0, J, (0.0, 0.0, -a0 / J))
        a_p = -math.sqrt(peak_sq)
        t2 = 0.0
        if a_p < -A:
            a_p = -A
            t2 = (v0 + (a0 * a0 - 2.0 * A * A) / (2.0 * J)) / A
        return cls(v0, a0, J, ((a0 - a_p) / J, max(0.0, t2), -a_p / J))

    @property
    def duration_s(self) -> float:
        return sum(self.t_phase_s)

    @property
    def distance_mm(self) -> float:
        return self.sample(self.duration_s)[0]

    def sample(self, t_s: float) -> tuple[float, float, float]:
        """Distance travelled, feed and acceleration ``t_s`` after braking began."""
        J = self.jerk_mm_s3
        s, v, a = 0.0, self.v0_mm_s, self.a0_mm_s2
        remaining = max(0.0, t_s)
        for jerk, duration in zip((-J, 0.0, J), self.t_phase_s, strict=True):
            dt = min(remaining, duration)
            s += v * dt + a * dt * dt / 2.0 + jerk * dt**3 / 6.0
            v += a * dt + jerk * dt * dt / 2.0
            a += jerk * dt
            remaining -= dt
            if remaining <= 0.0:
                break
        if v <= 0.0 or t_s >= self.duration_s:
            # Rest: rounding of the phase times must not leave a creeping residual feed.
            return s, 0.0, 0.0
        return s, v, a
