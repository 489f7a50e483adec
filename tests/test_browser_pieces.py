"""A single patch with a detached piece (manifest ``pieces``, ``pieces.tsa``) in headless
Chromium: the viewer fetches and draws the piece with no error, and its Download PLY of a
level is `tessera tessellate`'s, piece included; the base PLY carries it too, and so do
the 3DHOP page's."""

from __future__ import annotations

import json

import pytest
import trimesh
from fragment_scan import fragment_scan
from live import VIEWER_READY as READY
from live import download_ply, open_viewer, serve_collection

from client_py.bundle import PIECES_FILE, plan_levels
from fitter.fitting.options import FitOptions
from fitter.fitting.pipeline import fit_scan

pytestmark = pytest.mark.browser


@pytest.fixture(scope="module")
def pieces_collection(tmp_path_factory):
    """The relief with its fragment fitted as one patch (``patches=1``: the pieces are a
    single patch's; with the smooth base, the default, a mesh is an atlas)."""
    root = tmp_path_factory.mktemp("pieces-collection")
    fit_scan(fragment_scan(), root / "fragment", FitOptions(patches=1))
    return root


@pytest.fixture(scope="module")
def pieces_page(browser, pieces_collection):
    with serve_collection(pieces_collection) as live, \
            open_viewer(browser, f"{live.url}/objects/fragment/") as page:
        yield page


def test_the_viewer_fetches_and_draws_the_pieces(pieces_page, pieces_collection):
    assert pieces_page.evaluate("document.body.dataset.error") is None
    bundle = pieces_collection / "fragment"
    stats = pieces_page.evaluate("window.tessera.stats")
    assert stats["bytes_downloaded"] >= (bundle / PIECES_FILE).stat().st_size
    drawn = stats["pieces_triangles"]
    manifest = json.loads((bundle / "manifest.json").read_text())
    from client_py.atlas_format import read_atlas
    from client_py.bundle import pieces_mesh

    pieces = pieces_mesh(manifest, read_atlas((bundle / PIECES_FILE).read_bytes())[0])
    assert drawn == pieces.triangle_count > 0
    assert pieces_page.errors == []


def test_download_ply_of_a_level_is_the_cli_s_with_the_pieces(pieces_page, pieces_collection,
                                                             tmp_path):
    from fitter.cli import main

    bundle = pieces_collection / "fragment"
    manifest = json.loads((bundle / "manifest.json").read_text())
    level = plan_levels(manifest)[-1].level
    path = download_ply(pieces_page, level, tmp_path)
    out = tmp_path / "cli.ply"
    assert main(["tessellate", str(bundle), "--level", str(level), "-o", str(out)]) == 0
    assert path.read_bytes().replace(b"source base.tsp", b"source fragment") == out.read_bytes()
    assert b"detached pieces" in out.read_bytes()[:1000]
    base = download_ply(pieces_page, -1, tmp_path)
    assert b"detached pieces" in base.read_bytes()[:1000]
    mesh = trimesh.load(base, process=False, fix_texture=False)
    stats = pieces_page.evaluate("window.tessera.stats")
    assert len(mesh.faces) > stats["triangles"]  # the base grid on screen, and the pieces
    assert pieces_page.errors == []


def test_the_3dhop_page_shows_the_pieces(page, pieces_collection):
    """The 3DHOP page's PLY of a level and of the base hold the pieces (the worker has them
    before it writes either)."""
    with serve_collection(pieces_collection) as live:
        if page.request.get(f"{live.url}/vendor/3dhop/js/presenter.js").status != 200:
            pytest.skip("3DHOP is not configured (../shared/vendor/3dhop-4.3 absent)")
        errors: list[str] = []
        page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        for query in ("?level=0", ""):
            page.goto(f"{live.url}/objects/fragment/3dhop{query}")
            page.wait_for_function(READY, timeout=90_000)
            assert page.evaluate("document.body.dataset.error") is None
            header = bytes(page.evaluate("""async () => {
                const buffer = await (await fetch(window.tessera.plyUrl)).arrayBuffer();
                return Array.from(new Uint8Array(buffer.slice(0, 600)));
            }""")).split(b"end_header", 1)[0].decode()
            assert "detached pieces" in header, query
        assert errors == []


def test_a_bad_pieces_file_leaves_the_patch_drawn_and_says_why(browser, pieces_collection,
                                                               tmp_path):
    """pieces.tsa corrupt: the viewer still shows the patch, the reason in
    document.body.dataset.piecesError (the worker's PatchFormatError)."""
    import shutil

    collection = tmp_path / "collection"
    shutil.copytree(pieces_collection, collection)
    (collection / "fragment" / PIECES_FILE).write_bytes(b"not an atlas")
    with serve_collection(collection) as live, \
            open_viewer(browser, f"{live.url}/objects/fragment/") as page:
        assert page.evaluate("document.body.dataset.error") is None
        assert "PatchFormatError" in page.evaluate("document.body.dataset.piecesError")
        assert "pieces_triangles" not in page.evaluate("window.tessera.stats")
