"""Axis scaling: absolute mm <-> counts conversion, direction, INTEGER32 range and travel limits."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drives.errors import DriveError, ScalingError
from drives.scaling import INT32_MAX, INT32_MIN, AxisScaling


def test_to_counts_rounds_to_nearest_count() -> None:
    scaling = AxisScaling(counts_per_mm=1000.0)
    assert scaling.to_counts(1.2344) == 1234
    assert scaling.to_counts(1.2346) == 1235
    assert scaling.to_counts(-0.0004) == 0
    assert scaling.to_counts(-2.5) == -2500


def test_direction_mirrors_counts_and_back() -> None:
    scaling = AxisScaling(counts_per_mm=400.0, direction=-1)
    assert scaling.to_counts(10.0) == -4000
    assert scaling.to_mm(-4000) == pytest.approx(10.0)
    assert scaling.to_mm(scaling.to_counts(-3.25)) == pytest.approx(-3.25)


def test_round_trip_error_is_at_most_half_a_count() -> None:
    scaling = AxisScaling(counts_per_mm=10000.0 / 3.0)
    for position_mm in np.linspace(-500.0, 500.0, 2001):
        error_mm = scaling.to_mm(scaling.to_counts(float(position_mm))) - position_mm
        assert abs(error_mm) <= 0.5 / scaling.counts_per_mm + 1e-12


def test_rounding_never_accumulates_over_a_million_cycles() -> None:
    # A slow ramp whose per-cycle step is a fraction of a count: converting each absolute
    # setpoint keeps the error within half a count however many cycles have run, whereas
    # summing rounded per-cycle increments would have drifted by thousands of counts.
    scaling = AxisScaling(counts_per_mm=10000.0 / 3.0)
    step_mm = 0.000_137
    cycles = 1_000_000
    worst = 0.0
    rounded_increments = 0
    previous_exact = 0.0
    for k in range(cycles):
        position_mm = k * step_mm
        exact = position_mm * scaling.counts_per_mm
        worst = max(worst, abs(scaling.to_counts(position_mm) - exact))
        rounded_increments += round(exact - previous_exact)
        previous_exact = exact
    assert worst <= 0.5 + 1e-6
    final_exact = (cycles - 1) * step_mm * scaling.counts_per_mm
    assert scaling.to_counts((cycles - 1) * step_mm) == round(final_exact)
    # The naive incremental scheme is what the absolute conversion protects against.
    assert abs(rounded_increments - final_exact) > 1000


def test_int32_range_is_enforced() -> None:
    scaling = AxisScaling(counts_per_mm=1.0)
    assert scaling.to_counts(float(INT32_MAX)) == INT32_MAX
    assert scaling.to_counts(float(INT32_MIN)) == INT32_MIN
    for position_mm in (INT32_MAX + 1.0, INT32_MIN - 1.0, math.inf, -math.inf, math.nan):
        with pytest.raises(ScalingError) as caught:
            scaling.to_counts(position_mm)
        assert isinstance(caught.value, DriveError)
        assert isinstance(caught.value, ValueError)
        assert "INTEGER32" in str(caught.value)


def test_travel_limits_scalar_and_vectorised() -> None:
    scaling = AxisScaling(counts_per_mm=100.0, travel_min_mm=-10.0, travel_max_mm=250.0)
    assert scaling.within_travel(-10.0)
    assert scaling.within_travel(250.0)
    assert not scaling.within_travel(250.001)
    assert not scaling.within_travel(-10.5)
    mask = scaling.outside_travel([0.0, -11.0, 250.0, 251.0, math.nan])
    assert mask.tolist() == [False, True, False, True, True]


def test_unlimited_travel_by_default() -> None:
    scaling = AxisScaling(counts_per_mm=100.0)
    assert scaling.within_travel(1e12)
    assert not scaling.outside_travel(np.array([-1e12, 1e12])).any()


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"counts_per_mm": 0.0}, "counts_per_mm"),
        ({"counts_per_mm": math.inf}, "counts_per_mm"),
        ({"counts_per_mm": 10.0, "direction": 2}, "direction"),
        ({"counts_per_mm": 10.0, "travel_min_mm": 5.0, "travel_max_mm": 1.0}, "travel_min_mm"),
    ],
)
def test_invalid_scaling_is_rejected(kwargs: dict[str, float], field: str) -> None:
    with pytest.raises(ValueError, match=field):
        AxisScaling(**kwargs)
