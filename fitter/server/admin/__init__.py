"""The ``admin`` blueprint: uploads, fit jobs, the catalog, publishing — behind one secret.

The gate (token, session, CSRF) is :mod:`.auth`; the pages are :mod:`.pages`, the JSON
API :mod:`.api`, and what both do :mod:`.service`. :func:`init_app` sets the area up.

Publishing
----------
On a managed collection (one with ``.tessera/catalog.sqlite``) the public
site — gallery, ``/api/objects``, viewer, bundle files — shows exactly the
catalog's published objects (:class:`PublishedCollection`), with the
catalog's title. A plain directory of bundles with no catalog is served whole,
as before. See docs/admin.md for when bundles join the catalog.
"""

from __future__ import annotations

from pathlib import Path

from flask import Flask

from ...collection.catalog import (
    Catalog,
    PublishedCollection,
    ThreadCatalogs,
    adopt_bundles,
    catalog_exists,
    state_dir,
)
from ...collection.resumable import PartialUploads
from ...collection.tokens import TOKEN_SETTING, check_token_strength, hash_token
from ...collection.uploads import UploadLimits
from . import api, pages  # noqa: F401 - their routes join ``bp``
from .auth import AdminState, CheapRefusals, bp


def init_app(app: Flask) -> None:
    """Set up the admin area and, on a managed collection, the published-only public view.

    Called by :func:`fitter.server.create_app` after the collection is in
    ``app.extensions['tessera_collection']``.
    """
    collection_dir = Path(app.config["TESSERA_COLLECTION"]).resolve()
    plain_token = str(app.config.get("TESSERA_ADMIN_TOKEN") or "")
    app.config["TESSERA_ADMIN_TOKEN"] = ""  # keep only the hash in memory
    token_hash = None
    catalogs = None
    single_bundle = (collection_dir / "manifest.json").is_file()
    if plain_token:
        check_token_strength(plain_token)
        token_hash = hash_token(plain_token)
        if single_bundle:
            raise ValueError(f"TESSERA_COLLECTION={collection_dir} is a single bundle; the "
                             "admin area needs a collection folder")
    if not single_bundle and (plain_token or catalog_exists(collection_dir)):
        with Catalog(collection_dir, create=True) as catalog:
            # first creation: what was public stays public; later arrivals wait for the admin
            adopt_bundles(catalog, publish=catalog.created)
            token_hash = token_hash or catalog.get_setting(TOKEN_SETTING)
            secret_key = catalog.secret_key()
        catalogs = ThreadCatalogs(collection_dir)
        app.extensions["tessera_all_bundles"] = app.extensions["tessera_collection"]
        app.extensions["tessera_collection"] = PublishedCollection(collection_dir, catalogs)
        if not app.config.get("SECRET_KEY"):
            app.config["SECRET_KEY"] = secret_key
    app.config.update(SESSION_COOKIE_HTTPONLY=True, SESSION_COOKIE_SAMESITE="Strict",
                      SESSION_COOKIE_SECURE=bool(app.config.get("TESSERA_ADMIN_SECURE_COOKIE")),
                      SESSION_COOKIE_NAME="tessera_admin")
    limits = UploadLimits(max_bytes=int(app.config["TESSERA_UPLOAD_MAX_BYTES"]),
                          max_expanded_bytes=int(app.config["TESSERA_UPLOAD_MAX_EXPANDED_BYTES"]),
                          max_ratio=float(app.config["TESSERA_UPLOAD_MAX_RATIO"]),
                          max_points=int(app.config["TESSERA_UPLOAD_MAX_POINTS"]),
                          max_files=int(app.config["TESSERA_UPLOAD_MAX_FILES"]))
    app.extensions["tessera_admin"] = AdminState(collection_dir, token_hash, catalogs, limits,
                                                 token_from_environment=bool(plain_token))
    if catalogs is not None:
        # resumable uploads (.resumable): the unfinished ones left by a stopped server stay
        # resumable until they expire; those already expired go now
        partials = PartialUploads(state_dir(collection_dir) / "partial", limits,
                                  float(app.config["TESSERA_UPLOAD_EXPIRE_S"]))
        partials.sweep()
        app.extensions["tessera_partial_uploads"] = partials
    app.register_blueprint(bp)
    app.wsgi_app = CheapRefusals(app, app.extensions["tessera_admin"])
