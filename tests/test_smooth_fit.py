"""The smooth base's fit (fitter.fitting.atlas.smooth): its matrices against the client's own
evaluation, and a control mesh fitted to a known surface."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from client_py.smooth_base import smooth_atlas, smooth_base
from fitter.fitting.atlas.fit import base_resolution, grid_mesh
from fitter.fitting.atlas.measure import closest_points_on_mesh
from fitter.fitting.atlas.patches import control_points, index_table
from fitter.fitting.atlas.smooth import (
    STEP_OVER_RMS,
    control_bits,
    fit_control_mesh,
    sample_matrix,
    smooth_matrix,
)


def icosphere(subdivisions: int, radius: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    mesh = trimesh.creation.icosphere(subdivisions, radius)
    return np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64)


def test_smooth_matrix_is_the_clients_atlas_stage_by_stage():
    rng = np.random.default_rng(3)
    vertices, triangles = icosphere(1)
    vertices = vertices * (1 + 0.1 * rng.standard_normal((len(vertices), 1)))
    base = smooth_base(len(vertices), triangles.tolist())
    atlas = smooth_atlas(vertices.tolist(), triangles.tolist(), base)
    M = smooth_matrix(len(vertices), base)
    assert M.shape == (atlas.control_point_count, len(vertices))
    assert np.allclose(M @ vertices, control_points(atlas), atol=1e-12)


def test_sample_matrix_draws_the_patches_as_grid_mesh_does():
    vertices, triangles = icosphere(1)
    atlas = smooth_atlas(vertices.tolist(), triangles.tolist())
    B, faces = sample_matrix(index_table(atlas), atlas.control_point_count, 4)
    expected_vertices, expected_faces = grid_mesh(atlas, 4)
    assert np.allclose(B @ control_points(atlas), expected_vertices, atol=1e-12)
    assert np.array_equal(faces, expected_faces)


def test_fit_control_mesh_draws_a_sphere_from_a_coarse_control_mesh():
    # the control mesh starts on the sphere's inscribed polyhedron, whose drawn surface
    # shrinks inside it (Catmull-Clark averages); the fit must bring it onto the sphere
    vertices, triangles = icosphere(1, 2.0)
    rng = np.random.default_rng(0)
    points = rng.standard_normal((4000, 3))
    points *= 2.0 / np.linalg.norm(points, axis=1, keepdims=True)
    atlas0 = smooth_atlas(vertices.tolist(), triangles.tolist())
    before = np.abs(np.linalg.norm(grid_mesh(atlas0, 5)[0], axis=1) - 2.0)
    fitted, history = fit_control_mesh(points, vertices, triangles, rounds=4)
    after = np.abs(np.linalg.norm(grid_mesh(smooth_atlas(fitted.tolist(),
                                                        triangles.tolist()), 9)[0], axis=1) - 2.0)
    assert before.max() > 0.05  # the unfitted control mesh draws a smaller sphere
    assert after.max() < 0.015 and np.sqrt(np.mean(after ** 2)) < 0.004
    assert history[-1] < 0.2 * history[0]


def test_control_bits_take_the_fewest_with_a_step_within_the_rms():
    vertices = np.array([[0.0, 0, 0], [1023.0, 0, 0], [0, 1, 0]])
    assert control_bits(vertices, 1.0 / STEP_OVER_RMS) == 10  # 1023 / (2^10 - 1) = 1
    assert control_bits(vertices, 0.99 / STEP_OVER_RMS) == 11
    assert control_bits(vertices, 1e-9) == 16  # the most
    assert control_bits(vertices, 1e9) == 8  # the fewest


@pytest.mark.parametrize(("patches", "expected"), [(1, 9), (3125, 9), (3126, 5), (12_500, 5),
                                                   (12_501, 3), (60_000, 3)])
def test_base_resolution_keeps_the_base_within_its_triangles(patches, expected):
    # 2 F (r - 1)^2 <= 400,000 triangles, r - 1 halved from 8 down to 2
    assert base_resolution(1, patches) == expected


def test_a_smooth_base_bundle_is_read_and_drawn_as_any_atlas(tmp_path):
    """``--base smooth`` end to end: ``base.tsa`` is a version-6 control mesh whose derived
    atlas the manifest describes, and the drawn mesh (base and level 0, welded as a
    visitor's browser draws it) follows the bumpy sphere it was fitted to."""
    from client_py.atlas_format import read_atlas
    from client_py.atlas_mesh import tessellate_atlas
    from client_py.bundle import atlas_tiles
    from client_py.control_mesh import read_control_header
    from fitter.fitting.io.scan import make_scan, new_source
    from fitter.fitting.options import FitOptions
    from fitter.fitting.pipeline import fit_scan

    mesh = trimesh.creation.icosphere(4, 10.0)
    v = np.asarray(mesh.vertices)
    v = v * (1 + 0.03 * np.sin(3 * v[:, :1]) * np.cos(2 * v[:, 1:2]) / 10)
    scan = make_scan("bumpy", v, faces=np.asarray(mesh.faces),
                     source=new_source("bumpy", None, "array", compression=None, reader="array"))
    manifest = fit_scan(scan, tmp_path / "b", FitOptions(base="smooth", patches=300)).manifest
    data = (tmp_path / "b" / "base.tsa").read_bytes()
    head = read_control_header(data)
    atlas, _ = read_atlas(data)
    base = manifest["base"]
    assert base["kind"] == "atlas" and head["triangles"] == 100 and base["patches"] == 300
    assert head["version"] == 6
    assert len(atlas.quads) == 300 and base["vertices"] == len(atlas.vertices)
    assert base["border_edges"] == 0 and manifest["coverage"]["uncovered_points"] == 0
    spec = atlas_tiles(manifest)
    assert spec.base_resolution == base["resolution"]
    drawn = tessellate_atlas(atlas, base["resolution"])
    far = closest_points_on_mesh(np.asarray(drawn.positions, float).reshape(-1, 3), v,
                                 np.asarray(mesh.faces))[0]
    assert far.max() < 0.01 * 20  # the base of 100 control triangles: no fin past 1 % (0.67)
    assert manifest["stats"]["max_relative"] < 0.001  # level 0, every point (0.04 %)


def _sheet(n: int) -> tuple[np.ndarray, np.ndarray]:
    """A wavy ``n x n`` grid sheet over ``[0, 1]^2`` (an open border of ``4 (n - 1)`` edges)."""
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    points = np.stack([u, v, 0.05 * np.sin(6 * u) * np.cos(5 * v)], axis=-1).reshape(-1, 3)
    k = np.arange(n * n).reshape(n, n)
    a, b, c, d = k[:-1, :-1].ravel(), k[1:, :-1].ravel(), k[1:, 1:].ravel(), k[:-1, 1:].ravel()
    return points, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def test_border_weights_weigh_a_short_open_border_of_the_scans_own_mesh():
    """The open border's vertices get ``BORDER_WEIGHT``, the others 1; none for a closed
    surface, a cloud's stand-in, or a border of more than ``BORDER_SHARE`` of the control
    points (a range scan's ragged rim)."""
    from fitter.fitting.atlas.smooth import BORDER_SHARE, BORDER_WEIGHT, border_weights
    from fitter.fitting.atlas.surface import ScanSurface

    points, faces = _sheet(41)  # 160 border vertices of 1,681
    sheet = ScanSurface(points, faces, "mesh", 1)
    weights = border_weights(sheet, 4000)
    rim = np.zeros(len(points), bool)
    rim[np.unique(np.concatenate([np.arange(41), np.arange(41) * 41, np.arange(41) * 41 + 40,
                                  1640 + np.arange(41)]))] = True
    np.testing.assert_array_equal(weights, np.where(rim, BORDER_WEIGHT, 1.0))
    assert 160 <= BORDER_SHARE * 4000 / 2  # 250: weighted
    assert border_weights(sheet, 2000) is None  # 160 > 125
    assert border_weights(ScanSurface(points, faces, "poisson", 1), 4000) is None
    assert border_weights(ScanSurface(*icosphere(3), "mesh", 1), 4000) is None


def test_the_control_mesh_is_decimated_with_its_border_weighted(monkeypatch):
    """``fit_smooth_atlas`` hands :func:`border_weights` of the surface to the decimation:
    the scan's rim vertices weighted. (On Laurana the
    plain decimation kept 107 control edges of 318 along the cut base, the weighted 249;
    a synthetic rim is kept whole by either, so this checks the wiring.)"""
    from fitter.fitting.atlas import smooth
    from fitter.fitting.atlas.surface import ScanSurface, border_edges
    from fitter.fitting.io.scan import make_scan, new_source

    v, f = icosphere(4)
    keep = v[f][:, :, 2].min(axis=1) > -0.8  # a cut base: an open rim
    used = np.unique(f[keep])
    renumber = np.full(len(v), -1)
    renumber[used] = np.arange(len(used))
    v, f = v[used], renumber[f[keep]]
    seen = []
    real = smooth.decimate

    def recording(source, target, weights=None, *args, **kwargs):
        seen.append((source, target, weights))
        return real(source, target, weights, *args, **kwargs)

    monkeypatch.setattr(smooth, "decimate", recording)
    scan = make_scan("cut", v, faces=f,
                     source=new_source("cut", None, "array", compression=None, reader="array"))
    surface = ScanSurface(v, f, "mesh", 1)
    fit = smooth.fit_smooth_atlas(scan, byte_budget=4000, surface=surface, triangles=1200)
    source, target, weights = seen[0]
    np.testing.assert_array_equal(weights, smooth.border_weights(source, target))
    assert weights is not None and np.count_nonzero(weights > 1) == len(np.unique(
        border_edges(f)))
    assert len(seen) == 1 and fit.trials[0]["triangles"] <= 1200


def test_smooth_detail_reaches_farther_on_a_mesh_only():
    """A smooth base's detail on a mesh's own triangles: 2 spans, offsets up to
    ``SMOOTH_OFFSET_LIMIT``; on a cloud's Poisson stand-in: 1 span, the patches base's
    ``OFFSET_LIMIT`` (wider drew a point past 1 % of the diagonal on the 15-scan Buddha);
    and far drawn nodes pulled from the nearer ``SMOOTH_PULL_REACH`` on a mesh only."""
    from fitter.fitting.atlas.detail import OFFSET_LIMIT, PULL_REACH
    from fitter.fitting.atlas.smooth import SMOOTH_OFFSET_LIMIT, SMOOTH_PULL_REACH, smooth_detail
    from fitter.fitting.atlas.surface import ScanSurface

    v, f = icosphere(1)
    mesh = smooth_detail(ScanSurface(v, f, "mesh", 1))
    cloud = smooth_detail(ScanSurface(v, f, "poisson", 1))
    assert (mesh["spans"], mesh["offset_limit"]) == (2, SMOOTH_OFFSET_LIMIT)
    assert (cloud["spans"], cloud["offset_limit"]) == (1, OFFSET_LIMIT)
    assert SMOOTH_OFFSET_LIMIT > OFFSET_LIMIT and mesh["keep_order"] and cloud["keep_order"]
    assert (mesh["pull_reach"], cloud["pull_reach"]) == (SMOOTH_PULL_REACH, PULL_REACH)
    assert SMOOTH_PULL_REACH < PULL_REACH
