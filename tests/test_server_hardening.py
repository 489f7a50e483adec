"""The server degrades, never dies (issue 15, part H2): a broken bundle is left out of the
gallery and the API with one logged reason, its own pages are 404s with a message; the
thumbnail reads only a bounded regular file inside its bundle and remembers its outcome; sizes
never follow symbolic links; every response carries the security headers; an unexpected error
is a JSON 500 under the APIs and a page elsewhere."""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import struct
import threading
import time
import zlib
from pathlib import Path

import pytest

from client_py import format as patch_format
from fitter.collection.bundles import MANIFEST, BundleError, Collection, parse_manifest
from fitter.server import WEB_ROOT, create_app
from fitter.server import thumbnail as thumbnail_module
from fitter.server.thumbnail import Thumbnail, ThumbnailCache

#: wall-clock bounds below: `make test` runs this file alone, after the parallel part
pytestmark = pytest.mark.timing

#: manifest text edits (applied to relief's manifest) and what parse_manifest says of each
BROKEN_MANIFESTS = {
    "stats-max-text": (lambda m: m["stats"].update(max="x"), "stats.max must be a number"),
    "grid-nan": (lambda m: m["base"].update(grid="@NaN@"), "NaN is not JSON"),
    "stats-infinity": (lambda m: m["stats"].update(rms="@Infinity@"), "Infinity is not JSON"),
    "huge-number": (lambda m: m["stats"].update(rms="@1e999@"), "numbers must be finite"),
    "grid-text": (lambda m: m["base"].update(grid="20x20"), "base.grid must be two integers"),
    "grid-bools": (lambda m: m["base"].update(grid=[True, True]),
                   "base.grid must be two integers"),
    "base-list": (lambda m: m.update(base=[1]), "'base' must be an object"),
    "file-number": (lambda m: m["base"].update(file=3), "base.file must be a relative name"),
    "file-absolute": (lambda m: m["base"].update(file="/etc/passwd"),
                      "base.file must be a relative name"),
    "file-parent": (lambda m: m["base"].update(file="../../../../etc/passwd"),
                    "base.file must be a relative name"),
    "file-backslash": (lambda m: m["base"].update(file="..\\x"), "no backslash"),
    "stats-text": (lambda m: m.update(stats="good"), "'stats' must be an object"),
    "title-number": (lambda m: m.update(title=7), "'title' must be text"),
    "provenance-bytes": (lambda m: m["provenance"].update(bytes=-1),
                         "provenance.bytes must be a number >= 0"),
    "files-sizes": (lambda m: m.update(files={"base.tsp": "big"}), "'files' must map names"),
    "version-2": (lambda m: m.update(format_version=2), "format_version 2"),
}


def _write_manifest(path: Path, manifest: dict) -> None:
    # "@NaN@" stands for a bare JSON constant the writer cannot make itself
    text = json.dumps(manifest)
    path.write_text(re.sub(r'"@([^@"]+)@"', r"\1", text))


@pytest.fixture(scope="module")
def hostile_collection(web_collection: Path, tmp_path_factory) -> Path:
    """relief, and one copy of it per entry of BROKEN_MANIFESTS (its manifest edited)."""
    root = tmp_path_factory.mktemp("hostile")
    shutil.copytree(web_collection / "relief", root / "relief")
    manifest = json.loads((root / "relief" / MANIFEST).read_text())
    for name, (edit, _) in BROKEN_MANIFESTS.items():
        folder = root / f"broken-{name}"
        folder.mkdir()
        shutil.copy(root / "relief" / "base.tsp", folder / "base.tsp")
        broken = json.loads(json.dumps(manifest))
        edit(broken)
        _write_manifest(folder / MANIFEST, broken)
    (root / "broken-deep").mkdir()
    (root / "broken-deep" / MANIFEST).write_text("[" * 100_000 + "]" * 100_000)
    (root / "broken-latin1").mkdir()
    (root / "broken-latin1" / MANIFEST).write_bytes(b'{"title": "\xe9"}')
    return root


@pytest.fixture(scope="module")
def hostile_client(hostile_collection):
    app = create_app({"TESSERA_COLLECTION": str(hostile_collection),
                      "TESSERA_PYODIDE_SNAPSHOT": False, "TESTING": True})
    return app.test_client()


def _copy_bundle(web_collection: Path, root: Path, name: str = "relief") -> Path:
    shutil.copytree(web_collection / "relief", root / name,
                    ignore=shutil.ignore_patterns("error.ply", "error.png"))
    return root / name


def _app(root: Path, **config):
    settings = {"TESSERA_COLLECTION": str(root), "TESSERA_PYODIDE_SNAPSHOT": False,
                "TESTING": True}
    settings.update(config)
    return create_app(settings)


# ------------------------------------------------------------------ broken manifests
@pytest.mark.parametrize("name", sorted(BROKEN_MANIFESTS))
def test_parse_manifest_refuses_a_malformed_field(hostile_collection, name):
    _, message = BROKEN_MANIFESTS[name]
    with pytest.raises(BundleError, match=re.escape(message)):
        parse_manifest(hostile_collection / f"broken-{name}" / MANIFEST)


def test_parse_manifest_refuses_deep_nesting_and_non_utf8(hostile_collection):
    with pytest.raises(BundleError, match="nested too deeply"):
        parse_manifest(hostile_collection / "broken-deep" / MANIFEST)
    with pytest.raises(BundleError, match="not UTF-8 text"):
        parse_manifest(hostile_collection / "broken-latin1" / MANIFEST)


def test_parse_manifest_refuses_a_manifest_that_is_no_regular_file(tmp_path):
    (tmp_path / "fifo").mkdir()
    os.mkfifo(tmp_path / "fifo" / MANIFEST)  # would block a plain open() forever
    with pytest.raises(BundleError, match="not a regular file"):
        parse_manifest(tmp_path / "fifo" / MANIFEST)
    (tmp_path / "zero").mkdir()
    (tmp_path / "zero" / MANIFEST).symlink_to("/dev/zero")  # would never end
    with pytest.raises(BundleError, match="leads outside the bundle"):
        parse_manifest(tmp_path / "zero" / MANIFEST)


def test_a_broken_bundle_is_left_out_of_the_gallery_and_the_api(hostile_client):
    gallery = hostile_client.get("/")
    assert gallery.status_code == 200
    ids = re.findall(r'data-object-id="([^"]+)"', gallery.get_data(as_text=True))
    assert ids == ["relief"]
    listed = hostile_client.get("/api/objects")
    assert listed.status_code == 200 and [o["id"] for o in listed.get_json()] == ["relief"]


@pytest.mark.parametrize("name", ["stats-max-text", "grid-nan", "file-parent", "deep"])
def test_a_broken_bundle_s_own_urls_are_404s_with_the_reason(hostile_client, name):
    object_id = f"broken-{name}"
    for url in (f"/objects/{object_id}/", f"/objects/{object_id}/3dhop",
                f"/objects/{object_id}/thumbnail.png", f"/bundles/{object_id}/base.tsp"):
        response = hostile_client.get(url)
        assert response.status_code == 404, url
        assert "is not a readable bundle" in response.get_data(as_text=True), url
    api = hostile_client.get(f"/api/objects/{object_id}")
    assert api.status_code == 404 and "is not a readable bundle" in api.get_json()["error"]


def test_a_broken_bundle_is_logged_once_per_version_of_its_manifest(web_collection, tmp_path,
                                                                    caplog):
    _copy_bundle(web_collection, tmp_path)
    broken = _copy_bundle(web_collection, tmp_path, "broken")
    manifest = json.loads((broken / MANIFEST).read_text())
    manifest["stats"]["max"] = "x"
    _write_manifest(broken / MANIFEST, manifest)
    client = _app(tmp_path).test_client()
    caplog.set_level(logging.WARNING, logger="fitter.collection.bundles")
    for _ in range(3):
        assert client.get("/").status_code == 200
        assert client.get("/api/objects").status_code == 200
    reports = [r for r in caplog.records if "broken" in r.getMessage()]
    assert len(reports) == 1 and "stats.max must be a number" in reports[0].getMessage()
    manifest["base"]["grid"] = "@NaN@"  # a new version of the manifest: reported again
    _write_manifest(broken / MANIFEST, manifest)
    os.utime(broken / MANIFEST, ns=(time.time_ns() + 10**9,) * 2)
    for _ in range(2):
        client.get("/")
    reports = [r for r in caplog.records if "broken" in r.getMessage()]
    assert len(reports) == 2


# ------------------------------------------------------------------ the thumbnail
def _thumbnail_failure(web_collection: Path, tmp_path: Path, plant) -> tuple[int, str, float]:
    bundle = _copy_bundle(web_collection, tmp_path)
    plant(bundle)
    client = _app(tmp_path).test_client()
    start = time.perf_counter()
    response = client.get("/objects/relief/thumbnail.png")
    return response.status_code, response.get_data(as_text=True), time.perf_counter() - start


def _replace_base(target: str):
    def plant(bundle: Path) -> None:
        (bundle / "base.tsp").unlink()
        (bundle / "base.tsp").symlink_to(target)
    return plant


def test_a_thumbnail_never_reads_a_symlink_out_of_its_bundle(web_collection, tmp_path):
    status, text, _ = _thumbnail_failure(web_collection, tmp_path, _replace_base("/etc/passwd"))
    assert status == 404 and "leads outside the bundle" in text
    assert "root" not in text  # the first bytes of /etc/passwd are never echoed


def test_a_thumbnail_never_reads_dev_zero(web_collection, tmp_path):
    status, text, seconds = _thumbnail_failure(web_collection, tmp_path,
                                               _replace_base("/dev/zero"))
    assert status == 404 and "leads outside the bundle" in text
    assert seconds < 1.0


def test_a_thumbnail_never_opens_a_fifo(web_collection, tmp_path):
    def plant(bundle: Path) -> None:
        (bundle / "base.tsp").unlink()
        os.mkfifo(bundle / "base.tsp")
    status, text, seconds = _thumbnail_failure(web_collection, tmp_path, plant)
    assert status == 404 and "not a regular file" in text
    assert seconds < 1.0


def test_a_thumbnail_reads_no_more_than_the_manifest_records(web_collection, tmp_path):
    recorded = json.loads((web_collection / "relief" / MANIFEST).read_text())["files"]["base.tsp"]

    def plant(bundle: Path) -> None:
        (bundle / "base.tsp").write_bytes(b"\0" * (recorded + 10_000))
    status, text, _ = _thumbnail_failure(web_collection, tmp_path, plant)
    assert status == 404
    assert f"{recorded + 10_000} bytes; at most {recorded} are read" in text


def test_a_patch_too_large_to_draw_is_refused_from_its_header(web_collection, tmp_path):
    """A 2048 x 2048 patch of zeros: 24 KB that would decode into gigabytes. The header says
    its size, and the thumbnail refuses it before decoding, at once."""
    n, bits = 2048, 12
    planes = (bits + 7) // 8
    raw = bytes(8 * (4 + 6 + 2 + n + n) + 3 * n * n * planes)
    packed = zlib.compress(raw, 9)
    flags = patch_format.FLAG_UNIFORM_U | patch_format.FLAG_UNIFORM_V
    header = patch_format.HEADER.pack(patch_format.MAGIC, patch_format.VERSION, flags, 2, 2, n,
                                      n, bits, 0, len(packed), len(raw))
    body = header + packed
    hostile = body + struct.pack("<I", zlib.crc32(body))
    assert len(hostile) < 100_000

    def plant(bundle: Path) -> None:
        (bundle / "base.tsp").write_bytes(hostile)
        manifest = json.loads((bundle / MANIFEST).read_text())
        manifest["files"]["base.tsp"] = len(hostile)
        (bundle / MANIFEST).write_text(json.dumps(manifest))
    status, text, seconds = _thumbnail_failure(web_collection, tmp_path, plant)
    assert status == 404 and "2048" in text, text
    assert seconds < 1.0


def test_a_patch_over_the_drawing_limit_says_so(monkeypatch, web_collection):
    monkeypatch.setattr(thumbnail_module, "MAX_CONTROL_POINTS", 100)
    bundle = Collection(web_collection).get("relief")
    made = thumbnail_module.thumbnail_of(bundle)
    assert made.png is None and "grid 20x20 has more than the 100 control points" in made.error


def test_thumbnails_and_their_failures_are_rendered_once_per_version(web_collection,
                                                                     tmp_path):
    _copy_bundle(web_collection, tmp_path)
    corrupt = _copy_bundle(web_collection, tmp_path, "corrupt")
    shutil.copy(web_collection / "corrupt" / "base.tsp", corrupt / "base.tsp")
    app = _app(tmp_path)
    client = app.test_client()
    cache = app.extensions["tessera_thumbnails"]
    first = client.get("/objects/relief/thumbnail.png")
    bad = client.get("/objects/corrupt/thumbnail.png")
    assert first.status_code == 200 and bad.status_code == 404 and cache.renders == 2
    start = time.perf_counter()
    for _ in range(5):
        assert client.get("/objects/relief/thumbnail.png").data == first.data
        again = client.get("/objects/corrupt/thumbnail.png")
        assert again.status_code == 404 and "CRC32" in again.get_data(as_text=True)
    assert cache.renders == 2  # the failure is remembered as well as the success
    assert time.perf_counter() - start < 1.0
    # a new version of the file is drawn again
    (corrupt / "base.tsp").write_bytes((tmp_path / "relief" / "base.tsp").read_bytes())
    os.utime(corrupt / "base.tsp", ns=(time.time_ns() + 10**9,) * 2)
    assert client.get("/objects/corrupt/thumbnail.png").status_code == 200
    assert cache.renders == 3


def test_the_thumbnail_cache_is_bounded_in_entries_and_bytes():
    cache = ThumbnailCache(max_entries=2, max_bytes=10_000)
    for key in "abc":
        cache.get(key, lambda: Thumbnail(b"x" * 100))
    assert len(cache) == 2
    cache.get("a", lambda: Thumbnail(b"new"))  # "a" was the least recently used: evicted
    assert cache.renders == 4
    cache.get("c", lambda: Thumbnail(b"x" * 100))  # still kept
    assert cache.renders == 4
    for key in "defgh":
        cache.get(key, lambda: Thumbnail(b"x" * 4_000))
    assert cache.nbytes <= 10_000 and len(cache) == 2
    with pytest.raises(ValueError, match="max_entries, max_bytes and renders_at_once"):
        ThumbnailCache(max_entries=0)


def test_concurrent_requests_for_one_thumbnail_render_it_once():
    cache = ThumbnailCache()
    started = threading.Event()

    def slow() -> Thumbnail:
        started.set()
        time.sleep(0.2)
        return Thumbnail(None, "bad patch")

    results = []
    threads = [threading.Thread(target=lambda: results.append(cache.get("k", slow)))
               for _ in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert cache.renders == 1 and len(results) == 8
    assert all(r.error == "bad patch" for r in results)


# ------------------------------------------------------------------ sizes and symlinks
def test_sizes_never_follow_symlinks_out_of_the_bundle(web_collection, tmp_path):
    bundle = _copy_bundle(web_collection, tmp_path / "collection")
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "big.bin").write_bytes(b"\0" * 123_457)
    (bundle / "leak.bin").symlink_to(outside / "big.bin")
    (bundle / "leakdir").symlink_to(outside)
    (bundle / "passwd").symlink_to("/etc/passwd")
    summary = _app(tmp_path / "collection").test_client().get("/api/objects/relief").get_json()
    assert not {"leak.bin", "passwd"} & set(summary["files"])
    assert not any(name.startswith("leakdir") for name in summary["files"])
    regular = {p.relative_to(bundle).as_posix(): p.stat().st_size for p in bundle.rglob("*")
               if p.is_file() and not p.is_symlink() and not p.relative_to(bundle).as_posix()
               .startswith("leakdir")}
    assert summary["files"] == regular
    assert summary["bytes"] == sum(regular.values())


# ------------------------------------------------------------------ security headers
PUBLIC_URLS = ["/", "/api/objects", "/api/objects/relief", "/objects/relief/",
               "/objects/relief/3dhop", "/objects/relief/thumbnail.png",
               "/bundles/relief/base.tsp", "/bundles/relief/manifest.json",
               "/web/src/mesh-worker.js", "/vendor/pyodide/pyodide.mjs",
               "/client_py/sources.json", "/objects/no-such-thing/", "/api/objects/nothing"]


@pytest.mark.parametrize("url", PUBLIC_URLS)
def test_every_public_response_has_the_security_headers_and_stays_embeddable(hostile_client,
                                                                            url):
    response = hostile_client.get(url)
    assert response.headers["X-Content-Type-Options"] == "nosniff"
    assert response.headers["Referrer-Policy"] == "strict-origin-when-cross-origin"
    csp = response.headers["Content-Security-Policy"]
    for directive in ("default-src 'self'", "object-src 'none'", "worker-src 'self' blob:",
                      "'wasm-unsafe-eval'"):
        assert directive in csp
    assert "'unsafe-inline'" not in csp.split("script-src", 1)[1].split(";", 1)[0]
    # the README's <iframe> embed works on any site: no frame restriction on public pages
    assert "X-Frame-Options" not in response.headers and "frame-ancestors" not in csp


def test_the_viewer_s_import_map_carries_the_policy_s_nonce(hostile_client):
    response = hostile_client.get("/objects/relief/")
    nonce = re.search(r"'nonce-([^']+)'", response.headers["Content-Security-Policy"]).group(1)
    assert f'<script nonce="{nonce}" type="importmap">' in response.get_data(as_text=True)
    other = hostile_client.get("/objects/relief/").headers["Content-Security-Policy"]
    assert f"'nonce-{nonce}'" not in other  # one per response


def test_no_template_has_an_inline_event_handler():
    for template in sorted((WEB_ROOT / "templates").glob("*.html")):
        text = template.read_text()
        assert not re.search(r"\son[a-z]+\s*=", text), template.name


def test_a_3dhop_url_elsewhere_is_allowed_by_the_policy(web_collection):
    app = _app(web_collection, TESSERA_3DHOP_DIR="",
               TESSERA_3DHOP_URL="https://hop.example.org/3dhop/minimal/")
    csp = app.test_client().get("/objects/relief/3dhop").headers["Content-Security-Policy"]
    script = csp.split("script-src", 1)[1].split(";", 1)[0]
    assert "https://hop.example.org" in script


# ------------------------------------------------------------------ errors in kind
def _boom() -> None:
    raise RuntimeError("a bug with a secret in its message")


def test_an_unexpected_error_is_a_page_or_json_500_and_is_logged(web_collection, caplog):
    app = _app(web_collection, TESTING=False)
    app.view_functions["gallery.index"] = _boom
    app.view_functions["api.list_objects"] = _boom
    client = app.test_client()
    with caplog.at_level(logging.ERROR):
        page = client.get("/")
        api = client.get("/api/objects")
    assert page.status_code == 500 and page.mimetype == "text/html"
    assert "the server failed to answer this request" in page.get_data(as_text=True)
    assert "secret" not in page.get_data(as_text=True)
    assert api.status_code == 500 and "the server failed" in api.get_json()["error"]
    assert page.headers["X-Content-Type-Options"] == "nosniff"
    assert any(r.exc_info and "a bug with a secret" in str(r.exc_info[1])
               for r in caplog.records)


def test_a_wrong_method_under_the_api_is_json(hostile_client):
    response = hostile_client.post("/api/objects")
    assert response.status_code == 405 and response.is_json
    assert "GET" in response.headers["Allow"]


# ------------------------------------------------------------------ the policy in a browser
#: records every Content-Security-Policy violation of the page (and of its workers' reports)
RECORD_VIOLATIONS = """
window.__cspViolations = [];
document.addEventListener("securitypolicyviolation", (event) => {
  window.__cspViolations.push(`${event.violatedDirective} ${event.blockedURI}`);
});
"""
READY = "document.body.dataset.ready === '1' || !!document.body.dataset.error"


@pytest.mark.parametrize("path", ["/", "/objects/relief/?resolution=48", "/objects/relief/3dhop"])
def test_the_pages_run_under_their_policy_without_a_violation(page, live_server, path):
    if path.endswith("3dhop") and page.request.get(
            f"{live_server.url}/vendor/3dhop/js/presenter.js").status != 200:
        pytest.skip("3DHOP is not configured (../shared/vendor/3dhop-4.3 absent)")
    refused = []
    page.on("console", lambda message: refused.append(message.text)
            if "Content Security Policy" in message.text else None)
    page.add_init_script(RECORD_VIOLATIONS)
    response = page.goto(f"{live_server.url}{path}")
    assert "script-src 'self'" in response.header_value("Content-Security-Policy")
    if path == "/":
        # the corrupt object's card falls back to its note (the handler of a module, not an
        # inline attribute), the relief's shows its thumbnail
        page.wait_for_function("document.querySelector('[data-object-id=corrupt] .thumb')"
                               ".classList.contains('missing')", timeout=20_000)
        assert not page.evaluate("document.querySelector('[data-object-id=relief] .thumb')"
                                 ".classList.contains('missing')")
    else:
        page.wait_for_function(READY, timeout=90_000)
        assert page.evaluate("document.body.dataset.error || null") is None
    assert page.evaluate("window.__cspViolations") == [] and refused == []
