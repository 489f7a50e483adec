"""The ``objects`` blueprint: the pages a museum visitor opens for one object.

``/objects/<id>/`` is the three.js viewer (the mesh is tessellated in the
visitor's browser by ``client_py`` under Pyodide, in a Web Worker);
``/objects/<id>/3dhop`` shows the same client-made mesh in 3DHOP;
``/objects/<id>/thumbnail.png`` is a small server-side rendering for the gallery, cached
per version of the base file and of the view (failures too: a bad patch is a quick 404
after the first try; see :mod:`fitter.server.thumbnail`).

Every URL the pages need is computed here and handed to them in a JSON block:
the front end never builds or hard-codes a URL.
"""

from __future__ import annotations

import hashlib
import json
from typing import Any

from flask import Blueprint, Response, abort, current_app, render_template, request, url_for
from flask.typing import ResponseReturnValue

from client_py.tessellate import MAX_GRID

from ..collection.bundles import Bundle
from .api import get_bundle_or_404, object_summary
from .runtime import runtime_config
from .thumbnail import ThumbnailCache, thumbnail_of

bp = Blueprint("objects", __name__, url_prefix="/objects")


@bp.record_once
def _make_thumbnail_cache(setup: Any) -> None:
    setup.app.extensions["tessera_thumbnails"] = ThumbnailCache()

MAX_PAGE_RESOLUTION = 1024  # a visitor's browser: 1 M vertices is plenty


def _resolution() -> int:
    """``?resolution=N`` (a fixed grid) or the configured default; a bad value is a 400."""
    text = request.args.get("resolution")
    if text is None:
        return int(current_app.config["TESSERA_RESOLUTION"])
    try:
        value = int(text)
    except ValueError:
        abort(400, description=f"resolution must be an integer, got {text!r}")
    if not 2 <= value <= min(MAX_PAGE_RESOLUTION, MAX_GRID):
        abort(400, description=f"resolution must be 2 to {MAX_PAGE_RESOLUTION}, got {value}")
    return value


def _hop_base() -> str | None:
    """Base URL of 3DHOP's ``minimal/`` folder (ending in ``/``), or None when not configured."""
    if current_app.config.get("TESSERA_3DHOP_DIR"):
        return url_for("runtime.hop_file", filename="")
    url = str(current_app.config.get("TESSERA_3DHOP_URL") or "")
    if url:
        return url if url.endswith("/") else url + "/"
    return None


def _snapshot_url() -> str | None:
    """URL of the Pyodide snapshot when it is built; otherwise start building it for later."""
    builder = current_app.extensions.get("tessera_snapshot")
    if builder is None:
        return None
    if builder.ready():
        return url_for("runtime.pyodide_snapshot", key=builder.key)
    if builder.failure is None:
        builder.start_background_build()  # this page loads Pyodide plainly; later ones won't
    return None


def page_config(bundle: Bundle) -> dict[str, Any]:
    """Everything the viewer and 3DHOP pages need, as JSON-ready data."""
    summary = object_summary(bundle)
    return {
        "id": bundle.id,
        "title": bundle.title,
        "manifest_url": summary["manifest_url"],
        "patch_url": url_for("bundles.bundle_file", object_id=bundle.id,
                             filename=bundle.base_file),
        "pyodide_url": url_for("runtime.pyodide_file", filename=""),
        "pyodide_snapshot_url": _snapshot_url(),
        **runtime_config(),
        "worker_url": url_for("runtime.web_file", filename="src/mesh-worker.js"),
        "viewer_url": summary["viewer_url"],
        "hop_url": summary["hop_url"] if _hop_base() else None,
        "gallery_url": url_for("gallery.index"),
        "resolution": _resolution(),
        "pyodide_timeout_s": float(current_app.config["TESSERA_PYODIDE_TIMEOUT"]),
        "ply_name": f"{bundle.id}.ply",
        "bytes": summary["bytes"],
        "view_bytes": summary["view_bytes"],
        "base_bytes": summary["base_bytes"],
    }


def _import_map() -> dict[str, Any]:
    three = url_for("runtime.three_file", filename="")
    return {"imports": {"three": f"{three}build/three.module.js",
                        "three/addons/": f"{three}examples/jsm/"}}


@bp.get("/<object_id>/")
def viewer(object_id: str) -> ResponseReturnValue:
    bundle = get_bundle_or_404(object_id)
    return render_template("viewer.html", config=page_config(bundle), import_map=_import_map(),
                           summary=object_summary(bundle))


@bp.get("/<object_id>/3dhop")
def hop(object_id: str) -> ResponseReturnValue:
    bundle = get_bundle_or_404(object_id)
    hop_base = _hop_base()
    if hop_base is None:
        abort(404, description="3DHOP is not configured on this server: set TESSERA_3DHOP_DIR "
                               "(a local copy of 3DHOP's minimal/ folder) or TESSERA_3DHOP_URL")
    return render_template("hop.html", config=page_config(bundle), hop_base=hop_base,
                           summary=object_summary(bundle))


@bp.get("/<object_id>/thumbnail.png")
def thumbnail(object_id: str) -> ResponseReturnValue:
    bundle = get_bundle_or_404(object_id)
    name = bundle.base_file  # a name inside the bundle (parse_manifest checked it)
    try:
        stat = (bundle.path / name).stat()
    except OSError:
        abort(404, description=f"object {object_id!r} has no {name}")
    # the view is part of the version: the admin may turn the object after its fit
    view = hashlib.sha256(json.dumps(bundle.manifest.get("view"), sort_keys=True).encode())
    version = (str(bundle.path), name, stat.st_mtime_ns, stat.st_size, stat.st_ino,
               view.hexdigest())
    made = current_app.extensions["tessera_thumbnails"].get(version,
                                                            lambda: thumbnail_of(bundle))
    if made.png is None:
        abort(404, description=f"object {object_id!r} has no thumbnail: {made.error}")
    response = Response(made.png, mimetype="image/png")
    response.set_etag(f"{stat.st_mtime_ns:x}-{stat.st_size:x}-{view.hexdigest()[:12]}-thumb")
    response.cache_control.public = True
    response.cache_control.max_age = 3600
    return response.make_conditional(request)
