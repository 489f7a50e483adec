"""Detail packs: round trip (version 2, one range-coded stream), the version 1 fixture still
read, and every malformed pack refused with a PatchFormatError."""

import math
import random
import struct
import time
import zlib
from pathlib import Path

import pytest

from client_py.atlas_detail import (
    MAX_PACK_VALUES,
    PACK_HEADER,
    PACK_HEADER_SIZE,
    pack_name,
    read_pack,
    write_pack,
)
from client_py.errors import PatchFormatError
from client_py.layers import DetailTile
from client_py.trim import TrimMask

V1_FIXTURE = Path(__file__).parent / "data" / "pack_v1.tsdp"  # write_pack of _tiles(), v1


def _tile(level: int, i: int, j: int, seed: int) -> DetailTile:
    rnd = random.Random(seed)
    return DetailTile(level, i, j, 2, 4, 0.01, tuple(rnd.randint(-9, 9) for _ in range(36)))


def _tiles() -> dict[int, list[DetailTile]]:
    return {3: [_tile(1, 0, 1, 1), _tile(1, 1, 0, 2)], 7: [_tile(1, 1, 1, 3)]}


def _as_table(tiles: dict) -> dict:
    return {p: [(t.level, t.i, t.j, t.degree, t.spans, t.step, t.values,
                 None if t.drawn is None else t.drawn.flat)
                for t in sorted(ts, key=lambda t: (t.i, t.j))] for p, ts in tiles.items()}


def test_round_trip():
    data = write_pack(1, _tiles())
    level, tiles = read_pack(data)
    assert level == 1
    assert _as_table(tiles) == _as_table(_tiles())
    assert data[4] == 2 and len(data) == PACK_HEADER_SIZE + len(data[PACK_HEADER_SIZE:-4]) + 4


def test_round_trip_against_an_independent_reference():
    """Integers drawn independently (a Laplacian-like spread with zeros, as real detail),
    some tiles absent and some with drawn masks: every one comes back exactly."""
    rnd = random.Random(5)
    reference = {}
    for patch in (4, 5, 9):
        for i in range(4):
            for j in range(4):
                if rnd.random() < 0.3:
                    continue
                values = [int(round(rnd.gauss(0, 3))) if rnd.random() < 0.6 else 0
                          for _ in range(100)]
                values[rnd.randrange(100)] = rnd.choice([-(1 << 20), 70_001])  # escapes
                cells = bytes(rnd.random() < 0.5 for _ in range(16 * 16))
                drawn = TrimMask.from_flat(16, 16, cells) if rnd.random() < 0.5 else None
                reference.setdefault(patch, []).append(
                    DetailTile(2, i, j, 2, 8, 0.0125, tuple(values), drawn))
    level, tiles = read_pack(write_pack(2, reference))
    assert level == 2
    assert _as_table(tiles) == _as_table(reference)


def test_version_1_packs_still_read():
    data = V1_FIXTURE.read_bytes()
    assert data[4] == 1
    level, tiles = read_pack(data)
    assert level == 1
    assert _as_table(tiles) == _as_table(_tiles())
    # version 2 drops the 30 bytes of per-tile framing (index entry, .tsd header, CRC)
    assert len(write_pack(1, _tiles())) < len(data) - 3 * 22


def test_writer_refuses_what_one_pack_cannot_hold():
    with pytest.raises(ValueError, match="one step"):
        write_pack(1, {0: [_tile(1, 0, 0, 1)],
                       1: [DetailTile(1, 0, 0, 2, 4, 0.02, (0,) * 36)]})
    with pytest.raises(ValueError, match="given twice"):
        write_pack(1, {0: [_tile(1, 0, 0, 1), _tile(1, 0, 0, 2)]})
    with pytest.raises(ValueError, match="at least one tile"):
        write_pack(1, {0: []})
    with pytest.raises(ValueError, match="split the group"):
        write_pack(7, {0: [DetailTile(7, 0, 0, 2, 64, 0.1, (1,) * 66 ** 2)],
                       60_000: [DetailTile(7, 0, 0, 2, 64, 0.1, (1,) * 66 ** 2)]})


def test_name_rule():
    assert pack_name(2, 15) == "detail/2/15.tsdp"
    with pytest.raises(ValueError, match="group"):
        pack_name(2, -1)


def test_writer_refuses_mixed_levels():
    with pytest.raises(ValueError, match="level-0 tile in a level-1 pack"):
        write_pack(1, {0: [_tile(0, 0, 0, 1)]})


def _reframe(body: bytes) -> bytes:
    return body + struct.pack("<I", zlib.crc32(body))


def _with_header(data: bytes, **fields) -> bytes:
    names = ("magic", "version", "level", "degree", "spans", "step", "first", "count", "side",
             "reserved", "reserved2")
    head = dict(zip(names, PACK_HEADER.unpack_from(data), strict=True)) | fields
    return _reframe(PACK_HEADER.pack(*head.values()) + data[PACK_HEADER_SIZE:-4])


@pytest.mark.parametrize("edit,match", [
    (lambda b: b[:10], "at least"),
    (lambda b: b[:-5] + bytes([b[-5] ^ 1]) + b[-4:], "CRC"),
    (lambda b: _reframe(b"TSDX" + b[4:-4]), "magic"),
    (lambda b: _with_header(b, version=3), "version 3"),
    (lambda b: _with_header(b, level=9), "level 9"),
    (lambda b: _with_header(b, degree=0), "degree 0"),
    (lambda b: _with_header(b, spans=65), "spans = 65"),
    (lambda b: _with_header(b, step=math.nan), "step"),
    (lambda b: _with_header(b, step=-1.0), "step"),
    (lambda b: _with_header(b, count=0), "patches"),
    (lambda b: _with_header(b, first=65_535), "patches"),
    (lambda b: _with_header(b, count=50_000), "values"),
    (lambda b: _with_header(b, side=65), "drawn mask side 65"),
    (lambda b: _with_header(b, reserved2=1), "reserved"),
    (lambda b: _reframe(b[:PACK_HEADER_SIZE + 3]), "end early"),
    (lambda b: _with_header(b, count=40), "end early"),
])
def test_bad_packs(edit, match):
    with pytest.raises(PatchFormatError, match=match):
        read_pack(edit(write_pack(1, _tiles())))


@pytest.mark.parametrize("edit,match", [
    (lambda b: _reframe(b[:8] + struct.pack("<I", 10**6) + b[12:-4]), "count"),
    (lambda b: _reframe(b[:-5]), "add up"),
    (lambda b: _reframe(b[:5] + b"\x00" + b[6:-4]), "of level 1"),
])
def test_bad_version_1_packs(edit, match):
    with pytest.raises(PatchFormatError, match=match):
        read_pack(edit(V1_FIXTURE.read_bytes()))


def test_the_largest_pack_decodes_within_seconds():
    """The most values a header allows (MAX_PACK_VALUES), every tile present and zero, is
    a few kilobytes: the header, not the file's length, bounds the decoding."""
    zeros = (0,) * 256  # level 3, spans 14, degree 2: 64 tiles of 256 values a patch
    tiles = {p: [DetailTile(3, i, j, 2, 14, 0.1, zeros) for i in range(8) for j in range(8)]
             for p in range(MAX_PACK_VALUES // (64 * 256))}
    data = write_pack(3, tiles)
    assert len(data) < 10_000
    clock = time.perf_counter()
    level, decoded = read_pack(data)
    assert time.perf_counter() - clock < 20  # ~1.6 s on the 2-core machine
    assert sum(len(t) for t in decoded.values()) == 64 * len(tiles)
    with pytest.raises(PatchFormatError, match="values"):
        read_pack(_with_header(data, count=len(tiles) + 1))


def test_rows_that_neighbouring_tiles_share_cost_a_bit_each():
    """Tiles cut from one level grid (as the fitter cuts them) share p rows with their
    neighbours: the pack codes each shared value once (then one 'equal' bit); tiles that
    disagree there still round-trip exactly, at the full price."""
    rnd = random.Random(9)
    level, spans, degree = 2, 4, 2
    n, size = (spans << level) + degree, spans + degree
    grid = [[int(round(rnd.gauss(0, 4))) for _ in range(n)] for _ in range(n)]

    def cut(i, j, bump=0):
        return tuple(grid[i * spans + a][j * spans + b] + (bump if a < degree or b < degree
                                                           else 0)
                     for a in range(size) for b in range(size))

    nodes = [(i, j) for i in range(4) for j in range(4)]
    agree = {0: [DetailTile(level, i, j, degree, spans, 0.5, cut(i, j)) for i, j in nodes]}
    differ = {0: [DetailTile(level, i, j, degree, spans, 0.5, cut(i, j, i + j))
                  for i, j in nodes]}
    packs = [write_pack(level, tiles) for tiles in (agree, differ)]
    for data, tiles in zip(packs, (agree, differ), strict=True):
        assert _as_table(read_pack(data)[1]) == _as_table(tiles)
    shared = (16 * size * size - n * n) / (16 * size * size)  # values held twice: 44 %
    assert len(packs[0]) < (1 - 0.6 * shared) * len(packs[1])


def test_random_streams_behind_a_valid_header_and_crc_are_tiles_or_format_errors():
    """Any coded bytes after a valid header (and a CRC made to match) decode to tiles of the
    header's shape or raise PatchFormatError, never anything else, and quickly."""
    rnd = random.Random(11)
    head = write_pack(1, _tiles())[:PACK_HEADER_SIZE]
    for _ in range(300):
        data = _reframe(head + bytes(rnd.randrange(256) for _ in range(rnd.randrange(0, 60))))
        try:
            level, tiles = read_pack(data)
        except PatchFormatError:
            continue
        assert level == 1
        assert all(t.size == 6 and len(t.values) == 36 for ts in tiles.values() for t in ts)
