"""The ``api`` blueprint: the collection as JSON for other sites and scripts.

``GET /api/objects`` returns a list of ``{"id", "title", "viewer_url",
"bundle_url", "bytes", "stats", ...}``; ``GET /api/objects/<id>`` one of them.
URLs are relative to the server root (they start with ``/``, or with the
application's mount point when it is mounted under a prefix).

Only readable bundles are listed (what "readable" means is
:func:`fitter.collection.bundles.parse_manifest`, the one check every route shares); a
broken one is left out and logged, and its own URLs answer 404 with the reason. Sizes and
``files`` count the bundle's regular files only (symbolic links are never followed).
"""

from __future__ import annotations

from typing import Any

from flask import Blueprint, abort, current_app, jsonify, url_for
from flask.typing import ResponseReturnValue

from client_py.bundle import PIECES_FILE

from ..collection.bundles import Bundle, BundleError, served_manifest

bp = Blueprint("api", __name__, url_prefix="/api")


def scan_size(provenance: dict[str, Any]) -> dict[str, Any]:
    """What the scan behind a bundle weighs: ``{"bytes", "points", "files"}``.

    ``bytes`` is the sum over every file the fit read (``provenance.files``: a ``.conf``
    registration and each of its range scans, an OBJ and its material and texture), else
    ``provenance.bytes`` (one file, or a bundle written before ``files``; a ``.conf``'s own
    ``bytes`` are its text alone); ``points`` is ``provenance.points``; either None when
    the manifest does not say.
    """
    files = provenance.get("files")
    sizes = ([f.get("bytes") for f in files if isinstance(f, dict)]
             if isinstance(files, list) else [])
    counted = [b for b in sizes if isinstance(b, int) and not isinstance(b, bool) and b >= 0]
    total = sum(counted) if counted else provenance.get("bytes")
    return {"bytes": total, "points": provenance.get("points"),
            "files": len(counted) if counted else (1 if total is not None else None)}


def object_summary(bundle: Bundle) -> dict[str, Any]:
    """The public description of one object (used by the API and the gallery)."""
    sizes = bundle.file_sizes()
    base = bundle.base
    return {
        "id": bundle.id,
        "title": bundle.title,
        "description": str(bundle.manifest.get("description") or ""),
        "viewer_url": url_for("objects.viewer", object_id=bundle.id),
        "hop_url": url_for("objects.hop", object_id=bundle.id),
        "thumbnail_url": url_for("objects.thumbnail", object_id=bundle.id),
        "bundle_url": url_for("bundles.bundle_file", object_id=bundle.id, filename=""),
        "manifest_url": url_for("bundles.bundle_file", object_id=bundle.id,
                                filename="manifest.json"),
        "bytes": sum(sizes.values()),
        "base_bytes": sizes.get(bundle.base_file, 0),
        # what a visitor's viewer downloads: the manifest as served, the base and a patch's
        # pieces
        "view_bytes": len(served_manifest(bundle.manifest)) + sizes.get(bundle.base_file, 0)
        + sizes.get(PIECES_FILE, 0),
        "files": sizes,
        "units": bundle.units,
        "grid": base.get("grid"),
        "patches": base.get("patches"),  # an atlas (format_version 2): its patch count
        "degree": base.get("degree"),
        "stats": bundle.stats,
        "provenance": bundle.provenance,
        "scan": scan_size(bundle.provenance),
    }


def get_bundle_or_404(object_id: str) -> Bundle:
    """The collection's bundle ``object_id``, or a 404 saying why there is none."""
    try:
        return current_app.extensions["tessera_collection"].get(object_id)
    except KeyError:
        abort(404, description=f"no object {object_id!r} in this collection")
    except BundleError as exc:
        abort(404, description=f"object {object_id!r} is not a readable bundle: {exc}")


@bp.get("/objects")
def list_objects() -> ResponseReturnValue:
    collection = current_app.extensions["tessera_collection"]
    return jsonify([object_summary(b) for b in collection.bundles()])


@bp.get("/objects/<object_id>")
def get_object(object_id: str) -> ResponseReturnValue:
    return jsonify(object_summary(get_bundle_or_404(object_id)))
