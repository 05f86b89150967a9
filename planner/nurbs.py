"""NURBS curves: validation and vectorised evaluation of points and derivatives.

The tool path of the paper (Wang, Zhao, Lu, Liu, China Mechanical Engineering 23(3), 2012,
299-304), eq. (1): C(u) = (x(u), y(u), z(u)), a rational B-spline of degree p over a clamped knot
vector, here on the general domain [first knot, last knot] rather than only [0, 1].

Evaluation follows The NURBS Book (Piegl and Tiller, 2nd ed.). Once per curve, the homogeneous
form C^w(u) = sum N_i,p(u) (w_i P_i, w_i) on each non-empty knot span is turned into a
polynomial in the span's local parameter t in [0, 1], its Taylor coefficients from the
B-spline basis functions and their derivatives at the span's start (A2.3, with eq. 2.9,
vectorised over spans). Evaluation finds the span by binary search (as A2.1, over the
breakpoints), evaluates the polynomial and its derivatives by Horner's rule, vectorised over
an array of parameters (loops run only over degree and derivative order), then applies A4.2 for
the derivatives of the rational curve from those of its homogeneous form.

Units: control points and every derived point in mm; u is dimensionless; the k-th derivative
with respect to u is in mm per unit of u to the k; curvature in 1/mm.

Invariants of a constructed :class:`NurbsCurve` (checked once, vectorised, in
``__post_init__``): degree >= 1; at least degree + 1 control points of dimension 2 or 3, finite,
not all equal; finite weights > 0, one per point; knots finite, non-decreasing, clamped (the
first and the last value repeated exactly degree + 1 times), first < last, every interior knot
value repeated at most degree times (so the curve is continuous), distinct knots far enough
apart that one ulp of u moves the curve by at most ``PARAMETER_RESOLUTION_MM`` (or setpoints
inside the span could not be placed: a span one ulp wide jumps its whole length in one
period). Its arrays are read-only.

Thread safety: instances are immutable and may be shared between threads.

Not modelled: unclamped or periodic knot vectors, knot insertion or any other editing of a
curve, and derivatives beyond the third.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from numbers import Integral, Real
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from planner.errors import CurveError, CurveRule

#: Highest derivative order that :meth:`NurbsCurve.evaluate` computes.
MAX_ORDER = 3
#: Most a knot span's path may move over one step of the parameter (one ulp of u), mm.
PARAMETER_RESOLUTION_MM = 1e-6

#: Spans converted to polynomial form per pass while a curve is built.
_TAYLOR_CHUNK = 1 << 15

_KEYS_REQUIRED = ("degree", "control_points", "knots")
_KEYS_OPTIONAL = ("weights",)


@dataclass(frozen=True, eq=False)
class NurbsCurve:
    """A validated, immutable NURBS curve in the plane or in space.

    Build it with :meth:`from_arrays` (weights optional) or :meth:`from_mapping` (a YAML
    document); the constructor validates too and raises :class:`CurveError` naming the first
    broken rule.

    :param degree: polynomial degree p >= 1.
    :param control_points: (n, dim) control points in mm, dim 2 or 3.
    :param weights: (n,) weights, finite and > 0.
    :param knots: (n + p + 1,) clamped knot vector.
    """

    degree: int
    control_points: np.ndarray = field(repr=False)
    weights: np.ndarray = field(repr=False)
    knots: np.ndarray = field(repr=False)
    _rational: bool = field(init=False, repr=False)
    _breaks: np.ndarray = field(init=False, repr=False)
    _inverse_widths: np.ndarray = field(init=False, repr=False)
    _taylor: np.ndarray = field(init=False, repr=False)
    _falling: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        degree = _validated_degree(self.degree)
        points = _validated_points(self.control_points, degree)
        weights = _validated_weights(self.weights, len(points))
        knots = _validated_knots(self.knots, degree, len(points))
        _check_nonzero_length(points)
        _check_parameter_resolution(knots, degree, points, weights)
        # Equal weights cancel: the curve is a B-spline and needs no division by w(u).
        rational = bool((weights != weights[0]).any())
        homogeneous = (
            np.hstack([points * weights[:, None], weights[:, None]]) if rational else points
        )
        breaks, taylor = _taylor_coefficients(knots, degree, homogeneous)
        for name, value in (
            ("_rational", rational),
            ("_breaks", breaks),
            ("_inverse_widths", 1.0 / np.diff(breaks)),
            ("_taylor", taylor),
            # _falling[k, i] = i! / (i - k)!, the factor of t^(i-k) in the k-th derivative.
            (
                "_falling",
                np.array(
                    [[math.perm(i, k) for i in range(degree + 1)] for k in range(MAX_ORDER + 1)],
                    dtype=float,
                ),
            ),
            ("degree", degree),
            ("control_points", points),
            ("weights", weights),
            ("knots", knots),
        ):
            if isinstance(value, np.ndarray):
                value.flags.writeable = False
            object.__setattr__(self, name, value)

    @classmethod
    def from_arrays(
        cls,
        degree: int,
        control_points: ArrayLike,
        knots: ArrayLike,
        weights: ArrayLike | None = None,
    ) -> NurbsCurve:
        """Build a curve from array-likes; weights default to 1 (a non-rational B-spline).

        :raises CurveError: if any rule listed in the module docstring is broken.
        """
        points = _float_array("control_points", control_points)
        if weights is None:
            weights = np.ones(len(points) if points.ndim >= 1 else 0)
        return cls(
            degree=degree,
            control_points=points,
            weights=_float_array("weights", weights),
            knots=_float_array("knots", knots),
        )

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any]) -> NurbsCurve:
        """Build a curve from a parsed document (e.g. YAML).

        Keys: ``degree`` (int), ``control_points`` (list of [x, y] or [x, y, z] in mm),
        ``knots`` (list of numbers) and optionally ``weights`` (list of numbers, default 1).

        :raises CurveError: for an unknown or missing key, a value of the wrong type, or any
            broken curve rule.
        """
        if not isinstance(data, Mapping):
            raise CurveError(
                "document",
                f"got {type(data).__name__}, must be a mapping with keys "
                f"{', '.join(_KEYS_REQUIRED + _KEYS_OPTIONAL)}",
                rule=CurveRule.FORMAT,
            )
        allowed = _KEYS_REQUIRED + _KEYS_OPTIONAL
        for key in data:
            if key not in allowed:
                raise CurveError(
                    str(key),
                    f"unknown key, allowed keys are {', '.join(sorted(allowed))}",
                    rule=CurveRule.FORMAT,
                )
        for key in _KEYS_REQUIRED:
            if key not in data:
                raise CurveError(key, "missing, this key is required", rule=CurveRule.FORMAT)
        points = data["control_points"]
        if not _is_list(points):
            raise CurveError(
                "control_points",
                f"got {points!r}, must be a list of [x, y] or [x, y, z] points",
                rule=CurveRule.FORMAT,
            )
        for i, point in enumerate(points):
            if not _is_list(point):
                raise CurveError(
                    f"control_points[{i}]",
                    f"got {point!r}, must be a list of 2 or 3 numbers",
                    rule=CurveRule.FORMAT,
                )
            _check_numbers(f"control_points[{i}]", point)
        weights = data.get("weights")
        if weights is not None:
            _check_number_list("weights", weights)
        _check_number_list("knots", data["knots"])
        return cls.from_arrays(data["degree"], points, data["knots"], weights)

    def __repr__(self) -> str:
        return (
            f"NurbsCurve(degree={self.degree}, points={len(self.control_points)}, "
            f"dimension={self.dimension}, domain={self.domain})"
        )

    @property
    def dimension(self) -> int:
        """Number of coordinates of a point: 2 (planar) or 3 (spatial)."""
        return int(self.control_points.shape[1])

    @property
    def domain(self) -> tuple[float, float]:
        """Parameter domain (first knot, last knot)."""
        return float(self.knots[0]), float(self.knots[-1])

    @property
    def breakpoints(self) -> np.ndarray:
        """Distinct knot values, ascending: the ends of the non-empty knot spans (read-only)."""
        return self._breaks

    @property
    def start_point(self) -> np.ndarray:
        """C(first knot), equal to the first control point (mm)."""
        return self.control_points[0]

    @property
    def end_point(self) -> np.ndarray:
        """C(last knot), equal to the last control point (mm)."""
        return self.control_points[-1]

    def evaluate(self, u: ArrayLike, order: int = 0) -> np.ndarray:
        """Points and derivatives C, C', C'', C''' at parameters ``u``.

        :param u: parameter or array of parameters (flattened to m values), each finite and
            within :attr:`domain`.
        :param order: highest derivative order, 0 to 3.
        :returns: array of shape (order + 1, m, dimension); row k holds the k-th derivative
            (mm per unit u to the k). At the first and last knot row 0 is exactly the first
            and last control point.
        :raises CurveError: for an order outside 0..3 or a parameter outside the domain.
        """
        if (
            isinstance(order, bool)
            or not isinstance(order, Integral)
            or not 0 <= order <= MAX_ORDER
        ):
            raise CurveError(
                "order",
                f"got {order!r}, must be an integer from 0 to {MAX_ORDER}",
                rule=CurveRule.PARAMETER,
            )
        params = self._checked_parameters(u)
        p = self.degree
        breaks = self._breaks
        # A knot value belongs to the span it starts; the last knot to the last span.
        span = np.minimum(np.searchsorted(breaks, params, side="right") - 1, len(breaks) - 2)
        inverse_width = self._inverse_widths[span]
        t = ((params - breaks[span]) * inverse_width)[:, None]
        # np.take: an order of magnitude faster than fancy indexing for these gathers.
        coefficients = np.take(self._taylor, span, axis=1)
        # Derivatives of the homogeneous curve: A^(k) in the first columns, w^(k) in the last;
        # the k-th derivative of sum c_i t^i is sum_{i>=k} c_i i!/(i-k)! t^(i-k), by Horner.
        homogeneous = np.zeros((order + 1, params.size, self._taylor.shape[2]))
        for k in range(min(order, p) + 1):
            factor = self._falling[k]
            value = coefficients[p] * factor[p] if k else coefficients[p]
            for i in range(p - 1, k - 1, -1):
                value = value * t + (coefficients[i] * factor[i] if k else coefficients[i])
            homogeneous[k] = value * (inverse_width**k)[:, None] if k else value
        if self._rational:
            a_ders = homogeneous[..., :-1]
            w_ders = homogeneous[..., -1:]
            ders = np.empty_like(a_ders)
            for k in range(order + 1):  # The NURBS Book A4.2
                value = a_ders[k].copy()
                for i in range(1, k + 1):
                    value -= math.comb(k, i) * w_ders[i] * ders[k - i]
                ders[k] = value / w_ders[0]
        else:
            ders = homogeneous
        # The ends are interpolated exactly; floating point would otherwise leave ~1 ulp.
        ders[0][params == self.knots[0]] = self.control_points[0]
        ders[0][params == self.knots[-1]] = self.control_points[-1]
        return ders

    def point(self, u: float) -> np.ndarray:
        """C(u) as a (dimension,) array in mm."""
        return self.evaluate(u)[0, 0]

    def curvature(self, u: ArrayLike, still_speed: float = 0.0) -> np.ndarray:
        """Curvature kappa(u) = |C' x C''| / |C'|^3 in 1/mm, one value per parameter.

        Where C'(u) = 0 (a cusp or a sharp corner made by repeated control points) the radius of
        curvature is zero and kappa is ``inf``; also where |C'| is at most ``still_speed`` (mm
        per unit of u): a rational curve leaves round-off there, not 0, and its curvature is
        noise.
        """
        _, d1, d2 = self.evaluate(u, order=2)
        if self.dimension == 2:
            cross = np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
        else:
            cross = np.linalg.norm(np.cross(d1, d2), axis=1)
        speed = np.linalg.norm(d1, axis=1)
        kappa = np.full(speed.shape, math.inf)
        moving = speed > still_speed
        with np.errstate(over="ignore", divide="ignore"):  # a speed near 0 gives kappa -> inf
            kappa[moving] = cross[moving] / speed[moving] ** 3
        return kappa

    def _checked_parameters(self, u: ArrayLike) -> np.ndarray:
        try:
            params = np.asarray(u, dtype=np.float64).ravel()
        except (TypeError, ValueError) as exc:
            raise CurveError(
                "u", f"got {u!r}, must be a number or an array of numbers", rule=CurveRule.PARAMETER
            ) from exc
        low, high = self.knots[0], self.knots[-1]
        outside = ~((params >= low) & (params <= high))
        if outside.any():
            bad = params[np.argmax(outside)]
            raise CurveError(
                "u",
                f"got {float(bad)!r}, must be finite and within the domain "
                f"[{float(low)!r}, {float(high)!r}]",
                rule=CurveRule.PARAMETER,
            )
        return params


def _taylor_coefficients(
    knots: np.ndarray, p: int, homogeneous: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Breakpoints, and the homogeneous curve on each non-empty span as a polynomial in
    t = (u - start) / width: taylor[i, j] = A^(i)(start_j) width_j^i / i! (A with w last)."""
    breaks = np.unique(knots)
    starts = breaks[:-1]
    span = np.searchsorted(knots, starts, side="right") - 1
    taylor = np.empty((p + 1, starts.size, homogeneous.shape[1]))
    widths = np.diff(breaks)
    factorials = np.array([float(math.factorial(i)) for i in range(p + 1)])
    for first in range(0, starts.size, _TAYLOR_CHUNK):  # bounded memory on long curves
        chunk = slice(first, first + _TAYLOR_CHUNK)
        basis = _basis_derivatives(knots, p, span[chunk], starts[chunk], p)
        rows = homogeneous[span[chunk] + np.arange(-p, 1)[:, None]]
        ders = np.einsum("kim,imc->kmc", basis, rows)
        scale = widths[chunk] ** np.arange(p + 1)[:, None] / factorials[:, None]
        taylor[:, chunk] = ders * scale[:, :, None]
    for array in (breaks, taylor):
        array.flags.writeable = False
    return breaks, taylor


def _basis_derivatives(
    knots: np.ndarray, p: int, span: np.ndarray, u: np.ndarray, n_der: int
) -> np.ndarray:
    """B-spline basis functions and their derivatives at u, vectorised over u.

    The NURBS Book A2.3, organised a degree at a time: the triangle of basis functions of
    rising degree (A2.2, ``ndu`` in the book) is built for all functions of one degree at once;
    the k-th derivatives apply eq. (2.9),
    N'_{i,d} = d (N_{i,d-1} / (t_{i+d} - t_i) - N_{i+1,d-1} / (t_{i+d+1} - t_{i+1})),
    k times to the functions of degree p - k, which is where A2.3's coefficients a_{k,j} come
    from. Knot differences inside a non-empty span are never zero.

    :returns: ders of shape (n_der + 1, p + 1, m): ders[k, j] = N^(k)_{span-p+j, p}(u).
    """
    m = u.size
    offsets = np.arange(1, p + 1)[:, None]
    left = u - knots[span + 1 - offsets]  # left[j - 1] = u - t[span + 1 - j]
    right = knots[span + offsets] - u  # right[j - 1] = t[span + j] - u
    # levels[d][r] = N_{span-d+r, d}(u); inverses[d][r] = 1 / (t[span+1+r] - t[span+1+r-d]).
    levels = [np.ones((1, m))]
    inverses = [np.empty((0, m))]
    for d in range(1, p + 1):
        inverse = 1.0 / (right[:d] + left[d - 1 :: -1])
        temp = levels[-1] * inverse
        values = np.empty((d + 1, m))
        values[:d] = right[:d] * temp
        values[d] = 0.0
        values[1:] += left[d - 1 :: -1] * temp
        levels.append(values)
        inverses.append(inverse)
    ders = np.zeros((n_der + 1, p + 1, m))
    ders[0] = levels[p]
    for k in range(1, min(n_der, p) + 1):
        values = levels[p - k]
        for d in range(p - k + 1, p + 1):  # eq. (2.9), raising derivative and degree by one
            scaled = values * inverses[d]
            values = np.empty((d + 1, m))
            values[0] = -scaled[0]
            values[1:d] = scaled[:-1] - scaled[1:]
            values[d] = scaled[-1]
            values *= d
        ders[k] = values
    return ders


def _is_list(value: object) -> bool:
    return isinstance(value, Sequence) and not isinstance(value, (str, bytes))


def _check_numbers(name: str, values: Sequence[object]) -> None:
    for i, value in enumerate(values):
        if isinstance(value, bool) or not isinstance(value, Real):
            raise CurveError(
                f"{name}[{i}]", f"got {value!r}, must be a number", rule=CurveRule.FORMAT
            )


def _check_number_list(name: str, values: object) -> None:
    if not _is_list(values):
        raise CurveError(name, f"got {values!r}, must be a list of numbers", rule=CurveRule.FORMAT)
    _check_numbers(name, values)


def _float_array(name: str, value: ArrayLike) -> np.ndarray:
    try:
        return np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        if name == "control_points" and _is_list(value) and value and _is_list(value[0]):
            expected = len(value[0])
            for i, point in enumerate(value):
                if not _is_list(point) or len(point) != expected:
                    raise CurveError(
                        f"control_points[{i}]",
                        f"got {point!r}, every point must have the same dimension as "
                        f"control_points[0] ({expected})",
                        rule=CurveRule.DIMENSION,
                    ) from exc
        raise CurveError(
            name, f"got {value!r}, must be an array of numbers", rule=CurveRule.FORMAT
        ) from exc


def _validated_degree(degree: object) -> int:
    if isinstance(degree, bool) or not isinstance(degree, Integral) or degree < 1:
        raise CurveError(
            "degree", f"got {degree!r}, must be an integer >= 1", rule=CurveRule.DEGREE
        )
    return int(degree)


def _validated_points(points: ArrayLike, degree: int) -> np.ndarray:
    points = _float_array("control_points", points)
    if points.ndim != 2:
        raise CurveError(
            "control_points",
            f"got an array of shape {points.shape}, must be a list of points (n, 2) or (n, 3)",
            rule=CurveRule.DIMENSION,
        )
    n, dim = points.shape
    if dim not in (2, 3):
        raise CurveError(
            "control_points",
            f"points have {dim} coordinates, the dimension must be 2 or 3",
            rule=CurveRule.DIMENSION,
        )
    if n < degree + 1:
        raise CurveError(
            "control_points",
            f"got {n} points, must be at least degree + 1 = {degree + 1}",
            rule=CurveRule.TOO_FEW_POINTS,
        )
    finite = np.isfinite(points)
    if not finite.all():
        i, j = np.argwhere(~finite)[0]
        raise CurveError(
            f"control_points[{i}][{j}]",
            f"got {float(points[i, j])!r}, must be finite",
            rule=CurveRule.NOT_FINITE,
        )
    return points


def _validated_weights(weights: ArrayLike, n_points: int) -> np.ndarray:
    weights = _float_array("weights", weights)
    if weights.ndim != 1 or len(weights) != n_points:
        raise CurveError(
            "weights",
            f"got {weights.size} weights for {n_points} control points, "
            "must be one weight per control point",
            rule=CurveRule.WEIGHT,
        )
    good = np.isfinite(weights) & (weights > 0.0)
    if not good.all():
        i = int(np.argmax(~good))
        raise CurveError(
            f"weights[{i}]",
            f"got {float(weights[i])!r}, must be finite and > 0",
            rule=CurveRule.WEIGHT,
        )
    return weights


def _validated_knots(knots: ArrayLike, degree: int, n_points: int) -> np.ndarray:
    knots = _float_array("knots", knots)
    expected = n_points + degree + 1
    if knots.ndim != 1 or len(knots) != expected:
        raise CurveError(
            "knots",
            f"got {knots.size} knots, must be control points + degree + 1 = "
            f"{n_points} + {degree} + 1 = {expected}",
            rule=CurveRule.KNOT_COUNT,
        )
    finite = np.isfinite(knots)
    if not finite.all():
        i = int(np.argmax(~finite))
        raise CurveError(
            f"knots[{i}]", f"got {float(knots[i])!r}, must be finite", rule=CurveRule.NOT_FINITE
        )
    falling = np.diff(knots) < 0.0
    if falling.any():
        i = int(np.argmax(falling)) + 1
        raise CurveError(
            f"knots[{i}]",
            f"got {float(knots[i])!r} after knots[{i - 1}] = {float(knots[i - 1])!r}, "
            "knots must be non-decreasing",
            rule=CurveRule.KNOT_ORDER,
        )
    p = degree
    for name, block, first in (
        ("first", knots[: p + 1], 0),
        ("last", knots[-(p + 1) :], expected - p - 1),
    ):
        if (block != block[0]).any():
            raise CurveError(
                f"knots[{first}..{first + p}]",
                f"got {block.tolist()}, the {name} degree + 1 = {p + 1} knots must be equal "
                "(clamped knot vector)",
                rule=CurveRule.KNOT_CLAMP,
            )
    if not knots[0] < knots[-1]:
        raise CurveError(
            "knots",
            f"first knot {float(knots[0])!r} equals last knot {float(knots[-1])!r}, "
            "first must be < last",
            rule=CurveRule.KNOT_ORDER,
        )
    # Runs of equal knot values: [starts[r], starts[r] + counts[r]).
    starts = np.flatnonzero(np.concatenate(([True], np.diff(knots) != 0.0)))
    counts = np.diff(np.append(starts, expected))
    for run, where in ((0, "first"), (-1, "last")):
        if counts[run] != p + 1:
            begin = starts[run]
            raise CurveError(
                f"knots[{begin}..{begin + counts[run] - 1}]",
                f"value {float(knots[begin])!r} repeats {counts[run]} times as the {where} knot, "
                f"an end knot must repeat exactly degree + 1 = {p + 1} times (clamped)",
                rule=CurveRule.KNOT_CLAMP,
            )
    too_many = counts[1:-1] > p
    if too_many.any():
        run = int(np.argmax(too_many)) + 1
        begin = starts[run]
        raise CurveError(
            f"knots[{begin}..{begin + counts[run] - 1}]",
            f"interior value {float(knots[begin])!r} repeats {counts[run]} times, "
            f"must repeat at most degree = {p} times (otherwise the curve is discontinuous)",
            rule=CurveRule.KNOT_MULTIPLICITY,
        )
    return knots


def _check_parameter_resolution(
    knots: np.ndarray, p: int, points: np.ndarray, weights: np.ndarray
) -> None:
    """Every non-empty span resolves its path: one ulp of u moves the curve by at most
    PARAMETER_RESOLUTION_MM.

    On span [knots[k], knots[k + 1]), |C'| is at most the largest of the derivative's control
    points Q_i = p (P_i+1 - P_i) / (knots[i + p + 1] - knots[i + 1]), i = k - p .. k - 1
    (The NURBS Book, eq. 3.4), times (w_max / w_min)² over the span's weights for a rational
    curve (a bound, not the exact value); one ulp of u moves it by |C'| ulp.
    """
    n = len(points)
    reach = knots[p + 1 : n + p] - knots[1:n]
    with np.errstate(divide="ignore"):
        q = p * np.linalg.norm(np.diff(points, axis=0), axis=1) / reach
    k = np.arange(p, n)
    # Over each span's window (shifted copies: faster than a sliding window's reduction).
    speed = np.max([q[j : j + n - p] for j in range(p)], axis=0)
    w_max = np.max([weights[j : j + n - p] for j in range(p + 1)], axis=0)
    w_min = np.min([weights[j : j + n - p] for j in range(p + 1)], axis=0)
    speed = speed * (w_max / w_min) ** 2
    width = knots[k + 1] - knots[k]
    ulp = np.spacing(np.maximum(np.abs(knots[k]), np.abs(knots[k + 1])))
    move = np.where(width > 0.0, speed * ulp, 0.0)
    coarse = move > PARAMETER_RESOLUTION_MM
    if coarse.any():
        i = int(np.argmax(coarse))
        j = int(k[i])
        raise CurveError(
            f"knots[{j}..{j + 1}]",
            f"got {float(knots[j])!r} and {float(knots[j + 1])!r}, {float(width[i]):.3g} apart: "
            f"one step of the parameter there (one ulp) moves the tool by up to "
            f"{float(move[i]):.3g} mm, must be at most {PARAMETER_RESOLUTION_MM} mm (space "
            "them further apart, or merge them where the degree allows)",
            rule=CurveRule.KNOT_SPACING,
        )


def _check_nonzero_length(points: np.ndarray) -> None:
    if (points == points[0]).all():
        raise CurveError(
            "control_points",
            f"all {len(points)} points equal {points[0].tolist()}, the curve must have "
            "non-zero length",
            rule=CurveRule.ZERO_LENGTH,
        )
