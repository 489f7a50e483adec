"""Detail packs: the detail tiles of one level for a group of neighbouring atlas patches.

An atlas (``client_py.atlas``) has hundreds of patches, each refined by its own pyramid of
``.tsd`` detail tiles over its own ``[0, 1]²`` (``client_py.layers.DetailTile``,
docs/format.md). One file per tile would cost a visitor thousands of requests, so the
tiles of level ``k`` of the patches in group ``g`` travel together in one *pack*,
``detail/K/G.tsdp`` (:func:`pack_name`: the one naming rule). A viewer fetches the packs of
the groups on screen whose error it must refine; ``tessera tessellate --level L`` reads
every pack of levels ``0..L``.

Layout (little-endian; ``client_py.format`` frames the tiles themselves)::

    offset  size       field
    0       4          magic  b"TSDP"
    4       1          version 1
    5       1          level k (0..7, as in every tile it holds)
    6       2          reserved, 0
    8       4          count: tiles in the pack (1..MAX_PACK_TILES)
    12      8 count    index: per tile, u32 patch and u32 byte length, in file order
    ...     sum(len)   the tiles' .tsd bytes, back to back, in index order
    end-4   4          CRC-32 of everything before it

The lengths must add up to the file exactly; every tile must be of level ``k``; the
patches must be in non-decreasing order and a patch's tiles in ``(i, j)`` order without a
repeat. Every failure is a ``PatchFormatError(offset, reason)``, checked before any tile is
decoded; decoding is bounded by the file's length.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Mapping, Sequence

from .errors import PatchFormatError
from .format import read_detail_tile, write_detail_tile
from .layers import MAX_LEVEL, DetailTile

PACK_MAGIC = b"TSDP"
PACK_VERSION = 1
PACK_HEADER = struct.Struct("<4sBBHI")
PACK_HEADER_SIZE = PACK_HEADER.size  # 12
PACK_ENTRY = struct.Struct("<II")
MAX_PACK_TILES = 1 << 16
MAX_PACK_PATCH = 1 << 16  # client_py.atlas.MAX_ATLAS_QUADS


def pack_name(level: int, group: int) -> str:
    """The bundle file of level ``level``'s tiles for patch group ``group``."""
    for name, value in (("level", level), ("group", group)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"{name} must be an integer >= 0, got {value!r}")
    return f"detail/{level}/{group}.tsdp"


def write_pack(level: int, tiles: Mapping[int, Sequence[DetailTile]]) -> bytes:
    """The pack of ``tiles`` (patch -> its level-``level`` tiles).

    Raises
    ------
    ValueError
        An empty pack, a tile of another level, a patch index out of range or too many tiles.
    """
    entries: list[tuple[int, bytes]] = []
    for patch in sorted(tiles):
        if isinstance(patch, bool) or not isinstance(patch, int) \
                or not 0 <= patch < MAX_PACK_PATCH:
            raise ValueError(f"patch index must be an int in 0..{MAX_PACK_PATCH - 1}, "
                             f"got {patch!r}")
        for tile in sorted(tiles[patch], key=lambda t: (t.i, t.j)):
            if tile.level != level:
                raise ValueError(f"patch {patch}: a level-{tile.level} tile in a level-{level} "
                                 "pack")
            entries.append((patch, write_detail_tile(tile)))
    if not 1 <= len(entries) <= MAX_PACK_TILES:
        raise ValueError(f"a pack holds 1..{MAX_PACK_TILES} tiles, got {len(entries)}")
    body = b"".join([PACK_HEADER.pack(PACK_MAGIC, PACK_VERSION, level, 0, len(entries))]
                    + [PACK_ENTRY.pack(patch, len(data)) for patch, data in entries]
                    + [data for _, data in entries])
    return body + struct.pack("<I", zlib.crc32(body))


def read_pack(data: bytes) -> tuple[int, dict[int, list[DetailTile]]]:
    """``(level, {patch: [tiles]})`` of a pack's bytes (module docstring for the checks)."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise PatchFormatError(0, f"a pack is bytes, got {type(data).__name__}")
    data = bytes(data)
    if len(data) < PACK_HEADER_SIZE + PACK_ENTRY.size + 4:
        raise PatchFormatError(len(data), f"a pack has at least "
                               f"{PACK_HEADER_SIZE + PACK_ENTRY.size + 4} bytes, got {len(data)}")
    magic, version, level, reserved, count = PACK_HEADER.unpack_from(data)
    if magic != PACK_MAGIC:
        raise PatchFormatError(0, f"magic {magic!r} is not {PACK_MAGIC!r}")
    (crc,) = struct.unpack_from("<I", data, len(data) - 4)
    if zlib.crc32(data[:-4]) != crc:
        raise PatchFormatError(len(data) - 4, "CRC-32 mismatch: the pack is corrupt")
    if version != PACK_VERSION:
        raise PatchFormatError(4, f"version {version} is not {PACK_VERSION}")
    if level > MAX_LEVEL:
        raise PatchFormatError(5, f"level {level} is above {MAX_LEVEL}")
    if reserved:
        raise PatchFormatError(6, f"reserved field is {reserved}, not 0")
    body_end = len(data) - 4
    index_end = PACK_HEADER_SIZE + count * PACK_ENTRY.size
    if not 1 <= count <= MAX_PACK_TILES or index_end > body_end:
        raise PatchFormatError(8, f"count {count} does not fit the pack's {len(data)} bytes "
                               f"(1..{MAX_PACK_TILES} tiles)")
    entries = [PACK_ENTRY.unpack_from(data, PACK_HEADER_SIZE + k * PACK_ENTRY.size)
               for k in range(count)]
    if sum(length for _, length in entries) != body_end - index_end:
        raise PatchFormatError(index_end, "the index's lengths do not add up to the tiles' "
                               f"{body_end - index_end} bytes")
    tiles: dict[int, list[DetailTile]] = {}
    offset, previous = index_end, (-1, -1, -1)
    for k, (patch, length) in enumerate(entries):
        at = PACK_HEADER_SIZE + k * PACK_ENTRY.size
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
    return level, tiles
