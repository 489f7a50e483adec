"""The atlas file ``.tsa`` v1 (docs/format.md, "Atlas patch file"): round trips within half a
quantisation step with shared points one value, the header layout, sizes checked before
inflating, and every malformed file a PatchFormatError (property-based, bounded examples)."""

from __future__ import annotations

import math
import struct
import time
import tracemalloc
import zlib
from functools import cache

import pytest
from atlas_cases import random_atlas, sphere_atlas
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_atlas import random_cube_atlas

from client_py.atlas import AtlasSurface
from client_py.atlas_format import (
    HEADER,
    HEADER_SIZE,
    MAGIC,
    payload_size_range,
    read_atlas,
    write_atlas,
)
from client_py.errors import PatchFormatError
from client_py.format import MAX_CONTROL_POINTS

FUZZ = settings(max_examples=120, deadline=2000, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow])


@cache
def cube_file() -> bytes:
    return write_atlas(random_cube_atlas(), 12, {"title": "cube", "units": "mm"})


def _points(atlas: AtlasSurface) -> list[tuple[float, float, float]]:
    return [*atlas.vertices, *atlas.edge_points, *atlas.face_points]


def _with_crc(body: bytes) -> bytes:
    return body + struct.pack("<I", zlib.crc32(body))


def payload_of(data: bytes) -> bytes:
    return zlib.decompress(data[HEADER_SIZE:-4])


def reframe(raw: bytes, data: bytes | None = None) -> bytes:
    """``raw`` as the payload of ``data``'s header (default the cube), sizes and CRC fixed."""
    fields = list(HEADER.unpack_from(data or cube_file()))
    blob = zlib.compress(raw, 9)
    fields[9], fields[10] = len(blob), len(raw)
    return _with_crc(HEADER.pack(*fields) + blob)


# ------------------------------------------------------------------ round trips
@pytest.mark.parametrize("make", [
    lambda: random_cube_atlas(3, 2), lambda: random_cube_atlas(1, 1),
    lambda: random_cube_atlas(2, 1), lambda: random_cube_atlas(3, 4),
    lambda: sphere_atlas(3, 2, 3), lambda: random_atlas(2, 3, 2, rational=False),
])
@pytest.mark.parametrize("bits", [8, 12, 16, 24])
def test_round_trip_within_half_a_step(make, bits):
    atlas = make()
    back, meta = read_atlas(write_atlas(atlas, bits, {"units": "mm", "n": [1, 2]}))
    assert meta == {"units": "mm", "n": [1, 2]}
    assert (back.degree, back.spans, back.quads) == (atlas.degree, atlas.spans, atlas.quads)
    assert back.edges.edges == atlas.edges.edges
    before, after = _points(atlas), _points(back)
    assert len(before) == len(after)
    top = (1 << bits) - 1
    for axis in range(3):
        lo, hi = min(p[axis] for p in before), max(p[axis] for p in before)
        half = (hi - lo) / (2 * top)
        worst = max(abs(p[axis] - q[axis]) for p, q in zip(before, after, strict=True))
        assert worst <= half * (1 + 1e-9) + 1e-300
    if atlas.weights is None:
        assert back.weights is None
    else:
        lo, hi = math.log(min(atlas.weights)), math.log(max(atlas.weights))
        bound = math.exp((hi - lo) / (2 * top)) - 1
        assert max(abs(b / a - 1) for a, b in zip(atlas.weights, back.weights,
                                                 strict=True)) <= bound * (1 + 1e-9)


def test_shared_points_are_one_value_so_neighbours_keep_one_border_curve():
    """After quantisation two neighbours still evaluate the same points on their side."""
    back, _ = read_atlas(write_atlas(random_cube_atlas(3, 2), 10))
    table = back.edges
    for (f, k), (g, m) in table.faces:
        same_way = table.sides[f][k][1] == table.sides[g][m][1]
        sf, sg = back.patch_surface(f), back.patch_surface(g)
        for t in (0.0, 0.3, 0.71, 1.0):
            a = sf.evaluate(*((t, 0.0), (1.0, t), (t, 1.0), (0.0, t))[k])
            t2 = t if same_way else 1.0 - t
            b = sg.evaluate(*((t2, 0.0), (1.0, t2), (t2, 1.0), (0.0, t2))[m])
            assert max(abs(x - y) for x, y in zip(a, b, strict=True)) < 1e-12


def test_the_same_atlas_gives_the_same_bytes_and_rereads_to_them():
    atlas = sphere_atlas(2, rational=True)
    data = write_atlas(atlas, 14)
    assert write_atlas(atlas, 14) == data
    back, meta = read_atlas(data)
    assert write_atlas(back, 14, meta) == data  # quantised values are fixed points


def test_header_layout_matches_the_spec():
    atlas = random_cube_atlas(3, 2)
    data = write_atlas(atlas, 12)
    magic, version, flags, d, s, bits, reserved, n_v, n_f, size, raw = HEADER.unpack_from(data)
    assert HEADER_SIZE == 28 and magic == b"TSPA" and version == 1
    assert (flags, d, s, bits, reserved, n_v, n_f) == (1, 3, 2, 12, 0, 8, 6)
    assert len(data) == HEADER_SIZE + size + 4
    assert zlib.crc32(data[:-4]) == struct.unpack("<I", data[-4:])[0]
    raw_bytes = payload_of(data)
    assert len(raw_bytes) == raw
    least, most = payload_size_range(flags, d, s, bits, n_v, n_f)
    assert least <= raw <= most
    # quads as u16 (V <= 65536), then the bounds
    quads = struct.unpack_from(f"<{4 * n_f}H", raw_bytes)
    assert [tuple(quads[4 * f : 4 * f + 4]) for f in range(n_f)] == atlas.quads
    bounds = struct.unpack_from("<6d", raw_bytes, 8 * n_f)
    pts = _points(atlas)
    assert bounds[:3] == tuple(min(p[a] for p in pts) for a in range(3))


def test_smooth_atlases_compress_and_random_ones_cost_their_entropy():
    """Sizes reported in docs/format.md: the prediction pays on smooth control points."""
    smooth = len(write_atlas(sphere_atlas(10), 12))
    rough = len(write_atlas(random_atlas(10), 12))
    points = random_atlas(10).control_point_count
    assert points == 9602
    assert smooth < 8000  # 0.8 byte per point
    assert rough < points * 4 * 12 / 8 * 1.3  # near the 12 bits x 4 coordinates of noise


def test_write_atlas_rejects_bad_arguments():
    atlas = random_cube_atlas()
    with pytest.raises(ValueError, match="bits must be an integer in 2..30, got 31"):
        write_atlas(atlas, 31)
    with pytest.raises(ValueError, match="bits must be an integer"):
        write_atlas(atlas, True)
    with pytest.raises(ValueError, match="atlas must be an AtlasSurface, got dict"):
        write_atlas({}, 12)
    with pytest.raises(ValueError, match="metadata must be JSON-serialisable"):
        write_atlas(atlas, 12, {"a": float("nan")})
    with pytest.raises(ValueError, match="metadata must be a dict, got list"):
        write_atlas(atlas, 12, [1])


# ------------------------------------------------------------------ malformed files
def _header_with(**fields) -> bytes:
    names = ["magic", "version", "flags", "degree", "spans", "bits", "reserved", "vertices",
             "quads", "size", "raw"]
    values = dict(zip(names, HEADER.unpack_from(cube_file()), strict=True)) | fields
    return HEADER.pack(*values.values())


def refused_quickly(data: bytes, match: str, seconds: float = 1.0, megabytes: float = 50):
    tracemalloc.start()
    start = time.perf_counter()
    try:
        with pytest.raises(PatchFormatError, match=match) as info:
            read_atlas(data)
        elapsed = time.perf_counter() - start
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert elapsed < seconds and peak < megabytes * 1e6, (elapsed, peak)
    return info.value


@pytest.mark.parametrize(("fields", "offset", "match"), [
    ({"magic": b"TSPF"}, 0, "not a Tessera atlas"),
    ({"version": 2}, 4, "atlas format version 2 is not supported"),
    ({"flags": 2}, 6, "unknown flags 0x0002"),
    ({"degree": 4}, 8, "degree 4 outside 1..3"),
    ({"degree": 0}, 8, "degree 0 outside 1..3"),
    ({"spans": 17}, 9, "spans = 17 outside 1..16"),
    ({"bits": 31}, 10, "bits = 31 outside 2..30"),
    ({"reserved": 1}, 11, "reserved byte is 1"),
    ({"vertices": 3}, 12, "3 vertices; 4..131072 accepted"),
    ({"quads": 0}, 16, "0 quads; 1..65536 accepted"),
    ({"quads": 65536, "vertices": 8}, 12, f"at most {MAX_CONTROL_POINTS} accepted"),
    ({"raw": 10**9}, 24, "exceeds the .* the layout allows"),
    ({"raw": 60}, 24, "payload size 60 is below the"),
])
def test_bad_header_fields_are_named_in_header_order(fields, offset, match):
    blob = cube_file()[HEADER_SIZE:-4]
    err = refused_quickly(_with_crc(_header_with(**fields) + blob), match)
    assert err.offset == offset and err.section == "file"


def test_claimed_sizes_above_the_limits_are_refused_before_inflating():
    """A valid CRC over a zlib bomb claiming the largest layout: refused on the header."""
    bomb = zlib.compress(bytes(1 << 22), 9)  # 4 MiB of zeros in about 4 KB
    small = zlib.compress(bytes(100), 9)
    for blob, fields, match in (
        (bomb, {"vertices": 1 << 17, "quads": 1 << 16, "spans": 16}, "at most 262144 accepted"),
        (bomb, {"raw": 1 << 22}, "payload size 4194304 exceeds the .* the layout allows"),
        (small, {"raw": 1032 * len(small) + 1}, f"exceeds the {1032 * len(small)} bytes a "
         f"{len(small)}-byte zlib stream can inflate to"),
    ):
        head = _header_with(size=len(blob), **fields)
        refused_quickly(_with_crc(head + blob), match, seconds=0.2, megabytes=2)


def test_framing_errors():
    data = cube_file()
    with pytest.raises(PatchFormatError, match="expected bytes, got str"):
        read_atlas("TSPA")
    with pytest.raises(PatchFormatError, match="truncated"):
        read_atlas(data[:-1])
    with pytest.raises(PatchFormatError, match="1 unexpected trailing bytes"):
        read_atlas(data + b"\0")
    flipped = bytearray(data)
    flipped[HEADER_SIZE + 5] ^= 0x10
    with pytest.raises(PatchFormatError, match="CRC32 mismatch") as info:
        read_atlas(bytes(flipped))
    assert info.value.offset == len(data) - 4


def _raw_with(edit) -> bytes:
    raw = bytearray(payload_of(cube_file()))
    edit(raw)
    return reframe(bytes(raw))


@pytest.mark.parametrize(("edit", "match"), [
    (lambda r: r.__setitem__(slice(0, 2), struct.pack("<H", 8)), "refers to vertex 8 of 8"),
    (lambda r: r.__setitem__(slice(0, 8), struct.pack("<4H", 0, 1, 1, 2)),
     "the quads are no valid layout: .*4 distinct"),
    (lambda r: r.__setitem__(slice(48, 56), struct.pack("<d", float("inf"))),
     "control point bounds holds a non-finite number"),
    (lambda r: r.__setitem__(slice(-5, None), b"[1]\x00\x00"), "metadata"),
    (lambda r: r.extend(b"xx"), "bytes left after metadata|metadata is not UTF-8 JSON"),
])
def test_bad_payloads_behind_a_valid_crc(edit, match):
    with pytest.raises(PatchFormatError, match=match) as info:
        read_atlas(_raw_with(edit))
    assert isinstance(info.value, ValueError)


def test_a_grid_value_outside_the_quantised_range_is_refused():
    raw = bytearray(payload_of(cube_file()))
    at = 48 + 48  # quads (6 x 8 bytes), bounds: the first residual of x (low byte plane)
    raw[at] = 255  # zig-zag 255: -128 for vertex 0, a value below 0
    raw[at + 98] = 255  # its second byte plane (B = 2 for 12 bits, 98 points)
    with pytest.raises(PatchFormatError, match="control points axis x decode outside 0..4095"):
        read_atlas(reframe(bytes(raw)))


# ------------------------------------------------------------------ fuzzing
def read_or_format_error(data: bytes):
    try:
        return read_atlas(data)
    except PatchFormatError:
        return None


@FUZZ
@given(st.data())
def test_truncation_is_detected(data):
    file = cube_file()
    with pytest.raises(PatchFormatError):
        read_atlas(file[: data.draw(st.integers(0, len(file) - 1))])


@FUZZ
@given(st.lists(st.integers(0, 8 * len(cube_file()) - 1), min_size=1, max_size=8, unique=True))
def test_bit_flips_are_detected(bits):
    data = bytearray(cube_file())
    for bit in bits:
        data[bit // 8] ^= 1 << (bit % 8)
    with pytest.raises(PatchFormatError):
        read_atlas(bytes(data))


@FUZZ
@given(st.binary(max_size=400))
def test_random_bytes_are_rejected(blob):
    for data in (blob, MAGIC + blob, cube_file()[:HEADER_SIZE] + blob):
        with pytest.raises(PatchFormatError):
            read_atlas(data)


@FUZZ
@given(st.binary(min_size=HEADER_SIZE - 6, max_size=HEADER_SIZE - 6))
def test_random_header_with_valid_crc(head):
    body = MAGIC + b"\x01\x00" + head + cube_file()[HEADER_SIZE:-4]
    read_or_format_error(body + struct.pack("<I", zlib.crc32(body)))


@FUZZ
@given(st.data())
def test_corrupt_payload_with_valid_crc(data):
    """Byte edits of the decompressed payload, recompressed and reframed: an atlas or a
    PatchFormatError, nothing else."""
    raw = bytearray(payload_of(cube_file()))
    for _ in range(data.draw(st.integers(1, 4))):
        kind = data.draw(st.sampled_from(["set", "cut", "insert"]))
        at = data.draw(st.integers(0, len(raw)))
        if kind == "set" and at < len(raw):
            raw[at] = data.draw(st.integers(0, 255))
        elif kind == "cut":
            del raw[at : at + data.draw(st.integers(1, 16))]
        else:
            raw[at:at] = data.draw(st.binary(min_size=1, max_size=16))
    result = read_or_format_error(reframe(bytes(raw)))
    assert result is None or isinstance(result[0], AtlasSurface)


def test_the_documented_header_is_the_code_s():
    """docs/format.md's atlas section gives the header's size and the limits the reader holds."""
    from pathlib import Path

    from client_py.atlas_format import ATLAS_LIMITS

    text = (Path(__file__).resolve().parent.parent / "docs" / "format.md").read_text()
    section = text[text.index("# Atlas patch file `.tsa`") : text.index("# Tiles:")]
    assert f"## Header ({HEADER_SIZE} bytes)" in section
    for row, limit in (("`d`, degree", ATLAS_LIMITS["degree"]),
                       ("`s`, spans", ATLAS_LIMITS["spans"]),
                       ("`V`, layout vertices", ATLAS_LIMITS["vertices"]),
                       ("`F`, quads", ATLAS_LIMITS["quads"])):
        line = next(x for x in section.splitlines() if row in x)
        assert f"..{limit}" in line, line
    assert ATLAS_LIMITS["control points"] == 1 << 18 and "<= 2^18" in section
