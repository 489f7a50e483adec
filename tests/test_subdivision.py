"""fitter.fitting.atlas.subdivision: Catmull-Clark and Loop steps against independent
references (scipy's B-spline basis, MeshLab's Loop, the rules' textbook values), the
quad-dominant control mesh, and the control points' fit."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import BSpline
from scipy.spatial import cKDTree

from fitter.fitting.atlas.measure import closest_points_on_mesh
from fitter.fitting.atlas.subdivision import (
    beyond_border_weights,
    catmull_clark_step,
    corners_of,
    edges_of,
    fit_control_points,
    loop_step,
    subdivided,
    umbrella,
)

CUBE = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
CUBE_QUADS = np.array([[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4],
                       [1, 5, 7, 3]])


def edges_number(edges):
    """The index of the edge joining ``a`` and ``b`` (arrays) in ``edges``' sorted order."""
    def number(a, b):
        a, b = np.asarray(a), np.asarray(b)
        return np.searchsorted(edges.lo * edges.size + edges.hi,
                               np.minimum(a, b) * edges.size + np.maximum(a, b))
    return number


def torus_grid(n: int, m: int) -> np.ndarray:
    """Quads of an ``n x m`` grid closed in both directions, vertex ``(i, j)`` at ``i m + j``."""
    i, j = np.meshgrid(np.arange(n), np.arange(m), indexing="ij")
    i, j = i.ravel(), j.ravel()
    return np.stack([i * m + j, (i + 1) % n * m + j, (i + 1) % n * m + (j + 1) % m,
                     i * m + (j + 1) % m], axis=1)


def periodic_surface(P: np.ndarray, u: np.ndarray, v: np.ndarray, scale: int, shift: int
                     ) -> np.ndarray:
    """``sum_ij P_ij N(scale u - i - shift) N(scale v - j - shift)`` over the periodic grid
    ``P (n, m, 3)``, ``N`` the uniform cubic B-spline on ``[0, 4]`` (scipy)."""
    N = BSpline.basis_element(np.arange(5.0), extrapolate=False)
    n, m = P.shape[:2]
    out = np.zeros((len(u), 3))
    for i in range(-8, n + 8):
        bu = np.nan_to_num(N(scale * u - i - shift))
        for j in range(-8, m + 8):
            bv = np.nan_to_num(N(scale * v - j - shift))
            out += (bu * bv)[:, None] * P[i % n, j % m]
    return out


def test_catmull_clark_on_a_regular_grid_is_bicubic_b_spline_knot_insertion():
    rng = np.random.default_rng(0)
    n, m = 6, 7
    P = rng.normal(size=(n * m, 3))
    quads = torus_grid(n, m)
    S, out = catmull_clark_step(n * m, [quads])
    X = S @ P
    edges = edges_of(n * m, corners_of(n * m, [quads]))
    E = len(edges.lo)
    number = edges_number(edges)
    R = np.empty((2 * n, 2 * m, 3))
    i, j = np.meshgrid(np.arange(n), np.arange(m), indexing="ij")
    i, j = i.ravel(), j.ravel()
    k = i * m + j
    R[2 * i, 2 * j] = X[k]
    R[2 * i + 1, 2 * j] = X[n * m + number(k, (i + 1) % n * m + j)]
    R[2 * i, 2 * j + 1] = X[n * m + number(k, i * m + (j + 1) % m)]
    R[2 * i + 1, 2 * j + 1] = X[n * m + E + k]  # face (i, j) is quad k
    u, v = rng.uniform(0, n, 500), rng.uniform(0, m, 500)
    before = periodic_surface(P.reshape(n, m, 3), u, v, 1, 0)
    after = periodic_surface(R, u, v, 2, 2)  # vertex i's point is refined point 2i + 2
    assert np.abs(after - before).max() < 1e-12
    assert out.shape == (4 * n * m, 4)


def test_catmull_clark_matches_the_rules_at_a_cube_corner():
    S, quads = catmull_clark_step(8, [CUBE_QUADS])
    X = S @ CUBE
    # valence 3: (Q + 2 R + 0 v) / 3 with Q = (1/3, 1/3, 1/3), R = (1/6, 1/6, 1/6)
    assert np.allclose(X[0], [2 / 9] * 3)
    # edge (0, 0, 0)-(0, 0, 1): (a + b + the two face centres) / 4
    edges = edges_of(8, corners_of(8, [CUBE_QUADS]))
    assert np.allclose(X[8 + edges_number(edges)(0, 1)], [0.125, 0.125, 0.5])
    assert np.allclose(X[:8], 2 / 9 + 5 / 9 * CUBE)  # every corner alike
    assert np.allclose(X[20:], CUBE[CUBE_QUADS].mean(axis=1))
    assert len(quads) == 24


@pytest.mark.parametrize("levels", [1, 2])
def test_catmull_clark_of_triangles_and_quads_keeps_a_closed_oriented_mesh(levels):
    # a square pyramid: one quad, four triangles
    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 1]], float)
    quads = np.array([[0, 3, 2, 1]])
    triangles = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    surface = subdivided(5, [quads, triangles], levels)
    S = surface.matrix
    assert np.allclose(np.asarray(S.sum(axis=1)).ravel(), 1)  # affine invariance
    assert S.min() >= 0  # within the control points' convex hull
    t = surface.triangles
    directed = {(a, b) for tri in t for a, b in zip(tri, np.roll(tri, -1), strict=True)}
    assert len(directed) == 3 * len(t)  # no edge run twice the same way
    assert all((b, a) in directed for a, b in directed)  # closed, consistently oriented
    X = S @ V
    assert X[:, 2].max() < 1 and (X[:4, 2] > 0).all()  # the apex and the base's corners pulled in


def test_loop_matches_meshlab():
    pymeshlab = pytest.importorskip("pymeshlab")
    rng = np.random.default_rng(1)
    # an octahedron (valence 4) with a cap of valence 3 and 5 around: perturbed, and open
    V = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    F = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5],
                  [0, 3, 5]])
    for faces in (F, F[:6]):  # closed, then open (two faces left out)
        used = np.unique(faces)
        Vp = V + 0.1 * rng.normal(size=V.shape)
        S, out = loop_step(len(V), faces)
        S2, out2 = loop_step(S.shape[0], out)
        X = (S2 @ S @ Vp)[np.unique(out2)]
        ms = pymeshlab.MeshSet()
        ms.add_mesh(pymeshlab.Mesh(Vp[used], np.searchsorted(used, faces)))
        ms.meshing_surface_subdivision_loop(loopweight=0, iterations=2,
                                            threshold=pymeshlab.PercentageValue(0))
        R = ms.current_mesh().vertex_matrix()
        assert len(R) == len(X)
        assert cKDTree(R).query(X)[0].max() < 1e-9


def test_loop_border_follows_the_cubic_b_spline_curve():
    # a fan of four triangles around an interior vertex: the rim is a closed border
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], float)
    F = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 1]])
    S, _ = loop_step(5, F)
    X = S @ V
    assert np.allclose(X[1], (V[4] + 6 * V[1] + V[2]) / 8)
    edges = edges_of(5, corners_of(5, [F]))
    assert np.allclose(X[5 + edges_number(edges)(1, 2)], (V[1] + V[2]) / 2)
    assert np.allclose(X[5 + edges_number(edges)(0, 1)], 3 / 8 * (V[0] + V[1]) + (V[2] + V[4]) / 8)


def test_fit_control_points_recovers_a_surface_drawn_from_its_own_control_mesh():
    # the cube's control net once refined (26 points): a cube's own eight are ambiguous, the
    # alternating mode of a mesh of valence-3 vertices only being annihilated by the rules
    rng = np.random.default_rng(2)
    step, quads = catmull_clark_step(8, [CUBE_QUADS])
    truth = step @ CUBE + 0.05 * rng.normal(size=(26, 3))
    surface = subdivided(26, [quads], 3)
    points = surface.matrix @ truth
    start = truth + 0.05 * rng.normal(size=truth.shape)
    before = closest_points_on_mesh(surface.matrix @ start, points, surface.triangles)[0]
    fitted, history = fit_control_points(points, start, surface, scan_faces=surface.triangles,
                                         rounds=8, smoothing=1e-8)
    after = closest_points_on_mesh(surface.matrix @ fitted, points, surface.triangles)[0]
    assert history[0] > 1e-2
    assert history[-1] < 0.05 * history[0]  # every point near the drawn mesh
    assert after.max() < 0.1 * before.max()  # and the drawn mesh near the surface


def open_grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    """An ``n x n`` vertex grid of quads over ``[0, 1]^2`` in the plane ``z = 0``."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    vertices = np.stack([i.ravel() / (n - 1), j.ravel() / (n - 1), 0 * i.ravel()], 1)
    a = (i[:-1, :-1] * n + j[:-1, :-1]).ravel()
    return vertices.astype(float), np.stack([a, a + n, a + n + 1, a + 1], 1)


def test_beyond_border_weights_weigh_a_residual_along_the_surface_fully():
    normal = np.array([[0.0, 0.0, 1.0]] * 3)
    residual = np.array([[0.0, 0.0, 0.3], [0.1, 0.0, 0.3], [0.5, 0.0, 0.1]])
    assert beyond_border_weights(residual, normal, 0.1).tolist() == [0.1, 0.1, 1.0]


def test_fit_control_points_brings_an_open_border_out_to_the_points():
    # an open grid over [0, 1]^2 fitted to points of a wavy sheet that reaches 0.1 past it
    # on every side: the drawn border (a cubic B-spline curve of the control border) must
    # reach them. With the distance along the surface weighed as inside (t^2 = 0.01) it
    # stayed within 0.035 of the start after 4 rounds.
    vertices, quads = open_grid(6)
    surface = subdivided(len(vertices), [quads], 3)
    g = np.linspace(-0.1, 1.1, 61)
    x, y = np.meshgrid(g, g, indexing="ij")
    points = np.stack([x.ravel(), y.ravel(), 0.05 * np.sin(3 * x.ravel())], 1)
    fitted, history = fit_control_points(points, vertices, surface, rounds=4)
    drawn = surface.matrix @ fitted
    assert history[-1] < 0.1 * history[0]
    assert drawn[:, 0].min() < -0.09 and drawn[:, 0].max() > 1.09
    assert drawn[:, 1].min() < -0.09 and drawn[:, 1].max() > 1.09


def test_subdivided_refuses_absurd_arguments():
    with pytest.raises(ValueError, match="scheme"):
        subdivided(8, [CUBE_QUADS], 1, "butterfly")
    with pytest.raises(ValueError, match="levels"):
        subdivided(8, [CUBE_QUADS], 9)


def test_catmull_clark_border_follows_the_cubic_b_spline_curve():
    # a 3 x 3 grid of quads: an open mesh whose rim is a border
    i, j = np.meshgrid(np.arange(4), np.arange(4), indexing="ij")
    rng = np.random.default_rng(3)
    V = np.stack([i.ravel(), j.ravel(), rng.normal(size=16)], 1)
    a = (np.arange(3)[:, None] * 4 + np.arange(3)).ravel()
    quads = np.stack([a, a + 4, a + 5, a + 1], 1)
    S, _ = catmull_clark_step(16, [quads])
    X = S @ V
    number = edges_number(edges_of(16, corners_of(16, [quads])))
    assert np.allclose(X[1], (V[0] + 6 * V[1] + V[2]) / 8)  # on the rim
    assert np.allclose(X[0], (V[4] + 6 * V[0] + V[1]) / 8)  # the rim's turn: the same curve
    assert np.allclose(X[16 + number(1, 2)], (V[1] + V[2]) / 2)  # a border edge
    inner = 5  # valence 4, no border edge: the bicubic mask
    ring = [1, 4, 6, 9]
    diagonal = [0, 2, 8, 10]
    assert np.allclose(X[inner], 9 / 16 * V[inner] + 3 / 32 * V[ring].sum(0)
                       + V[diagonal].sum(0) / 64)


def test_a_vertex_in_no_face_stays_and_empty_blocks_are_no_faces():
    V = np.vstack([CUBE, [[5.0, 5.0, 5.0]]])
    S, _ = catmull_clark_step(9, [CUBE_QUADS, np.zeros((0, 3), np.int64)])
    assert np.allclose((S @ V)[8], V[8])
    assert S.min() >= 0
    F = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]])  # a tetrahedron, and vertex 4
    T = np.vstack([np.eye(3), [[0, 0, 0]], [[7.0, 7.0, 7.0]]])
    S, _ = loop_step(5, F)
    assert np.allclose((S @ T)[4], T[4])
    assert np.allclose(umbrella(5, [F]).toarray()[4], 0)


def test_bad_faces_are_refused_with_what_is_wrong():
    with pytest.raises(ValueError, match="triangles"):
        loop_step(8, CUBE_QUADS)
    with pytest.raises(ValueError, match="one array"):
        subdivided(8, [CUBE_QUADS[:, :3], CUBE_QUADS[:, 1:]], 1, "loop")
    with pytest.raises(ValueError, match="vertices"):
        subdivided(4, [CUBE_QUADS], 1)
    with pytest.raises(ValueError, match="k >= 3"):
        catmull_clark_step(8, [CUBE_QUADS[:, :2]])


def dense_round(points, start, surface, s, r, t, far_reach=None, far_weight=1.0):
    """One round of ``fit_control_points`` from ``start``: its documented objective, dense,
    built row by row and solved by ``numpy.linalg.lstsq``."""
    S = surface.matrix.toarray()
    n = len(start)
    drawn, T = S @ start, surface.triangles
    _, tri, foot = closest_points_on_mesh(points, drawn, T)
    B, normal = np.zeros((len(points), n)), np.zeros((len(points), 3))
    for k in range(len(points)):
        a, b, c = drawn[T[tri[k]]]
        st = np.linalg.lstsq(np.stack([b - a, c - a], 1), foot[k] - a, rcond=None)[0]
        w = [1 - st.sum(), st[0], st[1]]
        B[k] = sum(w[i] * S[T[tri[k], i]] for i in range(3))
        normal[k] = np.cross(b - a, c - a) / np.linalg.norm(np.cross(b - a, c - a))
    q = points[cKDTree(points).query(drawn)[1]]
    U = umbrella(n, surface.faces).toarray()
    N, M = len(points), len(S)
    pull = np.full(M, r * np.sqrt(N / M))
    if far_reach is not None:  # a far drawn vertex's reverse row weighs far_weight times
        diagonal = np.linalg.norm(np.ptp(points, axis=0))
        pull[np.linalg.norm(drawn - q, axis=1) > far_reach * diagonal] *= far_weight

    def coordinate(matrix, c):
        out = np.zeros((len(matrix), 3 * n))
        out[:, c::3] = matrix
        return out

    rows = [sum(normal[:, [c]] * coordinate(B, c) for c in range(3))]
    rhs = [(normal * points).sum(1)]
    for c in range(3):
        rows += [t * coordinate(B, c), pull[:, None] * coordinate(S, c),
                 np.sqrt(s * N / n) * coordinate(U, c)]
        rhs += [t * points[:, c], pull * q[:, c], np.zeros(n)]
    return np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0].reshape(n, 3)


def noisy_cube_fit():
    rng = np.random.default_rng(3)
    step, quads = catmull_clark_step(8, [CUBE_QUADS])
    start = step @ CUBE + 0.03 * rng.normal(size=(26, 3))
    surface = subdivided(26, [quads], 2)
    S = surface.matrix.toarray()
    points = (S @ start)[rng.choice(len(S), 150)] + 0.02 * rng.normal(size=(150, 3))
    return points, start, surface


def test_one_round_of_the_fit_is_the_least_squares_it_documents():
    points, start, surface = noisy_cube_fit()
    s, r, t = 1e-3, 0.3, 0.1
    fitted, _ = fit_control_points(points, start, surface, rounds=1, smoothing=s, reverse=r,
                                   tangential=t)
    dense = dense_round(points, start, surface, s, r, t)
    assert np.abs(fitted - dense).max() < 1e-9 * np.abs(dense).max()


def test_far_drawn_vertices_weigh_more_from_the_second_round_on():
    # the points (150 of the 386 drawn vertices, noisy) leave the drawn vertices 1.6-6.8 %
    # of the diagonal from the nearest point (10th-90th percentiles): 5 % makes a third far
    points, start, surface = noisy_cube_fit()
    s, r, t, reach, weight = 1e-3, 0.3, 0.1, 0.05, 3.0
    plain, _ = fit_control_points(points, start, surface, rounds=1, smoothing=s, reverse=r,
                                  tangential=t)
    first, _ = fit_control_points(points, start, surface, rounds=1, smoothing=s, reverse=r,
                                  tangential=t, far_reach=reach, far_weight=weight)
    assert np.array_equal(first, plain)  # the first round has no far rows
    second, _ = fit_control_points(points, start, surface, rounds=2, smoothing=s, reverse=r,
                                   tangential=t, far_reach=reach, far_weight=weight)
    drawn = surface.matrix @ first
    gap = cKDTree(points).query(drawn)[0] / np.linalg.norm(np.ptp(points, axis=0))
    assert 0 < np.count_nonzero(gap > reach) < len(drawn) // 2
    dense = dense_round(points, first, surface, s, r, t, reach, weight)
    assert np.abs(second - dense).max() < 1e-9 * np.abs(dense).max()
    unweighted = dense_round(points, first, surface, s, r, t)
    assert np.abs(second - unweighted).max() > 1e-4  # the far rows changed the solve
    with pytest.raises(ValueError, match="far_reach"):
        fit_control_points(points, start, surface, far_reach=0.0)
    with pytest.raises(ValueError, match="far_weight"):
        fit_control_points(points, start, surface, far_reach=reach, far_weight=0.5)


def test_fit_refuses_what_it_cannot_solve():
    surface = subdivided(8, [CUBE_QUADS], 1)
    with pytest.raises(ValueError, match="smoothing"):
        fit_control_points(CUBE, CUBE, surface, smoothing=0.0)
    with pytest.raises(ValueError, match="control"):
        fit_control_points(CUBE, CUBE[:5], surface)
