"""Exceptions of the planner package.

Hierarchy::

    PlannerError                 base of every planner error
     ├── CurveError (ValueError) a NURBS curve, its document, or a parameter on it is invalid
     └── StartTooFast (ValueError) a start state that cannot stop before the curve's end

Messages name the field, the offending value and the rule it breaks, for example
``curve: weights[3]: got -0.2, must be finite and > 0``.
"""

from __future__ import annotations

from enum import Enum


class PlannerError(Exception):
    """Base of every planner error."""


class CurveRule(Enum):
    """The rule a curve breaks, for callers that answer with a code (e.g. the HMI)."""

    FORMAT = "format"
    """The document: a missing or unknown key, a value of the wrong type."""
    DEGREE = "degree"
    """The degree is not an integer >= 1."""
    DIMENSION = "dimension"
    """Points are not all 2-D or all 3-D (or have more coordinates than the machine has axes)."""
    TOO_FEW_POINTS = "too few points"
    """Fewer than degree + 1 control points."""
    NOT_FINITE = "not finite"
    """A coordinate or knot is NaN or infinite."""
    WEIGHT = "weight"
    """A weight is missing, not finite, or not > 0."""
    KNOT_COUNT = "knot count"
    """The number of knots is not points + degree + 1."""
    KNOT_ORDER = "knot order"
    """Knots decrease, or the first equals the last."""
    KNOT_CLAMP = "knot clamp"
    """The end knots are not repeated exactly degree + 1 times."""
    KNOT_MULTIPLICITY = "knot multiplicity"
    """An interior knot repeats more than degree times (the curve would be discontinuous)."""
    KNOT_SPACING = "knot spacing"
    """Two distinct knots so close that the parameter cannot resolve the path between them."""
    ZERO_LENGTH = "zero length"
    """All control points coincide."""
    PARAMETER = "parameter"
    """An argument of an evaluation (u, s, order) is outside its range."""
    TRAVEL = "travel"
    """The curve leaves an axis's travel limits (checked by the runtime)."""


class CurveError(PlannerError, ValueError):
    """A curve definition (or a parameter value on a curve) breaks a rule.

    :param field: the offending field, with its index where there is one
        (``"weights[3]"``, ``"knots[4..7]"``, ``"control_points[2][1]"``).
    :param message: the value found and the rule it breaks.
    :param rule: which rule, as a code.
    """

    def __init__(self, field: str, message: str, *, rule: CurveRule) -> None:
        super().__init__(f"curve: {field}: {message}")
        self.field = field
        self.message = message
        self.rule = rule


class StartTooFast(PlannerError, ValueError):
    """A start state from which no motion within the limits stops before the curve's end.

    Raised when the plan gets there instead of releasing a motion that would arrive at speed
    (a jump to rest on the last setpoint). A state taken from a plan of the same path never
    raises it, whatever the feed override.
    """

    def __init__(
        self, s_mm: float, v_mm_s: float, a_mm_s2: float, end_mm: float, end_feed_mm_s: float
    ) -> None:
        super().__init__(
            f"start: s {s_mm:.6f} mm, feed {v_mm_s:.6g} mm/s, acceleration {a_mm_s2:.6g} mm/s²: "
            f"cannot stop before the curve's end at {end_mm:.6f} mm within the limits "
            f"(it would get there at {end_feed_mm_s:.6g} mm/s)"
        )
