"""Parameter update per interpolation period: from planned arc length s to curve parameter u.

Source: eq. (2) of Wang, Zhao, Lu, Liu, China Mechanical Engineering 23(3), 2012, 299-304, in
its standard second-order Taylor form (the print is garbled):
    u(i+1) = u(i) + V·T / |C'| - (V·T)² (C'·C'') / (2 |C'|⁴), at u = u(i),
with V·T taken as the planned step s(i+1) - s(i) (the profile's exact step, not V(i)·T).
- ``taylor2``: eq. (2) alone, step after step (the paper's interpolator; its step length drifts
  from the plan, most where the radius of curvature is small against the step).
- ``corrected`` (default, beyond the paper, motion-planning.md §2): the arc-length table predicts
  u (quintic Hermite interpolation of u(s) with its first two derivatives, the same second-order
  information as eq. (2)), then Newton steps on s(u) - s_target with ds/du = |C'(u)|
  (:meth:`ArcLengthTable.u_of_s`) make the arc length of every setpoint equal the plan to
  1e-10 mm, so the realised feed is the planned one.

Realised feed: the arc length between consecutive setpoints over T. The chord between them is
shorter by about (kappa L)²/24 relative (L the step), which is geometry, not interpolation error.

Units: s in mm, u dimensionless. One interpolator per stream (``taylor2`` carries u); not
thread-safe.
"""

from __future__ import annotations

from enum import Enum

import numpy as np

from planner.arclength import ArcLengthTable
from planner.nurbs import NurbsCurve


class ParameterUpdate(Enum):
    """How u follows the planned arc length."""

    TAYLOR2 = "taylor2"
    CORRECTED = "corrected"


def taylor2_step(d1: np.ndarray, d2: np.ndarray, step_mm: np.ndarray) -> np.ndarray:
    """du of eq. (2): VT/|C'| - (VT)² (C'·C'') / (2|C'|⁴), rows of d1, d2 at u(i)."""
    speed2 = np.sum(d1 * d1, axis=-1)
    dot = np.sum(d1 * d2, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        du = step_mm / np.sqrt(speed2) - step_mm**2 * dot / (2.0 * speed2**2)  # eq. (2)
    return du


class Interpolator:
    """Turns planned arc lengths into curve parameters, row after row.

    :param curve: the curve.
    :param arc: its arc-length table.
    :param update: ``"taylor2"`` or ``"corrected"``.
    :param s_start_mm: arc length of the stream's start state (the first step starts there).
    :raises ValueError: for an unknown update name.
    """

    def __init__(
        self, curve: NurbsCurve, arc: ArcLengthTable, update: str, s_start_mm: float
    ) -> None:
        try:
            self.update = ParameterUpdate(update)
        except ValueError:
            names = ", ".join(m.value for m in ParameterUpdate)
            raise ValueError(f"update: got {update!r}, must be one of {names}") from None
        self._curve = curve
        self._arc = arc
        self._u0, self._u1 = curve.domain
        self._s = float(s_start_mm)
        # Only taylor2 steps from the previous parameter; corrected solves each row afresh.
        self._u = (
            float(arc.u_of_s(arc.extent_mm(max(s_start_mm, 0.0)))[0])
            if self.update is ParameterUpdate.TAYLOR2
            else float("nan")
        )

    def parameters(self, s_mm: np.ndarray) -> np.ndarray:
        """u for each planned arc length in ``s_mm`` (consecutive rows of the stream)."""
        s_mm = np.maximum(np.asarray(s_mm, dtype=np.float64), 0.0)
        if s_mm.size:
            s_mm = np.minimum(s_mm, self._arc.extent_mm(float(s_mm.max())))
        if s_mm.size == 0:
            return s_mm.copy()
        if self.update is ParameterUpdate.CORRECTED:
            u = self._corrected(s_mm)
        else:
            u = self._taylor2(s_mm)
        self._s, self._u = float(s_mm[-1]), float(u[-1])
        return u

    def _corrected(self, s_mm: np.ndarray) -> np.ndarray:
        return self._arc.u_of_s(s_mm)

    def _taylor2(self, s_mm: np.ndarray) -> np.ndarray:
        out = np.empty(len(s_mm))
        u, s_prev = self._u, self._s
        for i, s in enumerate(s_mm):
            ders = self._curve.evaluate(u, order=2)
            du = float(taylor2_step(ders[1, 0], ders[2, 0], s - s_prev))
            if not np.isfinite(du):
                # C'(u) = 0 (a sharp corner): eq. (2) has no step; take it from the table.
                du = float(self._arc.u_of_s(s)[0]) - u
            u = min(max(u + du, self._u0), self._u1)
            out[i] = u
            s_prev = s
        return out
