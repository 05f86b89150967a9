"""Arc length s(u) of a NURBS curve and its inverse u(s).

The parameter update of the paper (Wang, Zhao, Lu, Liu, China Mechanical Engineering 23(3),
2012, 299-304), eq. (2), predicts u by a Taylor expansion; its drift is removed by solving
s(u) = s_target with the exact arc length, s(u) = integral of |C'(t)| dt from the first knot.

The table is built once per curve. Every non-empty knot span is cut into ``samples_per_span``
equal table intervals (|C'| is smooth inside a span). A group of intervals is accepted when the
Gauss-Legendre value of the whole group agrees with the sum of the Gauss-Legendre values of its
intervals to ``_RTOL`` relative (plus a tiny absolute floor); otherwise each interval becomes a
group of its own and is cut again. The intervals of accepted groups, whose values are far more
accurate than the coarse rule that was checked, form the table; their cumulative sums give
s at the table points. All of it is vectorised over intervals, one numpy pass per refinement
level.

Between table points, s(u) = s(u_i) + Gauss-Legendre quadrature of |C'| over [u_i, u]; u(s)
starts from quintic Hermite interpolation of u, du/ds and d2u/ds2 at the table points (or from
a caller's guess inside the bracketing table interval) and takes Newton steps with
ds/du = |C'(u)|, falling back to bisection of the bracket where a step would leave it (for
example where C'(u) = 0 at a sharp corner). A step whose predicted error (d2s/du2)/2 du^2 is far
below the tolerance is accepted without another evaluation, so the usual cost of u(s) is one
quadrature and one evaluation of C', C'' at the answer.

Units: s and lengths in mm, u dimensionless.
Accuracy: about 1e-9 relative to the curve length or better for s(u); u(s) meets
|s(u) - s| <= 1e-10 mm, or the bracket shrinks to a few ulp of u.
Thread safety: immutable after construction; may be shared between threads.
Not modelled: lengths of offset curves or of anything but the curve itself.
"""

from __future__ import annotations

from numbers import Integral

import numpy as np
from numpy.typing import ArrayLike

from planner.errors import CurveError, CurveRule
from planner.nurbs import NurbsCurve

#: Gauss-Legendre nodes per table interval and per partial-interval quadrature.
_GAUSS_NODES = 7
#: Relative agreement required between a group's coarse value and the sum over its intervals.
_RTOL = 1e-10
#: Absolute floor of that agreement, relative to the curve length; ends refinement at cusps.
_ATOL_PER_LENGTH = 1e-14
#: Refinement levels after which a group is accepted regardless (each level halves it at least).
_MAX_LEVELS = 60
#: Target |s(u) - s| of u_of_s, mm.
_S_TOL_MM = 1e-10
#: Largest |s(u) - s| at which a Newton step may be accepted without checking it, mm.
_SETTLE_RESIDUAL_MM = 1e-5
#: Newton/bisection iterations of u_of_s before it stops at the best bracket.
_MAX_ITERATIONS = 100

_NODES, _WEIGHTS = np.polynomial.legendre.leggauss(_GAUSS_NODES)


class ArcLengthTable:
    """Arc length s(u) of a curve, accurate to ~1e-9 relative, built once per curve.

    :param curve: the curve.
    :param samples_per_span: table intervals each non-empty knot span starts with (>= 2, the
        check compares a group with its intervals); where |C'| needs it, refinement cuts every
        interval of a rejected group into as many again.
    :raises CurveError: if ``samples_per_span`` is not an integer >= 2.
    """

    def __init__(self, curve: NurbsCurve, *, samples_per_span: int = 2) -> None:
        if (
            isinstance(samples_per_span, bool)
            or not isinstance(samples_per_span, Integral)
            or samples_per_span < 2
        ):
            raise CurveError(
                "samples_per_span",
                f"got {samples_per_span!r}, must be an integer >= 2",
                rule=CurveRule.PARAMETER,
            )
        self.curve = curve
        self._u_grid, self._s_grid = _build_table(curve, int(samples_per_span))
        self.length_mm = float(self._s_grid[-1])
        self._du_ds, self._d2u_ds2 = _inverse_slopes(curve, self._u_grid)

    @property
    def u_grid(self) -> np.ndarray:
        """Table parameters, ascending, from the first to the last knot (read-only)."""
        return self._u_grid

    @property
    def s_grid(self) -> np.ndarray:
        """Arc length at :attr:`u_grid` in mm, from 0 to :attr:`length_mm` (read-only)."""
        return self._s_grid

    def s_of_u(self, u: ArrayLike) -> np.ndarray:
        """Arc length from the start of the curve to each parameter, in mm.

        :param u: parameter or array of parameters (flattened), each within the domain.
        :returns: 1-D array of s, exactly 0 at the first knot and :attr:`length_mm` at the last.
        :raises CurveError: for a parameter outside the domain or not finite.
        """
        params = _checked(u, "u", *self.curve.domain)
        i = np.minimum(np.searchsorted(self._u_grid, params, side="right") - 1, self._last)
        s = self._s_grid[i] + _gauss(self.curve, self._u_grid[i], params)
        s[params == self._u_grid[-1]] = self.length_mm
        return s

    def u_of_s(self, s: ArrayLike, u_guess: ArrayLike | None = None) -> np.ndarray:
        """Parameter at each arc length, inverse of :meth:`s_of_u`.

        :param s: arc length or array of arc lengths (flattened) in mm, within [0, length_mm].
        :param u_guess: optional starting parameters (same number as ``s``), e.g. a Taylor
            prediction; a guess outside the table interval that holds the answer is replaced by
            the table's own (quintic Hermite interpolation).
        :returns: 1-D array of u with |s_of_u(u) - s| <= 1e-10 mm (or u located to a few ulp).
        :raises CurveError: for an arc length outside [0, length_mm] or not finite, or a guess
            of the wrong size.
        """
        target = _checked(s, "s", 0.0, self.length_mm)
        i = np.minimum(np.searchsorted(self._s_grid, target, side="right") - 1, self._last)
        lo, hi = self._u_grid[i].copy(), self._u_grid[i + 1].copy()
        s_lo = self._s_grid[i]
        u = self._hermite_guess(i, target)
        if u_guess is not None:
            guess = np.asarray(u_guess, dtype=np.float64).ravel()
            if guess.shape != target.shape:
                raise CurveError(
                    "u_guess",
                    f"got {guess.size} values for {target.size} arc lengths, must match",
                    rule=CurveRule.PARAMETER,
                )
            inside = (guess >= lo) & (guess <= hi)
            u[inside] = guess[inside]
        u[target == self.length_mm] = self._u_grid[-1]
        self._newton(u, lo, hi, s_lo, target, i)
        return u

    def _hermite_guess(self, i: np.ndarray, target: np.ndarray) -> np.ndarray:
        """u(s) on table interval i by quintic Hermite interpolation of u, du/ds and d2u/ds2.

        Accurate enough that one Newton step usually settles; where the slopes are not finite
        (C' = 0 at a node) or the result leaves the interval, linear interpolation instead.
        """
        u0, u1 = self._u_grid[i], self._u_grid[i + 1]
        s0, s1 = self._s_grid[i], self._s_grid[i + 1]
        h = s1 - s0
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            t = np.clip((target - s0) / h, 0.0, 1.0)
            t2 = t * t
            t3 = t2 * t
            right = t3 * (10.0 - 15.0 * t + 6.0 * t2)
            u = (
                u0
                + (u1 - u0) * right
                + h * self._du_ds[i] * (t - t3 * (6.0 - 8.0 * t + 3.0 * t2))
                - h * self._du_ds[i + 1] * t3 * (4.0 - 7.0 * t + 3.0 * t2)
                + h * h * self._d2u_ds2[i] * 0.5 * t2 * (1.0 - t) ** 3
                + h * h * self._d2u_ds2[i + 1] * 0.5 * t3 * (1.0 - t) ** 2
            )
            linear = u0 + (u1 - u0) * t
        good = np.isfinite(u) & (u >= u0) & (u <= u1)
        return np.where(good, u, np.where(np.isfinite(linear), linear, u0))

    @property
    def _last(self) -> int:
        return len(self._u_grid) - 2

    def _newton(
        self,
        u: np.ndarray,
        lo: np.ndarray,
        hi: np.ndarray,
        s_lo: np.ndarray,
        target: np.ndarray,
        interval: np.ndarray,
    ) -> None:
        """Solve s_lo + integral from u_grid[interval] to u of |C'| = target in place."""
        active = np.flatnonzero(target < self.length_mm)
        start = self._u_grid[interval]
        for _ in range(_MAX_ITERATIONS):
            if active.size == 0:
                return
            ua = u[active]
            partial, ds_du, d2s_du2 = _integral_and_slope(self.curve, start[active], ua)
            residual = s_lo[active] + partial - target[active]
            below = residual < 0.0
            lo[active[below]] = ua[below]
            hi[active[~below]] = ua[~below]
            done = np.abs(residual) <= _S_TOL_MM
            la, ha = lo[active], hi[active]
            done |= ha - la <= 4.0 * np.spacing(np.maximum(np.abs(la), np.abs(ha)))
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                du = residual / ds_du
                # Newton leaves an error of about s''/2 du^2: far below the tolerance, the step
                # needs no further evaluation to be trusted.
                settled = (np.abs(residual) <= _SETTLE_RESIDUAL_MM) & (
                    0.5 * np.abs(d2s_du2) * du * du <= 0.25 * _S_TOL_MM
                )
            step = ua - du
            bisect = ~((step > la) & (step < ha))
            step[bisect] = 0.5 * (la[bisect] + ha[bisect])
            settled &= ~bisect
            moving = ~done
            u[active[moving]] = step[moving]
            active = active[moving & ~settled]


def _checked(values: ArrayLike, name: str, low: float, high: float) -> np.ndarray:
    try:
        array = np.asarray(values, dtype=np.float64).ravel()
    except (TypeError, ValueError) as exc:
        raise CurveError(
            name,
            f"got {values!r}, must be a number or an array of numbers",
            rule=CurveRule.PARAMETER,
        ) from exc
    outside = ~((array >= low) & (array <= high))
    if outside.any():
        bad = array[np.argmax(outside)]
        raise CurveError(
            name,
            f"got {float(bad)!r}, must be finite and within [{low!r}, {high!r}]",
            rule=CurveRule.PARAMETER,
        )
    return array


def _gauss(curve: NurbsCurve, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Gauss-Legendre integral of |C'| over each [a, b] (elementwise arrays)."""
    half = 0.5 * (b - a)
    nodes = (a + half)[:, None] + half[:, None] * _NODES
    speed = np.linalg.norm(curve.evaluate(nodes, order=1)[1], axis=1)
    return half * (speed.reshape(nodes.shape) @ _WEIGHTS)


def _integral_and_slope(
    curve: NurbsCurve, a: np.ndarray, b: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Integral of |C'| over each [a, b], ds/du = |C'(b)| and d2s/du2 = C'.C''/|C'| at b."""
    integral = _gauss(curve, a, b)
    _, d1, d2 = curve.evaluate(b, order=2)
    ds_du = np.linalg.norm(d1, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        d2s_du2 = np.einsum("ij,ij->i", d1, d2) / ds_du
    return integral, ds_du, d2s_du2


def _inverse_slopes(curve: NurbsCurve, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """du/ds = 1/|C'| and d2u/ds2 = -(C'.C'')/|C'|^4 at u (inf or nan where C' = 0)."""
    _, d1, d2 = curve.evaluate(u, order=2)
    speed2 = np.sum(d1 * d1, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return 1.0 / np.sqrt(speed2), -np.sum(d1 * d2, axis=1) / (speed2 * speed2)


def _build_table(curve: NurbsCurve, parts: int) -> tuple[np.ndarray, np.ndarray]:
    """Adaptive Gauss-Legendre table: returns read-only (u_grid, s_grid)."""
    breaks = curve.breakpoints
    group_a, group_b = breaks[:-1], breaks[1:]
    group_value = _gauss(curve, group_a, group_b)
    atol = _ATOL_PER_LENGTH * float(group_value.sum())
    fractions = np.arange(parts) / parts
    accepted_a: list[np.ndarray] = []
    accepted_value: list[np.ndarray] = []
    for level in range(_MAX_LEVELS + 1):
        width = (group_b - group_a)[:, None]
        edges = np.concatenate([group_a[:, None] + width * fractions, group_b[:, None]], axis=1)
        left, right = edges[:, :-1].ravel(), edges[:, 1:].ravel()
        value = _gauss(curve, left, right).reshape(-1, parts)
        refined = value.sum(axis=1)
        good = np.abs(refined - group_value) <= _RTOL * refined + atol
        # Intervals a few ulp wide cannot be cut any further.
        good |= width[:, 0] <= 64.0 * np.spacing(np.maximum(np.abs(group_a), np.abs(group_b)))
        if level == _MAX_LEVELS:
            good[:] = True
        accepted_a.append(left.reshape(-1, parts)[good].ravel())
        accepted_value.append(value[good].ravel())
        if good.all():
            break
        group_a = left.reshape(-1, parts)[~good].ravel()
        group_b = right.reshape(-1, parts)[~good].ravel()
        group_value = value[~good].ravel()
    starts = np.concatenate(accepted_a)
    values = np.concatenate(accepted_value)
    order = np.argsort(starts, kind="stable")
    u_grid = np.append(starts[order], breaks[-1])
    s_grid = np.concatenate([[0.0], np.cumsum(values[order])])
    u_grid.flags.writeable = False
    s_grid.flags.writeable = False
    return u_grid, s_grid
