"""Atlases for the atlas format and mesh tests: a subdivided cube layout, closed and
consistently oriented, with control points on a sphere (smooth) or random.

``cube_layout(k)`` cuts each face of the cube ``[0, k]^3`` into ``k x k`` quads (``6 k^2``
quads, ``6 k^2 + 2`` vertices), counter-clockwise seen from outside. ``sphere_atlas``
places every control point on the unit sphere: corners and edge points by the straight
cube edge's lattice point, face points by the quad's bilinear point, each normalised, so
shared points are one point by construction. ``random_atlas`` jitters them.
"""

from __future__ import annotations

import math
import random

from client_py.atlas import AtlasSurface, atlas_edges

# (origin, u axis, v axis) of each cube face, u x v outward
_FACES = (((0, 0, 0), (0, 1, 0), (1, 0, 0)), ((0, 0, 1), (1, 0, 0), (0, 1, 0)),
          ((0, 0, 0), (1, 0, 0), (0, 0, 1)), ((0, 1, 0), (0, 0, 1), (1, 0, 0)),
          ((0, 0, 0), (0, 0, 1), (0, 1, 0)), ((1, 0, 0), (0, 1, 0), (0, 0, 1)))


def cube_layout(k: int) -> tuple[list[tuple[int, int, int]], list[tuple[int, int, int, int]]]:
    """Integer lattice vertices and quads of the cube ``[0, k]^3`` with ``k x k`` quads a face."""
    index: dict[tuple[int, int, int], int] = {}
    quads = []

    def vertex(p):
        return index.setdefault(p, len(index))

    for o, u, v in _FACES:
        def at(i, j, o=o, u=u, v=v):
            return vertex(tuple(k * o[c] + i * u[c] + j * v[c] for c in range(3)))
        for i in range(k):
            for j in range(k):
                quads.append((at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1)))
    lattice = sorted(index, key=index.get)
    return lattice, quads


def _on_sphere(p, k: int) -> tuple[float, float, float]:
    x, y, z = (2.0 * c / k - 1.0 for c in p)
    r = math.sqrt(x * x + y * y + z * z)
    return (x / r, y / r, z / r)


def sphere_atlas(k: int, degree: int = 3, spans: int = 2, noise: float = 0.0,
                 seed: int = 0, rational: bool = False, cube: bool = False) -> AtlasSurface:
    """``6 k^2`` patches on the unit sphere (control points on it; ``noise`` jitters them);
    with ``cube``, on the cube ``[-1, 1]^3`` instead (flat faces meeting at right angles)."""
    rnd = random.Random(seed)
    lattice, quads = cube_layout(k)
    table = atlas_edges(quads)
    m = spans + degree - 1

    def put(p):
        x, y, z = (tuple(2.0 * c / k - 1.0 for c in p) if cube else _on_sphere(p, k))
        return (x + noise * rnd.uniform(-1, 1), y + noise * rnd.uniform(-1, 1),
                z + noise * rnd.uniform(-1, 1))

    vertices = [put(p) for p in lattice]
    edge_points = []
    for lo, hi in table.edges:
        a, b = lattice[lo], lattice[hi]
        for t in range(1, m):
            edge_points.append(put(tuple(a[c] + (b[c] - a[c]) * t / m for c in range(3))))
    face_points = []
    for quad in quads:
        pa, pb, pc, pd = (lattice[q] for q in quad)
        for i in range(1, m):
            s = i / m
            for j in range(1, m):
                t = j / m
                face_points.append(put(tuple(
                    (1 - s) * (1 - t) * pa[c] + s * (1 - t) * pb[c] + s * t * pc[c]
                    + (1 - s) * t * pd[c] for c in range(3))))
    weights = None
    if rational:
        count = len(vertices) + len(edge_points) + len(face_points)
        weights = [0.5 + rnd.random() for _ in range(count)]
    return AtlasSurface(degree, spans, vertices, quads, edge_points, face_points, weights)


def random_atlas(k: int, degree: int = 3, spans: int = 2, seed: int = 0,
                 rational: bool = True) -> AtlasSurface:
    """The cube layout of ``6 k^2`` quads with every control point uniform in ``[-1, 1]^3``
    and weights in ``[0.5, 1.5]``: the worst case for prediction."""
    rnd = random.Random(seed)
    lattice, quads = cube_layout(k)
    table = atlas_edges(quads)
    inner = spans + degree - 2

    def jitter(count):
        return [(rnd.uniform(-1, 1), rnd.uniform(-1, 1), rnd.uniform(-1, 1))
                for _ in range(count)]

    vertices = jitter(len(lattice))
    edge_points = jitter(len(table.edges) * inner)
    face_points = jitter(len(quads) * inner * inner)
    weights = None
    if rational:
        count = len(vertices) + len(edge_points) + len(face_points)
        weights = [0.5 + rnd.random() for _ in range(count)]
    return AtlasSurface(degree, spans, vertices, quads, edge_points, face_points, weights)
