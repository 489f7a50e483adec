"""Raw range scans: the ``range_grid`` element read (ASCII and binary) and triangulated.

References: the triangles of a synthetic range image are counted square by square
independently of the code (a step between two planes, a missing pixel), every triangle is
checked to lie on one plane (none spans the step), and the real Happy Buddha scan 0 is
checked against its grid's own counts.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from fitter.fitting.io import ScanError, load_scan
from fitter.fitting.io.range_grid import EDGE_FACTOR, triangulate

ROWS, COLS, STEP = 12, 10, 0.125  # exact in float32, as the binary file stores it


def step_image(missing: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A range image of two planes, ``z = 0`` left of column 5 and ``z = -1`` right of it
    (a depth jump of 8 sample spacings), and its grid; ``missing`` a pixel without a sample."""
    points, grid = [], np.full((ROWS, COLS), -1, np.int64)
    for r in range(ROWS):
        for c in range(COLS):
            if (r, c) == missing:
                continue
            grid[r, c] = len(points)
            points.append((c * STEP, -r * STEP, 0.0 if c < 5 else -1.0))
    return np.array(points), grid


def expected_triangles(grid: np.ndarray) -> int:
    """Squares on one plane (columns 0..3 and 5..8): two triangles with 4 samples, one with 3."""
    count = 0
    for r in range(ROWS - 1):
        for c in [*range(0, 4), *range(5, 9)]:
            present = int((grid[r:r + 2, c:c + 2] >= 0).sum())
            count += {4: 2, 3: 1}.get(present, 0)
    return count


@pytest.mark.parametrize("missing", [None, (4, 2), (0, 0)])
def test_step_is_not_bridged(missing):
    points, grid = step_image(missing)
    faces = triangulate(points, grid)
    assert len(faces) == expected_triangles(grid)
    z = points[faces][:, :, 2]
    assert np.all(z.max(axis=1) == z.min(axis=1))  # every triangle on one plane
    p = points[faces]
    normals = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert np.all(normals[:, 2] > 0)  # facing the scanner (+z)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), STEP ** 2)  # half squares


def test_orientation_follows_the_scanner_side():
    points, grid = step_image()
    mirrored = points * [1, 1, -1]
    faces = triangulate(mirrored, grid[:, ::-1])  # the image seen mirrored: winding flips
    p = mirrored[faces]
    assert np.all(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])[:, 2] > 0)


def test_longer_edges_than_the_threshold_are_left_out():
    points, grid = step_image()
    points[grid[3, 2], 2] = (EDGE_FACTOR + 0.5) * STEP  # one spike sample
    faces = triangulate(points, grid)
    assert not np.any(faces == grid[3, 2])
    # each of the 4 squares around the spike is split along the diagonal that avoids it
    # (the shorter one), so the spike is in one triangle of each: 4 triangles left out
    assert len(faces) == expected_triangles(grid) - 4


def ply_text(points: np.ndarray, grid: np.ndarray, extra_header: str = "",
             records: str | None = None) -> str:
    body = "".join(f"{x} {y} {z}\n" for x, y, z in points)
    lines = records if records is not None else "".join(
        "0\n" if i < 0 else f"1 {i}\n" for i in grid.ravel())
    return ("ply\nformat ascii 1.0\nobj_info is_mesh 0\n"
            f"obj_info num_cols {grid.shape[1]}\nobj_info num_rows {grid.shape[0]}\n"
            f"{extra_header}element vertex {len(points)}\nproperty float x\nproperty float y\n"
            f"property float z\nelement range_grid {grid.size}\n"
            "property list uchar int vertex_indices\nend_header\n" + body + lines)


def ply_binary(points: np.ndarray, grid: np.ndarray) -> bytes:
    header = ("ply\nformat binary_big_endian 1.0\n"
              f"obj_info num_cols {grid.shape[1]}\nobj_info num_rows {grid.shape[0]}\n"
              f"element vertex {len(points)}\nproperty float x\nproperty float y\n"
              f"property float z\nelement range_grid {grid.size}\n"
              "property list uchar int vertex_indices\nend_header\n").encode()
    body = points.astype(">f4").tobytes()
    cells = b"".join(b"\x00" if i < 0 else struct.pack(">Bi", 1, i) for i in grid.ravel())
    return header + body + cells


def test_ascii_and_binary_files_give_the_same_mesh(tmp_path: Path):
    points, grid = step_image((4, 2))
    (tmp_path / "a.ply").write_text(ply_text(points, grid))
    (tmp_path / "b.ply").write_bytes(ply_binary(points, grid))
    a, b = load_scan(tmp_path / "a.ply"), load_scan(tmp_path / "b.ply")
    assert a.source["reader"] == b.source["reader"] == "ply-range-grid"
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_array_equal(a.faces, triangulate(points, grid))


@pytest.mark.parametrize("change, match", [
    (lambda t: t.replace("obj_info num_cols 10\n", "").replace("obj_info num_rows 12\n", ""),
     "no 'obj_info num_cols'"),
    (lambda t: t.replace("obj_info num_rows 12", "obj_info num_rows 11"),
     "not num_rows x num_cols = 11 x 10"),
    (lambda t: t.replace("\n1 7\n", "\n1 700\n"), "names vertex 700, but the scan has 119"),
    (lambda t: t.replace("\n1 7\n", "\n1 x\n"), "not integers"),
    (lambda t: t[:t.rindex("\n1 ")] + "\n", "truncated range_grid"),
])
def test_bad_range_grids_are_named(tmp_path: Path, change, match):
    points, grid = step_image((4, 2))
    (tmp_path / "bad.ply").write_text(change(ply_text(points, grid)))
    with pytest.raises(ScanError, match=match):
        load_scan(tmp_path / "bad.ply")


def test_a_registration_keeps_the_points_only(tmp_path: Path):
    """Overlapping range images are not one surface: a ``.conf`` of them is a cloud."""
    points, grid = step_image()
    for name in ("s0.ply", "s1.ply"):
        (tmp_path / name).write_text(ply_text(points, grid))
    (tmp_path / "r.conf").write_text("bmesh s0.ply 0 0 0 0 0 0 1\nbmesh s1.ply 0 0 1 0 0 0 1\n")
    scan = load_scan(tmp_path / "r.conf")
    assert scan.faces is None and scan.n_points == 2 * len(points)


def test_a_registration_of_meshes_is_a_cloud_and_of_one_scan_a_mesh(tmp_path: Path):
    """The rule does not depend on the scan's reader: two triangle-mesh PLYs give a cloud;
    one placed scan keeps its triangles, moved with its points."""
    points, grid = step_image()
    faces = triangulate(points, grid)
    mesh = ["ply", "format ascii 1.0", f"element vertex {len(points)}", "property float x",
            "property float y", "property float z", f"element face {len(faces)}",
            "property list uchar int vertex_indices", "end_header",
            *(" ".join(map(repr, p.tolist())) for p in points.astype(np.float32)),
            *(f"3 {a} {b} {c}" for a, b, c in faces)]
    (tmp_path / "m.ply").write_text("\n".join(mesh) + "\n")
    (tmp_path / "r.ply").write_text(ply_text(points, grid))
    (tmp_path / "two.conf").write_text("bmesh m.ply 0 0 0 0 0 0 1\nbmesh r.ply 0 0 1 0 0 0 1\n")
    assert load_scan(tmp_path / "two.conf").faces is None
    (tmp_path / "one.conf").write_text("bmesh r.ply 0 0 5 0 0 0 1\n")
    one = load_scan(tmp_path / "one.conf")
    np.testing.assert_array_equal(one.faces, faces)
    np.testing.assert_allclose(one.points, points + [0, 0, 5], atol=1e-5)


@pytest.mark.realdata
def test_real_buddha_scan_is_a_mesh_with_open_borders(shared_data):
    path = shared_data / "happy-buddha-rangescans" / "happyStandRight_0.ply.gz"
    if not path.exists():
        pytest.skip(f"{path} is absent")
    scan = load_scan(path)
    assert scan.source["reader"] == "ply-range-grid" and scan.n_points == 78056
    p = scan.points[scan.faces]
    normals = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    area = np.linalg.norm(normals, axis=1)
    assert 140_000 < len(scan.faces) < 2 * 78056  # at most two triangles a sample
    assert area[normals[:, 2] > 0].sum() > 0.99 * area.sum()  # one sheet facing the scanner
    edges = np.linalg.norm(p - p[:, [1, 2, 0]], axis=2)
    assert edges.max() <= EDGE_FACTOR * np.median(edges) * 1.5
