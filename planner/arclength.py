"""Arc length s(u) of a NURBS curve and its inverse u(s).

The parameter update of the paper (Wang, Zhao, Lu, Liu, China Mechanical Engineering 23(3),
2012, 299-304), eq. (2), predicts u by a Taylor expansion; its drift is removed by solving
s(u) = s_target with the exact arc length, s(u) = integral of |C'(t)| dt from the first knot.

The table is built lazily, in chunks of ``CHUNK_SPANS`` knot spans in order along the curve,
when a query first reaches them (a stream's first setpoints need only the first chunk, however
long the curve). The speed |C'| is smooth inside a knot span; on each table
interval it is replaced by its Chebyshev interpolant of ``CHEBYSHEV_NODES`` nodes, and an
interval whose last two coefficients say the interpolant is not accurate to ``_RTOL`` of the
interval's length (plus a tiny absolute floor) is halved, starting from the knot spans (cut
into equal parts on curves of fewer than ``MIN_INTERVALS`` spans). All of it is vectorised
over intervals, one numpy pass per halving. The interpolant's antiderivative, a Chebyshev
series too, is s(u) on its interval: s_of_u evaluates series and no curve.

u(s) starts from quintic Hermite interpolation of u, du/ds and d2u/ds2 at the ends of the
interval that holds s (or from a caller's guess inside that interval) and takes Newton steps on
the series, with ds/du = |C'| from the interpolant, falling back to bisection of the bracket
where a step would leave it (for example where C'(u) = 0 at a sharp corner). A step whose
predicted error (the interval's bound of |d2s/dx2| / 2 dx^2, x its local parameter) is far
below the tolerance is accepted without another evaluation; u(s) usually takes two or three
Newton steps.

Units: s and lengths in mm, u dimensionless.
Accuracy: about 1e-11 relative to the curve length for s(u) where |C'| is smooth (at a cusp
inside a span, down to the absolute floor); u(s) meets |s(u) - s| <= 1e-10 mm, or the bracket
shrinks to a few ulp of x.
Thread safety: the table grows on first use, so one thread at a time may query it; once
complete (after :attr:`ArcLengthTable.length_mm`), it no longer changes and may be shared.
Not modelled: lengths of offset curves or of anything but the curve itself.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from planner.errors import CurveError, CurveRule
from planner.nurbs import NurbsCurve

#: Chebyshev nodes (first kind) per table interval, the degree of the speed interpolant + 1.
CHEBYSHEV_NODES = 16
#: Table intervals a curve starts with, at least (each knot span cut into equal parts): on a
#: curve of few spans, extra intervals cost less than extra halving passes, and give u(s) a
#: closer first guess.
MIN_INTERVALS = 16
#: Estimated error of an interval's length allowed, relative to that length.
_RTOL = 1e-11
#: Absolute floor of that error, relative to the length of the control polygon (at least the
#: curve's); ends refinement at cusps.
_ATOL_PER_LENGTH = 1e-14
#: Halvings after which an interval is accepted regardless.
_MAX_LEVELS = 60
#: Knot spans per chunk of the table (built when a query first needs it).
CHUNK_SPANS = 256
#: Curve evaluations per call while the table is built (bounds its memory on long curves).
_EVALUATION_CHUNK = 1 << 16
#: Share of an interval's accepted error that the terms dropped from its evaluation may add.
_TRIM_SHARE = 0.1
#: Target |s(u) - s| of u_of_s, mm.
_S_TOL_MM = 1e-10
#: Largest |s(u) - s| at which a Newton step may be accepted without checking it, mm.
_SETTLE_RESIDUAL_MM = 1e-5
#: Newton/bisection iterations of u_of_s before it stops at the best bracket.
_MAX_ITERATIONS = 100

_ANGLES = np.pi * (np.arange(CHEBYSHEV_NODES) + 0.5) / CHEBYSHEV_NODES
#: Interpolation nodes on [-1, 1], strictly inside: a knot's one-sided speeds never mix.
_NODES = np.cos(_ANGLES)
#: Chebyshev coefficients from the values at _NODES: a = values @ _TO_COEFFICIENTS.
_TO_COEFFICIENTS = (2.0 / CHEBYSHEV_NODES) * np.cos(np.outer(_ANGLES, np.arange(CHEBYSHEV_NODES)))
_TO_COEFFICIENTS[:, 0] *= 0.5
_EVEN = np.arange(0, CHEBYSHEV_NODES, 2)
#: Integral of T_k over [-1, 1] for even k (zero for odd k).
_EVEN_INTEGRALS = 2.0 / (1.0 - _EVEN**2)
_SIGNS = (-1.0) ** np.arange(CHEBYSHEV_NODES)
_SQUARES = np.arange(CHEBYSHEV_NODES) ** 2.0


class ArcLengthTable:
    """Arc length s(u) of a curve, accurate to ~1e-11 relative, built lazily chunk by chunk.

    The table is built in chunks of ``CHUNK_SPANS`` knot spans, in order along the curve, when
    a query first needs one: :meth:`s_of_u` up to the chunk of its largest parameter,
    :meth:`u_of_s` until its largest arc length is covered. :attr:`length_mm`, :attr:`u_grid`
    and :attr:`s_grid` need the whole table (on a 100,000-span curve about half a second of
    CPU time and 50 MB); :meth:`extent_mm` answers "where does the curve end, if before s?"
    with only the chunks up to s.

    :param curve: the curve.
    """

    def __init__(self, curve: NurbsCurve) -> None:
        self.curve = curve
        self._breaks = curve.breakpoints
        spans = len(self._breaks) - 1
        self._split = -(-MIN_INTERVALS // spans)
        polygon_mm = float(np.linalg.norm(np.diff(curve.control_points, axis=0), axis=1).sum())
        self._floor_mm = _ATOL_PER_LENGTH * polygon_mm
        self._chunk_count = -(-spans // CHUNK_SPANS)
        self._chunks: list[_Chunk] = []
        # Arc length at the start of each built chunk, and at the end of the last one.
        self._chunk_s = np.zeros(1)
        self._whole: _Chunk | None = None

    @property
    def complete(self) -> bool:
        """Whether the whole curve is in the table (its length is known)."""
        return len(self._chunks) == self._chunk_count

    @property
    def built_mm(self) -> float:
        """Arc length covered by the chunks built so far, in mm."""
        return float(self._chunk_s[-1])

    @property
    def length_mm(self) -> float:
        """Length of the curve in mm (builds the whole table)."""
        self._cover(np.inf)
        return self.built_mm

    def extent_mm(self, s_mm: float) -> float:
        """min(s_mm, length of the curve): builds only the chunks up to s_mm."""
        self._cover(s_mm)
        return min(s_mm, self.built_mm) if self.complete else s_mm

    def breakpoint_s(self, first: int, last: int) -> np.ndarray:
        """Arc lengths of breakpoints ``first`` to ``last`` (inclusive), in mm."""
        c0, c1 = first // CHUNK_SPANS, max(last - 1, first) // CHUNK_SPANS
        self._build_chunk(c1)
        # Neighbouring chunks share a breakpoint: each after the first drops its start.
        s = np.concatenate([self._chunks[c].break_s[(c > c0) :] for c in range(c0, c1 + 1)])
        return s[first - c0 * CHUNK_SPANS : last - c0 * CHUNK_SPANS + 1]

    def span_at_s(self, s_mm: float) -> int:
        """Index of the knot span holding arc length s_mm (the last span beyond the end)."""
        self._cover(s_mm)
        c = min(int(np.searchsorted(self._chunk_s, s_mm, side="right")) - 1, len(self._chunks) - 1)
        chunk = self._chunks[max(c, 0)]
        local = int(np.searchsorted(chunk.break_s, s_mm, side="right")) - 1
        return max(c, 0) * CHUNK_SPANS + min(max(local, 0), len(chunk.break_s) - 2)

    @property
    def u_grid(self) -> np.ndarray:
        """Parameters of the table's interval ends, ascending, from the first to the last knot
        (every breakpoint among them; read-only; builds the whole table)."""
        return self._whole_table().u_grid

    @property
    def s_grid(self) -> np.ndarray:
        """Arc length at :attr:`u_grid` in mm, from 0 to :attr:`length_mm` (read-only)."""
        return self._whole_table().s_grid

    def s_of_u(self, u: ArrayLike) -> np.ndarray:
        """Arc length from the start of the curve to each parameter, in mm.

        :param u: parameter or array of parameters (flattened), each within the domain.
        :returns: 1-D array of s, exactly 0 at the first knot and :attr:`length_mm` at the last.
        :raises CurveError: for a parameter outside the domain or not finite.
        """
        params = _checked(u, "u", *self.curve.domain)
        if params.size == 0:
            return params.copy()
        spans = np.minimum(
            np.searchsorted(self._breaks, params, side="right") - 1, len(self._breaks) - 2
        )
        chunk_of = spans // CHUNK_SPANS
        self._build_chunk(int(chunk_of.max()))
        out = np.empty(params.size)
        for c in np.unique(chunk_of).tolist():
            rows = chunk_of == c
            out[rows] = self._chunks[c].s_of_u(params[rows])
        out[params == self._breaks[-1]] = self.built_mm
        return out

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
        target = _as_array(s, "s")
        valid = (target >= 0.0) & (target < np.inf)
        top = float(target[valid].max()) if valid.any() else 0.0
        self._cover(top)
        if not valid.all() or top > self.built_mm:
            # The message names the length: the error path may build the whole table.
            _checked(target, "s", 0.0, self.length_mm)
        guess = None
        if u_guess is not None:
            guess = np.asarray(u_guess, dtype=np.float64).ravel()
            if guess.shape != target.shape:
                raise CurveError(
                    "u_guess",
                    f"got {guess.size} values for {target.size} arc lengths, must match",
                    rule=CurveRule.PARAMETER,
                )
        chunk_of = np.minimum(
            np.searchsorted(self._chunk_s, target, side="right") - 1, len(self._chunks) - 1
        )
        out = np.empty(target.size)
        for c in np.unique(chunk_of).tolist():
            rows = chunk_of == c
            out[rows] = self._chunks[c].u_of_s(target[rows], None if guess is None else guess[rows])
        if self.complete:
            out[target == self.built_mm] = self._breaks[-1]
        return out

    def _cover(self, s_mm: float) -> None:
        """Build chunks until one holds s_mm strictly inside or the curve ends."""
        while not self.complete and self.built_mm <= s_mm:
            self._build_chunk(len(self._chunks))

    def _build_chunk(self, index: int) -> None:
        """Build chunks in order up to ``index`` (inclusive)."""
        while len(self._chunks) <= min(index, self._chunk_count - 1):
            c = len(self._chunks)
            first, last = c * CHUNK_SPANS, min((c + 1) * CHUNK_SPANS, len(self._breaks) - 1)
            chunk = _Chunk(
                self.curve,
                self._breaks[first : last + 1],
                self._split,
                self._floor_mm,
                float(self._chunk_s[-1]),
            )
            self._chunks.append(chunk)
            self._chunk_s = np.append(self._chunk_s, chunk.s_end)

    def _whole_table(self) -> _Chunk:
        if self._whole is None:
            self._cover(np.inf)
            self._whole = _Chunk.joined(self._chunks)
        return self._whole


class _Chunk:
    """The table over consecutive knot spans: Chebyshev series of |C'| and of s on intervals."""

    def __init__(
        self,
        curve: NurbsCurve | None,
        breaks: np.ndarray,
        split: int,
        floor_mm: float,
        s_start: float,
        table: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> None:
        lo, hi, speed = table if table is not None else _build_table(curve, breaks, split, floor_mm)
        half = 0.5 * (hi - lo)
        # |C'| = sum a_k T_k(x) with u = lo + (x + 1) half; its antiderivative from x = -1,
        # times half, is the arc length from the interval's start in mm. Queries evaluate only
        # the terms that matter anywhere on the chunk (a smooth curve's last few are far below
        # the tolerance; evaluating the series is most of u(s) and s(u)).
        self._speed = speed
        self._terms = _terms_needed(speed, half, floor_mm)
        self._ds_dx = speed[:, : self._terms] * half[:, None]
        self._length = _antiderivative(speed[:, : self._terms]) * half[:, None]
        self._lo, self._hi, self._half = lo, hi, half
        self.u_grid = np.append(lo, hi[-1])
        self.s_grid = s_start + np.concatenate([[0.0], np.cumsum(self._length.sum(axis=1))])
        for array in (self.u_grid, self.s_grid):
            array.flags.writeable = False
        self.s_end = float(self.s_grid[-1])
        self.breaks = breaks
        self.break_s = self.s_grid[np.searchsorted(self.u_grid, breaks)]
        # |C'| and d|C'|/du at each interval's start and end (T_k(+-1) = (+-1)^k,
        # T_k'(+-1) = (+-1)^(k+1) k^2), for the Hermite guess of u(s).
        ends = np.stack([speed @ _SIGNS, speed.sum(axis=1)], axis=1)
        slopes = np.stack([-(speed @ (_SIGNS * _SQUARES)), speed @ _SQUARES], axis=1)
        slopes /= half[:, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            self._du_ds = 1.0 / ends
            self._d2u_ds2 = -slopes / ends**3
        # |d2s/dx2| <= half sum k^2 |a_k| (|T_k'| <= k^2): bounds the error of a Newton step.
        self._d2s_dx2_bound = half * (np.abs(speed) @ _SQUARES)

    @staticmethod
    def joined(chunks: list[_Chunk]) -> _Chunk:
        """One chunk holding the intervals of consecutive ``chunks``."""
        if len(chunks) == 1:
            return chunks[0]
        table = tuple(
            np.concatenate([getattr(c, name) for c in chunks]) for name in ("_lo", "_hi", "_speed")
        )
        breaks = np.unique(np.concatenate([c.breaks for c in chunks]))
        return _Chunk(None, breaks, 0, 0.0, 0.0, table)

    @property
    def _last(self) -> int:
        return len(self._lo) - 1

    def s_of_u(self, params: np.ndarray) -> np.ndarray:
        i = np.minimum(np.searchsorted(self.u_grid, params, side="right") - 1, self._last)
        x = self._local(i, params)
        s = self.s_grid[i] + _series(_chebyshev_t(x, self._terms + 1), self._length[i].T)
        at_start = params == self._lo[i]
        s[at_start] = self.s_grid[i][at_start]
        s[params == self.u_grid[-1]] = self.s_end
        return s

    def u_of_s(self, target: np.ndarray, guess: np.ndarray | None) -> np.ndarray:
        i = np.minimum(np.searchsorted(self.s_grid, target, side="right") - 1, self._last)
        i = np.maximum(i, 0)
        u = self._hermite_guess(i, target)
        if guess is not None:
            inside = (guess >= self._lo[i]) & (guess <= self._hi[i])
            u[inside] = guess[inside]
        x = self._newton(i, self._local(i, u), target - self.s_grid[i])
        # Exact at both ends of the interval.
        return np.where(
            x <= 0.0,
            self._lo[i] + (x + 1.0) * self._half[i],
            self._hi[i] - (1.0 - x) * self._half[i],
        )

    def _local(self, i: np.ndarray, u: np.ndarray) -> np.ndarray:
        """x in [-1, 1] of u on interval i, exactly -1 and 1 at its ends."""
        lo, hi = self._lo[i], self._hi[i]
        return np.clip(((u - lo) - (hi - u)) / (hi - lo), -1.0, 1.0)

    def _hermite_guess(self, i: np.ndarray, target: np.ndarray) -> np.ndarray:
        """u(s) on interval i by quintic Hermite interpolation of u, du/ds and d2u/ds2.

        Where the slopes are not finite (C' = 0 at an end) or the result leaves the interval,
        linear interpolation instead.
        """
        u0, u1 = self._lo[i], self._hi[i]
        s0, s1 = self.s_grid[i], self.s_grid[i + 1]
        v0, v1 = self._du_ds[i, 0], self._du_ds[i, 1]
        w0, w1 = self._d2u_ds2[i, 0], self._d2u_ds2[i, 1]
        h = s1 - s0
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            t = np.clip((target - s0) / h, 0.0, 1.0)
            t2 = t * t
            t3 = t2 * t
            u = (
                u0
                + (u1 - u0) * t3 * (10.0 - 15.0 * t + 6.0 * t2)
                + h * v0 * (t - t3 * (6.0 - 8.0 * t + 3.0 * t2))
                - h * v1 * t3 * (4.0 - 7.0 * t + 3.0 * t2)
                + h * h * w0 * 0.5 * t2 * (1.0 - t) ** 3
                + h * h * w1 * 0.5 * t3 * (1.0 - t) ** 2
            )
            linear = u0 + (u1 - u0) * t
        good = np.isfinite(u) & (u >= u0) & (u <= u1)
        return np.where(good, u, np.where(np.isfinite(linear), linear, u0))

    def _newton(self, i: np.ndarray, x: np.ndarray, offset: np.ndarray) -> np.ndarray:
        """Solve length_i(x) = offset for x in [-1, 1], from the guess x."""
        length = self._length[i].T
        slope = self._ds_dx[i].T
        bound = self._d2s_dx2_bound[i]
        lo, hi = np.full(x.size, -1.0), np.full(x.size, 1.0)
        active = np.arange(x.size)
        for _ in range(_MAX_ITERATIONS):
            if active.size == 0:
                break
            xa = x[active]
            whole = active.size == x.size
            t = _chebyshev_t(xa, self._terms + 1)
            residual = _series(t, length if whole else length[:, active]) - offset[active]
            ds_dx = _series(t, slope if whole else slope[:, active])
            below = residual < 0.0
            lo[active[below]] = xa[below]
            hi[active[~below]] = xa[~below]
            la, ha = lo[active], hi[active]
            done = (np.abs(residual) <= _S_TOL_MM) | (ha - la <= 4.0 * np.spacing(1.0))
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                dx = residual / ds_dx
                # Newton leaves an error of at most bound/2 dx^2: far below the tolerance, the
                # step needs no further evaluation to be trusted.
                settled = (np.abs(residual) <= _SETTLE_RESIDUAL_MM) & (
                    0.5 * bound[active] * dx * dx <= 0.25 * _S_TOL_MM
                )
            step = xa - dx
            bisect = ~((step > la) & (step < ha))
            step[bisect] = 0.5 * (la[bisect] + ha[bisect])
            settled &= ~bisect
            moving = ~done
            x[active[moving]] = step[moving]
            active = active[moving & ~settled]
        return x


def _terms_needed(speed: np.ndarray, half: np.ndarray, floor_mm: float) -> int:
    """The fewest leading terms of the speed series (one per row) whose dropped tail changes
    no interval's length by more than ``_TRIM_SHARE`` of its accepted error (a term's
    antiderivative stays within 2 half over the interval)."""
    length = 2.0 * half * speed[:, 0]
    allowed = _TRIM_SHARE * (_RTOL * np.abs(length) + floor_mm)
    tails = 2.0 * half[:, None] * np.cumsum(np.abs(speed[:, ::-1]), axis=1)[:, ::-1]
    fits = np.all(tails <= allowed[:, None], axis=0)
    # fits[k]: dropping terms k onwards is harmless; keep at least two terms.
    harmless = np.flatnonzero(fits[2:])
    return 2 + int(harmless[0]) if harmless.size else speed.shape[1]


def _chebyshev_t(x: np.ndarray, terms: int) -> np.ndarray:
    """T_k(x) for k < terms (rows) at each x in [-1, 1] (columns), by the three-term recurrence
    T_k = 2x T_k-1 - T_k-2."""
    t = np.empty((terms, x.size))
    t[0] = 1.0
    t[1] = x
    twice = 2.0 * x
    for k in range(2, terms):
        np.multiply(twice, t[k - 1], out=t[k])
        t[k] -= t[k - 2]
    return t


def _series(t: np.ndarray, coefficients: np.ndarray) -> np.ndarray:
    """sum_k coefficients[k] T_k(x) for each column, from :func:`_chebyshev_t` rows ``t``."""
    return np.einsum("km,km->m", t[: len(coefficients)], coefficients)


def _antiderivative(coefficients: np.ndarray) -> np.ndarray:
    """Chebyshev coefficients (one series per row) of the integral from -1 of each series.

    From the integrals of T_0 (T_1), T_1 (T_2 / 4) and T_k, k >= 2,
    (T_k+1 / (k + 1) - T_k-1 / (k - 1)) / 2; the constant term makes the value 0 at x = -1.
    """
    rows, terms = coefficients.shape
    padded = np.zeros((rows, terms + 2))
    padded[:, :terms] = coefficients
    padded[:, 0] *= 2.0
    result = np.empty((rows, terms + 1))
    result[:, 1:] = (padded[:, :terms] - padded[:, 2:]) / (2.0 * np.arange(1, terms + 1))
    result[:, 0] = -(result[:, 1:] @ (-1.0) ** np.arange(1, terms + 1))
    return result


def _as_array(values: ArrayLike, name: str) -> np.ndarray:
    try:
        return np.asarray(values, dtype=np.float64).ravel()
    except (TypeError, ValueError) as exc:
        raise CurveError(
            name,
            f"got {values!r}, must be a number or an array of numbers",
            rule=CurveRule.PARAMETER,
        ) from exc


def _checked(values: ArrayLike, name: str, low: float, high: float) -> np.ndarray:
    array = _as_array(values, name)
    outside = ~((array >= low) & (array <= high))
    if outside.any():
        bad = array[np.argmax(outside)]
        raise CurveError(
            name,
            f"got {float(bad)!r}, must be finite and within [{low!r}, {high!r}]",
            rule=CurveRule.PARAMETER,
        )
    return array


def _speeds(curve: NurbsCurve, u: np.ndarray) -> np.ndarray:
    """|C'(u)| for an array of parameters, evaluated a chunk at a time."""
    flat = u.ravel()
    out = np.empty(flat.size)
    for start in range(0, flat.size, _EVALUATION_CHUNK):
        chunk = flat[start : start + _EVALUATION_CHUNK]
        out[start : start + chunk.size] = np.linalg.norm(curve.evaluate(chunk, order=1)[1], axis=1)
    return out.reshape(u.shape)


def _build_table(
    curve: NurbsCurve, breaks: np.ndarray, split: int, floor: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Intervals (lo, hi), ascending, over the spans between ``breaks`` (each first cut into
    ``split`` equal parts), and the Chebyshev coefficients of |C'| on each."""
    edges = np.linspace(breaks[:-1], breaks[1:], split + 1, axis=1)
    lo, hi = edges[:, :-1].ravel(), edges[:, 1:].ravel()
    lo, hi = lo[hi > lo], hi[hi > lo]  # a span a few ulp wide has fewer distinct parts
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    for level in range(_MAX_LEVELS + 1):
        half = 0.5 * (hi - lo)
        speed = _speeds(curve, (0.5 * (lo + hi))[:, None] + half[:, None] * _NODES)
        coefficients = speed @ _TO_COEFFICIENTS
        length = half * (coefficients[:, _EVEN] @ _EVEN_INTEGRALS)
        # The last coefficients stand for the tail the interpolant leaves out; a term's
        # antiderivative stays within 2 half over the interval.
        error = 2.0 * half * np.abs(coefficients[:, -2:]).sum(axis=1)
        good = error <= _RTOL * length + floor
        # Intervals a few ulp wide cannot be cut any further.
        good |= hi - lo <= 64.0 * np.spacing(np.maximum(np.abs(lo), np.abs(hi)))
        if level == _MAX_LEVELS:
            good[:] = True
        parts.append((lo[good], hi[good], coefficients[good]))
        if good.all():
            break
        lo, hi = lo[~good], hi[~good]
        mid = 0.5 * (lo + hi)
        lo, hi = np.concatenate([lo, mid]), np.concatenate([mid, hi])
    lo, hi, coefficients = (np.concatenate(column) for column in zip(*parts, strict=True))
    order = np.argsort(lo, kind="stable")
    return lo[order], hi[order], coefficients[order]
