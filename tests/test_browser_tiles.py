"""Detail tiles on zoom in real headless Chromium (issue 6, the viewer half).

A bundle fitted from the generated relief with four detail levels is served; the viewer shows
the base with at most coarse tiles at the fitted view; zooming into one spot (through the
documented hook ``window.tessera.zoomTo``) fetches that spot's finest tiles, and only tiles
the camera sees (checked by projecting each fetched tile's rectangle, evaluated on the base
patch in Python, through the page's own camera matrices); the regions drawn there lie closer
to the exact relief (``fitter.fitting.examples.relief_height``) than the base does.
"""

from __future__ import annotations

import base64
import io
import json
import re
import shutil

import numpy as np
import pytest
from PIL import Image

from fitter.fitting.examples import relief_height

pytestmark = pytest.mark.browser

LEVELS = 4
READY = "document.body.dataset.ready === '1' || !!document.body.dataset.error"
TILE_URL = re.compile(r"/detail/(\d+)/(\d+)_(\d+)\.tsd$")


@pytest.fixture(scope="module")
def detail_collection(tmp_path_factory: pytest.TempPathFactory):
    """One bundle: the relief (40,000 points) with a 20x20 base and 4 detail levels."""
    from fitter.fitting.examples import relief_scan
    from fitter.fitting.options import FitOptions
    from fitter.fitting.pipeline import fit_scan

    root = tmp_path_factory.mktemp("detail-collection")
    points = relief_scan(40_000)
    fit_scan(points, root / "relief-detail",
             FitOptions(grid=(20, 20), detail_levels=LEVELS, title="Relief with detail"))
    fit_scan(_coloured(points), root / "relief-colour",
             FitOptions(grid=(20, 20), detail_levels=2, title="Relief with colour"))
    shutil.copytree(root / "relief-colour", root / "relief-texture")
    _add_texture_level(root / "relief-texture")
    return root


#: the level-1 texture tile _add_texture_level leaves out (as the fitter leaves out a tile with
#: no colour samples of its own)
MISSING_TEXTURE = (1, 1, 1)


def _add_texture_level(bundle) -> None:
    """Give a bundle (one texture level, 0) a texture level 1 of three tiles, lossless WebP
    256 x 256 gradients (red along x, green along y, blue per tile), tile 1/1_1 left out."""
    from PIL import Image

    manifest = json.loads((bundle / "manifest.json").read_text())
    texture = manifest["tiles"]["texture"]
    assert [entry["level"] for entry in texture["levels"]] == [0]
    size = texture["size"]
    ramp = np.linspace(0, 255, size).round().astype(np.uint8)
    nodes = []
    for i, j in ((0, 0), (1, 0), (0, 1)):
        rgb = np.empty((size, size, 3), np.uint8)
        rgb[..., 0] = ramp[None, :]
        rgb[..., 1] = ramp[:, None]
        rgb[..., 2] = 60 + 70 * (i + 2 * j)
        name = f"texture/1/{i}_{j}.webp"
        (bundle / "texture" / "1").mkdir(exist_ok=True)
        Image.fromarray(rgb).save(bundle / name, "WEBP", lossless=True)
        nbytes = (bundle / name).stat().st_size
        nodes.append({"level": 1, "i": i, "j": j, "uv": [i / 2, j / 2, (i + 1) / 2, (j + 1) / 2],
                      "file": name, "bytes": nbytes})
        manifest["files"][name] = nbytes
    texture["nodes"] += nodes
    texture["levels"].append({"level": 1, "tiles": len(nodes),
                              "bytes_total": sum(n["bytes"] for n in nodes)})
    manifest["title"] = "Relief with two texture levels"
    (bundle / "manifest.json").write_text(json.dumps(manifest, indent=1))


def _local(points: np.ndarray) -> np.ndarray:
    """Scan-frame points in the relief's own frame (the example's tilt undone)."""
    a, b = np.deg2rad(20.0), np.deg2rad(-35.0)
    rot_x = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    rot_z = np.array([[np.cos(b), -np.sin(b), 0], [np.sin(b), np.cos(b), 0], [0, 0, 1]])
    return (points - np.array([250.0, -40.0, 1200.0])) @ (rot_z @ rot_x)


def _coloured(points: np.ndarray):
    """The relief painted with red and blue stripes 12 mm wide across x: a point-coloured scan."""
    from fitter.fitting.io.scan import Scan

    stripes = (np.floor(_local(points)[:, 0] / 12) % 2).astype(bool)
    colours = np.where(stripes[:, None], [[200, 60, 40]], [[40, 80, 200]]).astype(np.uint8)
    return Scan(points=points, colors=colours)


@pytest.fixture(scope="module")
def detail_server(detail_collection):
    from live import serve_collection

    with serve_collection(detail_collection) as live:
        yield live


def _scan_frame_surface(bundle):
    from client_py import read_patch

    return read_patch((bundle / "base.tsp").read_bytes()).to_scan_frame()


def _relief_deviation(points: np.ndarray) -> np.ndarray:
    """Vertical distance of scan-frame points to the exact relief."""
    local = _local(points)
    return local[:, 2] - relief_height(local[:, 0], local[:, 1])


def _rect_points(surface, rect) -> np.ndarray:
    """9 x 9 points of the base patch (scan frame) over a normalised ``rect``."""
    (a0, a1), (b0, b1) = surface.domain
    u0, v0, u1, v1 = rect
    return np.array([surface.evaluate(a0 + (a1 - a0) * u, b0 + (b1 - b0) * v)
                     for u in np.linspace(u0, u1, 9) for v in np.linspace(v0, v1, 9)])


def _rect_in_view(surface, rect, view) -> bool:
    """Whether any point of the base patch over ``rect`` projects into the viewport."""
    pts = _rect_points(surface, rect)
    m = (np.array(view["projection"]).reshape(4, 4).T @ np.array(view["view"]).reshape(4, 4).T)
    clip = np.c_[pts, np.ones(len(pts))] @ m.T
    ndc = clip[:, :3] / clip[:, 3:4]
    inside = (clip[:, 3] > 0) & (np.abs(ndc[:, 0]) <= 1.05) & (np.abs(ndc[:, 1]) <= 1.05)
    return bool(inside.any())


def _projected_px(surface, rect, error: float, view, height_px: int) -> float:
    """``error`` (scan units) in pixels at the nearest point of the patch over ``rect``:
    ``error * f / d`` with ``f = P[1][1] H / 2`` the focal length in pixels."""
    pts = _rect_points(surface, rect)
    camera = np.linalg.inv(np.array(view["view"]).reshape(4, 4).T)[:3, 3]
    focal = np.array(view["projection"]).reshape(4, 4).T[1, 1] * height_px / 2
    return error * focal / np.linalg.norm(pts - camera, axis=1).min()


def _shown_error(manifest: dict, nodes: dict, level: int, i: int, j: int) -> float:
    """geometric_error of node (level, i, j), or its nearest present ancestor's, or base.max."""
    for k in range(level, -1, -1):
        node = nodes.get((k, i >> (level - k), j >> (level - k)))
        if node:
            return node["geometric_error"]
    return manifest["tiles"]["detail"]["base"]["max"]


def _watched_page(browser, **options):
    """A new context and page, and the list its page errors and console errors go to."""
    context = browser.new_context(**options)
    page = context.new_page()
    problems: list[str] = []
    page.on("pageerror", lambda exc: problems.append(str(exc)))
    page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
    return context, page, problems


def _open_detail_viewer(browser, server, object_id: str = "relief-detail", **options):
    """A new page on the viewer of ``object_id`` (the relief with detail by default), ready
    and its base refined: ``(context, page, problems, fetched)`` with the page's errors and
    the ``(level, i, j)`` of every detail tile it requests."""
    context, page, problems = _watched_page(browser, viewport={"width": 800, "height": 600},
                                            **options)
    fetched: list[tuple[int, int, int]] = []

    def on_request(request):
        match = TILE_URL.search(request.url)
        if match:
            fetched.append(tuple(int(g) for g in match.groups()))

    page.on("request", on_request)
    page.goto(f"{server.url}/objects/{object_id}/?resolution=64")
    page.wait_for_function(READY, timeout=60_000)
    assert page.evaluate("document.body.dataset.error") is None
    # the base at its grid too (it waits in the worker behind the first regions)
    page.wait_for_function("document.body.dataset.refined === '1'", timeout=60_000)
    return context, page, problems, fetched


def test_zoom_fetches_only_the_tiles_in_view_and_refines_the_mesh(browser, detail_server,
                                                                  detail_collection):
    bundle = detail_collection / "relief-detail"
    manifest = json.loads((bundle / "manifest.json").read_text())
    nodes = {(n["level"], n["i"], n["j"]): n for n in manifest["tiles"]["detail"]["nodes"]}
    finest = max(k for k, _, _ in nodes)
    assert finest == LEVELS - 1

    context, page, problems, fetched = _open_detail_viewer(browser, detail_server)
    try:
        before = page.evaluate("window.tessera.tilesIdle()")
        view = page.evaluate("window.tessera.view()")
        surface = _scan_frame_surface(bundle)
        # the fitted view: coarse tiles, and finer ones only where the coarser projected error
        # is above the 2 px threshold (1 px here: the page measures to a padded box)
        assert all(key in nodes for key in fetched)
        assert len(set(fetched)) == len(fetched)  # each once
        for level, i, j in fetched:
            if level > 0:
                parent = (level - 1, i // 2, j // 2)
                error = _shown_error(manifest, nodes, *parent)
                rect = nodes[(level, i, j)]["uv"]
                assert _projected_px(surface, rect, error, view, 600) > 1.0, (level, i, j)
        assert 0 < sum(k[0] == finest for k in fetched) < sum(k[0] == finest for k in nodes) / 2
        assert before["tile_bytes"] == sum(nodes[k]["bytes"] for k in fetched)
        first = set(fetched)

        # a spot whose finest tile was not needed at the fitted view, with little error left
        candidates = [k for k in nodes if k[0] == finest and k not in first
                      and nodes[k]["geometric_error"] < 0.3]
        level, i, j = candidates[len(candidates) // 2]
        n = 2**level
        u, v = (i + 0.5) / n, (j + 0.5) / n
        fetched.clear()
        after = page.evaluate(f"window.tessera.zoomTo({u}, {v}, 40)")
        view = page.evaluate("window.tessera.view()")
        regions = page.evaluate("window.tessera.regionMeshes()")

        assert (level, i, j) in fetched  # the spot's finest tile came
        assert len(set(fetched)) == len(fetched)  # each once
        for key in fetched:  # ... and only tiles the camera sees
            assert _rect_in_view(surface, nodes[key]["uv"], view), f"tile {key} is out of view"
        hidden = [k for k in nodes if k not in first and k not in fetched
                  and _rect_in_view(surface, nodes[k]["uv"], view)]
        assert len(fetched) > 0 and len(hidden) < len(nodes)
        assert after["tiles_loaded"] > 0 and after["regions"] == len(regions) > 0
        assert after["tile_bytes"] == before["tile_bytes"] + sum(nodes[k]["bytes"] for k in fetched)
        assert after["tile_tessellate_ms"] > 0

        # the region at the spot is the refined surface: closer to the exact relief than the base
        spot = next(r for r in regions if r["level"] == level and (r["i"], r["j"]) == (i, j))
        positions = np.array(spot["positions"]).reshape(-1, 3)
        uvs = np.array(spot["uvs"]).reshape(-1, 2)
        (a0, a1), (b0, b1) = surface.domain
        base = np.array([surface.evaluate(a0 + (a1 - a0) * s, b0 + (b1 - b0) * t) for s, t in uvs])
        assert np.abs(positions - base).max() > 0.01  # detail moved the vertices
        refined_rms = np.sqrt(np.mean(_relief_deviation(positions) ** 2))
        base_rms = np.sqrt(np.mean(_relief_deviation(base) ** 2))
        assert refined_rms < 0.8 * base_rms, (refined_rms, base_rms)

        zoomed = len(fetched)
        # back to the whole object: the fine regions go, their tiles are unloaded
        page.click("#fit-view")
        back = page.evaluate("window.tessera.tilesIdle()")
        assert back["regions"] == before["regions"]
        assert back["tiles_loaded"] == before["tiles_loaded"]
        assert "Detail" in page.locator(".facts").inner_text()
        assert page.evaluate("document.body.dataset.error") is None
        assert page.evaluate("document.body.dataset.tileError") is None
        assert problems == []
        print(f"\nfit view: {len(first)} tiles, {before['tile_bytes']} B, "
              f"{before['tile_tessellate_ms']:.0f} ms; zoom: {zoomed} tiles, "
              f"{after['tile_bytes'] - before['tile_bytes']} B, {after['regions']} regions, "
              f"{after['tile_tessellate_ms']:.0f} ms; rms {base_rms:.3f} -> {refined_rms:.3f}")
    finally:
        context.close()


def test_a_wheel_step_draws_its_regions_and_keeps_the_base_a_backdrop(browser, detail_server):
    """With detail regions on screen the base is a backdrop, at most 96² (every draw processes
    all its vertices: 9k instead of the 147k of the 384² the view would want); a wheel zoom
    draws its new regions and asks for no finer base, and nothing is chosen again after."""
    context, page, problems = _watched_page(browser, viewport={"width": 800, "height": 600})
    try:
        page.goto(f"{detail_server.url}/objects/relief-detail/")
        page.wait_for_function("document.body.dataset.refined === '1' || "
                               "!!document.body.dataset.error", timeout=60_000)
        before = page.evaluate("window.tessera.tilesIdle()")
        assert before["regions"] > 0
        assert before["coarse_resolution"] < before["resolution"] <= 96
        page.mouse.move(400, 300)
        page.mouse.wheel(0, -1200)
        page.wait_for_function(f"window.tessera.stats.tile_updates > {before['tile_updates']}",
                               timeout=60_000)
        after = page.evaluate("window.tessera.tilesIdle()")
        assert after["tile_timing"]["at"] > before["tile_timing"]["at"]  # new regions drawn
        assert after["regions"] > 0
        page.wait_for_timeout(1000)  # the base's settle time and more: nothing follows
        final = page.evaluate("window.tessera.stats")
        assert final["resolution"] == before["resolution"]
        assert final["meshes"] == before["meshes"]
        assert final["tile_updates"] == after["tile_updates"]
        assert problems == []
    finally:
        context.close()


def test_texture_tiles_colour_the_object(browser, detail_server, detail_collection):
    """A point-coloured scan's texture tiles are fetched and drawn: the stripes show."""
    import base64
    import io

    from PIL import Image

    manifest = json.loads((detail_collection / "relief-colour" / "manifest.json").read_text())
    assert manifest["tiles"]["texture"]["nodes"]
    context, page, problems = _watched_page(browser, viewport={"width": 800, "height": 600})
    textures: list[str] = []
    page.on("request", lambda r: textures.append(r.url) if "/texture/" in r.url else None)
    try:
        page.goto(f"{detail_server.url}/objects/relief-colour/?resolution=64")
        page.wait_for_function(READY, timeout=60_000)
        stats = page.evaluate("window.tessera.tilesIdle()")
        assert textures and stats["tiles_loaded"] > 0
        files = {n["file"] for n in manifest["tiles"]["texture"]["nodes"]}
        assert all(url.split("/relief-colour/", 1)[1] in files for url in textures)
        url = page.eval_on_selector("#view", "c => c.toDataURL('image/png')")
        rgb = np.asarray(Image.open(io.BytesIO(base64.b64decode(url.split(",", 1)[1])))
                         .convert("RGB")).astype(int)
        red = (rgb[..., 0] > rgb[..., 2] + 60).mean()
        blue = (rgb[..., 2] > rgb[..., 0] + 60).mean()
        assert red > 0.05 and blue > 0.05, (red, blue)  # both stripe colours on screen
        assert page.evaluate("document.body.dataset.tileError") is None
        assert problems == []
    finally:
        context.close()


def _ply_arrays(path) -> tuple[str, np.ndarray, np.ndarray]:
    """A PLY's header text, vertices (N, 3) and triangles (M, 3), as trimesh's loader reads them
    (``fix_texture=False``: no re-indexing, unused vertices kept)."""
    header, loaded = _load_ply(path)
    return header, np.asarray(loaded["vertices"]), np.asarray(loaded["faces"])


def _load_ply(path) -> tuple[str, dict]:
    """A PLY's header text and trimesh's raw loader output (vertices, faces, vertex_colors)."""
    import trimesh

    header = path.read_bytes().split(b"end_header", 1)[0].decode("ascii")
    with open(path, "rb") as handle:
        return header, trimesh.exchange.ply.load_ply(handle, fix_texture=False)


def _pillow_textures(bundle, manifest: dict, level: int) -> list:
    """Every texture tile of levels 0..level, decoded by Pillow (not by the browser) into
    client_py TextureImage objects."""
    from PIL import Image

    from client_py import TextureImage

    images = []
    for node in manifest["tiles"]["texture"]["nodes"]:
        if node["level"] <= level:
            with Image.open(bundle / node["file"]) as im:
                rgb = im.convert("RGB")
                images.append(TextureImage(node["level"], node["i"], node["j"], rgb.width,
                                           rgb.height, rgb.tobytes()))
    return images


def _level_reference(bundle, level: int, resolution: int):
    """The bundle at ``level`` by CPython's client_py (tessellate_bundle, colours from every
    texture tile of levels <= level decoded by Pillow): ``(positions, indices, colours)``."""
    from client_py.bundle import tessellate_bundle

    manifest = json.loads((bundle / "manifest.json").read_text())
    mesh = tessellate_bundle(manifest, lambda name: (bundle / name).read_bytes(), level=level,
                             resolution=resolution,
                             textures=_pillow_textures(bundle, manifest, level))
    return (np.frombuffer(mesh.positions, np.float32).reshape(-1, 3),
            np.frombuffer(mesh.indices, np.uint32),
            np.frombuffer(mesh.colors, np.uint8).reshape(-1, 3))


def test_download_ply_at_a_detail_level_is_the_bundle_at_that_level(browser, detail_server,
                                                                     detail_collection, tmp_path):
    """Download PLY at the finest level: every tile of levels 0..L is fetched once (those the
    tile layer already fetched not again) and the file is client_py.tessellate_bundle at level
    L in CPython on the same grid; "base" still gives the mesh on screen; a tile that cannot
    be fetched is named in the error."""
    from collections import Counter

    from client_py.bundle import tessellate_bundle

    bundle = detail_collection / "relief-detail"
    manifest = json.loads((bundle / "manifest.json").read_text())
    detail = manifest["tiles"]["detail"]
    nodes = {(n["level"], n["i"], n["j"]): n for n in detail["nodes"]}
    level = len(detail["levels"]) - 1
    assert level == LEVELS - 1
    resolution = detail["levels"][level]["resolution"]  # as the fitter states it
    # docs/format.md, "The grid a level is drawn on": two vertices per knot span, at least
    # 256 cells across
    assert resolution == max(257, 2 * detail["spans_per_tile"] * 2**level + 1)

    context, page, problems, fetched = _open_detail_viewer(browser, detail_server,
                                                           accept_downloads=True)
    try:
        before = page.evaluate("window.tessera.tilesIdle()")
        by_layer = set(fetched)
        assert 0 < len(by_layer) < len(nodes)

        # the choice: base (default) and one entry per level, with its bytes, RMS and grid
        choice = page.locator("#ply-level")
        assert choice.is_visible() and choice.is_enabled()
        assert choice.input_value() == "-1"
        labels = choice.locator("option").all_inner_texts()
        assert len(labels) == 1 + LEVELS and labels[0].startswith("base")
        for k, (label, entry) in enumerate(zip(labels[1:], detail["levels"], strict=True)):
            assert label.startswith(f"level {k} ") and f"{entry['rms']:.3f}" in label, label
        title = choice.locator("option").last.get_attribute("title")
        assert f"{resolution} × {resolution} grid" in title, title

        page.evaluate("""() => {  // every text the status line shows, in order
            window.plyStatus = [];
            new MutationObserver(() => window.plyStatus.push(
                document.getElementById("ply-status").textContent))
              .observe(document.getElementById("ply-status"), {childList: true});
        }""")
        choice.select_option(str(level))
        hop = page.locator(".actions a", has_text="Open in 3DHOP")
        assert hop.get_attribute("href").endswith(f"/objects/relief-detail/3dhop?level={level}")
        with page.expect_download(timeout=60_000) as info:
            page.click("#download-ply")
        download = info.value
        assert download.suggested_filename == f"relief-detail_level{level}.ply"
        path = tmp_path / "level.ply"
        download.save_as(path)
        page.wait_for_function("!document.body.dataset.plyBusy")
        stats = page.evaluate("window.tessera.stats")
        shown = page.evaluate("window.plyStatus")
        heading = f"Fetching the detail tiles of levels 0–{level}: "
        fetching = [t for t in shown if t.startswith(heading)]
        percents = [int(re.search(r": (\d+) % \(", t).group(1)) for t in fetching]
        assert percents and all(0 <= p <= 100 for p in percents) and percents[-1] == 100, fetching
        assert any(t.startswith(f"Tessellating level {level} on a {resolution} × ") for t in shown)
        assert shown[-1].startswith(f"relief-detail_level{level}.ply: ")

        # every detail tile of levels 0..L came, each once: the export fetched only the rest
        wanted = {key for key in nodes if key[0] <= level}
        assert set(fetched) == wanted
        assert max(Counter(fetched).values()) == 1
        assert stats["ply_tiles_fetched"] == len(wanted - by_layer)
        assert stats["ply_fetch_bytes"] == sum(nodes[k]["bytes"] for k in wanted - by_layer)
        assert stats["ply_level"] == level and stats["ply_resolution"] == resolution
        assert stats["ply_bytes"] == path.stat().st_size

        # the file is the bundle at level L (CPython's client_py, same grid)
        header, vertices, faces = _ply_arrays(path)
        assert f"comment detail level {level}:" in header
        assert f"{resolution}x{resolution} grid" in header
        reference = tessellate_bundle(manifest, lambda name: (bundle / name).read_bytes(),
                                      level=level, resolution=resolution)
        expected = np.frombuffer(reference.positions, np.float32).reshape(-1, 3)
        assert vertices.shape == expected.shape == (resolution * resolution, 3)
        tolerance = 4 * np.finfo(np.float32).eps * np.abs(expected).max()
        assert np.abs(vertices - expected).max() <= tolerance
        assert np.array_equal(faces.ravel(), np.frombuffer(reference.indices, np.uint32))
        # ... and not the base: the detail moved the vertices
        base = tessellate_bundle(manifest, lambda name: (bundle / name).read_bytes(),
                                 level=-1, resolution=resolution)
        assert np.abs(vertices - np.frombuffer(base.positions, np.float32).reshape(-1, 3)
                      ).max() > 0.1

        # "base": the mesh on screen, as before
        choice.select_option("-1")
        assert hop.get_attribute("href").endswith("/objects/relief-detail/3dhop")
        with page.expect_download(timeout=60_000) as info:
            page.click("#download-ply")
        path = tmp_path / "base.ply"
        info.value.save_as(path)
        assert info.value.suggested_filename == "relief-detail.ply"
        header, vertices, _ = _ply_arrays(path)
        assert "detail level" not in header
        assert len(vertices) == before["vertices"] == 64 * 64
        assert page.evaluate("window.tessera.stats.ply_level") == -1
        assert page.is_enabled("#download-ply") and choice.is_enabled()
        assert page.locator("#ply-status").inner_text().startswith("relief-detail.ply: ")
        assert problems == []
        print(f"\nlevel {level} PLY, {resolution}x{resolution}: {stats['ply_tiles_fetched']} tiles "
              f"fetched ({stats['ply_fetch_bytes']} B), {stats['ply_ms']:.0f} ms in Python, "
              f"{stats['ply_total_ms']:.0f} ms in all, {stats['ply_bytes']} B")

        # a tile that cannot be fetched fails the export with its name and HTTP status
        lost = min(k for k in wanted - by_layer if k[0] == level)
        lost_file = nodes[lost]["file"]
        page.route(f"**/{lost_file}", lambda route: route.fulfill(status=404, body="gone"))
        choice.select_option(str(level))
        page.click("#download-ply")
        page.wait_for_function("!!document.body.dataset.error", timeout=30_000)
        message = page.evaluate("document.body.dataset.error")
        assert lost_file in message and "HTTP 404" in message, message
        assert page.locator("#error").is_visible()
        page.wait_for_function("!document.body.dataset.plyBusy")
        assert page.is_enabled("#download-ply")
    finally:
        context.close()


def test_download_ply_at_a_level_carries_the_texture_colours(browser, detail_server,
                                                              detail_collection, tmp_path):
    """A bundle with texture tiles: the level-L PLY has per-vertex colours, sampled from the
    texture tiles the browser fetched and decoded, equal (within WebP decoder differences) to
    client_py.tessellate_bundle with every texture tile of levels <= L decoded by Pillow; where
    the finest texture level lacks a tile, the level-0 tile colours the vertices (not black)."""
    bundle = detail_collection / "relief-texture"
    manifest = json.loads((bundle / "manifest.json").read_text())
    detail = manifest["tiles"]["detail"]
    level = len(detail["levels"]) - 1
    assert level == 1
    resolution = detail["levels"][level]["resolution"]  # as the fitter states it
    # docs/format.md, "The grid a level is drawn on": two vertices per knot span, at least
    # 256 cells across
    assert resolution == max(257, 2 * detail["spans_per_tile"] * 2**level + 1)

    context, page, problems, fetched = _open_detail_viewer(browser, detail_server,
                                                           "relief-texture", accept_downloads=True)
    textures: list[str] = []
    page.on("request", lambda r: textures.append(r.url.split("/relief-texture/", 1)[1])
            if "/texture/" in r.url else None)
    try:
        page.evaluate("window.tessera.tilesIdle()")
        textures.clear()  # the tile layer's own texture requests
        label = page.locator(f"#ply-level option[value='{level}']").inner_text()
        assert label.endswith("· colour"), label
        page.select_option("#ply-level", str(level))
        with page.expect_download(timeout=60_000) as info:
            page.click("#download-ply")
        path = tmp_path / "texture.ply"
        info.value.save_as(path)
        page.wait_for_function("!document.body.dataset.plyBusy")
        stats = page.evaluate("window.tessera.stats")

        # the texture tiles asked for: the three of level 1 and, for the missing one's
        # quadrant, level 0's
        expected_files = {"texture/0/0_0.webp", "texture/1/0_0.webp", "texture/1/1_0.webp",
                          "texture/1/0_1.webp"}
        assert set(textures) == expected_files and len(textures) == 4
        assert stats["ply_textures"] == 4
        assert stats["ply_texture_bytes"] == sum((bundle / f).stat().st_size
                                                 for f in expected_files)

        header, loaded = _load_ply(path)
        assert "property uchar red" in header
        assert "comment vertex colours sampled from 4 texture tiles of levels 0, 1" in header
        vertices = np.asarray(loaded["vertices"])
        colours = np.asarray(loaded["vertex_colors"])[:, :3].astype(int)
        positions, indices, expected = _level_reference(bundle, level, resolution)
        assert vertices.shape == positions.shape == (resolution**2, 3)
        assert np.abs(vertices - positions).max() <= 4 * np.finfo(np.float32).eps * \
            np.abs(positions).max()
        assert np.array_equal(np.asarray(loaded["faces"]).ravel(), indices)
        difference = np.abs(colours - expected.astype(int))
        assert difference.max() <= 2, difference.max()

        # independent of client_py's sampler: vertices inside a lossless level-1 tile carry its
        # gradient (red along u, green down the rows = up v, blue of the tile), and those in
        # the missing tile's quadrant level 0's red or blue stripes
        u, v = np.meshgrid(np.linspace(0, 1, resolution), np.linspace(0, 1, resolution),
                           indexing="ij")
        u, v = u.ravel(), v.ravel()
        inner = (u > 0.01) & (u < 0.49) & (v > 0.01) & (v < 0.49)  # inside tile 1/0_0
        x, y = u[inner] * 2 * 256 - 0.5, (1 - 2 * v[inner]) * 256 - 0.5
        ramp = np.linspace(0, 255, 256)
        assert np.abs(colours[inner, 0] - np.interp(x, np.arange(256), ramp)).max() <= 1.5
        assert np.abs(colours[inner, 1] - np.interp(y, np.arange(256), ramp)).max() <= 1.5
        assert (colours[inner, 2] == 60).all()
        _, mi, mj = MISSING_TEXTURE
        quadrant = (u > 0.5 * mi + 0.01) & (v > 0.5 * mj + 0.01)
        stripe = colours[quadrant]
        red = (stripe[:, 0] > stripe[:, 2] + 60).mean()
        blue = (stripe[:, 2] > stripe[:, 0] + 60).mean()
        assert red > 0.2 and blue > 0.2 and red + blue > 0.8, (red, blue)
        assert problems == []
        print(f"\ntextured level {level} PLY, {resolution}x{resolution}: {stats['ply_textures']} "
              f"texture tiles ({stats['ply_texture_bytes']} B), {stats['ply_ms']:.0f} ms in "
              f"Python, {stats['ply_total_ms']:.0f} ms in all; colour difference max "
              f"{difference.max()}, mean {difference.mean():.3f}")
    finally:
        context.close()


def _hop_available(page, server) -> None:
    if page.request.get(f"{server.url}/vendor/3dhop/js/presenter.js").status != 200:
        pytest.skip("3DHOP is not configured (../shared/vendor/3dhop-4.3 absent)")


def test_3dhop_page_at_a_detail_level(browser, detail_server, detail_collection, tmp_path):
    """?level=L on the 3DHOP page: every detail tile of levels 0..L and the texture tile are
    fetched, 3DHOP loads the level-L PLY (grid min(1025, 2 spans 2^L + 1)^2, the vertices and
    colours of client_py.tessellate_bundle at L) and shows the coloured stripes; a level the
    bundle lacks, a malformed one and ?colors=error with a level are named errors."""
    bundle = detail_collection / "relief-colour"
    manifest = json.loads((bundle / "manifest.json").read_text())
    detail = manifest["tiles"]["detail"]
    level = len(detail["levels"]) - 1
    resolution = detail["levels"][level]["resolution"]  # as the fitter states it
    # docs/format.md, "The grid a level is drawn on": two vertices per knot span, at least
    # 256 cells across
    assert resolution == max(257, 2 * detail["spans_per_tile"] * 2**level + 1)

    context, page, problems = _watched_page(browser, viewport={"width": 900, "height": 640})
    requested: list[str] = []
    page.on("request", lambda r: requested.append(r.url.split("/relief-colour/", 1)[1])
            if "/bundles/relief-colour/" in r.url else None)
    page.add_init_script("""  // every text the loading panel shows, in order
        window.loadingTexts = [];
        new MutationObserver(() => {
            const text = document.getElementById("loading-text")?.textContent;
            if (text && window.loadingTexts.at(-1) !== text) window.loadingTexts.push(text);
        }).observe(document, {subtree: true, childList: true, characterData: true});""")
    try:
        _hop_available(page, detail_server)
        page.goto(f"{detail_server.url}/objects/relief-colour/3dhop?level={level}")
        page.wait_for_function(READY, timeout=60_000)
        assert page.evaluate("document.body.dataset.error") is None
        assert page.evaluate("window.presenter._isSceneReady()") is True
        stats = page.evaluate("window.tessera.stats")
        assert stats["level"] == level and stats["resolution"] == resolution
        assert stats["vertices"] == resolution**2

        # the files: every detail tile of levels 0..L once, and the texture tile
        wanted = {n["file"] for n in detail["nodes"] if n["level"] <= level}
        textures = {n["file"] for n in manifest["tiles"]["texture"]["nodes"]}
        assert {f for f in requested if f.startswith("detail/")} == wanted
        assert {f for f in requested if f.startswith("texture/")} == textures
        assert len(requested) == len(set(requested))
        assert stats["ply_tiles_fetched"] == len(wanted)
        shown = page.evaluate("window.loadingTexts")
        assert any(t.startswith(f"Fetching the detail tiles of levels 0–{level}: ") and
                   "texture tiles: " in t for t in shown), shown
        tessellating = f"Tessellating level {level} on a {resolution} × {resolution} grid " \
                       f"with {len(wanted)} detail tiles and 1 texture tile: "
        assert any(re.fullmatch(re.escape(tessellating) + r"\d{1,3} %…", t) for t in shown), shown
        assert f"Handing the mesh to 3DHOP ({resolution**2:,} vertices)…" in shown, shown

        # the PLY 3DHOP was given is the bundle at level L, coloured
        data = base64.b64decode(page.evaluate("""async () => {  // base64: a list is slow
            const blob = await (await fetch(window.tessera.plyUrl)).blob();
            const url = await new Promise((resolve) => {
                const reader = new FileReader();
                reader.onload = () => resolve(reader.result);
                reader.readAsDataURL(blob);
            });
            return url.slice(url.indexOf(",") + 1);
        }"""))
        assert len(data) == stats["ply_bytes"]
        path = tmp_path / "hop-level.ply"
        path.write_bytes(data)
        header, loaded = _load_ply(path)
        assert f"element vertex {resolution**2}" in header and "property uchar red" in header
        assert f"comment detail level {level}:" in header
        positions, _, colours = _level_reference(bundle, level, resolution)
        vertices = np.asarray(loaded["vertices"])
        assert np.abs(vertices - positions).max() <= 4 * np.finfo(np.float32).eps * \
            np.abs(positions).max()
        assert np.abs(np.asarray(loaded["vertex_colors"])[:, :3].astype(int)
                      - colours.astype(int)).max() <= 2

        # the level choice shows L; 3DHOP draws the vertex colours: both stripes show
        assert page.locator("#hop-level").input_value() == str(level)
        assert page.locator("#hop-level option").count() == 1 + len(detail["levels"])
        assert page.is_disabled("#hop-colors")
        shot = np.asarray(Image.open(io.BytesIO(page.locator("#draw-canvas").screenshot()))
                          .convert("RGB")).astype(int)
        red = (shot[..., 0] > shot[..., 2] + 60).mean()
        blue = (shot[..., 2] > shot[..., 0] + 60).mean()
        assert red > 0.03 and blue > 0.03, (red, blue)
        assert problems == []
        print(f"\n3DHOP level {level}: {stats['vertices']} vertices, {stats['ply_bytes']} B, "
              f"{stats['tessellate_ms']:.0f} ms in Python, {stats['ply_total_ms']:.0f} ms "
              f"fetch + PLY, first frame at {stats['first_frame_ms']:.0f} ms")

        # named errors, before any mesh is made
        for query, text in ((f"level={level + 5}", f"has no detail level {level + 5} "
                             f"(its levels are 0–{level})"),
                            ("level=fine", "?level=fine is not a level of detail"),
                            (f"level={level}&colors=error", "cannot be combined with a detail "
                             f"level (?level={level})")):
            page.goto(f"{detail_server.url}/objects/relief-colour/3dhop?{query}")
            page.wait_for_function(READY, timeout=30_000)
            message = page.evaluate("document.body.dataset.error")
            assert message and text in message, (query, message)
            assert page.locator("#error").is_visible()
    finally:
        context.close()
