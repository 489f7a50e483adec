"""fit_scan's atlas branch: a closed object becomes a format-2 bundle scored on every point."""

import json

import numpy as np
import pytest
import trimesh

from client_py.atlas_format import read_atlas
from fitter.fitting.atlas.measure import closest_points_on_triangles, point_mesh_distance
from fitter.fitting.atlas.pipeline import wants_atlas
from fitter.fitting.io import Scan
from fitter.fitting.io.scan import make_scan, new_source
from fitter.fitting.options import OPTION, FitOptions, OptionError
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


def test_auto_rule_keeps_one_patch_for_a_height_field_and_an_atlas_for_a_closed_object():
    x, y = np.meshgrid(np.linspace(0, 1, 60), np.linspace(0, 1, 60))
    relief = np.column_stack([x.ravel(), y.ravel(), 0.05 * np.sin(6 * x.ravel()) * y.ravel()])
    assert not wants_atlas(Scan.from_array(relief), None)
    assert wants_atlas(_mesh_scan(trimesh.creation.icosphere(subdivisions=3)), None)
    assert not wants_atlas(_mesh_scan(trimesh.creation.icosphere(subdivisions=3)), 1)
    assert wants_atlas(Scan.from_array(relief), 30)


def test_patches_option_spells_auto_and_counts():
    assert OPTION["patches"].parse("auto") is None
    assert OPTION["patches"].parse("120") == 120
    with pytest.raises(OptionError, match="patches must be"):
        OPTION["patches"].parse("0")


def test_closed_sphere_becomes_a_watertight_atlas_bundle(tmp_path):
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=50.0)
    bundle = fit_scan(_mesh_scan(mesh, "sphere"), tmp_path / "sphere", FitOptions(patches=60))
    manifest = json.loads((bundle.path / "manifest.json").read_text())
    assert manifest["format_version"] == 2
    base = manifest["base"]
    assert base["kind"] == "atlas" and base["border_edges"] == 0
    atlas, _ = read_atlas((bundle.path / "base.tsa").read_bytes())
    assert len(atlas.quads) == base["patches"] and atlas.edges.border_edges == []
    stats = manifest["stats_all_points"]
    assert stats["points"] == len(mesh.vertices)  # every scan point, no covered subset
    assert stats["rms_relative"] < 0.002 and manifest["coverage"]["uncovered_points"] == 0
    packs = {f"detail/{p['level']}/{p['group']}.tsdp" for p in manifest["tiles"]["detail"]["packs"]}
    assert set(manifest["files"]) == {"base.tsa", "error.png", "error.ply"} | packs
    assert all((bundle.path / name).stat().st_size == size
               for name, size in manifest["files"].items())


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


def test_thin_to_count_keeps_about_the_target():
    from fitter.fitting.io.thin import thin_to_count

    points = np.random.default_rng(1).random((50_000, 3))
    for target, slack in ((5_000, 1.0), (5_000, 1.2), (60_000, 1.0)):
        keep = thin_to_count(points, target, slack)
        assert len(keep) <= slack * target and len(keep) > 0.3 * min(target, len(points))
        assert np.all(np.diff(keep) > 0)  # ascending, no repeats: a subset in order
