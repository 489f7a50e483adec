"""NurbsSurface: evaluation against scipy, derivatives against finite differences,
exact known surfaces, degenerate normals, and rejected input."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from nurbs_cases import (
    bilinear,
    dome,
    oracle,
    oracle_normals,
    quarter_cylinder,
    random_surface,
    sphere_octant,
)

from client_py import NurbsSurface, TrimMask, uniform_clamped_knots

DEGREES = list(itertools.product([1, 2, 3, 4], repeat=2))


def sample_params(rng, surface, count=60):
    """Random parameters plus the domain corners and every knot value inside the domain."""
    (u0, u1), (v0, v1) = surface.domain
    us = np.concatenate([rng.uniform(u0, u1, count), [u0, u1, u0, u1], surface.knots[0]])
    vs = np.concatenate([rng.uniform(v0, v1, count), [v0, v0, v1, v1],
                         rng.uniform(v0, v1, len(surface.knots[0]))])
    return us, vs


@pytest.mark.parametrize(("p", "q"), DEGREES)
def test_evaluate_matches_scipy(p, q):
    rng = np.random.default_rng(100 * p + q)
    for _ in range(3):
        s = random_surface(rng, p, q, domain=((-1.0, 2.5), (10.0, 10.75)))
        us, vs = sample_params(rng, s)
        ref, ref_u, ref_v = oracle(s, us, vs)
        got = np.array([s.evaluate(u, v) for u, v in zip(us, vs, strict=True)])
        assert np.abs(got - ref).max() <= 1e-10
        ders = [s.derivatives(u, v) for u, v in zip(us, vs, strict=True)]
        pts, su, sv = (np.array(d) for d in zip(*ders, strict=True))
        assert np.abs(pts - ref).max() <= 1e-10
        # derivatives of random rational patches reach 1e3: compare relative to that scale
        assert np.abs(su - ref_u).max() <= 1e-10 * (1 + np.abs(ref_u).max())
        assert np.abs(sv - ref_v).max() <= 1e-10 * (1 + np.abs(ref_v).max())


def test_non_rational_surface_matches_scipy():
    rng = np.random.default_rng(7)
    s = random_surface(rng, 3, 2, 9, 7, rational=False)
    assert not s.is_rational and s.flat_weights is None
    us, vs = sample_params(rng, s)
    got = np.array([s.evaluate(u, v) for u, v in zip(us, vs, strict=True)])
    assert np.abs(got - oracle(s, us, vs)[0]).max() <= 1e-12


@pytest.mark.parametrize(("p", "q"), [(1, 1), (2, 2), (3, 2), (4, 4)])
def test_derivatives_match_finite_differences(p, q):
    rng = np.random.default_rng(p * 7 + q)
    s = random_surface(rng, p, q, 8, 8)
    (u0, u1), (v0, v1) = s.domain
    h = 1e-6
    knots_u, knots_v = np.array(s.knots[0]), np.array(s.knots[1])
    checked = 0
    for u, v in zip(rng.uniform(u0, u1, 200), rng.uniform(v0, v1, 200), strict=True):
        # central differences need a smooth neighbourhood: away from knots and the boundary
        if min(np.abs(knots_u - u).min(), np.abs(knots_v - v).min()) < 1e-3:
            continue
        _, su, sv = s.derivatives(u, v)
        fd_u = (np.array(s.evaluate(u + h, v)) - s.evaluate(u - h, v)) / (2 * h)
        fd_v = (np.array(s.evaluate(u, v + h)) - s.evaluate(u, v - h)) / (2 * h)
        scale = 1 + max(np.abs(su).max(), np.abs(sv).max())
        assert np.abs(fd_u - su).max() <= 1e-5 * scale
        assert np.abs(fd_v - sv).max() <= 1e-5 * scale
        checked += 1
    assert checked > 50


@pytest.mark.parametrize(("p", "q"), [(1, 2), (2, 2), (3, 4)])
def test_normal_is_unit_cross_product(p, q):
    rng = np.random.default_rng(3 + p + q)
    s = random_surface(rng, p, q)
    us, vs = rng.uniform(0, 1, 50), rng.uniform(0, 1, 50)
    got = np.array([s.normal(u, v) for u, v in zip(us, vs, strict=True)])
    assert np.abs(got - oracle_normals(s, us, vs)).max() <= 1e-9


# ------------------------------------------------------------------ exact surfaces
def test_bilinear_patch_is_exact():
    corners = np.array([[0.0, 0.0, 0.0], [0.0, 2.0, 1.0], [3.0, 0.0, -1.0], [3.5, 2.5, 4.0]])
    p00, p01, p10, p11 = corners
    s = bilinear(corners.tolist())
    rng = np.random.default_rng(0)
    for u, v in rng.uniform(0, 1, (200, 2)):
        exact = (1 - u) * (1 - v) * p00 + (1 - u) * v * p01 + u * (1 - v) * p10 + u * v * p11
        exact_u = (1 - v) * (p10 - p00) + v * (p11 - p01)
        exact_v = (1 - u) * (p01 - p00) + u * (p11 - p10)
        pt, su, sv = s.derivatives(u, v)
        assert np.abs(np.array(s.evaluate(u, v)) - exact).max() <= 1e-14
        assert np.abs(np.array(pt) - exact).max() <= 1e-14
        assert np.abs(np.array(su) - exact_u).max() <= 1e-14
        assert np.abs(np.array(sv) - exact_v).max() <= 1e-14
        n = np.cross(exact_u, exact_v)
        assert np.abs(np.array(s.normal(u, v)) - n / np.linalg.norm(n)).max() <= 1e-14


def test_quarter_cylinder_is_an_exact_circle():
    radius, height = 2.5, 3.0
    s = quarter_cylinder(radius, height)
    rng = np.random.default_rng(1)
    us = np.concatenate([rng.uniform(0, 1, 500), [0.0, 0.5, 1.0]])
    vs = np.concatenate([rng.uniform(0, 1, 500), [0.0, 1.0, 0.5]])
    pts = np.array([s.evaluate(u, v) for u, v in zip(us, vs, strict=True)])
    assert np.abs(np.hypot(pts[:, 0], pts[:, 1]) - radius).max() <= 1e-12
    assert np.abs(pts[:, 2] - vs * height).max() <= 1e-12
    assert pts[:, :2].min() >= -1e-15  # the first quadrant only
    # the arc's ends and midpoint: (R, 0), (0, R), and 45 degrees at u = 1/2 by symmetry
    assert np.allclose(s.evaluate(0.0, 0.0), (radius, 0.0, 0.0), atol=1e-15)
    assert np.allclose(s.evaluate(1.0, 1.0), (0.0, radius, height), atol=1e-15)
    assert np.allclose(s.evaluate(0.5, 0.0), (radius * math.sqrt(0.5),) * 2 + (0.0,), atol=1e-15)
    normals = np.array([s.normal(u, v) for u, v in zip(us, vs, strict=True)])
    radial = np.column_stack([pts[:, 0], pts[:, 1], np.zeros(len(pts))]) / radius
    sign = np.sign(np.einsum("ij,ij->i", normals, radial))
    assert np.all(sign == sign[0])  # one side throughout
    assert np.abs(normals - sign[0] * radial).max() <= 1e-12


def test_sphere_octant_points_and_normals_are_radial():
    radius, center = 4.0, np.array([10.0, -5.0, 2.0])
    s = sphere_octant(radius, tuple(center))
    rng = np.random.default_rng(2)
    us, vs = rng.uniform(0, 1, 400), rng.uniform(0, 1, 400)
    pts = np.array([s.evaluate(u, v) for u, v in zip(us, vs, strict=True)]) - center
    assert np.abs(np.linalg.norm(pts, axis=1) - radius).max() <= 1e-12
    normals = np.array([s.normal(u, v) for u, v in zip(us, vs, strict=True)])
    sign = np.sign(np.einsum("ij,ij->i", normals, pts))[0]
    assert np.abs(normals - sign * pts / radius).max() <= 1e-11
    # u = 1 is the pole: S_v vanishes there, the normal is the limit from inside
    for v in np.linspace(0, 1, 9):
        assert np.linalg.norm(s.derivatives(1.0, v)[2]) <= 1e-12
        n = np.array(s.normal(1.0, v))
        assert np.isfinite(n).all() and abs(np.linalg.norm(n) - 1) <= 1e-12
        assert np.abs(n - sign * np.array([0.0, 0.0, 1.0])).max() <= 1e-6


@pytest.mark.parametrize("rational", [False, True])
@pytest.mark.parametrize("transpose", [False, True])
def test_pole_normal_is_the_limit(rational, transpose):
    """A collapsed control row (or column) far from the origin, rational or not: the
    computed S_v there is zero or pure rounding noise; the normal must still be +z."""
    s = dome(rational)
    if transpose:
        P = np.transpose(np.array(s.control_points), (1, 0, 2))
        W = np.array(s.weights).T
        s = NurbsSurface(s.degree[::-1], s.knots[::-1], P, W)
    for t in np.linspace(0, 1, 11):
        u, v = (t, 0.0) if transpose else (0.0, t)
        n = np.array(s.normal(u, v))
        assert abs(np.linalg.norm(n) - 1.0) <= 1e-12
        # orientation: S_u x S_v points up on this cap (checked inside the domain)
        assert s.normal(0.5, 0.5)[2] * (-1 if transpose else 1) > 0
        assert np.abs(n - np.array([0.0, 0.0, -1.0 if transpose else 1.0])).max() <= 1e-5


def test_fully_degenerate_surface_has_no_normal():
    U = uniform_clamped_knots(3, 2)
    s = NurbsSurface((2, 2), (U, U), [[[1.0, 2.0, 3.0]] * 3] * 3)
    assert s.evaluate(0.3, 0.6) == pytest.approx((1.0, 2.0, 3.0), abs=1e-15)
    with pytest.raises(ValueError, match="degenerate around"):
        s.normal(0.3, 0.6)


# ------------------------------------------------------------------ data views, transforms
def test_data_views_round_trip():
    rng = np.random.default_rng(11)
    s = random_surface(rng, 2, 3, 5, 6, domain=((2.0, 3.0), (-1.0, 1.0)))
    P = np.array(s.control_points)
    assert s.shape == (5, 6) and P.shape == (5, 6, 3)
    assert s.domain == ((2.0, 3.0), (-1.0, 1.0))
    assert s.is_rational and np.array(s.weights).shape == (5, 6)
    assert s.flat_points == P.ravel().tolist()
    lo, hi = s.bounding_box()
    assert lo == tuple(P.reshape(-1, 3).min(0)) and hi == tuple(P.reshape(-1, 3).max(0))
    same = NurbsSurface(s.degree, s.knots, s.control_points, s.weights)
    assert same.evaluate(2.4, 0.1) == s.evaluate(2.4, 0.1)
    ones = NurbsSurface(s.degree, s.knots, s.control_points, np.ones((5, 6)))
    assert not ones.is_rational and ones.flat_weights is None
    assert np.array(ones.weights).tolist() == np.ones((5, 6)).tolist()


def test_transformed_is_affine_invariant():
    rng = np.random.default_rng(12)
    s = random_surface(rng, 2, 2, 5, 5)
    a = np.linalg.qr(rng.normal(size=(3, 3)))[0] * 2.5
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = a, [100.0, -20.0, 5.0]
    moved = s.transformed(m.tolist())
    framed = NurbsSurface(s.degree, s.knots, s.control_points, s.weights,
                          metadata={"transform": m.tolist(), "units": "mm"}).to_scan_frame()
    for u, v in rng.uniform(0, 1, (50, 2)):
        expected = a @ np.array(s.evaluate(u, v)) + m[:3, 3]
        assert np.abs(np.array(moved.evaluate(u, v)) - expected).max() <= 1e-12
        assert np.abs(np.array(framed.evaluate(u, v)) - expected).max() <= 1e-12
    assert framed.metadata["units"] == "mm"
    assert s.to_scan_frame() is s  # no transform: already in scan coordinates
    with pytest.raises(ValueError, match="affine"):
        s.transformed([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]])
    with pytest.raises(ValueError, match="3x4 or 4x4"):
        s.transformed([[1, 0, 0], [0, 1, 0], [0, 0, 1]])


# ------------------------------------------------------------------ rejected input
U3 = [0.0, 0.0, 0.0, 1.0, 1.0, 1.0]
GRID = [[[float(i), float(j), 0.0] for j in range(3)] for i in range(3)]


def make(**changes):
    args = {"degree": (2, 2), "knots": (U3, U3), "control_points": GRID, "weights": None}
    args.update(changes)
    return NurbsSurface(**args)


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"knots": ([0, 0, 0, 1, 1], U3)}, r"knots\[0\] \(U\) has 5 knots; 3 control points of "
                                           r"degree 2 need n \+ p \+ 1 = 6"),
        ({"knots": (U3, [0, 0, 0, 1, 1, 1, 1])}, r"knots\[1\] \(V\) has 7 knots"),
        ({"knots": ([0, 0, 0, 0.7, 0.3, 1, 1, 1], U3),
          "control_points": GRID + GRID[:2]}, r"knots\[0\] \(U\) decreases at index 4"),
        ({"weights": [[1, 1, 1], [1, 0, 1], [1, 1, 1]]},
         r"weights\[1\]\[1\] = 0.0; weights must be finite and > 0"),
        ({"weights": [[1, 1, 1], [1, 1, 1], [1, 1, -2]]}, r"weights\[2\]\[2\] = -2.0"),
        ({"weights": [[1, 1, 1], [1, float("nan"), 1], [1, 1, 1]]}, r"weights\[1\]\[1\] = nan"),
        ({"weights": [[1, 1], [1, 1], [1, 1]]}, r"weights must have shape \(3, 3\)"),
        ({"control_points": [GRID[0], GRID[1], [[0, 0, float("nan")]] * 3]},
         r"control_points\[2\]\[0\] = \(0.0, 0.0, nan\) is not finite"),
        ({"control_points": [GRID[0], GRID[1][:2], GRID[2]]}, "row 1 has 2 points, row 0 has 3"),
        ({"control_points": [[[0, 0]] * 3] * 3}, r"control_points\[0\]\[0\] has 2 coordinates"),
        ({"control_points": []}, "non-empty"),
        ({"degree": 2}, r"degree must be a pair \(p, q\)"),
        ({"degree": (0, 2)}, r"degree for knots\[0\] \(U\) must be an integer >= 1, got 0"),
        ({"knots": U3}, r"knots must be a pair \(U, V\)"),
        ({"trim": [[1]]}, "trim must be a TrimMask or None, got list"),
    ],
)
def test_invalid_input_names_the_argument(changes, match):
    with pytest.raises(ValueError, match=match):
        make(**changes)


@pytest.mark.parametrize(
    ("u", "v", "match"),
    [
        (1.5, 0.5, r"parameter u = 1.5 is outside the domain \[0.0, 1.0\]"),
        (0.5, -0.25, r"parameter v = -0.25 is outside the domain"),
        (float("nan"), 0.5, "parameter u = nan is not finite"),
        (0.5, float("inf"), "parameter v = inf is not finite"),
    ],
)
def test_parameters_outside_the_domain_are_rejected(u, v, match):
    s = make()
    for method in (s.evaluate, s.derivatives, s.normal):
        with pytest.raises(ValueError, match=match):
            method(u, v)


def test_domain_ends_and_rounding_slack_are_accepted():
    s = make(trim=TrimMask([[1, 0], [1, 1]]))
    assert s.evaluate(1.0 + 1e-15, 0.0) == s.evaluate(1.0, 0.0)
    assert s.trim.rows == 2
