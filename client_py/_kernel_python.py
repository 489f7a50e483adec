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
"""

from __future__ import annotations

import math
import struct
from array import array
from collections.abc import Callable, Sequence
from functools import cache

from .basis import basis_table
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
    comp: Sequence[float], n_u: int, n_v: int, q: int, spans_v, Nv, dNv
) -> tuple[list[list[float]], list[list[float]]]:
    """``T_a(v_j)`` and ``dT_a/dv(v_j)`` for every control row ``a`` of one component.

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
    for a in range(n_u):
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
    # Homogeneous components P^w = (w x, w y, w z, w), each row-major over (a, b).
    comps = [pts[0::3], pts[1::3], pts[2::3]]
    if rational:
        comps = [[w * x for w, x in zip(wts, comp, strict=True)] for comp in comps] + [wts]
    blended = [_blend_rows_along_v(comp, n_u, n_v, q, spans_v, Nv, dNv) for comp in comps]

    evaluate_row = _row_evaluator(p, rational)
    tol = normal_tolerance(surface)
    n_j = len(vs)
    positions, normals = array(typecode), array(typecode)
    # struct packs a row of floats into the array's bytes 2-3 times faster than fromlist()
    pack = struct.Struct(f"={3 * n_j}{typecode}").pack
    degenerate: list[int] = []
    for i, (span, nu_i, dnu_i) in enumerate(zip(spans_u, Nu, dNu, strict=True)):
        lo, hi = span - p, span + 1
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
    p = degree
    spans_u, Nu, _ = basis_table(p, knots_u, n_u, us)
    spans_v, Nv, _ = basis_table(p, knots_v, n_v, vs)
    gather = [[span - p + k for span in spans_v] for k in range(p + 1)]
    coeffs = [[row[k] for row in Nv] for k in range(p + 1)]
    blend = _blend(p + 1)
    rows: dict[int, list[float]] = {}
    for a in range(min(spans_u) - p, max(spans_u) + 1):
        get = coefficients[a * n_v : (a + 1) * n_v].__getitem__
        rows[a] = blend(coeffs, [list(map(get, index)) for index in gather])
    out = array("d")
    n_j = len(vs)
    for span, nu_i in zip(spans_u, Nu, strict=True):
        window = [rows[span - p + k] for k in range(p + 1)]
        out.extend(blend([[c] * n_j for c in nu_i], window))
    return out


def displace_grid(positions: array, normals: array, displacement: array, n_rows: int,
                  n_cols: int, window: tuple[int, int, int, int]) -> tuple[array, array]:
    """``X = S + D n`` on an ``n_rows x n_cols`` grid and unit normals of ``X`` by differences.

    ``positions``/``normals`` hold ``S`` and the unit normal ``n`` of the base per
    vertex (``3`` values each, row-major), ``displacement`` holds ``D``. Only the
    vertices of ``window = (r0, r1, c0, c1)`` (rows ``r0 <= i < r1``, columns
    ``c0 <= j < c1``) are returned: positions and normals as ``array('f')``. The
    normal at ``(i, j)`` is ``(X_{i+1,j} - X_{i-1,j}) x (X_{i,j+1} - X_{i,j-1})``
    normalised, one-sided on the grid's outer rows/columns (which is why the
    caller evaluates one ring beyond its region where the domain allows); where
    that vanishes (a pole) the base normal is kept.
    """
    count = n_rows * n_cols
    xs = [positions[3 * k] + displacement[k] * normals[3 * k] for k in range(count)]
    ys = [positions[3 * k + 1] + displacement[k] * normals[3 * k + 1] for k in range(count)]
    zs = [positions[3 * k + 2] + displacement[k] * normals[3 * k + 2] for k in range(count)]
    r0, r1, c0, c1 = window
    pos: list[float] = []
    nrm: list[float] = []
    for i in range(r0, r1):
        up, down = min(i + 1, n_rows - 1) * n_cols, max(i - 1, 0) * n_cols
        row = i * n_cols
        for j in range(c0, c1):
            k = row + j
            jp, jm = min(j + 1, n_cols - 1), max(j - 1, 0)
            ax, ay, az = xs[up + j] - xs[down + j], ys[up + j] - ys[down + j], \
                zs[up + j] - zs[down + j]
            bx, by, bz = xs[row + jp] - xs[row + jm], ys[row + jp] - ys[row + jm], \
                zs[row + jp] - zs[row + jm]
            nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
            length = math.sqrt(nx * nx + ny * ny + nz * nz)
            pos += (xs[k], ys[k], zs[k])
            if length > 0.0:
                nrm += (nx / length, ny / length, nz / length)
            else:
                nrm += (normals[3 * k], normals[3 * k + 1], normals[3 * k + 2])
    return array("f", pos), array("f", nrm)
