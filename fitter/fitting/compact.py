"""Make a fitted patch cheap to store without changing what a visitor sees.

Three steps between the fit and ``base.tsp``:

0. **Stray cells.** :func:`drawn_cells` leaves out of the trim mask the cells
   where the surface strays from every scan point (overshoot at cliffs and poles).

1. **Hidden control points.** On a trimmed patch, a control point whose support
   (the ``(p + 1) x (q + 1)`` knot spans it scales) meets no drawn cell cannot
   change the drawn surface, yet least squares leaves it wherever the data at
   the rim or the thin-plate extrapolation put it: far out, widening the
   quantisation box of every axis and costing bits everywhere. Such points
   (and their log-weights) are replaced by the harmonic extension of the
   visible ones: the solution of the grid Laplace equation with the visible
   points held fixed, which lies inside their range (maximum principle) and
   varies smoothly, so it quantises and predicts cheaply.
2. **Quantisation bits.** :func:`choose_bits` takes the fewest bits (8..16)
   whose quantisation moves the surface, at the fitted scan points' parameters,
   by an RMS of at most ``QUANTISATION_SHARE`` of the fit's RMS: adding
   independent errors, the RMS grows by at most ``sqrt(1 + 0.1^2) - 1 = 0.5 %``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy import ndimage
from scipy.sparse.linalg import spsolve
from scipy.spatial import cKDTree

from client_py import NurbsSurface, read_patch, write_patch

from .nurbs import PatchModel

STRAY_FACTOR = 8.0  # how many fit RMS (plus 2 point spacings) a drawn surface may stray
GAP_QUANTILE = 0.99  # of the points' nearest-neighbour distances: the sampling's gaps
QUANTISATION_SHARE = 0.1  # quantisation RMS / fit RMS: the fit's RMS grows by <= 0.5 %
BITS_RANGE = (8, 16)
DRAWN_MARGIN = 1 / 32  # of the domain: tessellation triangles reach this far past a kept cell


def visible_control_points(model: PatchModel, cells: np.ndarray,
                           periodic_u: bool = False, poles: bool = False) -> np.ndarray:
    """``(n_u, n_v)`` booleans: control points whose support meets a drawn cell.

    ``cells (rows, cols)`` is the trim mask (true where drawn), dilated by
    ``DRAWN_MARGIN`` of the domain, since a tessellation keeps whole triangles
    whose centre is in a drawn cell. Knots are uniform clamped: control point
    ``a`` scales the spans ``a - p .. a`` of the ``n - p`` equal spans. In a
    periodic ``u`` direction the seam closure ties ``Q_0, Q_1`` to
    ``Q_{n-2}, Q_{n-1}``; the four rows count as visible together. With
    ``poles`` the first and last columns are one point each, visible together.
    """
    (p, q), (n_u, n_v) = model.degree, model.shape
    rows, cols = cells.shape
    grow = (max(1, int(np.ceil(DRAWN_MARGIN * rows))), max(1, int(np.ceil(DRAWN_MARGIN * cols))))
    pad = grow[0] if periodic_u else 0  # a periodic u wraps around the seam
    drawn = ndimage.binary_dilation(np.pad(cells, ((pad, pad), (0, 0)), mode="wrap"),
                                    np.ones((2 * grow[0] + 1, 2 * grow[1] + 1), bool))
    drawn = drawn[pad:pad + rows]
    # drawn knot spans: span s of n - p covers [s, s + 1) / (n - p) of the domain
    spans = np.zeros((n_u - p, n_v - q), bool)
    r_idx, c_idx = np.nonzero(drawn)
    for lo_r, hi_r, lo_c, hi_c in _cell_spans(r_idx, c_idx, rows, cols, n_u - p, n_v - q):
        spans[lo_r:hi_r, lo_c:hi_c] = True
    visible = _support_dilation(spans, p, q)
    if periodic_u:
        tied = visible[[0, 1, n_u - 2, n_u - 1]].any(axis=0)
        visible[[0, 1, n_u - 2, n_u - 1]] |= tied
    if poles:
        for col in (0, n_v - 1):
            visible[:, col] = visible[:, col].any()
    return visible


def _cell_spans(r: np.ndarray, c: np.ndarray, rows: int, cols: int, su: int, sv: int):
    """Span index ranges ``[lo, hi)`` each drawn cell ``(r, c)`` overlaps."""
    lo_r = np.floor(r * su / rows).astype(int)
    hi_r = np.ceil((r + 1) * su / rows).astype(int)
    lo_c = np.floor(c * sv / cols).astype(int)
    hi_c = np.ceil((c + 1) * sv / cols).astype(int)
    return zip(lo_r, hi_r, lo_c, hi_c, strict=True)


def _support_dilation(spans: np.ndarray, p: int, q: int) -> np.ndarray:
    """Control point ``(a, b)`` is visible when a drawn span ``(s, t)`` has
    ``a - p <= s <= a`` and ``b - q <= t <= b``."""
    su, sv = spans.shape
    visible = np.zeros((su + p, sv + q), bool)
    for i in range(p + 1):
        for j in range(q + 1):
            visible[i:i + su, j:j + sv] |= spans
    return visible


def harmonic_fill(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Replace ``values[~known]`` by the discrete harmonic extension of ``values[known]``.

    ``values (n_u, n_v, ...)``; solves ``sum_j (x_i - x_j) = 0`` over the
    4-neighbours of every unknown node (Dirichlet data at the known ones).
    The grid is connected, so with one known node every unknown one is reached.
    """
    n_u, n_v = known.shape
    flat = values.reshape(n_u * n_v, -1).astype(float)
    unknown = np.flatnonzero(~known.ravel())
    if len(unknown) == 0 or not known.any():
        return values.copy()

    def grid_path(n: int) -> sp.csr_matrix:
        return sp.diags([1.0, 1.0], [-1, 1], shape=(n, n), format="csr")

    adjacency = (sp.kron(grid_path(n_u), sp.identity(n_v)) +
                 sp.kron(sp.identity(n_u), grid_path(n_v))).tocsr()
    laplacian = (sp.diags(np.asarray(adjacency.sum(axis=1)).ravel()) - adjacency).tocsr()
    fixed = np.setdiff1d(np.arange(n_u * n_v), unknown)
    L_uu = laplacian[unknown][:, unknown].tocsc()
    rhs = -(laplacian[unknown][:, fixed] @ flat[fixed])
    solved = spsolve(L_uu, rhs)
    out = flat.copy()
    out[unknown] = solved.reshape(len(unknown), -1)
    return out.reshape(values.shape)


def settle_hidden(model: PatchModel, cells: np.ndarray | None,
                  periodic_u: bool = False, poles: bool = False) -> PatchModel:
    """``model`` with its hidden control points and log-weights harmonically filled."""
    if cells is None:
        return model
    visible = visible_control_points(model, cells, periodic_u, poles)
    out = model.copy()
    out.Q = harmonic_fill(model.Q, visible)
    if not np.all(model.W == 1.0):
        out.W = np.exp(harmonic_fill(np.log(model.W), visible))
    return out


class ScanNeighbourhood:
    """Nearest-point queries against a scan: a KD-tree of (at most 10^6 of) its points
    ``(N, 3)`` (patch frame), their median spacing (nearest other point) and their
    ``GAP_QUANTILE`` spacing ``gap`` (:meth:`wall_limit`)."""

    def __init__(self, points: np.ndarray) -> None:
        sample = points[:: max(1, len(points) // 1_000_000)]
        self.tree = cKDTree(sample)
        probe = sample[:: max(1, len(sample) // 20_000)]
        nearest = self.tree.query(probe, k=2)[0][:, 1]
        self.spacing = float(np.median(nearest))
        self.gap = float(np.quantile(nearest, GAP_QUANTILE)) if len(nearest) else 0.0

    def stray(self, surface, r: np.ndarray, c: np.ndarray, shape: tuple[int, int],
              fit_rms: float, gaps: bool = False) -> np.ndarray:
        """Which cells ``(r, c)`` of a ``shape`` grid over the unit domain stray: where
        ``surface(u, v) -> (m, 3)`` at the cell's centre or one of its corners lies
        farther from every scan point than ``STRAY_FACTOR * fit_rms`` plus twice the
        spacing (a perfect fit still passes between the points: :meth:`limit`), or with
        ``gaps`` twice the sampling's gaps (:meth:`wall_limit`)."""
        rows, cols = shape
        if len(r) == 0:
            return np.zeros(0, bool)
        u = np.concatenate([(r + a) / rows for a, _ in CELL_PROBES])
        v = np.concatenate([(c + b) / cols for _, b in CELL_PROBES])
        far = self.farther(surface(u, v),
                           self.wall_limit(fit_rms) if gaps else self.limit(fit_rms))
        return far.reshape(len(CELL_PROBES), -1).any(axis=0)

    def limit(self, fit_rms: float) -> float:
        """How far a drawn surface may lie from every scan point: ``STRAY_FACTOR * fit_rms``
        plus twice the spacing (a perfect fit still passes between the points)."""
        return STRAY_FACTOR * fit_rms + 2 * self.spacing

    def wall_limit(self, fit_rms: float) -> float:
        """How far a surface drawn between the scan's points may lie from every one of
        them: ``STRAY_FACTOR * fit_rms`` plus twice the ``GAP_QUANTILE`` spacing ``gap``.

        :meth:`limit` takes the median spacing: on a range image (a grid of samples)
        a point of the surface is within ``spacing / sqrt(2)`` of one, but a scattered
        cloud leaves wider gaps. The nearest-point distance from a point of the surface
        is distributed as the spacing (for a Poisson sample, ``P(R > r) = 2^-(r/m)^2``
        with ``m`` the median spacing), so its quantile measures the sampling's gaps: on
        the Happy Buddha's range scan ``gap = 1.41 m``; on a uniform random cloud ``2.8 m``
        (``2.6 m`` for a Poisson sample, whose surface is then farther than ``2 gap`` from
        every point at one place in ``10^8``), where ``2 m`` left holes in a quarter of a
        dome's finest cells.
        """
        return STRAY_FACTOR * fit_rms + 2 * self.gap

    def farther(self, positions: np.ndarray, limit: float) -> np.ndarray:
        """``(m,)`` booleans: which ``positions (m, 3)`` lie farther than ``limit`` from
        every scan point."""
        distance, _ = self.tree.query(positions)
        return distance > limit


CELL_PROBES = ((0.5, 0.5), (0.0, 0.0), (0.0, 1.0), (1.0, 0.0), (1.0, 1.0))


def drawn_cells(model: PatchModel, cells: np.ndarray, points: np.ndarray,
                fit_rms: float) -> np.ndarray:
    """``cells (rows, cols)`` without the cells where the patch strays from the scan.

    Where the scan's height over the domain jumps (a mask's rim seen from its
    centre, a sphere map's poles) the B-spline overshoots between the points
    that pin it, and a tessellation would draw the spikes. A covered cell is
    dropped when it strays from ``points`` (:meth:`ScanNeighbourhood.stray`).
    """
    r, c = np.nonzero(cells)
    far = ScanNeighbourhood(points).stray(model.evaluate, r, c, cells.shape, fit_rms)
    out = cells.copy()
    out[r[far], c[far]] = False
    return out


def choose_bits(surface: NurbsSurface, u: np.ndarray, v: np.ndarray, fit_rms: float
                ) -> tuple[int, bytes]:
    """The fewest bits in ``BITS_RANGE`` whose quantised patch stays within
    ``QUANTISATION_SHARE * fit_rms`` (RMS of the displacement at ``(u, v)``) of
    ``surface``; returns the bits and the encoded patch."""
    exact = PatchModel.from_surface(surface).evaluate(u, v)
    tolerance = QUANTISATION_SHARE * fit_rms
    lo, hi = BITS_RANGE
    chosen = None
    while lo <= hi:  # the displacement halves with each bit: bisect
        bits = (lo + hi) // 2
        data = write_patch(surface, bits=bits)
        moved = PatchModel.from_surface(read_patch(data)).evaluate(u, v) - exact
        if np.sqrt(np.mean(np.einsum("ij,ij->i", moved, moved))) <= tolerance:
            chosen, hi = (bits, data), bits - 1
        else:
            lo = bits + 1
    return chosen or (BITS_RANGE[1], write_patch(surface, bits=BITS_RANGE[1]))
