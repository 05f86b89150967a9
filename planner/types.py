"""Records shared by the planner stages: machine limits, a motion state, a block of setpoints.

Source: the limits of the paper's experiment (Wang, Zhao, Lu, Liu, China Mechanical Engineering
23(3), 2012, 299-304): vmax, amax, jmax and the chord error delta of eq. (3); the normal
acceleration and per-axis limits are not in the paper and are off (``None``) by default.

Units: mm, s (``_mm``, ``_s``, ``_mm_s``, ``_mm_s2``, ``_mm_s3``); u is the dimensionless curve
parameter; positions are (k, dim) arrays in mm.

Threading: every record is immutable (frozen dataclasses, read-only arrays) and may be shared.

Invariants: every limit is finite and > 0 (an axis tuple entry likewise); a setpoint block holds
k >= 1 rows with no NaN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np


def _check_positive(field_name: str, value: float) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"limits: {field_name}: got {value!r}, must be a number")
    if not (math.isfinite(value) and value > 0.0):
        raise ValueError(f"limits: {field_name}: got {value!r}, must be finite and > 0")


@dataclass(frozen=True)
class Limits:
    """Feed, acceleration and jerk limits of the tool-path motion.

    :param vmax_mm_s: programmed feed (tangential speed limit).
    :param amax_mm_s2: tangential acceleration limit.
    :param jmax_mm_s3: tangential jerk limit.
    :param chord_error_mm: allowed chord error delta of eq. (3).
    :param normal_accel_mm_s2: optional normal (centripetal) acceleration limit; not in the paper.
    :param axis_vmax_mm_s: optional per-axis velocity limits, one per coordinate; not in the paper.
    :param axis_amax_mm_s2: optional per-axis acceleration limits, one per coordinate; not in the
        paper.
    :raises ValueError: naming the field, the value and the rule when a limit is not finite > 0.
    """

    vmax_mm_s: float
    amax_mm_s2: float
    jmax_mm_s3: float
    chord_error_mm: float
    normal_accel_mm_s2: float | None = None
    axis_vmax_mm_s: tuple[float, ...] | None = None
    axis_amax_mm_s2: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        for name in ("vmax_mm_s", "amax_mm_s2", "jmax_mm_s3", "chord_error_mm"):
            _check_positive(name, getattr(self, name))
        if self.normal_accel_mm_s2 is not None:
            _check_positive("normal_accel_mm_s2", self.normal_accel_mm_s2)
        for name in ("axis_vmax_mm_s", "axis_amax_mm_s2"):
            values = getattr(self, name)
            if values is None:
                continue
            values = tuple(values)
            if len(values) not in (2, 3):
                raise ValueError(
                    f"limits: {name}: got {len(values)} values, must be one per axis (2 or 3)"
                )
            for i, value in enumerate(values):
                _check_positive(f"{name}[{i}]", value)
            object.__setattr__(self, name, tuple(float(v) for v in values))

    def with_feed_override(self, ratio: float) -> Limits:
        """These limits with vmax scaled by ``ratio`` (acceleration and jerk unchanged).

        :raises ValueError: if ratio is not finite and > 0 (a hold is a stop, not a 0 override).
        """
        _check_positive("feed override ratio", ratio)
        return replace(self, vmax_mm_s=self.vmax_mm_s * ratio)


@dataclass(frozen=True)
class MotionState:
    """A point of the path motion: arc length, feed and tangential acceleration."""

    s_mm: float
    v_mm_s: float = 0.0
    a_mm_s2: float = 0.0


#: The per-row columns of a SetpointBlock.
_COLUMNS = ("t_s", "s_mm", "u", "position_mm", "feed_mm_s", "accel_mm_s2", "jerk_mm_s3")


def _readonly(array: np.ndarray) -> np.ndarray:
    array = np.ascontiguousarray(array, dtype=np.float64)
    array.flags.writeable = False
    return array


@dataclass(frozen=True, eq=False)
class SetpointBlock:
    """Consecutive setpoints, one row per interpolation period.

    :param t_s: time of each row since the start state of the stream.
    :param s_mm: planned arc length.
    :param u: curve parameter of the setpoint.
    :param position_mm: (k, dim) setpoint C(u).
    :param feed_mm_s: planned feed.
    :param accel_mm_s2: planned tangential acceleration.
    :param jerk_mm_s3: planned tangential jerk.
    :param last: True on the block holding the final setpoint (motion at rest).
    """

    t_s: np.ndarray = field(repr=False)
    s_mm: np.ndarray = field(repr=False)
    u: np.ndarray = field(repr=False)
    position_mm: np.ndarray = field(repr=False)
    feed_mm_s: np.ndarray = field(repr=False)
    accel_mm_s2: np.ndarray = field(repr=False)
    jerk_mm_s3: np.ndarray = field(repr=False)
    last: bool = False

    def __post_init__(self) -> None:
        for name in _COLUMNS:
            object.__setattr__(self, name, _readonly(getattr(self, name)))

    def __len__(self) -> int:
        return len(self.t_s)

    def __repr__(self) -> str:
        return f"SetpointBlock(rows={len(self)}, t_s={self.t_s[0]:.3f}.., last={self.last})"

    def state(self, i: int) -> MotionState:
        """Motion state of row ``i`` (negative indices count from the end)."""
        return MotionState(
            s_mm=float(self.s_mm[i]),
            v_mm_s=float(self.feed_mm_s[i]),
            a_mm_s2=float(self.accel_mm_s2[i]),
        )

    def rows(self, start: int, stop: int) -> SetpointBlock:
        """Rows ``start`` to ``stop`` (exclusive) as a block; ``last`` if it holds the final row."""
        columns = {name: getattr(self, name)[start:stop] for name in _COLUMNS}
        return SetpointBlock(**columns, last=self.last and stop >= len(self))

    @staticmethod
    def concatenate(blocks: list[SetpointBlock]) -> SetpointBlock:
        """One block holding the rows of ``blocks`` in order (``last`` from the final block)."""
        columns = {name: np.concatenate([getattr(b, name) for b in blocks]) for name in _COLUMNS}
        return SetpointBlock(**columns, last=blocks[-1].last)
