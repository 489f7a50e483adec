"""fitter.fitting.detail: the level fit against a dense solve, errors falling level by level, the
written tiles (read back by client_py) reproducing the reported errors, and the CLI --level."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from scipy.interpolate import BSpline

from client_py import read_detail_tile
from client_py.layers import displacement_grid, level_knots
from fitter.cli import main
from fitter.fitting import detail


def field_samples(n: int = 6000, noise: float = 0.0, seed: int = 0) -> detail.DetailSamples:
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(0, 1, n), rng.uniform(0, 1, n)
    s = (0.5 * np.sin(9 * u) * np.cos(7 * v) + 0.2 * np.exp(-((u - 0.3) ** 2 + (v - 0.6) ** 2)
         / 0.002) + rng.normal(0, noise, n))
    return detail.DetailSamples(u, v, s, np.zeros(n))


def test_fit_level_matches_a_dense_least_squares_solve():
    smp = field_samples(1500)
    level, degree, spans = 1, 2, 3
    got = detail.fit_level(smp, smp.s, level, degree, spans)
    t = np.array(level_knots(degree, spans, level))
    Bu = BSpline.design_matrix(smp.u, t, degree).toarray()
    Bv = BSpline.design_matrix(smp.v, t, degree).toarray()
    A = np.einsum("ma,mb->mab", Bu, Bv).reshape(len(smp.u), -1)
    n = Bu.shape[1]
    mu = np.einsum("ma,ma->", A, A) / (n * n)
    D2 = np.diff(np.eye(n), 2, axis=0)
    Lu, Lv = np.kron(D2, np.eye(n)), np.kron(np.eye(n), D2)
    stacked = np.vstack([A, np.sqrt(mu * detail.RIDGE) * np.eye(n * n),
                         np.sqrt(mu * detail.SMOOTHING) * Lu, np.sqrt(mu * detail.SMOOTHING) * Lv])
    rhs = np.concatenate([smp.s, np.zeros(n * n + 2 * Lu.shape[0])])
    expected = np.linalg.lstsq(stacked, rhs, rcond=None)[0].reshape(n, n)
    np.testing.assert_allclose(got, expected, atol=1e-8 * np.abs(expected).max())


def test_rms_falls_level_by_level_and_tiles_reproduce_the_reported_errors():
    smp = field_samples(5000, noise=0.002)
    pyramid = detail.fit_pyramid(smp, 3, spans=4)
    rms = [pyramid.base_rms] + [lev.rms for lev in pyramid.levels]
    assert all(b < a for a, b in zip(rms, rms[1:], strict=False)), rms
    assert rms[-1] < 0.05 * rms[0]
    # the tiles as bytes, read back and evaluated by client_py, give the reported errors
    for lev in pyramid.levels:
        e = np.abs(_residual_after(pyramid, lev.level, smp))  # t = 0 here
        assert float(np.sqrt(np.mean(e**2))) == pytest.approx(lev.rms, rel=1e-9)
        assert float(e.max()) == pytest.approx(lev.max, rel=1e-9)
        for tile, _, worst in lev.tiles:
            u0, v0, u1, v1 = tile.uv_rect
            inside = ((smp.u >= u0) & ((smp.u < u1) | (u1 == 1.0))
                      & (smp.v >= v0) & ((smp.v < v1) | (v1 == 1.0)))
            assert worst == pytest.approx(e[inside].max(), rel=1e-9)


def _one_per_level(tiles, u, v):
    chosen = {}
    for t in tiles:
        if t.contains(u, v) and t.level not in chosen:
            chosen[t.level] = t
    return chosen.values()


def _residual_after(pyramid, level, smp):
    tiles = [read_detail_tile(d) for lev in pyramid.levels[: level + 1] for _, d, _ in lev.tiles]
    D = np.array([sum(t.evaluate(a, b) for t in _one_per_level(tiles, a, b))
                  for a, b in zip(smp.u, smp.v, strict=True)])
    return smp.s - D


def test_nothing_to_explain_writes_no_tiles():
    smp = field_samples(3000)
    smp.s[:] = 0.0
    pyramid = detail.fit_pyramid(smp, 3, spans=4)
    assert all(not lev.tiles for lev in pyramid.levels)


def test_periodic_field_closes_at_the_seam():
    smp = field_samples(8000)
    smp.s += 0.3 * np.cos(2 * np.pi * smp.u)
    pyramid = detail.fit_pyramid(smp, 2, spans=4, periodic_u=True)
    tiles = [read_detail_tile(d) for lev in pyramid.levels for _, d, _ in lev.tiles]
    vs = list(np.linspace(0, 1, 23))
    left = np.array(displacement_grid(tiles, [0.0], vs))
    right = np.array(displacement_grid(tiles, [1.0], vs))
    np.testing.assert_allclose(left, right, atol=1e-12)
    assert np.abs(left).max() > 0.1


@pytest.fixture(scope="module")
def relief_bundle(tmp_path_factory):
    from fitter.fitting.examples import relief_scan
    from fitter.fitting.options import FitOptions
    from fitter.fitting.pipeline import fit_scan

    out = tmp_path_factory.mktemp("detail") / "relief"
    return fit_scan(relief_scan(12_000), out, FitOptions(grid=(12, 12), detail_levels=3))


def test_bundle_tiles_and_manifest(relief_bundle):
    m = relief_bundle.manifest
    tree = m["tiles"]["detail"]
    rms = [tree["base"]["rms"]] + [lev["rms"] for lev in tree["levels"]]
    assert all(b < a for a, b in zip(rms, rms[1:], strict=False)), rms
    assert tree["base"]["rms"] == pytest.approx(m["stats"]["rms"], rel=0.05)
    for node in tree["nodes"]:
        data = (relief_bundle.path / node["file"]).read_bytes()
        assert m["files"][node["file"]] == node["bytes"] == len(data)
        tile = read_detail_tile(data)
        assert (tile.level, tile.i, tile.j) == (node["level"], node["i"], node["j"])
        assert list(tile.uv_rect) == node["uv"]
        assert node["geometric_error"] <= m["stats"]["max"] * 1.5


def test_cli_level_applies_the_tiles(relief_bundle, tmp_path, capsys):
    import trimesh

    from client_py import read_patch, tessellate_grid

    base, fine = tmp_path / "base.ply", tmp_path / "fine.ply"
    assert main(["tessellate", str(relief_bundle.path), "--level", "-1", "--resolution", "33",
                 "-o", str(base)]) == 0
    assert main(["tessellate", str(relief_bundle.path), "--resolution", "33",
                 "-o", str(fine)]) == 0
    a = trimesh.load(base, process=False)
    b = trimesh.load(fine, process=False)
    surface = read_patch((relief_bundle.path / "base.tsp").read_bytes()).to_scan_frame()
    plain = np.array(tessellate_grid(surface, 33, 33).positions).reshape(-1, 3)
    np.testing.assert_allclose(a.vertices, plain, atol=1e-3)
    moved = np.linalg.norm(b.vertices - a.vertices, axis=1)
    assert moved.max() > 0.05 and len(b.vertices) == 33 * 33
    assert "level 2" in capsys.readouterr().out
    assert main(["tessellate", str(relief_bundle.path), "--level", "7", "-o",
                 str(fine)]) == 2
    assert "level must be an integer in -1..2" in capsys.readouterr().err
    manifest = json.loads((relief_bundle.path / "manifest.json").read_text())
    assert manifest["options"]["detail_levels"] == 3


@pytest.mark.realdata
def test_real_scan_rms_falls_with_levels(shared_data, tmp_path):
    from fitter.fitting.io import load_scan
    from fitter.fitting.options import FitOptions
    from fitter.fitting.pipeline import fit_scan

    scan = load_scan(shared_data / "happy-buddha-rangescans" / "happyStandRight_0.ply.gz")
    # one patch, as the grid says: on the smooth base, the default, this mesh is an atlas of
    # 18,408 patches, whose three levels took 365 s of the suite (session 31)
    m = fit_scan(scan, tmp_path / "b", FitOptions(grid=(16, 16), patches=1, detail_levels=3,
                                                  texture=False)).manifest
    tree = m["tiles"]["detail"]
    rms = [tree["base"]["rms"]] + [lev["rms"] for lev in tree["levels"]]
    assert all(b < a for a, b in zip(rms, rms[1:], strict=False)), rms
    assert rms[-1] < 0.5 * rms[0]


@pytest.mark.realdata
def test_drawn_masks_bring_back_scan_points_the_base_trim_cut_away(shared_data, tmp_path):
    """Bali mask: the base's trim leaves out cells where it strays (the rim, the eye holes);
    with the tiles' drawn masks the covered points lie much nearer the drawn surface
    (distance to the nearest vertex of a fine tessellation, with and without the masks)."""
    from scipy.spatial import cKDTree

    from client_py import read_patch
    from client_py.bundle import detail_nodes
    from client_py.layers import tessellate_region
    from fitter.fitting.io import load_scan
    from fitter.fitting.options import FitOptions
    from fitter.fitting.parameterize import choose_projection
    from fitter.fitting.pipeline import fit_scan

    scan = load_scan(shared_data / "bali-mask" / "mask.obj")
    root = tmp_path / "b"
    m = fit_scan(scan, root, FitOptions(grid=(32, 32), patches=1, detail_levels=4,
                                        texture=False)).manifest
    surface = read_patch((root / "base.tsp").read_bytes())
    tiles = [read_detail_tile((root / n["file"]).read_bytes()) for n in detail_nodes(m)]
    assert surface.trim is not None and any(t.drawn is not None for t in tiles)
    covered = scan.points[choose_projection(scan.points, None, "auto").covered]
    matrix = np.asarray(surface.metadata["transform"])
    local = (covered - matrix[:3, 3]) @ matrix[:3, :3]  # a rotation: back to the patch frame
    errors = []
    for masks in (True, False):
        given = tiles if masks else [dataclasses.replace(t, drawn=None) for t in tiles]
        mesh = tessellate_region(surface, (0, 0, 1, 1), 513, 513, given, kernel="numpy")
        used = np.unique(np.frombuffer(mesh.indices, np.uint32))
        vertices = np.frombuffer(mesh.positions, np.float32).reshape(-1, 3)[used]
        errors.append(float(np.sqrt(np.mean(cKDTree(vertices).query(local)[0] ** 2))))
    assert errors[0] < 0.85 * errors[1], errors  # 0.87e-3 against 1.08e-3 m


def test_detail_spans_option(tmp_path):
    from fitter.fitting.examples import relief_scan
    from fitter.fitting.options import FitOptions
    from fitter.fitting.pipeline import fit_scan

    for bad in (3, 65, True, 16.0):
        with pytest.raises(ValueError, match="detail_spans must be an integer in 4..64"):
            fit_scan(relief_scan(3000), tmp_path / "x", FitOptions(detail_spans=bad))
    m = fit_scan(relief_scan(6000), tmp_path / "b", FitOptions(grid=(10, 10), detail_levels=2,
                                                               detail_spans=8)).manifest
    assert m["tiles"]["detail"]["spans_per_tile"] == 8
    tile = read_detail_tile((tmp_path / "b" / m["tiles"]["detail"]["nodes"][-1]["file"])
                            .read_bytes())
    assert tile.spans == 8 and tile.size == 10


# ------------------------------------------------------------------ redrawn cells
def plane_sample(seed: int, count: int = 20_000) -> np.ndarray:
    """``count`` points drawn uniformly from the plane ``z = 0`` over the unit square
    (:func:`plane_model`'s surface: their foot points are their ``x, y``)."""
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(0, 1, count), rng.uniform(0, 1, count)
    return np.column_stack([u, v, 0 * u])


def plane_model():
    """The plane ``z = 0`` over the unit square as a degree-2 patch."""
    from client_py import NurbsSurface
    from client_py.basis import uniform_clamped_knots
    from fitter.fitting.nurbs import PatchModel

    greville = [0.0, 0.25, 0.75, 1.0]  # control points there: S(u, v) = (u, v, 0)
    a, b = np.meshgrid(greville, greville, indexing="ij")
    knots = uniform_clamped_knots(4, 2)
    return PatchModel.from_surface(NurbsSurface((2, 2), (knots, knots),
                                                np.stack([a, b, 0 * a], axis=-1)))


def test_stray_flags_cells_far_from_every_scan_point():
    from fitter.fitting.compact import ScanNeighbourhood

    g = np.linspace(0, 1, 81)
    P = np.array([(x, y, 0.0) for x in g for y in g if x <= 0.5])  # scan: the half u <= 0.5
    near = ScanNeighbourhood(P)
    assert near.spacing == pytest.approx(1 / 80)
    r, c = np.nonzero(np.ones((10, 10), bool))
    plane = lambda u, v: np.column_stack([u, v, 0 * u])  # noqa: E731
    far = near.stray(plane, r, c, (10, 10), fit_rms=0.0)
    # a cell strays when a corner lies beyond 2 spacings (0.025) of the scan: u > 0.525
    np.testing.assert_array_equal(far, r + 1 > 5.25)
    lifted = near.stray(lambda u, v: plane(u, v) + [0, 0, 0.03], r, c, (10, 10), 0.0)
    assert lifted.all()  # 0.03 above the scan: every cell strays
    assert not near.stray(lambda u, v: plane(u, v) + [0, 0, 0.03], r[r < 5], c[r < 5],
                          (10, 10), fit_rms=0.01).any()  # within 8 RMS + 2 spacings


def test_tiles_redraw_left_out_cells_where_the_scan_is():
    """A trim leaving out a block of a plane: the level-0 tile's drawn mask brings back the
    part of the block with scan points on the plane, not the part without points."""
    model = plane_model()
    drawn = np.ones((16, 16), bool)
    drawn[4:10, 4:10] = False  # the base's trim leaves out rows 4..9, cols 4..9
    g = (np.arange(160) + 0.5) / 160
    U, V = (x.ravel() for x in np.meshgrid(g, g, indexing="ij"))
    keep = ~((U >= 4 / 16) & (U < 10 / 16) & (V >= 7 / 16) & (V < 10 / 16))  # hole: cols 7..9
    U, V = U[keep], V[keep]
    points = np.column_stack([U, V, 0 * U])
    redraw = detail.Redraw.from_foot_points(model, drawn, points, U, V, False)
    smp = detail.DetailSamples(U, V, np.zeros(len(U)), np.zeros(len(U)))
    pyramid = detail.fit_pyramid(smp, 1, redraw=redraw)
    (tile, data, _), = pyramid.levels[0].tiles  # nothing to explain: kept for its mask
    assert not any(tile.values)
    got = np.frombuffer(read_detail_tile(data).drawn.flat, np.uint8).reshape(32, 32)
    expected = np.zeros((16, 16), np.uint8)
    expected[4:10, 4:7] = 1  # left out, with scan points (the hole's cells have none)
    np.testing.assert_array_equal(got, np.kron(expected, np.ones((2, 2), np.uint8)))


def test_no_mask_while_the_level_is_coarser_than_the_trim():
    model = plane_model()
    drawn = np.ones((64, 64), bool)
    drawn[10:20, 10:20] = False
    g = (np.arange(200) + 0.5) / 200
    U, V = (x.ravel() for x in np.meshgrid(g, g, indexing="ij"))
    redraw = detail.Redraw.from_foot_points(model, drawn, np.column_stack([U, V, 0 * U]),
                                            U, V, False)
    smp = detail.DetailSamples(U, V, 0.01 * np.sin(20 * U), np.zeros(len(U)))
    pyramid = detail.fit_pyramid(smp, 2, spans=4, redraw=redraw)
    # DRAWN_SIDE (32) cells per tile: level 0 is coarser than the trim, level 1 matches it
    assert all(t.drawn is None for t, _, _ in pyramid.levels[0].tiles)
    masks = [t.drawn for t, _, _ in pyramid.levels[1].tiles if t.drawn is not None]
    assert len(masks) == 1 and sum(masks[0].flat) == 10 * 10  # the block, in tile (0, 0)


@pytest.mark.parametrize("periodic_u", [False, True])
def test_normal_matrix_is_the_sparse_product(periodic_u):
    """``normal_matrix`` (diagonals summed by bincount) against scipy's ``A.T @ A``."""
    from fitter.fitting.detail import collocation_matrix, normal_matrix

    rng = np.random.default_rng(4)
    u, v = rng.random(20_000), rng.random(20_000)
    u[:3] = [0.0, 1.0, 0.999999]
    n = 16 + 2
    knots = np.array(level_knots(2, 16, 0))
    A = collocation_matrix(2, knots, n, u, v, periodic_u)
    expected = (A.T @ A).toarray()
    np.testing.assert_allclose(normal_matrix(A).toarray(), expected, rtol=1e-12,
                               atol=1e-12 * np.abs(expected).max())


# ------------------------------------------------------------------ walls at depth jumps
JUMP = 0.15  # depth of the step below: 23.9 sample spacings, 10.6 % of the diagonal


def step_range_image(n: int = 160) -> tuple[np.ndarray, np.ndarray]:
    """A range image of ``n x n`` pixels over the unit square seen from ``+z``: the plane
    ``z = 0`` where ``x + 0.3 y < 0.55`` and the plane ``z = -JUMP`` beyond that slanted
    occluding contour; its points and its triangles (``range_grid.triangulate``, which
    leaves the step open)."""
    from fitter.fitting.io.range_grid import triangulate

    g = np.arange(n) / (n - 1)
    x, y = (a.ravel() for a in np.meshgrid(g, g, indexing="ij"))
    points = np.column_stack([x, y, np.where(x + 0.3 * y < 0.55, 0.0, -JUMP)])
    return points, triangulate(points, np.arange(n * n).reshape(n, n))


def distance_to_step(p: np.ndarray) -> np.ndarray:
    """Exact distance of ``p (m, 3)`` to the two half-planes of :func:`step_range_image`
    (each bounded by the contour line ``x + 0.3 y = 0.55``; the square's own borders are
    not reached by a drawn mesh inside it)."""
    normal = np.array([1.0, 0.3]) / np.hypot(1.0, 0.3)  # of the contour, in the xy-plane
    past = p[:, :2] @ normal - 0.55 / np.hypot(1.0, 0.3)  # signed, > 0 on the far side
    near = np.hypot(np.maximum(past, 0.0), p[:, 2])
    far = np.hypot(np.maximum(-past, 0.0), p[:, 2] + JUMP)
    return np.minimum(near, far)


def test_a_range_image_step_is_drawn_without_a_wall_at_every_level(tmp_path):
    """A single patch (``patches=1``; the smooth base, the default, would make this mesh
    an atlas) over a range image with a depth jump: EVERY level a visitor is drawn
    follows both planes and leaves the jump open. Dense samples of each level's drawn mesh
    lie within 3 sample spacings of the exact surface (the stray limit, 2 spacings and 8
    RMS, is what a wall's ends may keep: 2.3 spacings at the finest level; with the trim of
    the base's cells alone the finest wall reached 5.1, and without walls masks levels 0
    and 1 reached 5.8 and 7.1), and the drawn mesh still holds the scan (at the finest
    level 99 % of its points within 0.5 % of the diagonal, every point within 2 %; 95 %
    and 3 % at the coarser ones). Both kernels draw the same cells. Every level is drawn
    on at least 256 cells across (``client_py.bundle.level_resolution``), among which the
    coarser levels' smooth surfaces draw no wall here: their tiles carry no walls mask (on
    two vertices per knot span, 33 and 65 per side, their triangles joined both planes and
    levels 0 and 1 needed walls masks)."""
    from client_py.bundle import plan_levels, tessellate_bundle
    from client_py.format import read_detail_tile
    from fitter.fitting.atlas.measure import point_mesh_distance
    from fitter.fitting.atlas.surface import area_samples
    from fitter.fitting.io import Scan
    from fitter.fitting.options import FitOptions
    from fitter.fitting.pipeline import fit_scan

    points, faces = step_range_image()
    diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    manifest = fit_scan(Scan(points, faces=faces, source={"name": "step"}), tmp_path / "b",
                        FitOptions(patches=1)).manifest
    assert manifest["format_version"] == 1 and manifest["fit"]["wall_cells"] > 0
    read = lambda name: (tmp_path / "b" / name).read_bytes()  # noqa: E731
    plans = plan_levels(manifest)
    assert len(plans) >= 3
    tiles = [read_detail_tile(read(n["file"])) for n in manifest["tiles"]["detail"]["nodes"]]
    walled = {t.level for t in tiles if t.walls is not None and any(t.walls.flat)}
    assert walled == set() and not any(manifest["fit"].get("level_wall_cells") or [0])
    assert all(plan.resolution >= 257 for plan in plans)
    spacing = 1 / 159
    for plan in plans:
        meshes = {k: tessellate_bundle(manifest, read, level=plan.level,
                                       resolution=plan.resolution, kernel=k)
                  for k in ("numpy", "python")}
        assert bytes(meshes["numpy"].indices) == bytes(meshes["python"].indices)
        mesh = meshes["numpy"]
        vertices = np.frombuffer(mesh.positions, np.float32).reshape(-1, 3).astype(float)
        triangles = np.frombuffer(mesh.indices, np.uintc).reshape(-1, 3).astype(np.int64)
        samples, _ = area_samples(vertices, triangles, 200_000, np.random.default_rng(0))
        assert distance_to_step(samples).max() <= 3 * spacing, plan.level
        d = point_mesh_distance(points, vertices, triangles)
        finest = plan.level == plans[-1].level
        assert np.mean(d <= 0.005 * diagonal) >= (0.99 if finest else 0.95), plan.level
        assert d.max() <= (0.02 if finest else 0.03) * diagonal, plan.level


def test_a_scattered_clouds_gaps_are_not_walls():
    """The plane fitted exactly to a uniform random sample of it: no cell of the finest
    grid is a wall (``wall_limit``, 2 gaps of the 99th-percentile spacing), though its
    sampling gaps reach beyond 2 median spacings (``limit``) at many probes."""
    model = plane_model()
    rng = np.random.default_rng(4)
    U, V = rng.uniform(0, 1, 20_000), rng.uniform(0, 1, 20_000)
    points = np.column_stack([U, V, 0 * U])
    redraw = detail.Redraw.from_foot_points(model, np.ones((1, 1), bool), points, U, V, False)
    fields = [np.zeros((detail.SPANS << k) + detail.DEGREE) for k in range(3)]
    fields = [np.zeros((len(f), len(f))) for f in fields]
    assert not redraw.walls(fields, detail.DEGREE, detail.SPANS, rms=0.0, size=128).any()
    corner = np.arange(129) / 128  # the finest grid's corners, 128 cells a side
    u, v = (x.ravel() for x in np.meshgrid(corner, corner, indexing="ij"))
    gaps = redraw.near.farther(np.column_stack([u, v, 0 * u]), redraw.near.limit(0.0))
    assert gaps.sum() > 100
    lifted = [f.copy() for f in fields]
    lifted[-1][40:50, 40:50] = 3 * redraw.near.wall_limit(0.0)  # a bump off the scan
    assert redraw.walls(lifted, detail.DEGREE, detail.SPANS, rms=0.0, size=128).any()


def test_a_levels_walls_are_only_among_the_cells_it_draws():
    """``Redraw.walls`` with the drawn masks of the levels applied (``drawn``): the walls of
    the default (every candidate cell may be drawn) on exactly the cells the trim or one
    of those masks covers. A plane sampled uniformly, its trim (32 x 32) leaving out the
    block ``[0.25, 0.5)^2`` (candidates: foot points fall there), a bump off the scan over
    ``[0.19, 0.56)^2`` (cells 24..71 of 128), half of the block given back by a level's
    drawn mask (64 x 64, full domain)."""
    model, points, trim = plane_model(), plane_sample(5), np.ones((32, 32), bool)
    trim[8:16, 8:16] = False
    U, V = points[:, 0], points[:, 1]
    redraw = detail.Redraw.from_foot_points(model, trim, points, U, V, False)
    assert redraw.candidates[8:16, 8:16].all() and redraw.candidates.sum() == 64
    fields = [np.zeros(((detail.SPANS << k) + detail.DEGREE,) * 2) for k in range(3)]
    fields[2][24:36, 24:36] = 3 * redraw.near.wall_limit(0.0)  # spans 22..35 of 64
    args = (fields, detail.DEGREE, detail.SPANS, 0.0, 128)
    every = redraw.walls(*args)
    block = np.zeros((128, 128), bool)
    block[32:64, 32:64] = True  # the trim's left-out cells on the 128 grid
    assert every[block].any() and every[~block].any()
    assert not redraw.walls(*args, drawn=[])[block].any()
    np.testing.assert_array_equal(redraw.walls(*args, drawn=[]), every & ~block)
    half = np.zeros((64, 64), bool)
    half[16:24, 16:32] = True  # rows 0.25..0.375 of the block, every column
    given = block.copy()
    given[48:64] = False
    np.testing.assert_array_equal(redraw.walls(*args, drawn=[half]), every & ~(block & ~given))


def test_samples_no_triangle_uses_do_not_hold_a_wall_up():
    """A range image's triangulation leaves out lone samples (past an occluding contour);
    the walls are measured against the points its triangles use. The plane ``z = 0``
    sampled on a grid of 160 x 160 (triangulated) and 16 x 16 lone samples at height
    ``H = 0.05`` over ``[0.375, 0.5]^2`` (in no triangle); the finest field lifts the
    surface to exactly ``H`` there (its coefficients ``24..33`` on 64 spans: the spans
    ``24..31``, cells ``48..63`` of 128, have only lifted ones) and ramps down over the
    next two spans (cells ``44..47`` and ``64..67``). Measured against every point the
    lifted cells lie on the lone samples (within ``0.0055 < wall_limit = 0.0125``): no
    wall there, only on the ramps. Against the triangles' points all of them are walls
    (``H = 4 wall_limit`` from the plane); nothing beyond the ramps ever is."""
    from fitter.fitting.io import Scan
    from fitter.fitting.pipeline import _on_triangles

    model = plane_model()
    g = (np.arange(160) + 0.5) / 160
    U, V = (x.ravel() for x in np.meshgrid(g, g, indexing="ij"))
    lone = (np.arange(16) + 0.5) / 16 * 0.125 + 0.375
    lu, lv = (x.ravel() for x in np.meshgrid(lone, lone, indexing="ij"))
    points = np.vstack([np.column_stack([U, V, 0 * U]), np.column_stack([lu, lv, 0 * lu + 0.05])])
    grid = np.arange(160 * 160).reshape(160, 160)
    quads = np.stack([grid[:-1, :-1], grid[1:, :-1], grid[:-1, 1:], grid[1:, 1:]], -1)
    quads = quads.reshape(-1, 4)
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [1, 3, 2]]])
    surface = _on_triangles(Scan(points, faces=faces, source={"name": "lone"}))
    np.testing.assert_array_equal(surface, np.arange(len(points)) < 160 * 160)
    assert _on_triangles(Scan(points, source={"name": "cloud"})) is None
    fields = [np.zeros(((detail.SPANS << k) + detail.DEGREE,) * 2) for k in range(3)]
    fields[2][24:34, 24:34] = 0.05
    plateau, lifted = np.zeros((128, 128), bool), np.zeros((128, 128), bool)
    plateau[48:64, 48:64], lifted[44:68, 44:68] = True, True
    walls = {}
    for name, on in (("every point", None), ("triangles' points", surface)):
        redraw = detail.Redraw.from_foot_points(model, np.ones((1, 1), bool), points,
                                                points[:, 0], points[:, 1], False, on)
        assert redraw.near.wall_limit(0.0) == pytest.approx(0.0125)
        walls[name] = redraw.walls(fields, detail.DEGREE, detail.SPANS, rms=0.0, size=128)
        assert not (walls[name] & ~lifted).any(), name
    assert not (walls["every point"] & plateau).any() and walls["every point"].any()
    assert walls["triangles' points"][plateau].all()


@pytest.mark.parametrize("mesh", [False, True])
def test_a_meshs_redraw_strays_beyond_the_walls_limit(mesh):
    """The plane ``z = 0`` sampled at 20,000 uniform random points and a trim leaving out
    a block; the refined surface lifted to ``z = d`` between the two limits
    (``limit = 2 spacing < d < wall_limit = 2 gap``). A candidate cell is drawn where its
    five probes (centre, corners) lie within the limit of the nearest point, at distance
    ``sqrt(d^2 + r^2)`` with ``r`` the probe's distance in the plane: ``limit`` for a
    cloud (``d`` alone exceeds it: none), the walls' ``wall_limit`` for a mesh
    (:attr:`Redraw.mesh`), whose walls leave out what strays farther. Both against that
    count."""
    from scipy.spatial import KDTree

    model, points = plane_model(), plane_sample(7)
    U, V = points[:, 0], points[:, 1]
    drawn = np.ones((16, 16), bool)
    drawn[4:10, 4:10] = False
    redraw = detail.Redraw.from_foot_points(model, drawn, points, U, V, False,
                                            np.ones(len(U), bool) if mesh else None)
    assert redraw.mesh == mesh
    near = redraw.near
    assert 2 * near.spacing < 2 * near.gap  # a scattered sample: the limits differ
    d = near.spacing + near.gap
    fields = [np.full((detail.SPANS + detail.DEGREE,) * 2, d)]  # D = d: X = (u, v, d)
    got = redraw.cells(0, fields, detail.DEGREE, detail.SPANS, rms=0.0)
    limit = 2 * (near.gap if mesh else near.spacing)
    size = detail.DRAWN_SIDE
    expected = np.zeros((size, size), bool)
    expected[8:20, 8:20] = True  # the block's candidate cells (all hold points)
    tree = KDTree(points[:, :2])
    for r, c in np.argwhere(expected):
        probes = np.array([(r + a, c + b) for a, b in
                           ((0.5, 0.5), (0, 0), (0, 1), (1, 0), (1, 1))]) / size
        expected[r, c] = np.all(np.hypot(d, tree.query(probes)[0]) <= limit)
    np.testing.assert_array_equal(got, expected)
    assert expected.sum() > 100 if mesh else not expected.any()  # d > limit: none for a cloud


@pytest.mark.realdata
def test_buddha_range_scan_0s_coarse_levels_hold_the_scan_as_the_base_alone(shared_data,
                                                                            tmp_path):
    """Buddha range scan 0 as one patch (``patches=1``; the smooth base, the default, makes
    it an atlas, whose levels ``bench/bench_atlas.py`` measures): every level a visitor is drawn
    (``client_py.bundle.plan_level``'s grid, at least 256 cells across) holds ALL scan points
    at least as well as the base alone on its 256 x 256 grid, within a margin: on the 33 x
    33 grid of two vertices per knot span level 0 held 80.0 % of them within 0.5 % of the
    diagonal (the base alone 98.3 %) and strayed 2.0 % of the diagonal from the scan. Both
    distances by brute-force projection onto the drawn triangles
    (``fitter.fitting.atlas.measure``), the mesh's by 200,000 samples over its area."""
    from client_py.bundle import plan_level, plan_levels, tessellate_bundle
    from fitter.fitting.atlas.measure import point_mesh_distance
    from fitter.fitting.atlas.surface import area_samples
    from fitter.fitting.io import load_scan
    from fitter.fitting.options import FitOptions
    from fitter.fitting.pipeline import fit_scan

    scan = load_scan(shared_data / "happy-buddha-rangescans" / "happyStandRight_0.ply.gz")
    points = np.asarray(scan.points, float)
    diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    manifest = fit_scan(scan, tmp_path / "b", FitOptions(patches=1)).manifest
    read = lambda name: (tmp_path / "b" / name).read_bytes()  # noqa: E731
    from scipy.spatial import KDTree

    near = KDTree(points)
    within, stray = {}, {}
    for plan in [plan_level(manifest, -1)] + plan_levels(manifest):
        mesh = tessellate_bundle(manifest, read, level=plan.level, resolution=plan.resolution)
        vertices = np.frombuffer(mesh.positions, np.float32).reshape(-1, 3).astype(float)
        faces = np.frombuffer(mesh.indices, np.uintc).reshape(-1, 3).astype(np.int64)
        d = point_mesh_distance(points, vertices, faces)
        within[plan.level] = float(np.mean(d <= 0.005 * diagonal))
        samples, _ = area_samples(vertices, faces, 200_000, np.random.default_rng(0))
        stray[plan.level] = float(near.query(samples)[0].max()) / diagonal
        assert plan.level < 0 or plan.resolution >= 257
    for level in range(len(plan_levels(manifest))):
        assert within[level] >= within[-1] - 0.002, (level, within)
        assert stray[level] <= stray[-1] + 0.001, (level, stray)
    assert within[0] >= 0.975 and stray[0] <= 0.016, (within, stray)
