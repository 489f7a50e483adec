"""A coloured atlas bundle in headless Chromium: the viewer fetches its colour packs and draws
the welded atlas with vertex colours, with no console error, and "Download PLY" gives the
same coloured PLY as `tessera tessellate`. The bundle is made without the fitter
(tests/atlas_bundle.py's sphere of 24 patches in 6 groups) with one solid colour per group
in colour packs of two levels (docs/format.md, "Atlas colour")."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
import trimesh
from atlas_bundle import add_colour_packs, write_atlas_bundle
from live import VIEWER_READY as READY
from live import download_ply, open_viewer, serve_collection
from PIL import Image

pytestmark = pytest.mark.browser

GROUP_COLOURS = [(220, 30, 30), (30, 200, 40), (40, 60, 230), (230, 200, 20), (200, 40, 210),
                 (20, 210, 210)]


def add_group_colours(folder, manifest: dict) -> dict:
    """Colour packs of two levels (level 0: one pack of every group; level 1: two packs of
    three groups), each patch its group's colour (tests/atlas_bundle.py)."""
    per_group = manifest["tiles"]["detail"]["groups"][0]["count"]
    return add_colour_packs(folder, manifest, lambda level, patch, side: np.full(
        (side, side, 3), GROUP_COLOURS[patch // per_group], np.uint8))


def group_colours_seen(page) -> set[int]:
    """The groups whose colour (GROUP_COLOURS, shaded) covers 200+ pixels of the canvas: a
    pixel of a colour's hue has its strong channels 60+ above its weak ones."""
    shot = np.asarray(Image.open(io.BytesIO(page.locator("canvas").screenshot())))
    rgb = shot[..., :3].astype(int).reshape(-1, 3)
    seen = set()
    for k, colour in enumerate(GROUP_COLOURS):
        strong = [c for c, v in enumerate(colour) if v > 150]
        weak = [c for c, v in enumerate(colour) if v <= 150]
        if np.count_nonzero(rgb[:, strong].min(axis=1) > rgb[:, weak].max(axis=1) + 60) > 200:
            seen.add(k)
    return seen


@pytest.fixture(scope="module")
def colour_collection(tmp_path_factory):
    root = tmp_path_factory.mktemp("atlas-colour")
    manifest = write_atlas_bundle(root / "sphere", k=2, levels=2, base_resolution=5)
    add_group_colours(root / "sphere", manifest)
    return root


@pytest.fixture(scope="module")
def colour_server(colour_collection):
    with serve_collection(colour_collection) as live:
        yield live


@pytest.fixture(scope="module")
def colour_page(browser, colour_server):
    with open_viewer(browser, f"{colour_server.url}/objects/sphere/") as page:
        yield page


def test_the_viewer_draws_the_atlas_in_its_colours(colour_page):
    assert colour_page.evaluate("document.body.dataset.error") is None
    stats = colour_page.evaluate("window.tessera.stats")
    assert stats["atlas_colour_packs_loaded"] == 1  # the base: level 0's one pack
    assert stats["atlas_colour_bytes"] > 0
    seen = group_colours_seen(colour_page)
    assert len(seen) >= 2, seen  # a sphere shows several faces of its cube, each a colour
    assert colour_page.errors == []


def test_zooming_in_fetches_the_finer_colour_pack_of_the_groups_in_view(colour_page,
                                                                        colour_collection):
    manifest = json.loads((colour_collection / "sphere" / "manifest.json").read_text())
    centre = np.array(manifest["tiles"]["detail"]["groups"][0]["center"])
    outward = centre / np.linalg.norm(centre)
    stats = colour_page.evaluate("([p, t]) => window.tessera.atlasView(p, t)",
                                 [(centre + 0.6 * outward).tolist(), centre.tolist()])
    assert stats["atlas_levels"][0] == 1  # group 0 at the finest level ...
    # ... coloured from level 1's pack of groups 0-2 (texture/1/0.webp), fetched after the
    # base's (other groups in view may need level 1's second pack too)
    assert stats["atlas_colour_packs_loaded"] >= 2
    # drawn as group meshes now (the welded first frame is hidden): the refined ones made,
    # the others the base meshes made after the first frame
    assert stats["atlas_parts_made"] >= 1
    assert stats["atlas_parts_made"] + stats["atlas_parts_cached"] == 6
    shot = np.asarray(Image.open(io.BytesIO(colour_page.locator("canvas").screenshot())))
    rgb = shot[..., :3].astype(int).reshape(-1, 3)
    red = (rgb[:, 0] > rgb[:, 1] + 60) & (rgb[:, 0] > rgb[:, 2] + 60)
    assert red.mean() > 0.2  # group 0 (red) fills much of the close view
    assert colour_page.errors == []


def test_group_meshes_kept_come_back_in_their_colours(colour_page, colour_collection):
    """Seen whole, every group is refined for its colour (its texels look large) and drawn
    coloured; looking away sends them to the base meshes kept since the first frame
    (nothing made; the colour packs no mesh to make needs are dropped); looking back shows
    the kept refined meshes again in their colours, with nothing tessellated or fetched."""
    manifest = json.loads((colour_collection / "sphere" / "manifest.json").read_text())
    centre = np.array(manifest["tiles"]["detail"]["groups"][0]["center"])
    whole = [(centre * 6 + [1.5, 1.5, 0]).tolist(), [0, 0, 0]]
    seen_whole = colour_page.evaluate("([p, t]) => window.tessera.atlasView(p, t)", whole)
    assert seen_whole["atlas_levels"] == [1] * 6
    assert len(group_colours_seen(colour_page)) >= 3
    away = colour_page.evaluate("([p, t]) => window.tessera.atlasView(p, t)",
                                [(centre * 3).tolist(), (centre * 6).tolist()])
    assert away["atlas_levels"] == [-1] * 6
    assert away["atlas_parts_made"] == 0 and away["atlas_parts_cached"] == 6
    again = colour_page.evaluate("([p, t]) => window.tessera.atlasView(p, t)", whole)
    assert again["atlas_levels"] == [1] * 6 and again["atlas_updates"] == away["atlas_updates"] + 1
    assert again["atlas_parts_made"] == 0 and again["atlas_parts_cached"] == 6
    assert again["atlas_colour_packs_loaded"] == seen_whole["atlas_colour_packs_loaded"]
    assert len(group_colours_seen(colour_page)) >= 3  # the kept meshes' own colours
    assert colour_page.errors == []


def test_download_ply_has_the_cli_s_colours(colour_page, colour_collection, tmp_path):
    from fitter.cli import main

    path = download_ply(colour_page, 1, tmp_path)
    out = tmp_path / "cli.ply"
    assert main(["tessellate", str(colour_collection / "sphere"), "--level", "1",
                 "-o", str(out)]) == 0
    assert path.read_bytes().replace(b"source base.tsa", b"source sphere") == out.read_bytes()
    mesh = trimesh.load(path, process=False)
    colours = {tuple(c[:3]) for c in np.asarray(mesh.visual.vertex_colors)}
    assert colours <= set(GROUP_COLOURS) and len(colours) == 6
    assert colour_page.errors == []


def test_the_3dhop_page_shows_the_atlas_with_its_colours(page, colour_server):
    if page.request.get(f"{colour_server.url}/vendor/3dhop/js/presenter.js").status != 200:
        pytest.skip("3DHOP is not configured (../shared/vendor/3dhop-4.3 absent)")
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(f"{colour_server.url}/objects/sphere/3dhop")  # the base: colour level 0
    page.wait_for_function(READY, timeout=90_000)
    assert page.evaluate("document.body.dataset.error") is None
    assert page.evaluate("window.presenter._isSceneReady()") is True
    header = bytes(page.evaluate("""async () => {
        const buffer = await (await fetch(window.tessera.plyUrl)).arrayBuffer();
        return Array.from(new Uint8Array(buffer.slice(0, 600)));
    }""")).split(b"end_header", 1)[0].decode()
    assert "property uchar red" in header and "colour packs of level 0" in header
    # 3DHOP draws the vertex colours (color -2: "use the mesh's"), not its stone colour
    assert page.evaluate("window.presenter._scene.modelInstances.object.color[0]") == -2
    assert errors == []
