"""Detail packs: round trip and every malformed pack refused with a PatchFormatError."""

import random
import struct
import zlib

import pytest

from client_py.atlas_detail import pack_name, read_pack, write_pack
from client_py.errors import PatchFormatError
from client_py.layers import DetailTile


def _tile(level: int, i: int, j: int, seed: int) -> DetailTile:
    rnd = random.Random(seed)
    return DetailTile(level, i, j, 2, 4, 0.01, tuple(rnd.randint(-9, 9) for _ in range(36)))


def _tiles() -> dict[int, list[DetailTile]]:
    return {3: [_tile(1, 0, 1, 1), _tile(1, 1, 0, 2)], 7: [_tile(1, 1, 1, 3)]}


def test_round_trip():
    level, tiles = read_pack(write_pack(1, _tiles()))
    assert level == 1
    assert {p: [(t.i, t.j, t.coefficients) for t in ts] for p, ts in tiles.items()} == {
        p: [(t.i, t.j, t.coefficients) for t in sorted(ts, key=lambda t: (t.i, t.j))]
        for p, ts in _tiles().items()}


def test_name_rule():
    assert pack_name(2, 15) == "detail/2/15.tsdp"
    with pytest.raises(ValueError, match="group"):
        pack_name(2, -1)


def test_writer_refuses_mixed_levels():
    with pytest.raises(ValueError, match="level-0 tile in a level-1 pack"):
        write_pack(1, {0: [_tile(0, 0, 0, 1)]})


def _reframe(body: bytes) -> bytes:
    return body + struct.pack("<I", zlib.crc32(body))


@pytest.mark.parametrize("edit,match", [
    (lambda b: b[:10], "at least"),
    (lambda b: b[:-5] + b"\0" + b[-4:], "CRC"),
    (lambda b: _reframe(b"TSDX" + b[4:-4]), "magic"),
    (lambda b: _reframe(b[:4] + b"\x02" + b[5:-4]), "version"),
    (lambda b: _reframe(b[:5] + b"\x09" + b[6:-4]), "level 9"),
    (lambda b: _reframe(b[:8] + struct.pack("<I", 10**6) + b[12:-4]), "count"),
    (lambda b: _reframe(b[:-5]), "add up"),
    (lambda b: _reframe(b[:5] + b"\x00" + b[6:-4]), "of level 1"),
])
def test_bad_packs(edit, match):
    with pytest.raises(PatchFormatError, match=match):
        read_pack(edit(write_pack(1, _tiles())))


def test_every_single_byte_change_is_refused():
    data = write_pack(1, _tiles())
    for k in range(len(data)):
        bad = bytearray(data)
        bad[k] ^= 0x5A
        with pytest.raises(PatchFormatError):
            read_pack(bytes(bad))
