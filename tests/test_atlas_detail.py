"""Detail packs: round trip (version 4, one range-coded stream with neighbour contexts;
welded: each shared border coefficient coded once a pack), the version 3, 2 and 1 fixtures
still read, a welded pack
decoding alone and against the old writer's values, and every malformed pack refused with a
PatchFormatError."""

import math
import random
import struct
import time
import zlib
from dataclasses import replace
from pathlib import Path

import pytest
from atlas_cases import sphere_atlas

from client_py.atlas import ring_positions
from client_py.atlas_detail import (
    MAX_PACK_VALUES,
    PACK_FLAG_WELDED,
    PACK_HEADER,
    PACK_HEADER_SIZE,
    PACK_VERSION,
    WALLS_FREE_VERSION,
    pack_is_welded,
    pack_name,
    read_pack,
    write_pack,
)
from client_py.errors import PatchFormatError
from client_py.layers import DetailTile
from client_py.trim import TrimMask

V1_FIXTURE = Path(__file__).parent / "data" / "pack_v1.tsdp"  # write_pack of _tiles(), v1
V2_FIXTURE = Path(__file__).parent / "data" / "pack_v2.tsdp"  # write_pack of _tiles(), v2
# version 2's write_pack (main 43b3669) of _welded_tiles(): every patch, no atlas
V2_WELDED_FIXTURE = Path(__file__).parent / "data" / "pack_v2_welded.tsdp"
# version 3's write_pack (main 732fe1f) of _tiles(), and of _welded_tiles() with its atlas
V3_FIXTURE = Path(__file__).parent / "data" / "pack_v3.tsdp"
V3_WELDED_FIXTURE = Path(__file__).parent / "data" / "pack_v3_welded.tsdp"
# version 4's write_pack (main 90503fb, before walls masks) of _tiles(), and of
# _welded_tiles() with its atlas
V4_FIXTURE = Path(__file__).parent / "data" / "pack_v4.tsdp"
V4_WELDED_FIXTURE = Path(__file__).parent / "data" / "pack_v4_welded.tsdp"


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
    assert data[4] == WALLS_FREE_VERSION == 4 and data[21] == 0 and not pack_is_welded(data)
    assert len(data) == PACK_HEADER_SIZE + len(data[PACK_HEADER_SIZE:-4]) + 4


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


def _walls_table(tiles: dict) -> dict:
    return {p: [(t.i, t.j, None if t.walls is None else (t.walls.rows, t.walls.flat))
                for t in sorted(ts, key=lambda t: (t.i, t.j))] for p, ts in tiles.items()}


@pytest.mark.parametrize("welded", [False, True])
def test_walls_masks_round_trip_as_version_5(welded):
    """Tiles with walls masks (some without, some with drawn masks too, one with all-zero
    values and an all-clear mask) come back exactly from a version 5 pack, welded or
    not; the same tiles without their walls masks are written as version 4, byte for byte
    the pack of before."""
    rnd = random.Random(11)
    atlas = sphere_atlas(2, noise=0.0) if welded else None
    reference = {}
    for patch in range(6):
        for i in range(2):
            for j in range(2):
                values = tuple(0 if welded else rnd.randint(-5, 5) for _ in range(36))
                walls = TrimMask.from_flat(8, 8, bytes(rnd.random() < 0.3 for _ in range(64))) \
                    if rnd.random() < 0.6 else None
                if (patch, i, j) == (2, 1, 1):
                    walls = TrimMask.from_flat(8, 8, bytes(64))  # all clear
                drawn = TrimMask.from_flat(4, 4, bytes(rnd.random() < 0.5 for _ in range(16))) \
                    if rnd.random() < 0.3 else None
                reference.setdefault(patch, []).append(
                    DetailTile(1, i, j, 2, 4, 0.01, values, drawn, walls))
    data = write_pack(1, reference, atlas)
    assert data[4] == PACK_VERSION == 5 and data[22] == 8 and data[23] == 0
    level, tiles = read_pack(data, atlas)
    assert level == 1
    assert _as_table(tiles) == _as_table(reference)
    assert _walls_table(tiles) == _walls_table(reference)
    bare = {p: [replace(t, walls=None) for t in ts] for p, ts in reference.items()}
    old = write_pack(1, bare, atlas)
    assert old[4] == WALLS_FREE_VERSION and old[22] == 0
    assert _walls_table(read_pack(old, atlas)[1]) == _walls_table(bare)
    # the walls masks add their bits, nothing else changes but the version and side bytes
    assert old[:4] + old[5:22] == data[:4] + data[5:22] and len(old) < len(data)


def test_walls_masks_of_a_pack_share_one_side():
    tiles = {0: [replace(_tile(1, 0, 0, 1), walls=TrimMask.from_flat(4, 4, bytes(16))),
                 replace(_tile(1, 0, 1, 2), walls=TrimMask.from_flat(8, 8, bytes(64)))]}
    with pytest.raises(ValueError, match="every walls mask of a pack is square with one side"):
        write_pack(1, tiles)
    big = TrimMask.from_flat(256, 256, bytes(256 * 256))
    with pytest.raises(ValueError, match="a walls mask has 1..255 cells per side, got 256"):
        write_pack(0, {0: [replace(_tile(0, 0, 0, 1), walls=big)]})


@pytest.mark.parametrize("fixture,version", [(V1_FIXTURE, 1), (V2_FIXTURE, 2),
                                             (V3_FIXTURE, 3)])
def test_older_packs_still_read(fixture, version):
    data = fixture.read_bytes()
    assert data[4] == version
    level, tiles = read_pack(data)
    assert level == 1
    assert _as_table(tiles) == _as_table(_tiles())


def test_one_stream_drops_version_1_s_framing_and_is_version_2_s():
    new = write_pack(1, _tiles())
    # version 2 dropped the 30 bytes of per-tile framing (index entry, .tsd header, CRC)
    assert len(new) < len(V1_FIXTURE.read_bytes()) - 3 * 22
    # without an atlas, version 3 was version 2's stream: only the version byte differs
    old, v3 = V2_FIXTURE.read_bytes(), V3_FIXTURE.read_bytes()
    assert v3[:4] + v3[5:-4] == old[:4] + old[5:-4]
    # version 4 changed the contexts only: the same header but the version byte
    assert new[:4] + new[5:PACK_HEADER_SIZE] == v3[:4] + v3[5:PACK_HEADER_SIZE]


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
             "flags", "walls", "reserved")
    head = dict(zip(names, PACK_HEADER.unpack_from(data), strict=True)) | fields
    return _reframe(PACK_HEADER.pack(*head.values()) + data[PACK_HEADER_SIZE:-4])


@pytest.mark.parametrize("edit,match", [
    (lambda b: b[:10], "at least"),
    (lambda b: b[:-5] + bytes([b[-5] ^ 1]) + b[-4:], "CRC"),
    (lambda b: _reframe(b"TSDX" + b[4:-4]), "magic"),
    (lambda b: _with_header(b, version=6), "version 6"),
    (lambda b: _with_header(b, flags=2), "unknown flags 0x02"),
    (lambda b: _with_header(b, version=2, flags=1), "reserved"),
    (lambda b: _with_header(b, level=9), "level 9"),
    (lambda b: _with_header(b, degree=0), "degree 0"),
    (lambda b: _with_header(b, spans=65), "spans = 65"),
    (lambda b: _with_header(b, step=math.nan), "step"),
    (lambda b: _with_header(b, step=-1.0), "step"),
    (lambda b: _with_header(b, count=0), "patches"),
    (lambda b: _with_header(b, first=65_535), "patches"),
    (lambda b: _with_header(b, count=50_000), "values"),
    (lambda b: _with_header(b, side=65), "drawn mask side 65"),
    (lambda b: _with_header(b, reserved=1), "reserved"),
    (lambda b: _with_header(b, walls=1), "reserved"),  # a version 4 pack has no walls
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


# ------------------------------------------------------------------ welded packs
WELD_LEVEL, WELD_SPANS, WELD_DEGREE = 1, 4, 2


def _welded_tiles(seed: int = 3, absent: float = 0.1) -> tuple[object, dict]:
    """Level-1 tiles of the 24 patches of a sphere atlas as the fitter makes them: per patch
    a level grid of ``n = 4 * 2 + 2`` coefficients a side whose border ring takes one value
    per shared slot (the atlas's rule, computed here from the layout's corners and edges
    directly, not through ``border_slots``), interior values of their own; a share
    ``absent`` of the tiles left out (a zero field there, which a neighbour need not match).
    """
    atlas = sphere_atlas(2)
    rnd = random.Random(seed)
    n = (WELD_SPANS << WELD_LEVEL) + WELD_DEGREE
    size = WELD_SPANS + WELD_DEGREE
    slot_value: dict = {}

    def shared(key):
        if key not in slot_value:
            slot_value[key] = int(round(rnd.gauss(0, 4)))
        return slot_value[key]

    tiles = {}
    for f, quad in enumerate(atlas.quads):
        grid = [[int(round(rnd.gauss(0, 4))) for _ in range(n)] for _ in range(n)]
        for (a, b), corner in zip(((0, 0), (n - 1, 0), (n - 1, n - 1), (0, n - 1)), quad,
                                  strict=True):
            grid[a][b] = shared(("vertex", corner))
        sides = (((1, 0), (1, 0)), ((n - 1, 1), (0, 1)), ((1, n - 1), (1, 0)), ((0, 1), (0, 1)))
        for k, ((a0, b0), (da, db)) in enumerate(sides):
            start, end = quad[(0, 1, 3, 0)[k]], quad[(1, 2, 2, 3)[k]]
            for t in range(n - 2):  # t-th interior point from the side's start corner
                along = t if start < end else n - 3 - t  # from the edge's lower vertex
                grid[a0 + da * t][b0 + db * t] = shared(("edge", min(start, end),
                                                         max(start, end), along))
        for i in range(2):
            for j in range(2):
                if rnd.random() < absent:
                    continue
                values = tuple(grid[i * WELD_SPANS + a][j * WELD_SPANS + b]
                               for a in range(size) for b in range(size))
                tiles.setdefault(f, []).append(DetailTile(WELD_LEVEL, i, j, WELD_DEGREE,
                                                          WELD_SPANS, 0.02, values))
    return atlas, tiles


def test_welded_pack_round_trips_to_the_old_writers_values_in_fewer_bytes():
    atlas, tiles = _welded_tiles()
    old = V2_WELDED_FIXTURE.read_bytes()
    assert old[4] == 2
    _, old_tiles = read_pack(old)
    assert _as_table(old_tiles) == _as_table(tiles)  # the generator has not drifted
    data = write_pack(WELD_LEVEL, tiles, atlas)
    assert data[4] == 4 and data[21] == PACK_FLAG_WELDED and pack_is_welded(data)
    level, decoded = read_pack(data, atlas)
    assert level == WELD_LEVEL and _as_table(decoded) == _as_table(old_tiles)
    # 24 patches of 10 x 10 coefficients: 36 ring values each, 26 slots per edge and vertex
    # ring of the cube layout's 48 edges (8 each) and 26 vertices: 864 ring values over
    # 26 + 48 * 8 = 410 slots; about half of the ring values are not coded again
    assert len(data) < 0.9 * len(old)
    with pytest.raises(ValueError, match="needs the atlas"):
        read_pack(data)


def test_a_version_3_welded_pack_still_reads_and_version_4_is_smaller():
    """Version 3 (the ``.tsd`` v2 tile's contexts) against its atlas: the same tiles as the
    generator and as version 4 writes them, version 4 in fewer bytes (its sign contexts
    pay on values that share their neighbours' sign; these random ones do not, so only a
    little)."""
    atlas, tiles = _welded_tiles()
    old = V3_WELDED_FIXTURE.read_bytes()
    assert old[4] == 3 and pack_is_welded(old)
    level, decoded = read_pack(old, atlas)
    assert level == WELD_LEVEL and _as_table(decoded) == _as_table(tiles)
    assert len(write_pack(WELD_LEVEL, tiles, atlas)) <= len(old) * 1.02


def test_neighbour_signs_cost_less_in_version_4():
    """A smooth field (a sine of the coefficient position, rounded): version 4's sign and
    magnitude contexts code it in fewer bytes than version 3 did (its fixture is of random
    values, so the comparison is against a version 3 writer made here from the same
    stream with the old contexts)."""
    import client_py.atlas_detail as module
    from client_py.atlas_detail import _model

    smooth = {p: [DetailTile(1, i, j, 2, 8, 0.01, tuple(
        round(6 * math.sin(0.7 * (a + 8 * i) + 0.3 * p) * math.cos(0.5 * (b + 8 * j)))
        for a in range(10) for b in range(10))) for i in range(2) for j in range(2)]
        for p in range(6)}
    new = write_pack(1, smooth)
    assert read_pack(new)[1] == {p: sorted(ts, key=lambda t: (t.i, t.j))
                                 for p, ts in smooth.items()}
    module._model = lambda version: _model(3)  # the version 3 contexts, same stream
    try:
        old = write_pack(1, smooth)
    finally:
        module._model = _model
    assert len(new) < 0.9 * len(old)


def test_a_welded_pack_decodes_without_its_neighbour_pack():
    """Two groups of 12 patches: each pack codes what its own earlier patches did not, so
    either decodes alone (the border slots shared with the other group are in both)."""
    atlas, tiles = _welded_tiles(seed=4)
    halves = [{f: t for f, t in tiles.items() if f < 12}, {f: t for f, t in tiles.items()
                                                           if f >= 12}]
    for half in halves:
        level, decoded = read_pack(write_pack(WELD_LEVEL, half, atlas), atlas)
        assert _as_table(decoded) == _as_table(half)
    # one patch alone shares nothing within its pack: the same stream as unwelded
    one = {13: tiles[13]}
    welded, plain = write_pack(WELD_LEVEL, one, atlas), write_pack(WELD_LEVEL, one)
    assert welded[:21] + welded[22:-4] == plain[:21] + plain[22:-4]
    assert _as_table(read_pack(welded, atlas)[1]) == _as_table(one)


def test_welded_writer_refuses_borders_that_differ():
    atlas, tiles = _welded_tiles(absent=0.0)
    first = tiles[1][0]
    tiles[1][0] = DetailTile(first.level, first.i, first.j, first.degree, first.spans,
                             first.step, (first.values[0] + 1,) + first.values[1:])
    with pytest.raises(ValueError, match="same shared border slot"):
        write_pack(WELD_LEVEL, tiles, atlas)
    with pytest.raises(ValueError, match="not one of the atlas's 24 patches"):
        write_pack(WELD_LEVEL, {30: tiles[2]}, atlas)


@pytest.mark.parametrize("edit,match", [
    (lambda b: b[:PACK_HEADER_SIZE + 6], "at least|CRC"),
    (lambda b: _reframe(b[:len(b) // 2]), "end early"),
    (lambda b: b[:40] + bytes([b[40] ^ 0x10]) + b[41:], "CRC"),
    (lambda b: _with_header(b, count=40), "the atlas has 24"),
    (lambda b: _with_header(b, flags=3), "unknown flags"),
])
def test_bad_welded_packs(edit, match):
    atlas, tiles = _welded_tiles()
    with pytest.raises(PatchFormatError, match=match):
        read_pack(edit(write_pack(WELD_LEVEL, tiles, atlas)), atlas)


@pytest.mark.parametrize("n", [2, 3, 7, 10])
def test_border_slots_number_the_points_neighbours_share(n):
    """An independent reference: the atlas is watertight, so the point of patch ``f`` at
    ``(a, b) / (n - 1)`` of its grid is the same 3D point for every patch holding the slot,
    and different slots are different points; every layout vertex is a slot, every edge
    ``n - 2`` of them."""
    atlas = sphere_atlas(2, noise=0.05, seed=2)
    at: dict = {}
    for f in range(len(atlas.quads)):
        ring = list(zip(ring_positions(n), atlas.border_slots(f, n), strict=True))
        assert len(ring) == 4 * (n - 1) == len({ab for ab, _ in ring})
        assert all(0 in ab or n - 1 in ab for ab, _ in ring)
        surface = atlas.patch_surface(f)
        for (a, b), slot in ring:
            point = surface.evaluate(a / (n - 1), b / (n - 1))
            if slot in at:
                assert math.dist(point, at[slot]) < 1e-9
            at[slot] = point
    assert sorted(at) == list(range(len(atlas.vertices)
                                    + (n - 2) * len(atlas.edges.edges)))
    assert len({tuple(round(x, 6) for x in p) for p in at.values()}) == len(at)
    with pytest.raises(ValueError, match="n >= 2"):
        atlas.border_slots(0, 1)


def test_packs_without_walls_masks_are_version_4_byte_for_byte():
    """Tiles without walls masks are written as the writer before version 5 wrote them
    (its bytes kept as fixtures, plain and welded), and those bytes read back."""
    assert write_pack(1, _tiles()) == V4_FIXTURE.read_bytes()
    atlas, tiles = _welded_tiles()
    assert write_pack(WELD_LEVEL, tiles, atlas) == V4_WELDED_FIXTURE.read_bytes()
    assert _as_table(read_pack(V4_WELDED_FIXTURE.read_bytes(), atlas)[1]) == _as_table(tiles)
