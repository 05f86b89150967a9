"""Axis scaling: millimetres on the machine side, drive counts (INTEGER32) on the bus.

Source: CiA 402 position objects 0x607A target position and 0x6064 position actual value, both
INTEGER32 in drive increments ("counts").

Units: positions in mm (float), counts as int. ``direction`` = -1 mirrors the axis (the drive
counts up where the machine moves towards negative mm).

Threading: pure and immutable; safe from any thread, including the cyclic one.

Invariants: every conversion is absolute, ``counts = round(position_mm * counts_per_mm *
direction)``, computed from the position and never from the previous target, so rounding never
accumulates: after millions of cycles the error is still at most half a count.

Not modelled: modulo (rotary) axes, gear ratios other than a constant counts per mm, backlash.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from drives.errors import ScalingError

INT32_MIN = -(2**31)
INT32_MAX = 2**31 - 1


@dataclass(frozen=True)
class AxisScaling:
    """Conversion between machine millimetres and drive counts, and the axis travel range.

    :raises ValueError: if counts_per_mm is not finite and > 0, direction is not +1 or -1,
        or travel_min_mm > travel_max_mm.
    """

    counts_per_mm: float
    direction: int = 1
    travel_min_mm: float = -math.inf
    travel_max_mm: float = math.inf

    def __post_init__(self) -> None:
        if not (math.isfinite(self.counts_per_mm) and self.counts_per_mm > 0):
            raise ValueError(f"counts_per_mm = {self.counts_per_mm!r}: must be finite and > 0")
        if self.direction not in (1, -1):
            raise ValueError(f"direction = {self.direction!r}: must be 1 or -1")
        if math.isnan(self.travel_min_mm) or math.isnan(self.travel_max_mm):
            raise ValueError("travel limits must not be NaN")
        if self.travel_min_mm > self.travel_max_mm:
            raise ValueError(
                f"travel_min_mm = {self.travel_min_mm!r} > travel_max_mm = "
                f"{self.travel_max_mm!r}: the range must not be empty"
            )

    def to_counts(self, position_mm: float) -> int:
        """The drive target in counts for an absolute machine position.

        :raises ScalingError: if the result is not finite or does not fit INTEGER32.
        """
        exact = position_mm * self.counts_per_mm * self.direction
        if not (INT32_MIN - 0.5 < exact < INT32_MAX + 0.5):
            raise ScalingError(position_mm, exact)
        return round(exact)

    def to_mm(self, counts: int) -> float:
        """The machine position in mm of a drive position in counts."""
        return counts * self.direction / self.counts_per_mm

    def within_travel(self, position_mm: float) -> bool:
        """Whether a position lies inside the travel range (limits included)."""
        return self.travel_min_mm <= position_mm <= self.travel_max_mm

    def outside_travel(self, positions_mm: ArrayLike) -> NDArray[np.bool_]:
        """Mask of the positions outside the travel range (NaN counts as outside).

        Vectorised check of a whole path, e.g. every setpoint of a curve before it is accepted.
        """
        positions = np.asarray(positions_mm, dtype=float)
        inside = (positions >= self.travel_min_mm) & (positions <= self.travel_max_mm)
        return ~inside
