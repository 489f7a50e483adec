"""The ``bundles`` blueprint: a bundle's files, immutable and cacheable.

``GET /bundles/<id>/<file>``: a fitted bundle never changes in place (a refit
writes a new bundle), so its files are served with a year-long
``Cache-Control: public, immutable``, an ETag, HTTP ranges and gzip where it
helps (see :mod:`fitter.server.files`). A name leading outside the bundle
directory is a 404.

``manifest.json`` is the visitor's manifest (``fitter.collection.bundles.served_manifest``):
the file without the fit's own records (its trials, timings and options, the file sizes),
which only the admin's pages and the command line read from the file itself; compact
JSON, in brotli or gzip as the client accepts, with an ETag of its bytes (no ranges: it is
a few KB). In a managed
collection the admin edits an object's title, description, units and first view after its
fit (``fitter.collection.catalog``), so there it is made from the manifest as the catalog
lays it over the file (:class:`~fitter.collection.catalog.CatalogBundle`) and revalidated on
every visit (``no-cache``: a 304 while nothing was edited). The viewer reads the title,
units and ``view`` from this manifest, so an edit reaches the next visit.
"""

from __future__ import annotations

import functools
import hashlib

from flask import Blueprint, Response, abort, current_app, request
from flask.typing import ResponseReturnValue

from ..collection.bundles import MANIFEST, Bundle, served_manifest
from ..collection.catalog import CatalogBundle
from .api import get_bundle_or_404
from .files import COMPRESS_MIN_BYTES, SUFFIXES, accepted_encodings, compress, send_from

bp = Blueprint("bundles", __name__, url_prefix="/bundles")


@bp.get("/<object_id>/", defaults={"filename": ""})
@bp.get("/<object_id>/<path:filename>")
def bundle_file(object_id: str, filename: str) -> ResponseReturnValue:
    bundle = get_bundle_or_404(object_id)
    if not filename:
        abort(404, description="name a file of the bundle, e.g. manifest.json")
    if filename == MANIFEST:
        return _visitor_manifest(bundle)
    return send_from(bundle.path, filename, current_app.config["TESSERA_BUNDLE_MAX_AGE"],
                     immutable=True)


@functools.lru_cache(maxsize=64)
def _encoded(data: bytes, encoding: str) -> bytes:
    """``files.compress`` of a served manifest, kept for the next visitors (brotli at quality
    11 takes about 30 ms for a 12 KB manifest)."""
    return compress(data, encoding)


def _visitor_manifest(bundle: Bundle) -> Response:
    """:func:`served_manifest` of ``bundle.manifest``, in brotli or gzip as the client
    accepts (the levels of :mod:`.files`): immutable as the bundle's other files, or
    revalidated each time where the admin edits it (module docstring)."""
    data = served_manifest(bundle.manifest)
    etag = hashlib.sha256(data).hexdigest()[:32]
    accepted = (accepted_encodings(request.headers.get("Accept-Encoding", ""))
                if current_app.config.get("TESSERA_GZIP", True)
                and len(data) >= COMPRESS_MIN_BYTES else set())
    encoding = next((e for e in ("br", "gzip") if e in accepted), None)
    response = Response(_encoded(data, encoding) if encoding else data,
                        mimetype="application/json")
    if encoding:
        response.headers["Content-Encoding"] = encoding
        etag += "-" + SUFFIXES[encoding]
    response.headers["Vary"] = "Accept-Encoding"
    response.set_etag(etag)
    response.cache_control.public = True
    max_age = (0 if isinstance(bundle, CatalogBundle)
               else current_app.config["TESSERA_BUNDLE_MAX_AGE"])
    response.cache_control.max_age = max_age
    if max_age == 0:
        response.cache_control.no_cache = True
    else:
        response.cache_control.immutable = True
    return response.make_conditional(request)
