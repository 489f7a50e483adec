"""Pure-Python grid evaluation kernel: the fast path in the browser (Pyodide has no numpy here).

Evaluating ``S`` on a grid ``u_0..u_{I-1} x v_0..v_{J-1}`` is separable:

    S^w(u_i, v_j) = sum_a N_a(u_i) T_a(v_j),   T_a(v_j) = sum_b N_b(v_j) P^w_ab

so the kernel (1) builds the basis tables once per grid direction (A2.1, A2.3),
(2) blends every control *row* ``a`` along ``v`` into ``T_a`` and ``T'_a``
(value and v-derivative at all ``v_j``, homogeneous components
``(w x, w y, w z, w)``), and (3) for each ``u_i`` blends the ``p + 1`` rows its
span selects into the point, both tangents and the unit normal of every vertex
of the grid row. No basis function is computed per point.

Speed: pure-Python time is spent per float operation and per list built, so
step (3), which does almost all the work, is one loop over the grid row in
which every sum ``c_0 x_0 + ... + c_p x_p`` is written out term by term and
no intermediate list is made. Writing it out for any degree means the loop is
generated once per ``(p, rational)`` from the template in
:func:`_row_source` (``functools.cache``); step (2) likewise uses a generated
``q + 1``-term comprehension (:func:`_blend_source`). Measured against the
earlier term-by-term list passes: see ``docs/benchmarks.md``.

The other whole-grid operations of a tessellation live here too, each with a
numpy twin of the same name and contract in ``_kernel_numpy`` that gives the
same bits: :func:`field_grid` (a detail tile's field; :func:`field_grids`
many tiles' at once), :func:`add_level`
(summing a level's tiles), :func:`displace_grid` (``S + D n`` and its
normals), :func:`cell_indices` (the triangles of the drawn cells),
:func:`map_vectors` (an affine map of positions or normals) and
:func:`sample_texture` (vertex colours from texture tiles). They work on
whole rows (slices, ``map``, ``int.from_bytes``) rather than per vertex.
"""

from __future__ import annotations

import math
import re
import struct
from array import array
from collections.abc import Callable, Sequence
from functools import cache, lru_cache
from itertools import chain
from operator import add

from .basis import basis_functions, basis_table, find_span
from .surface import normal_tolerance


def _compile(source: str, name: str) -> Callable:
    """Define the function ``name`` from generated ``source`` (only our own templates)."""
    namespace: dict = {"sqrt": math.sqrt}
    exec(compile(source, f"<client_py kernel: {name}>", "exec"), namespace)
    return namespace[name]


def _terms(coeff: str, value: str, n_terms: int) -> str:
    """``'n0 * x0 + n1 * x1 + ...'``: a written-out sum of ``n_terms`` products."""
    return " + ".join(f"{coeff}{k} * {value}{k}" for k in range(n_terms))


def _blend_source(n_terms: int) -> str:
    """Source of ``blend(coeffs, rows)``: ``[sum_k coeffs[k][e] * rows[k][e] for e]``."""
    ks = range(n_terms)
    pairs = ", ".join(f"c{k}, x{k}" for k in ks)
    lists = ", ".join(f"C{k}, R{k}" for k in ks)
    return (
        "def blend(coeffs, rows):\n"
        f"    {', '.join(f'C{k}' for k in ks)}, = coeffs\n"
        f"    {', '.join(f'R{k}' for k in ks)}, = rows\n"
        f"    return [{_terms('c', 'x', n_terms)} for {pairs} in zip({lists})]\n"
    )


@cache
def _blend(n_terms: int) -> Callable[[Sequence, Sequence], list[float]]:
    """Element-wise ``sum_k coeffs[k][e] * rows[k][e]`` over ``n_terms`` lists."""
    return _compile(_blend_source(n_terms), "blend")


@cache
def _combine(n_terms: int) -> Callable[[Sequence[float], Sequence], list[float]]:
    """``[sum_k coeffs[k] * rows[k][e] for e]``: lists combined with scalar coefficients."""
    ks = range(n_terms)
    return _compile(
        "def combine(coeffs, rows):\n"
        f"    {', '.join(f'c{k}' for k in ks)}, = coeffs\n"
        f"    return [{_terms('c', 'x', n_terms)} for {', '.join(f'x{k}' for k in ks)} "
        f"in zip(*rows)]\n", "combine")


def _row_source(p: int, rational: bool) -> str:
    """Source of ``evaluate_row``: points and normals of one grid row ``u = u_i``.

    ``evaluate_row(nu, du, rows, drows, tol, pos, nrm, bad)`` takes the basis
    values ``nu = (N_0(u_i), ..., N_p(u_i))`` and derivatives ``du`` of the
    span's ``p + 1`` control rows, ``rows``/``drows``: the blended rows
    ``T_a`` / ``T'_a`` of those control rows, component-major (``x``-rows of
    terms ``0..p``, then ``y``, ``z`` and, when rational, ``w``), and appends
    ``x, y, z`` per vertex to ``pos`` and the unit normal to ``nrm``; vertices
    whose normal is degenerate get ``0, 0, 0`` and their row index in ``bad``.
    For ``p = 2``, non-rational, the loop reads::

        for x0, x1, x2, y0, y1, y2, z0, z1, z2, X0, ..., Z2 in zip(*rows, *drows):
            x = n0 * x0 + n1 * x1 + n2 * x2          # S      (likewise y, z)
            ax = d0 * x0 + d1 * x1 + d2 * x2         # dS/du
            bx = n0 * X0 + n1 * X1 + n2 * X2         # dS/dv
            nx = ay * bz - az * by                   # S_u x S_v
            ...

    Rational: ``S = A / w`` and the tangents ``(A_u - w_u S) / w`` share the
    positive factor ``1 / w``, which the normalisation removes, so the loop
    uses ``A_u - w_u S`` and scales the degeneracy tolerance by ``w^2``.
    """
    n = p + 1
    comps = "xyzw" if rational else "xyz"
    names = [f"{c}{k}" for c in comps for k in range(n)]
    names += [f"{c.upper()}{k}" for c in comps for k in range(n)]
    body = []
    if rational:
        body += [f"w = {_terms('n', 'w', n)}",
                 f"wu = {_terms('d', 'w', n)}",
                 f"wv = {_terms('n', 'W', n)}"]
        for c in "xyz":
            body.append(f"{c} = ({_terms('n', c, n)}) / w")
        for c in "xyz":
            body.append(f"a{c} = {_terms('d', c, n)} - wu * {c}")
        for c in "xyz":
            body.append(f"b{c} = {_terms('n', c.upper(), n)} - wv * {c}")
        small = "tol * w * w"
    else:
        for c in "xyz":
            body += [f"{c} = {_terms('n', c, n)}",
                     f"a{c} = {_terms('d', c, n)}",
                     f"b{c} = {_terms('n', c.upper(), n)}"]
        small = "tol"
    body += [
        "nx = ay * bz - az * by",
        "ny = az * bx - ax * bz",
        "nz = ax * by - ay * bx",
        "length = sqrt(nx * nx + ny * ny + nz * nz)",
        "pos += (x, y, z)",
        f"if length > {small}:",
        "    nrm += (nx / length, ny / length, nz / length)",
        "else:",
        "    nrm += (0.0, 0.0, 0.0)",
        "    bad.append(len(nrm) // 3 - 1)",
    ]
    return (
        "def evaluate_row(nu, du, rows, drows, tol, pos, nrm, bad):\n"
        f"    {', '.join(f'n{k}' for k in range(n))}, = nu\n"
        f"    {', '.join(f'd{k}' for k in range(n))}, = du\n"
        f"    for {', '.join(names)} in zip(*rows, *drows):\n"
        + "".join(f"        {line}\n" for line in body)
    )


@cache
def _row_evaluator(p: int, rational: bool) -> Callable:
    return _compile(_row_source(p, rational), "evaluate_row")


def _blend_rows_along_v(
    comp: Sequence[float], rows: int | range, n_v: int, q: int, spans_v, Nv, dNv
) -> tuple[list[list[float]], list[list[float]]]:
    """``T_a(v_j)`` and ``dT_a/dv(v_j)`` for the control rows ``a`` in ``rows`` (an int
    ``n``: all ``n`` rows) of one component (``comp`` row-major, ``n_v`` per row).

    The window of row ``a`` that ``v_j`` needs starts at ``spans_v[j] - q``;
    gathering it per term (``x_k[j] = P_{a, spans_v[j] - q + k}``) turns the
    per-``j`` windows into ``q + 1`` lists that :func:`_blend` combines with
    per-element coefficients ``N_k(v_j)``.
    """
    gather = [[span - q + k for span in spans_v] for k in range(q + 1)]
    coeffs = [[row[k] for row in Nv] for k in range(q + 1)]
    dcoeffs = [[row[k] for row in dNv] for k in range(q + 1)]
    blend = _blend(q + 1)
    vals, dvals = [], []
    for a in range(rows) if isinstance(rows, int) else rows:
        get = comp[a * n_v : (a + 1) * n_v].__getitem__
        window = [list(map(get, index)) for index in gather]
        vals.append(blend(coeffs, window))
        dvals.append(blend(dcoeffs, window))
    return vals, dvals


def evaluate_grid(surface, us: Sequence[float], vs: Sequence[float], typecode: str = "f"):
    """Points and unit normals of ``surface`` at every ``(u_i, v_j)``, row-major in ``i``.

    Parameters
    ----------
    surface : NurbsSurface
    us, vs : sequence of float
        Parameters inside the surface's domain, ``I`` and ``J`` of them.
    typecode : {'f', 'd'}
        Output precision: float32 (what meshes carry) or float64.

    Returns
    -------
    positions, normals : array(typecode), each ``3 * I * J`` values
        Vertex ``k = i * J + j`` at ``[3k : 3k + 3]``.
    degenerate : list of int
        Vertices where ``|S_u x S_v| <= normal_tolerance(surface)`` (a pole, a
        collapsed edge): their normal is left ``(0, 0, 0)`` for the caller.
    """
    (p, q), (n_u, n_v) = surface.degree, surface.shape
    U, V = surface.knots
    spans_u, Nu, dNu = basis_table(p, U, n_u, us)
    spans_v, Nv, dNv = basis_table(q, V, n_v, vs)
    pts, wts = surface.flat_points, surface.flat_weights
    rational = wts is not None
    # Only the control rows the parameters' spans select are blended along v: a region of a
    # zoom (a small rectangle of the domain) needs a few of them, not all n_u.
    first = min(spans_u) - p
    rows = range(first, max(spans_u) + 1)
    lo_pt, hi_pt = 3 * first * n_v, 3 * rows.stop * n_v
    # Homogeneous components P^w = (w x, w y, w z, w) of those rows, row-major over (a, b)
    # (index (a - first) n_v + b).
    comps = [pts[lo_pt + c : hi_pt : 3] for c in range(3)]
    if rational:
        w_rows = wts[first * n_v : rows.stop * n_v]
        comps = [[w * x for w, x in zip(w_rows, comp, strict=True)] for comp in comps] + [w_rows]
    blended = [_blend_rows_along_v(comp, len(rows), n_v, q, spans_v, Nv, dNv) for comp in comps]

    evaluate_row = _row_evaluator(p, rational)
    tol = normal_tolerance(surface)
    n_j = len(vs)
    positions, normals = array(typecode), array(typecode)
    # struct packs a row of floats into the array's bytes 2-3 times faster than fromlist()
    pack = struct.Struct(f"={3 * n_j}{typecode}").pack
    degenerate: list[int] = []
    for i, (span, nu_i, dnu_i) in enumerate(zip(spans_u, Nu, dNu, strict=True)):
        lo, hi = span - p - first, span + 1 - first
        rows = [r for vals, _ in blended for r in vals[lo:hi]]
        drows = [r for _, dvals in blended for r in dvals[lo:hi]]
        pos: list[float] = []
        nrm: list[float] = []
        bad: list[int] = []
        evaluate_row(nu_i, dnu_i, rows, drows, tol, pos, nrm, bad)
        try:
            positions.frombytes(pack(*pos))
        except OverflowError:  # beyond float32: fromlist() stores inf, as numpy would
            positions.fromlist(pos)
        normals.frombytes(pack(*nrm))
        degenerate += [i * n_j + j for j in bad]
    return positions, normals, degenerate


# ------------------------------------------------------------------ detail layers
@lru_cache(maxsize=256)
def _value_table(degree: int, knots: tuple[float, ...], n_ctrl: int,
                 params: tuple[float, ...]) -> tuple[list[int], list[list[float]]]:
    """Spans and basis values (A2.1, A2.2; no derivatives) at ``params``.

    Cached: the tiles of one tile row share their ``u`` knots and parameters,
    those of one tile column their ``v`` ones, so a region's tiles of a level
    need one table per row and per column of tiles, not two per tile.
    """
    spans = [find_span(degree, knots, n_ctrl, t) for t in params]
    return spans, [basis_functions(degree, knots, s, t) for s, t in zip(spans, params,
                                                                          strict=True)]


def field_grid(degree: int, knots_u: Sequence[float], knots_v: Sequence[float], n_u: int,
               n_v: int, coefficients: Sequence[float], us: Sequence[float],
               vs: Sequence[float]) -> array:
    """Scalar B-spline field ``D(u_i, v_j) = sum_a sum_b N_a(u_i) N_b(v_j) c_ab`` on a grid.

    ``coefficients`` are ``c_ab`` row-major over ``(n_u, n_v)``; the knot
    vectors need not be clamped (a tile's slice of its level's knots), but every
    parameter must lie in the spans ``knots[p] .. knots[n]``. Returns
    ``array('d')`` of ``len(us) * len(vs)`` values, row-major in ``i``; the same
    separable scheme as :func:`evaluate_grid` (blend along ``v``, then ``u``).
    """
    return field_grids(degree, knots_u, knots_v, n_u, n_v, [coefficients], us, vs)[0]


def field_grids(degree: int, knots_u: Sequence[float], knots_v: Sequence[float], n_u: int,
                n_v: int, coefficients: Sequence[Sequence[float]], us: Sequence[float],
                vs: Sequence[float]) -> list[array]:
    """:func:`field_grid` of each of several coefficient grids on the same knots and
    parameters (the detail tiles of many patches), bit for bit: the control rows of all
    of them blended along ``v`` in one pass per ``v_j``, and grid row ``i`` of all of them
    combined along ``u`` in one pass (a call per tile cost more than its arithmetic)."""
    p = degree
    spans_u, Nu = _value_table(p, tuple(knots_u), n_u, tuple(us))
    spans_v, Nv = _value_table(p, tuple(knots_v), n_v, tuple(vs))
    count, n_i, n_j = len(coefficients), len(us), len(vs)
    first = min(spans_u) - p  # the control rows read: first .. first + rows - 1
    rows = max(spans_u) + 1 - first
    # the control rows first + a of every grid t, ordered (a, t): coefficient b of all of
    # them is one strided slice, and each v_j one combination of the slices its span reads
    flat = list(chain.from_iterable(c[first * n_v : (first + rows) * n_v]
                                    for c in coefficients))
    flat = swap_blocks(flat, count, rows, n_v)
    columns = [flat[b::n_v] for b in range(n_v)]
    combine = _combine(p + 1)
    along_v: list[float] = []
    for span, nv_j in zip(spans_v, Nv, strict=True):
        along_v += combine(nv_j, columns[span - p : span + 1])
    # (j, a, t) -> (a, t, j): row a of every grid, sampled at every v_j, in one slice
    blended = swap_blocks(along_v, n_j, rows * count, 1)
    width = count * n_j
    out: list[float] = []
    for span, nu_i in zip(spans_u, Nu, strict=True):
        lo = span - p - first
        out += combine(nu_i, [blended[(lo + k) * width : (lo + k + 1) * width]
                              for k in range(p + 1)])
    if count > 1:  # (i, grid) -> (grid, i)
        out = swap_blocks(out, n_i, count, n_j)
    size = n_i * n_j
    return [array("d", out[t * size : (t + 1) * size]) for t in range(count)]


def swap_blocks(values: Sequence[float], outer: int, inner: int, width: int) -> list:
    """``values``, ``outer x inner`` blocks of ``width`` values laid ``(x, y)`` (block
    ``(x, y)`` at ``(x inner + y) width``), reordered to ``(y, x)``: many small grids from
    (grid, row) order to (row, grid), so that one pass of arithmetic takes a row of all of
    them, and back.

    By slices, with no index list (a cached list of indices had held 80 MB for 256
    patches of 33 x 33 samples), along whichever axis needs the fewest of them: value
    ``c`` of block ``(x, y)`` moves from ``(x inner + y) width + c`` to ``(y outer + x)
    width + c``, so fixing two of ``x, y, c`` makes the third a strided run on both sides:
    ``outer inner`` runs of ``width`` (whole blocks), ``inner width`` runs of ``outer`` or
    ``outer width`` runs of ``inner``. The patches' grids are few rows of many patches, or
    the reverse: a whole-block copy per block cost 10-20 times the fewest runs there."""
    if isinstance(values, array):
        values = values.tolist()
    blocks, across_x, across_y = outer * inner, inner * width, outer * width
    if blocks <= min(across_x, across_y):
        return list(chain.from_iterable(
            values[(x * inner + y) * width : (x * inner + y + 1) * width]
            for y in range(inner) for x in range(outer)))
    out = [0.0] * (blocks * width)
    if across_x <= across_y:  # (y, c) fixed: x runs with steps width (out) and inner width
        for y in range(inner):
            for c in range(width):
                out[y * across_y + c : (y + 1) * across_y : width] = \
                    values[y * width + c :: across_x]
    else:  # (x, c) fixed: y runs with steps outer width (out) and width
        for x in range(outer):
            for c in range(width):
                out[x * width + c :: across_y] = \
                    values[x * across_x + c : (x + 1) * across_x : width]
    return out


def check_panel(n_cols: int, panel: int | None) -> None:
    """``ValueError`` unless ``panel`` is ``None`` or ``n_cols`` is whole panels of it
    (:func:`displace_grid`'s grids side by side: a part panel would be clamped wrong)."""
    if panel is not None and (isinstance(panel, bool) or not isinstance(panel, int)
                              or panel < 1 or n_cols % panel):
        raise ValueError(f"panel = {panel!r}: the grid's {n_cols} columns must be whole panels")


def displace_grid(positions: array, normals: array, displacement: array, n_rows: int,
                  n_cols: int, window: tuple[int, int, int, int],
                  panel: int | None = None, with_positions: bool = True
                  ) -> tuple[array, array]:
    """``X = S + D n`` on an ``n_rows x n_cols`` grid and unit normals of ``X`` by differences.

    ``positions``/``normals`` hold ``S`` and the unit normal ``n`` of the base per
    vertex (``3`` values each, row-major), ``displacement`` holds ``D``. Only the
    vertices of ``window = (r0, r1, c0, c1)`` (rows ``r0 <= i < r1``, columns
    ``c0 <= j < c1``) are returned: positions and normals as ``array('f')``. The
    normal at ``(i, j)`` is ``(X_{i+1,j} - X_{i-1,j}) x (X_{i,j+1} - X_{i,j-1})``
    normalised, one-sided on the grid's outer rows/columns (which is why the
    caller evaluates one ring beyond its region where the domain allows); where
    that vanishes (a pole) the base normal is kept. ``panel``: the grid is
    ``n_cols / panel`` grids of ``panel`` columns side by side, each one-sided on
    its own outer columns (the same normals as each grid alone): many small
    grids in one call (``client_py.atlas_mesh``'s patches of one resolution).
    ``with_positions=False``: the positions are not returned (an empty array),
    for a caller that only wants the normals.

    Per grid row, the rows above and below and the row shifted left and right
    (clamped at its ends) are sliced once per component and zipped, so the
    loop over the row's vertices does arithmetic only; the positions are
    copied a component at a time. A zero displacement (the welded positions of
    ``client_py.atlas_mesh``, shaded as they are) is not added (:func:`_displaced`).
    """
    check_panel(n_cols, panel)
    comps = _displaced(positions, normals, displacement)
    r0, r1, c0, c1 = window
    sqrt = math.sqrt
    nrm: list[float] = []
    for i in range(r0, r1):
        up, down, row = min(i + 1, n_rows - 1) * n_cols, max(i - 1, 0) * n_cols, i * n_cols
        lists = []
        for xs in comps:
            line = xs[row : row + n_cols]
            right, left = line[1:] + line[-1:], line[:1] + line[:-1]
            if panel is not None and panel < n_cols:  # clamped at each panel's own ends
                right[panel - 1 :: panel] = line[panel - 1 :: panel]
                left[::panel] = line[::panel]
            lists += (xs[up + c0 : up + c1], xs[down + c0 : down + c1], right[c0:c1],
                      left[c0:c1])
        bad = []
        for ux, dx, rx, lx, uy, dy, ry, ly, uz, dz, rz, lz in zip(*lists, strict=True):
            ax, ay, az = ux - dx, uy - dy, uz - dz
            bx, by, bz = rx - lx, ry - ly, rz - lz
            nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
            length = sqrt(nx * nx + ny * ny + nz * nz)
            if length > 0.0:
                nrm += (nx / length, ny / length, nz / length)
            else:
                bad.append(len(nrm))
                nrm += (0.0, 0.0, 0.0)
        for at in bad:  # a pole: keep the base normal (vertex at // 3 of the window)
            k = 3 * (row + c0 + (at // 3) % (c1 - c0))
            nrm[at : at + 3] = normals[k : k + 3]
    # the window's positions, a component at a time: strided copies of whole rows
    pos = array("f", bytes(12 * (r1 - r0) * (c1 - c0) if with_positions else 0))
    for c, xs in enumerate(comps if with_positions else ()):
        pos[c::3] = array("f", [x for i in range(r0, r1)
                                for x in xs[i * n_cols + c0 : i * n_cols + c1]])
    return pos, array("f", nrm)


def _displaced(positions: Sequence[float], normals: Sequence[float],
               displacement: Sequence[float]) -> list[list[float]]:
    """``X = S + D n`` a component at a time (lists). Where every ``D`` is zero, ``S + D n``
    is ``S`` itself, bit for bit, in a component without a zero (``p + (+-0) = p`` for
    ``p != 0``, ``n`` a finite unit normal), which is then only copied; a component with a
    zero (where ``-0 + 0 = +0``) is computed as in general."""
    zero = not any(displacement)
    comps = []
    for c in range(3):
        xs = list(positions[c::3])
        if not zero or 0.0 in xs:
            xs = [p + d * n for p, d, n in zip(xs, displacement, normals[c::3], strict=True)]
        comps.append(xs)
    return comps


def add_level(total: array, n_cols: int, blocks: Sequence[tuple]) -> None:
    """Add one detail level's tile fields to ``total`` in place, each vertex once.

    ``total`` is ``array('d')``, row-major with ``n_cols`` columns; ``blocks``
    are ``(r0, r1, c0, c1, values)``: ``values`` (``array('d')``, row-major,
    ``(r1 - r0) (c1 - c0)`` of them) belong to the vertices of rows ``r0 <= i
    < r1`` and columns ``c0 <= j < c1``. A vertex that several blocks cover (a
    tile border) takes the value of the first block in ``blocks`` that covers it.

    The level's field is assembled first, block rows copied as whole slices
    (C speed) in reverse order, so that the first block covering a vertex is
    the one written last; then it is added to ``total`` with one ``map(add,
    ...)`` over the rows the blocks span. Vertices that no block covers get
    ``+ 0.0``, which changes nothing: ``total`` starts at ``+0.0`` and sums
    from it are never ``-0.0``.
    """
    if not blocks:
        return
    if len(blocks) == 1:  # one block (a region's tile of a level): added row by row
        r0, r1, c0, c1, values = blocks[0]
        if (c0, c1) == (0, n_cols):  # whole rows: at once
            lo, hi = r0 * n_cols, r1 * n_cols
            total[lo:hi] = array("d", map(add, total[lo:hi], values))
            return
        width = c1 - c0
        for a in range(r1 - r0):
            start = (r0 + a) * n_cols + c0
            total[start : start + width] = array(
                "d", map(add, total[start : start + width], values[a * width : (a + 1) * width]))
        return
    level = array("d", bytes(8 * len(total)))
    for r0, r1, c0, c1, values in reversed(blocks):
        width = c1 - c0
        for a in range(r1 - r0):
            start = (r0 + a) * n_cols + c0
            level[start : start + width] = values[a * width : (a + 1) * width]
    lo = min(block[0] for block in blocks) * n_cols
    hi = max(block[1] for block in blocks) * n_cols
    total[lo:hi] = array("d", map(add, total[lo:hi], level[lo:hi]))


def _full_grid(nu: int, nv: int) -> array:
    """The triangles of every cell of an ``nu x nv`` vertex grid: see :func:`cell_indices`.

    Whole columns by strided copies (C speed, no per-index Python work):
    ``left[r c1 + j]`` and ``right[...]`` are vertices ``(r, j)`` and
    ``(r, j + 1)`` of every vertex row ``r``, ``c1 = nv - 1`` cells per row; then
    cell ``k``'s corners are left/right of its row and of the next.
    """
    c1, cells = nv - 1, (nu - 1) * (nv - 1)
    every = array("I", range(nu * nv))
    left, right = array("I", bytes(4 * nu * c1)), array("I", bytes(4 * nu * c1))
    for j in range(c1):
        left[j::c1] = every[j::nv]
        right[j::c1] = every[j + 1 :: nv]
    indices = array("I", bytes(24 * cells))
    indices[0::6] = left[:cells]  # k
    indices[1::6] = indices[4::6] = left[c1:]  # k + nv
    indices[2::6] = indices[3::6] = right[:cells]  # k + 1
    indices[5::6] = right[c1:]  # k + nv + 1
    return indices


_RUNS = re.compile(b"[^\0]+")  # a run of drawn cells: non-zero flag bytes


def cell_indices(nu: int, nv: int, covers: Sequence[tuple] | None = None,
                 vetoes: Sequence[tuple] | None = None) -> array:
    """Triangles of the drawn cells of an ``nu x nv`` vertex grid (vertex ``k = i nv + j``).

    Cell ``(i, j)`` gives ``(k, k + nv, k + 1, k + 1, k + nv, k + nv + 1)``;
    cells in row-major order. With ``covers`` ``None`` every cell is drawn;
    else cell ``(i, j)`` is drawn when any cover ``(i0, j0, rows, cols, cells,
    width)`` has it inside its block (``i0 <= i < i0 + len(rows)``, ``j0 <= j <
    j0 + len(cols)``) and ``cells[rows[i - i0] width + cols[j - j0]]`` is non-zero:
    a mask (``bytes``, ``width`` columns) sampled at one mask row per cell row
    and one mask column per cell column (the mask cell holding the cell's centre).
    ``vetoes`` (same tuples, in order) then take cells away: each *sets* a cell's
    veto to its mask's value over its block, so of the vetoes holding a cell the
    last decides, and a vetoed cell is not drawn.

    A cell row's drawn flags are one integer per (cover, mask row), a byte per
    cell, ORed over the covers of the row (``int.from_bytes``: C speed); a veto's
    integer replaces the bytes of its block in the row's veto integer; the
    runs of drawn cells (a regular expression over the bytes) are copied from
    the full grid's triangles as whole slices. Rows with the same covers,
    vetoes and mask rows share their runs.
    """
    full = _full_grid(nu, nv)
    if covers is None:
        return full
    c1 = nv - 1
    every = list(covers) + list(vetoes or ())
    first_veto = len(covers)
    by_row: list[list[tuple[int, int]]] = [[] for _ in range(nu - 1)]
    for c, (i0, _, rows, _, _, _) in enumerate(every):
        for i, r in enumerate(rows, i0):
            by_row[i].append((c, r))
    bits_of: dict[tuple[int, int], int] = {}
    runs_of: dict[tuple, list[tuple[int, int]]] = {}
    source = memoryview(full).cast("B")
    indices = array("I")
    for i, row_covers in enumerate(by_row):
        key = tuple(row_covers)
        runs = runs_of.get(key)
        if runs is None:
            bits = veto = 0
            for c, r in key:
                b = bits_of.get((c, r))
                _, j0, _, cols, cells, width = every[c]
                if b is None:
                    get = cells[r * width : (r + 1) * width].__getitem__
                    b = int.from_bytes(bytes(map(get, cols)), "little") << (8 * j0)
                    bits_of[c, r] = b
                if c < first_veto:
                    bits |= b
                else:  # the block's bytes of the veto become this veto's
                    veto = veto & ~(((1 << (8 * len(cols))) - 1) << (8 * j0)) | b
            flags = (bits & ~veto).to_bytes(c1, "little")
            runs = runs_of[key] = [m.span() for m in _RUNS.finditer(flags)]
        base = 24 * i * c1
        for j0, j1 in runs:
            indices.frombytes(source[base + 24 * j0 : base + 24 * j1])
    return indices


def map_vectors(values: array, matrix: Sequence[Sequence[float]],
                offset: Sequence[float] | None = None, normalise: bool = False) -> array:
    """``M x + t`` for each 3-vector ``x`` of ``values`` (flat ``x, y, z, ...``): ``array('f')``.

    Each component is ``m_r0 x + m_r1 y + m_r2 z (+ t_r)``, summed in that
    order in float64; with ``normalise`` the result is divided by its length
    (left as is where that is zero). ``offset`` ``None`` adds nothing (not even
    ``0.0``, which would turn ``-0.0`` into ``0.0``).
    """
    if normalise and offset is not None:
        raise ValueError("map_vectors normalises directions, which take no offset")
    if len(values) % 3:
        raise ValueError(f"values hold 3-vectors: {len(values)} is not a multiple of 3")
    (a, b, c), (d, e, f), (g, h, k) = matrix
    sqrt = math.sqrt
    it = iter(values)
    out: list[float] = []
    if normalise:
        for x, y, z in zip(it, it, it, strict=False):
            mx, my, mz = a * x + b * y + c * z, d * x + e * y + f * z, g * x + h * y + k * z
            length = sqrt(mx * mx + my * my + mz * mz) or 1.0
            out += (mx / length, my / length, mz / length)
    elif offset is not None:
        tx, ty, tz = offset
        for x, y, z in zip(it, it, it, strict=False):
            out += (a * x + b * y + c * z + tx, d * x + e * y + f * z + ty,
                    g * x + h * y + k * z + tz)
    else:
        for x, y, z in zip(it, it, it, strict=False):
            out += (a * x + b * y + c * z, d * x + e * y + f * z, g * x + h * y + k * z)
    return array("f", out)


def _texel_axis(params: Sequence[float], lo: float, hi: float, size: int,
                flip: bool) -> list[tuple[int, int, float, float]]:
    """Per parameter the texels and weights along one image axis, as
    :meth:`client_py.layers.TextureImage.sample` computes them: ``(t0, t1, 1 - f, f)``
    with ``t = (x - lo) / (hi - lo) size - 1/2`` (``(hi - x) / ...`` when ``flip``:
    image rows run down in ``v``) clamped to ``[0, size - 1]``, ``t0 = min(int(t),
    size - 2)`` (``0`` for one texel), ``t1 = min(t0 + 1, size - 1)``, ``f = t - t0``."""
    out = []
    span, top, last = hi - lo, size - 1.0, size - 2
    for x in params:
        t = ((hi - x) if flip else (x - lo)) / span * size - 0.5
        t = min(max(t, 0.0), top)
        t0 = min(int(t), last) if size > 1 else 0
        f = t - t0
        out.append((t0, min(t0 + 1, size - 1), 1 - f, f))
    return out


def sample_texture(us: Sequence[float], vs: Sequence[float], blocks: Sequence[tuple]) -> array:
    """RGB bytes (``array('B')``, 3 per vertex, row-major) of the grid ``us x vs`` sampled
    bilinearly from images over blocks of it; ``0`` outside every block.

    ``blocks`` are ``(r0, r1, c0, c1, (width, height, rgb, (u0, v0, u1, v1)))``,
    disjoint: the image (``rgb`` ``3 width height`` bytes, rows top to bottom)
    over the uv rectangle colours the vertices of rows ``r0 <= i < r1`` and
    columns ``c0 <= j < c1``. Vertex ``(u, v)`` gets, per channel,
    ``int(top (1 - fy) + bottom fy + 0.5)`` with ``top = p(y0, x0) (1 - fx) +
    p(y0, x1) fx``, ``bottom`` likewise on row ``y1``, texels and weights as
    :func:`_texel_axis` (:meth:`client_py.layers.TextureImage.sample`, float64
    operations in the same order: the same bytes).

    Per block, the column texels come once and the image rows they read are
    copied into one compact image; per grid row, that image's columns ``x0``
    and ``x1`` are strided slices (C speed), blended into the ``top``/``bottom``
    values of all three channels by one comprehension, and a second one picks
    and blends those per vertex and channel (truncated by ``map(int, ...)``, which
    measured faster than ``int()`` in the comprehension in CPython and as fast in
    Pyodide). Consecutive rows with the same ``x0`` and ``fx``
    (clamped at an image edge) repeat the previous row's bytes.
    """
    n_cols = len(vs)
    out = bytearray(3 * len(us) * n_cols)
    for r0, r1, c0, c1, (width, height, rgb, (u0, v0, u1, v1)) in blocks:
        cols = _texel_axis(vs[c0:c1], v0, v1, height, flip=True)
        read = sorted({y for y0, y1, _, _ in cols for y in (y0, y1)})
        rank = {y: k for k, y in enumerate(read)}
        n = len(read)  # channel c of compact row k: value c n + k of a grid row's blend
        picks = [(c * n + rank[y0], c * n + rank[y1], gy, fy)
                 for y0, y1, gy, fy in cols for c in range(3)]
        stride = 3 * width
        compact = b"".join([rgb[stride * y : stride * (y + 1)] for y in read])
        span = 3 * (c1 - c0)
        last, row = None, b""
        for i, (x0, x1, gx, fx) in enumerate(_texel_axis(us[r0:r1], u0, u1, width, False), r0):
            if (x0, fx) != last:
                a, b = 3 * x0, 3 * x1
                left = compact[a::stride] + compact[a + 1 :: stride] + compact[a + 2 :: stride]
                right = compact[b::stride] + compact[b + 1 :: stride] + compact[b + 2 :: stride]
                h = [p * gx + q * fx for p, q in zip(left, right, strict=True)]
                row = bytes(map(int, [h[k0] * gy + h[k1] * fy + 0.5
                                        for k0, k1, gy, fy in picks]))
                last = (x0, fx)
            at = 3 * (i * n_cols + c0)
            out[at : at + span] = row
    return array("B", out)
