"""A relief range scan with a detached fragment behind it: the synthetic scan of the pieces'
tests (tests/test_pieces.py, tests/test_browser_pieces.py)."""

from __future__ import annotations

import numpy as np

from fitter.fitting.io.scan import Scan, make_scan

FRAGMENT = 64  # points of the detached fragment (8 x 8), the scan's last points


def grid_mesh(n: int, x: tuple[float, float], y: tuple[float, float], height) -> tuple:
    """An ``n x n`` grid mesh over ``x x y`` at ``z = height(x, y)``."""
    gx, gy = np.meshgrid(np.linspace(*x, n), np.linspace(*y, n), indexing="ij")
    points = np.column_stack([gx.ravel(), gy.ravel(), height(gx, gy).ravel()])
    k = np.arange(n * n).reshape(n, n)
    a, b, c, d = k[:-1, :-1].ravel(), k[1:, :-1].ravel(), k[:-1, 1:].ravel(), k[1:, 1:].ravel()
    return points, np.concatenate([np.column_stack([a, b, c]), np.column_stack([c, b, d])])


def fragment_scan(fragment: bool = True) -> Scan:
    """A relief (a height field over the plane), with a small curved fragment 0.4 behind it
    inside its footprint when ``fragment``: a second depth the height field cannot draw."""
    points, faces = grid_mesh(120, (-1, 1), (-1, 1),
                               lambda x, y: 0.15 * np.sin(2 * x) * np.cos(1.5 * y))
    if fragment:
        more, more_faces = grid_mesh(8, (0.2, 0.35), (-0.1, 0.05),
                                     lambda x, y: -0.4 + 0.2 * (x - 0.2) ** 2)
        faces = np.concatenate([faces, more_faces + len(points)])
        points = np.concatenate([points, more])
    return make_scan("synthetic", points, faces=faces, source={"name": "synthetic.ply"})
