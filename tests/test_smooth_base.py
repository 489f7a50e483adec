"""client_py.smooth_base: the smooth atlas of a triangle control mesh against independent
references: the fitter's Catmull-Clark step and deep subdivision (the limit surface), scipy's
B-spline for the border, the layout's quads, and geometry (planes, affine maps, shared
borders)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import BSpline
from scipy.spatial import ConvexHull

from client_py.atlas import MAX_ATLAS_QUADS, MAX_ATLAS_VERTICES, AtlasSurface
from client_py.smooth_base import (
    SmoothBase,
    base_atlas,
    check_control_mesh,
    smooth_atlas,
    smooth_base,
)
from fitter.fitting.atlas.layout import quad_layout
from fitter.fitting.atlas.measure import closest_points_on_mesh
from fitter.fitting.atlas.subdivision import catmull_clark_step, subdivided

GOLD = (1 + 5 ** 0.5) / 2
ICO_POINTS = np.array([(-1, GOLD, 0), (1, GOLD, 0), (-1, -GOLD, 0), (1, -GOLD, 0), (0, -1, GOLD),
                       (0, 1, GOLD), (0, -1, -GOLD), (0, 1, -GOLD), (GOLD, 0, -1), (GOLD, 0, 1),
                       (-GOLD, 0, -1), (-GOLD, 0, 1)], float)
ICO_TRIANGLES = np.array([(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9),
                          (5, 11, 4), (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2),
                          (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10),
                          (8, 6, 7), (9, 8, 1)])
OCTAHEDRON = (np.array([(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)],
                       float),
              np.array([(0, 2, 4), (2, 1, 4), (1, 3, 4), (3, 0, 4), (2, 0, 5), (1, 2, 5),
                        (3, 1, 5), (0, 3, 5)]))
# two triangles meeting at vertex 0 only (4 border edges there: a corner), and point 5 in no
# triangle
BOWTIE = (np.array([(0, 0, 0), (1, 0, 0), (1, 1, 0.5), (-1, 0, 0.2), (-1, -1, 0), (5, 5, 5)],
                   float),
          np.array([(0, 1, 2), (0, 3, 4)]))
# two triangles closing on each other (every vertex of valence 2): the quads on an edge share
# more than the edge
DIHEDRON = (np.array([(0, 0, 0), (1, 0, 0), (0, 1, 0)], float), np.array([(0, 1, 2), (1, 0, 2)]))


def icosphere(bump: float = 0.2, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The icosahedron split once (42 points, 80 triangles, valences 5 and 6), each point's
    radius scaled by a random factor in ``1 ± bump``."""
    points, triangles, middle = list(ICO_POINTS), [], {}

    def mid(a, b):
        key = (min(a, b), max(a, b))
        if key not in middle:
            middle[key] = len(points)
            points.append((points[a] + points[b]) / 2)
        return middle[key]

    for a, b, c in ICO_TRIANGLES:
        ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
        triangles += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
    p = np.array(points)
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    p *= 1 + bump * np.random.default_rng(seed).uniform(-1, 1, (len(p), 1))
    return p, np.array(triangles)


def grid(nx: int, ny: int, height=lambda x, y: np.sin(x) * np.cos(0.7 * y)
         ) -> tuple[np.ndarray, np.ndarray]:
    """An open ``nx x ny`` grid of points ``(i, j, height)``, each square cut along a
    diagonal into two counter-clockwise triangles."""
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    x, y = i.ravel().astype(float), j.ravel().astype(float)
    points = np.stack([x, y, height(x, y)], axis=1)
    triangles = []
    for a in range(nx - 1):
        for b in range(ny - 1):
            p00, p10, p01, p11 = a * ny + b, (a + 1) * ny + b, a * ny + b + 1, (a + 1) * ny + b + 1
            triangles += [(p00, p10, p11), (p00, p11, p01)]
    return points, np.array(triangles)


def dense(rows, columns: int) -> np.ndarray:
    """Sparse rows ``[(i, w), ...]`` as a dense matrix."""
    out = np.zeros((len(rows), columns))
    for r, row in enumerate(rows):
        assert len({i for i, _ in row}) == len(row), f"row {r} repeats an index"
        for i, w in row:
            out[r, i] += w
    return out


def patch_grid(atlas: AtlasSurface, f: int, samples: int) -> np.ndarray:
    """Patch ``f`` evaluated on a ``samples x samples`` grid of ``[0, 1]²``, ``(s, s, 3)``."""
    surface, t = atlas.patch_surface(f), np.linspace(0.0, 1.0, samples)
    return np.array([[surface.evaluate(u, v) for v in t] for u in t])


def side_points(atlas: AtlasSurface, f: int, k: int, s: np.ndarray) -> np.ndarray:
    """Patch ``f``'s side ``k`` (``SIDES``) at ``s`` from the edge's lower vertex to its
    higher."""
    e, reverse = atlas.edges.sides[f][k]
    surface = atlas.patch_surface(f)
    t = 1.0 - s if reverse else s
    at = {0: lambda t: (t, 0.0), 1: lambda t: (1.0, t), 2: lambda t: (t, 1.0),
          3: lambda t: (0.0, t)}[k]
    return np.array([surface.evaluate(*at(x)) for x in t])


MESHES = {"octahedron": OCTAHEDRON, "icosphere": icosphere(), "grid": grid(5, 4),
          "bowtie": BOWTIE, "dihedron": DIHEDRON}


@pytest.mark.parametrize("name", MESHES)
def test_step_rows_and_quads_are_the_fitters_catmull_clark_step(name):
    points, triangles = MESHES[name]
    base = smooth_base(len(points), triangles.tolist())
    S, quads = catmull_clark_step(len(points), [triangles])
    # catmull_clark_step numbers vertex points, edge points (edges sorted by lo * n + hi, the
    # sorted (lo, hi) order) and face points as smooth_base does, and its quad per corner
    # (corner, edge point after it, face point, edge point before it) is quad 3 t + k
    np.testing.assert_allclose(dense(base.step_rows, len(points)), S.toarray(), atol=1e-15)
    assert base.quads == [tuple(q) for q in quads.tolist()]
    assert base.quads == [tuple(q) for q in quad_layout(points, triangles).quads.tolist()]
    assert base.step_vertex_count == S.shape[0]


@pytest.mark.parametrize("name", MESHES)
def test_rows_are_affine_combinations(name):
    points, triangles = MESHES[name]
    base = smooth_base(len(points), triangles)
    V = base.step_vertex_count
    np.testing.assert_allclose(dense(base.step_rows, len(points)).sum(axis=1), 1.0, atol=1e-14)
    acc = dense(base.acc_rows, V)
    np.testing.assert_allclose(acc.sum(axis=1), 1.0, atol=1e-14)
    assert acc.min() >= 0.0  # convex combinations: the patches stay in the control hull


@pytest.mark.parametrize("name", ["octahedron", "icosphere", "grid", "bowtie", "dihedron"])
def test_corner_points_are_catmull_clark_limit_positions(name):
    points, triangles = MESHES[name]
    atlas = smooth_atlas(points, triangles)
    V = len(atlas.vertices)
    drawn = subdivided(len(points), [triangles], levels=6).matrix @ points
    coarser = subdivided(len(points), [triangles], levels=5).matrix @ points
    # vertex points come first at every level, so step-1 vertex j is drawn vertex j; it
    # converges to its limit slowly at the centroids (valence 3): 9e-4 off at level 5, 3.5e-4
    # at level 6 on the icosphere (mean control edge 0.59)
    corners = np.array(atlas.vertices)
    error, before = (np.linalg.norm(corners - d[:V], axis=1) for d in (drawn, coarser))
    edge = np.mean(np.linalg.norm(points[triangles] - points[np.roll(triangles, 1, 1)], axis=2))
    assert error.max() < 1e-3 * edge
    assert error.max() < 0.6 * before.max()  # and the subdivision closes in on them
    if name == "bowtie":  # a corner and a point in no triangle are kept
        np.testing.assert_array_equal(corners[[0, 5]], points[[0, 5]])


def quad_grid(nx: int, ny: int, closed: bool) -> list[tuple[int, int, int, int]]:
    """Quads ``((i, j), (i+1, j), (i+1, j+1), (i, j+1))`` of an ``nx x ny`` grid of vertices
    ``i ny + j`` (``u`` along ``i``), closed into a torus or open."""
    quads = []
    for i in range(nx if closed else nx - 1):
        for j in range(ny if closed else ny - 1):
            i1, j1 = (i + 1) % nx, (j + 1) % ny
            quads.append((i * ny + j, i1 * ny + j, i1 * ny + j1, i * ny + j1))
    return quads


@pytest.mark.parametrize("closed", [True, False], ids=["torus", "open"])
def test_regular_quads_give_the_uniform_bicubic_b_spline(closed):
    """Where every corner is regular (4 quads inside, 2 on the border) the ACC rules are the
    uniform bicubic B-spline's Bézier form: scipy's B-spline of the grid, extended on an
    open border by the phantom points ``2 P_0 - P_1`` (Catmull-Clark's regular border with
    the B-spline border curve), is the reference."""
    from client_py.smooth_base import _acc_rows

    nx, ny = 7, 6
    rng = np.random.default_rng(5)
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    net = np.stack([i, j, np.zeros((nx, ny))], axis=-1) + rng.normal(size=(nx, ny, 3))
    quads = quad_grid(nx, ny, closed)
    rows = _acc_rows(nx * ny, quads)
    at = (dense(rows, nx * ny) @ net.reshape(-1, 3)).tolist()
    V, F = nx * ny, len(quads)
    atlas = AtlasSurface(3, 1, at[:V], quads, at[V:len(at) - 4 * F], at[len(at) - 4 * F:])
    if closed:  # coefficient k is P_(k-1) mod n, so that x = i is vertex i's limit
        ext = net[np.arange(-1, nx + 2) % nx][:, np.arange(-1, ny + 2) % ny]
    else:
        ext = np.zeros((nx + 2, ny + 2, 3))
        ext[1:-1, 1:-1] = net
        ext[0], ext[-1] = 2 * ext[1] - ext[2], 2 * ext[-2] - ext[-3]
        ext[:, 0], ext[:, -1] = 2 * ext[:, 1] - ext[:, 2], 2 * ext[:, -2] - ext[:, -3]
    basis_u = BSpline(np.arange(-3.0, len(ext) + 1), np.eye(len(ext)), 3)
    basis_v = BSpline(np.arange(-3.0, ext.shape[1] + 1), np.eye(ext.shape[1]), 3)
    quads_at = np.bincount(np.ravel(quads), minlength=V)
    on_border = np.zeros((nx, ny), bool)
    if not closed:
        on_border[[0, -1]], on_border[:, [0, -1]] = True, True
    regular = quads_at == np.where(on_border.ravel(), 2, 4)
    t = np.linspace(0.0, 1.0, 4)
    compared = 0
    for f, quad in enumerate(quads):
        if not regular[list(quad)].all():
            continue  # a grid corner (1 quad): no B-spline there
        i, j = divmod(quad[0], ny)
        expected = np.einsum("ua,abc,vb->uvc", basis_u(i + t), ext, basis_v(j + t))
        np.testing.assert_allclose(patch_grid(atlas, f, 4), expected, atol=1e-12)
        compared += 1
    assert compared == (F if closed else F - 4)


def test_atlas_stays_close_to_the_limit_surface():
    points, triangles = icosphere(bump=0.2)
    atlas = smooth_atlas(points, triangles)
    fine = subdivided(len(points), [triangles], levels=5)
    samples = np.concatenate([patch_grid(atlas, f, 5).reshape(-1, 3)
                              for f in range(len(atlas.quads))])
    distance, _, _ = closest_points_on_mesh(samples, fine.matrix @ points, fine.triangles)
    edge = np.mean(np.linalg.norm(points[triangles] - points[np.roll(triangles, 1, 1)], axis=2))
    # measured: 0.0033 of the mean control edge (0.00195 at edge 0.588); the level-5 mesh's
    # own chords are ~1e-4 of it. A patch per step-1 quad on its bilinear corners is ~100x off.
    assert distance.max() < 0.005 * edge
    assert np.median(distance) < 0.001 * edge


def test_planar_control_mesh_gives_a_planar_atlas():
    rng = np.random.default_rng(3)
    points, triangles = grid(6, 5, height=lambda x, y: 0.0 * x)
    points[:, :2] += rng.uniform(-0.2, 0.2, (len(points), 2))
    normal, offset = np.array([0.3, -0.5, 0.8]), 1.5
    points[:, 2] = (offset - points[:, :2] @ normal[:2]) / normal[2]  # on n . x = offset
    atlas = smooth_atlas(points, triangles)
    every = np.array([atlas.control_point(k) for k in range(atlas.control_point_count)])
    np.testing.assert_allclose(every @ normal, offset, atol=1e-12)
    assert np.ptp(every[:, 0]) > 4  # not collapsed


@pytest.mark.parametrize("name", ["icosphere", "grid"])
def test_affine_map_of_control_points_maps_the_atlas(name):
    points, triangles = MESHES[name]
    rng = np.random.default_rng(7)
    matrix, shift = rng.normal(size=(3, 3)), rng.normal(size=3)
    before = smooth_atlas(points, triangles)
    after = smooth_atlas(points @ matrix.T + shift, triangles)
    count = before.control_point_count
    mapped = np.array([before.control_point(k) for k in range(count)]) @ matrix.T + shift
    np.testing.assert_allclose([after.control_point(k) for k in range(count)], mapped,
                               atol=1e-12)


@pytest.mark.parametrize("name", ["icosphere", "grid"])
def test_patches_on_a_shared_edge_evaluate_alike(name):
    points, triangles = MESHES[name]
    atlas = smooth_atlas(points, triangles)
    s = np.linspace(0.0, 1.0, 5)
    shared = [pairs for pairs in atlas.edges.faces if len(pairs) == 2]
    assert shared
    for (f, k), (g, m) in shared:
        np.testing.assert_allclose(side_points(atlas, f, k, s), side_points(atlas, g, m, s),
                                   atol=1e-12)


# side k (SIDES) of a bicubic patch: its two inner border points (i, j) and the step inwards
SIDE_ROW = {0: ((1, 0), (2, 0)), 1: ((3, 1), (3, 2)), 2: ((1, 3), (2, 3)), 3: ((0, 1), (0, 2))}
INWARD = {0: (0, 1), 1: (-1, 0), 2: (0, -1), 3: (1, 0)}


@pytest.mark.parametrize("name", ["icosphere", "grid", "dihedron"])
def test_edge_and_corner_points_are_means_of_interior_points(name):
    """Read back through AtlasSurface's own numbering (``patch_indices``): on an interior
    edge each edge point's row is the mean of the rows of the two interior points beside it
    (one per patch); at an interior vertex the corner's row is the mean of the rows of the
    interior points next to it. Rows, not positions: the dihedron's centroids coincide."""
    points, triangles = MESHES[name]
    base = smooth_base(len(points), triangles)
    atlas = smooth_atlas(points, triangles, base)
    rows = dense(base.acc_rows, base.step_vertex_count)
    shared = [pairs for pairs in atlas.edges.faces if len(pairs) == 2]
    for pairs in shared:
        inner = []  # per patch: {edge point slot: the interior point beside it}
        for f, k in pairs:
            indices, (di, dj) = atlas.patch_indices(f), INWARD[k]
            inner.append({indices[i][j]: indices[i + di][j + dj] for i, j in SIDE_ROW[k]})
        assert inner[0].keys() == inner[1].keys()
        for slot, beside in inner[0].items():
            np.testing.assert_allclose(rows[slot], (rows[beside] + rows[inner[1][slot]]) / 2,
                                       atol=1e-15)
    around = [[] for _ in atlas.vertices]  # interior points next to each layout vertex
    for f in range(len(atlas.quads)):
        indices = atlas.patch_indices(f)
        for (i, j), (ii, jj) in zip([(0, 0), (3, 0), (3, 3), (0, 3)],
                                    [(1, 1), (2, 1), (2, 2), (1, 2)], strict=True):
            around[indices[i][j]].append(indices[ii][jj])
    border = {v for e in atlas.edges.border_edges for v in atlas.edges.edges[e]}
    inside = [v for v in range(len(atlas.vertices)) if around[v] and v not in border]
    assert inside
    for v in inside:
        np.testing.assert_allclose(rows[v], rows[around[v]].mean(axis=0), atol=1e-15)


def border_loop(atlas: AtlasSurface) -> list[tuple[int, int, int]]:
    """The atlas's single border loop as ``(patch, side, +1 | -1)`` per layout edge, the sign
    the direction from the edge's lower vertex (+1) or higher (-1), in walking order."""
    border = {}
    for e in atlas.edges.border_edges:
        (f, k), = atlas.edges.faces[e]
        lo, hi = atlas.edges.edges[e]
        border.setdefault(lo, []).append((hi, f, k, 1))
        border.setdefault(hi, []).append((lo, f, k, -1))
    assert all(len(v) == 2 for v in border.values())  # one loop, no corner
    start = min(border)
    loop, previous, vertex = [], None, start
    while True:
        step = next(s for s in border[vertex] if s[0] != previous) if previous is not None \
            else border[vertex][0]
        loop.append(step[1:])
        previous, vertex = vertex, step[0]
        if vertex == start:
            return loop


@pytest.mark.parametrize("shape, height", [((6, 5), None), ((2, 7), lambda x, y: 0.0 * x)],
                         ids=["grid", "planar strip"])
def test_border_is_the_cubic_b_spline_of_the_step_one_border(shape, height):
    points, triangles = grid(*shape) if height is None else grid(*shape, height=height)
    base = smooth_base(len(points), triangles)
    atlas = smooth_atlas(points, triangles, base)
    step = dense(base.step_rows, len(points)) @ points  # step-1 positions, independently
    loop = border_loop(atlas)
    # the step-1 border polygon in walking order: each edge's starting vertex
    polygon = []
    for f, k, sign in loop:
        lo, hi = atlas.edges.edges[atlas.edges.sides[f][k][0]]
        polygon.append(lo if sign > 0 else hi)
    m = len(polygon)
    # closed uniform cubic B-spline: coefficients P_{m-1}, P_0, ..., P_{m-1}, P_0, P_1 on
    # knots -3..m+3, so that x = j is (P_{j-1} + 4 P_j + P_{j+1}) / 6, span j the edge j
    coefficients = step[[polygon[(k - 1) % m] for k in range(m + 3)]]
    curve = BSpline(np.arange(-3.0, m + 4.0), coefficients, 3)
    s = np.linspace(0.0, 1.0, 5)
    drawn = []
    for j, (f, k, sign) in enumerate(loop):
        along = side_points(atlas, f, k, s if sign > 0 else 1.0 - s)
        np.testing.assert_allclose(along, curve(j + s), atol=1e-12)
        drawn.append(along)
    # and inside the control border's convex hull (on x, y: the strip is planar there, the
    # grid's border a rectangle)
    border = np.unique(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]]]), axis=0)
    hull = ConvexHull(points[np.unique(border)][:, :2])
    xy = np.concatenate(drawn)[:, :2]
    assert np.all(xy @ hull.equations[:, :2].T + hull.equations[:, 2] <= 1e-12)


def test_precomputed_base_gives_the_same_atlas():
    points, triangles = icosphere()
    base = smooth_base(len(points), triangles)
    with_base, without = smooth_atlas(points, triangles, base), smooth_atlas(points, triangles)
    assert (with_base.vertices, with_base.edge_points, with_base.face_points, with_base.quads) \
        == (without.vertices, without.edge_points, without.face_points, without.quads)
    assert (with_base.degree, with_base.spans, with_base.weights) == (3, 1, None)
    assert isinstance(base, SmoothBase)


TRIANGLE = ([(0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0), (2, 2, 2)], [(0, 1, 2)])


@pytest.mark.parametrize("n_points, triangles, match", [
    (0, [(0, 1, 2)], "n_points must be an int >= 1"),
    (True, [(0, 1, 2)], "n_points must be an int >= 1"),
    (3, [], r"non-empty sequence of index triples \(T >= 1\)"),
    (3, [(0, 1)], r"triangles\[0\] = \(0, 1\): a triangle is 3 int indices"),
    (3, [(0, 1, 1.5)], r"triangles\[0\] = .*: a triangle is 3 int indices"),
    (3, [(0, 1, 3)], r"triangles\[0\] = \(0, 1, 3\): indices must be in 0..2"),
    (3, [(0, -1, 2)], r"indices must be in 0..2"),
    (3, [(0, 1, 1)], r"triangles\[0\] = \(0, 1, 1\) repeats a vertex"),
    (4, [(0, 1, 2), (0, 1, 3)], r"triangles 0 and 1 both run edge 0->1"),
    (5, [(0, 1, 2), (1, 0, 3), (4, 0, 1)], r"triangles 0 and 2 both run edge 0->1.*at most 2"),
    (MAX_ATLAS_VERTICES, [(0, 1, 2)], r"n \+ E \+ T = 131076 layout vertices.*at most 131072"),
])
@pytest.mark.parametrize("check", [smooth_base, check_control_mesh])
def test_bad_triangles_are_rejected(n_points, triangles, match, check):
    with pytest.raises(ValueError, match=match):
        check(n_points, triangles)


@pytest.mark.parametrize("check", [smooth_base, check_control_mesh])
def test_too_many_quads_are_rejected(check):
    _, triangles = grid(2, MAX_ATLAS_QUADS // 6 + 2)  # 2 (ny - 1) > MAX_ATLAS_QUADS / 3
    assert 3 * len(triangles) > MAX_ATLAS_QUADS
    with pytest.raises(ValueError, match=r"\d+ quads; an AtlasSurface takes at most 65536"):
        check(int(triangles.max()) + 1, triangles)


def test_base_atlas_of_the_applied_rows_is_the_smooth_atlas():
    points, triangles = OCTAHEDRON
    base = smooth_base(len(points), triangles.tolist())
    step = [np.sum([w * points[i] for i, w in row], axis=0) for row in base.step_rows]
    atlas_points = [np.sum([w * step[j] for j, w in row], axis=0).tolist()
                    for row in base.acc_rows]
    expected = smooth_atlas(points, triangles, base)
    atlas = base_atlas(base, atlas_points)
    assert atlas.quads == expected.quads
    for got, want in ((atlas.vertices, expected.vertices),
                      (atlas.edge_points, expected.edge_points),
                      (atlas.face_points, expected.face_points)):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-14)
    with pytest.raises(ValueError, match=r"atlas_points has \d+ points; the base has \d+"):
        base_atlas(base, atlas_points[:-1])


@pytest.mark.parametrize("points, match", [
    ([], r"points must be a non-empty \(n, 3\)"),
    ([(0, 0, 0), (1, 0, 0), (0, 1)], r"points\[2\] = \(0, 1\): a control point has 3"),
    ([(0, 0, 0), (1, 0, float("nan")), (0, 1, 0)], r"points\[1\] = .* is not finite"),
    ([(0, 0, 0), (1, 0, 0), (0, None, 0)], r"points\[2\] = .*: coordinates must be numbers"),
    ([(0, 0, 0), (1, 0, 0)], r"indices must be in 0..1"),
])
def test_bad_points_are_rejected(points, match):
    with pytest.raises(ValueError, match=match):
        smooth_atlas(points, [(0, 1, 2)])


def test_base_of_another_mesh_is_rejected():
    points, triangles = TRIANGLE
    other = smooth_base(5, [(0, 2, 1)])
    with pytest.raises(ValueError, match="base is not the smooth_base of these 5 points"):
        smooth_atlas(points, triangles, other)
