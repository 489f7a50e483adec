"""Read and write atlas files (``.tsa``, versions 1 to 4): an :class:`~client_py.atlas.AtlasSurface`
in bytes, in the manner of the ``.tsp`` patch (``client_py.format``, whose pieces it reuses).

The layout is specified in ``docs/format.md`` ("Atlas patch file ``.tsa``"). In short: a
28-byte header (magic ``TSPA``, version, flags, degree ``d``, spans ``s``, quantisation
bits, ``V`` vertices, ``F`` quads, payload sizes), a zlib-compressed payload (the quads'
vertex indices, the global bounds of the control points, every control point *once*
quantised over those bounds (to the nearest grid point, but for a patch's corners that
would fall on one: :func:`keep_corners_apart`) and coded as the residual from a
prediction made from integers decoded before it, the log-weights coded the same way,
metadata JSON) and a CRC32 of all that precedes it. Version 4 (written with a
``tangent_factor``) codes the edge and patch interior points in local frames made from
the decoded vertices instead (:class:`FrameCoder`).

Prediction (all in integers, so reader and writer agree bit for bit): a layout vertex
from the vertex before it; an edge's interior point ``t`` (``1..n-2``, ``m = n - 1``) from
the linear interpolation of the edge's end vertices, ``((m - t) q_lo + t q_hi) / m``; a
patch's interior point ``(i, j)`` from the discrete bilinearly blended Coons patch of its
four border rows (Coons 1967; The NURBS Book §10.6, eq. 10.25),

``C_ij = (1-s) P_0j + s P_mj + (1-t) P_i0 + t P_im - [(1-s)(1-t) P_00 + s(1-t) P_m0
+ (1-s)t P_0m + st P_mm]``, ``s = i/m``, ``t = j/m``,

rounded half up and clamped to ``0..2^bits - 1``. Residuals are zig-zag coded in byte
planes (as ``.tsp``), then deflated at level 9.

Any file that is not a valid atlas raises :class:`~client_py.errors.PatchFormatError`
with the byte offset and the reason, with the checks in header order; every size is
checked on the header before anything is inflated, so time and memory are bounded by
:data:`ATLAS_LIMITS` whatever the bytes claim.
"""

from __future__ import annotations

import copy
import json
import math
import struct
import sys
import zlib
from array import array
from collections.abc import Sequence
from itertools import accumulate
from operator import add, sub

from .atlas import (
    MAX_ATLAS_DEGREE,
    MAX_ATLAS_QUADS,
    MAX_ATLAS_SPANS,
    MAX_ATLAS_VERTICES,
    SIDES,
    AtlasSurface,
    EdgeTable,
    atlas_edges,
)
from .errors import PatchFormatError
from .format import (
    _WORD_CODE,
    CRC_SIZE,
    MAX_BITS,
    MAX_CONTROL_POINTS,
    MAX_INFLATE_RATIO,
    MAX_METADATA,
    MIN_BITS,
    _Cursor,
    _decode_planes,
    _dequantise,
    _inflate,
    _plane_count,
    _quantise,
    _read_metadata,
    _unframe,
    check_bits,
)
from .rangecoder import (
    HALF,
    RangeDecodeError,
    RangeDecoder,
    RangeEncoder,
    decode_exp_golomb,
    encode_exp_golomb,
)

MAGIC = b"TSPA"
VERSION = 3  # written; versions 1 and 2 are still read
FRAME_VERSION = 4  # written with a tangent_factor (local frames)
READ_VERSIONS = (1, 2, 3, 4)
#: versions of a smooth base's control mesh, which ``client_py.control_mesh`` reads (5: the
#: layout's triangle coder, points from their neighbours' mean; 6, written: Edgebreaker's
#: triangles, ``client_py.triangle_coder``, and points from parallelograms in an order of
#: their own)
CONTROL_MESH_VERSIONS = (5, 6)
# magic version flags degree spans bits reserved V F payload_size raw_size
HEADER = struct.Struct("<4sHHBBBBIIII")
HEADER_SIZE = HEADER.size  # 28
FLAG_RATIONAL = 1
KNOWN_FLAGS = FLAG_RATIONAL

#: most sides at one layout vertex (versions 3 and 4): a quad's corner scans all of its
#: vertex's neighbours for candidates (:func:`_candidates`), so a reader stops a layout at
#: a vertex beyond this and a writer refuses one; fitted layouts reach 14 (the 15-scan
#: Happy Buddha's base), 10 (Laurana's)
MAX_LAYOUT_VALENCE = 64

#: what a reader accepts (docs/format.md, "Atlas limits"): the layout's limits are the
#: data model's (client_py.atlas); the control points are the ``.tsp`` limit, which bounds
#: the decoded grids (2^18 points decode in about a second of pure Python)
ATLAS_LIMITS = {
    "degree": MAX_ATLAS_DEGREE, "spans": MAX_ATLAS_SPANS, "vertices": MAX_ATLAS_VERTICES,
    "quads": MAX_ATLAS_QUADS, "layout valence": MAX_LAYOUT_VALENCE,
    "control points": MAX_CONTROL_POINTS, "metadata bytes": MAX_METADATA,
    "inflate ratio": MAX_INFLATE_RATIO,
}


def index_width(n_vertices: int) -> int:
    """Bytes per stored vertex index: 2 (u16) for ``V <= 65536``, else 4 (u32)."""
    return 2 if n_vertices <= 1 << 16 else 4


def _control_point_range(n_vertices: int, n_quads: int, side: int) -> tuple[int, int]:
    """``(least, most)`` control points of a layout: ``V + E (n-2) + F (n-2)^2`` with
    ``2F <= E <= 4F`` (each quad has 4 sides, each edge at most 2 quads)."""
    inner = side - 2
    base = n_vertices + n_quads * inner * inner
    return base + 2 * n_quads * inner, base + 4 * n_quads * inner


def payload_size_range(flags: int, degree: int, spans: int, bits: int, n_vertices: int,
                       n_quads: int, version: int = VERSION) -> tuple[int, int]:
    """``(least, most)`` bytes of the decompressed payload of an atlas with these header fields.

    ``4 F w + 48 + G N B + (16 if rational) + 4 + L`` with ``w`` the index width (versions
    1 and 2; 0 in version 3, whose quads are range-coded), ``G = 4`` when rational else 3,
    ``B`` bytes per residual (version 1; 0 from version 2 on, whose residuals are
    range-coded after the zlib stream), ``N`` the control points (between
    :func:`_control_point_range`'s bounds) and ``L`` the metadata (2 bytes ``{}`` .. 2^20).
    """
    least_points, most_points = _control_point_range(n_vertices, n_quads, spans + degree)
    grids = 4 if flags & FLAG_RATIONAL else 3
    quad_bytes = 4 * n_quads * index_width(n_vertices) if version < 3 else 0
    fixed = quad_bytes + 48 + 4 + (16 if flags & FLAG_RATIONAL else 0)
    planes = _plane_count(bits) if version == 1 else 0
    return (fixed + grids * least_points * planes + 2,
            fixed + grids * most_points * planes + MAX_METADATA)


# ------------------------------------------------------------------ prediction
def _border_indices(quads: Sequence[Sequence[int]], table: EdgeTable, side: int,
                    n_vertices: int) -> list[tuple[list[int], ...]]:
    """Per patch, the global indices of its four border rows (``SIDES`` order: ``v = 0``,
    ``u = 1``, ``v = 1``, ``u = 0``), each ``n`` long along increasing ``u`` or ``v``; the
    edge points read reversed where the side runs from the edge's ``hi`` to its ``lo``."""
    inner = side - 2
    out = []
    for quad, sides in zip(quads, table.sides, strict=True):
        rows = []
        for (s, t), (e, reverse) in zip(SIDES, sides, strict=True):
            run = list(range(n_vertices + e * inner, n_vertices + (e + 1) * inner))
            if reverse:
                run.reverse()
            rows.append([quad[s], *run, quad[t]])
        out.append(tuple(rows))
    return out


def _coons_terms(side: int) -> list[tuple[tuple[int, int, int], ...]]:
    """For each interior ``(i, j)`` (``i``-major), the integer Coons weights times ``m^2``
    as ``(weight, border row, position)`` triples (module docstring; ``m = n - 1``): the
    four border points facing ``(i, j)``, then the four corners."""
    m = side - 1
    terms = []
    for i in range(1, m):
        for j in range(1, m):
            terms.append((
                (m * (m - i), 3, j), (m * i, 1, j), (m * (m - j), 0, i), (m * j, 2, i),
                (-(m - i) * (m - j), 0, 0), (-i * (m - j), 0, m),
                (-(m - i) * j, 2, 0), (-i * j, 2, m),
            ))
    return terms


def _vertex_prediction(q: Sequence[int], k: int, earlier: Sequence[int]) -> int:
    """Version 2's prediction of layout vertex ``k``: the mean of its layout neighbours
    ``earlier`` (those ``< k``) rounded half up, ``floor((2 sum + c) / 2c)``; without one,
    vertex ``k - 1`` (0 for the first)."""
    if earlier:
        c = len(earlier)
        return (2 * sum(q[n] for n in earlier) + c) // (2 * c)
    return q[k - 1] if k else 0


def _run_links(n_vertices: int, n_edges: int, n_quads: int, inner: int
               ) -> list[tuple[int, ...]]:
    """Version 3: per control point (global order), the earlier points of its *run* whose
    residuals predict its residual (:func:`_run_differences`): none for a layout vertex
    and for the first point of an edge or of a patch interior; edge point ``t > 0``: the
    point ``t - 1`` of the same edge; patch interior point ``(i, j)`` (0-based in its
    ``(n-2)²`` block): ``(i, j-1)`` in row 0, ``(i-1, j)`` in column 0, both elsewhere."""
    links: list[tuple[int, ...]] = [()] * n_vertices
    for e in range(n_edges):
        start = n_vertices + e * inner
        links += [()] + [(start + t - 1,) for t in range(1, inner)]
    first = n_vertices + n_edges * inner
    for f in range(n_quads):
        at = first + f * inner * inner
        for i in range(inner):
            for j in range(inner):
                k = at + i * inner + j
                links.append((k - 1, k - inner) if i and j else (k - 1,) if j
                             else (k - inner,) if i else ())
    return links


def _run_differences(res: Sequence[int], links: Sequence[tuple[int, ...]]) -> list[int]:
    """``r'_k = r_k - r_a`` for one link ``a``, ``r_k - floor((r_a + r_b) / 2)`` for two.

    A curved patch leaves its Coons and linear predictions wrong by about the same amount
    at neighbouring points of an edge or of an interior (the surface bulges away from the
    blend of its border), so the difference of neighbouring residuals is the smaller
    number: on the benchmark's bunny and Lucy bases (main 732fe1f) the coded residuals
    are 4.5 % / 3.4 % smaller for it."""
    out = list(res)
    for k, link in enumerate(links):
        if len(link) == 1:
            out[k] = res[k] - res[link[0]]
        elif link:
            out[k] = res[k] - (res[link[0]] + res[link[1]]) // 2
    return out


def _run_sums(diff: Sequence[int], links: Sequence[tuple[int, ...]]) -> list[int]:
    """Inverse of :func:`_run_differences` (links point to earlier points only)."""
    res = list(diff)
    for k, link in enumerate(links):
        if len(link) == 1:
            res[k] = diff[k] + res[link[0]]
        elif link:
            res[k] = diff[k] + (res[link[0]] + res[link[1]]) // 2
    return res


class _Predictor:
    """The predictions of one atlas layout (module docstring), for any integer axis;
    ``version`` 1 predicts a layout vertex from the vertex before it, version 2 from its
    layout neighbours decoded before it; version 3 then codes edge and interior points'
    residuals as differences along their runs (:func:`_run_differences`)."""

    def __init__(self, quads: Sequence[Sequence[int]], table: EdgeTable, side: int,
                 n_vertices: int, bits: int, version: int = VERSION) -> None:
        self.n_vertices, self.side, self.top = n_vertices, side, (1 << bits) - 1
        self.edges = table.edges
        self.earlier: list[list[int]] | None = None
        if version >= 2:  # per vertex, its layout neighbours with a lower index
            linked: list[set[int]] = [set() for _ in range(n_vertices)]
            for a, b in table.edges:
                linked[max(a, b)].add(min(a, b))
            self.earlier = [sorted(n) for n in linked]
        borders = _border_indices(quads, table, side, n_vertices)
        # per interior (i, j): its 8 weights and, per term, the point of every patch
        self.coons = [(tuple(w for w, _, _ in terms),
                       [[rows[r][k] for rows in borders] for _, r, k in terms])
                      for terms in _coons_terms(side)]
        self.n_edge_points = len(table.edges) * (side - 2)
        self.n_quads = len(quads)
        self.runs: list[tuple[int, ...]] | None = None
        self.sources: list[int] | None = None
        if version >= 3:
            self.runs = _run_links(n_vertices, len(table.edges), len(quads), side - 2)
            # the context point of each residual: a vertex's highest earlier neighbour,
            # else the first link (-1: none)
            self.sources = [max(e) if e else -1 for e in self.earlier] \
                + [link[0] if link else -1 for link in self.runs[n_vertices:]]

    def edge_points(self, q: Sequence[int]) -> list[int]:
        """Predicted edge points from the vertices ``q[:V]``: ``round(((m-t) a + t b) / m)``."""
        m = self.side - 1
        weights = [(m - t, t) for t in range(1, m)]
        return [(2 * (wa * q[a] + wb * q[b]) + m) // (2 * m)
                for a, b in self.edges for wa, wb in weights]

    def face_points(self, q: Sequence[int]) -> list[int]:
        """Predicted face points from the vertices and edge points ``q[:V + E (n-2)]``: one
        interior position ``(i, j)`` of every patch at a time."""
        m2, top = (self.side - 1) ** 2, self.top
        per_patch = len(self.coons)
        out = [0] * (per_patch * self.n_quads)
        get = q.__getitem__
        for at, ((w0, w1, w2, w3, w4, w5, w6, w7), index) in enumerate(self.coons):
            out[at::per_patch] = [
                (2 * (w0 * a + w1 * b + w2 * c + w3 * d + w4 * e + w5 * f + w6 * g + w7 * h)
                 + m2) // (2 * m2)
                for a, b, c, d, e, f, g, h in zip(*[map(get, k) for k in index], strict=True)]
        if out and (min(out) < 0 or max(out) > top):  # a blend beyond the box: clamp it
            out = [top if p > top else 0 if p < 0 else p for p in out]
        return out

    def edge_blend(self, x: Sequence[float]) -> list[float]:
        """Version 4: :meth:`edge_points` in floats, ``((m-t) a + t b) / m``, unrounded."""
        m = self.side - 1
        return [((m - t) * x[a] + t * x[b]) / m for a, b in self.edges for t in range(1, m)]

    def face_blend(self, x: Sequence[float]) -> list[float]:
        """Version 4: :meth:`face_points` in floats (the same terms in the same order, over
        ``m^2``), unrounded and unclamped."""
        m2 = (self.side - 1) ** 2
        per_patch = len(self.coons)
        out = [0.0] * (per_patch * self.n_quads)
        get = x.__getitem__
        for at, ((w0, w1, w2, w3, w4, w5, w6, w7), index) in enumerate(self.coons):
            out[at::per_patch] = [
                (w0 * a + w1 * b + w2 * c + w3 * d + w4 * e + w5 * f + w6 * g + w7 * h) / m2
                for a, b, c, d, e, f, g, h in zip(*[map(get, k) for k in index], strict=True)]
        return out

    def vertices(self, q: Sequence[int]) -> list[int]:
        """Predicted layout vertices (version 2) from ``q[:V]`` (:func:`_vertex_prediction`)."""
        return [_vertex_prediction(q, k, earlier) for k, earlier in enumerate(self.earlier)]

    def undo_vertices(self, residuals: Sequence[int]) -> list[int]:
        """The layout vertices' codes from their residuals (run sums already undone)."""
        if self.earlier is None:
            return list(accumulate(residuals[:self.n_vertices]))
        q: list[int] = []  # one vertex at a time: each prediction needs the vertices before it
        for k, earlier in enumerate(self.earlier):
            q.append(residuals[k] + _vertex_prediction(q, k, earlier))
        return q

    def residuals(self, q: Sequence[int]) -> list[int]:
        """``q`` (every control point of one axis, global order) minus its prediction."""
        n_v, n_e = self.n_vertices, self.n_vertices + self.n_edge_points
        if self.earlier is None:
            res = [q[0], *map(sub, q[1:n_v], q[: n_v - 1])]
        else:
            res = list(map(sub, q[:n_v], self.vertices(q)))
        res += map(sub, q[n_v:n_e], self.edge_points(q))
        res += map(sub, q[n_e:], self.face_points(q))
        return res if self.runs is None else _run_differences(res, self.runs)

    def undo(self, residuals: Sequence[int]) -> list[int]:
        """Inverse of :meth:`residuals`: vertices by a running sum, then edges, then faces."""
        n_v, n_e = self.n_vertices, self.n_vertices + self.n_edge_points
        if self.runs is not None:
            residuals = _run_sums(residuals, self.runs)
        q = self.undo_vertices(residuals)
        q += map(add, residuals[n_v:n_e], self.edge_points(q))
        q += map(add, residuals[n_e:], self.face_points(q))
        return q


# ------------------------------------------------------------------ residual coding (v2)
RESIDUAL_BUCKETS = 5  # context: bit length of a neighbouring residual, 0..4+
#: a residual's bit length never reaches this: versions 2-3 code ``|r| < 2^(bits + 1)``,
#: version 4 frame codes of up to ``bits + 3`` bits whose run differences take ``bits + 4``
#: (:func:`_frame_residuals`, ``longest`` in :func:`_read_coded_axes`)
PREFIX_LIMIT = MAX_BITS + 5


class _ResidualModel:
    """Adaptive contexts of one run of residuals (docs/format.md, "Atlas residuals"): by the
    point's class ``c`` (0 layout vertex, 1 edge point, 2 patch interior), a bucket ``b``,
    the bit length (capped at 4) of a neighbouring residual, and (version 3) a bucket
    ``b'`` of the residual of its source point (:class:`_Predictor`'s ``sources``; 0 in
    version 2, whose contexts are these with ``b' = 0``)."""

    def __init__(self, classes: int = 3) -> None:
        self.zero = [HALF] * (classes * RESIDUAL_BUCKETS * RESIDUAL_BUCKETS)
        self.sign = [HALF] * classes
        self.prefix = [HALF] * (classes * RESIDUAL_BUCKETS * RESIDUAL_BUCKETS * PREFIX_LIMIT)
        self.mantissa = [HALF] * (classes * PREFIX_LIMIT)


def _bucket(r: int) -> int:
    m = abs(r).bit_length()
    return m if m < RESIDUAL_BUCKETS else RESIDUAL_BUCKETS - 1


def _buckets(residuals: Sequence[int]) -> list[int]:
    """:func:`_bucket` of every residual, in one pass."""
    top = RESIDUAL_BUCKETS - 1
    return [m if m < top else top for m in map(int.bit_length, map(abs, residuals))]


def _classes(n_v: int, n_e: int, count: int, tangential: bool = False) -> list[int]:
    """Per point its class: 0 layout vertex, 1 edge point, 2 patch interior; version 4's
    tangential codes (its second and third passes) 3 and 4 for the latter two."""
    edge, face = (3, 4) if tangential else (1, 2)
    return [0] * n_v + [edge] * (n_e - n_v) + [face] * (count - n_e)


def _encode_residuals(enc: RangeEncoder, residuals: Sequence[int], classes: Sequence[int],
                      before: Sequence[int] | None, model: _ResidualModel,
                      sources: Sequence[int] | None = None) -> None:
    """Code one axis's residuals: per value ``r`` of class ``c`` with bucket ``b`` (of the
    same point's residual on the axis ``before``, or of the previous residual on the first
    axis) and ``b'`` (of this axis's residual at ``sources[k]``; 0 without ``sources`` or
    for ``-1``), a zero bit (context ``c, b, b'``); then a sign bit (``c``), then ``n =
    bitlen(|r|) - 1`` in unary (``c, b, b'``, position), then the ``n`` bits of ``|r|``
    below its leading one, most significant first (``c``, position). The buckets are made
    once per run (:func:`_buckets`), each context from them."""
    own = _buckets(residuals)
    prior = _buckets(before) if before is not None else [0, *own][:len(own)]
    if sources is None:
        sources = [-1] * len(residuals)
    n_b = RESIDUAL_BUCKETS
    bit, zero, sign, prefix, mantissa = enc.bit, model.zero, model.sign, model.prefix, \
        model.mantissa
    # classes and sources read by the residuals' index: they may run on past them
    for r, c, b, s in zip(residuals, classes, prior, sources, strict=False):
        ctx = (c * n_b + b) * n_b + (own[s] if s >= 0 else 0)
        bit(zero, ctx, r != 0)
        if not r:
            continue
        bit(sign, c, r < 0)
        encode_exp_golomb(enc, abs(r), prefix, ctx * PREFIX_LIMIT, mantissa, c * PREFIX_LIMIT)


def _decode_residuals(dec: RangeDecoder, classes: Sequence[int], before: Sequence[int] | None,
                      model: _ResidualModel, longest: int, what: str,
                      sources: Sequence[int] | None = None) -> list[int]:
    """Inverse of :func:`_encode_residuals`; a bit length beyond ``longest`` (``bits``: no
    residual of ``bits``-bit values has more; ``bits + 1`` for version 3's differences) is
    a :class:`PatchFormatError`."""
    out: list[int] = []
    bit = dec.bit
    zero, sign, prefix, mantissa = model.zero, model.sign, model.prefix, model.mantissa
    previous = 0
    top = RESIDUAL_BUCKETS - 1
    for k, c in enumerate(classes):
        m = abs(before[k] if before is not None else previous).bit_length()
        ctx = c * RESIDUAL_BUCKETS + (m if m < top else top)
        s = sources[k] if sources is not None else -1
        m = abs(out[s]).bit_length() if s >= 0 else 0
        ctx = ctx * RESIDUAL_BUCKETS + (m if m < top else top)
        if not bit(zero, ctx):
            out.append(0)
            previous = 0
            continue
        negative = bit(sign, c)
        m = decode_exp_golomb(dec, prefix, ctx * PREFIX_LIMIT,
                              mantissa, c * PREFIX_LIMIT, longest)
        if m is None:
            raise PatchFormatError(HEADER_SIZE, f"{what}: residual {k} longer than "
                                   f"{longest} bits")
        previous = -m if negative else m
        out.append(previous)
    return out


def _all_points(atlas: AtlasSurface) -> list[tuple[float, float, float]]:
    return [*atlas.vertices, *atlas.edge_points, *atlas.face_points]


# ------------------------------------------------------------------ local frames (v4)
#: version 4's tangential factor is stored in quarters (header byte 11): 1..63.75
FACTOR_QUARTERS = 4
_TINY = 1e-12  # squared length below which a frame candidate is no direction


def _unit(v: Sequence[float]) -> tuple[float, float, float] | None:
    """``v / |v|``, or ``None`` when ``|v|² <=`` :data:`_TINY` (no direction)."""
    x, y, z = v
    n2 = x * x + y * y + z * z
    if n2 <= _TINY:
        return None
    n = math.sqrt(n2)
    return (x / n, y / n, z / n)


def _frame(normal: Sequence[float], along: Sequence[float]) -> tuple[float, ...]:
    """The orthonormal frame ``(n, t1, t2)`` (9 floats) of a normal and a direction along
    the surface: ``n`` the first of ``normal``, ``x``, ``y``, ``z`` with a direction
    (:func:`_unit`); ``t1`` the first of ``along``, ``x``, ``y``, ``z`` whose part
    across ``n``, ``a - (a·n) n``, has one; ``t2 = n × t1``. Defined for any input
    (a degenerate normal or a direction along it falls through to the axes)."""
    axes = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    n = _unit(normal)
    if n is None:
        n = axes[0]
    for a in (along, *axes):
        d = a[0] * n[0] + a[1] * n[1] + a[2] * n[2]
        t = _unit((a[0] - d * n[0], a[1] - d * n[1], a[2] - d * n[2]))
        if t is not None:
            break
    return (*n, *t, n[1] * t[2] - n[2] * t[1], n[2] * t[0] - n[0] * t[2],
            n[0] * t[1] - n[1] * t[0])


def point_frames(vertices: Sequence[Sequence[float]], quads: Sequence[Sequence[int]],
                 table: EdgeTable) -> tuple[list[tuple[float, ...]], list[tuple[float, ...]]]:
    """Version 4's frames from the decoded layout vertices: ``(per edge, per patch)``.

    A patch's normal is the unit cross product of its diagonals, ``(c - a) × (d - b)`` for
    quad ``(a, b, c, d)`` (0 when that vanishes); an edge's normal the sum of its patches'.
    The direction along: an edge's ``hi - lo``, a patch's ``(b - a) + (c - d)`` (along
    ``u``). Each made a frame by :func:`_frame`."""
    normals = []
    for a, b, c, d in quads:
        pa, pb, pc, pd = vertices[a], vertices[b], vertices[c], vertices[d]
        e = (pc[0] - pa[0], pc[1] - pa[1], pc[2] - pa[2])
        f = (pd[0] - pb[0], pd[1] - pb[1], pd[2] - pb[2])
        normals.append(_unit((e[1] * f[2] - e[2] * f[1], e[2] * f[0] - e[0] * f[2],
                              e[0] * f[1] - e[1] * f[0])) or (0.0, 0.0, 0.0))
    edge_frames = []
    for (lo, hi), pairs in zip(table.edges, table.faces, strict=True):
        n = [0.0, 0.0, 0.0]
        for patch, _ in pairs:
            m = normals[patch]
            n = [n[0] + m[0], n[1] + m[1], n[2] + m[2]]
        p, q = vertices[lo], vertices[hi]
        edge_frames.append(_frame(n, (q[0] - p[0], q[1] - p[1], q[2] - p[2])))
    face_frames = []
    for (a, b, c, d), n in zip(quads, normals, strict=True):
        pa, pb, pc, pd = vertices[a], vertices[b], vertices[c], vertices[d]
        face_frames.append(_frame(n, tuple(pb[k] - pa[k] + pc[k] - pd[k] for k in range(3))))
    return edge_frames, face_frames


def frame_steps(lows: Sequence[float], highs: Sequence[float], bits: int,
                factor: float) -> tuple[float, float]:
    """Version 4's steps ``(normal, tangential)``: the mean of the three axes' grid steps
    ``(hi - lo) / (2^bits - 1)`` (1 when all three are 0), and ``factor`` times that."""
    top = (1 << bits) - 1
    s = ((highs[0] - lows[0]) / top + (highs[1] - lows[1]) / top
         + (highs[2] - lows[2]) / top) / 3
    if not s > 0:
        s = 1.0
    return s, s * factor


class FrameCoder:
    """Version 4's edge and patch-interior points (docs/format.md, "Local frames (version
    4)"): point ``k`` is ``P_k = C_k + s_n a_k n + s_t (b_k t1 + c_k t2)`` with ``C_k`` the
    prediction from the decoded points before it (an edge point's linear interpolation of
    its end vertices, a patch interior point's Coons blend of its border, in floats), ``(n,
    t1, t2)`` its edge's or patch's :func:`point_frames` frame, ``(s_n, s_t)`` the
    :func:`frame_steps` and ``(a_k, b_k, c_k)`` its integer codes. One rule for the reader,
    the writer (codes rounded to nearest) and the fitter's rounding with the error fed back.
    """

    def __init__(self, predictor: _Predictor, quads: Sequence[Sequence[int]],
                 table: EdgeTable, steps: tuple[float, float]) -> None:
        self.predictor, self.quads, self.table = predictor, quads, table
        self.steps = steps
        self.n_vertices = predictor.n_vertices
        self.n_edge = predictor.n_vertices + predictor.n_edge_points
        self.inner = predictor.side - 2

    def frames(self, vertices: Sequence[Sequence[float]]) -> list[tuple[float, ...]]:
        """Per edge and patch-interior point (global order from ``V``), its frame."""
        edge_frames, face_frames = point_frames(vertices, self.quads, self.table)
        inner = self.inner
        return ([f for f in edge_frames for _ in range(inner)]
                + [f for f in face_frames for _ in range(inner * inner)])

    def predictions(self, axes: Sequence[list[float]], faces: bool) -> list[list[float]]:
        """The predictions ``C_k`` of the edge points (``faces=False``, from ``axes[:V]``)
        or of the patch interior points (from ``axes[:V + E (n-2)]``), one list per axis."""
        predictor = self.predictor
        return [predictor.face_blend(a) if faces else predictor.edge_blend(a) for a in axes]

    def place(self, axes: list[list[float]], frames: Sequence[tuple[float, ...]],
              start: int, stop: int, codes: Sequence[list[int]] | None = None,
              targets: Sequence[Sequence[float]] | None = None,
              predictions: Sequence[Sequence[float]] | None = None) -> None:
        """Fill ``axes[a][start:stop]`` (the edge points, or the interior points, after the
        points they are predicted from) from ``codes`` (three lists over all points), or,
        with ``targets`` (the points' coordinates, three lists), first set those codes to
        the nearest, ``floor(d · e / s + 1/2)`` of ``d = target - C`` per frame axis.
        ``predictions``: :meth:`predictions` of these ``axes`` when already made (they
        depend on the points before ``start`` alone)."""
        sn, st = self.steps
        n_v = self.n_vertices
        pred = (self.predictions(axes, start >= self.n_edge) if predictions is None
                else predictions)
        at = start - (n_v if start < self.n_edge else self.n_edge)
        x, y, z = axes
        for k in range(start, stop):
            cx, cy, cz = pred[0][at], pred[1][at], pred[2][at]
            nx, ny, nz, ux, uy, uz, vx, vy, vz = frames[k - n_v]
            if targets is not None:
                dx, dy, dz = targets[0][k] - cx, targets[1][k] - cy, targets[2][k] - cz
                codes[0][k] = math.floor((dx * nx + dy * ny + dz * nz) / sn + 0.5)
                codes[1][k] = math.floor((dx * ux + dy * uy + dz * uz) / st + 0.5)
                codes[2][k] = math.floor((dx * vx + dy * vy + dz * vz) / st + 0.5)
            a, b, c = sn * codes[0][k], st * codes[1][k], st * codes[2][k]
            x[k] = cx + a * nx + b * ux + c * vx
            y[k] = cy + a * ny + b * uy + c * vy
            z[k] = cz + a * nz + b * uz + c * vz
            at += 1

    def decode(self, vertex_axes: Sequence[Sequence[float]], codes: Sequence[list[int]],
               targets: Sequence[Sequence[float]] | None = None) -> list[list[float]]:
        """Every point's coordinates (three lists) from the decoded vertices and the codes
        of the rest (or, with ``targets``, those codes set first: :meth:`place`)."""
        count = len(codes[0])
        axes = [list(a) + [0.0] * (count - self.n_vertices) for a in vertex_axes]
        frames = self.frames(list(zip(*vertex_axes, strict=True)))
        self.place(axes, frames, self.n_vertices, self.n_edge, codes, targets)
        self.place(axes, frames, self.n_edge, count, codes, targets)
        return axes


# ------------------------------------------------------------------ layout coding (v3)
#: quads before this one whose corners are the candidates for its first corner
QUAD_RECENT = 4
QUAD_RANK_CONTEXTS = 32  # ranks 0..31 have contexts of their own, later ones share the last
QUAD_DISTANCE_BITS = 18  # 1 <= distance <= V - 1 < 2^17: its bit length is below this
#: a control mesh's triangles take their candidates from this many latest neighbours of a
#: vertex (real control meshes have valences under 20: the same bytes as no limit)
FACE_REACH = 32


def canonical_atlas(atlas: AtlasSurface) -> AtlasSurface:
    """``atlas`` with its layout vertices numbered in the order the quads first use them.

    Vertex ``k`` becomes the ``k``-th distinct index met reading ``quads`` in order (corner
    by corner); vertices no quad uses follow in their old order. The quads keep their order
    and corner order, so every patch is the same surface with the same ``(u, v)``; an
    edge's points are re-read from its new lower vertex. Version 3 files store this
    numbering (:func:`_code_quads` then codes a first use as one likely bit), so
    ``read_atlas(write_atlas(a))`` has ``canonical_atlas(a)``'s layout, and an atlas whose
    numbering is already canonical is returned as it is. Shared slots
    (:meth:`~client_py.atlas.AtlasSurface.border_slots`) are renumbered with the
    vertices, one to one, so a welded detail pack reads alike against either numbering.
    """
    order: dict[int, int] = {}
    for quad in atlas.quads:
        for k in quad:
            order.setdefault(k, len(order))
    n_vertices = len(atlas.vertices)
    for k in range(n_vertices):
        order.setdefault(k, len(order))
    if all(new == old for old, new in order.items()):
        return atlas
    old_of = [0] * n_vertices
    for old, new in order.items():
        old_of[new] = old
    quads = [tuple(order[k] for k in quad) for quad in atlas.quads]
    inner = atlas.side - 2
    old_edge = {edge: e for e, edge in enumerate(atlas.edges.edges)}
    edge_index: list[int] = []
    for lo, hi in atlas_edges(quads).edges:
        a, b = old_of[lo], old_of[hi]
        start = n_vertices + old_edge[min(a, b), max(a, b)] * inner
        run = range(start, start + inner)
        edge_index.extend(reversed(run) if a > b else run)
    points = _all_points(atlas)
    index = old_of + edge_index + list(range(n_vertices + len(edge_index), len(points)))
    moved = [points[k] for k in index]
    weights = None if atlas.weights is None else [atlas.weights[k] for k in index]
    n_edge = n_vertices + len(edge_index)
    return AtlasSurface(atlas.degree, atlas.spans, moved[:n_vertices], quads,
                        moved[n_vertices:n_edge], moved[n_edge:], weights)


class _FaceModel:
    """Adaptive contexts of a layout of quads (docs/format.md, "Atlas layout (version 3)")
    or of a version-5 control mesh's triangles ("Control mesh (versions 5 and 6)"; version
    6 codes them with ``client_py.triangle_coder``), by the corner's slot ``s`` (0..3 in the
    face; a triangle uses slots 0..2)."""

    def __init__(self) -> None:
        self.new = [HALF] * 8  # s, and whether the corner before it in the face was new
        self.hit = [HALF] * 16  # s, min(candidates, 3)
        self.rank = [HALF] * (4 * QUAD_RANK_CONTEXTS)  # s, min(t, 31)
        self.prefix = [HALF] * (4 * QUAD_DISTANCE_BITS)  # s, t
        self.suffix = [HALF] * (4 * QUAD_DISTANCE_BITS)  # s, t


def _candidates(face: Sequence[int], slot: int, recent: Sequence[Sequence[int]],
                linked: Sequence[list[int]], directed: set[tuple[int, int]],
                last: int = 3, reach: int | None = None) -> list[int]:
    """The vertices corner ``slot`` of a face most likely reuses, likeliest first, from its
    corners ``face[:slot]`` and the faces decoded before it.

    Corner 0: the corners of the last :data:`QUAD_RECENT` faces, the latest first. Corner
    ``s > 0``: the layout neighbours (in the order their sides were first decoded; with
    ``reach``, only the latest ``reach`` of them) of the corner before it, ``x`` of ``p =
    face[s - 1]``, and for the ``last`` corner (3 in a quad, 2 in a triangle) also of the
    first, ``y = face[0]``, leaving out the face's corners so far; ranked by a score, ties
    in that order: 1 per such neighbour relation, 2 more where an earlier face runs the
    side the other way and no face runs it this way yet (an *open* side, ``x -> p`` or
    ``y -> x``, which only the face across it still needs: a manifold layout runs each side
    once each way). ``x`` and ``p`` are neighbours exactly when a face ran ``x -> p`` or
    ``p -> x``, so ``directed`` answers that in constant time.
    """
    if slot == 0:
        out: list[int] = []
        for q in reversed(recent):
            out.extend(k for k in q if k not in out)
        return out
    before, first = face[slot - 1], face[0] if slot == last else None
    pool = linked[before] if reach is None else linked[before][-reach:]
    if first is not None:
        pool = pool + (linked[first] if reach is None else linked[first][-reach:])
    scored: dict[int, int] = {}
    for x in pool:
        if x in scored or x in face[:slot]:
            continue
        score = 0
        into, out_of = (x, before) in directed, (before, x) in directed
        if into or out_of:
            score += 1 + 2 * (into and not out_of)
        if first is not None:
            into, out_of = (first, x) in directed, (x, first) in directed
            if into or out_of:
                score += 1 + 2 * (into and not out_of)
        scored[x] = score
    return sorted(scored, key=lambda x: -scored[x])


def _code_quads(coder: RangeEncoder | RangeDecoder, n_quads: int, n_vertices: int,
                quads: Sequence[Sequence[int]] | None = None) -> list[tuple[int, int, int, int]]:
    """Encode ``quads`` (numbered as :func:`canonical_atlas` numbers them) or, with
    ``quads=None``, decode ``n_quads`` of them (docs/format.md, "Atlas layout (version 3)"):
    :func:`_code_faces` of 4 corners."""
    return _code_faces(coder, n_quads, n_vertices, quads, 4)


def _code_faces(coder: RangeEncoder | RangeDecoder, n_faces: int, n_vertices: int,
                faces: Sequence[Sequence[int]] | None, corners: int) -> list[tuple[int, ...]]:
    """Encode ``faces`` of ``corners`` (4: a layout's quads, versions 3 and 4; 3: a version-5
    control mesh's triangles) vertices each, numbered in the order they first use them, or,
    with ``faces=None``, decode ``n_faces`` of them (docs/format.md, "Atlas layout (version
    3)" and "Control mesh (versions 5 and 6)", version 5).

    Per corner ``v`` in slot ``s`` of each face, with ``u`` the count of distinct
    vertices so far: a bit ``v == u`` (a first use; context ``s`` and whether the corner
    before it in the face was one); else, with the :func:`_candidates` ``C`` non-empty,
    a bit ``v in C`` (context ``s, min(|C|, 3)``) and then its rank ``r`` in ``C`` in
    unary (``r`` ones and a zero, none after rank ``|C| - 1``; the ``t``-th with context
    ``s, min(t, 31)``); else ``u - v >= 1`` as adaptive Exp-Golomb (context ``s``).
    Triangles draw their candidates from a vertex's latest :data:`FACE_REACH` neighbours
    alone, quads from all of them, at most :data:`MAX_LAYOUT_VALENCE`: either way a
    corner costs a bounded time, whatever the faces.

    Raises
    ------
    PatchFormatError
        (decoding) a first use beyond ``n_vertices``, a distance beyond the vertices so far,
        or a quad's side that gives a vertex more than :data:`MAX_LAYOUT_VALENCE` neighbours.
    ValueError
        (encoding) a corner that is neither a first use nor an earlier vertex: the numbering
        is not canonical; a vertex of more than :data:`MAX_LAYOUT_VALENCE` quad sides.
    """
    encoding = faces is not None
    noun = "quad" if corners == 4 else "triangle"
    canonical = "canonical_atlas" if corners == 4 else "canonical_control_mesh"
    reach = None if corners == 4 else FACE_REACH
    most = MAX_LAYOUT_VALENCE if corners == 4 else n_vertices  # n_vertices: no limit
    last = corners - 1
    model, out = _FaceModel(), []
    # per vertex its neighbours, each list made when its vertex is first used (any other
    # corner is a vertex used before): a hostile header's 2^17 vertices cost no lists up front
    linked: list[list[int]] = []
    directed: set[tuple[int, int]] = set()
    used = 0

    def flag(probs: list[int], context: int, bit: bool) -> bool:
        if encoding:
            coder.bit(probs, context, bit)
            return bit
        return bool(coder.bit(probs, context))

    for f in range(n_faces):
        face: list[int] = []
        was_new = True
        for slot in range(corners):
            v = faces[f][slot] if encoding else -1
            if encoding and v > used:
                raise ValueError(f"{noun}s[{f}][{slot}] = {v}: a canonical numbering uses "
                                 f"vertex {used} first ({canonical})")
            was_new = flag(model.new, 2 * slot + was_new, v == used)
            if was_new:
                if used >= n_vertices:
                    raise PatchFormatError(HEADER_SIZE, f"{noun} {f} uses more than the "
                                           f"{n_vertices} vertices")
                face.append(used)
                linked.append([])
                used += 1
                continue
            pool = _candidates(face, slot, out[-QUAD_RECENT:], linked, directed, last, reach)
            if pool and flag(model.hit, 4 * slot + min(len(pool), 3), v in pool):
                rank, target = 0, pool.index(v) if encoding else -1
                while rank < len(pool) - 1 and flag(
                        model.rank, slot * QUAD_RANK_CONTEXTS + min(rank, QUAD_RANK_CONTEXTS - 1),
                        rank < target):
                    rank += 1
                face.append(pool[rank])
                continue
            at = slot * QUAD_DISTANCE_BITS
            if encoding:
                encode_exp_golomb(coder, used - v, model.prefix, at, model.suffix, at)
                face.append(v)
                continue
            distance = decode_exp_golomb(coder, model.prefix, at, model.suffix, at,
                                         QUAD_DISTANCE_BITS)
            if distance is None or distance > used:
                raise PatchFormatError(HEADER_SIZE, f"{noun} {f}: corner {slot} refers to a "
                                       f"vertex before the first")
            face.append(used - distance)
        for k in range(corners):
            a, b = face[k], face[(k + 1) % corners]
            # neighbours already exactly when a face ran the side either way
            if (a, b) not in directed and (b, a) not in directed:
                linked[a].append(b)
                linked[b].append(a)
                crowded = a if len(linked[a]) > most else b if len(linked[b]) > most else -1
                if crowded >= 0 and encoding:
                    raise ValueError(f"layout vertex {crowded} (first-use numbering) has more "
                                     f"than {most} sides (MAX_LAYOUT_VALENCE); a reader "
                                     "refuses it")
                if crowded >= 0:  # now, before its candidates cost more
                    raise PatchFormatError(HEADER_SIZE, f"{noun} {f} gives vertex {crowded} "
                                           f"more than {most} neighbours; at most {most} "
                                           "accepted (MAX_LAYOUT_VALENCE)")
            directed.add((a, b))
        out.append(tuple(face))
    return out


# ------------------------------------------------------------------ writing
#: passes of :func:`keep_corners_apart`: one separates every pair; another is needed only
#: where three corners of one patch fell on one grid point
APART_PASSES = 3


def file_codes(axes: Sequence[Sequence[float]], lows: Sequence[float],
               highs: Sequence[float], bits: int, quads: Sequence[Sequence[int]]
               ) -> list[list[int]]:
    """The integer codes ``base.tsa`` holds for the control points whose coordinates are
    ``axes`` (three sequences) within the bounds ``lows``, ``highs``: each value rounded to
    the nearest of ``2^bits`` steps of its axis's bounds (``client_py.format``'s rule), then
    :func:`keep_corners_apart` over ``quads``. The writer's rule, and the fitter's start
    when it rounds with the error fed back (``fitter.fitting.atlas.fit.fed_back_atlas``)."""
    codes = [_quantise(axis, lo, hi, bits) for axis, lo, hi in zip(axes, lows, highs,
                                                                     strict=True)]
    keep_corners_apart(codes, axes, lows, highs, bits, quads)
    return codes


def keep_corners_apart(codes: list[list[int]], axes: Sequence[Sequence[float]],
                       lows: Sequence[float], highs: Sequence[float], bits: int,
                       quads: Sequence[Sequence[int]]) -> int:
    """Round apart the corners of a patch that rounding to nearest would put on one point.

    ``x_ak = (p_ak - lo_k) (2^bits - 1) / (hi_k - lo_k)`` is corner ``a``'s coordinate
    ``k`` in steps, ``codes[k][a] = round(x_ak)`` its code. Two corners ``a``, ``b`` of one
    patch less than a step apart can get the same code on all three axes: a short layout
    edge (or a quad's diagonal) of the fit becomes a point in the file. A side whose two
    corners are one point and whose edge points round alike reads the same both ways,
    ``C(t) = C(1 - t)``: it folds back onto itself and the two patches' tessellations along
    it overlap, so a mesh welded by position has edges of four triangles (the bunny's
    1,152-patch base at 10 bits: two patches at its open bottom, whose shared side the fit
    left 0.60 ‰ of the diagonal long, a step being 0.63 ‰; 2 non-manifold edges at the
    base, 8 at level 0). On the axis ``k`` where they lie farthest apart (``x_ak < x_bk``),
    ``a`` takes ``floor(x_ak)`` and ``b`` ``ceil(x_bk)``: different integers, since
    ``floor(x_ak) <= x_ak < x_bk <= ceil(x_bk)``. A corner moved so is within one step of
    the fit instead of half of one; the file's layout and the reader are unchanged.

    ``codes`` (three axes of ``N`` codes, the layout vertices first; ``axes`` their
    coordinates) is changed in place. Returns the number of pairs rounded apart.
    """
    top = (1 << bits) - 1
    scales = [top / (hi - lo) if hi > lo else 0.0 for lo, hi in zip(lows, highs, strict=True)]
    pairs = sorted({(min(a, b), max(a, b)) for quad in quads for i, a in enumerate(quad)
                    for b in quad[i + 1:] if a != b})
    total = 0
    for _ in range(APART_PASSES):
        moved = 0
        for a, b in pairs:
            if any(axis[a] != axis[b] for axis in codes):
                continue
            gaps = [abs(x[a] - x[b]) * scale for x, scale in zip(axes, scales, strict=True)]
            k = gaps.index(max(gaps))
            if gaps[k] == 0.0:
                continue  # one point in the fit already: nothing to keep apart
            low, high = (a, b) if axes[k][a] < axes[k][b] else (b, a)
            codes[k][low] = max(0, math.floor((axes[k][low] - lows[k]) * scales[k]))
            codes[k][high] = min(top, math.ceil((axes[k][high] - lows[k]) * scales[k]))
            moved += 1
        total += moved
        if not moved:
            break
    return total


def check_tangent_factor(factor: object) -> int:
    """Version 4's header byte for ``factor`` (its quarters, ``4..255``; 0 for ``None``,
    version 3); ``ValueError`` for any other value."""
    if factor is None:
        return 0
    quarters = factor * FACTOR_QUARTERS if isinstance(factor, int | float) \
        and not isinstance(factor, bool) else -1.0
    if not (4 <= quarters <= 255 and quarters == int(quarters)):
        raise ValueError(f"tangent_factor must be a multiple of 1/4 in 1..63.75 or None, "
                         f"got {factor!r}")
    return int(quarters)


def frame_codes(predictor: _Predictor, quads: Sequence[Sequence[int]], table: EdgeTable,
                axes: Sequence[Sequence[float]], lows: Sequence[float],
                highs: Sequence[float], bits: int, factor: float) -> list[list[int]]:
    """Version 4's codes of the points ``axes`` (three lists, global order): the layout
    vertices' as :func:`file_codes`, the others' :class:`FrameCoder` frame codes rounded
    to nearest, each point given the decoded points before it."""
    return _frame_codes_and_points(predictor, quads, table, axes, lows, highs, bits,
                                   factor)[0]


def _frame_codes_and_points(predictor: _Predictor, quads: Sequence[Sequence[int]],
                            table: EdgeTable, axes: Sequence[Sequence[float]],
                            lows: Sequence[float], highs: Sequence[float], bits: int,
                            factor: float) -> tuple[list[list[int]], list[list[float]]]:
    """:func:`frame_codes` and the points a reader decodes from them (three lists)."""
    n_v = predictor.n_vertices
    codes = file_codes([a[:n_v] for a in axes], lows, highs, bits, quads)
    count = len(axes[0])
    codes = [c + [0] * (count - n_v) for c in codes]
    vertex_axes = [_dequantise(c[:n_v], lo, hi, bits)
                   for c, lo, hi in zip(codes, lows, highs, strict=True)]
    coder = FrameCoder(predictor, quads, table, frame_steps(lows, highs, bits, factor))
    return codes, coder.decode(vertex_axes, codes, axes)


def _frame_residuals(predictor: _Predictor, codes: Sequence[list[int]], bits: int
                     ) -> list[list[int]]:
    """Version 4's three passes: the vertices' residuals (version 3's prediction), the
    other points' frame codes as they are, then version 3's run differences."""
    n_v = predictor.n_vertices
    _check_frame_codes(codes, n_v, bits)
    return [_run_differences([*map(sub, q[:n_v], predictor.vertices(q[:n_v])), *q[n_v:]],
                             predictor.runs) for q in codes]


def _check_frame_codes(codes: Sequence[list[int]], n_vertices: int, bits: int) -> None:
    """``ValueError`` when a frame code (a point past the ``n_vertices`` layout vertices)
    needs more than version 4's ``bits + 3`` bits."""
    limit = 1 << (bits + 3)
    for q in codes:
        tail = q[n_vertices:]
        if tail and max(max(tail), -min(tail)) >= limit:
            raise ValueError(f"a frame code of {max(max(tail), -min(tail))} needs more than "
                             f"{bits + 3} bits")


def write_atlas(atlas: AtlasSurface, bits: int = 16, metadata: dict | None = None,
                tangent_factor: float | None = None) -> bytes:
    """Encode ``atlas`` as a ``.tsa`` v3 file (docs/format.md): its layout numbered by
    :func:`canonical_atlas` and range-coded (:func:`_code_quads`), then the residuals of
    the control points (and log-weights) in the same range-coded stream.

    Parameters
    ----------
    atlas : AtlasSurface
    bits : int
        Quantisation of each coordinate over the global bounds of all control points
        (``2..30``): a shared point is one value, so neighbours keep one border curve;
        the error is at most half a step, ``(hi - lo) / (2 (2^bits - 1))`` per axis, and one
        step for a patch corner that rounding to nearest would have put onto another of
        the same patch (:func:`keep_corners_apart`).
    metadata : dict, optional
        JSON-serialisable object (strict JSON: finite numbers), at most 1 MiB.
    tangent_factor : float, optional
        Version 4 (:func:`frame_codes`): the edge and patch interior points coded in their
        local frames, the step along the surface this factor (a multiple of 1/4 in
        ``1..63.75``) times the step across it. ``None``: version 3.

    Returns
    -------
    bytes
        The same atlas and options always give the same bytes; :func:`read_atlas` gives
        back ``canonical_atlas(atlas)``'s layout (the same patches, vertices renumbered).
        ``AtlasWriter(atlas).write(bits, metadata)``, which writes one atlas at several
        bits for the price of one layout.
    """
    if not isinstance(atlas, AtlasSurface):
        raise ValueError(f"atlas must be an AtlasSurface, got {type(atlas).__name__}")
    check_bits(bits)
    return AtlasWriter(atlas).write(bits, metadata, tangent_factor)


class AtlasWriter:
    """:func:`write_atlas` of one atlas at any bits: what does not depend on the bits (the
    canonical layout, the range coder's state after the layout's quads, the control
    points' bounds, the predictor's sources and classes) made once, in the constructor.

    A fit choosing the bits of its base writes the same atlas at two to four bit depths;
    the second and later files cost their residuals alone (each file is the bytes
    :func:`write_atlas` gives). Three bits of a fitted 1,473-patch base (the 15-scan
    Happy Buddha's, in a layout numbering that is not canonical) took 0.47 s of CPU
    instead of 0.64 s, of Lucy's 2,304 patches 0.62 s instead of 0.88 (load 17)."""

    def __init__(self, atlas: AtlasSurface) -> None:
        if not isinstance(atlas, AtlasSurface):
            raise ValueError(f"atlas must be an AtlasSurface, got {type(atlas).__name__}")
        if atlas.control_point_count > MAX_CONTROL_POINTS:
            raise ValueError(f"the atlas has {atlas.control_point_count} control points; a "
                             f"reader accepts at most {MAX_CONTROL_POINTS}")
        self.atlas = atlas = canonical_atlas(atlas)
        self._layout = RangeEncoder()
        _code_quads(self._layout, len(atlas.quads), len(atlas.vertices), atlas.quads)
        points = _all_points(atlas)
        self._axes = [[p[a] for p in points] for a in range(3)]
        self._lows = [min(a) for a in self._axes]
        self._highs = [max(a) for a in self._axes]
        n_v = len(atlas.vertices)  # version 4's bounds: the layout vertices'
        self._vertex_bounds = ([min(a[:n_v]) for a in self._axes],
                               [max(a[:n_v]) for a in self._axes])
        # its clamp (``top``) is set per bits on a copy; the rest is the layout's
        self._predictor = _Predictor(atlas.quads, atlas.edges, atlas.side,
                                     len(atlas.vertices), 16)
        n_edge = len(atlas.vertices) + self._predictor.n_edge_points
        self._classes = _classes(len(atlas.vertices), n_edge, len(points))
        self._tangential = _classes(len(atlas.vertices), n_edge, len(points), True)
        self._coded: dict = {}  # (bits, quarters) -> (codes, decoded points): _codes

    def _codes(self, bits: int, quarters: int, tangent_factor: float | None
               ) -> tuple[list[list[int]], list[list[float]]]:
        """The three axes' codes of the file at ``bits`` (version 4 when ``quarters``)
        and the points a reader decodes from them, made once per ``bits`` and factor."""
        key = bits, quarters
        if key not in self._coded:
            if quarters:
                lows, highs = self._vertex_bounds
                predictor = copy.copy(self._predictor)
                predictor.top = (1 << bits) - 1
                self._coded[key] = _frame_codes_and_points(
                    predictor, self.atlas.quads, self.atlas.edges, self._axes, lows, highs,
                    bits, tangent_factor)
            else:
                codes = file_codes(self._axes, self._lows, self._highs, bits,
                                   self.atlas.quads)
                self._coded[key] = codes, [
                    _dequantise(c, lo, hi, bits)
                    for c, lo, hi in zip(codes, self._lows, self._highs, strict=True)]
        return self._coded[key]

    def decoded(self, bits: int = 16, tangent_factor: float | None = None) -> AtlasSurface:
        """The atlas :func:`read_atlas` gives back from ``write(bits, ...,
        tangent_factor)`` (the canonical layout, every control point and weight as
        decoded), from the writer's own codes (made once for it and the file): no range
        coding either way. ``fitter``'s check that every patch keeps its normal, on the
        15-scan Happy Buddha's 2,346-patch base at 8 bits (writer, file and check, in turns,
        load 2.4): 0.78 s of CPU where writing the file and reading it back took 1.12 s."""
        check_bits(bits)
        quarters = check_tangent_factor(tangent_factor)
        codes, axes = self._codes(bits, quarters, tangent_factor)
        atlas, n_v = self.atlas, len(self.atlas.vertices)
        if quarters:
            _check_frame_codes(codes, n_v, bits)  # a file write refuses
        n_edge = n_v + len(atlas.edge_points)
        weights = None
        if atlas.weights is not None:
            logs = [math.log(w) for w in atlas.weights]
            lo, hi = min(logs), max(logs)
            weights = [math.exp(x) for x in _dequantise(_quantise(logs, lo, hi, bits), lo, hi,
                                                        bits)]
        points = list(zip(*axes, strict=True))
        return AtlasSurface(atlas.degree, atlas.spans, points[:n_v], atlas.quads,
                            points[n_v:n_edge], points[n_edge:], weights)

    def write(self, bits: int = 16, metadata: dict | None = None,
              tangent_factor: float | None = None) -> bytes:
        """The ``.tsa`` file at ``bits``: ``write_atlas(atlas, bits, metadata,
        tangent_factor)``."""
        check_bits(bits)
        quarters = check_tangent_factor(tangent_factor)
        if metadata is not None and not isinstance(metadata, dict):
            raise ValueError(f"metadata must be a dict, got {type(metadata).__name__}")
        try:
            meta_bytes = json.dumps(metadata or {}, sort_keys=True, separators=(",", ":"),
                                    allow_nan=False).encode()
        except (TypeError, ValueError) as exc:
            raise ValueError(f"metadata must be JSON-serialisable: {exc}") from None
        if len(meta_bytes) > MAX_METADATA:
            raise ValueError(f"metadata is {len(meta_bytes)} bytes of JSON; at most 1 MiB fits")

        atlas, lows, highs = self.atlas, self._lows, self._highs
        if quarters:
            lows, highs = self._vertex_bounds
        n_vertices, quads = len(atlas.vertices), atlas.quads
        enc = copy.deepcopy(self._layout)
        parts = [struct.pack("<6d", *lows, *highs)]
        predictor = copy.copy(self._predictor)
        predictor.top = (1 << bits) - 1
        classes = self._classes
        if quarters:
            codes = self._codes(bits, quarters, tangent_factor)[0]
            passes = _frame_residuals(predictor, codes, bits)
            model, before = _ResidualModel(5), None
            for axis, residuals in enumerate(passes):
                _encode_residuals(enc, residuals, self._tangential if axis else classes,
                                  before, model, predictor.sources)
                before = residuals
        else:
            codes = self._codes(bits, quarters, tangent_factor)[0]
            model, before = _ResidualModel(), None
            for axis_codes in codes:
                residuals = predictor.residuals(axis_codes)
                _encode_residuals(enc, residuals, classes, before, model, predictor.sources)
                before = residuals
        flags = 0
        if atlas.weights is not None:
            flags |= FLAG_RATIONAL
            logs = [math.log(w) for w in atlas.weights]
            lo, hi = min(logs), max(logs)
            parts.append(struct.pack("<2d", lo, hi))
            _encode_residuals(enc, predictor.residuals(_quantise(logs, lo, hi, bits)),
                              classes, None, _ResidualModel(), predictor.sources)
        parts.append(struct.pack("<I", len(meta_bytes)) + meta_bytes)

        raw = b"".join(parts)
        payload = zlib.compress(raw, 9)
        header = HEADER.pack(MAGIC, FRAME_VERSION if quarters else VERSION, flags,
                             atlas.degree, atlas.spans, bits, quarters, n_vertices,
                             len(quads), len(payload), len(raw))
        body = header + payload + enc.finish()
        return body + struct.pack("<I", zlib.crc32(body))


# ------------------------------------------------------------------ reading
def read_atlas_header(data: bytes) -> dict:
    """Check the framing (magic, version, sizes, CRC32) and the header fields, in order.

    Version 1's zlib stream ends at the CRC; from version 2 on it is followed by the
    range-coded residuals (version 3: the layout, then the residuals), at least 4 bytes.

    Returns
    -------
    dict
        ``version``, ``flags``, ``degree``, ``spans``, ``bits``, ``vertices``, ``quads``,
        ``payload_size``, ``raw_size`` and the file's ``data``.
    """
    version = VERSION
    if isinstance(data, bytes | bytearray | memoryview) and len(data) >= 6:
        (stated,) = struct.unpack("<H", bytes(data[4:6]))
        version = stated if stated in READ_VERSIONS else VERSION
    data, fields = _unframe(data, MAGIC, "atlas", HEADER, version, 9 if version == 1 else None)
    _, _, flags, degree, spans, bits, reserved, n_vertices, n_quads, size, raw_size = fields
    if flags & ~KNOWN_FLAGS:
        raise PatchFormatError(6, f"unknown flags 0x{flags:04x}")
    if not 1 <= degree <= MAX_ATLAS_DEGREE:
        raise PatchFormatError(8, f"degree {degree} outside 1..{MAX_ATLAS_DEGREE}")
    if not 1 <= spans <= MAX_ATLAS_SPANS:
        raise PatchFormatError(9, f"spans = {spans} outside 1..{MAX_ATLAS_SPANS}")
    if not MIN_BITS <= bits <= MAX_BITS:
        raise PatchFormatError(10, f"bits = {bits} outside {MIN_BITS}..{MAX_BITS}")
    if version < FRAME_VERSION and reserved:
        raise PatchFormatError(11, f"reserved byte is {reserved}, must be 0")
    if version >= FRAME_VERSION and reserved < FACTOR_QUARTERS:
        raise PatchFormatError(11, f"tangential factor {reserved}/4 is below 1")
    if not 4 <= n_vertices <= MAX_ATLAS_VERTICES:
        raise PatchFormatError(12, f"{n_vertices} vertices; 4..{MAX_ATLAS_VERTICES} accepted")
    if not 1 <= n_quads <= MAX_ATLAS_QUADS:
        raise PatchFormatError(16, f"{n_quads} quads; 1..{MAX_ATLAS_QUADS} accepted")
    least_points, _ = _control_point_range(n_vertices, n_quads, spans + degree)
    if least_points > MAX_CONTROL_POINTS:
        raise PatchFormatError(12, f"{n_vertices} vertices and {n_quads} quads of side "
                               f"{spans + degree} need at least {least_points} control "
                               f"points; at most {MAX_CONTROL_POINTS} accepted")
    least, most = payload_size_range(flags, degree, spans, bits, n_vertices, n_quads, version)
    if raw_size > most:
        raise PatchFormatError(24, f"payload size {raw_size} exceeds the {most} the layout "
                               "allows")
    if raw_size > MAX_INFLATE_RATIO * size:
        raise PatchFormatError(24, f"payload size {raw_size} exceeds the "
                               f"{MAX_INFLATE_RATIO * size} bytes a {size}-byte zlib stream "
                               f"can inflate to ({MAX_INFLATE_RATIO}:1)")
    if raw_size < least:
        raise PatchFormatError(24, f"payload size {raw_size} is below the {least} bytes "
                               "the layout needs")
    if version >= 2 and HEADER_SIZE + size + 4 > len(data) - CRC_SIZE:
        raise PatchFormatError(20, f"payload size {size} leaves no room for the coded "
                               f"residuals in {len(data)} bytes")
    return {"version": version, "flags": flags, "degree": degree, "spans": spans,
            "bits": bits, "vertices": n_vertices, "quads": n_quads, "payload_size": size,
            "raw_size": raw_size, "data": data,
            "tangent_factor": reserved / FACTOR_QUARTERS if version >= FRAME_VERSION else None}


def _in_range(values: list[int], top: int, start: int, what: str) -> list[int]:
    if values and (min(values) < 0 or max(values) > top):
        raise PatchFormatError(start, f"{what} decode outside 0..{top}", "payload")
    return values


def _read_axis(cur: _Cursor, predictor: _Predictor, count: int, bits: int,
               what: str) -> list[int]:
    """Version 1: one axis's byte planes from the payload, undone."""
    start, planes = cur.pos, _plane_count(bits)
    values = predictor.undo(_decode_planes(cur.take(count * planes, what), count, planes))
    return _in_range(values, predictor.top, start, what)


def read_atlas(data: bytes) -> tuple[AtlasSurface, dict]:
    """Decode a ``.tsa`` file, version 4, 3, 2 or 1, into ``(AtlasSurface, metadata)``;
    version 5 or 6 (:data:`CONTROL_MESH_VERSIONS`), a smooth base's control mesh, into the
    atlas it draws (``client_py.control_mesh``).

    Raises
    ------
    PatchFormatError
        For anything but a valid atlas (truncation, corruption, a foreign file), with the
        byte offset and the reason; never anything else.
    """
    if isinstance(data, bytes | bytearray | memoryview) and len(data) >= 6 \
            and struct.unpack("<H", bytes(data[4:6]))[0] in CONTROL_MESH_VERSIONS:
        from .control_mesh import read_atlas_file  # a smooth base's control mesh

        return read_atlas_file(data)
    head = read_atlas_header(data)
    version, flags, bits = head["version"], head["flags"], head["bits"]
    degree, spans = head["degree"], head["spans"]
    n_vertices, n_quads = head["vertices"], head["quads"]
    raw = _inflate(head["data"], HEADER_SIZE, head["payload_size"], head["raw_size"], 24)

    cur = _Cursor(raw)
    dec = None
    if version >= 3:  # the layout leads the range-coded stream
        start = HEADER_SIZE + head["payload_size"]
        try:  # the decoder reads its first bytes when it is made: inside the try too
            dec = RangeDecoder(head["data"][start:len(head["data"]) - CRC_SIZE])
            quads = _code_quads(dec, n_quads, n_vertices)
        except RangeDecodeError as exc:
            raise PatchFormatError(len(head["data"]) - CRC_SIZE,
                                   f"coded layout ends early: {exc}") from None
    else:
        quads = _read_quads(cur, n_quads, n_vertices)
    try:
        table = atlas_edges(quads)
    except ValueError as exc:
        raise PatchFormatError(0, f"the quads are no valid layout: {exc}", "payload") from None
    side = spans + degree
    inner = side - 2
    count = n_vertices + len(table.edges) * inner + n_quads * inner * inner
    if count > MAX_CONTROL_POINTS:  # E lies in 2F..4F, so this only refines the header check
        raise PatchFormatError(0, f"the layout has {count} control points; at most "
                               f"{MAX_CONTROL_POINTS} accepted", "payload")
    bounds = cur.finite("<6d", "control point bounds")
    predictor = _Predictor(quads, table, side, n_vertices, bits, version)
    if version == 1:
        grids = [_read_axis(cur, predictor, count, bits, f"control points axis {name}")
                 for name in "xyz"]
        if flags & FLAG_RATIONAL:
            log_bounds = _log_weight_bounds(cur)
            grids.append(_read_axis(cur, predictor, count, bits, "weights"))
    else:
        log_bounds = _log_weight_bounds(cur) if flags & FLAG_RATIONAL else None
        grids = _read_coded_axes(head["data"], HEADER_SIZE + head["payload_size"], predictor,
                                 n_vertices, count, bits, log_bounds is not None, dec,
                                 version >= FRAME_VERSION)
    metadata = _read_metadata(cur, raw)
    if version >= FRAME_VERSION:
        vertex_axes = [_dequantise(grids[a][:n_vertices], bounds[a], bounds[a + 3], bits)
                       for a in range(3)]
        coder = FrameCoder(predictor, quads, table,
                           frame_steps(bounds[:3], bounds[3:], bits, head["tangent_factor"]))
        axes = coder.decode(vertex_axes, grids[:3])
        if not all(map(math.isfinite, (x for a in axes for x in a))):
            raise PatchFormatError(HEADER_SIZE, "decoded control points are not finite")
    else:
        axes = [_dequantise(grids[a], bounds[a], bounds[a + 3], bits) for a in range(3)]
    weights = None
    if flags & FLAG_RATIONAL:
        weights = [math.exp(x) for x in _dequantise(grids[3], *log_bounds, bits)]
    points = list(zip(*axes, strict=True))
    n_edge = n_vertices + len(table.edges) * inner
    try:
        atlas = AtlasSurface(degree, spans, points[:n_vertices], quads,
                             points[n_vertices:n_edge], points[n_edge:], weights)
    except ValueError as exc:
        raise PatchFormatError(HEADER_SIZE, f"decoded atlas is invalid: {exc}") from None
    return atlas, metadata


def _log_weight_bounds(cur: _Cursor) -> tuple[float, float]:
    lo, hi = cur.finite("<2d", "log-weight bounds")
    if max(abs(lo), abs(hi)) > 700:
        raise PatchFormatError(cur.pos - 16, "log-weights beyond +-700 overflow", "payload")
    return lo, hi


def _read_quads(cur: _Cursor, n_quads: int, n_vertices: int) -> list[tuple[int, ...]]:
    """Versions 1 and 2: ``4 F`` vertex indices (u16, or u32 beyond 65,536 vertices)."""
    width = index_width(n_vertices)
    flat = array(_WORD_CODE[width])
    flat.frombytes(cur.take(4 * n_quads * width, "quads"))
    if sys.byteorder == "big":
        flat.byteswap()
    if max(flat) >= n_vertices:
        raise PatchFormatError(0, f"a quad refers to vertex {max(flat)} of {n_vertices}",
                               "payload")
    return [tuple(flat[4 * f : 4 * f + 4]) for f in range(n_quads)]


def _read_coded_axes(data: bytes, start: int, predictor: _Predictor, n_vertices: int,
                     count: int, bits: int, rational: bool,
                     dec: RangeDecoder | None = None, frames: bool = False
                     ) -> list[list[int]]:
    """Versions 2 to 4: the range-coded residuals of x, y, z (and the log-weights), each
    undone and checked to lie in ``0..2^bits - 1``; from ``data[start:-4]`` (version 2) or
    where ``dec`` left off after the layout (versions 3, 4). Version 4 (``frames``): the
    three passes' layout vertices undone and checked so, the other points' frame codes
    as they are (:class:`FrameCoder` places them)."""
    n_edge = n_vertices + predictor.n_edge_points
    classes = _classes(n_vertices, n_edge, count)
    tangential = _classes(n_vertices, n_edge, count, True)
    grids, before, model = [], None, _ResidualModel(5 if frames else 3)
    longest = bits if predictor.runs is None else bits + 4 if frames else bits + 1
    names = ["control points axis x", "control points axis y", "control points axis z"]
    try:  # the decoder reads its first bytes when it is made: inside the try too
        if dec is None:
            dec = RangeDecoder(data[start:len(data) - CRC_SIZE])
        for what in names + (["weights"] if rational else []):
            if what == "weights":
                before, model, longest = None, _ResidualModel(), bits + 1
            residuals = _decode_residuals(dec, tangential if frames and len(grids) in (1, 2)
                                          else classes, before, model, longest, what,
                                          predictor.sources)
            before = residuals
            if frames and what != "weights":
                summed = _run_sums(residuals, predictor.runs)
                vertices = _in_range(predictor.undo_vertices(summed), predictor.top, start,
                                     what)
                grids.append(vertices + summed[n_vertices:])
                continue
            grids.append(_in_range(predictor.undo(residuals), predictor.top, start, what))
    except RangeDecodeError as exc:
        raise PatchFormatError(len(data) - CRC_SIZE, f"coded residuals end early: {exc}") \
            from None
    return grids


__all__ = ["ATLAS_LIMITS", "CONTROL_MESH_VERSIONS", "FRAME_VERSION", "HEADER", "HEADER_SIZE",
           "MAGIC", "READ_VERSIONS", "VERSION", "CRC_SIZE", "FrameCoder", "canonical_atlas",
           "check_tangent_factor", "frame_codes", "frame_steps", "index_width",
           "payload_size_range", "point_frames", "read_atlas", "read_atlas_header",
           "write_atlas"]
