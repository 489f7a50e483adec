"""The detail pyramid: what the base patch leaves of the scan, as displacement along its normal.

Every covered scan point ``P`` has a foot point ``(u, v)`` on the base ``S``
(``fitter.fitting.error.deviations``) and splits into a *normal* deviation ``s =
(P - S(u, v)) . n(u, v)`` and a tangential remainder ``t`` (zero when the foot
point is an exact orthogonal projection; not zero at the domain's border). The
refined surface ``X = S + D n`` with ``D = sum_k D_k`` reproduces ``P`` when
``D(u, v) = s``; its distance to ``P`` at the foot point is
``e = sqrt((s - D)^2 + t^2)``, an upper bound of the true distance from ``P`` to
the refined surface, and the figure reported here (RMS, max, per-tile
``geometric_error``).

Level ``k`` is a uniform B-spline field of degree ``p`` with ``m 2^k`` spans per
side (``client_py.layers.level_knots``), fitted by regularised sparse least
squares to what levels ``0..k-1`` left:

    min_c  sum_points (A c - r)^2 + mu (lambda_r |c|^2 + lambda_s (|L_u c|^2 + |L_v c|^2))

with ``A`` the collocation matrix (``(p+1)^2`` non-zeros per row), ``L_u, L_v``
second differences of the coefficient grid (a thin-plate term that keeps the
field smooth where points are sparse), a small ridge that takes it to zero
where there are none, and ``mu = trace(A^T A) / n_coefficients``. Coefficients
are quantised with a step proportional to the level's remaining RMS
(``step_factor``), and the residual is recomputed from the *quantised* field,
so every reported error is the error of the bytes on disk. The level is cut
into ``2^k x 2^k`` tiles (``client_py.layers.DetailTile``): tile ``(i, j)``
keeps the ``(m + p)^2`` coefficients whose support meets its rectangle; a tile
whose coefficients all quantise to zero is not written. With a periodic map
(cylinder) the coefficient columns at ``u = 0`` and ``u = 1`` are one unknown,
so the field, like the base, closes without a crack.

*Redrawn cells.* The base's trim leaves out the cells where the base strays
from the scan (``fitter.fitting.compact.drawn_cells``), and scan points whose foot
points fall there would stay unrepresented at every level. From the level whose
grid (``DRAWN_SIDE`` cells per tile side) is at least as fine as the trim, a
tile carries a ``drawn`` mask (:class:`Redraw`): the cells near the scan's foot
points, not drawn by the base, where the surface refined up to that level does
not stray (``ScanNeighbourhood.stray`` with that level's RMS).

*Walls.* Where the scan's height over the domain jumps (a range image's occluding
contour: the scanner saw a near and a far surface side by side) a cell of the base's
trim holds points of both, and the refined surface, following both, joins them with a
steep wall narrower than the cell; past the scan's open border it hangs a fin. The
drawn cells only grow from level to level, so after the last level the cells of the
finest level's grid where the mesh drawn of it strays from every point (beyond
``ScanNeighbourhood.wall_limit``) are left out of the base's trim, which is then kept at
that resolution (the pyramid's ``trim``), and out of every level's drawn mask
(:meth:`Redraw.walls`), the scan being the points the mesh's triangles use (a lone
sample the triangulation left out holds no surface up: :meth:`Redraw.from_foot_points`;
Buddha range scan 0, level 3: 1.15 -> 0.89 %). Only for a mesh: its triangulation leaves
a range image's jumps open, while a cloud cannot tell a wall from a steep face it samples
thinly, and the cells the finest level overshoots there become pinholes (the generated
example relief of ``make demo``, a cloud: 20 of its 65,536 finest cells; Buddha range
scan 0, a mesh: its largest distance to the scan 3.33 -> 1.16 % of the diagonal at level
3).

A coarser level draws walls of its own where the finest level's do not reach: its
smoother surface bridges the jump more widely (and, on a grid as coarse as two vertices
per knot span, its triangles join vertices on both sides of it even where the surface
does not). So each coarser level ``k``'s tiles carry a *walls mask*
(``client_py.layers.DetailTile``: the finest applied tile's walls mask leaves cells out,
whatever the trim and drawn masks say): the cells of the grid a client draws level ``k``
on (``client_py.bundle.level_resolution``, at least ``MIN_LEVEL_CELLS`` = 256 cells
across) among those it draws, where that mesh strays (:meth:`Redraw.walls`,
:func:`level_walls`), and every finer tile over them an all-clear mask, which gives them
back. Buddha range scan 0, levels 0/1/2, largest distance to the scan: 7.70/5.79/3.30 %
of the diagonal without walls masks, 2.00/1.56/1.33 % with them on grids of two vertices
per span (33/65/129 per side), 1.49/1.51/1.18 % on 257 (far area 2.6/0.91/0.15 ->
0.09/0.08/0.02 %; levels 0 and 1 then need no walls mask, level 2 five cells).
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from client_py import layers
from client_py._numpy_basis import basis_arrays
from client_py.bundle import level_resolution
from client_py.format import MAX_TILE_VALUE, MAX_WALLS_SIDE, TILE_VERSION, write_detail_tile
from client_py.trim import MAX_SIDE, TrimMask

from .compact import ScanNeighbourhood
from .nurbs import PatchModel
from .parameterize import trim_cells
from .spd import spd_lu

DEGREE = 2
SPANS = 16  # spans per tile side: (16 + 2)^2 = 324 coefficients a tile
STEP_FACTOR = 2.0  # quantisation step / the level's remaining RMS (docs/benchmarks.md)
RIDGE = 1e-4
SMOOTHING = 1e-3
MIN_POINTS_PER_CELL = 4.0  # auto depth: finest level keeps this many points per knot cell
MAX_AUTO_LEVELS = 6
DRAWN_SIDE = 32  # cells per side of a tile's drawn mask (any spans)
WALL_BAND = 64  # rows of cells whose walls Redraw.walls finds at once (bounds its memory)


@dataclass
class DetailSamples:
    """Foot points ``u, v (N,)``, normal deviations ``s (N,)`` and squared tangential
    remainders ``t2 (N,)`` of the scan points a pyramid is fitted to."""

    u: np.ndarray
    v: np.ndarray
    s: np.ndarray
    t2: np.ndarray

    def error(self, displacement: np.ndarray) -> np.ndarray:
        """``e = sqrt((s - D)^2 + t^2)`` per point."""
        return np.sqrt((self.s - displacement) ** 2 + self.t2)


@dataclass
class DetailLevel:
    """One fitted level: its tiles (written bytes) and the error after it."""

    level: int
    step: float
    tiles: list[tuple[layers.DetailTile, bytes, float]]  # tile, file bytes, geometric_error
    rms: float
    max: float
    coefficients: int

    @property
    def bytes_total(self) -> int:
        return sum(len(data) for _, data, _ in self.tiles)


@dataclass
class DetailPyramid:
    degree: int
    spans: int
    levels: list[DetailLevel] = field(default_factory=list)
    base_rms: float = 0.0
    base_max: float = 0.0
    # the base's trim without the finest level's walls (Redraw.trim_without; None: the
    # trim as it was) and how many of its cells they took
    trim: np.ndarray | None = None
    wall_cells: int = 0
    # per level, the cells of its own walls its tiles leave out (level_walls)
    level_wall_cells: list[int] = field(default_factory=list)


def detail_samples(model: PatchModel, points: np.ndarray, u: np.ndarray,
                   v: np.ndarray) -> DetailSamples:
    """Split ``points (N, 3)`` (patch frame) at their foot points ``u, v`` on ``model``
    into normal deviations and tangential remainders (see the module docstring)."""
    S, Su, Sv = model.evaluate(u, v, derivatives=True)
    s, t2 = normal_split(points, S, Su, Sv)
    return DetailSamples(np.asarray(u, float), np.asarray(v, float), s, t2)


def normal_split(points: np.ndarray, S: np.ndarray, Su: np.ndarray,
                 Sv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``s = (P - S) . n`` and ``t^2 = |P - S|^2 - s^2`` of points ``P (N, 3)`` at their foot
    points ``S`` with tangents ``Su, Sv`` (``n = Su x Sv / |Su x Sv|``; where the normal
    vanishes, a pole, all of ``|P - S|`` is normal)."""
    n = np.cross(Su, Sv)
    length = np.linalg.norm(n, axis=1)
    ok = length > 1e-12 * max(float(length.max(initial=0.0)), 1e-300)
    n = n / np.where(ok, length, 1.0)[:, None]
    r = points - S
    rr = np.einsum("ij,ij->i", r, r)
    s = np.where(ok, np.einsum("ij,ij->i", r, n), np.sqrt(rr))
    return s, np.maximum(rr - s * s, 0.0)


@dataclass
class Redraw:
    """Cells the base's trim leaves out that a detail level may draw again.

    ``model`` is the base, ``drawn (R, C)`` its trim (true where drawn),
    ``candidates (R, C)`` the left-out cells near foot points of covered scan
    points, ``near`` the scan (patch frame) and ``periodic_u`` the map's seam. ``mesh``:
    the scan is a mesh, whose walls are found (:meth:`walls`); a candidate cell then
    strays beyond the walls' limit (``ScanNeighbourhood.wall_limit``: twice the
    sampling's gaps, not its median spacing), as what strays less but still draws a wall
    is left out by the walls (Buddha range scan 0, level 3: within 0.5 % of the diagonal
    99.54 -> 99.60 %, largest distance 0.886 -> 0.879 %; every candidate drawn, left to
    the walls alone: 99.60 %, 1.07 %).
    """

    model: PatchModel
    drawn: np.ndarray
    candidates: np.ndarray
    near: ScanNeighbourhood
    periodic_u: bool = False
    mesh: bool = False

    @classmethod
    def from_foot_points(cls, model: PatchModel, drawn: np.ndarray, points: np.ndarray,
                         u: np.ndarray, v: np.ndarray, periodic_u: bool,
                         surface: np.ndarray | None = None) -> Redraw:
        """Candidates: the trim cells holding a foot point ``(u, v)`` of ``points (N, 3)``,
        with one-cell gaps closed (``fitter.fitting.parameterize.trim_cells``), not drawn.
        The scan :attr:`near` measures against: the ``points`` a mesh's triangles use
        (``surface (N,)`` booleans, given for a mesh: :attr:`mesh`; ``None``: every point
        of a cloud). A range image's triangulation
        leaves out samples it cannot join (a lone sample past an occluding contour): a
        surface drawn near one of them alone is not near the scan's surface (Buddha range
        scan 0: its 66 such points held level 3's largest distance, 1.15 % of the
        diagonal)."""
        rows, cols = drawn.shape
        feet = np.zeros_like(drawn)
        feet[np.minimum((u * rows).astype(np.int64), rows - 1),
             np.minimum((v * cols).astype(np.int64), cols - 1)] = True
        near = points if surface is None or not surface.any() else points[surface]
        return cls(model, drawn, trim_cells(feet, periodic_u) & ~drawn,
                   ScanNeighbourhood(near), periodic_u, surface is not None)

    def cells(self, level: int, fields: list[np.ndarray], degree: int, spans: int,
              rms: float) -> np.ndarray | None:
        """``(DRAWN_SIDE 2^level)^2`` booleans: candidate cells where the surface refined by
        ``fields`` (coefficients of levels ``0..level``) does not stray
        (``ScanNeighbourhood.stray``, with the walls' limit for a :attr:`mesh`); ``None``
        while the grid is coarser than the trim."""
        size = DRAWN_SIDE << level
        rows, cols = self.drawn.shape
        if size < max(rows, cols):
            return None
        centre = (np.arange(size) + 0.5) / size
        fine = self.candidates[np.ix_((centre * rows).astype(np.int64),
                                      (centre * cols).astype(np.int64))]
        r, c = np.nonzero(fine)
        far = self.near.stray(self._refined(fields, degree, spans), r, c, (size, size), rms,
                              gaps=self.mesh)
        out = np.zeros((size, size), bool)
        out[r[~far], c[~far]] = True
        return out

    def _refined(self, fields: list[np.ndarray], degree: int, spans: int):
        """``X(u, v) = S + sum_k D_k n``: the base refined by the levels ``fields``."""
        def refined(u: np.ndarray, v: np.ndarray) -> np.ndarray:
            S, Su, Sv = self.model.evaluate(u, v, derivatives=True)
            n = np.cross(Su, Sv)
            length = np.linalg.norm(n, axis=1, keepdims=True)
            n = np.divide(n, length, out=np.zeros_like(n), where=length > 0)
            d = sum(evaluate_level(f, k, degree, spans, u, v) for k, f in enumerate(fields))
            return S + d[:, None] * n
        return refined

    def walls(self, fields: list[np.ndarray], degree: int, spans: int, rms: float,
              size: int, trim: np.ndarray | None = None,
              drawn: list[np.ndarray] | None = None) -> np.ndarray:
        """``(size, size)`` booleans: the cells the base's trim (``trim``, as the bundle
        carries it: by default :attr:`drawn`) or a tile's drawn mask may draw where the mesh
        a client draws on the grid of ``size`` cells per side strays from the scan (beyond
        ``ScanNeighbourhood.wall_limit(rms)``). The drawn masks: ``drawn``, the full-domain
        masks of the levels applied with ``fields`` (:meth:`cells`, as the tiles carry
        them), or by default every :attr:`candidates` cell, which any level's mask is part
        of. A cell centre on the border of two mask cells (a finer trim:
        ``trim_without``) may be either's in a client's arithmetic, so both count.

        That mesh joins the refined surface's values ``X`` at the grid's vertices with two
        triangles a cell (``client_py._kernel_python.cell_indices``: the diagonal from
        ``(i + 1, j)`` to ``(i, j + 1)``); its probes are the four corners, the midpoints of
        the four sides and of the diagonal, and the two triangles' centroids. Where a cell
        straddles an occluding contour the corners lie on both surfaces and the triangles
        between them are a wall even where ``X`` itself has none: probes of ``X`` alone (at
        the cells' centres and corners) found no wall of a coarse level on a range image's
        step. The one rule for every level: the finest level's walls leave the base's trim
        (:func:`fit_pyramid`; Buddha range scan 0, level 3: largest distance 1.15 % of the
        diagonal, 1.16 % with ``X``'s probes), a coarser one's are its walls masks
        (:func:`level_walls`).
        """
        centre = (np.arange(size) + 0.5) / size
        may = np.zeros((size, size), bool)
        for mask in (self.drawn if trim is None else trim,
                     *((self.candidates,) if drawn is None else drawn)):
            for shift in (-1e-9, 1e-9):
                rows = np.clip(((centre + shift) * mask.shape[0]).astype(np.int64), 0,
                               mask.shape[0] - 1)
                cols = np.clip(((centre + shift) * mask.shape[1]).astype(np.int64), 0,
                               mask.shape[1] - 1)
                may |= mask[np.ix_(rows, cols)]
        refined, limit = self._refined(fields, degree, spans), self.near.wall_limit(rms)
        corner = np.arange(size + 1) / size

        def far_band(r0: int, r1: int) -> np.ndarray:
            u, v = np.meshgrid(corner[r0:r1 + 1], corner, indexing="ij")
            X = refined(u.ravel(), v.ravel()).reshape(*u.shape, 3)
            held = may[r0:r1]  # only the cells that may be drawn are probed
            a, b, c, d = (X[:-1, :-1][held], X[1:, :-1][held], X[:-1, 1:][held],
                          X[1:, 1:][held])  # corners (i, j) (i + 1, j) (i, j + 1) (i + 1, j + 1)
            hit = np.zeros(len(a), bool)
            for probe in (a, b, c, d, (a + b) / 2, (a + c) / 2, (b + d) / 2, (c + d) / 2,
                          (b + c) / 2, (a + b + c) / 3, (b + c + d) / 3):
                hit |= self.near.farther(probe, limit)
            far = np.zeros((r1 - r0, size), bool)
            far[held] = hit
            return far
        return _by_bands(may, far_band)

    def trim_without(self, walls: np.ndarray) -> np.ndarray | None:
        """The base's trim at the resolution of ``walls (R, R)`` (:meth:`walls`) without
        them; ``None`` when it draws none of them (the trim stays as it was)."""
        size = len(walls)
        rows, cols = self.drawn.shape
        centre = (np.arange(size) + 0.5) / size
        fine = self.drawn[np.ix_((centre * rows).astype(np.int64),
                                 (centre * cols).astype(np.int64))]
        if not (fine & walls).any():
            return None
        return fine & ~walls


def _by_bands(may: np.ndarray, far_band) -> np.ndarray:
    """``may & far`` for a ``(size, size)`` grid of cells, ``far_band(r0, r1)`` giving rows
    ``r0..r1-1`` of ``far``, ``WALL_BAND`` rows at a time (bounds the memory), skipping the
    bands where ``may`` holds nothing."""
    out = np.zeros_like(may)
    for r0 in range(0, len(may), WALL_BAND):
        r1 = min(r0 + WALL_BAND, len(may))
        if may[r0:r1].any():
            out[r0:r1] = far_band(r0, r1) & may[r0:r1]
    return out


def auto_levels(n_points: int, spans: int = SPANS) -> int:
    """Levels ``0..L-1`` with at least ``MIN_POINTS_PER_CELL`` points per knot cell."""
    levels = 0
    while levels < MAX_AUTO_LEVELS and n_points / (spans << levels) ** 2 >= MIN_POINTS_PER_CELL:
        levels += 1
    return levels


def collocation_matrix(degree: int, knots: np.ndarray, n: int, u: np.ndarray, v: np.ndarray,
                       periodic_u: bool = False, block: np.ndarray | None = None,
                       blocks: int = 1) -> sp.csr_matrix:
    """``A[k, a n + b] = N_a(u_k) N_b(v_k)`` (A2.2 per direction), ``(p + 1)^2`` entries a row.

    With ``block (N,)`` the field of sample ``k`` is grid ``block[k]`` of ``blocks`` grids
    stored one after the other: column ``block[k] n^2 + a n + b`` of ``blocks n^2`` (an
    atlas's patches, each with its own ``(n, n)`` coefficients).
    """
    su, Nu, _ = basis_arrays(degree, knots, n, u)
    sv, Nv, _ = basis_arrays(degree, knots, n, v)
    a = su[:, None] - degree + np.arange(degree + 1)
    if periodic_u:
        a = np.where(a == n - 1, 0, a)  # D(0, v) = D(1, v): one column of unknowns
    b = sv[:, None] - degree + np.arange(degree + 1)
    cols = (a[:, :, None] * n + b[:, None, :]).reshape(len(u), -1)
    if block is not None:
        cols = cols + (np.asarray(block, np.int64) * (n * n))[:, None]
    vals = (Nu[:, :, None] * Nv[:, None, :]).reshape(len(u), -1)
    k = cols.shape[1]
    return sp.csr_matrix((vals.ravel(), cols.ravel(), np.arange(0, len(u) * k + 1, k)),
                         shape=(len(u), blocks * n * n))



def normal_matrix(A: sp.csr_matrix) -> sp.csr_matrix:
    """``A^T A`` of a collocation matrix (``k`` entries a row, :func:`collocation_matrix`).

    Entry pair ``(i, j)`` of every row adds ``A_ki A_kj`` at ``(c_ki, c_kj)``; where the
    offset ``c_kj - c_ki`` is the same in every row (always, but for a periodic map's
    wrapped columns) the pair fills one diagonal, summed per column by ``bincount``: three
    times faster than the sparse product (0.6 s against 2.0 s for 888,000 rows, level 4).
    Pair ``(j, i)`` holds the same products as ``(i, j)`` in the same rows, so its column
    sums are those of ``(i, j)`` moved by the offset: only the ``k (k + 1) / 2`` pairs
    ``i <= j`` are summed (the same numbers, added in the same order).
    """
    m, columns = A.shape
    k = A.indptr[1] - A.indptr[0] if m else 0
    if m == 0 or not np.all(np.diff(A.indptr) == k):
        return (A.T @ A).tocsr()
    cols = np.ascontiguousarray(A.indices.reshape(m, k).T)  # entry i of every row
    vals = np.ascontiguousarray(A.data.reshape(m, k).T)
    # entry i's column less entry 0's: the same in every row unless a periodic map wraps, and
    # then so is every pair's offset (one check per entry instead of one per pair)
    steady = [bool(np.all(d == d[0])) for d in (cols[i] - cols[0] for i in range(k))]
    diagonals: dict[int, np.ndarray] = {}
    rows, cols_other, data = [], [], []
    pairs: dict[tuple[int, int], tuple] = {}  # (i, j), i <= j: (offset, column sums or products)
    for i in range(k):
        for j in range(k):
            first, second = min(i, j), max(i, j)
            if (first, second) not in pairs:
                products = vals[first] * vals[second]
                offset = cols[second, :1] - cols[first, :1]
                if not (steady[first] and steady[second]):
                    offset = cols[second] - cols[first]
                if np.all(offset == offset[0]):
                    pairs[first, second] = (int(offset[0]), np.bincount(
                        cols[first], weights=products, minlength=columns))
                else:
                    pairs[first, second] = (None, products)
            key, total = pairs[first, second]
            if key is None:
                rows.append(cols[i])
                cols_other.append(cols[j])
                data.append(total)
                continue
            if i > j:  # (i, j)'s sum at column c is (j, i)'s at column c + offset
                key, moved = -key, np.zeros(columns)
                moved[max(0, -key):columns - max(0, key)] = total[max(0, key):
                                                                 columns + min(0, key)]
                total = moved
            diagonals[key] = diagonals[key] + total if key in diagonals else total
    for key, total in diagonals.items():
        start = max(0, -key)
        stop = min(columns, columns - key)
        rows.append(np.arange(start, stop))
        cols_other.append(np.arange(start, stop) + key)
        data.append(total[start:stop])
    return sp.csr_matrix((np.concatenate(data), (np.concatenate(rows),
                                                 np.concatenate(cols_other))),
                         shape=(columns, columns))


def _second_differences(n: int) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    d2 = sp.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(n - 2, n))
    eye = sp.identity(n)
    return sp.kron(d2, eye).tocsr(), sp.kron(eye, d2).tocsr()


def regularisation(n: int) -> sp.csr_matrix:
    """``lambda_r I + lambda_s (L_u^T L_u + L_v^T L_v)`` of an ``(n, n)`` coefficient grid: the
    module docstring's penalty without its scale ``mu``, shape ``(n^2, n^2)``."""
    Lu, Lv = _second_differences(n)
    return RIDGE * sp.identity(n * n) + SMOOTHING * (Lu.T @ Lu + Lv.T @ Lv)


def fit_level(samples: DetailSamples, residual: np.ndarray, level: int, degree: int = DEGREE,
              spans: int = SPANS, periodic_u: bool = False,
              A: sp.csr_matrix | None = None, AtA: sp.csr_matrix | None = None) -> np.ndarray:
    """Unquantised coefficients ``(n, n)``, ``n = spans 2^level + degree``, of the level's
    field fitted to ``residual (N,)`` at the samples' ``(u, v)`` (see module docstring);
    ``A`` is the level's :func:`collocation_matrix` and ``AtA`` its :func:`normal_matrix`
    when the caller has them.

    The normal equations are symmetric positive definite: SuperLU factors them as a
    Cholesky factorisation (:func:`fitter.fitting.spd.spd_lu`: minimum degree on
    ``M^T + M``, no pivoting, SuperLU's own supernodes). With partial pivoting, as
    ``spsolve`` does, the generated relief's level 3 (40,000 points, 16,900 unknowns)
    took 37-47 s: its pivots left the diagonal where few points hold the coefficients;
    without, 0.5 s, the solution the same to 3e-15 relative (session 18)."""
    n = (spans << level) + degree
    if A is None:
        knots = np.array(layers.level_knots(degree, spans, level))
        A = collocation_matrix(degree, knots, n, samples.u, samples.v, periodic_u)
    if AtA is None:
        AtA = normal_matrix(A)
    mu = AtA.diagonal().sum() / (n * n)
    M = AtA + mu * regularisation(n)
    c = spd_lu(M, single_columns=False).solve(A.T @ residual).reshape(n, n)
    if periodic_u:
        c[n - 1] = c[0]
    return c


def evaluate_level(coefficients: np.ndarray, level: int, degree: int, spans: int,
                   u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``D_k(u, v)`` of a coefficient grid ``(n, n)`` at scattered parameters."""
    n = coefficients.shape[0]
    knots = np.array(layers.level_knots(degree, spans, level))
    return collocation_matrix(degree, knots, n, u, v, False) @ coefficients.ravel()


def _tile_index(t: np.ndarray, level: int) -> np.ndarray:
    count = 1 << level
    return np.minimum((t * count).astype(np.int64), count - 1)


def quantisation_step(rms_fit: float, coefficient_max: float, residual_max: float,
                      step_factor: float = STEP_FACTOR) -> float:
    """The level's quantisation step: ``step_factor`` times the RMS its unquantised field
    leaves (``rms_fit``), as single precision (as ``.tsd`` stores it).

    An exactly explained residual still needs a positive step (``1e-9`` of the largest
    coefficient or residual ``|.|``; and zero explains zero: step 1); a step that would
    quantise the largest coefficient beyond ``MAX_TILE_VALUE`` is raised to fit it (never
    for a real scan: the tiles stay valid).
    """
    floor = 1e-9 * max(coefficient_max, residual_max)
    step = layers.single(step_factor * max(rms_fit, floor) or 1.0)
    if np.rint(coefficient_max / step) > MAX_TILE_VALUE:
        step = layers.single(coefficient_max / MAX_TILE_VALUE * (1 + 1e-6))
    return step


def level_tiles(q: np.ndarray, step: float, level: int, degree: int, spans: int,
                u: np.ndarray, v: np.ndarray, e: np.ndarray,
                drawn: np.ndarray | None = None, encode: bool = True,
                walls: tuple[np.ndarray, np.ndarray] | None = None
                ) -> list[tuple[layers.DetailTile, bytes | None, float]]:
    """Cut a level's quantised coefficients ``q (n, n)`` into its ``2^level x 2^level`` tiles.

    Tile ``(i, j)`` keeps ``q[i m : i m + m + p, j m : j m + m + p]``; its
    ``geometric_error`` is the largest ``e (N,)`` of the samples ``(u, v) (N,)`` inside its
    rectangle (0 without any). A tile whose values are all zero (and without a ``drawn``
    mask, the ``(DRAWN_SIDE 2^level)^2`` cells of :meth:`Redraw.cells`) is not written.
    With ``walls = (cells, keep)`` (:func:`level_walls`), tile ``(i, j)`` carries its block
    of ``cells (W 2^level, W 2^level)`` as its walls mask where the block has a wall or
    ``keep[i, j]``, and is then written.

    Returns
    -------
    list of (DetailTile, bytes, float)
        Each tile, its ``.tsd`` bytes (``None`` with ``encode=False``: a caller that packs
        the tiles itself) and its ``geometric_error``, in ``(i, j)`` order.
    """
    count = 1 << level
    cell = _tile_index(u, level) * count + _tile_index(v, level)
    worst = np.zeros(count * count)
    np.maximum.at(worst, cell, e)
    tiles = []
    size = spans + degree
    for i in range(count):
        for j in range(count):
            block = q[i * spans : i * spans + size, j * spans : j * spans + size]
            mask = None
            if drawn is not None:
                mask = drawn[i * DRAWN_SIDE : (i + 1) * DRAWN_SIDE,
                             j * DRAWN_SIDE : (j + 1) * DRAWN_SIDE]
                mask = TrimMask(mask) if mask.any() else None
            wall = None
            if walls is not None:
                side = len(walls[0]) >> level
                wall = walls[0][i * side : (i + 1) * side, j * side : (j + 1) * side]
                wall = TrimMask(wall) if wall.any() or walls[1][i, j] else None
            if not block.any() and mask is None and wall is None:
                continue
            tile = layers.DetailTile(level, i, j, degree, spans, step,
                                     tuple(int(x) for x in block.ravel()), mask, wall)
            tiles.append((tile, write_detail_tile(tile) if encode else None,
                          float(worst[i * count + j])))
    return tiles


def fit_pyramid(samples: DetailSamples, levels: int, degree: int = DEGREE, spans: int = SPANS,
                step_factor: float = STEP_FACTOR, periodic_u: bool = False,
                progress=None, redraw: Redraw | Future | None = None,
                background: ThreadPoolExecutor | None = None,
                find_walls: bool = True) -> DetailPyramid:
    """Fit levels ``0..levels-1`` coarse to fine; each fits what the coarser ones left.

    Returns the tiles to write (with their bytes and ``geometric_error``: max
    ``e`` of the points inside the tile's rectangle after levels ``0..k``) and
    per level the RMS and max of ``e`` over all samples. With ``redraw`` (or the future of
    one) the tiles carry drawn masks (module docstring), and with ``find_walls`` the finest
    level's walls are left out of them and of the base's trim, and the coarser levels'
    travel in their walls masks (:meth:`Redraw.walls`, :func:`level_walls`).

    The work is shared with one ``background`` thread (a new one by default): it makes the
    even levels' matrices (:func:`level_matrices`: they depend on the samples alone) while
    this thread makes the odd levels' and solves (SuperLU frees the GIL), then each level's
    tiles (:func:`_level_result`). The numbers are those of one thread doing it all in turn.
    """
    if not (isinstance(levels, int) and 0 <= levels <= layers.MAX_LEVEL + 1):  # 0..MAX_LEVEL
        raise ValueError(f"levels must be an integer in 0..{layers.MAX_LEVEL + 1}, "
                         f"got {levels!r}")
    if not step_factor > 0:
        raise ValueError(f"step_factor must be positive, got {step_factor!r}")
    if background is None:
        with ThreadPoolExecutor(1) as background:
            return fit_pyramid(samples, levels, degree, spans, step_factor, periodic_u,
                               progress, redraw, background, find_walls)
    pyramid = DetailPyramid(degree, spans)
    residual = samples.s.copy()
    e = samples.error(np.zeros_like(residual))
    pyramid.base_rms, pyramid.base_max = float(np.sqrt(np.mean(e**2))), float(e.max())
    fields: list[np.ndarray] = []
    results: list[Future] = []
    # the even levels' matrices on the background thread, in order, the odd levels' here:
    # the finest level's (the largest) are then ready when the coarser ones are solved
    made = {k: background.submit(level_matrices, samples, k, degree, spans, periodic_u)
            for k in range(0, levels, 2)}
    for k in range(levels):
        A, E, AtA = (made.pop(k).result() if k in made
                     else level_matrices(samples, k, degree, spans, periodic_u))
        c = fit_level(samples, residual, k, degree, spans, periodic_u, A, AtA)
        fitted = residual - E @ c.ravel()
        rms_fit = float(np.sqrt(np.mean(fitted**2 + samples.t2)))
        step = quantisation_step(rms_fit, float(np.abs(c).max(initial=0.0)),
                                 float(np.abs(residual).max()), step_factor)
        q = np.rint(c / step).astype(np.int64)
        fields.append(q * step)
        residual = residual - E @ fields[-1].ravel()
        del A, E, AtA, fitted
        results.append(background.submit(_level_result, samples, residual, q, step, k, degree,
                                         spans, list(fields), redraw))
        if progress is not None:
            progress((k + 1) / levels)
    done = [result.result() for result in results]
    pyramid.levels = [level for level, _, _ in done]
    if isinstance(redraw, Future):
        redraw = redraw.result()
    if find_walls and redraw is not None and levels:
        walls = redraw.walls(fields, degree, spans, pyramid.levels[-1].rms,
                                  min(DRAWN_SIDE << (len(fields) - 1), MAX_SIDE))
        pyramid.trim = redraw.trim_without(walls)
        pyramid.wall_cells = int(walls.sum())
        thinned = [_without_walls(drawn, walls) for _, drawn, _ in done]
        coarser = level_walls(redraw, fields, degree, spans,
                              [level.rms for level in pyramid.levels], walls, pyramid.trim,
                              thinned)
        pyramid.level_wall_cells = [int(w[0].sum()) for w in coarser]
        for k, (level, drawn, e) in enumerate(done):
            if thinned[k] is not drawn or coarser[k][1].any() or coarser[k][0].any():
                # this level's mask drew some of them, or it has walls (or must undo a
                # coarser level's): tiles anew
                q = np.rint(fields[k] / level.step).astype(np.int64)
                level.tiles = level_tiles(q, level.step, k, degree, spans, samples.u,
                                          samples.v, e, thinned[k], walls=coarser[k])
    return pyramid


def level_walls(redraw: Redraw, fields: list[np.ndarray], degree: int, spans: int,
                rms: list[float], finest: np.ndarray, trim: np.ndarray | None = None,
                drawn: list[np.ndarray | None] | None = None
                ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per level ``k`` the walls its tiles carry (:class:`client_py.layers.DetailTile`,
    ``walls``): ``(cells, keep)``.

    ``cells (W_k, W_k)``: :meth:`Redraw.walls` of the surface refined by
    ``fields[:k + 1]`` (level ``k``'s ``rms[k]``) on the grid a client draws level ``k``
    on (``client_py.bundle.level_resolution``: ``W_k = c_k 2^k`` cells, ``c_k = 2 m 2^j``
    per tile side with ``W_k >= MIN_LEVEL_CELLS``, at most ``MAX_WALLS_SIDE 2^k``), among
    the cells it draws: the trim and the drawn masks of levels ``0..k`` (``drawn``, per
    level its full-domain mask or ``None``; by default every candidate cell). A level
    whose grid is finer than its drawn masks draws no cell a coarser one's walls mask must
    leave out: Buddha range scan 0, levels 0/1 on 256 cells, 1,617/1,600 wall cells, all
    in candidate cells no mask of theirs draws, 432/441 B of walls masks that changed no
    triangle. None for the finest level, whose walls (``finest``, found by
    :meth:`Redraw.walls`) are already out of the base's trim (``trim``: the pyramid's) and
    so of every level. ``keep (2^k, 2^k)``: the tiles whose
    rectangle holds a coarser level's walls, which carry a walls mask even without walls
    of their own, to draw again what the coarser one left out (a tessellation takes the
    finest given walls mask: ``client_py.layers.walls_vetoes``).
    """
    last = len(fields) - 1
    out, taken = [], []  # taken: per coarser level, its walls at its resolution
    for k in range(len(fields)):
        size = min(level_resolution(spans, k) - 1, MAX_WALLS_SIDE << k)
        if k < last:
            masks = None if drawn is None else [d for d in drawn[: k + 1] if d is not None]
            cells = redraw.walls(fields[: k + 1], degree, spans, rms[k], size, trim, masks)
        else:
            cells = np.zeros((size, size), bool)
        count = 1 << k
        keep = np.zeros((count, count), bool)
        for w in taken:
            keep |= coarsened(w, count)
        out.append((cells, keep))
        taken.append(cells)
    return out


def coarsened(cells: np.ndarray, size: int) -> np.ndarray:
    """``(size, size)`` booleans: which blocks of ``cells (R, R)`` (``size`` divides ``R``,
    or ``R`` divides ``size``: each cell then repeated) hold a true cell."""
    r = len(cells)
    if r >= size:
        block = r // size
        return cells.reshape(size, block, size, block).any(axis=(1, 3))
    return np.repeat(np.repeat(cells, size // r, axis=0), size // r, axis=1)


def _without_walls(drawn: np.ndarray | None, walls: np.ndarray) -> np.ndarray | None:
    """A level's drawn mask ``(D, D)`` without the cells holding a cell of ``walls (R, R)``
    (:meth:`Redraw.walls`); ``drawn`` itself when it has none, or when it is finer than
    ``walls`` (a level past ``client_py.trim.MAX_SIDE``: its own stray test stands)."""
    if drawn is None or len(drawn) > len(walls):
        return drawn
    block = len(walls) // len(drawn)
    hit = walls.reshape(len(drawn), block, len(drawn), block).any(axis=(1, 3))
    return drawn & ~hit if (drawn & hit).any() else drawn


def _level_result(samples: DetailSamples, residual: np.ndarray, q: np.ndarray, step: float,
                  level: int, degree: int, spans: int, fields: list[np.ndarray],
                  redraw: Redraw | Future | None
                  ) -> tuple[DetailLevel, np.ndarray | None, np.ndarray]:
    """Level ``level`` of :func:`fit_pyramid` once its quantised coefficients ``q`` (the
    field ``fields[-1] = q step``) left ``residual``: the level with its tiles, its drawn
    mask (:meth:`Redraw.cells`) and the samples' errors after it."""
    e = samples.error(samples.s - residual)
    rms = float(np.sqrt(np.mean(e**2)))
    if isinstance(redraw, Future):
        redraw = redraw.result()
    drawn = None if redraw is None else redraw.cells(level, fields, degree, spans, rms)
    tiles = level_tiles(q, step, level, degree, spans, samples.u, samples.v, e, drawn)
    return (DetailLevel(level, step, tiles, rms, float(e.max()), int(np.count_nonzero(q))),
            drawn, e)


def level_matrices(samples: DetailSamples, level: int, degree: int, spans: int,
                   periodic_u: bool) -> tuple[sp.csr_matrix, sp.csr_matrix, sp.csr_matrix]:
    """A level's :func:`collocation_matrix` ``A``, the matrix ``E`` of its field's values at
    the samples (``A`` but for a periodic map, whose columns wrap while its field does not)
    and :func:`normal_matrix` ``A^T A``: they depend on the samples alone, so
    :func:`fit_pyramid` makes some levels' on a second thread."""
    n = (spans << level) + degree
    knots = np.array(layers.level_knots(degree, spans, level))
    A = collocation_matrix(degree, knots, n, samples.u, samples.v, periodic_u)
    E = collocation_matrix(degree, knots, n, samples.u, samples.v) if periodic_u else A
    return A, E, normal_matrix(A)


# ------------------------------------------------------------------ the bundle's tile tree
def fit_detail(model: PatchModel, points_local: np.ndarray, dev, covered: np.ndarray,
               periodic_u: bool, levels: int | None = None, progress=None,
               step_factor: float = STEP_FACTOR, trim: TrimMask | None = None,
               spans: int = SPANS, find_walls: bool = True,
               surface: np.ndarray | None = None) -> DetailPyramid:
    """The pipeline's detail stage: samples of the covered points at their foot points
    ``dev.u, dev.v`` on the decoded base ``model``, then :func:`fit_pyramid`
    (``levels=None``: :func:`auto_levels`) with ``spans`` per tile side; ``trim`` is
    the base's trim mask, which the tiles' drawn masks complete (:class:`Redraw`), and
    which loses the finest level's walls (:meth:`Redraw.walls`: the pyramid's ``trim``)
    with ``find_walls`` (the module docstring says when); ``surface (N,)`` marks the points
    a mesh's triangles use (:meth:`Redraw.from_foot_points`; ``None``: every point)."""
    if levels is None:
        levels = auto_levels(int(covered.sum()), spans)
    if levels == 0:  # no pyramid: the base error is the foot-point deviation itself
        d = np.abs(dev.d[covered])
        return DetailPyramid(DEGREE, spans, base_rms=float(np.sqrt(np.mean(d**2))),
                             base_max=float(d.max(initial=0.0)))
    points = points_local[covered]
    u, v = np.asarray(dev.u[covered], float), np.asarray(dev.v[covered], float)
    with ThreadPoolExecutor(1) as background:  # the redraw's k-d tree beside the samples
        # without a trim every cell is drawn: nothing to draw again, but the walls to find
        drawn = (np.ones((1, 1), bool) if trim is None else
                 np.frombuffer(trim.flat, np.uint8).reshape(trim.rows, trim.cols).astype(bool))
        redraw = background.submit(Redraw.from_foot_points, model, drawn, points, u, v,
                                   periodic_u, None if surface is None else surface[covered])
        samples = detail_samples(model, points, u, v)
        return fit_pyramid(samples, levels, spans=spans, periodic_u=periodic_u,
                           progress=progress, step_factor=step_factor, redraw=redraw,
                           background=background, find_walls=find_walls)


def _rounded(x: float) -> float:
    return float(f"{x:.6g}")


def write_layers(root, pyramid: DetailPyramid, texture_tiles: list) -> tuple[dict, dict]:
    """Write ``detail/K/I_J.tsd`` and ``texture/K/I_J.<ext>`` under ``root``; return the
    manifest's ``tiles`` tree and ``{file: bytes}`` (schema: docs/format.md, "Tiles")."""
    from pathlib import Path

    root = Path(root)
    files: dict[str, int] = {}
    nodes, summary = [], []
    for lev in pyramid.levels:
        for tile, data, worst in lev.tiles:
            name = f"detail/{tile.level}/{tile.i}_{tile.j}.tsd"
            (root / name).parent.mkdir(parents=True, exist_ok=True)
            (root / name).write_bytes(data)
            files[name] = len(data)
            nodes.append({"level": tile.level, "i": tile.i, "j": tile.j,
                          "uv": list(tile.uv_rect), "file": name, "bytes": len(data),
                          "geometric_error": _rounded(worst)})
        # the grid a client draws the level on, which its walls masks were found on: its
        # presence tells a reader the bundle is drawn by the rule of session 13
        summary.append({"level": lev.level, "tiles": len(lev.tiles), "rms": _rounded(lev.rms),
                        "max": _rounded(lev.max), "bytes_total": lev.bytes_total,
                        "step": _rounded(lev.step), "coefficients": lev.coefficients,
                        "resolution": level_resolution(pyramid.spans, lev.level)})
    tree: dict = {"version": 1, "detail": {
        "format": "tsd", "format_version": TILE_VERSION, "degree": pyramid.degree,
        "spans_per_tile": pyramid.spans,
        "base": {"rms": _rounded(pyramid.base_rms), "max": _rounded(pyramid.base_max)},
        "levels": summary, "nodes": nodes}, "texture": None}
    if texture_tiles:
        t_nodes, t_levels = [], {}
        for t in texture_tiles:
            name = f"texture/{t.level}/{t.i}_{t.j}.{t.ext}"
            (root / name).parent.mkdir(parents=True, exist_ok=True)
            (root / name).write_bytes(t.data)
            files[name] = len(t.data)
            t_nodes.append({"level": t.level, "i": t.i, "j": t.j,
                            "uv": list(layers.tile_rect(t.level, t.i, t.j)), "file": name,
                            "bytes": len(t.data)})
            entry = t_levels.setdefault(t.level, {"level": t.level, "tiles": 0, "bytes_total": 0})
            entry["tiles"] += 1
            entry["bytes_total"] += len(t.data)
        tree["texture"] = {"format": texture_tiles[0].ext, "size": texture_tiles[0].size,
                           "levels": [t_levels[k] for k in sorted(t_levels)], "nodes": t_nodes}
    return tree, files
