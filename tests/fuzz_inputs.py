"""Hostile inputs for client_py's decoders: the fuzz tests' and ``python -m bench fuzz``'s.

Every generator takes a ``random.Random`` so that one seed gives one input, in a
hypothesis test (``st.randoms``) and in the benchmark's 10^5 runs alike:

* :func:`mutate_patch`, :func:`mutate_tile`: byte flips, inserts and deletes of a real
  ``.tsp``/``.tsd`` (as ``client_py.format`` writes it for the fitter), usually with the CRC
  recomputed so the decoder behind it is reached, and claimed sizes enlarged (grid, degree,
  payload sizes, level, spans, mask side) in the header;
* :func:`random_manifest`: a real manifest (:func:`seed_manifest`) with entries replaced by
  values of other types, out-of-range numbers, deep nesting and hostile file names.

:func:`check_contract` runs one decoder call and says whether it kept client_py's error
contract: a result or :class:`~client_py.errors.PatchFormatError`, nothing else.
"""

from __future__ import annotations

import copy
import json
import math
import random
import struct
import zlib

from client_py import NurbsSurface
from client_py.errors import PatchFormatError
from client_py.format import HEADER, HEADER_SIZE, TILE_HEADER, write_detail_tile, write_patch
from client_py.layers import DetailTile
from client_py.trim import TrimMask


def seed_patch() -> bytes:
    """A rational, trimmed 9 x 7 degree-2 patch with metadata, as the fitter writes one."""
    n_u, n_v, p = 9, 7, 2
    U = [0.0] * 3 + [0.1, 0.3, 0.45, 0.6, 0.8, 0.9] + [1.0] * 3
    V = [0.0] * 3 + [k / (n_v - p) for k in range(1, n_v - p)] + [1.0] * 3
    points = [[[i, j, math.sin(i) * math.cos(j)] for j in range(n_v)] for i in range(n_u)]
    weights = [[1.0 + 0.1 * ((i + j) % 3) for j in range(n_v)] for i in range(n_u)]
    trim = TrimMask.from_flat(8, 8, bytes((k * 7) % 5 != 0 for k in range(64)))
    surface = NurbsSurface((p, p), (U, V), points, weights, trim=trim,
                           metadata={"units": "mm", "transform": [[1, 0, 0, 5], [0, 1, 0, 0],
                                                                  [0, 0, 1, 0], [0, 0, 0, 1]]})
    return write_patch(surface, bits=12)


def seed_tiles() -> list[bytes]:
    """Detail tiles of the fitter's kinds: level 0 and a level-2 tile with a drawn mask."""
    rnd = random.Random(3)
    plain = DetailTile(0, 0, 0, 2, 16, 2.0**-8,
                       tuple(rnd.randint(-20, 20) for _ in range(18 * 18)))
    drawn = TrimMask.from_flat(32, 32, bytes(rnd.random() < 0.8 for _ in range(32 * 32)))
    masked = DetailTile(2, 3, 1, 3, 8, 2.0**-10,
                        tuple(rnd.choice((0, 0, 0, 1, -1, 9, -300)) for _ in range(11 * 11)), drawn)
    return [write_detail_tile(plain), write_detail_tile(masked)]


def seed_manifest() -> dict:
    """A manifest with detail levels 0..1 and a texture pyramid, as the fitter writes it."""
    detail = [{"level": k, "i": i, "j": j, "uv": [i / 2**k, j / 2**k, (i + 1) / 2**k,
                                                    (j + 1) / 2**k],
               "file": f"detail/{k}/{i}_{j}.tsd", "bytes": 300, "geometric_error": 1.0}
              for k in range(2) for i in range(1 << k) for j in range(1 << k)]
    texture = [{"level": k, "i": i, "j": j, "file": f"texture/{k}/{i}_{j}.webp", "bytes": 900}
               for k in range(3) for i in range(1 << k) for j in range(1 << k) if (k, i, j)
               != (2, 3, 3)]
    return {"format": "tessera-bundle", "format_version": 1, "units": "mm",
            "base": {"file": "base.tsp", "grid": [9, 7]},
            "stats": {"rms": 0.1, "max": 1.0},
            "tiles": {"version": 1,
                      "detail": {"format": "tsd", "format_version": 2, "degree": 2,
                                 "spans_per_tile": 16, "base": {"rms": 0.4, "max": 2.0},
                                 "levels": [{"level": 0, "rms": 0.3}, {"level": 1, "rms": 0.2}],
                                 "nodes": detail},
                      "texture": {"format": "webp", "size": 256,
                                  "levels": [{"level": k} for k in range(3)], "nodes": texture}}}


# ------------------------------------------------------------------ byte mutations
def _with_crc(body: bytes) -> bytes:
    return body + struct.pack("<I", zlib.crc32(body))


def _edit_bytes(rnd: random.Random, data: bytearray, start: int) -> None:
    """1..4 flips, inserts or deletes at offsets >= ``start``."""
    for _ in range(rnd.randint(1, 4)):
        at = rnd.randint(start, len(data))
        kind = rnd.choice(("flip", "set", "insert", "delete"))
        if kind == "flip" and at < len(data):
            data[at] ^= 1 << rnd.randrange(8)
        elif kind == "set" and at < len(data):
            data[at] = rnd.randrange(256)
        elif kind == "insert":
            data[at:at] = bytes(rnd.randrange(256) for _ in range(rnd.randint(1, 8)))
        else:
            del data[at : at + rnd.randint(1, 8)]


def _big(rnd: random.Random, bits: int) -> int:
    """A claimed size: the largest, a power of two, or any value of ``bits`` bits."""
    return rnd.choice(((1 << bits) - 1, 1 << rnd.randrange(bits), rnd.randrange(1 << bits)))


def mutate_patch(rnd: random.Random, data: bytes) -> bytes:
    """A ``.tsp`` mutation: header claims enlarged, payload edited (recompressed, sizes
    and CRC made consistent), or raw byte edits with the CRC recomputed or not."""
    kind = rnd.choice(("claims", "payload", "bytes", "bytes-crc"))
    fields = list(HEADER.unpack_from(data))
    if kind == "claims":
        for _ in range(rnd.randint(1, 3)):
            field = rnd.choice((3, 4, 5, 6, 7, 9, 10))  # p q n_u n_v bits size raw_size
            fields[field] = _big(rnd, {3: 8, 4: 8, 5: 16, 6: 16, 7: 8, 9: 32, 10: 32}[field])
        if rnd.random() < 0.5:
            fields[2] = rnd.randrange(16)  # flags
        return _with_crc(HEADER.pack(*fields) + data[HEADER_SIZE:-4])
    if kind == "payload":
        raw = bytearray(zlib.decompress(data[HEADER_SIZE:-4]))
        _edit_bytes(rnd, raw, 0)
        blob = zlib.compress(bytes(raw), 9)
        fields[9], fields[10] = len(blob), len(raw)
        return _with_crc(HEADER.pack(*fields) + blob)
    out = bytearray(data)
    _edit_bytes(rnd, out, 0)
    return _with_crc(bytes(out[:-4])) if kind == "bytes-crc" and len(out) > 4 else bytes(out)


def mutate_tile(rnd: random.Random, data: bytes) -> bytes:
    """A ``.tsd`` mutation: header claims enlarged (level, degree, spans, mask side, i, j,
    step) or coded bytes edited, with the CRC recomputed (or, sometimes, not)."""
    fields = list(TILE_HEADER.unpack_from(data))
    body = bytearray(data[:-4])
    if rnd.random() < 0.5:
        for _ in range(rnd.randint(1, 3)):
            field = rnd.choice((2, 3, 4, 5, 6, 7, 8, 9))
            if field == 9:
                fields[9] = rnd.choice((0.0, -1.0, math.inf, math.nan, 1e-30, 3e38))
            else:
                fields[field] = _big(rnd, 16 if field in (7, 8) else 8)
        body[: TILE_HEADER.size] = TILE_HEADER.pack(*fields)
    else:
        _edit_bytes(rnd, body, TILE_HEADER.size)
    return bytes(body) + data[-4:] if rnd.random() < 0.1 else _with_crc(bytes(body))


# ------------------------------------------------------------------ manifests
HOSTILE_NAMES = ("../../../../etc/passwd", "/etc/passwd", "detail/0/0_0.tsd/../../x",
                 "detail\\0\\0_0.tsd", "detail/0/0_0.tsd\0", "C:/x.tsd", "detail/00/0_0.tsd",
                 "texture/0/0_0.exe", "", "base.tsp", "/dev/zero", "detail/0/1_0.tsd")


def _hostile_value(rnd: random.Random, depth: int = 0) -> object:
    choices = [None, True, -1, 0, 2**40, 1e308, math.nan, math.inf,
               "x", "", [], {}, rnd.choice(HOSTILE_NAMES), [1, 2], {"level": "0"}]
    if depth < 2:
        choices += [[_hostile_value(rnd, depth + 1)], {"a": _hostile_value(rnd, depth + 1)}]
    return rnd.choice(choices)


def _paths(value: object, prefix: tuple = ()) -> list[tuple]:
    """Every key path into nested dicts and lists."""
    out = [prefix]
    if isinstance(value, dict):
        for key, item in value.items():
            out += _paths(item, prefix + (key,))
    elif isinstance(value, list):
        for k, item in enumerate(value):
            out += _paths(item, prefix + (k,))
    return out


def random_manifest(rnd: random.Random, manifest: dict | None = None) -> object:
    """A malformed manifest: 1..4 entries of a real one replaced by hostile values, deleted,
    or nested deep; sometimes not an object at all."""
    if rnd.random() < 0.03:
        return _hostile_value(rnd)
    m = copy.deepcopy(manifest or seed_manifest())
    paths = _paths(m)[1:]
    for _ in range(rnd.randint(1, 4)):
        path = rnd.choice(paths)
        parent = m
        try:
            for key in path[:-1]:
                parent = parent[key]
            kind = rnd.random()
            if kind < 0.15 and isinstance(parent, dict):
                del parent[path[-1]]
            elif kind < 0.2:
                deep: object = []
                for _ in range(rnd.choice((50, 3000))):
                    deep = [deep]
                parent[path[-1]] = deep
            else:
                parent[path[-1]] = _hostile_value(rnd)
        except (KeyError, IndexError, TypeError):  # an earlier edit removed this path
            continue
    return m


def manifest_text(manifest: object) -> str:
    """``manifest`` as the JSON text a worker receives; a manifest nested too deep for
    ``json.dumps`` becomes the same depth of brackets, written out."""
    try:
        return json.dumps(manifest)
    except RecursionError:
        return '{"tiles": ' + "[" * 3000 + "]" * 3000 + "}"


# ------------------------------------------------------------------ the contract
def check_contract(call, *args) -> str | None:
    """``None`` when ``call(*args)`` returns or raises PatchFormatError (client_py's one error
    of a bad file or manifest), else the name of the exception that escaped."""
    try:
        call(*args)
    except PatchFormatError:
        return None
    except Exception as exc:  # noqa: BLE001 -- the point: report whatever escapes
        return f"{type(exc).__name__}: {exc}"[:200]
    return None
