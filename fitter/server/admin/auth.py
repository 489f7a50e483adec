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
  fingerprint of the current secret's hash and of the catalog's session version
  into Flask's signed session cookie (``HttpOnly``, ``SameSite=Strict``;
  ``Secure`` with ``TESSERA_ADMIN_SECURE_COOKIE``). Every form carries a CSRF
  token checked on every POST (400 when wrong). A page without a valid session
  redirects to the login page.

Rotation and logout take effect at once
---------------------------------------
Every admin request first re-reads two catalog settings in one indexed SQLite
read (:meth:`AdminState.refresh`; no hashing): the token hash that ``tessera
admin set-token`` writes and the session version that ``POST /admin/logout``
increments. A new hash replaces the old one in this process at once (the old
token is refused, the caches of checked tokens are emptied) and voids every
session cookie made under the old one; a logout voids every session cookie (one
shared secret is one admin identity, so logging out ends the admin's sessions in
every browser). ``TESSERA_ADMIN_TOKEN`` from the environment takes precedence
over the catalog's hash, as before: then only the session version is re-read.

Failed tokens cost little and are rate-limited
----------------------------------------------
A token check is a scrypt hash (0.35-1 s of CPU), so each presented token
(bearer or login form) passes, in order, cheapest first (:meth:`AdminState.check`):

1. the per-address limiter (:class:`FailureLimiter`): after
   :data:`FREE_FAILURES` failed hash checks from one client address, that address
   waits ``min(BASE_DELAY_S * 2**(n - FREE_FAILURES), MAX_DELAY_S)`` seconds after
   its ``n``-th failure; until then every token from it, right or wrong, is a 429
   with ``Retry-After`` (JSON under ``/admin/api/``, the wait on the login page).
   An address also has one hash check at a time: while one runs, its other tokens
   are 429s (``Retry-After: 1``), so a burst from one address costs one hash;
2. the shape (:func:`fitter.collection.tokens.token_shape_ok`): a token of an
   impossible length or character is a 401 at once;
3. the tokens this process has already checked: a right one (kept, as before) is
   accepted, a recently refused one (the last :data:`REMEMBERED_FAILURES`) is a
   401, both without hashing (under ``/admin/api/`` steps 1-3 refuse before Flask,
   :class:`CheapRefusals`: a refused attacker costs a settings read and a digest,
   not a Flask request);
4. the hash itself, on a pool of :data:`HASH_POOL_SIZE` slot(s) per process, with
   at most :data:`HASH_QUEUE_SIZE` requests waiting, each at most
   :data:`HASH_WAIT_S`: any further request is a 503 with ``Retry-After`` at once,
   so token checks never hold more than ``HASH_POOL_SIZE + HASH_QUEUE_SIZE`` of a
   process's request threads and the public routes keep the others.

Every refused token (401, 429 or 503, whichever step refused it) also puts its connection
in the tarpit (:mod:`fitter.server.tarpit`): the refusal is sent at once, then that
connection's next request is not read for :data:`~fitter.server.tarpit.REFUSED_HOLD_S`
seconds, without a request thread or CPU (``tessera serve --production``'s worker,
:mod:`fitter.server.tarpit_worker`; the development server has no tarpit). A client that
keeps its connection alive, as every load generator does, is answered at most once a second
per connection, so 32 attacking connections make about 32 requests a second instead of a
thousand, and the public routes keep the CPU; other connections, even from the same
address, are not slowed.

Only failed hash checks count against an address: repeating a refused token, or
sending one of impossible shape, is no new guess and costs no hash. A right token
clears the address's record. The limiter is per process (``tessera serve
--production`` runs several: each allows its own ``FREE_FAILURES``) and holds at
most :data:`MAX_TRACKED_ADDRESSES` addresses, each forgotten
:data:`FORGET_AFTER_S` after its last failure.

The client address is ``request.remote_addr``, the peer of the TCP connection.
Behind a reverse proxy that is the proxy's address, so every client would share
one limit: configure werkzeug's ``ProxyFix`` (``app.wsgi_app = ProxyFix(app.wsgi_app,
x_for=1)``, with the number of proxies you run) so that ``remote_addr`` becomes
the client's. ``X-Forwarded-For`` is not trusted by default: any client can send it.

Which routes are public is decided in one place, :func:`_authorize`, run
before every view of the blueprint: only ``admin.login`` is exempt, so a new
route is protected unless it is deliberately added there (the tests enumerate
``app.url_map`` to hold this).
"""

from __future__ import annotations

import hashlib
import hmac
import json
import math
import secrets
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from http import HTTPStatus
from pathlib import Path
from typing import Any

from flask import (
    Blueprint,
    Flask,
    abort,
    current_app,
    has_request_context,
    jsonify,
    redirect,
    request,
    session,
    url_for,
)
from flask.typing import ResponseReturnValue
from werkzeug.security import check_password_hash

from ...collection.catalog import Catalog, ThreadCatalogs
from ...collection.tokens import SESSION_VERSION_SETTING, TOKEN_SETTING, token_shape_ok
from ...collection.uploads import UploadLimits
from ..tarpit import hold_connection

bp = Blueprint("admin", __name__, url_prefix="/admin")

#: endpoints reachable without the secret (the login form itself)
PUBLIC_ENDPOINTS = frozenset({"admin.login"})
UNSAFE_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
#: page endpoints that take a streamed multipart form and check its CSRF field themselves
STREAMING_FORM_ENDPOINTS = frozenset({"admin.upload"})
CSRF_MESSAGE = "the form's CSRF token is missing or wrong; reload the page and try again"

#: failed hash checks an address may make before it has to wait
FREE_FAILURES = 5
#: the wait after the first failure beyond :data:`FREE_FAILURES` (s); doubled by each further one
BASE_DELAY_S = 1.0
#: the longest wait (s)
MAX_DELAY_S = 300.0
#: an address's record is dropped this long after its last failure (s)
FORGET_AFTER_S = 900.0
#: addresses the limiter follows at once (the least recently failed is dropped beyond)
MAX_TRACKED_ADDRESSES = 10_000
#: digests of refused tokens remembered (refused again without hashing)
REMEMBERED_FAILURES = 4096
#: scrypt checks running at once in one process
HASH_POOL_SIZE = 1
#: token checks that may wait for a hash slot; more are refused with a 503 at once
HASH_QUEUE_SIZE = 1
#: the longest a token check waits for a hash slot before a 503 (s)
HASH_WAIT_S = 1.0


class FailureLimiter:
    """Exponential backoff of failed token checks, per client address.

    After ``n`` failures (``n >= free_failures``) the address waits
    ``min(base_delay * 2**(n - free_failures), max_delay)`` seconds from its last
    failure; a success clears its record. Thread-safe; bounded to
    ``max_addresses`` records (least recently failed dropped first).

    Parameters
    ----------
    free_failures, base_delay, max_delay, forget_after, max_addresses
        See :data:`FREE_FAILURES`, :data:`BASE_DELAY_S`, :data:`MAX_DELAY_S`,
        :data:`FORGET_AFTER_S`, :data:`MAX_TRACKED_ADDRESSES` (the defaults).
    clock : callable, optional
        Seconds, monotonic (``time.monotonic``; tests pass their own).
    """

    def __init__(self, free_failures: int = FREE_FAILURES, base_delay: float = BASE_DELAY_S,
                 max_delay: float = MAX_DELAY_S, forget_after: float = FORGET_AFTER_S,
                 max_addresses: int = MAX_TRACKED_ADDRESSES,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if free_failures < 0:
            raise ValueError(f"free_failures must be >= 0, got {free_failures}")
        if not 0 < base_delay <= max_delay:
            raise ValueError(f"need 0 < base_delay <= max_delay, got {base_delay}, {max_delay}")
        if max_addresses < 1:
            raise ValueError(f"max_addresses must be >= 1, got {max_addresses}")
        self.free_failures = free_failures
        self.base_delay = base_delay
        self.max_delay = max_delay
        self.forget_after = max(forget_after, max_delay)
        self.max_addresses = max_addresses
        self.clock = clock
        self._records: OrderedDict[str, tuple[int, float]] = OrderedDict()  # failures, last
        self._checking: set[str] = set()  # addresses with a hash check running
        self._lock = threading.Lock()

    def _delay(self, failures: int) -> float:
        if failures < self.free_failures:
            return 0.0
        exponent = min(failures - self.free_failures, 64)  # 2**64 * base is past any max
        return min(self.base_delay * 2.0 ** exponent, self.max_delay)

    def _wait(self, address: str, now: float) -> float:
        if address in self._checking:
            return self.base_delay
        record = self._records.get(address)
        if record is None:
            return 0.0
        failures, last = record
        if now - last > self.forget_after:
            del self._records[address]
            return 0.0
        return max(0.0, last + self._delay(failures) - now)

    def wait(self, address: str) -> float:
        """Seconds ``address`` must still wait before its token is checked (0: none); while
        a check of one of its tokens runs, ``base_delay``."""
        now = self.clock()
        with self._lock:
            return self._wait(address, now)

    def begin(self, address: str) -> float:
        """Start a hash check for ``address`` unless it must wait: return that wait (0: the
        check may run, and :meth:`end` must follow). One check per address at a time, so a
        burst from one address costs one hash, the rest are refused at once."""
        now = self.clock()
        with self._lock:
            wait = self._wait(address, now)
            if wait == 0:
                self._checking.add(address)
            return wait

    def end(self, address: str) -> None:
        with self._lock:
            self._checking.discard(address)

    def record_failure(self, address: str) -> float:
        """Count a failed check from ``address``; return the wait it now has (s)."""
        now = self.clock()
        with self._lock:
            failures, last = self._records.pop(address, (0, now))
            if now - last > self.forget_after:
                failures = 0
            self._records[address] = (failures + 1, now)
            while len(self._records) > self.max_addresses:
                self._records.popitem(last=False)
            return self._delay(failures + 1)

    def record_success(self, address: str) -> None:
        with self._lock:
            self._records.pop(address, None)


class RecentDigests:
    """A bounded set of SHA-256 digests, the oldest dropped first (refused tokens)."""

    def __init__(self, size: int = REMEMBERED_FAILURES) -> None:
        self.size = size
        self._digests: OrderedDict[str, None] = OrderedDict()

    def add(self, digest: str) -> None:
        self._digests[digest] = None
        self._digests.move_to_end(digest)
        while len(self._digests) > self.size:
            self._digests.popitem(last=False)

    def __contains__(self, digest: object) -> bool:
        return digest in self._digests

    def clear(self) -> None:
        self._digests.clear()


@dataclass(frozen=True)
class AuthResult:
    """The outcome of one token check: ``status`` 200 (right), 401 (wrong), 429 (this address
    must wait ``retry_after`` s) or 503 (every hash slot busy: retry after ``retry_after`` s)."""

    status: int
    message: str = ""
    retry_after: int = 0

    @property
    def ok(self) -> bool:
        return self.status == 200


ACCEPTED = AuthResult(200)
WRONG_TOKEN = AuthResult(401, "wrong admin token")
HASH_BUSY = AuthResult(503, "the server is busy checking other admin tokens; retry in a "
                            "second", retry_after=1)


def _must_wait(seconds: float) -> AuthResult:
    wait = max(1, math.ceil(seconds))
    return AuthResult(429, f"too many admin token attempts from this address: wait {wait} s "
                           "before the next one", retry_after=wait)


@dataclass
class AdminState:
    """What the admin blueprint needs at request time (``app.extensions['tessera_admin']``).

    ``token_hash`` is the secret's hash now in force: the environment's when
    ``token_from_environment``, else the catalog's as last read by :meth:`refresh`.
    """

    collection: Path
    token_hash: str | None
    catalogs: ThreadCatalogs | None
    limits: UploadLimits
    token_from_environment: bool = False
    session_version: str = "0"
    limiter: FailureLimiter = field(default_factory=FailureLimiter)
    _stored_hash: str | None = None
    _verified: set[str] = field(default_factory=set)
    _refused: RecentDigests = field(default_factory=RecentDigests)
    _hash_slots: threading.BoundedSemaphore = field(
        default_factory=lambda: threading.BoundedSemaphore(HASH_POOL_SIZE))
    _hash_queue: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def __post_init__(self) -> None:
        if not self.token_from_environment:
            self._stored_hash = self.token_hash

    @property
    def enabled(self) -> bool:
        return self.token_hash is not None

    @property
    def fingerprint(self) -> str:
        """What a valid session cookie carries: a digest of the secret's hash and of the
        session version (a new secret or a logout changes it)."""
        material = f"{self.token_hash or ''}\0{self.session_version}"
        return hashlib.sha256(material.encode()).hexdigest()[:32]

    def refresh(self) -> None:
        """Re-read the catalog's token hash and session version (one SQLite read, no hash).

        A changed token hash replaces :attr:`token_hash` (unless the environment's is in
        force) and empties the caches of checked tokens.
        """
        if self.catalogs is None:
            return
        values = self.catalogs.get().get_settings(TOKEN_SETTING, SESSION_VERSION_SETTING)
        with self._lock:
            self.session_version = values.get(SESSION_VERSION_SETTING, "0")
            stored = values.get(TOKEN_SETTING)
            if not self.token_from_environment and stored != self._stored_hash:
                self._stored_hash = self.token_hash = stored
                self._verified = set()
                self._refused.clear()

    def end_sessions(self) -> None:
        """Void every admin session cookie (``POST /admin/logout``)."""
        if self.catalogs is None:
            self.session_version = secrets.token_hex(8)
            return
        self.catalogs.get().increment_setting(SESSION_VERSION_SETTING)
        self.refresh()

    def precheck(self, presented: str, address: str) -> AuthResult | None:
        """The cheap steps of :meth:`check` (limiter, shape, checked tokens): their answer,
        or None when only the hash can tell."""
        wait = self.limiter.wait(address)
        if wait > 0:
            return _must_wait(wait)
        if not self.token_hash or not token_shape_ok(presented):
            return WRONG_TOKEN
        digest = hashlib.sha256(presented.encode()).hexdigest()
        with self._lock:
            if digest in self._verified:
                self.limiter.record_success(address)
                return ACCEPTED
            if digest in self._refused:
                return WRONG_TOKEN
        return None

    def check(self, presented: str, address: str) -> AuthResult:
        """Whether ``presented``, from client ``address``, is the secret (see the module's
        "Failed tokens cost little" for the order of the checks). In a request, a refusal
        puts the request's connection in the tarpit
        (:func:`fitter.server.tarpit.hold_connection`)."""
        result = self._check(presented, address)
        if not result.ok and has_request_context():
            hold_connection(request.environ)
        return result

    def _check(self, presented: str, address: str) -> AuthResult:
        known = self.precheck(presented, address)
        if known is not None:
            return known
        token_hash = self.token_hash
        if not token_hash:
            return WRONG_TOKEN
        digest = hashlib.sha256(presented.encode()).hexdigest()
        wait = self.limiter.begin(address)
        if wait > 0:
            return _must_wait(wait)
        try:
            return self._check_hash(presented, digest, token_hash, address)
        finally:
            self.limiter.end(address)

    def _check_hash(self, presented: str, digest: str, token_hash: str,
                    address: str) -> AuthResult:
        """The costly check, on the bounded pool (:data:`HASH_POOL_SIZE`)."""
        with self._lock:
            if self._hash_queue >= HASH_POOL_SIZE + HASH_QUEUE_SIZE:
                return HASH_BUSY
            self._hash_queue += 1
        try:
            if not self._hash_slots.acquire(timeout=HASH_WAIT_S):
                return HASH_BUSY
            try:
                right = check_password_hash(token_hash, presented)
                with self._lock:
                    current = self.token_hash == token_hash  # not rotated while hashing
                    if current:
                        (self._verified.add if right else self._refused.add)(digest)
                if right:
                    self.limiter.record_success(address)
                else:
                    self.limiter.record_failure(address)
            finally:
                self._hash_slots.release()
        finally:
            with self._lock:
                self._hash_queue -= 1
        return ACCEPTED if right and current else WRONG_TOKEN

    def catalog(self) -> Catalog:
        assert self.catalogs is not None
        return self.catalogs.get()


def state() -> AdminState:
    return current_app.extensions["tessera_admin"]


def client_address() -> str:
    """The client's address for the limiter: ``request.remote_addr`` (see the module's note
    on ``ProxyFix`` behind a proxy)."""
    return request.remote_addr or "unknown"


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


def api_error(message: str, status: int, retry_after: int = 0) -> ResponseReturnValue:
    body: dict[str, Any] = {"error": message}
    if retry_after:
        body["retry_after"] = retry_after
    response = jsonify(body)
    response.status_code = status
    if status == 401:
        response.headers["WWW-Authenticate"] = 'Bearer realm="tessera-admin"'
    if retry_after:
        response.headers["Retry-After"] = str(retry_after)
    return response


class CheapRefusals:
    """WSGI middleware: the admin API's Bearer requests that the cheap steps refuse
    (:meth:`AdminState.precheck`: an address that must wait, a token of impossible shape,
    a token refused before) are answered here, before Flask.

    During an attack nearly every request is such a refusal; answered by the Flask view
    it would cost a request context, the URL map, the session and the response hooks
    (about 0.3 ms of Python), which 32 connections turn into a large share of the CPU that
    the public routes need. Here it costs the catalog's settings read
    (:meth:`AdminState.refresh`, so a rotated token is seen at once) and a digest.
    The answer is the one :func:`_authorize` gives (the same JSON, ``Retry-After`` or
    ``WWW-Authenticate``), with the headers that the app's ``after_request`` hooks put
    on an admin API response of that status (the security headers of
    :mod:`fitter.server.headers`), taken once from a real response. Installed by
    :func:`fitter.server.admin.init_app` as ``app.wsgi_app``; a ``ProxyFix`` wrapped
    around the app later runs first, so ``REMOTE_ADDR`` is then the client's. Each
    refusal puts its connection in the tarpit (:func:`fitter.server.tarpit.hold_connection`),
    as :meth:`AdminState.check` does.
    """

    def __init__(self, app: Flask, admin: AdminState) -> None:
        self.app = app
        self.wsgi_app = app.wsgi_app
        self.admin = admin
        self.prefix = f"{bp.url_prefix}/api/"
        self._headers: dict[int, list[tuple[str, str]]] = {}

    def _response_headers(self, status: int) -> list[tuple[str, str]]:
        headers = self._headers.get(status)
        if headers is None:
            with self.app.test_request_context(self.prefix):
                response = self.app.process_response(api_error("", status))
            skip = {"content-type", "content-length", "set-cookie", "vary", "retry-after"}
            headers = self._headers[status] = [(k, v) for k, v in response.headers.items()
                                               if k.lower() not in skip]
        return headers

    def __call__(self, environ: dict[str, Any],
                 start_response: Callable[..., Any]) -> Any:
        scheme, _, token = environ.get("HTTP_AUTHORIZATION", "").partition(" ")
        token = token.strip()
        if (token and scheme.lower() == "bearer" and self.admin.catalogs is not None
                and environ.get("PATH_INFO", "").startswith(self.prefix)):
            address = environ.get("REMOTE_ADDR") or "unknown"
            wait = self.admin.limiter.wait(address)  # first: it needs no catalog read
            if wait > 0:
                result: AuthResult | None = _must_wait(wait)
            else:
                self.admin.refresh()
                result = (self.admin.precheck(token, address)
                          if self.admin.enabled else None)  # off: Flask's 404 says so
            if result is not None and not result.ok:
                hold_connection(environ)
                body: dict[str, Any] = {"error": result.message}
                headers = [("Content-Type", "application/json")]
                if result.retry_after:
                    body["retry_after"] = result.retry_after
                    headers.append(("Retry-After", str(result.retry_after)))
                data = json.dumps(body).encode()
                headers.append(("Content-Length", str(len(data))))
                status = f"{result.status} {HTTPStatus(result.status).phrase.upper()}"
                start_response(status, headers + self._response_headers(result.status))
                return [data]
        return self.wsgi_app(environ, start_response)


@bp.before_request
def _authorize() -> ResponseReturnValue | None:
    """The one gate of every admin route (see the module docstring)."""
    admin = state()
    admin.refresh()
    if not admin.enabled:
        abort(404, description="the admin area is off: no admin token is configured "
                               "(TESSERA_ADMIN_TOKEN or `tessera admin set-token`)")
    if request.endpoint in PUBLIC_ENDPOINTS:
        return None
    if request.path.startswith(url_for("admin.api_root")):
        token = _bearer()
        if token is not None:
            result = admin.check(token, client_address())
            return None if result.ok else api_error(result.message, result.status,
                                                    result.retry_after)
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
