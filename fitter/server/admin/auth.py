"""The admin area's gate: its blueprint, its state, login sessions, CSRF and bearer tokens.

Authentication
--------------
The secret is ``TESSERA_ADMIN_TOKEN`` (environment or ``create_app`` config) or
the hash stored by ``tessera admin set-token`` in the catalog. Only a werkzeug
password hash is kept (the plain environment value is hashed at start-up and
dropped from ``app.config``). With no secret at all the admin area is off:
every ``/admin`` URL answers 404 and the public site works as before.

* The JSON API (``/admin/api/...``) takes ``Authorization: Bearer TOKEN``, or
  the admin pages' session cookie together with an ``X-CSRF-Token`` header on
  methods that change something (how the admin pages' own scripts call it).
  Anything else is a 401 with ``WWW-Authenticate: Bearer``.
* The pages take a login form with the same secret; a successful login puts a
  fingerprint of the current secret's hash into Flask's signed session cookie
  (``HttpOnly``, ``SameSite=Strict``; ``Secure`` with
  ``TESSERA_ADMIN_SECURE_COOKIE``), so changing the secret logs everybody out.
  Every form carries a CSRF token checked on every POST (400 when wrong).
  A page without a valid session redirects to the login page.

Which routes are public is decided in one place, :func:`_authorize`, run
before every view of the blueprint: only ``admin.login`` is exempt, so a new
route is protected unless it is deliberately added there (the tests enumerate
``app.url_map`` to hold this).
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from flask import Blueprint, abort, current_app, jsonify, redirect, request, session, url_for
from flask.typing import ResponseReturnValue
from werkzeug.security import check_password_hash

from ...collection.catalog import Catalog, ThreadCatalogs
from ...collection.uploads import UploadLimits

bp = Blueprint("admin", __name__, url_prefix="/admin")

#: endpoints reachable without the secret (the login form itself)
PUBLIC_ENDPOINTS = frozenset({"admin.login"})
UNSAFE_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
#: page endpoints that take a streamed multipart form and check its CSRF field themselves
STREAMING_FORM_ENDPOINTS = frozenset({"admin.upload"})
CSRF_MESSAGE = "the form's CSRF token is missing or wrong; reload the page and try again"


@dataclass
class AdminState:
    """What the admin blueprint needs at request time (``app.extensions['tessera_admin']``)."""

    collection: Path
    token_hash: str | None
    catalogs: ThreadCatalogs | None
    limits: UploadLimits
    _verified: set[str] = field(default_factory=set)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def enabled(self) -> bool:
        return self.token_hash is not None

    @property
    def fingerprint(self) -> str:
        return hashlib.sha256((self.token_hash or "").encode()).hexdigest()[:32]

    def check(self, presented: str) -> bool:
        """Whether ``presented`` is the secret (the slow hash check is done once per token)."""
        if not self.token_hash or not presented:
            return False
        digest = hashlib.sha256(presented.encode()).hexdigest()
        with self._lock:
            if digest in self._verified:
                return True
        if check_password_hash(self.token_hash, presented):
            with self._lock:
                self._verified.add(digest)
            return True
        return False

    def catalog(self) -> Catalog:
        assert self.catalogs is not None
        return self.catalogs.get()


def state() -> AdminState:
    return current_app.extensions["tessera_admin"]


def csrf_token() -> str:
    """This session's CSRF token (made on first use)."""
    token = session.get("csrf")
    if not token:
        token = session["csrf"] = secrets.token_urlsafe(32)
    return token


def csrf_ok(presented: str | None) -> bool:
    expected = session.get("csrf")
    return bool(expected and presented and hmac.compare_digest(str(expected), str(presented)))


def logged_in() -> bool:
    mark = session.get("admin")
    return bool(mark) and hmac.compare_digest(str(mark), state().fingerprint)


def _bearer() -> str | None:
    header = request.headers.get("Authorization", "")
    scheme, _, value = header.partition(" ")
    return value.strip() if scheme.lower() == "bearer" and value.strip() else None


def api_error(message: str, status: int) -> ResponseReturnValue:
    response = jsonify({"error": message})
    response.status_code = status
    if status == 401:
        response.headers["WWW-Authenticate"] = 'Bearer realm="tessera-admin"'
    return response


@bp.before_request
def _authorize() -> ResponseReturnValue | None:
    """The one gate of every admin route (see the module docstring)."""
    admin = state()
    if not admin.enabled:
        abort(404, description="the admin area is off: no admin token is configured "
                               "(TESSERA_ADMIN_TOKEN or `tessera admin set-token`)")
    if request.endpoint in PUBLIC_ENDPOINTS:
        return None
    if request.path.startswith(url_for("admin.api_root")):
        token = _bearer()
        if token is not None:
            return None if admin.check(token) else api_error("wrong admin token", 401)
        if logged_in():
            if request.method in UNSAFE_METHODS and not csrf_ok(
                    request.headers.get("X-CSRF-Token")):
                return api_error("missing or wrong X-CSRF-Token header", 403)
            return None
        return api_error("authentication required: send Authorization: Bearer TOKEN", 401)
    if not logged_in():
        return redirect(url_for("admin.login", next=request.full_path.rstrip("?")))
    if request.method in UNSAFE_METHODS:
        if request.mimetype == "multipart/form-data":
            # a streamed upload: touching request.form here would make werkzeug spool the
            # whole body first, so the view checks the token once the body is on disk
            if request.endpoint not in STREAMING_FORM_ENDPOINTS:
                abort(400, description="this form does not take multipart bodies")
        elif not csrf_ok(request.form.get("csrf_token")):
            abort(400, description=CSRF_MESSAGE)
    return None


@bp.context_processor
def _template_globals() -> dict[str, Any]:
    return {"admin_csrf_token": csrf_token}
