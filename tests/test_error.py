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
