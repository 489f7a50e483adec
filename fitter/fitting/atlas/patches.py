"""The base atlas's polynomial patches as arrays: evaluation and foot points.

Patch ``f`` of an :class:`~client_py.atlas.AtlasSurface` of degree ``d`` with ``s`` spans a
side is ``C_f(u, v) = Σ_ij N_i(u) N_j(v) P_{I_f(i, j)}`` over ``[0, 1]²``, ``n = s + d``
basis functions a side and ``I_f`` its ``n × n`` indices into the unique control points
(``AtlasSurface.patch_indices``). Here, for many points at once: the basis
(:func:`basis_matrix`), the index table and control points as arrays, the points and first
derivatives at ``(f_k, u_k, v_k)`` (:func:`evaluate_patches`), the sparse design matrix of
the least squares (:func:`design_matrix`), and the foot point of a point in space: first in
the layout triangle that holds it (:func:`assign_triangles`, :func:`triangle_to_quad`), then
by Gauss-Newton point inversion hopping across patch borders (:func:`correct_parameters`).

The base fit (:mod:`.fit`), the detail (:mod:`.detail`) and the colour (:mod:`.texture`)
share these; the client's tessellation evaluates the same patches on its own
(``client_py.atlas_mesh``).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp
from scipy.interpolate import BSpline
from scipy.spatial import cKDTree

from client_py.atlas import AtlasSurface

from ..cores import usable_cores
from .layout import triangle_samples
from .threads import on_threads


# ------------------------------------------------------------------ basis and evaluation
def basis_matrix(t: np.ndarray, degree: int, spans: int, derivative: int = 0) -> np.ndarray:
    """``N_i^{(r)}(t_k)`` of the clamped uniform knot vector, shape (K, n), ``n = s + d``.

    One span (the atlas's default): the Bernstein polynomials (:func:`bernstein_matrix`).
    More: scipy's ``BSpline`` with the identity as coefficients gives every basis function
    at once (de Boor's recurrence, The NURBS Book A2.2/A2.3).
    """
    if spans == 1:
        return bernstein_matrix(t, degree, derivative)
    n = spans + degree
    knots = np.r_[np.zeros(degree), np.linspace(0.0, 1.0, spans + 1), np.ones(degree)]
    return BSpline(knots, np.eye(n), degree, extrapolate=False)(
        np.clip(t, 0.0, 1.0), nu=derivative)


def bernstein_matrix(t: np.ndarray, degree: int, derivative: int = 0) -> np.ndarray:
    """``B_{i,d}^{(r)}(t_k)``, shape (K, d + 1): the basis of one clamped span on ``[0, 1]``.

    ``B_{i,d}(t) = C(d, i) t^i (1 - t)^(d - i)`` (The NURBS Book eq. 1.8), whose ``r``-th
    derivative is ``d!/(d - r)!`` times the ``r``-th forward difference of the degree
    ``d - r`` polynomials, ``B'_{i,d} = d (B_{i-1,d-1} - B_{i,d-1})`` (eq. 1.9), with
    ``B_{-1} = B_{d-r+1} = 0``. ``t`` is clamped to ``[0, 1]`` as :func:`basis_matrix`'s.
    Equal to scipy's ``BSpline`` of the knots ``0^{d+1} 1^{d+1}`` to rounding (1e-15);
    :func:`evaluate_patches` with derivatives took 0.32-0.40 s instead of 0.47-0.55 for
    five on Lucy's 100,000 working points, and half the time in chunks of 500 points
    (docs/benchmarks.md, session 19).
    """
    t = np.clip(np.asarray(t, np.float64), 0.0, 1.0)
    m = degree - derivative
    if m < 0:
        return np.zeros((len(t), degree + 1))
    s = 1.0 - t
    t_power, s_power = [np.ones_like(t)], [np.ones_like(t)]
    for _ in range(m):
        t_power.append(t_power[-1] * t)
        s_power.append(s_power[-1] * s)
    scale = math.factorial(degree) // math.factorial(m)
    b = np.empty((m + 1, len(t)))  # a row a function: contiguous writes, returned as (K, n)
    for i in range(m + 1):
        np.multiply((scale * math.comb(m, i)) * t_power[i], s_power[m - i], out=b[i])
    for _ in range(derivative):  # B_{i-1} - B_i, one function more
        d = np.empty((len(b) + 1, len(t)))
        np.negative(b[0], out=d[0])
        np.subtract(b[:-1], b[1:], out=d[1:-1])
        d[-1] = b[-1]
        b = d
    return b.T


def index_table(atlas: AtlasSurface) -> np.ndarray:
    """``I[f, i, j]``: the global index of patch ``f``'s ``P[i][j]``, shape (F, n, n)."""
    return np.array([atlas.patch_indices(f) for f in range(len(atlas.quads))], np.int64)


def control_points(atlas: AtlasSurface) -> np.ndarray:
    """Every control point once, shape (N_cp, 3), in the order vertices, edge, face points."""
    return np.array(atlas.vertices + atlas.edge_points + atlas.face_points, np.float64)


def with_control_points(atlas: AtlasSurface, points: np.ndarray) -> AtlasSurface:
    """``atlas`` with its control points replaced by ``points (N_cp, 3)`` (same order)."""
    n_v, n_e = len(atlas.vertices), len(atlas.edge_points)
    rows = np.asarray(points, np.float64).tolist()
    return AtlasSurface(atlas.degree, atlas.spans, rows[:n_v], atlas.quads, rows[n_v:n_v + n_e],
                        rows[n_v + n_e:], atlas.weights)


def point_nets(table: np.ndarray, points: np.ndarray, f: np.ndarray) -> np.ndarray:
    """The control net of patch ``f_k`` for each point, ``P[I[f_k]]``, shape ``(K, n², 3)``.

    Gathered as whole nets, ``P[I]`` of every patch once (``(F, n², 3)``) and then one
    contiguous ``n² x 3`` row per point, instead of ``n²`` single control points per point:
    the same numbers, and on the 15-scan Happy Buddha's 1,473-patch base (``n = 4``,
    20,000 points, thread CPU time at load 10) 0.65 ms instead of 3.7 ms; an evaluation
    with derivatives 10.3 ms instead of 13.1. With fewer
    points than a quarter of the patches, the points' own nets are gathered alone."""
    k, n2 = len(f), table.shape[1] * table.shape[2]
    if 4 * k < len(table):
        return points[table[f].reshape(k, n2)]
    return points[table.reshape(len(table), n2)][f]


def evaluate_patches(table: np.ndarray, points: np.ndarray, degree: int, spans: int,
                     f: np.ndarray, u: np.ndarray, v: np.ndarray, derivatives: bool = False
                     ) -> tuple[np.ndarray, ...]:
    """``C_{f_k}(u_k, v_k)`` (and ``C_u``, ``C_v``) of polynomial patches, each (K, 3).

    ``C = Σ_ij N_i(u) N_j(v) P_{I[f, i, j]}``: the ``n²`` products ``N_i(u) N_j(v)`` of each
    point times its patch's net ``(n², 3)``, one batched matrix product (twice as fast as
    the three-operand ``einsum`` it replaced, equal to rounding). The nets are gathered
    patch by patch, ``P[I]`` once, then one row of ``n² x 3`` per point (:func:`point_nets`).
    """
    k, n = len(f), table.shape[1]
    net = point_nets(table, points, f)  # (K, n², 3)

    def combine(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.matmul((a[:, :, None] * b[:, None, :]).reshape(k, 1, n * n), net)[:, 0]

    bu, bv = basis_matrix(u, degree, spans), basis_matrix(v, degree, spans)
    c = combine(bu, bv)
    if not derivatives:
        return (c,)
    du, dv = basis_matrix(u, degree, spans, 1), basis_matrix(v, degree, spans, 1)
    return c, combine(du, bv), combine(bu, dv)


def design_matrix(table: np.ndarray, n_control: int, degree: int, spans: int,
                  f: np.ndarray, u: np.ndarray, v: np.ndarray) -> sp.csr_matrix:
    """``A[k, I[f_k, i, j]] = N_i(u_k) N_j(v_k)``, shape (K, N_cp), ``n²`` entries a row."""
    bu, bv = basis_matrix(u, degree, spans), basis_matrix(v, degree, spans)
    values = (bu[:, :, None] * bv[:, None, :]).reshape(len(f), -1)
    columns = table[f].reshape(len(f), -1)
    rows = np.repeat(np.arange(len(f)), values.shape[1])
    return sp.csr_matrix((values.reshape(-1), (rows, columns.reshape(-1))),
                         shape=(len(f), n_control))


# ------------------------------------------------------------------ foot points
def assign_triangles(points: np.ndarray, normals: np.ndarray, vertices: np.ndarray,
                     triangles: np.ndarray, candidates: int = 24) -> np.ndarray:
    """The layout triangle of each point: nearest among those whose normal agrees.

    Among the triangles of the ``candidates`` nearest triangle samples, the nearest (by
    sample) with ``n_t · n_x > 0.5``; the plain nearest when none agrees.
    """
    tri = vertices[triangles]
    tri_normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    tri_normals /= np.maximum(np.linalg.norm(tri_normals, axis=1, keepdims=True), 1e-300)
    samples, owner = triangle_samples(vertices, triangles, 5)
    k = min(candidates, len(samples))
    _, near = cKDTree(samples).query(points, k=k)
    near = near.reshape(len(points), k)
    cand = owner[near]  # (K, k), by increasing distance
    agree = np.einsum("kc,kjc->kj", normals, tri_normals[cand]) > 0.5
    first = np.where(agree.any(axis=1), np.argmax(agree, axis=1), 0)
    return cand[np.arange(len(points)), first]


def triangle_to_quad(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray,
                     t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Patch and ``(u, v)`` of each point in its triangle's split (``layout.quad_layout``).

    The point's barycentric coordinates ``(α, β, γ)`` in triangle ``t`` (its projection,
    clamped into the triangle) pick the quad of the largest; in the quad
    ``(x, m_xy, g, m_zx)`` the bilinear map is ``β = u (1/2 - v/6)``, ``γ = v (1/2 - u/6)``
    (``β, γ``: the weights of ``y`` and ``z``), inverted by Newton's method.
    """
    tri = vertices[triangles[t]]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    r = points - tri[:, 0]
    d11, d12, d22 = (np.einsum("kc,kc->k", a, b) for a, b in ((e1, e1), (e1, e2), (e2, e2)))
    r1, r2 = np.einsum("kc,kc->k", r, e1), np.einsum("kc,kc->k", r, e2)
    det = np.maximum(d11 * d22 - d12 * d12, 1e-300)
    b1 = (d22 * r1 - d12 * r2) / det
    b2 = (d11 * r2 - d12 * r1) / det
    bary = np.clip(np.stack([1 - b1 - b2, b1, b2], axis=1), 0.0, None)
    bary /= np.maximum(bary.sum(axis=1, keepdims=True), 1e-300)
    corner = np.argmax(bary, axis=1)
    rows = np.arange(len(points))
    beta = bary[rows, (corner + 1) % 3]
    gamma = bary[rows, (corner + 2) % 3]
    u, v = 2 * beta, 2 * gamma
    for _ in range(8):
        fu = u * (0.5 - v / 6) - beta
        fv = v * (0.5 - u / 6) - gamma
        a, b, c, d = 0.5 - v / 6, -u / 6, -v / 6, 0.5 - u / 6
        det2 = a * d - b * c
        u = u - (d * fu - b * fv) / det2
        v = v - (a * fv - c * fu) / det2
    return 3 * t + corner, np.clip(u, 0.0, 1.0), np.clip(v, 0.0, 1.0)


def neighbour_table(atlas: AtlasSurface) -> np.ndarray:
    """``nb[f, k] = (g, m, same_way)``: the patch across side ``k`` of ``f``; ``g = -1`` on
    an open border. Shape (F, 4, 3)."""
    nb = np.full((len(atlas.quads), 4, 3), -1, np.int64)
    edges = atlas.edges
    for pairs in edges.faces:
        if len(pairs) != 2:
            continue
        (f, k), (g, m) = pairs
        same = int(edges.sides[f][k][1] == edges.sides[g][m][1])
        nb[f, k] = (g, m, same)
        nb[g, m] = (f, k, same)
    return nb


def _hop(nb: np.ndarray, f: np.ndarray, u: np.ndarray, v: np.ndarray
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Move ``(f, u, v)`` that left ``[0, 1]²`` into the patch across the side it crossed
    furthest (depth kept, at most 0.5); clamp on an open border."""
    over = np.stack([-v, u - 1, v - 1, -u], axis=1)
    side = np.argmax(over, axis=1)
    depth = np.minimum(over[np.arange(len(f)), side], 0.5)
    out = depth > 0
    g, m, same = (nb[f, side, c] for c in range(3))
    move = out & (g >= 0)
    along = np.where(side % 2 == 0, u, v)
    along = np.clip(along, 0.0, 1.0)
    along = np.where(same == 1, along, 1.0 - along)
    nu = np.select([m == 0, m == 1, m == 2, m == 3],
                   [along, 1.0 - depth, along, depth])
    nv = np.select([m == 0, m == 1, m == 2, m == 3],
                   [depth, along, 1.0 - depth, along])
    f = np.where(move, g, f)
    u = np.where(move, nu, u)
    v = np.where(move, nv, v)
    return f, np.clip(u, 0.0, 1.0), np.clip(v, 0.0, 1.0)


def correct_parameters(table: np.ndarray, points: np.ndarray, degree: int, spans: int,
                       nb: np.ndarray, x: np.ndarray, normals: np.ndarray, f: np.ndarray,
                       u: np.ndarray, v: np.ndarray, iterations: int = 6
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Foot points of ``x (K, 3)`` on the atlas by Gauss-Newton point inversion with hops.

    Step ``[C_u·C_u  C_u·C_v; C_u·C_v  C_v·C_v] δ = [C_u·r; C_v·r]``, ``r = x - C``
    (The NURBS Book eq. 6.6 without the second-derivative terms), limited to 0.5 in
    ``(u, v)``; a point that leaves its patch hops (:func:`_hop`). A point whose step moved
    it by less than :data:`CONVERGED_STEP` without a hop takes no more steps (the steps
    shrink about a hundredfold an iteration: docs/benchmarks.md, session 19). A point
    keeps its old foot point unless the new one is nearer and the surface's normal there
    agrees with the point's (``n · n_x > 0.3``): no jump around a thin part's edge to its
    other sheet.

    Every point's steps are its own, so the points are split into :data:`CORRECT_THREADS`
    runs done at once (numpy's products release the GIL): the same numbers (the 15-scan
    Happy Buddha's bundle byte for byte), and its final fit's corrections took 1.16-1.39 s of
    wall time instead of 2.25-2.42 s (2 cores, load 1-4, 4 interleaved runs each).

    Returns
    -------
    f, u, v, distance : ndarray, each (K,)
    """
    threads = min(CORRECT_THREADS, usable_cores(), len(x) // CORRECT_RUN_POINTS)
    if threads <= 1:
        return _correct_run(table, points, degree, spans, nb, x, normals, f, u, v, iterations)
    run = -(-len(x) // threads)
    runs = on_threads(lambda lo: _correct_run(table, points, degree, spans, nb, *(
        a[lo:lo + run] for a in (x, normals, f, u, v)), iterations), len(x), run, threads)
    return tuple(np.concatenate([run[i] for run in runs]) for i in range(4))


CORRECT_THREADS = 2  # correct_parameters' runs at once (the machine's 2 cores)
CORRECT_RUN_POINTS = 10_000  # ... each of at least this many points
# A point whose Gauss-Newton step moved its (u, v) by less than this (and kept its patch)
# takes no further step (correct_parameters): 1e-7 of a patch side is ~1e-9 of the diagonal
CONVERGED_STEP = 1e-7


def _correct_run(table: np.ndarray, points: np.ndarray, degree: int, spans: int,
                 nb: np.ndarray, x: np.ndarray, normals: np.ndarray, f: np.ndarray,
                 u: np.ndarray, v: np.ndarray, iterations: int
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`correct_parameters` of one run of points, in this thread."""
    (c0,) = evaluate_patches(table, points, degree, spans, f, u, v)
    best = np.linalg.norm(x - c0, axis=1)
    cf, cu_, cv_ = f.copy(), u.copy(), v.copy()
    moving = np.arange(len(x))  # the points still stepping (CONVERGED_STEP)
    for _ in range(iterations):
        if not len(moving):
            break
        mf, mu, mv = cf[moving], cu_[moving], cv_[moving]
        c, du, dv = evaluate_patches(table, points, degree, spans, mf, mu, mv, True)
        r = x[moving] - c
        a, b, d = (np.einsum("kc,kc->k", p, q) for p, q in ((du, du), (du, dv), (dv, dv)))
        ru, rv = np.einsum("kc,kc->k", du, r), np.einsum("kc,kc->k", dv, r)
        det = a * d - b * b
        ok = det > 1e-30 * np.maximum(a * d, 1e-300)
        det = np.where(ok, det, 1.0)
        su = np.where(ok, (d * ru - b * rv) / det, 0.0)
        sv = np.where(ok, (a * rv - b * ru) / det, 0.0)
        length = np.hypot(su, sv)
        scale = np.minimum(1.0, 0.5 / np.maximum(length, 1e-300))
        nf, nu, nv = _hop(nb, mf, mu + scale * su, mv + scale * sv)
        cf[moving], cu_[moving], cv_[moving] = nf, nu, nv
        moving = moving[(nf != mf) | (np.hypot(nu - mu, nv - mv) > CONVERGED_STEP)]
    c1, du, dv = evaluate_patches(table, points, degree, spans, cf, cu_, cv_, True)
    dist = np.linalg.norm(x - c1, axis=1)
    normal = np.cross(du, dv)
    agree = np.einsum("kc,kc->k", normal, normals) > 0.3 * np.linalg.norm(normal, axis=1)
    better = (dist < best) & agree
    return (np.where(better, cf, f), np.where(better, cu_, u), np.where(better, cv_, v),
            np.where(better, dist, best))


def signed_distances(table: np.ndarray, points: np.ndarray, degree: int, spans: int,
                     x: np.ndarray, f: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``|x - C| · sign((x - C) · (C_u × C_v))`` at each foot point, shape (K,)."""
    c, du, dv = evaluate_patches(table, points, degree, spans, f, u, v, True)
    r = x - c
    side = np.einsum("kc,kc->k", r, np.cross(du, dv))
    return np.linalg.norm(r, axis=1) * np.where(side < 0, -1.0, 1.0)
