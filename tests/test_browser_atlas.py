"""An atlas bundle (manifest format_version 2) in headless Chromium: the viewer draws the
welded atlas with no console error, refines the groups a close camera looks at (and only
those), downloads one welded PLY per level that equals `tessera tessellate`'s, and the
3DHOP page loads the same PLY. The bundle is made without the fitter (tests/atlas_bundle.py):
a sphere of 24 patches in 6 groups, 3 detail levels."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from atlas_bundle import write_atlas_bundle
from live import VIEWER_READY as READY
from live import download_ply, open_viewer, serve_collection

from fitter.collection.bundles import served_manifest

pytestmark = pytest.mark.browser

# drawn by group: 6 groups (a cube face each) of 2 x 2 patches at 5 samples a side, each its
# triangles of the welded atlas (9 x 9 vertices, its seam vertices copies of its neighbours')
BASE_VERTICES = 6 * 9 * 9


@pytest.fixture(scope="module")
def atlas_collection(tmp_path_factory):
    root = tmp_path_factory.mktemp("atlas-collection")
    write_atlas_bundle(root / "sphere", k=2, levels=3, base_resolution=5)
    write_atlas_bundle(root / "walled", k=2, levels=3, base_resolution=5, welded=True,
                       walls=0.3, title="Walled sphere")
    return root


@pytest.fixture(scope="module")
def atlas_server(atlas_collection):
    with serve_collection(atlas_collection) as live:
        yield live


@pytest.fixture(scope="module")
def atlas_page(browser, atlas_server):
    with open_viewer(browser, f"{atlas_server.url}/objects/sphere/", 30_000) as page:
        yield page


def test_the_atlas_shows_welded_with_no_error(atlas_page, atlas_collection):
    assert atlas_page.evaluate("document.body.dataset.error") is None
    stats = atlas_page.evaluate("window.tessera.stats")
    assert stats["atlas_patches"] == 24
    assert stats["atlas_levels"] == [-1] * 6
    # the first frame: 24 patches at 5 samples a side, welded: 26 corners + 48 edges x 3 +
    # 24 x 9 inside
    assert stats["vertices"] == 26 + 48 * 3 + 24 * 9
    assert stats["triangles"] == 24 * 2 * 16
    manifest = json.loads((atlas_collection / "sphere" / "manifest.json").read_text())
    expected = len(served_manifest(manifest)) + (atlas_collection / "sphere" / "base.tsa"
                                                 ).stat().st_size
    assert stats["bytes_downloaded"] == expected
    assert "24 patches" in atlas_page.locator("#fact-grid").inner_text()
    assert atlas_page.locator("#toggle-error").is_enabled()  # the atlas's error_raster
    assert atlas_page.errors == []
    shot = atlas_page.locator("#view").screenshot()
    from io import BytesIO

    from PIL import Image
    rgb = np.asarray(Image.open(BytesIO(shot)).convert("RGB")).astype(int)
    differs = np.abs(rgb - rgb[2, -3]).max(axis=2) > 30
    assert differs.mean() > 0.05


def _canvas(page):
    from io import BytesIO

    from PIL import Image
    return np.asarray(Image.open(BytesIO(page.locator("#view").screenshot()))
                      .convert("RGB")).astype(int)


def test_the_atlas_error_map_colours_it_with_the_panels_max(atlas_page, atlas_collection):
    """The Error map button of an atlas: the worker colours every group per vertex from the
    bundle's error_raster.bin (fetched once, counted), in viridis (blue over red, where the
    plain material is grey), the legend ending at the panel's max; pressed again, the plain
    mesh is back."""
    before = _canvas(atlas_page)
    atlas_page.click("#toggle-error")
    try:
        atlas_page.wait_for_function("!document.getElementById('legend').hidden && "
                                     "!document.body.dataset.errorMapBusy", timeout=60_000)
        assert atlas_page.inner_text("#legend-max") == atlas_page.inner_text("#fact-max") != "—"
        assert "no scan point" in atlas_page.inner_text("#legend")
        stats = atlas_page.evaluate("window.tessera.stats")
        size = (atlas_collection / "sphere" / "error_raster.bin").stat().st_size
        assert stats["atlas_error_map_bytes"] == size
        after = _canvas(atlas_page)
        changed = np.abs(after - before).max(axis=2) > 30
        assert changed.mean() > 0.05
        assert after[changed][:, 2].mean() > after[changed][:, 0].mean()  # viridis: blue
    finally:
        atlas_page.click("#toggle-error")
    atlas_page.wait_for_function("document.getElementById('legend').hidden && "
                                 "!document.body.dataset.errorMapBusy", timeout=60_000)
    assert np.abs(_canvas(atlas_page) - before).max(axis=2).mean() < 5
    assert atlas_page.errors == []


def test_zooming_refines_the_groups_in_view(atlas_page, atlas_collection):
    manifest = json.loads((atlas_collection / "sphere" / "manifest.json").read_text())
    groups = manifest["tiles"]["detail"]["groups"]
    # close to group 0's sphere, looking at its centre from outside
    centre = np.array(groups[0]["center"])
    outward = centre / np.linalg.norm(centre)
    position = (centre + 0.6 * outward).tolist()
    stats = atlas_page.evaluate("([p, t]) => window.tessera.atlasView(p, t)",
                                [position, centre.tolist()])
    levels = stats["atlas_levels"]
    assert levels[0] == 2, levels  # the camera is inside its bounding sphere: the finest
    assert stats["atlas_packs_loaded"] >= levels[0] + 1
    assert stats["atlas_pack_bytes"] > 0 and stats["atlas_updates"] >= 1
    assert stats["vertices"] > BASE_VERTICES
    # only the groups whose level changed and their neighbours (whose seams with them moved)
    # were tessellated, the others kept; the face opposite group 0 is no neighbour of it
    from client_py.session import WorkerSession

    session = WorkerSession(kernel="python")
    session.load_atlas((atlas_collection / "sphere" / "base.tsa").read_bytes(), "base.tsa")
    session.read_manifest(json.dumps(manifest))
    neighbours = [g["neighbours"] for g in session.atlas_refinement()["groups"]]
    changed = {g for g, k in enumerate(levels) if k >= 0}
    changed |= {h for g in changed for h in neighbours[g]}
    assert stats["atlas_parts_made"] <= len(changed)
    assert stats["atlas_parts_made"] + stats["atlas_parts_cached"] == 6
    assert "groups refined" in atlas_page.locator("#fact-detail").inner_text()
    # looking away from the object: no group is in view, all go back to the base
    outside = (centre + 2 * outward).tolist()  # beyond every group's sphere
    away = (centre + 5 * outward).tolist()
    stats = atlas_page.evaluate("([p, t]) => window.tessera.atlasView(p, t)", [outside, away])
    assert stats["atlas_levels"] == [-1] * 6
    assert stats["vertices"] == BASE_VERTICES
    assert stats["atlas_parts_made"] == 0  # the base of every group was kept: nothing made
    # far away: a coarser choice than close up, never finer
    far = (centre + 30 * outward).tolist()
    stats = atlas_page.evaluate("([p, t]) => window.tessera.atlasView(p, t)", [far, [0, 0, 0]])
    assert max(stats["atlas_levels"]) <= 1
    assert atlas_page.evaluate("document.body.dataset.tileError") is None
    assert atlas_page.errors == []


@pytest.mark.parametrize("level", [-1, 2])
def test_download_ply_is_the_cli_s_welded_mesh(atlas_page, atlas_collection, tmp_path, level):
    from fitter.cli import main

    path = download_ply(atlas_page, level, tmp_path)
    out = tmp_path / "cli.ply"
    assert main(["tessellate", str(atlas_collection / "sphere"), "--level", str(level),
                 "-o", str(out)]) == 0
    assert path.read_bytes().replace(b"source base.tsa", b"source sphere") == out.read_bytes()
    # the worker reported its progress while it tessellated (shown as a percentage)
    progress = atlas_page.evaluate("window.tessera.stats.ply_progress")
    assert progress and progress == sorted(progress) and 0 < progress[-1] <= 1
    mesh = trimesh.load(path, process=False)
    mesh.merge_vertices()
    assert mesh.is_watertight
    assert atlas_page.errors == []


def test_walls_masks_leave_cells_out_in_the_viewer_and_its_ply(browser, atlas_server,
                                                              atlas_collection, tmp_path):
    """A bundle whose version 5 packs carry walls masks: the viewer refines it with no
    error and draws fewer triangles than the full grids, and its "Download PLY" at level 2
    is `tessera tessellate`'s mesh, which leaves out the masks' cells (docs/format.md,
    "Atlas detail packs")."""
    from client_py.bundle import tessellate_bundle
    from fitter.cli import main

    folder = atlas_collection / "walled"
    manifest = json.loads((folder / "manifest.json").read_text())
    assert manifest["tiles"]["detail"]["format_version"] == 5
    assert all((folder / f"detail/{p['level']}/{p['group']}.tsdp").read_bytes()[4] == 5
               for p in manifest["tiles"]["detail"]["packs"])
    with open_viewer(browser, f"{atlas_server.url}/objects/walled/", 30_000) as page:
        centre = np.array(manifest["tiles"]["detail"]["groups"][0]["center"])
        position = (centre + 0.6 * centre / np.linalg.norm(centre)).tolist()
        stats = page.evaluate("([p, t]) => window.tessera.atlasView(p, t)",
                              [position, centre.tolist()])
        assert stats["atlas_levels"][0] == 2
        path = download_ply(page, 2, tmp_path)
        assert page.evaluate("document.body.dataset.tileError") is None
        assert page.errors == []
    out = tmp_path / "cli.ply"
    assert main(["tessellate", str(folder), "--level", "2", "-o", str(out)]) == 0
    assert path.read_bytes().replace(b"source base.tsa", b"source walled") == out.read_bytes()
    mesh = tessellate_bundle(manifest, lambda name: (folder / name).read_bytes(), level=2)
    cells = 24 * (manifest["tiles"]["detail"]["levels"][2]["resolution"] - 1) ** 2
    assert 0 < mesh.triangle_count < 2 * cells
    ply = trimesh.load(path, process=False)
    assert len(ply.faces) == mesh.triangle_count and not ply.is_watertight


def test_the_3dhop_page_loads_the_atlas_ply(page, atlas_server):
    if page.request.get(f"{atlas_server.url}/vendor/3dhop/js/presenter.js").status != 200:
        pytest.skip("3DHOP is not configured (../shared/vendor/3dhop-4.3 absent)")
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(f"{atlas_server.url}/objects/sphere/3dhop?level=1")
    page.wait_for_function(READY, timeout=90_000)
    assert page.evaluate("document.body.dataset.error") is None
    assert page.evaluate("window.presenter._isSceneReady()") is True
    stats = page.evaluate("window.tessera.stats")
    assert stats["ply_level"] == 1 and stats["resolution"] == 9
    header = bytes(page.evaluate("""async () => {
        const buffer = await (await fetch(window.tessera.plyUrl)).arrayBuffer();
        return Array.from(new Uint8Array(buffer.slice(0, 400)));
    }""")).split(b"end_header", 1)[0].decode()
    assert f"element vertex {stats['vertices']}" in header and "one welded mesh" in header
    assert errors == []


def test_a_close_view_of_a_real_default_fit_shows_its_detail(browser, laurana_bundle, tmp_path):
    """The Laurana bust fitted with the default options (about 2,270 patches, whose base
    alone draws about 184,000 vertices at 9 x 9 samples a patch): a close view of the group
    at the front of the bust refines it, and only part of the bust. Before the viewer's
    budget counted only the groups in its frustum and the groups were boxes of the patches'
    k-d tree (atlas.detail.spatial_order), no group of such a fit was ever refined: the
    base filled most of the budget and each of its 3 groups spanned the whole object."""
    manifest = laurana_bundle.manifest
    groups = manifest["tiles"]["detail"]["groups"]
    assert len(groups) >= 8
    front = np.array(manifest["view"]["front"])
    g = int(np.argmax([np.dot(group["center"], front) for group in groups]))
    centre, radius = np.array(groups[g]["center"]), groups[g]["radius"]
    collection = tmp_path / "collection"
    collection.mkdir()
    (collection / "laurana").symlink_to(laurana_bundle.path, target_is_directory=True)
    with serve_collection(collection) as live, \
            open_viewer(browser, f"{live.url}/objects/laurana/", 120_000) as page:
        assert page.evaluate("window.tessera.stats")["atlas_levels"] == [-1] * len(groups)
        stats = page.evaluate("([p, t]) => window.tessera.atlasView(p, t)",
                              [(centre + 1.5 * radius * front).tolist(), centre.tolist()])
        levels = stats["atlas_levels"]
        assert levels[g] >= 0, levels
        assert min(levels) == -1, levels  # a part of the bust, not all of it
        assert stats["atlas_packs_loaded"] >= 1
        assert page.errors == []
