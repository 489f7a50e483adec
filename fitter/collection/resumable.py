"""Resumable uploads: a multi-gigabyte scan sent in chunks, each streamed to disk, resumable
after a dropped connection, then fitted as a one-request upload is.

The protocol follows the tus resumable upload protocol 1.0.0 (https://tus.io/protocols/
resumable-upload, core protocol with its *creation*, *expiration*, *termination* and
*checksum* extensions): the client declares the size at creation, learns the server's
offset with ``HEAD``, and sends bytes with ``PATCH`` and ``Upload-Offset``; what the server
has is always a prefix of the file, so a client resumes from the server's offset after any
failure. One step of Tessera's own follows: ``POST .../fit`` turns a complete upload into the
same fit job as ``POST /admin/api/uploads``. The HTTP side is in
:mod:`fitter.server.admin.api`; this module keeps the partial files (the collection layer:
no Flask here):

* ``<collection>/.tessera/partial/<id>/data.part`` holds the bytes received so far; its size
  *is* the offset (written, then fsynced, before an answer), ``upload.json`` the declared
  length, the client's file name, the optional declared SHA-256 and the fit options given
  at creation, ``lock`` the ``flock`` that serialises writers: a second ``PATCH`` (or a
  ``fit`` or ``DELETE``) while one writes is refused at once with a 409, in any process.
* A ``PATCH`` body is read in :data:`READ_BYTES` pieces (into one reused buffer where the
  WSGI server's stream has ``readinto``) and written at the offset, so the server holds at
  most one piece of any upload whatever its size. A body cut off mid-way keeps the bytes
  that arrived (the offset moves by them).
* The SHA-256 of the whole file is computed on the way: each process keeps the running
  hash of the uploads it last wrote (:class:`_RunningHashes`, a few hundred bytes each). A
  ``PATCH`` that reaches another process (gunicorn's workers: a browser's keep-alive
  connection mostly stays with one) or comes after a restart continues without it, and
  the whole file is then hashed once when its last byte is in (about 10 s for 3 GB):
  never the prefix again at every chunk, which would make the upload quadratic. A SHA-256
  declared at creation is checked when the last byte arrives (a mismatch discards the
  upload: 422); a ``PATCH`` may also carry ``Upload-Checksum`` (tus checksum extension:
  ``sha1`` or ``sha256`` of that chunk, base64), and a chunk that does not match is cut off
  again (460, the extension's status) and may be resent.
* Refusals: a declared size over ``TESSERA_UPLOAD_MAX_BYTES`` (413) or over the free disk
  space left after the other unfinished uploads (507); a ``PATCH`` at another offset than
  the server's (409), one that would pass the declared size (413), without
  ``Content-Length`` (411) or of another content type (415); ``fit`` of an unfinished
  upload (409).
* An upload without new bytes for ``TESSERA_UPLOAD_EXPIRE_S`` (default a day) expires: a
  request for it is a 410 and its folder is deleted; every creation (and the list) sweeps
  the expired ones.
"""

from __future__ import annotations

import base64
import binascii
import errno
import fcntl
import hashlib
import json
import os
import re
import secrets
import shutil
import threading
import time
from collections import OrderedDict
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from .uploads import ReceivedFile, UploadError, UploadLimits, format_size

TUS_VERSION = "1.0.0"
TUS_EXTENSIONS = "creation,expiration,termination,checksum"
#: the content type of a ``PATCH`` body (tus core)
OFFSET_CONTENT_TYPE = "application/offset+octet-stream"
#: bytes read from a ``PATCH`` body at a time, into one reused buffer
READ_BYTES = 1 << 20
#: ``Upload-Checksum`` algorithms accepted (the tus checksum extension requires sha1)
CHUNK_CHECKSUMS = ("sha1", "sha256")
#: the tus checksum extension's status for a chunk whose checksum does not match
CHECKSUM_MISMATCH = 460
#: ``Upload-Metadata`` keys read (``filetype`` is what tus clients send besides the name)
METADATA_KEYS = ("filename", "filetype", "sha256")
#: running hashes kept per process (each a few hundred bytes)
RUNNING_HASHES = 64
#: disk space kept free beyond the unfinished uploads' remaining bytes
DISK_MARGIN_BYTES = 256 << 20
_ID = re.compile(r"^[0-9a-f]{32}$")
_HEX_SHA256 = re.compile(r"^[0-9a-fA-F]{64}$")


def parse_metadata(header: str) -> dict[str, str]:
    """The tus ``Upload-Metadata`` header: comma-separated ``key base64(value)`` pairs.

    Raises
    ------
    UploadError
        A pair that is not ``key base64``, a value that is not UTF-8, a key given twice or
        one of none of :data:`METADATA_KEYS`.
    """
    found: dict[str, str] = {}
    for pair in filter(None, (p.strip() for p in header.split(","))):
        key, _, value = pair.partition(" ")
        if key not in METADATA_KEYS:
            raise UploadError(f"Upload-Metadata: unknown key {key!r}; accepted: "
                              f"{', '.join(METADATA_KEYS)}")
        if key in found:
            raise UploadError(f"Upload-Metadata: the key {key!r} is given twice")
        try:
            found[key] = base64.b64decode(value.strip(), validate=True).decode("utf-8")
        except (binascii.Error, UnicodeDecodeError):
            raise UploadError(f"Upload-Metadata: the value of {key!r} is not base64 of "
                              "UTF-8 text") from None
    if "sha256" in found and not _HEX_SHA256.match(found["sha256"]):
        raise UploadError("Upload-Metadata: sha256 must be the file's SHA-256 as 64 hex "
                          f"digits, got {found['sha256'][:80]!r}")
    return found


def parse_chunk_checksum(header: str) -> tuple[str, bytes]:
    """The tus ``Upload-Checksum`` header, ``ALGORITHM base64(digest)``.

    Raises
    ------
    UploadError
        An algorithm not in :data:`CHUNK_CHECKSUMS` or a digest that is not base64 of one.
    """
    algorithm, _, value = header.strip().partition(" ")
    if algorithm not in CHUNK_CHECKSUMS:
        raise UploadError(f"Upload-Checksum: algorithm {algorithm!r} is not supported; "
                          f"use one of {', '.join(CHUNK_CHECKSUMS)}")
    try:
        digest = base64.b64decode(value.strip(), validate=True)
    except binascii.Error:
        digest = b""
    if len(digest) != hashlib.new(algorithm).digest_size:
        raise UploadError(f"Upload-Checksum: {value.strip()[:80]!r} is not a base64 "
                          f"{algorithm} digest")
    return algorithm, digest


def expires_http_date(timestamp: float) -> str:
    """``Upload-Expires``: an HTTP date (RFC 9110, IMF-fixdate)."""
    return time.strftime("%a, %d %b %Y %H:%M:%S GMT", time.gmtime(timestamp))


@dataclass
class PartialUpload:
    """An unfinished (or finished, not yet fitted) resumable upload, as stored."""

    id: str
    folder: Path
    length: int
    filename: str
    options: dict[str, Any]
    created: float
    declared_sha256: str | None = None
    sha256: str | None = None  # of the whole file, once complete

    @property
    def data(self) -> Path:
        return self.folder / "data.part"

    @property
    def offset(self) -> int:
        return self.data.stat().st_size

    def last_activity(self) -> float:
        """When bytes last arrived (or the upload was created)."""
        return self.data.stat().st_mtime

    def public(self, expire_s: float) -> dict[str, Any]:
        """The upload as the API shows it."""
        offset = self.offset
        return {"id": self.id, "filename": self.filename, "length": self.length,
                "offset": offset, "complete": offset == self.length,
                "created": self.created, "expires": self.last_activity() + expire_s}

    def save(self) -> None:
        record = {"length": self.length, "filename": self.filename, "options": self.options,
                  "created": self.created, "declared_sha256": self.declared_sha256,
                  "sha256": self.sha256}
        temporary = self.folder / "upload.json.tmp"
        temporary.write_text(json.dumps(record))
        os.replace(temporary, self.folder / "upload.json")


class _RunningHashes:
    """The SHA-256 of each upload's bytes so far, as last written by this process: ``id ->
    (offset, hash)``, the least recently used dropped beyond ``size`` entries. Thread-safe."""

    def __init__(self, size: int = RUNNING_HASHES) -> None:
        self.size = size
        self._hashes: OrderedDict[str, tuple[int, Any]] = OrderedDict()
        self._lock = threading.Lock()

    def take(self, upload_id: str, offset: int) -> Any | None:
        """The hash of the first ``offset`` bytes of ``upload_id``, if kept (then forgotten:
        the writer gives it back with :meth:`put`)."""
        with self._lock:
            kept = self._hashes.pop(upload_id, None)
        return kept[1] if kept is not None and kept[0] == offset else None

    def put(self, upload_id: str, offset: int, running: Any) -> None:
        with self._lock:
            self._hashes[upload_id] = (offset, running)
            self._hashes.move_to_end(upload_id)
            while len(self._hashes) > self.size:
                self._hashes.popitem(last=False)

    def forget(self, upload_id: str) -> None:
        with self._lock:
            self._hashes.pop(upload_id, None)


def _hash_prefix(path: Path, nbytes: int) -> Any:
    """SHA-256 of the first ``nbytes`` of ``path``, read in :data:`READ_BYTES` pieces."""
    running = hashlib.sha256()
    buffer = bytearray(READ_BYTES)
    view = memoryview(buffer)
    with open(path, "rb", buffering=0) as fh:
        left = nbytes
        while left:
            n = fh.readinto(view[:min(left, READ_BYTES)])
            if not n:
                break
            running.update(view[:n])
            left -= n
    return running


@dataclass
class PartialUploads:
    """The resumable uploads of one collection (see the module docstring).

    Parameters
    ----------
    root : Path
        ``<collection>/.tessera/partial``.
    limits : UploadLimits
        ``max_bytes`` bounds the declared size.
    expire_s : float
        Seconds without new bytes after which an unfinished upload is deleted.
    clock : callable
        ``time.time`` (tests pass their own).
    """

    root: Path
    limits: UploadLimits
    expire_s: float
    clock: Any = time.time
    _hashes: _RunningHashes = field(default_factory=_RunningHashes)

    # ------------------------------------------------------------------ reading
    def get(self, upload_id: str) -> PartialUpload:
        """The upload ``upload_id``.

        Raises
        ------
        UploadError
            404 when unknown; 410 when it expired (it is deleted then).
        """
        folder = self.root / upload_id
        if not _ID.match(upload_id) or not (folder / "upload.json").is_file():
            raise UploadError(f"no resumable upload {upload_id!r}: unknown, already fitted, "
                              "deleted or expired; create a new one", status=404)
        record = json.loads((folder / "upload.json").read_text())
        upload = PartialUpload(upload_id, folder, int(record["length"]), record["filename"],
                               record["options"], record["created"],
                               record.get("declared_sha256"), record.get("sha256"))
        if self._expired(upload) and self._delete_if_idle(folder):
            raise UploadError(f"the resumable upload {upload_id} expired: no bytes arrived "
                              f"for {self.expire_s:g} s (TESSERA_UPLOAD_EXPIRE_S); its "
                              "partial file is deleted, start again", status=410)
        return upload

    def list(self) -> list[PartialUpload]:
        """The unexpired uploads, oldest first (the expired ones are swept)."""
        self.sweep()
        found = []
        for folder in sorted(self.root.glob("*/upload.json")):
            try:
                found.append(self.get(folder.parent.name))
            except (UploadError, OSError, ValueError, KeyError):
                continue
        return sorted(found, key=lambda u: u.created)

    def _expired(self, upload: PartialUpload) -> bool:
        try:
            return self.clock() - upload.last_activity() > self.expire_s
        except FileNotFoundError:
            return True

    # ------------------------------------------------------------------ writing
    @contextmanager
    def _locked(self, upload: PartialUpload, doing: str) -> Iterator[None]:
        """Hold the upload's ``flock`` (any process), or refuse at once with a 409."""
        with open(upload.folder / "lock", "a+b") as lock:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise UploadError(f"another request is writing to the resumable upload "
                                  f"{upload.id} now; {doing} when it has ended (HEAD gives "
                                  "the offset)", status=409) from None
            yield  # the lock ends with the file's close

    def create(self, length: int, metadata: Mapping[str, str],
               options: dict[str, Any]) -> PartialUpload:
        """A new upload of ``length`` bytes (checked against the limits and the free disk).

        Raises
        ------
        UploadError
            400 for an empty file; 413 over ``limits.max_bytes``; 507 when the disk cannot
            hold it besides the other unfinished uploads.
        """
        if length < 1:
            raise UploadError("Upload-Length is 0: the file is empty")
        if length > self.limits.max_bytes:
            raise UploadError(f"the file has {format_size(length)}, over the upload limit of "
                              f"{format_size(self.limits.max_bytes)} "
                              "(TESSERA_UPLOAD_MAX_BYTES)", status=413)
        self.root.mkdir(parents=True, exist_ok=True)
        pending = sum(u.length - u.offset for u in self.list())
        free = shutil.disk_usage(self.root).free
        if length + pending + DISK_MARGIN_BYTES > free:
            raise UploadError(f"not enough disk space for {format_size(length)}: "
                              f"{format_size(free)} free, {format_size(pending)} promised to "
                              "unfinished uploads", status=507)
        upload_id = secrets.token_hex(16)
        folder = self.root / upload_id
        folder.mkdir()
        upload = PartialUpload(upload_id, folder, length, metadata.get("filename", "")[:255],
                               options, self.clock(), metadata.get("sha256", "").lower() or None)
        upload.data.touch()
        upload.save()
        return upload

    def append(self, upload_id: str, offset: int, body: IO[bytes], nbytes: int,
               checksum: tuple[str, bytes] | None = None) -> PartialUpload:
        """Write ``nbytes`` read from ``body`` at ``offset`` of the upload (a ``PATCH``).

        The body is read in :data:`READ_BYTES` pieces; when it ends early (the client went
        away) the bytes that came are kept and the error re-raised. ``checksum`` is the
        chunk's ``Upload-Checksum``; the declared SHA-256 is checked when the last byte is
        in.

        Raises
        ------
        UploadError
            404/410 (see :meth:`get`); 409 another writer, or ``offset`` is not the
            server's; 413 past the declared length; 460 the chunk's checksum differs (the
            chunk is cut off again); 422 the whole file's SHA-256 differs from the declared
            one (the upload is deleted).
        """
        upload = self.get(upload_id)
        with self._locked(upload, "send this chunk"):
            current = upload.offset
            if offset != current:
                raise UploadError(f"Upload-Offset {offset} is not the server's offset "
                                  f"{current} of the resumable upload {upload_id}; resume "
                                  "from the offset HEAD gives", status=409)
            if offset + nbytes > upload.length:
                raise UploadError(f"a chunk of {nbytes} bytes at offset {offset} passes the "
                                  f"declared length of {upload.length} bytes", status=413)
            # the running hash of the bytes so far, if this process wrote the last chunk (else
            # the whole file is hashed once at the end: never the prefix again at every chunk)
            running = self._hashes.take(upload_id, current) or (
                hashlib.sha256() if current == 0 else None)
            before = running.copy() if running is not None else None
            chunk_hash = hashlib.new(checksum[0]) if checksum else None
            written, failure = self._write(upload.data, offset, body, nbytes,
                                           (running, chunk_hash))
            if failure is not None:
                # the client went away mid-chunk (or the disk is full): keep what arrived
                self._remember(upload_id, offset + written, running)
                kept = f"the {written} bytes before are kept: resume from offset {offset + written}"
                if isinstance(failure, UploadError):
                    raise failure
                if isinstance(failure, OSError) and failure.errno == errno.ENOSPC:
                    raise UploadError(f"the server's disk is full; {kept} once there is "
                                      "space", status=507) from failure
                raise UploadError(f"the chunk was cut off after {written} of its {nbytes} "
                                  f"bytes ({type(failure).__name__}: {failure}); {kept}"
                                  ) from failure
            if checksum and chunk_hash is not None and chunk_hash.digest() != checksum[1]:
                os.truncate(upload.data, offset)
                self._remember(upload_id, offset, before)
                raise UploadError(f"Upload-Checksum: the {checksum[0]} of the {written} bytes "
                                  f"received at offset {offset} is not the one sent; the "
                                  "chunk is discarded, send it again",
                                  status=CHECKSUM_MISMATCH)
            end = offset + written
            if end < upload.length:
                self._remember(upload_id, end, running)
                return upload
            self._hashes.forget(upload_id)
            if running is None:
                running = _hash_prefix(upload.data, end)
            upload.sha256 = running.hexdigest()
            if upload.declared_sha256 and upload.sha256 != upload.declared_sha256:
                self._remove_unlocked(upload)
                raise UploadError(f"the SHA-256 of the {upload.length} bytes received is "
                                  f"{upload.sha256}, not the declared {upload.declared_sha256}:"
                                  " the file changed or was damaged on the way; the upload is "
                                  "deleted, start again", status=422)
            upload.save()
            return upload

    def _remember(self, upload_id: str, offset: int, running: Any | None) -> None:
        if running is None:
            self._hashes.forget(upload_id)
        else:
            self._hashes.put(upload_id, offset, running)

    @staticmethod
    def _write(path: Path, offset: int, body: IO[bytes], nbytes: int,
               hashes: tuple[Any, ...]) -> tuple[int, Exception | None]:
        """Copy ``nbytes`` of ``body`` to ``path`` at ``offset``, updating ``hashes``, then
        fsync: ``(bytes written, None)``, or ``(bytes written before it, the exception)``
        when the body ended early or could not be read or written."""
        # werkzeug's LimitedStream reads into one reused buffer; gunicorn's request body
        # (wsgi.input_terminated: Flask passes it as it is) only has read(), one piece at a time
        readinto = getattr(body, "readinto", None)
        buffer = memoryview(bytearray(READ_BYTES)) if readinto is not None else None
        written = 0
        with open(path, "r+b", buffering=0) as out:
            out.seek(offset)
            try:
                while written < nbytes:
                    wanted = min(READ_BYTES, nbytes - written)
                    if buffer is not None:
                        piece = buffer[:readinto(buffer[:wanted]) or 0]
                    else:
                        piece = memoryview(body.read(wanted))
                    if not len(piece):
                        raise UploadError(f"the chunk ended after {written} of its {nbytes} "
                                          "bytes (Content-Length); they are kept, resume "
                                          f"from offset {offset + written}")
                    done = 0
                    while done < len(piece):  # a raw write may take part of the piece
                        step = out.write(piece[done:])
                        for running in hashes:
                            if running is not None:
                                running.update(piece[done:done + step])
                        done += step
                        written += step
            except Exception as exc:  # noqa: BLE001 - returned to the caller, who re-raises
                return written, exc
            finally:
                os.fsync(out.fileno())
        return written, None

    def take(self, upload_id: str, destination: Path) -> tuple[PartialUpload, ReceivedFile]:
        """Move a complete upload's file to ``destination/incoming.part`` (a rename, same
        file system) and forget the upload.

        Raises
        ------
        UploadError
            404/410 (see :meth:`get`); 409 while a chunk is written, or when the upload is
            not complete.
        """
        upload = self.get(upload_id)
        with self._locked(upload, "submit it for a fit"):
            offset = upload.offset
            if offset < upload.length or upload.sha256 is None:
                raise UploadError(f"the resumable upload {upload_id} is not complete: "
                                  f"{offset} of {upload.length} bytes received; send the "
                                  "rest before fitting it", status=409)
            destination.mkdir(parents=True, exist_ok=True)
            target = destination / "incoming.part"
            os.replace(upload.data, target)
            self._remove_unlocked(upload)
        return upload, ReceivedFile(target, upload.filename, upload.length, upload.sha256)

    def remove(self, upload_id: str) -> None:
        """Delete the upload (tus termination).

        Raises
        ------
        UploadError
            404/410 (see :meth:`get`); 409 while a chunk is written.
        """
        upload = self.get(upload_id)
        with self._locked(upload, "delete it"):
            self._remove_unlocked(upload)

    def _remove_unlocked(self, upload: PartialUpload) -> None:
        self._hashes.forget(upload.id)
        shutil.rmtree(upload.folder, ignore_errors=True)

    def _delete_if_idle(self, folder: Path) -> bool:
        """Delete ``folder`` unless a request holds its lock; whether it was deleted."""
        try:
            with open(folder / "lock", "a+b") as lock:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
                shutil.rmtree(folder, ignore_errors=True)
        except (BlockingIOError, FileNotFoundError):
            return False
        self._hashes.forget(folder.name)
        return True

    def sweep(self) -> list[str]:
        """Delete the expired uploads that no request is writing; their ids."""
        if not self.root.is_dir():
            return []
        removed = []
        for folder in self.root.iterdir():
            try:
                idle = self.clock() - (folder / "data.part").stat().st_mtime
            except FileNotFoundError:  # half created or half removed
                idle = self.clock() - folder.stat().st_mtime
            if idle > self.expire_s and self._delete_if_idle(folder):
                removed.append(folder.name)
        return removed
