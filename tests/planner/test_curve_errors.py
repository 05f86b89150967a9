"""Every curve rule has its own CurveError naming the field, the value and the rule."""

from __future__ import annotations

import copy
import math
from typing import Any

import pytest

from planner.errors import CurveError, CurveRule, PlannerError
from planner.nurbs import NurbsCurve

POINTS = [[5, 5, 4], [25, 40, 9], [50, 70, 16], [65, 75, 22], [77, 73, 30], [105, 57, 32]]
POINTS.append([132, 40, 41])
WEIGHTS = [1.0, 1.2, 1.0, 1.25, 0.9, 0.85, 1.0]
KNOTS = [0, 0, 0, 0, 0.4531, 0.5485, 0.6306, 1, 1, 1, 1]


def document(**changes: Any) -> dict[str, Any]:
    data = {"degree": 3, "control_points": POINTS, "weights": WEIGHTS, "knots": KNOTS}
    data = copy.deepcopy(data)
    data.update(changes)
    return data


def rejected(data: Any) -> CurveError:
    with pytest.raises(CurveError) as caught:
        NurbsCurve.from_mapping(data)
    return caught.value


def test_valid_document_is_accepted_and_weights_default_to_one() -> None:
    assert NurbsCurve.from_mapping(document()).weights.tolist() == WEIGHTS
    data = document()
    del data["weights"]
    assert NurbsCurve.from_mapping(data).weights.tolist() == [1.0] * 7


def test_curve_error_is_a_planner_error_and_a_value_error_with_its_field() -> None:
    error = rejected(document(weights=[1, 1, 1, -0.2, 1, 1, 1]))
    assert isinstance(error, PlannerError)
    assert isinstance(error, ValueError)
    assert error.field == "weights[3]"
    assert str(error) == "curve: weights[3]: got -0.2, must be finite and > 0"


@pytest.mark.parametrize("degree", [0, -2, 2.0, True, "3", None])
def test_degree_must_be_an_integer_of_at_least_one(degree: object) -> None:
    error = rejected(document(degree=degree))
    assert str(error) == f"curve: degree: got {degree!r}, must be an integer >= 1"


def test_at_least_degree_plus_one_control_points() -> None:
    error = rejected(document(control_points=POINTS[:3], weights=WEIGHTS[:3], knots=[0] * 7))
    assert str(error) == "curve: control_points: got 3 points, must be at least degree + 1 = 4"


def test_every_point_has_the_same_dimension() -> None:
    points = copy.deepcopy(POINTS)
    points[2] = [50, 70]
    error = rejected(document(control_points=points))
    assert str(error) == (
        "curve: control_points[2]: got [50, 70], every point must have the same dimension "
        "as control_points[0] (3)"
    )


@pytest.mark.parametrize("dimension", [1, 4])
def test_dimension_is_two_or_three(dimension: int) -> None:
    points = [[float(i)] * dimension for i in range(7)]
    error = rejected(document(control_points=points))
    assert str(error) == (
        f"curve: control_points: points have {dimension} coordinates, the dimension must be 2 or 3"
    )


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_coordinates_are_finite(value: float) -> None:
    points = copy.deepcopy(POINTS)
    points[2][1] = value
    error = rejected(document(control_points=points))
    assert str(error) == f"curve: control_points[2][1]: got {value!r}, must be finite"


def test_one_weight_per_control_point() -> None:
    error = rejected(document(weights=WEIGHTS[:6]))
    assert str(error) == (
        "curve: weights: got 6 weights for 7 control points, must be one weight per control point"
    )


@pytest.mark.parametrize("value", [-0.2, 0.0, math.nan, math.inf])
def test_weights_are_finite_and_positive(value: float) -> None:
    weights = list(WEIGHTS)
    weights[3] = value
    error = rejected(document(weights=weights))
    assert str(error) == f"curve: weights[3]: got {value!r}, must be finite and > 0"


def test_knot_count_is_points_plus_degree_plus_one() -> None:
    error = rejected(document(knots=KNOTS[:10]))
    assert str(error) == (
        "curve: knots: got 10 knots, must be control points + degree + 1 = 7 + 3 + 1 = 11"
    )


@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_knots_are_finite(value: float) -> None:
    knots = list(KNOTS)
    knots[5] = value
    error = rejected(document(knots=knots))
    assert str(error) == f"curve: knots[5]: got {value!r}, must be finite"


def test_knots_are_non_decreasing() -> None:
    knots = list(KNOTS)
    knots[5] = 0.3
    error = rejected(document(knots=knots))
    assert str(error) == (
        "curve: knots[5]: got 0.3 after knots[4] = 0.4531, knots must be non-decreasing"
    )


def test_first_degree_plus_one_knots_are_equal() -> None:
    knots = [0, 0, 0, 0.1, 0.4531, 0.5485, 0.6306, 1, 1, 1, 1]
    error = rejected(document(knots=knots))
    assert str(error) == (
        "curve: knots[0..3]: got [0.0, 0.0, 0.0, 0.1], the first degree + 1 = 4 knots must be "
        "equal (clamped knot vector)"
    )


def test_last_degree_plus_one_knots_are_equal() -> None:
    knots = [0, 0, 0, 0, 0.4531, 0.5485, 0.6306, 0.9, 1, 1, 1]
    error = rejected(document(knots=knots))
    assert str(error) == (
        "curve: knots[7..10]: got [0.9, 1.0, 1.0, 1.0], the last degree + 1 = 4 knots must be "
        "equal (clamped knot vector)"
    )


def test_first_knot_is_below_the_last() -> None:
    error = rejected(document(knots=[2.5] * 11))
    assert str(error) == "curve: knots: first knot 2.5 equals last knot 2.5, first must be < last"


def test_end_knots_repeat_exactly_degree_plus_one_times() -> None:
    knots = [0, 0, 0, 0, 0, 0.5485, 0.6306, 1, 1, 1, 1]
    error = rejected(document(knots=knots))
    assert str(error) == (
        "curve: knots[0..4]: value 0.0 repeats 5 times as the first knot, an end knot must "
        "repeat exactly degree + 1 = 4 times (clamped)"
    )


def test_interior_knot_multiplicity_is_at_most_degree() -> None:
    knots = [0, 0, 0, 0.5, 0.5, 0.5, 0.7, 1, 1, 1]
    error = rejected(document(degree=2, knots=knots))
    assert str(error) == (
        "curve: knots[3..5]: interior value 0.5 repeats 3 times, must repeat at most "
        "degree = 2 times (otherwise the curve is discontinuous)"
    )


def test_interior_knot_of_multiplicity_degree_is_allowed() -> None:
    knots = [0, 0, 0, 0.5, 0.5, 0.7, 0.8, 1, 1, 1]
    assert NurbsCurve.from_mapping(document(degree=2, knots=knots)).degree == 2


def test_distinct_knots_resolve_the_path_between_them() -> None:
    # Knots one ulp apart: u has no value inside the span, whose 1 mm of path the tool would
    # jump in one period (found by a property run: 250 mm/s on a 20 mm/s plan).
    knots = [0, 0, 0.05, 0.05000000000000001, 0.5, 0.75, 1, 1]
    points = [[0, 0], [0, 0], [0, 1], [0, 0], [0, 0], [0, 0]]
    error = rejected(document(degree=1, control_points=points, weights=[1.0] * 6, knots=knots))
    assert error.rule is CurveRule.KNOT_SPACING
    assert str(error) == (
        "curve: knots[2..3]: got 0.05 and 0.05000000000000001, 6.94e-18 apart: one step of the "
        "parameter there (one ulp) moves the tool by up to 1 mm, must be at most 1e-06 mm "
        "(space them further apart, or merge them where the degree allows)"
    )
    # Equal knots hold no span, and knots 1e-9 apart resolve 1 mm to 1e-8 mm.
    knots[3] = 0.05 + 1e-9
    assert (
        NurbsCurve.from_mapping(
            document(degree=1, control_points=points, weights=[1.0] * 6, knots=knots)
        ).degree
        == 1
    )


def test_curve_has_non_zero_length() -> None:
    error = rejected(document(control_points=[[5, 5, 4]] * 7))
    assert str(error) == (
        "curve: control_points: all 7 points equal [5.0, 5.0, 4.0], the curve must have "
        "non-zero length"
    )


def test_unknown_key_is_named() -> None:
    error = rejected(document(colour="red"))
    assert error.field == "colour"
    assert str(error) == (
        "curve: colour: unknown key, allowed keys are control_points, degree, knots, weights"
    )


@pytest.mark.parametrize("key", ["degree", "control_points", "knots"])
def test_missing_required_key_is_named(key: str) -> None:
    data = document()
    del data[key]
    assert str(rejected(data)) == f"curve: {key}: missing, this key is required"


def test_document_must_be_a_mapping() -> None:
    assert str(rejected([1, 2, 3])) == (
        "curve: document: got list, must be a mapping with keys "
        "degree, control_points, knots, weights"
    )


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        (
            {"control_points": "abc"},
            "curve: control_points: got 'abc', must be a list of [x, y] or [x, y, z] points",
        ),
        (
            {"control_points": [5, *POINTS[1:]]},
            "curve: control_points[0]: got 5, must be a list of 2 or 3 numbers",
        ),
        (
            {"control_points": [POINTS[0], [25, 40, "x"], *POINTS[2:]]},
            "curve: control_points[1][2]: got 'x', must be a number",
        ),
        (
            {"control_points": [POINTS[0], [25, True, 9], *POINTS[2:]]},
            "curve: control_points[1][1]: got True, must be a number",
        ),
        ({"weights": "heavy"}, "curve: weights: got 'heavy', must be a list of numbers"),
        ({"weights": [1, 1, None, 1, 1, 1, 1]}, "curve: weights[2]: got None, must be a number"),
        ({"knots": 4}, "curve: knots: got 4, must be a list of numbers"),
        (
            {"knots": [0, 0, 0, "0", 0.5, 0.5, 0.6, 1, 1, 1, 1]},
            "curve: knots[3]: got '0', must be a number",
        ),
    ],
)
def test_wrong_types_are_named(changes: dict[str, Any], message: str) -> None:
    assert str(rejected(document(**changes))) == message


def test_from_arrays_rejects_a_flat_point_list_and_non_numbers() -> None:
    with pytest.raises(CurveError) as caught:
        NurbsCurve.from_arrays(1, [0.0, 1.0, 2.0], [0, 0, 1, 1])
    assert str(caught.value) == (
        "curve: control_points: got an array of shape (3,), must be a list of points "
        "(n, 2) or (n, 3)"
    )
    with pytest.raises(CurveError) as caught:
        NurbsCurve.from_arrays(1, [[0, 0], [1, 1]], ["a", "b", "c", "d"])
    assert str(caught.value) == (
        "curve: knots: got ['a', 'b', 'c', 'd'], must be an array of numbers"
    )
