"""A smooth atlas from a small triangle control mesh: Catmull-Clark, approximated by patches.

The atlas base (:class:`client_py.atlas.AtlasSurface`) is a quad layout of bicubic Bézier
patches. Here it is derived from a far smaller *control mesh* of ``n`` points and ``T``
triangles (an oriented 2-manifold, possibly with borders) in two linear stages, each given
as sparse rows so that the fitter builds its matrices from these same rules:

1. **One Catmull-Clark step** (Catmull & Clark, *Recursively generated B-spline surfaces on
   arbitrary topological meshes*, CAD 10(6), 1978; borders by Hoppe et al., *Piecewise
   smooth surface reconstruction*, SIGGRAPH 1994) turns the triangles into the *step-1*
   quad mesh of ``V₁ = n + E + T`` vertices and ``F = 3 T`` quads, numbered as
   ``fitter.fitting.atlas.layout.quad_layout``: the ``n`` control points, one vertex per
   undirected edge in sorted ``(lo, hi)`` order, one per triangle; quad ``3 t + k`` is
   ``(x, m_xy, g, m_zx)`` for triangle ``t = (x, y, z)`` rotated to start at its ``k``-th
   vertex (``m`` an edge's vertex, ``g`` the triangle's). Positions
   (``fitter.fitting.atlas.subdivision.catmull_clark_step``'s rules):

   - face point ``g = (a + b + c) / 3``;
   - edge point ``(a + b + F₁ + F₂) / 4`` on an edge of two triangles (face points
     ``F₁, F₂``), the midpoint ``(a + b) / 2`` on a border edge (one triangle);
   - vertex point ``(Q + 2 R + (k - 3) v) / k`` of a vertex with ``k`` edges, none on the
     border (``Q`` the mean of its triangles' face points, ``R`` of its edges' midpoints);
     ``(a + 6 v + b) / 8`` on exactly two border edges (to ``a`` and ``b``: the border
     follows the cubic B-spline of the control border); ``v`` on one or more than two (a
     corner), or in no triangle.

2. **ACC patches** (Loop & Schaefer, *Approximating Catmull-Clark subdivision surfaces with
   bicubic patches*, ACM TOG 27(1), 2008, the geometry patches): every step-1 quad carries
   one bicubic Bézier patch (degree 3, 1 span: ``4 × 4`` control points). With ``N`` the
   valence of step-1 vertex ``v``: its number of quads, twice that on the border (so that
   a regular border vertex, on 2 quads, counts 4 like a regular interior one):

   - interior point of a quad near its corner ``v``: ``(N v + 2 e₁ + 2 e₂ + d) / (N + 5)``,
     ``e₁, e₂`` the quad's corners next to ``v``, ``d`` the opposite one;
   - edge point near ``v`` of edge ``(v, w)``: the mean of the interior points near ``v``
     of the two quads on the edge; on a border edge ``(2 v + w) / 3``;
   - corner point: the mean of the interior points near ``v`` of its ``N`` quads, which is
     the Catmull-Clark limit position ``(N² v + 4 Σ eᵢ + Σ fᵢ) / (N (N + 5))`` (``eᵢ`` its
     edge neighbours, ``fᵢ`` its quads' opposite corners); ``(a + 4 v + b) / 6`` on exactly
     two border edges (the limit of the border's cubic B-spline); ``v`` otherwise.

On a regular mesh (``N = 4`` everywhere) these are the uniform bicubic B-spline's Bézier
points, which Catmull-Clark reproduces there: the interior points ``(4 v + 2 e₁ + 2 e₂ +
d) / 9`` are the tensor product of the curve's ``(2 v + w) / 3`` and ``(v + 2 w) / 3``;
an edge point averages two of them, ``(8 v + 4 w + 2 (x₁ + x₂) + (y₁ + y₂)) / 18`` =
``(1 4 1)/6 ⊗ (2 1)/3``; a corner point is ``(16 v + 4 Σ eᵢ + Σ fᵢ) / 36`` =
``(1 4 1)/6 ⊗ (1 4 1)/6``. Along a regular border Catmull-Clark is the B-spline continued
past the border by the phantom points ``2 P₀ - P₁``, whose Bézier points there are the
border curve's ``(2 v + w) / 3`` and ``(a + 4 v + b) / 6`` and, inside, the same
``(4 v + 2 e₁ + 2 e₂ + d) / 9`` (hence ``N = 2 × 2``). Elsewhere the patches meet with C0
(shared border rows: :mod:`client_py.atlas`) and approximate the limit surface closely
(0.3 % of the control edge length on a bumpy sphere, ``tests/test_smooth_base.py``).

:func:`smooth_base` returns the two stages' rows (:class:`SmoothBase`), :func:`smooth_atlas`
the :class:`~client_py.atlas.AtlasSurface` of given control points, stage by stage (its last
step, :func:`base_atlas`, from the atlas's control points).
Standard library only (Pyodide).
"""

from __future__ import annotations

import math
import operator
from collections.abc import Sequence
from dataclasses import dataclass

from .atlas import MAX_ATLAS_QUADS, MAX_ATLAS_VERTICES, AtlasSurface
from .gc_pause import without_cyclic_gc

Row = list[tuple[int, float]]

#: the ACC patches: bicubic, one span (4 x 4 Bézier control points)
SMOOTH_DEGREE = 3
SMOOTH_SPANS = 1


@dataclass(frozen=True)
class SmoothBase:
    """The two linear stages from ``n`` control points to the atlas's control points.

    Attributes
    ----------
    quads : list of (int, int, int, int), length ``F = 3 T``
        The step-1 quads (module docstring), the atlas's layout.
    step_rows : list of list of (int, float), length ``V₁ = n + E + T``
        Step-1 vertex ``j`` is ``Σ w p_i`` over ``(i, w)`` in ``step_rows[j]``, ``p_i`` the
        control points (shape ``(n, 3)``); each ``i`` at most once per row.
    acc_rows : list of list of (int, float), length ``V₁ + 2 E₁ + 4 F``
        The atlas's control points in :class:`~client_py.atlas.AtlasSurface`'s global
        order (layout vertices, then 2 points per step-1 edge, then 4 per quad) as
        ``Σ w s_j`` over ``(j, w)``, ``s_j`` the step-1 vertices; each ``j`` at most once.
    """

    quads: list[tuple[int, int, int, int]]
    step_rows: list[Row]
    acc_rows: list[Row]

    @property
    def step_vertex_count(self) -> int:
        """``V₁``: step-1 vertices, the atlas's layout vertices."""
        return len(self.step_rows)


def _as_list(value: object) -> object:
    """numpy arrays (or anything with ``tolist``) become nested lists; no numpy import."""
    return value.tolist() if hasattr(value, "tolist") else value


def _checked_triangles(n_points: int, triangles: object
                       ) -> tuple[int, list[tuple[int, int, int]]]:
    """``n_points`` as an int and ``triangles`` as int triples, checked to be an oriented
    2-manifold of ``n_points`` points (:func:`smooth_base`'s Raises)."""
    try:
        n = -1 if isinstance(n_points, bool) else operator.index(n_points)
    except TypeError:
        n = -1
    if n < 1:
        raise ValueError(f"n_points must be an int >= 1, got {n_points!r}")
    n_points = n
    rows = _as_list(triangles)
    if not isinstance(rows, Sequence) or not rows:
        raise ValueError("triangles must be a non-empty sequence of index triples (T >= 1)")
    out: list[tuple[int, int, int]] = []
    directed: dict[tuple[int, int], int] = {}
    for t, tri in enumerate(rows):
        try:
            if len(tri) != 3 or any(isinstance(k, bool) for k in tri):
                raise TypeError
            a, b, c = (operator.index(k) for k in tri)
        except TypeError:
            raise ValueError(f"triangles[{t}] = {tri!r}: a triangle is 3 int indices") from None
        if not (0 <= a < n_points and 0 <= b < n_points and 0 <= c < n_points):
            raise ValueError(f"triangles[{t}] = {(a, b, c)}: indices must be in "
                             f"0..{n_points - 1} (there are {n_points} points)")
        if a == b or b == c or c == a:
            raise ValueError(f"triangles[{t}] = {(a, b, c)} repeats a vertex; a triangle "
                             "needs 3 distinct vertices")
        for key in ((a, b), (b, c), (c, a)):
            if key in directed:
                raise ValueError(
                    f"triangles {directed[key]} and {t} both run edge {key[0]}->{key[1]}: "
                    "an oriented 2-manifold has at most 2 triangles on an edge, running it "
                    "once each way")
            directed[key] = t
        out.append((a, b, c))
    return n_points, out


def _combined(terms: list[tuple[float, Row]]) -> Row:
    """``Σ c · row`` over ``(c, row)`` in ``terms``, each index once."""
    acc: dict[int, float] = {}
    get = acc.get
    for c, row in terms:
        for i, w in row:
            acc[i] = get(i, 0.0) + c * w
    return list(acc.items())


def _catmull_clark_rows(n: int, triangles: list[tuple[int, int, int]]
                        ) -> tuple[list[Row], list[tuple[int, int, int, int]]]:
    """Stage 1 (module docstring): the step-1 rows, length ``n + E + T``, and quads."""
    keys = sorted({(a, b) if a < b else (b, a) for tri in triangles
                   for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0]))})
    index = {key: e for e, key in enumerate(keys)}
    E = len(keys)
    third = 1.0 / 3.0
    face_rows: list[Row] = [[(a, third), (b, third), (c, third)] for a, b, c in triangles]
    edge_faces: list[list[int]] = [[] for _ in keys]
    # mid[t][k]: edge index of triangles[t][k] -> triangles[t][k + 1]
    mid: list[tuple[int, int, int]] = []
    for t, (a, b, c) in enumerate(triangles):
        e0 = index[(a, b) if a < b else (b, a)]
        e1 = index[(b, c) if b < c else (c, b)]
        e2 = index[(c, a) if c < a else (a, c)]
        edge_faces[e0].append(t)
        edge_faces[e1].append(t)
        edge_faces[e2].append(t)
        mid.append((e0, e1, e2))
    edge_rows: list[Row] = []
    for (a, b), faces in zip(keys, edge_faces, strict=True):
        if len(faces) == 2:
            edge_rows.append(_combined([(0.25, [(a, 1.0), (b, 1.0)]),
                                        (0.25, face_rows[faces[0]]),
                                        (0.25, face_rows[faces[1]])]))
        else:
            edge_rows.append([(a, 0.5), (b, 0.5)])
    neighbours: list[list[int]] = [[] for _ in range(n)]
    border: list[list[int]] = [[] for _ in range(n)]
    for (a, b), faces in zip(keys, edge_faces, strict=True):
        neighbours[a].append(b)
        neighbours[b].append(a)
        if len(faces) == 1:
            border[a].append(b)
            border[b].append(a)
    around: list[list[int]] = [[] for _ in range(n)]
    for t, tri in enumerate(triangles):
        for v in tri:
            around[v].append(t)
    vertex_rows: list[Row] = []
    for v in range(n):
        k, crease = len(neighbours[v]), border[v]
        if k and not crease:
            # (Q + 2 R + (k - 3) v) / k, 2 R = v + mean(neighbours)
            faces = around[v]
            q = 1.0 / (k * len(faces))
            r = 1.0 / (k * k)
            terms = [((k - 3) / k + k * r, [(v, 1.0)]), (r, [(w, 1.0) for w in neighbours[v]])]
            terms.extend((q, face_rows[t]) for t in faces)
            vertex_rows.append(_combined(terms))
        elif len(crease) == 2:
            vertex_rows.append([(v, 0.75), (crease[0], 0.125), (crease[1], 0.125)])
        else:
            vertex_rows.append([(v, 1.0)])
    quads: list[tuple[int, int, int, int]] = []
    first_edge, first_face = n, n + E
    for t, (x, y, z) in enumerate(triangles):
        m_xy, m_yz, m_zx = (first_edge + e for e in mid[t])
        g = first_face + t
        quads.append((x, m_xy, g, m_zx))
        quads.append((y, m_yz, g, m_xy))
        quads.append((z, m_zx, g, m_yz))
    return vertex_rows + edge_rows + face_rows, quads


def _step_edges(n_vertices: int, quads: list[tuple[int, int, int, int]]
                ) -> list[list[tuple[int, int, int]]]:
    """The quads on each step-1 edge, edges numbered as :func:`client_py.atlas.atlas_edges`
    does (sorted ``(lo, hi)``): ``(f, position of lo in quad f, position of hi)``.

    The same numbering as ``atlas_edges``, without its orientation checks (the step-1 quads
    of checked triangles pass them) at a fraction of its cost on ``12 T`` sides."""
    sides = [(a, b) for quad in quads
             for a, b in ((quad[0], quad[1]), (quad[1], quad[2]), (quad[2], quad[3]),
                          (quad[3], quad[0]))]
    keys = sorted({a * n_vertices + b if a < b else b * n_vertices + a for a, b in sides})
    index = {key: e for e, key in enumerate(keys)}
    on_edge: list[list[tuple[int, int, int]]] = [[] for _ in keys]
    for k, (a, b) in enumerate(sides):
        f, p = divmod(k, 4)
        q = (p + 1) & 3
        if a < b:
            on_edge[index[a * n_vertices + b]].append((f, p, q))
        else:
            on_edge[index[b * n_vertices + a]].append((f, q, p))
    return on_edge


def _acc_rows(n_vertices: int, quads: list[tuple[int, int, int, int]]) -> list[Row]:
    """Stage 2 (module docstring): the atlas's control points from the step-1 vertices."""
    on_edge = _step_edges(n_vertices, quads)
    quads_at = [0] * n_vertices
    for quad in quads:
        for v in quad:
            quads_at[v] += 1
    border: list[list[int]] = [[] for _ in range(n_vertices)]
    for pairs in on_edge:
        if len(pairs) == 1:
            f, p, q = pairs[0]
            lo, hi = quads[f][p], quads[f][q]
            border[lo].append(hi)
            border[hi].append(lo)
    # N of the interior point rule: the quads at v, twice that on the border
    valence = [2 * k if crease else k for k, crease in zip(quads_at, border, strict=True)]
    # near[f][p]: interior point of quad f near its corner p (order a, b, c, d)
    near: list[tuple[Row, Row, Row, Row]] = []
    corners: list[list[Row]] = [[] for _ in range(n_vertices)]
    for a, b, c, d in quads:
        rows = []
        for v, e1, o, e2 in ((a, b, c, d), (b, c, d, a), (c, d, a, b), (d, a, b, c)):
            n = valence[v]
            s = 1.0 / (n + 5)
            row = [(v, n * s), (e1, 2.0 * s), (e2, 2.0 * s), (o, s)]
            rows.append(row)
            corners[v].append(row)
        near.append(tuple(rows))  # type: ignore[arg-type]
    vertex_rows: list[Row] = []
    sixth = 1.0 / 6.0
    for v in range(n_vertices):
        crease = border[v]
        if quads_at[v] and not crease:
            mean = 1.0 / quads_at[v]
            vertex_rows.append(_combined([(mean, row) for row in corners[v]]))
        elif len(crease) == 2:
            vertex_rows.append([(v, 4.0 * sixth), (crease[0], sixth), (crease[1], sixth)])
        else:
            vertex_rows.append([(v, 1.0)])
    edge_rows: list[Row] = []
    two_thirds, third = 2.0 / 3.0, 1.0 / 3.0
    for pairs in on_edge:
        if len(pairs) == 1:
            f, p, q = pairs[0]
            lo, hi = quads[f][p], quads[f][q]
            edge_rows.append([(lo, two_thirds), (hi, third)])
            edge_rows.append([(hi, two_thirds), (lo, third)])
            continue
        (f, p, q), (g, r, t) = pairs
        edge_rows.append(_mean_near(quads[f], p, q, quads[g], r, valence, near[f][p],
                                    near[g][r]))
        edge_rows.append(_mean_near(quads[f], q, p, quads[g], t, valence, near[f][q],
                                    near[g][t]))
    # face points P[i][j] in the order (1, 1), (1, 2), (2, 1), (2, 2): near a, d, b, c
    face_rows = [row for rows in near for row in (rows[0], rows[3], rows[1], rows[2])]
    return vertex_rows + edge_rows + face_rows


def _mean_near(quad_f: tuple[int, ...], p: int, q: int, quad_g: tuple[int, ...], r: int,
               valence: list[int], near_f: Row, near_g: Row) -> Row:
    """The mean of the interior points near corner ``v`` (position ``p`` of quad ``f``,
    ``r`` of quad ``g``) of two quads on edge ``(v, w)`` (``w`` at position ``q`` of
    ``f``): ``(N v + 2 w + x_f + x_g + (o_f + o_g) / 2) / (N + 5)``, ``x`` the quad's other
    corner next to ``v``, ``o`` the one opposite. Written out rather than merged by
    :func:`_combined` (0.5 s of the stage's 1.1 s at ``T = 10,000``), which remains for
    quads whose four other corners are not distinct (two triangles closed on each other)."""
    v, w = quad_f[p], quad_f[q]
    x_f, o_f = quad_f[(2 * p - q) & 3], quad_f[(p + 2) & 3]
    x_g = quad_g[(r + 1) & 3] if quad_g[(r + 3) & 3] == w else quad_g[(r + 3) & 3]
    o_g = quad_g[(r + 2) & 3]
    if len({x_f, o_f, x_g, o_g}) < 4:
        return _combined([(0.5, near_f), (0.5, near_g)])
    n = valence[v]
    s = 1.0 / (n + 5)
    return [(v, n * s), (w, 2.0 * s), (x_f, s), (x_g, s), (o_f, 0.5 * s), (o_g, 0.5 * s)]


def check_control_mesh(n_points: int, triangles: Sequence[Sequence[int]]
                       ) -> tuple[int, list[tuple[int, int, int]]]:
    """Check that ``n_points`` and ``triangles`` are a control mesh :func:`smooth_base`
    takes (its Raises, in the same order), without deriving its rows: a reader or writer of
    a control mesh checks it so (:mod:`client_py.control_mesh`). Returns ``n_points`` as an
    int and the triangles as int triples."""
    n_points, checked = _checked_triangles(n_points, triangles)
    T = len(checked)
    if 3 * T > MAX_ATLAS_QUADS:
        raise ValueError(f"the smooth atlas of {T} triangles would have "
                         f"{3 * T} quads; an AtlasSurface takes at most "
                         f"{MAX_ATLAS_QUADS} (client_py.atlas.MAX_ATLAS_QUADS), so at most "
                         f"{MAX_ATLAS_QUADS // 3} triangles")
    # each directed edge once (checked): an undirected edge is run once or twice
    E = len({(a, b) if a < b else (b, a) for tri in checked
             for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0]))})
    if n_points + E + T > MAX_ATLAS_VERTICES:
        raise ValueError(f"the smooth atlas of {n_points} points and {T} triangles would have "
                         f"n + E + T = {n_points + E + T} layout vertices; an AtlasSurface "
                         f"takes at most {MAX_ATLAS_VERTICES} "
                         "(client_py.atlas.MAX_ATLAS_VERTICES)")
    return n_points, checked


def smooth_base(n_points: int, triangles: Sequence[Sequence[int]]) -> SmoothBase:
    """The rows of the smooth atlas of a triangle control mesh (module docstring).

    Parameters
    ----------
    n_points : int
        ``n >= 1`` control points.
    triangles : sequence of 3 ints, shape (T, 3)
        Indices into the control points; an oriented 2-manifold with ``T >= 1``
        triangles, possibly with borders and points in no triangle.

    Returns
    -------
    SmoothBase
        ``F = 3 T`` quads, ``V₁ = n + E + T`` step-1 rows over the ``n`` control points and
        ``V₁ + 2 E₁ + 4 F`` ACC rows over the step-1 vertices (``E``, ``E₁``: the control
        mesh's and the step-1 mesh's undirected edges).

    Raises
    ------
    ValueError
        ``n_points`` not an int >= 1; no triangle; a triangle that is not 3 distinct indices
        in ``0..n-1``; an edge run twice the same way (misoriented, or on more than 2
        triangles); or more quads or layout vertices than an
        :class:`~client_py.atlas.AtlasSurface` takes (``MAX_ATLAS_QUADS``,
        ``MAX_ATLAS_VERTICES``).
    """
    n_points, checked = check_control_mesh(n_points, triangles)
    with without_cyclic_gc():
        step_rows, quads = _catmull_clark_rows(n_points, checked)
        return SmoothBase(quads, step_rows, _acc_rows(len(step_rows), quads))


def _applied(rows: list[Row], xs: list[float], ys: list[float], zs: list[float]
             ) -> tuple[list[float], list[float], list[float]]:
    """``Σ w p_i`` for every row, coordinate by coordinate."""
    out_x, out_y, out_z = [], [], []
    for row in rows:
        x = y = z = 0.0
        for i, w in row:
            x += w * xs[i]
            y += w * ys[i]
            z += w * zs[i]
        out_x.append(x)
        out_y.append(y)
        out_z.append(z)
    return out_x, out_y, out_z


def smooth_atlas(points: Sequence[Sequence[float]], triangles: Sequence[Sequence[int]],
                 base: SmoothBase | None = None) -> AtlasSurface:
    """The atlas of bicubic Bézier patches approximating the Catmull-Clark limit surface of
    the control mesh (module docstring): step-1 vertices ``s = S p``, then the atlas's
    control points ``A s``, each stage applied to positions in turn.

    Parameters
    ----------
    points : sequence of (x, y, z), shape (n, 3)
        The control points, finite.
    triangles : sequence of 3 ints, shape (T, 3)
        As for :func:`smooth_base`.
    base : SmoothBase, optional
        ``smooth_base(n, triangles)``, computed once for many point sets; ``None``:
        computed here.

    Returns
    -------
    AtlasSurface
        Degree 3, 1 span, no weights; layout ``base.quads``.

    Raises
    ------
    ValueError
        ``points`` not of shape ``(n, 3)`` with ``n >= 1`` or not finite, bad
        ``triangles`` (:func:`smooth_base`), or a ``base`` of another mesh.
    """
    rows = _as_list(points)
    if not isinstance(rows, Sequence) or not rows:
        raise ValueError("points must be a non-empty (n, 3) sequence of control points")
    xs: list[float] = []
    ys: list[float] = []
    zs: list[float] = []
    for i, p in enumerate(rows):
        if not isinstance(p, Sequence) or len(p) != 3:
            raise ValueError(f"points[{i}] = {p!r}: a control point has 3 coordinates")
        try:
            x, y, z = float(p[0]), float(p[1]), float(p[2])
        except (TypeError, ValueError):
            raise ValueError(f"points[{i}] = {p!r}: coordinates must be numbers") from None
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            raise ValueError(f"points[{i}] = {(x, y, z)} is not finite")
        xs.append(x)
        ys.append(y)
        zs.append(z)
    if base is None:
        base = smooth_base(len(rows), triangles)
    else:
        _, checked = _checked_triangles(len(rows), triangles)
        # counts, and the step-1 quads starting at the triangles' corners: a cheap check
        edges = {(a, b) if a < b else (b, a) for tri in checked
                 for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0]))}
        if not isinstance(base, SmoothBase) or len(base.quads) != 3 * len(checked) \
                or len(base.step_rows) != len(rows) + len(edges) + len(checked) or any(
                base.quads[3 * t + k][0] != tri[k]
                for t, tri in enumerate(checked) for k in range(3)):
            raise ValueError(f"base is not the smooth_base of these {len(rows)} points and "
                             f"{len(checked)} triangles")
    with without_cyclic_gc():
        step_x, step_y, step_z = _applied(base.step_rows, xs, ys, zs)
        acc_x, acc_y, acc_z = _applied(base.acc_rows, step_x, step_y, step_z)
        return base_atlas(base, list(zip(acc_x, acc_y, acc_z, strict=True)))


def base_atlas(base: SmoothBase, atlas_points: Sequence[Sequence[float]]) -> AtlasSurface:
    """The :class:`~client_py.atlas.AtlasSurface` on ``base``'s layout whose control points
    are ``atlas_points``, shape ``(V₁ + 2 E₁ + 4 F, 3)`` in ``base.acc_rows``' order (layout
    vertices, then 2 points per step-1 edge, then 4 per quad): :func:`smooth_atlas`'s last
    step, for a caller that has the points another way (the fitter's sparse ``M V``).

    Raises
    ------
    ValueError
        ``atlas_points`` not one point per row of ``base.acc_rows``, or points
        :class:`~client_py.atlas.AtlasSurface` refuses.
    """
    if len(atlas_points) != len(base.acc_rows):
        raise ValueError(f"atlas_points has {len(atlas_points)} points; the base has "
                         f"{len(base.acc_rows)} (len(base.acc_rows))")
    V, faces_from = base.step_vertex_count, len(atlas_points) - 4 * len(base.quads)
    return AtlasSurface(SMOOTH_DEGREE, SMOOTH_SPANS, atlas_points[:V], base.quads,
                        atlas_points[V:faces_from], atlas_points[faces_from:], None)
