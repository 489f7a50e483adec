"""Sending files: explicit MIME types, cache lifetimes, ETags, ranges and gzip when it helps.

Pyodide needs ``.wasm`` served as ``application/wasm`` (streaming compilation
refuses anything else) and its ``.mjs`` modules as ``text/javascript`` (a
module script or worker with another type is refused); ``mimetypes`` depends on
the host's tables, so the types that matter are set here explicitly.

Uncompressed responses go through werkzeug's ``send_file`` with
``conditional=True``: strong ETags, ``If-None-Match`` -> 304 and HTTP range
requests (206). When the client accepts gzip, does not ask for a range, and the
file is of a type that compresses (text, JSON, JavaScript, PLY, WebAssembly),
the gzip form is sent instead (a fresh ``<file>.gz`` next to it, else compressed once per
file version), kept in memory;
it carries its own ETag (``-gz`` suffix) and ``Vary: Accept-Encoding``.
"""

from __future__ import annotations

import gzip
import mimetypes
import threading
from pathlib import Path

from flask import Response, abort, current_app, request, send_file
from werkzeug.security import safe_join

MIME_TYPES = {
    ".wasm": "application/wasm",
    ".mjs": "text/javascript",
    ".js": "text/javascript",
    ".json": "application/json",
    ".map": "application/json",
    ".css": "text/css",
    ".html": "text/html; charset=utf-8",
    ".zip": "application/zip",
    ".tsp": "application/octet-stream",
    ".tsd": "application/octet-stream",
    ".ply": "application/octet-stream",
    ".png": "image/png",
    ".jpg": "image/jpeg",
    ".webp": "image/webp",
    ".py": "text/x-python; charset=utf-8",
}

#: Suffixes worth compressing (``.tsp``, ``.png``, ``.zip`` are compressed already).
COMPRESSIBLE = {".wasm", ".mjs", ".js", ".json", ".map", ".css", ".html", ".ply", ".py", ".txt",
                ".bin"}
GZIP_MIN_BYTES = 1024
GZIP_MAX_BYTES = 64 << 20  # keep memory bounded: bigger files go uncompressed

_gzip_cache: dict[tuple[str, int, int], bytes] = {}
_gzip_lock = threading.Lock()


def mime_type(path: Path) -> str:
    """The Content-Type for ``path``: the explicit table first, then ``mimetypes``."""
    suffix = path.suffix.lower()
    if suffix in MIME_TYPES:
        return MIME_TYPES[suffix]
    guessed, _ = mimetypes.guess_type(path.name)
    return guessed or "application/octet-stream"


def resolve(directory: Path, relative: str) -> Path:
    """``directory / relative`` as an existing regular file, else 404.

    ``safe_join`` rejects absolute paths and ``..`` segments; symbolic links
    leading outside ``directory`` are refused as well.
    """
    joined = safe_join(str(directory), relative)
    if joined is None:
        abort(404, description=f"no file {relative!r} here")
    path = Path(joined)
    try:
        real = path.resolve(strict=True)
        real.relative_to(Path(directory).resolve())
    except (OSError, ValueError):
        abort(404, description=f"no file {relative!r} here")
    if not real.is_file():
        abort(404, description=f"no file {relative!r} here")
    return real


def _gzipped(path: Path, size: int, mtime: int) -> bytes:
    key = (str(path), size, mtime)
    with _gzip_lock:
        data = _gzip_cache.get(key)
    if data is None:
        sibling = Path(f"{path}.gz")  # made ahead of time (e.g. the Pyodide snapshot)
        try:
            fresh = sibling.stat().st_mtime_ns >= mtime
        except OSError:
            fresh = False
        data = sibling.read_bytes() if fresh else gzip.compress(path.read_bytes(), mtime=0)
        with _gzip_lock:
            _gzip_cache[key] = data
    return data


def send_path(path: Path, max_age: int, immutable: bool = False) -> Response:
    """Send the file ``path`` with the caching, ETag, range and gzip rules above."""
    mimetype = mime_type(path)
    stat = path.stat()
    use_gzip = (
        current_app.config.get("TESSERA_GZIP", True)
        and path.suffix.lower() in COMPRESSIBLE
        and GZIP_MIN_BYTES <= stat.st_size <= GZIP_MAX_BYTES
        and "gzip" in request.headers.get("Accept-Encoding", "")
        and "Range" not in request.headers
    )
    if use_gzip:
        data = _gzipped(path, stat.st_size, stat.st_mtime_ns)
        if len(data) < 0.9 * stat.st_size:
            response = Response(data, mimetype=mimetype)
            response.headers["Content-Encoding"] = "gzip"
            response.set_etag(f"{stat.st_mtime_ns:x}-{stat.st_size:x}-gz")
            response.last_modified = stat.st_mtime
            response.make_conditional(request)
        else:
            use_gzip = False
    if not use_gzip:
        response = send_file(path, mimetype=mimetype, conditional=True, etag=True,
                             max_age=max_age)
    response.headers["Vary"] = "Accept-Encoding"
    response.cache_control.public = True
    response.cache_control.max_age = max_age
    if immutable:
        response.cache_control.immutable = True
    return response


def send_from(directory: Path, relative: str, max_age: int, immutable: bool = False) -> Response:
    """Send ``relative`` from ``directory`` (404 for anything outside it)."""
    return send_path(resolve(directory, relative), max_age, immutable)
