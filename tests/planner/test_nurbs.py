"""NurbsCurve evaluation against an independent evaluator, Table 1 figures, curvature cases."""

from __future__ import annotations

import math
import time
from functools import cache
from pathlib import Path

import numpy as np
import pytest
import yaml

from planner.errors import CurveError
from planner.nurbs import NurbsCurve

PAPER_CURVE = Path(__file__).resolve().parents[2] / "configs" / "curves" / "paper.yaml"


def reference_derivatives(curve: NurbsCurve, u: float, order: int = 3) -> np.ndarray:
    """C^(k)(u) for k = 0..order from the textbook definitions, one parameter at a time.

    Basis functions by the Cox-de Boor recursion with half-open spans (the last non-empty span
    closed at the end of the domain), their derivatives by
    N^(k)_{i,p} = p (N^(k-1)_{i,p-1} / (t_{i+p} - t_i) - N^(k-1)_{i+1,p-1} / (t_{i+p+1} - t_{i+1}))
    with 0/0 = 0, the rational curve by C = A / W and the quotient rule written out.
    """
    t = [float(x) for x in curve.knots]
    p = curve.degree
    last_span = max(i for i in range(len(t) - 1) if t[i] < t[i + 1])

    def ratio(x: float, d: float) -> float:
        return 0.0 if d == 0.0 else x / d

    @cache
    def basis(i: int, degree: int, k: int) -> float:
        if k > degree:
            return 0.0
        if degree == 0:
            if u == t[-1]:
                return 1.0 if i == last_span else 0.0
            return 1.0 if t[i] <= u < t[i + 1] else 0.0
        if k == 0:
            return ratio(u - t[i], t[i + degree] - t[i]) * basis(i, degree - 1, 0) + ratio(
                t[i + degree + 1] - u, t[i + degree + 1] - t[i + 1]
            ) * basis(i + 1, degree - 1, 0)
        return degree * (
            ratio(basis(i, degree - 1, k - 1), t[i + degree] - t[i])
            - ratio(basis(i + 1, degree - 1, k - 1), t[i + degree + 1] - t[i + 1])
        )

    support = [i for i in range(len(curve.control_points)) if t[i] <= u <= t[i + p + 1]]
    a = np.zeros((4, curve.dimension))
    w = np.zeros(4)
    for i in support:
        for k in range(4):
            n_ik = basis(i, p, k)
            a[k] += n_ik * curve.weights[i] * curve.control_points[i]
            w[k] += n_ik * curve.weights[i]
    c0 = a[0] / w[0]
    c1 = (a[1] - w[1] * c0) / w[0]
    c2 = (a[2] - 2 * w[1] * c1 - w[2] * c0) / w[0]
    c3 = (a[3] - 3 * w[1] * c2 - 3 * w[2] * c1 - w[3] * c0) / w[0]
    return np.array([c0, c1, c2, c3])[: order + 1]


def random_curve(rng: np.random.Generator) -> NurbsCurve:
    """A random clamped NURBS: degree 1-5, planar or spatial, repeated interior knots."""
    degree = int(rng.integers(1, 6))
    dimension = int(rng.choice([2, 3]))
    n = degree + 1 + int(rng.integers(0, 9))
    start = float(rng.uniform(-5.0, 5.0))
    width = float(rng.uniform(0.5, 10.0))
    grid = start + width * np.arange(1, 20) / 20.0
    while True:
        interior = np.sort(rng.choice(grid, size=n - degree - 1, replace=True))
        _, counts = np.unique(interior, return_counts=True)
        if counts.size == 0 or counts.max() <= degree:
            break
    knots = np.concatenate([[start] * (degree + 1), interior, [start + width] * (degree + 1)])
    return NurbsCurve.from_arrays(
        degree,
        rng.normal(scale=50.0, size=(n, dimension)),
        knots,
        rng.uniform(0.2, 5.0, size=n),
    )


@pytest.mark.parametrize("seed", range(60))
def test_evaluate_matches_independent_evaluator(seed: int) -> None:
    rng = np.random.default_rng(seed)
    curve = random_curve(rng)
    low, high = curve.domain
    u = np.concatenate([rng.uniform(low, high, size=12), np.unique(curve.knots)])
    ours = curve.evaluate(u, order=3)
    reference = np.stack([reference_derivatives(curve, x) for x in u], axis=1)
    assert ours.shape == (4, u.size, curve.dimension)
    for k in range(4):
        scale = np.abs(reference[k]).max()
        np.testing.assert_allclose(ours[k], reference[k], rtol=0, atol=1e-9 * scale)


@pytest.mark.parametrize("order", [0, 1, 2, 3])
def test_lower_orders_are_prefixes_of_order_three(order: int) -> None:
    curve = random_curve(np.random.default_rng(7))
    u = np.linspace(*curve.domain, 50)
    np.testing.assert_array_equal(
        curve.evaluate(u, order=order), curve.evaluate(u, order=3)[: order + 1]
    )


def test_ends_are_exactly_the_end_control_points() -> None:
    for seed in range(20):
        curve = random_curve(np.random.default_rng(100 + seed))
        low, high = curve.domain
        np.testing.assert_array_equal(curve.point(low), curve.control_points[0])
        np.testing.assert_array_equal(curve.point(high), curve.control_points[-1])
        np.testing.assert_array_equal(curve.start_point, curve.control_points[0])
        np.testing.assert_array_equal(curve.end_point, curve.control_points[-1])


def test_shapes_for_scalar_and_array_parameters() -> None:
    curve = random_curve(np.random.default_rng(3))
    low, high = curve.domain
    assert curve.evaluate(low).shape == (1, 1, curve.dimension)
    assert curve.evaluate(np.linspace(low, high, 7), order=2).shape == (3, 7, curve.dimension)
    assert curve.point(0.5 * (low + high)).shape == (curve.dimension,)
    assert curve.curvature(np.linspace(low, high, 5)).shape == (5,)


def test_arrays_are_read_only_copies() -> None:
    points = np.array([[0.0, 0.0], [1.0, 2.0], [3.0, 1.0]])
    knots = np.array([0.0, 0.0, 0.0, 1.0, 1.0, 1.0])
    curve = NurbsCurve.from_arrays(2, points, knots)
    points[1] = [100.0, 100.0]
    assert curve.control_points[1].tolist() == [1.0, 2.0]
    np.testing.assert_array_equal(curve.weights, np.ones(3))
    for array in (curve.control_points, curve.weights, curve.knots):
        with pytest.raises(ValueError):
            array[0] = 7.0


def test_parameters_outside_the_domain_are_rejected() -> None:
    curve = random_curve(np.random.default_rng(5))
    low, high = curve.domain
    for bad in (low - 1e-9, high + 1e-9, math.nan, math.inf):
        with pytest.raises(CurveError) as caught:
            curve.evaluate([low, bad])
        assert caught.value.field == "u"
        assert f"got {bad!r}, must be finite and within the domain [{low!r}, {high!r}]" in str(
            caught.value
        )


@pytest.mark.parametrize("order", [-1, 4, 1.0, True])
def test_derivative_order_outside_zero_to_three_is_rejected(order: object) -> None:
    curve = random_curve(np.random.default_rng(5))
    with pytest.raises(CurveError) as caught:
        curve.evaluate(curve.domain[0], order=order)  # type: ignore[arg-type]
    assert str(caught.value) == f"curve: order: got {order!r}, must be an integer from 0 to 3"


def quarter_circle(radius: float) -> NurbsCurve:
    return NurbsCurve.from_arrays(
        2,
        [[radius, 0.0], [radius, radius], [0.0, radius]],
        [0, 0, 0, 1, 1, 1],
        [1.0, math.sqrt(0.5), 1.0],
    )


def test_rational_quarter_circle_lies_on_the_circle_with_curvature_one_over_radius() -> None:
    curve = quarter_circle(25.0)
    u = np.linspace(0.0, 1.0, 1001)
    np.testing.assert_allclose(np.linalg.norm(curve.evaluate(u)[0], axis=1), 25.0, rtol=1e-14)
    np.testing.assert_allclose(curve.curvature(u), 1.0 / 25.0, rtol=1e-12)


def test_spatial_circle_curvature_in_a_tilted_plane() -> None:
    planar = quarter_circle(8.0)
    rotation, _ = np.linalg.qr(np.random.default_rng(11).normal(size=(3, 3)))
    points = np.hstack([planar.control_points, np.zeros((3, 1))]) @ rotation.T + [1.0, 2.0, 3.0]
    curve = NurbsCurve.from_arrays(2, points, planar.knots, planar.weights)
    np.testing.assert_allclose(curve.curvature(np.linspace(0.0, 1.0, 101)), 1.0 / 8.0, rtol=1e-12)


def test_sharp_corner_has_infinite_curvature_and_no_nan_around_it() -> None:
    # A doubled control point of a quadratic gives C'(0.5) = 0: a corner at (10, 0).
    curve = NurbsCurve.from_arrays(2, [[0, 0], [10, 0], [10, 0], [10, 10]], [0, 0, 0, 0.5, 1, 1, 1])
    np.testing.assert_array_equal(curve.point(0.5), [10.0, 0.0])
    assert curve.curvature(0.5)[0] == math.inf
    kappa = curve.curvature(np.linspace(0.0, 1.0, 10_001))
    assert not np.isnan(kappa).any()


def test_straight_line_has_zero_curvature() -> None:
    curve = NurbsCurve.from_arrays(
        3, [[0, 0, 0], [1, 1, 1], [3, 3, 3], [4, 4, 4]], [0, 0, 0, 0, 1, 1, 1, 1], [1, 2, 0.5, 1]
    )
    np.testing.assert_allclose(curve.curvature(np.linspace(0.0, 1.0, 101)), 0.0, atol=1e-12)


def load_paper_curve() -> NurbsCurve:
    return NurbsCurve.from_mapping(yaml.safe_load(PAPER_CURVE.read_text()))


def test_paper_curve_document_is_table_1() -> None:
    curve = load_paper_curve()
    assert curve.degree == 3
    assert curve.dimension == 3
    assert curve.domain == (0.0, 1.0)
    assert curve.control_points.tolist()[0] == [5.0, 5.0, 4.0]
    assert curve.control_points.tolist()[-1] == [132.0, 40.0, 41.0]
    assert curve.weights.tolist() == [1.0, 1.2, 1.0, 1.25, 0.9, 0.85, 1.0]
    assert curve.knots.tolist() == [0, 0, 0, 0, 0.4531, 0.5485, 0.6306, 1, 1, 1, 1]


def test_paper_curve_length_is_about_173_9_mm() -> None:
    points = load_paper_curve().evaluate(np.linspace(0.0, 1.0, 200_001))[0]
    length_mm = np.linalg.norm(np.diff(points, axis=0), axis=1).sum()
    assert abs(length_mm - 173.9) < 0.3


def test_paper_curve_minimum_radius_is_about_10_5_mm_near_u_0_544() -> None:
    u = np.linspace(0.0, 1.0, 100_001)
    kappa = load_paper_curve().curvature(u)
    peak = int(np.argmax(kappa))
    assert abs(1.0 / kappa[peak] - 10.5) < 0.1
    assert abs(u[peak] - 0.544) < 0.005
    # A single curvature maximum: kappa rises up to the peak and falls after it.
    assert (np.diff(kappa[peak - 2000 : peak + 1]) > 0).all()
    assert (np.diff(kappa[peak : peak + 2001]) < 0).all()


def test_huge_curve_of_100_000_spans_is_validated_and_evaluated_quickly() -> None:
    rng = np.random.default_rng(2)
    degree, n = 3, 100_003
    knots = np.concatenate([np.zeros(4), np.sort(rng.random(n - 4)), np.ones(4)])
    points = np.cumsum(rng.normal(size=(n, 3)), axis=0)
    weights = rng.uniform(0.5, 2.0, size=n)
    u = rng.random(100_000)
    started = time.process_time()
    curve = NurbsCurve.from_arrays(degree, points, knots, weights)
    ders = curve.evaluate(u, order=3)
    elapsed_s = time.process_time() - started
    # CPU time, measured about 0.1 s on an idle machine; the bound leaves room for a loaded one.
    assert elapsed_s < 3.0
    for i in rng.choice(u.size, size=4, replace=False):
        reference = reference_derivatives(curve, float(u[i]))
        for k in range(4):
            np.testing.assert_allclose(
                ders[k, i], reference[k], rtol=0, atol=1e-9 * np.abs(reference[k]).max()
            )
