"""Receiving a scan upload: the multipart body streamed to disk, hashed and capped on the way.

The admin's ``POST /admin/api/uploads`` (and the upload page) hand the raw WSGI
request to :func:`receive_upload`, which parses the multipart body with
werkzeug's streaming parser and a stream factory of its own: the file part is
written in the parser's chunks straight into the upload's folder (never held
whole in memory, never in a system temp folder), SHA-256 and size computed on
the way, and the size limit enforced on the bytes actually received (so a body
without ``Content-Length`` is capped too). What the bytes are is decided next,
by :func:`fitter.collection.uploads.prepare_scan`.
"""

from __future__ import annotations

import hashlib
import io
import os
from pathlib import Path
from typing import IO, Any

from werkzeug.datastructures import MultiDict
from werkzeug.exceptions import RequestEntityTooLarge
from werkzeug.formparser import parse_form_data

from ...collection.uploads import ReceivedFile, UploadError, UploadLimits, format_size


class _HashingFile(io.FileIO):
    """A file that hashes and counts what is written, refusing more than ``limit`` bytes."""

    def __init__(self, path: Path, limit: int) -> None:
        super().__init__(path, "w+")
        self.limit = limit
        self.hasher = hashlib.sha256()
        self.count = 0

    def write(self, data: Any) -> int:
        view = memoryview(data)
        if self.count + len(view) > self.limit:
            raise RequestEntityTooLarge(f"the upload is larger than the limit of "
                                        f"{format_size(self.limit)}")
        n = super().write(view)
        self.hasher.update(view[:n])
        self.count += n
        return n



def receive_upload(environ: dict[str, Any], directory: Path, limits: UploadLimits,
                   field_name: str = "scan") -> tuple[MultiDict, ReceivedFile]:
    """Parse a ``multipart/form-data`` request, streaming its file into ``directory``.

    Returns the form fields and the received file (``directory/incoming.part``).

    Raises
    ------
    UploadError
        413 over ``limits.max_bytes``; 400 when not multipart, when the file
        field is missing or empty, or when other file fields are sent.
    """
    content_type = environ.get("CONTENT_TYPE", "")
    if not content_type.startswith("multipart/form-data"):
        raise UploadError(f"send the scan as multipart/form-data with a file field "
                          f"{field_name!r}, not {content_type or 'no content type'}")
    directory.mkdir(parents=True, exist_ok=True)
    streams: list[_HashingFile] = []

    def stream_factory(total_content_length: int | None, content_type: str | None,
                       filename: str | None, content_length: int | None = None) -> IO[bytes]:
        part = _HashingFile(directory / f"incoming-{len(streams)}.part", limits.max_bytes)
        streams.append(part)
        return part  # type: ignore[return-value]

    try:
        _, form, files = parse_form_data(environ, stream_factory=stream_factory,
                                         max_form_memory_size=1 << 20,
                                         max_content_length=limits.max_bytes, silent=False,
                                         max_form_parts=100)
    except RequestEntityTooLarge:
        raise UploadError(f"the upload is larger than the limit of {format_size(limits.max_bytes)} "
                          "(TESSERA_UPLOAD_MAX_BYTES)", status=413) from None
    except ValueError as exc:
        raise UploadError(f"malformed multipart body: {exc}") from None
    finally:
        for part in streams:
            part.close()
    extra = [k for k in files if k != field_name]
    if extra:
        raise UploadError(f"unexpected file field(s) {', '.join(sorted(extra))}: send one "
                          f"file, in the field {field_name!r}")
    storage = files.get(field_name)
    if storage is None:
        raise UploadError(f"no file in the field {field_name!r}")
    index = next(i for i, s in enumerate(streams) if s is storage.stream)
    part = streams[index]
    path = directory / "incoming.part"
    os.replace(part.name, path)
    original = storage.filename or ""
    if part.count == 0:
        raise UploadError(f"the uploaded file {original!r} is empty (0 bytes)")
    return form, ReceivedFile(path, original, part.count, part.hasher.hexdigest())
