"""One welded, watertight triangle mesh of an atlas (``client_py.atlas``), with detail.

Patch ``f`` is sampled on the uniform grid ``u_i = i / (r_f - 1)``, ``v_j = j / (r_f - 1)``
(``r_f >= 2`` samples per side). The mesh is welded by construction, not by merging
nearby points: every layout corner is one vertex, every layout edge ``e`` has its
``R_e - 2`` interior vertices once, in the edge's ``lo -> hi`` order (``atlas_edges``: a
patch whose side runs ``hi -> lo`` reads them reversed), and every patch its
``(r_f - 2)^2`` interior vertices. Vertex order: corners (the layout vertices in use, by
index), then edges, then patches. Triangles turn counter-clockwise about ``C_u x C_v``:
in a consistently oriented layout, every interior edge is used once in each direction.

Evaluation is separable and shares its tables: every patch has the same clamped uniform
knot vector, so the spans and the basis values and derivatives ``N_a(t_k)``, ``N'_a(t_k)``
(The NURBS Book A2.1, A2.3) are computed once per ``(d, s, r)``; each patch then blends
its control rows along ``v`` and the rows along ``u`` in homogeneous coordinates
(``client_py._kernel_python``'s generated row evaluator; with numpy, all patches of one
resolution at once as ``B P^w B^T``). With numpy the whole mesh is also welded by the
kernel (``_kernel_numpy.weld_atlas``: the same arithmetic, its sums in the same order, so
the same bytes as the pure-Python weld here; the 4.7 M vertices of the Happy Buddha's
finest level in 4.5 CPU-s instead of 17).

Mixed resolutions: an edge is *evaluated* at its coarser side's resolution ``r_c`` and
carries ``R_e = r_fine`` vertices; those between two evaluated ones lie on the straight
segment joining them (the coarse side's piecewise-linear border), so the finer patch's
border vertices sit on the coarse side's triangles (no crack, no T-gap) and the coarse
side's border cells are split into fans through them (every mesh edge in exactly two
triangles). Resolutions of neighbours must be ``2^k c + 1`` for one ``c``.

Normals. Without detail, the analytic unit normal ``C_u x C_v / |C_u x C_v|`` (the exact
surface's, free with the derivatives); with detail, the normal of the displaced grid by
central differences within the patch (one-sided on its border), as
``client_py.layers.tessellate_region`` does for a single patch. On a border vertex
either is the normalised sum of the unit normals of the patches that sample it: the
welded vertex has ONE normal, so shading is smooth across patch borders.

Detail: ``X = C_f + D_f n_f`` with ``D_f`` the sum of patch ``f``'s tiles
(``client_py.layers.displacement_grid`` over its own ``[0, 1]^2``) and ``n_f`` its unit
normal; a border vertex that several patches sample takes the mean of their
displacements along the normalised mean of their unit normals, so the mesh stays welded
and watertight at every level.

Drawn cells (docs/format.md, "Atlas detail packs", version 5): a patch's tiles may carry
*walls masks*, the single patch's rule (``client_py.layers.drawn_cell_indices``): a cell
whose centre the walls mask of the finest applied tile carrying one covers is not drawn
(the fitter marks the cells of a level with no scan point within reach, where the atlas
was extrapolated over a part the scan lacks). Only triangles are left out: every vertex
stays where it is, so the patches left drawn on either side of a border still share its
vertices (no crack), and the mesh is open only around the cells left out.
"""

from __future__ import annotations

import math
import struct
import weakref
from array import array
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import lru_cache, partial
from itertools import chain
from operator import itemgetter

from . import _kernel, _kernel_python
from ._kernel_python import swap_blocks
from .atlas import AtlasSurface, atlas_edges
from .basis import basis_table
from .gc_pause import without_cyclic_gc
from .layers import DetailTile, displacement_grid, displacement_grids, drawn_cell_indices
from .ply import write_ply
from .surface import NORMAL_TOLERANCE
from .tessellate import MAX_GRID, Mesh, _samples, grid_indices

#: vertices of one atlas mesh: 2^24 (16.7 M) float32 positions and normals, 400 MB of
#: pure-Python floats while it is built
MAX_ATLAS_MESH_VERTICES = 1 << 24
#: patches between two progress reports of :func:`tessellate_atlas`
PROGRESS_BATCH = 32
#: the share of :func:`tessellate_atlas`'s work reported for evaluating the patches' grids
#: (the rest: displacing them and welding)
PROGRESS_EVALUATION = 0.5


@dataclass
class AtlasMesh(Mesh):
    """A :class:`~client_py.tessellate.Mesh` of an atlas with the patch of every vertex.

    Attributes
    ----------
    patches : array('I'), ``n_vertices``
        The patch whose ``(u, v)`` the vertex's ``uvs`` are: its own for a patch's interior
        vertex, the first patch (in index order) that samples it for a border vertex.
    """

    patches: array = field(default_factory=lambda: array("I"))


# ------------------------------------------------------------------ arguments
def _check_resolutions(atlas: AtlasSurface, resolution: object) -> list[int]:
    count = len(atlas.quads)
    if isinstance(resolution, int) and not isinstance(resolution, bool):
        values = [resolution] * count
    elif isinstance(resolution, Sequence) and not isinstance(resolution, str | bytes):
        values = list(resolution)
        if len(values) != count:
            raise ValueError(f"resolution has {len(values)} values; the atlas has {count} "
                             "patches (give one int, or one per patch)")
    else:
        raise ValueError(f"resolution must be an int or a sequence of ints, got {resolution!r}")
    for f, r in enumerate(values):
        if isinstance(r, bool) or not isinstance(r, int) or not 2 <= r <= MAX_GRID:
            raise ValueError(f"resolution of patch {f} = {r!r}; an int in 2..{MAX_GRID} "
                             "samples per side is needed")
    total = sum(r * r for r in values)
    if total > MAX_ATLAS_MESH_VERTICES:
        raise ValueError(f"resolution gives about {total} vertices; at most "
                         f"{MAX_ATLAS_MESH_VERTICES} are accepted")
    return values


def _check_detail(atlas: AtlasSurface, detail: object) -> dict[int, list[DetailTile]]:
    if detail is None:
        return {}
    if not isinstance(detail, Mapping):
        raise ValueError(f"detail must be a mapping of patch index to DetailTile lists, "
                         f"got {type(detail).__name__}")
    out = {}
    for f, tiles in detail.items():
        if isinstance(f, bool) or not isinstance(f, int) or not 0 <= f < len(atlas.quads):
            raise ValueError(f"detail key {f!r} is no patch index in 0..{len(atlas.quads) - 1}")
        tiles = list(tiles)
        for tile in tiles:
            if not isinstance(tile, DetailTile):
                raise ValueError(f"detail[{f}] holds a {type(tile).__name__}, not a DetailTile")
        if tiles:
            out[f] = tiles
    return out


def _edge_resolutions(atlas: AtlasSurface, res: list[int]) -> tuple[list[int], list[int]]:
    """``(R_e, r_c)`` per edge: vertices along it (the finer side) and its evaluated
    resolution (the coarser); ``ValueError`` where ``(R_e - 1) / (r_c - 1)`` is no power
    of 2."""
    if len(set(res)) == 1:  # one resolution: every edge at it
        return [res[0]] * len(atlas.edges.edges), [res[0]] * len(atlas.edges.edges)
    fine, coarse = [], []
    for e, pairs in enumerate(atlas.edges.faces):
        rs = [res[f] for f, _ in pairs]
        hi, lo = max(rs), min(rs)
        ratio, rest = divmod(hi - 1, lo - 1)
        if rest or ratio & (ratio - 1):
            f, g = (f for f, _ in pairs)
            raise ValueError(f"patches {f} and {g} share edge {atlas.edges.edges[e]} with "
                             f"resolutions {res[f]} and {res[g]}: neighbours need "
                             "2^k c + 1 samples for one c (r - 1 a power-of-2 multiple of "
                             "the other's)")
        fine.append(hi)
        coarse.append(lo)
    return fine, coarse


# ------------------------------------------------------------------ evaluation
@lru_cache(maxsize=32)
def _tables(degree: int, spans: int, r: int) -> tuple[list[float], list[int], list, list]:
    """Parameters ``t_k = k / (r - 1)`` and their spans, basis values and derivatives (A2.1,
    A2.3), once per ``(d, s, r)`` for every patch of that resolution."""
    n = spans + degree
    knots = [0.0] * degree + [i / spans for i in range(spans + 1)] + [1.0] * degree
    params = _samples(0.0, 1.0, r)
    spans_t, values, derivs = basis_table(degree, knots, n, params)
    return params, spans_t, values, derivs


def _homogeneous(atlas: AtlasSurface) -> list[list[float]]:
    """``(w x, w y, w z[, w])`` of every control point, component-major (global order)."""
    points = [*atlas.vertices, *atlas.edge_points, *atlas.face_points]
    comps = [[p[c] for p in points] for c in range(3)]
    if atlas.weights is None:
        return comps
    w = atlas.weights
    return [[a * b for a, b in zip(w, comp, strict=True)] for comp in comps] + [list(w)]


#: patches blended together by the pure-Python evaluator: long enough rows that the
#: per-call overhead vanishes, short enough that its lists stay a few MB
PATCHES_PER_BATCH = 256


def _evaluate_python(atlas: AtlasSurface, comps: list[list[float]], patches: list[int],
                     r: int, tol: float) -> dict[int, tuple[list, list, list]]:
    """``{f: (positions, unit normals, degenerate)}`` of the ``r x r`` grid of each patch:
    ``3 r^2`` floats each, row-major in ``i`` (``u``); ``degenerate`` lists the vertices
    whose ``|C_u x C_v|`` is at most ``tol`` (normal left ``0, 0, 0``).

    All patches share the knots and the parameters, so a batch of ``B`` patches is blended
    as one: along ``v``, ``T_{a f}(v_j) = sum_k N_k(v_j) P^w_{f, a, span_j - d + k}`` for
    every control row ``a`` of every patch at once, one written-out combination with the
    scalars ``N_k(v_j)`` per ``v_j`` (``client_py._kernel_python``'s ``_combine``) over the
    strided slices ``P^w_{., ., span_j - d + k}`` of the batch's control points (ordered
    ``(a, f, b)``); along ``u``, grid row ``i`` of all ``B`` patches is one call of the
    kernel's row evaluator over ``B r`` vertices with the shared ``N_a(u_i)``.
    """
    d, n = atlas.degree, atlas.side
    _, spans_t, N, dN = _tables(d, atlas.spans, r)
    rational = atlas.weights is not None
    evaluate_row = _kernel_python._row_evaluator(d, rational)
    combine = _kernel_python._combine(d + 1)
    out = {}
    for first in range(0, len(patches), PATCHES_PER_BATCH):
        batch = patches[first : first + PATCHES_PER_BATCH]
        count = len(batch)
        rows_all = n * count  # control rows (a, f) of the batch
        # control point (f, a, b) of the batch at (a count + f) n + b: rows a of all patches
        flat = list(chain.from_iterable(map(atlas.flat_patch_indices, batch)))
        flat = swap_blocks(flat, count, n, n)
        blended = []
        for comp in comps:
            mine = list(map(comp.__getitem__, flat))
            # column b of every control row: the terms of each v_j's span
            columns = [mine[b::n] for b in range(n)]
            values, derivatives = [], []
            for span, nv_j, dnv_j in zip(spans_t, N, dN, strict=True):
                window = columns[span - d : span + 1]
                values += combine(nv_j, window)
                derivatives += combine(dnv_j, window)
            # (j, a, f) -> (a, f, j): control row a of every patch, sampled at every v_j
            blended.append((swap_blocks(values, r, rows_all, 1),
                            swap_blocks(derivatives, r, rows_all, 1)))
        width = count * r  # one control row of every patch, sampled at every v_j
        pos_rows, nrm_rows, bad = [], [], []
        for i, (span, nu_i, dnu_i) in enumerate(zip(spans_t, N, dN, strict=True)):
            lo = span - d
            rows = [vals[(lo + k) * width : (lo + k + 1) * width]
                    for vals, _ in blended for k in range(d + 1)]
            drows = [dvals[(lo + k) * width : (lo + k + 1) * width]
                     for _, dvals in blended for k in range(d + 1)]
            pos: list[float] = []
            nrm: list[float] = []
            row_bad: list[int] = []
            evaluate_row(nu_i, dnu_i, rows, drows, tol, pos, nrm, row_bad)
            pos_rows.append(pos)
            nrm_rows.append(nrm)
            bad += [(i, b) for b in row_bad]
        # the rows (i, patch, j) reordered to (patch, i, j) at once, then cut per patch
        size = 3 * r * r
        pos_all = swap_blocks(list(chain.from_iterable(pos_rows)), r, count, 3 * r)
        nrm_all = swap_blocks(list(chain.from_iterable(nrm_rows)), r, count, 3 * r)
        for g, f in enumerate(batch):
            out[f] = (pos_all[g * size : (g + 1) * size], nrm_all[g * size : (g + 1) * size],
                      [])
        for i, b in bad:
            g, j = divmod(b, r)
            out[batch[g]][2].append(i * r + j)
    return out


def _evaluate_numpy(atlas: AtlasSurface, comps: list[list[float]], patches: list[int],
                    r: int, tol: float, backend) -> dict[int, tuple[list, list, list]]:
    """:func:`_evaluate_python`'s contract, all patches at once, by the numpy kernel
    (``client_py._kernel_numpy.atlas_patch_grids``: ``S^w = B P^w B^T``)."""
    _, spans_t, N, dN = _tables(atlas.degree, atlas.spans, r)
    index = [atlas.patch_indices(f) for f in patches]
    grids = backend.atlas_patch_grids(comps, index, atlas.weights is not None, atlas.degree,
                                      atlas.side, spans_t, N, dN, tol)
    return dict(zip(patches, grids, strict=True))


def _normal_tolerance(comps: list[list[float]]) -> float:
    """``NORMAL_TOLERANCE d^2`` with ``d`` the diagonal plus the largest coordinate of all
    the control points: ``client_py.surface.normal_tolerance``'s rule on ``[0, 1]^2``, over
    the whole atlas (a patch's own box would only lower it)."""
    xyz = comps[:3] if len(comps) == 3 else [[a / w for a, w in zip(c, comps[3], strict=True)]
                                             for c in comps[:3]]
    lows, highs = [min(c) for c in xyz], [max(c) for c in xyz]
    diagonal = math.sqrt(sum((b - a) ** 2 for a, b in zip(lows, highs, strict=True)))
    d = diagonal + max(abs(c) for c in lows + highs)
    return NORMAL_TOLERANCE * d * d


#: the last atlas :func:`_atlas_tolerance` was asked for (a weak reference) and its tolerance
_last_tolerance: list = [None, 0.0]


def _atlas_tolerance(atlas: AtlasSurface) -> float:
    """:func:`_normal_tolerance` of a whole atlas, remembered for the last atlas asked:
    :func:`atlas_parts` needs it at every refinement of the viewer's one atlas, and it reads
    every control point (50 ms of the 24,000-patch smooth bases)."""
    held, tol = _last_tolerance
    if held is None or held() is not atlas:
        tol = _normal_tolerance(_homogeneous(atlas))
        _last_tolerance[:] = [weakref.ref(atlas), tol]
    return tol


# ------------------------------------------------------------------ the welded mesh
class _Layout:
    """Vertex numbering of the welded mesh: corners, edges, patches (module docstring)."""

    def __init__(self, atlas: AtlasSurface, res: list[int]) -> None:
        self.atlas, self.res = atlas, res
        self.table = atlas.edges
        self.fine, self.coarse = _edge_resolutions(atlas, res)
        used = sorted({k for quad in atlas.quads for k in quad})
        self.corner = {v: i for i, v in enumerate(used)}
        self.used = used
        count = len(used)
        self.edge_base = []
        # per edge, its R_e vertices from lo and whether each is evaluated: every side of a
        # patch on it is a strided slice of these
        self.edge_nodes: list[list[int]] = []
        self.edge_evaluated: list[tuple[bool, ...]] = []
        for (lo, hi), fine, coarse in zip(self.table.edges, self.fine, self.coarse,
                                          strict=True):
            self.edge_base.append(count)
            self.edge_nodes.append([self.corner[lo], *range(count, count + fine - 2),
                                    self.corner[hi]])
            self.edge_evaluated.append(_evaluated_flags(fine, (fine - 1) // (coarse - 1)))
            count += fine - 2
        self.border_count = count
        self.face_base = []
        for r in res:
            self.face_base.append(count)
            count += (r - 2) ** 2
        self.count = count

    def edge_node(self, e: int, K: int) -> int:
        """Vertex ``K`` (``0..R_e - 1``, from ``lo``) of edge ``e``."""
        return self.edge_nodes[e][K]

    def side_nodes(self, f: int, k: int) -> tuple[list[int], tuple[bool, ...]]:
        """The vertex of each sample ``t = 0..r_f - 1`` of side ``k`` of patch ``f``, and
        whether it is *evaluated* (at the edge's coarser resolution) or lies between two
        evaluated vertices (a finer neighbour's)."""
        e, reverse = self.table.sides[f][k]
        return self.edge_samples(e, reverse, self.res[f])

    def edge_samples(self, e: int, reverse: bool, r: int) -> tuple[list[int], tuple[bool, ...]]:
        """:meth:`side_nodes` of a side of ``r`` samples on edge ``e``, from its ``hi`` end
        when ``reverse``."""
        step = (self.fine[e] - 1) // (r - 1)
        if reverse:  # from hi: the edge's last vertex is its hi corner
            step = -step
        return self.edge_nodes[e][::step], self.edge_evaluated[e][::step]

    def finer_sides(self, f: int) -> list[bool]:
        """Whether each side of patch ``f`` has a finer neighbour (its cells there are fans)."""
        return [self.fine[self.table.sides[f][k][0]] > self.res[f] for k in range(4)]

    def between(self, f: int, k: int, t0: int, t1: int) -> list[int]:
        """The edge vertices strictly between samples ``t0`` and ``t1`` of side ``k`` of
        patch ``f``, in the order from ``t0`` to ``t1``."""
        e, reverse = self.table.sides[f][k]
        fine = self.fine[e]
        step = (fine - 1) // (self.res[f] - 1)
        K0, K1 = t0 * step, t1 * step
        if reverse:
            K0, K1 = fine - 1 - K0, fine - 1 - K1
        way = 1 if K1 > K0 else -1
        return [self.edge_node(e, K) for K in range(K0 + way, K1, way)]

    def patch_vertices(self, f: int) -> tuple[list[int], tuple[tuple, tuple, tuple]]:
        """``(ids, border)``: the global vertex of each sample ``(i, j)`` of patch ``f`` at
        ``i r + j``, and its border samples, each corner once, as ``(slots, vertices,
        evaluated)`` tuples (``zip`` them: sample ``(slot, vertex, evaluated)``)."""
        r = self.res[f]
        ids = [0] * (r * r)
        base, inner = self.face_base[f], r - 2
        for i in range(1, r - 1):
            ids[i * r + 1 : i * r + r - 1] = range(base + (i - 1) * inner,
                                                   base + i * inner)
        nodes: list[int] = []  # sample t of side k at k r + t
        evaluated: list[bool] = []
        for side, (e, reverse) in zip(_side_slices(r), self.table.sides[f], strict=True):
            side_nodes, side_evaluated = self.edge_samples(e, reverse, r)
            ids[side] = side_nodes
            nodes += side_nodes
            evaluated += side_evaluated
        pick = _border_picker(r)
        return ids, (_border_samples(r)[0], pick(nodes), pick(evaluated))

    def in_between(self) -> tuple[list[int], list[int], list[int], list[float]]:
        """The edge vertices between two evaluated ones (a finer side's, where the edge is
        evaluated at its coarser side's resolution): ``(vertex, a, b, s)`` lists, the vertex
        at ``(1 - s) X_a + s X_b`` on the segment of its evaluated neighbours ``a``, ``b``."""
        nodes, lows, highs, shares = [], [], [], []
        for e, (fine, coarse) in enumerate(zip(self.fine, self.coarse, strict=True)):
            step = (fine - 1) // (coarse - 1)
            for K in range(1, fine - 1) if step > 1 else ():
                if K % step:
                    K0 = K - K % step
                    nodes.append(self.edge_node(e, K))
                    lows.append(self.edge_node(e, K0))
                    highs.append(self.edge_node(e, K0 + step))
                    shares.append((K - K0) / step)
        return nodes, lows, highs, shares


@lru_cache(maxsize=64)
def _evaluated_flags(fine: int, step: int) -> tuple[bool, ...]:
    """Whether each of the ``fine`` vertices of an edge evaluated every ``step`` of them is
    evaluated (``K % step == 0``)."""
    return tuple(K % step == 0 for K in range(fine))


@lru_cache(maxsize=64)
def _side_slices(r: int) -> tuple[slice, ...]:
    """Each side's samples (``SIDES`` order: ``v = 0``, ``u = 1``, ``v = 1``, ``u = 0``)
    as a slice of the ``r x r`` grid's slots ``i r + j``, along increasing ``u`` or ``v``."""
    last = r - 1
    return slice(0, None, r), slice(last * r, None), slice(last, None, r), slice(0, r)


@lru_cache(maxsize=64)
def _side_slots(r: int) -> tuple[tuple[int, ...], ...]:
    """Grid slots ``i r + j`` of sample ``t`` along each side (``SIDES`` order): those of
    :func:`_side_slices`."""
    return tuple(tuple(range(r * r)[side]) for side in _side_slices(r))


@lru_cache(maxsize=64)
def _border_samples(r: int) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """A patch's border samples in the weld's order, each corner once (sides 0 and 2 hold
    the four corners): their grid slots ``i r + j``, and where each is in its sides' nodes
    listed side after side (``k r + t`` for sample ``t`` of side ``k``)."""
    picks = tuple(k * r + t for k in range(4) for t in range(r)
                  if k in (0, 2) or 0 < t < r - 1)
    sides = _side_slots(r)
    return tuple(sides[k // r][k % r] for k in picks), picks


@lru_cache(maxsize=64)
def _border_picker(r: int) -> itemgetter:
    """The gatherer of a patch's border samples (:func:`_border_samples`) from its sides'
    samples listed side after side."""
    return itemgetter(*_border_samples(r)[1])


@lru_cache(maxsize=64)
def _interior(r: int) -> tuple[itemgetter, itemgetter, array]:
    """Gatherers of the ``(r - 2)^2`` interior samples of an ``r x r`` grid (row-major):
    their ``x, y, z`` triples, and their scalars each three times (one per ``x, y, z``);
    and their ``(u, v)`` block."""
    slots = [i * r + j for i in range(1, r - 1) for j in range(1, r - 1)]
    params = _samples(0.0, 1.0, r)
    uv = array("d", [t for slot in slots for t in (params[slot // r], params[slot % r])])
    return (itemgetter(*[3 * s + c for s in slots for c in range(3)]),
            itemgetter(*[s for s in slots for _ in range(3)]), uv)


@lru_cache(maxsize=64)
def _zeros(count: int) -> tuple[float, ...]:
    """``count`` times ``+0.0``."""
    return (0.0,) * count


@lru_cache(maxsize=64)
def _slot_uvs(r: int) -> tuple[tuple[float, float], ...]:
    """``(u_i, v_j)`` of each slot ``i r + j`` of an ``r x r`` grid."""
    params = _samples(0.0, 1.0, r)
    return tuple((u, v) for u in params for v in params)


def _drawn_normals(backend, coords: list[array], ids: Mapping[int, list[int]],
                   grids: Mapping[int, tuple], res: list[int], patches: Sequence[int]
                   ) -> dict[int, list[float]]:
    """``{f: unit normals}`` of the drawn surface (the welded positions, ``coords`` their
    ``x``, ``y`` and ``z``) by differences on the whole grid of each of ``patches`` (``ids``:
    its vertices, ``grids``: its unit base normals, kept at a pole): a list in slot order,
    of the kernel's float32 normals. Per resolution, the patches' grids side by side
    as the panels of one ``displace_grid`` call (each panel's normals are those of its grid
    alone): one call per patch cost more than its arithmetic."""
    by_res: dict[int, list[int]] = {}
    for f in patches:
        by_res.setdefault(res[f], []).append(f)
    out = {}
    for r, some in by_res.items():
        count, size = len(some), 3 * r * r
        # row i of every patch in turn: from (patch, row) order to (row, patch)
        nodes = list(chain.from_iterable(ids[f] for f in some))
        nodes = swap_blocks(nodes, count, r, r)
        grid = array("d", bytes(8 * size * count))
        for c, xs in enumerate(coords):
            grid[c::3] = array("d", map(xs.__getitem__, nodes))
        base = list(chain.from_iterable(grids[f][1] for f in some))
        base = array("d", swap_blocks(base, count, r, 3 * r))
        shaded = swap_blocks(backend.displace_grid(
            grid, base, array("d", bytes(8 * count * r * r)), r, count * r,
            (0, r, 0, count * r), r, with_positions=False)[1], r, count, 3 * r)
        for g, f in enumerate(some):
            out[f] = shaded[g * size : (g + 1) * size]
    return out


def _units(xs: Sequence[float], ys: Sequence[float], zs: Sequence[float]) -> list[float]:
    """``x / |v|, y / |v|, z / |v|`` of each vector ``v = (x, y, z)`` given a component at a
    time, ``|v| = sqrt(x x + y y + z z)``, interleaved; ``0, 0, 0`` where ``|v| = 0``."""
    sqrt = math.sqrt
    out: list[float] = []
    for x, y, z in zip(xs, ys, zs, strict=True):
        length = sqrt(x * x + y * y + z * z)
        if length != 0.0:
            out += (x / length, y / length, z / length)
        else:
            out += (0.0, 0.0, 0.0)
    return out


def tessellate_atlas(atlas: AtlasSurface, resolution: int | Sequence[int],
                     detail: Mapping[int, Sequence[DetailTile]] | None = None,
                     kernel: str | None = None,
                     progress: Callable[[float], object] | None = None,
                     normals: bool = True) -> AtlasMesh:
    """One welded, watertight mesh of ``atlas`` (module docstring for the rules).

    Parameters
    ----------
    atlas : AtlasSurface
    resolution : int or sequence of int
        ``r >= 2`` samples per patch side, for all patches or one per patch; neighbours'
        ``r - 1`` must differ by a power of 2 (``2^k c + 1``).
    detail : mapping of int to sequence of DetailTile, optional
        Patch ``f`` -> its detail tiles over its own ``[0, 1]^2``.
    kernel : {'python', 'numpy'}, optional
        Force an evaluation kernel; default the one ``client_py._kernel`` selects.
    progress : callable, optional
        Called with the share done, ``0 < x <= 1``, after every :data:`PROGRESS_BATCH`
        patches evaluated (:data:`PROGRESS_EVALUATION` of the work) and displaced (the
        rest): the viewer's "Download PLY" shows it.
    normals : bool, optional
        ``False``: no shading normals (``normals`` left empty), for a caller that only
        measures the mesh (``fitter.fitting.atlas.measure``). The drawn normals by
        differences and the border vertices' normalised sums are then skipped; the unit
        base normals the detail displaces along are still computed, so the positions,
        ``(u, v)``, triangles and patches are those of ``normals=True``, bit for bit.

    Returns
    -------
    AtlasMesh
        ``V_used + sum_e (R_e - 2) + sum_f (r_f - 2)^2`` vertices (and one more per cell of
        a 2-sample patch bordered by finer neighbours on opposite sides) and
        ``2 sum_f (r_f - 1)^2`` triangles plus the fans at resolution changes, less the
        cells the tiles' walls masks leave out (their vertices stay).
    """
    if not isinstance(atlas, AtlasSurface):
        raise ValueError(f"atlas must be an AtlasSurface, got {type(atlas).__name__}")
    res = _check_resolutions(atlas, resolution)
    tiles = _check_detail(atlas, detail)
    return _welded_mesh(atlas, res, tiles, kernel, progress=progress, normals=normals)[0]


def patches_without_normal(atlas: AtlasSurface, resolution: int | Sequence[int],
                           kernel: str | None = None) -> list[int]:
    """The patches for which :func:`tessellate_atlas` at ``resolution`` (without detail)
    raises ``ValueError``: a grid sample whose ``|C_u x C_v|`` is at most the atlas's
    tolerance (:func:`_normal_tolerance`, the same kernel's evaluation) and where the
    limit normal from inside the patch (:func:`_pole_normal`) does not exist either: the
    patch collapsed to a line or a point. Empty: the tessellation draws every patch.

    The same evaluation and rule as the tessellation, without numbering, welding or
    packing its mesh (``fitter``'s check of every base it rounds: the 15-scan Happy
    Buddha's 2,451-patch base at 9 samples a side, numpy kernel, 0.16 s where the
    tessellation took 0.31-0.38 s, load 1).
    """
    if not isinstance(atlas, AtlasSurface):
        raise ValueError(f"atlas must be an AtlasSurface, got {type(atlas).__name__}")
    res = _check_resolutions(atlas, resolution)
    _edge_resolutions(atlas, res)  # mixed resolutions refused as the tessellation refuses
    backend = _kernel.backend(kernel)
    comps = _homogeneous(atlas)
    tol = _normal_tolerance(comps)
    by_res: dict[int, list[int]] = {}
    for f, r in enumerate(res):
        by_res.setdefault(r, []).append(f)
    refused = []
    for r, patches in sorted(by_res.items()):
        params, spans_t, N, dN = _tables(atlas.degree, atlas.spans, r)
        if backend is _kernel_python:
            degenerate = [bad for _, _, bad in
                          _evaluate_python(atlas, comps, patches, r, tol).values()]
        else:  # the arrays _weld_plan evaluates, not made into lists
            degenerate = backend.atlas_patch_arrays(
                comps, [atlas.patch_indices(f) for f in patches], atlas.weights is not None,
                atlas.degree, atlas.side, spans_t, N, dN, tol)[2]
        for f, bad in zip(patches, degenerate, strict=True):
            if bad:
                surface = atlas.patch_surface(f)
                try:
                    for k in bad:
                        _pole_normal(surface, params, r, k)
                except ValueError:
                    refused.append(f)
    return sorted(refused)


def _pole_normal(surface, params: Sequence[float], r: int, k: int
                 ) -> tuple[float, float, float]:
    """The unit normal at sample ``k = i r + j`` of a patch's ``r x r`` grid where
    ``|C_u x C_v|`` vanishes (a pole): ``surface.normal``'s limit from inside the patch,
    ``ValueError`` where none exists (``client_py.surface.NurbsSurface.normal``)."""
    return surface.normal(params[k // r], params[k % r])


class PatchGrids:
    """The evaluated grids (points and unit normals) and displacement grids of an atlas's
    patches, kept between the meshes :func:`tessellate_atlas_parts` makes of one atlas: a
    patch's depend on its own resolution and tiles alone, and a refinement re-makes the
    groups around the one that changed, whose patches are mostly as before. Least recently
    used entries are dropped beyond ``max_samples`` grid samples (about 56 bytes each).
    """

    def __init__(self, max_samples: int = 1 << 19) -> None:
        self.max_samples = max_samples
        self._items: OrderedDict = OrderedDict()  # key -> (samples, value)
        self._samples = 0

    def get(self, key: tuple) -> object | None:
        item = self._items.get(key)
        if item is None:
            return None
        self._items.move_to_end(key)
        return item[1]

    def holds(self, key: tuple) -> bool:
        """Whether ``key`` is held (without making it the most recently used)."""
        return key in self._items

    def first_kept(self, samples: Sequence[int], later: int = 0) -> int:
        """The first of puts of ``samples[k]`` samples, in order and followed by puts of at
        least ``later`` samples more, that outlives them: entry ``k`` is dropped by the
        puts after it when ``sum(samples[k:]) + later > max_samples`` and one comes after
        it (the least recently used go first, and no put makes room for an older one), so
        the caller need not make the copies of those before it."""
        total = later
        for k in range(len(samples) - 1, -1, -1):
            total += samples[k]
            if total > self.max_samples and (k < len(samples) - 1 or later > 0):
                return k + 1
        return 0

    def put(self, key: tuple, value: object, samples: int) -> None:
        old = self._items.pop(key, None)
        if old is not None:
            self._samples -= old[0]
        self._items[key] = (samples, value)
        self._samples += samples
        while self._samples > self.max_samples and len(self._items) > 1:
            _, (dropped, _) = self._items.popitem(last=False)
            self._samples -= dropped


def _detail_key(names: Sequence[int], res: list[int], tiles: dict[int, list[DetailTile]],
                f: int) -> tuple:
    """The :class:`PatchGrids` key of patch ``f``'s summed tiles (:func:`_displacements`)."""
    return ("detail", names[f], res[f], tuple(map(id, tiles[f])))


def _displacements(atlas: AtlasSurface, res: list[int], tiles: dict[int, list[DetailTile]],
                   kernel: str | None, names: Sequence[int], cache: PatchGrids | None
                   ) -> dict[int, array]:
    """``{f: the sum of patch f's tiles on its grid}`` (``displacement_grid``) for the patches
    with tiles; those not held in ``cache`` (under their ``names``, resolution and tiles)
    are summed :data:`PATCHES_PER_BATCH` patches of one resolution at a time
    (``displacement_grids``: their tiles that share their knots in one kernel call) and
    put there (but those the later ones would drop at once: :meth:`PatchGrids.first_kept`)."""
    key = partial(_detail_key, names, res, tiles)
    out: dict[int, array] = {}
    wanted: dict[int, list[int]] = {}  # r -> the patches to sum
    for f in sorted(tiles):
        held = cache and cache.get(key(f))
        if held:
            out[f] = held[1]
        else:
            wanted.setdefault(res[f], []).append(f)
    order = list(chain.from_iterable(wanted.values()))  # in the order they are put
    kept = set(order[cache.first_kept([res[f] ** 2 for f in order]):] if cache else ())
    for r, patches in wanted.items():
        params = _tables(atlas.degree, atlas.spans, r)[0]
        for start in range(0, len(patches), PATCHES_PER_BATCH):
            some = patches[start : start + PATCHES_PER_BATCH]
            sums = displacement_grids([tiles[f] for f in some], params, params, kernel)
            for f, disp in zip(some, sums, strict=True):
                out[f] = disp
                if f in kept:  # the tiles stay referenced: their ids stay theirs
                    cache.put(key(f), (tuple(tiles[f]), array("d", disp)), r * r)
    return out


@without_cyclic_gc()
def _welded_mesh(atlas: AtlasSurface, res: list[int], tiles: dict[int, list[DetailTile]],
                 kernel: str | None, tol: float | None = None,
                 drawn: Sequence[Sequence[int]] | None = None,
                 names: Sequence[int] | None = None,
                 cache: PatchGrids | None = None,
                 progress: Callable[[float], object] | None = None,
                 weld: str | None = None, normals: bool = True) -> list[AtlasMesh]:
    """:func:`tessellate_atlas` of checked arguments (one mesh); ``tol``: the
    degenerate-normal tolerance (default :func:`_normal_tolerance` of ``atlas``); ``drawn``:
    instead, one mesh per sequence of patches (in increasing order): their triangles, with
    only the vertices these use, in increasing order of their number in the whole mesh
    (:func:`tessellate_atlas_parts`);
    ``cache``: patch grids kept between calls, under the patches' ``names`` (default their
    indices); ``progress``, ``normals``: :func:`tessellate_atlas`'s (``normals=False``
    with ``drawn``: empty normals for every part).

    The whole mesh (no ``drawn``, no ``cache``) with the numpy kernel is welded by the
    kernel (``_kernel_numpy.weld_atlas`` of :func:`_weld_plan`: the same bytes at array
    speed); ``weld='python'`` welds it here whatever the kernel (the two are compared in
    tests/test_atlas_mesh.py).

    The cyclic garbage collector is paused meanwhile (``client_py.gc_pause``):
    the per-patch lists and tuples of a 24,000-patch smooth base, none in a reference
    cycle, set off full collections that took a fifth of the time (the bunny's welded base,
    pure-Python kernel: 1.45 s, 1.13 s with the collector paused)."""
    backend = _kernel.backend(kernel)
    layout = _Layout(atlas, res)
    comps = _homogeneous(atlas)
    if tol is None:
        tol = _normal_tolerance(comps)
    surfaces: dict[int, object] = {}

    def surface(f):
        if f not in surfaces:
            surfaces[f] = atlas.patch_surface(f)
        return surfaces[f]

    if weld not in (None, "python"):
        raise ValueError(f"weld must be None or 'python', got {weld!r}")
    if backend is not _kernel_python and weld is None and drawn is None and cache is None:
        plan = _weld_plan(atlas, layout, comps, tiles, kernel, backend, tol, surface, progress,
                          normals)
        positions, shading, uvs, indices, owners = backend.weld_atlas(plan)
        return [AtlasMesh(positions, shading, uvs, indices, patches=owners)]
    shade = normals
    evaluate = (_evaluate_python if backend is _kernel_python
                else partial(_evaluate_numpy, backend=backend))

    names = names or range(len(res))
    by_res: dict[int, list[int]] = {}
    grids: dict[int, tuple] = {}  # patch -> (points, unit normals) of its grid
    for f, r in enumerate(res):
        held = cache and cache.get(("grid", names[f], r))
        if held:
            grids[f] = held
        else:
            by_res.setdefault(r, []).append(f)
    kept: set[int] = set()  # the grids to put in the cache: those its later puts keep
    if cache is not None:
        order = list(chain.from_iterable(patches for _, patches in sorted(by_res.items())))
        # the tiles' sums not held are put after the grids
        later = sum(res[f] ** 2 for f in tiles if not cache.holds(_detail_key(names, res,
                                                                               tiles, f)))
        kept = set(order[cache.first_kept([res[f] ** 2 for f in order], later):])
    batch = PROGRESS_BATCH if progress is not None else len(res)
    for r, patches in sorted(by_res.items()):
        params = _tables(atlas.degree, atlas.spans, r)[0]
        for start in range(0, len(patches), batch):
            some = patches[start:start + batch]
            for f, (pos, nrm, bad) in evaluate(atlas, comps, some, r, tol).items():
                for k in bad:  # a pole: the limit normal from inside the patch
                    nrm[3 * k : 3 * k + 3] = _pole_normal(surface(f), params, r, k)
                grids[f] = (pos, nrm)
                if f in kept:
                    cache.put(("grid", names[f], r), (array("d", pos), array("d", nrm)),
                              r * r)
            if progress is not None:
                progress(PROGRESS_EVALUATION * len(grids) / len(res))

    count = layout.count
    positions = array("d", bytes(24 * count))
    normals = array("d", bytes(24 * count))
    uvs = array("d", bytes(16 * count))
    owners = array("I", bytes(4 * count))
    n_border = layout.border_count
    seen = bytearray(n_border)  # whether a border vertex has had its first sampler
    # the border vertices' sums, x, y and z apart, in arrays: their values stay together
    # in memory (list items made one by one scatter, and every later pass over them waits)
    shift = array("d", bytes(8 * n_border))  # sum of the samplers' displacements
    direction = [array("d", bytes(8 * n_border)) for _ in range(3)]  # of their unit normals
    samplers = [0] * n_border
    # sum of the unit normals of the drawn surface
    shading = [array("d", bytes(8 * n_border)) for _ in range(3)]

    ids, borders = {}, {}
    mine = range(len(res)) if drawn is None else set(chain.from_iterable(drawn))
    for f in range(len(res)):
        ids[f], borders[f] = layout.patch_vertices(f)
    displacements = _displacements(atlas, res, tiles, kernel, names, cache)
    for f, r in enumerate(res):
        if progress is not None and f % PROGRESS_BATCH == PROGRESS_BATCH - 1:
            progress(PROGRESS_EVALUATION + (1 - PROGRESS_EVALUATION) * f / len(res))
        pos, nrm = grids[f]
        disp = displacements.get(f)
        # interior vertices: one contiguous block of the patch, gathered at C speed
        at, block = layout.face_base[f], 3 * (r - 2) ** 2
        if block and (f in mine or tiles):  # else never read
            take3, take_thrice, block_uvs = _interior(r)
            inner_pos, inner_nrm = take3(pos), take3(nrm)
            if disp is not None:
                d3 = take_thrice(disp)
                inner_pos = [p + d * n for p, d, n in zip(inner_pos, d3, inner_nrm, strict=True)]
            positions[3 * at : 3 * at + block] = array("d", inner_pos)
            normals[3 * at : 3 * at + block] = array("d", inner_nrm)
            uvs[2 * at : 2 * at + 2 * block // 3] = block_uvs
            owners[at : at + block // 3] = array("I", [f]) * (block // 3)
        # border samples: the first sampler of a welded vertex gives its (u, v), its patch
        # and, when evaluated, its base point (an in-between vertex's is its segment's,
        # below); then each sampler adds to the vertex's sums
        slots, nodes, evaluated = borders[f]
        slot_uvs = _slot_uvs(r)
        for slot, node, on in zip(slots, nodes, evaluated, strict=True):
            if not seen[node]:
                seen[node] = 1
                owners[node] = f
                m = 2 * node
                uvs[m], uvs[m + 1] = slot_uvs[slot]
                if on:
                    k, m = 3 * slot, 3 * node
                    positions[m], positions[m + 1] = pos[k], pos[k + 1]
                    positions[m + 2] = pos[k + 2]
        nx, ny, nz = nrm[0::3], nrm[1::3], nrm[2::3]
        if tiles:  # displaced along the mean normal (the drawn normals come by differences)
            sx, sy, sz = direction
            if not all(evaluated):  # an in-between vertex: its segment's, not summed
                slots = [slot for slot, on in zip(slots, evaluated, strict=True) if on]
                nodes = [node for node, on in zip(nodes, evaluated, strict=True) if on]
            # a patch without detail adds +0.0 to the shifts, which changes none: a sum
            # from +0.0 is never -0.0
            shifts = disp if disp is not None else _zeros(r * r)
            for slot, node in zip(slots, nodes, strict=True):
                samplers[node] += 1
                shift[node] += shifts[slot]
                sx[node] += nx[slot]
                sy[node] += ny[slot]
                sz[node] += nz[slot]
        else:  # not displaced: shaded by the sum of the unit normals
            sx, sy, sz = shading
            for slot, node in zip(slots, nodes, strict=True):
                sx[node] += nx[slot]
                sy[node] += ny[slot]
                sz[node] += nz[slot]

    # welded border positions: evaluated vertices displaced (by the mean shift along the
    # normalised sum of the unit normals, a component at a time; a vertex whose shift sums
    # to zero stays where it is), then the in-between ones on their segment
    if tiles and n_border:
        units = _units(*direction)
        means = [s / k if s else 0.0 for s, k in zip(shift, samplers, strict=True)]
        for c in range(3):
            positions[c : 3 * n_border : 3] = array("d", [
                p + d * n if d_shift else p for p, d, n, d_shift in
                zip(positions[c : 3 * n_border : 3], means, units[c::3], shift, strict=True)])
    for node, a, b, s in zip(*layout.in_between(), strict=True):
        positions[3 * node : 3 * node + 3] = array("d", [
            (1 - s) * positions[3 * a + c] + s * positions[3 * b + c] for c in range(3)])

    if not shade:  # measured, not drawn: no shading normals
        normals = array("d")
    elif tiles:
        # normals of the drawn (displaced, welded) surface by differences within each patch,
        # on its whole grid, also for a patch not drawn (drawn's ring): those at the drawn
        # patches' vertices are what its window of them one sample wider would give, and
        # its others go to vertices no part keeps
        shading = [array("d", bytes(8 * n_border)) for _ in range(3)]
        sx, sy, sz = shading
        chunk_normals: dict[int, list] = {}  # a chunk of PATCHES_PER_BATCH patches' at a time
        coords = [positions[c::3] for c in range(3)]
        for f, r in enumerate(res):
            if f % PATCHES_PER_BATCH == 0:
                chunk_normals = _drawn_normals(backend, coords, ids, grids, res,
                                               range(f, min(f + PATCHES_PER_BATCH, len(res))))
            shaded = chunk_normals[f]
            if f in mine and r > 2:  # the whole grid in slot order: its interior block
                at = layout.face_base[f]
                normals[3 * at : 3 * at + 3 * (r - 2) ** 2] = array("d", _interior(r)[0](shaded))
            nx, ny, nz = shaded[0::3], shaded[1::3], shaded[2::3]
            for slot, g in zip(*borders[f][:2], strict=True):  # every border sample
                sx[g] += nx[slot]
                sy[g] += ny[slot]
                sz[g] += nz[slot]
    if shade and n_border:  # the border vertices' sums normalised
        normals[: 3 * n_border] = array("d", _units(*shading))

    centres = _Centres(surface, tiles, kernel, count)
    # per part, per patch: its triangles as (vertices, cells, whole), the triangles'
    # corners vertices[c] for c in cells (or the vertices themselves, cells None: a patch
    # fanned to finer sides), whole when they use every one of the vertices
    pieces: list[list[tuple[list[int], array | None, bool]]] = []
    whole_grids: dict[int, array] = {}  # r -> the triangles of every cell of an r x r grid
    for patches in [range(len(res))] if drawn is None else drawn:
        mine_pieces = []
        for f in patches:
            r, local = res[f], ids[f]
            finer = layout.finer_sides(f)
            kept = _drawn_cells(tiles.get(f), r, kernel)
            if not any(finer):
                if kept is None and r not in whole_grids:
                    whole_grids[r] = grid_indices(r, r, kernel=kernel)
                mine_pieces.append((local, whole_grids[r] if kept is None else kept,
                                    kept is None))
            else:
                mine_pieces.append((_patch_triangles(layout, f, r, local, finer, centres.add,
                                                     kept), None, True))
        pieces.append(mine_pieces)
    if centres.owners:
        positions.extend(centres.positions)
        normals.extend(centres.normals if shade else ())
        uvs.extend(centres.uvs)
        owners.extend(centres.owners)
    if drawn is None:
        indices = array("I")
        for vertices, cells, _ in pieces[0]:
            indices.extend(vertices if cells is None else map(vertices.__getitem__, cells))
        return [_packed(positions, normals, uvs, owners, indices)]
    meshes = []
    # x, y, z (u, v) of every vertex apart, so that a part's are gathered at C speed
    planes = [[values[c::width] for c in range(width)] if values else []
              for values, width in ((positions, 3), (normals, 3), (uvs, 2))]
    # the new number of each vertex of the part at hand (a list: read at C speed by map)
    number = [0] * len(owners)
    for part in pieces:
        # the vertices the part's triangles use, in order: every vertex of a patch whose
        # cells are all drawn (its r^2 ids, not its 6 (r - 1)^2 corners), else its corners
        used: set[int] = set()
        for vertices, cells, whole in part:
            used.update(vertices if whole else map(vertices.__getitem__, cells))
        if not used:  # every cell of the part left out (walls): an empty mesh
            meshes.append(_packed(array("d"), array("d"), array("d"), array("I"),
                                  array("I")))
            continue
        keep = sorted(used)
        for new, old in enumerate(keep):
            number[old] = new
        indices = array("I")
        for vertices, cells, _ in part:  # renumbered once per vertex, then the corners read
            renumbered = list(map(number.__getitem__, vertices))
            indices.extend(renumbered if cells is None else map(renumbered.__getitem__, cells))
        # gathered at C speed, each straight into float32 (the same rounding as _packed's)
        get = itemgetter(*keep) if len(keep) > 1 else itemgetter(slice(keep[0], keep[0] + 1))
        pos, nrm, uv = (_gathered(comps, get, len(keep)) for comps in planes)
        meshes.append(AtlasMesh(pos, nrm, uv, indices, patches=array("I", get(owners))))
    return meshes


def _gathered(planes: list[array], get: itemgetter, count: int) -> array:
    """The values of ``planes`` (one array per component) at the ``count`` vertices ``get``
    picks, the components interleaved (``x, y, z`` of each vertex in turn), as float32
    (``array('f')``, empty for no planes)."""
    width = len(planes)
    out = array("f", bytes(4 * width * count))
    for c, values in enumerate(planes):
        out[c::width] = array("f", get(values))
    return out


@dataclass
class _WeldGroup:
    """The patches of one resolution ``r`` in a :class:`_WeldPlan`.

    ``grid``: the kernel's ``atlas_patch_arrays`` (points, unit normals, and per patch the
    samples without a normal), ``pole_normals`` the limit normal of each of those;
    ``sides``: per patch, the vertex of sample ``t`` of each side ``k`` at ``(4 g + k) r +
    t`` (``_Layout.side_nodes``), ``evaluated`` their flags; ``border_slots``,
    ``border_picks``: :func:`_border_samples`; ``displacements``: per patch its tiles' sum
    on the grid (``array('d')``) or ``None``."""

    r: int
    patches: list[int]
    face_base: list[int]
    grid: tuple
    pole_normals: list[list[tuple[float, float, float]]]
    sides: array
    evaluated: bytearray
    border_slots: tuple[int, ...]
    border_picks: tuple[int, ...]
    displacements: list
    params: list[float]


@dataclass
class _WeldPlan:
    """What a kernel's ``weld_atlas`` needs to weld a whole atlas: ``count`` vertices of
    the layout (``n_border`` of them on corners and edges), the groups of patches by
    resolution, the in-between vertices (``_Layout.in_between``), whether normals are taken
    by differences of the displaced surface (any detail), the triangles of the patches with
    finer neighbours or walls masks (``{f: triangles}``, :func:`_patch_triangles`,
    :func:`_drawn_cells`), the centre vertices
    these add (``positions, normals, uvs, owners``, :class:`_Centres`), and whether shading
    normals are wanted at all (``shading``: :func:`tessellate_atlas`'s ``normals``)."""

    count: int
    n_border: int
    groups: list[_WeldGroup]
    between: tuple[list, list, list, list]
    by_differences: bool
    fans: dict[int, array]
    extra: tuple[list, list, list, list]
    shading: bool = True


def _weld_plan(atlas: AtlasSurface, layout: _Layout, comps: list[list[float]],
               tiles: dict[int, list[DetailTile]], kernel: str | None, backend, tol: float,
               surface: Callable, progress: Callable[[float], object] | None,
               shading: bool = True) -> _WeldPlan:
    """The :class:`_WeldPlan` of the whole atlas: every patch evaluated by the kernel
    (``atlas_patch_arrays``, by resolution, in :data:`PROGRESS_BATCH` patches when
    ``progress`` is given), its tiles summed on its grid, its sides' vertices numbered; the
    progress reports are :func:`_welded_mesh`'s; ``shading``: :attr:`_WeldPlan.shading`."""
    res = layout.res
    by_res: dict[int, list[int]] = {}
    for f, r in enumerate(res):
        by_res.setdefault(r, []).append(f)
    batch = PROGRESS_BATCH if progress is not None else len(res)
    grids: dict[int, list] = {}
    done = 0
    for r, patches in sorted(by_res.items()):
        _, spans_t, N, dN = _tables(atlas.degree, atlas.spans, r)
        parts = []
        for start in range(0, len(patches), batch):
            some = patches[start:start + batch]
            parts.append(backend.atlas_patch_arrays(
                comps, [atlas.patch_indices(f) for f in some], atlas.weights is not None,
                atlas.degree, atlas.side, spans_t, N, dN, tol))
            done += len(some)
            if progress is not None:
                progress(PROGRESS_EVALUATION * done / len(res))
        grids[r] = parts
    groups = []
    for r, patches in sorted(by_res.items()):
        params = _tables(atlas.degree, atlas.spans, r)[0]
        parts = grids.pop(r)
        grid = parts[0] if len(parts) == 1 else backend.join_patch_arrays(parts)
        groups.append(_WeldGroup(r, patches, [layout.face_base[f] for f in patches], grid,
                                 [], array("I"), bytearray(), *_border_samples(r), [],
                                 params))
    for f, r in enumerate(res):  # in patch order, as _welded_mesh reports its progress
        if progress is not None and f % PROGRESS_BATCH == PROGRESS_BATCH - 1:
            progress(PROGRESS_EVALUATION + (1 - PROGRESS_EVALUATION) * f / len(res))
        group = next(g for g in groups if g.r == r)
        g = len(group.displacements)
        params = group.params
        group.pole_normals.append([_pole_normal(surface(f), params, r, k)
                                   for k in group.grid[2][g]])
        for k in range(4):
            nodes, evaluated = layout.side_nodes(f, k)
            group.sides.extend(nodes)
            group.evaluated.extend(evaluated)
        group.displacements.append(displacement_grid(tiles[f], params, params, kernel)
                                   if f in tiles else None)
    centres = _Centres(surface, tiles, kernel, layout.count)
    fans = {}  # the patches whose triangles are not the whole grid's
    for f, r in enumerate(res):
        finer = layout.finer_sides(f)
        kept = _drawn_cells(tiles.get(f), r, kernel)
        if any(finer):
            fans[f] = array("I", _patch_triangles(layout, f, r, layout.patch_vertices(f)[0],
                                                  finer, centres.add, kept))
        elif kept is not None:
            fans[f] = array("I", map(layout.patch_vertices(f)[0].__getitem__, kept))
    return _WeldPlan(layout.count, layout.border_count, groups, layout.in_between(),
                     bool(tiles), fans,
                     (centres.positions, centres.normals, centres.uvs, centres.owners),
                     shading)


def _packed(positions: array, normals: array, uvs: array, owners: array,
            indices: array) -> AtlasMesh:
    """An :class:`AtlasMesh` of double-precision vertex arrays, stored as float32."""
    total = len(owners)
    pack = struct.Struct(f"={3 * total}f").pack
    try:
        out_positions = array("f", pack(*positions))
    except OverflowError:  # beyond float32: store inf, as fromlist() and numpy would
        out_positions = array("f", positions.tolist())
    return AtlasMesh(out_positions, array("f", pack(*normals)) if normals else array("f"),
                     array("f", struct.pack(f"={2 * total}f", *uvs)), indices,
                     patches=owners)


class _Centres:
    """The centre vertices of the cells of 2-sample patches between finer neighbours
    (:func:`_patch_triangles`), numbered after the ``count`` vertices of the layout: the
    surface at the cell's centre, displaced by the patch's tiles along its unit normal."""

    def __init__(self, surface: Callable, tiles: dict, kernel: str | None, count: int) -> None:
        self.surface, self.tiles, self.kernel, self.count = surface, tiles, kernel, count
        self.positions: list[float] = []
        self.normals: list[float] = []
        self.uvs: list[float] = []
        self.owners: list[int] = []

    def add(self, f: int, r: int, i: int, j: int) -> int:
        """The centre vertex of cell ``(i, j)`` of patch ``f`` (``r`` samples a side)."""
        u, v = (i + 0.5) / (r - 1), (j + 0.5) / (r - 1)
        point, n = self.surface(f).evaluate(u, v), self.surface(f).normal(u, v)
        if f in self.tiles:
            d = displacement_grid(self.tiles[f], [u], [v], self.kernel)[0]
            point = tuple(p + d * c for p, c in zip(point, n, strict=True))
        self.positions.extend(point)
        self.normals.extend(n)
        self.uvs.extend((u, v))
        self.owners.append(f)
        return self.count + len(self.owners) - 1


def _drawn_cells(tiles: Sequence[DetailTile] | None, r: int, kernel: str | None
                 ) -> array | None:
    """The triangles (grid slots ``i r + j``) of the cells of a patch's ``r x r`` grid that
    its tiles' walls masks leave drawn (``client_py.layers.drawn_cell_indices``); ``None``
    when no tile has a walls mask (every cell is drawn)."""
    if not tiles or all(tile.walls is None for tile in tiles):
        return None
    params = _samples(0.0, 1.0, r)
    return drawn_cell_indices(None, tiles, params, params, kernel)


def _patch_triangles(layout: _Layout, f: int, r: int, local: list[int], finer: list[bool],
                     centre, kept: array | None = None) -> list[int]:
    """Triangles of a patch with finer neighbours on the sides ``finer[k]``: whole cells
    as two triangles, border cells as a fan through the neighbour's extra vertices from a
    corner whose own two sides have none (or from the cell's centre, a new vertex, when no
    corner has: a 2-sample patch between finer neighbours). ``kept``: the drawn cells'
    triangles (:func:`_drawn_cells`; ``None``: every cell), whose first slots ``i r + j``
    name the cells drawn."""
    out: list[int] = []
    last = r - 2
    drawn = None if kept is None else set(kept[0::6])
    for i in range(r - 1):
        for j in range(r - 1):
            if drawn is not None and i * r + j not in drawn:
                continue
            a, b = local[i * r + j], local[(i + 1) * r + j]
            c, d = local[(i + 1) * r + j + 1], local[i * r + j + 1]
            # CCW in (u, v): a(i, j) -> b(i+1, j) -> c(i+1, j+1) -> d(i, j+1)
            ab = layout.between(f, 0, i, i + 1) if j == 0 and finer[0] else []
            bc = layout.between(f, 1, j, j + 1) if i == last and finer[1] else []
            cd = layout.between(f, 2, i + 1, i) if j == last and finer[2] else []
            da = layout.between(f, 3, j + 1, j) if i == 0 and finer[3] else []
            if not (ab or bc or cd or da):
                out += (a, b, d, d, b, c)
                continue
            loop = [a, *ab, b, *bc, c, *cd, d, *da]
            at = {a: 0, b: 1 + len(ab), c: 2 + len(ab) + len(bc),
                  d: 3 + len(ab) + len(bc) + len(cd)}
            for corner, clean in ((c, not (bc or cd)), (d, not (cd or da)),
                                  (b, not (ab or bc)), (a, not (da or ab))):
                if clean:
                    start = at[corner]
                    ring = loop[start:] + loop[:start]
                    for m in range(1, len(ring) - 1):
                        out += (corner, ring[m], ring[m + 1])
                    break
            else:
                z = centre(f, r, i, j)
                for m in range(len(loop)):
                    out += (z, loop[m], loop[(m + 1) % len(loop)])
    return out


def atlas_ply(atlas: AtlasSurface, resolution: int | Sequence[int],
              detail: Mapping[int, Sequence[DetailTile]] | None = None, binary: bool = True,
              comments: list[str] | None = None, kernel: str | None = None) -> bytes:
    """:func:`tessellate_atlas`'s mesh as one 3DHOP-ready PLY (``client_py.ply.write_ply``):
    float32 ``x, y, z, nx, ny, nz`` per vertex and the triangles."""
    return write_ply(tessellate_atlas(atlas, resolution, detail, kernel), binary,
                     comments=comments)


# ------------------------------------------------------------------ one group's share of it
@dataclass(frozen=True)
class AtlasPart:
    """Groups of patches of an atlas (detail groups) and the patches around them: all that
    their triangles in the welded mesh (:func:`tessellate_atlas`) depend on
    (:func:`tessellate_atlas_parts`).

    Attributes
    ----------
    atlas : AtlasSurface
        The groups' patches and their rings (:func:`atlas_ring`) as an atlas of their own, in
        the full atlas's patch order, on its layout vertices (unused ones stay, so vertex
        indices are the full atlas's), with their own edge numbering (``atlas_edges`` of
        their quads) and the control points of their edges and faces; the full atlas
        itself when that is every patch (the same numbers, without cutting them out).
    patches : tuple of int
        The full atlas's index of each patch of ``atlas`` (increasing).
    drawn : tuple of tuple of int
        Each group's patches, as indices into ``patches`` (increasing).
    patch_count : int
        Patches of the full atlas.
    rings : int
        Rings of patches around the part in ``atlas``.
    tolerance : float
        The full atlas's degenerate-normal tolerance (:func:`_normal_tolerance`).
    """

    atlas: AtlasSurface
    patches: tuple[int, ...]
    drawn: tuple[tuple[int, ...], ...]
    patch_count: int
    rings: int
    tolerance: float


def atlas_ring(atlas: AtlasSurface, patches: Sequence[int], rings: int = 1) -> list[int]:
    """``patches`` and every patch within ``rings`` vertex rings of them (ring 1: the
    patches sharing a layout vertex with one of ``patches``; ring ``k + 1``: those sharing
    one with ring ``k``), in increasing order."""
    around, quads = atlas.patches_around, atlas.quads
    found = set(patches)
    for _ in range(rings):
        found.update(g for f in list(found) for k in quads[f] for g in around[k])
    return sorted(found)


@without_cyclic_gc()
def atlas_parts(atlas: AtlasSurface, groups: Sequence[Sequence[int]],
                rings: int = 1) -> AtlasPart:
    """The groups of patches ``groups`` of ``atlas`` with ``rings`` rings of patches around
    them (:func:`atlas_ring`) as an :class:`AtlasPart`.

    One ring is all :func:`tessellate_atlas_parts` needs while every patch of it has at
    least 3 samples per side; with detail on 2-sample patches it needs two (a drawn normal
    by differences then reaches the far corners of the ring's patches).

    Raises
    ------
    ValueError
        A group without patches, a patch in two places or one that is no index of
        ``atlas``; ``rings`` not 1 or 2.
    """
    if not isinstance(atlas, AtlasSurface):
        raise ValueError(f"atlas must be an AtlasSurface, got {type(atlas).__name__}")
    if rings not in (1, 2) or isinstance(rings, bool):
        raise ValueError(f"rings = {rings!r}; 1 or 2 is needed")
    groups = [tuple(group) for group in groups]
    chosen = tuple(chain.from_iterable(groups))
    count = len(atlas.quads)
    if not groups or not all(groups):
        raise ValueError("a part needs groups of at least one patch")
    for f in chosen:
        if isinstance(f, bool) or not isinstance(f, int) or not 0 <= f < count:
            raise ValueError(f"part patch {f!r} is no patch index in 0..{count - 1}")
    if len(set(chosen)) != len(chosen):
        raise ValueError("a part lists a patch twice")
    # chosen holds distinct indices: all of them, or a ring to find
    ring = range(count) if len(chosen) == count else atlas_ring(atlas, chosen, rings)
    if len(ring) == count:  # every patch (the viewer's first close view): the atlas itself
        return AtlasPart(atlas, tuple(ring), tuple(tuple(sorted(group)) for group in groups),
                         count, rings, _atlas_tolerance(atlas))
    quads = [atlas.quads[f] for f in ring]
    table = atlas_edges(quads)
    full_edges = list(map(atlas.edge_numbers.__getitem__, table.edges))
    inner = atlas.side - 2
    edge_runs = [range(e * inner, (e + 1) * inner) for e in full_edges]
    face_runs = [range(f * inner * inner, (f + 1) * inner * inner) for f in ring]
    weights = None
    if atlas.weights is not None:
        w, vertex_count = atlas.weights, len(atlas.vertices)
        face_at = vertex_count + len(atlas.edge_points)
        weights = (w[:vertex_count] + [w[vertex_count + k] for run in edge_runs for k in run]
                   + [w[face_at + k] for run in face_runs for k in run])
    part = AtlasSurface._of_checked(atlas.degree, atlas.spans, atlas.vertices, quads,
                                    [atlas.edge_points[k] for run in edge_runs for k in run],
                                    [atlas.face_points[k] for run in face_runs for k in run],
                                    weights, table)
    at = {f: k for k, f in enumerate(ring)}
    return AtlasPart(part, tuple(ring), tuple(tuple(sorted(at[f] for f in group))
                                              for group in groups),
                     count, rings, _atlas_tolerance(atlas))


def tessellate_atlas_parts(part: AtlasPart, resolution: int | Sequence[int],
                           detail: Mapping[int, Sequence[DetailTile]] | None = None,
                           kernel: str | None = None, cache: PatchGrids | None = None
                           ) -> list[AtlasMesh]:
    """Per group of ``part``, its patches' triangles in :func:`tessellate_atlas` ``(atlas,
    resolution, detail)`` of the full atlas, with the vertices they use (renumbered in
    order): the same positions, normals, ``(u, v)`` and patches, bit for bit.

    Every rule of the welded mesh is local: a border vertex is placed and shaded by the
    patches that sample it (the mean of their displacements along the normalised mean of
    their normals; the normalised sum of their drawn normals), an edge is evaluated at its
    coarser side's resolution, and a drawn normal by differences reaches one sample into
    each patch. So the part's triangles depend only on the patches sharing a layout vertex
    with it (its ring): this is the welded mesh of the groups and their ring
    (``part.atlas``) with the full atlas's resolutions, detail and normal tolerance, cut
    into the groups' triangles (one evaluation for all the groups, their rings shared).
    Two groups' meshes share their seam vertices exactly, made together or apart (the same
    arithmetic on the same numbers, in the same order: the grid kernels evaluate each patch
    alike whatever else is in the batch), so they meet without a crack, and the groups of
    a partition of the atlas together are its welded mesh. A group's mesh depends on the
    resolutions and detail of its ring's patches too: a viewer redraws a group when its
    own or a neighbouring group's level changes.

    Parameters
    ----------
    part : AtlasPart
        From :func:`atlas_parts`.
    resolution : int or sequence of int
        Samples per patch side, for all patches or one per patch of the *full* atlas (as
        :func:`tessellate_atlas`; only the ring's are read).
    detail : mapping of int to sequence of DetailTile, optional
        Full-atlas patch index -> its tiles (only the ring's are read).
    kernel : {'python', 'numpy'}, optional
    cache : PatchGrids, optional
        Patch grids kept between the parts of one atlas (made with one kernel): a patch is
        evaluated, and its tiles summed, once per resolution and tiles.

    Returns
    -------
    list of AtlasMesh
        One per group of ``part``, in its order; ``patches`` holds the full atlas's patch
        indices.

    Raises
    ------
    ValueError
        Bad arguments (:func:`tessellate_atlas`'s checks), or detail on a 2-sample patch of
        a part of one ring.
    """
    if not isinstance(part, AtlasPart):
        raise ValueError(f"part must be an AtlasPart (atlas_parts), got {type(part).__name__}")
    if isinstance(resolution, int) and not isinstance(resolution, bool):
        resolution = [resolution] * part.patch_count
    elif isinstance(resolution, Sequence) and not isinstance(resolution, str | bytes) \
            and len(resolution) != part.patch_count:
        raise ValueError(f"resolution has {len(resolution)} values; the atlas has "
                         f"{part.patch_count} patches (give one int, or one per patch)")
    elif not isinstance(resolution, Sequence):
        raise ValueError(f"resolution must be an int or a sequence of ints, got {resolution!r}")
    atlas = part.atlas
    res = _check_resolutions(atlas, [resolution[f] for f in part.patches])
    detail = detail or {}
    if not isinstance(detail, Mapping):
        raise ValueError(f"detail must be a mapping of patch index to DetailTile lists, "
                         f"got {type(detail).__name__}")
    for f in detail:
        if isinstance(f, bool) or not isinstance(f, int) or not 0 <= f < part.patch_count:
            raise ValueError(f"detail key {f!r} is no patch index in 0..{part.patch_count - 1}")
    tiles = _check_detail(atlas, {k: detail[f] for k, f in enumerate(part.patches)
                                  if f in detail})
    if tiles and part.rings < 2 and min(res) < 3:
        raise ValueError("detail on 2-sample patches needs a part of two rings "
                         "(atlas_parts(..., rings=2))")
    meshes = _welded_mesh(atlas, res, tiles, kernel, part.tolerance, part.drawn,
                          part.patches, cache)
    for mesh in meshes:
        mesh.patches = array("I", map(part.patches.__getitem__, mesh.patches))
    return meshes
