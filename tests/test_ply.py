"""write_ply: round trips through trimesh, the byte layout, and the header and ASCII
tokenisation that 3DHOP 4.3's loader (js/ply.js) needs."""

from __future__ import annotations

import io
import re
from array import array

import numpy as np
import pytest
import trimesh
from conftest import PROJECT_ROOT
from nurbs_cases import random_surface

from client_py import Mesh, NurbsSurface, TrimMask, tessellate_grid, write_ply
from client_py.ply import write_points_ply

PLY_JS = PROJECT_ROOT.parent / "shared" / "vendor" / "3dhop-4.3" / "js" / "ply.js"


def sample_mesh(colors: bool = True, trimmed: bool = False) -> Mesh:
    s = random_surface(np.random.default_rng(3), 2, 2, 5, 6)
    if trimmed:
        s = NurbsSurface(s.degree, s.knots, s.control_points, s.weights,
                         trim=TrimMask([[1, 0], [1, 1]]))
    mesh = tessellate_grid(s, 7, 9)
    if colors:
        rng = np.random.default_rng(4)
        mesh.colors = array("B", rng.integers(0, 256, 3 * mesh.vertex_count).tolist())
    return mesh


def split_header(data: bytes) -> tuple[list[str], bytes]:
    end = data.index(b"end_header\n") + len(b"end_header\n")
    return data[:end].decode("ascii").splitlines(), data[end:]


def load(data: bytes) -> trimesh.Trimesh:
    return trimesh.load(io.BytesIO(data), file_type="ply", process=False, fix_texture=False)


def expected_header(mesh: Mesh, fmt: str, extra: list[str], uvs: bool) -> list[str]:
    lines = ["ply", f"format {fmt} 1.0", "comment written by Tessera client_py", *extra,
             f"element vertex {mesh.vertex_count}"]
    lines += [f"property float {n}" for n in ("x", "y", "z", "nx", "ny", "nz")]
    if uvs:
        lines += ["property float texture_u", "property float texture_v"]
    if mesh.colors is not None:
        lines += ["property uchar red", "property uchar green", "property uchar blue"]
    return lines + [f"element face {mesh.triangle_count}", "property list uchar int vertex_indices",
                    "end_header"]


@pytest.mark.parametrize("binary", [True, False])
@pytest.mark.parametrize("colors", [True, False])
def test_round_trip_through_trimesh(binary, colors):
    mesh = sample_mesh(colors=colors, trimmed=True)
    data = write_ply(mesh, binary=binary, texture_file="relief_tex.png",
                     comments=["units mm", "two\nlines"])
    header, _ = split_header(data)
    fmt = "binary_little_endian" if binary else "ascii"
    assert header == expected_header(
        mesh, fmt, ["comment units mm", "comment two lines", "comment TextureFile relief_tex.png"],
        uvs=True)
    tm = load(data)
    pos = np.array(mesh.positions, dtype=np.float32).reshape(-1, 3)
    assert tm.vertices.shape == (mesh.vertex_count, 3)
    assert np.array_equal(tm.vertices, pos)  # float32 exactly, ASCII too (9 digits)
    assert np.array_equal(tm.faces, np.array(mesh.indices).reshape(-1, 3))
    assert np.array_equal(tm.vertex_normals, np.array(mesh.normals, np.float32).reshape(-1, 3))
    # trimesh reads uvs per face corner: vertices no triangle uses (trimmed) come back 0
    used = np.unique(np.array(mesh.indices))
    assert len(used) < mesh.vertex_count
    assert np.array_equal(tm.visual.uv[used], np.array(mesh.uvs, np.float32).reshape(-1, 2)[used])
    raw = tm.metadata["_ply_raw"]["vertex"]["data"]
    if colors:
        rgb = np.column_stack([raw["red"], raw["green"], raw["blue"]])
        assert np.array_equal(rgb, np.array(mesh.colors).reshape(-1, 3))
    else:
        assert "red" not in (raw.keys() if isinstance(raw, dict) else raw.dtype.names)


def test_no_texture_no_uvs():
    """Without a texture the header has no texture_u/v: 3DHOP would sample an unbound
    texture wherever u != 0 and draw those vertices black."""
    mesh = sample_mesh(colors=False)
    for binary in (True, False):
        header, _ = split_header(write_ply(mesh, binary=binary))
        fmt = "binary_little_endian" if binary else "ascii"
        assert header == expected_header(mesh, fmt, [], uvs=False)
    tm = load(write_ply(mesh))
    assert np.array_equal(tm.vertices, np.array(mesh.positions, np.float32).reshape(-1, 3))


@pytest.mark.parametrize("texture", [None, "t.png"])
def test_binary_layout(texture):
    mesh = sample_mesh()
    header, body = split_header(write_ply(mesh, texture_file=texture))
    floats = ("x", "y", "z", "nx", "ny", "nz") + (("u", "v") if texture else ())
    vertex = np.dtype([(n, "<f4") for n in floats] + [(c, "u1") for c in "rgb"])
    face = np.dtype([("count", "u1"), ("idx", "<i4", 3)])
    n, m = mesh.vertex_count, mesh.triangle_count
    assert len(body) == n * vertex.itemsize + m * 13
    verts = np.frombuffer(body[: n * vertex.itemsize], vertex)
    faces = np.frombuffer(body[n * vertex.itemsize :], face)
    assert np.array_equal(np.column_stack([verts["x"], verts["y"], verts["z"]]).ravel(),
                          np.array(mesh.positions, np.float32))
    if texture:
        assert np.array_equal(np.column_stack([verts["u"], verts["v"]]).ravel(),
                              np.array(mesh.uvs, np.float32))
    assert np.array_equal(np.column_stack([verts[c] for c in "rgb"]).ravel(),
                          np.array(mesh.colors))
    assert (faces["count"] == 3).all()
    assert np.array_equal(faces["idx"].ravel(), np.array(mesh.indices))


def js_parse_float(token: str) -> float:
    """JavaScript's parseFloat: skip leading whitespace, read the longest number prefix."""
    match = re.match(r"\s*([+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?)", token)
    return float(match.group(1)) if match else float("nan")


def test_ascii_body_reads_with_3dhops_tokenisation():
    """ply.js reads an ASCII body as ``text.split(" ")`` and parseFloat/parseInt per value:
    only spaces separate values, so every line must end with one before its newline."""
    mesh = sample_mesh()
    _, body = split_header(write_ply(mesh, binary=False, texture_file="t.png"))
    tokens = body.decode("ascii").split(" ")
    n, m = mesh.vertex_count, mesh.triangle_count
    per_vertex = 11
    values = [js_parse_float(t) for t in tokens[: n * per_vertex + 4 * m]]
    verts = np.array(values[: n * per_vertex]).reshape(n, per_vertex)
    assert np.array_equal(verts[:, :3].astype(np.float32).ravel(),
                          np.array(mesh.positions, np.float32))
    assert np.array_equal(verts[:, 6:8].astype(np.float32).ravel(),
                          np.array(mesh.uvs, np.float32))
    assert np.array_equal(verts[:, 8:].ravel(), np.array(mesh.colors))
    faces = np.array(values[n * per_vertex :]).reshape(m, 4)
    assert (faces[:, 0] == 3).all()
    assert np.array_equal(faces[:, 1:].ravel(), np.array(mesh.indices))


@pytest.mark.skipif(not PLY_JS.is_file(), reason=f"3DHOP's loader not found at {PLY_JS}")
def test_header_uses_what_3dhops_loader_reads():
    """The property names and types we write are the ones js/ply.js looks up and maps to
    float32 / uint8, and the texture comes from a 'comment TextureFile' header line."""
    js = PLY_JS.read_text()
    for name in ("x", "nx", "texture_u", "texture_v", "red", "vertex_indices"):
        assert f'props["{name}"]' in js
    assert re.search(r'"float"\s*:\s*"float32"', js) and re.search(r'"uchar"\s*:\s*"uint8"', js)
    assert 'info.comments[i][0]=="TextureFile"' in js
    assert "binary_little_endian" in js
    header, _ = split_header(write_ply(sample_mesh(), texture_file="t.png"))
    assert "comment TextureFile t.png" in header
    assert "property list uchar int vertex_indices" in header


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (lambda m: setattr(m, "normals", m.normals[:-3]), r"mesh.normals has \d+ values"),
        (lambda m: setattr(m, "uvs", m.uvs[:-1]), r"mesh.uvs has"),
        (lambda m: setattr(m, "colors", array("B", [0, 0, 0])), r"mesh.colors has 3 values"),
        (lambda m: setattr(m, "indices", m.indices[:-1]), "not a multiple of 3"),
        (lambda m: m.indices.__setitem__(0, 10**6), "refers to vertex 1000000 of 63"),
    ],
)
def test_inconsistent_mesh_is_rejected(change, match):
    mesh = sample_mesh()
    change(mesh)
    with pytest.raises(ValueError, match=match):
        write_ply(mesh)


@pytest.mark.parametrize("name", ["", "my texture.png", " t.png", "t.png\n", "a\tb"])
def test_texture_file_must_be_one_word(name):
    with pytest.raises(ValueError, match="texture_file must be a file name without whitespace"):
        write_ply(sample_mesh(), texture_file=name)


def test_not_a_mesh():
    with pytest.raises(ValueError, match="mesh must be a Mesh, got str"):
        write_ply("mesh")


# ----------------------------------------------------------------- point clouds, extra properties
def sample_cloud(n: int = 500):
    rng = np.random.default_rng(9)
    positions = rng.normal(size=(n, 3)).astype(np.float32) * 100
    colors = rng.integers(0, 256, (n, 3)).astype(np.uint8)
    quality = rng.normal(size=n).astype(np.float32)
    return positions, colors, quality


@pytest.mark.parametrize("binary", [True, False])
def test_point_cloud_round_trip_through_trimesh(binary):
    positions, colors, quality = sample_cloud()
    data = write_points_ply(positions, colors, {"quality": quality}, binary=binary,
                            comments=["units mm"])
    header, _ = split_header(data)
    fmt = "binary_little_endian" if binary else "ascii"
    assert header == ["ply", f"format {fmt} 1.0", "comment written by Tessera client_py",
                      "comment units mm", "element vertex 500", "property float x",
                      "property float y", "property float z", "property uchar red",
                      "property uchar green", "property uchar blue", "property float quality",
                      "end_header"]
    cloud = trimesh.load(io.BytesIO(data), file_type="ply", process=False)
    assert np.array_equal(cloud.vertices, positions)
    raw = cloud.metadata["_ply_raw"]["vertex"]["data"]
    assert np.array_equal(np.column_stack([raw["red"], raw["green"], raw["blue"]]), colors)
    assert np.array_equal(np.ravel(raw["quality"]), quality)  # trimesh's ASCII reader: (n, 1)


def test_point_cloud_binary_layout_and_every_input_type_give_the_same_bytes():
    positions, colors, quality = sample_cloud()
    data = write_points_ply(positions, colors, {"quality": quality})
    _, body = split_header(data)
    record = np.dtype([("p", "<f4", 3), ("c", "u1", 3), ("q", "<f4")])
    expected = np.empty(len(positions), record)
    expected["p"], expected["c"], expected["q"] = positions, colors, quality
    assert body == expected.tobytes()
    same = [
        write_points_ply(array("f", positions.ravel().tolist()), array("B", colors.ravel()),
                         {"quality": array("f", quality.tolist())}),
        write_points_ply(positions.astype(np.float64), colors.astype(np.int64),
                         {"quality": quality.astype(np.float64)}),
        write_points_ply(np.asfortranarray(positions), colors.tolist() and colors.ravel(),
                         {"quality": quality.astype(">f4")}),
        write_points_ply(positions.ravel().tolist(), colors.ravel().tolist(),
                         {"quality": quality.tolist()}),
    ]
    for other in same:
        assert other == data


def test_points_without_colours_and_an_empty_cloud():
    positions, _, _ = sample_cloud(4)
    header, body = split_header(write_points_ply(positions))
    assert header[-4:] == ["property float x", "property float y", "property float z",
                           "end_header"]
    assert body == positions.astype("<f4").tobytes()
    header, body = split_header(write_points_ply(np.zeros((0, 3), np.float32)))
    assert "element vertex 0" in header and body == b""


def test_mesh_extra_properties_follow_the_3dhop_layout():
    mesh = sample_mesh()
    quality = np.arange(mesh.vertex_count, dtype=np.float32) / 7
    data = write_ply(mesh, properties={"quality": quality})
    header, body = split_header(data)
    assert header[:-4] == expected_header(mesh, "binary_little_endian", [], uvs=False)[:-3]
    assert header[-4:] == ["property float quality", f"element face {mesh.triangle_count}",
                           "property list uchar int vertex_indices", "end_header"]
    plain_header, plain_body = split_header(write_ply(mesh))
    n = mesh.vertex_count
    vertex = np.dtype([("v", "V27"), ("q", "<f4")])  # the 3DHOP record, then quality
    verts = np.frombuffer(body[: n * vertex.itemsize], vertex)
    plain = np.frombuffer(plain_body[: n * 27], "V27")
    assert np.array_equal(verts["v"], plain) and np.array_equal(verts["q"], quality)
    assert body[n * vertex.itemsize :] == plain_body[n * 27 :]  # the faces unchanged
    tm = load(data)
    assert np.array_equal(tm.metadata["_ply_raw"]["vertex"]["data"]["quality"], quality)


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda p, c, q: write_points_ply(p.ravel()[:-2]), "positions has 1498 values, "
                                                           "not a multiple of 3"),
        (lambda p, c, q: write_points_ply(p, c[:-1]), r"colors has 1497 values; 500 vertices "
                                                      r"need 1500"),
        (lambda p, c, q: write_points_ply(p, c.astype(np.int64) + 200), "colors must be "
                                                                         "0..255 integer"),
        (lambda p, c, q: write_points_ply(p, c.astype(np.float32)), "colors must be 0..255"),
        (lambda p, c, q: write_points_ply(p, c, {"quality": q[:-1]}),
         r"properties\['quality'\] has 499 values; 500 vertices need 500"),
        (lambda p, c, q: write_points_ply(p, c, {"two words": q}),
         "property name must be an ASCII identifier, got 'two words'"),
        (lambda p, c, q: write_points_ply(p, c, {"red": q}), "'red' is already written"),
        (lambda p, c, q: write_points_ply(p, c, [("quality", q)]),
         "properties must map names to values, got list"),
        (lambda p, c, q: write_points_ply(p.astype(np.float16)), "positions must hold numbers, "
                                                                 "got buffer format 'e'"),
        (lambda p, c, q: write_points_ply(["x"] * 3), "positions must be float32 values"),
    ],
)
def test_bad_point_clouds_are_rejected(call, match):
    with pytest.raises(ValueError, match=match):
        call(*sample_cloud())
