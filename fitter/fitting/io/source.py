"""Opening an input file once: transparent gzip and a SHA-256 computed while reading.

Every reader gets its bytes through ``HashedInput``: the file as stored is read
in chunks by ``HashingReader``, which feeds each chunk to SHA-256 as it passes,
and gzip (when the name ends in ``.gz``) decompresses on top of it. After the
reader is done, ``finish()`` hashes whatever the reader did not consume, so the
digest always covers the whole stored file (the compressed bytes for ``.gz``)
without a second read. The memory-mapped PLY path hashes the map instead
(see ``fitter.fitting.io.ply``).

A gzip stream is bounded (``fitter.fitting.io.limits``): its trailer's declared size is
checked as soon as the first chunk decompresses, and ``BoundedReader`` counts every
decompressed chunk (at most ``CHUNK_BYTES`` at a time) against the read's
``InputBudget``, so a decompression bomb is refused within one chunk of its limit.
"""

from __future__ import annotations

import gzip
import hashlib
import io
import os
import zlib
from pathlib import Path

from .limits import InputBudget
from .scan import ScanError

CHUNK_BYTES = 1 << 20
#: compressed bytes gzip reads at a time: how finely the running ratio is held
GZIP_READ_BYTES = 16 << 10

#: errors of the standard decompressor on a corrupt or truncated ``.gz``
GZIP_ERRORS = (gzip.BadGzipFile, EOFError, zlib.error)


class HashingReader(io.RawIOBase):
    """A raw binary reader that feeds every byte it returns to a SHA-256.

    Parameters
    ----------
    raw : binary file object
        The stored file, opened ``"rb"``.
    max_read : int, optional
        At most this many bytes per read (gzip's reads, so that ``nbytes`` follows what
        the decompressor has consumed closely).
    """

    def __init__(self, raw: io.BufferedIOBase, max_read: int | None = None) -> None:
        super().__init__()
        self._raw = raw
        self.max_read = max_read
        self.hasher = hashlib.sha256()
        self.nbytes = 0

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:  # noqa: ANN001 - any writable buffer
        if self.max_read is not None:
            buffer = memoryview(buffer).cast("B")[:self.max_read]
        n = self._raw.readinto(buffer)
        if n:
            self.hasher.update(memoryview(buffer)[:n])
            self.nbytes += n
        return n or 0

    def drain(self) -> None:
        """Read (and hash) the rest of the file."""
        self.max_read = None
        buf = bytearray(CHUNK_BYTES)
        while self.readinto(buf):
            pass


class BoundedReader(io.RawIOBase):
    """The decompressed bytes of a gzip stream, counted against an ``InputBudget``.

    Parameters
    ----------
    gzipped : gzip.GzipFile
        The decompressing stream.
    source : HashingReader
        What ``gzipped`` reads the stored file through: its ``nbytes`` are the compressed
        bytes consumed so far, for the running ratio.
    name : str
        The file's name, for the refusal.
    compressed : int
        The stored (compressed) size in bytes, for the ratio limit.
    budget : InputBudget
        The read's budget; :meth:`InputBudget.take_expanded` refuses past a limit.
    declared : int or None
        The size the gzip trailer states, checked once the first chunk has decompressed
        (so that a corrupt stream is reported as corrupt, not by its garbage trailer).
    """

    def __init__(self, gzipped: gzip.GzipFile, source: HashingReader, name: str,
                 compressed: int, budget: InputBudget, declared: int | None = None) -> None:
        super().__init__()
        self._gzip, self._source = gzipped, source
        self.name_shown, self.compressed, self.budget = name, compressed, budget
        self.declared = declared
        self.nbytes = 0

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:  # noqa: ANN001 - any writable buffer
        view = memoryview(buffer).cast("B")[:CHUNK_BYTES]  # overshoot at most one chunk
        n = self._gzip.readinto(view)
        if n and self.declared is not None:
            self.budget.check_declared_size(self.name_shown, self.compressed, self.declared)
            self.declared = None
        if n:
            self.nbytes += n
            self.budget.take_expanded(self.name_shown, self.compressed, self._source.nbytes,
                                      self.nbytes, n)
        return n or 0


def declared_gzip_size(path: Path) -> int | None:
    """The uncompressed size modulo 2^32 a gzip file's trailer states (ISIZE, RFC 1952),
    or None for a file too short to have one."""
    with open(path, "rb") as fh:
        fh.seek(0, os.SEEK_END)
        if fh.tell() < 18:  # a 10-byte header and the 8-byte trailer
            return None
        fh.seek(-4, os.SEEK_END)
        return int.from_bytes(fh.read(4), "little")


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
        Decompress with gzip on the fly, within ``budget``.
    budget : InputBudget, optional
        The read's limits and what it has used (default: a fresh budget of the default
        ``InputLimits``).

    Reads of ``stream`` raise ``ScanError`` when a gzip trailer declares more than the
    budget allows (checked on the first chunk) or once the decompressed bytes pass it.
    """

    def __init__(self, path: Path, gzipped: bool, budget: InputBudget | None = None) -> None:
        self.path = path
        budget = budget if budget is not None else InputBudget()
        compressed = path.stat().st_size
        self._file = open(path, "rb")  # noqa: SIM115 - closed in close()
        self._hashing = HashingReader(self._file, GZIP_READ_BYTES if gzipped else None)
        if gzipped:
            bounded = BoundedReader(gzip.GzipFile(fileobj=self._hashing, mode="rb"),
                                    self._hashing, path.name, compressed, budget,
                                    declared_gzip_size(path))
            self.stream: io.BufferedIOBase = io.BufferedReader(bounded, CHUNK_BYTES)
        else:
            self.stream = io.BufferedReader(self._hashing, CHUNK_BYTES)

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
