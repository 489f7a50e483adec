"""The ``runtime`` blueprint: what the browser runs (our modules, Pyodide, three.js, 3DHOP).

==============================  ===========================================
``/web/<file>``                 the viewer's modules and styles (``web/``)
``/vendor/pyodide/<file>``      npm ``pyodide`` (``loadPyodide``'s indexURL)
``/vendor/three/<file>``        npm ``three`` (ES modules, via an import map)
``/vendor/3dhop/<file>``        3DHOP from ``TESSERA_3DHOP_DIR`` (404 if unset)
``/vendor/pyodide-snapshot/``   Pyodide memory snapshot (:mod:`.snapshot`)
``/client_py/sources.json``     ``client_py``'s source files for the worker
==============================  ===========================================

Everything is served from this machine: the pages work offline, no CDN.
``client_py`` reaches the worker as one JSON document ``{"version",
"files": {name: source}}`` read once at start-up; the worker writes the files
into Pyodide's file system and imports the package (a few ms, no wheel to
unpack, nothing for the browser to cache wrongly: its ETag is the sources' hash).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from flask import Blueprint, Response, abort, current_app, request
from flask.typing import ResponseReturnValue

import client_py

from .files import send_from, send_path

bp = Blueprint("runtime", __name__)

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


@bp.get("/client_py/sources.json")
def client_py_sources_json() -> ResponseReturnValue:
    sources = current_app.extensions["tessera_client_py"]
    response = Response(json.dumps(sources), mimetype="application/json")
    response.set_etag(str(sources["sha256"]))
    response.cache_control.no_cache = True  # revalidate: cheap 304 while unchanged
    return response.make_conditional(request)


@bp.get("/web/<path:filename>")
def web_file(filename: str) -> ResponseReturnValue:
    if filename.startswith(("node_modules/", "templates/")) or filename.endswith(".json"):
        abort(404, description=f"no file {filename!r} here")
    response = send_from(Path(current_app.config["TESSERA_WEB_DIR"]), filename, max_age=0)
    response.cache_control.no_cache = True  # our own modules change with the server
    return response


@bp.get("/vendor/pyodide/", defaults={"filename": ""})
@bp.get("/vendor/pyodide/<path:filename>")
def pyodide_file(filename: str) -> ResponseReturnValue:
    if not filename:
        abort(404, description="name a file of the Pyodide runtime")
    return send_from(Path(current_app.config["TESSERA_PYODIDE_DIR"]), filename,
                     current_app.config["TESSERA_RUNTIME_MAX_AGE"])


@bp.get("/vendor/pyodide-snapshot/<key>.bin")
def pyodide_snapshot(key: str) -> ResponseReturnValue:
    builder = current_app.extensions.get("tessera_snapshot")
    if builder is None or key != builder.key or builder.ensure() is None:
        abort(404, description="no Pyodide snapshot here")
    return send_path(builder.path, current_app.config["TESSERA_BUNDLE_MAX_AGE"], immutable=True)


@bp.get("/vendor/three/", defaults={"filename": ""})
@bp.get("/vendor/three/<path:filename>")
def three_file(filename: str) -> ResponseReturnValue:
    if not filename.startswith(THREE_PUBLIC):
        abort(404, description=f"no file {filename!r} here")
    return send_from(Path(current_app.config["TESSERA_THREE_DIR"]), filename,
                     current_app.config["TESSERA_RUNTIME_MAX_AGE"])


@bp.get("/vendor/3dhop/", defaults={"filename": ""})
@bp.get("/vendor/3dhop/<path:filename>")
def hop_file(filename: str) -> ResponseReturnValue:
    directory = current_app.config.get("TESSERA_3DHOP_DIR")
    if not directory:
        abort(404, description="3DHOP is not configured: set TESSERA_3DHOP_DIR")
    if not filename:
        abort(404, description="name a file of 3DHOP")
    return send_from(Path(directory), filename, current_app.config["TESSERA_RUNTIME_MAX_AGE"])
