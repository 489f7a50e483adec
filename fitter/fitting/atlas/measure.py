"""The distance of every scan point to the triangle mesh a visitor is drawn.

One implementation for the fitter's error report of an atlas bundle and for the
benchmarks (``bench/scoring.py``): exact point-to-triangle distances (the closest-point
regions of Ericson, *Real-Time Collision Detection*, 2005, §5.1.5) to the ``k`` triangles
whose centroids are nearest (``scipy.spatial.cKDTree``), taken in chunks so memory stays
``O(chunk k)`` whatever the point count. With ``k`` candidates the figure is an upper bound
of the true distance, exact whenever the nearest triangle is among them (always, for
triangles smaller than the gaps between points; checked against a brute force in
tests/test_atlas_pipeline.py).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

CANDIDATES = 16
CHUNK = 200_000


def closest_points_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray,
                                c: np.ndarray) -> np.ndarray:
    """The closest point of triangle ``(a_i, b_i, c_i)`` to ``p_i``, all ``(m, 3)``
    (Ericson §5.1.5: the Voronoi regions of the vertices, edges and face)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp, cp = p - b, p - c
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    denom = va + vb + vc
    proper = np.abs(denom) > 1e-300
    safe = np.where(proper, denom, 1.0)
    q = a + ab * (vb / safe)[:, None] + ac * (vc / safe)[:, None]
    outside = (va <= 0) | (vb <= 0) | (vc <= 0) | ~proper
    if outside.any():  # the nearest point of the three edges
        o = outside
        best = None
        best_d = None
        for x, y in ((a[o], b[o]), (a[o], c[o]), (b[o], c[o])):
            e = y - x
            t = np.einsum("ij,ij->i", p[o] - x, e) / np.maximum(np.einsum("ij,ij->i", e, e),
                                                               1e-300)
            cand = x + e * np.clip(t, 0.0, 1.0)[:, None]
            dist = np.einsum("ij,ij->i", p[o] - cand, p[o] - cand)
            if best is None:
                best, best_d = cand, dist
            else:
                closer = dist < best_d
                best[closer], best_d[closer] = cand[closer], dist[closer]
        q[o] = best
    return q


def closest_points_on_mesh(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                           k: int = CANDIDATES
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The closest point of the mesh ``(vertices (V, 3), faces (T, 3))`` to each of
    ``points (N, 3)``: ``(distance (N,), triangle (N,), closest (N, 3))`` (the module's
    rule: the best of the ``k`` triangles whose centroids are nearest).

    Raises
    ------
    ValueError
        An empty mesh or point set.
    """
    points = np.asarray(points, dtype=float)
    vertices = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    if len(points) == 0 or len(faces) == 0:
        raise ValueError(f"a point-to-mesh distance needs points and triangles, got {len(points)} "
                         f"points and {len(faces)} triangles")
    tri = vertices[faces]
    tree = cKDTree(tri.mean(axis=1))
    k = min(k, len(faces))
    out = np.empty(len(points))
    out_tri = np.empty(len(points), dtype=np.int64)
    out_q = np.empty_like(points)
    for start in range(0, len(points), CHUNK):
        p = points[start:start + CHUNK]
        _, cand = tree.query(p, k=k)
        cand = cand.reshape(len(p), -1)
        best = np.full(len(p), np.inf)
        best_tri = np.zeros(len(p), dtype=np.int64)
        best_q = np.zeros_like(p)
        for col in range(cand.shape[1]):
            t = tri[cand[:, col]]
            q = closest_points_on_triangles(p, t[:, 0], t[:, 1], t[:, 2])
            d = np.einsum("ij,ij->i", p - q, p - q)
            closer = d < best
            best[closer], best_tri[closer], best_q[closer] = d[closer], cand[closer, col], \
                q[closer]
        out[start:start + CHUNK] = np.sqrt(best)
        out_tri[start:start + CHUNK] = best_tri
        out_q[start:start + CHUNK] = best_q
    return out, out_tri, out_q


def signed_point_mesh_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                               k: int = CANDIDATES
                               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`closest_points_on_mesh` with the distance signed: positive on the side the
    closest triangle's normal ``(b - a) x (c - a)`` points to. Returns ``(d (N,),
    triangle (N,), closest (N, 3))``.

    Raises
    ------
    ValueError
        An empty mesh or point set.
    """
    points = np.asarray(points, dtype=float)
    dist, best_tri, best_q = closest_points_on_mesh(points, vertices, faces, k)
    t = np.asarray(vertices, dtype=float)[np.asarray(faces, dtype=np.int64)[best_tri]]
    normal = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    dist = np.where(np.einsum("ij,ij->i", points - best_q, normal) < 0, -dist, dist)
    return dist, best_tri, best_q


def point_mesh_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                        k: int = CANDIDATES, signed: bool = False) -> np.ndarray:
    """Distance of each of ``points (N, 3)`` to the mesh ``(vertices (V, 3), faces (T, 3))``
    (:func:`closest_points_on_mesh`; ``signed``: :func:`signed_point_mesh_distance`).

    Raises
    ------
    ValueError
        An empty mesh or point set.
    """
    if signed:
        return signed_point_mesh_distance(points, vertices, faces, k)[0]
    return closest_points_on_mesh(points, vertices, faces, k)[0]
