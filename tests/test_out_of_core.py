"""Out-of-core fitting (issue 16, ``fitter.fitting.stream``): streamed thinning against the
in-memory rule, every point's error against a direct dense measurement, the same bundle on
a Dask LocalCluster of 2 workers as in one process."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import numpy as np
import pytest

import fitter.fitting.stream as stream
from client_py import read_patch
from client_py.ply import write_points_ply
from fitter.fitting.error import deviations, error_stats
from fitter.fitting.examples import relief_scan
from fitter.fitting.io import load_scan, voxel_thin_indices
from fitter.fitting.io.ply import open_ply_stream
from fitter.fitting.io.points import PointStream
from fitter.fitting.io.scan import make_scan
from fitter.fitting.io.thin import VoxelGrid, VoxelSums, unique_inverse, voxel_size_for
from fitter.fitting.nurbs import PatchModel
from fitter.fitting.options import FitOptions
from fitter.fitting.parameterize import Projection
from fitter.fitting.pipeline import fit_scan

N_POINTS = 40_000
OPTIONS = dict(grid=(12, 12), samples=5_000, detail_levels=1, texture=False)


@pytest.fixture
def small_out_of_core(monkeypatch):
    """The out-of-core path for a 40,000-point scan: over 20,000 points, a working set of
    about 8,000, blocks of 6,000 points (several blocks, a ragged last one)."""
    monkeypatch.setattr(stream, "STREAM_ABOVE", 20_000)
    monkeypatch.setattr(stream, "WORKING_SET_POINTS", 8_000)
    monkeypatch.setattr(stream, "WORKING_SET_MOST", 32_000)
    monkeypatch.setattr(stream, "BLOCK_POINTS", 6_000)
    monkeypatch.setattr(stream, "VOXEL_SAMPLE", 10_000)


def _relief_ply(path: Path, n: int = N_POINTS, normals: bool = False) -> np.ndarray:
    points = relief_scan(n, seed=3).astype(np.float32)
    up = {"nx": np.zeros(n, np.float32), "ny": np.zeros(n, np.float32),
          "nz": np.ones(n, np.float32)}
    path.write_bytes(write_points_ply(points, properties=up if normals else None))
    return points.astype(np.float64)


def test_ply_stream_reads_what_the_loader_reads(tmp_path):
    points = _relief_ply(tmp_path / "cloud.ply", 5_000, normals=True)
    opened = open_ply_stream(tmp_path / "cloud.ply")
    assert opened is not None
    pstream, source, _ = opened
    assert pstream.count == 5_000 and pstream.has_normals
    got, normals = pstream.read(1_000, 2_500)
    np.testing.assert_array_equal(got, points[1_000:2_500])
    np.testing.assert_array_equal(normals[:, 2], 1.0)
    np.testing.assert_array_equal(pstream.take(np.array([0, 7, 4_999]))[0], points[[0, 7, 4_999]])
    np.testing.assert_array_equal(load_scan(tmp_path / "cloud.ply").points, points)
    pstream.read(0, 1)  # map it; a pickled stream leaves the map behind and reopens it
    again = pickle.loads(pickle.dumps(pstream))
    assert again._records is None
    np.testing.assert_array_equal(again.read(0, 10)[0], points[:10])
    assert source["reader"] == "ply-memmap-stream"


def test_blocks_cover_the_points_once():
    pstream = PointStream.from_arrays("a", np.zeros((10, 3)))
    assert pstream.blocks(4) == [(0, 4), (4, 8), (8, 10)]
    with pytest.raises(ValueError, match="size must be a positive number of points, got 0"):
        pstream.blocks(0)


def test_streamed_thinning_equals_voxel_thin_indices(monkeypatch):
    rng = np.random.default_rng(5)
    points = rng.uniform(0, 10, (30_000, 3)) * [1, 1, 0.1]
    monkeypatch.setattr(stream, "BLOCK_POINTS", 7_000)
    lo, hi = points.min(axis=0), points.max(axis=0)
    index, sums, kept = stream.thin_stream(PointStream.from_arrays("p", points), lo, hi, 0.37,
                                       stream.LocalBlocks(2))
    expected = voxel_thin_indices(points, 0.37)
    np.testing.assert_array_equal(kept, expected)
    assert sums.counts.sum() == len(points) and len(sums.keys) == len(expected)


def test_unique_inverse_and_merged_sums_are_numpy_unique_and_bincount():
    """The sums pass's sort-based ``unique_inverse`` and its merge of two blocks' sums by
    binary search give, to the last bit, what ``np.unique`` and one ``bincount`` over both
    blocks give (each voxel's sum ``(0 + first) + second``; a -0.0 sum becomes +0.0)."""
    rng = np.random.default_rng(9)
    keys = rng.integers(0, 5_000, 40_000)
    for got, expected in zip(unique_inverse(keys), np.unique(keys, return_inverse=True),
                             strict=True):
        np.testing.assert_array_equal(got, expected)
    big = np.array([2**61, 3, 2**61, 0])  # too large to pack with a position: np.unique
    np.testing.assert_array_equal(unique_inverse(big)[1], [2, 1, 2, 0])
    assert [len(x) for x in unique_inverse(np.empty(0, np.int64))] == [0, 0]
    parts = []
    for n in (3_000, 2_000):
        k = np.unique(rng.integers(0, 8_000, n))
        sums = rng.normal(size=(len(k), 3))
        sums[:5] = -0.0
        parts.append(VoxelSums(k, sums, rng.integers(1, 9, len(k))))
    merged = parts[0].merged(parts[1])
    keys, inverse = np.unique(np.concatenate([p.keys for p in parts]), return_inverse=True)
    both = np.concatenate([p.sums for p in parts])
    np.testing.assert_array_equal(merged.keys, keys)
    for k in range(3):
        expected = np.bincount(inverse, weights=both[:, k], minlength=len(keys))
        assert merged.sums[:, k].tobytes() == expected.tobytes()
    np.testing.assert_array_equal(merged.counts, np.bincount(
        inverse, weights=np.concatenate([p.counts for p in parts])).astype(np.int64))
    assert merged.merged(VoxelSums.empty()).keys.tolist() == keys.tolist()


def test_voxel_size_for_a_surface_hits_the_target():
    points = relief_scan(200_000, seed=1)
    lo, hi = points.min(axis=0), points.max(axis=0)
    size = voxel_size_for(points[::4], len(points), 20_000, lo, hi)
    occupied = len(voxel_thin_indices(points, size))
    assert 14_000 < occupied < 28_000
    with pytest.raises(ValueError, match="target must be a positive number of voxels"):
        voxel_size_for(points[::4], len(points), 0, lo, hi)


def test_voxel_grid_refuses_more_voxels_than_a_key_holds():
    with pytest.raises(ValueError, match="more than one int64 key holds"):
        VoxelGrid.over(np.zeros(3), np.full(3, 1.0), 1e-7)


def test_every_point_is_measured_against_the_decoded_base(tmp_path, small_out_of_core):
    points = _relief_ply(tmp_path / "cloud.ply")
    seen = []
    bundle = fit_scan(tmp_path / "cloud.ply", tmp_path / "b", FitOptions(**OPTIONS),
                      lambda stage, fraction, done=None: seen.append((stage, done)))
    m = bundle.manifest
    working = m["provenance"]["working_set"]
    assert m["provenance"]["points"] == N_POINTS
    assert working["points_before"] == N_POINTS and 4_000 < working["points_after"] < 16_000
    assert {"load", "error"} <= {stage for stage, done in seen if done is not None}
    # an independent measurement: every point against the decoded base.tsp, in one call
    model = PatchModel.from_surface(read_patch((bundle.path / "base.tsp").read_bytes()))
    transform = np.array(m["transform"])
    proj = Projection("plane", transform[:3, 3], transform[:3, :3].T.copy())
    local = proj.local(points)
    lo, hi = local[:, :2].min(axis=0), local[:, :2].max(axis=0)
    proj.lo, proj.hi = lo, hi
    u, v, _ = proj.to_uvh(points)
    dense = error_stats(deviations(model, local, u, v).d, m["stats"]["bbox_diagonal"], "mm")
    got = m["stats_all_points"]
    assert got["points"] == N_POINTS
    for key in ("rms", "mean", "max", "p95", "p99"):
        assert got[key] == pytest.approx(dense[key], rel=1e-4), key
    assert m["projection"]["coverage"] == 1.0 and m["stats"]["points"] == N_POINTS
    # the error report shows the working set
    assert (bundle.path / "error.ply").read_bytes().count(
        f"element vertex {working['points_after']}".encode())


def test_small_scans_keep_the_in_memory_path(tmp_path):
    _relief_ply(tmp_path / "cloud.ply", 5_000)
    m = fit_scan(tmp_path / "cloud.ply", tmp_path / "b", FitOptions(**OPTIONS)).manifest
    assert "working_set" not in m["provenance"] and m["stats"]["points"] == 5_000


def test_a_large_array_is_fitted_out_of_core(tmp_path, small_out_of_core):
    points = relief_scan(N_POINTS, seed=3)
    m = fit_scan(points, tmp_path / "b", FitOptions(**OPTIONS)).manifest
    assert m["provenance"]["points"] == N_POINTS and m["stats_all_points"]["points"] == N_POINTS


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file()}


def _without_clocks(manifest: bytes) -> dict:
    m = json.loads(manifest)
    m.pop("timings")
    m["provenance"]["working_set"].pop("seconds")
    return m


def test_a_dask_cluster_of_two_workers_writes_the_same_bundle(tmp_path, small_out_of_core):
    distributed = pytest.importorskip("distributed")
    _relief_ply(tmp_path / "cloud.ply")
    local = fit_scan(tmp_path / "cloud.ply", tmp_path / "local", FitOptions(**OPTIONS))
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        on_dask = fit_scan(tmp_path / "cloud.ply", tmp_path / "dask", FitOptions(**OPTIONS),
                           blocks=stream.DaskBlocks(client))
    a, b = _files(local.path), _files(on_dask.path)
    assert a.keys() == b.keys() and len(a) > 3
    for name in a:
        if name != "manifest.json":
            assert a[name] == b[name], name
    # the manifest differs only in the clocks (stage timings, the thinning's seconds)
    assert _without_clocks(a["manifest.json"]) == _without_clocks(b["manifest.json"])


def _bumpy_sphere(subdivisions: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """A closed, genus-0 mesh with relief: an icosphere of radius 50 whose radius swells
    by up to 4 along three waves (40,962 vertices at 6 subdivisions)."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    v = np.asarray(sphere.vertices)
    r = 50.0 + 4.0 * np.sin(5 * v[:, 0]) * np.cos(4 * v[:, 1]) + 2.0 * v[:, 2] ** 2
    return v * r[:, None], np.asarray(sphere.faces, np.int64)


def _drawn_distances(folder: Path, manifest: dict, points: np.ndarray, level: int) -> np.ndarray:
    """Every point's distance to the mesh client_py draws of the bundle at ``level``."""
    from client_py.bundle import tessellate_bundle
    from fitter.fitting.atlas.measure import point_mesh_distance

    mesh = tessellate_bundle(manifest, lambda name: (folder / name).read_bytes(), level,
                             kernel="numpy")
    return point_mesh_distance(points, np.frombuffer(mesh.positions, np.float32).reshape(-1, 3),
                               np.frombuffer(mesh.indices, np.uintc).reshape(-1, 3))


def _check_every_point(folder: Path, manifest: dict, points: np.ndarray) -> None:
    """The manifest's figures are those of EVERY original point against the drawn levels,
    not of the working set the atlas was fitted to."""
    stats = manifest["stats_all_points"]
    assert manifest["stats"] == stats and stats["points"] == len(points)
    assert manifest["provenance"]["points"] == len(points)
    diagonal = float(np.linalg.norm(np.ptp(points, axis=0)))
    assert stats["bbox_diagonal"] == pytest.approx(diagonal, rel=1e-12)
    levels = manifest["tiles"]["detail"]["levels"]
    for level, entry in ((-1, manifest["tiles"]["detail"]["base"]), (len(levels) - 1,
                                                                     levels[-1])):
        d = _drawn_distances(folder, manifest, points, level)
        assert entry["rms"] == pytest.approx(np.sqrt(np.mean(d ** 2)), rel=1e-4)
        assert entry["max"] == pytest.approx(d.max(), rel=1e-4)
    assert stats["rms"] == pytest.approx(np.sqrt(np.mean(d ** 2)), rel=1e-4)
    coverage = manifest["coverage"]
    assert coverage["points"] == len(points)
    assert coverage["within_0.5%"] == pytest.approx(np.mean(d <= 0.005 * diagonal), abs=1e-4)
    assert coverage["uncovered_points"] == np.sum(d > 0.01 * diagonal)


def test_a_large_closed_mesh_is_fitted_as_an_atlas_of_its_working_mesh(tmp_path,
                                                                       small_out_of_core):
    """A mesh over ``STREAM_ABOVE`` vertices is an atlas (it was a single height field, with
    ``--patches`` ignored): fitted to the mesh reduced to about ``WORKING_SET_POINTS``
    vertices, its figures of every original vertex."""
    vertices, faces = _bumpy_sphere()
    colours = np.clip(vertices[:, :3] * 2 + 128, 0, 255).astype(np.uint8)
    scan = make_scan("bumpy", vertices, faces=faces, colors=colours, units="mm",
                     source={"name": "bumpy"})
    working = stream.working_mesh(scan)
    assert 7_000 <= working.n_points <= 9_000 and len(working.faces) <= 16_000
    record = working.source["working_set"]
    assert record["points_before"] == len(vertices) and record["points_after"] == \
        working.n_points and record["triangles_before"] == len(faces)
    # a working vertex's colour is its nearest original vertex's
    from scipy.spatial import cKDTree
    _, nearest = cKDTree(vertices).query(working.points[:50])
    np.testing.assert_array_equal(working.colors[:50], colours[nearest])
    # within the reduction's error of the surface (far below the relief's 4 mm)
    from fitter.fitting.atlas.measure import point_mesh_distance
    assert point_mesh_distance(working.points, vertices, faces).max() < 0.5

    bundle = fit_scan(scan, tmp_path / "b", FitOptions(patches=60, texture=False))
    m = bundle.manifest
    assert m["format_version"] == 2 and m["base"]["kind"] == "atlas"
    assert m["base"]["border_edges"] == 0 and "atlas_refused" not in m
    assert m["provenance"]["working_set"]["points_after"] == working.n_points
    assert m["fit"]["surface"] == "mesh"
    # the detail is fitted to the scan's own vertices, its depth set by the scan's edges
    from fitter.fitting.atlas.fit import median_edge
    assert m["fit"]["detail"]["samples"] == len(vertices)
    assert m["fit"]["detail"]["spacing"] == pytest.approx(median_edge(vertices, faces), rel=1e-3)
    _check_every_point(bundle.path, m, vertices)
    assert m["coverage"]["uncovered_points"] == 0 and m["stats"]["rms_relative"] < 0.002


def test_a_large_closed_cloud_is_fitted_as_an_atlas_of_its_working_set(tmp_path,
                                                                       small_out_of_core):
    """A point cloud of a closed object over ``STREAM_ABOVE`` points (a binary PLY, streamed
    from its memory map) is an atlas of its voxel-thinned working set; every point scored."""
    import trimesh

    vertices, faces = _bumpy_sphere(5)
    points, _ = trimesh.sample.sample_surface(trimesh.Trimesh(vertices, faces), 40_000, seed=2)
    (tmp_path / "cloud.ply").write_bytes(write_points_ply(points.astype(np.float32)))
    points = points.astype(np.float32).astype(np.float64)
    bundle = fit_scan(tmp_path / "cloud.ply", tmp_path / "b", FitOptions(patches=60))
    m = bundle.manifest
    assert m["base"]["kind"] == "atlas" and m["fit"]["surface"] != "mesh"
    assert m["provenance"]["working_set"]["points_before"] == len(points)
    assert m["fit"]["working_points"] < 10_000
    assert m["fit"]["detail"]["samples"] == len(points)  # the detail: its own points
    _check_every_point(bundle.path, m, points)
    assert m["coverage"]["within_0.5%"] > 0.99


def test_a_large_cloud_far_from_the_origin_is_streamed_moved_near_it(tmp_path,
                                                                     small_out_of_core):
    """A streamed cloud in map coordinates (float64, 1,000 km out): every pass reads it
    moved by ``provenance.origin``, and every point is scored in that frame."""
    import trimesh

    vertices, faces = _bumpy_sphere(5)
    points, _ = trimesh.sample.sample_surface(trimesh.Trimesh(vertices, faces), 40_000, seed=2)
    offset = np.array([1e6, -2e6, 150.0])
    _float64_ply(tmp_path / "far.ply", points + offset)
    bundle = fit_scan(tmp_path / "far.ply", tmp_path / "b", FitOptions(patches=60))
    m = bundle.manifest
    origin = np.asarray(m["provenance"]["origin"])
    diagonal = float(np.linalg.norm(np.ptp(points, axis=0)))
    assert np.abs(origin - offset).max() <= diagonal and m["base"]["kind"] == "atlas"
    assert m["provenance"]["working_set"]["points_before"] == len(points)
    _check_every_point(bundle.path, m, points + offset - origin)
    assert m["coverage"]["within_0.5%"] > 0.99
    assert "warnings" not in m["provenance"]  # double precision: nothing lost
    # the same cloud written in single precision: its file lost what the move cannot restore
    (tmp_path / "far32.ply").write_bytes(write_points_ply((points + offset)
                                                          .astype(np.float32)))
    large = stream.load_working_set(*stream.open_stream(tmp_path / "far32.ply"))
    assert [w for w in large.working.source["warnings"] if "single precision" in w]


def _float64_ply(path: Path, points: np.ndarray) -> None:
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
              "property double x\nproperty double y\nproperty double z\nend_header\n")
    path.write_bytes(header.encode() + points.astype("<f8").tobytes())


def test_a_large_height_field_far_from_the_origin_is_one_patch_as_near_it(tmp_path,
                                                                        small_out_of_core):
    """One patch out of core (``LargeScan.measure`` streams every point against it) of a
    relief 10^6 diagonals out: the same RMS as the relief at the origin; its PLYs (the
    viewer's base download, error.ply) name the origin."""
    from client_py.session import WorkerSession

    points = relief_scan(N_POINTS, seed=3)
    diagonal = float(np.linalg.norm(np.ptp(points, axis=0)))
    _float64_ply(tmp_path / "near.ply", points)
    _float64_ply(tmp_path / "far.ply", points + np.array([3e5, -7e5, 40.0]) * diagonal)
    near = fit_scan(tmp_path / "near.ply", tmp_path / "bn", FitOptions(patches=1)).manifest
    far = fit_scan(tmp_path / "far.ply", tmp_path / "bf", FitOptions(patches=1)).manifest
    assert "origin" not in near["provenance"] and "origin" in far["provenance"]
    assert far["stats"]["points"] == N_POINTS
    assert far["stats"]["rms"] == pytest.approx(near["stats"]["rms"], rel=0.05)
    comment = "comment origin " + " ".join(repr(x) for x in far["provenance"]["origin"])
    assert comment in (tmp_path / "bf" / "error.ply").read_bytes()[:1000].decode("latin-1")
    session = WorkerSession()
    session.load_patch((tmp_path / "bf" / "base.tsp").read_bytes(), "base.tsp")
    session.read_manifest((tmp_path / "bf" / "manifest.json").read_text())
    assert comment in session.base_ply(12).data[:1000].decode("latin-1")


def test_a_large_clouds_detail_points_are_its_own_thinned_by_the_working_sets_rule(
        tmp_path, small_out_of_core, monkeypatch):
    points = _relief_ply(tmp_path / "cloud.ply")
    large = stream.load_working_set(*stream.open_stream(tmp_path / "cloud.ply"))
    assert large.whole is None and large.detail_scan().n_points == N_POINTS  # all of them
    monkeypatch.setattr(stream, "DETAIL_POINTS", 20_000)
    own = large.detail_scan()
    assert 14_000 <= own.n_points <= 24_000 and own.n_points > large.working.n_points
    rows = {tuple(x) for x in points.astype(np.float32).astype(np.float64)}
    assert all(tuple(x) in rows for x in own.points)  # the cloud's own points, none made up


def test_a_large_height_field_stays_one_patch_and_one_patch_can_be_asked_for(tmp_path,
                                                                            small_out_of_core):
    vertices, faces = _bumpy_sphere()
    scan = make_scan("bumpy", vertices, faces=faces, units="mm", source={"name": "bumpy"})
    m = fit_scan(scan, tmp_path / "one", FitOptions(patches=1, **OPTIONS)).manifest
    assert m["base"].get("kind") != "atlas" and m["provenance"]["points"] == len(vertices)
    points = _relief_ply(tmp_path / "cloud.ply")
    m = fit_scan(tmp_path / "cloud.ply", tmp_path / "relief", FitOptions(**OPTIONS)).manifest
    assert m["base"].get("kind") != "atlas" and m["provenance"]["points"] == len(points)


def test_welding_joins_a_triangle_soup_and_drops_what_collapses():
    vertices, faces = _bumpy_sphere(3)
    soup = vertices[faces].reshape(-1, 3)  # every triangle with vertices of its own
    soup_faces = np.arange(len(soup)).reshape(-1, 3)
    soup_faces = np.concatenate([soup_faces, [[0, 0, 1]]])  # and one degenerate triangle
    points, joined = stream.welded(soup, soup_faces)
    assert len(points) == len(vertices) and len(joined) == len(faces)
    np.testing.assert_array_equal(points[joined], vertices[faces])  # the same triangles
    same, same_faces = stream.welded(vertices, faces)
    assert same is vertices and same_faces is faces


def test_a_working_mesh_welds_a_soup_and_takes_a_textures_colours():
    """A large STL-like soup is reduced as one closed surface (collapsed triangle by triangle
    it fell apart); a textured mesh's working vertices take the texture's colour at their
    nearest original vertex's ``uv``."""
    from PIL import Image

    from fitter.fitting.atlas.layout import border_edges
    from fitter.fitting.texture import sample_image

    vertices, faces = _bumpy_sphere(5)
    soup = make_scan("soup", vertices[faces].reshape(-1, 3),
                     faces=np.arange(3 * len(faces)).reshape(-1, 3), source={"name": "soup"})
    working = stream.working_mesh(soup, 2_000)
    assert len(border_edges(working.faces)) == 0 and len(working.faces) <= 4_000
    small = stream.working_mesh(soup, 20_000)  # few enough triangles: the welded mesh itself
    assert len(small.faces) == len(faces) and small.n_points == len(vertices)
    image = np.random.default_rng(3).integers(0, 256, (64, 64, 3)).astype(np.uint8)
    uv = (vertices[:, :2] - vertices[:, :2].min(axis=0)) / np.ptp(vertices[:, :2], axis=0)
    textured = make_scan("tex", vertices, faces=faces, uv=uv, texture=Image.fromarray(image),
                         colors=np.zeros((len(vertices), 3), np.uint8), source={"name": "tex"})
    working = stream.working_mesh(textured, 2_000)
    from scipy.spatial import cKDTree
    _, nearest = cKDTree(vertices).query(working.points)
    expected = np.clip(np.rint(sample_image(image, uv[nearest])), 0, 255)
    np.testing.assert_array_equal(working.colors, expected)
    assert working.colors.any()  # the texture's, not the (black) vertex colours


def test_a_large_cloud_given_as_an_array_is_an_atlas(tmp_path, small_out_of_core):
    """A cloud loaded whole (an array, a ``Scan``, a format not streamed) over the threshold:
    its working set is the atlas's scan (it is not kept whole as a mesh is)."""
    import trimesh

    vertices, faces = _bumpy_sphere(5)
    points, _ = trimesh.sample.sample_surface(trimesh.Trimesh(vertices, faces), 30_000, seed=4)
    m = fit_scan(points, tmp_path / "b", FitOptions(patches=60)).manifest
    assert m["base"]["kind"] == "atlas" and m["provenance"]["points"] == len(points)
    assert m["stats"]["points"] == len(points) and m["coverage"]["within_0.5%"] > 0.99
    assert m["error_raster"]["max"] >= m["stats"]["max"]


def test_a_mesh_that_cannot_be_reduced_is_one_patch_under_auto(tmp_path, small_out_of_core,
                                                              monkeypatch):
    def refuse(scan, vertices=None):
        raise stream.WorkingMeshError("bumpy: its triangles could not be reduced (test)")

    monkeypatch.setattr(stream, "working_mesh", refuse)
    vertices, faces = _bumpy_sphere()
    scan = make_scan("bumpy", vertices, faces=faces, units="mm", source={"name": "bumpy"})
    m = fit_scan(scan, tmp_path / "auto", FitOptions(**OPTIONS)).manifest
    assert m["base"].get("kind") != "atlas" and "could not be reduced" in m["atlas_refused"]
    with pytest.raises(stream.WorkingMeshError, match="could not be reduced"):
        fit_scan(scan, tmp_path / "asked", FitOptions(patches=60, **OPTIONS))
