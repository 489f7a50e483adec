"""Tessera's Flask server: a collection of bundles, the browser viewer, its runtime, 3DHOP pages.

``create_app(config=None)`` builds the application (the Flask tutorial's app
factory pattern). Every setting has its default in :data:`DEFAULTS`, one
table; an environment variable of the same name overrides the default, and the
``config`` mapping given to :func:`create_app` overrides both. Each resource is
one blueprint:

=============  ==============================================================
``gallery``    ``/``: the collection as a page of cards (title, sizes, error)
``objects``    ``/objects/<id>/`` viewer, ``/objects/<id>/3dhop`` 3DHOP page,
               ``/objects/<id>/thumbnail.png``
``api``        ``/api/objects`` and ``/api/objects/<id>`` (JSON)
``bundles``    ``/bundles/<id>/<file>``: the immutable bundle files
``runtime``    ``/web/``, ``/vendor/pyodide/``, ``/vendor/three/``,
               ``/vendor/3dhop/``, ``/client_py/sources.json``
``admin``      ``/admin/``: uploads, fit jobs, catalog, publishing (off
               without an admin token; see :mod:`fitter.server.admin`)
=============  ==============================================================

Every response carries the security headers of :mod:`fitter.server.headers`. Errors are
answered in kind: JSON (``{"error": message}``) under ``/api/`` and ``/admin/api/``, a page
elsewhere — 400, 404 and 500 alike (a 500's traceback goes to the log, never to the client).

The public side does no fitting and writes nothing: a collection is a
directory of bundle directories (each the output of ``tessera fit``), read as
they are. The admin area writes only into the collection's ``.tessera/``
folder and, through its fit workers, new bundle directories. When the
collection has a catalog (``.tessera/catalog.sqlite``), the public side shows
only the objects published there; without one, every bundle is public.

The viewer's templates, modules and runtime (Pyodide, three.js) are read from
:data:`WEB_ROOT`: the checkout's ``web/`` (after ``npm ci`` there) when running
from a source tree or an editable install, else the copy an installed wheel
carries. What the server writes for itself (the Pyodide snapshot) goes to the
Flask instance folder unless ``TESSERA_CACHE_DIR`` says otherwise.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from flask import Flask, jsonify, render_template, request
from flask.typing import ResponseReturnValue
from werkzeug.exceptions import HTTPException

_PACKAGED_WEB = Path(__file__).resolve().parent / "web"

#: The source checkout this package runs from (an editable install, or the tree on
#: ``sys.path``); None when it is installed from a wheel, which carries its own copy of web/.
SOURCE_CHECKOUT: Path | None = (None if _PACKAGED_WEB.is_dir()
                                else Path(__file__).resolve().parents[2])

#: The viewer's files: the checkout's ``web/``, or in a wheel ``fitter/server/web/`` — the same
#: layout holding only what the server sends or runs (templates, ``src/``, the snapshot script,
#: the Pyodide, three.js and ws files; see ``build_web.py`` at the checkout's root).
WEB_ROOT = _PACKAGED_WEB if SOURCE_CHECKOUT is None else SOURCE_CHECKOUT / "web"


def _default_3dhop_dir() -> str:
    """``../shared/vendor/3dhop-4.3`` beside a source checkout when present; else none (GPL,
    used by path: a wheel never carries it, nor guesses where it might be)."""
    if SOURCE_CHECKOUT is None:
        return ""
    vendored = SOURCE_CHECKOUT.parent / "shared" / "vendor" / "3dhop-4.3"
    return str(vendored) if vendored.is_dir() else ""


#: Every setting, its default and what it means. The environment variable of
#: the same name overrides the default; ``create_app(config)`` overrides both.
DEFAULTS: dict[str, tuple[Any, str]] = {
    "TESSERA_COLLECTION": ("", "directory of bundle directories to serve (required)"),
    "TESSERA_WEB_DIR": (str(WEB_ROOT), "the viewer's static files and templates (web/)"),
    "TESSERA_PYODIDE_DIR": (str(WEB_ROOT / "node_modules" / "pyodide"),
                            "the npm pyodide package (loadPyodide's indexURL)"),
    "TESSERA_THREE_DIR": (str(WEB_ROOT / "node_modules" / "three"), "the npm three package"),
    "TESSERA_3DHOP_DIR": (_default_3dhop_dir(),
                          "a local copy of 3DHOP 4.3's minimal/ folder, served at /vendor/3dhop/ "
                          "(default: ../shared/vendor/3dhop-4.3 beside a source checkout)"),
    "TESSERA_3DHOP_URL": ("", "base URL of a 3DHOP installation elsewhere (instead of a dir)"),
    "TESSERA_PYODIDE_TIMEOUT": (45.0, "seconds the page waits for Pyodide before an error"),
    "TESSERA_PYODIDE_SNAPSHOT": (False, "start Pyodide from a memory snapshot made with node "
                                        "(about 2 s instead of 5-15; +4.6 MB brotli on a first "
                                        "visit, over its 6 MB budget: docs/benchmarks.md)"),
    "TESSERA_CACHE_DIR": ("", "where Pyodide snapshots are kept (empty: cache/ in the Flask "
                              "instance folder, app.instance_path)"),
    "TESSERA_NODE": ("", "the node executable for snapshots (default: node on PATH)"),
    "TESSERA_RESOLUTION": (0, "fixed tessellation grid per side; 0 follows the view"),
    "TESSERA_GZIP": (True, "gzip compressible responses when the client accepts it"),
    "TESSERA_BUNDLE_MAX_AGE": (365 * 24 * 3600, "Cache-Control max-age of bundle files (s)"),
    "TESSERA_RUNTIME_MAX_AGE": (24 * 3600, "Cache-Control max-age of Pyodide and three.js (s)"),
    # the admin area (fitter/server/admin, docs/admin.md); off without a token
    "TESSERA_ADMIN_TOKEN": ("", "the admin secret (else the hash from `tessera admin set-token`)"),
    "TESSERA_ADMIN_SECURE_COOKIE": (False, "send the admin session cookie over HTTPS only"),
    "TESSERA_UPLOAD_MAX_BYTES": (4 << 30, "largest upload accepted (bytes; 413 above)"),
    "TESSERA_UPLOAD_MAX_EXPANDED_BYTES": (16 << 30, "largest decompressed .gz / .zip (bytes)"),
    "TESSERA_UPLOAD_MAX_RATIO": (200.0, "largest decompressed/compressed ratio of an upload"),
    "TESSERA_UPLOAD_MAX_POINTS": (20_000_000, "most points an uploaded scan (a .conf: all its "
                                              "scans) may hold, counted before they are read"),
    "TESSERA_UPLOAD_MAX_FILES": (1000, "most scan files an uploaded .conf may name"),
    "TESSERA_UPLOAD_CHUNK_BYTES": (8 << 20, "bytes per request of the upload page's resumable "
                                            "upload (keep it under a proxy's body limit)"),
    "TESSERA_UPLOAD_EXPIRE_S": (24 * 3600, "seconds an unfinished resumable upload is kept "
                                           "after its last bytes; then it is deleted"),
    "TESSERA_JOB_WORKERS": (0, "fits run at once by `tessera serve` (0: one per core)"),
}


def _coerce(name: str, text: str, default: Any) -> Any:
    """An environment string converted to the type of the setting's default."""
    if isinstance(default, bool):
        if text.lower() in ("1", "true", "yes", "on"):
            return True
        if text.lower() in ("0", "false", "no", "off"):
            return False
        raise ValueError(f"environment variable {name}={text!r}: expected true/false")
    if isinstance(default, int | float):
        try:
            return type(default)(text)
        except ValueError:
            raise ValueError(
                f"environment variable {name}={text!r}: expected a {type(default).__name__}"
            ) from None
    return text


def load_settings(config: Mapping[str, Any] | None = None,
                  environ: Mapping[str, str] | None = None) -> dict[str, Any]:
    """Settings from :data:`DEFAULTS`, then ``environ`` (``os.environ``), then ``config``."""
    environ = os.environ if environ is None else environ
    settings = {}
    for name, (default, _) in DEFAULTS.items():
        value = default
        if name in environ:
            value = _coerce(name, environ[name], default)
        settings[name] = value
    settings.update(config or {})
    return settings


def create_app(config: Mapping[str, Any] | None = None) -> Flask:
    """The Tessera web application.

    Parameters
    ----------
    config : mapping, optional
        Settings overriding :data:`DEFAULTS` and the environment, plus any
        Flask setting (``TESTING`` ...).

    Raises
    ------
    ValueError
        When ``TESSERA_COLLECTION`` is unset or not a directory, or a runtime
        directory (web/, pyodide, three) is missing.
    """
    from ..collection.bundles import Collection
    from . import admin, api, bundles, gallery, headers, objects, runtime
    from .snapshot import SnapshotBuilder

    settings = load_settings(config)
    collection_dir = Path(str(settings["TESSERA_COLLECTION"]))
    if not str(settings["TESSERA_COLLECTION"]):
        raise ValueError("TESSERA_COLLECTION is not set: give the directory of bundles to serve")
    if not collection_dir.is_dir():
        raise ValueError(f"TESSERA_COLLECTION={collection_dir}: not a directory")
    for name in ("TESSERA_WEB_DIR", "TESSERA_PYODIDE_DIR", "TESSERA_THREE_DIR"):
        if not Path(settings[name]).is_dir():
            hint = " (run `npm ci` in web/)" if "node_modules" in str(settings[name]) else ""
            raise ValueError(f"{name}={settings[name]}: not a directory{hint}")

    web_dir = Path(settings["TESSERA_WEB_DIR"])
    app = Flask(__name__, template_folder=str(web_dir / "templates"), static_folder=None)
    app.config.update(settings)
    # the instance folder: writable wherever the package is installed (a wheel's own folder
    # may not be), and outside the checkout's tracked files
    cache_dir = Path(str(settings["TESSERA_CACHE_DIR"]) or Path(app.instance_path) / "cache")
    app.config["TESSERA_CACHE_DIR"] = str(cache_dir)
    app.extensions["tessera_collection"] = Collection(collection_dir)
    app.extensions["tessera_client_py"] = sources = runtime.client_py_sources()
    app.extensions["tessera_snapshot"] = None
    if settings["TESSERA_PYODIDE_SNAPSHOT"]:
        app.extensions["tessera_snapshot"] = SnapshotBuilder(
            Path(settings["TESSERA_PYODIDE_DIR"]), sources, cache_dir,
            node=settings["TESSERA_NODE"] or None)

    for module in (gallery, objects, api, bundles, runtime):
        app.register_blueprint(module.bp)
    # the admin area; on a managed collection (with a catalog) it also narrows the public
    # site to the published objects (a plain folder of bundles is served whole, as before)
    admin.init_app(app)
    headers.init_app(app)

    @app.errorhandler(404)
    def not_found(error: HTTPException) -> ResponseReturnValue:
        message = getattr(error, "description", "not found")
        if request.path.startswith(("/api/", "/admin/api/")):
            return jsonify({"error": message}), 404
        return render_template("404.html", message=message), 404

    @app.errorhandler(400)
    def bad_request(error: HTTPException) -> ResponseReturnValue:
        message = getattr(error, "description", "bad request")
        if request.path.startswith(("/api/", "/admin/api/")):
            return jsonify({"error": message}), 400
        return render_template("404.html", message=message, status=400), 400

    @app.errorhandler(500)
    def server_error(error: HTTPException) -> ResponseReturnValue:
        # Flask has logged the traceback (app.log_exception) before calling this
        message = ("the server failed to answer this request; the error is in its log "
                   "(please report it)")
        if request.path.startswith(("/api/", "/admin/api/")):
            return jsonify({"error": message}), 500
        return render_template("500.html", message=message), 500

    @app.errorhandler(HTTPException)
    def other_http_error(error: HTTPException) -> ResponseReturnValue:
        """Any other HTTP error (405, 413 ...): JSON under the APIs, werkzeug's page elsewhere."""
        if error.code is None or not request.path.startswith(("/api/", "/admin/api/")):
            return error
        response = jsonify({"error": error.description})
        response.status_code = error.code
        for name, value in error.get_headers():
            if name.lower() != "content-type":
                response.headers[name] = value  # e.g. a 405's Allow
        return response

    return app


__all__ = ["DEFAULTS", "SOURCE_CHECKOUT", "WEB_ROOT", "create_app", "load_settings"]
