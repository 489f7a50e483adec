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
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .source import CHUNK_BYTES


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
            return np.asarray(self.points[start:stop], np.float64), normals
        records = self._mapped()[start:stop]
        points = np.column_stack([records[n] for n in self.xyz]).astype(np.float64)
        normals = (np.column_stack([records[n] for n in self.normal_fields])
                   .astype(np.float32) if self.normal_fields else None)
        return points, normals

    def take(self, index: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Points (float64 ``(K, 3)``) and normals of the ascending indices ``index (K,)``."""
        if self.points is not None:
            normals = None if self.normals is None else self.normals[index]
            return np.asarray(self.points[index], np.float64), normals
        records = self._mapped()[index]
        points = np.column_stack([records[n] for n in self.xyz]).astype(np.float64)
        normals = (np.column_stack([records[n] for n in self.normal_fields])
                   .astype(np.float32) if self.normal_fields else None)
        return points, normals

    def blocks(self, size: int) -> list[tuple[int, int]]:
        """``[start, stop)`` of consecutive blocks of ``size`` points covering ``0..N``."""
        if size < 1:
            raise ValueError(f"size must be a positive number of points, got {size!r}")
        return [(s, min(s + size, self.count)) for s in range(0, self.count, size)]


def file_sha256(path: Path) -> str:
    """SHA-256 of the stored file, read in ``CHUNK_BYTES`` chunks."""
    hasher = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(CHUNK_BYTES):
            hasher.update(block)
    return hasher.hexdigest()
