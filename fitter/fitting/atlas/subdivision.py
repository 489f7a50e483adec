"""Subdivision surfaces as linear maps, and a control mesh fitted to a scan.

A smooth base, measured by ``python -m bench subdivision`` (docs/benchmarks.md, "Session
28: a smooth base, measured"); the smooth base (``.smooth``) fits its control points with
:func:`fit_control_points`. The patches base is bicubic
patches that join C0, about nine stored control points a patch. A subdivision surface
stores one point per control vertex and is smooth by its rules: C2 where the control mesh
is regular, C1 at its extraordinary vertices.

Each step is linear in the control points, so ``k`` steps are one sparse matrix ``S``
(``S_k ... S_1``) and the drawn mesh is ``S V`` with its own triangles:

* **Catmull-Clark** (Catmull & Clark, *Recursively generated B-spline surfaces on arbitrary
  topological meshes*, CAD 1978), any polygons (one step makes every face a quad; on a
  regular quad mesh the steps are the uniform bicubic B-spline's knot insertion, Lane &
  Riesenfeld 1980):

  - face point: the mean of the face's vertices;
  - edge point: ``(a + b + F_1 + F_2) / 4`` with ``F_i`` the two face points;
  - vertex point of valence ``k``: ``(Q + 2 R + (k - 3) v) / k``, ``Q`` the mean of its faces'
    points, ``R`` the mean of its edges' midpoints.

* **Loop** (Loop, *Smooth subdivision surfaces based on triangles*, MS thesis, Utah 1987),
  triangles (each into four; on a regular mesh the quartic box spline):

  - edge point: ``3/8 (a + b) + 1/8 (c + d)``, ``c, d`` opposite the edge;
  - vertex point: ``(1 - k beta) v + beta sum(neighbours)``,
    ``beta = (5/8 - (3/8 + cos(2 pi / k) / 4)^2) / k``.

Borders (Hoppe et al., *Piecewise smooth surface reconstruction*, SIGGRAPH 1994): an edge
with one face (or more than two) is a crease; its edge point is its midpoint, and a vertex
on exactly two such edges follows the cubic B-spline curve, ``(a + 6 v + b) / 8`` of its
two border neighbours; a vertex on one or more than two is a corner and stays, as does a
vertex in no face. So the border of the drawn mesh is a curve of the control border alone,
as a scan's open rim needs.

:func:`fit_control_points` moves the control points so that the drawn surface fits a scan:
least squares over every scan point's closest point on the drawn mesh (rows ``S``
interpolated at it), rows pulling every drawn vertex toward its closest scan point (so no
part of the drawn surface drifts where no scan point holds it) and an umbrella smoothing
of the control mesh, the closest points found again each round (as the paper's parameter
correction, Ćurković, Vučina et al., and the atlas's base fit do).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from ..spd import node_order, spd_lu
from .measure import barycentric, closest_points_on_mesh

SCHEMES = ("catmull-clark", "loop")
MAX_LEVELS = 6
#: a point whose residual is this many times longer along the drawn surface than across it
#: lies beyond the surface's border (:func:`beyond_border_weights`)
BEYOND_BORDER = 2.0


@dataclass(frozen=True)
class Corners:
    """Every corner of a polygon mesh, face after face and in each face's order: its
    ``vertex``, its ``face``, the ``next`` and ``prev`` corners of its face, and the face
    sizes (``size``, per face)."""

    vertex: np.ndarray
    face: np.ndarray
    next: np.ndarray
    prev: np.ndarray
    size: np.ndarray


def corners_of(n: int, faces: Sequence[np.ndarray]) -> Corners:
    """The :class:`Corners` of ``faces``: arrays ``(m, k)`` of ``k``-gons (``k >= 3``; an
    empty array is no face), numbered array after array, of vertices ``0..n-1``.

    Raises
    ------
    ValueError
        A block that is not ``(m, k)`` with ``k >= 3``, or a vertex index outside ``0..n-1``.
    """
    vertex, face, nxt, prev, size = [], [], [], [], []
    first = corner = 0
    for block in faces:
        block = np.asarray(block)
        if block.ndim != 2 or (block.size and block.shape[1] < 3) or \
                (block.size and not np.issubdtype(block.dtype, np.integer)):
            raise ValueError(f"faces must be (m, k) integer arrays with k >= 3, got shape "
                             f"{block.shape} of {block.dtype}")
        if not block.size:
            continue
        m, k = block.shape
        if block.min() < 0 or block.max() >= n:
            raise ValueError(f"faces use vertices {block.min()}..{block.max()}; there are {n}")
        at = corner + np.arange(m * k).reshape(m, k)
        vertex.append(block.reshape(-1).astype(np.int64))
        face.append(np.repeat(np.arange(first, first + m), k))
        nxt.append(np.roll(at, -1, axis=1).reshape(-1))
        prev.append(np.roll(at, 1, axis=1).reshape(-1))
        size.append(np.full(m, k))
        first, corner = first + m, corner + m * k
    empty = np.zeros(0, np.int64)
    return Corners(*(np.concatenate(a) if a else empty for a in (vertex, face, nxt, prev, size)))


@dataclass(frozen=True)
class Edges:
    """The undirected edges of a polygon mesh of ``size`` vertices, sorted by
    ``lo * size + hi``: edge ``e`` joins ``lo[e] < hi[e]`` and borders ``uses[e]`` faces;
    ``of_corner[c]`` is the edge from corner ``c`` to the next corner of its face."""

    size: int
    lo: np.ndarray
    hi: np.ndarray
    of_corner: np.ndarray
    uses: np.ndarray

    @property
    def crease(self) -> np.ndarray:
        """Edges that do not join exactly two faces: a border (or a non-manifold edge)."""
        return self.uses != 2

    def ends(self) -> tuple[np.ndarray, np.ndarray]:
        """Each edge from both ends: ``(vertex, other end)``, ``2 E`` of each."""
        return np.concatenate([self.lo, self.hi]), np.concatenate([self.hi, self.lo])

    def valence(self) -> np.ndarray:
        """Edges at each vertex, shape ``(size,)``."""
        return np.bincount(self.ends()[0], minlength=self.size)

    def creases_at(self) -> np.ndarray:
        """Crease edges at each vertex, shape ``(size,)``."""
        return np.bincount(self.ends()[0][np.tile(self.crease, 2)], minlength=self.size)

    def smooth_vertices(self) -> np.ndarray:
        """Vertices with edges and no crease edge, which take a scheme's interior rule."""
        return (self.creases_at() == 0) & (self.valence() > 0)

    def endpoint_rows(self, inner: float, crease: float) -> sp.csr_matrix:
        """``(E, size)``: each edge's two ends weighed ``inner`` (an edge of two faces) or
        ``crease``."""
        E = len(self.lo)
        weight = np.tile(np.where(self.crease, crease, inner), 2)
        return sp.csr_matrix((weight, (np.tile(np.arange(E), 2), self.ends()[0])),
                             shape=(E, self.size))


def edges_of(n: int, corners: Corners) -> Edges:
    """The :class:`Edges` of a mesh of ``n`` vertices from its ``corners``."""
    a, b = corners.vertex, corners.vertex[corners.next]
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    keys, of_corner, uses = np.unique(lo * n + hi, return_inverse=True, return_counts=True)
    return Edges(n, keys // n, keys % n, of_corner.reshape(-1), uses)


def _vertex_rows(edges: Edges, interior: tuple[np.ndarray, np.ndarray]) -> sp.csr_matrix:
    """The vertex points ``(n, n)``: ``interior = (own weight, each neighbour's weight)``
    per vertex for a vertex of edges and no crease edge; the cubic B-spline curve's ``(a +
    6 v + b) / 8`` on exactly two crease edges; kept (weight 1) otherwise."""
    n = edges.size
    ends, other = edges.ends()
    smooth, curve = edges.smooth_vertices(), edges.creases_at() == 2
    own, weight = interior
    diagonal = np.where(smooth, own, np.where(curve, 0.75, 1.0))
    inner = smooth[ends]
    along = curve[ends] & np.tile(edges.crease, 2)
    rows = np.concatenate([np.arange(n), ends[inner], ends[along]])
    cols = np.concatenate([np.arange(n), other[inner], other[along]])
    vals = np.concatenate([diagonal, weight[ends[inner]], np.full(along.sum(), 0.125)])
    return sp.csr_matrix((vals, (rows, cols)), shape=(n, n))


def catmull_clark_step(n: int, faces: Sequence[np.ndarray]) -> tuple[sp.csr_matrix, np.ndarray]:
    """One Catmull-Clark step (module docstring).

    Parameters
    ----------
    n : int
        Control points.
    faces : sequence of ndarray, shape (m, k)
        Arrays of ``k``-gons, e.g. ``[quads, triangles]`` (:func:`corners_of`).

    Returns
    -------
    S : scipy.sparse.csr_matrix, shape (n + E + F, n)
        The new points from the old: the vertex points, then the edge points (in
        :func:`edges_of`' order), then the face points (faces numbered array after array).
    quads : ndarray, shape (C, 4)
        One quad per corner ``(corner, edge point after it, face point, edge point before
        it)``, turning as its face did.
    """
    corners = corners_of(n, faces)
    F = len(corners.size)
    face_points = sp.csr_matrix((1.0 / corners.size[corners.face],
                                 (corners.face, corners.vertex)), shape=(F, n))
    edges = edges_of(n, corners)
    E = len(edges.lo)
    inner = ~edges.crease[edges.of_corner]  # the corner's edge joins two faces
    beside = sp.csr_matrix((np.full(inner.sum(), 0.25), (edges.of_corner[inner],
                                                         corners.face[inner])), shape=(E, F))
    edge_points = edges.endpoint_rows(0.25, 0.5) + beside @ face_points
    # a smooth vertex of valence k: (Q + 2 R + (k - 3) v) / k = Q / k + (k - 2) / k v + R' / k
    # with R' the mean of its neighbours (2 R = v + R')
    k = np.maximum(edges.valence(), 1).astype(float)
    vertex_points = _vertex_rows(edges, ((k - 2) / k, 1 / k ** 2))
    at_vertex = np.bincount(corners.vertex, minlength=n).astype(float)
    mean_face = sp.csr_matrix((1 / at_vertex[corners.vertex], (corners.vertex, corners.face)),
                              shape=(n, F))
    smooth = sp.diags(np.where(edges.smooth_vertices(), 1 / k, 0.0))
    vertex_points = vertex_points + smooth @ mean_face @ face_points
    S = sp.vstack([vertex_points, edge_points, face_points]).tocsr()
    quads = np.stack([corners.vertex, n + edges.of_corner, n + E + corners.face,
                      n + edges.of_corner[corners.prev]], axis=1)
    return S, quads


def loop_step(n: int, triangles: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """One Loop step (module docstring) of ``n`` control points and ``triangles (m, 3)``.

    Returns
    -------
    S : scipy.sparse.csr_matrix, shape (n + E, n)
        The vertex points, then the edge points (in :func:`edges_of`' order).
    triangles : ndarray, shape (4 m, 3)
        Each triangle's four, turning as it did.

    Raises
    ------
    ValueError
        ``triangles`` not of shape ``(m, 3)`` (Loop's rules are for triangles).
    """
    triangles = np.asarray(triangles)
    if triangles.ndim != 2 or triangles.shape[1] != 3:
        raise ValueError(f"Loop subdivides triangles: an (m, 3) array, got shape "
                         f"{triangles.shape}")
    corners = corners_of(n, [triangles])
    edges = edges_of(n, corners)
    E = len(edges.lo)
    inner = ~edges.crease[edges.of_corner]  # corner c's edge c -> next: prev is opposite it
    opposite = sp.csr_matrix((np.full(inner.sum(), 0.125), (
        edges.of_corner[inner], corners.vertex[corners.prev][inner])), shape=(E, n))
    k = np.maximum(edges.valence(), 1).astype(float)
    beta = (0.625 - (0.375 + np.cos(2 * np.pi / k) / 4) ** 2) / k
    S = sp.vstack([_vertex_rows(edges, (1 - k * beta, beta)),
                   edges.endpoint_rows(0.375, 0.5) + opposite]).tocsr()
    e = (n + edges.of_corner).reshape(-1, 3)  # edges (a, b), (b, c), (c, a)
    a, b, c = corners.vertex.reshape(-1, 3).T
    out = [(a, e[:, 0], e[:, 2]), (e[:, 0], b, e[:, 1]), (e[:, 2], e[:, 1], c),
           (e[:, 0], e[:, 1], e[:, 2])]
    return S, np.concatenate([np.stack(t, axis=1) for t in out])


@dataclass(frozen=True)
class Subdivided:
    """``levels`` steps of ``scheme`` from the control mesh ``faces`` of ``control``
    points: the drawn points are ``matrix @ V`` (``matrix`` of shape ``(points,
    control)``), its triangles ``triangles`` (a Catmull-Clark quad ``(a, b, c, d)`` as ``(a,
    b, c), (a, c, d)``)."""

    scheme: str
    levels: int
    control: int
    faces: tuple[np.ndarray, ...]
    matrix: sp.csr_matrix
    triangles: np.ndarray


def subdivided(n: int, faces: Sequence[np.ndarray], levels: int,
               scheme: str = "catmull-clark") -> Subdivided:
    """``levels`` (1..:data:`MAX_LEVELS`) steps of ``scheme`` (:data:`SCHEMES`) of ``n``
    control points and ``faces`` (for Loop, one array of triangles).

    Raises
    ------
    ValueError
        An unknown scheme, a level count out of range, faces Loop cannot take, or faces
        :func:`corners_of` refuses.
    """
    if scheme not in SCHEMES:
        raise ValueError(f"scheme must be one of {', '.join(SCHEMES)}, got {scheme!r}")
    if isinstance(levels, bool) or not isinstance(levels, int | np.integer) or \
            not 1 <= levels <= MAX_LEVELS:
        raise ValueError(f"levels must be an int in 1..{MAX_LEVELS}, got {levels!r}")
    faces = tuple(np.asarray(block) for block in faces)
    matrix = sp.identity(n, format="csr")
    if scheme == "loop":
        if len(faces) != 1:
            raise ValueError(f"Loop subdivides one array of triangles, got {len(faces)} arrays")
        current = faces[0]
        for _ in range(levels):
            step, current = loop_step(matrix.shape[0], current)
            matrix = (step @ matrix).tocsr()
        return Subdivided(scheme, levels, n, faces, matrix, current)
    current = list(faces)
    for _ in range(levels):
        step, quads = catmull_clark_step(matrix.shape[0], current)
        matrix, current = (step @ matrix).tocsr(), [quads]
    quads = current[0]
    return Subdivided(scheme, levels, n, faces, matrix,
                      np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]]))


def umbrella(n: int, faces: Sequence[np.ndarray]) -> sp.csr_matrix:
    """The umbrella operator ``v - mean(neighbours)`` of a polygon mesh, ``(n, n)`` (a
    vertex in no face: 0)."""
    edges = edges_of(n, corners_of(n, faces))
    ends, other = edges.ends()
    adjacency = sp.csr_matrix((np.ones(len(ends)), (ends, other)), shape=(n, n))
    valence = edges.valence()
    return (sp.diags((valence > 0).astype(float))
            - sp.diags(1.0 / np.maximum(valence, 1)) @ adjacency).tocsr()


def beyond_border_weights(residual: np.ndarray, normal: np.ndarray, tangential: float
                          ) -> np.ndarray:
    """Each point's weight ``t_i`` of its distance along the surface in
    :func:`fit_control_points`: ``tangential``, or 1 where the point lies beyond the drawn
    surface's border, its residual ``r_i = p_i - foot_i`` more than :data:`BEYOND_BORDER`
    times as long along the surface as along the normal ``n_i``.

    Inside the surface a closest point's residual is along the normal, and the squared
    distance there is the point-to-plane one. Past a border it is the distance to the border
    curve, as Wang, Pottmann & Liu take the point distance at a curve's end: weighed as the
    interior's, the tangential part (``t^2`` of it) let a border stay short of the scan's (a
    bust's cut base drawn up to 0.7 % of the diagonal above it).
    """
    along = np.einsum("ic,ic->i", residual, normal)
    across = np.linalg.norm(residual - along[:, None] * normal, axis=1)
    return np.where(across > BEYOND_BORDER * np.abs(along), 1.0, tangential)


def fit_control_points(points: np.ndarray, control: np.ndarray, surface: Subdivided,
                       scan_faces: np.ndarray | None = None, rounds: int = 10,
                       smoothing: float = 1e-4, reverse: float = 0.3, tangential: float = 0.1,
                       far_reach: float | None = None, far_weight: float = 1.0
                       ) -> tuple[np.ndarray, list[float]]:
    """Control points whose drawn surface (``surface.matrix @ V``) fits ``points``.

    Each round finds every point's closest point on the drawn mesh, with the unit normal
    ``n_i`` of its triangle there, and solves for the three coordinates together (``3 n``
    unknowns, one sparse Cholesky of the normal equations: :func:`..spd.spd_lu`)

        ``min sum_i [(n_i . (B_i V - p_i))^2 + t_i^2 |B_i V - p_i|^2]
              + r^2 (N/M) sum_j |S_j V - q_j|^2 + s (N/n) |U V|^2``

    ``B_i`` the row of ``S`` interpolated at point ``i``'s closest point (barycentric):
    the distance along the normal weighs ``1 + t_i^2``, along the surface ``t_i^2`` (``t``,
    or 1 for a point past the drawn border: :func:`beyond_border_weights`), a squared
    distance minimisation (Wang, Pottmann & Liu, *Fitting B-spline curves to point clouds by
    curvature-based squared distance minimization*, ACM TOG 2006) which converges where
    fitting the closest points alone (``t`` large) slides along the surface; ``q_j`` the
    scan's closest point to drawn vertex ``j``; ``U`` the control mesh's umbrella operator
    (:func:`umbrella`), which also holds the combinations of control points the rules
    cancel (on a mesh whose vertices all have valence 3, the alternating one); ``N``,
    ``M``, ``n`` the counts of points, drawn vertices and control points. The normal matrix
    is assembled by coordinate blocks, ``(c, d)`` (``3 x 3`` blocks of ``n x n``) being

        ``sum_i (n_ic n_id + delta_cd t_i^2) B_i^T B_i
              + delta_cd (r^2 (N/M) S^T S + s (N/n) U^T U)``,

    the last two the same every round (computed once).

    Far drawn vertices. Where the control mesh bridges a crease or a wedge (the Bali mask's
    stand-in across a sharp inner fold of the carving by a tusk), the drawn surface
    stands off the scan as a fin that few points reach, and the uniform reverse term
    (``r``) holds it against the points' pull and the umbrella only partly. With
    ``far_reach`` (a share of the points' bounding-box diagonal), from the second round on
    a drawn vertex farther than it from its ``q_j`` has its reverse row weighed
    ``far_weight`` times (its squared term ``far_weight^2`` times): the other half of the
    two-sided distance, where it is large, as the patches base's ``fit.reverse_rows`` does.
    Not in the first round: its start, the control mesh itself, lies off the scan where the
    fit will not (the bunny's level 0 had 0.9 % more bytes and RMS with them).

    Parameters
    ----------
    points : ndarray, shape (N, 3)
    control : ndarray, shape (n, 3)
        The control points to start from.
    surface : Subdivided
        The drawn surface of the control mesh (:func:`subdivided`).
    scan_faces : ndarray, shape (T, 3), optional
        The scan's triangles over ``points``: ``q_j`` is the closest point on them; without,
        the nearest of ``points``.
    rounds : int
    smoothing, reverse, tangential : float
        ``s > 0``, ``r >= 0``, ``t >= 0``.
    far_reach, far_weight : float
        ``None`` (no far rows) or ``> 0``; ``>= 1``.

    Returns
    -------
    control : ndarray, shape (n, 3)
    history : list of float
        The RMS distance of the points to the drawn mesh before each round and after the
        last (``rounds + 1`` values).

    Raises
    ------
    ValueError
        Shapes that do not agree, no point, or a weight out of range.
    """
    points = np.asarray(points, float)
    V = np.asarray(control, float).copy()
    S, triangles = surface.matrix, surface.triangles
    n, m = len(V), S.shape[0]
    if V.shape != (surface.control, 3) or points.ndim != 2 or points.shape[1] != 3 or \
            not len(points):
        raise ValueError(f"control must be ({surface.control}, 3) and points (N > 0, 3), got "
                         f"{V.shape} and {points.shape}")
    if not smoothing > 0 or not reverse >= 0 or not tangential >= 0 or rounds < 1:
        raise ValueError(f"smoothing must be > 0, reverse and tangential >= 0, rounds >= 1; "
                         f"got {smoothing}, {reverse}, {tangential}, {rounds}")
    if (far_reach is not None and not far_reach > 0) or not far_weight >= 1:
        raise ValueError(f"far_reach must be None or > 0 and far_weight >= 1; got "
                         f"{far_reach}, {far_weight}")
    smooth = umbrella(n, surface.faces) * np.sqrt(smoothing * len(points) / n)
    pull = np.sqrt(len(points) / m) * reverse
    diagonal = float(np.linalg.norm(np.ptp(points, axis=0)))
    # the reverse and smoothing rows are the same every round: their part of the normal
    # matrix once
    fixed = (pull ** 2 * (S.T @ S) + smooth.T @ smooth).tocsr()
    pull_rows = (pull ** 2 * S.T).tocsr()
    # the unknowns are all x, all y, all z; a point's row B_i couples about the control
    # points a drawn vertex's row does, so the reverse rows' pattern orders every round
    order = node_order(fixed, 3)
    nearest = cKDTree(points) if scan_faces is None else None
    history = []

    def closest(V):
        drawn = S @ V
        distance, tri, foot = closest_points_on_mesh(points, drawn, triangles)
        history.append(float(np.sqrt(np.mean(distance ** 2))))
        return drawn, tri, foot

    drawn, tri, foot = closest(V)
    for round_ in range(rounds):
        corners = [drawn[triangles[tri, k]] for k in range(3)]
        w = barycentric(foot, *corners)
        # B_i: the rows of the triangle's corners weighed by the barycentric coordinates
        rows = (sp.csr_matrix((w.reshape(-1), triangles[tri].reshape(-1),
                               np.arange(0, w.size + 1, 3)), shape=(len(w), m)) @ S).tocsr()
        normal = np.cross(corners[1] - corners[0], corners[2] - corners[0])
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
        if nearest is None:
            target = closest_points_on_mesh(drawn, points, scan_faces)[2]
        else:
            target = points[nearest.query(drawn)[1]]
        weight = beyond_border_weights(points - foot, normal, tangential) ** 2
        reverse_matrix, far_rhs = fixed, np.zeros((n, 3))
        if far_reach is not None and round_ > 0:  # far vertices' rows weigh far_weight^2
            far = np.flatnonzero(np.linalg.norm(drawn - target, axis=1) > far_reach * diagonal)
            rows_far = S[far]
            extra = (far_weight ** 2 - 1) * pull ** 2
            reverse_matrix = (fixed + extra * (rows_far.T @ rows_far)).tocsr()
            far_rhs = extra * (rows_far.T @ target[far])
        rows_t = rows.T.tocsr()
        blocks = [[None] * 3 for _ in range(3)]
        for c in range(3):
            for d in range(c, 3):
                share = normal[:, c] * normal[:, d] + (weight if c == d else 0.0)
                blocks[c][d] = rows_t @ (sp.diags(share) @ rows)
                blocks[d][c] = blocks[c][d].T
            blocks[c][c] = blocks[c][c] + reverse_matrix
        along = np.einsum("ic,ic->i", normal, points)
        rhs = np.concatenate([rows_t @ (normal[:, c] * along + weight * points[:, c])
                              + pull_rows @ target[:, c] + far_rhs[:, c] for c in range(3)])
        # single-column supernodes are too narrow for these factors (some 400 non-zeros a
        # column; minimum degree on all 3 n unknowns: 1.5 s a round on the bunny against 2.3)
        lu = spd_lu(sp.bmat(blocks, format="csr")[order][:, order], permc_spec="NATURAL",
                    single_columns=False)
        solution = np.empty(3 * n)
        solution[order] = lu.solve(rhs[order])
        V = solution.reshape(3, n).T
        drawn, tri, foot = closest(V)
    return V, history
