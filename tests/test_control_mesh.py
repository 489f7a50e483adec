"""``.tsa`` version 5, a smooth base's control mesh (client_py.control_mesh): round trips,
the reader's atlas, and every refusal."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest
import trimesh

from client_py.atlas_format import HEADER, read_atlas
from client_py.control_mesh import (
    MAX_TRIANGLES,
    canonical_control_mesh,
    read_control_header,
    read_control_mesh,
    traversal_order,
    write_control_mesh,
)
from client_py.errors import PatchFormatError
from client_py.smooth_base import smooth_atlas


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


@pytest.mark.parametrize("mesh", [icosphere, grid, two_pieces])
@pytest.mark.parametrize("bits", [8, 12, 16])
def test_a_control_mesh_reads_back_within_half_a_step(mesh, bits):
    points, triangles = mesh()
    data = write_control_mesh(points, triangles, bits, {"units": "mm"})
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


@pytest.mark.parametrize(("fields", "offset", "match"), [
    ({"flags": 1}, 6, "unknown flags"),
    ({"degree": 2}, 8, "degree 2"),
    ({"spans": 2}, 9, "spans = 2"),
    ({"bits": 1}, 10, "bits = 1"),
    ({"reserved": 3}, 11, "reserved"),
    ({"points": 2}, 12, "2 points"),
    ({"triangles": MAX_TRIANGLES + 1}, 16, "triangles"),
    ({"raw": 10}, 24, "payload size 10"),
])
def test_a_bad_header_field_is_named_at_its_offset(fields, offset, match):
    points, triangles = icosphere()
    data = _with_header(write_control_mesh(points, triangles), **fields)
    with pytest.raises(PatchFormatError, match=match) as info:
        read_control_mesh(data)
    assert info.value.offset == offset


def test_cut_extended_or_flipped_files_are_refused():
    points, triangles = grid()
    data = write_control_mesh(points, triangles)
    for bad in (data[:-1], data + b"\0", data[:40], bytes([data[0] ^ 1]) + data[1:]):
        with pytest.raises(PatchFormatError):
            read_atlas(bad)
    flipped = bytearray(data)
    flipped[len(data) // 2] ^= 0x10
    with pytest.raises(PatchFormatError, match="CRC"):
        read_control_mesh(bytes(flipped))


def test_a_coded_stream_that_decodes_to_no_mesh_is_refused():
    points, triangles = grid()
    data = write_control_mesh(points, triangles)
    head = read_control_header(data)
    start = HEADER.size + head["payload_size"]
    for garbage in (b"\xff" * 8, bytes(range(256)) * 4):
        body = data[:start] + garbage
        bad = body + struct.pack("<I", zlib.crc32(body) & 0xFFFFFFFF)
        with pytest.raises(PatchFormatError):
            read_control_mesh(bad)


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
