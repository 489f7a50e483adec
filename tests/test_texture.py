"""fitter.fitting.texture: push-pull hole filling, triangle rasterisation in (u, v), tiles that
decode to the scan's colours, and a coloured scan's bundle with texture nodes."""

from __future__ import annotations

import io

import numpy as np
from PIL import Image

from fitter.fitting import texture
from fitter.fitting.io.scan import Scan


def test_push_pull_keeps_covered_texels_and_fills_holes_from_neighbours():
    colour = np.zeros((8, 8, 3))
    weight = np.zeros((8, 8))
    colour[1, 1], weight[1, 1] = (200, 0, 0), 1
    colour[6, 6], weight[6, 6] = (0, 0, 100), 2  # a sum of two samples of (0, 0, 50)
    out = texture.push_pull(colour, weight)
    np.testing.assert_allclose(out[1, 1], (200, 0, 0))
    np.testing.assert_allclose(out[6, 6], (0, 0, 50))
    assert out[0, 0, 0] == 200 and out[7, 7, 2] == 50  # nearest sample wins near each
    assert np.all(np.isfinite(out)) and np.all(out.sum(axis=2) > 0)


def test_rasterised_triangle_covers_its_area_with_interpolated_values():
    uv = np.array([[0.1, 0.1], [0.9, 0.1], [0.1, 0.9]])
    attrs = np.array([[0.0], [1.0], [0.0]])  # = barycentric weight of vertex 1: linear in u
    total, count = texture._rasterise(uv, np.array([[0, 1, 2]]), attrs, 64)
    area = 0.5 * 0.8 * 0.8 * 64 * 64  # 1311 texels; closed edges add up to half a perimeter
    assert area <= count.sum() < area + 0.5 * 2.4 * 64
    x, y = np.nonzero(count)
    expected = ((x + 0.5) / 64 - 0.1) / 0.8
    np.testing.assert_allclose(total[x, y, 0] / count[x, y], expected, atol=1e-9)


def coloured_plane(n: int = 20_000) -> tuple[Scan, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    u, v = rng.uniform(0, 1, n), rng.uniform(0, 1, n)
    colours = np.column_stack([255 * u, 255 * v, np.full(n, 60.0)]).round().astype(np.uint8)
    scan = Scan(points=np.column_stack([u, v, np.zeros(n)]), colors=colours)
    return scan, u, v


def test_tiles_decode_to_the_scan_colours_with_v_up():
    scan, u, v = coloured_plane()
    tiles = texture.texture_pyramid(scan, u, v, np.ones(len(u), bool), 2, size=32, fmt="png")
    assert sorted((t.level, t.i, t.j) for t in tiles) == [(0, 0, 0), (1, 0, 0), (1, 0, 1),
                                                           (1, 1, 0), (1, 1, 1)]
    tile = next(t for t in tiles if (t.level, t.i, t.j) == (1, 1, 0))  # u >= 0.5, v < 0.5
    img = np.asarray(Image.open(io.BytesIO(tile.data)).convert("RGB")).astype(float)
    assert img.shape == (32, 32, 3)
    # pixel (x, y): u = 0.5 + (x + 0.5) / 64, v = 0.5 - (y + 0.5) / 64 (row 0 on top)
    xs = (np.arange(32) + 0.5) / 64
    np.testing.assert_allclose(img[16, :, 0], 255 * (0.5 + xs), atol=14)
    np.testing.assert_allclose(img[:, 16, 1], 255 * (0.5 - xs), atol=14)
    assert np.all(np.abs(img[..., 2] - 60) <= 1)


def test_no_colour_no_tiles():
    scan = Scan(points=np.zeros((10, 3)))
    assert texture.texture_pyramid(scan, np.zeros(10), np.zeros(10), np.ones(10, bool), 2) == []
