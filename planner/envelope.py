"""Geometric feed limit along the arc length, v_limit(s), built lazily chunk by chunk.

Source: the pre-interpolation of section 2.2 of Wang, Zhao, Lu, Liu, China Mechanical
Engineering 23(3), 2012, 299-304: the feed limit of eq. (4) (and the optional limits of
:mod:`planner.feed`) is sampled on a grid of every knot span, the curvature maxima refined, in
place of the paper's step-by-step pre-interpolation at vmax.

Beyond the paper: the limits other than the chord error (the chord-deficit jerk, with its jumps
at knots, and the accelerations) depend on the steps either side of a setpoint, so each sample
is lowered to those a whole period's step from it can reach (the dilation,
:mod:`planner.dilation`, exact for the piecewise-linear limit between samples, and never across
a stop); then the chord deficit's change from step to step is checked at each sample
(:func:`planner.feed.chord_deficit_change_feed`). The chord-error feed is not dilated: a
chord's deviation from the curve is set by the curvature around its middle (to first order,
L^2 kappa / 8 with kappa at the middle), where the look-ahead keeps the plan's feed under the
limit, and that feed is at least the step's mean feed L / T less J T^2 / 24 (0.013 mm/s with
the bench's limits: within ``CHORD_MARGIN`` of delta above about 1 mm/s). Sharp corners and
cusps (C'(u) = 0 with a turning tangent) are stops (limit 0) with a grid refined towards them;
the curvature maxima are located by a shrinking grid search of the curvature itself, so that a
tip far narrower than the grid is planned at its own radius.

Units: s in mm, feeds in mm/s, u dimensionless. Chunks of ``CHUNK_SPANS`` knot spans are
computed when a query first reaches them and the last ``CACHE_CHUNKS`` are kept, so memory does
not grow with the length of the curve. One envelope per path; not thread-safe (it shares the
lazily built arc-length table).

Invariants: samples are ascending in s; a zero limit is a stop; no NaN.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from planner.arclength import ArcLengthTable
from planner.dilation import reach_lowered
from planner.feed import (
    binding_curvature,
    chord_deficit_change_feed,
    curvature_jump_feed,
    geometric_feed_limits,
    normal_cosine,
    singular_floor_feed,
)
from planner.nurbs import PARAMETER_RESOLUTION_MM, NurbsCurve
from planner.types import Limits

#: Target spacing of the envelope grid along the path, mm. Where the limit changes fast the
#: grid is halved (``TIGHT_CHANGE``) and curvature peaks are searched between samples, so the
#: base spacing matters only where the limit is smooth. Against 0.4 mm, the bench's 15 family
#: and paper plans each moved by 2 periods or less (38.860 s -> 38.876 s in all; chord error
#: still <= 0.97 delta), and the smooth curve's planning CPU time fell by about 16 %.
GRID_SPACING_MM = 1.0
#: Grid samples per knot span, at least and at most.
GRID_MIN_PER_SPAN, GRID_MAX_PER_SPAN = 8, 128
#: Relative change of the feed limit across a grid interval above which it is halved, and the
#: most halvings.
TIGHT_CHANGE, TIGHT_LEVELS = 0.05, 8
#: The same where another limit than the chord error's binds (per-axis feed and acceleration,
#: normal acceleration): the per-axis feed limit V_k / |t_k| falling convexly towards V_k was
#: exceeded by 1.06 % between samples 4 % apart.
TIGHT_CHANGE_OTHER = 0.01
#: Knot spans per envelope chunk, and chunks kept in the cache.
CHUNK_SPANS, CACHE_CHUNKS = 256, 16
#: Feed limits below this are treated as a stop, mm/s.
MIN_FEED_MM_S = 1e-6
#: 1 - cos of the tangent turn at a knot above which the knot is a sharp corner.
CORNER_COS_TOL = 1e-12
#: Ternary-search steps locating a cusp inside a span.
CUSP_SEARCH_STEPS = 60
#: |C'| relative to the largest |C'| on the chunk's grid at or below which the curve is still
#: (round-off): a reversal there is a cusp (a stop; the search ends about 1e-11 from a true
#: cusp), and its curvature is noise, not a peak to search.
CUSP_SPEED_RTOL = 1e-6
#: Points, at halving distances, at which a grid interval is searched for a reversal towards
#: an end where C' = 0 (the last is 2^-40 of the interval from it).
STILL_END_HALVINGS = 40
#: A near-cusp is a tip, not a stop, where its feed limit is above this many singular floors
#: (planner.feed.singular_floor_feed).
TIP_FLOOR_RATIO = 4.0
#: Passes that look for curvature maxima the refined samples show and no search found yet.
MISSED_PEAK_PASSES = 3
#: Rounds and points per round of the search of a curvature maximum between its grid
#: neighbours (each round shrinks the bracket to 2 / (points + 1) of it).
PEAK_SEARCH_STEPS, PEAK_SEARCH_POINTS = 6, 9
#: Relative change of the curvature across a bracket below which its peak is resolved.
PEAK_FLAT_RTOL = 1e-5
#: Ternary-search steps locating where a tangent component peaks between grid samples (the
#: bracket shrinks to 3e-4 of two grid intervals, where the component is flat).
AXIS_SEARCH_STEPS = 20
#: Samples around such a peak, in grid intervals from it.
AXIS_PEAK_OFFSETS = np.array([-0.5, -0.25, -0.125, 0.0, 0.125, 0.25, 0.5])
#: Halvings of the grid towards a sharp corner (C'(u) = 0).
CORNER_REFINEMENTS = 30
#: The envelope dilation assumes feed overrides up to this ratio of the path's vmax.
MAX_OVERRIDE_RATIO = 2.0
#: Fraction of the chord error kept as margin when planning.
CHORD_MARGIN = 0.03


def curvature_slope(d1: np.ndarray, d2: np.ndarray, d3: np.ndarray) -> np.ndarray:
    """dkappa/du from the rows of C', C'' and the third derivative D3 (0 where the curve is
    straight, C' x C'' = 0).

    With c = C' x C'' (dc/du = C' x D3), kappa = |c| / |C'|^3 and
    dkappa/du = ((c . dc/du) |C'|^2 - 3 |c|^2 (C' . C'')) / (|c| |C'|^5).
    """
    if d1.shape[1] == 2:
        c = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
        dc = d1[:, 0] * d3[:, 1] - d1[:, 1] * d3[:, 0]
        c_dc, c_c = c * dc, c * c
    else:
        c, dc = np.cross(d1, d2), np.cross(d1, d3)
        c_dc, c_c = np.einsum("ij,ij->i", c, dc), np.einsum("ij,ij->i", c, c)
    speed2 = np.einsum("ij,ij->i", d1, d1)
    numerator = c_dc * speed2 - 3.0 * c_c * np.einsum("ij,ij->i", d1, d2)
    denominator = np.sqrt(c_c) * speed2 * speed2 * np.sqrt(speed2)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(denominator > 0.0, numerator / denominator, 0.0)


def hermite_peaks(
    du: np.ndarray, k0: np.ndarray, k1: np.ndarray, slope0: np.ndarray, slope1: np.ndarray
) -> np.ndarray:
    """Whether the cubic Hermite interpolant of the curvature over each grid interval (values
    k0, k1 and slopes dkappa/du at its ends, du long) has a maximum inside it.

    Catches a peak that the signs of the end slopes hide: both ends rising (a peak, then a
    dip) or both falling (a dip, then a peak). With p'(t) = a t² + b t + m0 on t in [0, 1]
    (m = slope du), the maximum is the root where p'' = 2 a t + b < 0.
    """
    # A corner's inf curvature, or slopes so steep next to a cusp that b² overflows: no peak
    # found here (the cusps' and tips' own searches take those).
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        m0, m1, rise = slope0 * du, slope1 * du, k1 - k0
        a = 3.0 * (m0 + m1) - 6.0 * rise
        b = 6.0 * rise - 4.0 * m0 - 2.0 * m1
        quadratic = (-b - np.sqrt(b * b - 4.0 * a * m0)) / (2.0 * a)
        t_max = np.where(a != 0.0, quadratic, np.where(b < 0.0, -m0 / b, np.nan))
    return (t_max > 0.0) & (t_max < 1.0)


def range_minima(padded: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """min(padded[lo:hi]) for each pair, lo < hi, of a 1-D array whose last entry is a
    sentinel (so that hi may reach it), in one reduceat over the interleaved bounds: the odd
    results, from one range's end to the next one's start, are dropped, and the array is cut
    after the highest bound, or the last of them would run to its end."""
    bounds = np.stack([lo, hi], axis=1).ravel()
    return np.minimum.reduceat(padded[: bounds.max() + 1], bounds)[::2]


def ternary_minima(
    lo: np.ndarray,
    hi: np.ndarray,
    value: Callable[[np.ndarray], np.ndarray],
    steps: int,
) -> np.ndarray:
    """Where ``value`` is lowest in each bracket ``[lo, hi]`` (unimodal there), to the bracket
    left after ``steps`` thirds. ``value`` takes every bracket's two inner points at once:
    the left ones, then the right ones."""
    for _ in range(steps):
        a, b = lo + (hi - lo) / 3.0, hi - (hi - lo) / 3.0
        both = value(np.concatenate([a, b]))
        left = both[: a.size] < both[a.size :]
        hi = np.where(left, b, hi)
        lo = np.where(left, lo, a)
    return 0.5 * (lo + hi)


def _pointing_apart(
    u: np.ndarray, d1: np.ndarray, still_mm: float
) -> tuple[np.ndarray, np.ndarray]:
    """Brackets (lo, hi) from each parameter where |C'| (``d1``) is above ``still_mm`` to the
    next such one, where their tangents point apart (turn by more than 90 degrees)."""
    rows = np.flatnonzero(np.linalg.norm(d1, axis=1) > still_mm)
    turn = np.sum(d1[rows[:-1]] * d1[rows[1:]], axis=1) < 0.0
    return u[rows[:-1][turn]], u[rows[1:][turn]]


def _other_peaks(
    k: np.ndarray, best: np.ndarray, least_kappa: float
) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of the local maxima of each row of ``k`` besides its highest
    (column ``best``), above ``least_kappa``, that rise more than ``PEAK_FLAT_RTOL`` above the
    lowest value between them and it.

    A grid interval can hold two peaks: a degree-5 curve's curvature rose to 22 /mm, fell to 1
    and rose to 10 /mm between two grid samples; the search followed the higher peak alone, and
    the plan passed the other, 11 µm from a lower sample it took for the limit's minimum, at
    1.05 delta.
    """
    local = np.ones(k.shape, dtype=bool)
    local[:, 1:] = k[:, 1:] > k[:, :-1]
    local[:, :-1] &= k[:, :-1] >= k[:, 1:]
    # Most brackets hold one peak: only those with more local maxima go on.
    several = np.flatnonzero(np.count_nonzero(local, axis=1) > 1)
    if several.size == 0:
        return several, several
    k, best, local = k[several], best[several], local[several]
    columns = np.arange(k.shape[1])
    left, right = columns < best[:, None], columns > best[:, None]
    # The lowest value from each column to the best one, both included.
    towards_left = np.minimum.accumulate(np.where(right, np.inf, k)[:, ::-1], axis=1)[:, ::-1]
    towards_right = np.minimum.accumulate(np.where(left, np.inf, k), axis=1)
    between = np.full(k.shape, np.inf)
    between[:, :-1] = np.where(left[:, :-1], towards_left[:, 1:], np.inf)
    between[:, 1:] = np.where(right[:, 1:], towards_right[:, :-1], between[:, 1:])
    with np.errstate(invalid="ignore"):
        other = local & (left | right) & (k > least_kappa) & (k > between * (1.0 + PEAK_FLAT_RTOL))
    rows, found = np.nonzero(other)
    return several[rows], found


def _trios(u: np.ndarray, peaks: np.ndarray) -> np.ndarray:
    """Each peak and two neighbours a tenth of the sample interval around it away, so that the
    limit, interpolated linearly, rises from the tip as the curvature falls."""
    i = np.clip(np.searchsorted(u, peaks), 1, len(u) - 1)
    width = 0.1 * (u[i] - u[i - 1])
    return np.clip(np.stack([peaks - width, peaks, peaks + width], axis=1), u[0], u[-1]).ravel()


def _tight_change(v: np.ndarray) -> np.ndarray:
    """The relative change of the feed limit allowed across a grid interval from each sample
    (``v``'s rows): by which of the limit's two parts binds there."""
    return np.where(v[:, 1] < v[:, 0], TIGHT_CHANGE_OTHER, TIGHT_CHANGE)


def _lower_part(v: np.ndarray) -> np.ndarray:
    """The lower of the feed limit's two parts (``v``'s columns) at each sample.

    Not ``v.min(axis=1)``: a reduction along rows of two is some 50 times slower, and the
    envelope took it five times per chunk (6 % of the smooth curve's planning).
    """
    return np.minimum(v[:, 0], v[:, 1])


def _snapped_to_stops(s_mm: np.ndarray, stop: np.ndarray) -> np.ndarray:
    """Ascending ``s_mm`` with the samples within PARAMETER_RESOLUTION_MM of a stop moved onto
    it (merged with it by the caller).

    At a cusp C'(u) = 0: the curvature of the samples the corner grid puts next to it is
    round-off (|C'| vanishes), and their feed limit falls to the singular floor even where the
    curve runs straight into the cusp and back. Reached by every step towards the cusp, they
    held each sample to its distance from them over a period (v <= d / T): the motion crept
    into the cusp and out again, about 40 ms per cusp at the bench's limits. Closer than the
    planner's resolution, they are the cusp.
    """
    stop_s = s_mm[stop]
    if stop_s.size == 0:
        return s_mm
    after = np.searchsorted(stop_s, s_mm).clip(max=stop_s.size - 1)
    before = (after - 1).clip(min=0)
    nearest = np.where(
        np.abs(stop_s[before] - s_mm) < np.abs(stop_s[after] - s_mm),
        stop_s[before],
        stop_s[after],
    )
    return np.where(np.abs(nearest - s_mm) <= PARAMETER_RESOLUTION_MM, nearest, s_mm)


class FeedEnvelope:
    """Geometric feed limit v_limit(s) of a curve (no vmax), computed lazily per chunk of spans.

    Each grid sample carries the feed limit of :func:`planner.feed.geometric_feed_limits`: its
    chord-error part as it is there (a step is held to it where its middle is), its other part
    lowered to the smallest, interpolated linearly between samples, within a period's step (T
    times its own limit, capped at ``MAX_OVERRIDE_RATIO`` x vmax) on either side and at its
    grid neighbours, so that the steps around a setpoint never see a larger curvature than
    planned. Sharp corners (feed limit 0) keep their single zero sample and a grid refined
    towards them.
    """

    def __init__(
        self, curve: NurbsCurve, arc: ArcLengthTable, limits: Limits, period_s: float
    ) -> None:
        self._curve = curve
        self._arc = arc
        self._limits = limits
        self._T = period_s
        self._breaks = curve.breakpoints
        self._vcap_mm_s = MAX_OVERRIDE_RATIO * limits.vmax_mm_s
        self._step_cap_mm = self._vcap_mm_s * period_s
        # The sampled curvature can miss a little of a very sharp peak: plan a shade inside delta.
        self._planning_limits = replace(
            limits, chord_error_mm=limits.chord_error_mm * (1.0 - CHORD_MARGIN)
        )
        # Curvature peaks below this bind no plan: the search follows no other peaks there.
        self._binding_kappa = binding_curvature(self._planning_limits, period_s, self._vcap_mm_s)
        self._cache: OrderedDict[int, tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self._joined_last: tuple[tuple[int, int], tuple[np.ndarray, np.ndarray]] | None = None

    @property
    def spans(self) -> int:
        """Number of non-empty knot spans."""
        return len(self._breaks) - 1

    def query(self, s_lo: float, s_hi: float) -> tuple[np.ndarray, np.ndarray]:
        """Grid (s, v_limit) covering [s_lo, s_hi], from the sample at or before s_lo."""
        first = self._arc.span_at_s(s_lo)
        last = min(self._arc.span_at_s(s_hi) + 1, self.spans)
        s, v = self._joined(first // CHUNK_SPANS, (max(last, first + 1) - 1) // CHUNK_SPANS)
        i0 = max(int(np.searchsorted(s, s_lo, side="right")) - 1, 0)
        i1 = min(int(np.searchsorted(s, s_hi, side="left")) + 1, len(s))
        return s[i0:i1], v[i0:i1]

    def _joined(self, first: int, last: int) -> tuple[np.ndarray, np.ndarray]:
        """Samples of chunks ``first`` to ``last`` (inclusive), one read-only array each; the
        last ones joined are kept, since consecutive windows mostly query the same chunks."""
        if self._joined_last is not None and self._joined_last[0] == (first, last):
            return self._joined_last[1]
        s_parts, v_parts = [], []
        for chunk in range(first, last + 1):
            s, v = self._chunk(chunk)
            if s_parts:
                s, v = s[1:], v[1:]
            s_parts.append(s)
            v_parts.append(v)
        joined = (np.concatenate(s_parts), np.concatenate(v_parts))
        for array in joined:
            array.flags.writeable = False
        self._joined_last = ((first, last), joined)
        return joined

    def _chunk(self, chunk: int) -> tuple[np.ndarray, np.ndarray]:
        if chunk in self._cache:
            self._cache.move_to_end(chunk)
            return self._cache[chunk]
        a = chunk * CHUNK_SPANS
        b = min(a + CHUNK_SPANS, self.spans)
        margin = self._step_cap_mm
        s_a, s_b = self._arc.breakpoint_s(a, b)[[0, -1]]
        # The samples within a step of the chunk's ends see the neighbouring spans too.
        a_ext = max(self._arc.span_at_s(s_a - margin) - 1, 0)
        b_ext = min(self._arc.span_at_s(s_b + margin) + 2, self.spans)
        s, v = self._samples(a_ext, b_ext)
        keep = (s >= s_a) & (s <= s_b)
        result = (s[keep], v[keep])
        self._cache[chunk] = result
        if len(self._cache) > CACHE_CHUNKS:
            self._cache.popitem(last=False)
        return result

    def _samples(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        breaks = self._breaks
        lengths = np.diff(self._arc.breakpoint_s(a, b))
        counts = np.clip(
            np.ceil(lengths / GRID_SPACING_MM), GRID_MIN_PER_SPAN, GRID_MAX_PER_SPAN
        ).astype(int)
        span = np.repeat(np.arange(a, b), counts)
        offsets = np.repeat(np.cumsum(counts) - counts, counts)
        frac = (np.arange(counts.sum()) - offsets) / np.repeat(counts, counts)
        u = np.append(breaks[span] + (breaks[span + 1] - breaks[span]) * frac, breaks[b])
        # Curvature may jump at a knot (degree 2, repeated knots): keep the lower side's limit.
        # A tangent that turns at a knot is a sharp corner: the feed must come to 0 there.
        knot_rows = np.cumsum(counts)[:-1]
        below = np.nextafter(u[knot_rows], -np.inf)
        kappa, v, (_, d1, d2, d3) = self._limit(np.concatenate([u, below]), order=3)
        slope = curvature_slope(d1, d2, d3)
        # Where the curve is still (repeated control points: C' is round-off, not 0), its
        # curvature is noise: a stop, as where C' = 0. Passed at the feed of its noise, a
        # still knot where a degree-5 curve turned by 15 degrees measured 4.3 delta.
        speed = np.linalg.norm(d1, axis=1)
        still_mm = CUSP_SPEED_RTOL * speed.max()
        v[speed <= still_mm], kappa[speed <= still_mm] = 0.0, np.inf
        k_left, v_left, d_left, d2_left = kappa[u.size :], v[u.size :], d1[u.size :], d2[u.size :]
        kappa, v, d1, d2 = kappa[: u.size], v[: u.size], d1[: u.size], d2[: u.size]
        # The curvature and its slope at the end of each grid interval seen from inside it (the
        # left side of a knot). A peak hides between two samples where the curvature rises at
        # the first and falls at the second, or where its cubic through them peaks: between two
        # rising ends of a degree-5 curve, a peak of 0.579 /mm and a dip after it left the
        # planned feed 1.1 % above the chord-error limit (1.021 delta on the setpoints).
        kappa_end, slope_end = kappa[1:].copy(), slope[1 : u.size].copy()
        kappa_end[knot_rows - 1], slope_end[knot_rows - 1] = k_left, slope[u.size :]
        slope_start = slope[: u.size - 1]
        hidden = np.flatnonzero(
            ((slope_start > 0.0) & ~(slope_end > 0.0))
            | hermite_peaks(np.diff(u), kappa[:-1], kappa_end, slope_start, slope_end)
        )
        if knot_rows.size:
            v[knot_rows] = np.minimum(v[knot_rows], v_left)
            bend = normal_cosine(d_left, d2_left, d1[knot_rows], d2[knot_rows])
            jump = curvature_jump_feed(k_left, kappa[knot_rows], self._limits, self._T, bend)
            v[knot_rows, 1] = np.minimum(v[knot_rows, 1], jump)
            kappa[knot_rows] = np.maximum(kappa[knot_rows], k_left)
            d_right = d1[knot_rows]
            norms = np.linalg.norm(d_left, axis=1) * np.linalg.norm(d_right, axis=1)
            with np.errstate(invalid="ignore", divide="ignore"):
                cos_turn = np.sum(d_left * d_right, axis=1) / norms
            corner = (norms > 0.0) & (cos_turn < 1.0 - CORNER_COS_TOL)
            v[knot_rows[corner]] = 0.0
            kappa[knot_rows[corner]] = np.inf
        samples = (u, v, kappa)
        extras = []
        cusps, tips = self._reversals(u, d1, still_mm)
        peaks = np.concatenate([self._curvature_maxima(u, kappa, hidden, still_mm), tips])
        if peaks.size:
            extras.append(self._sampled(_trios(u, peaks)))
        aligned = self._axis_alignments(u, d1)
        if aligned.size:
            extras.append(self._sampled(aligned))
        if cusps.size:
            # A cusp is a stop, with C' = 0 (located to round-off, where |C'| has its kink).
            stops = (cusps, np.zeros((cusps.size, 2)), np.full(cusps.size, np.inf))
            samples = self._merged(samples, [stops])
        extras.append(self._sampled(self._corner_grid(samples[0], _lower_part(samples[1]))))
        grid = samples[0]
        # Halved where the limit changes fast between any two samples, the tips' among them: a
        # grid interval whose ends are alike can hold a tip, and the limit is concave on either
        # side of it (interpolated linearly from the tip to the grid, it measured 1.02 delta).
        u, v, kappa = self._merged(samples, extras)
        u, v, kappa = self._merged((u, v, kappa), [self._tight_midpoints(u, v)])
        for _ in range(MISSED_PEAK_PASSES):
            missed = self._missed_maxima(u, v, kappa, peaks, grid, still_mm)
            if missed.size == 0:
                break
            peaks = np.concatenate([peaks, missed])
            u, v, kappa = self._merged((u, v, kappa), [self._sampled(_trios(u, missed))])
            # Halved around each new peak alone: the rest of the samples are as halved before.
            at = np.searchsorted(u, missed)
            near = [slice(max(i - 2, 0), min(i + 3, u.size)) for i in np.unique(at).tolist()]
            u, v, kappa = self._merged(
                (u, v, kappa), [self._tight_midpoints(u[part], v[part]) for part in near]
            )
        s = np.maximum.accumulate(self._arc.s_of_u(u))
        # Samples that round to one arc length (next to a corner) become one, with the lowest
        # limit; limits below MIN_FEED_MM_S are a stop.
        v[_lower_part(v) < MIN_FEED_MM_S] = 0.0
        s = _snapped_to_stops(s, _lower_part(v) <= 0.0)
        fresh = np.concatenate([[True], np.diff(s) > 0.0])
        starts = np.flatnonzero(fresh)
        v = np.minimum.reduceat(v, starts)
        kappa = np.maximum.reduceat(kappa, starts)
        s = s[starts]
        limit = self._dilated(s, v)
        return s, chord_deficit_change_feed(
            s, kappa, limit, self._vcap_mm_s, self._planning_limits, self._T
        )

    def _limit(
        self, u: np.ndarray, *, order: int = 2
    ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, ...]]:
        """kappa, v_limit and the curve's derivatives up to ``order`` (at least 2) at u.
        v_limit has two columns: the chord-error feed and every other limit
        (:func:`planner.feed.geometric_feed_limits`), the latter dilated alone."""
        ders = self._curve.evaluate(u, order=order)
        kappa, v_chord, v_other = geometric_feed_limits(
            ders[1], ders[2], self._planning_limits, self._T
        )
        return kappa, np.stack([v_chord, v_other], axis=1), ders

    def _sampled(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Samples (u, v_limit, kappa) at u."""
        kappa, v, _ = self._limit(u)
        return u, v, kappa

    @staticmethod
    def _merged(
        samples: tuple[np.ndarray, ...], extras: list[tuple[np.ndarray, ...]]
    ) -> tuple[np.ndarray, ...]:
        """Samples (u, v_limit, kappa) with the extra ones strictly inside them added, in order
        of u."""
        lo, hi = samples[0][0], samples[0][-1]
        parts = [samples]
        for extra in extras:
            inside = (extra[0] > lo) & (extra[0] < hi)
            if inside.any():
                parts.append(tuple(column[inside] for column in extra))
        if len(parts) == 1:
            return samples
        columns = [np.concatenate(column) for column in zip(*parts, strict=True)]
        order = np.argsort(columns[0], kind="stable")
        return tuple(column[order] for column in columns)

    def _axis_alignments(self, u: np.ndarray, d1: np.ndarray) -> np.ndarray:
        """Parameters where a component of the unit tangent peaks between grid samples, with
        per-axis feed limits configured (none otherwise).

        There V_k / |t_k| is lowest, and flat: interpolated linearly from the grid, the limit
        missed that minimum by 1 % where a tangent turned through an axis's direction between
        two samples. Found where |t_k| at a sample is above its neighbours', by ternary search
        between them; the first and last samples have one neighbour (a peak just after the
        curve's start was missed: 1.03 of an axis's feed limit).
        """
        if self._planning_limits.axis_vmax_mm_s is None or len(u) < 2:
            return np.empty(0)
        with np.errstate(invalid="ignore", divide="ignore"):
            t = np.abs(d1) / np.linalg.norm(d1, axis=1)[:, None]
        padded = np.pad(t, ((1, 1), (0, 0)), constant_values=-1.0)
        rows, axes = np.nonzero((padded[1:-1] > padded[:-2]) & (padded[1:-1] >= padded[2:]))
        lo, hi = u[np.maximum(rows - 1, 0)], u[np.minimum(rows + 1, len(u) - 1)]

        def less_component(at: np.ndarray) -> np.ndarray:
            d = self._curve.evaluate(at, order=1)[1]
            with np.errstate(invalid="ignore", divide="ignore"):
                return -np.abs(d[np.arange(len(at)), np.tile(axes, 2)]) / np.linalg.norm(d, axis=1)

        peaks = ternary_minima(lo, hi, less_component, AXIS_SEARCH_STEPS)
        # V_k / |t_k| is convex around its minimum: interpolated linearly from there over a
        # whole grid interval, it stood 1.3 % above the limit. Samples at an eighth, a quarter
        # and half the interval either side bring that under 0.4 %.
        i = np.clip(np.searchsorted(u, peaks), 1, len(u) - 1)
        width = (u[i] - u[i - 1])[:, None]
        return np.clip(peaks[:, None] + width * AXIS_PEAK_OFFSETS, u[0], u[-1]).ravel()

    def _reversals(
        self, u: np.ndarray, d1: np.ndarray, still_mm: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Parameters inside a span where the tangent reverses: (cusps, tips).

        Found where consecutive samples' tangents (``d1``, C' at u) point apart (turn by more
        than 90 degrees), by ternary search of the smallest |C'| between them. A cusp (C' = 0)
        is a stop.
        A near-cusp is a tip the plan passes at the feed its radius allows (at the bench's
        limits about 2.5 mm/s for a 0.02 mm radius, where a stop cost some 30 ms), when that is
        clear: |C'| there above round-off (``still_mm``: in a span of zero length the ends'
        |C'| is round-off too), and its feed limit above ``TIP_FLOOR_RATIO`` times the
        singular floor. A reversal of a rational curve
        nearly on a line has a radius of 1e-11 mm, far too narrow for the curvature maxima's
        search: taken for a tip, it was passed at speed (4.7 A, 117 J).
        """
        lo, hi = self._turns(u, d1, still_mm)
        if lo.size == 0:
            return np.empty(0), np.empty(0)

        def speed(at: np.ndarray) -> np.ndarray:
            return np.linalg.norm(self._curve.evaluate(at, order=1)[1], axis=1)

        mid = ternary_minima(lo, hi, speed, CUSP_SEARCH_STEPS)
        mid = mid[(mid > lo) & (mid < hi)]
        _, v, (_, d1_mid, _) = self._limit(mid)
        floor = singular_floor_feed(self._planning_limits, self._T)
        tip = (np.linalg.norm(d1_mid, axis=1) > still_mm) & (
            _lower_part(v) > TIP_FLOOR_RATIO * floor
        )
        return mid[~tip], mid[tip]

    def _turns(
        self, u: np.ndarray, d1: np.ndarray, still_mm: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Brackets (lo, hi) between parameters whose tangents point apart.

        A sample where |C'| is at most ``still_mm`` (a repeated end control point, a cusp on the
        grid, a span of zero length; a rational curve leaves round-off there, not 0) has no
        tangent direction to trust. Each moving sample is compared with the next moving one,
        and a grid interval next to a still sample is also searched at points halving their
        distance to it. Compared with the still sample itself, a reversal just before the end of
        a curve whose last control points repeat went unseen and was passed at speed (1.15 A,
        19 J).
        """
        lo, hi = _pointing_apart(u, d1, still_mm)
        brackets = [(lo, hi)]
        moving = np.linalg.norm(d1, axis=1) > still_mm
        halvings = 0.5 ** np.arange(1, STILL_END_HALVINGS + 1)
        for i in np.flatnonzero(~(moving[:-1] & moving[1:]) & (u[1:] > u[:-1])):
            a, b = u[i], u[i + 1]
            inner = [a + (b - a) * halvings] if not moving[i] else []
            if not moving[i + 1]:
                inner.append(b - (b - a) * halvings)
            at = np.unique(np.concatenate([[a, b], *inner]))
            brackets.append(_pointing_apart(at, self._curve.evaluate(at, order=1)[1], still_mm))
        lows, highs = zip(*brackets, strict=True)
        return np.concatenate(lows), np.concatenate(highs)

    def _tight_midpoints(
        self, u: np.ndarray, v: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Samples (u, v_limit, kappa) added where the grid is coarse for the feed limit.

        The limit is interpolated linearly between samples, which is only safe where it changes
        little: an interval is halved, up to ``TIGHT_LEVELS`` times, while its limit changes by
        more than ``TIGHT_CHANGE`` of the lower end, unless that is above any feed a plan of
        this path may use (``TIGHT_CHANGE_OTHER`` where another limit than the chord error's
        binds at either end). Stops (a zero limit) have a grid of their own.
        """
        combined, tight = _lower_part(v), _tight_change(v)
        lo, hi, v_lo, v_hi = u[:-1], u[1:], combined[:-1], combined[1:]
        tight_lo, tight_hi = tight[:-1], tight[1:]
        added = []
        for _ in range(TIGHT_LEVELS):
            low = np.minimum(v_lo, v_hi)
            with np.errstate(invalid="ignore"):
                coarse = (
                    (low > 0.0)
                    & (low < self._vcap_mm_s)
                    & (np.abs(v_hi - v_lo) > np.minimum(tight_lo, tight_hi) * low)
                )
            if not coarse.any():
                break
            mid = self._sampled(0.5 * (lo[coarse] + hi[coarse]))
            added.append(mid)
            mid_v, mid_tight = _lower_part(mid[1]), _tight_change(mid[1])
            lo, hi = np.concatenate([lo[coarse], mid[0]]), np.concatenate([mid[0], hi[coarse]])
            v_lo, v_hi = (
                np.concatenate([v_lo[coarse], mid_v]),
                np.concatenate([mid_v, v_hi[coarse]]),
            )
            tight_lo, tight_hi = (
                np.concatenate([tight_lo[coarse], mid_tight]),
                np.concatenate([mid_tight, tight_hi[coarse]]),
            )
        if not added:
            return np.empty(0), np.empty((0, 2)), np.empty(0)
        return tuple(np.concatenate(column) for column in zip(*added, strict=True))

    def _curvature_maxima(
        self, u: np.ndarray, kappa: np.ndarray, hidden: np.ndarray, still_mm: float
    ) -> np.ndarray:
        """Parameters of the interior local maxima of curvature, by a shrinking grid search.

        Each grid maximum brackets one between its neighbours, and each grid interval in
        ``hidden`` (the curvature rising at its start and falling at its end: a peak between
        two low samples) one between its ends; up to ``PEAK_SEARCH_STEPS`` times the
        curvature is evaluated at ``PEAK_SEARCH_POINTS`` points across the bracket (all peaks
        in one call) and the bracket shrinks to the best point's neighbours, until it is flat
        (``PEAK_FLAT_RTOL``: a broad maximum takes two or three rounds), so that a tip far
        narrower than the grid (a near-cusp) is planned at its own radius (a parabola through
        the grid samples would miss most of it). Every other local maximum of a round's
        points that stands out of the dip between it and the best one brackets a peak of its
        own (:func:`_other_peaks`).
        """
        k0, k1, k2 = kappa[:-2], kappa[1:-1], kappa[2:]
        peak = np.flatnonzero((k1 > k0) & (k1 >= k2) & np.isfinite(k0 + k1 + k2)) + 1
        if peak.size + hidden.size == 0:
            return np.empty(0)
        return self._peak_search(
            np.concatenate([u[peak - 1], u[hidden]]),
            np.concatenate([u[peak + 1], u[hidden + 1]]),
            still_mm,
        )

    def _missed_maxima(
        self,
        u: np.ndarray,
        v: np.ndarray,
        kappa: np.ndarray,
        peaks: np.ndarray,
        grid: np.ndarray,
        still_mm: float,
    ) -> np.ndarray:
        """Curvature maxima near the local maxima of the refined samples (``u``, ``v``,
        ``kappa``) that no peak found so far (``peaks``) lies next to, where the limit is below
        any feed a plan of this path may use and |C'| above ``still_mm``: the highest in each
        interval of the ``grid``. Next to a cusp the refined samples' curvature is round-off
        noise with maxima by the thousand; one search per grid interval and pass bounds the
        work there.

        The grid's own test can miss a peak: a degree-5 curve's curvature fell from 20.6 /mm at
        its start to 0.3, rose to 2.85 and fell to 1.93 at the next grid sample; with both ends
        falling and their slopes shallow against the drop, the cubic through them falls all
        the way. The samples halved in where the limit changes fast showed the dip and the rise,
        but the plan crossed the peak at the feed of its neighbours: 1.42 delta.
        """
        k0, k1, k2 = kappa[:-2], kappa[1:-1], kappa[2:]
        i = np.flatnonzero((k1 > k0) & (k1 >= k2) & np.isfinite(k0 + k1 + k2)) + 1
        if i.size == 0:
            return np.empty(0)
        i = i[_lower_part(v[i]) < self._vcap_mm_s]
        known = np.sort(peaks)
        if known.size and i.size:
            nearest = np.searchsorted(known, u[i - 1]).clip(max=known.size - 1)
            i = i[~((known[nearest] >= u[i - 1]) & (known[nearest] <= u[i + 1]))]
        if i.size:
            i = i[np.linalg.norm(self._curve.evaluate(u[i], order=1)[1], axis=1) > still_mm]
        if i.size == 0:
            return np.empty(0)
        interval = np.searchsorted(grid, u[i], side="right") - 1
        order = np.lexsort((-kappa[i], interval))
        i, interval = i[order], interval[order]
        i = i[np.concatenate([[True], interval[1:] != interval[:-1]])]
        return self._peak_search(u[i - 1], u[i + 1], still_mm)

    def _peak_search(self, lo: np.ndarray, hi: np.ndarray, still_mm: float) -> np.ndarray:
        """The curvature maxima in brackets [lo, hi], as :meth:`_curvature_maxima` searches
        them; where |C'| is at most ``still_mm`` the curvature counts as infinite (round-off,
        not a peak)."""
        inner = np.linspace(0.0, 1.0, PEAK_SEARCH_POINTS + 2)
        found = []
        # Brackets an other peak opened open none of their own: next to a cusp the curvature
        # is round-off noise well above |C'|'s round-off, and following every wiggle of it
        # turned 9 brackets into 9,505 within the search's rounds.
        opened_by_other = np.zeros(lo.size, dtype=bool)
        for _ in range(PEAK_SEARCH_STEPS):
            x = lo[:, None] + (hi - lo)[:, None] * inner
            k = self._curve.curvature(x[:, 1:-1].ravel(), still_mm).reshape(len(lo), -1)
            k = np.where(np.isfinite(k), k, np.inf)
            rows = np.arange(len(lo))
            best = np.argmax(k, axis=1)
            # The curvature within PEAK_FLAT_RTOL across the whole bracket: a broad maximum,
            # resolved (the limit no longer changes).
            flat = k.min(axis=1) >= k[rows, best] * (1.0 - PEAK_FLAT_RTOL)
            found.append(x[rows[flat], best[flat] + 1])
            first = np.flatnonzero(~opened_by_other)
            other_rows, other = _other_peaks(k[first], best[first], self._binding_kappa)
            rows = np.concatenate([rows[~flat], first[other_rows]])
            i = np.concatenate([best[~flat], other])
            opened_by_other = np.concatenate(
                [opened_by_other[~flat], np.ones(other_rows.size, dtype=bool)]
            )
            lo, hi = x[rows, i], x[rows, i + 2]
            if rows.size == 0:
                break
        found.append(0.5 * (lo + hi))
        return np.concatenate(found)

    @staticmethod
    def _corner_grid(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Samples at geometrically shrinking distances from each zero-feed (corner) sample."""
        corners = np.flatnonzero(v == 0.0)
        if corners.size == 0:
            return np.empty(0)
        left = u[np.maximum(corners - 1, 0)]
        right = u[np.minimum(corners + 1, len(u) - 1)]
        scale = 0.5 ** np.arange(1, CORNER_REFINEMENTS + 1)
        c = u[corners][:, None]
        return np.concatenate(
            [(c - (c - left[:, None]) * scale).ravel(), (c + (right[:, None] - c) * scale).ravel()]
        )

    def _dilated(self, s: np.ndarray, v: np.ndarray) -> np.ndarray:
        """The feed limit at each sample: the lower of its chord-error feed (``v``'s column 0)
        and its other limits (column 1) lowered to those a step from it can reach; 0 at a stop.

        A step from s_i at feed w is w T long. The chord-deficit jerk and the accelerations on
        the setpoints depend on the steps either side of it: column 1 is lowered to the limits
        within a whole step (half a step measured 1.055 J on a tip whose limit falls from 140
        to 15 mm/s within two steps). A step's chord error is set by the curvature around its
        middle, where the plan's feed is held to column 0 itself: lowering column 0 to the
        limits within half a step as well held the plan under the limit wherever it changes (the
        bench's curves with loops took 1.032-1.036 of its jerk-limited reference instead of
        1.014-1.017), and the largest chord error on their setpoints stayed at 0.97 delta either
        way.
        """
        limit = _lower_part(v)
        stop = limit <= 0.0
        if len(s) < 2:
            return np.where(stop, 0.0, limit)
        lowered = reach_lowered(s, np.where(stop, 0.0, v[:, 1]), limit, self._T, self._vcap_mm_s)
        # Never below the singular floor (a step that short needs no geometric limit): next to
        # a sample at the floor, that is not a stop, the dilation would otherwise leave a limit
        # vanishing with the distance to it, d / reach, which the motion approaches forever.
        floor = singular_floor_feed(self._planning_limits, self._T)
        return np.where(stop, 0.0, np.maximum(np.minimum(limit, lowered), floor))
