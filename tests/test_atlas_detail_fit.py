"""The atlas's detail pyramid (fitter.fitting.atlas.detail) on a bumpy sphere with a known field."""

import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh

from client_py.atlas_detail import pack_name, read_pack
from client_py.atlas_mesh import tessellate_atlas
from fitter.fitting.atlas import detail as atlas_detail
from fitter.fitting.atlas.fit import AtlasFit
from fitter.fitting.atlas.patches import control_points, evaluate_patches, index_table
from fitter.fitting.atlas.surface import ScanSurface
from fitter.fitting.io.scan import make_scan
from tests.atlas_cases import sphere_atlas

AMPLITUDE = 0.03


def bump(unit: np.ndarray) -> np.ndarray:
    """The known displacement of the unit sphere at unit directions ``(N, 3)``."""
    x, y, z = unit.T
    return AMPLITUDE * np.sin(3 * x) * np.sin(3 * y + 0.5) * np.cos(2 * z)


def _fake_fit(atlas, name: str, vertices: np.ndarray, faces: np.ndarray):
    """A fake base fit of ``atlas`` to the scan mesh ``(vertices, faces)``: the working
    points are exact points of the base (12 x 12 a patch)."""
    scan = make_scan(name, vertices, faces=faces, source={"name": name})
    surface = ScanSurface(vertices, faces, "mesh", 1)
    F = len(atlas.quads)
    t = np.linspace(0.02, 0.98, 12)
    uu, vv = np.meshgrid(t, t, indexing="ij")
    patch = np.repeat(np.arange(F), uu.size)
    u, v = np.tile(uu.ravel(), F), np.tile(vv.ravel(), F)
    (points,) = evaluate_patches(index_table(atlas), control_points(atlas), atlas.degree,
                                 atlas.spans, patch, u, v)
    fit = AtlasFit(atlas, None, surface, F // 3, F, points, patch, u, v, np.zeros(len(u)), 0.0,
                   0)
    return fit, scan


def _bumpy_sphere_fit():
    """A fake base fit: the 24-patch sphere atlas and, as the scan, the icosphere displaced
    radially by :func:`bump`."""
    ico = trimesh.creation.icosphere(subdivisions=5)
    unit = ico.vertices / np.linalg.norm(ico.vertices, axis=1, keepdims=True)
    vertices = unit * (1.0 + bump(unit))[:, None]
    return _fake_fit(sphere_atlas(2), "bumpy", vertices, np.asarray(ico.faces, np.int64))


@pytest.fixture(scope="module")
def fitted():
    fit, scan = _bumpy_sphere_fit()
    return fit, scan, atlas_detail.fit_atlas_detail(fit, scan, levels=3, spans=4, pack_bytes=1000)


def _radial_error(atlas, tiles, resolution):
    mesh = tessellate_atlas(atlas, resolution, tiles, kernel="numpy")
    x = np.frombuffer(mesh.positions, np.float32).reshape(-1, 3).astype(float)
    r = np.linalg.norm(x, axis=1)
    return np.sqrt(np.mean((r - 1.0 - bump(x / r[:, None])) ** 2)), mesh


def test_detail_recovers_the_known_bump(fitted):
    _, _, det = fitted
    base, _ = _radial_error(det.atlas, None, 33)
    finest, _ = _radial_error(det.atlas, det.detail_up_to(2), det.levels[2]["resolution"])
    assert base > 0.5 * AMPLITUDE / 2  # the base is the plain sphere: the bump's size
    assert finest < 0.1 * base, (base, finest)
    rms = [row["rms"] for row in det.levels]
    assert rms[-1] < 0.1 * det.tree["base"]["rms"]


def test_borders_are_shared_exactly_and_the_welded_mesh_is_closed(fitted):
    _, _, det = fitted
    for row in det.levels:
        assert row["border_jump"]["max"] <= 1e-9, row["border_jump"]
    _, mesh = _radial_error(det.atlas, det.detail_up_to(2), det.levels[2]["resolution"])
    tri = np.frombuffer(mesh.indices, np.uint32).reshape(-1, 3).astype(np.int64)
    edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)  # no boundary edge, no non-manifold edge


def test_packs_round_trip_and_the_manifest_is_consistent(fitted):
    _, _, det = fitted
    tree = det.tree
    F = len(det.atlas.quads)
    assert [row["level"] for row in tree["levels"]] == [0, 1, 2]
    assert [row["resolution"] for row in tree["levels"]] == [9, 17, 33]
    covered = []
    for g in tree["groups"]:
        covered += range(g["first"], g["first"] + g["count"])
        assert g["radius"] > 0
    assert covered == list(range(F))  # contiguous ranges, every patch exactly once
    assert len(tree["groups"]) > 1
    assert set(det.files) == {pack_name(p["level"], p["group"]) for p in tree["packs"]}
    for p in tree["packs"]:
        data = det.files[pack_name(p["level"], p["group"])]
        assert p["bytes"] == len(data)
        level, tiles = read_pack(data, det.atlas)  # welded: the renumbered atlas
        g = tree["groups"][p["group"]]
        assert level == p["level"]
        assert set(tiles) <= set(range(g["first"], g["first"] + g["count"]))
        for f, got in tiles.items():
            assert got == det.tiles[level][f]
    for row in tree["levels"]:
        assert row["bytes_total"] == sum(p["bytes"] for p in tree["packs"]
                                         if p["level"] == row["level"])
    finest = [p for p in tree["packs"] if p["level"] == 2]
    for p in finest:  # the groups' estimate of a pack's bytes holds (a lone patch may pass)
        assert p["bytes"] <= 1000 or tree["groups"][p["group"]]["count"] == 1


def test_shared_index_is_the_atlas_rule_and_renumbering_keeps_the_surface():
    atlas = sphere_atlas(2)
    grid = atlas_detail.shared_index(atlas, atlas.side)
    for f in range(len(atlas.quads)):
        assert grid[f].tolist() == atlas.patch_indices(f)
    order = np.random.default_rng(3).permutation(len(atlas.quads))
    moved = atlas_detail.renumber_patches(atlas, order)
    for k, f in enumerate(order):
        assert moved.patch_surface(k).evaluate(0.3, 0.7) == atlas.patch_surface(int(f)).evaluate(
            0.3, 0.7)


def test_bad_arguments_are_named():
    fit, scan = _bumpy_sphere_fit()
    with pytest.raises(ValueError, match="levels must be"):
        atlas_detail.fit_atlas_detail(fit, scan, levels=99)
    with pytest.raises(ValueError, match="spans must be"):
        atlas_detail.fit_atlas_detail(fit, scan, spans=5)
    with pytest.raises(ValueError, match="step_factor"):
        atlas_detail.fit_atlas_detail(fit, scan, step_factor=0.0)
    for bad in (0.0, -1.0, float("nan"), True, "0.6"):
        with pytest.raises(ValueError, match="offset_limit must be"):
            atlas_detail.fit_detail_pyramid(fit, scan, offset_limit=bad)
        with pytest.raises(ValueError, match="offset_limit must be"):
            atlas_detail.fit_atlas_detail(fit, scan, offset_limit=bad)  # forwarded
        with pytest.raises(ValueError, match="pull_reach must be"):
            atlas_detail.fit_atlas_detail(fit, scan, pull_reach=bad)
    with pytest.raises(ValueError, match="permutation"):
        atlas_detail.renumber_patches(fit.atlas, np.zeros(len(fit.atlas.quads), int))


def test_levels_an_atlas_cannot_hold_are_refused_before_any_is_fitted(monkeypatch):
    """The most levels: the viewer draws a patch side at most ``ATLAS_MAX_RESOLUTION``
    samples (two a span) and the finest level holds at most ``MAX_COEFFICIENTS``; an
    explicit depth past them is an ``OptionError`` naming why, before the samples are
    projected (it once ran for ten minutes toward 10^9 coefficients)."""
    from client_py.bundle import ATLAS_MAX_RESOLUTION
    from fitter.fitting.options import OptionError

    # 8 spans: levels 0..3 are drawn at 17, 33, 65, 129 samples a side; level 4 at 257
    assert atlas_detail.most_levels(1, 8)[0] == 4 and ATLAS_MAX_RESOLUTION == 129
    assert atlas_detail.most_levels(1, 4)[0] == 5
    # 2,274 patches (the vase's): level 3 has 2,274 * (64 + 2)^2 = 9,905,544 coefficients
    most, why = atlas_detail.most_levels(2274, 8)
    assert most == 3 and "9,905,544 coefficients, over 6,000,000" in why
    assert atlas_detail.most_levels(1377, 8)[0] == 4  # 1,377 * 66^2 = 5,998,212
    # the automatic depth is the spacing's, within the same caps
    assert atlas_detail.auto_levels(1.0, 1e-9, 2274, 8) == 3
    assert atlas_detail.auto_levels(1.0, 1e-9, 1, 8) == 4
    # knot spacing 1/8, 1/16, 1/32 at levels 0, 1, 2
    assert atlas_detail.auto_levels(1.0, 1.0 / 10, 1, 8) == 2
    assert atlas_detail.auto_levels(1.0, 1.0 / 20, 1, 8) == 3
    assert atlas_detail.auto_levels(1.0, 1.0, 1, 8) == 1
    with pytest.raises(OptionError, match=r"detail_levels 5: an atlas with 8 spans a tile "
                                          r"holds at most 4 levels \(level 4 would be drawn "
                                          r"at 257 samples a patch side"):
        atlas_detail.check_levels(5, None, 8)
    atlas_detail.check_levels(4, None, 8)
    fit, scan = _bumpy_sphere_fit()
    monkeypatch.setattr(atlas_detail, "surface_samples", lambda *a, **k: pytest.fail(
        "sampled before the depth was checked"))
    with pytest.raises(OptionError, match=f"an atlas of {len(fit.atlas.quads)} patches with "
                                          "4 spans a tile holds at most 5 levels"):
        atlas_detail.fit_atlas_detail(fit, scan, levels=6, spans=4)


def test_a_sample_from_the_other_sheet_is_not_fitted():
    """A sample whose own normal opposes the base's at its foot point (the back of a thin
    part matched to its front) is left out of the fit; one that agrees is fitted."""
    fit, _ = _bumpy_sphere_fit()
    rng = np.random.default_rng(3)
    unit = rng.normal(size=(400, 3))
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    points = unit * 1.01
    normals = np.where(np.arange(400)[:, None] < 200, unit, -unit)  # half face inward
    samples = atlas_detail.project_samples(fit.atlas, fit, points, normals)
    assert np.sum(samples.facing < 0) == 200  # the foot points' normals: outward, all
    np.testing.assert_allclose(np.abs(samples.facing), 1.0, atol=0.05)
    use = atlas_detail.fit_samples(samples, spacing=0.05, side=1.0)
    np.testing.assert_array_equal(use, samples.facing > 0)


def test_the_offset_limit_decides_which_offsets_are_fitted():
    """A sample farther along the normal than ``offset_limit`` median patch sides is left
    out (the base missed that part), one within it is fitted: at the default
    ``OFFSET_LIMIT`` and at a smooth base's wider ``SMOOTH_OFFSET_LIMIT``."""
    from fitter.fitting.atlas.smooth import SMOOTH_OFFSET_LIMIT

    fit, _ = _bumpy_sphere_fit()
    rng = np.random.default_rng(4)
    unit = rng.normal(size=(300, 3))
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    side = 0.1
    offset = np.repeat([0.1, 0.4, 0.8], 100) * side  # in patch sides
    samples = atlas_detail.project_samples(fit.atlas, fit, unit * (1.0 + offset[:, None]),
                                           unit)
    s = np.abs(samples.s)
    for limit in (atlas_detail.OFFSET_LIMIT, SMOOTH_OFFSET_LIMIT):
        use = atlas_detail.fit_samples(samples, spacing=0.05, side=side, offset_limit=limit)
        np.testing.assert_array_equal(use, s <= limit * side)
        assert 0 < use.sum() < len(use)


def test_drawn_triangles_are_the_clients_grid_triangles():
    """Each (u, v)'s nodes and barycentric weights against a search over the triangles
    ``client_py.tessellate.grid_indices`` draws, in the parameter plane."""
    from client_py.tessellate import grid_indices

    r = 5
    tri = np.asarray(grid_indices(r, r), np.int64).reshape(-1, 3)
    nodes = np.stack(np.divmod(np.arange(r * r), r), axis=1) / (r - 1)  # vertex k = i r + j
    rng = np.random.default_rng(5)
    uv = np.concatenate([rng.random((300, 2)), [[0.0, 0.0], [1.0, 1.0], [0.5, 0.25]]])
    a, b, beta = atlas_detail.drawn_triangles(uv[:, 0], uv[:, 1], r)
    for k, p in enumerate(uv):
        # the reference: the triangle whose barycentric coordinates of p are all >= 0
        for t in tri:
            m = np.column_stack([nodes[t[1]] - nodes[t[0]], nodes[t[2]] - nodes[t[0]]])
            l1, l2 = np.linalg.solve(m, p - nodes[t[0]])
            weights = np.array([1 - l1 - l2, l1, l2])
            if weights.min() >= -1e-12:
                break
        got = {(int(x), int(y)): w for x, y, w in zip(a[k], b[k], beta[k], strict=True)}
        rows, cols = np.divmod(t, r)
        want = {(int(x), int(y)): w for x, y, w in zip(rows, cols, weights, strict=True)}
        for key, w in want.items():
            if w > 1e-9:
                assert got.get(key, 0.0) == pytest.approx(w, abs=1e-9), (p, got, want)
        assert sum(got.values()) == pytest.approx(1.0)


def _bump_samples(fit, atlas, seed: int, count: int):
    """``count`` random points of the bumped unit sphere, projected on ``atlas``."""
    unit = np.random.default_rng(seed).normal(size=(count, 3))
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    points = unit * (1.0 + bump(unit))[:, None]
    return atlas_detail.project_samples(atlas, fit, points, unit)


def test_projection_along_the_morton_curve_is_each_samples_own(fitted):
    """project_samples takes its chunks along the Morton curve of the samples: every field
    is that of each sample projected alone (chunks of one sample), and of the samples given
    in another order, bit for bit."""
    fit, _, det = fitted
    rng = np.random.default_rng(5)
    unit = rng.normal(size=(600, 3))
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    points = unit * (1.0 + bump(unit))[:, None]
    weights = rng.uniform(0.5, 2.0, len(points))
    chunked = atlas_detail.project_samples(det.atlas, fit, points, unit, chunk=97,
                                           weights=weights)
    alone = atlas_detail.project_samples(det.atlas, fit, points, unit, chunk=1, threads=1,
                                         weights=weights)
    names = ("patch", "u", "v", "s", "t2", "offsets", "distance", "facing", "weight")
    for name in names:
        assert getattr(chunked, name).tobytes() == getattr(alone, name).tobytes(), name
    turn = rng.permutation(len(points))
    turned = atlas_detail.project_samples(det.atlas, fit, points[turn], unit[turn], chunk=97,
                                          weights=weights[turn])
    a, b = np.argsort(chunked.weight), np.argsort(turned.weight)  # the weights name them
    for name in names[:5] + names[6:]:
        assert getattr(chunked, name)[a].tobytes() == getattr(turned, name)[b].tobytes(), name


def test_drawn_model_is_the_offset_from_the_clients_drawn_triangle(fitted):
    """``target - sum_levels drawn`` of a sample is ``(x - sum_i beta_i X_i) . n`` with
    ``X_i`` the vertices of ``client_py.atlas_mesh``'s welded, displaced mesh (border
    vertices included), found by their undisplaced positions."""
    from scipy.spatial import cKDTree

    fit, scan, det = fitted
    atlas = det.atlas
    samples = _bump_samples(fit, atlas, 7, 3000)
    level = 1
    r = det.levels[level]["resolution"]
    model = atlas_detail.DrawnModel.of(atlas, samples, r)
    fields = [_coefficients(det, k) for k in range(level + 1)]
    predicted = model.target - sum(model.drawn(c, k, det.tree["spans_per_tile"])
                                   for k, c in enumerate(fields))
    base = tessellate_atlas(atlas, r, None, kernel="numpy")
    drawn = tessellate_atlas(atlas, r, det.detail_up_to(level), kernel="numpy")
    plain = np.frombuffer(base.positions, np.float32).reshape(-1, 3).astype(float)
    shown = np.frombuffer(drawn.positions, np.float32).reshape(-1, 3).astype(float)
    table, cps = index_table(atlas), control_points(atlas)
    c, cu, cv = evaluate_patches(table, cps, atlas.degree, atlas.spans, samples.patch,
                                 samples.u, samples.v, derivatives=True)
    n = np.cross(cu, cv)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    x = c + samples.s[:, None] * n + 0.0  # the sample with its tangential part dropped
    a, b, beta = atlas_detail.drawn_triangles(samples.u, samples.v, r)
    tree = cKDTree(plain)
    corner = np.zeros_like(x)
    for i in range(3):
        (node,) = evaluate_patches(table, cps, atlas.degree, atlas.spans, samples.patch,
                                   a[:, i] / (r - 1), b[:, i] / (r - 1))
        gap, vertex = tree.query(node)
        assert gap.max() < 1e-5
        corner += beta[:, i, None] * shown[vertex]
    want = np.einsum("kc,kc->k", x - corner, n)
    np.testing.assert_allclose(predicted, want, atol=2e-6)


def test_projection_keeps_the_feet_drawn_model_feet_would_evaluate(fitted):
    """project_samples keeps each sample's base point and unit normal (AtlasSamples.foot,
    normal): DrawnModel.feet returns them, equal bit for bit to its own evaluation of the
    samples without them, and the model made of either is the same."""
    fit, scan, det = fitted
    atlas = det.atlas
    samples = _bump_samples(fit, atlas, 11, 2500)
    assert samples.foot.shape == samples.normal.shape == (len(samples.u), 3)
    bare = replace(samples, foot=None, normal=None)
    kept, made = atlas_detail.DrawnModel.feet(atlas, samples), atlas_detail.DrawnModel.feet(
        atlas, bare, chunk=333)
    assert kept[0] is samples.foot
    for a, b in zip(kept, made, strict=True):
        assert a.tobytes() == b.tobytes()
    r = det.levels[1]["resolution"]
    one, two = atlas_detail.DrawnModel.of(atlas, samples, r), atlas_detail.DrawnModel.of(atlas,
                                                                                         bare, r)
    assert one.target.tobytes() == two.target.tobytes()
    assert one.weight.tobytes() == two.weight.tobytes()


def test_drawn_model_evaluates_each_node_once_to_the_same_numbers(fitted):
    """DrawnModel evaluates every drawn node once and gathers it per sample: its target,
    weights and ``drawn`` are those of the per-sample reference (each sample's three nodes
    evaluated on their own, the model as it was written first), to rounding (the same
    numbers on the 15-scan Happy Buddha); and the feet given or computed make the same
    model, bit for bit."""
    fit, scan, det = fitted
    atlas = det.atlas
    samples = _bump_samples(fit, atlas, 11, 2500)
    spans = det.tree["spans_per_tile"]
    level = 1
    r = det.levels[level]["resolution"]
    model = atlas_detail.DrawnModel.of(atlas, samples, r, chunk=700)
    again = atlas_detail.DrawnModel.of(atlas, samples, r,
                                       feet=atlas_detail.DrawnModel.feet(atlas, samples))
    table, cps = index_table(atlas), control_points(atlas)
    d, s = atlas.degree, atlas.spans
    a, b, beta = atlas_detail.drawn_triangles(samples.u, samples.v, r)
    # the reference: border directions as the model's docstring says, nodes per sample
    G = atlas_detail.shared_index(atlas, r)
    F = len(atlas.quads)
    rim = [(f, i, j) for f in range(F) for i in range(r) for j in range(r)
           if i in (0, r - 1) or j in (0, r - 1)]
    rf, ra, rb = (np.array(x) for x in zip(*rim, strict=True))
    _, cu, cv = evaluate_patches(table, cps, d, s, rf, ra / (r - 1), rb / (r - 1),
                                 derivatives=True)
    unit_n = np.cross(cu, cv)
    unit_n /= np.linalg.norm(unit_n, axis=1, keepdims=True)
    total = np.zeros((int(G.max()) + 1, 3))
    np.add.at(total, G[rf, ra, rb], unit_n)
    total /= np.maximum(np.linalg.norm(total, axis=1, keepdims=True), 1e-300)
    c, cu, cv = evaluate_patches(table, cps, d, s, samples.patch, samples.u, samples.v,
                                 derivatives=True)
    n = np.cross(cu, cv)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    target = samples.s.copy()
    field = _coefficients(det, level)
    drawn = np.zeros(len(samples.u))
    for i in range(3):
        ci, cui, cvi = evaluate_patches(table, cps, d, s, samples.patch, a[:, i] / (r - 1),
                                        b[:, i] / (r - 1), derivatives=True)
        di = np.cross(cui, cvi)
        di /= np.linalg.norm(di, axis=1, keepdims=True)
        on_rim = (a[:, i] == 0) | (a[:, i] == r - 1) | (b[:, i] == 0) | (b[:, i] == r - 1)
        di[on_rim] = total[G[samples.patch[on_rim], a[on_rim, i], b[on_rim, i]]]
        weight = beta[:, i] * np.maximum(np.einsum("kc,kc->k", di, n),
                                         atlas_detail.MIN_DIRECTION)
        np.testing.assert_allclose(model.weight[:, i], weight, rtol=1e-12, atol=1e-15)
        target += beta[:, i] * np.einsum("kc,kc->k", c - ci, n)
        drawn += weight * atlas_detail.evaluate_fields(field, level, spans, samples.patch,
                                                       a[:, i] / (r - 1), b[:, i] / (r - 1))
    np.testing.assert_allclose(model.target, target, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(model.drawn(field, level, spans), drawn, rtol=1e-12,
                               atol=1e-15)
    for name in ("weight", "target", "node", "node_u", "node_v"):
        assert getattr(model, name).tobytes() == getattr(again, name).tobytes(), name


def test_drawn_model_of_the_levels_node_frames_is_the_model_it_evaluates(fitted):
    """DrawnModel.of given the level's LevelNodes (every node's frame, evaluated once for
    the level's far and fold rows) takes its nodes' positions and directions from them:
    the model it evaluates itself, bit for bit; frames of another resolution are refused."""
    fit, scan, det = fitted
    atlas = det.atlas
    samples = _bump_samples(fit, atlas, 11, 2500)
    spans = det.tree["spans_per_tile"]
    for level in (0, 1):
        r = det.levels[level]["resolution"]
        frames = atlas_detail.level_nodes(atlas, [], level, spans)
        plain = atlas_detail.DrawnModel.of(atlas, samples, r, chunk=700)
        given = atlas_detail.DrawnModel.of(atlas, samples, r, frames=frames)
        for name in ("weight", "target", "node", "node_u", "node_v", "node_patch"):
            assert getattr(plain, name).tobytes() == getattr(given, name).tobytes(), name
        # drawn evaluates each node once (evaluate_at_nodes): the plain evaluation, each time
        for k in range(level + 1):
            field = _coefficients(det, k)
            at_nodes = atlas_detail.evaluate_fields(field, k, spans, given.node_patch,
                                                    given.node_u, given.node_v, chunk=333)
            want = sum(given.weight[:, i] * at_nodes[given.node[:, i]] for i in range(3))
            for _ in range(2):
                assert given.drawn(field, k, spans).tobytes() == want.tobytes()
            assert given.drawn(2 * field, k, spans).tobytes() == (2 * want).tobytes()
    with pytest.raises(ValueError, match="nodes a side"):
        atlas_detail.DrawnModel.of(atlas, samples, det.levels[0]["resolution"],
                                   frames=atlas_detail.level_nodes(atlas, [], 1, spans))


@pytest.mark.parametrize("level", [0, 1, 2])
def test_drawn_model_rows_are_the_weighted_collocation_rows(fitted, level):
    """DrawnModel.rows (each node's basis once per parameter, the three nodes added into a
    window) holds the entries of ``sum_i diag(w_i) A_i``, ``A_i`` the collocation matrix at
    the samples' node ``i`` (the sum scipy forms, node after node), bit for bit; a patch
    block's offset moves its columns; an empty range has no rows."""
    from fitter.fitting.detail import collocation_matrix

    fit, scan, det = fitted
    atlas = det.atlas
    samples = _bump_samples(fit, atlas, 11, 2500)
    spans = det.tree["spans_per_tile"]
    r = det.levels[level]["resolution"]
    n = (spans << level) + atlas_detail.DEGREE
    knots = np.array(atlas_detail.layers.level_knots(atlas_detail.DEGREE, spans, level))
    model = atlas_detail.DrawnModel.of(atlas, samples, r)
    F = len(atlas.quads)
    lo, hi = samples.offsets[3], samples.offsets[9]
    block = samples.patch[lo:hi] - 3
    want = sp.csr_matrix((hi - lo, 6 * n * n))
    for i in range(3):
        want = want + sp.diags(model.weight[lo:hi, i]) @ collocation_matrix(
            atlas_detail.DEGREE, knots, n, model.u[lo:hi, i], model.v[lo:hi, i], block=block,
            blocks=6)
    want = want.tocsr()
    want.sort_indices()
    got = model.rows(atlas_detail.DEGREE, knots, n, lo, hi, block, 6)
    assert got.shape == want.shape and got.has_sorted_indices
    for name in ("indptr", "indices", "data"):
        assert getattr(got, name).tobytes() == getattr(want, name).tobytes(), name
    moved = model.rows(atlas_detail.DEGREE, knots, n, lo, hi, block + 1, 7)
    assert (moved.indices == got.indices + n * n).all() and moved.data.tobytes() == \
        got.data.tobytes()
    assert model.rows(atlas_detail.DEGREE, knots, n, lo, lo, block[:0], F).shape == \
        (0, F * n * n)


def test_fields_at_nodes_are_evaluate_fields_and_node_frames_each_nodes_own(fitted):
    """evaluate_at_nodes gives evaluate_fields' numbers at drawn nodes, bit for bit (a
    level at its own resolution, at a finer one, in chunks); node_frames of a shuffled
    subset of the nodes (border sums then evaluating the border nodes not asked for) is
    that of every node at those nodes, bit for bit."""
    fit, scan, det = fitted
    atlas = det.atlas
    spans = det.tree["spans_per_tile"]
    F = len(atlas.quads)
    rng = np.random.default_rng(3)
    for level, r in ((0, 9), (0, 17), (1, 17), (2, 33)):
        n = (spans << level) + atlas_detail.DEGREE
        field = rng.normal(size=(F, n, n))
        f, a, b = atlas_detail.all_nodes(F, r)
        want = atlas_detail.evaluate_fields(field, level, spans, f, a / (r - 1), b / (r - 1))
        got = atlas_detail.evaluate_at_nodes(field, level, spans, f, a / (r - 1), b / (r - 1),
                                             r, chunk=1000)
        assert got.tobytes() == want.tobytes()
    r = 17
    f, a, b = atlas_detail.all_nodes(F, r)
    every = atlas_detail.node_frames(atlas, r, f, a, b)
    some = rng.permutation(len(f))[: len(f) // 5]
    part = atlas_detail.node_frames(atlas, r, f[some], a[some], b[some], chunk=301)
    for whole, mine in zip(every, part, strict=True):
        assert mine.tobytes() == whole[some].tobytes()
    border = (a == 0) | (b == r - 1)
    assert np.abs(np.linalg.norm(every[1][border], axis=1) - 1.0).max() < 1e-12


def _coefficients(det, level):
    """Level ``level``'s field ``(F, n, n)`` (times its step) read back from its tiles."""
    spans = det.tree["spans_per_tile"]
    n = (spans << level) + det.tree["degree"]
    out = np.zeros((len(det.atlas.quads), n, n))
    size = spans + det.tree["degree"]
    for f, tiles in det.tiles[level].items():
        for t in tiles:
            out[f, t.i * spans:t.i * spans + size, t.j * spans:t.j * spans + size] = \
                np.asarray(t.values, float).reshape(size, size) * t.step
    return out


def test_a_sample_of_weight_two_is_that_sample_twice(fitted):
    """``_solve_blocks``'s weights are weights of the sum of squares: doubling a sample's
    weight gives the coefficients of the samples with that one repeated (an independent
    reading of the objective)."""
    fit, _, det = fitted
    rng = np.random.default_rng(11)
    unit = rng.normal(size=(4000, 3))
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    points = unit * (1.0 + bump(unit))[:, None]
    twice = np.arange(len(points)) % 3 == 0
    weights = np.where(twice, 2.0, 1.0)
    one = atlas_detail.project_samples(det.atlas, fit, points, unit, weights=weights)
    both = atlas_detail.project_samples(det.atlas, fit, np.concatenate([points, points[twice]]),
                                        np.concatenate([unit, unit[twice]]))
    c1, _ = atlas_detail._solve_blocks(one, one.s, 0, 4, weights=one.weight)
    c2, _ = atlas_detail._solve_blocks(both, both.s, 0, 4, weights=both.weight)
    np.testing.assert_allclose(c1, c2, atol=1e-10 * np.abs(c2).max())


def test_mesh_samples_weigh_vertices_one_and_triangles_their_share():
    fit, scan = _bumpy_sphere_fit()
    V = len(fit.surface.vertices)
    points, normals, weights = atlas_detail.surface_samples(scan, fit, 3 * V)
    assert len(points) == len(normals) == len(weights) == 3 * V
    np.testing.assert_array_equal(weights[:V], 1.0)
    assert weights[V:].sum() == pytest.approx(atlas_detail.TRIANGLE_SHARE * V)


def test_coefficients_are_bounded_by_twice_their_patchs_residual():
    """Patch 0's fitted residuals reach 0.5 (an unfitted sample's 9 does not count):
    its coefficients are clipped to +-1; patch 1 has no fitted sample: all 0."""
    patch = np.array([0, 0, 0, 1])
    samples = atlas_detail.AtlasSamples(patch, *(np.zeros(4) for _ in range(4)),
                                        np.array([0, 3, 4]), *(np.zeros(4) for _ in range(2)),
                                        np.ones(4))
    residual = np.array([0.5, -0.2, 9.0, 3.0])
    use = np.array([True, True, False, False])
    c = np.array([[[3.0, -0.7], [-5.0, 1.0]], [[2.0, 0.0], [0.0, -1.0]]])
    out = atlas_detail.bounded_by_residual(c, samples, residual, use)
    np.testing.assert_array_equal(out, [[[1.0, -0.7], [-1.0, 1.0]], np.zeros((2, 2))])


def _noisy_sphere_cloud(count: int = 60_000, noise: float = 0.01, seed: int = 5):
    """The bumpy sphere as a cloud of ``count`` points with radial Gaussian noise of
    standard deviation ``noise`` (a third of the bump), fitted as a cloud (a stand-in
    surface for the normals)."""
    fit, mesh_scan = _bumpy_sphere_fit()
    rng = np.random.default_rng(seed)
    unit = rng.normal(size=(count, 3))
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    points = unit * (1.0 + bump(unit) + rng.normal(0.0, noise, count))[:, None]
    scan = make_scan("noisy", points, source={"name": "noisy"})
    surface = ScanSurface(mesh_scan.points, mesh_scan.faces, "poisson", 1)
    from dataclasses import replace
    return replace(fit, surface=surface), scan


def test_automatic_depth_stops_before_levels_that_draw_the_noise():
    """Against the noise-free surface (the independent reference), the levels the held-out
    samples reject are worse than none: the automatic pyramid stops before them, and
    is nearer the true surface than the full depth forced by hand."""
    fit, scan = _noisy_sphere_cloud()
    auto = atlas_detail.fit_atlas_detail(fit, scan, spans=4)
    side = float(np.median(atlas_detail.patch_sides(auto.atlas)))
    full_depth = atlas_detail.auto_levels(side, auto.spacing, len(auto.atlas.quads), 4)
    kept = len(auto.levels)
    assert 1 <= kept < full_depth, (kept, full_depth)
    held = auto.tree["held_out"]
    assert len(held["rms"]) == kept + 2  # the base, each kept level, the rejected one
    assert all(b < (1 - held["min_gain"]) * a for a, b in zip(held["rms"][:kept],
                                                                held["rms"][1:kept + 1],
                                                                strict=True))
    assert held["rms"][-1] >= (1 - held["min_gain"]) * held["rms"][-2]
    assert 0.08 < held["share"] < 0.12
    forced = atlas_detail.fit_atlas_detail(fit, scan, levels=full_depth, spans=4)
    assert "held_out" not in forced.tree and len(forced.levels) == full_depth
    true_auto, _ = _radial_error(auto.atlas, auto.detail_up_to(kept - 1),
                                 auto.levels[-1]["resolution"])
    true_forced, _ = _radial_error(forced.atlas, forced.detail_up_to(full_depth - 1),
                                   forced.levels[-1]["resolution"])
    assert true_auto < true_forced, (true_auto, true_forced)
    assert sum(len(d) for d in auto.files.values()) < sum(len(d) for d in forced.files.values())


def test_a_level_with_too_few_samples_per_unknown_is_not_tried(monkeypatch):
    """A cloud's level whose coefficients are too many for its fitted samples is not
    fitted: the pyramid stops before it and the manifest's tree names it."""
    fit, scan = _noisy_sphere_cloud(count=20_000)
    monkeypatch.setattr(atlas_detail, "MIN_SAMPLES_PER_UNKNOWN", 1e9)
    none = atlas_detail.fit_atlas_detail(fit, scan, spans=4)
    untried = none.tree["held_out"]["not_tried"]
    # the level's shared coefficients: the distinct slots of every patch's (6, 6) grid
    shared = [len(np.unique(atlas_detail.shared_index(none.atlas, n))) for n in (6, 10)]
    assert shared == [atlas_detail.shared_count(none.atlas, n) for n in (6, 10)]
    assert none.levels == [] and untried["level"] == 0 and untried["unknowns"] == shared[0]
    fitted = untried["fitted_samples"]
    # every point but the held-out tenth and the few fit_samples leaves out
    assert 0.85 * 0.9 * 20_000 < fitted <= 0.9 * 20_000
    # a threshold between level 0's samples per unknown (n = 6) and level 1's (n = 10)
    monkeypatch.setattr(atlas_detail, "MIN_SAMPLES_PER_UNKNOWN", 2 * fitted / sum(shared))
    one = atlas_detail.fit_atlas_detail(fit, scan, spans=4, levels=None)
    assert len(one.levels) == 1
    assert one.tree["held_out"]["not_tried"] == {"level": 1, "unknowns": shared[1],
                                                 "fitted_samples": fitted}
    assert len(one.tree["held_out"]["rms"]) == 2  # the base and level 0: level 1 not fitted
    assert one.tree["held_out"]["rms"][1] < one.tree["held_out"]["rms"][0]


def test_a_mesh_keeps_every_sample_and_its_automatic_depth():
    fit, scan = _bumpy_sphere_fit()
    det = atlas_detail.fit_atlas_detail(fit, scan, spans=4)
    side = float(np.median(atlas_detail.patch_sides(det.atlas)))
    assert "held_out" not in det.tree
    assert len(det.levels) == atlas_detail.auto_levels(side, det.spacing, len(det.atlas.quads), 4)


# ------------------------------------------------------------------ a web over a pit
PIT_AXIS = np.array([0.3, 0.2, 1.0]) / np.linalg.norm([0.3, 0.2, 1.0])
PIT_ANGLE, PIT_DEPTH, RIM = 0.12, 0.3, 0.03


def pit_radius(theta: np.ndarray) -> np.ndarray:
    """The pitted sphere's radius at the angle ``theta`` from :data:`PIT_AXIS`: a cone
    ``PIT_DEPTH`` deep of half-angle ``PIT_ANGLE`` ringed by a raised lip ``RIM`` high."""
    return (1.0 - PIT_DEPTH * np.clip(1.0 - theta / PIT_ANGLE, 0.0, None)
            + RIM * np.exp(-((theta - 1.3 * PIT_ANGLE) / (0.4 * PIT_ANGLE)) ** 2))


def distance_to_pitted_sphere(p: np.ndarray, steps: int = 200_000) -> np.ndarray:
    """Distance of ``p (K, 3)`` to the exact pitted sphere (a surface of revolution about
    :data:`PIT_AXIS`): the nearest point lies in ``p``'s meridian half-plane, so it is the
    nearest of the profile ``pit_radius(theta) (cos theta, sin theta)`` sampled every
    ``pi / steps`` (at most 5e-5 apart along the profile, so the distance is over by at
    most 2.5e-5), found by a k-d tree of the samples."""
    from scipy.spatial import cKDTree

    h = p @ PIT_AXIS
    q = np.stack([h, np.linalg.norm(p - np.outer(h, PIT_AXIS), axis=1)], axis=1)
    theta = np.linspace(0.0, np.pi, steps + 1)
    profile = np.stack([np.cos(theta), np.sin(theta)], axis=1) * pit_radius(theta)[:, None]
    return cKDTree(profile).query(q)[0]


def _pitted_sphere_fit():
    """A fake base fit as :func:`_bumpy_sphere_fit`: the unit sphere's atlas is the base, a
    web across the mouth of a pit too deep for the detail's offsets (``OFFSET_LIMIT``)
    whose lip pushes the detail outward."""
    ico = trimesh.creation.icosphere(subdivisions=6)
    unit = ico.vertices / np.linalg.norm(ico.vertices, axis=1, keepdims=True)
    vertices = unit * pit_radius(np.arccos(np.clip(unit @ PIT_AXIS, -1.0, 1.0)))[:, None]
    faces = np.asarray(ico.faces, np.int64)
    fit, _ = _bumpy_sphere_fit()
    scan = make_scan("pit", vertices, faces=faces, source={"name": "pit"})
    return replace(fit, surface=ScanSurface(vertices, faces, "mesh", 1)), scan


def _farthest(atlas, tiles, resolution: int, diagonal: float) -> float:
    """The largest distance over ``diagonal`` of the drawn mesh from the exact pitted
    sphere, at every triangle's corners, edge midpoints and centroid (the same points
    whatever order the patches come in)."""
    mesh = tessellate_atlas(atlas, resolution, tiles, kernel="numpy")
    x = np.frombuffer(mesh.positions, np.float32).reshape(-1, 3).astype(float)
    tri = x[np.frombuffer(mesh.indices, np.uint32).reshape(-1, 3).astype(np.int64)]
    weights = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.5, 0.5, 0], [0, 0.5, 0.5],
                        [0.5, 0, 0.5], [1 / 3, 1 / 3, 1 / 3]])
    p = np.einsum("kc,tcd->tkd", weights, tri).reshape(-1, 3)
    return float(distance_to_pitted_sphere(p).max()) / diagonal


def test_far_drawn_nodes_are_pulled_toward_the_scan_not_pushed_away(monkeypatch):
    """Where the base is a web across a pit's mouth, the lip's samples push the detail
    outward and nothing inside the pit holds it: without the far nodes' rows
    (``far_node_rows``) the finest drawn mesh lies farther from the exact surface than the
    base does; with them it lies nearer."""
    fit, scan = _pitted_sphere_fit()
    diagonal = float(np.linalg.norm(np.ptp(scan.points, axis=0)))
    found = {}
    for weight in (0.0, atlas_detail.PULL_WEIGHT):
        monkeypatch.setattr(atlas_detail, "PULL_WEIGHT", weight)
        det = atlas_detail.fit_atlas_detail(fit, scan, levels=2, spans=4)
        found[weight] = _farthest(det.atlas, det.detail_up_to(1), det.levels[1]["resolution"],
                                  diagonal)
    base = _farthest(det.atlas, None, det.levels[1]["resolution"], diagonal)
    assert base > 0.01  # the web: its middle is over 1 % of the diagonal off the pit
    # pushed out without the rows (0.0310 against the base's 0.0255 of the diagonal)
    assert found[0.0] > 1.15 * base, (found, base)
    assert found[atlas_detail.PULL_WEIGHT] < base, (found, base)  # and nearer with them
    # a node is pulled only past pull_reach: past the web's own distance, none is
    det = atlas_detail.fit_atlas_detail(fit, scan, levels=2, spans=4, pull_reach=0.05)
    beyond = _farthest(det.atlas, det.detail_up_to(1), det.levels[1]["resolution"], diagonal)
    assert beyond > 1.15 * base, (beyond, base)


def test_drawn_model_and_node_frames_on_threads_equal_one_thread(fitted, monkeypatch):
    """node_frames, DrawnModel.feet and DrawnModel.of run their chunks on one thread per
    core (atlas.threads.on_threads); each chunk writes its own rows, so many small chunks on
    four threads give the numbers of one thread, bit for bit."""
    fit, scan, det = fitted
    atlas = det.atlas
    samples = _bump_samples(fit, atlas, 11, 2500)
    r = det.levels[1]["resolution"]
    F = len(atlas.quads)
    f = np.repeat(np.arange(F), r * r)
    a = np.tile(np.repeat(np.arange(r), r), F)
    b = np.tile(np.arange(r), F * r)
    made = {}
    for cores in (1, 4):
        monkeypatch.setattr(os, "sched_getaffinity", lambda pid, cores=cores: set(range(cores)),
                            raising=False)  # the cores it may run on (fitting.cores)
        made[cores] = (atlas_detail.node_frames(atlas, r, f, a, b, chunk=333),
                       atlas_detail.DrawnModel.of(atlas, samples, r, chunk=97))
    (frames_1, model_1), (frames_4, model_4) = made[1], made[4]
    for x, y in zip(frames_1, frames_4, strict=True):
        np.testing.assert_array_equal(x, y)
    for name in ("u", "v", "weight", "target", "node", "node_patch", "node_u", "node_v"):
        np.testing.assert_array_equal(getattr(model_1, name), getattr(model_4, name))


# ------------------------------------------------------------------ drawn cells
CAP = 0.6  # the capped scan has no point above z = CAP


def _capped_sphere_fit():
    """The bumpy sphere as a CLOUD without its cap ``z > CAP`` (a part the scan lacks),
    fitted on the plain sphere atlas, whose cap then lies over no scan point (its stand-in
    surface, as a cloud's Poisson surface, is the whole icosphere)."""
    fit, mesh_scan = _bumpy_sphere_fit()
    rng = np.random.default_rng(2)
    # a cloud: points of the bumpy sphere's triangles, none above the cap's plane
    tri = mesh_scan.points[mesh_scan.faces]
    w = rng.dirichlet(np.ones(3), size=len(tri) * 3)
    points = np.einsum("nk,nkc->nc", w, np.repeat(tri, 3, axis=0))
    points = points[points[:, 2] <= CAP]
    scan = make_scan("capped", points, source={"name": "capped"})
    surface = ScanSurface(mesh_scan.points, mesh_scan.faces, "cloud", 1)
    return replace(fit, surface=surface), scan


@pytest.fixture(scope="module")
def capped():
    fit, scan = _capped_sphere_fit()
    return scan, atlas_detail.fit_atlas_detail(fit, scan, levels=2, spans=4, pack_bytes=1000)


def _cell_triangles(mesh, F, r):
    """The drawn mesh's triangles as ``(F, r - 1, r - 1, 2, 3)`` vertex indices (whole grids)."""
    return np.frombuffer(mesh.indices, np.uint32).reshape(F, r - 1, r - 1, 2, 3)


def test_levels_stop_drawing_the_cells_over_no_scan_and_only_those(capped):
    """Read back from the packs, each level's walls masks leave out cells of its drawn grid
    that reach farther than DRAWN_REACH of the diagonal from the scan (checked on the
    lattice of FINEST_LATTICE steps a side, which holds the fitter's coarser ones, with a
    KD-tree of the points), all of them over the missing cap and every cell deep inside it;
    every scan point's distance to the drawn mesh is what it was without the masks, but
    for HANDOVER_SLACK of the reach (no cell a scan point is drawn by goes unless another
    draws it as near); the rest of the mesh is the mesh drawn without masks, open only
    around the cells left out
    (no edge of three triangles)."""
    from scipy.spatial import cKDTree

    from fitter.fitting.atlas.measure import signed_point_mesh_distance

    scan, det = capped
    F = len(det.atlas.quads)
    points = np.asarray(scan.points)
    reach = atlas_detail.DRAWN_REACH * np.linalg.norm(np.ptp(points, axis=0))
    tree = cKDTree(points)
    read: dict = {}
    for p in det.tree["packs"]:
        data = det.files[pack_name(p["level"], p["group"])]
        assert data[4] == 5  # walls masks: version 5
        level, tiles = read_pack(data, det.atlas)
        for f, got in tiles.items():
            read.setdefault(level, {})[f] = got
    assert det.tree["format_version"] == 5
    n = atlas_detail.FINEST_LATTICE  # holds the fitter's lattices (4, 8, 16, 32 steps)
    bary = np.array([(a, b, n - a - b) for a in range(n + 1) for b in range(n + 1 - a)]) / n
    for k, row in enumerate(det.tree["levels"]):
        r = row["resolution"]
        upto = {}
        for j in range(k + 1):
            for f, got in read.get(j, {}).items():
                upto.setdefault(f, []).extend(got)
        walled = tessellate_atlas(det.atlas, r, upto, kernel="python")
        plain = tessellate_atlas(det.atlas, r, {f: [replace(t, walls=None) for t in ts]
                                                for f, ts in upto.items()}, kernel="numpy")
        assert walled.positions.tobytes() == plain.positions.tobytes()
        cells = _cell_triangles(plain, F, r).reshape(-1, 2, 3)
        kept = {tuple(t) for t in np.frombuffer(walled.indices, np.uint32).reshape(-1, 3)[::2]}
        left_out = np.array([tuple(c[0]) not in kept for c in cells])
        assert row["walls"] == left_out.sum() > 0
        assert len(walled.indices) == 6 * (len(cells) - left_out.sum())
        x = np.frombuffer(plain.positions, np.float32).reshape(-1, 3).astype(float)
        reaches = np.zeros(len(cells), bool)
        for t in range(2):
            d, _ = tree.query(np.einsum("sk,ckd->csd", bary, x[cells[:, t]]).reshape(-1, 3))
            reaches |= (d.reshape(len(cells), -1) > reach).any(axis=1)
        assert reaches[left_out].all()
        centre = x[cells[:, 0, 0]] * 0.5 + x[cells[:, 1, 2]] * 0.5
        assert left_out[centre[:, 2] > 0.9].all()  # deep in the cap: nothing drawn
        # only cells over the missing cap: each reaches over it (a rim cell whose holders
        # keep the issue's bounds goes too, its centre just under the rim)
        assert x[cells[left_out]][..., 2].max(axis=(1, 2)).min() > CAP
        faces = [np.frombuffer(m.indices, np.uint32).reshape(-1, 3).astype(np.int64)
                 for m in (walled, plain)]
        before, after = (np.abs(signed_point_mesh_distance(points, x, f)[0]) for f in faces)
        # those within the reach keep their distance within the hand-over's slack, or the
        # bound of the issue's two they met (HANDOVER_WITHIN of the reach, or the reach)
        near = before <= reach
        half = atlas_detail.HANDOVER_WITHIN * reach
        bound = np.maximum(before + atlas_detail.HANDOVER_SLACK * reach,
                           np.where(before <= half, half, reach))
        assert np.all(after[near] <= bound[near])
        counts, _ = _edge_counts(walled)
        assert counts.max() == 2 and counts.min() == 1


def _fin_mesh():
    """One patch of 3 x 3 nodes (x, y, z): its cells (0, j) flat on z = 0 over x in [0,
    0.5], its cells (1, j) a fin standing on the flat's edge x = 0.5, up to z = 0.5, cell
    (i, j) over y in [j / 2, (j + 1) / 2]; the client's cut (:func:`grid_triangles`)."""
    a, b = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
    x = np.minimum(a, 1) * 0.5
    z = np.where(a == 2, 0.5, 0.0)
    vertices = np.stack([x, b * 0.5, z], axis=-1).reshape(-1, 3).astype(float)
    return vertices, atlas_detail.grid_triangles(1, 3)


def _fin_distance(points):
    """Each point's distance to the fin mesh's flat (``x in [0, 0.5]``, ``z = 0``) and to
    its fin (``x = 0.5``, ``z in [0, 0.5]``), both over ``y in [0, 1]``: rectangles, by
    clamping."""
    x, y, z = points.T
    dy = y - np.clip(y, 0.0, 1.0)
    flat = np.sqrt((x - np.clip(x, 0.0, 0.5)) ** 2 + dy ** 2 + z ** 2)
    fin = np.sqrt((x - 0.5) ** 2 + dy ** 2 + (z - np.clip(z, 0.0, 0.5)) ** 2)
    return flat, fin


def test_far_cells_hands_a_fins_root_over_to_the_surface_it_stands_on():
    """A fin standing on a scanned sheet (the 15-scan Happy Buddha's level 0: a web across a
    gap, 1.1 % of the diagonal off the scan at its far end) is left out where the scan
    points whose closest drawn point lies on its root are drawn nearly as near by the sheet
    (within HANDOVER_SLACK of the reach), and stays where they are not; the sheet, drawn
    by its points, stays. The distances are the rectangles' (not the fitter's)."""
    from scipy.spatial import cKDTree

    vertices, faces = _fin_mesh()
    g = np.arange(0.0, 1.0001, 0.01)
    sheet = np.stack(np.meshgrid(g * 0.5, g, [0.0], indexing="ij"), -1).reshape(-1, 3)
    y = np.linspace(0.05, 0.45, 9)
    low = np.stack([np.full(9, 0.5005), y, np.full(9, 1e-4)], 1)  # by the fin's first cell
    high = np.stack([np.full(9, 0.5005), y + 0.5, np.full(9, 8e-3)], 1)  # by its second
    points = np.concatenate([sheet, low, high])
    reach = atlas_detail.DRAWN_REACH * np.linalg.norm(np.ptp(points, axis=0))
    slack = atlas_detail.HANDOVER_SLACK * reach
    flat, fin = _fin_distance(points)
    # the fin cells hold the low and high points (closer to the fin than to the flat); the
    # low ones lose less than the slack to the flat alone, the high ones more
    assert np.all(fin[-18:] < flat[-18:]) and np.all(flat[-18:-9] - fin[-18:-9] < slack)
    assert np.all(flat[-9:] - fin[-9:] > slack) and np.all(fin[-18:] < reach)
    tree = cKDTree(points)
    far = atlas_detail.far_cells(vertices, faces, 1, 3, points,
                                 lambda x: tree.query(x)[0], reach)
    assert far.tolist() == [[[False, False], [True, False]]]
    # without the hand-over (no slack, no bound), every fin cell holding a point stays
    far = atlas_detail.far_cells(vertices, faces, 1, 3, points,
                                 lambda x: tree.query(x)[0], reach, slack=-1.0, within=None)
    assert not far.any()


@pytest.mark.parametrize("second", [(0.5005, 4e-3), (0.506, 8e-3)])
def test_far_cells_hands_a_fin_over_where_its_holders_keep_the_issues_bounds(second):
    """A fin cell whose holders lose more than the slack still goes where each stays on the
    same side of the issue's bounds: within HANDOVER_WITHIN of the reach (0.5 % of the
    diagonal) if it was (points 4e-3 over the sheet, 5e-4 from the fin: 4e-3 from the
    sheet), else within the reach (points 6e-3 from the fin, 8e-3 over the sheet: 1e-2
    from it, where the reach is 1.1e-2: the 15-scan Buddha's level 0 kept a cell 1.035 %
    off for one point that went from 0.56 to 0.89 %)."""
    from scipy.spatial import cKDTree

    vertices, faces = _fin_mesh()
    g = np.arange(0.0, 1.0001, 0.01)
    sheet = np.stack(np.meshgrid(g * 0.5, g, [0.0], indexing="ij"), -1).reshape(-1, 3)
    y = np.linspace(0.05, 0.45, 9)
    low = np.stack([np.full(9, 0.5005), y, np.full(9, 1e-4)], 1)
    high = np.stack([np.full(9, second[0]), y + 0.5, np.full(9, second[1])], 1)
    points = np.concatenate([sheet, low, high])
    diagonal = np.linalg.norm(np.ptp(points, axis=0))
    reach = atlas_detail.DRAWN_REACH * diagonal
    flat, fin = _fin_distance(points)
    gained = flat[-9:] - fin[-9:]
    assert np.all(fin[-9:] < flat[-9:]) and np.all(gained > atlas_detail.HANDOVER_SLACK * reach)
    within = atlas_detail.HANDOVER_WITHIN * reach
    assert (np.all(flat[-9:] <= within) if second[0] < 0.501
            else np.all((fin[-9:] > within) & (flat[-9:] <= reach)))
    tree = cKDTree(points)
    far = atlas_detail.far_cells(vertices, faces, 1, 3, points,
                                 lambda x: tree.query(x)[0], reach)
    assert far.tolist() == [[[False, False], [True, True]]]
    far = atlas_detail.far_cells(vertices, faces, 1, 3, points,
                                 lambda x: tree.query(x)[0], reach, within=None)
    assert far.tolist() == [[[False, False], [True, False]]]  # the slack alone keeps it


def test_far_cells_finds_a_cell_reaching_far_only_between_its_lattice_points():
    """A flat cell whose scan lies at the points of its triangles' first lattice
    (CELL_LATTICE steps a side) only: it reaches farther than the reach between them (at
    the small triangles' centres, by a lattice 8 times finer: the reference), and far_cells
    leaves it out (no scan point lies on it: ``points`` holds none); within the reach
    everywhere (the reach a little above its largest distance) it stays."""
    from scipy.spatial import cKDTree

    vertices, faces = _fin_mesh()
    vertices[:, 2] = 0.0  # all flat: x in [0, 0.5], y in [0, 1]
    cell = faces[:2]  # cell (0, 0): x in [0, 0.5], y in [0, 0.5]
    n = atlas_detail.CELL_LATTICE
    coarse = atlas_detail.lattice_weights(n)
    scan = np.concatenate([coarse @ vertices[t] for t in cell])
    tree = cKDTree(scan)
    fine = np.concatenate([atlas_detail.lattice_weights(8 * n) @ vertices[t] for t in cell])
    largest = tree.query(fine)[0].max()
    assert tree.query(scan)[0].max() == 0.0 and largest > 0.05
    one = (vertices, cell, 1, 2, np.zeros((0, 3)), lambda x: tree.query(x)[0])
    assert atlas_detail.far_cells(*one, reach=0.9 * largest).tolist() == [[[True]]]
    assert atlas_detail.far_cells(*one, reach=1.01 * largest).tolist() == [[[False]]]


def _edge_counts(mesh):
    tri = np.frombuffer(mesh.indices, np.uint32).reshape(-1, 3).astype(np.int64)
    edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return counts, None


def test_a_closed_scan_has_no_walls_masks_and_version_4_packs(fitted):
    """The bumpy sphere's mesh is within reach everywhere: no level leaves a cell out, and
    every pack is version 4 (the bytes of before)."""
    _, _, det = fitted
    assert det.tree["format_version"] == 4
    assert all(data[4] == 4 for data in det.files.values())
    assert all("walls" not in row for row in det.tree["levels"])
    assert all(t.walls is None for level in det.tiles for ts in level.values() for t in ts)


def test_a_mesh_scan_leaves_no_cell_out_even_without_its_cap(monkeypatch):
    """DRAWN_MESHES is off: a mesh's triangles say where its surface ends, so a mesh with a
    part missing (the capped bumpy sphere as a mesh) is drawn whole, version 4 packs; with
    it on, the cap's cells go (measured against the mesh's triangles)."""
    fit, mesh_scan = _bumpy_sphere_fit()
    faces = mesh_scan.faces[mesh_scan.points[mesh_scan.faces][:, :, 2].max(axis=1) <= CAP]
    used, faces = np.unique(faces, return_inverse=True)  # the vertices the cap left
    scan = make_scan("capped mesh", mesh_scan.points[used], faces=faces.reshape(-1, 3),
                     source={"name": "capped mesh"})
    det = atlas_detail.fit_atlas_detail(fit, scan, levels=1, spans=4, pack_bytes=1000)
    assert not atlas_detail.DRAWN_MESHES
    assert det.tree["format_version"] == 4 and all(d[4] == 4 for d in det.files.values())
    assert all(t.walls is None for level in det.tiles for ts in level.values() for t in ts)
    monkeypatch.setattr(atlas_detail, "DRAWN_MESHES", True)
    det = atlas_detail.fit_atlas_detail(fit, scan, levels=1, spans=4, pack_bytes=1000)
    assert det.tree["format_version"] == 5 and det.tree["levels"][0]["walls"] > 0


# ------------------------------------------------------------------ folds
def test_grid_triangles_are_the_clients_grid_triangles():
    """``grid_triangles`` numbers every patch's drawn triangles as the client cuts them
    (``client_py.tessellate.grid_indices`` over one patch's ``r x r`` grid), patch after
    patch at ``f r²``."""
    from client_py.tessellate import grid_indices

    for r in (2, 5, 9):
        one = np.asarray(grid_indices(r, r, kernel="python"), np.int64).reshape(-1, 3)
        expected = np.concatenate([one + f * r * r for f in range(3)])
        assert np.array_equal(atlas_detail.grid_triangles(3, r), expected)
        f, a, b = atlas_detail.all_nodes(3, r)
        assert np.array_equal((f * r + a) * r + b, np.arange(3 * r * r))


def _facing(before, step, s):
    """``N(s) . N(0)`` of the triangles ``before + s step`` by their cross products."""
    n0 = np.cross(before[:, 1] - before[:, 0], before[:, 2] - before[:, 0])
    x = before + s[:, None, None] * step
    return np.einsum("tc,tc->t", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), n0), \
        np.einsum("tc,tc->t", n0, n0)


def test_fold_shrink_is_the_first_share_that_keeps_the_area():
    """Against a dense scan of ``s`` over ``[0, 1]`` (10,001 steps, cross products): where
    the whole step leaves the triangle ``keep`` of its facing area, 1 (the facing may dip
    below it on the way: the drawn mesh is the end, not the path); else the first ``s``
    where it falls to that, found to the scan's step, and the facing there is
    ``keep |N(0)|²``."""
    rng = np.random.default_rng(4)
    before = rng.normal(size=(400, 3, 3))
    step = 2.0 * rng.normal(size=(400, 3, 3))
    keep = 0.1
    s = atlas_detail.fold_shrink(before, step, keep)
    grid = np.linspace(0.0, 1.0, 10_001)
    facing = np.stack([_facing(before, step, np.full(400, t))[0] for t in grid], axis=1)
    _, alpha = _facing(before, step, s)
    low = facing < keep * alpha[:, None]
    kept = ~low[:, -1]
    assert kept.any() and (~kept).any()  # both kinds are tested
    assert np.all(s[kept] == 1.0)
    first = grid[np.argmax(low, axis=1)]
    assert np.allclose(s[~kept], first[~kept], atol=2e-4)
    at, _ = _facing(before, step, s)
    assert np.allclose(at[~kept], keep * alpha[~kept], rtol=1e-6, atol=1e-9 * alpha.max())


def test_merged_rows_sort_by_patch_and_keep_each_rows_weight():
    one = atlas_detail.PullRows(np.array([0, 2]), np.array([0.1, 0.2]), np.zeros(2),
                                np.array([1.0, 2.0]), np.array([0, 1, 1, 2]), 3.0)
    two = atlas_detail.PullRows(np.array([1, 2]), np.array([0.3, 0.4]), np.zeros(2),
                                np.array([3.0, 4.0]), np.array([0, 0, 1, 2]), 5.0)
    both = atlas_detail.merged_rows(one, two)
    assert np.array_equal(both.patch, [0, 1, 2, 2])
    assert np.array_equal(both.target, [1.0, 3.0, 2.0, 4.0])
    assert np.array_equal(both.u, [0.1, 0.3, 0.2, 0.4])
    assert np.array_equal(both.weight, [3.0, 5.0, 3.0, 5.0])
    assert np.array_equal(both.offsets, [0, 1, 2, 4])
    assert atlas_detail.merged_rows(None, two) is two


def test_a_row_of_weight_two_is_that_row_twice():
    """``PullRows.weight`` per row: the normal equations (``_BatchSystem``, which every
    solve and the quantisation share) with a row weighing ``2`` are those with that row
    twice at weight 1 (the sum of squares)."""
    rng = np.random.default_rng(2)
    count = 40
    patch = np.repeat([0, 1], count // 2)
    samples = atlas_detail.AtlasSamples(
        patch, rng.random(count), rng.random(count), rng.normal(size=count),
        np.zeros(count), np.array([0, count // 2, count]), np.ones(count), np.ones(count),
        np.ones(count))
    at, u, v, target = np.array([0, 0, 1]), rng.random(3), rng.random(3), rng.normal(size=3)
    once = atlas_detail.PullRows(at, u, v, target, np.array([0, 2, 3]),
                                 np.array([1.0, 2.0, 1.0]))
    twice = atlas_detail.merged_rows(
        atlas_detail.PullRows(at, u, v, target, np.array([0, 2, 3]), 1.0),
        atlas_detail.PullRows(at[1:2], u[1:2], v[1:2], target[1:2], np.array([0, 1, 1]), 1.0))
    found = []
    for rows in (once, twice):
        system = atlas_detail._BatchSystem(samples, samples.s, 0, 2, None, None, None, rows)
        M, rhs, _ = system.normal(0)
        found.append((M.toarray(), rhs))
    assert np.allclose(found[0][0], found[1][0]) and np.allclose(found[0][1], found[1][1])
    # and the rows count: without them the equations differ
    plain = atlas_detail._BatchSystem(samples, samples.s, 0, 2, None, None, None, None)
    assert not np.allclose(plain.normal(0)[0].toarray(), found[0][0])


def _ball_in_a_cube_fit(radius: float):
    """A fake base fit: the cube ``[-1, 1]³`` (6 flat patches meeting at right angles, C0
    creases, as the real bases' patch borders) and, as the scan, a ball of ``radius``:
    beyond the faces' middles and under the corners, so the detail drawn at a corner moves
    along the corner's averaged direction (toward the cube's centre) farther than a cell."""
    ico = trimesh.creation.icosphere(subdivisions=5)
    return _fake_fit(sphere_atlas(1, cube=True), "ball", np.asarray(ico.vertices) * radius,
                     np.asarray(ico.faces, np.int64))


def _drawn(atlas, resolution, tiles):
    mesh = tessellate_atlas(atlas, resolution, tiles, kernel="numpy")
    return (np.frombuffer(mesh.positions, np.float32).reshape(-1, 3).astype(float),
            np.frombuffer(mesh.indices, np.uint32).reshape(-1, 3).astype(np.int64))


@pytest.mark.parametrize("radius", [1.0, 1.3])
def test_fold_rows_keep_the_drawn_level_from_turning_over_at_creases(radius, monkeypatch):
    """A ball in a cube: without the fold rows (``FOLD_PASSES`` 0), level 0 drawn by the
    client (``tessellate_atlas``) has triangles at the cube's corners facing against the
    base's (``bench.pleats.turned_share``); with them none, the radial error of the drawn
    vertices within 30 % of the unconstrained fit's (radius 1.3: the ball's sides,
    2 % more; 1.0: the ball far under the corners, where a fold-free mesh cannot follow).
    The rows weigh 10 here: a corner where three faces meet at right angles is the worst
    case, and at the default :data:`FOLD_WEIGHT` (1, chosen on the scans: Lucy's RMS) the
    data still turn half of them (docs/benchmarks.md, "Pleats")."""
    from bench.pleats import turned_share

    fit, scan = _ball_in_a_cube_fit(radius)
    monkeypatch.setattr(atlas_detail, "FOLD_WEIGHT", 10.0)
    found = {}
    for passes in (0, atlas_detail.FOLD_PASSES):
        monkeypatch.setattr(atlas_detail, "FOLD_PASSES", passes)
        det = atlas_detail.fit_atlas_detail(fit, scan, levels=1, spans=4)
        r = det.levels[0]["resolution"]
        level = _drawn(det.atlas, r, det.detail_up_to(0))
        error = np.linalg.norm(level[0], axis=1) - radius
        found[passes] = (turned_share(_drawn(det.atlas, r, None), level),
                         float(np.sqrt(np.mean(error ** 2))))
    assert atlas_detail.FOLD_PASSES > 0
    assert found[0][0] > 0.004, found  # the corners turn over without the rows
    assert found[atlas_detail.FOLD_PASSES][0] == 0.0, found
    assert found[atlas_detail.FOLD_PASSES][1] < 1.3 * found[0][1], found


def test_fold_rows_made_a_few_patches_at_a_time_are_those_made_at_once(monkeypatch):
    """``fold_node_rows`` works a chunk of patches at a time on threads (``CHUNK`` nodes):
    with one patch a chunk, the same rows to the bit as with every patch in one chunk, and
    rows there are (random coefficients large enough to turn triangles over)."""
    fit, _ = _ball_in_a_cube_fit(1.3)
    atlas = fit.atlas
    spans, n = 4, 4 + atlas_detail.DEGREE
    nodes = atlas_detail.level_nodes(atlas, [], 0, spans)
    c = np.random.default_rng(7).normal(scale=0.4, size=(len(atlas.quads), n, n))
    monkeypatch.setattr(atlas_detail, "CHUNK", 10 ** 9)
    whole = atlas_detail.fold_node_rows(nodes, c, 0, spans, 1.0)
    monkeypatch.setattr(atlas_detail, "CHUNK", 1)
    parts = atlas_detail.fold_node_rows(nodes, c, 0, spans, 1.0)
    assert len(whole.patch) > 20 and len(np.unique(whole.patch)) > 1
    for name in ("patch", "u", "v", "target", "offsets"):
        assert getattr(whole, name).tobytes() == getattr(parts, name).tobytes(), name


def test_groups_leave_room_for_walls_masks():
    """A level-3 pack of 200 patches holds 1.28 M coefficients (within the 2^21 values a
    pack may hold): one group; with walls masks of 16 cells a side it would hold 4.56 M, so
    the ranges are split until each pack, masks counted, is within the bound."""
    from client_py.atlas_detail import MAX_PACK_VALUES, pack_capacity

    finest = {f: [(None, b"x" * 40, 0)] for f in range(200)}
    deg, spans = atlas_detail.DEGREE, atlas_detail.SPANS
    plain = atlas_detail._groups(finest, 200, 10**9, 3, spans)
    walled = atlas_detail._groups(finest, 200, 10**9, 3, spans, 16)
    assert plain == [(0, 200)]
    assert len(walled) > 1 and sum(n for _, n in walled) == 200
    assert all(pack_capacity(3, n, deg, spans, walls=16) <= MAX_PACK_VALUES for _, n in walled)


def test_groups_are_boxes_of_the_patches_k_d_tree_and_small_enough_to_draw():
    """Patch centres in a long box (8 x 1 x 1): spatial_order's halves, which _groups cuts
    along, are compact boxes (a sixteenth of the patches within 0.75 of its middle, the
    half-diagonal of a 0.5 x 1 x 1 box, where the Morton curve's runs reach up to 2); a
    group holds at most
    ``most`` patches and its pack's bytes; and the viewer's budget holds at least four
    groups at their finest level (atlas-layer.js's MAX_VERTICES, GROUP_VERTICES)."""
    import re

    rng = np.random.default_rng(5)
    centres = rng.random((1024, 3)) * [8.0, 1.0, 1.0]
    order = atlas_detail.spatial_order(centres)
    assert sorted(order.tolist()) == list(range(1024))
    finest = {f: [(None, b"x" * 40, 0)] for f in range(1024)}
    groups = atlas_detail._groups(finest, 1024, 10**9, 0, atlas_detail.SPANS, most=64)
    assert groups == [(64 * k, 64) for k in range(16)]

    def radius(run):
        return np.linalg.norm(run - 0.5 * (run.min(axis=0) + run.max(axis=0)), axis=1).max()

    assert max(radius(centres[order[f:f + n]]) for f, n in groups) < 0.75
    morton = atlas_detail.morton_order(centres)
    assert max(radius(centres[morton[f:f + n]]) for f, n in groups) > 1.5
    # where the bytes bind: 1024 patches of 18 coded bytes (40 less the tile's header and
    # CRC) in 1000-byte packs (28 of framing): 64 patches pass, 32 do not
    by_bytes = atlas_detail._groups(finest, 1024, 1000, 0, atlas_detail.SPANS)
    assert by_bytes == [(32 * k, 32) for k in range(32)]
    source = (Path(__file__).resolve().parents[1] / "web" / "src" / "atlas-layer.js").read_text()
    budget = int(re.search(r"export const MAX_VERTICES = (\d+);", source).group(1))
    assert 4 * atlas_detail.GROUP_VERTICES <= budget


def test_rounded_bounds_stay_bounds():
    """A group's sphere and a pack's geometric_error are written short, rounded up: never
    below what they bound (a value one double above a 3-digit number included), at most
    1 % above it; a lone point's sphere keeps its centre."""
    import math

    rng = np.random.default_rng(2)
    for x in rng.uniform(1, 10, 2000) * 10.0 ** rng.integers(-300, 300, 2000):
        for y in (float(x), float(f"{x:.3g}"), float(np.nextafter(float(f"{x:.3g}"), np.inf))):
            up = atlas_detail._rounded_up(y)
            assert y <= up <= y * 1.0101, (y, up)
    assert atlas_detail._rounded_up(0.0) == 0.0 and math.isnan(atlas_detail._rounded_up(math.nan))
    for _ in range(300):
        points = rng.normal(size=(20, 3)) * 10.0 ** rng.uniform(-4, 4) + rng.uniform(-1e5, 1e5, 3)
        reach = float(rng.uniform(0, 1))
        centre, radius = atlas_detail._bounding_sphere(points, reach)
        assert np.linalg.norm(points - centre, axis=1).max() + reach <= radius
    assert atlas_detail._bounding_sphere(np.array([[0.123456, 0, 0]]), 0.0) == (
        [0.123456, 0.0, 0.0], 0.0)


def test_the_fold_re_solve_of_the_changed_patches_is_the_full_re_solve(monkeypatch):
    """After the fold rows, ``_solve_level(again=..., changed=...)`` solves only the patches
    with new rows (and the interiors whose shared ring moved): its coefficients, the
    independent solve's and the data weights are those of solving every patch again, to
    the bit, and so are the packs (quantised with the batches' rows it leaves)."""
    ico = trimesh.creation.icosphere(subdivisions=5)
    fit, scan = _fake_fit(sphere_atlas(3, cube=True), "ball", np.asarray(ico.vertices) * 1.3,
                          np.asarray(ico.faces, np.int64))
    monkeypatch.setattr(atlas_detail, "FOLD_WEIGHT", 10.0)  # fold rows at both levels
    solve_level = atlas_detail._solve_level
    compared = []

    def both(*args, again=None, changed=None):
        reduced = solve_level(*args, again=again, changed=changed)
        if again is not None:
            full = solve_level(*args)
            for name in ("coefficients", "free", "weight", "shared"):
                assert np.array_equal(getattr(reduced, name), getattr(full, name)), name
            compared.append((int(changed.sum()), len(changed)))
        return reduced

    monkeypatch.setattr(atlas_detail, "_solve_level", both)
    reduced = atlas_detail.fit_atlas_detail(fit, scan, levels=2, spans=4)
    assert len(compared) == 2 and any(0 < c < F for c, F in compared), compared

    def full_only(*args, again=None, changed=None):
        return solve_level(*args)

    monkeypatch.setattr(atlas_detail, "_solve_level", full_only)
    full = atlas_detail.fit_atlas_detail(fit, scan, levels=2, spans=4)
    assert reduced.files == full.files and reduced.files


def test_a_level_solved_in_one_batch_per_core_gives_the_packs_of_one_batch(monkeypatch):
    """A level within one batch of ``BATCH_UNKNOWNS`` is solved and quantised in one batch
    per core (``_BatchSystem.per_batch``), with one ``lambda`` for the level (the ring's
    slots too): the packs of one batch, byte for byte, on 1 and 3 cores (3 batches of the
    24 patches). The cores are
    those the process may run on (its affinity mask, ``fitting.cores.usable_cores``), not
    the machine's."""
    fit, scan = _bumpy_sphere_fit()
    descent = atlas_detail.lattice_descent
    files, calls = {}, {}
    for cores in (1, 3):
        monkeypatch.setattr(os, "sched_getaffinity", lambda pid, cores=cores: set(range(cores)),
                            raising=False)  # the cores it may run on (fitting.cores)
        calls[cores] = 0

        def counted(*args, cores=cores):
            calls[cores] += 1
            return descent(*args)

        monkeypatch.setattr(atlas_detail, "lattice_descent", counted)
        files[cores] = atlas_detail.fit_atlas_detail(fit, scan, levels=2, spans=4).files
    # per level: each batch's interiors, the ring's slots once, each batch's interiors again
    assert calls == {1: 2 * (1 + 1 + 1), 3: 2 * (3 + 1 + 3)}
    assert files[1] == files[3] and files[1]


def test_the_detail_cross_product_is_numpys_to_the_bit():
    from fitter.fitting.atlas.detail import _cross

    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(1000, 3)) * 1e3, rng.normal(size=(1000, 3))
    for x, y in ((a, b), (a[:, None, :], b[None, :5, :]), (a[0], b), (a.astype(np.int64), b)):
        expected = np.cross(x, y)
        got = _cross(x, y)
        assert got.dtype == expected.dtype and np.array_equal(got, expected)


def test_the_border_ring_moves_on_a_mesh_only(monkeypatch):
    """The quantisation moves the shared border slots (``_ring_descent``) on the scan's own
    triangles; over a cloud's stand-in, whose webs span the gaps between its sheets, the
    ring stays rounded (module docstring, "Quantisation")."""
    moved = []
    descent = atlas_detail._ring_descent

    def counted(q, *args):
        out = descent(q, *args)
        moved.append(int(np.count_nonzero(out != q)))
        return out

    monkeypatch.setattr(atlas_detail, "_ring_descent", counted)
    fit, scan = _bumpy_sphere_fit()
    atlas_detail.fit_atlas_detail(fit, scan, levels=1, spans=4)
    assert len(moved) == 1 and moved[0] > 0
    fit, scan = _noisy_sphere_cloud(count=20_000)
    atlas_detail.fit_atlas_detail(fit, scan, levels=1, spans=4)
    assert len(moved) == 1
