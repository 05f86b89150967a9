"""ArcLengthTable against brute-force polyline lengths, exact lengths, and its own inverse."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from test_nurbs import load_paper_curve, random_curve

from planner import arclength
from planner.arclength import ArcLengthTable
from planner.errors import CurveError
from planner.nurbs import NurbsCurve


def polyline_s(curve: NurbsCurve, u: np.ndarray, per_span: int = 4000) -> np.ndarray:
    """s(u) by the length of inscribed polylines, Richardson-extrapolated.

    Each knot span is sampled on its own (corners at knots are vertices), the query parameters
    are vertices too; halving every segment cuts the O(h^2) error by four.
    """
    breaks = curve.breakpoints
    spans = np.linspace(breaks[:-1], breaks[1:], per_span + 1).ravel()
    coarse = np.unique(np.concatenate([spans, u]))
    fine = np.empty(2 * coarse.size - 1)
    fine[0::2] = coarse
    fine[1::2] = 0.5 * (coarse[:-1] + coarse[1:])

    def cumulative(grid: np.ndarray) -> np.ndarray:
        points = curve.evaluate(grid)[0]
        return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])

    estimate = (4.0 * cumulative(fine)[0::2] - cumulative(coarse)) / 3.0
    return estimate[np.searchsorted(coarse, u)]


def test_paper_curve_length_matches_brute_force_and_table_1() -> None:
    curve = load_paper_curve()
    table = ArcLengthTable(curve)
    brute_mm = polyline_s(curve, np.array([1.0]), per_span=50_000)[0]
    assert table.length_mm == pytest.approx(brute_mm, rel=1e-10)
    assert abs(table.length_mm - 173.9) < 0.3


@pytest.mark.parametrize("seed", range(25))
def test_s_of_u_matches_brute_force_on_random_curves(seed: int) -> None:
    rng = np.random.default_rng(seed)
    curve = random_curve(rng)
    table = ArcLengthTable(curve)
    low, high = curve.domain
    u = np.sort(np.concatenate([rng.uniform(low, high, size=20), [low, high]]))
    s = table.s_of_u(u)
    np.testing.assert_allclose(s, polyline_s(curve, u), rtol=0, atol=1e-9 * table.length_mm)
    assert (np.diff(s) >= 0).all()


@pytest.mark.parametrize("seed", range(25))
def test_u_of_s_inverts_s_of_u(seed: int) -> None:
    rng = np.random.default_rng(1000 + seed)
    curve = random_curve(rng)
    table = ArcLengthTable(curve)
    s = rng.uniform(0.0, table.length_mm, size=200)
    u = table.u_of_s(s)
    assert np.abs(table.s_of_u(u) - s).max() <= 1e-9
    low, high = curve.domain
    u_back = table.u_of_s(table.s_of_u(u))
    assert np.abs(u_back - u).max() <= 1e-9 * (high - low)


def test_ends_map_exactly() -> None:
    curve = random_curve(np.random.default_rng(4))
    table = ArcLengthTable(curve)
    low, high = curve.domain
    assert table.s_of_u([low, high]).tolist() == [0.0, table.length_mm]
    assert table.u_of_s([0.0, table.length_mm]).tolist() == [low, high]
    assert table.u_grid[0] == low
    assert table.u_grid[-1] == high
    assert table.s_grid[0] == 0.0
    assert table.s_grid[-1] == table.length_mm


def test_series_terms_left_out_change_no_length_beyond_the_tolerance(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    curve = load_paper_curve()
    trimmed = ArcLengthTable(curve)
    u = np.linspace(*curve.domain, 2001)
    s = trimmed.s_of_u(u)
    u_back = trimmed.u_of_s(s)
    # Leaving out nothing: every term of every interval's series.
    monkeypatch.setattr(arclength, "_TRIM_SHARE", 0.0)
    full = ArcLengthTable(curve)
    np.testing.assert_allclose(s, full.s_of_u(u), rtol=0, atol=1e-12 * full.length_mm)
    # The paper's curve is smooth: its last few terms are below the tolerance and left out.
    assert full._chunks[0]._terms > trimmed._chunks[0]._terms
    np.testing.assert_allclose(full.s_of_u(u_back), s, rtol=0, atol=2e-10)


def test_grid_is_read_only_ascending_holds_every_breakpoint_and_matches_s_of_u() -> None:
    curve = load_paper_curve()
    table = ArcLengthTable(curve)
    assert (np.diff(table.u_grid) > 0).all()
    assert (np.diff(table.s_grid) > 0).all()
    assert np.isin(curve.breakpoints, table.u_grid).all()
    np.testing.assert_allclose(table.s_of_u(table.u_grid), table.s_grid, rtol=0, atol=1e-12)
    for array in (table.u_grid, table.s_grid):
        with pytest.raises(ValueError):
            array[0] = 1.0


def test_u_guess_is_used_when_inside_the_bracket_and_replaced_otherwise() -> None:
    table = ArcLengthTable(load_paper_curve())
    s = np.array([10.0, 87.0, 150.0])
    expected = table.u_of_s(s)
    near = table.u_of_s(s, u_guess=expected + 1e-6)
    wild = table.u_of_s(s, u_guess=[1.0, 0.0, 0.0])
    np.testing.assert_allclose(near, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(wild, expected, rtol=0, atol=1e-12)
    with pytest.raises(CurveError) as caught:
        table.u_of_s(s, u_guess=[0.5])
    assert str(caught.value) == "curve: u_guess: got 1 values for 3 arc lengths, must match"


def cusp_curve() -> NurbsCurve:
    """Cubic Bezier along x that stops and reverses inside its span: x(u) = 30u(1-u) + 5u^3."""
    return NurbsCurve.from_arrays(
        3, [[0.0, 0.0], [10.0, 0.0], [10.0, 0.0], [5.0, 0.0]], [0, 0, 0, 0, 1, 1, 1, 1]
    )


def test_reversal_inside_a_span_has_its_exact_length_and_no_nan() -> None:
    curve = cusp_curve()
    u_turn = 2.0 - math.sqrt(2.0)  # x'(u) = 0
    x_turn = 30.0 * u_turn * (1.0 - u_turn) + 5.0 * u_turn**3
    table = ArcLengthTable(curve)
    assert table.length_mm == pytest.approx(2.0 * x_turn - 5.0, rel=1e-10)
    assert table.s_of_u(u_turn)[0] == pytest.approx(x_turn, rel=1e-10)
    s = np.linspace(0.0, table.length_mm, 2001)
    u = table.u_of_s(s)
    assert not np.isnan(u).any()
    assert np.abs(table.s_of_u(u) - s).max() <= 1e-9
    assert table.u_of_s(x_turn)[0] == pytest.approx(u_turn, abs=1e-6)


def test_sharp_corner_at_a_knot_matches_brute_force() -> None:
    curve = NurbsCurve.from_arrays(
        2, [[0, 0], [10, 0], [10, 0], [10, 10]], [0, 0, 0, 0.5, 1, 1, 1], [1.0, 2.0, 0.5, 1.0]
    )
    table = ArcLengthTable(curve)
    u = np.array([0.25, 0.5, 0.75, 1.0])
    np.testing.assert_allclose(table.s_of_u(u), polyline_s(curve, u), rtol=1e-10)
    s = np.linspace(0.0, table.length_mm, 501)
    assert np.abs(table.s_of_u(table.u_of_s(s)) - s).max() <= 1e-9


def test_huge_curve_of_100_000_spans_builds_quickly() -> None:
    n = 100_003
    angle = np.linspace(0.0, 2000.0 * np.pi, n)
    points = np.stack([50.0 * np.cos(angle), 50.0 * np.sin(angle), angle], axis=1)
    knots = np.concatenate([np.zeros(3), np.linspace(0.0, 1.0, n - 2), np.ones(3)])
    curve = NurbsCurve.from_arrays(3, points, knots)
    started = time.process_time()
    table = ArcLengthTable(curve)
    elapsed_s = time.process_time() - started
    # CPU time, measured about 0.5 s on an idle machine; the bound leaves room for a loaded one.
    assert elapsed_s < 5.0
    chord_mm = np.linalg.norm(points[-1] - points[0])
    polygon_mm = np.linalg.norm(np.diff(points, axis=0), axis=1).sum()
    assert chord_mm < table.length_mm <= polygon_mm
    u = np.linspace(0.0, 1.0, 1001)
    assert (np.diff(table.s_of_u(u)) > 0).all()


def test_arguments_outside_their_range_are_rejected() -> None:
    table = ArcLengthTable(load_paper_curve())
    with pytest.raises(CurveError) as caught:
        table.s_of_u(1.5)
    assert str(caught.value) == "curve: u: got 1.5, must be finite and within [0.0, 1.0]"
    for bad in (-1e-6, table.length_mm + 1e-6, math.nan):
        with pytest.raises(CurveError) as caught:
            table.u_of_s([1.0, bad])
        assert caught.value.field == "s"
        assert f"got {bad!r}, must be finite and within [0.0, {table.length_mm!r}]" in str(
            caught.value
        )
