"""Voxel thinning: keep one representative point per occupied cube of a grid.

The grid has cubes of edge ``h`` anchored at the cloud's minimum corner
``p_min``; point ``p`` falls in voxel ``floor((p - p_min) / h)``. In each
occupied voxel the point nearest to the voxel's mean (centroid) is kept, ties
going to the lower index, so the result is a subset of the input (no new,
averaged points) and deterministic.
Kept points stay in their original order. Cost: one ``numpy.unique`` (a sort,
``O(N log N)``) and one ``lexsort``.
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
    cells = np.floor((pts - pts.min(axis=0)) / h).astype(np.int64)
    dims = cells.max(axis=0) + 1
    if float(dims[0]) * float(dims[1]) * float(dims[2]) < 2.0**62:
        keys = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
        _, voxel = np.unique(keys, return_inverse=True)
    else:  # a grid too fine for one int64 key: unique rows instead (slower, same result)
        _, voxel = np.unique(cells, axis=0, return_inverse=True)
    voxel = voxel.reshape(-1)
    count = np.bincount(voxel).astype(np.float64)
    centroid = np.column_stack([np.bincount(voxel, pts[:, k]) / count for k in range(3)])
    dist2 = ((pts - centroid[voxel]) ** 2).sum(axis=1)
    order = np.lexsort((np.arange(len(pts)), dist2, voxel))
    first = np.ones(len(order), bool)
    first[1:] = voxel[order[1:]] != voxel[order[:-1]]
    return np.sort(order[first])


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
