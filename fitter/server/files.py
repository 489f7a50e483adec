"""Sending files: explicit MIME types, cache lifetimes, ETags, ranges, and compression made once.

Pyodide needs ``.wasm`` served as ``application/wasm`` (streaming compilation
refuses anything else) and its ``.mjs`` modules as ``text/javascript`` (a
module script or worker with another type is refused); ``mimetypes`` depends on
the host's tables, so the types that matter are set here explicitly.

Uncompressed responses go through werkzeug's ``send_file`` with
``conditional=True``: strong ETags, ``If-None-Match`` -> 304 and HTTP range
requests (206). When the client accepts an encoding, does not ask for a range, and the
file is of a type that compresses (text, JSON, JavaScript, PLY, WebAssembly, memory
snapshots), the compressed form is sent instead: brotli when the client accepts ``br``
(Chromium sends it to HTTPS sites and to ``localhost``), else gzip. Each form is made once
per file version and kept on disk (:class:`CompressedCache`, under ``TESSERA_CACHE_DIR``):

=========  =====================================================================
gzip       level 9, made in the request that first needs it (the 9.6 MB wasm: about 1 s)
brotli     quality 11 (9 above :data:`BROTLI_BEST_MAX_BYTES`, where 11 takes minutes), made
           in a background thread; until it is there, gzip is sent
=========  =====================================================================

A compressed response carries its own ETag (``-gz`` / ``-br`` suffix) and every response of
a compressible type ``Vary: Accept-Encoding``.
"""

from __future__ import annotations

import contextlib
import gzip
import hashlib
import logging
import mimetypes
import os
import threading
from pathlib import Path

import brotli
from flask import Response, abort, current_app, request, send_file
from werkzeug.security import safe_join

log = logging.getLogger(__name__)

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
    ".tsa": "application/octet-stream",  # an atlas base (zlib inside: not compressed again)
    ".tsdp": "application/octet-stream",  # a pack of range-coded detail tiles (idem)
    ".ply": "application/octet-stream",
    ".png": "image/png",
    ".jpg": "image/jpeg",
    ".webp": "image/webp",
    ".py": "text/x-python; charset=utf-8",
}

#: Suffixes worth compressing (``.tsp``, ``.png``, ``.zip`` are compressed already).
COMPRESSIBLE = {".wasm", ".mjs", ".js", ".json", ".map", ".css", ".html", ".ply", ".py", ".txt",
                ".bin"}
COMPRESS_MIN_BYTES = 1024
COMPRESS_MAX_BYTES = 256 << 20  # a file is compressed in memory: bigger ones go as they are
#: A compressed form is sent only when it saves at least this fraction of the bytes.
COMPRESS_MIN_SAVING = 0.1
BROTLI_BEST_MAX_BYTES = 4 << 20
#: Content codings in the order preferred (the first the client accepts is sent).
ENCODINGS = ("br", "gzip")
SUFFIXES = {"br": "br", "gzip": "gz"}


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


def accepted_encodings(header: str) -> set[str]:
    """The content codings an ``Accept-Encoding`` header allows (``q=0`` excluded).

    >>> sorted(accepted_encodings("gzip, deflate, br;q=0"))
    ['deflate', 'gzip']
    """
    accepted = set()
    for item in header.split(","):
        name, _, params = item.strip().partition(";")
        quality = 1.0
        key, _, value = params.strip().partition("=")
        if key.strip() == "q":
            try:
                quality = float(value)
            except ValueError:
                quality = 0.0
        if name and quality > 0:
            accepted.add(name.strip().lower())
    return accepted


def compress(data: bytes, encoding: str) -> bytes:
    """``data`` in the content coding ``encoding`` (``"br"`` or ``"gzip"``), at the levels of
    the module docstring's table."""
    if encoding == "gzip":
        return gzip.compress(data, compresslevel=9, mtime=0)
    if encoding == "br":
        quality = 11 if len(data) <= BROTLI_BEST_MAX_BYTES else 9
        return brotli.compress(data, quality=quality, lgwin=24)
    raise ValueError(f"encoding must be one of {ENCODINGS}, got {encoding!r}")


class CompressedCache:
    """Compressed copies of served files, made once per file version, kept in ``directory``.

    A version is (real path, size, mtime); its copy is ``directory/<sha256 of it>.<gz|br>``,
    written atomically (a temporary name, then a rename), so concurrent requests and
    processes never see half a file. A copy that cannot be written (a read-only cache) is
    logged and the file is sent uncompressed.

    Parameters
    ----------
    directory : Path
        Where the copies go (made on first use).
    """

    def __init__(self, directory: Path) -> None:
        self.directory = Path(directory)
        self._lock = threading.Lock()
        self._pending: dict[Path, threading.Thread] = {}  # brotli copies being made

    def copy_path(self, path: Path, stat: os.stat_result, encoding: str) -> Path:
        key = f"{path}\0{stat.st_size}\0{stat.st_mtime_ns}".encode()
        return self.directory / f"{hashlib.sha256(key).hexdigest()[:32]}.{SUFFIXES[encoding]}"

    def get(self, path: Path, stat: os.stat_result, encodings: set[str]) -> tuple[str, Path] | None:
        """``(encoding, copy)`` of the best form of ``path`` that ``encodings`` allows and
        exists now (gzip made here if needed; brotli started in the background), or None."""
        if "br" in encodings:
            copy = self.copy_path(path, stat, "br")
            if copy.is_file():
                return "br", copy
            self._start_background(path, stat, "br", copy)
        if "gzip" in encodings:
            copy = self.copy_path(path, stat, "gzip")
            if copy.is_file() or self._make(path, "gzip", copy):
                return "gzip", copy
        return None

    def _make(self, path: Path, encoding: str, copy: Path) -> bool:
        tmp = copy.with_name(f"{copy.name}.{os.getpid()}.{threading.get_ident()}.tmp")
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            tmp.write_bytes(compress(path.read_bytes(), encoding))
            tmp.replace(copy)
        except OSError as exc:
            log.warning("cannot keep a %s copy of %s in %s: %s", encoding, path,
                        self.directory, exc)
            with contextlib.suppress(OSError):  # no folder, no temporary file
                tmp.unlink()
            return False
        return True

    def _start_background(self, path: Path, stat: os.stat_result, encoding: str,
                          copy: Path) -> None:
        def run() -> None:
            try:
                self._make(path, encoding, copy)
            finally:
                with self._lock:
                    self._pending.pop(copy, None)

        with self._lock:
            if copy in self._pending:
                return
            thread = self._pending[copy] = threading.Thread(
                target=run, daemon=True, name=f"compress-{path.name}")
        thread.start()

    def wait(self) -> None:
        """Block until no background copy is being made (for tests and benchmarks)."""
        while True:
            with self._lock:
                threads = list(self._pending.values())
            if not threads:
                return
            for thread in threads:
                thread.join()


def compressed_cache() -> CompressedCache:
    """The application's :class:`CompressedCache` (``compressed/`` in ``TESSERA_CACHE_DIR``)."""
    cache = current_app.extensions.get("tessera_compressed")
    if cache is None:
        directory = Path(current_app.config["TESSERA_CACHE_DIR"]) / "compressed"
        cache = current_app.extensions["tessera_compressed"] = CompressedCache(directory)
    return cache


def send_path(path: Path, max_age: int, immutable: bool = False,
              compress: bool | None = None) -> Response:
    """Send the file ``path`` with the caching, ETag, range and compression rules above.

    ``max_age`` is the Cache-Control lifetime in seconds (0: the browser revalidates every
    time, a cheap 304 while the ETag holds); ``immutable`` adds ``immutable`` for URLs that
    name one version of a file forever (a digest or a version in the path). ``compress``
    says whether the file's content compresses when its suffix does not tell (the trimmed
    standard library is a ``.zip`` of stored members); None: by :data:`COMPRESSIBLE`.
    """
    mimetype = mime_type(path)
    stat = path.stat()
    if compress is None:
        compress = path.suffix.lower() in COMPRESSIBLE
    compressible = (current_app.config.get("TESSERA_GZIP", True) and compress
                    and COMPRESS_MIN_BYTES <= stat.st_size <= COMPRESS_MAX_BYTES)
    found = None
    if compressible and "Range" not in request.headers:
        found = compressed_cache().get(
            path, stat, accepted_encodings(request.headers.get("Accept-Encoding", "")))
    if found is not None and found[1].stat().st_size < (1 - COMPRESS_MIN_SAVING) * stat.st_size:
        encoding, copy = found
        response = send_file(copy, mimetype=mimetype, conditional=False, etag=False,
                             download_name=path.name, max_age=max_age)
        response.headers["Content-Encoding"] = encoding
        response.set_etag(f"{stat.st_mtime_ns:x}-{stat.st_size:x}-{SUFFIXES[encoding]}")
        response.last_modified = stat.st_mtime
        response.make_conditional(request)
    else:
        response = send_file(path, mimetype=mimetype, conditional=True, etag=True,
                             max_age=max_age)
    if compressible:
        response.headers["Vary"] = "Accept-Encoding"
    response.cache_control.public = True
    response.cache_control.max_age = max_age
    response.cache_control.no_cache = True if max_age == 0 else None  # send_file's default
    if immutable:
        response.cache_control.immutable = True
    return response


def send_from(directory: Path, relative: str, max_age: int, immutable: bool = False) -> Response:
    """Send ``relative`` from ``directory`` (404 for anything outside it)."""
    return send_path(resolve(directory, relative), max_age, immutable)
