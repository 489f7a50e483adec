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
from dataclasses import replace
from numbers import Real

import numpy as np

from .scan import Scan, ScanError


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
        keys = np.zeros(n, np.int64)
        for k in range(3):
            np.subtract(pts[:, k], lo[k], out=column)
            column /= h
            np.floor(column, out=column)
            keys *= dims[k]
            keys += column.astype(np.int64)
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
