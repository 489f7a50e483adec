"""Opening an input file once: transparent gzip and a SHA-256 computed while reading.

Every reader gets its bytes through ``HashedInput``: the file as stored is read
in chunks by ``HashingReader``, which feeds each chunk to SHA-256 as it passes,
and gzip (when the name ends in ``.gz``) decompresses on top of it. After the
reader is done, ``finish()`` hashes whatever the reader did not consume, so the
digest always covers the whole stored file (the compressed bytes for ``.gz``)
without a second read. The memory-mapped PLY path hashes the map instead
(see ``fitter.fitting.io.ply``).
"""

from __future__ import annotations

import gzip
import hashlib
import io
import os
import zlib
from pathlib import Path

from .scan import ScanError

CHUNK_BYTES = 1 << 20

#: errors of the standard decompressor on a corrupt or truncated ``.gz``
GZIP_ERRORS = (gzip.BadGzipFile, EOFError, zlib.error)


class HashingReader(io.RawIOBase):
    """A raw binary reader that feeds every byte it returns to a SHA-256.

    Parameters
    ----------
    raw : binary file object
        The stored file, opened ``"rb"``.
    """

    def __init__(self, raw: io.BufferedIOBase) -> None:
        super().__init__()
        self._raw = raw
        self.hasher = hashlib.sha256()
        self.nbytes = 0

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:  # noqa: ANN001 - any writable buffer
        n = self._raw.readinto(buffer)
        if n:
            self.hasher.update(memoryview(buffer)[:n])
            self.nbytes += n
        return n or 0

    def drain(self) -> None:
        """Read (and hash) the rest of the file."""
        buf = bytearray(CHUNK_BYTES)
        while self.readinto(buf):
            pass


def file_record(name: str, data: bytes | None = None, *, nbytes: int | None = None,
                sha256: str | None = None, role: str = "input") -> dict:
    """``{"name", "bytes", "sha256", "role"}`` for one file (hashing ``data`` if given)."""
    if data is not None:
        nbytes, sha256 = len(data), hashlib.sha256(data).hexdigest()
    return {"name": name, "bytes": nbytes, "sha256": sha256, "role": role}


def check_path(path: Path) -> int:
    """Size of an existing, non-empty regular file; ``ScanError`` otherwise."""
    try:
        st = path.stat()
    except FileNotFoundError:
        raise ScanError(f"{path}: no such file") from None
    except OSError as exc:
        raise ScanError(f"{path}: cannot access the file ({exc.strerror})") from None
    if path.is_dir():
        raise ScanError(f"{path}: is a directory, not a scan file")
    if st.st_size == 0:
        raise ScanError(f"{path}: the file is empty (0 bytes)")
    if not os.access(path, os.R_OK):
        raise ScanError(f"{path}: the file is not readable (permission denied)")
    return st.st_size


class HashedInput:
    """The decompressed byte stream of one input file, hashed as it is read.

    Use as a context manager; read from ``stream``; call ``finish()`` once the
    reader is done to hash the unread rest and get the file's record.

    Parameters
    ----------
    path : Path
        The stored file.
    gzipped : bool
        Decompress with gzip on the fly.
    """

    def __init__(self, path: Path, gzipped: bool) -> None:
        self.path = path
        self._file = open(path, "rb")  # noqa: SIM115 - closed in close()
        self._hashing = HashingReader(self._file)
        buffered = io.BufferedReader(self._hashing, CHUNK_BYTES)
        self.stream: io.BufferedIOBase = (
            gzip.GzipFile(fileobj=buffered, mode="rb") if gzipped else buffered)

    def finish(self, role: str = "input") -> dict:
        """Hash the rest of the stored file; its record ``{name, bytes, sha256, role}``."""
        self._hashing.drain()
        return file_record(self.path.name, nbytes=self._hashing.nbytes,
                           sha256=self._hashing.hasher.hexdigest(), role=role)

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> HashedInput:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def read_exactly(stream: io.BufferedIOBase, buffer: memoryview) -> int:
    """Fill ``buffer`` from ``stream``; the number of bytes read (short only at end of file)."""
    done = 0
    while done < len(buffer):
        n = stream.readinto(buffer[done:])
        if not n:
            break
        done += n
    return done
