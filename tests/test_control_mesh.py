"""``.tsa`` versions 5 and 6, a smooth base's control mesh (client_py.control_mesh): round
trips, the reader's atlas, version 6's point coder against version 5, and every refusal."""

from __future__ import annotations

import struct
import zlib
from functools import cache
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from client_py.atlas_format import HEADER, read_atlas
from client_py.control_mesh import (
    MAX_TRIANGLES,
    WEIGHT_STEPS,
    ControlMeshCodes,
    canonical_control_mesh,
    point_order,
    point_predictors,
    read_control_codes,
    read_control_header,
    read_control_mesh,
    traversal_order,
    write_control_codes,
    write_control_mesh,
)
from client_py.errors import PatchFormatError
from client_py.rangecoder import RangeDecodeError, RangeDecoder, RangeEncoder
from client_py.smooth_base import smooth_atlas
from client_py.triangle_coder import decode_triangles, encode_triangles

FUZZ = settings(max_examples=120, deadline=2000, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow])
#: ``two_pieces()`` at 12 bits with metadata ``{"units": "mm"}``, as session 30's writer
#: wrote version 5 (before version 6)
V5_FIXTURE = Path(__file__).parent / "data" / "control_mesh_v5.tsa"


def icosphere() -> tuple[np.ndarray, np.ndarray]:
    mesh = trimesh.creation.icosphere(2, 3.0)
    return np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64)


def grid(n: int = 6) -> tuple[np.ndarray, np.ndarray]:
    x, y = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
    points = np.stack([x.ravel(), y.ravel(), np.sin(x.ravel()) * np.cos(y.ravel())], 1)
    tris = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
            tris += [(a, b, c), (a, c, d)]
    return points, np.array(tris)


def two_pieces() -> tuple[np.ndarray, np.ndarray]:
    p, t = icosphere()
    q, u = grid(4)
    return np.concatenate([p, q + 10]), np.concatenate([t, u + len(p)])


def bumpy_sphere(n: int = 400, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A decimated-like sphere: the hull of ``n`` random points on the unit sphere (valences
    and triangle shapes as irregular as a quadric decimation's), then bumped and stretched."""
    rng = np.random.default_rng(seed)
    p = rng.standard_normal((n, 3))
    hull = trimesh.convex.convex_hull(p / np.linalg.norm(p, axis=1)[:, None])
    v, f = np.asarray(hull.vertices, float), np.asarray(hull.faces, np.int64)
    r = 1 + 0.1 * np.sin(3 * v[:, 0]) * np.cos(2 * v[:, 1]) + 0.05 * v[:, 2] ** 2
    return v * r[:, None] * [3.0, 2.0, 1.5], f


def open_caps() -> tuple[np.ndarray, np.ndarray]:
    """Two pieces with borders: the bumpy sphere's triangles below z = 0.6, and a second
    such cap of another sphere, apart (points in no triangle kept: the writer allows them)."""
    parts, offset = [], 0
    for seed, shift in ((1, 0.0), (2, 10.0)):
        v, f = bumpy_sphere(300, seed)
        f = f[v[f].mean(axis=1)[:, 2] < 0.6]
        parts.append((v + shift, f + offset))
        offset += len(v)
    return np.concatenate([v for v, _ in parts]), np.concatenate([f for _, f in parts])


MESHES = [icosphere, grid, two_pieces, bumpy_sphere, open_caps]


@pytest.mark.parametrize("version", [5, 6])
@pytest.mark.parametrize("mesh", MESHES)
@pytest.mark.parametrize("bits", [8, 12, 16])
def test_a_control_mesh_reads_back_within_half_a_step(mesh, bits, version):
    points, triangles = mesh()
    data = write_control_mesh(points, triangles, bits, {"units": "mm"}, version=version)
    assert read_control_header(data)["version"] == version
    got, tris, metadata = read_control_mesh(data)
    order, expected = canonical_control_mesh(len(points), traversal_order(triangles))
    assert tris == expected
    step = np.ptp(points, axis=0) / ((1 << bits) - 1)
    assert np.all(np.abs(np.asarray(got) - points[order]) <= step / 2 + 1e-12)
    assert metadata == {"units": "mm"}
    # the same surface: every triangle of the input, up to the renumbering and a rotation
    new = {v: k for k, v in enumerate(order)}
    rotations = {tuple(np.roll([new[v] for v in t], -r)) for t in triangles for r in range(3)}
    assert len(tris) == len(triangles) and all(t in rotations for t in tris)


@pytest.mark.parametrize("mesh", MESHES)
@pytest.mark.parametrize("bits", [2, 11, 30])
def test_the_codes_round_trip_exactly(mesh, bits):
    """Random codes over the whole range (no smoothness to lean on) and the mesh's own,
    through version 6 and back: the same integers and triangles, and the same as version 5
    decodes to."""
    points, triangles = mesh()
    rng = np.random.default_rng(bits)
    top = (1 << bits) - 1
    for codes in (rng.integers(0, top + 1, (len(points), 3)),
                  np.rint((points - points.min(0)) / np.ptp(points, axis=0) * top)):
        mesh_codes = ControlMeshCodes([tuple(map(int, c)) for c in codes], triangles.tolist(),
                                      bits, (0.0, -1.0, 2.0), (1.0, 1.0, 2.0), {"n": 1})
        v6 = read_control_codes(write_control_codes(mesh_codes))
        order, expected = canonical_control_mesh(len(points), traversal_order(triangles))
        assert v6.triangles == expected and v6.metadata == {"n": 1}
        assert v6.codes == [mesh_codes.codes[v] for v in order]
        assert (v6.lows, v6.highs) == ((0.0, -1.0, 2.0), (1.0, 1.0, 2.0))
        assert read_control_codes(write_control_codes(mesh_codes, 5)) == v6
        assert write_control_codes(v6) == write_control_codes(mesh_codes)  # a file's own order


def test_a_version_5_file_still_reads_as_written():
    """Session 30's version-5 file: the same bytes from the version-5 writer, and the same
    mesh as its version-6 file."""
    data = V5_FIXTURE.read_bytes()
    points, triangles = two_pieces()
    assert write_control_mesh(points, triangles, 12, {"units": "mm"}, version=5) == data
    old = read_control_codes(data)
    assert read_control_header(data)["version"] == 5 and old.metadata == {"units": "mm"}
    new = write_control_codes(old)
    assert read_control_header(new)["version"] == 6 and len(new) < len(data)
    assert read_control_codes(new) == old
    assert read_atlas(data)[0].vertices == read_atlas(new)[0].vertices


def test_version_6_is_smaller_than_version_5_on_smooth_meshes():
    """The point and triangle coders pay: on a decimated-like bumpy sphere (2,000 points,
    3,996 triangles, 12 bits) version 6 took 6,995 bytes against version 5's 8,483 (0.825;
    the fitted bases of session 31: 0.779-0.921, docs/benchmarks.md); on a regular
    icosphere, whose parallelograms are near exact and whose triangles are mostly C and R,
    4,270 against 8,266 (0.517)."""
    points, triangles = bumpy_sphere(2000)
    v5 = len(write_control_mesh(points, triangles, 12, version=5))
    v6 = len(write_control_mesh(points, triangles, 12))
    assert v6 < 0.85 * v5
    ico = trimesh.creation.icosphere(4, 3.0)
    v5 = len(write_control_mesh(ico.vertices, ico.faces, 12, version=5))
    v6 = len(write_control_mesh(ico.vertices, ico.faces, 12))
    assert v6 < 0.55 * v5


def test_the_point_order_grows_from_the_most_known_ring():
    """Each point is, of those not coded yet, the one with the largest share of its ring
    coded (``floor(64 k / d)``, ties to the lowest number), or with none coded anywhere the
    lowest-numbered; its neighbours and parallelograms' corners are coded before it, and
    the order is a permutation (points in no triangle included)."""
    points, triangles = open_caps()
    order, tris = canonical_control_mesh(len(points), traversal_order(triangles))
    steps = point_predictors(len(points), tris)
    ring: dict[int, set[int]] = {v: set() for v in range(len(points))}
    for t in tris:
        for k in range(3):
            ring[t[k]] |= {t[k - 1], t[k - 2]}
    seen: set[int] = set()
    used = {v for t in tris for v in t}
    for v, earlier, ab, c_s, prev in steps:
        assert set(earlier) <= seen and set(ab) <= seen and set(c_s) <= seen
        assert set(earlier) == ring[v] & seen
        assert len(ab) == 2 * len(c_s) and set(ab) <= set(earlier)
        shares = {u: 64 * len(ring[u] & seen) // len(ring[u])
                  for u in set(ring) - seen if ring[u] & seen}
        if shares:
            assert v == min(shares, key=lambda u: (-shares[u], u))
        else:
            assert v == min(set(range(len(points))) - seen)
        assert prev == (-1 if not seen else steps[len(seen) - 1][0])
        seen.add(v)
    assert [s[0] for s in steps] == point_order(len(points), tris)
    assert sorted(seen) == list(range(len(points))) and len(used) < len(points)


def test_read_atlas_draws_the_control_meshs_smooth_atlas():
    points, triangles = icosphere()
    data = write_control_mesh(points, triangles, 14)
    atlas, metadata = read_atlas(data)
    got, tris, _ = read_control_mesh(data)
    expected = smooth_atlas(got, tris)
    assert atlas.quads == expected.quads and atlas.vertices == expected.vertices
    assert atlas.face_points == expected.face_points and metadata == {}


def test_the_traversal_makes_the_connectivity_small():
    # a depth-first walk across edges: each triangle shares an edge with one just before it
    points, triangles = icosphere()
    shuffled = triangles[np.random.default_rng(0).permutation(len(triangles))]
    walked = traversal_order(shuffled)
    edges = {frozenset(e) for t in walked[:1] for e in ((t[0], t[1]), (t[1], t[2]))}
    shared = 0
    for t in walked[1:]:
        shared += frozenset((t[0], t[1])) in edges  # reached across its first edge
        edges |= {frozenset((t[0], t[1])), frozenset((t[1], t[2])), frozenset((t[2], t[0]))}
    assert shared == len(walked) - 1  # one piece: every triangle after the first
    assert sorted(map(sorted, walked)) == sorted(map(sorted, shuffled.tolist()))


def _with_header(data: bytes, **fields) -> bytes:
    names = ["magic", "version", "flags", "degree", "spans", "bits", "reserved", "points",
             "triangles", "size", "raw"]
    values = dict(zip(names, HEADER.unpack(data[:HEADER.size]), strict=True))
    values.update(fields)
    body = HEADER.pack(*values.values()) + data[HEADER.size:-4]
    return body + struct.pack("<I", zlib.crc32(body) & 0xFFFFFFFF)


@pytest.mark.parametrize(("version", "fields", "offset", "match"), [
    *[(version, fields, offset, match) for version in (5, 6) for fields, offset, match in [
        ({"flags": 1}, 6, "unknown flags"),
        ({"degree": 2}, 8, "degree 2"),
        ({"spans": 2}, 9, "spans = 2"),
        ({"bits": 1}, 10, "bits = 1"),
        ({"points": 2}, 12, "2 points"),
        ({"triangles": MAX_TRIANGLES + 1}, 16, "triangles"),
        ({"raw": 10}, 24, "payload size 10"),
    ]],
    (5, {"reserved": WEIGHT_STEPS + 1}, 11, "reserved byte is 9, must be 0"),
    (6, {"reserved": WEIGHT_STEPS + 1}, 11, "parallelogram weight 9/8 above 1"),
])
def test_a_bad_header_field_is_named_at_its_offset(version, fields, offset, match):
    points, triangles = icosphere()
    data = _with_header(write_control_mesh(points, triangles, version=version), **fields)
    with pytest.raises(PatchFormatError, match=match) as info:
        read_control_mesh(data)
    assert info.value.offset == offset


def test_version_5_has_no_weight_and_no_other_version_is_read():
    points, triangles = icosphere()
    with pytest.raises(PatchFormatError, match="reserved byte is 3") as info:
        read_control_mesh(_with_header(write_control_mesh(points, triangles, version=5),
                                       reserved=3))
    assert info.value.offset == 11
    for version in (4, 7):
        with pytest.raises(PatchFormatError, match=rf"version {version} is not supported "
                           r"\(this reader: 5, 6\)"):
            read_control_mesh(_with_header(write_control_mesh(points, triangles),
                                           version=version))
    with pytest.raises(ValueError, match="version must be one of"):
        write_control_mesh(points, triangles, version=4)


@pytest.mark.parametrize("version", [5, 6])
def test_cut_extended_or_flipped_files_are_refused(version):
    points, triangles = grid()
    data = write_control_mesh(points, triangles, version=version)
    for bad in (data[:-1], data + b"\0", data[:40], bytes([data[0] ^ 1]) + data[1:]):
        with pytest.raises(PatchFormatError):
            read_atlas(bad)
    flipped = bytearray(data)
    flipped[len(data) // 2] ^= 0x10
    with pytest.raises(PatchFormatError, match="CRC"):
        read_control_mesh(bytes(flipped))


def _with_stream(data: bytes, stream: bytes) -> bytes:
    """``data`` with its range-coded stream replaced, the CRC made anew."""
    start = HEADER.size + read_control_header(data)["payload_size"]
    body = data[:start] + stream
    return body + struct.pack("<I", zlib.crc32(body) & 0xFFFFFFFF)


@pytest.mark.parametrize("version", [5, 6])
def test_a_coded_stream_that_decodes_to_no_mesh_is_refused(version):
    points, triangles = grid()
    data = write_control_mesh(points, triangles, version=version)
    for garbage in (b"\xff" * 8, bytes(range(256)) * 4):
        with pytest.raises(PatchFormatError):
            read_control_mesh(_with_stream(data, garbage))


def _points_stream(triangles, residuals, bits: int) -> bytes:
    """A version-6 stream of the canonical ``triangles`` and then the three axes'
    ``residuals``, as the writer codes them (whatever they decode to)."""
    from client_py.control_mesh import _code_point_residuals, _PointModel

    enc = RangeEncoder()
    encode_triangles(enc, 1 + max(map(max, triangles)), triangles)
    model = _PointModel()
    for axis in residuals:
        _code_point_residuals(enc, axis, model)
    return enc.finish()


def test_version_6_residuals_too_long_or_out_of_range_are_refused():
    points, triangles = grid(4)
    data = write_control_mesh(points, triangles, 8)
    tris = read_control_codes(data).triangles
    n = len(points)
    with pytest.raises(PatchFormatError, match="axis x: residual 0 longer than 8 bits"):
        read_control_mesh(_with_stream(data, _points_stream(tris, [[256] * n] * 3, 8)))
    with pytest.raises(PatchFormatError, match="axis y decode outside 0..255"):
        read_control_mesh(_with_stream(data, _points_stream(tris, [[0] * n, [-1] * n,
                                                                   [0] * n], 8)))
    with pytest.raises(PatchFormatError, match="ends early"):
        read_control_mesh(_with_stream(data, _points_stream(tris, [[3] * n] * 2, 8)[:-3]))


@cache
def _small_file(version: int) -> bytes:
    points, triangles = open_caps()
    keep = np.unique(triangles[:60])  # a few dozen triangles: fast to fuzz
    new = {v: k for k, v in enumerate(keep)}
    return write_control_mesh(points[keep], [[new[v] for v in t] for t in triangles[:60]],
                              10, {"units": "m"}, version=version)


@pytest.mark.parametrize("version", [5, 6])
@FUZZ
@given(st.data())
def test_fuzzed_truncation_is_refused(version, data):
    file = _small_file(version)
    with pytest.raises(PatchFormatError):
        read_atlas(file[: data.draw(st.integers(0, len(file) - 1))])


@pytest.mark.parametrize("version", [5, 6])
@FUZZ
@given(st.data())
def test_fuzzed_coded_streams_with_a_valid_crc_read_or_are_refused(version, data):
    """Bit flips, cuts and insertions in the range-coded stream, the CRC made anew: a
    control mesh or a PatchFormatError, in bounded time, never anything else."""
    file = _small_file(version)
    start = HEADER.size + read_control_header(file)["payload_size"]
    stream = bytearray(file[start:-4])
    for _ in range(data.draw(st.integers(1, 4))):
        kind = data.draw(st.sampled_from(["flip", "cut", "insert"]))
        at = data.draw(st.integers(0, len(stream)))
        if kind == "flip" and at < len(stream):
            stream[at] ^= 1 << data.draw(st.integers(0, 7))
        elif kind == "cut":
            del stream[at : at + data.draw(st.integers(1, 16))]
        else:
            stream[at:at] = data.draw(st.binary(min_size=1, max_size=16))
    try:
        points, triangles, _ = read_control_mesh(_with_stream(file, bytes(stream)))
    except PatchFormatError:
        return
    assert len(points) == read_control_header(file)["points"] and triangles


@pytest.mark.parametrize("version", [5, 6])
@FUZZ
@given(st.binary(min_size=HEADER.size - 6, max_size=HEADER.size - 6))
def test_fuzzed_headers_with_a_valid_crc_read_or_are_refused(version, head):
    file = _small_file(version)
    body = file[:4] + struct.pack("<H", version) + head + file[HEADER.size:-4]
    try:
        read_atlas(body + struct.pack("<I", zlib.crc32(body) & 0xFFFFFFFF))
    except PatchFormatError:
        pass


@pytest.mark.parametrize(("points", "triangles", "bits", "match"), [
    (np.eye(4, 3), [(0, 1, 2), (0, 1, 3)], 12, "edge|manifold|orient"),
    (np.full((3, 3), np.nan), [(0, 1, 2)], 12, "finite"),
    (np.zeros((3, 2)), [(0, 1, 2)], 12, "3 coordinates"),
    (np.zeros((3, 3)), [(0, 1, 5)], 12, "5|range|index"),
    (np.zeros((3, 3)), [(0, 1, 2)], 1, "bits"),
    (np.zeros((3, 3)), [], 12, "triangles"),
])
def test_the_writer_refuses_what_is_no_control_mesh(points, triangles, bits, match):
    with pytest.raises(ValueError, match=match):
        write_control_mesh(points, triangles, bits)


def test_four_triangles_on_one_edge_are_refused():
    points = np.random.default_rng(1).standard_normal((6, 3))
    triangles = [(0, 1, 2), (1, 0, 3), (0, 1, 4), (1, 0, 5)]
    with pytest.raises(ValueError, match="edge"):
        write_control_mesh(points, triangles)


def torus() -> tuple[np.ndarray, np.ndarray]:
    mesh = trimesh.creation.torus(2.0, 0.5, 16, 8)  # genus 1: Edgebreaker's S with offsets
    return np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64)


def _shared_points() -> list[tuple[int, int, int]]:
    """A bow tie (two fans at point 0) and a third piece on points of the first two."""
    return [(0, 1, 2), (0, 3, 4), (2, 5, 3), (1, 6, 7)]


def _rotations(triangles) -> set[tuple[int, ...]]:
    return {tuple(t[r:] + t[:r]) for t in map(list, triangles) for r in range(3)}


@pytest.mark.parametrize("triangles", [
    icosphere()[1], grid()[1], two_pieces()[1], open_caps()[1], torus()[1],
    np.array(_shared_points()), np.array(_shared_points()[::-1])])
def test_the_triangle_coder_round_trips_borders_handles_and_shared_points(triangles):
    """Holes, several pieces, a handle and points shared by fans and pieces: decoded as
    encoded, the same triangles renumbered, in traversal_order numbered canonically."""
    n = 1 + int(triangles.max()) + 2  # two points in no triangle, numbered last
    enc = RangeEncoder()
    order, coded = encode_triangles(enc, n, triangles.tolist())
    decoded = decode_triangles(RangeDecoder(enc.finish()), len(triangles), n, 0)
    assert decoded == coded and sorted(order) == list(range(n)) and order[-2:] == [n - 2, n - 1]
    renumbered = [tuple(order[v] for v in t) for t in decoded]
    assert _rotations(renumbered) == _rotations(triangles.tolist())
    assert (order, coded) == canonical_control_mesh(n, traversal_order(triangles))


def strip(n: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """A strip of ``2 n`` triangles on 2 rows of ``n + 1`` points: every triangle but the
    two ends is a bridge (the strip falls apart without it)."""
    x = np.arange(n + 1, dtype=float)
    points = np.concatenate([np.stack([x, 0 * x, np.sin(x)], 1), np.stack([x, 1 + 0 * x,
                                                                            np.cos(x)], 1)])
    tris = []
    for j in range(n):
        a, b, c, d = j, j + 1, n + 2 + j, n + 1 + j
        tris += [(a, b, c), (a, c, d)]
    return points, np.array(tris)


def _shuffled(triangles, rng) -> list[tuple[int, int, int]]:
    """``triangles`` in a random order, each from a random corner."""
    out = [tuple(np.roll(t, -rng.integers(3)).tolist()) for t in triangles]
    return [out[k] for k in rng.permutation(len(out))]


def _bridge_first(triangles) -> list[tuple[int, int, int]]:
    t = [tuple(map(int, x)) for x in triangles]
    return t[len(t) // 2 :] + t[: len(t) // 2]


@pytest.mark.parametrize("mesh", [strip, grid, two_pieces, open_caps, torus])
def test_versions_5_and_6_hold_any_triangle_order_alike(mesh):
    """Triangles in any order (shuffled, from any corner; a strip from its middle, a
    bridge): the coder's own order and numbering are traversal_order's, numbered
    canonically, and versions 5 and 6 decode to the same triangles and codes."""
    points, triangles = mesh()
    rng = np.random.default_rng(5)
    top = (1 << 10) - 1
    codes = [tuple(map(int, c)) for c in rng.integers(0, top + 1, (len(points), 3))]
    orders = [_bridge_first(triangles)] + [_shuffled(triangles, rng) for _ in range(12)]
    for ordered in orders:
        expected = canonical_control_mesh(len(points), traversal_order(ordered))
        assert encode_triangles(RangeEncoder(), len(points), ordered) == expected
        mesh_codes = ControlMeshCodes(codes, ordered, 10, (0.0,) * 3, (1.0,) * 3, {})
        v6 = read_control_codes(write_control_codes(mesh_codes))
        v5 = read_control_codes(write_control_codes(mesh_codes, 5))
        assert v6 == v5 and v6.triangles == expected[1]
        assert v6.codes == [codes[v] for v in expected[0]]
        assert read_control_codes(write_control_codes(v6, 5)) == v6


def test_the_triangle_coder_takes_under_two_bits_a_triangle_and_a_fifth_on_a_regular_mesh():
    """Version 5's coder took 3.3-3.9 bits a triangle on the fitted bases; this one
    1.3-2.1 (docs/benchmarks.md, session 31). Measured: the decimated-like bumpy sphere
    1.69 bits a triangle; a subdivided icosphere, mostly C and R, 0.10."""
    points, triangles = bumpy_sphere(2000)
    enc = RangeEncoder()
    encode_triangles(enc, len(points), triangles.tolist())
    assert 8 * len(enc.finish()) < 1.9 * len(triangles)
    mesh = trimesh.creation.icosphere(4)
    enc = RangeEncoder()
    encode_triangles(enc, len(mesh.vertices), mesh.faces.tolist())
    assert 8 * len(enc.finish()) < 0.2 * len(mesh.faces)


@pytest.mark.parametrize(("n_points", "match"), [(5, "more than the 5 points")])
def test_a_triangle_stream_beyond_its_points_is_refused(n_points, match):
    triangles = icosphere()[1][:10]
    enc = RangeEncoder()
    _, coded = encode_triangles(enc, 1 + int(triangles.max()), triangles.tolist())
    with pytest.raises(PatchFormatError, match=match) as info:
        decode_triangles(RangeDecoder(enc.finish()), len(coded), n_points, 99)
    assert info.value.offset == 99


@FUZZ
@given(st.binary(min_size=4, max_size=600), st.integers(1, 400), st.integers(3, 300))
def test_fuzzed_triangle_streams_decode_or_are_refused(stream, n_tris, n_points):
    """Any bytes, any counts: triangles with distinct corners in range, each directed edge
    once, or a PatchFormatError or RangeDecodeError, in bounded time."""
    try:
        tris = decode_triangles(RangeDecoder(stream), n_tris, n_points, 7)
    except (PatchFormatError, RangeDecodeError):
        return
    assert len(tris) == n_tris
    assert all(0 <= v < n_points for t in tris for v in t)
    assert all(len(set(t)) == 3 for t in tris)
    edges = [(t[i], t[(i + 1) % 3]) for t in tris for i in range(3)]
    assert len(set(edges)) == len(edges)
