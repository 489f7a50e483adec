"""Voxel thinning: keep one representative point per occupied cube of a grid.

The grid has cubes of edge ``h`` anchored at the cloud's minimum corner
``p_min``; point ``p`` falls in voxel ``floor((p - p_min) / h)``. In each
occupied voxel the point nearest to the voxel's mean (centroid) is kept, ties
going to the lower index, so the result is a subset of the input (no new,
averaged points) and deterministic.
Kept points stay in their original order. Cost: one ``argsort`` of the int64
voxel keys (``O(N log N)``) and segment reductions (``reduceat``).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, replace
from numbers import Real

import numpy as np

from .scan import Scan, ScanError

#: the largest grid a :class:`VoxelIndex` keeps a table of (4 bytes a cell: 192 MB)
DENSE_INDEX_CELLS = 48_000_000


def check_voxel_size(size: object, name: str = "thin") -> float:
    """A finite voxel edge ``> 0`` as float; ``ScanError`` naming ``name`` otherwise."""
    if isinstance(size, bool) or not isinstance(size, Real):
        raise ScanError(f"{name} must be a positive voxel size in scan units, got "
                        f"{type(size).__name__} {size!r}")
    value = float(size)
    if not math.isfinite(value) or value <= 0:
        raise ScanError(f"{name} must be a positive, finite voxel size in scan units, got "
                        f"{value!r}")
    return value


def voxel_keys(points: np.ndarray, lo: np.ndarray, size: float, dims: np.ndarray,
               column: np.ndarray | None = None) -> np.ndarray:
    """The voxel of each point as one int64 key (the module's one rule for it).

    ``key = (i_0 d_1 + i_1) d_2 + i_2`` with ``i_k = floor((p_k - lo_k) / h)`` and
    ``dims = (d_0, d_1, d_2)`` voxels per axis (``d_0 d_1 d_2 < 2^62``).

    Parameters
    ----------
    points : ndarray, shape (m, 3), float64
    lo : ndarray, shape (3,)
        The grid's anchor ``p_min`` (the whole cloud's minimum corner).
    size : float
        Voxel edge ``h``.
    dims : ndarray of int64, shape (3,)
    column : ndarray, shape (m,), float64, optional
        Scratch space (reused by callers that key many points).
    """
    n = len(points)
    column = np.empty(n, np.float64) if column is None else column
    keys = np.zeros(n, np.int64)
    for k in range(3):
        np.subtract(points[:, k], lo[k], out=column)
        column /= size
        np.floor(column, out=column)
        keys *= dims[k]
        keys += column.astype(np.int64)
    return keys


def voxel_thin_indices(points: np.ndarray, size: float) -> np.ndarray:
    """Indices (ascending) of one point per occupied voxel of edge ``size``.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Finite coordinates.
    size : float
        Voxel edge ``h > 0`` in the points' units.

    Returns
    -------
    ndarray, shape (K,), int64
        ``K`` = number of occupied voxels; for each, the point minimising
        ``||p - c_v||^2`` with ``c_v`` the mean of the voxel's points.
    """
    h = check_voxel_size(size, "size")
    pts = np.asarray(points, np.float64)
    n = len(pts)
    if n == 0:
        return np.empty(0, np.int64)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    dims = np.floor((hi - lo) / h).astype(np.int64) + 1
    # Large temporaries are few and reused: fresh memory costs page faults, and
    # at 10^7 points each (N,) array is 80 MB.
    column = np.empty(n, np.float64)
    if float(dims[0]) * float(dims[1]) * float(dims[2]) < 2.0**62:
        keys = voxel_keys(pts, lo, h, dims, column)
    else:  # a grid too fine for one int64 key: number the occupied cells instead
        cells = np.floor((pts - lo) / h).astype(np.int64)
        keys = np.unique(cells, axis=0, return_inverse=True)[1].reshape(-1)
        del cells
    order = np.argsort(keys)  # by voxel (quicksort: ties are broken explicitly below)
    np.take(keys, order, out=keys)
    starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
    counts = np.diff(np.r_[starts, n])
    group = np.repeat(np.arange(len(starts)), counts)
    del keys
    dist2 = np.zeros(n, np.float64)
    expanded = np.empty(n, np.float64)
    for k in range(3):  # |p - c|^2 summed over the coordinates, in voxel order
        np.take(pts[:, k], order, out=column)
        centroid = np.add.reduceat(column, starts) / counts
        np.take(centroid, group, out=expanded)
        column -= expanded
        column *= column
        dist2 += column
    nearest = dist2 == np.minimum.reduceat(dist2, starts)[group]
    candidates = np.flatnonzero(nearest)  # in voxel order; several per voxel only on ties
    voxel_of = group[candidates]
    first = np.flatnonzero(np.r_[True, voxel_of[1:] != voxel_of[:-1]])
    return np.sort(np.minimum.reduceat(order[candidates], first))  # ties: the lowest index


def thin_scan(scan: Scan, size: object) -> Scan:
    """The scan reduced to one point per voxel of edge ``size`` (see ``voxel_thin_indices``).

    Faces are dropped (they index removed points); normals, colours and uv follow
    the kept points; ``source["thinning"]`` records the voxel size and counts.

    Raises
    ------
    ScanError
        ``size`` not a finite number ``> 0``, or so large (at least the bounding-box
        diagonal) that the whole scan would collapse to a handful of points.
    """
    name = scan.source.get("name", "scan")
    h = check_voxel_size(size)
    diagonal = float(np.linalg.norm(np.ptp(scan.points, axis=0)))
    if h >= diagonal:
        raise ScanError(f"{name}: thin={h!r} is not smaller than the scan's bounding-box "
                        f"diagonal {diagonal:.6g}: every point would fall in one or two voxels")
    keep = voxel_thin_indices(scan.points, h)

    def take(a: np.ndarray | None) -> np.ndarray | None:
        return None if a is None else a[keep]

    source = dict(scan.source, thinning={"voxel_size": h, "points_before": scan.n_points,
                                         "points_after": int(len(keep)),
                                         "faces_dropped": scan.faces is not None})
    return replace(scan, points=scan.points[keep], normals=take(scan.normals),
                   colors=take(scan.colors), uv=take(scan.uv), faces=None, source=source)


# ------------------------------------------------------------- the same rule, streamed
# A cloud too large for memory is thinned in blocks of consecutive points: a first pass sums
# each voxel's points (VoxelSums, merged block by block in file order, so the centroids are
# the same sums whatever ran the blocks), a second finds each voxel's point nearest its
# centroid (VoxelNearest, the smallest (distance^2, index): order-free). The result is the
# rule of voxel_thin_indices; only the centroid's rounding may differ (its sum runs in file
# order here, in sort order there), which decides nothing but exact distance ties.


@dataclass(frozen=True)
class VoxelGrid:
    """The grid of a streamed thinning: anchor ``lo (3,)``, edge ``size``, ``dims (3,)``."""

    lo: np.ndarray
    size: float
    dims: np.ndarray

    @classmethod
    def over(cls, lo: np.ndarray, hi: np.ndarray, size: float) -> VoxelGrid:
        """The grid of edge ``size`` over the box ``[lo, hi]``.

        Raises
        ------
        ValueError
            ``size`` so small that the voxels do not fit one int64 key (``< 2^62``).
        """
        lo = np.asarray(lo, np.float64)
        dims = np.floor((np.asarray(hi, np.float64) - lo) / size).astype(np.int64) + 1
        if float(dims[0]) * float(dims[1]) * float(dims[2]) >= 2.0**62:
            raise ValueError(f"size {size!r} gives {dims.tolist()} voxels, more than one int64 "
                             "key holds; a larger voxel is needed")
        return cls(lo, float(size), dims)

    def keys(self, points: np.ndarray) -> np.ndarray:
        """:func:`voxel_keys` of ``points (m, 3)``."""
        return voxel_keys(points, self.lo, self.size, self.dims)

    def centres(self, keys: np.ndarray) -> np.ndarray:
        """The centres ``(K, 3)`` of the voxels of ``keys (K,)`` (:func:`voxel_keys`'
        inverse): ``lo + (i + 1/2) h``."""
        cells = np.empty((len(keys), 3), np.int64)
        rest = np.asarray(keys, np.int64)
        for k in (2, 1, 0):
            rest, cells[:, k] = np.divmod(rest, self.dims[k])
        return self.lo + (cells + 0.5) * self.size

    @property
    def half_diagonal(self) -> float:
        """The distance from a voxel's centre to its corners, ``h sqrt(3) / 2``."""
        return 0.5 * math.sqrt(3.0) * self.size


class VoxelIndex:
    """The position of each point's voxel among the ascending ``keys (K,)`` of a
    :class:`VoxelGrid` (every point's voxel must be among them).

    A table of one int32 per cell of the grid when the grid has at most
    ``DENSE_INDEX_CELLS`` cells (a gather: ten times faster than a binary search over a
    million keys), else a binary search (``searchsorted``). The table is built on first use
    in each process (a Dask worker builds its own: only the keys travel).
    """

    def __init__(self, grid: VoxelGrid, keys: np.ndarray) -> None:
        self.grid, self.keys = grid, keys
        self._table: np.ndarray | None = None
        self._lock = threading.Lock()

    def __getstate__(self) -> dict:
        return {"grid": self.grid, "keys": self.keys}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["grid"], state["keys"])

    def _dense(self) -> np.ndarray | None:
        cells = int(np.prod(self.grid.dims))
        if cells > DENSE_INDEX_CELLS:
            return None
        with self._lock:
            if self._table is None:
                table = np.zeros(cells, np.int32)
                table[self.keys] = np.arange(len(self.keys), dtype=np.int32)
                self._table = table
        return self._table

    def positions(self, points: np.ndarray) -> np.ndarray:
        """Positions ``(m,)`` in ``keys`` of the voxels of ``points (m, 3)``."""
        keys = self.grid.keys(points)
        table = self._dense()
        return (np.searchsorted(self.keys, keys) if table is None
                else table[keys].astype(np.intp))


@dataclass
class VoxelSums:
    """Per occupied voxel: ``keys (K,)`` ascending, coordinate sums ``sums (K, 3)`` and
    point counts ``counts (K,)``."""

    keys: np.ndarray
    sums: np.ndarray
    counts: np.ndarray

    @classmethod
    def empty(cls) -> VoxelSums:
        return cls(np.empty(0, np.int64), np.empty((0, 3)), np.empty(0, np.int64))

    @classmethod
    def of(cls, points: np.ndarray, grid: VoxelGrid) -> VoxelSums:
        """The sums of one block of points ``(m, 3)`` (in the block's order)."""
        keys, inverse = unique_inverse(grid.keys(points))
        sums = np.column_stack([np.bincount(inverse, weights=points[:, k], minlength=len(keys))
                                for k in range(3)])
        return cls(keys, sums, np.bincount(inverse, minlength=len(keys)).astype(np.int64))

    def merged(self, later: VoxelSums) -> VoxelSums:
        """These sums and those of a ``later`` block: ``self``'s terms first (each voxel's
        sum is ``(0 + self's) + later's``, as a ``bincount`` of both would add them).

        Both key lists are ascending: the union is a merge of two sorted runs, and each
        list's place in it a binary search (no sort of the concatenation)."""
        n = len(self.keys)
        place = np.searchsorted(self.keys, later.keys)
        shared = place < n
        shared[shared] = self.keys[place[shared]] == later.keys[shared]
        new_keys = later.keys[~shared]
        keys = np.sort(np.concatenate([self.keys, new_keys]), kind="stable")  # two runs
        self_at = np.arange(n) + np.searchsorted(new_keys, self.keys)
        later_at = np.empty(len(later.keys), np.intp)
        later_at[shared] = self_at[place[shared]]
        later_at[~shared] = place[~shared] + np.arange(len(new_keys))
        sums = np.zeros((3, len(keys)))  # column by column: 1-d assignments are faster
        for row, first, second in zip(sums, self.sums.T, later.sums.T, strict=True):
            row[self_at] = first + 0.0  # 0 + x, as bincount adds it (-0.0 gives +0.0)
            row[later_at] += second
        counts = np.zeros(len(keys), np.int64)
        counts[self_at] = self.counts
        counts[later_at] += later.counts
        return VoxelSums(keys, sums.T, counts)

    def centroids(self) -> np.ndarray:
        """``c_v = sums / counts``, ``(K, 3)``."""
        return self.sums / self.counts[:, None]


@dataclass
class VoxelNearest:
    """Per voxel of a :class:`VoxelSums` (by position ``0..K-1``): the squared distance
    ``dist2 (K,)`` of the best point found so far to the centroid, and its index ``index
    (K,)`` (``-1`` where none yet)."""

    dist2: np.ndarray
    index: np.ndarray

    @classmethod
    def empty(cls, voxels: int) -> VoxelNearest:
        return cls(np.full(voxels, np.inf), np.full(voxels, -1, np.int64))

    @staticmethod
    def of_block(points: np.ndarray, first: int, index: VoxelIndex, centroids: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The block's candidates: voxel positions, squared distances and indices of the point
        of points ``first .. first + m - 1`` nearest each voxel's centroid (lowest index on
        ties), for :meth:`update`. Two unbuffered minima per voxel (``np.minimum.at``: the
        distance, then the index among the points at it), no sort."""
        position = index.positions(points)
        dist2 = np.zeros(len(points))
        for k in range(3):  # |p - c|^2 summed over the coordinates in order, as above
            column = points[:, k] - np.take(centroids[:, k], position)
            column *= column
            dist2 += column
        best = np.full(len(centroids), np.inf)
        np.minimum.at(best, position, dist2)
        at_best = np.flatnonzero(dist2 == best[position])
        lowest = np.full(len(centroids), np.iinfo(np.int64).max)
        np.minimum.at(lowest, position[at_best], at_best)
        found = np.flatnonzero(lowest < len(points))
        return found, best[found], lowest[found] + first

    def update(self, position: np.ndarray, dist2: np.ndarray, index: np.ndarray) -> None:
        """Keep the smaller ``(dist2, index)`` per voxel (order-free)."""
        better = (dist2 < self.dist2[position]) | ((dist2 == self.dist2[position])
                                                   & (index < self.index[position]))
        self.dist2[position[better]] = dist2[better]
        self.index[position[better]] = index[better]

    def kept(self) -> np.ndarray:
        """The representatives' indices, ascending."""
        return np.sort(self.index[self.index >= 0])


def unique_inverse(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(keys, return_inverse=True)`` of int64 ``keys (n,)`` at or above 0.

    When a key and a position fit one int64 (``key < 2^(62 - bits(n))``) by one sort of
    ``key 2^bits + position`` (a sort: twice as fast as the argsort ``np.unique`` makes);
    the inverse is then the running count of distinct keys, put back at the positions."""
    n = len(keys)
    bits = max(1, (n - 1).bit_length())
    if n == 0 or keys.min() < 0 or keys.max() >= 1 << (62 - bits):
        return np.unique(keys, return_inverse=True)
    packed = keys << bits
    packed |= np.arange(n)
    packed.sort()
    position = packed & ((1 << bits) - 1)
    packed >>= bits  # the keys, ascending
    first = np.empty(n, bool)
    first[0] = True
    np.not_equal(packed[1:], packed[:-1], out=first[1:])
    inverse = np.empty(n, np.intp)
    inverse[position] = np.cumsum(first) - 1
    return packed[first], inverse


def _occupied(keys: np.ndarray) -> int:
    """The number of distinct ``keys`` (a sort: faster than ``np.unique``'s hash here; of
    int32 keys when they fit, which sort faster)."""
    if len(keys) and keys.max() < 2**31:
        keys = keys.astype(np.int32)
    ordered = np.sort(keys)
    return int(np.count_nonzero(ordered[1:] != ordered[:-1])) + (len(ordered) > 0)


def _voxels_from_sample(occupied: int, sample: int) -> float:
    """The number ``K`` of voxels a cloud occupies, from the ``occupied`` voxels of an even
    ``sample`` of it: each of ``K`` equally filled voxels is missed by the sample with
    probability ``exp(-s / K)`` (Poisson), so ``occupied = K (1 - exp(-s / K))``, solved for
    ``K`` by bisection on a log scale (``K >= occupied``; an ``occupied`` near ``s``, a sample
    too sparse to tell, gives ``K`` up to ``1000 s``)."""
    if occupied >= sample:
        return 1000.0 * sample
    low, high = float(occupied), 1000.0 * sample
    for _ in range(60):
        middle = math.sqrt(low * high)
        if middle * -math.expm1(-sample / middle) < occupied:
            low = middle
        else:
            high = middle
    return math.sqrt(low * high)


def voxel_size_for(sample: np.ndarray, total: int, target: int,
                   lo: np.ndarray, hi: np.ndarray) -> float:
    """The voxel edge ``h`` at which a cloud of ``total`` points occupies about ``target``
    voxels, estimated on an even ``sample (s, 3)`` of it.

    At each trial ``h`` (bisected on a log scale) the sample's occupied voxels give the
    cloud's by :func:`_voxels_from_sample`: measured at ``h`` itself, so measurement noise
    thicker than ``h`` counts as it will in the cloud (scaling a surface's count from a
    coarser voxel did not: 10^7 noisy points then occupied 1.3 times the target). Unevenly
    filled voxels make the estimate low (the caller checks the count it gets).
    """
    if not (isinstance(target, int) and target >= 1):
        raise ValueError(f"target must be a positive number of voxels, got {target!r}")
    s = len(sample)
    diagonal = float(np.linalg.norm(np.asarray(hi) - np.asarray(lo)))
    if s >= total:  # the sample is the cloud
        def count(h: float) -> float:
            return _occupied(VoxelGrid.over(lo, hi, h).keys(sample))
    else:
        def count(h: float) -> float:
            return _voxels_from_sample(_occupied(VoxelGrid.over(lo, hi, h).keys(sample)), s)
    small, large = diagonal * 2.0**-20, diagonal
    for _ in range(18):  # the ratio 2^20 to within 2^(20 / 2^18)
        middle = math.sqrt(small * large)
        small, large = (middle, large) if count(middle) > target else (small, middle)
    return math.sqrt(small * large)


def thin_to_count(points: np.ndarray, target: int, slack: float = 1.0) -> np.ndarray:
    """Indices of a voxel thinning (:func:`voxel_thin_indices`) to about ``target`` points:
    at most ``slack * target``, the voxel edge starting at ``diagonal / sqrt(target)`` (a
    surface of that extent, sampled ``target`` times) and grown by ``sqrt(kept / target)``
    per try, at most 8 tries. All indices when there are no more than ``target`` points."""
    if len(points) <= target:
        return np.arange(len(points))
    h = float(np.linalg.norm(np.ptp(points, axis=0))) / math.sqrt(target)
    keep = voxel_thin_indices(points, h)
    for _ in range(8):
        if len(keep) <= slack * target:
            break
        h *= math.sqrt(len(keep) / target)
        keep = voxel_thin_indices(points, h)
    return keep
