"""fitter.fitting.error's reports: the z-buffered scan view and the coloured error PLY."""

from __future__ import annotations

import matplotlib
import numpy as np
import trimesh

from fitter.fitting.error import _depth_view, write_error_ply


def test_depth_view_shows_the_nearest_point_of_each_pixel():
    rng = np.random.default_rng(0)
    points = rng.uniform(0, 1, (3000, 3))
    d = rng.normal(size=3000)
    view, extent = _depth_view(points, d, width=24)
    rows, cols = view.shape
    assert extent == (points[:, 0].min(), points[:, 0].max(),
                      points[:, 1].min(), points[:, 1].max())
    expected = np.full((rows, cols), np.nan)
    best = np.full((rows, cols), -np.inf)
    x0, x1, y0, y1 = extent
    for (x, y, z), dk in zip(points, d, strict=True):  # reference: one point at a time
        c = min(int((x - x0) / (x1 - x0) * cols), cols - 1)
        r = min(int((y - y0) / (y1 - y0) * rows), rows - 1)
        if z > best[r, c]:
            best[r, c], expected[r, c] = z, dk
    np.testing.assert_array_equal(view, expected)


def test_error_ply_colours_and_keeps_the_deviation(tmp_path):
    d = np.array([-2.0, -1.0, 0.0, 1.0, 2.0] + [0.5] * 95)
    points = np.column_stack([np.arange(100.0), np.zeros(100), np.zeros(100)])
    write_error_ply(tmp_path / "e.ply", points, d)
    mesh = trimesh.load(tmp_path / "e.ply", process=False)
    raw = mesh.metadata["_ply_raw"]["vertex"]["data"]
    np.testing.assert_array_equal(raw["quality"], d.astype(np.float32))
    rgb = np.column_stack([raw["red"], raw["green"], raw["blue"]]).astype(int)
    limit = np.percentile(np.abs(d), 99)
    cmap = matplotlib.colormaps["coolwarm"]
    for k in range(5):  # within one step of the 256-colour table
        want = np.array(cmap(np.clip(0.5 + 0.5 * d[k] / limit, 0, 1))[:3]) * 255
        assert np.abs(rgb[k] - want).max() <= 3


def test_error_ply_reads_back_through_trimesh_with_the_same_points_colours_and_quality(
        tmp_path):
    """error.ply through trimesh (an independent reader) and against the record layout
    written with numpy's structured dtype (the independent reference of the body bytes)."""
    rng = np.random.default_rng(5)
    n = 20_000
    points = rng.normal(size=(n, 3)) * [50.0, 30.0, 5.0] + [250.0, -40.0, 1200.0]
    d = rng.normal(scale=0.1, size=n)
    write_error_ply(tmp_path / "e.ply", points, d)
    data = (tmp_path / "e.ply").read_bytes()
    cloud = trimesh.load(tmp_path / "e.ply", process=False)
    assert not hasattr(cloud, "faces") or len(cloud.faces) == 0
    np.testing.assert_array_equal(np.asarray(cloud.vertices), points.astype(np.float32))
    raw = cloud.metadata["_ply_raw"]["vertex"]["data"]
    np.testing.assert_array_equal(raw["quality"], d.astype(np.float32))
    rgb = np.column_stack([raw["red"], raw["green"], raw["blue"]])
    lut = (matplotlib.colormaps["coolwarm"](np.linspace(0, 1, 256))[:, :3] * 255).round()
    limit = np.percentile(np.abs(d), 99)
    index = np.rint(np.clip(0.5 + 0.5 * d / limit, 0, 1) * 255).astype(int)
    np.testing.assert_array_equal(rgb, lut.astype(np.uint8)[index])
    record = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"),
                       ("green", "u1"), ("blue", "u1"), ("quality", "<f4")])
    expected = np.empty(n, record)
    expected["x"], expected["y"], expected["z"] = points.T
    expected["red"], expected["green"], expected["blue"] = rgb.T
    expected["quality"] = d
    assert data[data.index(b"end_header\n") + len(b"end_header\n"):] == expected.tobytes()
    assert b"element face" not in data[: data.index(b"end_header\n")]
