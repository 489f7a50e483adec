"""Security headers on every response, and the nonce the pages' one inline script carries.

=============================  ==============================================================
``X-Content-Type-Options``     ``nosniff`` everywhere: a file is only what its type says
``Referrer-Policy``            ``strict-origin-when-cross-origin``: other sites see the origin
``Content-Security-Policy``    :func:`content_security_policy`: scripts from this server only
                               (plus a configured ``TESSERA_3DHOP_URL``'s origin), the inline
                               import map by a per-request nonce, WebAssembly and ``eval`` for
                               Pyodide and 3DHOP's PLY loader, workers from here or ``blob:``
``X-Frame-Options``            ``DENY``, and ``frame-ancestors 'none'``, on ``/admin/`` only: the
                               public viewer stays embeddable in another site's ``<iframe>``
``Cache-Control``              ``no-store`` on ``/admin/`` (pages and API: never kept by a
                               browser or a proxy)
=============================  ==============================================================

Why each source: Pyodide compiles WebAssembly (``'wasm-unsafe-eval'``) and its runtime
builds functions from strings (``'unsafe-eval'``), as does 3DHOP's ``ply.js``; the 3DHOP page
hands 3DHOP its PLY as a ``blob:`` URL (``connect-src blob:``); inline ``style`` attributes and
``<style>`` blocks are allowed (``style-src 'unsafe-inline'``) because 3DHOP's markup needs
them, and styles cannot run code. Inline event handler attributes are not allowed: the
templates attach their handlers from modules.
"""

from __future__ import annotations

import secrets
from urllib.parse import urlsplit

from flask import Flask, Response, current_app, g, request

REFERRER_POLICY = "strict-origin-when-cross-origin"
ADMIN_PREFIX = "/admin"


def csp_nonce() -> str:
    """This request's nonce for an inline ``<script>`` (made on first use)."""
    nonce = g.get("csp_nonce")
    if nonce is None:
        nonce = g.csp_nonce = secrets.token_urlsafe(18)
    return nonce


def _hop_origin() -> str:
    """The origin (``https://host``) of ``TESSERA_3DHOP_URL``, or ``''`` when none is set."""
    parts = urlsplit(str(current_app.config.get("TESSERA_3DHOP_URL") or ""))
    return f"{parts.scheme}://{parts.netloc}" if parts.scheme and parts.netloc else ""


def content_security_policy(nonce: str | None, admin: bool) -> str:
    """The ``Content-Security-Policy`` value (see the module docstring for each source)."""
    extra = _hop_origin()
    extra = f" {extra}" if extra else ""
    script = "'self' 'wasm-unsafe-eval' 'unsafe-eval'" + extra
    if nonce:
        script += f" 'nonce-{nonce}'"
    directives = [
        "default-src 'self'",
        f"script-src {script}",
        "worker-src 'self' blob:",
        f"connect-src 'self' blob: data:{extra}",
        f"img-src 'self' data: blob:{extra}",
        f"style-src 'self' 'unsafe-inline'{extra}",
        "font-src 'self' data:",
        "object-src 'none'",
        "base-uri 'self'",
        "form-action 'self'",
    ]
    if admin:
        directives.append("frame-ancestors 'none'")
    return "; ".join(directives)


def add_security_headers(response: Response) -> Response:
    """Set the headers of the module docstring's table on ``response``."""
    admin = request.path == ADMIN_PREFIX or request.path.startswith(ADMIN_PREFIX + "/")
    response.headers["X-Content-Type-Options"] = "nosniff"
    response.headers["Referrer-Policy"] = REFERRER_POLICY
    response.headers["Content-Security-Policy"] = content_security_policy(
        g.get("csp_nonce"), admin)
    if admin:
        response.headers["X-Frame-Options"] = "DENY"
        response.headers["Cache-Control"] = "no-store"
    return response


def init_app(app: Flask) -> None:
    """Add the headers to every response of ``app`` and ``csp_nonce`` to its templates."""
    app.after_request(add_security_headers)
    app.context_processor(lambda: {"csp_nonce": csp_nonce})
