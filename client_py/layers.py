"""Detail and texture layers superimposed on a base patch: the zoom path of the viewer.

A bundle's base patch ``S(u, v)`` is refined by a pyramid of *detail levels*:
level ``k`` is a scalar uniform B-spline field ``D_k`` over the normalised
domain ``[0, 1]^2`` with ``m 2^k`` spans per side (``m`` = spans per tile),
cut into ``2^k x 2^k`` tiles; the refined surface is the displacement along
the base's unit normal ``n``

    X(u, v) = S(u, v) + sum_k D_k(u, v) n(u, v).

Tile ``(i, j)`` of level ``k`` covers ``[i / 2^k, (i + 1) / 2^k] x [j / 2^k,
(j + 1) / 2^k]`` and stores the ``(m + p)^2`` coefficients whose support meets
it (:class:`DetailTile`); neighbouring tiles store the ``p`` shared rows with the
same quantised values, so both evaluate the same field on their common border
and no crack opens where both are applied. A tile absent from the bundle is a
zero field. *Texture tiles* (:class:`TextureImage`) are RGB images over the same
quadtree rectangles. :func:`tessellate_region` evaluates the base on a grid
over a uv rectangle, adds every given detail tile where it applies and samples
the finest given texture tile for vertex colours. Pure Python (numpy only
through ``client_py._kernel``), no I/O: the bytes come from
``client_py.format.read_detail_tile``.
"""

from __future__ import annotations

import math
import struct
from array import array
from bisect import bisect_left, bisect_right
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from . import _kernel
from .basis import basis_functions, find_span
from .surface import NurbsSurface
from .tessellate import (
    Mesh,
    _check_count,
    _samples,
    grid_indices,
    grid_uvs,
    mask_indices,
    pole_normals,
)
from .trim import TrimMask

#: deepest detail level: the fitter writes at most 8 levels, 0..7
#: (``fitter.fitting.options``: ``detail_levels <= 8``); a level's knot vector has
#: ``m 2^k + 2p + 1`` knots, so the level bounds what a tile can make a reader allocate
MAX_LEVEL = 7
MAX_DETAIL_DEGREE = 3
#: spans per tile side: the fitter's largest (``detail_spans <= 64``); a tile holds
#: ``(m + p)^2`` values, so this bounds a tile's decoding
MAX_SPANS = 64

UVRect = tuple[float, float, float, float]


def single(x: float) -> float:
    """``x`` rounded to the nearest IEEE single-precision value (``.tsd`` stores steps so)."""
    try:
        return struct.unpack("<f", struct.pack("<f", x))[0]
    except OverflowError:
        return math.inf


def level_knots(degree: int, spans_per_tile: int, level: int) -> list[float]:
    """Clamped uniform knot vector of level ``level``'s field over ``[0, 1]``.

    ``S = spans_per_tile 2^level`` spans: ``(0,) * p + (s / S for s = 0..S) + (1,) * p``,
    ``S + 2p + 1`` knots for ``S + p`` coefficients per side. Tile borders
    ``i / 2^level`` are knots ``p + i m`` and exact in binary64.
    """
    spans = spans_per_tile << level
    return [0.0] * degree + [s / spans for s in range(spans + 1)] + [1.0] * degree


def tile_knots(degree: int, spans_per_tile: int, level: int, index: int) -> tuple[float, ...]:
    """Tile ``index``'s slice of :func:`level_knots`: knots ``index m .. index m + m + 2p``
    (``m + 2p + 1`` of them), the same floats, computed without the whole vector.

    Knot ``k`` of the level is ``0`` for ``k < p``, ``(k - p) / S`` up to ``k = p + S``
    and ``1`` beyond (``S = m 2^level``).
    """
    spans = spans_per_tile << level
    first = index * spans_per_tile
    return tuple(0.0 if k < degree else 1.0 if k > degree + spans else (k - degree) / spans
                 for k in range(first, first + spans_per_tile + 2 * degree + 1))


def tile_rect(level: int, i: int, j: int) -> UVRect:
    """``(u0, v0, u1, v1)`` of quadtree node ``(level, i, j)`` in the normalised domain."""
    n = 1 << level
    return (i / n, j / n, (i + 1) / n, (j + 1) / n)


def _check_int(name: str, value: object, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise ValueError(f"{name} must be an integer in {lo}..{hi}, got {value!r}")
    return value


def _check_node(level: object, i: object, j: object) -> None:
    _check_int("level", level, 0, MAX_LEVEL)
    _check_int("i", i, 0, (1 << level) - 1)
    _check_int("j", j, 0, (1 << level) - 1)


@dataclass(frozen=True)
class DetailTile:
    """One tile of a detail level: quantised B-spline coefficients over its rectangle.

    The field inside ``uv_rect`` is ``D(u, v) = sum_a sum_b N_a(u) N_b(v) step q_ab``
    with the basis of :func:`level_knots` ``(degree, spans, level)``; ``values``
    are the integers ``q_ab``, row-major over ``(size, size)``, ``size = spans +
    degree``, ``a`` along ``u``: global coefficient ``(i spans + a, j spans + b)``.

    Attributes
    ----------
    level, i, j : int
        Quadtree node: ``0 <= i, j < 2^level``.
    degree : int
        ``p`` in ``1..3``.
    spans : int
        Knot spans per tile side ``m`` in ``1..255``.
    step : float
        Quantisation step (scan units of the patch frame), ``> 0``; rounded to
        the nearest single-precision float (:func:`single`), as ``.tsd`` stores it.
    values : tuple of int
        ``size^2`` quantised coefficients.
    drawn : TrimMask, optional
        Cells of ``uv_rect`` (row ``r`` along ``u``) that the refined surface
        draws from this level on although the base's trim leaves them out: where
        the base strayed from the scan but the displacement brought it back
        (``fitter.fitting.detail``). A tessellation applying the tile draws a cell whose
        centre the base trim *or* this mask covers.
    walls : TrimMask, optional
        Cells of ``uv_rect`` (any square side) where the surface refined up to this
        level strays from the scan: a wall across an occluding contour
        (``fitter.fitting.detail``, "Walls"). A tessellation leaves out a cell whose
        centre the walls mask of the *finest* given tile carrying one covers, even where
        the base trim or a drawn mask covers it; a finer tile's walls mask (all clear,
        if need be) thus restores what a coarser level's walls took away.
    """

    level: int
    i: int
    j: int
    degree: int
    spans: int
    step: float
    values: tuple[int, ...]
    drawn: TrimMask | None = None
    walls: TrimMask | None = None
    _knots: tuple = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        _check_node(self.level, self.i, self.j)
        _check_int("degree", self.degree, 1, MAX_DETAIL_DEGREE)
        _check_int("spans", self.spans, 1, MAX_SPANS)
        if not (isinstance(self.step, float | int) and math.isfinite(self.step)
                and self.step > 0):
            raise ValueError(f"step must be a positive finite number, got {self.step!r}")
        object.__setattr__(self, "step", single(self.step))
        if not (math.isfinite(self.step) and self.step > 0):
            raise ValueError(f"step {self.step!r} is beyond single precision")
        values = tuple(self.values)
        if len(values) != self.size**2 or not all(isinstance(q, int) for q in values):
            raise ValueError(f"values must be {self.size}^2 = {self.size**2} integers, "
                             f"got {len(values)} items")
        object.__setattr__(self, "values", values)
        if self.drawn is not None and not isinstance(self.drawn, TrimMask):
            raise ValueError(f"drawn must be a TrimMask or None, got {type(self.drawn).__name__}")
        if self.walls is not None and not isinstance(self.walls, TrimMask):
            raise ValueError(f"walls must be a TrimMask or None, got {type(self.walls).__name__}")
        object.__setattr__(self, "_knots",
                           (tile_knots(self.degree, self.spans, self.level, self.i),
                            tile_knots(self.degree, self.spans, self.level, self.j)))

    @property
    def size(self) -> int:
        """Coefficients per side, ``spans + degree``."""
        return self.spans + self.degree

    @property
    def uv_rect(self) -> UVRect:
        """``(u0, v0, u1, v1)``: where the tile applies, in the normalised domain."""
        return tile_rect(self.level, self.i, self.j)

    @property
    def knots(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """The tile's slices ``(U, V)`` of its level's knot vector (``size + p + 1`` each)."""
        return self._knots

    @property
    def coefficients(self) -> list[float]:
        """``step q_ab``, row-major."""
        return [q * self.step for q in self.values]

    def contains(self, u: float, v: float) -> bool:
        """Whether ``(u, v)`` lies in the closed rectangle ``uv_rect``."""
        u0, v0, u1, v1 = self.uv_rect
        return u0 <= u <= u1 and v0 <= v <= v1

    def evaluate(self, u: float, v: float) -> float:
        """``D(u, v)`` at one point of ``uv_rect`` (A2.1, A2.2); ``ValueError`` outside it."""
        u, v = float(u), float(v)
        if not self.contains(u, v):
            raise ValueError(f"({u}, {v}) lies outside tile {self.level}/{self.i}_{self.j}'s "
                             f"rectangle {self.uv_rect}")
        p, n = self.degree, self.size
        U, V = self._knots
        su, sv = find_span(p, U, n, u), find_span(p, V, n, v)
        Nu, Nv = basis_functions(p, U, su, u), basis_functions(p, V, sv, v)
        total = 0.0
        for a in range(p + 1):
            row = (su - p + a) * n + sv - p
            total += Nu[a] * sum(Nv[b] * self.values[row + b] for b in range(p + 1))
        return total * self.step

    def evaluate_grid(self, us: Sequence[float], vs: Sequence[float],
                      kernel: str | None = None) -> array:
        """``D(u_i, v_j)`` for parameters inside ``uv_rect``: ``array('d')``, row-major in ``i``."""
        U, V = self._knots
        return _kernel.backend(kernel).field_grid(self.degree, U, V, self.size, self.size,
                                                  self.coefficients, us, vs)


@dataclass(frozen=True)
class TextureImage:
    """A decoded texture tile: 8-bit RGB over quadtree node ``(level, i, j)``.

    Pixel ``(x, y)`` (``y = 0`` the top row) is centred at ``u = u0 + (x + 1/2)
    (u1 - u0) / width``, ``v = v1 - (y + 1/2) (v1 - v0) / height``: ``u`` to the
    right, ``v`` up, as GL texture coordinates ``s = (u - u0) / (u1 - u0)``,
    ``t = (v - v0) / (v1 - v0)`` address an image uploaded top row first with
    ``flipY`` (three.js's default). ``rgb`` holds ``3 width height`` bytes, rows
    top to bottom. (client_py decodes no images: the browser or Pillow does.)
    """

    level: int
    i: int
    j: int
    width: int
    height: int
    rgb: bytes

    def __post_init__(self) -> None:
        _check_node(self.level, self.i, self.j)
        _check_int("width", self.width, 1, 1 << 15)
        _check_int("height", self.height, 1, 1 << 15)
        if len(self.rgb) != 3 * self.width * self.height:
            raise ValueError(f"rgb has {len(self.rgb)} bytes; a {self.width}x{self.height} "
                             f"RGB image needs {3 * self.width * self.height}")

    @property
    def uv_rect(self) -> UVRect:
        return tile_rect(self.level, self.i, self.j)

    def contains(self, u: float, v: float) -> bool:
        u0, v0, u1, v1 = self.uv_rect
        return u0 <= u <= u1 and v0 <= v <= v1

    def sample(self, u: float, v: float) -> tuple[int, int, int]:
        """Bilinear RGB at ``(u, v)`` (clamped to the edge texels), rounded to bytes."""
        u0, v0, u1, v1 = self.uv_rect
        x = (u - u0) / (u1 - u0) * self.width - 0.5
        y = (v1 - v) / (v1 - v0) * self.height - 0.5
        x = min(max(x, 0.0), self.width - 1.0)
        y = min(max(y, 0.0), self.height - 1.0)
        x0, y0 = min(int(x), self.width - 2) if self.width > 1 else 0, \
            min(int(y), self.height - 2) if self.height > 1 else 0
        fx, fy = x - x0, y - y0
        x1, y1 = min(x0 + 1, self.width - 1), min(y0 + 1, self.height - 1)
        rgb, w = self.rgb, self.width
        out = []
        for c in range(3):
            top = rgb[3 * (y0 * w + x0) + c] * (1 - fx) + rgb[3 * (y0 * w + x1) + c] * fx
            bottom = rgb[3 * (y1 * w + x0) + c] * (1 - fx) + rgb[3 * (y1 * w + x1) + c] * fx
            out.append(int(top * (1 - fy) + bottom * fy + 0.5))
        return out[0], out[1], out[2]


def _check_rect(uv_rect: object) -> UVRect:
    try:
        u0, v0, u1, v1 = (float(x) for x in uv_rect)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ValueError(f"uv_rect must be four numbers (u0, v0, u1, v1), got {uv_rect!r}"
                         ) from None
    if not (0.0 <= u0 < u1 <= 1.0 and 0.0 <= v0 < v1 <= 1.0):
        raise ValueError(f"uv_rect {uv_rect!r} must satisfy 0 <= u0 < u1 <= 1 and "
                         "0 <= v0 < v1 <= 1")
    return u0, v0, u1, v1


def displacement_levels(tiles: Iterable[DetailTile], us: Sequence[float], vs: Sequence[float],
                        kernel: str | None = None) -> list[tuple[int, array]]:
    """``[(k, D_k(u_i, v_j)), ...]``: each given level's field on a grid, levels increasing.

    Each field is ``array('d')``, row-major in ``i``; a tile adds its field at
    the grid vertices inside its closed rectangle (found by bisection: ``us``
    and ``vs`` are sorted normalised parameters), ``+0.0`` elsewhere; a vertex on
    the border of several tiles of one level takes that level's field once,
    from the first of them in ``(i, j)`` order (they agree there). The kernel
    assembles a level's tile fields as whole blocks (``add_level``).
    """
    return _displacement_levels([tiles], us, vs, kernel)[0]


def _displacement_levels(tile_lists: Sequence[Iterable[DetailTile]], us: Sequence[float],
                         vs: Sequence[float], kernel: str | None
                         ) -> list[list[tuple[int, array]]]:
    """:func:`displacement_levels` of each list of tiles on one grid. The tiles of all the
    lists that share their knots, size and block of the grid are evaluated in one kernel
    call (``field_grids``: the same bits as one call per tile), which is what many small
    patches with a tile each need (``client_py.atlas_mesh``)."""
    us, vs = [float(u) for u in us], [float(v) for v in vs]
    n_j = len(vs)
    backend = _kernel.backend(kernel)
    plans = []  # per list, per level: (level, [(r0, r1, c0, c1, tile), ...])
    batches: dict[tuple, list[DetailTile]] = {}  # tiles evaluated together
    for tiles in tile_lists:
        by_level: dict[int, list[DetailTile]] = {}
        for tile in tiles:
            if not isinstance(tile, DetailTile):
                raise ValueError(f"tiles must be DetailTile objects, got {type(tile).__name__}")
            by_level.setdefault(tile.level, []).append(tile)
        plan = []
        for level in sorted(by_level):
            blocks = []
            seen: set[tuple[int, int]] = set()
            level_tiles = by_level[level]
            if len(level_tiles) > 1:
                level_tiles = sorted(level_tiles, key=lambda t: (t.i, t.j))
            for tile in level_tiles:
                if (tile.i, tile.j) in seen:
                    raise ValueError(f"tile {level}/{tile.i}_{tile.j} is given twice")
                seen.add((tile.i, tile.j))
                u0, v0, u1, v1 = tile.uv_rect
                r0, r1 = bisect_left(us, u0), bisect_right(us, u1)
                c0, c1 = bisect_left(vs, v0), bisect_right(vs, v1)
                if r0 < r1 and c0 < c1:
                    blocks.append((r0, r1, c0, c1, tile))
                    batches.setdefault((tile.degree, tile.size, tile.knots, r0, r1, c0, c1),
                                       []).append(tile)
            plan.append((level, blocks))
        plans.append(plan)
    fields: dict[int, array] = {}  # id of a tile -> its field on its block
    for (degree, size, (U, V), r0, r1, c0, c1), tiles in batches.items():
        values = backend.field_grids(degree, U, V, size, size,
                                     [tile.coefficients for tile in tiles], us[r0:r1],
                                     vs[c0:c1])
        fields.update(zip(map(id, tiles), values, strict=True))
    out = []
    for plan in plans:
        levels = []
        for level, blocks in plan:
            field = array("d", bytes(8 * len(us) * n_j))
            backend.add_level(field, n_j, [(r0, r1, c0, c1, fields[id(tile)])
                                           for r0, r1, c0, c1, tile in blocks])
            levels.append((level, field))
        out.append(levels)
    return out


def displacement_grid(tiles: Iterable[DetailTile], us: Sequence[float], vs: Sequence[float],
                      kernel: str | None = None) -> array:
    """``sum_k D_k(u_i, v_j)`` of the given tiles on a grid: ``array('d')``, row-major in ``i``.

    The fields of :func:`displacement_levels` summed from ``+0.0`` in increasing
    level order (a vertex no tile of a level holds adds ``+0.0``, which changes
    nothing).
    """
    return displacement_grids([tiles], us, vs, kernel)[0]


def displacement_grids(tile_lists: Sequence[Iterable[DetailTile]], us: Sequence[float],
                       vs: Sequence[float], kernel: str | None = None) -> list[array]:
    """:func:`displacement_grid` of each list of tiles (one patch's) on one grid, bit for
    bit, the tiles of all the lists evaluated together where they share their knots
    (:func:`_displacement_levels`)."""
    n_i, n_j = len(us), len(vs)
    add_level = _kernel.backend(kernel).add_level
    out = []
    for levels in _displacement_levels(tile_lists, us, vs, kernel):
        if not levels:
            out.append(array("d", bytes(8 * n_i * n_j)))
            continue
        # +0.0 + the first level's field is that field itself: add_level makes it +0.0 plus
        # the tiles' values, or +0.0 where no tile holds a vertex, so it holds no -0.0 (the
        # one value that adding +0.0 changes)
        total = levels[0][1]
        for _, level_field in levels[1:]:
            add_level(total, n_j, [(0, n_i, 0, n_j, level_field)])
        out.append(total)
    return out


def _tile_blocks(centres: Sequence[float], count: int) -> dict[int, tuple[int, int]]:
    """``{t: (first, end)}``: the run of sorted ``centres`` that node ``t`` of a level with
    ``count`` nodes per side holds, as the node lookup picks it (``min(int(x count),
    count - 1)``) and the closed rectangle contains it (both monotone: one run per node)."""
    blocks: dict[int, tuple[int, int]] = {}
    last = count - 1
    for k, x in enumerate(centres):
        t = min(int(x * count), last)
        if t / count <= x <= (t + 1) / count:
            first = blocks.get(t, (k, k))[0]
            blocks[t] = (first, k + 1)
    return blocks


def drawn_covers(trim: TrimMask, tiles: Sequence[DetailTile], us: Sequence[float],
                 vs: Sequence[float]) -> list[tuple]:
    """Which cells of the grid ``us x vs`` a tessellation draws, as kernel *covers*.

    Cell ``(i, j)`` has its centre at ``u = (u_i + u_{i+1}) / 2``, ``v`` likewise
    (normalised domain); it is drawn where ``trim`` covers the centre, or where
    the ``drawn`` mask of a given tile holding it (looked up by its node
    ``min(int(u 2^L), 2^L - 1)`` per level ``L``, inside its closed rectangle)
    covers it, at ``((u - u0) / (u1 - u0), (v - v0) / (v1 - v0))``. The
    covers (see :func:`client_py._kernel_python.cell_indices`) are the base
    trim over all cells and one per tile with a mask over the cells it holds:
    mask rows and columns per cell row and column, no per-cell work.
    """
    cu = [0.5 * (a + b) for a, b in zip(us, us[1:], strict=False)]
    cv = [0.5 * (a + b) for a, b in zip(vs, vs[1:], strict=False)]
    covers = [(0, 0, mask_indices(cu, trim.rows), mask_indices(cv, trim.cols), trim.flat,
               trim.cols)]
    return covers + _mask_covers(tiles, cu, cv, "drawn")


def _mask_covers(tiles: Sequence[DetailTile], cu: Sequence[float], cv: Sequence[float],
                 attribute: str) -> list[tuple]:
    """Kernel covers of the tiles' ``attribute`` masks (``drawn`` or ``walls``) over the
    cells with centres ``cu x cv``, levels increasing, ``(i, j)`` order within a level."""
    covers = []
    by_level: dict[int, dict[tuple[int, int], DetailTile]] = {}
    for tile in tiles:
        if getattr(tile, attribute) is not None:
            by_level.setdefault(tile.level, {})[tile.i, tile.j] = tile
    for level, nodes in sorted(by_level.items()):
        row_blocks, col_blocks = _tile_blocks(cu, 1 << level), _tile_blocks(cv, 1 << level)
        for (ti, tj), tile in sorted(nodes.items()):
            if ti not in row_blocks or tj not in col_blocks:
                continue
            (i0, i1), (j0, j1) = row_blocks[ti], col_blocks[tj]
            u0, v0, u1, v1 = tile.uv_rect
            mask = getattr(tile, attribute)
            rows = mask_indices([(u - u0) / (u1 - u0) for u in cu[i0:i1]], mask.rows)
            cols = mask_indices([(v - v0) / (v1 - v0) for v in cv[j0:j1]], mask.cols)
            covers.append((i0, j0, rows, cols, mask.flat, mask.cols))
    return covers


def walls_vetoes(tiles: Sequence[DetailTile], us: Sequence[float],
                 vs: Sequence[float]) -> list[tuple] | None:
    """The cells of the grid ``us x vs`` the given tiles' ``walls`` masks leave out, as
    kernel *vetoes* (:func:`client_py._kernel_python.cell_indices`): one per tile with a
    walls mask, coarse levels first, each *setting* the veto over the cells it holds, so
    the finest given walls mask holding a cell decides (:class:`DetailTile`, ``walls``).
    ``None`` when no tile has one (the cells are as :func:`drawn_covers` alone says)."""
    if not any(tile.walls is not None for tile in tiles):
        return None
    cu = [0.5 * (a + b) for a, b in zip(us, us[1:], strict=False)]
    cv = [0.5 * (a + b) for a, b in zip(vs, vs[1:], strict=False)]
    return _mask_covers(tiles, cu, cv, "walls")


def drawn_cell_indices(trim: TrimMask | None, tiles: Sequence[DetailTile], us: Sequence[float],
                       vs: Sequence[float], kernel: str | None = None) -> array:
    """Triangles of the cells of the grid ``us x vs`` (normalised parameters, vertex ``k =
    i len(vs) + j``) a tessellation draws: the one rule of a single patch's region and of
    an atlas's patch (``client_py.atlas_mesh``). A cell is drawn where ``trim`` (``None``:
    every cell) or a given tile's ``drawn`` mask covers its centre (:func:`drawn_covers`),
    unless the ``walls`` mask of the finest given tile carrying one covers it
    (:func:`walls_vetoes`); the two triangles of a drawn cell as :func:`grid_indices`."""
    nu, nv = len(us), len(vs)
    vetoes = walls_vetoes(tiles, us, vs)
    if trim is None and vetoes is None:
        return grid_indices(nu, nv, kernel=kernel)
    backend = _kernel.backend(kernel)
    if vetoes is None:
        return backend.cell_indices(nu, nv, drawn_covers(trim, tiles, us, vs))
    # without a trim, every cell is drawn but for the walls
    trim = TrimMask.from_flat(1, 1, b"\x01") if trim is None else trim
    return backend.cell_indices(nu, nv, drawn_covers(trim, tiles, us, vs), vetoes)


@dataclass(frozen=True)
class RegionSamples:
    """The base patch and the detail levels sampled for one region: what its mesh
    (:func:`mesh_of_region`) and its skirts (:func:`client_py.skirts.hang_skirts`) are made of.

    Attributes
    ----------
    uv_rect : (u0, v0, u1, v1)
        The region, normalised domain.
    us, vs : list of float
        The region's grid: ``nu`` and ``nv`` normalised parameters
        (``u_i = u0 + i (u1 - u0) / (nu - 1)``).
    ext_u, ext_v : list of float
        The sampled grid: ``us``/``vs`` with one more parameter on each side where
        there are detail tiles and the domain goes on (for central differences).
    window : (r0, r1, c0, c1)
        Where the region's grid lies in the sampled one (rows ``r0 <= i < r1``).
    positions, normals : array('d')
        ``S`` and its unit normal at every sampled vertex, ``3`` values each,
        row-major over ``(len(ext_u), len(ext_v))``, patch frame; normals at
        poles are the limit normals (``client_py.tessellate.pole_normals``).
    degenerate : tuple of int
        Sampled vertices whose analytic normal vanished (the poles).
    levels : list of (int, array('d'))
        Per detail level given, increasing, its field on the sampled grid
        (:func:`displacement_levels`).
    """

    uv_rect: UVRect
    us: list[float]
    vs: list[float]
    ext_u: list[float]
    ext_v: list[float]
    window: tuple[int, int, int, int]
    positions: array
    normals: array
    degenerate: tuple[int, ...]
    levels: list[tuple[int, array]]

    def vertex(self, a: int, b: int) -> int:
        """Index in the sampled grid of the region's grid vertex ``(a, b)``."""
        return (self.window[0] + a) * len(self.ext_v) + self.window[2] + b


def sample_region(surface: NurbsSurface, uv_rect: Sequence[float], nu: int, nv: int,
                  tiles: Iterable[DetailTile] = (), kernel: str | None = None) -> RegionSamples:
    """The base and each detail level of ``tiles`` on the grid of a region (plus a ring).

    The base ``S`` and its unit normal come from the kernel's ``evaluate_grid``
    (float64) over the surface parameters ``a0 + (a1 - a0) t`` of the
    normalised ``t``; the levels from :func:`displacement_levels`. Arguments as
    :func:`tessellate_region`.
    """
    if not isinstance(surface, NurbsSurface):
        raise ValueError(f"surface must be a NurbsSurface, got {type(surface).__name__}")
    u0, v0, u1, v1 = _check_rect(uv_rect)
    nu, nv = _check_count("nu", nu), _check_count("nv", nv)
    tiles = list(tiles)
    us, vs = _samples(u0, u1, nu), _samples(v0, v1, nv)
    # one ring beyond the region (where the domain goes on) for central differences
    du, dv = (u1 - u0) / (nu - 1), (v1 - v0) / (nv - 1)
    ring = bool(tiles)
    r0 = 1 if ring and u0 - du >= 0.0 else 0
    c0 = 1 if ring and v0 - dv >= 0.0 else 0
    ext_u = ([u0 - du] if r0 else []) + us + ([u1 + du] if ring and u1 + du <= 1.0 else [])
    ext_v = ([v0 - dv] if c0 else []) + vs + ([v1 + dv] if ring and v1 + dv <= 1.0 else [])
    (a0, a1), (b0, b1) = surface.domain
    su = [a0 + (a1 - a0) * t for t in ext_u]
    sv = [b0 + (b1 - b0) * t for t in ext_v]
    positions, normals, degenerate = _kernel.backend(kernel).evaluate_grid(surface, su, sv, "d")
    pole_normals(surface, normals, su, sv, degenerate)
    levels = displacement_levels(tiles, ext_u, ext_v, kernel) if ring else []
    return RegionSamples((u0, v0, u1, v1), us, vs, ext_u, ext_v, (r0, r0 + nu, c0, c0 + nv),
                         positions, normals, tuple(degenerate), levels)


def mesh_of_region(surface: NurbsSurface, samples: RegionSamples, tiles: Sequence[DetailTile],
                   kernel: str | None = None, textures: Iterable[TextureImage] = ()) -> Mesh:
    """The mesh :func:`tessellate_region` returns, from the region's samples and its tiles."""
    us, vs = samples.us, samples.vs
    backend = _kernel.backend(kernel)
    if samples.levels:
        n_i, n_j = len(samples.ext_u), len(samples.ext_v)
        shift = array("d", bytes(8 * n_i * n_j))
        for _, level_field in samples.levels:
            backend.add_level(shift, n_j, [(0, n_i, 0, n_j, level_field)])
        positions, normals = backend.displace_grid(samples.positions, samples.normals, shift,
                                                   n_i, n_j, samples.window)
    else:  # no ring: the sampled grid is the region's
        positions, normals = array("f", samples.positions), array("f", samples.normals)
    uvs = grid_uvs(us, vs)
    mesh = Mesh(positions, normals, uvs, drawn_cell_indices(surface.trim, tiles, us, vs, kernel))
    textures = list(textures)
    if textures:
        mesh.colors = vertex_colours(uvs, textures, kernel, len(vs))
    return mesh


def tessellate_region(surface: NurbsSurface, uv_rect: Sequence[float], nu: int, nv: int,
                      tiles: Iterable[DetailTile] = (), kernel: str | None = None,
                      textures: Iterable[TextureImage] = ()) -> Mesh:
    """Triangle mesh of the refined surface ``X = S + sum D_k n`` over ``uv_rect``.

    Parameters
    ----------
    surface : NurbsSurface
        The base patch (its own frame; map the mesh with :func:`transform_mesh`).
    uv_rect : (u0, v0, u1, v1)
        Region in the *normalised* domain ``[0, 1]^2`` (``0`` and ``1`` are the
        ends of the surface's knot range).
    nu, nv : int
        Vertices per side of the uniform grid over ``uv_rect`` (vertex
        ``k = i nv + j`` at ``u_i = u0 + i (u1 - u0) / (nu - 1)``).
    tiles : iterable of DetailTile
        Applied where each contains a vertex (see :func:`displacement_grid`).
    textures : iterable of TextureImage
        When given, ``colors`` holds at each vertex the bilinear sample of the
        finest texture tile containing it (black where none does).

    Returns
    -------
    Mesh
        ``uvs`` are the normalised ``(u, v)`` (so a texture tile maps by its own
        rectangle). Without tiles, normals are the base's analytic normals, as
        :func:`client_py.tessellate_grid` gives; with tiles, the normals of the
        displaced grid by central differences, computed over one extra ring of
        vertices beyond ``uv_rect`` (inside the domain), so that two regions
        sharing a border get the same normals on it; on the domain's outer
        border the differences are one-sided. Cells are left out as by
        ``tessellate_grid`` where the base's trim leaves out their centre,
        unless a given tile's ``drawn`` mask covers it, and where the ``walls``
        mask of the finest given tile carrying one covers it.

    Notes
    -----
    :func:`sample_region` then :func:`mesh_of_region`; a caller that also hangs
    skirts passes the same samples to :func:`client_py.skirts.hang_skirts`,
    which then evaluates nothing again.
    """
    tiles = list(tiles)
    samples = sample_region(surface, uv_rect, nu, nv, tiles, kernel)
    return mesh_of_region(surface, samples, tiles, kernel, textures)


def vertex_colours(uvs: Sequence[float], textures: Iterable[TextureImage],
                   kernel: str | None = None, columns: int | None = None) -> array:
    """RGB per vertex (``array('B')``) from normalised ``uvs``: the finest texture tile
    containing each vertex, sampled bilinearly; ``0, 0, 0`` where none does.

    Parameters
    ----------
    uvs : sequence of float
        ``u, v`` per vertex (``2 N`` numbers).
    textures : iterable of TextureImage
        At each level, vertex ``(u, v)`` is in node ``(min(int(u 2^L), 2^L - 1),
        min(int(v 2^L), 2^L - 1))``; the finest level whose node is given samples
        it (:meth:`TextureImage.sample`). Of two images of one node the last given
        is used.
    kernel : {'python', 'numpy'}, optional
        The kernel that samples grids (default the selected one).
    columns : int, optional
        Vertices per row when ``uvs`` are a grid (vertex ``k = i columns + j`` at
        ``(u_i, v_j)``), as :func:`tessellate_region` lays them out; without it,
        the length of the first run of equal ``u`` is tried.

    Notes
    -----
    On a grid (checked) the node of a vertex is the pair of its row's and its
    column's nodes, so the vertices fall into blocks of whole row runs times
    column runs with one tile each (:func:`_texture_blocks`), and the kernel's
    ``sample_texture`` samples each block at once: per row the image column
    offsets and weights, per column the image row ones, then the same float64
    operations as :meth:`TextureImage.sample` (same bytes). Other layouts are
    sampled vertex by vertex.
    """
    finest_first = sorted(textures, key=lambda t: -t.level)
    by_level: dict[int, dict[tuple[int, int], TextureImage]] = {}
    for t in finest_first:
        if not isinstance(t, TextureImage):
            raise ValueError(f"textures must be TextureImage objects, got {type(t).__name__}")
        by_level.setdefault(t.level, {})[(t.i, t.j)] = t
    n_vertices = len(uvs) // 2
    if not by_level or not n_vertices:
        return array("B", bytes(3 * n_vertices))
    if not (isinstance(uvs, array) and uvs.typecode in "fd"):
        uvs = array("d", uvs)
    grid = _uv_grid(uvs[: 2 * n_vertices], columns)
    if grid is not None:
        us, vs = grid
        blocks = _texture_blocks(by_level, us, vs)
        return _kernel.backend(kernel).sample_texture(us, vs, blocks)
    out = array("B", bytes(3 * n_vertices))
    for k in range(n_vertices):
        u, v = uvs[2 * k], uvs[2 * k + 1]
        for level, images in by_level.items():
            n = 1 << level
            image = images.get((min(int(u * n), n - 1), min(int(v * n), n - 1)))
            if image is not None:
                out[3 * k : 3 * k + 3] = array("B", image.sample(u, v))
                break
    return out


def _uv_grid(uvs: array, columns: int | None) -> tuple[list[float], list[float]] | None:
    """``(us, vs)`` when ``uvs`` are the grid ``us x vs`` with ``columns`` vertices per row
    (``None``: the first run of equal ``u``), else ``None``. The arrays are compared bit
    for bit as whole byte strings."""
    u_col, v_col = uvs[0::2], uvs[1::2]
    n = len(u_col)
    if columns is None:
        first, columns = u_col[0], 1
        while columns < n and u_col[columns] == first:
            columns += 1
    if not isinstance(columns, int) or columns < 1 or n % columns:
        return None
    rows = n // columns
    vs = v_col[:columns]
    if v_col.tobytes() != (vs * rows).tobytes():  # bit for bit (memcmp)
        return None
    us = u_col[::columns]
    expected = array(u_col.typecode, bytes(u_col.itemsize * n))
    for j in range(columns):
        expected[j::columns] = us
    if u_col.tobytes() != expected.tobytes():
        return None
    return us.tolist(), vs.tolist()


def _texture_blocks(by_level: dict[int, dict[tuple[int, int], TextureImage]],
                    us: Sequence[float], vs: Sequence[float]) -> list[tuple]:
    """Kernel blocks ``(r0, r1, c0, c1, (width, height, rgb, uv_rect))`` of the grid
    ``us x vs``: rows ``r0 <= i < r1`` and columns ``c0 <= j < c1`` that one image
    colours, the finest of ``by_level`` (finest level first) whose node holds them.

    Rows are cut into runs of equal nodes at every level (``min(int(u 2^L), 2^L -
    1)``, the lookup of :func:`vertex_colours`), columns likewise; a row run times
    a column run has one node per level, hence one image (or none); neighbouring
    column runs of one image are merged.
    """
    sides = [1 << level for level in by_level]
    tables = list(by_level.values())

    def runs(xs: Sequence[float]) -> list[tuple[int, int, tuple[int, ...]]]:
        out: list[tuple[int, int, tuple[int, ...]]] = []
        for k, x in enumerate(xs):
            key = tuple([min(int(x * n), n - 1) for n in sides])
            if out and out[-1][2] == key:
                out[-1] = (out[-1][0], k + 1, key)
            else:
                out.append((k, k + 1, key))
        return out

    col_runs = runs(vs)
    blocks = []
    for r0, r1, row_key in runs(us):
        merged: list[list] = []
        for c0, c1, col_key in col_runs:
            image = None
            for images, a, b in zip(tables, row_key, col_key, strict=True):
                image = images.get((a, b))
                if image is not None:
                    break
            if merged and merged[-1][2] is image and merged[-1][1] == c0:
                merged[-1][1] = c1
            elif image is not None:
                merged.append([c0, c1, image])
        blocks += [(r0, r1, c0, c1, (t.width, t.height, t.rgb, t.uv_rect))
                   for c0, c1, t in merged]
    return blocks


def is_rigid_motion(matrix: Sequence[Sequence[float]] | None, tolerance: float = 1e-9) -> bool:
    """Whether ``x -> A x + b`` (``matrix``: 3x4 or 4x4 rows) is a rotation and a shift:
    ``|A^T A - I| <= tolerance`` entrywise and ``det A > 0``.

    Such a map commutes with a displacement along the unit normal
    (``A (S + D n) + b = (A S + b) + D (A n)`` and ``A n`` is the unit normal of
    the mapped surface, with the same orientation), so a region can be made on
    the mapped patch directly instead of mapping its mesh (:func:`transform_mesh`);
    the two agree to rounding. ``None`` (no map) is not one.
    """
    if matrix is None:
        return False
    try:
        a = [[float(x) for x in row[:3]] for row in list(matrix)[:3]]
    except (TypeError, ValueError):
        return False
    if len(a) != 3 or any(len(row) != 3 for row in a):
        return False
    for r in range(3):
        for c in range(3):
            dot = sum(a[k][r] * a[k][c] for k in range(3))
            if not abs(dot - (1.0 if r == c else 0.0)) <= tolerance:
                return False
    det = (a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1])
           - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
           + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0]))
    return det > 0.0


def transform_mesh(mesh: Mesh, matrix: Sequence[Sequence[float]],
                   kernel: str | None = None) -> Mesh:
    """``mesh`` under the affine map ``x -> A x + b`` (``matrix``: 3x4 or 4x4 rows).

    Normals map by the inverse transpose of ``A`` (as the cofactor matrix
    ``det(A) A^-T``, times the sign of ``det A``) and are renormalised; with
    ``det A < 0`` the triangles' winding is reversed so they stay
    counter-clockwise about their normals. The per-vertex work is the kernel's
    ``map_vectors`` (whole columns with numpy).
    """
    m = [[float(x) for x in row] for row in matrix]
    if len(m) not in (3, 4) or any(len(r) != 4 for r in m[:3]):
        raise ValueError("matrix must be 3x4 or 4x4 (rows of [a, b, c, t])")
    (a, b, c, tx), (d, e, f, ty), (g, h, k, tz) = m[:3]
    # cofactor matrix = det(A) * inverse transpose: normals up to a scale
    co = ((e * k - f * h, f * g - d * k, d * h - e * g),
          (c * h - b * k, a * k - c * g, b * g - a * h),
          (b * f - c * e, c * d - a * f, a * e - b * d))
    det = a * co[0][0] + b * co[0][1] + c * co[0][2]
    if det == 0.0:
        raise ValueError("matrix is singular: it flattens the mesh")
    sign = 1.0 if det > 0 else -1.0
    backend = _kernel.backend(kernel)
    pos = backend.map_vectors(mesh.positions, ((a, b, c), (d, e, f), (g, h, k)), (tx, ty, tz))
    nrm = backend.map_vectors(mesh.normals, [[sign * x for x in row] for row in co],
                              normalise=True)
    indices = mesh.indices
    if det < 0:
        indices = array("I", indices)
        indices[1::3], indices[2::3] = mesh.indices[2::3], mesh.indices[1::3]
    return Mesh(pos, nrm, array("f", mesh.uvs), indices,
                None if mesh.colors is None else array("B", mesh.colors))
