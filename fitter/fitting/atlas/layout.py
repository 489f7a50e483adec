"""The patch layout: a coarse triangle mesh of the surface, each triangle split into 3 quads.

Quadric error metric decimation (Garland & Heckbert, *Surface simplification using quadric
error metrics*, SIGGRAPH 1997; MeshLab's edge collapse through ``pymeshlab``) reduces the
surface to ``T`` triangles, preserving its topology (no collapse that changes the genus or
makes an edge non-manifold) and its open borders. Every triangle ``(a, b, c)`` is then cut
into three quads at its centroid ``g`` and edge midpoints ``m_ab, m_bc, m_ca`` (the midpoint
of a shared edge is shared): ``(a, m_ab, g, m_ca)``, ``(b, m_bc, g, m_ab)``,
``(c, m_ca, g, m_bc)``, counter-clockwise as the triangle is. This is a pure quad layout
of any manifold triangle mesh, ``F = 3 T`` quads, with valence-3 vertices at centroids
(the quadrangulation Eck & Hoppe 1996 reach through their triangle pairs is coarser but
needs a perfect matching; this split needs nothing).

:func:`flip_edges` swaps diagonals that cross a crease; where the fitted base still lies far
from the scan (a triangle bridging a groove or the gap between two sheets),
:func:`split_longest_edges` refines the layout (``atlas.fit.refine_far_base``).

The initial atlas puts every patch on its bilinear quad: control point ``P[i][j]`` is the
bilinear blend of the quad's corners at the Greville abscissae ``(ξ_i, ξ_j)``,
``ξ_i = (t_{i+1} + … + t_{i+d}) / d`` (The NURBS Book §9.2.2, the linear precision of
B-splines), so patch ``f`` *is* its planar quad ``B_f(u, v)`` and a point's bilinear
``(u, v)`` is its foot point on the initial atlas.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from client_py.atlas import AtlasSurface, atlas_edges

from ..io.scan import ScanError
from .surface import (
    ScanSurface,
    _arrays,
    _meshset,
    border_edges,
    clean_mesh,
    face_pieces,
    manifold_problems,
    unique_pairs,
    without_area,
    without_triangles,
)


class AtlasLayoutError(ScanError):
    """A decimated surface that is no oriented 2-manifold, so no quad layout of it exists."""


@dataclass(frozen=True)
class QuadLayout:
    """The layout: a decimated triangle mesh and its 3-quads-per-triangle split.

    Attributes
    ----------
    triangle_vertices : ndarray, shape (Vt, 3)
    triangles : ndarray, shape (T, 3), int64
    vertices : ndarray, shape (Vt + Et + T, 3)
        Layout corners: the triangle vertices, then the edge midpoints (edge order of
        ``triangle_edges``), then the centroids.
    quads : ndarray, shape (3 T, 4), int64
        Quad ``3 t + k`` is corner ``k`` of triangle ``t``: ``(x, m_xy, g, m_zx)`` for
        ``(x, y, z)`` the triangle rotated to start at its ``k``-th vertex.
    triangle_edges : ndarray, shape (Et, 2), int64
        Undirected triangle edges ``(lo, hi)``; edge ``e``'s midpoint is vertex ``Vt + e``.
    """

    triangle_vertices: np.ndarray
    triangles: np.ndarray
    vertices: np.ndarray
    quads: np.ndarray
    triangle_edges: np.ndarray

    @property
    def n_triangles(self) -> int:
        """``T``."""
        return len(self.triangles)


def decimate(surface: ScanSurface, target_triangles: int, weights: np.ndarray | None = None,
             boundary_weight: float = 1.0, require_area: bool = True
             ) -> tuple[np.ndarray, np.ndarray]:
    """The surface decimated to about ``target_triangles`` (topology and borders preserved).

    ``weights (V,)``, optional: per-vertex factors >= 1 on the quadric error of a collapse
    there (MeshLab's weighted simplification, the vertex quality), such as
    :func:`thin_part_weights`; a heavier vertex keeps more triangles around it. Equal
    weights (no thin part) are the plain decimation: MeshLab stretches the weights' range
    onto 1..100 and would divide by an empty one. ``boundary_weight``: MeshLab's weight of
    the quadric of the planes through each border edge, perpendicular to its triangle
    (``boundaryweight``; :func:`decimate_on_border` raises it). ``require_area=False``:
    triangles without area (:func:`.surface.without_area`) are let through, for an
    intermediate surface that is decimated again (``fit.PREDECIMATED_TRIANGLES``), not a
    layout.

    Raises
    ------
    ValueError
        ``target_triangles`` not an int >= 4, or ``weights`` not ``V`` finite numbers > 0.
    AtlasLayoutError
        The result is not an oriented 2-manifold (counts named).
    """
    if isinstance(target_triangles, bool) or not isinstance(target_triangles, int) \
            or target_triangles < 4:
        raise ValueError(f"target_triangles must be an int >= 4, got {target_triangles!r}")
    if weights is not None:
        weights = np.asarray(weights, np.float64)
        if weights.shape != (len(surface.vertices),) or not np.all(np.isfinite(weights)) \
                or np.any(weights <= 0):
            raise ValueError(f"weights must be {len(surface.vertices)} finite numbers > 0, "
                             f"got shape {weights.shape}")
        if np.ptp(weights) == 0:
            weights = None
    if len(surface.faces) <= target_triangles:
        return _checked(surface, surface.vertices.copy(), surface.faces.copy(), require_area)
    source = _pre_reduced(surface, target_triangles)
    if weights is not None and source[1] is not surface.faces:
        # reduced: each vertex takes the weight of the surface vertex nearest to it (the
        # weights are a smooth thickness field, far coarser than the fast pass's collapses)
        from scipy.spatial import cKDTree

        _, nearest = cKDTree(surface.vertices).query(source[0], workers=-1)
        weights = weights[nearest]
    # MeshLab's topology check also refuses every collapse of a border edge, so a scan with
    # holes (the bunny's base: 223 border edges) keeps its border at full resolution and the
    # coarse mesh becomes slivers fanned to it. Collapse freely first; keep the result when
    # it is an oriented 2-manifold with the input's pieces and Euler characteristics (its
    # topology), else decimate again with the topology check on.
    for preserve in (False, True):
        ms = _meshset(*source) if weights is None else _weighted_meshset(*source, weights)
        ms.meshing_decimation_quadric_edge_collapse(
            targetfacenum=target_triangles, preservetopology=preserve,
            preserveboundary=False, boundaryweight=boundary_weight, preservenormal=True,
            optimalplacement=False, planarquadric=True, qualitythr=0.5, autoclean=True,
            qualityweight=weights is not None)
        ms.meshing_remove_unreferenced_vertices()
        vertices, triangles = _arrays(ms)
        if preserve or _same_topology(surface, vertices, triangles):
            break
    problems = manifold_problems(triangles)
    if problems["nonmanifold_edges"] or problems["misoriented_edges"]:
        # a trimmed Poisson surface's many borders can pinch under the collapse even with
        # the topology check on (Buddha scan 0: 7 non-manifold edges at 144 triangles);
        # the same repair as the scan's (split, re-orient) makes it a layout again
        vertices, triangles, _ = clean_mesh(vertices, triangles, "the decimated surface")
    return _checked(surface, vertices, triangles, require_area)


#: a surface of more than PRE_REDUCE_FACES faces, and PRE_REDUCE_FACTOR times the target,
#: is first reduced to that many by the fast decimation (:func:`_pre_reduced`)
PRE_REDUCE_FACES = 200_000
PRE_REDUCE_FACTOR = 10


def _pre_reduced(surface: ScanSurface, target_triangles: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The surface for MeshLab to decimate: itself, or for a large one the same surface
    first reduced to ``max(PRE_REDUCE_FACES, PRE_REDUCE_FACTOR * target)`` faces by
    ``fast_simplification`` (Forstmann's fast quadric simplification: the same Garland &
    Heckbert error, a threshold sweep instead of a priority queue), kept only when it has
    the surface's topology (an oriented 2-manifold with its pieces' Euler characteristics).

    MeshLab's collapse costs about 30 µs a face removed here: a scan mesh of 2.24 M
    triangles (the example vase of 1.12 M vertices) took 65-73 s to reach the 20,000 of
    ``fit.PREDECIMATED_TRIANGLES``; reduced first to 200,000 in 2.8 s, MeshLab took 5.1 s
    more (docs/benchmarks.md, session 22). The fast pass makes the first nine tenths of
    the collapses, of edges far below the layout's scale; MeshLab's topology-checked
    decimation makes the rest, as for any smaller surface, and the border check
    (:func:`decimate_on_border`) is still against the surface itself. A weighted
    decimation (the thin parts' layouts) takes the reduction too, each of its vertices
    weighted as the surface vertex nearest to it: with the whole surface, MeshLab spent
    several minutes on each weighted layout of Stanford Lucy subdivided to 3.2 M vertices.
    """
    faces = surface.faces
    goal = max(PRE_REDUCE_FACES, PRE_REDUCE_FACTOR * target_triangles)
    if len(faces) <= 2 * goal:
        return surface.vertices, faces
    import fast_simplification

    try:
        vertices, reduced = fast_simplification.simplify(
            np.ascontiguousarray(surface.vertices, np.float64),
            np.ascontiguousarray(faces, np.int64), target_count=goal)
    except (ValueError, RuntimeError, MemoryError):  # a shortcut only: MeshLab takes it all
        return surface.vertices, faces
    vertices, reduced = np.asarray(vertices, np.float64), np.asarray(reduced, np.int64)
    if len(reduced) < 4 or not _same_topology(surface, vertices, reduced):
        return surface.vertices, faces
    return vertices, reduced


STRAY_REACH = 0.005  # a layout border vertex farther than this (x diagonal) off the border
BORDER_QUADRIC_WEIGHT = 30.0  # ... and :func:`decimate_on_border` decimates again at this


def border_strays(surface: ScanSurface, vertices: np.ndarray, triangles: np.ndarray) -> int:
    """How many vertices of the decimated surface's open border lie farther than
    ``STRAY_REACH`` of the diagonal from every border vertex of ``surface``.

    The decimation keeps vertices where they were (no optimal placement), so a layout
    border vertex still on the border IS a border vertex of ``surface``, at distance 0."""
    layout_border = np.unique(border_edges(triangles))
    if not len(layout_border):
        return 0
    own = np.unique(border_edges(surface.faces))
    if not len(own):
        return int(len(layout_border))
    from scipy.spatial import cKDTree

    distance, _ = cKDTree(surface.vertices[own]).query(vertices[layout_border])
    return int(np.sum(distance > STRAY_REACH * surface.diagonal))


def decimate_on_border(surface: ScanSurface, target_triangles: int,
                       weights: np.ndarray | None = None, require_area: bool = True
                       ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`decimate`, done again with the border's quadric weighted
    ``BORDER_QUADRIC_WEIGHT`` when a vertex of the layout's open border is left off the
    scan's border (:func:`border_strays`).

    The fit pulls the patches' border curves onto the scan's border (``fit.border_points``),
    so a layout border vertex that the decimation moved into the surface (an interior
    vertex collapsed onto a border one) pinches the drawn border into a notch up the
    surface: a hole where the scan is closed. Laurana's cut base at 768 triangles: 27 of
    its 30 border vertices up to 5.2 % of the diagonal off the border at MeshLab's
    default weight 1, none at 30, and 20 % of the drawn border (322 mm) off the scan's at
    both levels, then none (``bench.scoring.border_off_scan``), with the base's RMS of all
    points 0.2445 -> 0.2268 and its largest distance 0.90 -> 0.64 %. Only a layout that
    strays is redone: the bunny's border stays on at weight 1, and at 30 it gains a fan
    of slivers at its base's holes (84 triangles with an edge under a tenth of the median
    against 33), whose control points 9 bits no longer keep apart.
    """
    vertices, triangles = decimate(surface, target_triangles, weights,
                                   require_area=require_area)
    if border_strays(surface, vertices, triangles):
        vertices, triangles = decimate(surface, target_triangles, weights,
                                       BORDER_QUADRIC_WEIGHT, require_area)
    return vertices, triangles


THIN_POWER = 1.0  # weight (layout edge / thickness)^THIN_POWER (2: Lucy base 96.9 %, not 97.9)
THIN_CAP = 100.0  # ... at most this


def thickness(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Local thickness at every vertex: the distance along the inward normal to the
    surface's other side, ``inf`` where the ray leaves an open surface. Shape ``(V,)``.

    A ray cast from just under each vertex (``1e-5`` of the diagonal) along minus its
    area-weighted normal, against all triangles (``open3d``'s ``RaycastingScene``, Embree);
    the shape diameter function of Shapira, Shamir & Cohen-Or (*Consistent mesh
    partitioning and skeletonisation using the shape diameter function*, 2008) with its
    single central ray.
    """
    import open3d as o3d

    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, faces[:, k], cross)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = normals / np.where(length > 0, length, 1.0)
    diagonal = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)),
                        o3d.core.Tensor(faces.astype(np.uint32)))
    rays = np.concatenate([vertices - 1e-5 * diagonal * normals, -normals], axis=1)
    hit = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
    return np.where(np.isfinite(hit) & (length[:, 0] > 0), hit, np.inf).astype(np.float64)


def thin_part_weights(surface: ScanSurface, target_triangles: int) -> np.ndarray:
    """Per-vertex decimation weights that keep thin parts (ears, wings, drapery, fingers)
    in the layout: ``clip((ℓ / τ)^THIN_POWER, 1, THIN_CAP)``, shape ``(V,)``.

    ``τ`` is the local :func:`thickness` and ``ℓ = sqrt(4 A / (√3 T))`` the edge of an
    equilateral layout triangle when the surface's area ``A`` is cut into ``T`` of them.
    Plain quadric decimation measures the distance to the planes of the collapsed
    triangles only, so a sheet thinner than a layout triangle collapses onto a few
    triangles whose patches cannot hold both of its sides, and their points end up fitted
    to the other side (the bunny's ears: 4 % of the points farther than 0.5 % of the
    diagonal from the base). Weighting the quadric where ``τ < ℓ`` spends the same
    triangle count there instead of on flat parts.
    """
    if isinstance(target_triangles, bool) or not isinstance(target_triangles, int) \
            or target_triangles < 1:
        raise ValueError(f"target_triangles must be an int >= 1, got {target_triangles!r}")
    edge = math.sqrt(4.0 * float(surface.face_areas.sum()) / (math.sqrt(3.0) * target_triangles))
    tau = thickness(surface.vertices, surface.faces)
    ratio = edge / np.maximum(tau, 1e-300)
    return np.clip(ratio ** THIN_POWER, 1.0, THIN_CAP)


def _weighted_meshset(vertices: np.ndarray, faces: np.ndarray, weights: np.ndarray):
    """``_meshset`` of the mesh with ``weights`` (one per vertex) as its vertex quality.

    MeshLab's weighted simplification maps the quality range ``[min, max]`` affinely onto
    ``[1, 100]`` (vcglib's ``QualityWeightFactor``), so only the weights' ratios matter: the
    thinnest part always gets the full 100. (Pinning the range with an unreferenced vertex
    of quality :data:`THIN_CAP`, so that a weight means itself, made the bunny's base
    worse: 94.4 % of the points within 0.5 % of the diagonal against 99.5 %.)
    """
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.ascontiguousarray(vertices, np.float64),
                               face_matrix=np.ascontiguousarray(faces, np.int32),
                               v_scalar_array=np.ascontiguousarray(weights)))
    return ms


def triangle_samples(vertices: np.ndarray, triangles: np.ndarray, level: int
                     ) -> tuple[np.ndarray, np.ndarray]:
    """A barycentric grid of ``(level+1)(level+2)/2`` points in every triangle, shape
    ``(T (level+1)(level+2)/2, 3)``, triangle by triangle, and each point's triangle."""
    bary = np.array([(i, j, level - i - j) for i in range(level + 1)
                     for j in range(level + 1 - i)], np.float64) / level
    tri = np.asarray(vertices, np.float64)[triangles]  # (T, 3, 3)
    points = np.einsum("sk,tkc->tsc", bary, tri).reshape(-1, 3)
    return points, np.repeat(np.arange(len(triangles)), len(bary))


FLIP_SAMPLES = 4  # barycentric grid level of a layout triangle's samples (15 a triangle)
FLIP_PASSES = 6  # rounds of edge flips at most
FLIP_DISTANCE_GAIN = 0.7  # a flip that keeps the facing-away area must cut the energy to this
FLIP_DISTANCE_SLACK = 1.5  # one that lessens it may raise the energy up to this factor
FLIP_AWAY_REACH = 0.01  # a sample faces away when also this share of the diagonal away


def triangle_fidelity(surface: ScanSurface, vertices: np.ndarray, triangles: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """How closely each layout triangle lies on the surface: ``(energy (T,), away (T,))``.

    On a barycentric grid of level :data:`FLIP_SAMPLES` over triangle ``t`` (area ``A_t``,
    unit normal ``n_t``), with ``d_s`` the distance of sample ``s`` to the surface and
    ``m_s`` the normal of the surface triangle closest to it (``measure.closest_points_on_mesh``):
    ``energy_t = A_t mean_s d_s²`` and ``away_t = A_t mean_s [n_t · m_s < 0, d_s > ρ]``,
    the area of the triangle facing against the surface under it and farther from it than
    ``ρ``, :data:`FLIP_AWAY_REACH` of the diagonal. Where a thin shell folds over (the
    Bali mask's relief and back) a triangle near one side can be nearest to the other:
    with ``ρ = 0.5 %`` those flips raised the mask's RMS 1.7x (2.72e-4, 99.2 % of its
    points within 0.5 %); with 2 % the bunny's ear-root chords (2.4 % from the scan) stayed;
    at 1 % the mask has 1.29e-4 (99.94 %) and the bunny's base 0.61 % at most.
    """
    tri = vertices[triangles]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    normal = cross / np.maximum(2.0 * area, 1e-300)[:, None]
    d, m = triangle_distances(surface, vertices, triangles)
    facing = np.einsum("tsc,tc->ts", m, normal)
    energy = area * (d ** 2).mean(axis=1)
    far = d > FLIP_AWAY_REACH * surface.diagonal
    away = area * ((facing < 0) & far).mean(axis=1)
    return energy, away


def triangle_distances(surface: ScanSurface, vertices: np.ndarray, triangles: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Distance to the surface of every sample of each triangle's barycentric grid of level
    :data:`FLIP_SAMPLES`, shape ``(T, S)``, and the unit normal of the surface triangle
    closest to it, ``(T, S, 3)`` (``measure.closest_points_on_mesh``)."""
    from .measure import closest_points_on_mesh

    samples, _ = triangle_samples(vertices, triangles, FLIP_SAMPLES)
    d, nearest, _ = closest_points_on_mesh(samples, surface.vertices, surface.faces)
    return d.reshape(len(triangles), -1), surface.face_normals[nearest].reshape(
        len(triangles), -1, 3)


def flip_edges(surface: ScanSurface, vertices: np.ndarray, triangles: np.ndarray,
               passes: int = FLIP_PASSES) -> tuple[np.ndarray, int]:
    """The layout with edges flipped where the other diagonal lies on the surface better.

    Quadric decimation keeps each collapse close to the planes it removes, yet a coarse
    triangle can end up as a chord across a crease (the bunny's ear roots): facing against
    the surface under it, up to 2.4 % of the diagonal from it. Its patches then have no
    scan points to hold them and form a wall inside the object that no detail removes. As
    in Hoppe et al.'s mesh optimisation (*Mesh optimization*, SIGGRAPH 1993), whose edge
    swap is one of its three moves, the edge ``(a, b)`` between ``(a, b, c)`` and
    ``(b, a, d)`` becomes ``(c, d)``: triangles ``(c, a, d)``, ``(d, b, c)``, orientation
    kept, when the pair's facing-away area (:func:`triangle_fidelity`) falls and its energy
    grows by at most :data:`FLIP_DISTANCE_SLACK`, or the area does not grow and the energy
    falls below :data:`FLIP_DISTANCE_GAIN` of its value. A flip keeps the vertices, the
    triangle count, the manifold and its topology; ``(c, d)`` must not be an edge already
    and both new triangles must have area. Each pass flips the best non-overlapping pairs
    first, until a pass flips none or after ``passes``.

    Returns
    -------
    triangles : ndarray, shape (T, 3)
    flips : int
    """
    triangles = np.array(triangles, np.int64)
    vertices = np.asarray(vertices, np.float64)
    n_t = len(triangles)
    energy, away = triangle_fidelity(surface, vertices, triangles)
    total = 0
    for _ in range(passes):
        directed = np.stack([triangles, np.roll(triangles, -1, axis=1)], axis=2).reshape(-1, 2)
        owner = np.repeat(np.arange(n_t), 3)
        opposite = np.roll(triangles, -2, axis=1).reshape(-1)  # the vertex after the edge
        key = {(int(a), int(b)): i for i, (a, b) in enumerate(directed)}
        undirected = {(min(a, b), max(a, b)) for a, b in key}
        t_idx, s_idx, new_tris = [], [], []
        for i, (a, b) in enumerate(directed):
            j = key.get((int(b), int(a)))
            if j is None or j < i:
                continue
            c, d = int(opposite[i]), int(opposite[j])
            if c == d or (min(c, d), max(c, d)) in undirected:
                continue
            t_idx.append(owner[i])
            s_idx.append(owner[j])
            new_tris.append(((c, int(a), d), (d, int(b), c)))
        if not new_tris:
            break
        t_idx, s_idx = np.array(t_idx), np.array(s_idx)
        new_tris = np.array(new_tris, np.int64)  # (E, 2, 3)
        corners = vertices[new_tris]
        new_area = 0.5 * np.linalg.norm(np.cross(corners[..., 1, :] - corners[..., 0, :],
                                                 corners[..., 2, :] - corners[..., 0, :]),
                                        axis=-1)
        e_new, a_new = (x.reshape(-1, 2).sum(axis=1) for x in triangle_fidelity(
            surface, vertices, new_tris.reshape(-1, 3)))
        e_old = energy[t_idx] + energy[s_idx]
        a_old = away[t_idx] + away[s_idx]
        scale = 1e-9 * (e_old + a_old).max()
        better = (((a_new < a_old - scale) & (e_new <= FLIP_DISTANCE_SLACK * e_old))
                  | ((a_new <= a_old) & (e_new < FLIP_DISTANCE_GAIN * e_old)))
        better &= new_area.min(axis=1) > 1e-3 * new_area.sum(axis=1)  # no sliver
        # facing-away area first, then energy (lexicographic by scale)
        gain = (a_old - a_new) / max(float(a_old.max()), 1e-300) \
            + 1e-3 * (e_old - e_new) / max(float(e_old.max()), 1e-300)
        used = np.zeros(n_t, bool)
        flipped = 0
        for k in np.argsort(-gain):
            c, d = int(new_tris[k, 0, 0]), int(new_tris[k, 0, 2])
            if not better[k] or used[t_idx[k]] or used[s_idx[k]] \
                    or (min(c, d), max(c, d)) in undirected:
                continue
            undirected.add((min(c, d), max(c, d)))
            t, s = t_idx[k], s_idx[k]
            triangles[t], triangles[s] = new_tris[k]
            used[t] = used[s] = True
            flipped += 1
        if not flipped:
            break
        total += flipped
        energy, away = triangle_fidelity(surface, vertices, triangles)
    return triangles, total


MIN_WIDTH_SHARE = 0.1  # a layout triangle is narrow under this share of the median edge


def triangle_widths(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Smallest altitude of every triangle, ``w_t = 2 A_t / max_k |e_k|``, shape ``(T,)``.

    The width of the narrowest strip holding the triangle: small for a needle (one short
    edge) and for a cap (a vertex close to the opposite edge) alike; its three quads
    (:func:`quad_layout`) are then about ``w_t / 2`` across or narrower.
    """
    tri = np.asarray(vertices, np.float64)[np.asarray(triangles, np.int64)]
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    longest = np.linalg.norm(tri - np.roll(tri, -1, axis=1), axis=2).max(axis=1)
    return area2 / np.maximum(longest, 1e-300)


def collapse_narrow_triangles(surface: ScanSurface, vertices: np.ndarray,
                              triangles: np.ndarray, share: float | None = None
                              ) -> tuple[np.ndarray, np.ndarray, int]:
    """The layout with no triangle narrower than ``share`` of its median edge, where an edge
    collapse can remove it.

    Rule: with ``ℓ`` the median length of the layout's edges (measured once, before any
    collapse), while a triangle has its width :func:`triangle_widths` ``w_t < share ℓ``,
    the narrowest first, its shortest edge ``(a, b)`` is collapsed (Hoppe et al., *Mesh
    optimization*, SIGGRAPH 1993, the edge collapse; the half-edge collapse onto an end
    point): every triangle on ``b`` takes ``a`` instead, the two (one on a border) on
    ``(a, b)`` vanish, and ``a`` keeps its place on the surface (no new vertex off it). Of
    the two ways round, a border vertex is kept over an inner one; else the way whose
    changed triangles' smallest width is larger. A collapse is refused when it
    would change the topology or break the manifold: the link condition of Dey, Edelsbrunner
    et al. (*Topology preserving edge contraction*, 1999) -- the vertices next to both ``a``
    and ``b`` are exactly the apexes of the triangles on ``(a, b)`` --, an inner edge whose
    ends are both on a border (the border would pinch at one vertex), or a changed triangle
    that turns over (its normal against its old one) or loses its area, or one that
    leaves the surface: a sample of the changed triangles' barycentric grids of level
    :data:`FLIP_SAMPLES` farther from ``surface`` than :data:`FLIP_AWAY_REACH` of the
    diagonal and than every sample of the triangles it replaces (without it, collapses
    along the 15-scan Happy Buddha's stand-in's trimmed border over the head made a layout
    triangle span the arch, a sheet 3.9 % of the diagonal off the scan). A triangle none
    of whose edges may collapse is left as it is. A collapse keeps the Euler characteristic,
    the border loops and the orientation of every piece, so the layout stays an oriented
    2-manifold with its topology; each collapse is checked (the pieces' Euler
    characteristics, no non-manifold or misoriented edge) and undone if it changed them
    (on the 15-scan Buddha's stand-in, a trial layout of 86 triangles and 70 border edges
    had one the link condition let through).

    Why: quadric decimation keeps a triangle wherever its collapses would cost, such as at
    the small holes of a scan, whose borders the topology-preserving decimation keeps at full
    resolution. The bunny's 768-triangle weighted layout (session 14) has a median edge of
    5.05 % of the diagonal and triangles down to 0.03 % wide: at the small hole behind its
    head, (-0.058, 0.059, 0.022), and along the open bottom. ``base.tsa``'s 9-bit
    rounding (a step of about 0.12 % of the diagonal) gave control rows of 13 of their
    patches one code, those from triangles 0.011-0.098 of the median edge wide, and the
    welded level 0 had 5 non-manifold edges and 23 collapsed triangles there, the
    15-scan Happy Buddha's 2 and 6. ``share = 0.1`` is the smallest that removes all of
    them. Measured with the defaults against all scan points (``bench.bench_atlas.
    score_object``, session 14, load 8-15 on 2 cores, so fit times are not comparable;
    this change alone on main 7f30806, before: main as benchmarked in session 13; with the
    session's other changes, docs/benchmarks.md "Session 14"), before -> after: bunny 2,304 -> 2,082
    patches (the bottom's border fans collapsed), level-0 non-manifold edges 5 -> 0 and
    collapsed triangles 23 -> 0, level 0 88,749 -> 86,055 bytes, RMS 1.976e-5 -> 1.927e-5,
    largest distance of the drawn mesh to the scan 0.58 -> 0.79 % (at the bottom's border);
    15-scan Buddha 1,473 -> 1,428 patches, non-manifold 2 -> 0 but collapsed triangles 6 ->
    6 (its refined layout's splits and its fitted corners make triangles 0.02-0.08 of the
    median edge wide again), 57,522 -> 56,406 bytes, 99.58 -> 99.61 % of the points within
    0.5 %, RMS 2.12e-4 -> 2.03e-4, largest distance 2.15 -> 2.06 %; Lucy 2,304 -> 2,268
    patches, level-0 RMS 0.216 -> 0.224, largest distance 0.85 -> 0.83 %; Laurana 2,304 ->
    2,274, 0.0669 -> 0.0659, 0.72 -> 0.80 %; Nefertiti 2,304 -> 2,226, 74,710 -> 71,518
    bytes, 0.0384 -> 0.0418, 0.78 -> 0.68 %.
    A hole narrower than ``share ℓ`` keeps its narrow triangles: no collapse of its border
    keeps it open.

    Returns
    -------
    vertices, triangles, collapses
        The layout (unreferenced vertices dropped, the others in their order) and the
        number of edges collapsed.

    Raises
    ------
    ValueError
        ``share`` outside ``[0, 1)``.
    """
    vertices = np.asarray(vertices, np.float64)
    triangles = np.array(triangles, np.int64)
    share = MIN_WIDTH_SHARE if share is None else share
    if not 0.0 <= share < 1.0:
        raise ValueError(f"share must lie in [0, 1), got {share!r}")
    edges = np.unique(np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]],
                                              triangles[:, [2, 0]]]), axis=1), axis=0)
    limit = share * float(np.median(np.linalg.norm(vertices[edges[:, 0]]
                                                   - vertices[edges[:, 1]], axis=1)))
    before = euler_characteristics(vertices, triangles)
    off_surface = _distance_to(surface)
    alive = np.ones(len(triangles), bool)
    refused: set[int] = set()  # triangles none of whose edges may collapse (as they are)
    collapses = 0
    while True:
        width = np.where(alive, triangle_widths(vertices, triangles), np.inf)
        narrow = [t for t in np.argsort(width).tolist()
                  if width[t] < limit and t not in refused]
        if not narrow:
            break
        t = narrow[0]
        corners = vertices[triangles[t]]
        lengths = np.linalg.norm(corners - np.roll(corners, -1, axis=0), axis=1)
        for k in np.argsort(lengths).tolist():
            a, b = int(triangles[t, k]), int(triangles[t, (k + 1) % 3])
            kept = triangles.copy(), alive.copy()
            if _collapse(vertices, triangles, alive, a, b, off_surface,
                         FLIP_AWAY_REACH * surface.diagonal):
                if not _same_pieces(vertices, triangles[alive], before):
                    triangles[:], alive[:] = kept  # undone: the link condition missed it
                    continue
                collapses += 1
                # a refused triangle near the collapse may collapse now: try it again
                ring = np.unique(triangles[alive & np.isin(triangles, [a, b]).any(axis=1)])
                refused -= set(np.flatnonzero(np.isin(triangles, ring).any(axis=1)).tolist())
                break
        else:
            refused.add(t)
    return (*without_triangles(vertices, triangles, ~alive), collapses)


def _same_pieces(vertices: np.ndarray, triangles: np.ndarray, before: list[int]) -> bool:
    """Whether ``triangles`` is an oriented 2-manifold whose pieces' Euler characteristics
    are ``before``."""
    problems = manifold_problems(triangles)
    return not (problems["nonmanifold_edges"] or problems["misoriented_edges"]) \
        and euler_characteristics(vertices, triangles) == before


def _on_border(fan: np.ndarray, x: int) -> bool:
    """Whether vertex ``x`` of the triangles ``fan`` around it has an edge in one of them."""
    edges = np.sort(np.concatenate([fan[:, [0, 1]], fan[:, [1, 2]], fan[:, [2, 0]]]), axis=1)
    edges = edges[(edges == x).any(axis=1)]
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return bool(np.any(counts == 1))


def _distance_to(surface: ScanSurface):
    """``distance(points) -> (N,)``: the distance of each point to ``surface`` (``open3d``'s
    ``RaycastingScene.compute_distance``, single precision, the surface's scene shared with
    the fit's other queries of it: :func:`.measure.mesh_scene`)."""
    import open3d as o3d

    from .measure import mesh_scene

    scene = mesh_scene(np.ascontiguousarray(surface.vertices, np.float32),
                       np.ascontiguousarray(surface.faces, np.uint32))

    def distance(points: np.ndarray) -> np.ndarray:
        query = o3d.core.Tensor(np.ascontiguousarray(points, np.float32))
        return scene.compute_distance(query).numpy().astype(np.float64)

    return distance


def _collapse(vertices: np.ndarray, triangles: np.ndarray, alive: np.ndarray, a: int,
              b: int, off_surface, reach: float) -> bool:
    """Collapse the edge ``(a, b)`` of the live ``triangles`` in place, keeping ``a`` or
    ``b`` (:func:`collapse_narrow_triangles`' rules; ``off_surface(points)`` the distance
    to the surface, ``reach`` how far off it a sample may be); whether it was collapsed."""
    live = np.flatnonzero(alive)
    tri = triangles[live]
    on_a, on_b = live[(tri == a).any(axis=1)], live[(tri == b).any(axis=1)]
    shared = np.intersect1d(on_a, on_b)
    ring_a = set(triangles[on_a].reshape(-1).tolist()) - {a}
    ring_b = set(triangles[on_b].reshape(-1).tolist()) - {b}
    apexes = set(triangles[shared].reshape(-1).tolist()) - {a, b}
    if not len(shared) or (ring_a & ring_b) != apexes:
        return False  # no edge, or the link condition fails
    on_border = {x for x, on_x in ((a, on_a), (b, on_b)) if _on_border(triangles[on_x], x)}
    if len(shared) == 2 and len(on_border) == 2:
        return False  # an inner edge between two border vertices: the border would pinch
    ways = [(a, b), (b, a)] if len(on_border) != 1 else \
        [(a, b)] if a in on_border else [(b, a)]
    best = None
    for keep, gone in ways:
        changed = np.setdiff1d(on_b if gone == b else on_a, shared)
        old = triangles[changed]
        new = np.where(old == gone, keep, old)
        n_old = np.cross(vertices[old[:, 1]] - vertices[old[:, 0]],
                         vertices[old[:, 2]] - vertices[old[:, 0]])
        n_new = np.cross(vertices[new[:, 1]] - vertices[new[:, 0]],
                         vertices[new[:, 2]] - vertices[new[:, 0]])
        if np.any(np.einsum("ij,ij->i", n_old, n_new) <= 0.0):
            continue  # a triangle turns over or loses its area
        kept = on_b if keep == b else on_a  # a triangle the new ones could double has keep
        others = {frozenset(x) for x in triangles[np.setdiff1d(kept, shared)].tolist()}
        if any(frozenset(x) in others for x in new.tolist()):
            continue  # a triangle onto another (a tetrahedron collapsing to a double sheet)
        if len(new):
            far = off_surface(triangle_samples(vertices, new, FLIP_SAMPLES)[0]).max()
            if far > reach and far > off_surface(triangle_samples(
                    vertices, triangles[np.union1d(changed, shared)], FLIP_SAMPLES)[0]).max():
                continue  # the layout leaves the surface
        worst = float(triangle_widths(vertices, new).min()) if len(new) else np.inf
        if best is None or worst > best[0]:
            best = (worst, changed, new)
    if best is None:
        return False
    _, changed, new = best
    triangles[changed] = new
    alive[shared] = False
    return True


def euler_characteristics(vertices: np.ndarray, triangles: np.ndarray) -> list[int]:
    """``χ = V - E + F`` of every piece, sorted.

    Counted for all pieces at once: a face's piece is its vertices' and its edges' (pieces
    meet at no vertex), the edges found once by their 1-D keys (:func:`.surface.unique_pairs`).
    On a 2.24 M-triangle surface 1.5 s instead of 8.2 s piece by piece with row sorts."""
    triangles = np.asarray(triangles, np.int64)
    count, labels = face_pieces(triangles, len(vertices))
    if count == 0:
        return []
    faces = np.bincount(labels, minlength=count)
    pairs = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]],
                                    triangles[:, [2, 0]]]), axis=1)
    _, first = unique_pairs(pairs, return_index=True)
    edges = np.bincount(np.tile(labels, 3)[first], minlength=count)
    piece_of = np.full(len(vertices), -1, np.int64)
    piece_of[triangles.reshape(-1)] = np.repeat(labels, 3)
    used = np.bincount(piece_of[piece_of >= 0], minlength=count)
    return sorted(int(x) for x in used - edges + faces)


def _same_topology(surface: ScanSurface, vertices: np.ndarray, triangles: np.ndarray) -> bool:
    problems = manifold_problems(triangles)
    if problems["nonmanifold_edges"] or problems["misoriented_edges"]:
        return False
    return euler_characteristics(vertices, triangles) == euler_characteristics(
        surface.vertices, surface.faces)


def _checked(surface: ScanSurface, vertices: np.ndarray, triangles: np.ndarray,
             require_area: bool = True) -> tuple[np.ndarray, np.ndarray]:
    problems = manifold_problems(triangles)
    if problems["nonmanifold_edges"] or problems["misoriented_edges"]:
        raise AtlasLayoutError(
            f"the surface decimated to {len(triangles)} triangles has "
            f"{problems['nonmanifold_edges']} non-manifold and {problems['misoriented_edges']} "
            "misoriented edges; the layout needs an oriented 2-manifold")
    if require_area and (flat := without_area(vertices, triangles, surface.diagonal)).any():
        raise AtlasLayoutError(f"the decimated surface has {int(np.sum(flat))} triangles "
                               "without area; the layout needs every triangle to have area")
    return vertices, triangles


def quad_layout(vertices: np.ndarray, triangles: np.ndarray) -> QuadLayout:
    """Split every triangle into 3 quads at its centroid and shared edge midpoints.

    Parameters
    ----------
    vertices : ndarray, shape (Vt, 3)
    triangles : ndarray, shape (T, 3)
        An oriented 2-manifold (with or without border).

    Returns
    -------
    QuadLayout
    """
    vertices = np.asarray(vertices, np.float64)
    triangles = np.asarray(triangles, np.int64)
    if triangles.ndim != 2 or triangles.shape[1] != 3 or len(triangles) == 0:
        raise ValueError(f"triangles must have shape (T, 3) with T >= 1, got {triangles.shape}")
    n_v, n_t = len(vertices), len(triangles)
    directed = np.stack([triangles, np.roll(triangles, -1, axis=1)], axis=2)  # (T, 3, 2)
    edges, inverse = np.unique(np.sort(directed.reshape(-1, 2), axis=1), axis=0,
                               return_inverse=True)
    mid = n_v + inverse.reshape(n_t, 3)  # mid[t, k]: midpoint of edge tri[k] -> tri[k+1]
    centroid = n_v + len(edges) + np.arange(n_t)
    quads = np.empty((n_t, 3, 4), np.int64)
    for k in range(3):
        quads[:, k, 0] = triangles[:, k]
        quads[:, k, 1] = mid[:, k]
        quads[:, k, 2] = centroid
        quads[:, k, 3] = mid[:, (k + 2) % 3]
    corners = np.concatenate([vertices, vertices[edges].mean(axis=1),
                              vertices[triangles].mean(axis=1)])
    return QuadLayout(vertices, triangles, corners, quads.reshape(-1, 4), edges)


def greville(degree: int, spans: int) -> np.ndarray:
    """Greville abscissae ``ξ_i = (t_{i+1} + … + t_{i+d}) / d`` of the clamped uniform knots."""
    knots = np.r_[np.zeros(degree), np.linspace(0.0, 1.0, spans + 1), np.ones(degree)]
    n = spans + degree
    return np.array([knots[i + 1:i + degree + 1].mean() for i in range(n)])


def bilinear_atlas(layout: QuadLayout, degree: int = 3, spans: int = 2) -> AtlasSurface:
    """The atlas whose patch ``f`` is the bilinear quad of ``layout.quads[f]`` exactly.

    ``P_f[i][j] = (1-ξ_i)(1-ξ_j) a + ξ_i (1-ξ_j) b + ξ_i ξ_j c + (1-ξ_i) ξ_j d``; every shared
    point gets the same value from each patch that holds it (a bilinear quad restricted to
    a side is the segment between its ends).
    """
    xi = greville(degree, spans)
    inner = xi[1:-1]
    table = atlas_edges(layout.quads.tolist())
    corners = layout.vertices
    ends = np.asarray(table.edges, np.int64).reshape(-1, 2)
    lo, hi = corners[ends[:, 0]], corners[ends[:, 1]]
    edge_points = (lo[:, None, :] * (1 - inner)[None, :, None]
                   + hi[:, None, :] * inner[None, :, None]).reshape(-1, 3)
    q = corners[layout.quads]  # (F, 4, 3)
    s, t = inner[None, :, None, None], inner[None, None, :, None]  # i along u, j along v
    a, b, c, d = (q[:, k][:, None, None, :] for k in range(4))
    face = (1 - s) * (1 - t) * a + s * (1 - t) * b + s * t * c + (1 - s) * t * d
    return AtlasSurface(degree, spans, corners.tolist(), layout.quads.tolist(),
                        edge_points.tolist(), face.reshape(-1, 3).tolist(), None)


def split_edges(vertices: np.ndarray, triangles: np.ndarray, edges: np.ndarray,
                positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The triangle mesh with every edge of ``edges (S, 2)`` split at a new vertex.

    Edge ``(a, b)`` gets vertex ``Vt + i`` at ``positions[i]``; each triangle ``(a, b, c)``
    on it (one on an open border, two inside) becomes ``(a, m, c)`` and ``(m, b, c)`` in its
    own orientation. An edge split (Hoppe et al., *Mesh optimization*, 1993) keeps an
    oriented 2-manifold one, with its borders and topology. The edges must be distinct and
    no two may share a triangle (each triangle is split at most once).

    Raises
    ------
    ValueError
        An edge that is not an edge of ``triangles``, two edges of one triangle, or shapes
        that do not match.
    """
    vertices = np.asarray(vertices, np.float64)
    triangles = np.array(triangles, np.int64)
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    positions = np.asarray(positions, np.float64).reshape(-1, 3)
    if len(edges) != len(positions):
        raise ValueError(f"{len(edges)} edges but {len(positions)} positions")
    directed = {}
    for t, tri in enumerate(triangles.tolist()):
        for k in range(3):
            directed[tri[k], tri[(k + 1) % 3]] = (t, k)
    used: set[int] = set()
    added = []
    for i, (a, b) in enumerate(edges.tolist()):
        m = len(vertices) + i
        sides = [directed[e] for e in ((a, b), (b, a)) if e in directed]
        if not sides or a == b:
            raise ValueError(f"({a}, {b}) is not an edge of the triangles")
        for t, k in sides:
            if t in used:
                raise ValueError(f"triangle {t} holds two of the edges to split")
            used.add(t)
            x, y, z = triangles[t, k], triangles[t, (k + 1) % 3], triangles[t, (k + 2) % 3]
            triangles[t] = (x, m, z)
            added.append((m, y, z))
    return (np.concatenate([vertices, positions]),
            np.concatenate([triangles, np.array(added, np.int64).reshape(-1, 3)]))


def split_longest_edges(surface: ScanSurface, vertices: np.ndarray, triangles: np.ndarray,
                        chosen: np.ndarray, max_added: int | None = None
                        ) -> tuple[np.ndarray, np.ndarray, int]:
    """The longest edge of each triangle in ``chosen`` split at the surface.

    In the order given (the most urgent first), triangle ``t``'s longest edge is split
    (:func:`split_edges`) at the closest point of the surface to its midpoint
    (``measure.closest_points_on_mesh``); a triangle whose longest edge's triangles are
    already being split is skipped (one split per triangle). With ``max_added``, the splits
    stop before the triangles they add (one per triangle on the edge: two inside, one on
    an open border) would exceed it.

    Returns
    -------
    vertices, triangles, count
        The refined layout and the number of edges split.
    """
    from .measure import closest_points_on_mesh

    vertices = np.asarray(vertices, np.float64)
    triangles = np.asarray(triangles, np.int64)
    owners: dict[tuple[int, int], list[int]] = {}
    for t, tri in enumerate(triangles.tolist()):
        for k in range(3):
            a, b = tri[k], tri[(k + 1) % 3]
            owners.setdefault((min(a, b), max(a, b)), []).append(t)
    touched: set[int] = set()
    edges = []
    for t in np.asarray(chosen, np.int64).tolist():
        corners = vertices[triangles[t]]
        k = int(np.argmax(np.linalg.norm(corners - np.roll(corners, -1, axis=0), axis=1)))
        a, b = int(triangles[t, k]), int(triangles[t, (k + 1) % 3])
        on_edge = owners[min(a, b), max(a, b)]
        if touched.intersection(on_edge):
            continue
        if max_added is not None and len(touched) + len(on_edge) > max_added:
            break
        touched.update(on_edge)
        edges.append((a, b))
    if not edges:
        return vertices, triangles, 0
    edges = np.array(edges, np.int64)
    _, _, positions = closest_points_on_mesh(vertices[edges].mean(axis=1), surface.vertices,
                                             surface.faces)
    vertices, triangles = split_edges(vertices, triangles, edges, positions)
    return vertices, triangles, len(edges)
