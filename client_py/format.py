"""Read and write Tessera patch files (``.tsp``, format v1): the only module that knows bytes.

The layout is specified in ``docs/format.md``. In short: a 24-byte header
(magic ``TSPF``, version, flags, degrees, grid size, quantisation bits, payload
sizes), a zlib-compressed payload (domain, non-uniform knots, quantisation
bounds, control points quantised per axis to ``bits`` over their bounding box
and coded as parallelogram-prediction residuals in byte planes, log-weights
coded the same way, trim mask bits, metadata JSON) and a CRC32 of all that
precedes it. Readable with ``struct``, ``zlib`` and ``json`` alone.

Any file that is not a valid v1 patch raises :class:`PatchFormatError` with the
byte offset and the reason; decoding is bounded by sizes checked up front, so
it never hangs and never allocates more than the header announces.
"""

from __future__ import annotations

import json
import math
import struct
import sys
import zlib
from array import array
from collections.abc import Sequence
from itertools import accumulate
from operator import add

from .basis import is_uniform_clamped
from .errors import PatchFormatError
from .layers import MAX_DETAIL_DEGREE, DetailTile
from .layers import MAX_LEVEL as MAX_TILE_LEVEL
from .layers import MAX_SPANS as MAX_TILE_SPANS
from .rangecoder import (
    HALF,
    RangeDecodeError,
    RangeDecoder,
    RangeEncoder,
    decode_exp_golomb,
    encode_exp_golomb,
)
from .surface import NurbsSurface
from .trim import MAX_SIDE as TRIM_MAX_SIDE
from .trim import TrimMask

MAGIC = b"TSPF"
VERSION = 1
HEADER = struct.Struct("<4sHHBBHHBBII")  # magic version flags p q n_u n_v bits reserved sizes
HEADER_SIZE = HEADER.size  # 24
CRC_SIZE = 4

FLAG_RATIONAL = 1
FLAG_TRIM = 2
FLAG_UNIFORM_U = 4
FLAG_UNIFORM_V = 8
KNOWN_FLAGS = FLAG_RATIONAL | FLAG_TRIM | FLAG_UNIFORM_U | FLAG_UNIFORM_V

MIN_BITS, MAX_BITS = 2, 30

# ------------------------------------------------------------------ limits
# What a reader accepts, checked on the header before anything is inflated or allocated,
# so a decode's time and memory are bounded by these numbers whatever the bytes claim
# (docs/format.md, "Limits", lists the same; tests/test_fuzz.py holds the two together).
MAX_DEGREE = 15
#: control points per side of a patch: the fitter's largest grid side
#: (``fitter.fitting.options.GRID_SIDE_LIMIT``)
MAX_GRID_SIDE = 1024
#: control points of a patch, ``n_u n_v``: 512^2 decode in about 1 s and 150 MB of
#: CPython (pure Python); 4096^2 would take minutes and gigabytes
MAX_CONTROL_POINTS = 1 << 18
MAX_METADATA = 1 << 20
#: deflate's largest expansion (258-byte matches at about 2 bits each, 1032:1): a zlib
#: stream claiming more raw bytes per compressed byte is refused before it is inflated
MAX_INFLATE_RATIO = 1032
#: detail tiles: the deepest level, spans per tile side and degree are DetailTile's
#: (``client_py.layers``, imported above as MAX_TILE_LEVEL, MAX_TILE_SPANS and
#: MAX_DETAIL_DEGREE); the drawn mask's side is the file's
MAX_DRAWN_SIDE = 64  # the fitter writes 32 (fitter.fitting.detail.DRAWN_SIDE)

#: every limit above by the name docs/format.md gives it
LIMITS = {
    "degree": MAX_DEGREE, "grid side": MAX_GRID_SIDE, "control points": MAX_CONTROL_POINTS,
    "metadata bytes": MAX_METADATA, "inflate ratio": MAX_INFLATE_RATIO,
    "trim side": TRIM_MAX_SIDE, "tile level": MAX_TILE_LEVEL, "tile spans": MAX_TILE_SPANS,
    "tile degree": MAX_DETAIL_DEGREE, "drawn side": MAX_DRAWN_SIDE,
}

_WORD_WIDTH = {1: 1, 2: 2, 3: 4, 4: 4}  # bytes of the array item holding ``planes`` bytes
_WORD_CODE = {array(code).itemsize: code for code in "LIHB"}  # item size -> typecode


# ------------------------------------------------------------------ residual coding
def _plane_count(bits: int) -> int:
    """Bytes per zig-zag residual: residuals of ``bits``-bit values need ``bits + 2`` bits."""
    return (bits + 2 + 7) // 8


def _parallelogram_residuals(values: Sequence[int], n_u: int, n_v: int) -> list[int]:
    """``r_ij = q_ij - (q_{i-1,j} + q_{i,j-1} - q_{i-1,j-1})`` (missing neighbours are 0)."""
    res = []
    for i in range(n_u):
        row, up = i * n_v, (i - 1) * n_v
        for j in range(n_v):
            left = values[row + j - 1] if j else 0
            top = values[up + j] if i else 0
            diag = values[up + j - 1] if i and j else 0
            res.append(values[row + j] - (left + top - diag))
    return res


def _undo_parallelogram(residuals: Sequence[int], n_u: int, n_v: int) -> list[int]:
    """Inverse of :func:`_parallelogram_residuals`: ``q_ij = sum_{a <= i, b <= j} r_ab``,
    a 2-D prefix sum (running sums along each row, then down the columns) that
    ``itertools.accumulate`` and ``map`` compute at C speed."""
    values: list[int] = []
    above = [0] * n_v
    for i in range(n_u):
        above = list(map(add, above, accumulate(residuals[i * n_v : (i + 1) * n_v])))
        values += above
    return values


def _encode_planes(residuals: Sequence[int], planes: int) -> bytes:
    """Zig-zag residuals split into byte planes (low bytes first): zlib then finds the
    long runs of zero high bytes that smooth surfaces give."""
    zig = [2 * r if r >= 0 else -2 * r - 1 for r in residuals]
    return b"".join(bytes((z >> (8 * k)) & 255 for z in zig) for k in range(planes))


def _decode_planes(data: bytes, count: int, planes: int) -> list[int]:
    """Inverse of :func:`_encode_planes`: the planes interleaved back into little-endian
    words at C speed (slice assignment, ``array.frombytes``), then un-zig-zagged."""
    width = _WORD_WIDTH[planes]
    words = bytearray(count * width)
    for k in range(planes):
        words[k::width] = data[k * count : (k + 1) * count]
    zig = array(_WORD_CODE[width])
    zig.frombytes(words)
    if sys.byteorder == "big":
        zig.byteswap()
    return [(z >> 1) ^ -(z & 1) for z in zig]  # 2r -> r, 2r - 1 -> -r


def _pack_bits(cells: bytes) -> bytes:
    """0/1 bytes packed eight to a byte, cell ``k`` in bit ``k mod 8`` of byte ``k // 8``."""
    packed = bytearray((len(cells) + 7) // 8)
    for k, cell in enumerate(cells):
        if cell:
            packed[k >> 3] |= 1 << (k & 7)
    return bytes(packed)


def _unpack_bits(packed: bytes, count: int) -> bytes:
    return bytes((packed[k >> 3] >> (k & 7)) & 1 for k in range(count))


def _quantise(values: Sequence[float], lo: float, hi: float, bits: int) -> list[int]:
    top = (1 << bits) - 1
    if hi <= lo:
        return [0] * len(values)
    scale = top / (hi - lo)
    return [min(top, max(0, int(round((x - lo) * scale)))) for x in values]


def _dequantise(values: Sequence[int], lo: float, hi: float, bits: int) -> list[float]:
    step = (hi - lo) / ((1 << bits) - 1)
    return [lo + q * step for q in values]


# ------------------------------------------------------------------ writing
def check_bits(bits: object) -> int:
    """``bits`` if it is a quantisation the patch and atlas files accept
    (``MIN_BITS..MAX_BITS``); ``ValueError`` naming it otherwise."""
    if isinstance(bits, bool) or not isinstance(bits, int) or not MIN_BITS <= bits <= MAX_BITS:
        raise ValueError(f"bits must be an integer in {MIN_BITS}..{MAX_BITS}, got {bits!r}")
    return bits


def write_patch(surface: NurbsSurface, bits: int = 16, metadata: dict | None = None) -> bytes:
    """Encode ``surface`` as a v1 patch.

    Parameters
    ----------
    bits : int
        Quantisation of each control-point axis over its bounding box
        (``2..30``): the error is at most ``2^-(bits+1)`` of the box per axis.
    metadata : dict, optional
        JSON-serialisable; merged over ``surface.metadata``.

    Returns
    -------
    bytes
        The same surface and options always give the same bytes.
    """
    if not isinstance(surface, NurbsSurface):
        raise ValueError(f"surface must be a NurbsSurface, got {type(surface).__name__}")
    check_bits(bits)
    (p, q), (n_u, n_v) = surface.degree, surface.shape
    if p > MAX_DEGREE or q > MAX_DEGREE:
        raise ValueError(f"degree {surface.degree} exceeds the format's maximum {MAX_DEGREE}")
    if max(n_u, n_v) > MAX_GRID_SIDE or n_u * n_v > MAX_CONTROL_POINTS:
        raise ValueError(f"grid {n_u}x{n_v} exceeds what a reader accepts: at most "
                         f"{MAX_GRID_SIDE} control points per side and {MAX_CONTROL_POINTS} "
                         "in all")
    meta = dict(surface.metadata)
    meta.update(metadata or {})
    try:
        meta_bytes = json.dumps(meta, sort_keys=True, separators=(",", ":"),
                                allow_nan=False).encode()
    except (TypeError, ValueError) as exc:
        raise ValueError(f"metadata must be JSON-serialisable: {exc}") from None
    if len(meta_bytes) > MAX_METADATA:
        raise ValueError(f"metadata is {len(meta_bytes)} bytes of JSON; at most 1 MiB fits")

    U, V = surface.knots
    flags = 0
    parts = [struct.pack("<4d", U[p], U[-p - 1], V[q], V[-q - 1])]
    for flag, degree, knots in ((FLAG_UNIFORM_U, p, U), (FLAG_UNIFORM_V, q, V)):
        if is_uniform_clamped(degree, knots, tol=0.0):
            flags |= flag
        else:
            inner = knots[degree + 1 : -degree - 1]
            parts.append(struct.pack(f"<{len(inner)}d", *inner))

    planes = _plane_count(bits)
    pts = surface.flat_points
    axes = [pts[0::3], pts[1::3], pts[2::3]]
    lows = [min(a) for a in axes]
    highs = [max(a) for a in axes]
    parts.append(struct.pack("<6d", *lows, *highs))
    for axis, lo, hi in zip(axes, lows, highs, strict=True):
        quantised = _quantise(axis, lo, hi, bits)
        parts.append(_encode_planes(_parallelogram_residuals(quantised, n_u, n_v), planes))
    if surface.is_rational:
        flags |= FLAG_RATIONAL
        logs = [math.log(w) for w in surface.flat_weights]
        lo, hi = min(logs), max(logs)
        parts.append(struct.pack("<2d", lo, hi))
        quantised = _quantise(logs, lo, hi, bits)
        parts.append(_encode_planes(_parallelogram_residuals(quantised, n_u, n_v), planes))
    if surface.trim is not None:
        flags |= FLAG_TRIM
        trim = surface.trim
        parts.append(struct.pack("<HH", trim.rows, trim.cols) + _pack_bits(trim.flat))
    parts.append(struct.pack("<I", len(meta_bytes)) + meta_bytes)

    raw = b"".join(parts)
    payload = zlib.compress(raw, 9)
    header = HEADER.pack(MAGIC, VERSION, flags, p, q, n_u, n_v, bits, 0, len(payload), len(raw))
    body = header + payload
    return body + struct.pack("<I", zlib.crc32(body))


# ------------------------------------------------------------------ reading
class _Cursor:
    """Bounded reads from the decompressed payload; overruns become PatchFormatError."""

    def __init__(self, data: bytes) -> None:
        self.data, self.pos = data, 0

    def take(self, size: int, what: str) -> bytes:
        if self.pos + size > len(self.data):
            raise PatchFormatError(
                self.pos, f"{what} needs {size} bytes, {len(self.data) - self.pos} remain",
                "payload",
            )
        chunk = self.data[self.pos : self.pos + size]
        self.pos += size
        return chunk

    def unpack(self, fmt: str, what: str) -> tuple:
        return struct.unpack(fmt, self.take(struct.calcsize(fmt), what))

    def finite(self, fmt: str, what: str) -> tuple:
        start = self.pos
        values = self.unpack(fmt, what)
        if not all(math.isfinite(x) for x in values):
            raise PatchFormatError(start, f"{what} holds a non-finite number", "payload")
        return values


def _read_grid(cur: _Cursor, n_u: int, n_v: int, bits: int, what: str) -> list[int]:
    count = n_u * n_v
    start = cur.pos
    data = cur.take(count * _plane_count(bits), what)
    values = _undo_parallelogram(_decode_planes(data, count, _plane_count(bits)), n_u, n_v)
    top = (1 << bits) - 1
    if min(values) < 0 or max(values) > top:
        raise PatchFormatError(start, f"{what} decode outside 0..{top}", "payload")
    return values


def _read_knots(cur: _Cursor, uniform: bool, degree: int, n_ctrl: int, lo: float, hi: float,
                what: str) -> list[float]:
    if uniform:
        spans = n_ctrl - degree
        inner = [lo + (hi - lo) * i / spans for i in range(1, spans)]
    else:
        inner = list(cur.finite(f"<{n_ctrl - degree - 1}d", what))
    return [lo] * (degree + 1) + inner + [hi] * (degree + 1)


def _reject_constant(name: str) -> float:
    raise ValueError(f"{name} is not JSON (numbers must be finite)")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"number {text[:40]} overflows a double (numbers must be finite)")
    return value


def loads_finite_json(text: str):  # noqa: ANN201 - any JSON value
    """``json.loads(text)`` that refuses what strict JSON has not: ``NaN``, ``Infinity`` and
    numbers that overflow a double (``1e999``), with a ``ValueError`` naming them. Used for
    the patch metadata here and for bundle manifests by the server.

    Raises
    ------
    ValueError
        Not JSON (``json.JSONDecodeError``), or a non-finite number.
    RecursionError
        Nesting deeper than the interpreter's recursion limit.
    """
    return json.loads(text, parse_constant=_reject_constant, parse_float=_finite_float)


def _unframe(data: object, magic: bytes, what: str, header: struct.Struct,
             version: int | tuple[int, ...], size_field: int | None) -> tuple[bytes, tuple]:
    """Check a container's framing — bytes, magic, header length, version (field 1: ``version``
    or one of them), total length from the payload size (field ``size_field``; ``None``: the
    payload runs to the CRC), CRC32 — and return the bytes and the header fields."""
    if not isinstance(data, bytes | bytearray | memoryview):
        raise PatchFormatError(0, f"expected bytes, got {type(data).__name__}")
    data = bytes(data)
    if len(data) < 4 or data[:4] != magic:
        raise PatchFormatError(0, f"magic is {data[:4]!r}, not {magic!r}: not a Tessera {what}")
    if len(data) < header.size + CRC_SIZE:
        raise PatchFormatError(len(data), f"truncated: {len(data)} bytes, the header alone "
                               f"needs {header.size + CRC_SIZE}")
    fields = header.unpack_from(data)
    versions = (version,) if isinstance(version, int) else version
    if fields[1] not in versions:
        raise PatchFormatError(4, f"{what} format version {fields[1]} is not supported "
                               f"(this reader: {', '.join(map(str, versions))})")
    end = len(data) - CRC_SIZE if size_field is None else header.size + fields[size_field]
    if len(data) < end + CRC_SIZE:
        raise PatchFormatError(len(data), f"truncated: {len(data)} bytes of {end + CRC_SIZE}")
    if len(data) > end + CRC_SIZE:
        raise PatchFormatError(end + CRC_SIZE,
                               f"{len(data) - end - CRC_SIZE} unexpected trailing bytes")
    (crc,) = struct.unpack_from("<I", data, end)
    if zlib.crc32(data[:end]) != crc:
        raise PatchFormatError(end, "CRC32 mismatch: the file is corrupted")
    return data, fields


def payload_size_range(flags: int, degree: tuple[int, int], shape: tuple[int, int],
                       bits: int) -> tuple[int, int]:
    """``(least, most)`` bytes of the decompressed payload of a patch with these header fields.

    ``least = 8 (4 + k_u + k_v + 6) + G n_u n_v B + 4 + 2`` (domain, stored knots ``k = n -
    p - 1`` of a non-uniform vector, bounds, ``G`` grids of ``B``-byte residuals, the
    metadata length and ``{}``), plus ``16`` for the log-weight bounds and ``4 + 1`` for
    the smallest trim mask; ``most`` has the largest trim mask and metadata instead.
    """
    (p, q), (n_u, n_v) = degree, shape
    stored_knots = (0 if flags & FLAG_UNIFORM_U else n_u - p - 1) \
        + (0 if flags & FLAG_UNIFORM_V else n_v - q - 1)
    grids = 4 if flags & FLAG_RATIONAL else 3
    fixed = 8 * (4 + stored_knots + 6) + grids * n_u * n_v * _plane_count(bits) + 4
    if flags & FLAG_RATIONAL:
        fixed += 16
    trim_least, trim_most = (4 + 1, 4 + (TRIM_MAX_SIDE**2 + 7) // 8) if flags & FLAG_TRIM \
        else (0, 0)
    return fixed + trim_least + 2, fixed + trim_most + MAX_METADATA


def read_header(data: bytes) -> dict:
    """Check the framing (magic, version, sizes, CRC32) and return the header fields."""
    data, fields = _unframe(data, MAGIC, "patch", HEADER, VERSION, 9)
    magic, version, flags, p, q, n_u, n_v, bits, reserved, size, raw_size = fields
    if flags & ~KNOWN_FLAGS:
        raise PatchFormatError(6, f"unknown flags 0x{flags:04x}")
    for offset, name, degree in ((8, "p", p), (9, "q", q)):
        if not 1 <= degree <= MAX_DEGREE:
            raise PatchFormatError(offset, f"degree {name} = {degree} outside 1..{MAX_DEGREE}")
    for offset, name, n, degree in ((10, "n_u", n_u, p), (12, "n_v", n_v, q)):
        if not degree + 1 <= n <= MAX_GRID_SIDE:
            least = "< degree + 1" if n <= degree else f"> {MAX_GRID_SIDE} per side"
            raise PatchFormatError(offset, f"{name} = {n} control points {least}; "
                                   f"{degree + 1}..{MAX_GRID_SIDE} accepted")
    if n_u * n_v > MAX_CONTROL_POINTS:
        raise PatchFormatError(10, f"grid {n_u}x{n_v} exceeds {MAX_CONTROL_POINTS} control points")
    if not MIN_BITS <= bits <= MAX_BITS:
        raise PatchFormatError(14, f"bits = {bits} outside {MIN_BITS}..{MAX_BITS}")
    if reserved:
        raise PatchFormatError(15, f"reserved byte is {reserved}, must be 0")
    # the payload these header fields need and the largest they allow bound the inflation
    least, most = payload_size_range(flags, (p, q), (n_u, n_v), bits)
    if raw_size > most:
        raise PatchFormatError(20, f"payload size {raw_size} exceeds the {most} the grid allows")
    if raw_size > MAX_INFLATE_RATIO * size:
        raise PatchFormatError(20, f"payload size {raw_size} exceeds the "
                               f"{MAX_INFLATE_RATIO * size} bytes a {size}-byte zlib stream "
                               f"can inflate to ({MAX_INFLATE_RATIO}:1)")
    if raw_size < least:
        raise PatchFormatError(20, f"payload size {raw_size} is below the {least} bytes "
                               f"a {n_u}x{n_v} grid needs")
    return {"flags": flags, "degree": (p, q), "shape": (n_u, n_v), "bits": bits,
            "payload_size": size, "raw_size": raw_size, "data": data}


def _read_metadata(cur: _Cursor, raw: bytes) -> dict:
    """The payload's last section: a u32 length and that many bytes of a UTF-8 JSON object,
    which must end the payload (the ``.tsp`` and ``.tsa`` rule)."""
    (meta_len,) = cur.unpack("<I", "metadata length")
    meta_at = cur.pos
    if meta_len > MAX_METADATA:
        raise PatchFormatError(meta_at - 4, f"metadata length {meta_len} exceeds 1 MiB", "payload")
    try:
        metadata = loads_finite_json(cur.take(meta_len, "metadata").decode("utf-8"))
    except (ValueError, RecursionError) as exc:  # UnicodeDecodeError, JSONDecodeError, ...
        if isinstance(exc, PatchFormatError):
            raise
        raise PatchFormatError(meta_at, f"metadata is not UTF-8 JSON: {exc}", "payload") from None
    if not isinstance(metadata, dict):
        raise PatchFormatError(meta_at, "metadata JSON is not an object", "payload")
    if cur.pos != len(raw):
        raise PatchFormatError(cur.pos, f"{len(raw) - cur.pos} bytes left after metadata",
                               "payload")
    return metadata


def read_patch(data: bytes) -> NurbsSurface:
    """Decode a v1 patch into a :class:`NurbsSurface` (with ``trim`` and ``metadata``).

    Raises
    ------
    PatchFormatError
        For anything but a valid patch: truncation, corruption, a foreign file.
    """
    head = read_header(data)
    flags, bits = head["flags"], head["bits"]
    (p, q), (n_u, n_v) = head["degree"], head["shape"]
    raw = _inflate(head["data"], HEADER_SIZE, head["payload_size"], head["raw_size"], 20)

    cur = _Cursor(raw)
    u_lo, u_hi, v_lo, v_hi = cur.finite("<4d", "domain")
    U = _read_knots(cur, bool(flags & FLAG_UNIFORM_U), p, n_u, u_lo, u_hi, "knots U")
    V = _read_knots(cur, bool(flags & FLAG_UNIFORM_V), q, n_v, v_lo, v_hi, "knots V")
    bounds = cur.finite("<6d", "control point bounds")
    axes = [
        _dequantise(_read_grid(cur, n_u, n_v, bits, f"control points axis {name}"),
                    bounds[a], bounds[a + 3], bits)
        for a, name in enumerate("xyz")
    ]
    weights = None
    if flags & FLAG_RATIONAL:
        lo, hi = cur.finite("<2d", "log-weight bounds")
        logs = _dequantise(_read_grid(cur, n_u, n_v, bits, "weights"), lo, hi, bits)
        if max(abs(lo), abs(hi)) > 700:
            raise PatchFormatError(cur.pos, "log-weights beyond +-700 overflow", "payload")
        flat_w = [math.exp(x) for x in logs]
        weights = [flat_w[i * n_v : (i + 1) * n_v] for i in range(n_u)]
    trim = None
    if flags & FLAG_TRIM:
        rows, cols = cur.unpack("<HH", "trim mask size")
        if not (1 <= rows <= TRIM_MAX_SIDE and 1 <= cols <= TRIM_MAX_SIDE):
            raise PatchFormatError(cur.pos - 4, f"trim mask of {rows}x{cols} cells; "
                                   f"1..{TRIM_MAX_SIDE} per side accepted", "payload")
        packed = cur.take((rows * cols + 7) // 8, "trim mask bits")
        trim = TrimMask.from_flat(rows, cols, _unpack_bits(packed, rows * cols))
    metadata = _read_metadata(cur, raw)
    xyz = list(zip(*axes, strict=True))
    points = [xyz[i * n_v : (i + 1) * n_v] for i in range(n_u)]
    try:
        return NurbsSurface((p, q), (U, V), points, weights, trim=trim, metadata=metadata)
    except ValueError as exc:
        raise PatchFormatError(HEADER_SIZE, f"decoded surface is invalid: {exc}") from None


def _inflate(data: bytes, start: int, size: int, raw_size: int, size_at: int) -> bytes:
    """The zlib stream ``data[start : start + size]``,
    inflated to exactly ``raw_size`` bytes (at most ``raw_size + 1`` are ever inflated);
    ``size_at`` is where the header holds ``raw_size``, the offset a wrong size is reported at."""
    blob = data[start : start + size]
    try:
        inflater = zlib.decompressobj()
        raw = inflater.decompress(blob, raw_size + 1)
    except zlib.error as exc:
        raise PatchFormatError(start, f"payload does not decompress: {exc}") from None
    if len(raw) != raw_size:
        more = "more than " if len(raw) > raw_size else ""
        raise PatchFormatError(size_at, f"payload inflates to {more}{len(raw)} bytes, "
                               f"header says {raw_size}")
    if not inflater.eof:
        raise PatchFormatError(start + len(blob), "compressed payload ends early")
    if inflater.unused_data:
        raise PatchFormatError(start + len(blob) - len(inflater.unused_data),
                               f"{len(inflater.unused_data)} bytes after the compressed payload")
    return raw



# ------------------------------------------------------------------ detail tiles (.tsd)
TILE_MAGIC = b"TSDT"
TILE_VERSION = 2
# magic version flags level degree spans drawn_side i j step (then coded bytes, CRC32)
TILE_HEADER = struct.Struct("<4sBBBBBBHHf")
TILE_HEADER_SIZE = TILE_HEADER.size  # 18
TILE_FLAG_DRAWN = 1  # a drawn mask of drawn_side^2 cells follows the values
TILE_FLAG_WALLS = 2  # then a walls mask: its side (8 coded bits, side - 1) and side^2 cells
MAX_WALLS_SIDE = 256  # cells per side of a tile's walls mask
WALLS_SIDE_BITS = 8
MAX_TILE_VALUE = (1 << 28) - 1
UNARY_BINS = 6  # |q| = 1..UNARY_BINS in unary, larger through an Exp-Golomb escape
ESCAPE_BITS = 28  # an escape's Exp-Golomb prefix: |q| <= MAX_TILE_VALUE needs fewer


class _TileModel:
    """The adaptive contexts of one tile's values (docs/format.md, "Tile values").

    Neighbours are the coefficient before ``q_ab`` in its row (``q_a,b-1``) and
    the one above (``q_a-1,b``); missing ones count as 0.
    """

    def __init__(self) -> None:
        self.zero = [HALF] * 3  # by the number of non-zero neighbours
        self.sign = [HALF]
        self.unary = [HALF] * (2 * UNARY_BINS)  # by bin, and neighbour magnitudes > 2
        self.prefix = [HALF] * ESCAPE_BITS
        self.suffix = [HALF] * ESCAPE_BITS
        self.mask = [HALF] * 4  # drawn cells: by the cell above and the one before
        self.walls = [HALF] * 4  # walls cells, likewise
        self.walls_side = [HALF] * WALLS_SIDE_BITS  # one context per bit of side - 1
        self.same = [HALF]  # a value another tile also holds: is it that tile's? (packs)

    @staticmethod
    def contexts(values: Sequence[int], k: int, size: int) -> tuple[int, int, int]:
        """``(zero, unary, sign)`` contexts of value ``k`` of a ``size``-wide tile."""
        left = values[k - 1] if k % size else 0
        up = values[k - size] if k >= size else 0
        return (left != 0) + (up != 0), UNARY_BINS * (abs(left) + abs(up) > 2), 0


#: the neighbour magnitude ``|q_a,b-1| + |q_a-1,b|`` is a context up to this cap
NEIGHBOUR_CAP = 6


class _NeighbourTileModel(_TileModel):
    """The contexts of atlas detail packs from version 4 on (``client_py.atlas_detail``;
    docs/format.md, "Atlas detail packs"): the zero flag and the unary bins by ``s =
    min(|q_a,b-1| + |q_a-1,b|, 6)`` (7 contexts and 7 sets of bins instead of 3 and 2), and
    the sign by the signs of four decoded neighbours, the one before in the row, above,
    above-left and above-right (``3^4 = 81`` contexts instead of 1).

    A level's detail is a smooth displacement sampled by overlapping B-spline
    coefficients, so neighbours share their sign more often than not: on the benchmark's
    bunny and Lucy level-0 packs (main 732fe1f) the sign costs 7.5 / 6.5 KB of
    conditional entropy against 9.6 / 8.8 KB at one bit a non-zero value.
    """

    def __init__(self) -> None:
        super().__init__()
        self.zero = [HALF] * (NEIGHBOUR_CAP + 1)
        self.unary = [HALF] * (UNARY_BINS * (NEIGHBOUR_CAP + 1))
        self.sign = [HALF] * 81

    @staticmethod
    def contexts(values: Sequence[int], k: int, size: int) -> tuple[int, int, int]:
        j = k % size
        left = values[k - 1] if j else 0
        if k >= size:
            up = values[k - size]
            above_left = values[k - size - 1] if j else 0
            above_right = values[k - size + 1] if j < size - 1 else 0
        else:
            up = above_left = above_right = 0
        s = abs(left) + abs(up)
        if s > NEIGHBOUR_CAP:
            s = NEIGHBOUR_CAP
        sign = (27 * ((left > 0) - (left < 0) + 1) + 9 * ((up > 0) - (up < 0) + 1)
                + 3 * ((above_left > 0) - (above_left < 0) + 1)
                + (above_right > 0) - (above_right < 0) + 1)
        return s, UNARY_BINS * s, sign


def _encode_tile_values(enc: RangeEncoder, values: Sequence[int], size: int,
                        model: _TileModel, given: Sequence[int | None] | None = None,
                        known: Sequence[int | None] | None = None) -> None:
    """Code ``values``; where ``given[k]`` is not ``None`` (a value the decoder already
    has from another tile: ``client_py.atlas_detail``), first a bit whether ``values[k]``
    equals it, and the value itself only when it does not; where ``known[k]`` is not
    ``None`` (the caller's promise that it equals ``values[k]``: a welded pack's border
    slot another patch carried), nothing."""
    for k, q in enumerate(values):
        if known is not None and known[k] is not None:
            continue
        if given is not None and given[k] is not None:
            enc.bit(model.same, 0, q != given[k])
            if q == given[k]:
                continue
        zero_ctx, unary_ctx, sign_ctx = model.contexts(values, k, size)
        enc.bit(model.zero, zero_ctx, q != 0)
        if not q:
            continue
        enc.bit(model.sign, sign_ctx, q < 0)
        m = abs(q)
        for b in range(1, UNARY_BINS + 1):  # bit b-1: is |q| > b?
            enc.bit(model.unary, unary_ctx + b - 1, m > b)
            if m <= b:
                break
        else:  # Exp-Golomb order 0 of x = |q| - UNARY_BINS
            encode_exp_golomb(enc, m - UNARY_BINS, model.prefix, 0, model.suffix, 0)


def _decode_tile_values(dec: RangeDecoder, count: int, size: int,
                        model: _TileModel, given: Sequence[int | None] | None = None,
                        known: Sequence[int | None] | None = None) -> list[int]:
    """Inverse of :func:`_encode_tile_values` (the same ``given`` and ``known``)."""
    values: list[int] = []
    for k in range(count):
        if known is not None and known[k] is not None:
            values.append(known[k])
            continue
        if given is not None and given[k] is not None and not dec.bit(model.same, 0):
            values.append(given[k])
            continue
        zero_ctx, unary_ctx, sign_ctx = model.contexts(values, k, size)
        if not dec.bit(model.zero, zero_ctx):
            values.append(0)
            continue
        negative = dec.bit(model.sign, sign_ctx)
        m = 1
        while m <= UNARY_BINS and dec.bit(model.unary, unary_ctx + m - 1):
            m += 1
        if m > UNARY_BINS:
            x = decode_exp_golomb(dec, model.prefix, 0, model.suffix, 0, ESCAPE_BITS)
            if x is None:
                raise PatchFormatError(TILE_HEADER_SIZE, f"value {k}: escape longer "
                                       f"than {ESCAPE_BITS} bits")
            m = x + UNARY_BINS
        values.append(-m if negative else m)
    return values


def _code_mask(coder: RangeEncoder | RangeDecoder, model: _TileModel, side: int,
               cells: bytes | None = None, contexts: list[int] | None = None) -> bytes:
    """Encode ``cells`` (``side^2`` 0/1 bytes, row-major) or, with ``cells=None``, decode;
    ``contexts``: the four adaptive contexts (default the drawn mask's, ``model.mask``)."""
    ctxs = model.mask if contexts is None else contexts
    out = bytearray(side * side)
    for k in range(side * side):
        ctx = 2 * (out[k - side] if k >= side else 0) + (out[k - 1] if k % side else 0)
        if cells is None:
            out[k] = coder.bit(ctxs, ctx)
        else:
            out[k] = cells[k]
            coder.bit(ctxs, ctx, cells[k])
    return bytes(out)


def _code_walls(coder: RangeEncoder | RangeDecoder, model: _TileModel,
                walls: TrimMask | None = None) -> TrimMask:
    """Encode a tile's ``walls`` mask (its side ``w``: ``w - 1`` in ``WALLS_SIDE_BITS``
    bits, lowest first, then ``w^2`` cells as :func:`_code_mask` with ``model.walls``) or,
    with ``walls=None``, decode it."""
    if walls is not None:
        for b in range(WALLS_SIDE_BITS):
            coder.bit(model.walls_side, b, ((walls.rows - 1) >> b) & 1)
        _code_mask(coder, model, walls.rows, walls.flat, model.walls)
        return walls
    side = 1 + sum(coder.bit(model.walls_side, b) << b for b in range(WALLS_SIDE_BITS))
    return TrimMask.from_flat(side, side, _code_mask(coder, model, side, None, model.walls))


def write_detail_tile(tile: DetailTile) -> bytes:
    """Encode a :class:`~client_py.layers.DetailTile` as a ``.tsd`` v2 file (docs/format.md).

    The integers ``q_ab`` and the cells of the ``drawn`` mask are coded with an
    adaptive binary range coder (``client_py.rangecoder``): per value a zero
    flag (context: non-zero neighbours), a sign and ``|q|`` in unary up to
    ``UNARY_BINS`` (context: the neighbours' magnitude), then an Exp-Golomb
    escape; per mask cell one bit (context: the cells above and before). The
    same tile always gives the same bytes.
    """
    if not isinstance(tile, DetailTile):
        raise ValueError(f"tile must be a DetailTile, got {type(tile).__name__}")
    if any(abs(q) > MAX_TILE_VALUE for q in tile.values):
        raise ValueError(f"tile values must lie within +-{MAX_TILE_VALUE}: raise the step")
    if tile.spans > MAX_TILE_SPANS:
        raise ValueError(f"spans = {tile.spans}: a .tsd tile holds at most {MAX_TILE_SPANS}")
    side, flags = 0, 0
    if tile.drawn is not None:
        side = tile.drawn.rows
        if tile.drawn.cols != side or not 1 <= side <= MAX_DRAWN_SIDE:
            raise ValueError(f"a tile's drawn mask must be square with 1..{MAX_DRAWN_SIDE} "
                             f"cells per side, got {tile.drawn.rows}x{tile.drawn.cols}")
        flags = TILE_FLAG_DRAWN
    if tile.walls is not None:
        if tile.walls.cols != tile.walls.rows or not 1 <= tile.walls.rows <= MAX_WALLS_SIDE:
            raise ValueError(f"a tile's walls mask must be square with 1..{MAX_WALLS_SIDE} "
                             f"cells per side, got {tile.walls.rows}x{tile.walls.cols}")
        flags |= TILE_FLAG_WALLS
    enc, model = RangeEncoder(), _TileModel()
    _encode_tile_values(enc, tile.values, tile.size, model)
    if side:
        _code_mask(enc, model, side, tile.drawn.flat)
    if tile.walls is not None:
        _code_walls(enc, model, tile.walls)
    body = TILE_HEADER.pack(TILE_MAGIC, TILE_VERSION, flags, tile.level, tile.degree,
                            tile.spans, side, tile.i, tile.j, tile.step) + enc.finish()
    return body + struct.pack("<I", zlib.crc32(body))


def read_detail_tile(data: bytes) -> DetailTile:
    """Decode a ``.tsd`` v2 detail tile.

    Raises
    ------
    PatchFormatError
        For anything but a valid tile (truncation, corruption, a foreign file),
        with the byte offset and the reason; never anything else.
    """
    data, fields = _unframe(data, TILE_MAGIC, "detail tile", TILE_HEADER, TILE_VERSION, None)
    _, _, flags, level, degree, spans, side, i, j, step = fields
    if flags & ~(TILE_FLAG_DRAWN | TILE_FLAG_WALLS):
        raise PatchFormatError(5, f"unknown flags 0x{flags:02x}")
    if level > MAX_TILE_LEVEL:
        raise PatchFormatError(6, f"level {level} outside 0..{MAX_TILE_LEVEL}")
    if not 1 <= degree <= MAX_DETAIL_DEGREE:
        raise PatchFormatError(7, f"degree {degree} outside 1..{MAX_DETAIL_DEGREE}")
    if not 1 <= spans <= MAX_TILE_SPANS:
        raise PatchFormatError(8, f"spans = {spans} outside 1..{MAX_TILE_SPANS}")
    if side > MAX_DRAWN_SIDE:
        raise PatchFormatError(9, f"drawn mask side {side} outside 1..{MAX_DRAWN_SIDE}")
    if bool(side) != bool(flags & TILE_FLAG_DRAWN):
        raise PatchFormatError(9, f"drawn mask side {side} with flags 0x{flags:02x}: "
                               "non-zero exactly when flag 0x1 is set")
    for offset, name, index in ((10, "i", i), (12, "j", j)):
        if index >= 1 << level:
            raise PatchFormatError(offset, f"{name} = {index} outside 0..{(1 << level) - 1} "
                                   f"at level {level}")
    if not (math.isfinite(step) and step > 0):
        raise PatchFormatError(14, f"quantisation step {step} is not a positive finite number")
    model = _TileModel()
    try:  # the decoder reads its first bytes when it is made: inside the try too
        dec = RangeDecoder(data[TILE_HEADER_SIZE : len(data) - CRC_SIZE])
        values = _decode_tile_values(dec, (spans + degree) ** 2, spans + degree, model)
        drawn = TrimMask.from_flat(side, side, _code_mask(dec, model, side)) if side else None
        walls = _code_walls(dec, model) if flags & TILE_FLAG_WALLS else None
    except RangeDecodeError as exc:
        raise PatchFormatError(len(data) - CRC_SIZE, f"coded values end early: {exc}") from None
    if any(abs(q) > MAX_TILE_VALUE for q in values):
        raise PatchFormatError(TILE_HEADER_SIZE, f"decoded values beyond +-{MAX_TILE_VALUE}")
    return DetailTile(level, i, j, degree, spans, step, tuple(values), drawn, walls)
