"""The ``runtime`` blueprint: what the browser runs (our modules, Pyodide, three.js, 3DHOP).

==========================================  ===============================================
``/web/v/<digest>/<file>``                  the viewer's modules and styles (``web/``)
``/vendor/pyodide/v/<version>/<file>``      npm ``pyodide`` (``loadPyodide``'s indexURL)
``/vendor/pyodide-stdlib/<key>.zip``        its ``python_stdlib.zip`` trimmed (:mod:`.stdlib`)
``/vendor/three/v/<version>/<file>``        npm ``three`` (ES modules, via an import map)
``/vendor/3dhop/<file>``                    3DHOP from ``TESSERA_3DHOP_DIR`` (404 if unset)
``/vendor/pyodide-snapshot/<key>.bin``      Pyodide memory snapshot (:mod:`.snapshot`)
``/client_py/<sha256>/sources.json``        ``client_py``'s source files for the worker
==========================================  ===============================================

Everything is served from this machine: the pages work offline, no CDN. The pages get every
URL from ``url_for``, which puts a version in it (:func:`add_versions`): the package's
version for Pyodide and three.js, a digest of the served files' names, sizes and times for
``web/``, the sources' SHA-256 for ``client_py``, a content key for the stdlib and the
snapshot. Such a URL names one version of a file forever and is sent ``immutable`` for a
year (``TESSERA_BUNDLE_MAX_AGE``): a repeat visit takes it from the browser's cache without
asking. The same files without a version in their URL (``/web/<file>``,
``/vendor/pyodide/<file>``, ``/client_py/sources.json``, ...) are still served, revalidated
(ETag) or kept ``TESSERA_RUNTIME_MAX_AGE``; so is a URL with a version that is no longer
the current one (its file changed: never cached as if it had not). Every compressible file
goes gzip or brotli (:mod:`.files`).

``client_py`` reaches the worker as one JSON document ``{"version", "sha256", "files":
{name: source}}``; the worker writes the files into Pyodide's file system and imports the
package (a few ms, no wheel to unpack).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
from pathlib import Path
from typing import Any

from flask import Blueprint, Response, abort, current_app, g, request, url_for
from flask.typing import ResponseReturnValue

import client_py

from .files import send_from, send_path
from .stdlib import TrimmedStdlib

bp = Blueprint("runtime", __name__)
log = logging.getLogger(__name__)


@bp.record_once
def _make_stdlib(setup: Any) -> None:
    app = setup.app
    stdlib = app.extensions["tessera_stdlib"] = TrimmedStdlib(
        Path(app.config["TESSERA_PYODIDE_DIR"]), app.extensions["tessera_client_py"],
        Path(app.config["TESSERA_CACHE_DIR"]))
    stdlib.start_background_build()

# Runtime subtrees a page may load; everything else in node_modules stays private. A wheel
# carries only the modules the viewer imports from them (build_web.WEB_FILES).
THREE_PUBLIC = ("build/", "examples/jsm/")


def client_py_sources() -> dict[str, object]:
    """``{"version", "sha256", "files"}``: every ``.py`` file of the ``client_py`` package."""
    root = Path(client_py.__file__).resolve().parent
    files = {p.relative_to(root).as_posix(): p.read_text(encoding="utf-8")
             for p in sorted(root.rglob("*.py")) if "__pycache__" not in p.parts}
    digest = hashlib.sha256(json.dumps(files, sort_keys=True).encode()).hexdigest()
    return {"package": "client_py", "version": client_py.__version__, "sha256": digest,
            "files": files}


def package_version(directory: Path) -> str:
    """The ``version`` of the npm package in ``directory`` (``"unknown"`` without one)."""
    try:
        return str(json.loads((Path(directory) / "package.json").read_text())["version"])
    except (OSError, ValueError, KeyError):
        return "unknown"


def web_version(web_dir: Path) -> str:
    """Digest of the served ``web/src`` files' names, sizes and modification times.

    Read again for every request that builds a URL (about 40 ``stat`` calls): an edited
    module gets a new URL at once, so a browser never keeps an old one under a new page.
    """
    digest = hashlib.sha256()
    for path in sorted((Path(web_dir) / "src").rglob("*")):
        if path.is_file():
            stat = path.stat()
            digest.update(f"{path.name}\0{stat.st_size}\0{stat.st_mtime_ns}\0".encode())
    return digest.hexdigest()[:16]


def current_versions() -> dict[str, str]:
    """This request's versions of the runtime trees: ``{"web", "pyodide", "three"}``."""
    versions = g.get("tessera_versions")
    if versions is None:
        fixed = current_app.extensions.get("tessera_runtime_versions")
        if fixed is None:  # the npm packages change only with a new server
            fixed = current_app.extensions["tessera_runtime_versions"] = {
                "pyodide": package_version(current_app.config["TESSERA_PYODIDE_DIR"]),
                "three": package_version(current_app.config["TESSERA_THREE_DIR"])}
        versions = g.tessera_versions = {
            **fixed, "web": web_version(current_app.config["TESSERA_WEB_DIR"])}
    return versions


VERSIONED = {"runtime.web_file": "web", "runtime.pyodide_file": "pyodide",
             "runtime.three_file": "three"}


@bp.app_url_defaults
def add_versions(endpoint: str, values: dict) -> None:
    """Put the current version into every URL of a versioned runtime tree."""
    tree = VERSIONED.get(endpoint)
    if tree is not None and "version" not in values:
        values["version"] = current_versions()[tree]


def _send_versioned(directory: Path, filename: str, version: str | None, tree: str,
                    max_age: int) -> Response:
    """``filename`` from ``directory``: immutable for a year under the current version,
    else with ``max_age`` (0: revalidated)."""
    if version is not None and version == current_versions()[tree]:
        return send_from(directory, filename, current_app.config["TESSERA_BUNDLE_MAX_AGE"],
                         immutable=True)
    return send_from(directory, filename, max_age)


def client_py_sources_file() -> Path | None:
    """The sources document as a file in the cache folder (written once per digest), so
    that it is compressed and sent like any other file; None when the cache folder cannot
    be written (logged; the document is then sent from memory, uncompressed)."""
    sources = current_app.extensions["tessera_client_py"]
    path = Path(current_app.config["TESSERA_CACHE_DIR"]) / f"client_py-{sources['sha256']}.json"
    if not path.is_file():
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp.write_text(json.dumps(sources))
            tmp.replace(path)
        except OSError as exc:
            log.warning("cannot write client_py's sources in %s: %s", path.parent, exc)
            with contextlib.suppress(OSError):  # no folder, no temporary file
                tmp.unlink()
            return None
    return path


def _send_sources(max_age: int, immutable: bool) -> Response:
    path = client_py_sources_file()
    if path is not None:
        return send_path(path, max_age, immutable=immutable)
    sources = current_app.extensions["tessera_client_py"]
    response = Response(json.dumps(sources), mimetype="application/json")
    response.set_etag(str(sources["sha256"]))
    response.cache_control.public = True
    response.cache_control.max_age = max_age
    response.cache_control.no_cache = max_age == 0 or None
    response.cache_control.immutable = immutable or None
    return response.make_conditional(request)


@bp.get("/client_py/sources.json")
def client_py_sources_json() -> ResponseReturnValue:
    return _send_sources(0, immutable=False)  # revalidate: a 304 while unchanged


@bp.get("/client_py/<sha256>/sources.json")
def client_py_sources_versioned(sha256: str) -> ResponseReturnValue:
    if sha256 != current_app.extensions["tessera_client_py"]["sha256"]:
        abort(404, description="no such version of client_py here")
    return _send_sources(current_app.config["TESSERA_BUNDLE_MAX_AGE"], immutable=True)


@bp.get("/web/<path:filename>")
@bp.get("/web/v/<version>/<path:filename>")
def web_file(filename: str, version: str | None = None) -> ResponseReturnValue:
    if filename.startswith(("node_modules/", "templates/")) or filename.endswith(".json"):
        abort(404, description=f"no file {filename!r} here")
    return _send_versioned(Path(current_app.config["TESSERA_WEB_DIR"]), filename, version,
                           "web", max_age=0)  # our own modules change with the server


@bp.get("/vendor/pyodide/", defaults={"filename": ""})
@bp.get("/vendor/pyodide/<path:filename>")
@bp.get("/vendor/pyodide/v/<version>/", defaults={"filename": ""})
@bp.get("/vendor/pyodide/v/<version>/<path:filename>")
def pyodide_file(filename: str, version: str | None = None) -> ResponseReturnValue:
    if not filename:
        abort(404, description="name a file of the Pyodide runtime")
    return _send_versioned(Path(current_app.config["TESSERA_PYODIDE_DIR"]), filename, version,
                           "pyodide", current_app.config["TESSERA_RUNTIME_MAX_AGE"])


@bp.get("/vendor/pyodide-stdlib/<key>.zip")
def pyodide_stdlib(key: str) -> ResponseReturnValue:
    stdlib = current_app.extensions["tessera_stdlib"]
    if key != stdlib.key:
        abort(404, description="no such version of the standard library here")
    return send_path(stdlib.ensure(), current_app.config["TESSERA_BUNDLE_MAX_AGE"],
                     immutable=True, compress=True)  # stored members: brotli/gzip of the whole


@bp.get("/vendor/pyodide-snapshot/<key>.bin")
def pyodide_snapshot(key: str) -> ResponseReturnValue:
    builder = current_app.extensions.get("tessera_snapshot")
    if builder is None or key != builder.key or builder.ensure() is None:
        abort(404, description="no Pyodide snapshot here")
    return send_path(builder.path, current_app.config["TESSERA_BUNDLE_MAX_AGE"], immutable=True)


@bp.get("/vendor/three/", defaults={"filename": ""})
@bp.get("/vendor/three/<path:filename>")
@bp.get("/vendor/three/v/<version>/", defaults={"filename": ""})
@bp.get("/vendor/three/v/<version>/<path:filename>")
def three_file(filename: str, version: str | None = None) -> ResponseReturnValue:
    if not filename.startswith(THREE_PUBLIC):
        abort(404, description=f"no file {filename!r} here")
    return _send_versioned(Path(current_app.config["TESSERA_THREE_DIR"]), filename, version,
                           "three", current_app.config["TESSERA_RUNTIME_MAX_AGE"])


@bp.get("/vendor/3dhop/", defaults={"filename": ""})
@bp.get("/vendor/3dhop/<path:filename>")
def hop_file(filename: str) -> ResponseReturnValue:
    directory = current_app.config.get("TESSERA_3DHOP_DIR")
    if not directory:
        abort(404, description="3DHOP is not configured: set TESSERA_3DHOP_DIR")
    if not filename:
        abort(404, description="name a file of 3DHOP")
    return send_from(Path(directory), filename, current_app.config["TESSERA_RUNTIME_MAX_AGE"])


def runtime_config() -> dict[str, Any]:
    """The worker's runtime URLs and facts for a page's config block.

    ``client_py_url`` (immutable, by the sources' digest), ``pyodide_stdlib_url`` (the
    trimmed standard library), ``pyodide_lock`` (the lock file's ``info`` with no packages:
    the worker loads none, so the 119 KB ``pyodide-lock.json`` is not fetched) and
    ``runtime_bytes``: ``{name: bytes}`` of what the worker fetches, uncompressed, for the
    loading percentage.
    """
    sources = current_app.extensions["tessera_client_py"]
    stdlib = current_app.extensions["tessera_stdlib"]
    pyodide_dir = Path(current_app.config["TESSERA_PYODIDE_DIR"])
    lock = current_app.extensions.get("tessera_pyodide_lock")
    if lock is None:
        try:
            info = json.loads((pyodide_dir / "pyodide-lock.json").read_text())["info"]
        except (OSError, ValueError, KeyError):
            info = None  # the worker then lets Pyodide fetch the lock file itself
        lock = current_app.extensions["tessera_pyodide_lock"] = (
            {"info": info, "packages": {}} if info else None)
    sizes = {}
    for name in ("pyodide.asm.wasm", "pyodide.asm.mjs", "pyodide.mjs"):
        try:
            sizes[name] = (pyodide_dir / name).stat().st_size
        except OSError:
            pass
    sizes["python_stdlib.zip"] = stdlib.ensure().stat().st_size
    sources_file = client_py_sources_file()
    if sources_file is not None:
        sizes["sources.json"] = sources_file.stat().st_size
    builder = current_app.extensions.get("tessera_snapshot")
    if builder is not None and builder.ready():
        sizes["snapshot"] = builder.path.stat().st_size
    return {
        "client_py_url": url_for("runtime.client_py_sources_versioned",
                                 sha256=sources["sha256"]),
        "pyodide_stdlib_url": url_for("runtime.pyodide_stdlib", key=stdlib.key),
        "pyodide_lock": lock,
        "runtime_bytes": sizes,
    }
