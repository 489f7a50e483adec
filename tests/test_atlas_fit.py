"""The atlas fit (fitter.fitting.atlas): surface, layout, shared-border solve, watertightness."""

import os
from pathlib import Path

import numpy as np
import pytest
import trimesh

from fitter.fitting.atlas import AtlasFit, SurfaceError, fit_atlas, quad_layout, scan_surface
from fitter.fitting.atlas import fit as atlas_fit
from fitter.fitting.atlas import patches as atlas_patches
from fitter.fitting.atlas.fit import (
    base_file,
    border_foot_points,
    border_outward,
    border_points,
    cloud_warm,
    fit_layout,
    fold_row_weights,
    folded_patches,
    grid_mesh,
    regularisation_weights,
    smoothing_matrix,
    solve_control_points,
    warm_factor,
    working_points,
)
from fitter.fitting.atlas.layout import (
    STRAY_REACH,
    THIN_CAP,
    AtlasLayoutError,
    bilinear_atlas,
    border_strays,
    decimate,
    decimate_on_border,
    euler_characteristics,
    flip_edges,
    split_edges,
    split_longest_edges,
    thickness,
    thin_part_weights,
    triangle_fidelity,
)
from fitter.fitting.atlas.patches import (
    control_points,
    design_matrix,
    evaluate_patches,
    index_table,
    neighbour_table,
    triangle_to_quad,
)
from fitter.fitting.atlas.surface import (
    ScanSurface,
    clean_mesh,
    manifold_problems,
    unique_pairs,
)
from fitter.fitting.atlas.surface import border_edges as border_edges_of
from fitter.fitting.io.scan import Scan, make_scan, new_source
from tests.test_atlas import random_cube_atlas

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def _mesh_scan(vertices, faces, name="mesh") -> Scan:
    return make_scan(name, np.asarray(vertices, np.float64), faces=np.asarray(faces),
                     source=new_source(name, None, "array", None, "array"))


def _sphere_scan(subdivisions=4, centre=(0.0, 0.0, 0.0)) -> Scan:
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    return _mesh_scan(m.vertices + np.asarray(centre), m.faces, "sphere")


def _welded_border_edges(vertices: np.ndarray, faces: np.ndarray, tolerance: float) -> int:
    """Edges used by one triangle after merging vertices on a ``tolerance`` grid."""
    _, inverse = np.unique(np.round(vertices / tolerance).astype(np.int64), axis=0,
                           return_inverse=True)
    welded = inverse.reshape(-1)[faces]
    welded = welded[(welded[:, 0] != welded[:, 1]) & (welded[:, 1] != welded[:, 2])
                    & (welded[:, 2] != welded[:, 0])]
    return manifold_problems(welded)["border_edges"]


@pytest.mark.parametrize("options", [{}, {"return_counts": True}, {"return_index": True},
                                     {"return_inverse": True, "return_counts": True}])
def test_unique_pairs_is_numpys_unique_of_the_rows(options):
    rng = np.random.default_rng(3)
    for pairs in (rng.integers(0, 40, (2_000, 2)), rng.integers(0, 5, (7, 2)),
                  np.array([[0, 0]]), np.zeros((0, 2), np.int64)):
        ours = unique_pairs(pairs, **options)
        numpys = np.unique(pairs, axis=0, **options)
        ours, numpys = ((x if isinstance(x, tuple) else (x,)) for x in (ours, numpys))
        assert len(ours) == len(numpys)
        for a, b in zip(ours, numpys, strict=True):
            np.testing.assert_array_equal(a.reshape(-1), b.reshape(-1))
        assert ours[0].shape == (len(numpys[0]), 2)


def test_evaluation_and_grid_agree_with_the_reference_evaluator():
    rnd = random_cube_atlas(degree=3, spans=2, seed=4)
    polynomial = type(rnd)(rnd.degree, rnd.spans, rnd.vertices, rnd.quads, rnd.edge_points,
                           rnd.face_points, None)
    rng = np.random.default_rng(0)
    f = rng.integers(0, 6, 50)
    u, v = rng.random(50), rng.random(50)
    (c,) = evaluate_patches(index_table(polynomial), control_points(polynomial), 3, 2, f, u, v)
    for k in range(50):
        ref = polynomial.patch_surface(int(f[k])).evaluate(float(u[k]), float(v[k]))
        np.testing.assert_allclose(c[k], ref, atol=1e-12)
    for atlas in (polynomial, rnd):  # the grid also with weights
        vertices, _ = grid_mesh(atlas, 5)
        grid = vertices.reshape(6, 5, 5, 3)
        for face, a, b in ((0, 1, 3), (4, 4, 0), (5, 2, 2)):
            ref = atlas.patch_surface(face).evaluate(a / 4, b / 4)
            np.testing.assert_allclose(grid[face, a, b], ref, atol=1e-12)


def test_bilinear_atlas_is_its_layout_and_foot_points_are_exact():
    m = trimesh.creation.icosphere(subdivisions=1)
    layout = quad_layout(m.vertices, m.faces)
    assert len(layout.quads) == 3 * len(m.faces)
    atlas = bilinear_atlas(layout, 3, 2)
    rng = np.random.default_rng(1)
    t = rng.integers(0, len(m.faces), 200)
    bary = rng.dirichlet((1.0, 1.0, 1.0), 200)
    x = np.einsum("kj,kjc->kc", bary, m.vertices[m.faces[t]])
    f, u, v = triangle_to_quad(x, layout.triangle_vertices, layout.triangles, t)
    (c,) = evaluate_patches(index_table(atlas), control_points(atlas), 3, 2, f, u, v)
    np.testing.assert_allclose(c, x, atol=1e-10)


def test_solve_equals_a_dense_lstsq_of_the_same_system():
    tetra = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], np.float64)
    layout = quad_layout(tetra / np.sqrt(3), [[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])
    atlas = bilinear_atlas(layout, 3, 1)
    table = index_table(atlas)
    rng = np.random.default_rng(2)
    n = 200
    f = rng.integers(0, len(atlas.quads), n)
    u, v = rng.random(n), rng.random(n)
    (x,) = evaluate_patches(table, control_points(atlas), 3, 1, f, u, v)
    x = x / np.linalg.norm(x, axis=1, keepdims=True)  # points on the sphere
    A = design_matrix(table, atlas.control_point_count, 3, 1, f, u, v)
    L = smoothing_matrix(atlas, table)
    prior = control_points(atlas)
    got = solve_control_points(A, x, L, prior, 1e-2, 1e-2)
    lam, mu = regularisation_weights(A, L, 1e-2, 1e-2)
    stacked = np.vstack([A.toarray(), np.sqrt(lam) * L.toarray(),
                         np.sqrt(mu) * np.eye(A.shape[1])])
    rhs = np.vstack([x, np.zeros((L.shape[0], 3)), np.sqrt(mu) * prior])
    want = np.linalg.lstsq(stacked, rhs, rcond=None)[0]
    np.testing.assert_allclose(got, want, atol=1e-9)


@pytest.fixture(scope="module")
def sphere_fit() -> AtlasFit:
    return fit_atlas(_sphere_scan(4), 60, working_count=3000, rounds=3)


def test_a_sphere_is_recovered_far_below_the_layouts_chord_error(sphere_fit):
    layout = sphere_fit.layout
    chord = 1.0 - np.linalg.norm(layout.vertices, axis=1).min()  # the centroids' depth
    assert sphere_fit.patches == 3 * sphere_fit.triangles
    assert chord > 0.05
    assert sphere_fit.rms < chord / 30
    vertices, _ = grid_mesh(sphere_fit.atlas, 9)
    assert np.abs(np.linalg.norm(vertices, axis=1) - 1.0).max() < chord / 5
    assert sphere_fit.bytes > 0 and set(sphere_fit.timings) >= {"surface", "solve", "correct"}
    # signed distances: outward positive on a closed piece
    outside = np.linalg.norm(sphere_fit.points, axis=1) > 1.0 + 1e-3
    assert np.all(sphere_fit.distance[outside] > 0)


def test_the_base_is_watertight_on_a_closed_input(sphere_fit):
    vertices, faces = grid_mesh(sphere_fit.atlas, 9)
    assert _welded_border_edges(vertices, faces, 1e-9) == 0


def test_two_pieces_both_get_patches():
    a, b = _sphere_scan(3), _sphere_scan(3, centre=(3.0, 0.0, 0.0))
    scan = _mesh_scan(np.vstack([a.points, b.points]),
                      np.vstack([a.faces, b.faces + len(a.points)]), "two")
    surface = scan_surface(scan)
    assert surface.pieces == 2
    fit = fit_atlas(scan, 120, working_count=3000, rounds=2, surface=surface)
    corners = np.asarray(fit.atlas.vertices)
    assert (corners[:, 0] < 1.5).sum() > 10 and (corners[:, 0] > 1.5).sum() > 10
    assert fit.rms < 0.01
    vertices, faces = grid_mesh(fit.atlas, 5)
    assert _welded_border_edges(vertices, faces, 1e-9) == 0


def test_a_non_manifold_edge_is_split_and_a_moebius_strip_refused():
    # a fin: three triangles on one edge (0, 1)
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0, 1.0]])
    faces = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    v, f, repairs = clean_mesh(vertices, faces, "fin")
    problems = manifold_problems(f)
    assert problems["nonmanifold_edges"] == 0 and problems["misoriented_edges"] == 0
    assert len(f) == 3  # no face removed
    # a Möbius strip: no consistent orientation exists
    k = 12
    angle = np.linspace(0, 2 * np.pi, k, endpoint=False)
    rows = []
    for w in (-0.3, 0.3):
        rows.append(np.column_stack([(1 + w * np.cos(angle / 2)) * np.cos(angle),
                                     (1 + w * np.cos(angle / 2)) * np.sin(angle),
                                     w * np.sin(angle / 2)]))
    strip = np.vstack(rows)
    quads = []
    for i in range(k):
        j = (i + 1) % k
        a, b = i, k + i
        c, d = (j, k + j) if j else (k + j, j)  # the half twist
        quads += [[a, c, b], [b, c, d]]
    with pytest.raises(SurfaceError, match="non-orientable|non-manifold"):
        clean_mesh(strip, np.array(quads), "moebius")


def test_a_folded_flap_that_splitting_leaves_is_removed():
    # five triangles (the neighbourhood of a fold in a quadric decimation of the Buddha's
    # trimmed stand-in): edge (2, 3) has three faces, which MeshLab's split leaves as they are
    vertices = np.array([[-2.0, 0, 0], [0, 0, -1.0], [0, 0, 0], [1, 1, 0], [0, 1, 1.0]])
    faces = np.array([[2, 1, 0], [2, 3, 1], [3, 0, 4], [3, 2, 0], [3, 4, 2]])
    v, f, repairs = clean_mesh(vertices, faces, "flap")
    problems = manifold_problems(f)
    assert problems["nonmanifold_edges"] == 0 and problems["misoriented_edges"] == 0
    assert repairs["nonmanifold_faces_removed"] == 1 and len(f) == 4
    # independent reference: the removed face is the smallest of the three on edge (2, 3)
    kept = {tuple(sorted(map(tuple, v[face]))) for face in f}
    gone = [k for k, face in enumerate(faces)
            if tuple(sorted(map(tuple, vertices[face]))) not in kept]
    on_edge = [k for k, face in enumerate(faces) if {2, 3} <= set(face.tolist())]
    tri = vertices[faces[on_edge]]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    assert gone == [on_edge[int(np.argmin(area))]]


def test_a_folded_pair_of_faces_without_area_is_dropped_and_the_surface_lays_out():
    # what Forstmann's fast collapse made of Stanford Lucy subdivided (stream.working_mesh):
    # two opposite faces on the same three almost collinear vertices of a closed surface.
    # MeshLab keeps one of the pair and splits it off; alone, with no area, it made every
    # layout of the surface fail ("triangles without area")
    sphere = trimesh.creation.icosphere(subdivisions=3)
    vertices, faces = sphere.vertices.copy(), sphere.faces.copy()
    a, b = faces[0, 0], faces[0, 1]
    around = [k for k, face in enumerate(faces) if {a, b} <= set(face.tolist())]
    middle = len(vertices)
    off_line = np.cross(vertices[b] - vertices[a], vertices[a])
    vertices = np.vstack([vertices, 0.5 * (vertices[a] + vertices[b])
                          + 1e-12 * off_line / np.linalg.norm(off_line)])
    split = []
    for k in around:  # each face on edge (a, b) split at its middle, orientation kept
        face = faces[k].tolist()
        i = face.index(a)
        j = (i + 1) % 3 if face[(i + 1) % 3] == b else (i + 2) % 3
        for end in (i, j):
            half = list(face)
            half[j if end == i else i] = middle
            split.append(half)
    faces = np.vstack([np.delete(faces, around, axis=0), split,
                       [[a, middle, b], [a, b, middle]]])
    assert manifold_problems(faces)["nonmanifold_edges"] > 0
    v, f, repairs = clean_mesh(vertices, faces, "folded pair")
    assert repairs["pieces_without_area_dropped"] == 1
    assert manifold_problems(f)["border_edges"] == 0
    assert euler_characteristics(v, f) == [2]
    surface = scan_surface(_mesh_scan(vertices, faces, "folded pair"))
    assert surface.pieces == 1
    layout_vertices, layout = decimate(surface, 60)
    assert manifold_problems(layout)["border_edges"] == 0


def test_an_intermediate_decimation_may_keep_a_triangle_without_area_a_layout_may_not():
    # a flat quad (A, B, D, E) with C 1e-13 off the edge AB: the sliver (B, C, A) has a
    # twice-area of 1e-13, under NO_AREA x diagonal^2 = 5e-12, in a piece that has area
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1e-13, 0], [0.5, 1, 0], [0.5, -1, 0.0]])
    faces = np.array([[0, 2, 3], [2, 1, 3], [1, 2, 0], [1, 0, 4]])
    assert manifold_problems(faces)["misoriented_edges"] == 0
    surface = ScanSurface(vertices, faces, "mesh", 1, {})
    with pytest.raises(AtlasLayoutError, match="1 triangles without area"):
        decimate(surface, 10)
    v, f = decimate(surface, 10, require_area=False)
    assert len(f) == 4
    v, f = decimate_on_border(surface, 10, require_area=False)
    assert len(f) == 4


def test_a_point_cloud_is_reconstructed_and_fitted():
    rng = np.random.default_rng(3)
    p = rng.normal(size=(6000, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    scan = Scan.from_array(p, normals=p.astype(np.float32), name="cloud")
    surface = scan_surface(scan, poisson_depth=6)
    assert surface.origin == "poisson" and surface.pieces == 1
    assert manifold_problems(surface.faces)["border_edges"] == 0
    fit = fit_atlas(scan, 60, working_count=3000, rounds=2, surface=surface)
    assert fit.rms < 0.01


def test_an_open_cloud_stays_open_after_poisson():
    rng = np.random.default_rng(4)
    p = rng.normal(size=(6000, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    p = p[p[:, 2] > 0.2]  # a cap: Poisson closes it, the trim must open it again
    surface = scan_surface(Scan.from_array(p, normals=p.astype(np.float32), name="cap"),
                           poisson_depth=6)
    assert manifold_problems(surface.faces)["border_edges"] > 0
    assert surface.vertices[:, 2].min() > 0.2 - 0.1


@pytest.mark.parametrize("kwargs,match", [
    ({"patches": "many"}, "patches must be 'auto' or an int"),
    ({"patches": 1}, "single-patch"),
    ({"degree": 5}, "degree must be an int in 1..3"),
    ({"smoothing": float("nan")}, "smoothing must be"),
])
def test_bad_arguments_name_the_argument(kwargs, match):
    with pytest.raises(ValueError, match=match):
        fit_atlas(_sphere_scan(1), **kwargs)


def test_a_tiny_cloud_is_refused():
    with pytest.raises(SurfaceError, match="at least 100"):
        scan_surface(Scan.from_array(np.random.default_rng(0).random((20, 3)), name="tiny"))


@pytest.mark.skipif(not (DATA / "stanford-bunny" / "bun_zipper.ply.gz").exists(),
                    reason="the shared scans (../shared/data) are not on this machine")
def test_the_bunny_layout_keeps_its_topology_and_holes():
    from fitter.fitting.io import load_scan

    surface = scan_surface(load_scan(DATA / "stanford-bunny" / "bun_zipper.ply.gz"))
    vertices, triangles = decimate(surface, 20_000)  # as fit_atlas does: via 20,000
    middle = type(surface)(vertices, triangles, surface.origin, surface.pieces)
    vertices, triangles = decimate(middle, 200)
    assert abs(len(triangles) - 200) <= 10
    assert euler_characteristics(vertices, triangles) == euler_characteristics(
        surface.vertices, surface.faces)
    problems = manifold_problems(triangles)
    assert problems["nonmanifold_edges"] == 0 and problems["misoriented_edges"] == 0
    assert problems["border_edges"] > 0  # the scan's holes stay holes


def test_auto_grows_the_layout_within_the_byte_budget():
    fit = fit_atlas(_sphere_scan(3), "auto", byte_budget=9000, working_count=2000, rounds=1)
    sizes = [trial["bytes"] for trial in fit.trials if "bytes" in trial]
    assert len(sizes) >= 2 and sizes == sorted(sizes)
    assert fit.bytes <= 9000  # the final fit of the chosen layout, all points
    assert fit.patches == 3 * fit.triangles
    assert fit.triangles in [trial["triangles"] for trial in fit.trials]


def test_thickness_is_the_chord_through_the_solid_and_inf_on_an_open_sheet():
    m = trimesh.creation.icosphere(subdivisions=3, radius=2.0)
    tau = thickness(m.vertices, m.faces)
    np.testing.assert_allclose(tau, 4.0, rtol=0.01)  # every inward ray is a diameter
    grid = trimesh.creation.box().subdivide()  # a closed box, cut open below
    keep = grid.triangles_center[:, 2] > -0.49
    sheet = trimesh.Trimesh(grid.vertices, grid.faces[keep])
    sheet.remove_unreferenced_vertices()
    tau = dict(zip(map(tuple, np.round(sheet.vertices, 6)),
                   thickness(sheet.vertices, sheet.faces), strict=True))
    assert tau[(0.5, 0.0, 0.0)] == pytest.approx(1.0, rel=1e-3)  # a side's centre: across
    assert np.isinf(tau[(0.0, 0.0, 0.5)])  # the top's centre: the ray leaves by the opening


def _sphere_and_thin_disc() -> Scan:
    """A ball of radius 1 and, apart, a disc 1.6 wide and 0.06 thick (two closed pieces)."""
    ball = trimesh.creation.icosphere(subdivisions=4)
    disc = trimesh.creation.icosphere(subdivisions=4)
    disc.vertices = disc.vertices * [0.8, 0.8, 0.03] + [3.0, 0.0, 0.0]
    both = trimesh.util.concatenate([ball, disc])
    return _mesh_scan(both.vertices, both.faces, "ball and disc")


def test_thin_part_weights_give_a_thin_sheet_more_of_the_layout():
    surface = scan_surface(_sphere_and_thin_disc())
    weights = thin_part_weights(surface, 100)
    on_disc = surface.vertices[:, 0] > 2.0
    assert weights.min() >= 1.0 and weights.max() <= THIN_CAP
    assert np.median(weights[on_disc]) > 10 * np.median(weights[~on_disc])
    plain_v, plain_t = decimate(surface, 100)
    thin_v, thin_t = decimate(surface, 100, weights)
    disc_share = [np.mean(v[t].mean(axis=1)[:, 0] > 2.0) for v, t in
                  ((plain_v, plain_t), (thin_v, thin_t))]
    assert disc_share[1] > disc_share[0] + 0.1
    # equal weights (a ball alone has no thin part) are the plain decimation
    even_v, even_t = decimate(surface, 100, np.ones(len(surface.vertices)))
    np.testing.assert_array_equal(even_t, plain_t)
    with pytest.raises(ValueError, match="finite numbers > 0"):
        decimate(surface, 100, np.zeros(len(surface.vertices)))


def _bumpy_ball_and_small_disc() -> Scan:
    """A ball whose radius waves by 8 % (detail that needs layout triangles) and, apart, a
    disc 0.6 wide and 0.04 thick (a thin part that the weighted decimation favours)."""
    ball = trimesh.creation.icosphere(subdivisions=4)
    v = ball.vertices
    ball.vertices = v * (1 + 0.08 * np.prod(np.sin(6 * v), axis=1))[:, None]
    disc = trimesh.creation.icosphere(subdivisions=2)
    disc.vertices = disc.vertices * [0.3, 0.3, 0.02] + [1.6, 0.0, 0.0]
    both = trimesh.util.concatenate([ball, disc])
    return _mesh_scan(both.vertices, both.faces, "bumpy ball and small disc")


@pytest.mark.parametrize("triangles, kept", [(60, "plain"), (120, "weighted")])
def test_a_trial_keeps_the_layout_with_the_lower_rms(triangles, kept):
    # at 60 triangles the disc's weights take too many from the waves (plain RMS about half
    # the weighted); at 120 the waves have enough and the disc gains (weighted 0.6x plain)
    fit = fit_atlas(_bumpy_ball_and_small_disc(), 3 * triangles, working_count=2000,
                    rounds=1)
    (trial,) = fit.trials
    rms = trial["rms_by_layout"]
    assert set(rms) == {"plain", "weighted"}
    assert trial["layout"] == min(rms, key=rms.get) == kept
    assert max(rms.values()) > 1.3 * min(rms.values())  # a clear winner, not a tie
    assert fit.rms == trial["rms"] == rms[kept]  # the fit returned is the kept one
    assert fit.triangles == trial["triangles"]


def test_a_ball_alone_fits_the_plain_layout_only():
    fit = fit_atlas(_sphere_scan(3), 150, working_count=2000, rounds=1)
    (trial,) = fit.trials
    assert trial["layout"] == "plain" and set(trial["rms_by_layout"]) == {"plain"}


def _cut_sphere_scan(cut: float = -0.45) -> Scan:
    """A unit sphere with its cap below ``z = cut`` cut away: one open border, a bust's rim."""
    m = trimesh.creation.icosphere(subdivisions=4)
    faces = m.faces[m.vertices[m.faces][:, :, 2].min(axis=1) > cut]
    used, faces = np.unique(faces, return_inverse=True)
    return _mesh_scan(m.vertices[used], faces.reshape(-1, 3), "cut sphere")


def test_border_points_are_the_open_border_and_its_midpoints():
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 0.0]])
    fan = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    got = border_points(square, fan)
    assert len(got) == 8  # the 4 corners and the 4 side midpoints, not the centre
    assert not np.any(np.all(np.isclose(got, [0.5, 0.5, 0.0]), axis=1))
    assert len(border_points(*_sphere_mesh())) == 0


def test_border_outward_leaves_the_surface_across_its_rim():
    """The square fan: a side's midpoint leaves along the side's outer normal, a corner
    along the diagonal, and ``overshoot`` moves the points that far along them. The cut
    sphere: its rim's directions lie in the sphere's tangent plane (the triangles' planes,
    to their flatness) and point down the meridian, toward the cut cap."""
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 0.0]])
    fan = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    points, out = border_points(square, fan), border_outward(square, fan)
    centre = np.array([0.5, 0.5, 0.0])
    want = (points - centre) / np.linalg.norm(points - centre, axis=1, keepdims=True)
    np.testing.assert_allclose(out, want, atol=1e-12)
    np.testing.assert_allclose(border_points(square, fan, 0.1), points + 0.1 * want)
    scan = _cut_sphere_scan()
    rim, out = border_points(scan.points, scan.faces), border_outward(scan.points, scan.faces)
    radial = rim / np.linalg.norm(rim, axis=1, keepdims=True)
    assert np.max(np.abs(np.einsum("kc,kc->k", out, radial))) < 0.2
    # the meridian's downward tangent at each rim point: (z r_xy / |r_xy|, -|r_xy|)
    flat = np.linalg.norm(radial[:, :2], axis=1)
    down = np.column_stack([radial[:, 2, None] * radial[:, :2] / flat[:, None], -flat])
    along = np.einsum("kc,kc->k", out, down)  # the cut rim zigzags along its triangles
    assert np.all(along > 0.5) and np.mean(along) > 0.9
    assert len(border_outward(*_sphere_mesh())) == 0


def _sphere_mesh():
    m = trimesh.creation.icosphere(subdivisions=1)
    return m.vertices, m.faces


def test_open_border_curves_follow_the_scans_cut_rim():
    scan = _cut_sphere_scan()
    surface = scan_surface(scan)
    vertices, triangles = decimate(surface, 80)
    layout = quad_layout(vertices, triangles)
    points, normals = working_points(scan, surface, 4000)
    rim = border_points(surface.vertices, surface.faces)
    gaps, rms = {}, {}
    for name, border in (("free", None), ("held", rim)):
        atlas, _, _, _, distance = fit_layout(layout, points, normals, rounds=3, border=border)
        _, _, _, gaps[name] = border_foot_points(index_table(atlas), control_points(atlas), 3,
                                                 1, neighbour_table(atlas), rim)
        rms[name] = np.sqrt(np.mean(distance ** 2))
    # held, the open border curves run along the rim (free, the chords of the decimated rim
    # and the foot points clamped onto them leave 0.06 of the unit radius between them)
    assert gaps["held"].max() < 0.02
    assert gaps["free"].max() > 3 * gaps["held"].max()
    assert rms["held"] < 1.2 * rms["free"]  # and the rest of the sphere is fitted as well
    # fit_atlas holds the rim too, BORDER_OVERSHOOT median edges beyond it
    fit = fit_atlas(scan, 240, working_count=4000, rounds=3)
    beyond = border_points(surface.vertices, surface.faces, atlas_fit.BORDER_OVERSHOOT
                           * atlas_fit.median_edge(surface.vertices, surface.faces))
    _, _, _, gap = border_foot_points(index_table(fit.atlas), control_points(fit.atlas), 3, 1,
                                      neighbour_table(fit.atlas), beyond)
    assert gap.max() < 0.02
    with pytest.raises(ValueError, match="border must be finite points"):
        fit_layout(layout, points, normals, rounds=1, border=rim[:, :2])


def _jagged_cut_sphere_scan() -> Scan:
    """A unit sphere cut below ``z = -0.5 + 0.2 sin 9θ``: a bust's rim, sawn unevenly."""
    m = trimesh.creation.icosphere(subdivisions=4)
    centre = m.vertices[m.faces].mean(axis=1)
    keep = centre[:, 2] > -0.5 + 0.2 * np.sin(9 * np.arctan2(centre[:, 1], centre[:, 0]))
    used, faces = np.unique(m.faces[keep], return_inverse=True)
    return _mesh_scan(m.vertices[used], faces.reshape(-1, 3), "jagged cut sphere")


def test_a_layouts_border_vertices_are_kept_on_the_scans_border():
    surface = scan_surface(_jagged_cut_sphere_scan())
    own = surface.vertices[np.unique(border_edges_of(surface.faces))]
    reach = STRAY_REACH * np.linalg.norm(np.ptp(surface.vertices, axis=0))

    def strays(vertices, triangles):  # brute force: every layout border vertex to every rim one
        ends = vertices[np.unique(border_edges_of(triangles))]
        return int(np.sum(np.linalg.norm(ends[:, None] - own[None], axis=2).min(axis=1) > reach))

    plain = decimate(surface, 80)  # MeshLab's default border weight: a rim vertex pulled in
    kept = decimate_on_border(surface, 80)
    assert border_strays(surface, *plain) == strays(*plain) >= 1
    assert border_strays(surface, *kept) == strays(*kept) == 0
    assert euler_characteristics(*kept) == euler_characteristics(surface.vertices, surface.faces)
    assert not manifold_problems(kept[1])["nonmanifold_edges"]
    closed = scan_surface(_sphere_scan(2))  # no border of its own: every layout border strays
    assert border_strays(closed, *plain) == len(np.unique(border_edges_of(plain[1])))
    assert border_strays(closed, closed.vertices, closed.faces) == 0


def _valley_surface(n: int = 24):
    """``z = |x|`` over ``[-1.5, 1.5]²``: a straight valley along ``y``, its crease on grid
    lines, triangles counter-clockwise seen from ``+z``."""
    from fitter.fitting.atlas.surface import ScanSurface

    t = np.linspace(-1.5, 1.5, n + 1)
    x, y = np.meshgrid(t, t, indexing="ij")
    vertices = np.stack([x.ravel(), y.ravel(), np.abs(x.ravel())], axis=1)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    p = (i * (n + 1) + j).ravel()
    faces = np.concatenate([np.stack([p, p + n + 1, p + n + 2], axis=1),
                            np.stack([p, p + n + 2, p + 1], axis=1)])
    return ScanSurface(vertices, faces, "mesh", 1, {})


def test_a_layout_edge_bridging_a_valley_is_flipped_into_it():
    surface = _valley_surface()
    # a = (0, -1) and b = (0, 1) lie on the crease, c and d on the walls' tops; the edge
    # (c, d) bridges the valley 1 above its floor, the other diagonal (a, b) follows it
    vertices = np.array([[0, -1, 0], [0, 1, 0], [-1, 0, 1], [1, 0, 1]], np.float64)
    bridged = np.array([[2, 0, 3], [3, 1, 2]])
    energy, away = triangle_fidelity(surface, vertices, bridged)
    assert energy.sum() > 0.05 and away.sum() == 0  # far from the floor, facing up
    triangles, flips = flip_edges(surface, vertices, bridged)
    assert flips == 1
    assert {frozenset(t) for t in triangles.tolist()} == {frozenset((0, 1, 2)),
                                                         frozenset((0, 1, 3))}
    corners = vertices[triangles]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    assert np.all(normals[:, 2] > 0)  # still counter-clockwise seen from above
    np.testing.assert_allclose(triangle_fidelity(surface, vertices, triangles)[0], 0,
                               atol=1e-12)  # each new triangle lies in a wall's plane
    # a layout already on the surface is left alone
    assert flip_edges(surface, vertices, triangles)[1] == 0


def test_edge_flips_keep_a_decimated_layout_an_oriented_manifold_of_its_topology():
    torus = trimesh.creation.torus(major_radius=1.0, minor_radius=0.35, major_sections=64,
                                   minor_sections=32)
    v = torus.vertices
    torus.vertices = v * (1 + 0.06 * np.sin(7 * v[:, :1]) * np.cos(5 * v[:, 1:2]))
    surface = scan_surface(_mesh_scan(torus.vertices, torus.faces, "wavy torus"))
    vertices, triangles = decimate(surface, 120)
    before = triangle_fidelity(surface, vertices, triangles)
    flipped, flips = flip_edges(surface, vertices, triangles)
    after = triangle_fidelity(surface, vertices, flipped)
    assert flips > 0 and len(flipped) == len(triangles)
    problems = manifold_problems(flipped)
    assert problems["nonmanifold_edges"] == 0 and problems["misoriented_edges"] == 0
    assert euler_characteristics(vertices, flipped) == euler_characteristics(
        vertices, triangles) == [0]
    assert after[1].sum() <= before[1].sum()  # no more area facing away
    assert after[0].sum() < before[0].sum()


def _wavy_torus_surface(major: int = 96, minor: int = 48):
    torus = trimesh.creation.torus(major_radius=1.0, minor_radius=0.35, major_sections=major,
                                   minor_sections=minor)
    v = torus.vertices
    torus.vertices = v * (1 + 0.06 * np.sin(7 * v[:, :1]) * np.cos(5 * v[:, 1:2]))
    return scan_surface(_mesh_scan(torus.vertices, torus.faces, "wavy torus"))


def test_a_weighted_decimation_of_a_large_surface_is_reduced_fast_first_too(monkeypatch):
    """The thin-part weights (``fit``'s weighted layouts) went to MeshLab with the whole
    surface: minutes for a statue of 10^6 vertices. Above the threshold MeshLab now gets the
    fast pass's reduction, each of its vertices weighted as its nearest surface vertex."""
    from fitter.fitting.atlas import layout as atlas_layout

    surface = _wavy_torus_surface()  # 9,216 triangles
    weights = 1.0 + (surface.vertices[:, 2] > 0)  # 2 on the upper half, 1 below
    monkeypatch.setattr(atlas_layout, "PRE_REDUCE_FACES", 1_000)
    monkeypatch.setattr(atlas_layout, "PRE_REDUCE_FACTOR", 2)
    given = []
    weighted = atlas_layout._weighted_meshset
    monkeypatch.setattr(atlas_layout, "_weighted_meshset",
                        lambda v, f, w: given.append((v, f, w)) or weighted(v, f, w))
    vertices, triangles = decimate(surface, 200, weights)
    assert abs(len(triangles) - 200) <= 2
    assert euler_characteristics(vertices, triangles) == [0]
    v, f, w = given[0]
    assert len(f) == 1_000 and len(w) == len(v)  # the reduction, one weight a vertex
    upper = v[:, 2] > 0.05 * np.ptp(surface.vertices[:, 2])
    lower = v[:, 2] < -0.05 * np.ptp(surface.vertices[:, 2])
    assert np.all(w[upper] == 2.0) and np.all(w[lower] == 1.0)


def test_a_large_surface_is_reduced_fast_first_and_keeps_its_topology(monkeypatch):
    """Above PRE_REDUCE_FACES (lowered here) MeshLab decimates the fast pass's reduction:
    the same genus, the target's triangle count, and as near the surface as MeshLab alone."""
    from fitter.fitting.atlas import layout as atlas_layout
    from fitter.fitting.atlas.measure import closest_points_on_mesh

    surface = _wavy_torus_surface()  # 9,216 triangles
    alone = decimate(surface, 200)
    monkeypatch.setattr(atlas_layout, "PRE_REDUCE_FACES", 1_000)
    monkeypatch.setattr(atlas_layout, "PRE_REDUCE_FACTOR", 2)
    pre_vertices, pre_faces = atlas_layout._pre_reduced(surface, 200)
    assert len(pre_faces) == 1_000  # max(1,000, 2 x 200)
    assert euler_characteristics(pre_vertices, pre_faces) == [0]
    vertices, triangles = decimate(surface, 200)
    assert abs(len(triangles) - 200) <= 2
    problems = manifold_problems(triangles)
    assert problems["nonmanifold_edges"] == problems["misoriented_edges"] == 0
    assert euler_characteristics(vertices, triangles) == [0]
    probe = surface.vertices[::7]

    def rms(mesh):
        return float(np.sqrt(np.mean(closest_points_on_mesh(probe, *mesh)[0] ** 2)))

    assert rms((vertices, triangles)) < 1.5 * rms(alone)


def test_euler_characteristics_of_all_pieces_at_once_are_each_pieces_own():
    from fitter.fitting.atlas.surface import face_pieces

    def piece_by_piece(vertices, triangles):  # V - E + F of each piece on its own
        count, labels = face_pieces(triangles, len(vertices))
        out = []
        for piece in range(count):
            tri = triangles[labels == piece]
            edges = {tuple(sorted(e)) for t in tri.tolist()
                     for e in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}
            out.append(len(set(tri.reshape(-1).tolist())) - len(edges) + len(tri))
        return sorted(out)

    mesh = trimesh.util.concatenate([trimesh.creation.torus(1.0, 0.3),
                                     trimesh.creation.icosphere(2), trimesh.creation.box()])
    holed = mesh.faces[np.random.default_rng(0).permutation(len(mesh.faces))[:-40]]
    for faces in (mesh.faces, holed):
        assert euler_characteristics(mesh.vertices, faces) == piece_by_piece(
            mesh.vertices, np.asarray(faces))
    assert euler_characteristics(mesh.vertices, mesh.faces) == [0, 2, 2]
    assert euler_characteristics(mesh.vertices, mesh.faces[:0]) == []


def test_a_fast_reduction_that_changes_the_topology_or_fails_is_not_used(monkeypatch):
    import fast_simplification

    from fitter.fitting.atlas import layout as atlas_layout

    surface = _wavy_torus_surface()
    monkeypatch.setattr(atlas_layout, "PRE_REDUCE_FACES", 1_000)
    monkeypatch.setattr(atlas_layout, "PRE_REDUCE_FACTOR", 2)
    sphere = trimesh.creation.icosphere(3)  # genus 0 where the torus has genus 1
    monkeypatch.setattr(fast_simplification, "simplify",
                        lambda *a, **k: (sphere.vertices, sphere.faces))
    vertices, faces = atlas_layout._pre_reduced(surface, 200)
    assert vertices is surface.vertices and faces is surface.faces

    def fails(*args, **kwargs):
        raise RuntimeError("the fast pass gave up")

    monkeypatch.setattr(fast_simplification, "simplify", fails)  # nor one that fails
    assert atlas_layout._pre_reduced(surface, 200)[1] is surface.faces
    # and below the threshold the surface is MeshLab's input as it is
    monkeypatch.setattr(atlas_layout, "PRE_REDUCE_FACES", 5_000)
    assert atlas_layout._pre_reduced(surface, 200)[1] is surface.faces


def test_reverse_rows_pull_only_far_samples_straight_onto_the_surface():
    from fitter.fitting.atlas.fit import REVERSE_SAMPLES, reverse_rows

    plane = _valley_surface()
    flat = type(plane)(plane.vertices * [1.0, 1.0, 0.0], plane.faces, "mesh", 1, {})
    square = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64)
    atlas = bilinear_atlas(quad_layout(square, np.array([[0, 1, 2], [0, 2, 3]])), 3, 1)
    table = index_table(atlas)
    points = control_points(atlas)
    A, targets, held = reverse_rows(table, points, 3, 1, (flat.vertices, flat.faces))
    assert A.shape == (0, len(points)) and targets.shape == (0, 3)  # all on the plane
    assert held.shape == (len(table) * REVERSE_SAMPLES ** 2,) and not held.any()
    lifted = points.copy()
    inner = table[4][1:-1, 1:-1].reshape(-1)  # patch 4's own interior control points
    lifted[inner, 2] += 0.2
    A, targets, held = reverse_rows(table, lifted, 3, 1, (flat.vertices, flat.faces))
    drawn = A @ lifted  # the rows evaluate the atlas at the samples they hold
    assert 0 < len(targets) <= REVERSE_SAMPLES ** 2  # only the lifted patch is far
    assert np.all(drawn[:, 2] > 0.005 * flat.diagonal)
    np.testing.assert_allclose(targets[:, :2], drawn[:, :2], atol=1e-12)  # along the normal
    np.testing.assert_allclose(targets[:, 2], 0.0, atol=1e-12)  # onto the plane
    assert np.array_equal(np.nonzero(held)[0] // REVERSE_SAMPLES ** 2,
                          np.full(len(targets), 4))  # the far samples are patch 4's
    # a sample once far keeps its row in the next rounds, now pulled onto where it lies
    A2, targets2, held2 = reverse_rows(table, points, 3, 1, (flat.vertices, flat.faces), held)
    assert np.array_equal(held2, held) and len(targets2) == len(targets)
    np.testing.assert_allclose(targets2, A2 @ points, atol=1e-12)


def test_budget_bits_takes_up_to_three_bits_fewer_only_when_that_fits_the_budget(sphere_fit):
    from fitter.fitting.atlas.fit import (
        BASE_BITS,
        BUDGET_FEWER_BITS,
        atlas_bytes,
        base_bits,
        budget_bits,
    )

    atlas, rms = sphere_fit.atlas, sphere_fit.rms
    bits = base_bits(atlas, rms)
    assert BUDGET_FEWER_BITS == 3 and bits - 4 >= BASE_BITS[0]
    sizes = [atlas_bytes(atlas, bits - k) for k in range(5)]  # 0..4 bits fewer
    assert all(sizes[k] > sizes[k + 1] for k in range(4))
    assert budget_bits(atlas, rms, None, sizes[0]) == (bits, sizes[0])  # within: as the RMS says
    for k in (1, 2, 3):  # the most that fits
        assert budget_bits(atlas, rms, None, sizes[k - 1] - 1) == (bits - k, sizes[k])
    assert budget_bits(atlas, rms, None, sizes[3] - 1) == (bits, sizes[0])  # never four fewer
    assert budget_bits(atlas, rms, None, None) == (bits, sizes[0])  # an explicit patch count
    assert budget_bits(atlas, rms, 14, 10) == (14, atlas_bytes(atlas, 14))  # bits asked for
    assert sphere_fit.bits == 12  # fit_atlas asks for 12 bits unless told None


def _cyclic(triangles) -> list[tuple[int, ...]]:
    """Triangles each rotated to start at its smallest index (orientation kept), sorted."""
    out = []
    for t in np.asarray(triangles).tolist():
        k = t.index(min(t))
        out.append(tuple(t[k:] + t[:k]))
    return sorted(out)


def test_split_edges_cuts_both_triangles_of_an_edge_in_their_own_orientation():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float64)
    triangles = np.array([[0, 1, 2], [2, 1, 3]])
    new_v, new_t = split_edges(vertices, triangles, [[1, 2]], [[0.5, 0.5, 0.1]])
    np.testing.assert_array_equal(new_v[4], [0.5, 0.5, 0.1])
    # by hand: (0, 1, 2) -> (0, 1, 4), (4, 2, 0); (2, 1, 3) -> (2, 4, 3), (4, 1, 3)
    assert _cyclic(new_t) == _cyclic([(0, 1, 4), (4, 2, 0), (2, 4, 3), (4, 1, 3)])
    problems = manifold_problems(new_t)
    assert problems["nonmanifold_edges"] == 0 and problems["misoriented_edges"] == 0
    assert problems["border_edges"] == 4  # the square's outline, as before
    # a border edge splits its one triangle
    _, border_t = split_edges(vertices, triangles, [[0, 1]], [[0.5, 0, 0]])
    assert _cyclic(border_t) == _cyclic([(0, 4, 2), (4, 1, 2), (2, 1, 3)])
    with pytest.raises(ValueError, match="not an edge"):
        split_edges(vertices, triangles, [[0, 3]], [[0, 0, 0]])
    with pytest.raises(ValueError, match="two of the edges"):
        split_edges(vertices, triangles, [[0, 1], [1, 2]], [[0, 0, 0], [1, 1, 1]])
    with pytest.raises(ValueError, match="positions"):
        split_edges(vertices, triangles, [[0, 1]], np.zeros((2, 3)))


def test_split_longest_edges_drops_a_layout_bridging_a_valley_onto_its_floor():
    surface = _valley_surface()  # z = |x|
    # corners on the walls' tops (|x| = 1, z = 1); the shared diagonal (a, b) is the longest
    # edge and bridges the valley: its midpoint (0, 0, 1) is 1/sqrt(2) from both walls,
    # with feet (±1/2, 0, 1/2)
    vertices = np.array([[-1, -1, 1], [1, 1, 1], [1, -1, 1], [-1, 1, 1]], np.float64)
    triangles = np.array([[0, 2, 1], [0, 1, 3]])
    energy = triangle_fidelity(surface, vertices, triangles)[0].sum()
    new_v, new_t, made = split_longest_edges(surface, vertices, triangles, [1, 0])
    # both triangles share their longest edge: split once, for the first asked
    assert made == 1 and len(new_v) == 5 and len(new_t) == 4
    np.testing.assert_allclose(np.abs(new_v[4]), [0.5, 0.0, 0.5], atol=1e-9)
    assert _cyclic(new_t) == _cyclic([(0, 2, 4), (4, 2, 1), (0, 4, 3), (4, 1, 3)])
    assert triangle_fidelity(surface, new_v, new_t)[0].sum() < 0.6 * energy
    problems = manifold_problems(new_t)
    assert problems["nonmanifold_edges"] == 0 and problems["misoriented_edges"] == 0
    # then the longest edges are the square's sides (2 against 1.87 for the half
    # diagonals), border edges, which split their one triangle: 4 + 1 + 1 triangles, the
    # new vertices on the surface
    more_v, more_t, more = split_longest_edges(surface, new_v, new_t, [0, 2])
    assert more == 2 and len(more_t) == 6 and len(more_v) == 7
    np.testing.assert_allclose(more_v[5:, 2], np.abs(more_v[5:, 0]), atol=1e-9)
    assert split_longest_edges(surface, vertices, triangles, [])[2] == 0


def test_far_patch_samples_measure_the_drawn_base_against_the_scan():
    from fitter.fitting.atlas.fit import FAR_SAMPLES, far_patch_samples
    from fitter.fitting.atlas.patches import with_control_points

    plane = _valley_surface()
    flat = type(plane)(plane.vertices * [1.0, 1.0, 0.0], plane.faces, "mesh", 1, {})
    square = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64)
    atlas = bilinear_atlas(quad_layout(square, np.array([[0, 1, 2], [0, 2, 3]])), 3, 1)
    mesh = (flat.vertices, flat.faces)
    near = far_patch_samples(atlas, mesh)
    assert near.shape == (len(atlas.quads), FAR_SAMPLES ** 2)
    np.testing.assert_allclose(near, 0.0, atol=1e-12)
    # every control point 0.03 above the plane: the whole base is 0.03 / diagonal off
    lifted = with_control_points(atlas, control_points(atlas) + [0.0, 0.0, 0.03])
    diagonal = float(np.linalg.norm(np.ptp(flat.vertices, axis=0)))
    np.testing.assert_allclose(far_patch_samples(lifted, mesh), 0.03 / diagonal, rtol=1e-9)


def test_a_base_near_the_scan_everywhere_is_not_refined(sphere_fit):
    from fitter.fitting.atlas.fit import FAR_REACH, far_patch_samples, refine_far_base

    mesh = (sphere_fit.surface.vertices, sphere_fit.surface.faces)
    assert far_patch_samples(sphere_fit.atlas, mesh).max() <= FAR_REACH
    normals = np.zeros_like(sphere_fit.points)
    assert refine_far_base(sphere_fit.atlas, sphere_fit.layout, sphere_fit.surface,
                           sphere_fit.points, normals, scan_mesh=mesh) is None
    assert "refine_far" in sphere_fit.timings


def test_automatic_bits_never_collapse_a_small_piece():
    """A unit tetrahedron and one 2e-4 its size: at 8 bits (a step of 1/255) the small
    one's patches round to a point and the client has no normal for them; the automatic
    bits rise until it does, and that is what budget_bits returns."""
    from fitter.fitting.atlas.fit import atlas_bytes, budget_bits, keeps_every_normal
    from fitter.fitting.atlas.layout import bilinear_atlas, quad_layout

    tetra = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float64)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    vertices = np.concatenate([tetra, 0.5 + 2e-4 * tetra])
    atlas = bilinear_atlas(quad_layout(vertices, np.concatenate([faces, faces + 4])),
                           spans=1)
    assert keeps_every_normal(bilinear_atlas(quad_layout(tetra, faces), spans=1), 8)
    assert not keeps_every_normal(atlas, 8)
    bits, size = budget_bits(atlas, 1.0, None, None)  # an RMS that asks for 8 bits
    assert bits > 8 and keeps_every_normal(atlas, bits) and size == atlas_bytes(atlas, bits)
    assert not keeps_every_normal(atlas, bits - 1)
    assert budget_bits(atlas, 1.0, 8, None)[0] == 8  # bits asked for are kept


def test_decoded_base_is_what_a_reader_reads_from_base_file(sphere_fit, monkeypatch):
    """``decoded_base`` (the writer's own decoded atlas, no file read back) is
    ``read_atlas(base_file(...))``'s atlas, at the default tangential factor and in
    version 3 (the fallback when a frame code is too long)."""
    from client_py.atlas_format import read_atlas
    from fitter.fitting.atlas import fit as atlas_fit

    atlas = sphere_fit.atlas
    for factor in (atlas_fit.BASE_TANGENT_FACTOR, None):
        monkeypatch.setattr(atlas_fit, "BASE_TANGENT_FACTOR", factor)
        for bits in (8, 11):
            decoded = atlas_fit.decoded_base(atlas, bits)
            back, _ = read_atlas(atlas_fit.base_file(atlas, bits))
            assert decoded.vertices == back.vertices and decoded.quads == back.quads
            assert decoded.edge_points == back.edge_points
            assert decoded.face_points == back.face_points


# ------------------------------------------------------------------ folds
def _bezier_jacobian(net: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``det [C_u C_v]`` of a planar bicubic Bézier patch (net ``(4, 4, 2)``) on the grid
    ``t × t``, by the Bernstein form (independent of the B-spline evaluation)."""
    from math import comb

    b = np.array([[comb(3, i) * s ** i * (1 - s) ** (3 - i) for i in range(4)] for s in t])
    db = np.array([[3 * ((comb(2, i - 1) * s ** (i - 1) * (1 - s) ** (3 - i)) if i else 0)
                    - 3 * ((comb(2, i) * s ** i * (1 - s) ** (2 - i)) if i < 3 else 0)
                    for i in range(4)] for s in t])
    cu = np.einsum("ai,bj,ijc->abc", db, b, net)
    cv = np.einsum("ai,bj,ijc->abc", b, db, net)
    return cu[..., 0] * cv[..., 1] - cu[..., 1] * cv[..., 0]


@pytest.mark.parametrize("pleat", [0.0, 0.5, 1.0, 1.6, 2.5])
def test_the_fold_test_finds_a_jacobian_that_changes_sign(pleat):
    # one bicubic patch in the plane z = 0; its second column of control points pushed back
    # past the first by `pleat`: beyond some depth the map (u, v) -> C turns over
    net = np.stack(np.meshgrid(np.arange(4.0), np.arange(4.0), indexing="ij"), axis=-1)
    net[1, :, 0] -= pleat
    points = np.concatenate([net.reshape(16, 2), np.zeros((16, 1))], axis=1)
    table = np.arange(16).reshape(1, 4, 4)
    got = folded_patches(table, points, 3, 1)
    det = _bezier_jacobian(net, np.linspace(0.0, 1.0, 5))
    # the reference: some sample's Jacobian has the sign opposite to the patch's mean
    want = bool((det * det.sum() < -1e-9).any())
    assert got.tolist() == [want]
    assert want == (pleat > 1.0)  # the cases cover both answers


def test_fold_row_weights_stiffen_the_rows_of_a_folded_patch_only():
    m = trimesh.creation.icosphere(subdivisions=1)
    atlas = bilinear_atlas(quad_layout(m.vertices, m.faces), 3, 1)
    table = index_table(atlas)
    L = smoothing_matrix(atlas, table)
    stiff = np.zeros(len(table), bool)
    stiff[7] = True
    w = fold_row_weights(L, table, stiff, 9.0)
    own = set(table[7].reshape(-1).tolist())
    touches = np.array([bool(own & set(L[i].indices.tolist())) for i in range(L.shape[0])])
    np.testing.assert_array_equal(w, np.where(touches, 3.0, 1.0))


def _bumpy_sphere(amplitude: float = 0.2, k: int = 4):
    """A sphere with ``r = 1 + a sin(k θ) sin(k φ)``: the scan and its exact radius."""
    m = trimesh.creation.icosphere(subdivisions=5)

    def radius(p):
        p = p / np.linalg.norm(p, axis=1, keepdims=True)
        theta, phi = np.arctan2(p[:, 1], p[:, 0]), np.arccos(np.clip(p[:, 2], -1.0, 1.0))
        return 1.0 + amplitude * np.sin(k * theta) * np.sin(k * phi)

    return _mesh_scan(m.vertices * radius(m.vertices)[:, None], m.faces, "bumpy"), radius


def test_a_stiff_first_solve_fits_a_bumpy_sphere_closer_with_fewer_folds():
    scan, radius = _bumpy_sphere()
    surface = scan_surface(scan)
    vertices, triangles = decimate(surface, 24)
    triangles, _ = flip_edges(surface, vertices, triangles)
    layout = quad_layout(vertices, triangles)
    points, normals = working_points(scan, surface, 4000)
    result = {}
    for warm in (1.0, 100.0):
        atlas, *_ = fit_layout(layout, points, normals, rounds=4, warm_smoothing=warm,
                               scan_mesh=(surface.vertices, surface.faces))
        grid, _ = grid_mesh(atlas, 9)
        exact = np.sqrt(np.mean((np.linalg.norm(grid, axis=1) - radius(grid)) ** 2))
        folds = folded_patches(index_table(atlas), control_points(atlas), 3, 1).sum()
        result[warm] = exact, folds
    # the exact surface's radial error of the drawn base, not the fit's own measure
    assert result[100.0][0] < 0.9 * result[1.0][0]  # measured: 0.0143 against 0.0171
    assert result[100.0][1] <= result[1.0][1]


def test_warm_factor_steps_the_smoothing_down_geometrically_to_one():
    # s stages: solve i < s at warm ** ((s - i) / s), the rest and always the last round at 1
    assert [warm_factor(i, 4, 100.0, 1) for i in range(4)] == [100.0, 1.0, 1.0, 1.0]
    np.testing.assert_allclose([warm_factor(i, 4, 100.0, 2) for i in range(4)],
                               [100.0, 10.0, 1.0, 1.0])
    # more stages than rounds - 1: clamped, the last round stays at the normal smoothing
    np.testing.assert_allclose([warm_factor(i, 3, 1000.0, 5) for i in range(3)],
                               [1000.0, 1000.0 ** 0.5, 1.0])
    assert warm_factor(0, 1, 100.0, 2) == 1.0  # one round: no warm stage


def test_a_point_cloud_keeps_only_the_last_warm_stage(monkeypatch):
    # the default schedule 100, 10, 1, ... without its first stage: 10, 1, ...
    rounds = 6
    defaults = {"warm_smoothing": atlas_fit.WARM_SMOOTHING,
                "warm_stages": atlas_fit.WARM_STAGES}
    full = [warm_factor(i, rounds, **defaults) for i in range(rounds)]
    gentle = [warm_factor(i, rounds, **{**defaults, **cloud_warm()}) for i in range(rounds)]
    np.testing.assert_allclose(full, [100.0, 10.0, 1.0, 1.0, 1.0, 1.0])
    np.testing.assert_allclose(gentle, [10.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    monkeypatch.setattr(atlas_fit, "CLOUD_WARM_STAGES", 2)  # all stages kept: defaults
    assert cloud_warm() == {}
    monkeypatch.setattr(atlas_fit, "CLOUD_WARM_STAGES", 1)
    # fit_atlas hands it to every fit_layout of a cloud, and to none of a mesh
    calls = []
    real = atlas_fit.fit_layout

    def spy(*args, **kwargs):
        calls.append((kwargs.get("warm_stages"), kwargs.get("warm_smoothing")))
        return real(*args, **kwargs)

    monkeypatch.setattr(atlas_fit, "fit_layout", spy)
    mesh = _sphere_scan(3)
    fit_atlas(mesh, 60, working_count=2000, rounds=3)
    assert calls and all(call == (None, None) for call in calls)
    calls.clear()
    p = np.random.default_rng(3).normal(size=(6000, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    cloud = Scan.from_array(p, normals=p.astype(np.float32), name="cloud")
    surface = scan_surface(cloud, poisson_depth=6)
    assert surface.origin == "poisson"
    fit_atlas(cloud, 60, working_count=2000, rounds=3, surface=surface)
    assert calls and all(call == (1, pytest.approx(10.0)) for call in calls)


def test_split_longest_edges_stops_before_adding_more_than_max_added():
    surface = _valley_surface()
    vertices = np.array([[-1, -1, 1], [1, 1, 1], [1, -1, 1], [-1, 1, 1]], np.float64)
    triangles = np.array([[0, 2, 1], [0, 1, 3]])
    # the shared diagonal is both triangles' longest edge: its split adds two triangles
    assert split_longest_edges(surface, vertices, triangles, [0, 1], max_added=1)[2] == 0
    made_v, made_t, made = split_longest_edges(surface, vertices, triangles, [0], max_added=2)
    assert made == 1 and len(made_t) == 4


def _height_grid(n: int, height) -> tuple[np.ndarray, np.ndarray]:
    """``z = height(x, y)`` on an ``n × n`` grid over ``[-1.5, 1.5]²``, counter-clockwise
    from ``+z``."""
    t = np.linspace(-1.5, 1.5, n + 1)
    x, y = (a.ravel() for a in np.meshgrid(t, t, indexing="ij"))
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    p = (i * (n + 1) + j).ravel()
    faces = np.concatenate([np.stack([p, p + n + 1, p + n + 2], axis=1),
                            np.stack([p, p + n + 2, p + 1], axis=1)])
    return np.stack([x, y, height(x, y)], axis=1), faces


def _four_bumps_fit():
    """Four narrow bumps (heights 0.8, 0.72, 0.64, 0.56, width 0.17) on a plane, fitted on
    a 4 x 4 layout whose corners lie on the surface: the bicubic patches cannot rise into
    the bumps, 3.6 % of the diagonal off at the tallest."""
    from fitter.fitting.atlas.fit import fit_layout
    from fitter.fitting.atlas.surface import ScanSurface

    centres = [(0.2, 0.1), (-0.8, -0.7), (0.9, -0.8), (-0.7, 0.8)]

    def height(x, y):
        return sum(0.8 * (1 - 0.1 * k) * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / 0.03)
                   for k, (cx, cy) in enumerate(centres))

    surface = ScanSurface(*_height_grid(48, height), "mesh", 1, {})
    layout = quad_layout(*_height_grid(4, height))
    points, normals = surface.sample(4000, np.random.default_rng(3))
    options = dict(rounds=2, scan_mesh=(surface.vertices, surface.faces))
    atlas, *_ = fit_layout(layout, points, normals, **options)
    return surface, layout, atlas, points, normals, options


def test_a_far_base_over_the_budget_is_refined_where_farthest_within_it():
    from fitter.fitting.atlas.fit import (
        FAR_REACH,
        budget_bits,
        far_patch_samples,
        refine_far_base,
        refined_within_budget,
    )

    surface, layout, atlas, points, normals, options = _four_bumps_fit()
    far = far_patch_samples(atlas, options["scan_mesh"]).max()
    assert far > 1.5 * FAR_REACH
    size = budget_bits(atlas, 0.0, 8, None)[1]
    full = refine_far_base(atlas, layout, surface, points, normals, **options)
    full_size = budget_bits(full[0], 0.0, 8, None)[1]
    assert full[1].n_triangles >= layout.n_triangles + 4 and full_size > size
    # a budget with room for about 3/4 of the full refinement's triangles: the full refit is
    # over it, and the farthest triangles' splits that fit are fitted instead
    budget = size + 3 * (full_size - size) // 4
    rms, kept_size, kept_layout, kept_atlas, *_ , kept_bits = refined_within_budget(
        (atlas, layout, size), surface, points, normals, bits=8, byte_budget=budget,
        **options)
    assert kept_bits == 8 and kept_size <= budget
    assert layout.n_triangles < kept_layout.n_triangles < full[1].n_triangles
    assert far_patch_samples(kept_atlas, options["scan_mesh"]).max() < far
    # no budget, or room for all: the full refinement itself
    unlimited = refined_within_budget((atlas, layout, size), surface, points, normals,
                                      bits=8, byte_budget=None, **options)
    assert unlimited[2].n_triangles == full[1].n_triangles and unlimited[1] == full_size
    # no room for one more triangle: no refit
    assert refined_within_budget((atlas, layout, size), surface, points, normals, bits=8,
                                 byte_budget=size, **options) is None


def _plate_with_hole(n: int = 30, hole: float = 0.5):
    """The plane ``z = 0`` over ``[-1.5, 1.5]²`` on an ``n × n`` grid, without the cells
    inside the square ``|x|, |y| < hole`` (grid-aligned for ``n = 30``, ``hole = 0.5``)."""
    from fitter.fitting.atlas.surface import ScanSurface

    vertices, faces = _height_grid(n, lambda x, y: 0.0 * x)
    centre = vertices[faces].mean(axis=1)
    keep = (np.abs(centre[:, 0]) > hole) | (np.abs(centre[:, 1]) > hole)
    return ScanSurface(vertices, faces[keep], "mesh", 1, {})


def test_membrane_shares_are_the_area_spanning_the_hole_and_not_a_lifted_sheet():
    from fitter.fitting.atlas.fit import MEMBRANE_REACH, MEMBRANE_SHARE, membrane_shares
    from fitter.fitting.atlas.patches import with_control_points

    plate = _plate_with_hole()
    mesh = (plate.vertices, plate.faces)
    diagonal = float(np.linalg.norm(np.ptp(plate.vertices, axis=0)))
    square = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64)
    atlas = bilinear_atlas(quad_layout(square, np.array([[0, 1, 2], [0, 2, 3]])), 3, 1)
    # the reference: Monte Carlo over each triangle of the share farther than
    # MEMBRANE_REACH of the diagonal from the plate, in its plane (the hole shrunk by it)
    rng = np.random.default_rng(0)
    r1, r2 = rng.random((2, 200_000))
    fold = r1 + r2 > 1
    r1[fold], r2[fold] = 1 - r1[fold], 1 - r2[fold]
    reach = MEMBRANE_REACH * diagonal
    for t, tri in enumerate(([0, 1, 2], [0, 2, 3])):
        a, b, c = square[tri]
        p = a + r1[:, None] * (b - a) + r2[:, None] * (c - a)
        inside = np.all(np.abs(p[:, :2]) < 0.5 - reach, axis=1)
        np.testing.assert_allclose(membrane_shares(atlas, mesh)[t], inside.mean(), atol=0.03)
    assert membrane_shares(atlas, mesh).min() > MEMBRANE_SHARE
    # a narrower reach counts more of the hole: at half the reach, the hole shrunk by half
    assert np.all(membrane_shares(atlas, mesh, MEMBRANE_REACH / 2)
                  > membrane_shares(atlas, mesh) + 0.02)
    # the same sheet 0.2 above the plate without its hole: far everywhere, but with the
    # surface below it (along its normal), not beside it
    whole = _height_grid(30, lambda x, y: 0.0 * x)
    lifted = with_control_points(atlas, control_points(atlas) + [0.0, 0.0, 0.2])
    assert 0.2 > 2 * reach
    np.testing.assert_array_equal(membrane_shares(lifted, whole), 0.0)


def test_a_layout_spanning_a_hole_of_the_scan_is_opened_there():
    """A 6 x 6 layout over a plate with a square hole: the refit drops the triangles over
    the hole (the scan is open there, and a bicubic sheet over it is a wall no working
    point reaches), and keeps every other."""
    from fitter.fitting.atlas.fit import (
        FAR_REACH,
        MEMBRANE_SHARE,
        far_patch_samples,
        fit_layout,
        membrane_shares,
        refine_far_base,
    )

    plate = _plate_with_hole()
    layout = quad_layout(*_height_grid(6, lambda x, y: 0.0 * x))
    points, normals = plate.sample(4000, np.random.default_rng(3))
    normals = np.abs(normals)
    options = dict(rounds=2, scan_mesh=(plate.vertices, plate.faces))
    atlas, *_ = fit_layout(layout, points, normals, **options)
    shares = membrane_shares(atlas, options["scan_mesh"])
    centre = layout.triangle_vertices[layout.triangles].mean(axis=1)
    over_hole = np.all(np.abs(centre[:, :2]) < 0.5, axis=1)
    assert over_hole.sum() == 8
    assert np.all(shares[over_hole] > MEMBRANE_SHARE)
    assert np.all(shares[~over_hole] <= MEMBRANE_SHARE)
    far = far_patch_samples(atlas, options["scan_mesh"]).max()
    assert far > 2 * FAR_REACH
    refined = refine_far_base(atlas, layout, plate, points, normals, **options)
    assert refined is not None
    r_atlas, r_layout = refined[:2]
    r_centre = r_layout.triangle_vertices[r_layout.triangles].mean(axis=1)
    assert not np.any(np.all(np.abs(r_centre[:, :2]) < 0.5, axis=1))
    # every triangle away from the hole stays (none of them was far)
    assert r_layout.n_triangles == layout.n_triangles - 8
    assert far_patch_samples(r_atlas, options["scan_mesh"]).max() < far


def _points_by_the_sphere(n: int, patches: int, seed: int) -> tuple[np.ndarray, ...]:
    """``n`` points 2 % about the unit sphere, each with a random patch and ``(u, v)`` in
    ``patches``: foot points to correct (``x, f, u, v``)."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    x *= 1.0 + 0.02 * rng.normal(size=(n, 1))
    return x, rng.integers(0, patches, n), rng.random(n), rng.random(n)


def test_foot_point_corrections_on_threads_equal_one_run(sphere_fit, monkeypatch):
    """correct_parameters split over threads gives exactly the numbers of one run."""
    atlas = sphere_fit.atlas
    table = index_table(atlas)
    n = 30_000
    x, f, u, v = _points_by_the_sphere(n, len(atlas.quads), 5)
    args = (table, control_points(atlas), 3, 1, neighbour_table(atlas), x, x, f, u, v)
    monkeypatch.setattr(atlas_patches, "CORRECT_RUN_POINTS", n + 1)  # one run
    one = atlas_patches.correct_parameters(*args)
    monkeypatch.setattr(atlas_patches, "CORRECT_RUN_POINTS", 1_000)
    monkeypatch.setattr(atlas_patches, "CORRECT_THREADS", 3)  # uneven runs
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(4)), raising=False)
    split = atlas_patches.correct_parameters(*args)
    assert np.any(one[0] != f)  # some points hopped to another patch
    for a, b in zip(one, split, strict=True):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("degree", [1, 2, 3, 5])
def test_one_span_basis_is_scipys_bspline(degree):
    """The Bernstein tables of one span equal scipy's ``BSpline`` of the clamped knots
    ``0^{d+1} 1^{d+1}`` (values and every derivative, parameters clamped to [0, 1])."""
    from scipy.interpolate import BSpline

    t = np.r_[np.random.default_rng(degree).random(500), 0.0, 1.0, -0.3, 1.2]
    knots = np.r_[np.zeros(degree + 1), np.ones(degree + 1)]
    for derivative in range(degree + 2):
        reference = BSpline(knots, np.eye(degree + 1), degree, extrapolate=False)(
            np.clip(t, 0.0, 1.0), nu=derivative)
        got = atlas_patches.basis_matrix(t, degree, 1, derivative)
        assert got.shape == (len(t), degree + 1)
        np.testing.assert_allclose(got, reference, rtol=0, atol=1e-12 * 10.0 ** derivative)


def test_converged_foot_points_stop_stepping_and_land_where_every_step_would(sphere_fit,
                                                                             monkeypatch):
    """Points whose step fell under CONVERGED_STEP take no more steps: their foot points and
    distances are those of all the iterations taken by every point."""
    atlas = sphere_fit.atlas
    n = 5_000
    x, f, u, v = _points_by_the_sphere(n, len(atlas.quads), 8)
    fixed = (index_table(atlas), control_points(atlas), 3, 1, neighbour_table(atlas), x, x)
    # from the foot points of a few steps, as each round of a fit starts from the last's
    f, u, v, _ = atlas_patches._correct_run(*fixed, f, u, v, 6)
    args = (*fixed, f, u, v, 12)
    calls = []
    evaluate = atlas_patches.evaluate_patches
    monkeypatch.setattr(atlas_patches, "evaluate_patches",
                        lambda *a, **k: calls.append(len(a[4])) or evaluate(*a, **k))
    monkeypatch.setattr(atlas_patches, "CONVERGED_STEP", -1.0)  # every point, every step
    every = atlas_patches._correct_run(*args)
    assert calls[1:-1] == [n] * 12
    calls.clear()
    monkeypatch.setattr(atlas_patches, "CONVERGED_STEP", 1e-7)
    stopped = atlas_patches._correct_run(*args)
    assert sum(calls[1:-1]) < 0.6 * 12 * n  # fewer points stepped
    np.testing.assert_array_equal(stopped[0], every[0])
    np.testing.assert_allclose(stopped[1:3], every[1:3], rtol=0, atol=1e-6)
    np.testing.assert_allclose(stopped[3], every[3], rtol=0, atol=1e-9)


# ------------------------------------------------------------------ narrow layout triangles
def _altitudes(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Smallest distance of a corner to the line through the other two, per triangle
    (by projection, not by area: an independent check of ``triangle_widths``)."""
    out = np.full(len(triangles), np.inf)
    for k in range(3):
        p, a, b = (vertices[triangles[:, (k + i) % 3]] for i in range(3))
        d = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True)
        off = (p - a) - np.einsum("ij,ij->i", p - a, d)[:, None] * d
        out = np.minimum(out, np.linalg.norm(off, axis=1))
    return out


def _topology(vertices: np.ndarray, triangles: np.ndarray) -> tuple[int, int, int, int]:
    """``(V - E + F, border loops, edges in > 2 triangles, directed edges used twice)``,
    counted here: the loops by walking the border edges from vertex to vertex."""
    directed = [(int(t[k]), int(t[(k + 1) % 3])) for t in triangles for k in range(3)]
    undirected: dict[tuple[int, int], int] = {}
    for a, b in directed:
        undirected[min(a, b), max(a, b)] = undirected.get((min(a, b), max(a, b)), 0) + 1
    border = {(a, b) for a, b in directed if undirected[min(a, b), max(a, b)] == 1}
    following = {a: b for a, b in border}
    loops, seen = 0, set()
    for start in following:
        if start in seen:
            continue
        loops += 1
        a = start
        while a not in seen:
            seen.add(a)
            a = following[a]
    chi = len(np.unique(triangles)) - len(undirected) + len(triangles)
    return (chi, loops, sum(c > 2 for c in undirected.values()),
            len(directed) - len(set(directed)))


def _planted_torus():
    """A torus (144 triangles) with a hole (one quad removed) and, planted, a needle (an
    inner edge split 1 % from its end), a tiny triangle (a corner's 1-to-3 split 1 % of the
    way to the centroid) and a border sliver (a border edge split 1 % from its end)."""
    torus = trimesh.creation.torus(major_radius=1.0, minor_radius=0.4, major_sections=12,
                                   minor_sections=6)
    v, f = np.asarray(torus.vertices, np.float64), np.asarray(torus.faces, np.int64)
    f = f[2:]  # the hole: the first quad's two triangles
    problems = manifold_problems(f)
    assert problems["border_edges"] == 4
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    key = {tuple(e) for e in directed.tolist()}
    border = [e for e in directed.tolist() if (e[1], e[0]) not in key]
    a, b = f[40, 0], f[40, 1]  # an inner edge far from the hole
    v, f = split_edges(v, f, [[a, b]], [v[a] + 0.01 * (v[b] - v[a])])
    a, b = border[0]
    v, f = split_edges(v, f, [[a, b]], [v[a] + 0.01 * (v[b] - v[a])])
    t = 100
    x, y, z = f[t]
    n = len(v)
    v = np.vstack([v, v[x] + 0.01 * (v[f[t]].mean(axis=0) - v[x])])
    f = np.vstack([f, [[y, z, n], [z, x, n]]])
    f[t] = (x, y, n)
    return v, f


def test_narrow_layout_triangles_are_collapsed_and_the_topology_kept():
    """A planted needle, tiny triangle and border sliver leave the layout (no triangle
    narrower than ``MIN_WIDTH_SHARE`` of the median edge); the Euler characteristic, the
    border loops and the manifold are as before, counted independently."""
    from fitter.fitting.atlas.fit import layout_candidates
    from fitter.fitting.atlas.layout import MIN_WIDTH_SHARE, collapse_narrow_triangles

    v, f = _planted_torus()
    median = np.median([np.linalg.norm(v[a] - v[b]) for a, b in
                        {(min(a, b), max(a, b)) for t in f.tolist()
                         for a, b in zip(t, t[1:] + t[:1], strict=True)}])
    assert np.sum(_altitudes(v, f) < MIN_WIDTH_SHARE * median) >= 4
    before = _topology(v, f)
    assert before == (-1, 1, 0, 0)
    surface = scan_surface(_mesh_scan(v, f, "planted torus"))
    assert len(surface.faces) == len(f)  # nothing merged or repaired on the way
    (name, layout, _), = layout_candidates(surface, 2 * len(f), False)[0]
    vertices, triangles = layout.triangle_vertices, layout.triangles
    assert _topology(vertices, triangles) == before
    assert len(f) - 12 <= len(triangles) < len(f)  # a few collapses, 1 or 2 triangles each
    edges = layout.triangle_edges
    after_median = np.median(np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]],
                                            axis=1))
    assert _altitudes(vertices, triangles).min() >= MIN_WIDTH_SHARE * after_median
    with pytest.raises(ValueError, match="share"):
        collapse_narrow_triangles(surface, v, f, 1.0)
    # the layout's vertices are the input's (a collapse moves none)
    assert {tuple(p) for p in vertices.tolist()} <= {tuple(p) for p in v.tolist()}


def test_a_fitted_base_at_the_first_levels_resolution_welds_to_a_manifold():
    """The planted torus fitted with a patch per quad of its own triangles: its layout has
    no narrow triangle, and its fitted base written at 8 bits, read back and drawn at level
    0's resolution (17 samples a side), welded at 1e-6 of the diagonal as the benchmark
    welds, has no collapsed triangle and no edge in more than two triangles; its one open
    border is the hole's and its Euler characteristic the torus's."""
    from client_py.atlas_format import read_atlas
    from client_py.atlas_mesh import tessellate_atlas
    from client_py.bundle import atlas_level_resolution
    from fitter.fitting.atlas.detail import SPANS
    from fitter.fitting.atlas.layout import MIN_WIDTH_SHARE

    v, f = _planted_torus()
    fit = fit_atlas(_mesh_scan(v, f, "planted torus"), 3 * len(f), working_count=1000,
                    rounds=2, bits=8)
    layout = fit.layout
    edges = layout.triangle_edges
    fitted_median = np.median(np.linalg.norm(layout.triangle_vertices[edges[:, 0]]
                                             - layout.triangle_vertices[edges[:, 1]], axis=1))
    assert _altitudes(layout.triangle_vertices, layout.triangles).min() \
        >= MIN_WIDTH_SHARE * fitted_median
    assert _topology(layout.triangle_vertices, layout.triangles) == _topology(v, f) \
        == (-1, 1, 0, 0)
    decoded, _ = read_atlas(base_file(fit.atlas, 8))
    mesh = tessellate_atlas(decoded, atlas_level_resolution(SPANS, 0), kernel="numpy",
                            normals=False)
    points = np.asarray(mesh.positions, np.float64).reshape(-1, 3)
    faces = np.asarray(mesh.indices, np.int64).reshape(-1, 3)
    step = 1e-6 * np.linalg.norm(np.ptp(points, axis=0))
    _, welded = np.unique(np.round(points / step).astype(np.int64), axis=0,
                          return_inverse=True)
    corners = welded.reshape(-1)[faces]
    assert np.all((corners[:, 0] != corners[:, 1]) & (corners[:, 1] != corners[:, 2])
                  & (corners[:, 2] != corners[:, 0]))
    chi, loops, nonmanifold, _ = _topology(np.unique(corners), corners)
    assert nonmanifold == 0 and loops == 1 and chi == -1


@pytest.mark.parametrize("spans", [1, 2, 4])
def test_point_nets_equal_each_points_own_gather(spans):
    """point_nets (every patch's net once, then a row per point) gives exactly the plain
    gather P[I[f_k]] of each point's n^2 control points, with many points and with few, so
    evaluate_patches gives the same numbers either way."""
    atlas = random_cube_atlas(degree=3, spans=spans, seed=spans)
    table, points = index_table(atlas), control_points(atlas)
    rng = np.random.default_rng(spans)
    n2 = table.shape[1] * table.shape[2]
    for k in (1, 2, 5_000):  # 4 k < F = 6 patches: each point's own gather; else whole nets
        f = rng.integers(0, len(table), k)
        plain = np.stack([[points[i] for i in table[g].reshape(-1)] for g in f])
        nets = atlas_patches.point_nets(table, points, f)
        assert nets.shape == (k, n2, 3)
        np.testing.assert_array_equal(nets, plain)
    u, v = rng.random(len(f)), rng.random(len(f))
    bu, bv = atlas_patches.basis_matrix(u, 3, spans), atlas_patches.basis_matrix(v, 3, spans)
    plain = np.matmul((bu[:, :, None] * bv[:, None, :]).reshape(len(f), 1, n2), plain)[:, 0]
    (c,) = atlas_patches.evaluate_patches(table, points, 3, spans, f, u, v)
    np.testing.assert_array_equal(c, plain)


def test_layout_candidates_and_their_fits_on_threads_equal_one_after_the_other(monkeypatch):
    """The plain and weighted layouts made, and fitted, on two threads are exactly those
    made and fitted one after the other (MeshLab's collapses taking turns)."""
    scan = _bumpy_ball_and_small_disc()
    fits = {}
    for threads in (1, 2):
        monkeypatch.setattr(atlas_fit, "LAYOUT_THREADS", threads)
        surface = scan_surface(scan)
        candidates, failures = atlas_fit.layout_candidates(surface, 120, True)
        assert [c[0] for c in candidates] == ["plain", "weighted"] and not failures
        fit = fit_atlas(scan, 360, working_count=2000, rounds=1)
        fits[threads] = candidates, fit
    (one, fit_one), (two, fit_two) = fits[1], fits[2]
    for a, b in zip(one, two, strict=True):
        for name in ("triangle_vertices", "triangles", "vertices", "quads"):
            np.testing.assert_array_equal(getattr(a[1], name), getattr(b[1], name))
    assert fit_one.trials[0]["rms_by_layout"] == fit_two.trials[0]["rms_by_layout"]
    np.testing.assert_array_equal(control_points(fit_one.atlas), control_points(fit_two.atlas))


def test_the_ladder_starts_at_the_largest_size_within_half_the_budget():
    plan = [48, 96, 192, 384, 768, 1536, 3072]
    # 2 x 60 bytes per triangle: 96 -> 11,520 and 192 -> 23,040 bytes
    assert atlas_fit.AUTO_START_BYTES_PER_TRIANGLE == 60
    assert [atlas_fit.ladder_start(plan, budget) for budget in (6000, 11_519, 11_520, 24_000)
            ] == [0, 0, 1, 2]
    assert atlas_fit.ladder_start([30], 24_000) == 0


def test_a_doubling_predicted_over_the_budget_is_not_fitted_and_the_choice_is_the_full_ladders(
        monkeypatch, fit_layout_calls):
    """A sphere with a 12,000-byte budget: the ladder starts at 96 triangles, and 384 is
    predicted over 1.15 budgets (predicted_trial_bytes) and not fitted. The full ladder
    (from 48, every doubling fitted) finds that trial over the budget and chooses the same
    layout, fitted to the same control points."""
    scan = _sphere_scan(3)
    options = {"bits": None, "byte_budget": 12_000, "working_count": 2000, "rounds": 1}
    calls = fit_layout_calls
    fit = fit_atlas(scan, "auto", **options)
    (skipped,) = [t for t in fit.trials if "skipped" in t]
    assert skipped["predicted_bytes"] > atlas_fit.AUTO_SKIP_OVER_BUDGET * 12_000
    assert max(calls) < 0.8 * skipped["triangles"]  # nothing near its size was fitted
    assert fit.trials[0]["triangles"] > atlas_fit.AUTO_FIRST_TRIANGLES  # started higher

    monkeypatch.setattr(atlas_fit, "ladder_start", lambda plan, budget: 0)
    monkeypatch.setattr(atlas_fit, "AUTO_SKIP_OVER_BUDGET", float("inf"))
    full = fit_atlas(scan, "auto", **options)
    assert full.trials[0]["triangles"] == atlas_fit.AUTO_FIRST_TRIANGLES
    over = [t for t in full.trials if t["triangles"] > fit.triangles]
    assert over and over[0]["bytes"] > 12_000  # the prediction was right
    assert full.triangles == fit.triangles
    np.testing.assert_array_equal(control_points(full.atlas), control_points(fit.atlas))


def test_a_ladder_start_over_the_budget_climbs_the_full_ladder(monkeypatch, fit_layout_calls):
    """When the start's trial is over the budget, the smaller layouts are tried from
    ``AUTO_FIRST_TRIANGLES``: the choice is the full ladder's, and the start's trial, from
    the cache, is not fitted twice."""
    scan = _sphere_scan(3)
    options = {"bits": None, "byte_budget": 9000, "working_count": 2000, "rounds": 1}
    full = fit_atlas(scan, "auto", **options)
    assert full.trials[0]["triangles"] == atlas_fit.AUTO_FIRST_TRIANGLES  # 9000: from 48
    monkeypatch.setattr(atlas_fit, "AUTO_START_BYTES_PER_TRIANGLE", 1)  # start at the top
    start = len(fit_layout_calls)
    fit = fit_atlas(scan, "auto", **options)
    calls = fit_layout_calls[start:]
    assert calls[0] == max(calls) > 2 * fit.triangles  # the top was tried first, once
    assert calls.count(calls[0]) == 1
    assert [t["triangles"] for t in fit.trials] == [t["triangles"] for t in full.trials]
    assert fit.triangles == full.triangles
    np.testing.assert_array_equal(control_points(full.atlas), control_points(fit.atlas))


def test_auto_falls_back_to_the_smaller_layout_when_the_final_base_is_over_the_budget(
        monkeypatch):
    """The final fit (every working point, every round) has a lower RMS than its trial and
    asks for more bits; with no bits to give back (``BUDGET_FEWER_BITS`` 0) its file is over
    the budget its trial passed at (a subdivided box: the 96-triangle trial 5,413 bytes at 11
    bits, its final fit 5,982 at 12), and the layout taken before it is fitted instead."""
    monkeypatch.setattr(atlas_fit, "BUDGET_FEWER_BITS", 0)
    box = trimesh.creation.box(extents=(40, 30, 20)).subdivide_to_size(1.5)
    scan = _mesh_scan(box.vertices, box.faces, "box")
    cache: dict = {}
    roomy = fit_atlas(scan, "auto", bits=None, byte_budget=8000, trial_cache=cache)
    passed = [t for t in roomy.trials if t.get("bytes", 8001) <= 8000]
    assert len(passed) >= 2 and roomy.triangles == passed[-1]["triangles"]
    budget = passed[-1]["bytes"]  # the largest trial just fits
    fit = fit_atlas(scan, "auto", bits=None, byte_budget=budget, trial_cache=cache)
    assert fit.bytes <= budget
    refused = [t for t in fit.trials if "final_bytes" in t]
    assert [t["triangles"] for t in refused] == [passed[-1]["triangles"]]
    assert refused[0]["final_bytes"] > budget and refused[0]["final_bits"] > refused[0]["bits"]
    assert fit.triangles == passed[-2]["triangles"]
    assert fit.bytes == atlas_fit.atlas_bytes(fit.atlas, fit.bits)
