"""The base's control points rounded for ``base.tsa`` with the error fed back
(``fitter.fitting.atlas.fit``: ``grid_codes``, ``coupling_colours``, ``fed_back_atlas``)."""

import itertools

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh

from client_py.atlas_format import read_atlas, write_atlas
from fitter.fitting.atlas import fit as atlas_fit
from fitter.fitting.atlas import fit_atlas
from fitter.fitting.atlas.fit import base_resolution, coupling_colours, fed_back_atlas, grid_codes
from fitter.fitting.atlas.patches import control_points, index_table
from fitter.fitting.io.scan import make_scan, new_source


def _objective(A: np.ndarray, X: np.ndarray, P: np.ndarray) -> float:
    return float(np.sum((A @ P - X) ** 2))


def _random_problem(rng: np.random.Generator, k: int, n: int, density: float):
    """A sparse least-squares problem ``|A P - X|²`` with coupled unknowns, its dense
    ``numpy.linalg.lstsq`` minimiser and a grid whose step is comparable to the fit's
    error (where rounding matters)."""
    A = rng.normal(size=(k, n)) * (rng.random((k, n)) < density)
    A[np.arange(k), rng.integers(0, n, k)] += 1.0  # no empty row
    A[rng.integers(0, k, n), np.arange(n)] += 1.0  # no empty column
    X = rng.normal(size=(k, 3)) * 3.0
    x = np.linalg.lstsq(A, X, rcond=None)[0]
    lo = x.min(axis=0) - 0.1
    step = np.array([0.7, 1.1, 0.9])
    return A, X, x, lo, step


@pytest.mark.parametrize("seed", range(6))
def test_fed_back_codes_never_fit_worse_than_rounding_and_stay_within_a_step(seed):
    rng = np.random.default_rng(seed)
    A, X, x, lo, step = _random_problem(rng, 60, 24, 0.15)
    plain = np.rint((x - lo) / step).astype(np.int64)
    H = sp.kron(sp.csr_matrix(A.T @ A), sp.identity(3))  # the values flat: 3 j + axis
    q = grid_codes(H, A.T @ X, x, plain, lo, step)
    t = (x - lo) / step
    assert np.all(q >= np.floor(t)) and np.all(q <= np.ceil(t))
    got, rounded = _objective(A, X, lo + step * q), _objective(A, X, lo + step * plain)
    assert got <= rounded + 1e-9
    # and it is a coordinate-wise minimum: no single code moved by one lowers it
    for i, c in itertools.product(range(len(q)), range(3)):
        for d in (-1, 1):
            if np.floor(t[i, c]) <= q[i, c] + d <= np.ceil(t[i, c]):
                moved = q.copy()
                moved[i, c] += d
                assert _objective(A, X, lo + step * moved) >= got - 1e-9


def test_fed_back_codes_reach_the_best_codes_of_a_small_problem_more_often_than_rounding():
    """On problems small enough to try every code in the box (``2^n`` per axis), the fed
    back codes are the exhaustive optimum or near it, and on the sum far nearer than
    rounding to nearest."""
    rng = np.random.default_rng(7)
    excess_fed, excess_plain = 0.0, 0.0
    for _ in range(8):
        A, X, x, lo, step = _random_problem(rng, 20, 8, 0.5)
        t = (x - lo) / step
        plain = np.rint(t).astype(np.int64)
        q = grid_codes(sp.kron(sp.csr_matrix(A.T @ A), sp.identity(3)), A.T @ X, x, plain,
                       lo, step)
        for c in range(3):
            best = min(_objective(A[:, :], X[:, [c]], (lo[c] + step[c] * np.array(bits))[:, None])
                       for bits in itertools.product(*[(np.floor(v), np.ceil(v))
                                                        for v in t[:, c]]))
            fed = _objective(A, X[:, [c]], (lo[c] + step[c] * q[:, c])[:, None])
            rounded = _objective(A, X[:, [c]], (lo[c] + step[c] * plain[:, c])[:, None])
            assert best - 1e-9 <= fed <= rounded + 1e-9
            excess_fed += fed - best
            excess_plain += rounded - best
    assert excess_fed < 0.5 * excess_plain


def test_fixed_codes_are_not_moved_and_a_rate_keeps_more_codes():
    rng = np.random.default_rng(3)
    A, X, x, lo, step = _random_problem(rng, 80, 30, 0.1)
    plain = np.rint((x - lo) / step).astype(np.int64)
    H, rhs = sp.kron(sp.csr_matrix(A.T @ A), sp.identity(3)), A.T @ X
    fixed = rng.random(plain.shape) < 0.3
    q = grid_codes(H, rhs, x, plain, lo, step, fixed)
    assert np.array_equal(q[fixed], plain[fixed])
    free = grid_codes(H, rhs, x, plain, lo, step)
    taxed = grid_codes(H, rhs, x, plain, lo, step, rate=50.0)
    assert np.count_nonzero(taxed != plain) < np.count_nonzero(free != plain)
    assert np.array_equal(grid_codes(H, rhs, x, plain, lo, step, sweeps=0), plain)


def test_coupling_colours_never_give_two_coupled_unknowns_one_colour():
    B = sp.random(300, 300, density=0.02, random_state=np.random.RandomState(1))
    H = (B @ B.T + sp.identity(300)).tocsr()
    colour = coupling_colours(H)
    rows, cols = H.nonzero()
    off = rows != cols
    assert np.all(colour[rows[off]] != colour[cols[off]])
    degree = np.diff(H.indptr) - 1
    assert colour.max() <= degree.max()


def _greedy_colours(H: sp.csr_matrix) -> np.ndarray:
    """Welsh and Powell one unknown at a time: in order of decreasing row length (ties by
    index), the smallest colour that no unknown of its row has yet."""
    H = sp.csr_matrix(H)
    colour = [-1] * H.shape[0]
    for i in sorted(range(H.shape[0]), key=lambda i: (-(H.indptr[i + 1] - H.indptr[i]), i)):
        used = {colour[j] for j in H.indices[H.indptr[i]:H.indptr[i + 1]]}
        colour[i] = min(c for c in range(len(used) + 1) if c not in used)
    return np.array(colour)


@pytest.mark.parametrize("case", ["symmetric", "asymmetric", "a clique of 70",
                                  "entries stored twice"])
def test_coupling_colours_in_rounds_are_the_greedy_ones_in_turn(case):
    """The rounds of ``coupling_colours`` give the colours of the greedy order one at a time,
    on symmetric and asymmetric patterns, and (one at a time) where colours pass what a
    64-bit mask holds (70 unknowns all coupled: colours 0..69)."""
    rng = np.random.RandomState(3)
    B = sp.random(400, 400, density=0.015, random_state=rng)
    H = (B @ B.T + sp.identity(400)).tocsr() if case == "symmetric" else \
        (B + sp.identity(400)).tocsr()
    if case == "a clique of 70":
        clique = np.zeros((400, 400))
        clique[100:170, 100:170] = 1.0
        H = (H + sp.csr_matrix(clique)).tocsr()
    if case == "entries stored twice":  # each row's entries twice over, not summed
        rows = [np.tile(H.indices[H.indptr[i]:H.indptr[i + 1]], 2) for i in range(400)]
        H = sp.csr_matrix((np.ones(sum(map(len, rows))), np.concatenate(rows),
                           np.r_[0, np.cumsum([len(r) for r in rows])]), shape=H.shape)
    expected = _greedy_colours(H)
    assert expected.max() >= (69 if case == "a clique of 70" else 3)
    assert np.array_equal(coupling_colours(H), expected)


@pytest.mark.parametrize("anchored", [False, True])
def test_lattice_descent_leaves_no_better_single_move(anchored):
    """``atlas.lattice.lattice_descent`` on a small dense quadratic, against its objective
    written out here: ``J(p) + sum_i lambda_i |q_i - a_i|`` with ``p = lo + step q``,
    ``lambda_i = 2 H_ii step_i^2 shrink_i``; after converged sweeps no single move by one
    step within the box lowers it, it is below its value at the start, and the values of
    colour ``-1`` are not moved."""
    from fitter.fitting.atlas.lattice import lattice_descent

    rng = np.random.default_rng(4)
    m = 40
    B = rng.normal(size=(60, m)) * (rng.random((60, m)) < 0.15)
    H = B.T @ B + 0.05 * np.eye(m)
    rhs = rng.normal(size=m) * 3.0
    lo, step = rng.normal(size=m), rng.uniform(0.5, 1.5, m)
    start = np.rint((np.linalg.solve(H, rhs) - lo) / step).astype(np.int64)
    low, high = start - 3, start + 3
    colour = coupling_colours(sp.csr_matrix(H))
    colour[:4] = -1
    shrink = rng.uniform(0.0, 0.6, m) if anchored else None
    a = np.zeros(m, np.int64) if anchored else start

    def objective(q):
        p = lo + step * q
        tax = 0.0 if shrink is None else float(np.sum(2 * np.diag(H) * step ** 2 * shrink
                                                      * np.abs(q - a)))
        return float(p @ H @ p - 2 * rhs @ p) + tax

    q = lattice_descent(sp.csr_matrix(H), rhs, start, lo, step, low, high, colour, 200,
                        shrink, a if anchored else None)
    assert np.array_equal(q[:4], start[:4])
    assert np.all((q >= low) & (q <= high))
    best = objective(q)
    assert best <= objective(start)
    for i in range(4, m):
        for move in (-1, 1):
            other = q.copy()
            other[i] += move
            if low[i] <= other[i] <= high[i]:
                assert objective(other) >= best - 1e-9 * abs(best)


def _sphere_scan():
    m = trimesh.creation.icosphere(subdivisions=4)
    return make_scan("sphere", np.asarray(m.vertices, np.float64), faces=np.asarray(m.faces),
                     source=new_source("sphere", None, "array", None, "array"))


@pytest.mark.parametrize("across", [0.0, 10.0])
def test_the_fed_back_base_is_on_its_files_grid_and_nearer_its_points(across, monkeypatch):
    """``fed_back_atlas`` gives control points on the file's grid (the file holds exactly
    them, each within a step of the fit), and the working points lie nearer the surface
    drawn from them than from the file of the fit rounded to nearest (the sphere at 8
    bits, where a step is a sixth of the fit's RMS; distances to a fine drawing), point to
    point and with the offsets across the surface weighed more (``ROUND_ACROSS``)."""
    from fitter.fitting.atlas.fit import fit_layout, grid_mesh, working_points
    from fitter.fitting.atlas.layout import decimate, quad_layout
    from fitter.fitting.atlas.measure import point_mesh_distance
    from fitter.fitting.atlas.surface import scan_surface

    scan = _sphere_scan()
    surface = scan_surface(scan)
    layout = quad_layout(*decimate(surface, 40))
    points, normals = working_points(scan, surface, 3000)
    atlas, f, u, v, _ = fit_layout(layout, points, normals, rounds=3)
    monkeypatch.setattr(atlas_fit, "ROUND_ACROSS", across)
    monkeypatch.setattr(atlas_fit, "BASE_TANGENT_FACTOR", None)  # version 3's grid
    bits = 8
    rounded = fed_back_atlas(atlas, bits, layout, points, f, u, v, smoothing=0.1,
                             anchor=1e-3)
    decoded, _ = read_atlas(write_atlas(rounded, bits))
    table, table_d = index_table(rounded), index_table(decoded)
    np.testing.assert_allclose(control_points(decoded)[table_d], control_points(rounded)[table],
                               rtol=0, atol=1e-12)
    step = np.ptp(control_points(atlas), axis=0) / 255
    assert np.all(np.abs(control_points(rounded) - control_points(atlas)) <= step + 1e-12)
    plain, _ = read_atlas(write_atlas(atlas, bits))

    def rms(a):
        return float(np.sqrt(np.mean(point_mesh_distance(points, *grid_mesh(a, 17)) ** 2)))

    fit, fed, near = rms(atlas), rms(rounded), rms(plain)
    assert fed < near
    assert fed ** 2 - fit ** 2 < 0.75 * (near ** 2 - fit ** 2)  # a quarter of the rounding's
    # squared error gone at least (point to point: 43 %)


def test_fit_atlas_returns_its_base_on_the_grid_it_is_written_at():
    fit = fit_atlas(_sphere_scan(), 60, working_count=3000, rounds=2, bits=9)
    decoded, _ = read_atlas(atlas_fit.base_file(fit.atlas, 9))
    nets = [control_points(a)[index_table(a)] for a in (decoded, fit.atlas)]  # (F, n, n, 3)
    np.testing.assert_allclose(nets[0], nets[1], rtol=0, atol=1e-12)
    assert fit.bytes == len(atlas_fit.base_file(fit.atlas, 9))
    assert "round" in fit.timings


def _client_pleats(atlas, resolution: int) -> np.ndarray:
    """Reference: each patch's triangles as ``client_py`` draws the atlas (welded, float32),
    two of one patch sharing an edge with unit normals more than 120° apart."""
    from client_py.atlas_mesh import tessellate_atlas

    mesh = tessellate_atlas(atlas, resolution, kernel="numpy", normals=False)
    v = np.frombuffer(mesh.positions, np.float32).reshape(-1, 3).astype(np.float64)
    tri = np.frombuffer(mesh.indices, np.uintc).reshape(-1, 3).astype(np.int64)
    per = 2 * (resolution - 1) ** 2
    n = np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    pleated = np.zeros(len(tri) // per, bool)
    for f in range(len(pleated)):
        edges: dict = {}
        for t in range(f * per, (f + 1) * per):
            for a, b in ((0, 1), (1, 2), (2, 0)):
                edges.setdefault(frozenset((tri[t, a], tri[t, b])), []).append(t)
        pleated[f] = any(len(ts) == 2 and n[ts[0]] @ n[ts[1]] < -0.5 for ts in edges.values())
    return pleated


def test_pleated_patches_are_those_the_client_draws_folded():
    """A sphere's base with its interior control points shaken hard enough to fold some
    patches: the patches found folded are those whose drawn triangles (client_py's own
    tessellation, an independent cut of the cells) fold over each other."""
    from fitter.fitting.atlas.fit import pleated_patches
    from fitter.fitting.atlas.patches import with_control_points

    fit = fit_atlas(_sphere_scan(), 60, working_count=3000, rounds=2)
    table = index_table(fit.atlas)
    points = control_points(fit.atlas)
    assert not pleated_patches(table, points, 3, 1).any()
    assert not _client_pleats(fit.atlas, base_resolution(1)).any()
    rng = np.random.default_rng(5)
    interior = np.unique(table[:, 1:3, 1:3])
    shaken = points.copy()
    shaken[interior] += rng.normal(scale=0.5, size=(len(interior), 3))
    atlas = with_control_points(fit.atlas, shaken)
    got = pleated_patches(table, shaken, 3, 1)
    assert 0 < got.sum() < len(got)
    assert np.array_equal(got, _client_pleats(atlas, base_resolution(1)))


def test_grid_codes_stay_on_the_files_grid():
    """A value at the grid's top whose step came out a hair short has ``t = top + 3e-14``:
    its box reached ``top + 1``, a code the file cannot hold (the writer then re-quantised
    every point). With ``top`` no code leaves ``0..top``, whatever the objective asks."""
    top = 255
    x = np.array([0.0, 1.0, 1.0])
    step = np.full(3, (1.0 - 1e-12) / top)
    plain = np.array([0, top, top])
    fixed = np.array([True, True, False])  # the bounds' own points stay (the writer's rule)
    H, rhs = sp.identity(3, format="csr"), np.array([0.0, 1.0, 1.5])  # pulled past the top
    assert grid_codes(H, rhs, x, plain, 0.0, step, fixed).max() == top + 1  # without top
    q = grid_codes(H, rhs, x, plain, 0.0, step, fixed, top=top)
    assert q.min() >= 0 and q.max() == top
