"""Atlas bundles (manifest version 2) through client_py.bundle, the worker session, the CLI,
the server's checks and the gallery thumbnail; version-1 behaviour is covered elsewhere and
must not change (tests/test_session.py, test_fuzz.py, test_cli_tessellate.py)."""

from __future__ import annotations

import io
import json
from collections import Counter

import numpy as np
import pytest
import trimesh
from atlas_bundle import SPANS_PER_TILE, write_atlas_bundle

from client_py.atlas_detail import pack_name, read_pack, write_pack
from client_py.atlas_format import read_atlas
from client_py.atlas_mesh import tessellate_atlas
from client_py.bundle import (
    ManifestError,
    atlas_level_detail,
    atlas_resolution,
    base_file,
    check_file_name,
    manifest_version,
    plan_level,
    plan_levels,
    tessellate_bundle,
    write_level_ply,
)
from client_py.errors import PatchFormatError
from client_py.session import WorkerSession

LEVELS = 3


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    folder = tmp_path_factory.mktemp("atlas") / "sphere"
    write_atlas_bundle(folder, k=1, levels=LEVELS, base_resolution=5)
    return folder


def _manifest(folder):
    return json.loads((folder / "manifest.json").read_text())


def _reader(folder, asked=None):
    def read(name):
        if asked is not None:
            asked.append(name)
        return (folder / name).read_bytes()
    return read


def _boundary_edges(indices) -> int:
    """Mesh edges not used by exactly two triangles (0 on a closed welded surface)."""
    tri = np.frombuffer(indices, dtype=np.uint32).reshape(-1, 3)
    edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    counts = Counter(map(tuple, edges.tolist()))
    return sum(1 for c in counts.values() if c != 2)


# ------------------------------------------------------------------ the plan
def test_the_version_dispatch_and_an_unknown_version():
    assert manifest_version({}) == 1 and manifest_version({"format_version": 2}) == 2
    for bad in (3, "2", True, None):
        with pytest.raises(ManifestError, match=r"format_version .* is not a version this "
                           r"reader knows: 1, 2"):
            plan_level({"format_version": bad})


def test_plan_level_lists_the_packs_of_levels_0_to_L_with_their_bytes(bundle):
    manifest = _manifest(bundle)
    assert base_file(manifest) == "base.tsa"
    packs = manifest["tiles"]["detail"]["packs"]
    for level in range(-1, LEVELS):
        plan = plan_level(manifest, level)
        wanted = sorted((p["level"], p["group"]) for p in packs if p["level"] <= level)
        assert plan.detail_files == tuple(pack_name(k, g) for k, g in wanted)
        assert plan.detail_bytes == sum((bundle / name).stat().st_size
                                        for name in plan.detail_files)
        assert plan.texture_nodes == () and plan.texture_bytes == 0
        expected = 5 if level < 0 else min(129, 2 * SPANS_PER_TILE * 2**level + 1)
        assert plan.resolution == expected == atlas_resolution(manifest, level)
    assert plan_level(manifest) == plan_level(manifest, LEVELS - 1)
    assert [p.level for p in plan_levels(manifest)] == list(range(LEVELS))
    assert plan_level(manifest, 0).rms == manifest["tiles"]["detail"]["levels"][0]["rms"]
    with pytest.raises(ValueError, match=r"level must be an integer in -1\.\.2"):
        plan_level(manifest, LEVELS)


def test_the_resolution_rule_is_capped_at_129():
    manifest = {"format_version": 2, "base": {"file": "base.tsa", "kind": "atlas",
                                              "patches": 1, "resolution": 2},
                "tiles": {"detail": {"spans_per_tile": 8, "levels": [
                    {"level": k} for k in range(5)],
                    "groups": [{"first": 0, "count": 1, "center": [0, 0, 0], "radius": 1}],
                    "packs": []}}}
    assert [atlas_resolution(manifest, k) for k in range(-1, 5)] == [2, 17, 33, 65, 129, 129]


def test_pack_and_atlas_names_are_bundle_names_and_others_are_not():
    for name in ("base.tsa", "detail/0/0.tsdp", "detail/3/117.tsdp"):
        assert check_file_name(name, "x") == name
    for name in ("detail/0/00.tsdp", "detail/0/-1.tsdp", "detail/x/0.tsdp", "detail/0/0.tsdp/..",
                 "base.tsa/../x", "detail/0/0_0.tsdp"):
        with pytest.raises(ManifestError):
            check_file_name(name, "x")
    # a version-1 manifest's base stays base.tsp, a version-2 one's base.tsa
    with pytest.raises(ManifestError, match="is not 'base.tsp'"):
        base_file({"base": {"file": "base.tsa"}})
    with pytest.raises(ManifestError, match="is not 'base.tsa'"):
        base_file({"format_version": 2, "base": {"file": "base.tsp"}})


# ------------------------------------------------------------------ malformed manifests
def _detail(m):
    return m["tiles"]["detail"]


MALFORMED = [
    (lambda m: m["base"].update(kind="patch"), r"base\.kind must be 'atlas'"),
    (lambda m: m["base"].update(patches=0), r"base\.patches must be an integer in 1\.\.65536"),
    (lambda m: m["base"].pop("resolution"), r"base\.resolution must be an integer in 2\.\.129"),
    (lambda m: m["base"].update(resolution=1000), r"base\.resolution"),
    (lambda m: m["base"].update(resolution=7), "cannot be welded"),
    (lambda m: m["base"].update(file="../base.tsa"), r"base\.file .*climbs out"),
    (lambda m: m["tiles"].update(texture={"nodes": []}), r"tiles\.texture\.format must be 'webp'"),
    (lambda m: _detail(m).update(groups=[]), r"tiles\.detail\.groups must be a list of 1\.\.6"),
    (lambda m: _detail(m).update(groups="x"), r"tiles\.detail\.groups must be a list"),
    (lambda m: _detail(m)["groups"][1].update(first=3), r"groups\[1\] must hold patches first = 1"),
    (lambda m: _detail(m)["groups"][5].update(count=2), r"groups\[5\] must hold patches"),
    (lambda m: _detail(m)["groups"].pop(), r"cover patches 0\.\.4; every patch 0\.\.5"),
    (lambda m: _detail(m)["groups"][0].update(center=[0, 0]), r"groups\[0\]\.center must be 3"),
    (lambda m: _detail(m)["groups"][0].update(radius=-1), r"groups\[0\]\.radius must be a finite"),
    (lambda m: _detail(m)["groups"].__setitem__(2, None), r"groups\[2\] must be a JSON object"),
    (lambda m: _detail(m).update(packs={}), r"tiles\.detail\.packs must be a list"),
    (lambda m: _detail(m)["packs"].extend(_detail(m)["packs"]), r"packs must be a list of at most"),
    (lambda m: _detail(m)["packs"].__setitem__(1, dict(_detail(m)["packs"][0])),
     r"packs\[1\] repeats the pack of level 0, group 0"),
    (lambda m: _detail(m)["packs"][0].update(level=9), r"packs\[0\] needs an integer level in "
                                                       r"0\.\.2 and group in 0\.\.5"),
    (lambda m: _detail(m)["packs"][0].update(group="0"), r"packs\[0\] needs an integer level"),
    (lambda m: _detail(m)["packs"][0].update(bytes=-3), r"packs\[0\]\.bytes must be a byte count"),
    (lambda m: _detail(m)["packs"][0].update(geometric_error="big"),
     r"packs\[0\]\.geometric_error must be a finite number >= 0 or null"),
    (lambda m: _detail(m)["levels"][1].update(resolution=10), r"levels\[1\]\.resolution is 10"),
    (lambda m: _detail(m)["levels"][1].update(level=0), r"levels\[1\] must describe level 1"),
    (lambda m: _detail(m)["levels"][0].update(max=[]), r"levels\[0\]\.max must be a finite"),
    (lambda m: _detail(m).update(spans_per_tile=0), "spans_per_tile must be a positive integer"),
    (lambda m: _detail(m).update(levels=[{"level": k} for k in range(9)]), "at most 8 levels"),
]


@pytest.mark.parametrize(("change", "match"), MALFORMED)
def test_a_malformed_atlas_manifest_is_a_manifest_error(bundle, change, match):
    manifest = _manifest(bundle)
    change(manifest)
    asked = []
    with pytest.raises(ManifestError, match=match):
        plan_levels(manifest)
        plan_level(manifest, -1)
    with pytest.raises(ManifestError, match=match):
        tessellate_bundle(manifest, _reader(bundle, asked), -1)
    assert asked == []  # refused before any file is read
    with pytest.raises(ManifestError, match=match):
        WorkerSession().read_manifest(json.dumps(manifest))


def test_a_pack_of_another_group_or_level_is_a_format_error(bundle, tmp_path):
    manifest = _manifest(bundle)
    read = _reader(bundle)
    # pack (0, 1) served where (0, 0) is expected: patches outside group 0
    with pytest.raises(PatchFormatError, match=r"detail/0/0\.tsdp holds patch 1, outside "
                       r"group 0's patches 0\.\.0"):
        tessellate_bundle(manifest, lambda n: read("detail/0/1.tsdp" if n == "detail/0/0.tsdp"
                                                   else n), 0)
    with pytest.raises(PatchFormatError, match=r"detail/1/0\.tsdp holds level 0"):
        tessellate_bundle(manifest, lambda n: read("detail/0/0.tsdp" if n == "detail/1/0.tsdp"
                                                   else n), 1)
    with pytest.raises(PatchFormatError, match=r"\(detail pack detail/0/2\.tsdp\)"):
        tessellate_bundle(manifest, lambda n: read(n)[:-1] if n == "detail/0/2.tsdp"
                          else read(n), 0)
    manifest["base"]["patches"] = 12
    for group in manifest["tiles"]["detail"]["groups"]:
        group["first"], group["count"] = 2 * group["first"], 2
    with pytest.raises(ManifestError, match="base.patches is 12 but base.tsa holds 6"):
        tessellate_bundle(manifest, read, -1)


# ------------------------------------------------------------------ the mesh and the PLY
@pytest.mark.parametrize("kernel", ["python", "numpy"])
def test_tessellate_bundle_is_one_welded_closed_mesh_at_every_level(bundle, kernel):
    manifest = _manifest(bundle)
    atlas, _ = read_atlas((bundle / "base.tsa").read_bytes())
    previous = None
    for level in range(-1, LEVELS):
        mesh = tessellate_bundle(manifest, _reader(bundle), level, kernel=kernel)
        assert _boundary_edges(mesh.indices) == 0
        r = plan_level(manifest, level).resolution
        assert mesh.vertex_count == tessellate_atlas(atlas, r).vertex_count
        tm = trimesh.Trimesh(np.frombuffer(mesh.positions, np.float32).reshape(-1, 3),
                             np.frombuffer(mesh.indices, np.uint32).reshape(-1, 3), process=False)
        assert tm.is_watertight and tm.is_winding_consistent
        if previous is not None and level >= 0:
            # the same surface: the level's detail moves it by at most its tiles' amplitude
            assert abs(tm.volume - previous) < 0.15 * previous
        previous = tm.volume
    # the detail is applied: level 2 differs from the base evaluated on the same grid
    fine = tessellate_bundle(manifest, _reader(bundle), 2, kernel=kernel)
    bare = tessellate_atlas(atlas, plan_level(manifest, 2).resolution, kernel=kernel)
    delta = np.abs(np.frombuffer(fine.positions, np.float32) - np.frombuffer(bare.positions,
                                                                              np.float32))
    assert 1e-4 < delta.max() < 0.2


def test_the_level_detail_is_every_tile_of_the_packs(bundle):
    manifest = _manifest(bundle)
    detail = atlas_level_detail(manifest, _reader(bundle), 1)
    assert sorted(detail) == list(range(6))
    assert all(sorted((t.level, t.i, t.j) for t in tiles) ==
               [(0, 0, 0), (1, 0, 0), (1, 0, 1), (1, 1, 0), (1, 1, 1)]
               for tiles in detail.values())


def test_write_level_ply_is_the_cli_s_output_and_trimesh_reads_it_watertight(bundle, tmp_path,
                                                                              capsys):
    from fitter.cli import main

    manifest = _manifest(bundle)
    atlas, _ = read_atlas((bundle / "base.tsa").read_bytes())
    for level in (-1, 1):
        out = tmp_path / f"level{level}.ply"
        assert main(["tessellate", str(bundle), "--level", str(level), "-o", str(out)]) == 0
        assert f"level {level}, 6 patches" in capsys.readouterr().out
        detail = atlas_level_detail(manifest, _reader(bundle), level)
        data, mesh = write_level_ply(atlas, detail, level, plan_level(manifest, level).resolution,
                                     bundle.name, units="mm")
        assert out.read_bytes() == data
        assert b"comment units mm\n" in data and b"one welded mesh" in data
        tm = trimesh.load(io.BytesIO(data), file_type="ply", process=False)
        assert len(tm.vertices) == mesh.vertex_count
        tm.merge_vertices()
        assert tm.is_watertight
    # no --resolution: the finest level's full detail
    out = tmp_path / "finest.ply"
    assert main(["tessellate", str(bundle), "-o", str(out)]) == 0
    r = plan_level(manifest).resolution
    assert f"{tessellate_atlas(atlas, r).vertex_count} vertices" in capsys.readouterr().out
    assert main(["tessellate", str(bundle), "--texture", "-o", str(out)]) == 2
    assert "--texture: the bundle has no colour" in capsys.readouterr().err
    assert main(["tessellate", str(bundle), "--level", "7", "-o", str(out)]) == 2


def test_write_level_ply_refuses_a_finer_tile(bundle):
    atlas, _ = read_atlas((bundle / "base.tsa").read_bytes())
    detail = atlas_level_detail(_manifest(bundle), _reader(bundle), 1)
    with pytest.raises(ValueError, match="finer than level 0"):
        write_level_ply(atlas, detail, 0, 5, "x")
    with pytest.raises(ValueError, match="must be a mapping of patch index"):
        write_level_ply(atlas, [], 0, 5, "x")


# ------------------------------------------------------------------ the worker session
def _session(bundle, kernel="python"):
    session = WorkerSession(kernel=kernel)
    facts = session.load_atlas((bundle / "base.tsa").read_bytes(), "base.tsa")
    session.read_manifest((bundle / "manifest.json").read_text())
    return session, facts


def test_the_session_loads_an_atlas_and_refines_groups_watertight(bundle):
    session, facts = _session(bundle)
    assert facts["kind"] == "atlas" and facts["patches"] == 6 and facts["units"] == "mm"
    lo, hi = facts["bbox"]
    assert all(a < -0.9 and b > 0.9 for a, b in zip(lo, hi, strict=True))
    refinement = session.atlas_refinement()
    assert refinement["levels"] == LEVELS and refinement["base_error"] == 0.03
    # a bundle since issue 14: base.max is every point's, samples_max the packs' measure
    manifest = json.loads((bundle / "manifest.json").read_text())
    manifest["tiles"]["detail"]["base"].update(max=0.02, samples_max=0.05)
    restated = WorkerSession(kernel="python")
    restated.load_atlas((bundle / "base.tsa").read_bytes(), "base.tsa")
    restated.read_manifest(json.dumps(manifest))
    assert restated.atlas_refinement()["base_error"] == 0.05
    assert refinement["resolutions"] == [5, 5, 9, 17]
    groups = refinement["groups"]
    assert [(g["first"], g["count"]) for g in groups] == [(g, 1) for g in range(6)]
    assert groups[2]["packs"] == [pack_name(k, 2) for k in range(LEVELS)]
    assert groups[2]["errors"] == [0.01, 0.005, 0.0025]
    base = session.atlas_mesh([-1] * 6)
    assert _boundary_edges(base.indices) == 0 and base.vertex_count == 6 * 9 + 12 * 3 + 8
    with pytest.raises(ValueError, match="needs pack detail/0/0.tsdp, which was not handed over"):
        session.atlas_mesh([0, -1, -1, -1, -1, -1])
    for name in groups[0]["packs"] + groups[3]["packs"][:2]:
        assert session.add_pack(name, (bundle / name).read_bytes())["tiles"] >= 1
    assert session.holds_pack("detail/1/3.tsdp") and not session.holds_pack("detail/2/3.tsdp")
    mixed = session.atlas_mesh([2, -1, -1, 1, -1, -1])
    assert _boundary_edges(mixed.indices) == 0
    # group 0 at level 2 is the bundle's level 2 there: same vertices as a whole level-2 mesh
    # of patch 0's interior
    full = tessellate_bundle(_manifest(bundle), _reader(bundle), 2, kernel="python")
    inner = {tuple(np.round(p, 5)) for p, f in zip(
        np.frombuffer(full.positions, np.float32).reshape(-1, 3), full.patches, strict=True)
        if f == 0}
    mine = {tuple(np.round(p, 5)) for p, f in zip(
        np.frombuffer(mixed.positions, np.float32).reshape(-1, 3), mixed.patches, strict=True)
        if f == 0}
    assert len(inner & mine) >= 15 * 15  # patch 0's interior vertices agree
    session.drop_packs(["detail/2/0.tsdp", "not/held"])
    with pytest.raises(ValueError, match="needs pack detail/2/0.tsdp"):
        session.atlas_mesh([2, -1, -1, 1, -1, -1])
    with pytest.raises(ValueError, match="levels has 2 values; the atlas has 6 groups"):
        session.atlas_mesh([0, 0])
    with pytest.raises(ValueError, match=r"levels\[1\] = 5; an int in -1\.\.2"):
        session.atlas_mesh([-1, 5, -1, -1, -1, -1])


def test_the_session_refuses_foreign_packs(bundle):
    session, _ = _session(bundle)
    with pytest.raises(ValueError, match="is not a pack the manifest lists"):
        session.add_pack("detail/9/0.tsdp", b"")
    with pytest.raises(ValueError, match="is not a pack the manifest lists"):
        session.add_pack("../base.tsa", b"")
    with pytest.raises(PatchFormatError, match=r"outside group 0's"):
        session.add_pack("detail/0/0.tsdp", (bundle / "detail/0/1.tsdp").read_bytes())
    with pytest.raises(PatchFormatError, match=r"\(detail pack detail/0/0\.tsdp\)"):
        session.add_pack("detail/0/0.tsdp", b"TSDP" + bytes(20))
    assert not session.holds_pack("detail/0/0.tsdp")


def test_the_session_s_level_ply_is_the_cli_s(bundle, tmp_path):
    from fitter.cli import main

    session, _ = _session(bundle)
    plan = plan_level(_manifest(bundle), 1)
    held = plan.detail_files[:4]
    for name in held:
        session.add_pack(name, (bundle / name).read_bytes())
    fresh = {name: (bundle / name).read_bytes() for name in plan.detail_files[4:]}
    with pytest.raises(ValueError, match="neither handed over nor sent"):
        session.level_ply(1)
    ply = session.level_ply(1, fresh)
    out = tmp_path / "cli.ply"
    assert main(["tessellate", str(bundle), "--level", "1", "-o", str(out)]) == 0
    # the same mesh; only the source comment differs (the session names base.tsa)
    assert ply.data.replace(b"source base.tsa", b"source sphere") == out.read_bytes()
    assert ply.level == 1 and ply.resolution == 9
    with pytest.raises(ValueError, match="are not packs of level 0"):
        session.level_ply(0, fresh)
    with pytest.raises(ValueError, match="a colour pack sent must be"):
        session.level_ply(1, fresh, [{"level": 0}])
    with pytest.raises(ValueError, match=r"not in this level's plan \(no colour\)"):
        session.level_ply(1, fresh, [{"file": "texture/0/0.webp", "width": 1, "height": 1,
                                      "rgb": b"abc"}])
    base = session.level_ply(-1)
    assert base.level == -1 and base.resolution == 5


def test_loading_a_patch_forgets_the_atlas(bundle):
    from nurbs_cases import random_surface

    from client_py import write_patch

    session, _ = _session(bundle)
    surface = random_surface(np.random.default_rng(1), 2, 2, 5, 5)
    session.load_patch(write_patch(surface), "base.tsp")
    with pytest.raises(RuntimeError, match="no atlas is loaded"):
        session.atlas_refinement()


# ------------------------------------------------------------------ the server
def test_the_server_accepts_serves_and_thumbnails_an_atlas_bundle(bundle, tmp_path):
    import shutil

    from PIL import Image

    from fitter.collection.bundles import BundleError, parse_manifest
    from fitter.server import create_app

    root = tmp_path / "collection"
    shutil.copytree(bundle, root / "sphere")
    broken = root / "broken"
    shutil.copytree(bundle, broken)
    manifest = _manifest(bundle)
    manifest["tiles"]["detail"]["groups"].pop()
    (broken / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BundleError, match=r"format_version 2 \(atlas\): .*every patch 0\.\.5"):
        parse_manifest(broken / "manifest.json")
    assert parse_manifest(root / "sphere" / "manifest.json")["format_version"] == 2
    app = create_app({"TESSERA_COLLECTION": str(root), "TESSERA_PYODIDE_SNAPSHOT": False,
                      "TESTING": True})
    client = app.test_client()
    listed = client.get("/api/objects").get_json()
    assert [o["id"] for o in listed] == ["sphere"]
    assert listed[0]["patches"] == manifest["base"]["patches"] and listed[0]["grid"] is None
    gallery = client.get("/").get_data(as_text=True)
    assert f"atlas of {manifest['base']['patches']:,} patches" in gallery
    for name in ("base.tsa", "detail/1/4.tsdp"):
        response = client.get(f"/bundles/sphere/{name}", headers={"Accept-Encoding": "gzip"})
        assert response.status_code == 200
        assert response.mimetype == "application/octet-stream"
        assert "Content-Encoding" not in response.headers  # zlib / range coded already
        assert response.data == (bundle / name).read_bytes()
    page = client.get("/objects/sphere/")
    assert page.status_code == 200 and b"/bundles/sphere/base.tsa" in page.data
    thumb = client.get("/objects/sphere/thumbnail.png")
    assert thumb.status_code == 200 and thumb.mimetype == "image/png"
    image = np.asarray(Image.open(io.BytesIO(thumb.data)))
    alpha = image[..., 3] > 128
    # a sphere seen from the front: a round, filled silhouette in the card's middle
    rows, cols = np.nonzero(alpha)
    height, width = np.ptp(rows) + 1, np.ptp(cols) + 1
    assert 0.9 < height / width < 1.1 and alpha.sum() > 0.7 * np.pi / 4 * height * width
    shade = image[..., :3].mean(axis=2)[alpha]
    assert shade.std() > 5  # shaded, not flat


def test_the_thumbnail_of_a_degenerate_atlas_is_a_reason(tmp_path):
    from atlas_cases import sphere_atlas

    from client_py.atlas import AtlasSurface
    from client_py.atlas_format import write_atlas
    from fitter.server.thumbnail import render_atlas_thumbnail

    a = sphere_atlas(1)
    flat = AtlasSurface(a.degree, a.spans, [(0.0, 0.0, 0.0)] * len(a.vertices), a.quads,
                        [(0.0, 0.0, 0.0)] * len(a.edge_points),
                        [(0.0, 0.0, 0.0)] * len(a.face_points))
    with pytest.raises(ValueError, match="spans no area|degenerate"):
        render_atlas_thumbnail(write_atlas(flat, bits=8))
    with pytest.raises(PatchFormatError):
        render_atlas_thumbnail(b"TSA1" + bytes(40))


def test_write_pack_helper_round_trips(bundle):
    level, tiles = read_pack((bundle / "detail/1/2.tsdp").read_bytes())
    assert level == 1 and list(tiles) == [2]
    assert read_pack(write_pack(level, tiles)) == (level, tiles)


# ------------------------------------------------------------------ fit-collection, fuzz
def test_fit_collection_checks_an_atlas_bundle_s_tile_versions(bundle, tmp_path):
    from fitter.collection.batch import is_up_to_date, stored_options
    from fitter.fitting.options import FitOptions

    options = FitOptions()
    manifest = _manifest(bundle)
    manifest["provenance"]["sha256"] = "ab" * 32
    manifest["options"] = stored_options(options)
    folder = tmp_path / "b"
    folder.mkdir()
    (folder / "manifest.json").write_text(json.dumps(manifest))
    assert is_up_to_date(folder, "ab" * 32, options)
    for key, old in (("tile_format_version", 1), ("format_version", 0)):
        stale = json.loads(json.dumps(manifest))
        stale["tiles"]["detail"][key] = old
        (folder / "manifest.json").write_text(json.dumps(stale))
        assert not is_up_to_date(folder, "ab" * 32, options)


def _json_values():
    from hypothesis import strategies as st

    scalars = st.none() | st.booleans() | st.integers(-3, 200) | st.floats(
        allow_nan=False, allow_infinity=False) | st.text(max_size=12)
    return st.recursive(scalars, lambda inner: st.lists(inner, max_size=4)
                        | st.dictionaries(st.text(max_size=8), inner, max_size=4), max_leaves=8)


def test_any_change_to_an_atlas_manifest_is_planned_or_a_manifest_error(bundle):
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    seed = _manifest(bundle)

    def paths(value, prefix=()):
        yield prefix
        if isinstance(value, dict):
            for key, item in value.items():
                yield from paths(item, (*prefix, key))
        elif isinstance(value, list):
            for k, item in enumerate(value):
                yield from paths(item, (*prefix, k))

    where = [p for p in paths(seed) if p and p[0] in ("base", "tiles", "format_version")]

    @settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
    @given(st.lists(st.tuples(st.sampled_from(where), _json_values()), min_size=1, max_size=3))
    def check(changes):
        manifest = json.loads(json.dumps(seed))
        for path, value in changes:
            node = manifest
            try:
                for key in path[:-1]:
                    node = node[key]
                node[path[-1]] = value
            except (KeyError, IndexError, TypeError):
                continue  # an earlier change replaced the parent
        try:
            plans = plan_levels(manifest)
            plan_level(manifest, -1)
        except ManifestError:
            return
        for plan in plans:  # what was planned names only bundle files
            assert all(check_file_name(name, "x") == name for name in plan.detail_files)

    check()


# ------------------------------------------------------------------ a fitted atlas bundle
def test_a_fitted_atlas_bundle_reads_everywhere(tmp_path):
    """A real `fit_scan` atlas bundle (the lead's fitter.fitting.atlas.pipeline; skipped
    until it is there): planned, tessellated watertight at every level, loaded by the
    session, accepted by the server and thumbnailed."""
    pytest.importorskip("fitter.fitting.atlas.pipeline", reason="the atlas fit is not there yet")
    from fitter.collection.bundles import parse_manifest
    from fitter.fitting.io.scan import make_scan, new_source
    from fitter.fitting.options import FitOptions
    from fitter.fitting.pipeline import fit_scan
    from fitter.server.thumbnail import render_atlas_thumbnail

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=50.0)
    vertices = sphere.vertices * (1 + 0.03 * np.sin(sphere.vertices[:, :1] / 10))
    source = new_source("bumpy", None, "array", compression=None, reader="array")
    scan = make_scan("bumpy", vertices, faces=np.asarray(sphere.faces), source=source)
    folder = tmp_path / "bumpy"
    fit_scan(scan, folder, FitOptions(patches=60))
    manifest = parse_manifest(folder / "manifest.json")
    assert manifest_version(manifest) == 2
    for plan in [plan_level(manifest, -1), *plan_levels(manifest)]:
        mesh = tessellate_bundle(manifest, _reader(folder), plan.level)
        assert _boundary_edges(mesh.indices) == 0
        positions = np.frombuffer(mesh.positions, np.float32).reshape(-1, 3)
        radius = np.linalg.norm(positions, axis=1)
        assert np.abs(radius - 50).max() < 5  # the bumpy sphere, not fins or spikes
    session, _ = _session(folder)
    assert len(session.atlas_refinement()["resolutions"]) == len(plan_levels(manifest)) + 1
    png = render_atlas_thumbnail((folder / "base.tsa").read_bytes(), manifest.get("view"))
    assert png.startswith(b"\x89PNG")


# ------------------------------------------------------------------ welded packs
def test_a_welded_bundle_draws_the_same_mesh_as_its_tiles_unwelded(tmp_path):
    """Welded packs (version 4, each shared border coefficient coded once a pack) through
    every reader: tessellate_bundle (the atlas read once), atlas_level_detail without the
    atlas (it reads base.tsa), the session with one group's pack alone; the mesh is the one
    the same tiles draw in packs without welding, bit for bit."""
    folder = tmp_path / "welded"
    manifest = write_atlas_bundle(folder, k=2, levels=2, welded=True)
    atlas, _ = read_atlas((folder / "base.tsa").read_bytes())
    plain = tmp_path / "plain"
    plain.mkdir()
    for name in manifest["files"]:
        data = (folder / name).read_bytes()
        if name.endswith(".tsdp"):
            assert data[4] == 4 and data[21] == 1
            level, tiles = read_pack(data, atlas)
            data = write_pack(level, tiles)
        (plain / name).parent.mkdir(parents=True, exist_ok=True)
        (plain / name).write_bytes(data)
    (plain / "manifest.json").write_text(json.dumps(manifest))
    smaller = [len((folder / n).read_bytes()) < len((plain / n).read_bytes())
               for n in manifest["files"] if n.endswith(".tsdp")]
    assert all(smaller)
    for level in (0, 1):
        a = tessellate_bundle(manifest, _reader(folder), level, kernel="python")
        b = tessellate_bundle(manifest, _reader(plain), level, kernel="python")
        assert a.positions == b.positions and a.indices == b.indices
        assert _boundary_edges(a.indices) == 0
        assert atlas_level_detail(manifest, _reader(folder), level) == \
            atlas_level_detail(manifest, _reader(plain), level)
    session, _ = _session(folder)
    name = pack_name(1, 4)
    assert session.add_pack(name, (folder / name).read_bytes())["tiles"] == 4 * 4
    assert session._packs[name][2] == read_pack((plain / name).read_bytes())[1]
    with pytest.raises(ValueError, match="needs the atlas"):
        read_pack((folder / name).read_bytes())
