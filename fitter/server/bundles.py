"""The ``bundles`` blueprint: a bundle's files, immutable and cacheable.

``GET /bundles/<id>/<file>``: a fitted bundle never changes in place (a refit
writes a new bundle), so its files are served with a year-long
``Cache-Control: public, immutable``, an ETag, HTTP ranges and gzip where it
helps (see :mod:`fitter.server.files`). A name leading outside the bundle
directory is a 404.
"""

from __future__ import annotations

from flask import Blueprint, abort, current_app
from flask.typing import ResponseReturnValue

from .api import get_bundle_or_404
from .files import send_from

bp = Blueprint("bundles", __name__, url_prefix="/bundles")


@bp.get("/<object_id>/", defaults={"filename": ""})
@bp.get("/<object_id>/<path:filename>")
def bundle_file(object_id: str, filename: str) -> ResponseReturnValue:
    bundle = get_bundle_or_404(object_id)
    if not filename:
        abort(404, description="name a file of the bundle, e.g. manifest.json")
    return send_from(bundle.path, filename, current_app.config["TESSERA_BUNDLE_MAX_AGE"],
                     immutable=True)
