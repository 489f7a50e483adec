"""Tests of fitter.fitting.io: every format round-tripped from files written here, real
scans, bad input.

References are independent of the readers under test: files are written with
numpy/struct/plain text (or trimesh's exporters), digests with hashlib, the
.conf rotation with scipy's Rotation, thinning against a per-voxel Python loop.
"""

from __future__ import annotations

import gzip
import hashlib
import struct
from pathlib import Path

import numpy as np
import pytest

import fitter.fitting.io.ply as ply_module
from fitter.fitting.io import SUPPORTED_EXTENSIONS, Scan, ScanError, load_scan, voxel_thin_indices
from fitter.fitting.io.conf import quaternion_matrix

RNG = np.random.default_rng(7)


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def write_binary_ply(path: Path, records: np.ndarray, fmt: str = "binary_little_endian",
                     comments: tuple[str, ...] = (), extra: bytes = b"",
                     elements: str = "") -> None:
    """A vertex-only PLY whose properties are the fields of ``records`` (written here)."""
    names = {"f4": "float", "f8": "double", "u1": "uchar", "i4": "int", "u2": "ushort"}
    lines = ["ply", f"format {fmt} 1.0", *[f"comment {c}" for c in comments],
             f"element vertex {len(records)}"]
    lines += [f"property {names[records.dtype[f].str[1:]]} {f}" for f in records.dtype.names]
    header = ("\n".join(lines) + "\n" + elements + "end_header\n").encode()
    path.write_bytes(header + records.tobytes() + extra)


def cloud_records(n: int, order: str = "<") -> np.ndarray:
    dtype = np.dtype([("x", order + "f4"), ("y", order + "f4"), ("z", order + "f4"),
                      ("nx", order + "f4"), ("ny", order + "f4"), ("nz", order + "f4"),
                      ("red", "u1"), ("green", "u1"), ("blue", "u1"),
                      ("confidence", order + "f4")])
    rec = np.zeros(n, dtype)
    for k in "xyz":
        rec[k] = RNG.normal(size=n) * 100
    normals = RNG.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    rec["nx"], rec["ny"], rec["nz"] = normals.T
    for k in ("red", "green", "blue"):
        rec[k] = RNG.integers(0, 256, n)
    rec["confidence"] = RNG.uniform(size=n)
    return rec


def xyz_of(rec: np.ndarray) -> np.ndarray:
    return np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(np.float64)


# ---------------------------------------------------------------- PLY


@pytest.mark.parametrize("order,fmt", [("<", "binary_little_endian"), (">", "binary_big_endian")])
def test_binary_ply_point_cloud_memmap(tmp_path, order, fmt):
    rec = cloud_records(500, order)
    path = tmp_path / "cloud.ply"
    write_binary_ply(path, rec, fmt, comments=("units mm",))
    scan = load_scan(path)
    assert scan.source["reader"] == "ply-memmap"
    np.testing.assert_array_equal(scan.points, xyz_of(rec))
    assert scan.points.dtype == np.float64 and scan.normals.dtype == np.float32
    np.testing.assert_array_equal(scan.normals, np.column_stack([rec["nx"], rec["ny"], rec["nz"]]))
    np.testing.assert_array_equal(scan.colors,
                                  np.column_stack([rec["red"], rec["green"], rec["blue"]]))
    assert scan.faces is None and scan.units == "mm"
    assert scan.source["ignored_properties"] == ["confidence"]
    assert scan.source["sha256"] == sha256(path)
    assert scan.source["bytes"] == path.stat().st_size


def test_binary_ply_chunks_and_gzip_stream_agree(tmp_path, monkeypatch):
    """Chunk boundaries (chunk of 7 vertices, 50 vertices) and the .gz stream path."""
    monkeypatch.setattr(ply_module, "CHUNK_VERTICES", 7)
    rec = cloud_records(50)
    plain = tmp_path / "c.ply"
    write_binary_ply(plain, rec, extra=b"", elements="element range_grid 0\n"
                     "property list uchar int vertex_indices\n")
    packed = tmp_path / "c.ply.gz"
    packed.write_bytes(gzip.compress(plain.read_bytes()))
    a, b = load_scan(plain), load_scan(packed)
    assert (a.source["reader"], b.source["reader"]) == ("ply-memmap", "ply-stream")
    for scan in (a, b):
        np.testing.assert_array_equal(scan.points, xyz_of(rec))
        np.testing.assert_array_equal(scan.colors[:, 1], rec["green"])
    assert b.source["sha256"] == sha256(packed) and b.source["compression"] == "gzip"
    assert a.source["sha256"] == sha256(plain)


def test_binary_ply_double_and_float_colors(tmp_path):
    dtype = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("r", "<f4"), ("g", "<f4"),
                      ("b", "<f4")])
    rec = np.zeros(3, dtype)
    rec["x"] = [0.1, 1e-300, -5e200]
    rec["r"], rec["g"], rec["b"] = [0.0, 0.5, 1.0], [1.0, 0.2, 0.0], [0.25, 0.75, 1.0]
    path = tmp_path / "d.ply"
    lines = ["ply", "format binary_little_endian 1.0", "element vertex 3",
             "property double x", "property double y", "property double z",
             "property float r", "property float g", "property float b", "end_header", ""]
    path.write_bytes("\n".join(lines).encode() + rec.tobytes())
    scan = load_scan(path)
    assert scan.points[:, 0].tolist() == [0.1, 1e-300, -5e200]  # float64 kept exactly
    assert scan.colors.tolist() == [[0, 255, 64], [128, 51, 191], [255, 0, 255]]


def test_ascii_ply_cloud_with_range_grid(tmp_path):
    pts = np.round(RNG.normal(size=(20, 3)), 6)
    body = "".join(f"{x} {y} {z} {i % 256}\n" for i, (x, y, z) in enumerate(pts))
    grid = "".join(f"1 {i}\n" for i in range(20)) + "0\n" * 5
    text = ("ply\nformat ascii 1.0\nobj_info num_cols 5\nbye\nelement vertex 20\n"
            "property float x\nproperty float y\nproperty float z\nproperty uchar intensity\n"
            "element range_grid 25\nproperty list uchar int vertex_indices\nend_header\n"
            + body + grid)
    path = tmp_path / "scan.ply"
    path.write_text(text)
    scan = load_scan(path)
    assert scan.source["reader"] == "ply-range-grid"  # tests/test_range_grid.py: the faces
    np.testing.assert_array_equal(scan.points, pts)
    assert any("bye" in w for w in scan.source["warnings"])


def _ascii_mesh(faces: str, nf: int) -> str:
    return ("ply\nformat ascii 1.0\ncomment Units: millimetres\nelement vertex 5\n"
            "property float x\nproperty float y\nproperty float z\n"
            "property uchar red\nproperty uchar green\nproperty uchar blue\n"
            f"element face {nf}\nproperty list uchar int vertex_indices\nend_header\n"
            "0 0 0 255 0 0\n1 0 0 0 255 0\n1 1 0 0 0 255\n0 1 0 9 9 9\n2 2 2 1 2 3\n" + faces)


def test_ascii_ply_triangle_mesh(tmp_path):
    path = tmp_path / "tri.ply"
    path.write_text(_ascii_mesh("3 0 1 2\n3 0 2 3\n", 2))
    scan = load_scan(path)
    assert scan.source["reader"] == "ply-ascii" and scan.units == "mm"
    assert scan.faces.tolist() == [[0, 1, 2], [0, 2, 3]]
    assert scan.colors[:3].tolist() == [[255, 0, 0], [0, 255, 0], [0, 0, 255]]


def test_ascii_ply_polygons_go_through_trimesh(tmp_path):
    path = tmp_path / "quad.ply"
    path.write_text(_ascii_mesh("4 0 1 2 3\n3 1 4 2\n", 2))
    scan = load_scan(path)
    assert scan.source["reader"] == "trimesh"
    assert scan.faces.shape == (3, 3)  # the quad triangulated, plus the triangle
    corners = {frozenset(f) for f in scan.faces.tolist()}
    assert frozenset({1, 4, 2}) in corners and set(np.unique(scan.faces)) == {0, 1, 2, 3, 4}


def test_binary_ply_mesh_with_normals_and_colors(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    mesh = trimesh.creation.icosphere(subdivisions=2)
    colors = RNG.integers(0, 256, (len(mesh.vertices), 4)).astype(np.uint8)
    mesh.visual.vertex_colors = colors
    path = tmp_path / "ico.ply"
    path.write_bytes(trimesh.exchange.ply.export_ply(mesh, include_attributes=False,
                                                     vertex_normal=True))
    scan = load_scan(path)
    assert scan.source["reader"] == "trimesh"
    np.testing.assert_allclose(scan.points, mesh.vertices, atol=1e-6)
    np.testing.assert_array_equal(scan.faces, mesh.faces)
    np.testing.assert_array_equal(scan.colors, colors[:, :3])
    np.testing.assert_allclose(scan.normals, mesh.vertex_normals, atol=1e-6)


# ---------------------------------------------------------------- mesh formats


def test_obj_with_texture(tmp_path):
    from PIL import Image

    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float) * 0.5 + 0.25
    verts = np.array([[0, 0, 0], [2, 0, 0], [2, 1, 0], [0, 1, 0.5]])
    (tmp_path / "t.obj").write_text(
        "mtllib t.mtl\nusemtl m\n" + "".join(f"v {x} {y} {z}\n" for x, y, z in verts)
        + "".join(f"vt {u} {v}\n" for u, v in uv) + "f 1/1 2/2 3/3\nf 1/1 3/3 4/4\n")
    (tmp_path / "t.mtl").write_text("newmtl m\nKd 1 1 1\nmap_Kd tex.png\n")
    Image.new("RGB", (8, 4), (10, 20, 30)).save(tmp_path / "tex.png")
    scan = load_scan(tmp_path / "t.obj")
    assert scan.n_points == 4 and scan.faces.shape == (2, 3)
    order = [int(np.flatnonzero((verts == p).all(axis=1))[0]) for p in scan.points]
    np.testing.assert_allclose(scan.uv, uv[order])
    assert scan.texture.size == (8, 4) and scan.texture.getpixel((0, 0)) == (10, 20, 30)
    files = {f["name"]: f for f in scan.source["files"]}
    assert set(files) == {"t.obj", "t.mtl", "tex.png"}
    assert files["tex.png"]["sha256"] == sha256(tmp_path / "tex.png")


def test_obj_missing_texture_is_reported(tmp_path):
    (tmp_path / "t.obj").write_text("mtllib t.mtl\nusemtl m\nv 0 0 0\nv 1 0 0\nv 0 1 0\n"
                                    "vt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n")
    (tmp_path / "t.mtl").write_text("newmtl m\nmap_Kd gone.jpg\n")
    scan = load_scan(tmp_path / "t.obj")
    assert scan.texture is None and scan.uv is None
    assert any("gone.jpg" in w for w in scan.source["warnings"])


def test_stl_vertices_are_merged(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    mesh = trimesh.creation.box(extents=(1, 2, 3))
    for name, data in (("b.stl", trimesh.exchange.stl.export_stl(mesh)),
                       ("a.stl", trimesh.exchange.stl.export_stl_ascii(mesh).encode())):
        (tmp_path / name).write_bytes(data)
        scan = load_scan(tmp_path / name)
        assert scan.n_points == 8 and scan.faces.shape == (12, 3)
        triangles = mesh.vertices[mesh.faces]
        np.testing.assert_allclose(scan.points[scan.faces], triangles, atol=1e-6)


def test_off(tmp_path):
    path = tmp_path / "m.off"
    path.write_text("OFF\n# a tetrahedron\n4 4 6\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n"
                    "3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n")
    scan = load_scan(path)
    assert scan.points.tolist() == [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]
    assert scan.faces.tolist() == [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]


def test_glb_scene_transforms_are_applied(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    from scipy.spatial.transform import Rotation

    a = trimesh.creation.icosphere(subdivisions=1)
    b = trimesh.creation.box()
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_euler("xyz", [30, -20, 75], degrees=True).as_matrix()
    matrix[:3, 3] = [5.0, -1.0, 2.0]
    scene = trimesh.Scene()
    scene.add_geometry(a, geom_name="a")
    scene.add_geometry(b, geom_name="b", transform=matrix)
    path = tmp_path / "s.glb"
    path.write_bytes(scene.export(file_type="glb"))
    scan = load_scan(path)
    assert scan.units == "m"
    expected_b = b.vertices @ matrix[:3, :3].T + matrix[:3, 3]
    assert scan.n_points == len(a.vertices) + len(b.vertices)
    got = {tuple(np.round(p, 5)) for p in scan.points}
    want = {tuple(np.round(p, 5)) for p in np.vstack([a.vertices, expected_b])}
    assert got == want
    assert scan.faces.shape == (len(a.faces) + len(b.faces), 3)


def test_gltf_with_external_buffer(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    mesh = trimesh.creation.icosphere(subdivisions=1)
    files = trimesh.Scene(mesh).export(file_type="gltf")
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    scan = load_scan(tmp_path / "model.gltf")
    np.testing.assert_allclose(scan.points, mesh.vertices, atol=1e-6)
    assert len(scan.source["files"]) == len(files)


# ---------------------------------------------------------------- text clouds


def test_xyz_whitespace_plain(tmp_path):
    pts = np.round(RNG.normal(size=(30, 3)), 5)
    path = tmp_path / "p.xyz"
    rows = [f"{x!r}\t{y!r}  {z!r}\n" for x, y, z in pts.tolist()]
    path.write_text("# units: mm\n\n" + "".join(rows))
    scan = load_scan(path)
    np.testing.assert_array_equal(scan.points, pts)
    assert scan.units == "mm" and scan.normals is None and scan.colors is None


def test_xyz_comma_separated_rgb_gz(tmp_path):
    pts = np.round(RNG.normal(size=(10, 3)), 4)
    rgb = RNG.integers(0, 256, (10, 3))
    text = "".join(f"{p[0]}, {p[1]},{p[2]},{c[0]},{c[1]},{c[2]}\r\n"
                   for p, c in zip(pts, rgb, strict=True))
    path = tmp_path / "p.xyz.gz"
    path.write_bytes(gzip.compress(text.encode()))
    scan = load_scan(path)
    np.testing.assert_array_equal(scan.points, pts)
    np.testing.assert_array_equal(scan.colors, rgb)
    assert scan.source["columns"] == ["x", "y", "z", "r", "g", "b"]
    assert scan.source["sha256"] == sha256(path)


def test_xyz_unit_normals_by_layout(tmp_path):
    pts = RNG.normal(size=(10, 3))
    nrm = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    path = tmp_path / "n.xyz"
    np.savetxt(path, np.hstack([pts, nrm]), fmt="%.17g")
    scan = load_scan(path)
    np.testing.assert_allclose(scan.normals, nrm, rtol=1e-6)
    assert scan.colors is None


def test_xyz_header_row_names_columns(tmp_path):
    path = tmp_path / "h.xyz"
    path.write_text("nx ny nz x y z intensity\n0 0 1 1 2 3 0.5\n0 1 0 4 5 6 0.7\n")
    scan = load_scan(path)
    assert scan.points.tolist() == [[1, 2, 3], [4, 5, 6]]
    assert scan.normals.tolist() == [[0, 0, 1], [0, 1, 0]]


def test_pts_count_intensity_rgb(tmp_path):
    rows = ["3", "1 2 3 -1200 10 20 30", "4 5 6 -800 40 50 60", "7 8 9 0 70 80 90"]
    path = tmp_path / "c.pts"
    path.write_text("\n".join(rows) + "\n")
    scan = load_scan(path)
    assert scan.points.tolist() == [[1, 2, 3], [4, 5, 6], [7, 8, 9]]
    assert scan.colors.tolist() == [[10, 20, 30], [40, 50, 60], [70, 80, 90]]
    assert scan.source["columns"] == ["x", "y", "z", "intensity", "r", "g", "b"]


def test_asc_cloudcompare_comment_header(tmp_path):
    path = tmp_path / "c.asc"
    path.write_text("//X,Y,Z,R,G,B,Nx,Ny,Nz\n1,2,3,4,5,6,0,0,1\n7,8,9,10,11,12,1,0,0\n")
    scan = load_scan(path)
    assert scan.points.tolist() == [[1, 2, 3], [7, 8, 9]]
    assert scan.colors.tolist() == [[4, 5, 6], [10, 11, 12]]
    assert scan.normals.tolist() == [[0, 0, 1], [1, 0, 0]]
    assert scan.source["columns_named_by"] == "header"


def test_text_unknown_extra_columns_are_listed(tmp_path):
    path = tmp_path / "e.xyz"
    path.write_text("1 2 3 0.5 7.25\n4 5 6 0.25 1.5\n")
    scan = load_scan(path)
    assert scan.source["columns"] == ["x", "y", "z", "extra", "extra"]
    assert scan.source["warnings"]


# ---------------------------------------------------------------- .conf


def test_conf_registration_matches_scipy(tmp_path):
    from scipy.spatial.transform import Rotation

    clouds = [RNG.normal(size=(40, 3)), RNG.normal(size=(25, 3))]
    poses = [(np.array([0.1, -0.2, 0.3]), Rotation.random(random_state=1).as_quat()),
             (np.array([-1.0, 0.0, 2.0]), Rotation.random(random_state=2).as_quat() * 3.0)]
    lines = ["camera 0 -0.1 -0.7 0 1 0 0", "mesh raw_cybcyl 0 0 0 0 0 0 1"]
    for i, (cloud, (t, q)) in enumerate(zip(clouds, poses, strict=True)):
        np.savetxt(tmp_path / f"s{i}.xyz", cloud, fmt="%.17g")
        lines.append(f"bmesh s{i}.xyz {' '.join(map(repr, [*t.tolist(), *q.tolist()]))}")
    (tmp_path / "all.conf").write_text("\n".join(lines) + "\n")
    scan = load_scan(tmp_path / "all.conf")
    expected = np.vstack([Rotation.from_quat(q).inv().apply(c) + t  # R(q)^T p + t
                          for c, (t, q) in zip(clouds, poses, strict=True)])
    np.testing.assert_allclose(scan.points, expected, atol=1e-12)
    assert [s["points"] for s in scan.source["scans"]] == [40, 25]
    assert any("raw_cybcyl" in w for w in scan.source["warnings"])
    assert [f["role"] for f in scan.source["files"]] == ["input", "scan", "scan"]


def test_quaternion_matrix_matches_scipy():
    from scipy.spatial.transform import Rotation

    for seed in range(5):
        q = Rotation.random(random_state=seed).as_quat()
        np.testing.assert_allclose(quaternion_matrix(q), Rotation.from_quat(q).as_matrix(),
                                   atol=1e-14)


# ---------------------------------------------------------------- thinning


def test_voxel_thinning_matches_bruteforce():
    pts = RNG.uniform(0, 10, size=(3000, 3))
    h = 1.7
    cells = np.floor((pts - pts.min(axis=0)) / h).astype(int)
    groups: dict[tuple, list[int]] = {}
    for i, c in enumerate(map(tuple, cells)):
        groups.setdefault(c, []).append(i)
    expected = []
    for members in groups.values():
        centroid = pts[members].mean(axis=0)
        d = [float(((pts[i] - centroid) ** 2).sum()) for i in members]
        expected.append(members[int(np.argmin(d))])
    assert voxel_thin_indices(pts, h).tolist() == sorted(expected)


def test_voxel_thinning_ties_keep_the_lowest_index():
    """Points symmetric about their voxel's centroid are equidistant: the lowest index wins."""
    square = np.array([[0.25, 0.5, 0.5], [0.75, 0.5, 0.5], [0.5, 0.25, 0.5], [0.5, 0.75, 0.5]])
    pts = np.vstack([square + [v, 0, 0] for v in range(50)])  # 50 voxels of edge 1
    perm = RNG.permutation(len(pts))
    kept = voxel_thin_indices(pts[perm], 1.0)
    expected = sorted(int(np.flatnonzero(perm // 4 == v).min()) for v in range(50))
    assert kept.tolist() == expected


def test_load_with_thinning(tmp_path):
    rec = cloud_records(2000)
    path = tmp_path / "c.ply"
    write_binary_ply(path, rec)
    full, thin = load_scan(path), load_scan(path, thin=40.0)
    assert 1 < thin.n_points < full.n_points
    keep = voxel_thin_indices(full.points, 40.0)
    np.testing.assert_array_equal(thin.points, full.points[keep])
    np.testing.assert_array_equal(thin.colors, full.colors[keep])
    assert thin.source["thinning"]["points_after"] == thin.n_points
    np.testing.assert_array_equal(load_scan(path, thin=40.0).points, thin.points)


@pytest.mark.parametrize("bad,match", [
    (0, "positive"), (-1.0, "positive"), (float("nan"), "positive"), (float("inf"), "positive"),
    (True, "positive voxel size"), ("1", "positive voxel size"), (1e9, "diagonal")])
def test_bad_thinning_size(tmp_path, bad, match):
    path = tmp_path / "p.xyz"
    path.write_text("0 0 0\n1 1 1\n2 2 2\n")
    with pytest.raises(ScanError, match=match):
        load_scan(path, thin=bad)


def test_scan_from_array():
    pts = RNG.normal(size=(10, 3))
    scan = Scan.from_array(pts, name="relief")
    assert scan.source["sha256"] == hashlib.sha256(pts.tobytes()).hexdigest()
    with pytest.raises(ScanError, match="1 of 10 points have non-finite"):
        Scan.from_array(np.where(np.arange(30).reshape(10, 3) == 4, np.inf, pts))


# ---------------------------------------------------------------- bad input


def test_missing_file(tmp_path):
    with pytest.raises(ScanError, match="no such file"):
        load_scan(tmp_path / "nothing.ply")


def test_directory(tmp_path):
    (tmp_path / "d.ply").mkdir()
    with pytest.raises(ScanError, match="is a directory"):
        load_scan(tmp_path / "d.ply")


@pytest.mark.parametrize("name", ["e.ply", "e.xyz", "e.obj", "e.conf", "e.stl.gz"])
def test_empty_file(tmp_path, name):
    (tmp_path / name).write_bytes(b"")
    with pytest.raises(ScanError, match=r"empty \(0 bytes\)"):
        load_scan(tmp_path / name)


def test_unsupported_extension(tmp_path):
    # .ptx (Leica's gridded text export) is not read; .e57 was the example until it was
    (tmp_path / "scan.ptx").write_bytes(b"x")
    with pytest.raises(ScanError, match=r"unsupported file type '\.ptx'; supported: \.ply"):
        load_scan(tmp_path / "scan.ptx")
    assert ".xyz" in SUPPORTED_EXTENSIONS and ".conf" in SUPPORTED_EXTENSIONS
    assert {".e57", ".las", ".laz"} <= set(SUPPORTED_EXTENSIONS)


def test_zero_points(tmp_path):
    write_binary_ply(tmp_path / "z.ply", cloud_records(0))
    with pytest.raises(ScanError, match="no points"):
        load_scan(tmp_path / "z.ply")
    (tmp_path / "z.xyz").write_text("# only a comment\n\n")
    with pytest.raises(ScanError, match="no points"):
        load_scan(tmp_path / "z.xyz")


def test_nonfinite_binary_ply(tmp_path):
    rec = cloud_records(10)
    rec["y"][3] = np.nan
    rec["z"][7] = -np.inf
    write_binary_ply(tmp_path / "n.ply", rec)
    with pytest.raises(ScanError, match=r"2 of 10 points have non-finite .* point 3"):
        load_scan(tmp_path / "n.ply")


def test_nonfinite_text(tmp_path):
    (tmp_path / "n.xyz").write_text("0 0 0\n1 nan 1\ninf 2 2\n3 3 3\n")
    with pytest.raises(ScanError, match="2 of 4 points have non-finite"):
        load_scan(tmp_path / "n.xyz")


def test_truncated_binary_ply(tmp_path):
    path = tmp_path / "t.ply"
    write_binary_ply(path, cloud_records(100))
    data = path.read_bytes()
    path.write_bytes(data[:-1000])
    with pytest.raises(ScanError, match=r"truncated binary PLY: the header promises 100 "
                                        r"vertices .* \(67 whole vertices\)"):
        load_scan(path)
    gz = tmp_path / "t.ply.gz"
    gz.write_bytes(gzip.compress(data[:-1000]))
    with pytest.raises(ScanError, match="truncated binary PLY.*ends after 67 whole vertices"):
        load_scan(gz)


def test_truncated_ascii_ply(tmp_path):
    (tmp_path / "t.ply").write_text("ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\n"
                                    "property float y\nproperty float z\nend_header\n"
                                    "0 0 0\n1 1 1\n")
    with pytest.raises(ScanError, match="promises 5 vertices but the file holds only 2"):
        load_scan(tmp_path / "t.ply")


def test_truncated_binary_ply_mesh(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    data = trimesh.exchange.ply.export_ply(trimesh.creation.box())
    (tmp_path / "t.ply").write_bytes(data[:-40])
    with pytest.raises(ScanError, match="unreadable PLY content"):
        load_scan(tmp_path / "t.ply")


@pytest.mark.parametrize("content,match", [
    (b"PLY?\nformat ascii 1.0\n", "not a PLY file"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n", "no 'end_header'"),
    (b"ply\nformat binary_middle_endian 1.0\nend_header\n", "unknown format"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quad x\nend_header\n", "cannot parse"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float x\n"
     b"end_header\n1 2\n", "duplicate property 'x'"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float u\nend_header\n1\n",
     "no x, y, z properties"),
    (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
     b"property float z\nend_header\n0 0 0\n1 1 q\n", "unreadable ASCII PLY vertex data"),
    (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
     b"property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
     b"0 0 0\n1 0 0\n0 1 0\n3 0 1 9\n", r"face vertex indices must lie in \[0, 3\)"),
])
def test_corrupt_ply(tmp_path, content, match):
    (tmp_path / "c.ply").write_bytes(content)
    with pytest.raises(ScanError, match=match):
        load_scan(tmp_path / "c.ply")


def test_corrupt_gzip(tmp_path):
    (tmp_path / "c.ply.gz").write_bytes(b"\x1f\x8b\x08\x00garbage-not-deflate" * 3)
    with pytest.raises(ScanError, match="corrupt gzip"):
        load_scan(tmp_path / "c.ply.gz")


@pytest.mark.parametrize("name,content,match", [
    ("c.stl", b"\x00" * 80 + struct.pack("<I", 12) + b"\x00" * 100, "corrupt or truncated STL"),
    ("c.glb", b"glTF" + b"\x00" * 60, "unreadable GLB content"),
    ("c.off", b"OFF\n3 1 0\n0 0 0\n1 0 0\n", "unreadable OFF content"),
    ("c.obj", b"hello\nworld\n", "no points"),
])
def test_corrupt_mesh_files(tmp_path, name, content, match):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(ScanError, match=match):
        load_scan(tmp_path / name)


@pytest.mark.parametrize("name,content,match", [
    ("a.xyz", "1 2 3\n4 5 x\n", "unreadable point rows after line 1"),
    ("b.xyz", "1 2\n3 4\n", "at least x y z"),
    ("c.xyz", "1 2 3\n4 5 6 7\n", "line 1 has 3 values but the rows after it have 4"),
    ("i.xyz", "1 2 3\n4 5 6\n7 8\n", "number of columns changed"),
    ("d.pts", "5\n1 2 3\n4 5 6\n", "declares 5 points but the file holds 2"),
    ("e.xyz", "1 2 3\nhello 5 6\n", "unreadable point rows"),
    ("f.xyz", "a b c\n1 2 3\n", "names no x, y, z"),
    ("g.xyz", "x y z\n1 2 3 4\n", "header names 3 columns but the rows have 4"),
    ("h.xyz", "1 2 3 300 0 0 0 0 1\n", None),  # 9 columns fitting no layout: loads
])
def test_bad_text_clouds(tmp_path, name, content, match):
    (tmp_path / name).write_text(content)
    if match is None:
        assert load_scan(tmp_path / name).source["columns"][3:] == ["extra"] * 6
        return
    with pytest.raises(ScanError, match=match):
        load_scan(tmp_path / name)


def test_binary_garbage_as_text(tmp_path):
    (tmp_path / "g.xyz").write_bytes(bytes(range(128, 256)) * 4)
    with pytest.raises(ScanError, match="not a text point cloud"):
        load_scan(tmp_path / "g.xyz")


@pytest.mark.parametrize("content,match", [
    ("bmesh missing.ply 0 0 0 0 0 0 1\n", "neither .*missing.ply nor missing.ply.gz exists"),
    ("camera 0 0 0 0 0 0 1\n", "lists no scans"),
    ("bmesh a.xyz 0 0 0 0 0 1\n", "bmesh needs 8 fields, got 7"),
    ("bmesh a.xyz 0 0 0 0 0 0 one\n", "expected 7 numbers"),
    ("bmesh a.xyz 0 0 0 0 0 0 0\n", "quaternion non-zero"),
    ("scan a.xyz 0 0 0 0 0 0 1\n", "unknown keyword 'scan'"),
    ("bmesh c.conf 0 0 0 0 0 0 1\n", r"unsupported file type '\.conf'"),
])
def test_bad_conf(tmp_path, content, match):
    (tmp_path / "a.xyz").write_text("0 0 0\n")
    (tmp_path / "c.conf").write_text(content)
    with pytest.raises(ScanError, match=match):
        load_scan(tmp_path / "c.conf")


# ---------------------------------------------------------------- real scans


def real(shared_data: Path, relative: str) -> Path:
    path = shared_data / relative
    if not path.exists():
        pytest.skip(f"{path} is absent")
    return path


BUDDHA_COUNTS = {  # PROVENANCE.md of happy-buddha-rangescans
    0: 78056, 24: 75582, 48: 69158, 72: 61872, 96: 62682, 120: 78212, 144: 85036, 168: 84699,
    192: 80617, 216: 71459, 240: 60735, 264: 63298, 288: 72346, 312: 76166, 336: 79087}


@pytest.fixture(scope="module")
def buddha(shared_data):
    return load_scan(real(shared_data, "happy-buddha-rangescans/happyStandRight.conf"))


@pytest.mark.realdata
def test_real_buddha_conf_registers_all_scans(buddha):
    assert buddha.n_points == 1_099_005 == sum(BUDDHA_COUNTS.values())
    scans = buddha.source["scans"]
    assert [s["points"] for s in scans] == [BUDDHA_COUNTS[int(s["name"][16:-4])] for s in scans]
    size = np.ptp(buddha.points, axis=0)  # PROVENANCE: bbox about 0.083 x 0.200 x 0.082 m
    np.testing.assert_allclose(size, [0.083, 0.200, 0.082], atol=0.01)


@pytest.mark.realdata
def test_real_buddha_registration_overlaps(buddha, shared_data):
    """Neighbouring scans (0 and 24 degrees) coincide after registration: median NN ~ spacing."""
    from scipy.spatial import cKDTree
    from scipy.spatial.transform import Rotation

    n0, n1 = BUDDHA_COUNTS[0], BUDDHA_COUNTS[24]
    first, second = buddha.points[:n0], buddha.points[n0:n0 + n1]
    tree = cKDTree(first)
    median = float(np.median(tree.query(second[::8])[0]))
    assert median < 0.4e-3  # metres; the raw sampling step is about 0.3 mm
    raw = load_scan(real(shared_data, "happy-buddha-rangescans/happyStandRight_0.ply.gz"))
    t, q = buddha.source["scans"][0]["translation"], buddha.source["scans"][0]["quaternion_xyzw"]
    np.testing.assert_allclose(first, Rotation.from_quat(q).inv().apply(raw.points) + t,
                               atol=1e-12)
    wrong = Rotation.from_quat(buddha.source["scans"][1]["quaternion_xyzw"]).apply(
        load_scan(real(shared_data, "happy-buddha-rangescans/happyStandRight_24.ply.gz")).points)
    wrong_median = float(np.median(tree.query(wrong[::8])[0]))
    assert wrong_median > 10 * median  # the other rotation direction does not register


@pytest.mark.realdata
@pytest.mark.parametrize("relative,points,faces", [
    # raw range scans: their range grids triangulated (tests/test_range_grid.py)
    ("happy-buddha-rangescans/happyStandRight_0.ply.gz", 78056, 147889),
    ("stanford-bunny/bun000.ply.gz", 40256, 78336),
    ("stanford-bunny/bun_zipper.ply.gz", 35947, 69451),
    ("stanford-lucy/lucy.ply", 49987, 99970),
    ("nefertiti/nefertiti-lowres.obj", 35002, 70000),
])
def test_real_scans_counts(shared_data, relative, points, faces):
    path = real(shared_data, relative)
    scan = load_scan(path)
    assert scan.n_points == points
    assert (None if scan.faces is None else len(scan.faces)) == faces
    assert scan.source["sha256"] == sha256(path)


@pytest.mark.realdata
def test_real_laurana_colors_and_normals(shared_data):
    path = real(shared_data, "laurana-bust/laurana.ply")
    scan = load_scan(path)
    assert (scan.n_points, len(scan.faces)) == (25160, 50000)
    data = path.read_bytes()  # independent decode of the vertex block: 6 float32 + 4 uchar
    start = data.index(b"end_header\n") + len(b"end_header\n")
    rec = np.frombuffer(data, np.dtype([("p", "<f4", 3), ("n", "<f4", 3), ("c", "u1", 4)]),
                        25160, start)
    np.testing.assert_array_equal(scan.points, rec["p"])
    np.testing.assert_array_equal(scan.normals, rec["n"])
    np.testing.assert_array_equal(scan.colors, rec["c"][:, :3])


@pytest.mark.realdata
def test_real_bunny_conf_names_missing_scans(shared_data):
    with pytest.raises(ScanError, match="lists scan 'bun045.ply'"):
        load_scan(real(shared_data, "stanford-bunny/bun.conf"))


@pytest.mark.realdata
def test_real_bali_mask_obj_and_gltf(shared_data):
    obj = load_scan(real(shared_data, "bali-mask/mask.obj"))
    gltf = load_scan(real(shared_data, "bali-mask/mask-gltf-2.0_separated-valid.gltf"))
    for scan in (obj, gltf):
        assert (scan.n_points, len(scan.faces)) == (62383, 100000)
        assert scan.uv.shape == (62383, 2) and scan.texture.size == (4096, 4096)
        names = {f["name"] for f in scan.source["files"]}
        assert "Image_0.jpg" in names
    assert gltf.units == "m" and gltf.normals is not None and obj.normals is None
    size = np.ptp(gltf.points, axis=0)  # PROVENANCE: about 0.221 x 0.225 x 0.127 m
    np.testing.assert_allclose(size, [0.221, 0.225, 0.127], atol=0.005)
    jpg = next(f for f in obj.source["files"] if f["name"] == "Image_0.jpg")
    assert jpg["sha256"] == sha256(real(shared_data, "bali-mask/Image_0.jpg"))
    # same geometry in both files: every OBJ vertex is a glTF vertex (OBJ holds 8 decimals)
    from scipy.spatial import cKDTree

    assert cKDTree(gltf.points).query(obj.points)[0].max() < 1e-7

