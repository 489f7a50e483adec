"""The fitter's mathematics against exact surfaces and independent dense solvers."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from client_py import NurbsSurface, uniform_clamped_knots
from fitter.fitting.features import adaptive_sample, feature_weights, surface_variation
from fitter.fitting.fit import (
    _regularised_solve,
    fit_points_linear,
    fit_section_matrix,
    project_points,
    refine_nurbs,
    seam_closure,
    second_differences,
)
from fitter.fitting.nurbs import PatchModel


def _random_bspline(shape=(7, 6), degree=(2, 3), seed=1) -> PatchModel:
    rng = np.random.default_rng(seed)
    model = PatchModel.uniform(shape, degree)
    i, j = np.meshgrid(np.linspace(0, 1, shape[0]), np.linspace(0, 1, shape[1]), indexing="ij")
    model.Q = np.stack([i, j, 0.3 * rng.normal(size=shape)], axis=-1)
    return model


def test_patch_model_matches_client_py_evaluator():
    model = _random_bspline()
    model.W = np.random.default_rng(2).uniform(0.5, 2.0, model.shape)
    surface = model.to_surface()
    rng = np.random.default_rng(3)
    u, v = rng.random(50), rng.random(50)
    S, Su, Sv = model.evaluate(u, v, derivatives=True)
    for k in range(50):
        p, pu, pv = surface.derivatives(u[k], v[k])
        np.testing.assert_allclose(S[k], p, atol=1e-12)
        np.testing.assert_allclose(Su[k], pu, atol=1e-10)
        np.testing.assert_allclose(Sv[k], pv, atol=1e-10)


def test_exact_bspline_recovered_from_its_section_matrix():
    model = _random_bspline()
    u = np.linspace(0, 1, 30)
    v = np.linspace(0, 1, 25)
    UU, VV = np.meshgrid(u, v, indexing="ij")
    grid = model.evaluate(UU.ravel(), VV.ravel()).reshape(30, 25, 3)
    valid = np.ones((30, 25), bool)
    start = PatchModel.uniform(model.shape, model.degree)
    separable = fit_section_matrix(start, u, v, grid, valid, smoothing=0.0)
    np.testing.assert_allclose(separable.Q, model.Q, atol=1e-8)
    holes = valid.copy()
    holes[10:14, 5:9] = False
    sparse = fit_section_matrix(start, u, v, grid, holes, smoothing=0.0)
    np.testing.assert_allclose(sparse.Q, model.Q, atol=1e-8)


def test_linear_solve_equals_dense_lstsq_with_smoothing_and_holes():
    rng = np.random.default_rng(5)
    start = PatchModel.uniform((6, 5), (2, 2))
    u, v = np.linspace(0, 1, 14), np.linspace(0, 1, 11)
    grid = rng.normal(size=(14, 11, 3))
    valid = rng.random((14, 11)) > 0.3
    smoothing = 1e-2
    got = fit_section_matrix(start, u, v, grid, valid, smoothing=smoothing).Q.reshape(-1, 3)
    UU, VV = np.meshgrid(u, v, indexing="ij")
    A = start.basis_rows(UU.ravel()[valid.ravel()], VV.ravel()[valid.ravel()])
    A = A.matrix(start.n_ctrl).toarray()
    L = second_differences(start.shape).toarray()
    lam = smoothing * np.trace(A.T @ A) / np.trace(L.T @ L)
    stacked = np.vstack([A, np.sqrt(lam) * L])
    rhs = np.vstack([grid.reshape(-1, 3)[valid.ravel()], np.zeros((len(L), 3))])
    want = np.linalg.lstsq(stacked, rhs, rcond=None)[0]
    np.testing.assert_allclose(got, want, atol=1e-9)


def test_separable_solve_equals_dense_lstsq():
    rng = np.random.default_rng(6)
    start = PatchModel.uniform((5, 7), (2, 2))
    u, v = np.sort(rng.random(12)), np.sort(rng.random(15))
    grid = rng.normal(size=(12, 15, 3))
    got = fit_section_matrix(start, u, v, grid, np.ones((12, 15), bool), smoothing=0.0)
    UU, VV = np.meshgrid(u, v, indexing="ij")
    A = start.basis_rows(UU.ravel(), VV.ravel()).matrix(start.n_ctrl).toarray()
    want = np.linalg.lstsq(A, grid.reshape(-1, 3), rcond=None)[0]
    np.testing.assert_allclose(got.Q.reshape(-1, 3), want, atol=1e-9)


def test_periodic_closure_is_c1_across_the_seam():
    rng = np.random.default_rng(7)
    start = PatchModel.uniform((12, 6), (2, 2))
    theta = rng.uniform(0, 1, 4000)
    height = rng.uniform(0, 1, 4000)
    pts = np.column_stack([np.cos(2 * np.pi * theta) * (1 + 0.2 * height),
                           np.sin(2 * np.pi * theta) * (1 + 0.2 * height), height])
    model = fit_points_linear(start, theta, height, pts, periodic_u=True)
    v = np.linspace(0, 1, 7)
    S0, Su0, Sv0 = model.evaluate(np.zeros(7), v, derivatives=True)
    S1, Su1, Sv1 = model.evaluate(np.ones(7), v, derivatives=True)
    np.testing.assert_allclose(S0, S1, atol=1e-12)
    np.testing.assert_allclose(Su0, Su1, atol=1e-9)
    T = seam_closure(start.shape, True)
    assert T.shape == (72, 60)


def _sphere_cap(n=6000, seed=8):
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-0.7, 0.7, n), rng.uniform(-0.7, 0.7, n)
    return np.column_stack([x, y, np.sqrt(1.0 - x * x - y * y)]), (x + 0.7) / 1.4, (y + 0.7) / 1.4


def test_nonlinear_refinement_lowers_energy_on_a_sphere_cap():
    pts, u, v = _sphere_cap()
    start = fit_points_linear(PatchModel.uniform((5, 5), (2, 2)), u, v, pts)
    linear_energy = 0.5 * np.sum((start.evaluate(u, v) - pts) ** 2)
    refined, history = refine_nurbs(start, u, v, pts, iterations=10)
    final_energy = 0.5 * np.sum((refined.evaluate(u, v) - pts) ** 2)
    assert history == sorted(history, reverse=True)
    assert final_energy < 0.9 * linear_energy
    assert np.all(refined.W > 0) and not np.allclose(refined.W, 1.0)


def test_parameter_correction_finds_foot_points():
    pts, u, v = _sphere_cap()
    model = fit_points_linear(PatchModel.uniform((8, 8), (2, 2)), u, v, pts)
    rng = np.random.default_rng(9)
    u0 = np.clip(u + rng.normal(0, 0.02, len(u)), 0, 1)
    v0 = np.clip(v + rng.normal(0, 0.02, len(v)), 0, 1)
    fu, fv = project_points(model, pts, u0, v0, iterations=8)
    S, Su, Sv = model.evaluate(fu, fv, derivatives=True)
    r = pts - S
    inside = (fu > 0.01) & (fu < 0.99) & (fv > 0.01) & (fv < 0.99)
    # at a foot point the residual is orthogonal to both tangents
    cos_u = np.abs(np.einsum("ij,ij->i", r, Su)) / (np.linalg.norm(r, axis=1)
                                                     * np.linalg.norm(Su, axis=1) + 1e-300)
    assert np.percentile(cos_u[inside], 99) < 1e-3
    assert np.sum(r**2) <= np.sum((pts - model.evaluate(u0, v0)) ** 2)


def _crease(n=20000, seed=10):
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)
    z = 0.4 * np.abs(x) + rng.normal(0, 1e-4, n)  # a V-shaped crease along x = 0
    return np.column_stack([x, y, z])


def test_surface_variation_finds_a_crease():
    pts = _crease()
    sigma = surface_variation(pts, k=16)
    near = np.abs(pts[:, 0]) < 0.02
    far = np.abs(pts[:, 0]) > 0.2
    assert np.median(sigma[near]) > 20 * np.median(sigma[far])


def test_feature_adaptive_sampling_lowers_max_error_at_the_crease():
    pts = _crease(40000)
    u, v = (pts[:, 0] + 1) / 2, (pts[:, 1] + 1) / 2
    weights = feature_weights(surface_variation(pts))
    near = np.abs(pts[:, 0]) < 0.05
    errors = {}
    for name, w in (("uniform", np.ones(len(pts))), ("adaptive", weights)):
        idx = adaptive_sample(w, 1500, seed=3)
        model = fit_points_linear(PatchModel.uniform((12, 12), (2, 2)), u[idx], v[idx], pts[idx])
        errors[name] = np.abs(model.evaluate(u[near], v[near])[:, 2] - pts[near, 2]).max()
    assert errors["adaptive"] < errors["uniform"]


def test_regularised_solve_rejects_nothing_silently():
    A = sp.csr_matrix(np.eye(4))
    out = _regularised_solve(A, np.ones((4, 3)), False, 0.0, (2, 2))
    np.testing.assert_allclose(out, np.ones((4, 3)))


def test_round_trip_through_client_surface():
    model = _random_bspline()
    surface = model.to_surface(metadata={"units": "mm"})
    assert isinstance(surface, NurbsSurface)
    assert surface.knots[0] == tuple(uniform_clamped_knots(7, 2))
    back = PatchModel.from_surface(surface)
    np.testing.assert_array_equal(back.Q, model.Q)
    with pytest.raises(ValueError, match="weights"):
        bad = model.copy()
        bad.W[0, 0] = -1.0
        bad.to_surface()


def test_empty_inputs_evaluate_and_project_to_nothing():
    model = _random_bspline()
    empty = np.zeros(0)
    assert model.evaluate(empty, empty).shape == (0, 3)
    assert all(a.shape == (0, 3) for a in model.evaluate(empty, empty, derivatives=True))
    u, v = project_points(model, np.zeros((0, 3)), empty, empty)
    assert u.shape == v.shape == (0,)


def test_pole_closure_ties_each_pole_column_to_one_point():
    """Sphere maps: every control point of the v = 0 column is one point, as is every one of
    the v = 1 column, and the u seam closure still holds, for any free parameters."""
    shape = (9, 7)
    T = seam_closure(shape, True, poles=True)
    assert T.shape == (9 * 7, (9 - 2) * (7 - 2) + 2)
    Q = (T @ np.random.default_rng(4).normal(size=(T.shape[1], 3))).reshape(9, 7, 3)
    assert np.allclose(Q[:, 0], Q[0, 0]) and np.allclose(Q[:, -1], Q[0, -1])
    np.testing.assert_allclose(Q[-1], Q[0])
    np.testing.assert_allclose(Q[-2], 2 * Q[0] - Q[1])
    # a fit with the closure keeps it
    rng = np.random.default_rng(5)
    u, v = rng.uniform(0, 1, (2, 4000))
    pts = np.column_stack([np.cos(2 * np.pi * u) * np.sin(np.pi * v),
                           np.sin(2 * np.pi * u) * np.sin(np.pi * v), np.cos(np.pi * v)])
    model = fit_points_linear(PatchModel.uniform(shape, (2, 2)), u, v, pts, True, poles=True)
    assert np.allclose(model.Q[:, 0], model.Q[0, 0]) and np.allclose(model.Q[:, -1], model.Q[0, -1])
    assert np.abs(model.evaluate(u, v) - pts).max() < 0.1
