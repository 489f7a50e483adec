"""fit_scan's atlas branch: a closed object becomes a format-2 bundle scored on every point."""

import json
import zlib
from pathlib import Path

import numpy as np
import pytest
import trimesh

from client_py.atlas_format import read_atlas
from fitter.fitting.atlas.measure import (
    MeasuringProcess,
    MeasuringProcessError,
    closest_points_on_mesh,
    closest_points_on_triangles,
    far_places,
    farther_than,
    point_mesh_distance,
    signed_point_mesh_distance,
)
from fitter.fitting.atlas.pipeline import wants_atlas
from fitter.fitting.io import Scan
from fitter.fitting.io.scan import make_scan, new_source
from fitter.fitting.options import ATLAS_BASES, OPTION, FitOptions, OptionError
from fitter.fitting.pipeline import fit_scan


def _mesh_scan(mesh: trimesh.Trimesh, name: str = "mesh") -> Scan:
    source = new_source(name, None, "array", compression=None, reader="array")
    return make_scan(name, np.asarray(mesh.vertices), faces=np.asarray(mesh.faces),
                     source=source)


def test_point_mesh_distance_equals_brute_force():
    rng = np.random.default_rng(0)
    mesh = trimesh.creation.icosphere(subdivisions=2)
    points = rng.normal(size=(500, 3)) * 1.3
    tri = mesh.vertices[mesh.faces]
    brute = np.full(len(points), np.inf)
    for t in tri:  # every triangle, no candidate search
        q = closest_points_on_triangles(points, *(np.repeat(t[None, k], len(points), 0)
                                                  for k in range(3)))
        brute = np.minimum(brute, np.linalg.norm(points - q, axis=1))
    found = point_mesh_distance(points, mesh.vertices, mesh.faces)
    # the nearest triangle is picked in single precision: a near tie may give a triangle
    # 1e-9 farther (relative), the distance to it is exact
    np.testing.assert_allclose(found, brute, rtol=1e-7, atol=1e-12)
    signed = point_mesh_distance(points, mesh.vertices, mesh.faces, signed=True)
    inside = np.linalg.norm(points, axis=1) < 0.9
    assert np.all(signed[inside] < 0) and np.all(signed[np.linalg.norm(points, axis=1) > 1.1] > 0)



def test_farther_than_is_the_threshold_of_every_points_closest_point():
    """farther_than lets the points near a mesh vertex go unmeasured: the points it keeps,
    their distances and closest points are those of closest_points_on_mesh of every point
    beyond the reach, bit for bit, points at the reach itself included; a vertex no
    triangle uses lets no point go; bad input is named."""
    rng = np.random.default_rng(1)
    mesh = trimesh.creation.icosphere(subdivisions=3)
    vertices, faces = np.asarray(mesh.vertices) + 40.0, np.asarray(mesh.faces)
    direction = rng.normal(size=(4000, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    points = 40.0 + direction * rng.uniform(0.7, 1.3, size=(4000, 1))
    reach = 0.15
    dist, _, closest = closest_points_on_mesh(points, vertices, faces)
    points[:200] = closest[:200] + (points[:200] - closest[:200]) / dist[:200, None] * reach
    stray = np.vstack([vertices, points[200:260] + 1e-4])  # unused vertices beside points
    for verts in (vertices, stray):
        dist, _, closest = closest_points_on_mesh(points, verts, faces)
        want = np.flatnonzero(dist > reach)
        assert 100 < len(want) < len(points) - 1000
        got, got_dist, got_closest = farther_than(points, verts, faces, reach)
        assert got.tobytes() == want.tobytes()
        assert got_dist.tobytes() == dist[want].tobytes()
        assert got_closest.tobytes() == closest[want].tobytes()
    assert len(farther_than(points, vertices, faces, 0.0)[0]) == len(points)
    assert len(farther_than(np.zeros((0, 3)), vertices, faces, reach)[0]) == 0
    for bad in (-1.0, float("nan"), True):
        with pytest.raises(ValueError, match="reach"):
            farther_than(points, vertices, faces, bad)
    with pytest.raises(ValueError, match="triangles"):
        farther_than(points, vertices, np.zeros((0, 3), np.int64), reach)


def test_a_kept_scene_answers_as_a_new_one():
    """nearest_triangles keeps the ray-casting scenes of the meshes it queried last: a kept
    scene gives each point the triangle a scene built anew gives it, another mesh (or the
    same mesh moved by one float32 step) is not answered from it, and no more than
    SCENES meshes are kept."""
    import open3d as o3d

    from fitter.fitting.atlas import measure

    rng = np.random.default_rng(3)
    mesh = trimesh.creation.icosphere(subdivisions=3)
    vertices = np.asarray(mesh.vertices) + rng.normal(scale=0.01, size=mesh.vertices.shape)
    faces = np.asarray(mesh.faces)
    points = rng.normal(size=(3000, 3))

    def fresh(v):
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(np.asarray(v, np.float32)),
                            o3d.core.Tensor(np.asarray(faces, np.uint32)))
        query = o3d.core.Tensor(np.asarray(points, np.float32))
        return scene.compute_closest_points(query)["primitive_ids"].numpy().astype(np.int64)

    moved = vertices.astype(np.float32)
    moved[0, 0] = np.nextafter(moved[0, 0], np.float32(np.inf))
    other = vertices * 1.5
    measure._scenes.clear()
    for v in (vertices, vertices, moved, other, vertices, moved, vertices):
        np.testing.assert_array_equal(measure.nearest_triangles(points, v, faces), fresh(v))
        assert len(measure._scenes) <= measure.SCENES
    kept = measure._scenes[0][2]
    measure.nearest_triangles(points[:10], vertices.copy(), faces.copy())  # equal copies
    assert measure._scenes[0][2] is kept
    measure.nearest_triangles(points[:10], moved, faces)
    assert measure._scenes[0][2] is not kept
    measure._scenes.clear()


def _grid(xs, ys):
    x, y = np.meshgrid(xs, ys, indexing="ij")
    return x.ravel(), y.ravel()


def test_far_places_are_the_far_samples_linked_into_places():
    """Samples of a drawn mesh over the square [0, 4] x [0, 1] of the plane z = 0 (its
    closest points are their feet, written here): the plane itself, a vertical fin at x = 1
    rising to 0.5 (normal along x: the scan beside it), a tilted sheet rising to 0.3 (the
    plane x + 0.75 z = 3.8, normal (0.8, 0, 0.6)) and a lifted square at z = 0.2 (normal
    along z), each farther than the link from the others: three places, farthest first,
    with the counts, farthest samples and facings the geometry gives."""
    t = np.linspace(0.0, 1.0, 11)
    parts = []
    x, y = _grid(np.linspace(0, 4, 41), t)  # the plane: never far
    parts.append((np.c_[x, y, 0 * x], np.tile([0.0, 0.0, 1.0], (len(x), 1))))
    y, z = _grid(np.linspace(0.2, 0.8, 7), np.linspace(0.0, 0.5, 11))  # the fin
    parts.append((np.c_[np.full_like(y, 1.0), y, z], np.tile([1.0, 0.0, 0.0], (len(y), 1))))
    y, z = _grid(np.linspace(0.2, 0.8, 7), np.linspace(0.0, 0.3, 7))  # the tilted sheet
    parts.append((np.c_[3.8 - 0.75 * z, y, z], np.tile([0.8, 0.0, 0.6], (len(y), 1))))
    x, y = _grid(np.linspace(2.0, 2.2, 5), np.linspace(0.4, 0.6, 5))  # the lifted square
    parts.append((np.c_[x, y, np.full_like(x, 0.2)], np.tile([0.0, 0.0, 1.0], (len(x), 1))))
    samples = np.concatenate([p for p, _ in parts])
    normals = np.concatenate([n for _, n in parts])
    closest = samples * [1.0, 1.0, 0.0]  # the foot on z = 0, inside the square
    places = far_places(samples, normals, closest, reach=0.1, link=0.3)
    assert [round(p.distance, 12) for p in places] == [0.5, 0.3, 0.2]
    # z > 0.1: the fin's rows z = 0.15 .. 0.5 (8 of 7), the sheet's z = 0.15 .. 0.3 (4 of 7)
    assert [p.samples for p in places] == [8 * 7, 4 * 7, 25]
    np.testing.assert_allclose(places[0].where[[0, 2]], [1.0, 0.5])
    np.testing.assert_allclose(places[1].where[[0, 2]], [3.8 - 0.225, 0.3])
    np.testing.assert_allclose([p.facing for p in places], [0.0, 0.6, 1.0], atol=1e-12)
    # a link shorter than the spacing of the fin's rows (0.05) leaves every sample alone
    alone = far_places(samples, normals, closest, reach=0.1, link=0.04)
    assert len(alone) == 8 * 7 + 4 * 7 + 25
    assert far_places(samples, normals, closest, reach=0.6, link=0.3) == []


def test_far_places_refuses_bad_input():
    good = np.zeros((4, 3))
    with pytest.raises(ValueError, match="share a shape"):
        far_places(good, np.zeros((3, 3)), good, 0.1, 0.1)
    with pytest.raises(ValueError, match="reach must be"):
        far_places(good, good, good, 0.0, 0.1)
    with pytest.raises(ValueError, match="link must be"):
        far_places(good, good, good, 0.1, float("nan"))

def test_the_measuring_process_gives_the_distances_measured_here():
    """MeasuringProcess (a fresh Python process, arrays through pipes) returns the signed
    distances, triangles and feet of signed_point_mesh_distance here, bit for bit; a
    process that dies says so."""
    rng = np.random.default_rng(1)
    mesh = trimesh.creation.icosphere(subdivisions=3)
    points = rng.normal(size=(2000, 3))
    vertices = mesh.vertices.astype(np.float32).astype(float)  # drawn meshes are float32
    here = signed_point_mesh_distance(points, vertices, mesh.faces)
    there = MeasuringProcess().measure(points, vertices, mesh.faces)
    for a, b in zip(here, there, strict=True):
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes()
    # several meshes against the same points, in order (the coarser levels' process)
    other = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    meshes = [(other.vertices, other.faces), (vertices, mesh.faces)]
    for (v, f), answer in zip(meshes, MeasuringProcess().measure_all(points, meshes),
                              strict=True):
        for a, b in zip(signed_point_mesh_distance(points, v, f), answer, strict=True):
            assert a.dtype == b.dtype and a.tobytes() == b.tobytes()
    broken = MeasuringProcess()
    broken.process.kill()
    with pytest.raises(MeasuringProcessError):
        broken.measure(points, vertices, mesh.faces)
    broken.close()


def test_measure_levels_gives_the_same_distances_with_the_finest_level_in_a_process(
        monkeypatch):
    """The finest level measured in a MeasuringProcess (PROCESS_TRIANGLES lowered to 0) or
    here: the same distances at every level, the same feet."""
    from fitter.fitting.atlas import pipeline
    from fitter.fitting.atlas.detail import fit_atlas_detail
    from fitter.fitting.atlas.fit import fit_atlas

    mesh = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    scan = _mesh_scan(mesh, "sphere")
    fit = fit_atlas(scan, 24)
    detail = fit_atlas_detail(fit, scan, 1)
    points = np.asarray(mesh.vertices, dtype=float)
    here = pipeline.measure_levels(detail.atlas, detail, points)
    monkeypatch.setattr(pipeline, "PROCESS_TRIANGLES", 0)
    there = pipeline.measure_levels(detail.atlas, detail, points)
    assert here[0].keys() == there[0].keys() == {-1, 0}
    for k in here[0]:
        assert here[0][k].tobytes() == there[0][k].tobytes()
    assert here[2].tobytes() == there[2].tobytes() and here[3].tobytes() == there[3].tobytes()
    # a large scan's working set: the finest level alone, the same numbers, measured here
    # (no process, however many triangles) so that its scene stays for the every-point pass
    from fitter.fitting.atlas import measure

    monkeypatch.setattr(pipeline, "MeasuringProcess",
                        lambda: pytest.fail("a process for the finest level alone"))
    measure.forget_scenes()
    finest = pipeline.measure_levels(detail.atlas, detail, points, coarser=False)
    kept = measure.mesh_scene(finest[1].vertices.astype(np.float32),
                              finest[1].faces.astype(np.uint32))
    assert any(scene is kept for _, _, scene in measure._scenes[1:] + measure._scenes[:1])
    assert len(measure._scenes) == 1  # the query above found it: none was built
    assert finest[0].keys() == {0}
    assert finest[0][0].tobytes() == here[0][0].tobytes()
    assert finest[1].vertices.tobytes() == here[1].vertices.tobytes()
    assert finest[2].tobytes() == here[2].tobytes() and finest[3].tobytes() == here[3].tobytes()


def test_packs_coded_while_the_levels_are_measured_are_those_coded_before(monkeypatch):
    """fit_atlas_bundle codes the detail packs while the levels' meshes are measured
    (levels_measured: by a worker thread here or, PROCESS_TRIANGLES lowered to 0, by two
    MeasuringProcesses): the same packs, tree and distances as pack_pyramid and
    measure_levels one after the other, and fit_atlas_detail's; a coarser levels' process
    that fails leaves its levels to be measured here, the same numbers again."""
    from fitter.fitting.atlas import pipeline
    from fitter.fitting.atlas.detail import fit_atlas_detail, fit_detail_pyramid, pack_pyramid
    from fitter.fitting.atlas.fit import fit_atlas

    mesh = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    scan = _mesh_scan(mesh, "sphere")
    fit = fit_atlas(scan, 24)
    pyramid = fit_detail_pyramid(fit, scan, 2, spans=4)
    points = np.asarray(mesh.vertices, dtype=float)
    packed = pack_pyramid(pyramid)
    assert packed.files == fit_atlas_detail(fit, scan, 2, spans=4).files and packed.files
    serial = pipeline.measure_levels(pyramid.atlas, pyramid, points)
    assert serial[0].keys() == {-1, 0, 1}
    started = []

    class Counted(MeasuringProcess):
        def __init__(self):
            super().__init__()
            started.append(self)

    class Failing(Counted):
        def measure_all(self, points, meshes):
            if len(started) == 2 and self is started[1]:  # the coarser levels' process
                self.process.kill()
            return super().measure_all(points, meshes)

    for triangles, process in ((pipeline.PROCESS_TRIANGLES, Counted), (0, Counted),
                               (0, Failing)):
        monkeypatch.setattr(pipeline, "PROCESS_TRIANGLES", triangles)
        monkeypatch.setattr(pipeline, "MeasuringProcess", process)
        started.clear()
        with pipeline.levels_measured(pyramid.atlas, pyramid, points) as measured:
            detail = pack_pyramid(pyramid)
            together = measured()
        assert len(started) == (0 if triangles else 2)
        assert detail.files == packed.files and detail.tree == packed.tree
        assert list(together[0]) == list(serial[0]) == [1, 0, -1]
        for k in serial[0]:
            assert together[0][k].tobytes() == serial[0][k].tobytes()
        assert together[1].vertices.tobytes() == serial[1].vertices.tobytes()
        assert together[2].tobytes() == serial[2].tobytes()
        assert together[3].tobytes() == serial[3].tobytes()


def test_auto_rule_keeps_one_patch_for_a_height_field_and_an_atlas_for_a_closed_object():
    x, y = np.meshgrid(np.linspace(0, 1, 60), np.linspace(0, 1, 60))
    relief = np.column_stack([x.ravel(), y.ravel(), 0.05 * np.sin(6 * x.ravel()) * y.ravel()])
    sphere = _mesh_scan(trimesh.creation.icosphere(subdivisions=3))
    for base in ATLAS_BASES:
        assert not wants_atlas(Scan.from_array(relief), None, base)
        assert wants_atlas(sphere, None, base)
        assert not wants_atlas(sphere, 1, base)
        assert wants_atlas(Scan.from_array(relief), 30, base)
    # with the smooth base a height-field mesh is an atlas; a height-field cloud stays one patch
    a = (np.arange(59)[:, None] * 60 + np.arange(59)[None, :]).ravel()  # the grid's cells
    faces = np.concatenate([np.stack([a, a + 1, a + 61], 1), np.stack([a, a + 61, a + 60], 1)])
    relief_mesh = Scan(points=relief, faces=faces)
    assert not wants_atlas(relief_mesh, None, "patches")
    assert wants_atlas(relief_mesh, None, "smooth")
    assert not wants_atlas(Scan.from_array(relief), None, "smooth")
    assert not wants_atlas(relief_mesh, 1, "smooth")


def test_patches_option_spells_auto_and_counts():
    assert OPTION["patches"].parse("auto") is None
    assert OPTION["patches"].parse("120") == 120
    with pytest.raises(OptionError, match="patches must be"):
        OPTION["patches"].parse("0")


def test_more_detail_levels_than_an_atlas_holds_are_refused_before_the_scan_is_read(
        tmp_path):
    stages = []
    with pytest.raises(OptionError, match=r"detail_levels 5: an atlas with 8 spans a tile "
                                          r"holds at most 4 levels"):
        fit_scan(tmp_path / "no such scan.ply", tmp_path / "b",
                 FitOptions(patches=60, detail_levels=5),
                 lambda stage, fraction, points=None: stages.append(stage))
    assert stages == [] and not (tmp_path / "b").exists()
    # the option's help says the same most
    from fitter.fitting.atlas.detail import most_levels
    assert f"an atlas holds at most {most_levels(1)[0]}," in OPTION["detail_levels"].help


def test_more_detail_levels_than_an_atlas_not_asked_for_holds_are_capped(tmp_path,
                                                                          monkeypatch):
    """With ``patches`` automatic, ``detail_levels`` may be meant for the single patches of
    a collection: a closed object gets the most its atlas holds, and the manifest says so.

    The default base (smooth: here 3,840 patches of 2 spans a tile side, holding 2 levels;
    the patches base's fewer patches of 8 spans held 1): the levels held are computed from
    the patches and the spans the manifest records, so the rule is checked on either base."""
    from fitter.fitting.atlas import detail as atlas_detail

    monkeypatch.setattr(atlas_detail, "MAX_COEFFICIENTS", 200_000)
    mesh = trimesh.creation.icosphere(subdivisions=3)
    manifest = fit_scan(_mesh_scan(mesh, "sphere"), tmp_path / "b",
                        FitOptions(detail_levels=3)).manifest
    assert manifest["options"]["base"] == FitOptions().base
    patches = manifest["base"]["patches"]
    spans = manifest["tiles"]["detail"]["spans_per_tile"]
    # level k has (spans 2^k + 2)^2 coefficients a patch (degree 2); held: those within
    coefficients = [patches * ((spans << k) + 2) ** 2 for k in range(4)]
    held = next(k for k, n in enumerate(coefficients) if n > 200_000)
    assert 1 <= held < 3  # the cap keeps level 0 and drops one asked for
    assert manifest["fit"]["detail_levels_capped"] == {
        "asked": 3, "held": held, "why": f"level {held} would have {coefficients[held]:,} "
                                         "coefficients, over 200,000"}
    assert len(manifest["tiles"]["detail"]["levels"]) == held
    from client_py.bundle import fit_notes  # tessera fit's summary, the admin's page
    assert ("capped", f"detail_levels 3: the atlas holds {held} (level {held} would have "
                      f"{coefficients[held]:,} coefficients, over 200,000)") in fit_notes(manifest)


def test_a_closed_object_in_map_coordinates_is_fitted_near_the_origin(tmp_path):
    """A sphere 5,000 km from the origin (a scan registered to a map) is fitted moved by
    its rounded centre, recorded as ``provenance.origin``: as near its surface as the same
    sphere at the origin. In the file's coordinates single-precision searches and drawing
    lose it (a float32 step there is 0.5 for a radius of 1): the atlas was refused and one
    height-field patch drew part of it.

    The default (smooth) base with 120 patches, 40 control triangles: with 60 (20 control
    triangles) that base is too coarse for this sphere, 15 of its 642 points uncovered here
    and 9 at the origin (session 31: 90, 120 and 150 patches left none, the RMS 0.8 to 1.0
    times the origin's). Its drawn base strays up to 2.0 % of the radius from the sphere
    (1.1 % at 480 patches; the patches base's 60 patches 0.6 %), so the PLY's vertices are
    checked within 3 %, where the file's coordinates would be 6.4e6 away."""
    mesh = trimesh.creation.icosphere(subdivisions=3)
    offset = np.array([5e6, 4e6, 300.0])
    options = FitOptions(patches=120, detail_levels=0)
    far = fit_scan(_mesh_scan(trimesh.Trimesh(mesh.vertices + offset, mesh.faces,
                                              process=False), "far"),
                   tmp_path / "far", options).manifest
    near = fit_scan(_mesh_scan(mesh, "near"), tmp_path / "near", options).manifest
    assert far["provenance"]["origin"] == offset.tolist()
    assert "origin" not in near["provenance"]
    assert far["base"]["kind"] == "atlas" and far["base"]["border_edges"] == 0
    assert far["coverage"]["uncovered_points"] == 0
    rms = far["stats_all_points"]["rms"], near["stats_all_points"]["rms"]
    assert rms[0] < 1.5 * rms[1], rms
    atlas, _ = read_atlas((tmp_path / "far" / "base.tsa").read_bytes())
    assert np.abs(np.asarray(atlas.vertices)).max() < 2  # the bundle is near the origin
    # its PLY (the viewer's Download PLY) says what to add for the file's coordinates
    from fitter.cli import main
    assert main(["tessellate", str(tmp_path / "far"), "-o", str(tmp_path / "far.ply"),
                 "--level", "-1"]) == 0
    ply = trimesh.load(tmp_path / "far.ply", process=False)
    header = (tmp_path / "far.ply").read_bytes()[:2000].decode("latin-1")
    assert ("comment origin 5000000.0 4000000.0 300.0\ncomment the scan file's coordinates "
            "are each vertex plus the origin\n") in header
    assert np.allclose(np.linalg.norm(ply.vertices, axis=1), 1.0, atol=0.03)


def test_closed_sphere_becomes_a_watertight_atlas_bundle(tmp_path):
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=50.0)
    bundle = fit_scan(_mesh_scan(mesh, "sphere"), tmp_path / "sphere",
                      FitOptions(patches=60, grid=(12, 12)))  # a grid is a single patch's
    from fitter.fitting.atlas import measure
    assert measure._scenes == []  # the fit let go of its meshes' ray-casting scenes
    manifest = json.loads((bundle.path / "manifest.json").read_text())
    assert manifest["format_version"] == 2 and manifest["options_unused"] == ["grid"]
    base = manifest["base"]
    assert base["kind"] == "atlas" and base["border_edges"] == 0
    atlas, _ = read_atlas((bundle.path / "base.tsa").read_bytes())
    assert len(atlas.quads) == base["patches"] and atlas.edges.border_edges == []
    stats = manifest["stats_all_points"]
    assert stats["points"] == len(mesh.vertices)  # every scan point, no covered subset
    assert stats["rms_relative"] < 0.002 and manifest["coverage"]["uncovered_points"] == 0
    packs = {f"detail/{p['level']}/{p['group']}.tsdp" for p in manifest["tiles"]["detail"]["packs"]}
    assert set(manifest["files"]) == {"base.tsa", "error_raster.bin", "error.png",
                                      "error.ply"} | packs
    assert all((bundle.path / name).stat().st_size == size
               for name, size in manifest["files"].items())
    _check_error_raster(bundle.path, manifest, mesh.vertices, atlas)
    _check_level_errors(manifest, atlas, mesh.vertices, bundle.path)


def _check_error_raster(folder, manifest, points, atlas):
    """The atlas's error raster holds what the points give: its largest cell is the panel's
    max, and each point's |d| is within its cell's value, the cell found independently (the
    point's nearest vertex of the drawn mesh, away from cell borders)."""
    from scipy.spatial import cKDTree

    from client_py.atlas_mesh import tessellate_atlas

    raster = manifest["error_raster"]
    stats = manifest["stats"]
    assert raster["max"] == stats["max"] and raster["patches"] == len(atlas.quads)
    side = raster["rows"]
    codes = np.frombuffer(zlib.decompress((folder / raster["file"]).read_bytes()), np.uint8)
    assert codes.size == len(atlas.quads) * side * side == raster["cols"] * side * len(atlas.quads)
    assert codes[codes < 255].max() == 254  # the worst point's cell decodes to the max
    values = np.where(codes < 255, codes / 254 * raster["max"], np.nan)
    detail = manifest["tiles"]["detail"]
    finest = detail["levels"][-1]
    tiles = _finest_detail(folder, manifest)
    drawn = tessellate_atlas(atlas, finest_resolution(manifest), tiles, kernel="numpy")
    vertices = np.frombuffer(drawn.positions, np.float32).reshape(-1, 3)
    patch = np.frombuffer(drawn.patches, np.uintc)
    uv = np.frombuffer(drawn.uvs, np.float32).reshape(-1, 2)
    dist, nearest = cKDTree(vertices).query(points)
    d = point_mesh_distance(points, vertices, np.frombuffer(drawn.indices, np.uintc)
                            .reshape(-1, 3))
    assert finest["rms"] == pytest.approx(stats["rms"], rel=1e-5)
    cell_uv = uv[nearest] * side
    inner = np.all(np.abs(cell_uv - np.rint(cell_uv)) > 0.15, axis=1)
    cell = (patch[nearest].astype(np.int64) * side + np.minimum(cell_uv[:, 0].astype(int),
                                                               side - 1)) * side \
        + np.minimum(cell_uv[:, 1].astype(int), side - 1)
    held = values[cell[inner]]
    assert np.isfinite(held).mean() > 0.95
    ok = held >= d[inner] - raster["max"] / 254
    assert inner.sum() > 100 and ok.mean() > 0.95


def finest_resolution(manifest):
    from client_py.bundle import atlas_tiles

    spec = atlas_tiles(manifest)
    return spec.resolution(len(spec.levels) - 1)


def _finest_detail(folder, manifest):
    from client_py.atlas_detail import read_pack
    from client_py.atlas_format import read_atlas

    atlas, _ = read_atlas((folder / "base.tsa").read_bytes())  # the packs are welded
    tiles = {}
    for pack in manifest["tiles"]["detail"]["packs"]:
        _, found = read_pack((folder / f"detail/{pack['level']}/{pack['group']}.tsdp")
                             .read_bytes(), atlas)
        for patch, held in found.items():
            tiles.setdefault(patch, []).extend(held)
    return tiles


def _check_level_errors(manifest, atlas, points, folder):
    """The level list's figures are the panel's measure: the finest level's are the panel's
    stats, the base's are every point's distance to the welded base."""
    from client_py.atlas_mesh import tessellate_atlas

    detail = manifest["tiles"]["detail"]
    stats = manifest["stats"]
    assert detail["levels"][-1]["max"] == pytest.approx(stats["max"], rel=1e-5)
    base = tessellate_atlas(atlas, manifest["base"]["resolution"], kernel="numpy")
    d = point_mesh_distance(points, np.frombuffer(base.positions, np.float32).reshape(-1, 3),
                            np.frombuffer(base.indices, np.uintc).reshape(-1, 3))
    assert detail["base"]["rms"] == pytest.approx(np.sqrt(np.mean(d ** 2)), rel=1e-4)
    assert "samples_rms" in detail["base"] and "samples_rms" in detail["levels"][0]


def test_an_atlas_that_strays_from_the_surface_is_refused():
    from atlas_cases import sphere_atlas

    from fitter.fitting.atlas import AtlasFitError
    from fitter.fitting.atlas.pipeline import check_base_follows_surface
    from fitter.fitting.atlas.surface import ScanSurface

    mesh = trimesh.creation.icosphere(subdivisions=4)  # the unit sphere
    surface = ScanSurface(np.asarray(mesh.vertices), np.asarray(mesh.faces), "mesh", 1)
    assert check_base_follows_surface(sphere_atlas(3), surface) < 0.05
    with pytest.raises(AtlasFitError, match="strays from the scan"):
        check_base_follows_surface(sphere_atlas(3, noise=0.3), surface)


def test_a_base_with_a_patch_collapsed_to_a_point_is_refused_by_name():
    from fitter.fitting.atlas import AtlasFitError, quad_layout
    from fitter.fitting.atlas.layout import bilinear_atlas
    from fitter.fitting.atlas.patches import control_points, with_control_points
    from fitter.fitting.atlas.pipeline import check_base_follows_surface
    from fitter.fitting.atlas.surface import ScanSurface

    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float64)
    triangles = np.array([[0, 1, 2], [0, 2, 3]])
    atlas = bilinear_atlas(quad_layout(square, triangles), 3, 1)
    surface = ScanSurface(square, triangles, "mesh", 1)
    assert check_base_follows_surface(atlas, surface) == 0.0
    points = control_points(atlas)
    points[:] = 0.5  # every patch quantised onto one point
    with pytest.raises(AtlasFitError, match="collapsed to a line or a point"):
        check_base_follows_surface(with_control_points(atlas, points), surface)


def test_thin_to_count_keeps_about_the_target():
    from fitter.fitting.io.thin import thin_to_count

    points = np.random.default_rng(1).random((50_000, 3))
    for target, slack in ((5_000, 1.0), (5_000, 1.2), (60_000, 1.0)):
        keep = thin_to_count(points, target, slack)
        assert len(keep) <= slack * target and len(keep) > 0.3 * min(target, len(points))
        assert np.all(np.diff(keep) > 0)  # ascending, no repeats: a subset in order


def _holed_slab(n: int = 40, thick: int = 3, holes: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """A closed voxel slab ``n × n × thick`` (side 1) with ``holes²`` one-voxel tunnels
    through it: genus ``holes²``, each tunnel 1/n wide."""
    solid = np.ones((n, n, thick), bool)
    for i in range(holes):
        for j in range(holes):
            solid[(i + 1) * n // (holes + 1), (j + 1) * n // (holes + 1), :] = False
    pad = np.pad(solid, 1)
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    quads = []
    for axis in range(3):
        for step in (1, -1):  # a solid cell whose neighbour along ±axis is empty
            for cell in np.argwhere(pad & ~np.roll(pad, -step, axis=axis)) - 1:
                corner = cell.copy()
                corner[axis] += step == 1
                q = corner + np.roll(square, (axis + 1) % 3, axis=1)
                quads.append(q if step == 1 else q[::-1])
    vertices, inverse = np.unique(np.array(quads).reshape(-1, 3), axis=0, return_inverse=True)
    q = inverse.reshape(-1, 4)
    return vertices / n, np.vstack([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])


def test_handle_count_is_the_genus_summed_over_pieces():
    from fitter.fitting.atlas.surface import handle_count

    torus = trimesh.creation.torus(1.0, 0.3)
    sphere = trimesh.creation.icosphere(subdivisions=2)
    assert handle_count(torus.vertices, torus.faces) == 1
    assert handle_count(sphere.vertices, sphere.faces) == 0
    cap = sphere.faces[sphere.vertices[sphere.faces].mean(axis=1)[:, 2] < 0.5]
    assert handle_count(sphere.vertices, cap) == 0  # a border loop is no handle
    three = trimesh.util.concatenate([torus, torus.copy().apply_translation([5, 0, 0]), sphere])
    assert handle_count(three.vertices, three.faces) == 2
    assert handle_count(*_holed_slab()) == 9


def test_the_layout_stand_in_closes_narrow_tunnels_and_stays_on_the_surface():
    from fitter.fitting.atlas.layout import decimate, quad_layout
    from fitter.fitting.atlas.surface import (
        LAYOUT_TRIM,
        ScanSurface,
        clean_mesh,
        handle_count,
        layout_stand_in,
    )

    vertices, faces, _ = clean_mesh(*_holed_slab())
    surface = ScanSurface(vertices, faces, "mesh", 1)
    stand_in = layout_stand_in(surface, depth=5)  # cells of 1/29: the 1/40 tunnels close
    assert stand_in.repairs["handles"] == handle_count(stand_in.vertices, stand_in.faces) == 0
    samples, _ = surface.sample(5000, np.random.default_rng(0))
    assert np.max(point_mesh_distance(samples, stand_in.vertices, stand_in.faces)) \
        < 0.05 * surface.diagonal
    assert np.max(point_mesh_distance(stand_in.vertices, vertices, faces)) \
        <= LAYOUT_TRIM * surface.diagonal  # trimmed where it leaves the surface
    layout = quad_layout(*decimate(stand_in, 48))
    assert len(layout.quads) == 3 * layout.n_triangles >= 3 * 40


def _open_tube(around: int = 96, along: int = 72) -> tuple[np.ndarray, np.ndarray]:
    """The side of a cylinder of radius 1 and height 3 about ``z``, open at both ends."""
    angle = np.linspace(0.0, 2.0 * np.pi, around, endpoint=False)
    a, z = np.meshgrid(angle, np.linspace(-1.5, 1.5, along + 1), indexing="ij")
    vertices = np.stack([np.cos(a).ravel(), np.sin(a).ravel(), z.ravel()], axis=1)
    i, j = np.meshgrid(np.arange(around), np.arange(along), indexing="ij")
    p, q = (i * (along + 1) + j).ravel(), (((i + 1) % around) * (along + 1) + j).ravel()
    return vertices, np.concatenate([np.stack([p, q, q + 1], 1), np.stack([p, q + 1, p + 1], 1)])


@pytest.mark.parametrize("beside", [True, False])
def test_the_stand_in_of_an_open_tube_keeps_its_ends_open(beside):
    from fitter.fitting.atlas.surface import (
        LAYOUT_TRIM_BESIDE,
        ScanSurface,
        handle_count,
        layout_stand_in,
    )

    surface = ScanSurface(*_open_tube(), "mesh", 1)
    # Poisson closes the ends with caps; trimmed off
    stand_in = layout_stand_in(surface, trim_beside=LAYOUT_TRIM_BESIDE if beside else None)
    assert handle_count(stand_in.vertices, stand_in.faces) == 0
    samples, _ = stand_in.sample(50_000, np.random.default_rng(0))
    # exact distance to the tube: radial, and along z beyond its ends
    radial = np.hypot(samples[:, 0], samples[:, 1]) - 1.0
    beyond = np.maximum(0.0, np.abs(samples[:, 2]) - 1.5)
    distance = np.hypot(radial, beyond) / surface.diagonal
    if beside:
        # the caps' rims have the tube's rim beside them: cut at 0.75 % of the diagonal,
        # nothing is left over the ends (0.06 % of the diagonal at most)
        assert distance.max() < 0.2 * LAYOUT_TRIM_BESIDE
        assert np.abs(samples[:, 2]).max() < 1.5 + 0.002 * surface.diagonal
    else:
        # the 1.5 % trim alone keeps rims of the caps 1.3 % of the diagonal off the tube
        # (1.8 % at a 2 % trim), a ring over each end
        assert 0.01 < distance.max() < 0.015
        assert 0.001 < np.mean(distance > 0.01) < 0.005
    # and it still covers the tube: every sample of the tube has the stand-in near
    tube, _ = surface.sample(5000, np.random.default_rng(1))
    assert point_mesh_distance(tube, stand_in.vertices, stand_in.faces).max() \
        < 0.01 * surface.diagonal


def _two_strips():
    """Two flat strips x in [0, 1] and [2, 3] (y in [0, 1], z = 0), a gap 1 wide between."""
    from fitter.fitting.atlas.surface import ScanSurface

    grid = np.linspace(0.0, 1.0, 11)
    strip = np.array([[x, y, 0.0] for y in grid for x in grid])
    grid_faces = np.array([[j * 11 + i, j * 11 + i + 1, (j + 1) * 11 + i + 1]
                           for j in range(10) for i in range(10)]
                          + [[j * 11 + i, (j + 1) * 11 + i + 1, (j + 1) * 11 + i]
                             for j in range(10) for i in range(10)])
    return ScanSurface(np.vstack([strip, strip + [2.0, 0.0, 0.0]]),
                       np.vstack([grid_faces, grid_faces + len(strip)]), "mesh", 2)


def test_a_stand_in_triangle_over_a_gap_is_found_by_its_middle():
    from fitter.fitting.atlas.surface import stand_in_far

    surface = _two_strips()
    # corners on the strips: a triangle bridging the gap, one lying on a strip, one lifted
    tri = np.array([[0.9, 0.2, 0], [2.1, 0.2, 0], [2.1, 0.8, 0],  # bridges x 1..2
                    [0.1, 0.1, 0], [0.8, 0.1, 0], [0.1, 0.9, 0],  # on the first strip
                    [2.2, 0.2, 0], [2.8, 0.2, 0], [2.5, 0.5, 0.6]])  # a corner 0.6 above
    far = stand_in_far(tri, np.arange(9).reshape(3, 3), surface, reach=0.3)
    # independent reference: the gap is 1 wide, so the bridge's edge midpoint (1.5, 0.2)
    # is 0.5 from both strips while its corners are 0.1 away
    assert far.tolist() == [True, False, True]
    assert not stand_in_far(tri, np.arange(9).reshape(3, 3), surface, reach=0.61).any()


def test_a_stand_in_triangle_with_the_surface_beside_it_is_cut_nearer():
    from fitter.fitting.atlas.surface import BESIDE_COS, stand_in_far

    surface = _two_strips()
    tri = np.array([[1.1, 0.2, 0], [1.9, 0.2, 0], [1.5, 0.8, 0],  # a membrane in the gap
                    [0.2, 0.2, 0.4], [0.8, 0.2, 0.4], [0.5, 0.8, 0.4],  # 0.4 over a strip
                    [0.2, 0.2, 0], [0.8, 0.2, 0], [1.4, 0.8, 0.3]])  # a flap off the edge
    faces = np.arange(9).reshape(3, 3)
    # independent reference, exact: the membrane's probes lie in the strips' plane, their
    # closest points at the strips' edges x = 1 or 2 (offset along x, normal along z), the
    # farthest its corner (1.5, 0.8) at 0.5; the lifted triangle's probes are 0.4 straight
    # above the strip, along its normal; the flap's corner (1.4, 0.8, 0.3) is 0.5 from
    # (1, 0.8, 0), its offset (-0.4, 0, -0.3) at acos(|n . d| / 0.5) from the flap's normal
    assert stand_in_far(tri, faces, surface, reach=0.6).tolist() == [False] * 3
    assert stand_in_far(tri, faces, surface, reach=0.6, beside=0.3).tolist() \
        == [True, False, True]
    assert stand_in_far(tri, faces, surface, reach=0.6, beside=0.45).tolist() \
        == [True, False, True]
    assert stand_in_far(tri, faces, surface, reach=0.6, beside=0.51).tolist() == [False] * 3
    assert stand_in_far(tri, faces, surface, reach=0.35, beside=0.51).tolist() \
        == [True, True, True]
    flap = tri[6:]
    normal = np.cross(flap[1] - flap[0], flap[2] - flap[0])
    normal /= np.linalg.norm(normal)
    assert abs(normal @ np.array([-0.4, 0.0, -0.3])) < BESIDE_COS * 0.5  # it is beside


BUDDHA = (Path(__file__).resolve().parents[2] / "shared" / "data" / "happy-buddha-rangescans"
          / "happyStandRight.conf")


@pytest.mark.skipif(not BUDDHA.exists(), reason="the shared scans (../shared/data) are absent")
def test_the_buddha_stand_in_is_trimmed_off_its_cavities_and_still_decimates():
    from scipy.spatial import cKDTree

    from fitter.fitting.atlas.fit import layout_candidates
    from fitter.fitting.atlas.surface import (
        LAYOUT_TRIM,
        layout_stand_in,
        manifold_problems,
        scan_surface,
    )
    from fitter.fitting.io import load_scan

    scan = load_scan(BUDDHA)
    surface = scan_surface(scan)
    stand_in = layout_stand_in(surface)
    problems = manifold_problems(stand_in.faces)
    assert problems["nonmanifold_edges"] == problems["misoriented_edges"] == 0
    assert problems["border_edges"] > 0  # open where the scan never saw (the cavities)
    # independent reference: area samples of the stand-in against the 1.1 M scan points;
    # the 3 % vertex trim before left 9.3 % of the area farther than 1 % of the diagonal,
    # the 2 % trim 5.1 %, 1.5 % 2.7 %, and with the 0.75 % trim beside the surface 0.4 %
    samples, _ = stand_in.sample(100_000, np.random.default_rng(1))
    diagonal = float(np.linalg.norm(np.ptp(scan.points, axis=0)))
    distance = cKDTree(scan.points).query(samples)[0]
    assert np.mean(distance > 0.01 * diagonal) < 0.008
    assert np.max(distance) < 1.5 * LAYOUT_TRIM * diagonal
    # the layouts of 576 and 1152 patches decimate to oriented 2-manifolds
    for triangles in (192, 384):
        candidates, failures = layout_candidates(stand_in, triangles, True)
        assert candidates, failures


def test_small_pieces_are_dropped_with_their_vertices():
    from fitter.fitting.atlas.surface import MIN_ISLAND_SHARE, without_islands

    sphere = trimesh.creation.icosphere(subdivisions=3)  # 1280 faces
    sliver = np.array([[5.0, 0, 0], [6, 0, 0], [6, 1, 0], [5, 1, 0]])
    vertices = np.vstack([sphere.vertices, sliver])
    n = len(sphere.vertices)
    faces = np.vstack([sphere.faces, [[n, n + 1, n + 2], [n, n + 2, n + 3]]])
    assert 2 < MIN_ISLAND_SHARE * len(faces) < 4  # the 4-face floor decides
    kept_vertices, kept_faces, islands, island_faces = without_islands(vertices, faces)
    assert (islands, island_faces) == (1, 2)
    assert len(kept_vertices) == n and len(kept_faces) == len(sphere.faces)
    assert np.array_equal(kept_vertices[kept_faces], sphere.vertices[sphere.faces])


def test_a_surface_with_many_handles_is_laid_out_on_its_stand_in():
    from fitter.fitting.atlas.pipeline import fit_checked_base
    from fitter.fitting.atlas.surface import MAX_LAYOUT_HANDLES, scan_surface

    vertices, faces = _holed_slab(64, 8, holes=4)  # 16 handles, 1/64 wide
    scan = make_scan("slab", vertices, faces=faces,
                     source=new_source("slab", None, "array", compression=None, reader="array"))
    surface = scan_surface(scan)
    assert 16 > MAX_LAYOUT_HANDLES

    class Stages:
        def start(self, name):
            pass

        def report(self, fraction):
            pass

    fit, decoded, record = fit_checked_base(scan, surface, FitOptions(patches=300), Stages(), 12)
    assert record["source"] == "stand-in" and record["surface_handles"] == 16
    assert "16 handles" in record["refused"][0]
    assert record["stand_in_handles"] < 16 and record["stray_share"] < 0.05
    assert len(decoded.quads) == fit.patches


def test_cloud_outliers_are_not_fitted_and_are_reported_uncovered(tmp_path):
    from fitter.fitting.atlas.pipeline import without_outliers
    from fitter.fitting.atlas.surface import scan_surface

    rng = np.random.default_rng(0)
    sphere = rng.normal(size=(6000, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    outliers = rng.uniform(-3, 3, size=(60, 3))
    outliers = outliers[np.abs(np.linalg.norm(outliers, axis=1) - 1) > 0.2]
    scan = Scan.from_array(np.vstack([sphere, outliers]))
    surface = scan_surface(scan)
    kept, dropped = without_outliers(scan, surface)
    assert dropped == len(outliers) and kept.n_points == len(sphere)
    mesh_scan = _mesh_scan(trimesh.creation.icosphere(subdivisions=2))
    assert without_outliers(mesh_scan, surface) == (mesh_scan, 0)
    bundle = fit_scan(scan, tmp_path / "cloud", FitOptions(patches=150, detail_levels=0))
    manifest = json.loads((bundle.path / "manifest.json").read_text())
    assert manifest["fit"]["outliers_not_fitted"] == len(outliers)
    coverage = manifest["coverage"]
    assert coverage["points"] == scan.n_points  # every point measured, none dropped
    assert coverage["uncovered_points"] >= len(outliers) - 2
    assert coverage["uncovered_share"] == pytest.approx(
        coverage["uncovered_points"] / scan.n_points)
    assert coverage["within_0.5%"] > 0.98


def test_a_refit_with_a_larger_budget_reuses_the_trials_and_fits_the_same_atlas(fit_layout_calls):
    """``fit_checked_base``'s refit after a stray refusal passes the first fit's trials
    (``fit_atlas(trial_cache=)``): only the targets the smaller budget did not reach are
    fitted again, and the atlas is the one a fit from scratch gives."""
    import fitter.fitting.atlas.fit as fit_module

    scan = _mesh_scan(trimesh.creation.icosphere(subdivisions=3), "sphere")
    options = {"working_count": 1000, "rounds": 1}
    calls = fit_layout_calls
    cache: dict = {}
    small = fit_module.fit_atlas(scan, "auto", byte_budget=6000, trial_cache=cache, **options)
    first = len(calls)
    reused = fit_module.fit_atlas(scan, "auto", byte_budget=12_000, trial_cache=cache,
                                  **options)
    reused_calls = calls[first:]
    fresh = fit_module.fit_atlas(scan, "auto", byte_budget=12_000, **options)
    fresh_calls = calls[first + len(reused_calls):]
    assert fresh.patches > small.patches  # the larger budget reached a larger layout
    assert [t.get("rms") for t in reused.trials] == [t.get("rms") for t in fresh.trials]
    assert np.array_equal(fit_module.control_points(reused.atlas),
                          fit_module.control_points(fresh.atlas))
    shared = {t["triangles"] for t in small.trials if "rms" in t}  # fitted, not skipped
    assert shared & set(fresh_calls[:-1])  # from scratch, the shared targets are fitted
    assert not shared & set(reused_calls[:-1])  # with the cache, only the new ones
    assert reused_calls[-1] == fresh_calls[-1] == fresh.triangles  # then the final fit
