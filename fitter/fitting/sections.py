"""The paper's section matrix: the scan resampled on a structured ``(m0 + 1) x (m1 + 1)`` grid.

Node ``(j0, j1)`` has parameters ``u = j0 / m0``, ``v = j1 / m1`` (the paper's
eq. 4) and the point at height ``h(u, v)`` of the projection. The height at a
node is a local least-squares plane ``h ~ a + b du + c dv`` through the scan
points nearest to that node (its Voronoi cell in the domain), evaluated at the
node: unbiased on slopes, where a plain average would shift it. All moments
are accumulated with ``bincount``, so the pass is ``O(N)`` with no neighbour
search: millions of points take a fraction of a second. Nodes with no point
are holes (``valid`` false), which the linear fit bridges with its smoothness
term.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .parameterize import Projection


@dataclass
class SectionMatrix:
    """``points (m0 + 1, m1 + 1, 3)`` in the projection's local frame (NaN at holes),
    ``valid`` and ``counts`` per node, and the node parameters ``u (m0 + 1,)``, ``v (m1 + 1,)``."""

    u: np.ndarray
    v: np.ndarray
    points: np.ndarray
    valid: np.ndarray
    counts: np.ndarray

    @property
    def full(self) -> bool:
        return bool(self.valid.all())


def section_matrix(proj: Projection, u: np.ndarray, v: np.ndarray, h: np.ndarray,
                   shape: tuple[int, int]) -> SectionMatrix:
    """Resample heights ``h`` at parameters ``u, v`` (each ``(N,)``) onto a grid of ``shape``
    nodes (``m0 + 1, m1 + 1``); periodic projections wrap ``u``."""
    rows, cols = shape
    if rows < 2 or cols < 2:
        raise ValueError(f"section matrix needs at least 2x2 nodes, got {rows}x{cols}")
    m0, m1 = rows - 1, cols - 1
    periodic = proj.periodic_u
    ju = np.rint(u * m0).astype(np.int64)
    if periodic:
        ju %= m0  # node m0 is node 0
    jv = np.rint(v * m1).astype(np.int64)
    du = u - ju / m0
    if periodic:
        du = (du + 0.5) % 1.0 - 0.5
    dv = v - jv / m1
    node = ju * cols + jv
    size = rows * cols

    def total(values: np.ndarray | None = None) -> np.ndarray:
        return np.bincount(node, weights=values, minlength=size)

    n = total()
    su, sv, sh = total(du), total(dv), total(h)
    suu, suv, svv = total(du * du), total(du * dv), total(dv * dv)
    suh, svh = total(du * h), total(dv * h)
    # Normal equations of h ~ a + b du + c dv per node: M [a, b, c] = r
    M = np.stack([np.stack([n, su, sv], -1), np.stack([su, suu, suv], -1),
                  np.stack([sv, suv, svv], -1)], -2)
    r = np.stack([sh, suh, svh], -1)
    heights = np.divide(sh, n, out=np.full(size, np.nan), where=n > 0)
    det = np.linalg.det(M)
    spread = (suu * svv) / np.maximum(n, 1) ** 2
    good = (n >= 4) & (np.abs(det) > 1e-9 * np.maximum(n**3 * spread, 1e-300))
    if good.any():
        heights[good] = np.linalg.solve(M[good], r[good][:, :, None])[:, 0, 0]
    heights = heights.reshape(rows, cols)
    counts = n.reshape(rows, cols).astype(np.int64)
    if periodic:
        heights[m0], counts[m0] = heights[0], counts[0]
    valid = counts > 0
    gu = np.linspace(0.0, 1.0, rows)
    gv = np.linspace(0.0, 1.0, cols)
    UU, VV = np.meshgrid(gu, gv, indexing="ij")
    pts = proj.from_uvh(UU.ravel(), VV.ravel(), heights.ravel()).reshape(rows, cols, 3)
    return SectionMatrix(gu, gv, pts, valid, counts)


def section_shape(n_points: int, grid: tuple[int, int], oversample: int = 4) -> tuple[int, int]:
    """Nodes per side: ``oversample`` per control point, but no more than the scan can fill
    (about two points per node), and at least the control grid itself."""
    cap = max(int(np.sqrt(n_points / 2.0)), 2)
    return tuple(int(min(max(oversample * g + 1, g + 1), max(cap, g + 1))) for g in grid)
