"""Read and write a smooth base's triangle control mesh: ``.tsa`` version 5.

A smooth base (``fitter.fitting.atlas.smooth``) is stored as its control mesh alone, ``n``
points and ``T`` triangles, from which every reader derives the same atlas
(:func:`client_py.smooth_base.smooth_atlas`: one Catmull-Clark step, then a bicubic patch a
quad). :func:`read_atlas_file` (and ``client_py.atlas_format.read_atlas``, which hands a
version-5 file here) returns that atlas, so every reader of ``base.tsa`` takes either kind.
The layout is in ``docs/format.md`` ("Control mesh (version 5)"). In short, the ``.tsa``
framing: the 28-byte header (magic ``TSPA``, version 5, flags 0, degree 3, spans 1, the
quantisation bits, ``V = n`` points, ``F = T`` triangles, the payload sizes), a zlib payload
(the points' bounds as 6 f64, the metadata JSON), one range-coded stream and a CRC32:

* the triangles, in the file's order, each from its first corner, as version 3 codes a
  layout's quads (``client_py.atlas_format._code_faces`` with 3 corners): the points are
  numbered in the order the triangles first use them (:func:`canonical_control_mesh`);
* then each axis's quantised coordinates ``q`` (``round((x - lo) (2^bits - 1) / (hi -
  lo))``) as residuals from the mean of the point's neighbours (points it shares a
  triangle edge with) numbered before it, as version 3 codes its layout vertices
  (``client_py.atlas_format``, "Atlas residuals", class 0).

Any file that is not a valid control mesh raises
:class:`~client_py.errors.PatchFormatError` with the byte offset and the reason; sizes are
checked on the header before anything is inflated or decoded.
"""

from __future__ import annotations

import json
import math
import struct
import zlib
from collections.abc import Sequence

from .atlas import MAX_ATLAS_QUADS, MAX_ATLAS_VERTICES, AtlasSurface
from .atlas_format import (
    HEADER,
    HEADER_SIZE,
    MAGIC,
    _code_faces,
    _decode_residuals,
    _encode_residuals,
    _in_range,
    _ResidualModel,
    _vertex_prediction,
)
from .errors import PatchFormatError
from .format import (
    CRC_SIZE,
    MAX_BITS,
    MAX_INFLATE_RATIO,
    MAX_METADATA,
    MIN_BITS,
    _Cursor,
    _dequantise,
    _inflate,
    _quantise,
    _read_metadata,
    _unframe,
    check_bits,
)
from .rangecoder import RangeDecodeError, RangeDecoder, RangeEncoder
from .smooth_base import SMOOTH_DEGREE, SMOOTH_SPANS, check_control_mesh, smooth_atlas

VERSION = 5
#: the most control triangles: the derived atlas's quads (3 a triangle) within
#: ``client_py.atlas.MAX_ATLAS_QUADS``
MAX_TRIANGLES = MAX_ATLAS_QUADS // 3
#: the least zlib payload: the bounds (6 f64) and an empty metadata object (``{}``)
LEAST_PAYLOAD = 48 + 4 + 2


def traversal_order(triangles: Sequence[Sequence[int]]) -> list[tuple[int, int, int]]:
    """The triangles in the order the file holds them: a depth-first walk across shared
    edges from the first triangle (and from the first not yet reached, for each further
    piece), each triangle reached across an edge rotated to start on that edge's far
    corner, ``(y, x, z)`` from ``(x, y)``. Each triangle then shares an edge with one
    coded shortly before it, whose corners the connectivity coder offers first: on
    Nefertiti decimated to 6,000 triangles, the triangles took 2,744 bytes in this order,
    7,183 in k-d tree order of their centres and 10,018 in the decimation's own."""
    tris = [tuple(int(v) for v in t) for t in triangles]
    by_edge: dict[tuple[int, int], list[int]] = {}
    for t, (a, b, c) in enumerate(tris):
        for x, y in ((a, b), (b, c), (c, a)):
            by_edge.setdefault((min(x, y), max(x, y)), []).append(t)
    seen = [False] * len(tris)
    out: list[tuple[int, int, int]] = []
    for start in range(len(tris)):
        if seen[start]:
            continue
        stack = [(start, tris[start][0])]
        while stack:
            t, first = stack.pop()
            if seen[t]:
                continue
            seen[t] = True
            tri = tris[t]
            i = tri.index(first)
            a, b, c = tri[i], tri[(i + 1) % 3], tri[(i + 2) % 3]
            out.append((a, b, c))
            for x, y in ((a, b), (c, a), (b, c)):  # the last pushed, across (b, c), next
                for u in by_edge[(min(x, y), max(x, y))]:
                    if not seen[u]:
                        stack.append((u, y))
    return out


def canonical_control_mesh(n_points: int, triangles: Sequence[Sequence[int]]
                           ) -> tuple[list[int], list[tuple[int, int, int]]]:
    """The file's numbering: point ``order[k]`` becomes ``k``, in the order the triangles
    (each from its first corner) first use them, points in no triangle last in their own
    order; returns ``order`` and the triangles renumbered (same order, same corners)."""
    new = [-1] * n_points
    order: list[int] = []
    for tri in triangles:
        for v in tri:
            if new[v] < 0:
                new[v] = len(order)
                order.append(v)
    for v in range(n_points):
        if new[v] < 0:
            new[v] = len(order)
            order.append(v)
    return order, [(new[a], new[b], new[c]) for a, b, c in triangles]


def _earlier_neighbours(n_points: int, triangles: Sequence[Sequence[int]]
                        ) -> tuple[list[list[int]], list[int]]:
    """Per point, its neighbours (across a triangle edge) numbered before it, whose mean
    predicts it (version 3's layout vertex rule), and the highest of them (``-1``: none),
    its *source*, whose residual's size is a context of its own. (The parallelogram rule,
    Touma & Gotsman 1998, across the edge opposite a point's first triangle, was tried: on
    Nefertiti decimated to 6,000 triangles at 10 bits the points took 7,049 bytes for it,
    6,822 for the mean, 6,564 for the mean of both.)"""
    sets: list[set[int]] = [set() for _ in range(n_points)]
    for a, b, c in triangles:
        for x, y in ((a, b), (b, c), (c, a)):
            if x < y:
                sets[y].add(x)
            else:
                sets[x].add(y)
    earlier = [sorted(s) for s in sets]
    return earlier, [e[-1] if e else -1 for e in earlier]


def write_control_mesh(points: Sequence[Sequence[float]], triangles: Sequence[Sequence[int]],
                       bits: int = 12, metadata: dict | None = None) -> bytes:
    """``.tsa`` version 5 of the control mesh ``points (n, 3)``, ``triangles (T, 3)``.

    The triangles are put in :func:`traversal_order` and the points renumbered
    (:func:`canonical_control_mesh`), so :func:`read_control_mesh` gives the same triangles,
    reordered, rotated and renumbered so, each point within half a quantisation step of
    its own.

    Raises
    ------
    ValueError
        Points not ``n x 3`` finite numbers, triangles not index triples into them, a mesh
        that is not an oriented 2-manifold (``client_py.smooth_base``), more than
        :data:`MAX_TRIANGLES` triangles, ``bits`` outside ``MIN_BITS..MAX_BITS``, or
        metadata that is not a JSON object.
    """
    check_bits(bits)
    pts = [tuple(float(c) for c in p) for p in points]
    if len(pts) < 3 or any(len(p) != 3 for p in pts):
        raise ValueError(f"points must be n >= 3 rows of 3 coordinates, got {len(pts)} rows")
    if not all(math.isfinite(c) for p in pts for c in p):
        raise ValueError("points must be finite")
    tris = [tuple(int(v) for v in t) for t in triangles]
    if not 1 <= len(tris) <= MAX_TRIANGLES:
        raise ValueError(f"a control mesh has 1..{MAX_TRIANGLES} triangles, got {len(tris)}")
    if len(pts) > MAX_ATLAS_VERTICES:
        raise ValueError(f"a control mesh has at most {MAX_ATLAS_VERTICES} points, "
                         f"got {len(pts)}")
    check_control_mesh(len(pts), tris)  # an oriented 2-manifold whose atlas fits the limits
    metadata = {} if metadata is None else metadata
    if not isinstance(metadata, dict):
        raise ValueError(f"metadata must be a dict, got {type(metadata).__name__}")
    meta = json.dumps(metadata, separators=(",", ":"), allow_nan=False).encode("utf-8")
    if len(meta) > MAX_METADATA:
        raise ValueError(f"metadata is {len(meta)} bytes of JSON; at most {MAX_METADATA}")
    order, tris = canonical_control_mesh(len(pts), traversal_order(tris))
    pts = [pts[v] for v in order]
    lows = [min(p[a] for p in pts) for a in range(3)]
    highs = [max(p[a] for p in pts) for a in range(3)]
    earlier, sources = _earlier_neighbours(len(pts), tris)
    enc = RangeEncoder()
    _code_faces(enc, len(tris), len(pts), tris, 3)
    model, before = _ResidualModel(), None
    for a in range(3):
        q = _quantise([p[a] for p in pts], lows[a], highs[a], bits)
        residuals = [q[k] - _vertex_prediction(q, k, earlier[k]) for k in range(len(q))]
        _encode_residuals(enc, residuals, [0] * len(q), before, model, sources)
        before = residuals
    raw = struct.pack("<6d", *lows, *highs) + struct.pack("<I", len(meta)) + meta
    payload = zlib.compress(raw, 9)
    head = HEADER.pack(MAGIC, VERSION, 0, SMOOTH_DEGREE, SMOOTH_SPANS, bits, 0, len(pts),
                       len(tris), len(payload), len(raw))
    body = head + payload + enc.finish()
    return body + struct.pack("<I", zlib.crc32(body) & 0xFFFFFFFF)


def read_control_header(data: bytes) -> dict:
    """Check a version-5 file's framing (magic, version, CRC32) and header fields, in order
    (offsets as in docs/format.md). Returns ``bits``, ``points``, ``triangles``,
    ``payload_size``, ``raw_size`` and the file's ``data``."""
    data, fields = _unframe(data, MAGIC, "atlas", HEADER, VERSION, None)
    _, _, flags, degree, spans, bits, reserved, n_points, n_tris, size, raw_size = fields
    if flags:
        raise PatchFormatError(6, f"unknown flags 0x{flags:04x} (a control mesh has none)")
    if degree != SMOOTH_DEGREE:
        raise PatchFormatError(8, f"degree {degree}; a control mesh's patches have "
                               f"{SMOOTH_DEGREE}")
    if spans != SMOOTH_SPANS:
        raise PatchFormatError(9, f"spans = {spans}; a control mesh's patches have "
                               f"{SMOOTH_SPANS}")
    if not MIN_BITS <= bits <= MAX_BITS:
        raise PatchFormatError(10, f"bits = {bits} outside {MIN_BITS}..{MAX_BITS}")
    if reserved:
        raise PatchFormatError(11, f"reserved byte is {reserved}, must be 0")
    if not 3 <= n_points <= MAX_ATLAS_VERTICES:
        raise PatchFormatError(12, f"{n_points} points; 3..{MAX_ATLAS_VERTICES} accepted")
    if not 1 <= n_tris <= MAX_TRIANGLES:
        raise PatchFormatError(16, f"{n_tris} triangles; 1..{MAX_TRIANGLES} accepted")
    most = LEAST_PAYLOAD - 2 + MAX_METADATA
    if not LEAST_PAYLOAD <= raw_size <= most:
        raise PatchFormatError(24, f"payload size {raw_size} outside {LEAST_PAYLOAD}..{most}")
    if raw_size > MAX_INFLATE_RATIO * size:
        raise PatchFormatError(24, f"payload size {raw_size} exceeds the "
                               f"{MAX_INFLATE_RATIO * size} bytes a {size}-byte zlib stream "
                               f"can inflate to ({MAX_INFLATE_RATIO}:1)")
    if HEADER_SIZE + size + 4 > len(data) - CRC_SIZE:
        raise PatchFormatError(20, f"payload size {size} leaves no room for the coded "
                               f"triangles and points in {len(data)} bytes")
    return {"bits": bits, "points": n_points, "triangles": n_tris, "payload_size": size,
            "raw_size": raw_size, "data": data}


def read_control_mesh(data: bytes) -> tuple[list[tuple[float, float, float]],
                                            list[tuple[int, int, int]], dict]:
    """Decode a version-5 ``.tsa`` file into ``(points, triangles, metadata)`` (the file's
    numbering).

    Raises
    ------
    PatchFormatError
        For anything but a valid control mesh, with the byte offset and the reason.
    """
    head = read_control_header(data)
    data, bits = head["data"], head["bits"]
    n_points, n_tris = head["points"], head["triangles"]
    raw = _inflate(data, HEADER_SIZE, head["payload_size"], head["raw_size"], 24)
    cur = _Cursor(raw)
    bounds = cur.finite("<6d", "point bounds")
    if any(bounds[a] > bounds[a + 3] for a in range(3)):
        raise PatchFormatError(0, f"point bounds {bounds} have a low above its high",
                               "payload")
    metadata = _read_metadata(cur, raw)
    start, end = HEADER_SIZE + head["payload_size"], len(data) - CRC_SIZE
    try:  # the decoder reads its first bytes when it is made: inside the try too
        dec = RangeDecoder(data[start:end])
        tris = _code_faces(dec, n_tris, n_points, None, 3)
        try:
            check_control_mesh(n_points, tris)
        except ValueError as exc:
            raise PatchFormatError(start, f"the triangles are no control mesh: {exc}") \
                from None
        earlier, sources = _earlier_neighbours(n_points, tris)
        top = (1 << bits) - 1
        model, before, axes = _ResidualModel(), None, []
        for name in "xyz":
            what = f"control points axis {name}"
            residuals = _decode_residuals(dec, [0] * n_points, before, model, bits, what,
                                          sources)
            before = residuals
            q: list[int] = []
            for k, r in enumerate(residuals):
                q.append(r + _vertex_prediction(q, k, earlier[k]))
            _in_range(q, top, start, what)
            axes.append(_dequantise(q, bounds[len(axes)], bounds[len(axes) + 3], bits))
    except RangeDecodeError as exc:
        raise PatchFormatError(end, f"coded control mesh ends early: {exc}") from None
    return list(zip(*axes, strict=True)), tris, metadata


def read_atlas_file(data: bytes) -> tuple[AtlasSurface, dict]:
    """The atlas a version-5 file draws (:func:`client_py.smooth_base.smooth_atlas` of its
    control mesh) and its metadata."""
    points, tris, metadata = read_control_mesh(data)
    return smooth_atlas(points, tris), metadata


__all__ = ["MAX_TRIANGLES", "VERSION", "canonical_control_mesh", "read_atlas_file",
           "read_control_header", "read_control_mesh", "write_control_mesh"]
