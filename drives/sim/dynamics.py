"""Motion model of a simulated servo axis: CSP position following and braking ramps.

Source: CiA 402 cyclic synchronous position mode (8): the drive takes the target 0x607A of each
SYNC as its position demand and reports 0x6064 (position actual), 0x606C (velocity actual) and
0x60F4 (following error actual = position demand - position actual).

Model: a velocity- and acceleration-limited tracker, integrated once per control period. The
commanded velocity is the dead-beat velocity that reaches the demand at the end of the period,
bounded around the demand velocity by the braking speed sqrt(2 a |e|), then limited to
``max_velocity_counts_s``; its change per period is limited by ``max_accel_counts_s2``. A target
ramp within the limits is followed exactly; a step beyond them shows as a following error that
decays at the velocity limit. The demand may lag the received target by whole periods.

Units: counts, counts/s, counts/s², seconds.
Threading: plain objects, no locks; the simulated drive calls them under its own lock.
Not modelled: current loop, torque, load inertia, friction, encoder resolution beyond rounding,
overshoot or ringing of a real position loop.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True)
class DriveModel:
    """Dynamics and timing of a simulated drive.

    :param max_velocity_counts_s: velocity limit of the axis.
    :param max_accel_counts_s2: acceleration limit of the axis (also the current/voltage-limit
        ramps of 0x605A/0x605E codes 3, 4, 7, 8).
    :param lag_periods: whole SYNC periods between receiving a target and using it as demand
        (real drives interpolate over the next period: 1).
    :param initial_position_counts: position actual at power-on.
    :param sync_timeout_factor: SYNC-loss limit as a multiple of 0x1006 (CiA 301 devices use
        1.5 to 2).
    """

    max_velocity_counts_s: float = 400_000.0
    max_accel_counts_s2: float = 10_000_000.0
    lag_periods: int = 1
    initial_position_counts: int = 0
    sync_timeout_factor: float = 2.0

    def __post_init__(self) -> None:
        for name in ("max_velocity_counts_s", "max_accel_counts_s2", "sync_timeout_factor"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"drive model: {name} = {value!r}, must be finite and > 0")
        if self.lag_periods < 0:
            raise ValueError(f"drive model: lag_periods = {self.lag_periods}, must be >= 0")


class Axis:
    """Position and velocity of one simulated axis, advanced one control period at a time."""

    def __init__(self, model: DriveModel) -> None:
        self.model = model
        self.position_counts = float(model.initial_position_counts)
        self.velocity_counts_s = 0.0
        self.demand_counts = self.position_counts
        #: True if a velocity or acceleration limit cut the last commanded velocity.
        self.limited = False
        self._targets: deque[float] = deque(maxlen=model.lag_periods + 1)
        self._previous_demand_counts = self.position_counts

    def hold(self) -> None:
        """Stop at the actual position and make it the demand (power stage off, or enabling)."""
        self.velocity_counts_s = 0.0
        self.limited = False
        self.demand_counts = self.position_counts
        self._previous_demand_counts = self.position_counts
        self._targets.clear()
        self._targets.extend([self.position_counts] * self._targets.maxlen)

    def disturb(self, offset_counts: float) -> None:
        """Move the actual position by ``offset_counts`` at once (an external disturbance)."""
        self.position_counts += offset_counts

    @property
    def following_error_counts(self) -> float:
        """Position demand minus position actual."""
        return self.demand_counts - self.position_counts

    def follow(self, target_counts: float, period_s: float) -> None:
        """Advance one period in CSP toward ``target_counts`` (the target received this SYNC)."""
        self._targets.append(target_counts)
        demand = self._targets[0]
        demand_velocity = (demand - self._previous_demand_counts) / period_s
        self._previous_demand_counts = demand
        self.demand_counts = demand

        error = demand - self.position_counts
        braking = math.sqrt(2.0 * self.model.max_accel_counts_s2 * abs(error))
        wanted = min(max(error / period_s, demand_velocity - braking), demand_velocity + braking)
        self._advance(wanted, self.model.max_accel_counts_s2, period_s)

    def brake(self, decel_counts_s2: float, period_s: float) -> bool:
        """Ramp the velocity toward zero at ``decel_counts_s2``; return True once at rest.

        The demand follows the actual position, so no following error builds up while braking.
        """
        self._advance(0.0, decel_counts_s2, period_s)
        self.demand_counts = self.position_counts
        self._previous_demand_counts = self.position_counts
        return self.velocity_counts_s == 0.0

    def _advance(self, wanted_counts_s: float, accel_counts_s2: float, period_s: float) -> None:
        vmax = self.model.max_velocity_counts_s
        commanded = min(max(wanted_counts_s, -vmax), vmax)
        max_step = accel_counts_s2 * period_s
        step = min(max(commanded - self.velocity_counts_s, -max_step), max_step)
        self.limited = commanded != wanted_counts_s or step != commanded - self.velocity_counts_s
        self.velocity_counts_s += step
        self.position_counts += self.velocity_counts_s * period_s
