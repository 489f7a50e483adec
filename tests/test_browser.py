"""The pages in real headless Chromium (Debian's, through pytest-playwright): the viewer reaches
ready with plausible stats and draws the object, Download PLY gives a mesh trimesh reads, a
corrupt patch and a Pyodide timeout show their errors, 404s, MIME types over HTTP, and the 3DHOP
page loads the client-made mesh.

One browser for the module; the viewer page is loaded once and shared by the tests that
inspect it (Pyodide takes seconds to start per page).
"""

from __future__ import annotations

import base64
import io
import json
import re

import numpy as np
import pytest
import trimesh
from PIL import Image
from scipy.spatial import cKDTree

from fitter.collection.bundles import served_manifest
from fitter.fitting.examples import relief_scan

pytestmark = pytest.mark.browser

RESOLUTION = 64
READY = "document.body.dataset.ready === '1' || !!document.body.dataset.error"


def _canvas_rgb(page, selector: str) -> np.ndarray:
    """The WebGL canvas's own pixels (its drawing buffer is preserved), as an RGB array."""
    url = page.eval_on_selector(selector, "c => c.toDataURL('image/png')")
    data = base64.b64decode(url.split(",", 1)[1])
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB")).astype(int)


@pytest.fixture(scope="module")
def viewer(browser, live_server):
    """The relief's viewer page at a fixed 64 x 64 grid, refined and idle."""
    context = browser.new_context(accept_downloads=True, viewport={"width": 1000, "height": 700})
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(f"{live_server.url}/objects/relief/?resolution={RESOLUTION}")
    page.wait_for_function(READY, timeout=60_000)
    page.wait_for_function("document.body.dataset.refined === '1'", timeout=30_000)
    page.errors = errors
    yield page
    context.close()


def test_viewer_reaches_ready_with_plausible_stats(viewer, web_collection):
    assert viewer.evaluate("document.body.dataset.error") is None
    stats = viewer.evaluate("window.tessera.stats")
    assert stats["resolution"] == RESOLUTION
    assert stats["vertices"] == RESOLUTION * RESOLUTION
    full = 2 * (RESOLUTION - 1) ** 2  # a trim mask may leave some cells out, never add
    assert 0.8 * full <= stats["triangles"] <= full
    assert stats["kernel"] in ("python", "numpy")
    assert 0 < stats["pyodide_load_ms"] < stats["first_frame_ms"]
    assert stats["tessellate_ms"] > 0
    manifest = json.loads((web_collection / "relief" / "manifest.json").read_text())
    expected = len(served_manifest(manifest)) + (web_collection / "relief" / "base.tsp"
                                                 ).stat().st_size
    # plus the detail tiles the view asked for (tests/test_browser_tiles.py checks which)
    assert stats["bytes_downloaded"] == expected + stats["tile_bytes"]
    assert viewer.errors == []
    assert viewer.locator("#loading").is_hidden()


def test_viewer_canvas_shows_the_object(viewer):
    rgb = _canvas_rgb(viewer, "#view")
    background = rgb[2, -3]  # a corner: fit-to-view leaves a margin around the object
    differs = np.abs(rgb - background).max(axis=2) > 30
    assert differs.mean() > 0.10, f"only {differs.mean():.1%} of the canvas is not background"
    lit = rgb[differs]
    assert lit[:, 0].mean() > lit[:, 2].mean()  # the stone colour is warm: red over blue


def test_viewer_error_overlay_recolours_the_object(viewer):
    before = _canvas_rgb(viewer, "#view")
    viewer.click("#toggle-error")
    viewer.wait_for_function("document.getElementById('toggle-error')"
                             ".getAttribute('aria-pressed') === 'true'"
                             " && !document.body.dataset.errorMapBusy")
    after = _canvas_rgb(viewer, "#view")
    viewer.click("#toggle-error")
    assert viewer.locator("#legend").is_hidden()
    changed = np.abs(after - before).max(axis=2) > 30
    assert changed.mean() > 0.05
    # the stone is warm (red over blue); viridis is violet-blue-green (blue over red)
    assert before[changed][:, 0].mean() > before[changed][:, 2].mean()
    assert after[changed][:, 0].mean() < after[changed][:, 2].mean()


def test_the_error_legend_ends_at_the_panels_max_and_names_holes(viewer):
    viewer.click("#toggle-error")
    try:
        viewer.wait_for_function("!document.getElementById('legend').hidden")
        assert viewer.inner_text("#legend-max") == viewer.inner_text("#fact-max") != "—"
        assert "no scan point" in viewer.inner_text("#legend")
        swatch = viewer.eval_on_selector("#legend-hole-swatch",
                                         "e => getComputedStyle(e).backgroundColor")
        assert swatch == "rgb(150, 128, 170)"
    finally:
        viewer.click("#toggle-error")


def test_download_ply_is_the_mesh_trimesh_reads(viewer, tmp_path):
    with viewer.expect_download() as info:
        viewer.click("#download-ply")
    download = info.value
    assert download.suggested_filename == "relief.ply"
    path = tmp_path / "relief.ply"
    download.save_as(path)
    assert path.read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\n")
    # fix_texture=False: trimesh would otherwise re-index by texture_u/v and drop the
    # vertices no triangle uses (cells a trim mask left out)
    mesh = trimesh.load(path, process=False, fix_texture=False)
    stats = viewer.evaluate("window.tessera.stats")
    assert len(mesh.vertices) == RESOLUTION * RESOLUTION == stats["vertices"]
    assert len(mesh.faces) == stats["triangles"]
    # Independent check of the geometry: the browser's vertices lie on the scanned relief
    # (scan frame, millimetres), within a few fit-RMS of the scan points.
    scan = relief_scan(20_000)
    distance, _ = cKDTree(scan).query(np.asarray(mesh.vertices))
    assert np.median(distance) < 2.0  # point spacing of 20k points over 200x140 mm is ~1.2 mm


def test_download_ply_with_the_error_map_carries_its_colours(viewer, tmp_path):
    viewer.click("#toggle-error")
    try:
        with viewer.expect_download() as info:
            viewer.click("#download-ply")
        path = tmp_path / "coloured.ply"
        info.value.save_as(path)
    finally:
        viewer.click("#toggle-error")
    header = path.read_bytes().split(b"end_header", 1)[0].decode()
    assert "property uchar red" in header
    with open(path, "rb") as handle:  # the loader's raw arrays: trimesh keeps uv over colour
        loaded = trimesh.exchange.ply.load_ply(handle, fix_texture=False)
    colours = np.asarray(loaded["vertex_colors"])[:, :3]
    assert len(colours) == RESOLUTION * RESOLUTION
    assert len(np.unique(colours, axis=0)) > 10  # a colour scale, not one flat colour


def test_the_base_grid_follows_the_view_and_is_a_backdrop_under_regions(page, live_server):
    """Without a fixed ?resolution the grid follows the object's size on screen; while detail
    regions are drawn over the base it is a backdrop of at most 96² (base-mesh.js: hidden
    under them, it would cost every draw all its vertices)."""
    page.set_viewport_size({"width": 900, "height": 600})
    page.goto(f"{live_server.url}/objects/relief/")
    page.wait_for_function("document.body.dataset.refined === '1' || !!document.body.dataset.error",
                           timeout=60_000)
    before = page.evaluate("window.tessera.tilesIdle()")
    assert before["coarse_resolution"] < before["resolution"]  # coarse first, then refined
    assert before["vertices"] == before["resolution"] ** 2
    assert before["regions"] > 0 and before["resolution"] <= 96  # detail over the whole view
    page.mouse.move(600, 300)
    for _ in range(8):  # far out: no region is worth drawing, the base shows and follows
        page.mouse.wheel(0, 400)
        page.wait_for_timeout(50)
    page.wait_for_function(f"window.tessera.stats.resolution < {before['resolution']}",
                           timeout=30_000)
    far = page.evaluate("window.tessera.tilesIdle()")
    assert far["regions"] == 0 and far["vertices"] == far["resolution"] ** 2
    for _ in range(12):  # close in: regions again, and the base a backdrop
        page.mouse.wheel(0, -400)
        page.wait_for_timeout(50)
    page.wait_for_function("window.tessera.stats.regions > 0", timeout=30_000)
    page.wait_for_timeout(1000)
    close = page.evaluate("window.tessera.tilesIdle()")
    assert close["regions"] > 0 and close["resolution"] <= 96


def test_corrupt_patch_shows_its_error_quickly(page, live_server):
    page.goto(f"{live_server.url}/objects/corrupt/")
    page.wait_for_function(READY, timeout=30_000)
    message = page.evaluate("document.body.dataset.error")
    assert "invalid Tessera patch" in message and "CRC32" in message
    assert page.evaluate("document.body.dataset.ready") is None
    assert page.locator("#error").is_visible()
    assert "CRC32" in page.locator("#error-text").inner_text()


def test_pyodide_timeout_is_a_visible_error(page, live_server):
    """A runtime that never arrives (here: held back) ends in an error, not a spinner."""
    page.route("**/vendor/pyodide/**", lambda route: None)  # never answered

    def short_timeout(route):
        response = route.fetch()
        html = re.sub(r'"pyodide_timeout_s":\s*[0-9.]+', '"pyodide_timeout_s": 1.5',
                      response.text())
        route.fulfill(response=response, body=html)

    page.route("**/objects/relief/", short_timeout)
    page.goto(f"{live_server.url}/objects/relief/")
    page.wait_for_function(READY, timeout=20_000)
    message = page.evaluate("document.body.dataset.error")
    assert "did not load within 1.5 s" in message
    assert page.locator("#error").is_visible()


def test_unknown_object_is_404(page, live_server):
    response = page.goto(f"{live_server.url}/objects/no-such-object/")
    assert response.status == 404
    assert "no object" in page.locator("main").inner_text()


def test_runtime_mime_types_over_http(page, live_server):
    wasm = page.request.get(f"{live_server.url}/vendor/pyodide/pyodide.asm.wasm")
    assert wasm.headers["content-type"] == "application/wasm"
    mjs = page.request.get(f"{live_server.url}/vendor/pyodide/pyodide.mjs")
    assert mjs.headers["content-type"].startswith("text/javascript")


def test_3dhop_page_loads_the_client_made_mesh(page, live_server):
    if page.request.get(f"{live_server.url}/vendor/3dhop/js/presenter.js").status != 200:
        pytest.skip("3DHOP is not configured (../shared/vendor/3dhop-4.3 absent)")
    console_errors: list[str] = []
    page.on("console", lambda m: console_errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda exc: console_errors.append(str(exc)))
    page.set_viewport_size({"width": 900, "height": 640})
    page.goto(f"{live_server.url}/objects/relief/3dhop")
    page.wait_for_function(READY, timeout=60_000)
    assert page.evaluate("document.body.dataset.error") is None
    assert page.evaluate("window.presenter._isSceneReady()") is True
    stats = page.evaluate("window.tessera.stats")
    # the mesh 3DHOP loaded is the PLY client_py wrote in this page: read it back
    ply = page.evaluate("""async () => {
        const buffer = await (await fetch(window.tessera.plyUrl)).arrayBuffer();
        return Array.from(new Uint8Array(buffer.slice(0, 400)));
    }""")
    header = bytes(ply).split(b"end_header", 1)[0].decode()
    assert f"element vertex {stats['vertices']}" in header
    assert "written by Tessera client_py" in header
    renderable = page.evaluate("""() => {
        const r = window.presenter._scene.meshes.tessera.renderable;
        return {ready: !!r, radius: r.datasetRadius};
    }""")
    assert renderable["ready"] and renderable["radius"] > 10  # mm-sized relief, not empty
    shot = np.asarray(Image.open(io.BytesIO(page.locator("#draw-canvas").screenshot()))
                      .convert("RGB")).astype(int)
    # 3DHOP draws over its dark background image; the stone-coloured object is bright
    bright = shot.min(axis=2) > 110
    assert bright.mean() > 0.05, f"only {bright.mean():.1%} of 3DHOP's canvas shows the object"
    assert console_errors == []


def test_api_objects_from_the_browser(page, live_server):
    response = page.request.get(f"{live_server.url}/api/objects")
    objects = json.loads(response.body())
    relief = next(o for o in objects if o["id"] == "relief")
    page.goto(live_server.url + relief["viewer_url"] + f"?resolution={RESOLUTION}")
    assert page.title().startswith("Carved relief")


# ------------------------------------------------ the first view and the turntable (issue 14)
def _camera(page) -> dict:
    return {k: np.array(v) for k, v in page.evaluate("window.tessera.camera()").items()}


def _direction(camera: dict) -> np.ndarray:
    offset = camera["position"] - camera["target"]
    return offset / np.linalg.norm(offset)


def test_first_view_is_upright_and_from_the_front(viewer, web_collection):
    """After load the camera's up is the manifest's up and it looks from the front, 10 degrees
    above the horizon (web/src/camera-view.js TILT_DEG)."""
    view = json.loads((web_collection / "relief" / "manifest.json").read_text())["view"]
    viewer.click("#fit-view")
    camera = _camera(viewer)
    np.testing.assert_allclose(camera["up"], view["up"], atol=1e-6)
    up, front = np.array(view["up"]), np.array(view["front"])
    tilt = np.radians(10)
    np.testing.assert_allclose(_direction(camera), np.cos(tilt) * front + np.sin(tilt) * up,
                               atol=1e-5)


def test_orbiting_keeps_up_and_front_and_reset_restore_the_first_view(viewer, web_collection):
    view = json.loads((web_collection / "relief" / "manifest.json").read_text())["view"]
    viewer.click("#fit-view")
    first = _camera(viewer)
    box = viewer.locator("#view").bounding_box()
    x, y = box["x"] + box["width"] * 0.6, box["y"] + box["height"] * 0.5
    viewer.mouse.move(x, y)
    viewer.mouse.down()
    viewer.mouse.move(x + 180, y + 60, steps=8)
    viewer.mouse.up()
    turned = _camera(viewer)
    assert np.degrees(np.arccos(np.clip(_direction(turned) @ _direction(first), -1, 1))) > 20
    np.testing.assert_allclose(turned["up"], view["up"], atol=1e-6)  # a turntable: up stays
    # a drag far upwards stops at the polar limit instead of turning over the pole
    viewer.mouse.move(x, y)
    viewer.mouse.down()
    viewer.mouse.move(x, y + 2000, steps=10)
    viewer.mouse.up()
    polar = np.arccos(np.clip(_direction(_camera(viewer)) @ np.array(view["up"]), -1, 1))
    assert 0.1 < polar < np.pi - 0.1
    viewer.mouse.wheel(0, -600)  # zoom in
    viewer.wait_for_timeout(200)
    viewer.click("#front-view")
    front = _camera(viewer)
    np.testing.assert_allclose(_direction(front), _direction(first), atol=1e-5)
    viewer.click("#fit-view")
    reset = _camera(viewer)
    for key in ("position", "target", "up"):
        np.testing.assert_allclose(reset[key], first[key], rtol=1e-5, atol=1e-6)


def test_a_bundle_without_view_keeps_the_old_framing(browser, live_server, web_collection):
    """Bundles written before the manifest's ``view``: the page still starts (framed by the mean
    normal, as before), and Reset view comes back to that first view."""
    import shutil

    old = web_collection / "relief-before-view"
    shutil.copytree(web_collection / "relief", old)
    try:
        manifest = json.loads((old / "manifest.json").read_text())
        del manifest["view"]
        (old / "manifest.json").write_text(json.dumps(manifest))
        page = browser.new_page(viewport={"width": 1000, "height": 700})
        page.goto(f"{live_server.url}/objects/relief-before-view/?resolution={RESOLUTION}")
        page.wait_for_function(READY, timeout=60_000)
        assert page.evaluate("document.body.dataset.error || ''") == ""
        first = _camera(page)
        box = page.locator("#view").bounding_box()
        page.mouse.move(box["x"] + 500, box["y"] + 300)
        page.mouse.down()
        page.mouse.move(box["x"] + 700, box["y"] + 350, steps=6)
        page.mouse.up()
        assert not np.allclose(_camera(page)["position"], first["position"])
        page.click("#fit-view")
        reset = _camera(page)
        for key in ("position", "target", "up"):
            np.testing.assert_allclose(reset[key], first[key], rtol=1e-5, atol=1e-6)
        page.close()
    finally:
        shutil.rmtree(old)
