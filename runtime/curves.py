"""Curves as the machine loads them: read from YAML, checked against travel, prepared for planning.

A curve reaches the machine from a file (command line, demo) or from the HMI's staging
registers. Either way it is validated by the planner's rules (:class:`planner.errors.CurveError`)
and checked against every axis's travel limits here, and its planning geometry
(:class:`planner.stream.Path`) is prepared in the caller's thread, so that loading it into the
machine at a cycle boundary is a reference swap.

Coordinates map to axes in order: the curve's x, y (and z) drive the first two (three) axes.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path as FilePath

import numpy as np
import yaml

from planner.errors import CurveError, CurveRule
from planner.nurbs import NurbsCurve
from planner.stream import Path
from planner.types import Limits
from runtime.config import AxisConfig, MachineConfig

#: Parameters per knot span sampled when the control polygon leaves the travel box.
TRAVEL_SAMPLES_PER_SPAN = 64


class TravelError(CurveError):
    """A curve that leaves an axis's travel limits."""

    def __init__(self, axis: AxisConfig, value_mm: float) -> None:
        self.axis = axis.name
        super().__init__(
            f"axis {axis.name}",
            f"reaches {value_mm:.3f} mm, outside its travel "
            f"[{axis.travel_min_mm:g}, {axis.travel_max_mm:g}] mm",
            rule=CurveRule.TRAVEL,
        )


@dataclass(frozen=True, eq=False)
class LoadedCurve:
    """A validated curve with its planning geometry, ready to be swapped into the machine."""

    curve: NurbsCurve
    path: Path
    crc32: int = 0
    name: str = ""


def load_curve_file(path: str | FilePath) -> NurbsCurve:
    """Read a NURBS curve from a YAML document (``degree``, ``control_points``, ``weights``,
    ``knots``; mm).

    :raises CurveError: if the file cannot be read, is not YAML, or breaks a curve rule.
    """
    path = FilePath(path)
    try:
        document = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise CurveError(
            "file", f"{path}: cannot be read ({exc.strerror})", rule=CurveRule.FORMAT
        ) from None
    except yaml.YAMLError as exc:
        raise CurveError("file", f"{path}: not valid YAML ({exc})", rule=CurveRule.FORMAT) from None
    return NurbsCurve.from_mapping(document)


def planner_limits(config: MachineConfig) -> Limits:
    """The planner's limits from the machine description (per-axis limits only when set)."""
    planner = config.planner
    axis_vmax = [axis.vmax_mm_s for axis in config.axes]
    axis_amax = [axis.amax_mm_s2 for axis in config.axes]
    return Limits(
        vmax_mm_s=planner.vmax_mm_s,
        amax_mm_s2=planner.amax_mm_s2,
        jmax_mm_s3=planner.jmax_mm_s3,
        chord_error_mm=planner.chord_error_mm,
        normal_accel_mm_s2=planner.normal_accel_mm_s2,
        axis_vmax_mm_s=_per_axis(axis_vmax, planner.vmax_mm_s),
        axis_amax_mm_s2=_per_axis(axis_amax, planner.amax_mm_s2),
    )


def _per_axis(values: list[float | None], fallback: float) -> tuple[float, ...] | None:
    if all(v is None for v in values) or len(values) < 2:
        return None
    # An axis without a limit of its own is never the binding one: it gets the path limit.
    return tuple(fallback if v is None else v for v in values)


def limits_for_curve(limits: Limits, dimension: int) -> Limits:
    """``limits`` with the per-axis tuples cut to the curve's coordinates."""
    return replace(
        limits,
        axis_vmax_mm_s=_first(limits.axis_vmax_mm_s, dimension),
        axis_amax_mm_s2=_first(limits.axis_amax_mm_s2, dimension),
    )


def _first(values: tuple[float, ...] | None, count: int) -> tuple[float, ...] | None:
    return None if values is None else values[:count]


def check_travel(curve: NurbsCurve, axes: tuple[AxisConfig, ...]) -> None:
    """Reject a curve that leaves any axis's travel limits.

    A NURBS curve with positive weights lies in the convex hull of its control points, so when
    every control point is inside the travel box the whole curve is; otherwise the curve is
    sampled densely and its extreme coordinates checked.

    :raises TravelError: naming the axis and the coordinate reached.
    :raises CurveError: if the curve has more coordinates than the machine has axes.
    """
    if curve.dimension > len(axes):
        raise CurveError(
            "control_points",
            f"{curve.dimension} coordinates per point, the machine has {len(axes)} axes",
            rule=CurveRule.DIMENSION,
        )
    low = np.array([axis.travel_min_mm for axis in axes[: curve.dimension]])
    high = np.array([axis.travel_max_mm for axis in axes[: curve.dimension]])
    points = curve.control_points
    if np.all(points >= low) and np.all(points <= high):
        return
    breakpoints = curve.breakpoints
    fractions = np.linspace(0.0, 1.0, TRAVEL_SAMPLES_PER_SPAN, endpoint=False)
    u = (breakpoints[:-1, None] + np.diff(breakpoints)[:, None] * fractions).ravel()
    samples = curve.evaluate(np.append(u, breakpoints[-1]))[0]
    for i, axis in enumerate(axes[: curve.dimension]):
        if samples[:, i].min() < axis.travel_min_mm:
            raise TravelError(axis, float(samples[:, i].min()))
        if samples[:, i].max() > axis.travel_max_mm:
            raise TravelError(axis, float(samples[:, i].max()))


def prepare_curve(
    curve: NurbsCurve, config: MachineConfig, *, crc32: int = 0, name: str = ""
) -> LoadedCurve:
    """Check ``curve`` against travel and prepare its planning geometry (outside the cycle).

    :raises CurveError: (``TravelError`` for travel) if the machine cannot run this curve.
    """
    check_travel(curve, config.axes)
    limits = limits_for_curve(planner_limits(config), curve.dimension)
    return LoadedCurve(
        curve=curve, path=Path(curve, limits, config.cycle.period_s), crc32=crc32, name=name
    )
