"""A clean, consistently oriented triangle surface of a scan: the atlas's starting point.

A mesh scan is used as it is after cleaning (MeshLab's filters through ``pymeshlab``):
duplicate vertices merged, null and duplicate faces dropped, non-manifold edges and vertices
split (their faces kept, never removed), faces oriented coherently per connected piece and
each closed piece turned outward (positive signed volume). Every piece with area is kept; a
piece becomes patches of its own.

A point cloud (a range scan, a ``.conf`` registration) gets a surface by screened Poisson
reconstruction (Kazhdan & Hoppe, *Screened Poisson surface reconstruction*, ToG 2013)
through ``open3d``, on the cloud voxel-thinned to at most ``max_cloud_points``. Poisson
closes every surface, so the result is trimmed: a triangle with a vertex farther than
``trim_spacings`` point spacings (the median distance to the 4th nearest point) from every
scan point is cut away, and a range
scan stays open. Small islands that trimming leaves (reconstruction bubbles, under
``MIN_ISLAND_SHARE`` of the faces) are dropped and counted in ``repairs``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..io.scan import Scan, ScanError
from ..io.thin import thin_to_count
from .mesh_edges import MeshEdges, mesh_edges, vertex_fans

MIN_CLOUD_POINTS = 100
MIN_ISLAND_SHARE = 0.002
SPLIT_ROUNDS = 3  # rounds of splitting non-manifold elements before a fin's face is removed
LAYOUT_POISSON_DEPTH = 6  # the layout stand-in's octree (layout_stand_in)
LAYOUT_TRIM = 0.015  # ... trimmed where it reaches this share of the diagonal off the surface
LAYOUT_TRIM_BESIDE = 0.0075  # ... or this share with the surface beside it (stand_in_far)
BESIDE_COS = 0.7  # "beside": the offset to the surface at over acos(0.7) = 45.6° from the normal
MAX_LAYOUT_HANDLES = 8  # more handles than this: the layout is decimated from the stand-in
NORMAL_NEIGHBOURS = 20  # points of a cloud's local PCA normal
ORIENT_NEIGHBOURS = 10  # neighbours of a point in the orientation graph (orient_normals)
NO_AREA = 1e-12  # a triangle whose |(b - a) x (c - a)| is at most this x diagonal^2 has no area


class SurfaceError(ScanError):
    """A scan that gives no usable triangle surface (too few points, no area, a surface
    that stays non-manifold or non-orientable after repair); the message says which."""


@dataclass(frozen=True)
class ScanSurface:
    """A 2-manifold, consistently oriented triangle surface of a scan.

    Attributes
    ----------
    vertices : ndarray, shape (V, 3), float64
    faces : ndarray, shape (M, 3), int64
        Counter-clockwise seen from outside (right-hand normal outward on closed pieces).
    origin : {'mesh', 'poisson'}
        The scan's own triangles, or a screened Poisson reconstruction of its points.
    pieces : int
        Connected pieces (all kept).
    repairs : dict
        What cleaning changed: counts of merged vertices, dropped faces, split non-manifold
        elements, flipped pieces, trimmed Poisson faces, dropped islands.
    """

    vertices: np.ndarray
    faces: np.ndarray
    origin: str
    pieces: int
    repairs: dict = field(default_factory=dict)

    @property
    def face_normals(self) -> np.ndarray:
        """Unit normals ``(b - a) × (c - a) / |…|``, shape (M, 3)."""
        return _unit_rows(self._cross())

    def sample(self, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """``count`` points spread over the triangles by area and their triangles' unit
        normals (:func:`area_samples`)."""
        return area_samples(self.vertices, self.faces, count, rng)

    @property
    def face_areas(self) -> np.ndarray:
        """Triangle areas, shape (M,)."""
        return 0.5 * np.linalg.norm(self._cross(), axis=1)

    @property
    def vertex_normals(self) -> np.ndarray:
        """Area-weighted unit vertex normals, shape (V, 3)."""
        cross = self._cross()
        normals = np.zeros_like(self.vertices)
        for k in range(3):
            np.add.at(normals, self.faces[:, k], cross)
        return _unit_rows(normals)

    @property
    def diagonal(self) -> float:
        """Bounding-box diagonal of the vertices."""
        return float(np.linalg.norm(np.ptp(self.vertices, axis=0)))

    def _cross(self) -> np.ndarray:
        tri = self.vertices[self.faces]
        return np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])


def area_samples(vertices: np.ndarray, faces: np.ndarray, count: int,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points spread over the triangles ``faces`` of ``vertices`` by area, and
    their triangles' unit normals, shapes ``(count, 3)``.

    Uniform barycentric samples ``a + r1 (b - a) + r2 (c - a)`` with ``(r1, r2)`` folded
    into the triangle (Turk, *Generating random points in triangles*, Graphics Gems 1990).
    """
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = np.linalg.norm(cross, axis=1)
    pick = rng.choice(len(faces), size=count, p=area / area.sum())
    r1, r2 = rng.random(count), rng.random(count)
    fold = r1 + r2 > 1
    r1[fold], r2[fold] = 1 - r1[fold], 1 - r2[fold]
    t = tri[pick]
    points = t[:, 0] + r1[:, None] * (t[:, 1] - t[:, 0]) + r2[:, None] * (t[:, 2] - t[:, 0])
    return points, cross[pick] / np.maximum(area[pick], 1e-300)[:, None]


def _unit_rows(a: np.ndarray) -> np.ndarray:
    length = np.linalg.norm(a, axis=1, keepdims=True)
    return a / np.where(length > 0, length, 1.0)


def face_pieces(faces: np.ndarray, n_vertices: int) -> tuple[int, np.ndarray]:
    """Connected pieces of a triangle mesh through shared vertices.

    Returns
    -------
    count : int
    labels : ndarray, shape (M,), int
        The piece of every face.
    """
    m = len(faces)
    rows = np.repeat(np.arange(m), 3)
    graph = coo_matrix((np.ones(3 * m), (rows, faces.reshape(-1) + m)),
                       shape=(m + n_vertices, m + n_vertices))
    count, labels = connected_components(graph, directed=False)
    face_labels = labels[:m]
    _, face_labels = np.unique(face_labels, return_inverse=True)
    return int(face_labels.max() + 1) if m else 0, face_labels


def unique_pairs(pairs: np.ndarray, **options) -> np.ndarray | tuple:
    """``np.unique(pairs, axis=0, **options)`` of integer pairs ``(M, 2)`` with values in
    ``0..n-1`` (edges: vertex indices): the same rows, in the same lexicographic order, and
    the same ``return_index``/``return_inverse``/``return_counts`` arrays, from the 1-D keys
    ``a n + b``, whose sort is many times faster than the rows' (:func:`manifold_problems`'
    two on the 15-scan Happy Buddha's 205,170-face Poisson surface: 0.10 s, not 2.22 s)."""
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    n = int(pairs.max(initial=-1)) + 1
    found = np.unique(pairs[:, 0] * n + pairs[:, 1], **options)
    keys, rest = (found[0], found[1:]) if isinstance(found, tuple) else (found, ())
    rows = np.stack([keys // n, keys % n], axis=1) if n else np.zeros((0, 2), np.int64)
    return (rows, *rest) if rest else rows


def without_triangles(vertices: np.ndarray, triangles: np.ndarray, drop: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The mesh without the triangles ``drop (T,)`` of bool and the vertices no triangle
    left uses (renumbered in order)."""
    kept = np.asarray(triangles, np.int64)[~np.asarray(drop, bool)]
    used = np.zeros(len(vertices), bool)
    used[kept.reshape(-1)] = True
    remap = np.cumsum(used) - 1
    return np.asarray(vertices, np.float64)[used], remap[kept]


def without_area(vertices: np.ndarray, faces: np.ndarray, diagonal: float) -> np.ndarray:
    """Which triangles have no area: ``|(b - a) × (c - a)| <= NO_AREA · diagonal²``, shape
    ``(M,)`` bool (``diagonal``: the surface's, so that the rule does not depend on the
    units)."""
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return np.linalg.norm(cross, axis=1) <= NO_AREA * diagonal ** 2


def _without_arealess_pieces(vertices: np.ndarray, faces: np.ndarray
                             ) -> tuple[np.ndarray, np.ndarray, int]:
    """The mesh without its pieces whose every triangle has no area (:func:`without_area`),
    and without the vertices no face uses; with the count of pieces dropped.

    Such a piece is what splitting leaves of a folded pair of faces: Forstmann's fast
    quadric collapse (``stream.working_mesh``) of Stanford Lucy subdivided to 3.2 M vertices
    made two pairs of opposite faces on the same three vertices, 10⁻¹⁶ of the diagonal²
    in area; MeshLab keeps one face of each, splits it off its neighbours, and the lone
    face, with no area, made every layout of the surface fail."""
    diagonal = float(np.linalg.norm(np.ptp(vertices, axis=0))) if len(vertices) else 0.0
    flat = without_area(vertices, faces, diagonal)
    if not flat.any():  # then every piece has area
        return vertices, faces, 0
    count, labels = face_pieces(faces, len(vertices))
    arealess = np.bincount(labels, weights=~flat, minlength=count) == 0
    if not arealess.any():
        return vertices, faces, 0
    return (*without_triangles(vertices, faces, arealess[labels]), int(arealess.sum()))


def border_edges(faces: np.ndarray) -> np.ndarray:
    """The open border of a triangle surface: its undirected edges (``(B, 2)``, each sorted,
    in lexicographic order) that exactly one triangle uses."""
    faces = np.asarray(faces, np.int64)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]),
                    axis=1)
    unique, count = unique_pairs(edges, return_counts=True)
    return unique[count == 1]


def manifold_problems(faces: np.ndarray) -> dict:
    """Edges used by more than two faces, and edges two faces run the same way.

    Returns
    -------
    dict
        ``nonmanifold_edges``: undirected edges in > 2 faces; ``misoriented_edges``: directed
        edges used twice (two neighbours disagree on orientation); ``border_edges``: edges in
        one face (:attr:`.mesh_edges.MeshEdges.problems`).
    """
    return mesh_edges(faces).problems


def clean_as_it_is(vertices: np.ndarray, faces: np.ndarray) -> MeshEdges | None:
    """The :class:`.mesh_edges.MeshEdges` of a mesh that :func:`clean_mesh`'s MeshLab
    filters would leave exactly as it is, else ``None``: every vertex used, none at the
    position of another, every face with area (over ``NO_AREA`` x diagonal², so that none
    is left to :func:`_without_arealess_pieces` either) and three vertices no other face
    has, every edge in at most two faces run opposite ways, and one fan of faces at every
    vertex (:func:`.mesh_edges.vertex_fans`).

    A museum's mesh mostly is such a mesh: the dense vase's 2.24 M triangles are checked
    in about 2 s, against 10 s for the filters (which then change nothing)."""
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    if not len(faces) or np.bincount(faces.reshape(-1), minlength=len(vertices)).min() == 0:
        return None
    if without_area(vertices, faces, float(np.linalg.norm(np.ptp(vertices, axis=0)))).any():
        return None  # (a face with a repeated vertex has none either)
    ranked = vertices[np.lexsort(vertices.T[::-1])]
    if np.all(ranked[1:] == ranked[:-1], axis=1).any():
        return None
    table = mesh_edges(faces)
    if table.problems["nonmanifold_edges"] or table.problems["misoriented_edges"]:
        return None
    m = len(faces)
    across = np.where(table.twins >= 0, table.twins % m, -1 - np.arange(3 * m)).reshape(3, m)
    if np.any((across[0] == across[1]) & (across[1] == across[2])):
        return None  # two faces on the same three vertices, turned opposite ways
    if np.any(vertex_fans(table, len(vertices)) > 1):
        return None
    return table


def _signed_volumes(vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray,
                    count: int) -> np.ndarray:
    """``(1/6) Σ a · (b × c)`` per piece (the divergence theorem; positive when outward)."""
    tri = vertices[faces] - vertices.mean(axis=0)
    per_face = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6.0
    return np.bincount(labels, weights=per_face, minlength=count)


def _orient_outward(vertices: np.ndarray, faces: np.ndarray, table: MeshEdges | None = None
                    ) -> tuple[np.ndarray, int]:
    """Flip every closed piece whose signed volume is negative; returns faces and flips.
    ``table``: the faces' :func:`.mesh_edges.mesh_edges` when already made."""
    count, labels = face_pieces(faces, len(vertices))
    volume = _signed_volumes(vertices, faces, labels, count)
    open_edge = (table if table is not None else mesh_edges(faces)).border
    open_piece = np.zeros(count, bool)
    np.logical_or.at(open_piece, np.tile(labels, 3), open_edge)
    # an open piece (a bust's cut base, a range scan) keeps the orientation of its majority
    # of normals agreeing with the outward direction from the piece's centroid
    flip = np.zeros(count, bool)
    flip[~open_piece] = volume[~open_piece] < 0
    if open_piece.any():
        tri = vertices[faces]
        centroid = tri.mean(axis=1)
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        sums = np.zeros((count, 3))
        np.add.at(sums, labels, centroid * np.linalg.norm(normal, axis=1, keepdims=True))
        area = np.bincount(labels, weights=np.linalg.norm(normal, axis=1), minlength=count)
        piece_centre = sums / np.maximum(area, 1e-300)[:, None]
        outward = np.einsum("ij,ij->i", normal, centroid - piece_centre[labels])
        score = np.bincount(labels, weights=outward, minlength=count)
        flip[open_piece] = score[open_piece] < 0
    out = faces.copy()
    turn = flip[labels]
    out[turn] = out[turn][:, ::-1]
    return out, int(flip.sum())


def _meshset(vertices: np.ndarray, faces: np.ndarray):
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.ascontiguousarray(vertices, np.float64),
                               face_matrix=np.ascontiguousarray(faces, np.int32)))
    return ms


def _arrays(ms) -> tuple[np.ndarray, np.ndarray]:
    mesh = ms.current_mesh()
    return (np.asarray(mesh.vertex_matrix(), np.float64).copy(),
            np.asarray(mesh.face_matrix(), np.int64).copy())


def clean_mesh(vertices: np.ndarray, faces: np.ndarray, name: str = "scan"
               ) -> tuple[np.ndarray, np.ndarray, dict]:
    """Repair a triangle mesh into an oriented 2-manifold, keeping every face that has area.

    MeshLab's filters (:func:`_meshlab_repaired`), in order: remove duplicate vertices, null
    faces, duplicate faces; split non-manifold edges and vertices (``Split Vertices``: no
    face is removed); orient faces coherently; remove unreferenced vertices; skipped for a
    mesh they would leave as it is (:func:`clean_as_it_is`). Then each closed piece is
    turned outward (:func:`_orient_outward`). What ``SPLIT_ROUNDS`` rounds of splitting
    leave (a flap folded onto its neighbour, a third face on an edge, as quadric decimation
    makes near a trimmed stand-in's borders) loses the smallest faces of its edges
    (``Remove Faces``, counted in ``repairs['nonmanifold_faces_removed']``) before one more
    round. A piece left with no area at all (:func:`_without_arealess_pieces`) is dropped
    last and counted in ``repairs['pieces_without_area_dropped']``.

    Raises
    ------
    SurfaceError
        No face with area, or a mesh still non-manifold or non-orientable after the
        rounds of repair (e.g. a Möbius strip), naming the counts.
    """
    n_vertices, n_faces = len(vertices), len(faces)
    table = clean_as_it_is(vertices, faces)
    if table is not None:
        v, f = np.array(vertices, np.float64), np.array(faces, np.int64)
        after_dedup, removed = n_faces, 0
    else:
        v, f, after_dedup, removed = _meshlab_repaired(vertices, faces, name)
    split_faces, split_vertices = len(f), len(v)
    v, f, arealess = _without_arealess_pieces(v, f)
    if len(f) == 0:
        raise SurfaceError(f"{name}: none of the {n_faces} faces has area")
    f, flipped = _orient_outward(v, f, table if len(f) == split_faces else None)
    repairs = {"vertices_merged": int(n_vertices - split_vertices),
               "faces_dropped": int(n_faces - after_dedup),
               "faces_added_by_splits": int(split_faces + removed - after_dedup),
               "nonmanifold_faces_removed": int(removed), "pieces_flipped": flipped,
               "pieces_without_area_dropped": arealess}
    return v, f, repairs


def _meshlab_repaired(vertices: np.ndarray, faces: np.ndarray, name: str
                      ) -> tuple[np.ndarray, np.ndarray, int, int]:
    """:func:`clean_mesh`'s MeshLab filters: the repaired vertices and faces, the faces
    left after the duplicates went, and the faces ``Remove Faces`` took."""
    n_faces = len(faces)
    ms = _meshset(vertices, faces)
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_null_faces()
    ms.meshing_remove_duplicate_faces()
    ms.meshing_remove_unreferenced_vertices()
    after_dedup = ms.current_mesh().face_number()
    if after_dedup == 0:
        raise SurfaceError(f"{name}: none of the {n_faces} faces has area")
    problems: dict = {}
    import pymeshlab

    removed = 0
    for attempt in range(SPLIT_ROUNDS + 2):
        if attempt == SPLIT_ROUNDS:
            # what splitting leaves: a folded flap, a third face on an edge whose other two
            # already run opposite ways, which MeshLab's split leaves as it is (quadric
            # decimations of a trimmed Poisson stand-in fold so). MeshLab's ``Remove
            # Faces`` drops the smallest of an edge's faces until two remain; one more
            # round of splits and orientation follows
            before = ms.current_mesh().face_number()
            ms.meshing_repair_non_manifold_edges(method=0)
            removed += before - ms.current_mesh().face_number()
        else:
            ms.meshing_repair_non_manifold_edges(method=1)
        ms.meshing_repair_non_manifold_vertices()
        try:
            ms.meshing_re_orient_faces_coherently()
        except pymeshlab.PyMeshLabException:
            # MeshLab refuses to orient while a split left a non-manifold face; the next
            # round splits again, and the check after the loop names what remains
            pass
        ms.meshing_remove_unreferenced_vertices()
        v, f = _arrays(ms)
        problems = manifold_problems(f)
        if problems["nonmanifold_edges"] == 0 and problems["misoriented_edges"] == 0:
            return v, f, after_dedup, removed
    raise SurfaceError(
        f"{name}: after repair {problems['nonmanifold_edges']} edges still join more than "
        f"two faces and {problems['misoriented_edges']} edges have neighbours of opposite "
        "orientation (a non-orientable surface); a 2-manifold, orientable mesh is needed")


def _carried_agreement(points: np.ndarray, normals: np.ndarray, i: np.ndarray,
                       j: np.ndarray) -> np.ndarray:
    """The agreement of two neighbours' normals, shape ``(m,)``, symmetric in ``i, j``: of
    the plain ``n_i . n_j`` and the carried ``n_i . n_j - 2 (n_i . e)(n_j . e)`` (``e`` the
    unit vector from ``p_i`` to ``p_j``: ``n_i`` reflected in the plane bisecting
    ``p_i p_j``, carried along the circle through both points tangent to ``n_i``'s plane),
    the one of larger magnitude. Across a crease sharper than 90° the carried one is
    decisive; between noisy neighbours of one smooth sheet (a registration of range
    scans) the plain one is: the carried one alone left 6.4 % of the 15-scan Buddha's
    neighbour pairs inconsistent against 4.5 % for open3d's propagation."""
    e = points[j] - points[i]
    e /= np.maximum(np.linalg.norm(e, axis=1, keepdims=True), 1e-300)
    ni, nj = normals[i], normals[j]
    plain = np.einsum("ij,ij->i", ni, nj)
    carried = plain - 2.0 * np.einsum("ij,ij->i", ni, e) * np.einsum("ij,ij->i", nj, e)
    return np.where(np.abs(carried) > np.abs(plain), carried, plain)


def orient_normals(points: np.ndarray, normals: np.ndarray, k: int = ORIENT_NEIGHBOURS
                   ) -> np.ndarray:
    """Unoriented unit ``normals (N, 3)`` of a cloud turned to one consistent side, each
    connected piece outward on the whole.

    Hoppe et al. (*Surface reconstruction from unorganized points*, SIGGRAPH 1992, §3.3):
    the graph of each point's ``k`` nearest neighbours, its minimum spanning tree, and the
    orientation propagated along the tree from a root. The agreement of two neighbours is
    not always the plain ``n_i . n_j`` (which turns the wrong way across a crease sharper
    than 90°, a cone's rim against its base): :func:`_carried_agreement` also weighs the
    normal carried along the circular arc through both points (the idea of König &
    Gumhold, *Consistent propagation of normal orientations in point clouds*, VMV 2009)
    and takes the more decisive of the two: an edge costs ``1 - |c_ij|``, the tree prefers the
    edges whose relative orientation is least ambiguous, and ``n_j`` is flipped when
    ``c_ij < 0`` for its tree parent ``i``. The sign of each point relative to its piece's
    root is the product of the edge signs on its path, found by pointer doubling
    (``log2`` of the tree's depth vectorised passes). Last, each piece of the graph is
    turned so that ``sum_i n_i . (p_i - centroid) >= 0`` (outward on a closed piece, an
    open scan towards the side it bulges to).

    ``open3d``'s ``orient_normals_consistent_tangent_plane(12)`` took 70 s of a 30,000-point
    cone's fit; this takes well under a second for 10^5 points (scipy's k-d tree, minimum
    spanning tree and breadth-first order).

    Parameters
    ----------
    points : ndarray, shape (N, 3)
    normals : ndarray, shape (N, 3)
        Unit normals of either sign (a local PCA's least-variance direction).
    k : int
        Neighbours per point in the graph.

    Returns
    -------
    ndarray, shape (N, 3)
        ``normals`` with some rows negated.
    """
    from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree

    points = np.asarray(points, np.float64)
    normals = np.asarray(normals, np.float64)
    count = len(points)
    if count < 2:
        return normals.copy()
    k = min(k, count - 1)
    _, near = cKDTree(points).query(points, k=k + 1)
    i = np.repeat(np.arange(count), k)
    j = near[:, 1:].reshape(-1)
    keep = i != j  # duplicates of a point may list it among its own neighbours
    i, j = i[keep], j[keep]
    cost = 1.0 - np.abs(_carried_agreement(points, normals, i, j)) + 1e-9  # > 0: an edge
    tree = minimum_spanning_tree(coo_matrix((cost, (i, j)), shape=(count, count)).tocsr())
    pieces, piece = connected_components(tree, directed=False)
    # one breadth-first pass over every piece: a virtual root (index ``count``) joined to
    # the first point of each piece
    first = np.unique(piece, return_index=True)[1]
    tree = tree.tocoo()
    graph = coo_matrix((np.ones(len(tree.data) + pieces),
                        (np.r_[tree.row, np.full(pieces, count)], np.r_[tree.col, first])),
                       shape=(count + 1, count + 1)).tocsr()
    _, parent = breadth_first_order(graph, count, directed=False, return_predecessors=True)
    parent = parent[:count]
    sign = np.ones(count + 1)
    inner = parent != count
    sign[:count][inner] = np.where(
        _carried_agreement(points, normals, parent[inner], np.flatnonzero(inner)) < 0,
        -1.0, 1.0)
    hop = np.r_[parent, count]
    while np.any(hop[:count] != count):  # pointer doubling: sign to the root of the path
        sign, hop = sign * sign[hop], hop[hop]
    oriented = normals * sign[:count, None]
    centroid = np.zeros((pieces, 3))
    np.add.at(centroid, piece, points)
    centroid /= np.bincount(piece, minlength=pieces)[:, None]
    outward = np.bincount(piece, np.einsum("ij,ij->i", oriented, points - centroid[piece]),
                          minlength=pieces)
    return oriented * np.where(outward < 0, -1.0, 1.0)[piece, None]


def poisson_surface(points: np.ndarray, normals: np.ndarray | None, *, depth: int = 8,
                    trim_spacings: float = 2.0, max_cloud_points: int = 100_000,
                    name: str = "scan") -> tuple[np.ndarray, np.ndarray, dict]:
    """Screened Poisson surface of a cloud (Kazhdan & Hoppe 2013), trimmed to the scan.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
    normals : ndarray, shape (N, 3), or None
        Oriented normals; estimated when None (PCA of the ``NORMAL_NEIGHBOURS`` nearest
        points, then :func:`orient_normals`).
    depth : int
        Octree depth (a ``2^depth`` grid over the bounding cube).
    trim_spacings : float
        A triangle with a vertex farther than this many median point spacings from every
        point is removed.

    Returns
    -------
    vertices, faces, repairs
    """
    import open3d as o3d

    keep = thin_to_count(points, max_cloud_points)
    pts = points[keep]
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    if normals is not None and np.all(np.isfinite(normals[keep])) \
            and np.all(np.linalg.norm(normals[keep], axis=1) > 0):
        cloud.normals = o3d.utility.Vector3dVector(_unit_rows(np.asarray(normals[keep],
                                                                         np.float64)))
        estimated = False
    else:
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(NORMAL_NEIGHBOURS))
        cloud.normals = o3d.utility.Vector3dVector(
            orient_normals(pts, np.asarray(cloud.normals, np.float64)))
        estimated = True
    mesh, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
        cloud, depth=depth, n_threads=1)
    vertices = np.asarray(mesh.vertices, np.float64).copy()
    faces = np.asarray(mesh.triangles, np.int64).copy()
    if len(faces) == 0:
        raise SurfaceError(f"{name}: the Poisson reconstruction of {len(pts)} points is empty")
    tree = cKDTree(pts)
    # the spacing: the median distance to a point's 4th nearest neighbour, the grid step of
    # a regular range scan and robust to random sampling (whose nearest neighbour is often
    # much closer than the gaps between points)
    spacing = float(np.median(tree.query(pts, k=5)[0][:, 4]))
    far = tree.query(vertices)[0] > trim_spacings * spacing
    inside = ~far[faces].any(axis=1)
    trimmed = int(np.sum(~inside))
    faces = faces[inside]
    vertices, faces, islands, island_faces = without_islands(vertices, faces)
    if len(faces) == 0:
        raise SurfaceError(f"{name}: nothing of the Poisson surface is within "
                           f"{trim_spacings} point spacings of the points")
    repairs = {"cloud_points_used": int(len(pts)), "normals_estimated": estimated,
               "poisson_depth": depth, "median_spacing": spacing,
               "faces_trimmed": trimmed, "islands_dropped": islands,
               "island_faces_dropped": island_faces}
    return vertices, faces, repairs


def without_islands(vertices: np.ndarray, faces: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, int, int]:
    """The surface without its small pieces (under ``MIN_ISLAND_SHARE`` of the faces, or
    under 4 faces) and the vertices no face uses.

    Returns
    -------
    vertices, faces, islands, island_faces
        The kept surface (vertices renumbered), the count of dropped pieces and of their
        faces.
    """
    count, labels = face_pieces(faces, len(vertices))
    sizes = np.bincount(labels, minlength=count)
    big = sizes >= max(4, MIN_ISLAND_SHARE * len(faces))
    return (*without_triangles(vertices, faces, ~big[labels]), int(np.sum(~big)),
            int(sizes[~big].sum()))


def scan_surface(scan: Scan, *, poisson_depth: int = 8, trim_spacings: float = 2.0,
                 max_cloud_points: int = 100_000) -> ScanSurface:
    """The scan's triangle surface: its own triangles cleaned, or a trimmed Poisson surface.

    Raises
    ------
    ValueError
        ``poisson_depth`` outside 4..11 or ``trim_spacings`` not > 0.
    SurfaceError
        Fewer than ``MIN_CLOUD_POINTS`` points in a cloud, or a mesh that cannot be repaired.
    """
    if isinstance(poisson_depth, bool) or not isinstance(poisson_depth, int) \
            or not 4 <= poisson_depth <= 11:
        raise ValueError(f"poisson_depth must be an int in 4..11, got {poisson_depth!r}")
    if not trim_spacings > 0:
        raise ValueError(f"trim_spacings must be > 0, got {trim_spacings!r}")
    name = scan.source.get("name", "scan")
    if scan.faces is not None and len(scan.faces):
        vertices, faces, repairs = clean_mesh(scan.points, scan.faces, name)
        origin = "mesh"
    else:
        if scan.n_points < MIN_CLOUD_POINTS:
            raise SurfaceError(f"{name}: a point cloud of {scan.n_points} points; at least "
                               f"{MIN_CLOUD_POINTS} are needed to reconstruct a surface")
        vertices, faces, repairs = poisson_surface(
            scan.points, scan.normals, depth=poisson_depth, trim_spacings=trim_spacings,
            max_cloud_points=max_cloud_points, name=name)
        vertices, faces, cleaned = clean_mesh(vertices, faces, name)
        repairs.update(cleaned)
        origin = "poisson"
    count, _ = face_pieces(faces, len(vertices))
    return ScanSurface(vertices, faces, origin, count, repairs)


def handle_count(vertices: np.ndarray, faces: np.ndarray) -> int:
    """Handles (tunnels) of an oriented 2-manifold: the genus summed over its pieces.

    A piece with Euler characteristic ``χ = V - E + F`` and ``b`` border loops has genus
    ``g = (2 - χ - b) / 2``; the loops are the connected components of the border edges'
    graph (one loop per component on a manifold border).
    """
    count, labels = face_pieces(faces, len(vertices))
    vertex_piece = np.full(len(vertices), -1, np.int64)
    vertex_piece[faces.reshape(-1)] = np.repeat(labels, 3)  # pieces share no vertex
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    undirected, ucount = unique_pairs(np.sort(directed, axis=1), return_counts=True)
    border = undirected[ucount == 1]
    loops = np.zeros(count, np.int64)
    if len(border):
        graph = coo_matrix((np.ones(len(border)), (border[:, 0], border[:, 1])),
                           shape=(len(vertices), len(vertices)))
        _, vertex_loop = connected_components(graph, directed=False)
        _, first = np.unique(vertex_loop[border[:, 0]], return_index=True)
        np.add.at(loops, vertex_piece[border[first, 0]], 1)
    chi = (np.bincount(vertex_piece[vertex_piece >= 0], minlength=count)
           - np.bincount(vertex_piece[undirected[:, 0]], minlength=count)
           + np.bincount(labels, minlength=count))
    return int(np.sum(np.maximum(0, (2 - chi - loops) // 2)))


def stand_in_far(vertices: np.ndarray, faces: np.ndarray, surface: ScanSurface, reach: float,
                 beside: float | None = None) -> np.ndarray:
    """The triangles ``faces`` of ``vertices`` that reach farther than ``reach`` from the
    triangles of ``surface``, or (``beside`` given) farther than ``beside`` with the surface
    beside them; shape ``(M,)`` bool.

    Each triangle is probed at seven points ``p``: its corners, its edges' midpoints and its
    centroid, each with its exact closest point ``q`` on the surface
    (``measure.closest_points_on_mesh``). A coarse triangle whose corners all lie on the
    surface can still span a cavity the scan never saw (its middle hangs in the air); its
    probes find it. A probe has the surface beside it when its offset makes more than
    ``acos(BESIDE_COS)`` with the triangle's unit normal ``n``:
    ``|n · (q - p)| < BESIDE_COS |q - p|``. A Poisson membrane spanning a gap the scan left
    open (a tunnel narrower than the octree's cells, an open rim, the unseen space under an
    overhang) has its nearest surface at the gap's walls or rim, in its own plane; a coarse
    blob over a real part thinner than a cell has it below or above, along its normal.
    """
    from .measure import closest_points_on_mesh

    tri = np.asarray(vertices, np.float64)[faces]
    probes = np.concatenate([tri, 0.5 * (tri + tri[:, [1, 2, 0]]), tri.mean(axis=1)[:, None]],
                            axis=1)
    distance, _, closest = closest_points_on_mesh(probes.reshape(-1, 3), surface.vertices,
                                                  surface.faces)
    distance = distance.reshape(len(faces), 7)
    far = distance > reach
    if beside is not None:
        normal = _unit_rows(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
        far |= (distance > beside) & surface_beside(
            normal[:, None, :], closest.reshape(len(faces), 7, 3) - probes, distance)
    return np.any(far, axis=1)


def surface_beside(normal: np.ndarray, offset: np.ndarray, distance: np.ndarray
                   ) -> np.ndarray:
    """Whether the closest surface point lies *beside* a probe rather than along its
    normal: the offset ``q - p`` (``(..., 3)``, of length ``distance``) makes more than
    ``acos(BESIDE_COS)`` with the unit ``normal`` (``(..., 3)``, broadcast),
    ``|n · (q - p)| < BESIDE_COS |q - p|``. A sheet spanning a gap or an opening has its
    nearest surface at the gap's walls or rim, in its own plane; a sheet lifted off the
    surface (a coarse blob, a fin) has it below or above."""
    return np.abs(np.einsum("...j,...j->...", normal, offset)) < BESIDE_COS * distance


def layout_stand_in(surface: ScanSurface, *, depth: int = LAYOUT_POISSON_DEPTH,
                    trim: float = LAYOUT_TRIM, trim_beside: float | None = LAYOUT_TRIM_BESIDE,
                    samples: int = 100_000, seed: int = 0) -> ScanSurface:
    """A closed, low-genus stand-in of ``surface`` for the patch layout to be decimated from.

    A quad layout decimated from the surface keeps its topology (``atlas.layout``), so every
    handle needs triangles of its own: a genus-27 carved mask or a trimmed Poisson surface
    with dozens of small tunnels and holes gives long triangles that cross the object, and
    a base that folds through it. Here the handles narrower than the octree's cells close:
    screened Poisson (Kazhdan & Hoppe 2013, ``open3d``) of ``samples`` area-weighted points
    of the surface with their outward normals (:func:`area_samples`), on a coarse ``2^depth``
    grid over the bounding cube. On the Bali mask (a shell 1.2 % of the diagonal thick)
    ``depth = 6`` gives genus 3 and stays within 0.4 % of the diagonal of the scan.
    Poisson also closes what the scan leaves open (a statuette's unscanned underside, the
    cavity between a robe and the body), and the atlas draws whatever the layout covers, so
    a triangle reaching farther than ``trim`` of the diagonal from the surface
    (:func:`stand_in_far`: corners, edge midpoints and centroid) is cut away: the layout
    stays open where the scan is. On the 15-scan Happy Buddha (default fit, about 1140
    patches each) the share of the stand-in's area farther than 1 % of the diagonal from
    every scan point is 9.3 % at a 3 % trim of the vertices, 5.0 % at this 2 % trim and
    0.7 % at 1 %; at level 2 the drawn mesh's far area is 4.7 %, 4.1 % and 3.4 % and its
    largest distance to the scan 4.45 %, 4.05 % and 6.42 % of the diagonal. A 1 % trim cuts
    the stand-in open at the cavities between the arms and the body, and the coarse layout's
    decimation then spans the body's inside with triangles whose patches are drawn as walls
    through it (5.2 % of the diagonal off the surface at 379 triangles), which only
    ``fit.refined_within_budget`` splits. With it (session 11, level 0 of the default fit):
    a 2 % trim left the base's largest distance at 3.5 % and 3.9 % of its area farther than
    1 %, where the stand-in's 1–2 % skirts hang over the unscanned top of the pedestal under
    the robe and its open bottom; 1.5 % gives 2.85 % and 2.8 % at level 0 (99.73 % of the
    points within 0.5 %, RMS +2 %); 1 % gives 2.6 % and 1.7 % but 99.50 % within, RMS +14 %
    (more of the real surface's thin parts are cut with the membranes), 24 non-manifold
    edges in the welded drawn mesh, and 1.25 % a 384-triangle layout that does not decimate
    to a manifold (the fit falls back to 873 patches, 92.5 % within): hence 1.5 %. An open
    tube's stand-in (tests) keeps 1.8 % high rims over its ends at 2 %, 1.3 % at 1.5 %.
    What stays between 1 and 1.5 % is mostly membrane: caps' rims over open ends, skins
    over the unscanned pedestal top under the robe and over its open bottom, with the
    surface beside them (in their plane), where a coarse blob over a real thin part has it
    along its normal. So a triangle is also cut where a probe is farther than
    ``trim_beside`` (default :data:`LAYOUT_TRIM_BESIDE`, 0.75 %) with the surface beside it
    (:func:`stand_in_far`): the tube's rims go (0.06 % of the diagonal left), and on the
    Happy Buddha the stand-in's area farther than 1 % from every point falls from 2.65 % to
    0.40 % (a plain 1 % trim: 0.69 %). Its level 0 (session 12, three stand-in sample seeds,
    under load): drawn area farther than 1 % 2.57 / 4.45 / 3.22 % -> 1.62 / 1.94 / 1.20 %
    (the pedestal's top and bottom 1.2 / 1.1 / 1.2 % -> 0.25 / 0.27 / 0.18 %), largest
    distance 2.86 / 4.17 / 4.20 % -> 3.96 / 3.96 / 3.06 % (a sheet across the hole of the
    arch by the head: the stand-in keeps the hole, its decimated layout lost it, which
    ``fit.refine_far_base`` now opens again), points within 0.5 % 99.71 /
    99.61 / 99.36 -> 99.51 / 99.55 / 99.50 %, RMS 2.03 / 2.14 / 2.35 -> 2.17 / 2.25 / 2.19
    e-4, bytes 54.6 / 54.9 / 51.6 -> 57.3 / 52.9 / 56.2 KB; a plain 1 % trim gave far
    areas 1.38 / 2.16 / 2.20 % and 99.56 / 99.67 / 99.28 % within. The Bali mask's stand-in
    has nothing farther than 0.75 % beside its surface: it is the same (triangle for
    triangle) with or without this cut, and at every one of the trims above. Pieces under
    ``MIN_ISLAND_SHARE`` of the faces are then dropped, the rest
    repaired as a scan's mesh (:func:`clean_mesh`), and pieces under that share dropped
    again (MeshLab's split of a non-manifold vertex can cut off a sliver of two triangles,
    whose one layout triangle's patches quantise to a point). The trimmed stand-in is an
    oriented 2-manifold with open borders (17 border loops at 1 %); its quadric decimations
    (``layout.decimate``) can fold a flap over a border (a third face on an edge), which
    :func:`clean_mesh`'s last round removes: at 1 % that took the refused plain and weighted
    decimations from 48 to 1536 triangles from 8 of 12 (both at 192 and at 384, 576 and 1152
    patches) to 3. The working points stay the scan's: only the layout's triangles come from
    here.

    Raises
    ------
    SurfaceError
        The reconstruction is empty.
    """
    import open3d as o3d

    points, normals = surface.sample(samples, np.random.default_rng(seed))
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.normals = o3d.utility.Vector3dVector(normals)
    mesh, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
        cloud, depth=depth, n_threads=1)
    vertices = np.asarray(mesh.vertices, np.float64).copy()
    faces = np.asarray(mesh.triangles, np.int64).copy()
    if len(faces) == 0:
        raise SurfaceError("the layout's stand-in surface (Poisson of the surface) is empty")
    far = stand_in_far(vertices, faces, surface, trim * surface.diagonal,
                       None if trim_beside is None else trim_beside * surface.diagonal)
    faces = faces[~far]
    if len(faces) == 0:
        raise SurfaceError("nothing of the layout's stand-in surface lies near the surface")
    vertices, faces, _, _ = without_islands(vertices, faces)
    vertices, faces, repairs = clean_mesh(vertices, faces, "the layout's stand-in surface")
    # MeshLab's splits of non-manifold vertices can cut a sliver of two triangles off a
    # piece; decimated into one layout triangle, its patches quantise to a point
    vertices, faces, _, _ = without_islands(vertices, faces)
    pieces, _ = face_pieces(faces, len(vertices))
    repairs = {**repairs, "poisson_depth": depth, "trimmed_faces": int(far.sum()),
               "handles": handle_count(vertices, faces)}
    return ScanSurface(vertices, faces, "poisson", pieces, repairs)
