"""Jerk-limited near-time-optimal feed along a curve: a sequential linear program in v².

A reference for the planner's motion time (bench only; needs scipy, the ``bench`` extra).

Problem, on the grid of bench/feed_bound.py, s_0 = 0 < s_1 < ... < s_N = length (finer where
the feed limit is low or changes fast, and towards rest), unknowns b_i = v_i²:
- feed limit: b_i <= min(vmax, chord-error feed of eq. (3) at s_i)²; at rest at both ends;
- tangential acceleration: between nodes v² is linear in s (constant acceleration in time),
  a_i+1/2 = (b_i+1 - b_i) / (2 h_i), |a| <= A;
- jerk: j_i = (a_i+1/2 - a_i-1/2) / dt_i with dt_i = (h_i-1 / w_i-1/2 + h_i / w_i+1/2) / 2
  the time between the intervals' middles (w the mean feed of an interval), |j| <= J; at rest
  ends the acceleration outside the path is 0, so the first and last intervals start and end
  the acceleration with the jerk limit too. The speeds in dt_i are frozen at the top of the
  trust region around the previous solution (a longer time would only allow more), so each
  linear program keeps the jerk limit on the grid (its solution is feasible), and the trust
  region shrinks as the iterations converge;
- optionally, zero acceleration at the curve's own curvature maxima (the paper's sensitive
  points), where a_i-1/2 + a_i+1/2 = 0;
- objective: motion time sum 2 h_i / (v_i + v_i+1), linearised at the previous solution.

The time of the best feasible solution is the reference. It is an approximation from above
of the jerk-limited optimum on this grid (the linearisation only restricts), and the grid
does not check the feed limit between nodes (which favours the reference).

Units: mm, s.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from feed_bound import FeedLimitCurve, time_s
from scipy.optimize import linprog

#: Iterations of the sequential linear program, and the relative time change that ends them.
ITERATIONS, TOLERANCE = 40, 2e-4


def _accel_matrix(s: np.ndarray) -> sp.csr_matrix:
    """Sparse map b -> a at the interval midpoints, with a zero row before and after."""
    n = len(s)
    h = np.diff(s)
    rows = np.repeat(np.arange(1, n), 2)
    cols = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1).ravel()
    vals = np.stack([-1.0 / (2.0 * h), 1.0 / (2.0 * h)], axis=1).ravel()
    return sp.csr_matrix((vals, (rows, cols)), shape=(n + 1, n))


def _jerk_matrix(s: np.ndarray, accel: sp.csr_matrix, b_top: np.ndarray) -> sp.csr_matrix:
    """Sparse map b -> jerk at each node, with the times between intervals from b_top."""
    h = np.diff(s)
    v = np.sqrt(b_top)
    half_dt = h / np.maximum(v[:-1] + v[1:], 1e-9)  # half an interval's time
    dt = np.concatenate([[0.0], half_dt]) + np.concatenate([half_dt, [0.0]])
    n = len(s)
    step = sp.diags([-1.0 / dt, 1.0 / dt], [0, 1], shape=(n, n + 1))
    return (step @ accel).tocsr()


def jerk_limited_time_s(
    limit: FeedLimitCurve, amax: float, jmax: float, *, zero_accel_at_peaks: bool
) -> tuple[float, np.ndarray]:
    """Motion time of the best feasible profile found, and its feed at the grid nodes."""
    s, vlim = limit.s_mm, limit.v_limit_mm_s
    n = len(s)
    upper = vlim**2
    upper[0] = upper[-1] = 0.0
    accel = _accel_matrix(s)
    eq = None
    if zero_accel_at_peaks and limit.curvature_peak.any():
        nodes = np.flatnonzero(limit.curvature_peak)
        # a at a node: mean of the two neighbouring interval accelerations.
        eq = (accel[nodes] + accel[nodes + 1]).tocsr()
    b = np.zeros(n)
    best_t, best_b = np.inf, b
    radius = upper.copy()  # trust region half-width in b
    h = np.diff(s)
    for _ in range(ITERATIONS):
        lo = np.maximum(0.0, b - radius)
        hi = np.minimum(upper, b + radius)
        inner = accel[1:-1]
        jerk_rows = _jerk_matrix(s, accel, hi)
        a_ub = sp.vstack([inner, -inner, jerk_rows, -jerk_rows]).tocsr()
        b_ub = np.concatenate([np.full(2 * (n - 1), amax), np.full(2 * n, jmax)])
        v = np.sqrt(np.maximum(b, 1e-4))
        mean = v[:-1] + v[1:]
        dt_dv = -2.0 * h / mean**2
        grad_v = np.zeros(n)
        grad_v[:-1] += dt_dv
        grad_v[1:] += dt_dv
        cost = grad_v / (2.0 * v)
        result = linprog(
            cost,
            A_ub=a_ub,
            b_ub=b_ub,
            A_eq=eq,
            b_eq=None if eq is None else np.zeros(eq.shape[0]),
            bounds=np.stack([lo, hi], axis=1),
            method="highs",
        )
        if result.status != 0:
            radius *= 0.5
            continue
        b_new = np.clip(result.x, 0.0, upper)
        t_new = time_s(s, b_new)
        if t_new < best_t * (1.0 - TOLERANCE):
            best_t, best_b = t_new, b_new
            b = b_new
            radius = np.maximum(0.5 * radius, 0.05 * b + 1e-6)
        elif t_new < best_t:
            best_t, best_b = t_new, b_new
            break
        else:
            radius *= 0.5
    return best_t, np.sqrt(best_b)
