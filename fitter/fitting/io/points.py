"""``PointStream``: a scan's points read block by block, never all at once in float64.

The out-of-core passes (``fitter.fitting.stream``) walk a large scan several times: its
bounds and digest, the voxel sums and the voxel representatives of the working set
(``fitter.fitting.io.thin``), the deviation of every point. A ``PointStream`` gives them
the points of ``[start, stop)`` as float64 ``(m, 3)``, converted one block at a time from
what the file stores (float32 ``x y z`` of a binary PLY stay float32 in the page cache),
plus the normals of the block when the file has them.

Two kinds hold the same interface:

* a binary PLY point cloud, uncompressed (:meth:`PointStream.from_ply`): the vertex block
  memory-mapped (``numpy.memmap``) with the structured dtype of its header; the map is
  opened lazily in each process, so a stream is small to pickle and a Dask worker
  (``fitter.fitting.stream``) opens the file itself (every worker must see the path, as
  for ``tessera fit-collection``);
* in-memory arrays (:meth:`PointStream.from_arrays`): a scan another reader loaded.

A file a library decodes forward (an E57 compressed vector, a LAZ file) is a
:class:`ReaderStream` instead, with the same ``name``, ``count``, ``path``, ``has_normals``,
``read``, ``take`` and ``blocks``: its points come in *segments* (the scans of an E57 file,
each read from its start; the one point list of a LAS/LAZ file, which laspy seeks into),
decoded block by block by the format's module (``fitter.fitting.io.e57.E57Stream``,
``fitter.fitting.io.las.LasStream``). ``read(start, stop)`` serves a window of the blocks
decoded last and decodes forward from its cursor; a read behind the cursor, or in an
earlier segment, re-opens the segment (an E57 scan is decoded again from its first point:
libE57Format's reader cannot seek). The passes read consecutive blocks from a few threads,
so the window reaches ``WINDOW_REQUESTS`` requests back from the one being served: blocks a
thread skipped are kept for the thread that wants them, a block leaves the window once every
point of it has been read, and a pass in block order decodes every point once. The cursor
and the window are not pickled: each process (a Dask worker) opens the file itself.
"""

from __future__ import annotations

import hashlib
import threading
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..cores import usable_cores
from .scan import ScanError
from .source import CHUNK_BYTES

#: requests of the largest size seen that a ReaderStream's window of decoded blocks holds:
#: one per thread that may read a block ahead of another
WINDOW_REQUESTS = max(2, usable_cores())
#: points of the reads :meth:`ReaderStream.take` makes
TAKE_BLOCK = 1 << 20
#: a seekable segment is re-opened at the point asked for when the cursor is more than
#: this many points behind it (decoding forward is cheaper over a shorter gap)
SEEK_GAP = 1 << 18


def block_ranges(count: int, size: int) -> list[tuple[int, int]]:
    """``[start, stop)`` of consecutive blocks of ``size`` points covering ``0..count``."""
    if size < 1:
        raise ValueError(f"size must be a positive number of points, got {size!r}")
    return [(s, min(s + size, count)) for s in range(0, count, size)]


def moved_points(points: np.ndarray, origin: np.ndarray | None) -> np.ndarray:
    """A block of points read, in the frame of a stream's ``origin`` (None: as read)."""
    return points if origin is None else points - origin


@dataclass
class PointStream:
    """The points ``(N, 3)`` of a scan, read as float64 blocks.

    Attributes
    ----------
    name : str
        The input's name, for messages.
    count : int
        ``N``.
    path : Path or None
        The memory-mapped PLY file (None for arrays).
    offset : int
        Byte offset of the vertex block in ``path``.
    dtype : numpy.dtype or None
        Structured dtype of one vertex record (``fitter.fitting.io.ply.PlyHeader.vertex_dtype``).
    xyz, normal_fields : tuple of str
        The record fields of the coordinates and (``()`` when absent) of the normals.
    points, normals : ndarray or None
        The arrays of an in-memory stream (``(N, 3)`` each; ``normals`` may be None).
    origin : ndarray, shape (3,), or None
        Subtracted from every point read (``fitter.fitting.io.frame``: a scan far from the
        origin is fitted moved near it); None: the file's coordinates.
    """

    name: str
    count: int
    path: Path | None = None
    offset: int = 0
    dtype: np.dtype | None = None
    xyz: tuple[str, ...] = ("x", "y", "z")
    normal_fields: tuple[str, ...] = ()
    points: np.ndarray | None = None
    normals: np.ndarray | None = None
    origin: np.ndarray | None = None
    _records: np.ndarray | None = field(default=None, repr=False, compare=False)

    @classmethod
    def from_ply(cls, path: Path, offset: int, dtype: np.dtype, count: int,
                 normal_fields: tuple[str, ...] = ()) -> PointStream:
        """The vertex block of a binary PLY: ``count`` records of ``dtype`` at ``offset``."""
        return cls(Path(path).name, count, Path(path), offset, np.dtype(dtype),
                   normal_fields=tuple(normal_fields))

    @classmethod
    def from_arrays(cls, name: str, points: np.ndarray,
                    normals: np.ndarray | None = None) -> PointStream:
        """In-memory points ``(N, 3)`` (and normals ``(N, 3)`` or None)."""
        return cls(name, len(points), points=points, normals=normals)

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_records"] = None  # each process maps the file itself
        return state

    def _mapped(self) -> np.ndarray:
        if self._records is None:
            self._records = np.memmap(self.path, dtype=self.dtype, mode="r",
                                      offset=self.offset, shape=(self.count,))
        return self._records

    @property
    def has_normals(self) -> bool:
        return bool(self.normal_fields) or self.normals is not None

    def read(self, start: int, stop: int) -> tuple[np.ndarray, np.ndarray | None]:
        """Points ``[start, stop)`` as float64 ``(m, 3)`` and their normals (float32
        ``(m, 3)``, None when the scan has none)."""
        if self.points is not None:
            normals = None if self.normals is None else self.normals[start:stop]
            return self._moved(np.asarray(self.points[start:stop], np.float64)), normals
        return self._of_records(self._mapped()[start:stop])

    def _of_records(self, records: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        points = np.column_stack([records[n] for n in self.xyz]).astype(np.float64)
        normals = (np.column_stack([records[n] for n in self.normal_fields])
                   .astype(np.float32) if self.normal_fields else None)
        return self._moved(points), normals

    def _moved(self, points: np.ndarray) -> np.ndarray:
        return moved_points(points, self.origin)

    def take(self, index: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Points (float64 ``(K, 3)``) and normals of the ascending indices ``index (K,)``."""
        if self.points is not None:
            normals = None if self.normals is None else self.normals[index]
            return self._moved(np.asarray(self.points[index], np.float64)), normals
        return self._of_records(self._mapped()[index])

    def blocks(self, size: int) -> list[tuple[int, int]]:
        """``[start, stop)`` of consecutive blocks of ``size`` points covering ``0..N``."""
        return block_ranges(self.count, size)


@dataclass(eq=False)
class _Decoded:
    """A block in a ReaderStream's window: its first point's index, its points, and how
    many of them reads have taken (a block is dropped once all are taken: a pass asks for
    each point once)."""

    first: int
    points: np.ndarray
    served: int = 0

    @property
    def stop(self) -> int:
        return self.first + len(self.points)


@dataclass
class _Cursor:
    """Where a ReaderStream decodes: its segment, the global index of the next point its
    iterator yields, the iterator (float64 ``(m, 3)`` blocks)."""

    segment: int
    next: int
    blocks: Iterator[np.ndarray]

    def close(self) -> None:
        close = getattr(self.blocks, "close", None)
        if close is not None:
            close()


class ReaderStream:
    """The points ``(N, 3)`` of a file a library decodes forward, in segments (see the module
    docstring); a subclass opens its library's file (:meth:`open_file`) and a segment of it
    (:meth:`open_segment`).

    Attributes
    ----------
    name : str
        The file's name, for messages.
    path : Path
        The file (hashed beside the bounds pass, ``fitter.fitting.stream``).
    segments : tuple of int
        Points of each segment; ``count`` is their sum, ``starts`` their first indices.
    seekable : bool
        Whether :meth:`open_segment` starts at the point asked for (else at the segment's
        first point, and the points before are decoded and passed over).
    decoded : int
        Points decoded in this process so far (what a read order costs).
    origin : ndarray, shape (3,), or None
        Subtracted from every point read, as :attr:`PointStream.origin`.
    """

    seekable = False
    has_normals = False

    def __init__(self, name: str, path: Path, segments: list[int]) -> None:
        self.name, self.path = name, Path(path)
        self.origin: np.ndarray | None = None
        self.segments = tuple(int(c) for c in segments)
        self.starts = np.concatenate([[0], np.cumsum(self.segments, dtype=np.int64)])
        self.count = int(self.starts[-1])
        self._reset()

    def _reset(self) -> None:
        self._lock = threading.Lock()
        self._cursor: _Cursor | None = None
        self._window: deque[_Decoded] = deque()
        self._keep = 0
        self._file: object = None
        self.decoded = 0

    def open_segment(self, segment: int, first: int) -> tuple[int, Iterator[np.ndarray]]:
        """``(local index of the first point yielded, iterator of float64 (m, 3) blocks of
        consecutive points to the segment's end)``, starting at or before local ``first``."""
        raise NotImplementedError

    def open_file(self) -> object:
        """The library's open file (with a ``close()``), opened once per process."""
        raise NotImplementedError

    def file(self) -> object:
        """:meth:`open_file`'s object of this process, opened on first use."""
        if self._file is None:
            self._file = self.open_file()
        return self._file

    def close(self) -> None:
        """Close the cursor and the file; the stream can still be read (it reopens)."""
        with self._lock:
            self._close_cursor()
            self._window.clear()
            if self._file is not None:
                opened, self._file = self._file, None
                opened.close()

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        for key in ("_lock", "_cursor", "_window", "_keep", "decoded", "_file"):
            state.pop(key)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._reset()

    def blocks(self, size: int) -> list[tuple[int, int]]:
        """``[start, stop)`` of consecutive blocks of ``size`` points covering ``0..N``."""
        return block_ranges(self.count, size)

    def read(self, start: int, stop: int) -> tuple[np.ndarray, None]:
        """Points ``[start, stop)`` as float64 ``(m, 3)`` (a new array) and no normals."""
        if not 0 <= start <= stop <= self.count:
            raise IndexError(f"{self.name}: points [{start}, {stop}) outside 0..{self.count}")
        parts = []
        with self._lock:
            self._keep = max(self._keep, WINDOW_REQUESTS * (stop - start))
            position = start
            while position < stop:
                hit = self._in_window(position)
                if hit is None:
                    self._decode_through(position, stop - self._keep)
                    continue
                end = min(stop, hit.stop)
                parts.append(hit.points[position - hit.first:end - hit.first])
                hit.served += end - position
                if hit.served >= len(hit.points):  # every point handed out: not wanted again
                    self._window.remove(hit)
                position = end
            points = np.concatenate(parts) if parts else np.empty((0, 3))
        return moved_points(points, self.origin), None

    def take(self, index: np.ndarray) -> tuple[np.ndarray, None]:
        """Points (float64 ``(K, 3)``) of the ascending indices ``index (K,)``: one forward
        read in blocks of ``TAKE_BLOCK`` (a block without an index is decoded only where the
        file cannot seek past it)."""
        index = np.asarray(index, np.int64)
        points = np.empty((len(index), 3))
        for start, stop in self.blocks(TAKE_BLOCK):
            lo, hi = np.searchsorted(index, [start, stop])
            if hi > lo:
                points[lo:hi] = self.read(start, stop)[0][index[lo:hi] - start]
        return points, None

    def _in_window(self, position: int) -> _Decoded | None:
        for decoded in self._window:
            if decoded.first <= position < decoded.stop:
                return decoded
        return None

    def _close_cursor(self) -> None:
        if self._cursor is not None:
            cursor, self._cursor = self._cursor, None
            cursor.close()

    def _decode_through(self, position: int, horizon: int) -> None:
        """Decode the next block of the cursor, first moving it to ``position``'s segment
        (forward: after decoding the rest of its own segment when that is within the window's
        reach) or re-opening that segment (backward, or a long gap when seekable); the window
        then drops its blocks that end at or before ``horizon`` (never the new one)."""
        segment = int(np.searchsorted(self.starts, position, side="right")) - 1
        cursor = self._cursor
        if (cursor is not None and cursor.segment < segment and not self.seekable
                and cursor.next < self.starts[cursor.segment + 1]
                and position - cursor.next <= self._keep):
            segment = cursor.segment  # finish it: a thread may ask for the points passed over
        elif (cursor is None or cursor.segment != segment or cursor.next > position
                or (self.seekable and position - cursor.next > SEEK_GAP)):
            if cursor is not None and (cursor.segment > segment or cursor.next > position):
                self._window.clear()  # backward: the window holds points ahead, not wanted soon
            self._close_cursor()
            start = int(self.starts[segment])
            first, blocks = self.open_segment(segment, position - start)
            cursor = self._cursor = _Cursor(segment, start + first, blocks)
        end = int(self.starts[segment + 1])
        block = next(cursor.blocks, None)
        if block is None or cursor.next + len(block) > end:
            got = cursor.next - int(self.starts[segment]) + (0 if block is None else len(block))
            self._close_cursor()
            raise ScanError(f"{self.name}: the file changed while it was read: segment "
                            f"{segment} gave {'only ' if block is None else ''}{got:,} "
                            f"points, the first pass counted {self.segments[segment]:,}")
        if len(block) == 0:  # an E57 block of invalid points only
            return
        self._window.append(_Decoded(cursor.next, block))
        cursor.next += len(block)
        self.decoded += len(block)
        while len(self._window) > 1 and self._window[0].stop <= horizon:
            self._window.popleft()


def file_sha256(path: Path) -> str:
    """SHA-256 of the stored file, read in ``CHUNK_BYTES`` chunks."""
    hasher = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(CHUNK_BYTES):
            hasher.update(block)
    return hasher.hexdigest()
