"""Feed limits along the path: chord error and vmax (eqs. (3)-(4)), and limits beyond the paper.

Source: Wang, Zhao, Lu, Liu, China Mechanical Engineering 23(3), 2012, 299-304:
- (3) chord-error feed V = (2/T) sqrt(rho² - (rho - delta)²) = (2/T) sqrt(2 rho delta - delta²),
  the step V·T whose chord on the osculating circle of radius rho has sagitta delta;
- (4) adaptive feed V(u) = min(vmax, value of (3)).
Not in the paper, always on:
- chord-deficit jerk: the drives move along the chords between setpoints, and a chord is
  shorter than its arc by the fraction eps = theta²/24, theta = kappa V T the turn of a step.
  The chord feed V (1 - eps) then has an extra jerk V Δ²eps / T², Δ²eps the second difference
  of eps over periods: about 4 eps theta² where the curvature changes on the scale of the
  radius (a tip kappa0 / (1 + (kappa0 s)²)), and at most 2 eps (a tip narrower than a step).
  Keeping V 2 eps min(1, 2 theta²) / T² within ``CHORD_JERK_FRACTION`` of J gives
  v <= (6 f J / (kappa⁴ T²))^(1/5) while theta < 1/sqrt(2), else v <= (12 f J / kappa²)^(1/3)
  (:func:`chord_deficit_feed`). With the paper's limits it binds only below a radius of about
  0.05 mm (0.024 mm: 2.4 mm/s against 3.5 mm/s of eq. (3) at delta = 1 µm); without it a tip
  of radius 0.03 mm at delta = 10 µm measured 4 J on the setpoints. Where the curvature jumps
  at a knot (degree 2, repeated knots), eps changes within one step: Δ²eps is at most
  K V² T² / 24 with K = |kappa_b² - kappa_a²| + 3/4 kappa_a kappa_b (1 - cos phi), phi the
  angle between the normals on either side (the tangent's variance over a step straddling the
  knot; an S-bend of equal radii, phi = 180°, has no jump of |kappa| at all), which gives
  v <= (24 f J / K)^(1/3) (:func:`curvature_jump_feed`); without it a straight line turning
  into a 1 mm radius at delta = 10 µm measured 1.06 J, and with the first term alone a 3D
  degree-2 curve whose normal turned at a knot 1.065 J. Where the curvature changes faster
  than a tip's (its flanks, or a curvature falling to 0 within its radius), Δ²eps is taken
  from kappa² at the steps either side of each sample of the envelope
  (:func:`chord_deficit_change_feed`); without it such a curve measured 1.09 J.
Not in the paper (all off unless configured, so the paper's case is reproduced exactly):
- normal acceleration: v² kappa <= A_n, so v <= sqrt(A_n / kappa);
- per-axis velocity: |v t_k| <= V_k, so v <= V_k / |t_k| (t the unit tangent);
- per-axis acceleration: the normal part v² kappa |n_k| is given half of A_k
  (v <= sqrt(A_k / (2 kappa |n_k|)), n the unit normal) and the tangential part a t_k the other
  half, through a tangential limit of min(amax, min_k A_k / 2) (:func:`tangential_accel_limit`).
  Conservative, but it keeps every axis within its limit whatever the split.

Units: kappa in 1/mm (inf at a sharp corner), delta in mm, T in s, feeds in mm/s. Pure,
vectorised over numpy arrays; thread-safe.
"""

from __future__ import annotations

import numpy as np

from planner.types import Limits

#: Share of the jerk limit the chord deficit of a step may add to the chord feed's jerk.
CHORD_JERK_FRACTION = 0.03
#: Share of the acceleration limit the chord deficit's change from step to step may add to
#: the chord feed's acceleration (the setpoints are held to 1.02 A).
CHORD_ACCEL_FRACTION = 0.01
#: Fixed-point rounds of chord_deficit_change_feed.
DEFICIT_CHANGE_ROUNDS = 4
#: Fraction of J T³ a step may be long wherever the geometry is (see singular_floor_feed).
FLOOR_JERK_FRACTION = 0.05
#: Curvatures (1/mm) binding_curvature looks at: 2.3 % apart, radii from a pm to a Gm.
BINDING_CURVATURE_GRID = np.logspace(-12.0, 12.0, 2401)


def chord_error_feed(kappa: np.ndarray, delta: float, T: float) -> np.ndarray:
    """Feed whose step V·T has chord error delta on the osculating circle, eq. (3).

    Where the radius rho = 1/kappa is below delta the largest chord is the diameter, so the step
    is capped at 2 rho (V = 2 rho / T); at a sharp corner (kappa = inf) the feed is 0.
    """
    kappa = np.asarray(kappa, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.where(kappa > 0.0, 1.0 / kappa, np.inf)
        half_chord = np.where(
            rho > delta, np.sqrt(2.0 * rho * delta - delta * delta), rho
        )  # eq. (3)
    return 2.0 / T * half_chord


def adaptive_feed(kappa: np.ndarray, vmax: float, delta: float, T: float) -> np.ndarray:
    """Adaptive feed V(u) = min(vmax, chord-error feed), eq. (4) (the no-look-ahead rule)."""
    return np.minimum(vmax, chord_error_feed(kappa, delta, T))  # eq. (4)


def normal_accel_feed(kappa: np.ndarray, A_n: float) -> np.ndarray:
    """Feed keeping the normal acceleration v² kappa within A_n: sqrt(A_n / kappa)."""
    with np.errstate(divide="ignore"):
        return np.sqrt(A_n / np.asarray(kappa, dtype=np.float64))


def chord_deficit_feed(kappa: np.ndarray, J: float, T: float) -> np.ndarray:
    """Feed whose chord deficit adds at most CHORD_JERK_FRACTION J of jerk (module docstring)."""
    budget = CHORD_JERK_FRACTION * J
    with np.errstate(divide="ignore", over="ignore"):
        gradual = (6.0 * budget / (kappa**4 * T * T)) ** 0.2
        abrupt = np.cbrt(12.0 * budget / np.square(kappa))
    return np.where(kappa * gradual * T < np.sqrt(0.5), gradual, abrupt)


def normal_cosine(
    d1_a: np.ndarray, d2_a: np.ndarray, d1_b: np.ndarray, d2_b: np.ndarray
) -> np.ndarray:
    """Cosine of the angle between the principal normals of two rows of derivatives (C', C''
    each (m, dim)); 1 where either side has none (straight, or still)."""

    def normal(d1: np.ndarray, d2: np.ndarray) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            tangent = d1 / np.linalg.norm(d1, axis=1, keepdims=True)
            n = d2 - np.sum(d2 * tangent, axis=1, keepdims=True) * tangent
            return n / np.linalg.norm(n, axis=1, keepdims=True)

    cos = np.sum(normal(d1_a, d2_a) * normal(d1_b, d2_b), axis=1)
    return np.where(np.isfinite(cos), np.clip(cos, -1.0, 1.0), 1.0)


def curvature_jump_feed(
    kappa_a: np.ndarray,
    kappa_b: np.ndarray,
    limits: Limits,
    T: float,
    normal_cos: np.ndarray | float = 1.0,
) -> np.ndarray:
    """Feed across a jump of the curvature from kappa_a to kappa_b, with ``normal_cos`` the
    cosine of the angle between the normals either side, whose chord deficit adds at most
    CHORD_JERK_FRACTION J of jerk and CHORD_ACCEL_FRACTION A of acceleration (module
    docstring); inf where it does not jump, and never below :func:`singular_floor_feed` (a
    jump to a near-cusp's curvature would otherwise have the motion creep there)."""
    budget = min(
        CHORD_JERK_FRACTION * limits.jmax_mm_s3, CHORD_ACCEL_FRACTION * limits.amax_mm_s2 / T
    )
    with np.errstate(invalid="ignore", divide="ignore"):  # inf - inf: a corner, a stop anyway
        both = kappa_a * kappa_b
        bend = np.where(np.isfinite(both), 0.75 * both * (1.0 - normal_cos), 0.0)
        jump = np.abs(np.square(kappa_b) - np.square(kappa_a)) + bend
        feed = np.cbrt(24.0 * budget / jump)
    # Not np.nan_to_num: it would also turn inf into the largest float, and the envelope's
    # linear interpolation from there overflows to -inf.
    return np.maximum(np.where(np.isnan(feed), np.inf, feed), singular_floor_feed(limits, T))


def chord_deficit_change_feed(
    s_mm: np.ndarray,
    kappa: np.ndarray,
    v_limit: np.ndarray,
    v_cap_mm_s: float,
    limits: Limits,
    T: float,
) -> np.ndarray:
    """``v_limit`` at samples (s_mm, kappa), lowered where the chord deficit, changing from
    step to step, would add more than CHORD_JERK_FRACTION J of jerk or CHORD_ACCEL_FRACTION A
    of acceleration: where the curvature changes faster than a tip's (:func:`chord_deficit_feed`
    assumes a tip's shape; a curvature falling to 0 within less than its radius measured
    1.09 J on the setpoints), or changes at all within a few steps where A is small against J
    (a cubic with double knots at delta = 10 µm, A = 200 mm/s² and J = 200,000 mm/s³ measured
    1.085 A).

    A step of L = V T centred at s has eps = kappa(s)² L² / 24 (kappa² linear between
    samples); Δ²eps is that of the steps centred at s - L, s and s + L, Δeps that of the steps
    centred at s - L/2 and s + L/2. V Δ²eps / T² <= f J and V Δeps / T <= f' A are solved for V
    from min(v_limit, v_cap_mm_s) down by fixed point (the jerk grows like V⁵ where the
    curvature changes smoothly on the step's scale, the acceleration like V⁴; both like V³
    across a jump). V is at most the limit where each step is centred (the motion cannot pass
    there any faster), so a sample next to a tip is not held to steps that would cross the tip
    at its own feed. Samples within a step of a stop (limit 0) keep their limit: the motion
    rests there. Never below :func:`singular_floor_feed` (unless v_limit is).

    :param v_limit: the feed limit at the samples, already lowered to what a step reaches
        (:mod:`planner.envelope`); 0 at a stop.
    :returns: the lowered limit, one value per sample.
    """
    jerk_budget = CHORD_JERK_FRACTION * limits.jmax_mm_s3
    accel_budget = CHORD_ACCEL_FRACTION * limits.amax_mm_s2
    stops = v_limit <= 0.0
    square = np.where(stops | ~np.isfinite(kappa), 0.0, np.square(kappa))
    stop_s = s_mm[stops]
    capped = np.minimum(v_limit, v_cap_mm_s)
    floor = np.minimum(singular_floor_feed(limits, T), capped)

    def motion(rows: np.ndarray, feed: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The feed of the steps through samples ``rows`` (none faster than the limit where it
        is centred), and its ratios of the budgets to the deficit's jerk and acceleration."""
        s = s_mm[rows]
        step = feed * T
        reached = np.minimum(np.interp(s + step, s_mm, capped), np.interp(s - step, s_mm, capped))
        feed = np.minimum(feed, reached)
        step = feed * T
        ahead, behind = s + step, s - step
        second = np.abs(
            np.interp(ahead, s_mm, square) - 2.0 * square[rows] + np.interp(behind, s_mm, square)
        )
        first = np.abs(
            np.interp(s + 0.5 * step, s_mm, square) - np.interp(s - 0.5 * step, s_mm, square)
        )
        if stop_s.size:
            # No step crosses a stop: the motion rests there.
            nearest = np.searchsorted(stop_s, behind)
            beside = nearest < stop_s.size
            beside[beside] = stop_s[nearest[beside]] <= ahead[beside]
            second[beside] = first[beside] = 0.0
        deficit = feed * step * step / 24.0  # times the change of kappa² gives V Δeps
        jerk, accel = deficit * second / (T * T), deficit * first / T
        with np.errstate(divide="ignore"):
            return (
                feed,
                np.where(jerk > 0.0, jerk_budget / jerk, np.inf),
                np.where(accel > 0.0, accel_budget / accel, np.inf),
            )

    feed = capped.copy()
    rows = np.arange(len(s_mm))
    for jerk_exponent, accel_exponent in ((0.2, 0.25),) * DEFICIT_CHANGE_ROUNDS + (
        (1.0 / 3.0, 1.0 / 3.0),
    ):
        # The cube root last: where the jerk or the acceleration grows more slowly than the
        # rounds before assume, they may stop above the budget; it lands within it wherever
        # they grow at least like V³.
        through, jerk_ratio, accel_ratio = motion(rows, feed[rows])
        over = (jerk_ratio < 1.0) | (accel_ratio < 1.0)
        rows = rows[over]
        scale = np.minimum(
            np.minimum(jerk_ratio[over], 1.0) ** jerk_exponent,
            np.minimum(accel_ratio[over], 1.0) ** accel_exponent,
        )
        feed[rows] = np.maximum(through[over] * scale, floor[rows])
        if rows.size == 0:
            break
    return np.where(feed < capped, feed, v_limit)


def tangential_accel_limit(limits: Limits) -> float:
    """Tangential acceleration limit: amax, or min(amax, min_k A_k / 2) with axis limits."""
    if limits.axis_amax_mm_s2 is None:
        return limits.amax_mm_s2
    return min(limits.amax_mm_s2, 0.5 * min(limits.axis_amax_mm_s2))


def geometric_feed_limits(
    d1: np.ndarray, d2: np.ndarray, limits: Limits, T: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Feed limit from the geometry (chord error and the optional limits), without vmax, in
    two parts: the chord-error feed and every other limit.

    A step's chord error depends on the curvature around the step's middle; the chord-deficit
    jerk and the accelerations on the setpoints (second differences) on the steps either side
    as well, so the envelope reaches further for them (:mod:`planner.envelope`).

    :param d1: (m, dim) first derivatives C'(u).
    :param d2: (m, dim) second derivatives C''(u).
    :returns: (kappa, v_chord, v_other), each (m,); kappa is inf and both feeds 0 where
        C'(u) = 0.
    :raises ValueError: if an axis limit tuple does not match the curve dimension.
    """
    speed = np.sqrt(np.einsum("ij,ij->i", d1, d1))
    moving = speed > 0.0
    safe = np.where(moving, speed, 1.0)
    tangent = d1 / safe[:, None]
    along = np.einsum("ij,ij->i", d2, tangent)
    normal_vec = (d2 - along[:, None] * tangent) / (safe * safe)[:, None]
    kappa = np.sqrt(np.einsum("ij,ij->i", normal_vec, normal_vec))
    kappa[~moving] = np.inf
    dim = d1.shape[1]
    for name, values in (
        ("axis_vmax_mm_s", limits.axis_vmax_mm_s),
        ("axis_amax_mm_s2", limits.axis_amax_mm_s2),
    ):
        if values is not None and len(values) != dim:
            raise ValueError(
                f"limits: {name}: got {len(values)} values for a curve of dimension {dim}, "
                "must be one per axis"
            )
    with np.errstate(divide="ignore", invalid="ignore"):
        v_chord = chord_error_feed(kappa, limits.chord_error_mm, T)
        v_other = chord_deficit_feed(kappa, limits.jmax_mm_s3, T)
        if limits.normal_accel_mm_s2 is not None:
            v_other = np.minimum(v_other, normal_accel_feed(kappa, limits.normal_accel_mm_s2))
        if limits.axis_vmax_mm_s is not None:
            per_axis = np.asarray(limits.axis_vmax_mm_s) / np.abs(tangent)
            v_other = np.minimum(v_other, per_axis.min(axis=1))
        if limits.axis_amax_mm_s2 is not None:
            # |kappa n_k| is the k-th component of the curvature vector normal_vec.
            per_axis = np.sqrt(0.5 * np.asarray(limits.axis_amax_mm_s2) / np.abs(normal_vec))
            v_other = np.minimum(v_other, per_axis.min(axis=1))
    floor = singular_floor_feed(limits, T)
    parts = []
    for v in (v_chord, v_other):
        v = np.maximum(v, floor)
        v[~moving | np.isnan(v)] = 0.0
        parts.append(v)
    return kappa, parts[0], parts[1]


def binding_curvature(limits: Limits, T: float, feed_mm_s: float) -> float:
    """A curvature (1/mm) below which no limit that tightens with the curvature (chord error,
    chord deficit, normal and axis accelerations) holds the feed below ``feed_mm_s``: a peak
    of lower curvature binds no plan capped at that feed.

    Taken on a grid of BINDING_CURVATURE_GRID curvatures, one grid step below the first that
    binds (each limit falls as the curvature grows; the axis accelerations are bounded by
    the whole curvature vector's).
    """
    kappa = BINDING_CURVATURE_GRID
    feed = np.minimum(
        chord_error_feed(kappa, limits.chord_error_mm, T),
        chord_deficit_feed(kappa, limits.jmax_mm_s3, T),
    )
    if limits.normal_accel_mm_s2 is not None:
        feed = np.minimum(feed, normal_accel_feed(kappa, limits.normal_accel_mm_s2))
    if limits.axis_amax_mm_s2 is not None:
        feed = np.minimum(feed, np.sqrt(0.5 * min(limits.axis_amax_mm_s2) / kappa))
    binding = np.flatnonzero(feed < feed_mm_s)
    return float(kappa[binding[0] - 1]) if binding.size and binding[0] > 0 else 0.0


def singular_floor_feed(limits: Limits, T: float) -> float:
    """Feed below which no geometric limit is needed: steps of at most min(delta, J T³ / 20).

    A step of arc length L departs from its chord by at most L/2, so L <= delta keeps the chord
    error within half of delta (a margin for the planned feed's sampling); and with
    L <= J T³ / 20 even a step that turns completely around changes
    the chord feed by less than 5 % of what the jerk limit allows within a period. Without this
    floor, curvature growing without bound towards a cusp (a repeated end control point) would
    drive the limit to 0 over a stretch of the path and the motion would creep there.
    """
    return min(limits.chord_error_mm, FLOOR_JERK_FRACTION * limits.jmax_mm_s3 * T**3) / T
