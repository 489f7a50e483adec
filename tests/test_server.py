"""The Flask server through its test client: routes, JSON, caching, ranges, gzip, MIME types,
404s and path traversal, settings, the ``serve`` command. Browser behaviour is in test_browser.py.
"""

from __future__ import annotations

import gzip
import io
import json
import os
import re
from pathlib import Path

import brotli
import numpy as np
import pytest
from PIL import Image

import client_py
from fitter.cli import build_parser, main
from fitter.collection.bundles import FIT_RECORDS, Collection, served_manifest
from fitter.server import DEFAULTS, SOURCE_CHECKOUT, WEB_ROOT, create_app, load_settings

HOP_DIR = Path(DEFAULTS["TESSERA_3DHOP_DIR"][0]) if DEFAULTS["TESSERA_3DHOP_DIR"][0] else None


@pytest.fixture()
def client(web_app):
    return web_app.test_client()


def _bundle_bytes(directory: Path) -> int:
    return sum(p.stat().st_size for p in directory.rglob("*") if p.is_file())


# ------------------------------------------------------------------------ settings
def test_settings_environment_overrides_default_and_config_overrides_both():
    env = {"TESSERA_PYODIDE_TIMEOUT": "12.5", "TESSERA_GZIP": "off", "TESSERA_COLLECTION": "/x"}
    settings = load_settings({"TESSERA_COLLECTION": "/y"}, environ=env)
    assert settings["TESSERA_PYODIDE_TIMEOUT"] == 12.5
    assert settings["TESSERA_GZIP"] is False
    assert settings["TESSERA_COLLECTION"] == "/y"
    assert settings["TESSERA_RESOLUTION"] == DEFAULTS["TESSERA_RESOLUTION"][0]


def test_settings_reject_a_malformed_environment_value():
    with pytest.raises(ValueError, match="TESSERA_PYODIDE_TIMEOUT='soon'"):
        load_settings(environ={"TESSERA_PYODIDE_TIMEOUT": "soon"})
    with pytest.raises(ValueError, match="TESSERA_GZIP='maybe'"):
        load_settings(environ={"TESSERA_GZIP": "maybe"})


def test_create_app_needs_a_collection_directory(tmp_path, monkeypatch):
    monkeypatch.delenv("TESSERA_COLLECTION", raising=False)
    with pytest.raises(ValueError, match="TESSERA_COLLECTION is not set"):
        create_app()
    with pytest.raises(ValueError, match="not a directory"):
        create_app({"TESSERA_COLLECTION": str(tmp_path / "missing")})
    with pytest.raises(ValueError, match="TESSERA_PYODIDE_DIR"):
        create_app({"TESSERA_COLLECTION": str(tmp_path),
                    "TESSERA_PYODIDE_DIR": str(tmp_path / "x")})


# ------------------------------------------------------------------------ API and pages
def test_api_lists_the_collection_with_root_relative_urls(client, web_collection):
    response = client.get("/api/objects")
    assert response.status_code == 200
    objects = {o["id"]: o for o in response.get_json()}
    assert set(objects) == {"corrupt", "relief"}
    relief = objects["relief"]
    manifest = json.loads((web_collection / "relief" / "manifest.json").read_text())
    assert relief["title"] == "Carved relief (generated example)" == manifest["title"]
    assert relief["viewer_url"] == "/objects/relief/"
    assert relief["bundle_url"] == "/bundles/relief/"
    assert relief["bytes"] == _bundle_bytes(web_collection / "relief")
    assert relief["stats"]["rms"] == pytest.approx(manifest["stats"]["rms"])
    assert relief["grid"] == [20, 20]
    # every URL it gives works
    for key in ("viewer_url", "hop_url", "thumbnail_url", "manifest_url"):
        assert client.get(relief[key]).status_code == 200, key


def test_api_unknown_object_is_a_json_404(client):
    response = client.get("/api/objects/no-such-thing")
    assert response.status_code == 404
    assert "no object 'no-such-thing'" in response.get_json()["error"]


def test_gallery_lists_every_object(client):
    page = client.get("/").get_data(as_text=True)
    assert page.count('class="card"') == 2
    assert "Carved relief (generated example)" in page
    assert 'href="/objects/relief/"' in page


def test_viewer_page_passes_its_urls_and_import_map(client):
    html = client.get("/objects/relief/?resolution=64").get_data(as_text=True)
    config = json.loads(html.split('id="tessera-config">', 1)[1].split("</script>", 1)[0])
    assert config["patch_url"] == "/bundles/relief/base.tsp"
    assert re.fullmatch(r"/vendor/pyodide/v/[\w.]+/", config["pyodide_url"])
    assert config["resolution"] == 64
    import_map = json.loads(html.split('type="importmap">', 1)[1].split("</script>", 1)[0])
    assert re.fullmatch(r"/vendor/three/v/[\w.]+/build/three.module.js",
                        import_map["imports"]["three"])
    for url in (config["worker_url"], config["client_py_url"], import_map["imports"]["three"]):
        assert url.startswith("/")


@pytest.mark.parametrize("value", ["abc", "1", "5000"])
def test_viewer_rejects_a_bad_resolution_with_400(client, value):
    response = client.get(f"/objects/relief/?resolution={value}")
    assert response.status_code == 400
    assert "resolution must be" in response.get_data(as_text=True)


def test_unknown_object_is_a_404_page(client):
    response = client.get("/objects/no-such-thing/")
    assert response.status_code == 404
    assert response.mimetype == "text/html"
    assert "no object &#39;no-such-thing&#39;" in response.get_data(as_text=True)


def test_thumbnail_is_a_rendered_png_and_a_corrupt_patch_has_none(client):
    response = client.get("/objects/relief/thumbnail.png")
    assert response.status_code == 200 and response.mimetype == "image/png"
    image = Image.open(io.BytesIO(response.data))
    assert image.size == (320, 240)
    alpha = np.asarray(image.getchannel("A"))
    assert (alpha > 0).mean() > 0.4  # the object fills most of the card
    bad = client.get("/objects/corrupt/thumbnail.png")
    assert bad.status_code == 404
    assert "CRC32" in bad.get_data(as_text=True)


# ------------------------------------------------------------------------ bundle files
def test_bundle_files_are_immutable_with_etag_and_304(client, web_collection):
    response = client.get("/bundles/relief/base.tsp")
    assert response.status_code == 200
    assert response.data == (web_collection / "relief" / "base.tsp").read_bytes()
    cache = response.headers["Cache-Control"]
    assert "immutable" in cache and "max-age=31536000" in cache and "public" in cache
    etag = response.headers["ETag"]
    again = client.get("/bundles/relief/base.tsp", headers={"If-None-Match": etag})
    assert again.status_code == 304 and again.data == b""


def test_bundle_files_serve_http_ranges(client, web_collection):
    data = (web_collection / "relief" / "base.tsp").read_bytes()
    response = client.get("/bundles/relief/base.tsp", headers={"Range": "bytes=4-27"})
    assert response.status_code == 206
    assert response.data == data[4:28]
    assert response.headers["Content-Range"] == f"bytes 4-27/{len(data)}"


def test_a_visitor_is_served_the_manifest_without_the_fits_own_records(client, web_collection):
    on_disk = json.loads((web_collection / "relief" / "manifest.json").read_text())
    assert {"fit", "timings", "options", "files"} <= set(on_disk)  # kept for the admin
    response = client.get("/bundles/relief/manifest.json")
    served = json.loads(response.get_data())
    assert not set(FIT_RECORDS) & set(served)
    # everything else as in the file (stats_all_points left out only where it repeats stats)
    kept = {k: v for k, v in on_disk.items() if k not in FIT_RECORDS}
    if kept.get("stats_all_points") == kept.get("stats"):
        del kept["stats_all_points"]
    assert served == kept
    assert len(response.data) < 0.8 * len(json.dumps(on_disk).encode())
    cache = response.headers["Cache-Control"]  # a plain collection's bundles never change
    assert "immutable" in cache and "max-age=31536000" in cache and "public" in cache
    again = client.get("/bundles/relief/manifest.json",
                       headers={"If-None-Match": response.headers["ETag"]})
    assert again.status_code == 304 and again.data == b""
    # what the gallery says a visit downloads counts the manifest as served
    summary = client.get("/api/objects/relief").get_json()
    assert summary["view_bytes"] == len(response.data) + summary["files"]["base.tsp"]


def test_the_visitors_manifest_in_brotli_and_uncached_when_bundles_are(client, web_collection):
    served = served_manifest(json.loads((web_collection / "relief" / "manifest.json")
                                        .read_text()))
    response = client.get("/bundles/relief/manifest.json",
                          headers={"Accept-Encoding": "gzip, br"})
    assert response.headers["Content-Encoding"] == "br"
    assert brotli.decompress(response.data) == served
    assert response.headers["ETag"].endswith('-br"')
    zipped = client.get("/bundles/relief/manifest.json", headers={"Accept-Encoding": "gzip"})
    assert zipped.headers["ETag"] != response.headers["ETag"]
    # a server told not to cache bundles revalidates the manifest too
    app = create_app({"TESSERA_COLLECTION": str(web_collection), "TESTING": True,
                      "TESSERA_BUNDLE_MAX_AGE": 0})
    cache = app.test_client().get("/bundles/relief/manifest.json").headers["Cache-Control"]
    assert "no-cache" in cache and "immutable" not in cache


def test_gzip_only_when_accepted_and_when_it_helps(client, web_collection):
    manifest = served_manifest(json.loads((web_collection / "relief" / "manifest.json")
                                          .read_text()))
    zipped = client.get("/bundles/relief/manifest.json", headers={"Accept-Encoding": "gzip"})
    assert zipped.headers.get("Content-Encoding") == "gzip"
    assert gzip.decompress(zipped.data) == manifest
    assert len(zipped.data) < len(manifest)
    assert "Accept-Encoding" in zipped.headers["Vary"]
    revalidated = client.get("/bundles/relief/manifest.json", headers={
        "Accept-Encoding": "gzip", "If-None-Match": zipped.headers["ETag"]})
    assert revalidated.status_code == 304
    plain = client.get("/bundles/relief/manifest.json")
    assert "Content-Encoding" not in plain.headers and plain.data == manifest
    # base.tsp is zlib-compressed already: never gzipped again
    patch = client.get("/bundles/relief/base.tsp", headers={"Accept-Encoding": "gzip"})
    assert "Content-Encoding" not in patch.headers


@pytest.mark.parametrize("url", [
    "/bundles/relief/..%2f..%2fcorrupt/base.tsp",
    "/bundles/relief/%2e%2e/corrupt/base.tsp",
    "/bundles/relief/..%2F..%2F..%2F..%2Fetc%2Fpasswd",
    "/bundles/..%2frelief/manifest.json",
    "/bundles/relief//etc/passwd",
    "/vendor/pyodide/..%2fthree%2fpackage.json",
    "/vendor/three/package.json",
    "/web/package.json",
    "/web/templates/viewer.html",
    "/web/node_modules/three/package.json",
])
def test_paths_outside_are_404(client, url):
    # werkzeug may first redirect a URL with "//" to its merged form: follow it
    assert client.get(url, follow_redirects=True).status_code == 404


def test_symlink_out_of_a_bundle_is_404(web_collection, tmp_path):
    outside = tmp_path / "secret.txt"
    outside.write_text("not for the web")
    link = web_collection / "relief" / "leak.txt"
    link.symlink_to(outside)
    try:
        app = create_app({"TESSERA_COLLECTION": str(web_collection)})
        assert app.test_client().get("/bundles/relief/leak.txt").status_code == 404
    finally:
        link.unlink()


def test_a_single_bundle_directory_is_a_collection_of_one(web_collection):
    bundles = Collection(web_collection / "relief").bundles()
    assert [b.id for b in bundles] == ["relief"]


# ------------------------------------------------------------------------ runtime
@pytest.mark.parametrize("gzip_ok", [False, True])
def test_pyodide_mime_types(client, gzip_ok):
    headers = {"Accept-Encoding": "gzip"} if gzip_ok else {}
    wasm = client.get("/vendor/pyodide/pyodide.asm.wasm", headers=headers)
    assert wasm.status_code == 200
    assert wasm.headers["Content-Type"] == "application/wasm"
    body = gzip.decompress(wasm.data) if gzip_ok else wasm.data
    assert body[:4] == b"\0asm"
    for name in ("pyodide.mjs", "pyodide.asm.mjs"):
        module = client.get(f"/vendor/pyodide/{name}", headers=headers)
        assert module.status_code == 200
        assert module.headers["Content-Type"].startswith("text/javascript")
    assert client.get("/vendor/pyodide/python_stdlib.zip").headers["Content-Type"] == \
        "application/zip"


def test_three_and_web_modules_are_javascript(client):
    for url in ("/vendor/three/build/three.module.js",
                "/vendor/three/examples/jsm/controls/OrbitControls.js",
                "/web/src/viewer-page.js", "/web/src/mesh-worker.js"):
        response = client.get(url)
        assert response.status_code == 200, url
        assert response.headers["Content-Type"].startswith("text/javascript"), url


def test_client_py_sources_are_the_package_files(client):
    response = client.get("/client_py/sources.json")
    sources = response.get_json()
    package = Path(client_py.__file__).parent  # the package the server imported
    on_disk = {p.name for p in package.glob("*.py")}
    assert set(sources["files"]) >= on_disk
    assert sources["files"]["format.py"] == (package / "format.py").read_text(encoding="utf-8")
    etag = response.headers["ETag"]
    again = client.get("/client_py/sources.json", headers={"If-None-Match": etag})
    assert again.status_code == 304


def test_pyodide_snapshot_is_served_immutable_and_gzipped(web_collection):
    # the snapshot is off by default (the first visit's byte budget): turned on here
    app = create_app({"TESSERA_COLLECTION": str(web_collection), "TESSERA_PYODIDE_SNAPSHOT": True,
                      "TESTING": True})
    builder = app.extensions["tessera_snapshot"]
    if builder.ensure() is None:
        pytest.skip(f"no Pyodide snapshot on this machine: {builder.failure}")
    client = app.test_client()
    html = client.get("/objects/relief/").get_data(as_text=True)
    config = json.loads(html.split('id="tessera-config">', 1)[1].split("</script>", 1)[0])
    assert config["pyodide_snapshot_url"] == f"/vendor/pyodide-snapshot/{builder.key}.bin"
    response = client.get(config["pyodide_snapshot_url"], headers={"Accept-Encoding": "gzip"})
    assert response.status_code == 200
    assert "immutable" in response.headers["Cache-Control"]
    assert response.headers["Content-Encoding"] == "gzip"
    assert gzip.decompress(response.data) == builder.path.read_bytes()
    assert client.get("/vendor/pyodide-snapshot/pyodide-0-stale.bin").status_code == 404


def test_pages_load_pyodide_plainly_without_a_snapshot(web_collection):
    app = create_app({"TESSERA_COLLECTION": str(web_collection),
                      "TESSERA_PYODIDE_SNAPSHOT": False})
    html = app.test_client().get("/objects/relief/").get_data(as_text=True)
    assert '"pyodide_snapshot_url": null' in html


def test_the_snapshot_cache_is_the_instance_folder_unless_set(web_collection, tmp_path,
                                                                monkeypatch):
    monkeypatch.delenv("TESSERA_CACHE_DIR", raising=False)
    app = create_app({"TESSERA_COLLECTION": str(web_collection), "TESSERA_PYODIDE_SNAPSHOT": True})
    # a checkout's instance folder is instance/ at its root (Flask's rule for a package
    # that is not installed); tests/ sits at that root too
    checkout = Path(__file__).resolve().parent.parent
    assert Path(app.instance_path) == checkout / "instance"
    assert app.config["TESSERA_CACHE_DIR"] == str(checkout / "instance" / "cache")
    assert app.extensions["tessera_snapshot"].cache_dir == checkout / "instance" / "cache"
    chosen = create_app({"TESSERA_COLLECTION": str(web_collection),
                         "TESSERA_PYODIDE_SNAPSHOT": True,
                         "TESSERA_CACHE_DIR": str(tmp_path / "snapshots")})
    assert chosen.extensions["tessera_snapshot"].path.parent == tmp_path / "snapshots"


def test_an_unwritable_snapshot_cache_is_a_logged_failure(web_collection, tmp_path):
    (tmp_path / "a-file").write_text("not a folder")
    app = create_app({"TESSERA_COLLECTION": str(web_collection), "TESSERA_NODE": "node",
                      "TESSERA_PYODIDE_SNAPSHOT": True,
                      "TESSERA_CACHE_DIR": str(tmp_path / "a-file" / "cache")})
    builder = app.extensions["tessera_snapshot"]
    assert builder.ensure() is None
    assert builder.failure.startswith(f"cannot write in the cache folder {tmp_path}")
    html = app.test_client().get("/objects/relief/").get_data(as_text=True)
    assert '"pyodide_snapshot_url": null' in html



def test_builds_sharing_a_cache_folder_at_once_all_get_the_snapshot(tmp_path):
    """Several server processes (WSGI workers) may build the same snapshot at once: each
    builds in a folder of its own and the atomic replace leaves one whole file."""
    import threading

    from fitter.server.snapshot import SnapshotBuilder

    fake_node = tmp_path / "node"  # writes its output slowly, as the real build does
    fake_node.write_text("#!/usr/bin/env python3\nimport sys, time\n"
                         "out = open(sys.argv[4], 'wb')\nout.write(b'half ')\n"
                         "time.sleep(0.3)\nout.write(b'snapshot')\n")
    fake_node.chmod(0o755)
    cache = tmp_path / "cache"
    builders = [SnapshotBuilder(tmp_path / "pyodide", {"sha256": "0" * 64}, cache,
                                node=str(fake_node)) for _ in range(3)]
    found: list = [None] * len(builders)

    def build(i: int) -> None:
        found[i] = builders[i].ensure()

    threads = [threading.Thread(target=build, args=(i,)) for i in range(len(builders))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert [b.failure for b in builders] == [None] * len(builders)
    assert found == [builders[0].path] * len(builders)
    assert builders[0].path.read_bytes() == b"half snapshot"
    assert [p.name for p in cache.iterdir()] == [builders[0].path.name]  # nothing left over

def test_a_checkout_serves_its_own_web_folder():
    checkout = Path(__file__).resolve().parent.parent
    assert SOURCE_CHECKOUT == checkout and WEB_ROOT == checkout / "web"
    assert DEFAULTS["TESSERA_WEB_DIR"][0] == str(checkout / "web")
    assert DEFAULTS["TESSERA_PYODIDE_DIR"][0] == str(checkout / "web" / "node_modules" / "pyodide")


@pytest.mark.skipif(HOP_DIR is None, reason="3DHOP 4.3 is not in ../shared/vendor/3dhop-4.3")
def test_3dhop_page_and_files_are_served(client):
    page = client.get("/objects/relief/3dhop").get_data(as_text=True)
    assert 'src="/vendor/3dhop/js/presenter.js"' in page
    assert client.get("/vendor/3dhop/js/presenter.js").status_code == 200
    assert client.get("/vendor/3dhop/..%2f..%2fREADME.md").status_code == 404


def test_3dhop_page_is_404_when_not_configured(web_collection):
    app = create_app({"TESSERA_COLLECTION": str(web_collection), "TESSERA_3DHOP_DIR": "",
                      "TESSERA_3DHOP_URL": ""})
    response = app.test_client().get("/objects/relief/3dhop")
    assert response.status_code == 404
    assert "TESSERA_3DHOP_DIR" in response.get_data(as_text=True)
    viewer = app.test_client().get("/objects/relief/").get_data(as_text=True)
    assert "Open in 3DHOP" not in viewer


def test_3dhop_from_a_url(web_collection):
    app = create_app({"TESSERA_COLLECTION": str(web_collection), "TESSERA_3DHOP_DIR": "",
                      "TESSERA_3DHOP_URL": "https://museum.example/3dhop"})
    page = app.test_client().get("/objects/relief/3dhop").get_data(as_text=True)
    assert 'src="https://museum.example/3dhop/js/presenter.js"' in page


# ------------------------------------------------------------------------ CLI
def test_serve_command_parses_and_validates(tmp_path):
    args = build_parser().parse_args(["serve", str(tmp_path), "--host", "0.0.0.0", "--port", "0"])
    assert (args.collection, args.host, args.port) == (str(tmp_path), "0.0.0.0", 0)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["serve", str(tmp_path), "--port", "70000"])


def test_serve_command_reports_a_missing_collection(tmp_path, capsys):
    assert main(["serve", str(tmp_path / "nowhere")]) == 2
    assert "not a directory" in capsys.readouterr().err


# ------------------------------------------------------------ honest and small first visits
def _page_config(client, path="/objects/relief/"):
    html = client.get(path).get_data(as_text=True)
    return json.loads(html.split('id="tessera-config">', 1)[1].split("</script>", 1)[0]), html


def test_runtime_urls_carry_versions_and_are_immutable(client):
    config, html = _page_config(client)
    import_map = json.loads(html.split('type="importmap">', 1)[1].split("</script>", 1)[0])
    for url in (f"{config['pyodide_url']}pyodide.mjs", config["worker_url"],
                config["client_py_url"], config["pyodide_stdlib_url"],
                import_map["imports"]["three"]):
        response = client.get(url, headers={"Accept-Encoding": "gzip"})
        assert response.status_code == 200, url
        cache = response.headers["Cache-Control"]
        assert "immutable" in cache and "max-age=31536000" in cache, (url, cache)
    # the same files without a version, or under a version that is not the current one, are
    # revalidated: never kept as if they could not change
    for url in ("/web/src/viewer.js", config["worker_url"].replace("/v/", "/v/0", 1),
                "/client_py/sources.json"):
        cache = client.get(url).headers["Cache-Control"]
        assert "immutable" not in cache and "no-cache" in cache, (url, cache)
    assert client.get("/client_py/0123/sources.json").status_code == 404


def test_an_edited_module_gets_a_new_url(client, web_app):
    from fitter.server.runtime import web_version

    before = web_version(web_app.config["TESSERA_WEB_DIR"])
    module = Path(web_app.config["TESSERA_WEB_DIR"]) / "src" / "fetch-bytes.js"
    stat = module.stat()
    try:
        os.utime(module, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000))
        assert web_version(web_app.config["TESSERA_WEB_DIR"]) != before
    finally:
        os.utime(module, ns=(stat.st_atime_ns, stat.st_mtime_ns))


@pytest.mark.parametrize(("accept", "encoding"), [
    ("gzip, deflate, br, zstd", "br"), ("gzip, deflate", "gzip"), ("br;q=0, gzip", "gzip"),
    ("identity", None), ("", None)])
def test_compressed_forms_follow_accept_encoding(client, web_app, accept, encoding):
    from fitter.server.files import compressed_cache

    url = "/vendor/pyodide/pyodide.asm.mjs"
    client.get(url, headers={"Accept-Encoding": "br"})
    with web_app.app_context():
        compressed_cache().wait()  # brotli is made in the background, once
    response = client.get(url, headers={"Accept-Encoding": accept})
    original = (Path(web_app.config["TESSERA_PYODIDE_DIR"]) / "pyodide.asm.mjs").read_bytes()
    assert response.headers.get("Content-Encoding") == encoding
    assert response.headers["Vary"] == "Accept-Encoding"
    body = {"br": brotli.decompress, "gzip": gzip.decompress, None: bytes}[encoding](response.data)
    assert body == original
    if encoding:
        assert len(response.data) < 0.4 * len(original)
        again = client.get(url, headers={"Accept-Encoding": accept,
                                         "If-None-Match": response.headers["ETag"].strip('"')})
        assert again.status_code == 304


def test_compressed_copies_live_in_the_cache_folder(client, web_app):
    from fitter.server.files import compressed_cache

    client.get("/vendor/pyodide/pyodide.mjs", headers={"Accept-Encoding": "gzip"})
    with web_app.app_context():
        cache = compressed_cache()
        path = Path(web_app.config["TESSERA_PYODIDE_DIR"]).resolve() / "pyodide.mjs"
        copy = cache.copy_path(path, path.stat(), "gzip")
    assert copy.parent == Path(web_app.config["TESSERA_CACHE_DIR"]) / "compressed"
    assert gzip.decompress(copy.read_bytes()) == path.read_bytes()


def test_client_py_sources_are_compressed(client):
    config, _ = _page_config(client)
    response = client.get(config["client_py_url"], headers={"Accept-Encoding": "gzip"})
    assert response.headers["Content-Encoding"] == "gzip"
    sources = json.loads(gzip.decompress(response.data))
    assert sources["sha256"] in config["client_py_url"]


def test_trimmed_stdlib_holds_what_client_py_and_pyodide_import(client, web_app):
    import zipfile

    config, _ = _page_config(client)
    data = client.get(config["pyodide_stdlib_url"]).data
    full = Path(web_app.config["TESSERA_PYODIDE_DIR"]) / "python_stdlib.zip"
    with zipfile.ZipFile(io.BytesIO(data)) as trimmed, zipfile.ZipFile(full) as original:
        names = set(trimmed.namelist())
        for name in ("json/__init__.py", "traceback.py", "codeop.py", "_pyodide/docstring.py",
                     "pyodide/ffi/__init__.py", "encodings/utf_8.py", "encodings/latin_1.py"):
            assert name in names, name
            assert trimmed.read(name) == original.read(name)
        for name in ("sqlite3/__init__.py", "zoneinfo/__init__.py", "tomllib/__init__.py",
                     "encodings/cp1252.py"):  # in Pyodide's archive, never imported here
            assert name in original.namelist() and name not in names, name
    assert config["runtime_bytes"]["python_stdlib.zip"] == len(data)
    # stored members, compressed over the whole archive on the wire: smaller than the same
    # members deflated one by one (issue 14: the stdlib was sent without compression)
    with zipfile.ZipFile(io.BytesIO(data)) as trimmed:
        assert {info.compress_type for info in trimmed.infolist()} == {zipfile.ZIP_STORED}
        deflated = io.BytesIO()
        with zipfile.ZipFile(deflated, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as each:
            for info in trimmed.infolist():
                each.writestr(info, trimmed.read(info), compress_type=zipfile.ZIP_DEFLATED)
    zipped = client.get(config["pyodide_stdlib_url"], headers={"Accept-Encoding": "gzip"})
    assert zipped.headers["Content-Encoding"] == "gzip"
    assert "immutable" in zipped.headers["Cache-Control"]
    assert gzip.decompress(zipped.data) == data
    assert len(zipped.data) < 0.95 * len(deflated.getvalue()) < 0.75 * full.stat().st_size
    assert config["pyodide_lock"]["packages"] == {}
    assert config["pyodide_lock"]["info"]["abi_version"]


def test_imports_are_found_in_source_this_python_cannot_parse():
    from fitter.server.stdlib import imported_names

    source = ("import a.b as c, d\nfrom . import (x,  # a comment, with (a, b)\n  y)\n"
              "from .q import z as w, v\n"
              "try:\n    pass\nexcept A, B:\n    pass\n")
    assert imported_names(source, "pkg.mod", is_package=False) == {
        "a", "a.b", "d", "pkg", "pkg.x", "pkg.y", "pkg.q", "pkg.q.z", "pkg.q.v"}
    assert imported_names("from .. import k\n", "pkg.sub", is_package=True) == {"pkg", "pkg.k"}
    assert imported_names("from .events import *\n", "asyncio", is_package=True) == {
        "asyncio", "asyncio.events"}
