"""The server from an installed wheel: no checkout beside it, the viewer and runtime inside it.

The wheel is built from a copy of this checkout (``pip wheel --no-build-isolation``),
installed into a fresh ``python -m venv`` whose only link to this environment is a plain
path entry for the dependencies (it runs no ``.pth`` there, so the editable install's
finder never points it back at the checkout). The installed ``tessera`` command fits a
small bundle, a subprocess of the fresh venv serves it, and everything the viewer page
loads is fetched: the modules it references and those they import, followed through the
import map, Pyodide's files, the ``client_py`` sources and the Pyodide snapshot, made there
by node and kept in the Flask instance folder.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import sysconfig
import urllib.error
import urllib.request
from pathlib import Path
from urllib.parse import urljoin, urlsplit

import pytest

ROOT = Path(__file__).resolve().parent.parent
NODE_MODULES = ROOT / "web" / "node_modules"

pytestmark = pytest.mark.skipif(
    not (NODE_MODULES / "pyodide").is_dir() or not (NODE_MODULES / "three").is_dir(),
    reason="web/node_modules is missing (run `npm ci` in web/): a wheel carries its runtime")

#: what a build reads from the checkout (web/ is copied apart: its node_modules is linked)
BUILD_INPUTS = ("pyproject.toml", "README.md", "MANIFEST.in", "build_web.py", "client_py",
                "fitter")

#: the files loadPyodide fetches from its indexURL (Pyodide's package.json "exports")
PYODIDE_FETCHED = ("pyodide.mjs", "pyodide.asm.mjs", "pyodide.asm.wasm", "python_stdlib.zip",
                   "pyodide-lock.json")

#: module specifiers of ES imports: ``import ... from "x"``, ``export ... from "x"``,
#: ``import "x"`` and ``import("x")`` with a string literal
JS_IMPORT = re.compile(r"""(?:\bfrom\s*|\bimport\s*\(?\s*)["']([^"'\s]+)["']""")

SERVER_SCRIPT = r"""
import json, sys
from werkzeug.serving import make_server
from fitter.server import create_app

app = create_app({"TESSERA_COLLECTION": sys.argv[1],
                  "TESSERA_PYODIDE_SNAPSHOT": sys.argv[2] == "snapshot"})
builder = app.extensions["tessera_snapshot"]
if builder is not None:
    builder.ensure()  # node makes it from the wheel's Pyodide and script (a few seconds)
server = make_server("127.0.0.1", 0, app, threaded=True)
print(json.dumps({"port": server.server_port, "instance_path": app.instance_path,
                  "cache_dir": app.config["TESSERA_CACHE_DIR"],
                  "snapshot": str(builder.path) if builder and builder.ready() else None,
                  "snapshot_failure": builder and builder.failure}), flush=True)
server.serve_forever()
"""

WHERE_SCRIPT = r"""
import json
import client_py, fitter, fitter.server
print(json.dumps({"fitter": fitter.__file__, "client_py": client_py.__file__,
                  "web_root": str(fitter.server.WEB_ROOT),
                  "checkout": fitter.server.SOURCE_CHECKOUT and str(fitter.server.SOURCE_CHECKOUT),
                  "hop_default": fitter.server.DEFAULTS["TESSERA_3DHOP_DIR"][0]}))
"""

PURELIB_SCRIPT = "import sysconfig; print(sysconfig.get_path('purelib'))"

WRITE_SCAN = r"""
import sys
from client_py.ply import write_points_ply
from fitter.fitting.examples import relief_scan
open(sys.argv[1], "wb").write(write_points_ply(relief_scan(6_000), comments=["units mm"]))
"""


def _copy_source(destination: Path) -> Path:
    """The checkout's build inputs and web/, with web/node_modules linked, not copied."""
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "node_modules")
    destination.mkdir()
    for name in BUILD_INPUTS:
        source = ROOT / name
        if source.is_dir():
            shutil.copytree(source, destination / name, ignore=ignore)
        else:
            shutil.copy2(source, destination / name)
    shutil.copytree(ROOT / "web", destination / "web", ignore=ignore)
    (destination / "web" / "node_modules").symlink_to(NODE_MODULES, target_is_directory=True)
    return destination


def _run(args: list[str], cwd: Path, timeout: float = 120) -> str:
    done = subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, f"{args[:3]} failed:\n{done.stdout[-2000:]}\n{done.stderr[-4000:]}"
    return done.stdout


@pytest.fixture(scope="module")
def wheel_venv(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """``{"python", "tessera", "source", "work"}`` of a fresh venv with the wheel installed."""
    root = tmp_path_factory.mktemp("wheel")
    source = _copy_source(root / "source")
    dist = root / "dist"
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
          "--no-index", "-q", "-w", str(dist), str(source)], cwd=source)
    (wheel,) = dist.glob("tessera-*.whl")
    venv = root / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", str(venv)], cwd=root)
    python = venv / "bin" / "python"
    # pip of this environment installs into the fresh one, before the dependency path exists
    # there: it must not see this environment's (editable) tessera as already installed
    _run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps",
          "--no-index", "-q", str(wheel)], cwd=root)
    purelib = Path(_run([str(python), "-c", PURELIB_SCRIPT], cwd=root).strip())
    (purelib / "tessera-test-dependencies.pth").write_text(sysconfig.get_path("purelib") + "\n")
    work = root / "work"
    work.mkdir()
    return {"python": python, "tessera": venv / "bin" / "tessera", "source": source,
            "venv": venv, "work": work}


def test_the_wheel_runs_from_its_own_venv(wheel_venv):
    where = json.loads(_run([str(wheel_venv["python"]), "-c", WHERE_SCRIPT],
                            cwd=wheel_venv["work"]))
    venv = wheel_venv["venv"].resolve()
    for name in ("fitter", "client_py", "web_root"):
        assert Path(where[name]).resolve().is_relative_to(venv), (name, where[name])
    assert where["checkout"] is None
    assert where["hop_default"] == ""  # 3DHOP is never guessed beside an installed package


def _get(url: str) -> tuple[int, dict[str, str], bytes]:
    try:
        with urllib.request.urlopen(url, timeout=30) as response:
            return response.status, dict(response.headers), response.read()
    except urllib.error.HTTPError as error:
        return error.code, dict(error.headers), error.read()


def _module_urls(url: str, text: str, import_map: dict[str, str]) -> list[str]:
    """The URLs that the ES module at ``url`` imports, bare specifiers through the import map."""
    urls = []
    for specifier in JS_IMPORT.findall(text):
        if specifier.startswith(("./", "../", "/")):
            urls.append(urljoin(url, specifier))
            continue
        prefixes = [key for key in import_map if specifier == key or
                    (key.endswith("/") and specifier.startswith(key))]
        assert prefixes, f"{url} imports {specifier!r}, which the import map does not name"
        key = max(prefixes, key=len)
        urls.append(urljoin(url, import_map[key] + specifier[len(key):]))
    return urls


def _config(html: str) -> dict:
    return json.loads(html.split('id="tessera-config">', 1)[1].split("</script>", 1)[0])


def test_an_installed_wheel_serves_the_viewer_and_its_runtime(wheel_venv):
    work, python = wheel_venv["work"], str(wheel_venv["python"])
    scan = work / "relief.ply"
    _run([python, "-c", WRITE_SCAN, str(scan)], cwd=work)
    collection = work / "collection"
    _run([str(wheel_venv["tessera"]), "fit", str(scan), "-o", str(collection / "relief"),
          "--grid", "8x8", "--samples", "2000", "--detail-levels", "1", "--detail-spans", "4",
          "--no-texture", "--title", "Relief from the wheel", "-q"], cwd=work)

    mode = "snapshot" if shutil.which("node") else "plain"
    server = subprocess.Popen([python, "-c", SERVER_SCRIPT, str(collection), mode], cwd=work,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = server.stdout.readline()
        assert line, f"the server did not start:\n{server.stderr.read()[-4000:]}"
        started = json.loads(line)
        base = f"http://127.0.0.1:{started['port']}"

        # the snapshot cache is the instance folder's, inside the fresh venv
        instance = Path(started["instance_path"]).resolve()
        assert instance.is_relative_to(wheel_venv["venv"].resolve())
        assert Path(started["cache_dir"]).resolve() == instance / "cache"
        if mode == "snapshot":
            assert started["snapshot"], started["snapshot_failure"]
            assert Path(started["snapshot"]).resolve().parent == instance / "cache"

        status, _, body = _get(f"{base}/")
        assert status == 200
        assert b"Relief from the wheel" in body and b"/objects/relief/" in body
        status, _, body = _get(f"{base}/objects/relief/")
        assert status == 200
        page = body.decode()
        config = _config(page)
        import_map = json.loads(re.search(r'<script[^>]*type="importmap"[^>]*>(.*?)</script>', page,
                                          re.S)[1])["imports"]

        # every module the page references, and all they import, through the import map
        pending = [urljoin(f"{base}/objects/relief/", src) for src in
                   re.findall(r'<script type="module" src="([^"]+)"', page)]
        pending.append(urljoin(base, config["worker_url"]))
        assert any(re.sub(r"/v/[^/]+/", "/", url).endswith("/web/src/viewer-page.js")
                   for url in pending)
        seen: set[str] = set()
        while pending:
            url = pending.pop()
            if url in seen:
                continue
            seen.add(url)
            status, headers, body = _get(url)
            assert status == 200, url
            assert headers["Content-Type"].startswith("text/javascript"), url
            pending += _module_urls(url, body.decode(), import_map)
        # the paths without their version segment (/web/v/<digest>/, /vendor/three/v/<version>/)
        paths = {re.sub(r"/v/[^/]+/", "/", urlsplit(url).path) for url in seen}
        assert {"/web/src/viewer-page.js", "/web/src/viewer.js", "/web/src/mesh-worker.js",
                "/vendor/three/build/three.module.js",
                "/vendor/three/examples/jsm/controls/OrbitControls.js"} <= paths
        stylesheets = re.findall(r'<link rel="stylesheet" href="([^"]+)"', page)
        assert stylesheets
        for href in stylesheets:
            assert _get(urljoin(f"{base}/objects/relief/", href))[0] == 200, href

        for name in PYODIDE_FETCHED:
            status, headers, _ = _get(f"{base}{config['pyodide_url']}{name}")
            assert status == 200, name
            if name.endswith(".wasm"):
                assert headers["Content-Type"] == "application/wasm"

        status, _, body = _get(f"{base}{config['client_py_url']}")
        assert status == 200
        shipped = {p.relative_to(wheel_venv["source"] / "client_py").as_posix()
                   for p in (wheel_venv["source"] / "client_py").rglob("*.py")}
        assert set(json.loads(body)["files"]) == shipped

        status, _, body = _get(f"{base}{config['patch_url']}")
        assert status == 200
        assert body == (collection / "relief" / "base.tsp").read_bytes()
        if mode == "snapshot":
            assert config["pyodide_snapshot_url"], "the page should start Pyodide from it"
            status, _, body = _get(f"{base}{config['pyodide_snapshot_url']}")
            assert status == 200
            assert body == Path(started["snapshot"]).read_bytes()
        assert _get(f"{base}/objects/relief/3dhop")[0] == 404  # no 3DHOP in a wheel
    finally:
        server.terminate()
        server.wait(timeout=10)
        server.stdout.close()
        server.stderr.close()
