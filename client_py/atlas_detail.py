"""Detail packs: the detail tiles of one level for a group of neighbouring atlas patches.

An atlas (``client_py.atlas``) has hundreds of patches, each refined by its own pyramid of
detail tiles over its own ``[0, 1]²`` (``client_py.layers.DetailTile``, docs/format.md).
One file per tile would cost a visitor thousands of requests, so the tiles of level ``k``
of the patches in group ``g`` travel together in one *pack*, ``detail/K/G.tsdp``
(:func:`pack_name`: the one naming rule). A viewer fetches the packs of the groups on
screen whose error it must refine; ``tessera tessellate --level L`` reads every pack of
levels ``0..L``.

Version 4 (written when no tile has a walls mask; version 5 when one does:
docs/format.md, "Atlas detail packs") codes the whole pack as ONE stream of the adaptive
binary range coder (``client_py.rangecoder``) after a 24-byte header that holds what every
tile of an atlas level shares (level, degree, spans, the level's quantisation step, the
drawn and walls masks' sides) and the pack's patch range::

    offset  size  field
    0       4     magic  b"TSDP"
    4       1     version 4, or 5 with walls masks (3, 2 and 1 still read)
    5       1     level k (0..7)
    6       1     degree p (1..3)
    7       1     spans per tile m (1..64)
    8       4     f32 quantisation step (finite, > 0)
    12      4     u32 first patch
    16      4     u32 count: patches first..first+count-1 (>= 1)
    20      1     drawn mask side w (0: no tile has a mask; else 1..64)
    21      1     flags: bit 0 PACK_FLAG_WELDED (version 2: 0)
    22      1     version 5: walls mask side s (0: no tile has one; else 1..255); before: 0
    23      1     reserved, 0
    24      ...   range-coded stream
    end-4   4     CRC-32 of everything before it

The stream: for every patch of the range and every tile ``(i, j)`` of level ``k``
(``i``-major), a presence bit (context: the previous tile's); a present tile's ``(m + p)²``
values coded as a ``.tsd`` v2 tile's (``client_py.format``: zero flag, sign, unary
magnitude, Exp-Golomb escape, with neighbour contexts; from version 4 with more of them,
``client_py.format._NeighbourTileModel``: the zero flag and the unary bins by the two
neighbours' summed magnitude up to 6, the sign by the signs of four decoded neighbours,
6-7 % fewer bytes on the benchmark's level-0 packs), ONE adaptive model for the whole
pack, except that

* welded (flag bit 0): a value on the patch's border ring whose *shared slot* an earlier
  patch of the pack carried is not coded: it is that value. Level ``k``'s field of patch
  ``f`` is a grid of ``n = m 2^k + p`` coefficients a side (tile ``(i, j)`` holds rows ``i m
  .. i m + m + p - 1``, columns likewise), and neighbouring patches hold the same integers
  on their common border (``fitter.fitting.atlas.detail``, "Welded borders"); its ring's
  slots are numbered by the base's rule for shared control points
  (:meth:`client_py.atlas.AtlasSurface.border_slots`: layout vertices, then ``n - 2`` slots
  per edge from its lower vertex). A slot is carried by the first present tile that holds
  it. Slots shared with patches of other packs are coded here too: a pack decodes alone
  (the viewer fetches the packs of the groups on screen), given the atlas. On the bunny's
  and Lucy's fitted level 0 this is 18-19 % fewer bytes;
* a value the patch's tile ``(i - 1, j)`` or ``(i, j - 1)`` also holds (the ``p`` shared
  rows; 0 for an absent tile) is first a bit "equal to it", then the value only when it is
  not (a quarter to a third of a level's values from level 1 on);

then, with ``w > 0``, a bit whether the tile has a drawn mask and its ``w²`` cells, and
(version 5) with ``s > 0`` a bit whether the tile has a *walls mask* and its ``s²`` cells
(the ``.tsd`` walls mask's cells and contexts, its side in the header instead of the
stream): the cells that level, when it is the finest applied tile carrying one, leaves
out (``client_py.layers.DetailTile``, ``walls``: the single patch's rule), where the
fitter found the mesh drawn at that level with no scan point within reach
(``fitter.fitting.atlas.detail``, "Drawn cells"). A pack without walls masks is written
as version 4, byte for byte as before.
Version 3 is version 4 with the ``.tsd`` v2 tile's contexts; version 2 is version 3 with
the flags 0. Version 1 packs (an index of per-tile ``.tsd``
files, 30 bytes of framing per tile: half the bytes of a bunny's level 0) are still read
(:func:`read_pack`).

Every failure is a ``PatchFormatError(offset, reason)``; the header bounds the decoding
(at most ``MAX_PACK_TILES`` tiles and ``MAX_PACK_VALUES`` values), so it never hangs.
"""

from __future__ import annotations

import functools
import math
import struct
import zlib
from collections.abc import Mapping, Sequence

from .atlas import AtlasSurface, ring_positions
from .errors import PatchFormatError
from .format import (
    CRC_SIZE,
    MAX_DRAWN_SIDE,
    MAX_TILE_VALUE,
    _code_mask,
    _decode_tile_values,
    _encode_tile_values,
    _NeighbourTileModel,
    _TileModel,
    read_detail_tile,
)
from .layers import MAX_DETAIL_DEGREE, MAX_LEVEL, MAX_SPANS, DetailTile
from .rangecoder import HALF, RangeDecodeError, RangeDecoder, RangeEncoder
from .trim import TrimMask

PACK_MAGIC = b"TSDP"
PACK_VERSION = 5  # the newest written: a pack with walls masks (without: WALLS_FREE_VERSION)
WALLS_FREE_VERSION = 4  # a pack no tile of which has a walls mask, coded as before version 5
READ_VERSIONS = (1, 2, 3, 4, 5)
# magic version level degree spans step first count drawn_side flags(u8) walls_side(u8)
# reserved(u8); before version 5 the walls side is part of a reserved u16, 0
PACK_HEADER = struct.Struct("<4sBBBBfIIBBBB")
MAX_PACK_WALLS_SIDE = 255  # cells per side of a pack's walls masks (one byte)
PACK_FLAG_WELDED = 0x1  # from version 3: a border slot an earlier patch carried is not coded
PACK_HEADER_SIZE = PACK_HEADER.size  # 24
PACK_V1_HEADER = struct.Struct("<4sBBHI")  # magic version level reserved count
PACK_V1_HEADER_SIZE = PACK_V1_HEADER.size  # 12
PACK_ENTRY = struct.Struct("<II")  # version 1's index: patch, byte length
MAX_PACK_TILES = 1 << 16  # tiles a pack can hold (versions 2, 3: patches x 4^level)
MAX_PACK_VALUES = 1 << 21  # values a version 2 or 3 pack can hold: the decoding bound (~1.6 s)
MAX_PACK_PATCH = 1 << 16  # client_py.atlas.MAX_ATLAS_QUADS


def pack_name(level: int, group: int) -> str:
    """The bundle file of level ``level``'s tiles for patch group ``group``."""
    for name, value in (("level", level), ("group", group)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"{name} must be an integer >= 0, got {value!r}")
    return f"detail/{level}/{group}.tsdp"


def pack_capacity(level: int, patches: int, degree: int, spans: int, side: int = 0,
                  walls: int = 0) -> int:
    """The most values (coefficients, drawn and walls cells) a version 2..5 pack of
    ``patches`` patches of level ``level`` can hold, ``patches 4^level ((spans + degree)^2 +
    side^2 + walls^2)`` (``side``, ``walls``: the drawn and walls masks' sides): a writer
    keeps it within ``MAX_PACK_VALUES`` (and ``patches 4^level`` within
    ``MAX_PACK_TILES``), which bounds a reader's work whatever the bytes claim."""
    return patches * (1 << 2 * level) * ((spans + degree) ** 2 + side * side + walls * walls)


def _overlap_values(done: Mapping[tuple[int, int], Sequence[int]], i: int, j: int,
                    spans: int, size: int) -> list[int | None] | None:
    """Per value of tile ``(i, j)``, what the patch's tile before it along ``u``, ``(i - 1,
    j)``, or along ``v``, ``(i, j - 1)``, holds at the same coefficient (neighbouring tiles
    share ``size - spans = p`` rows: docs/format.md, "Detail field"), 0 where that tile is
    absent (a zero field), ``None`` where no earlier tile holds it; ``done`` maps the
    patch's tiles coded so far to their values."""
    if not i and not j:
        return None
    given: list[int | None] = [None] * (size * size)
    for a in range(size - spans if i else 0):  # rows a < p: rows spans + a of (i - 1, j)
        up = done.get((i - 1, j))
        for b in range(size):
            given[a * size + b] = up[(spans + a) * size + b] if up else 0
    for a in range(size if j else 0):  # columns b < p: columns spans + b of (i, j - 1)
        left = done.get((i, j - 1))
        for b in range(size - spans):
            given[a * size + b] = left[a * size + spans + b] if left else 0
    return given


@functools.lru_cache(maxsize=64)
def _ring_template(level: int, spans: int, degree: int
                   ) -> dict[tuple[int, int], tuple[tuple[int, int], ...]]:
    """Where a level's border ring lies in its tiles: ``(i, j) -> ((index in the tile's
    values, index in the ring), ...)``. Level ``k``'s grid has ``n = m 2^k + p``
    coefficients per side, its ring's points in the order of
    :func:`client_py.atlas.ring_positions` (that of ``AtlasSurface.border_slots``); tile
    ``(i, j)`` holds rows ``i m .. i m + m + p - 1`` and the same columns."""
    per_side, size = 1 << level, spans + degree
    out: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for r, (a, b) in enumerate(ring_positions(spans * per_side + degree)):
        # tiles i with i m <= a <= i m + size - 1
        for i in range(max(0, -((size - 1 - a) // spans)), min(per_side - 1, a // spans) + 1):
            for j in range(max(0, -((size - 1 - b) // spans)),
                           min(per_side - 1, b // spans) + 1):
                out.setdefault((i, j), []).append(((a - i * spans) * size + b - j * spans, r))
    return {key: tuple(entries) for key, entries in out.items()}


def _welded_values(carried: Mapping[int, tuple[int, int]], ring: Sequence[tuple[int, int]],
                   slots: Sequence[int], patch: int, size: int) -> list[int | None] | None:
    """Per value of a tile (``ring``: its border points, from :func:`_ring_template`;
    ``slots``: the patch's ring slots), the value an earlier patch of the pack carried in
    the same shared slot (``carried``: slot -> (patch, value), its first carrier), else
    ``None``; ``None`` when no value of the tile is so known."""
    known: list[int | None] | None = None
    for k, r in ring:
        held = carried.get(slots[r])
        if held is not None and held[0] != patch:
            if known is None:
                known = [None] * (size * size)
            known[k] = held[1]
    return known


def _carry(carried: dict[int, tuple[int, int]], ring: Sequence[tuple[int, int]],
           slots: Sequence[int], patch: int, values: Sequence[int]) -> None:
    """Record the tile's border values in the slots no earlier tile carried."""
    for k, r in ring:
        carried.setdefault(slots[r], (patch, values[k]))


def _model(version: int) -> _TileModel:
    """The adaptive contexts of a version 2..5 pack's stream: from version 4 the zero flag,
    the unary bins and the sign by the neighbours' magnitudes and signs
    (``client_py.format._NeighbourTileModel``), before it those of a ``.tsd`` v2 tile."""
    return _NeighbourTileModel() if version >= 4 else _TileModel()


def _shared(tiles: Sequence[DetailTile], name: str) -> object:
    values = {getattr(t, name) for t in tiles}
    if len(values) != 1:
        raise ValueError(f"every tile of a pack has one {name}; got {sorted(values)}")
    return values.pop()


def write_pack(level: int, tiles: Mapping[int, Sequence[DetailTile]],
               atlas: AtlasSurface | None = None) -> bytes:
    """The pack of ``tiles`` (patch -> its level-``level`` tiles): version 5 when a tile
    has a walls mask, else version 4 (the same bytes as before version 5).

    Every tile shares the pack's degree, spans and quantisation step (an atlas level has
    one step: ``fitter.fitting.atlas.detail``) and, when it has them, its drawn and walls
    masks' sides.
    With ``atlas`` (the layout the patches lie on) the pack is *welded* (module docstring):
    a border coefficient whose shared slot an earlier patch of the pack carried is not
    coded again, and reading it needs the same atlas.

    Raises
    ------
    ValueError
        An empty pack, a tile of another level, a patch index out of range (of the atlas
        too), a repeated tile, tiles that differ in degree, spans, step or a mask's side, more
        than ``MAX_PACK_TILES`` tiles / ``MAX_PACK_VALUES`` coefficients in the patch range,
        or, welded, a border coefficient that differs from the value an earlier patch of
        the pack holds in the same shared slot (neighbours share their border integers).
    """
    by_node: dict[tuple[int, int, int], DetailTile] = {}
    for patch in tiles:
        if isinstance(patch, bool) or not isinstance(patch, int) \
                or not 0 <= patch < MAX_PACK_PATCH:
            raise ValueError(f"patch index must be an int in 0..{MAX_PACK_PATCH - 1}, "
                             f"got {patch!r}")
        for tile in tiles[patch]:
            if not isinstance(tile, DetailTile):
                raise ValueError(f"patch {patch}: expected DetailTile, got "
                                 f"{type(tile).__name__}")
            if tile.level != level:
                raise ValueError(f"patch {patch}: a level-{tile.level} tile in a level-{level} "
                                 "pack")
            if (patch, tile.i, tile.j) in by_node:
                raise ValueError(f"patch {patch}: tile {tile.i}_{tile.j} given twice")
            by_node[patch, tile.i, tile.j] = tile
    if not by_node:
        raise ValueError("a pack holds at least one tile, got none")
    every = list(by_node.values())
    degree, spans, step = (_shared(every, name) for name in ("degree", "spans", "step"))
    side = _mask_side(every, "drawn", MAX_DRAWN_SIDE)
    walls = _mask_side(every, "walls", MAX_PACK_WALLS_SIDE)
    version = PACK_VERSION if walls else WALLS_FREE_VERSION
    if any(abs(q) > MAX_TILE_VALUE for t in every for q in t.values):
        raise ValueError(f"tile values must lie within +-{MAX_TILE_VALUE}: raise the step")
    first = min(p for p, _, _ in by_node)
    count = max(p for p, _, _ in by_node) - first + 1
    per_side = 1 << level
    if count * per_side * per_side > MAX_PACK_TILES \
            or pack_capacity(level, count, degree, spans, side, walls) > MAX_PACK_VALUES:
        raise ValueError(f"patches {first}..{first + count - 1} of level {level} hold up to "
                         f"{count * per_side * per_side} tiles of {(spans + degree) ** 2} "
                         f"values (and {side}² drawn, {walls}² walls cells); a pack holds at most "
                         f"{MAX_PACK_TILES} tiles and {MAX_PACK_VALUES} values: split the group")
    if atlas is not None and first + count > len(atlas.quads):
        raise ValueError(f"patch {first + count - 1} is not one of the atlas's "
                         f"{len(atlas.quads)} patches")
    enc, model = RangeEncoder(), _model(version)
    presence, has_mask, has_walls = [HALF, HALF], [HALF], [HALF]
    size, before = spans + degree, 0
    carried: dict[int, tuple[int, int]] = {}  # welded: slot -> (first patch, its value)
    for patch in range(first, first + count):
        done: dict[tuple[int, int], Sequence[int]] = {}
        slots = atlas.border_slots(patch, spans * per_side + degree) if atlas else ()
        rings = _ring_template(level, spans, degree) if atlas else {}
        for i in range(per_side):
            for j in range(per_side):
                tile = by_node.get((patch, i, j))
                enc.bit(presence, before, tile is not None)
                before = tile is not None
                if tile is None:
                    continue
                ring = rings.get((i, j), ())
                known = _welded_values(carried, ring, slots, patch, size)
                if known is not None:
                    for k, q in enumerate(known):
                        if q is not None and q != tile.values[k]:
                            raise ValueError(
                                f"patch {patch} tile {i}_{j}: value {k} is "
                                f"{tile.values[k]}, but an earlier patch of the pack holds "
                                f"{q} in the same shared border slot")
                _encode_tile_values(enc, tile.values, size, model,
                                    _overlap_values(done, i, j, spans, size), known)
                _carry(carried, ring, slots, patch, tile.values)
                done[i, j] = tile.values
                if side:
                    enc.bit(has_mask, 0, tile.drawn is not None)
                    if tile.drawn is not None:
                        _code_mask(enc, model, side, tile.drawn.flat)
                if walls:
                    enc.bit(has_walls, 0, tile.walls is not None)
                    if tile.walls is not None:
                        _code_mask(enc, model, walls, tile.walls.flat, model.walls)
    flags = PACK_FLAG_WELDED if atlas is not None else 0
    body = PACK_HEADER.pack(PACK_MAGIC, version, level, degree, spans, step, first,
                            count, side, flags, walls, 0) + enc.finish()
    return body + struct.pack("<I", zlib.crc32(body))


def _mask_side(tiles: Sequence[DetailTile], name: str, largest: int) -> int:
    """The one side of the tiles' ``name`` masks (``drawn`` or ``walls``), 0 without any;
    ``ValueError`` for masks that are not square with one side in ``1..largest``."""
    masks = [getattr(t, name) for t in tiles if getattr(t, name) is not None]
    sides = {m.rows for m in masks}
    if len(sides) > 1 or any(m.cols != m.rows for m in masks):
        raise ValueError(f"every {name} mask of a pack is square with one side; got "
                         f"{sorted((m.rows, m.cols) for m in masks)[:4]}")
    side = sides.pop() if sides else 0
    if side > largest:
        raise ValueError(f"a {name} mask has 1..{largest} cells per side, got {side}")
    return side


def pack_is_welded(data: bytes) -> bool:
    """Whether ``data`` looks like a welded pack (version 3 to 5, flag ``PACK_FLAG_WELDED``),
    which :func:`read_pack` reads only with its atlas; nothing else is checked here."""
    return len(data) > 21 and bytes(data[:4]) == PACK_MAGIC and data[4] >= 3 \
        and bool(data[21] & PACK_FLAG_WELDED)


def read_pack(data: bytes, atlas: AtlasSurface | None = None
              ) -> tuple[int, dict[int, list[DetailTile]]]:
    """``(level, {patch: [tiles]})`` of a pack's bytes, version 5, 4, 3, 2 or 1 (module
    docstring).

    ``atlas``: the layout the pack's patches lie on, needed by a welded pack (version 3 to
    5 with flag ``PACK_FLAG_WELDED``) and unused by any other.

    Raises
    ------
    PatchFormatError
        For anything but a valid pack, with the byte offset and the reason.
    ValueError
        A welded pack read without ``atlas``.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise PatchFormatError(0, f"a pack is bytes, got {type(data).__name__}")
    data = bytes(data)
    least = PACK_V1_HEADER_SIZE + PACK_ENTRY.size + CRC_SIZE  # the shortest of any version
    if len(data) < least:
        raise PatchFormatError(len(data), f"a pack has at least {least} bytes, got {len(data)}")
    if data[:4] != PACK_MAGIC:
        raise PatchFormatError(0, f"magic {data[:4]!r} is not {PACK_MAGIC!r}")
    (crc,) = struct.unpack_from("<I", data, len(data) - CRC_SIZE)
    if zlib.crc32(data[:-CRC_SIZE]) != crc:
        raise PatchFormatError(len(data) - CRC_SIZE, "CRC-32 mismatch: the pack is corrupt")
    version, level = data[4], data[5]
    if version not in READ_VERSIONS:
        raise PatchFormatError(4, f"version {version} is not one of {READ_VERSIONS}")
    if level > MAX_LEVEL:
        raise PatchFormatError(5, f"level {level} is above {MAX_LEVEL}")
    if version == 1:
        return level, _read_pack_v1(data, level)
    return level, _read_pack_stream(data, level, version, atlas)


def _read_pack_stream(data: bytes, level: int, version: int,
                      atlas: AtlasSurface | None) -> dict[int, list[DetailTile]]:
    """Versions 2..5: the header and ONE range-coded stream (version 2 is version 3 with
    every flag 0; version 4 is version 3 with the contexts of :func:`_model`; version 5 is
    version 4 with walls masks)."""
    if len(data) < PACK_HEADER_SIZE + CRC_SIZE:
        raise PatchFormatError(len(data), f"a version {version} pack has at least "
                               f"{PACK_HEADER_SIZE + CRC_SIZE} bytes, got {len(data)}")
    _, _, _, degree, spans, step, first, count, side, flags, walls, reserved = \
        PACK_HEADER.unpack_from(data)
    if not 1 <= degree <= MAX_DETAIL_DEGREE:
        raise PatchFormatError(6, f"degree {degree} outside 1..{MAX_DETAIL_DEGREE}")
    if not 1 <= spans <= MAX_SPANS:
        raise PatchFormatError(7, f"spans = {spans} outside 1..{MAX_SPANS}")
    if not (math.isfinite(step) and step > 0):
        raise PatchFormatError(8, f"quantisation step {step} is not a positive finite number")
    if side > MAX_DRAWN_SIDE:
        raise PatchFormatError(20, f"drawn mask side {side} outside 0..{MAX_DRAWN_SIDE}")
    if walls and version < 5:
        raise PatchFormatError(22, "reserved bytes are not 0")
    per_side = 1 << level
    if not 1 <= count or first + count > MAX_PACK_PATCH \
            or count * per_side * per_side > MAX_PACK_TILES \
            or pack_capacity(level, count, degree, spans, side, walls) > MAX_PACK_VALUES:
        raise PatchFormatError(12, f"patches {first}..{first + count - 1} of level {level}: "
                               f"a pack holds 1..{MAX_PACK_TILES} tiles, at most "
                               f"{MAX_PACK_VALUES} values, patches below {MAX_PACK_PATCH}")
    known_flags = PACK_FLAG_WELDED if version >= 3 else 0
    if flags & ~known_flags:
        raise PatchFormatError(21, f"unknown flags 0x{flags:02x} (version {version})"
                               if version >= 3 else "reserved bytes are not 0")
    if reserved:
        raise PatchFormatError(23, "reserved bytes are not 0")
    welded = bool(flags & PACK_FLAG_WELDED)
    if welded and atlas is None:
        raise ValueError("a welded pack (version 3 to 5, flag 0x1) codes each shared border "
                         "coefficient once: reading it needs the atlas (read_pack(data, atlas))")
    if welded and first + count > len(atlas.quads):
        raise PatchFormatError(12, f"patches {first}..{first + count - 1}: the atlas has "
                               f"{len(atlas.quads)}")
    size = spans + degree
    model = _model(version)
    presence, has_mask, has_walls = [HALF, HALF], [HALF], [HALF]
    tiles: dict[int, list[DetailTile]] = {}
    carried: dict[int, tuple[int, int]] = {}
    rings = _ring_template(level, spans, degree) if welded else {}
    before = 0
    try:  # the decoder reads its first bytes when it is made: inside the try too
        dec = RangeDecoder(data[PACK_HEADER_SIZE:len(data) - CRC_SIZE])
        for patch in range(first, first + count):
            done: dict[tuple[int, int], Sequence[int]] = {}
            slots = atlas.border_slots(patch, spans * per_side + degree) if welded else ()
            for i in range(per_side):
                for j in range(per_side):
                    before = dec.bit(presence, before)
                    if not before:
                        continue
                    ring = rings.get((i, j), ())
                    values = _decode_tile_values(dec, size * size, size, model,
                                                 _overlap_values(done, i, j, spans, size),
                                                 _welded_values(carried, ring, slots, patch,
                                                                size))
                    _carry(carried, ring, slots, patch, values)
                    done[i, j] = values
                    drawn = None
                    if side and dec.bit(has_mask, 0):
                        drawn = TrimMask.from_flat(side, side, _code_mask(dec, model, side))
                    wall = None
                    if walls and dec.bit(has_walls, 0):
                        wall = TrimMask.from_flat(walls, walls, _code_mask(dec, model, walls,
                                                                           None, model.walls))
                    if any(abs(q) > MAX_TILE_VALUE for q in values):
                        raise PatchFormatError(PACK_HEADER_SIZE, f"patch {patch} tile {i}_{j}: "
                                               f"decoded values beyond +-{MAX_TILE_VALUE}")
                    tiles.setdefault(patch, []).append(
                        DetailTile(level, i, j, degree, spans, step, tuple(values), drawn,
                                   wall))
    except RangeDecodeError as exc:
        raise PatchFormatError(len(data) - CRC_SIZE, f"coded tiles end early: {exc}") from None
    return tiles


def _read_pack_v1(data: bytes, level: int) -> dict[int, list[DetailTile]]:
    """Version 1: header ``<4sBBHI`` (magic, version, level, reserved, count), an index of
    ``(u32 patch, u32 length)`` per tile, the tiles' ``.tsd`` files back to back, CRC-32."""
    _, _, _, reserved, count = PACK_V1_HEADER.unpack_from(data)
    if reserved:
        raise PatchFormatError(6, f"reserved field is {reserved}, not 0")
    body_end = len(data) - CRC_SIZE
    index_end = PACK_V1_HEADER_SIZE + count * PACK_ENTRY.size
    if not 1 <= count <= MAX_PACK_TILES or index_end > body_end:
        raise PatchFormatError(8, f"count {count} does not fit the pack's {len(data)} bytes "
                               f"(1..{MAX_PACK_TILES} tiles)")
    entries = [PACK_ENTRY.unpack_from(data, PACK_V1_HEADER_SIZE + k * PACK_ENTRY.size)
               for k in range(count)]
    if sum(length for _, length in entries) != body_end - index_end:
        raise PatchFormatError(index_end, "the index's lengths do not add up to the tiles' "
                               f"{body_end - index_end} bytes")
    tiles: dict[int, list[DetailTile]] = {}
    offset, previous = index_end, (-1, -1, -1)
    for k, (patch, length) in enumerate(entries):
        at = PACK_V1_HEADER_SIZE + k * PACK_ENTRY.size
        if patch >= MAX_PACK_PATCH:
            raise PatchFormatError(at, f"patch {patch} is above {MAX_PACK_PATCH - 1}")
        try:
            tile = read_detail_tile(data[offset:offset + length])
        except PatchFormatError as exc:
            raise PatchFormatError(offset + exc.offset,
                                   f"tile {k} (patch {patch}): {exc.reason}") from None
        if tile.level != level:
            raise PatchFormatError(offset, f"tile {k} (patch {patch}) is of level {tile.level}, "
                                   f"the pack's is {level}")
        key = (patch, tile.i, tile.j)
        if key <= previous:
            raise PatchFormatError(at, f"tile {k}: patch {patch} tile {tile.i}_{tile.j} is out "
                                   "of order or repeated")
        previous = key
        tiles.setdefault(patch, []).append(tile)
        offset += length
    return tiles
