"""An atlas: tensor-product NURBS patches on a quad layout, meeting on shared borders.

A whole object (a statue, a bust) is no height field over one domain. The atlas
covers it with ``F`` quadrilateral patches laid on a quad mesh (the *layout*: ``V``
corners, ``F`` quads), in the manner of Eck and Hoppe, *Automatic reconstruction of
B-spline surfaces of arbitrary topological type* (SIGGRAPH 1996): every quad
``(a, b, c, d)`` carries one patch

``C_f(u, v) = Σ_i Σ_j N_i(u) N_j(v) w_ij P_ij / Σ_i Σ_j N_i(u) N_j(v) w_ij``,
``(u, v) ∈ [0, 1]²``,

of degree ``d`` in both directions on the clamped uniform knot vector of ``s``
spans (The NURBS Book eq. 4.2 per patch; ``n = s + d`` control points per side).
Corner ``a`` is ``(u, v) = (0, 0)``, ``b`` is ``(1, 0)``, ``c`` is ``(1, 1)``, ``d`` is
``(0, 1)``; ``u`` runs from ``a`` to ``b``, ``v`` from ``a`` to ``d``, so a
counter-clockwise quad seen from outside has its normal ``C_u × C_v`` outward.

Control points are stored once and shared (``P[i][j]``, ``i`` along ``u``):

* the corner ``P[0][0]`` of every patch meeting at a layout vertex is ``vertices[k]``;
* the ``n - 2`` interior points of a border row are the layout *edge*'s points, stored
  from the edge's lower vertex index to its higher and read reversed by the patch whose
  side runs the other way;
* the ``(n - 2)²`` interior points ``P[1..n-2][1..n-2]`` belong to the patch alone.

A clamped B-spline's border curve depends only on its border row of control points and
weights (The NURBS Book §3.4, end-point interpolation and the boundary curves of a
tensor-product surface), so two patches sharing a row are the *same curve* along their
common side: the atlas is watertight by construction, before any zippering. Edges are
numbered by :func:`atlas_edges`, the one rule every reader and writer uses.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

from .surface import NurbsSurface

Vec3 = tuple[float, float, float]

MAX_ATLAS_DEGREE = 3
MAX_ATLAS_SPANS = 16
MAX_ATLAS_QUADS = 1 << 16
MAX_ATLAS_VERTICES = 1 << 17

# The four sides of a patch, as (start corner, end corner) positions in the quad tuple,
# in the order they are listed everywhere (side 0: v = 0, side 1: u = 1, side 2: v = 1,
# side 3: u = 0), each oriented along increasing u or v.
SIDES = ((0, 1), (1, 2), (3, 2), (0, 3))


@functools.lru_cache(maxsize=32)
def ring_positions(n: int) -> tuple[tuple[int, int], ...]:
    """``(i, j)`` of the ``4 (n - 1)`` points on the border ring of an ``(n, n)`` grid, in the
    order :meth:`AtlasSurface.border_slots` numbers them: the corners ``(0, 0), (n-1, 0),
    (n-1, n-1), (0, n-1)``, then the inner points of sides 0..3 (``SIDES``: ``v = 0``, ``u =
    1``, ``v = 1``, ``u = 0``), each along increasing ``u`` or ``v``."""
    if isinstance(n, bool) or not isinstance(n, int) or n < 2:
        raise ValueError(f"a grid has n >= 2 points per side, got {n!r}")
    last, run = n - 1, range(1, n - 1)
    return ((0, 0), (last, 0), (last, last), (0, last), *((t, 0) for t in run),
            *((last, t) for t in run), *((t, last) for t in run), *((0, t) for t in run))


@functools.lru_cache(maxsize=16)
def _flat_order(n: int) -> tuple[int, ...]:
    """For each slot ``i n + j`` of an ``(n, n)`` grid, row-major, where its control point is
    in a patch's border ring (:func:`ring_positions` order) followed by its interior points
    (row-major): once per ``n``, for :meth:`AtlasSurface.flat_patch_indices`."""
    ring = {slot: k for k, slot in enumerate(i * n + j for i, j in ring_positions(n))}
    inner = n - 2
    return tuple(ring[i * n + j] if (i * n + j) in ring
                 else len(ring) + (i - 1) * inner + (j - 1)
                 for i in range(n) for j in range(n))


@dataclass(frozen=True)
class EdgeTable:
    """The layout's undirected edges and how every patch side maps onto them.

    Attributes
    ----------
    edges : list of (int, int)
        Edge ``e`` joins vertices ``edges[e] = (lo, hi)``, ``lo < hi``; sorted.
    sides : list of 4-tuples of (int, bool)
        ``sides[f][k] = (e, reversed)``: side ``k`` of patch ``f`` (``SIDES``) lies on edge
        ``e``; ``reversed`` when the side runs from ``hi`` to ``lo``.
    faces : list of list of (int, int)
        ``faces[e]``: the ``(patch, side)`` pairs on edge ``e``, one on an open border,
        two inside the surface.
    """

    edges: list[tuple[int, int]]
    sides: list[tuple[tuple[int, bool], ...]]
    faces: list[list[tuple[int, int]]]

    @property
    def border_edges(self) -> list[int]:
        """Edges with a single patch: the atlas's open border (a bust's cut base)."""
        return [e for e, pairs in enumerate(self.faces) if len(pairs) == 1]


def atlas_edges(quads: Sequence[Sequence[int]]) -> EdgeTable:
    """Number the undirected edges of a quad layout; the one rule readers and writers share.

    Parameters
    ----------
    quads : sequence of 4 ints, length F
        Vertex indices ``(a, b, c, d)`` of each quad.

    Returns
    -------
    EdgeTable

    Raises
    ------
    ValueError
        A degenerate quad (a repeated vertex), a side used twice in the same direction
        (inconsistent orientation) or an edge shared by more than two quads (not a
        2-manifold layout).
    """
    directed: dict[tuple[int, int], tuple[int, int]] = {}
    for f, quad in enumerate(quads):
        if len(quad) != 4 or len(set(quad)) != 4:
            raise ValueError(f"quads[{f}] = {tuple(quad)!r}: a quad needs 4 distinct vertices")
        for k, (s, t) in enumerate(SIDES):
            a, b = quad[s], quad[t]
            # a patch side runs along increasing u or v; its traversal direction around
            # the quad (a->b->c->d) is reversed on sides 2 and 3
            around = (a, b) if k < 2 else (b, a)
            if around in directed:
                g, _ = directed[around]
                raise ValueError(
                    f"quads {g} and {f} both run edge {around[0]}->{around[1]} the same way: "
                    "the layout's quads must be consistently oriented")
            directed[around] = (f, k)
    keys = sorted({(min(a, b), max(a, b)) for a, b in directed})
    index = {key: e for e, key in enumerate(keys)}
    faces: list[list[tuple[int, int]]] = [[] for _ in keys]
    sides: list[list[tuple[int, bool]]] = [[(0, False)] * 4 for _ in quads]
    for f, quad in enumerate(quads):
        for k, (s, t) in enumerate(SIDES):
            a, b = quad[s], quad[t]
            e = index[(min(a, b), max(a, b))]
            faces[e].append((f, k))
            sides[f][k] = (e, a > b)
    for e, pairs in enumerate(faces):
        if len(pairs) > 2:
            raise ValueError(f"edge {keys[e]} is shared by {len(pairs)} quads "
                             f"{[f for f, _ in pairs]}; at most 2 are accepted (a 2-manifold)")
    return EdgeTable(keys, [tuple(s) for s in sides], faces)


def _check_points(name: str, points: Sequence[Sequence[float]], count: int) -> list[Vec3]:
    if len(points) != count:
        raise ValueError(f"{name} has {len(points)} points; the layout needs {count}")
    out: list[Vec3] = []
    for k, p in enumerate(points):
        if len(p) != 3:
            raise ValueError(f"{name}[{k}] has {len(p)} coordinates; 3 are needed")
        x, y, z = float(p[0]), float(p[1]), float(p[2])
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            raise ValueError(f"{name}[{k}] = {(x, y, z)} is not finite")
        out.append((x, y, z))
    return out


@dataclass(frozen=True)
class AtlasSurface:
    """Patches of degree ``d`` with ``s`` spans per side on a quad layout (module docstring).

    Attributes
    ----------
    degree : int
        ``d``, 1..3, in ``u`` and ``v`` alike.
    spans : int
        ``s``, 1..16: uniform spans per patch side; ``n = s + d`` control points per side.
    vertices : list of (x, y, z), length V
        Corner control points, one per layout vertex.
    quads : list of (a, b, c, d), length F
    edge_points : list of (x, y, z), length ``E (n - 2)``
        Edge ``e``'s interior border points at ``e (n - 2) .. (e + 1)(n - 2) - 1``, from the
        edge's lower vertex to its higher (``atlas_edges``).
    face_points : list of (x, y, z), length ``F (n - 2)²``
        Patch ``f``'s interior point ``P[i][j]`` at ``f (n-2)² + (i - 1)(n - 2) + (j - 1)``.
    weights : list of float or None
        ``w > 0`` per control point in the order vertices, edge points, face points;
        ``None``: all 1 (polynomial patches).
    """

    degree: int
    spans: int
    vertices: list[Vec3]
    quads: list[tuple[int, int, int, int]]
    edge_points: list[Vec3]
    face_points: list[Vec3]
    weights: list[float] | None = None

    def __post_init__(self) -> None:
        if isinstance(self.degree, bool) or not isinstance(self.degree, int) \
                or not 1 <= self.degree <= MAX_ATLAS_DEGREE:
            raise ValueError(f"degree must be an int in 1..{MAX_ATLAS_DEGREE}, got {self.degree!r}")
        if isinstance(self.spans, bool) or not isinstance(self.spans, int) \
                or not 1 <= self.spans <= MAX_ATLAS_SPANS:
            raise ValueError(f"spans must be an int in 1..{MAX_ATLAS_SPANS}, got {self.spans!r}")
        if not 1 <= len(self.quads) <= MAX_ATLAS_QUADS:
            raise ValueError(f"an atlas has 1..{MAX_ATLAS_QUADS} quads, got {len(self.quads)}")
        if not 4 <= len(self.vertices) <= MAX_ATLAS_VERTICES:
            raise ValueError(f"an atlas has 4..{MAX_ATLAS_VERTICES} vertices, "
                             f"got {len(self.vertices)}")
        quads = []
        for f, quad in enumerate(self.quads):
            q = tuple(int(k) for k in quad)
            if len(q) != 4 or not all(0 <= k < len(self.vertices) for k in q):
                raise ValueError(f"quads[{f}] = {tuple(quad)!r}: 4 indices into the "
                                 f"{len(self.vertices)} vertices are needed")
            quads.append(q)
        table = atlas_edges(quads)
        inner = self.side - 2
        object.__setattr__(self, "quads", quads)
        object.__setattr__(self, "vertices", _check_points("vertices", self.vertices,
                                                           len(self.vertices)))
        object.__setattr__(self, "edge_points", _check_points(
            "edge_points", self.edge_points, len(table.edges) * inner))
        object.__setattr__(self, "face_points", _check_points(
            "face_points", self.face_points, len(quads) * inner * inner))
        object.__setattr__(self, "_table", table)
        if self.weights is not None:
            weights = [float(w) for w in self.weights]
            if len(weights) != self.control_point_count:
                raise ValueError(f"weights has {len(weights)} values; the atlas has "
                                 f"{self.control_point_count} control points")
            for k, w in enumerate(weights):
                if not (math.isfinite(w) and w > 0.0):
                    raise ValueError(f"weights[{k}] = {w}; weights must be finite and > 0")
            object.__setattr__(self, "weights", None if all(w == 1.0 for w in weights)
                               else weights)

    @classmethod
    def _of_checked(cls, degree: int, spans: int, vertices: list[Vec3],
                    quads: list[tuple[int, int, int, int]], edge_points: list[Vec3],
                    face_points: list[Vec3], weights: list[float] | None,
                    table: EdgeTable) -> AtlasSurface:
        """An atlas of parts already checked, without checking them again: ``quads``
        (tuples of ints), the points (``(x, y, z)`` float tuples) and the weights (finite,
        positive floats) taken from a checked atlas, ``table`` the ``atlas_edges`` of
        ``quads``. For ``client_py.atlas_mesh.atlas_parts``, which cuts the patches around
        the viewer's groups out of the whole atlas at every refinement: its own edge table is
        what the cut needs anyway, and checking every point again would cost as much. The
        weights are dropped when all are 1, as the checked constructor drops them."""
        atlas = object.__new__(cls)
        if weights is not None and all(w == 1.0 for w in weights):
            weights = None
        for name, value in (("degree", degree), ("spans", spans), ("vertices", vertices),
                            ("quads", quads), ("edge_points", edge_points),
                            ("face_points", face_points), ("weights", weights),
                            ("_table", table)):
            object.__setattr__(atlas, name, value)
        return atlas

    @property
    def side(self) -> int:
        """``n = s + d``, control points per patch side."""
        return self.spans + self.degree

    @property
    def edges(self) -> EdgeTable:
        """The layout's edge table (``atlas_edges`` of ``quads``)."""
        return self._table  # type: ignore[attr-defined]

    @functools.cached_property
    def patches_around(self) -> tuple[tuple[int, ...], ...]:
        """Per layout vertex, the patches that have it as a corner, in increasing order
        (made once per atlas: the viewer asks for rings of patches at every refinement)."""
        around: list[list[int]] = [[] for _ in self.vertices]
        for f, quad in enumerate(self.quads):
            for k in quad:
                around[k].append(f)
        return tuple(map(tuple, around))

    @functools.cached_property
    def edge_numbers(self) -> dict[tuple[int, int], int]:
        """``{(lo, hi): e}``: the number of each layout edge (made once per atlas, for the
        parts cut out of it at every refinement, ``client_py.atlas_mesh.atlas_parts``)."""
        return {key: e for e, key in enumerate(self.edges.edges)}

    @property
    def control_point_count(self) -> int:
        """``V + E (n - 2) + F (n - 2)²``: every control point once."""
        return len(self.vertices) + len(self.edge_points) + len(self.face_points)

    @property
    def knots(self) -> list[float]:
        """The clamped uniform knot vector of every patch side, ``n + d + 1`` knots on [0, 1]."""
        d, s = self.degree, self.spans
        return [0.0] * d + [i / s for i in range(s + 1)] + [1.0] * d

    def patch_indices(self, f: int) -> list[list[int]]:
        """Index of ``P[i][j]`` of patch ``f`` in the order vertices, edge points, face points.

        Returns
        -------
        list of list of int, shape ``(n, n)``
            ``i`` along ``u``, ``j`` along ``v``; the same numbering as ``weights``.
        """
        n, flat = self.side, self.flat_patch_indices(f)
        return [flat[i * n : (i + 1) * n] for i in range(n)]

    def flat_patch_indices(self, f: int) -> list[int]:
        """:meth:`patch_indices` row-major in one list: ``P[i][j]``'s at ``i n + j``."""
        n, inner = self.side, self.side - 2
        base = len(self.vertices) + len(self.edge_points) + f * inner * inner
        ring_then_inner = self.border_slots(f, n) + list(range(base, base + inner * inner))
        return list(map(ring_then_inner.__getitem__, _flat_order(n)))

    def border_slots(self, f: int, n: int) -> list[int]:
        """The shared slot of each point of the border ring of an ``(n, n)`` grid on patch
        ``f``, in the order of :func:`ring_positions`: the one rule numbering what
        neighbouring patches share, for the control points (``n = s + d``,
        :meth:`patch_indices`) and for any grid of coefficients laid on the patches the same
        way (a detail level's, ``client_py.atlas_detail``).

        Corner ``(0, 0), (n-1, 0), (n-1, n-1), (0, n-1)`` is slot ``quads[f][0..3]`` (the
        layout vertex); the ``n - 2`` inner points of side ``k`` (``SIDES``, from its start
        corner) are slots ``V + e (n - 2) + t``, ``t = 0..n-3`` from edge ``e``'s lower vertex
        to its higher, so reversed where the side runs ``hi -> lo``. ``n >= 2``.
        """
        if isinstance(n, bool) or not isinstance(n, int) or n < 2:
            raise ValueError(f"a grid has n >= 2 points per side, got {n!r}")
        inner, first = n - 2, len(self.vertices)
        slots = list(self.quads[f])
        for e, reverse in self.edges.sides[f]:
            start = first + e * inner
            slots.extend(range(start + inner - 1, start - 1, -1) if reverse
                         else range(start, start + inner))
        return slots

    def control_point(self, index: int) -> Vec3:
        """The control point with ``index`` in the order vertices, edge points, face points."""
        n_vertices, n_edge = len(self.vertices), len(self.edge_points)
        if index < n_vertices:
            return self.vertices[index]
        if index < n_vertices + n_edge:
            return self.edge_points[index - n_vertices]
        return self.face_points[index - n_vertices - n_edge]

    def patch_surface(self, f: int) -> NurbsSurface:
        """Patch ``f`` as a ``NurbsSurface`` on ``[0, 1]²`` (for evaluation and checks)."""
        if isinstance(f, bool) or not isinstance(f, int) or not 0 <= f < len(self.quads):
            raise ValueError(f"patch index must be an int in 0..{len(self.quads) - 1}, got {f!r}")
        grid = self.patch_indices(f)
        points = [[self.control_point(k) for k in row] for row in grid]
        weights = None if self.weights is None else [[self.weights[k] for k in row]
                                                     for row in grid]
        knots = self.knots
        return NurbsSurface((self.degree, self.degree), (knots, knots), points, weights)
