"""client_py.basis against scipy's B-splines and against the definitions (knots, spans)."""

from __future__ import annotations

import numpy as np
import pytest
from nurbs_cases import random_knots
from scipy.interpolate import BSpline

from client_py.basis import (
    basis_derivatives,
    basis_functions,
    basis_table,
    find_span,
    is_uniform_clamped,
    uniform_clamped_knots,
    validate_knots,
)


def scipy_basis(knots, degree, t, nu=0):
    """All ``n`` basis functions (or their ``nu``-th derivatives) at ``t`` from scipy."""
    n = len(knots) - degree - 1
    return BSpline(np.asarray(knots, float), np.eye(n), degree)(t, nu=nu)


def test_uniform_clamped_knots_is_eq_3():
    # n = 6, p = 2: 9 knots, interior at multiples of h = 1 / (n - p) = 1/4
    assert uniform_clamped_knots(6, 2) == [0, 0, 0, 0.25, 0.5, 0.75, 1, 1, 1]
    assert uniform_clamped_knots(3, 2, -2.0, 4.0) == [-2, -2, -2, 4, 4, 4]
    knots = uniform_clamped_knots(40, 3, 1.0, 5.0)
    assert len(knots) == 40 + 3 + 1
    assert np.allclose(np.diff(knots[3:-3]), 4.0 / 37, rtol=0, atol=1e-14)


@pytest.mark.parametrize(("n", "p", "match"), [(2, 2, "n_ctrl must be >= degree"),
                                               (5, 0, "degree must be >= 1")])
def test_uniform_clamped_knots_rejects(n, p, match):
    with pytest.raises(ValueError, match=match):
        uniform_clamped_knots(n, p)


def test_is_uniform_clamped():
    assert is_uniform_clamped(2, uniform_clamped_knots(10, 2, 3.0, 7.0))
    assert not is_uniform_clamped(2, [0, 0, 0, 0.3, 1, 1, 1])
    assert not is_uniform_clamped(2, [0, 0, 1, 1])  # too few knots for degree 2


@pytest.mark.parametrize("degree", [1, 2, 3, 4])
def test_find_span_is_the_definition(degree):
    rng = np.random.default_rng(degree)
    knots = random_knots(rng, 12, degree, (-1.0, 2.0))
    n = 12
    ts = np.concatenate([rng.uniform(-1.0, 2.0, 300), knots])  # knots themselves too
    for t in ts:
        span = find_span(degree, knots, n, t)
        assert degree <= span <= n - 1
        if t < knots[n]:
            assert knots[span] <= t < knots[span + 1]
        else:  # right end of the domain: the last non-empty span
            assert span == n - 1 and knots[span] < knots[span + 1]


@pytest.mark.parametrize("degree", [1, 2, 3, 4])
def test_basis_functions_match_scipy(degree):
    rng = np.random.default_rng(10 + degree)
    n = 9
    knots = random_knots(rng, n, degree, (0.5, 3.0))
    ts = np.concatenate([rng.uniform(0.5, 3.0, 200), [0.5, 3.0], knots[degree:-degree]])
    ref = scipy_basis(knots, degree, ts)
    for t, row in zip(ts, ref, strict=True):
        span = find_span(degree, knots, n, t)
        values = basis_functions(degree, knots, span, t)
        dense = np.zeros(n)
        dense[span - degree : span + 1] = values
        assert np.abs(dense - row).max() <= 1e-13
        assert abs(sum(values) - 1.0) <= 1e-14  # partition of unity


@pytest.mark.parametrize("degree", [1, 2, 3, 4])
def test_basis_derivatives_match_scipy(degree):
    rng = np.random.default_rng(20 + degree)
    n = 10
    knots = random_knots(rng, n, degree)
    ts = rng.uniform(0.0, 1.0, 150)
    order = degree + 1  # one past the degree: must be all zero
    refs = [scipy_basis(knots, degree, ts, nu=k) for k in range(order)]
    for m, t in enumerate(ts):
        span = find_span(degree, knots, n, t)
        ders = basis_derivatives(degree, knots, span, t, order)
        assert len(ders) == order + 1
        for k in range(order):
            dense = np.zeros(n)
            dense[span - degree : span + 1] = ders[k]
            scale = np.abs(refs[k][m]).max() + 1.0
            assert np.abs(dense - refs[k][m]).max() <= 1e-11 * scale, (k, t)
        assert ders[order] == [0.0] * (degree + 1)


def test_basis_table_matches_scipy():
    rng = np.random.default_rng(5)
    knots = random_knots(rng, 14, 3)
    ts = np.linspace(0.0, 1.0, 33)
    spans, values, derivs = basis_table(3, knots, 14, ts.tolist())
    ref, dref = scipy_basis(knots, 3, ts), scipy_basis(knots, 3, ts, nu=1)
    for k, span in enumerate(spans):
        cols = slice(span - 3, span + 1)
        assert np.abs(np.array(values[k]) - ref[k, cols]).max() <= 1e-13
        assert np.abs(np.array(derivs[k]) - dref[k, cols]).max() <= 1e-11 * (1 + abs(dref[k]).max())
        # outside the window every basis function is zero
        assert np.abs(np.delete(ref[k], np.arange(span - 3, span + 1))).max() == 0.0


@pytest.mark.parametrize(
    ("knots", "n_ctrl", "match"),
    [
        ([0, 0, 0, 1, 1, 1], 4, r"has 6 knots; 4 control points of degree 2 need n \+ p \+ 1 = 7"),
        ([0, 0, 0, 0.6, 0.4, 1, 1, 1], 5, "decreases at index 4"),
        ([0, 0, 0, float("nan"), 1, 1, 1], 4, r"U\[3\] is nan; knots must be finite"),
        ([0, 0, 0.1, 0.5, 1, 1, 1], 4, "not clamped"),
        ([1, 1, 1, 1, 1, 1], 3, "empty domain"),
        ([0, 0, 0, 0.5, 0.5, 0.5, 1, 1, 1], 6, "repeats more than degree"),
        ("abc", 0, "must be a sequence of numbers"),
    ],
)
def test_validate_knots_rejects(knots, n_ctrl, match):
    with pytest.raises(ValueError, match=match):
        validate_knots("U", 2, knots, n_ctrl)


def test_validate_knots_accepts_a_double_interior_knot():
    assert validate_knots("U", 2, [0, 0, 0, 0.5, 0.5, 1, 1, 1], 5)[3:5] == (0.5, 0.5)
    with pytest.raises(ValueError, match="degree for U must be an integer >= 1"):
        validate_knots("U", 0, [0, 1], 1)
