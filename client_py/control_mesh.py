"""Read and write a smooth base's triangle control mesh: ``.tsa`` versions 5 and 6.

A smooth base (``fitter.fitting.atlas.smooth``) is stored as its control mesh alone, ``n``
points and ``T`` triangles, from which every reader derives the same atlas
(:func:`client_py.smooth_base.smooth_atlas`: one Catmull-Clark step, then a bicubic patch a
quad). :func:`read_atlas_file` (and ``client_py.atlas_format.read_atlas``, which hands a
version-5 or -6 file here) returns that atlas, so every reader of ``base.tsa`` takes either
kind. The layout is in ``docs/format.md`` ("Control mesh (versions 5 and 6)"). In short, the
``.tsa`` framing: the 28-byte header (magic ``TSPA``, version, flags 0, degree 3, spans 1,
the quantisation bits, version 6's parallelogram weight, ``V = n`` points, ``F = T``
triangles, the payload sizes), a zlib payload (the points' bounds as 6 f64, the metadata
JSON), one range-coded stream and a CRC32:

* the triangles, in :func:`traversal_order`, the points numbered in the order the
  triangles first use them (:func:`canonical_control_mesh`). Version 5: each from its
  first corner, as version 3 codes a layout's quads (``client_py.atlas_format._code_faces``
  with 3 corners). Version 6: by Edgebreaker's symbols (:mod:`client_py.triangle_coder`,
  whose traversal is that order), 1.3-2.1 bits a triangle against 3.3-3.9;
* then each axis's quantised coordinates ``q`` (``round((x - lo) (2^bits - 1) / (hi -
  lo))``) as residuals from a prediction made of points decoded before. Version 5: in the
  points' order, from the mean of the point's neighbours (points it shares a triangle edge
  with) numbered before it, coded as version 3 codes its layout vertices
  (``client_py.atlas_format``, "Atlas residuals", class 0). Version 6 (written): in
  :func:`point_order`, from a blend of that mean and the mean of the parallelograms
  (:func:`point_predictors`), coded by :func:`_code_point_residuals`.

Any file that is not a valid control mesh raises
:class:`~client_py.errors.PatchFormatError` with the byte offset and the reason; sizes are
checked on the header before anything is inflated or decoded.
"""

from __future__ import annotations

import heapq
import json
import math
import struct
import zlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from itertools import islice
from typing import NamedTuple

from .atlas import MAX_ATLAS_QUADS, MAX_ATLAS_VERTICES, AtlasSurface
from .atlas_format import (
    CONTROL_MESH_VERSIONS,
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
from .rangecoder import HALF, SLOW_SHIFT, RangeDecodeError, RangeDecoder, RangeEncoder
from .smooth_base import SMOOTH_DEGREE, SMOOTH_SPANS, check_control_mesh, smooth_atlas
from .triangle_coder import decode_triangles, encode_triangles

VERSION = 6  # written; version 5 (``CONTROL_MESH_VERSIONS``) is still read and written on request
#: the parallelogram weight ``w`` of version 6 is ``w / WEIGHT_STEPS``, ``w`` in
#: ``0..WEIGHT_STEPS`` (the header's byte 11)
WEIGHT_STEPS = 8
#: the decoder makes the points' coding steps (:func:`grow_steps`) so many at a time, as its
#: first axis needs them
STEPS_AT_ONCE = 1024
#: :func:`point_order` ranks a point by the share of its neighbours decoded, in these steps
RING_SHARE_STEPS = 64
#: the most control triangles: the derived atlas's quads (3 a triangle) within
#: ``client_py.atlas.MAX_ATLAS_QUADS``
MAX_TRIANGLES = MAX_ATLAS_QUADS // 3
#: the least zlib payload: the bounds (6 f64) and an empty metadata object (``{}``)
LEAST_PAYLOAD = 48 + 4 + 2


@dataclass
class ControlMeshCodes:
    """A control mesh as a file holds it: the points' quantised coordinates ``codes (n,
    3)``, each ``q`` in ``0..2^bits - 1`` standing for ``lo + q (hi - lo) / (2^bits - 1)``
    over ``lows``/``highs`` (3 each), the ``triangles (T, 3)`` and the ``metadata``."""

    codes: list[tuple[int, int, int]]
    triangles: list[tuple[int, int, int]]
    bits: int
    lows: tuple[float, float, float]
    highs: tuple[float, float, float]
    metadata: dict

    def points(self) -> list[tuple[float, float, float]]:
        """The points ``(n, 3)`` the codes stand for."""
        axes = [_dequantise([c[a] for c in self.codes], self.lows[a], self.highs[a], self.bits)
                for a in range(3)]
        return list(zip(*axes, strict=True))


def traversal_order(triangles: Sequence[Sequence[int]]) -> list[tuple[int, int, int]]:
    """The triangles in the order the file holds them: a depth-first walk across shared
    edges from the first triangle (and from the first not yet reached, for each further
    piece), each triangle reached across an edge rotated to start on that edge's far
    corner, ``(y, x, z)`` from ``(x, y)``. Each triangle then shares an edge with one
    coded shortly before it, whose corners the connectivity coder offers first: on
    Nefertiti decimated to 6,000 triangles, version 5's triangles took 2,744 bytes in this
    order, 7,183 in k-d tree order of their centres and 10,018 in the decimation's own.
    Version 6's coder (:mod:`client_py.triangle_coder`), given triangles in any order,
    codes them in this walk of that order (a piece's first triangle opening all three of
    its edges, as here) and numbers the points as :func:`canonical_control_mesh` does; a
    change here must be made there too (``tests/test_control_mesh.py`` checks that they
    agree on shuffled, rotated and bridge-first triangles)."""
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


def _points_in_triangles(triangles: Sequence[Sequence[int]]) -> int:
    """One past the highest point in a triangle: the points from it on are in none, and
    the decoders make no per-point state for them."""
    return 1 + max(map(max, triangles), default=-1)


def _earlier_neighbours(n_points: int, triangles: Sequence[Sequence[int]]
                        ) -> tuple[list[Sequence[int]], list[int]]:
    """Version 5: per point, its neighbours (across a triangle edge) numbered before it,
    whose mean predicts it (version 3's layout vertex rule), and the highest of them (``-1``:
    none), its *source*, whose residual's size is a context of its own. (Sets and lists are
    made up to the highest point in a triangle only, the points past it sharing one empty
    tuple, as :func:`grow_steps` does: a hostile header may state ``2^17`` points and
    two triangles.)"""
    used = _points_in_triangles(triangles)
    sets: list[set[int]] = [set() for _ in range(used)]
    for a, b, c in triangles:
        for x, y in ((a, b), (b, c), (c, a)):
            if x < y:
                sets[y].add(x)
            else:
                sets[x].add(y)
    earlier: list[Sequence[int]] = [sorted(s) for s in sets]
    sources = [e[-1] if e else -1 for e in earlier]
    rest = n_points - used
    return earlier + [()] * rest, sources + [-1] * rest


def point_order(n_points: int, triangles: Sequence[Sequence[int]]) -> list[int]:
    """Version 6's coding order of the points: a greedy region growing over the triangles,
    the next point always the one with the largest share of its neighbours (points it
    shares a triangle edge with) already coded, ``floor(64 known / valence)``, ties to the
    lowest number; with none (the first point, each further piece's, a point in no
    triangle) the lowest-numbered point not yet coded.

    The triangles are all decoded before any point, so the points need not follow the
    triangles' traversal (:func:`canonical_control_mesh`'s numbering, an Edgebreaker-like
    order, Rossignac 1999): this order predicts each point from more of its ring. On the
    fitted bases of session 31 (4,000-6,400 points) the points took 0.5-2.0 % fewer bytes in
    it than in the numbering's order.
    """
    return [step.point for step in grow_steps(n_points, triangles)]


class Step(NamedTuple):
    """One coding step of version 6 (:func:`point_predictors`)."""

    #: the point ``v`` coded
    point: int
    #: its neighbours coded before it, ``N``
    neighbours: tuple[int, ...]
    #: its parallelograms' shared edges ``a, b`` (flat: ``a_0, b_0, a_1, b_1, ...``)
    edge_ends: tuple[int, ...]
    #: their far corners ``c``, one per parallelogram
    far_corners: tuple[int, ...]
    #: the point coded before it (``-1`` for the first)
    previous: int


def point_predictors(n_points: int, triangles: Sequence[Sequence[int]]) -> list[Step]:
    """:func:`grow_steps` as a list."""
    return list(grow_steps(n_points, triangles))


def grow_steps(n_points: int, triangles: Sequence[Sequence[int]]) -> Iterator[Step]:
    """Version 6's prediction of each point, in :func:`point_order`: per :class:`Step`, the
    point ``v``, its ``neighbours`` coded before it, and for each triangle ``(v, a, b)``
    whose far corners are coded, across whose edge ``a -> b`` a triangle ``(b, a, c)`` has
    its corner ``c`` coded too, the parallelogram ``a + b - c`` (Touma & Gotsman, *Triangle
    mesh compression*, Graphics Interface 1998), as ``a, b`` in ``edge_ends`` and ``c`` in
    ``far_corners``; all of them are used and averaged, as in *multi-way* prediction (Cohen-Or,
    Cohen & Irony, *Multi-way geometry encoding*, 2002). :func:`_prediction` blends the two
    means. (Sets and lists per point are made up to the highest point in a triangle only,
    and the steps are made as they are asked for: a hostile header may state ``2^17``
    points and one triangle, and the decoder stops at the first point its stream lacks.)"""
    n = n_points
    across: dict[int, int] = {}  # the directed edge a -> b, as a n + b: its triangle's c
    used = _points_in_triangles(triangles)
    corners: list[list[int]] = [[] for _ in range(used)]  # per point its triangles' a, b
    ring: list[set[int]] = [set() for _ in range(used)]
    for a, b, c in triangles:
        across[a * n + b], across[b * n + c], across[c * n + a] = c, a, b
        corners[a] += (b, c)
        corners[b] += (c, a)
        corners[c] += (a, b)
        ring[a].update((b, c))
        ring[b].update((a, c))
        ring[c].update((a, b))
    valence = [len(r) for r in ring]
    no_triangle: tuple[int, ...] = ()
    known = [0] * n
    done = [False] * n
    heap: list[tuple[int, int]] = []
    lowest, prev = 0, -1
    push, pop, get = heapq.heappush, heapq.heappop, across.get
    for _ in range(n):
        v = -1
        while heap:  # a point's share only grows: its newest entry pops first, stale ones later
            _, u = pop(heap)
            if not done[u]:
                v = u
                break
        if v < 0:
            while done[lowest]:
                lowest += 1
            v = lowest
        ab: list[int] = []
        c_s: list[int] = []
        flat = corners[v] if v < used else no_triangle
        for i in range(0, len(flat), 2):
            a, b = flat[i], flat[i + 1]
            if done[a] and done[b]:
                c = get(b * n + a, -1)
                if c >= 0 and done[c]:
                    ab += (a, b)
                    c_s.append(c)
        earlier = []
        for u in ring[v] if v < used else no_triangle:
            if done[u]:
                earlier.append(u)
            else:
                known[u] += 1
                push(heap, (-(known[u] * RING_SHARE_STEPS // valence[u]), u))
        done[v] = True
        yield Step(v, tuple(earlier), tuple(ab), tuple(c_s), prev)
        prev = v


def _blend_coefficients(steps: Sequence[Step], weight: int) -> list[tuple[int, int, int]]:
    """Per step the integers ``(m, p, d)`` of :func:`_prediction` for the parallelogram
    weight ``weight / WEIGHT_STEPS``."""
    out = []
    for _, earlier, _, c_s, _ in steps:
        n_m, n_p = len(earlier), len(c_s)
        if n_p:
            out.append(((WEIGHT_STEPS - weight) * n_p, weight * n_m, WEIGHT_STEPS * n_m * n_p))
        else:
            out.append((1, 0, n_m))
    return out


def _prediction(q: Sequence[int], step: Step, coefficients: tuple[int, int, int],
                top: int) -> int:
    """``p = M + w (P - M)``, ``M`` the mean of the earlier neighbours' ``q``, ``P`` that of
    the parallelograms, ``w`` the weight: ``floor((2 (m S_M + p S_P) + d) / 2 d)`` with
    ``S_M``, ``S_P`` their sums (:func:`_blend_coefficients`), clamped to ``0..top``; without a
    neighbour coded, the point coded before (0 for the first)."""
    _, earlier, ab, c_s, prev = step
    m, p, d = coefficients
    if not d:
        return q[prev] if prev >= 0 else 0
    total = m * sum(q[u] for u in earlier)
    if p:
        total += p * (sum(q[u] for u in ab) - sum(q[u] for u in c_s))
    guess = (2 * total + d) // (2 * d)
    return 0 if guess < 0 else top if guess > top else guess


class _PointModel:
    """Version 6's adaptive contexts of the point residuals, one set for all three axes
    (docs/format.md, "Control mesh (versions 5 and 6)"): the zero flag, the sign, the
    Exp-Golomb prefix by position ``t``, the mantissa by weight ``2^t``."""

    def __init__(self) -> None:
        self.zero = [HALF]
        self.sign = [HALF]
        self.prefix = [HALF] * MAX_BITS
        self.mantissa = [HALF] * MAX_BITS


def _code_point_residuals(enc: RangeEncoder, residuals: Sequence[int],
                          model: _PointModel) -> None:
    """Code one axis's residuals ``r``, each: a flag ``r != 0``; then a sign ``r < 0``; ``n =
    bitlen(|r|) - 1`` ones (the ``t``-th with context ``t``) and a zero; the ``n`` bits of
    ``|r|`` below its leading one, most significant first (weight ``2^t``: context ``t``);
    every bit at :data:`~client_py.rangecoder.SLOW_SHIFT`. (Contexts by the number of
    parallelograms or by the size of the neighbours' residuals changed the bytes by -0.1 to
    +0.2 % on the fitted bases of session 31: these residuals are close to independent.)"""
    bit, shift = enc.bit, SLOW_SHIFT
    zero, sign, prefix, mantissa = model.zero, model.sign, model.prefix, model.mantissa
    for r in residuals:
        bit(zero, 0, r != 0, shift)
        if not r:
            continue
        bit(sign, 0, r < 0, shift)
        x = -r if r < 0 else r
        n = x.bit_length() - 1
        for t in range(n):
            bit(prefix, t, 1, shift)
        bit(prefix, n, 0, shift)
        for t in range(n - 1, -1, -1):
            bit(mantissa, t, (x >> t) & 1, shift)


def _encode_points(enc: RangeEncoder, axes: Sequence[Sequence[int]], steps: Sequence[Step],
                   bits: int) -> int:
    """Code the three axes' codes (version 6) at the parallelogram weight that codes them in
    the fewest bytes, ties to the lower, and return that weight. (Fitted bases differ:
    session 31's best weights ran from 0 to 4 eighths.)"""
    top = (1 << bits) - 1
    best: tuple[int, int, list[list[int]]] | None = None
    for weight in range(WEIGHT_STEPS + 1):
        coefficients = _blend_coefficients(steps, weight)
        residuals = [[q[s.point] - _prediction(q, s, f, top)
                      for s, f in zip(steps, coefficients, strict=True)] for q in axes]
        trial, model = RangeEncoder(), _PointModel()
        for r in residuals:
            _code_point_residuals(trial, r, model)
        size = len(trial.finish())
        if best is None or size < best[0]:
            best = (size, weight, residuals)
    _, weight, residuals = best
    model = _PointModel()
    for r in residuals:
        _code_point_residuals(enc, r, model)
    return weight


def _decode_points(dec: RangeDecoder, steps: Iterator[Step], n_points: int, bits: int,
                   weight: int, start: int) -> list[list[int]]:
    """Inverse of :func:`_encode_points` at ``weight``: the three axes' codes, point by
    point in the file's numbering; a prefix of ``bits`` ones (no residual of ``bits``-bit
    codes is that long) or a code outside ``0..2^bits - 1`` is a :class:`PatchFormatError`
    (at ``start``, the coded stream's offset). ``steps`` (:func:`grow_steps`) are drawn as
    the first axis decodes, and kept for the other two: a stream that ends early is refused
    before the steps of points it does not hold are made (a 63-byte file stating 131,065
    points took 2.3 s and 27 MB to refuse when they were all made first)."""
    top = (1 << bits) - 1
    made: list[tuple[Step, tuple[int, int, int]]] = []  # the steps drawn, with their blend

    def draw() -> list[tuple[Step, tuple[int, int, int]]]:
        chunk = list(islice(steps, STEPS_AT_ONCE))
        made.extend(zip(chunk, _blend_coefficients(chunk, weight), strict=True))
        return made[len(made) - len(chunk):]

    model = _PointModel()
    bit, shift = dec.bit, SLOW_SHIFT
    zero, sign, prefix, mantissa = model.zero, model.sign, model.prefix, model.mantissa
    axes = []
    for name in "xyz":
        q = [0] * n_points
        before = 0  # the steps of the chunks before this one
        for chunk in iter(draw, []) if name == "x" else (made,):
            for k, (step, f) in enumerate(chunk, before):
                r = 0
                if bit(zero, 0, shift):
                    negative = bit(sign, 0, shift)
                    n = 0
                    while bit(prefix, n, shift):
                        n += 1
                        if n >= bits:
                            raise PatchFormatError(start, f"control points axis {name}: "
                                                   f"residual {k} longer than {bits} bits")
                    r = 1
                    for t in range(n - 1, -1, -1):
                        r = (r << 1) | bit(mantissa, t, shift)
                    if negative:
                        r = -r
                v, earlier, ab, c_s, prev = step  # _prediction, inlined: the decoder's hot loop
                m, p, d = f
                if d:
                    total = m * sum([q[u] for u in earlier])
                    if p:
                        total += p * (sum([q[u] for u in ab]) - sum([q[u] for u in c_s]))
                    guess = (2 * total + d) // (2 * d)
                    r += 0 if guess < 0 else top if guess > top else guess
                elif prev >= 0:
                    r += q[prev]
                q[v] = r
            before += len(chunk)
        axes.append(_in_range(q, top, start, f"control points axis {name}"))
    return axes


def _checked_mesh(n_points: int, triangles: Sequence[Sequence[int]], bits: int,
                  metadata: dict | None) -> tuple[list[tuple[int, int, int]], bytes]:
    """The writers' checks (:func:`write_control_mesh`'s Raises): the triangles as int
    triples and the metadata as JSON bytes."""
    check_bits(bits)
    tris = [tuple(int(v) for v in t) for t in triangles]
    if not 1 <= len(tris) <= MAX_TRIANGLES:
        raise ValueError(f"a control mesh has 1..{MAX_TRIANGLES} triangles, got {len(tris)}")
    if n_points > MAX_ATLAS_VERTICES:
        raise ValueError(f"a control mesh has at most {MAX_ATLAS_VERTICES} points, "
                         f"got {n_points}")
    check_control_mesh(n_points, tris)  # an oriented 2-manifold whose atlas fits the limits
    metadata = {} if metadata is None else metadata
    if not isinstance(metadata, dict):
        raise ValueError(f"metadata must be a dict, got {type(metadata).__name__}")
    meta = json.dumps(metadata, separators=(",", ":"), allow_nan=False).encode("utf-8")
    if len(meta) > MAX_METADATA:
        raise ValueError(f"metadata is {len(meta)} bytes of JSON; at most {MAX_METADATA}")
    return tris, meta


def write_control_mesh(points: Sequence[Sequence[float]], triangles: Sequence[Sequence[int]],
                       bits: int = 12, metadata: dict | None = None,
                       version: int = VERSION) -> bytes:
    """``.tsa`` ``version`` (6, or 5 for older readers) of the control mesh ``points (n,
    3)``, ``triangles (T, 3)``, quantised to ``bits`` over the points' bounds.

    The triangles are put in :func:`traversal_order` and the points renumbered
    (:func:`canonical_control_mesh`), in either version, so :func:`read_control_mesh` gives
    the same triangles, reordered, rotated and renumbered so (the same for versions 5 and
    6, whatever the triangles' order), each point within half a quantisation step of its
    own.

    Raises
    ------
    ValueError
        Points not ``n x 3`` finite numbers, triangles not index triples into them, a mesh
        that is not an oriented 2-manifold (``client_py.smooth_base``), more than
        :data:`MAX_TRIANGLES` triangles, ``bits`` outside ``MIN_BITS..MAX_BITS``, metadata
        that is not a JSON object, or a ``version`` not in
        ``client_py.atlas_format.CONTROL_MESH_VERSIONS``.
    """
    check_bits(bits)
    pts = [tuple(float(c) for c in p) for p in points]
    if len(pts) < 3 or any(len(p) != 3 for p in pts):
        raise ValueError(f"points must be n >= 3 rows of 3 coordinates, got {len(pts)} rows")
    if not all(math.isfinite(c) for p in pts for c in p):
        raise ValueError("points must be finite")
    tris, meta = _checked_mesh(len(pts), triangles, bits, metadata)
    lows = tuple(min(p[a] for p in pts) for a in range(3))
    highs = tuple(max(p[a] for p in pts) for a in range(3))
    axes = [_quantise([p[a] for p in pts], lows[a], highs[a], bits) for a in range(3)]
    return _write(list(zip(*axes, strict=True)), tris, bits, lows, highs, meta, version)


def write_control_codes(mesh: ControlMeshCodes, version: int = VERSION) -> bytes:
    """``.tsa`` ``version`` of a control mesh's codes as they are (no quantisation):
    :func:`read_control_codes` of the file gives ``mesh`` back, reordered and renumbered as
    :func:`write_control_mesh` does (a file's own triangles and codes unchanged).

    Raises
    ------
    ValueError
        As :func:`write_control_mesh`, and for codes outside ``0..2^bits - 1`` or bounds
        not finite with each low at most its high.
    """
    bits = check_bits(mesh.bits)
    codes = [tuple(int(c) for c in p) for p in mesh.codes]
    top = (1 << bits) - 1
    if len(codes) < 3 or any(len(p) != 3 or min(p) < 0 or max(p) > top for p in codes):
        raise ValueError(f"codes must be n >= 3 rows of 3 integers in 0..{top}")
    lows, highs = tuple(map(float, mesh.lows)), tuple(map(float, mesh.highs))
    if len(lows) != 3 or len(highs) != 3 or not all(map(math.isfinite, lows + highs)) \
            or any(lo > hi for lo, hi in zip(lows, highs, strict=True)):
        raise ValueError(f"bounds must be 3 finite lows at most their 3 highs, got {lows} "
                         f"and {highs}")
    tris, meta = _checked_mesh(len(codes), mesh.triangles, bits, mesh.metadata)
    return _write(codes, tris, bits, lows, highs, meta, version)


def _write(codes: list[tuple[int, ...]], tris: list[tuple[int, int, int]], bits: int,
           lows: Sequence[float], highs: Sequence[float], meta: bytes, version: int) -> bytes:
    """The file of checked codes and triangles (any numbering, any order)."""
    if version not in CONTROL_MESH_VERSIONS:
        raise ValueError(f"version must be one of {CONTROL_MESH_VERSIONS}, got {version!r}")
    enc = RangeEncoder()
    # both versions: the triangles in traversal order, the points numbered canonically
    order, tris = canonical_control_mesh(len(codes), traversal_order(tris))
    if version == 5:
        _code_faces(enc, len(tris), len(codes), tris, 3)
    else:  # the coder keeps that order and numbering (its own, composed, if it did not)
        renumbered, tris = encode_triangles(enc, len(codes), tris)
        order = [order[v] for v in renumbered]
    axes = [[codes[v][a] for v in order] for a in range(3)]
    weight = 0
    if version == 5:
        earlier, sources = _earlier_neighbours(len(codes), tris)
        model, before = _ResidualModel(), None
        for q in axes:
            residuals = [q[k] - _vertex_prediction(q, k, earlier[k]) for k in range(len(q))]
            _encode_residuals(enc, residuals, [0] * len(q), before, model, sources)
            before = residuals
    else:
        weight = _encode_points(enc, axes, point_predictors(len(codes), tris), bits)
    raw = struct.pack("<6d", *lows, *highs) + struct.pack("<I", len(meta)) + meta
    payload = zlib.compress(raw, 9)
    head = HEADER.pack(MAGIC, version, 0, SMOOTH_DEGREE, SMOOTH_SPANS, bits, weight,
                       len(codes), len(tris), len(payload), len(raw))
    body = head + payload + enc.finish()
    return body + struct.pack("<I", zlib.crc32(body) & 0xFFFFFFFF)


def read_control_header(data: bytes) -> dict:
    """Check a version-5 or -6 file's framing (magic, version, CRC32) and header fields, in
    order (offsets as in docs/format.md). Returns ``version``, ``bits``, ``weight`` (version
    6's parallelogram weight in :data:`WEIGHT_STEPS` ths; 0 in version 5), ``points``,
    ``triangles``, ``payload_size``, ``raw_size`` and the file's ``data``."""
    data, fields = _unframe(data, MAGIC, "atlas", HEADER, CONTROL_MESH_VERSIONS, None)
    _, version, flags, degree, spans, bits, weight, n_points, n_tris, size, raw_size = fields
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
    if version == 5 and weight:
        raise PatchFormatError(11, f"reserved byte is {weight}, must be 0")
    if weight > WEIGHT_STEPS:
        raise PatchFormatError(11, f"parallelogram weight {weight}/{WEIGHT_STEPS} above 1; "
                               f"0..{WEIGHT_STEPS} accepted")
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
    return {"version": version, "bits": bits, "weight": weight, "points": n_points,
            "triangles": n_tris, "payload_size": size, "raw_size": raw_size, "data": data}


def read_control_codes(data: bytes) -> ControlMeshCodes:
    """Decode a version-5 or -6 ``.tsa`` file into its :class:`ControlMeshCodes` (the file's
    numbering), exactly as written.

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
        if head["version"] == 5:
            tris = _code_faces(dec, n_tris, n_points, None, 3)
        else:
            tris = decode_triangles(dec, n_tris, n_points, start)
        try:
            check_control_mesh(n_points, tris)
        except ValueError as exc:
            raise PatchFormatError(start, f"the triangles are no control mesh: {exc}") \
                from None
        if head["version"] == 5:
            axes = _decode_points_v5(dec, n_points, tris, bits, start)
        else:
            axes = _decode_points(dec, grow_steps(n_points, tris), n_points, bits,
                                  head["weight"], start)
    except RangeDecodeError as exc:
        raise PatchFormatError(end, f"coded control mesh ends early: {exc}") from None
    return ControlMeshCodes(list(zip(*axes, strict=True)), tris, bits, tuple(bounds[:3]),
                            tuple(bounds[3:]), metadata)


def _decode_points_v5(dec: RangeDecoder, n_points: int, tris: Sequence[Sequence[int]],
                      bits: int, start: int) -> list[list[int]]:
    """Version 5's three axes of codes (the module docstring). Objects per point are made
    for the points in a triangle only (:func:`_earlier_neighbours`); any other point costs
    slots in lists (8 bytes each) until it is decoded."""
    earlier, sources = _earlier_neighbours(n_points, tris)
    top = (1 << bits) - 1
    model, before, axes = _ResidualModel(), None, []
    for name in "xyz":
        what = f"control points axis {name}"
        residuals = _decode_residuals(dec, [0] * n_points, before, model, bits, what, sources)
        before = residuals
        q: list[int] = []
        for k, r in enumerate(residuals):
            q.append(r + _vertex_prediction(q, k, earlier[k]))
        axes.append(_in_range(q, top, start, what))
    return axes


def read_control_mesh(data: bytes) -> tuple[list[tuple[float, float, float]],
                                            list[tuple[int, int, int]], dict]:
    """Decode a version-5 or -6 ``.tsa`` file into ``(points, triangles, metadata)`` (the
    file's numbering; :func:`read_control_codes` gives the quantised codes).

    Raises
    ------
    PatchFormatError
        For anything but a valid control mesh, with the byte offset and the reason.
    """
    mesh = read_control_codes(data)
    return mesh.points(), mesh.triangles, mesh.metadata


def read_atlas_file(data: bytes) -> tuple[AtlasSurface, dict]:
    """The atlas a version-5 or -6 file draws (:func:`client_py.smooth_base.smooth_atlas`
    of its control mesh) and its metadata."""
    points, tris, metadata = read_control_mesh(data)
    return smooth_atlas(points, tris), metadata


__all__ = ["MAX_TRIANGLES", "VERSION", "WEIGHT_STEPS", "ControlMeshCodes", "Step",
           "canonical_control_mesh", "grow_steps", "point_order", "point_predictors",
           "read_atlas_file", "read_control_codes", "read_control_header", "read_control_mesh",
           "traversal_order", "write_control_codes", "write_control_mesh"]
