"""Pure-Python grid evaluation kernel: the fast path in the browser (Pyodide has no numpy here).

Evaluating ``S`` on a grid ``u_0..u_{I-1} x v_0..v_{J-1}`` is separable:

    S^w(u_i, v_j) = sum_a N_a(u_i) T_a(v_j),   T_a(v_j) = sum_b N_b(v_j) P^w_ab

so the kernel (1) builds the basis tables once per grid direction, (2) blends
every control *row* ``a`` along ``v`` into ``T_a`` and ``T'_a`` (value and
v-derivative at all ``v_j``), and (3) for each ``u_i`` blends ``p + 1`` of
those rows. Every blend is a linear combination of whole lists
(:func:`_combine`), which CPython runs as tight comprehensions over ``zip``
without index arithmetic; no basis function is computed per point.
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Sequence

from .basis import basis_table


def _combine(coeffs: Sequence[float], rows: Sequence[Sequence[float]]) -> list[float]:
    """``sum_k coeffs[k] * rows[k]`` for equal-length lists (one pass per term)."""
    c0 = coeffs[0]
    acc = [c0 * x for x in rows[0]]
    for c, row in zip(coeffs[1:], rows[1:], strict=True):
        if c != 0.0:
            acc = [a + c * x for a, x in zip(acc, row, strict=False)]
    return acc


def evaluate_grid(surface, us: Sequence[float], vs: Sequence[float]):
    """Points and unit normals of ``surface`` at every ``(u_i, v_j)``, row-major in ``i``.

    Returns
    -------
    positions, normals : array('f'), each ``3 * I * J`` values
    degenerate : list of int
        Vertex indices where ``S_u x S_v`` vanished (normal left as 0, 0, 0).
    """
    (p, q), (n_u, n_v) = surface.degree, surface.shape
    U, V = surface.knots
    spans_u, Nu, dNu = basis_table(p, U, n_u, us)
    spans_v, Nv, dNv = basis_table(q, V, n_v, vs)
    pts, wts = surface.flat_points, surface.flat_weights
    rational = wts is not None
    # Control columns per homogeneous component: cols[c][b] = (P^w_{0b}[c], ..., P^w_{n_u-1,b}[c]).
    n_comp = 4 if rational else 3
    comps = [pts[0::3], pts[1::3], pts[2::3]]
    if rational:
        comps = [[w * x for w, x in zip(wts, comp, strict=True)] for comp in comps] + [wts]
    cols = [[comp[b::n_v] for b in range(n_v)] for comp in comps]

    # Stage 2: blend control columns along v, then transpose to rows T[c][a] over j.
    rows_val, rows_dv = [], []
    for c in range(n_comp):
        val_cols, dv_cols = [], []
        for span, nv_j, dnv_j in zip(spans_v, Nv, dNv, strict=True):
            window = cols[c][span - q : span + 1]
            val_cols.append(_combine(nv_j, window))
            dv_cols.append(_combine(dnv_j, window))
        rows_val.append(list(zip(*val_cols, strict=True)))
        rows_dv.append(list(zip(*dv_cols, strict=True)))

    n_j = len(vs)
    positions = array("f")
    normals = array("f")
    degenerate: list[int] = []
    sqrt = math.sqrt
    for i, (span, nu_i, dnu_i) in enumerate(zip(spans_u, Nu, dNu, strict=True)):
        lo, hi = span - p, span + 1
        S = [_combine(nu_i, rows_val[c][lo:hi]) for c in range(n_comp)]
        Su = [_combine(dnu_i, rows_val[c][lo:hi]) for c in range(n_comp)]
        Sv = [_combine(nu_i, rows_dv[c][lo:hi]) for c in range(n_comp)]
        if rational:
            # S = A / w; the tangents (A_u - w_u S) / w share the positive factor 1 / w,
            # which the normalisation removes, so it is never applied.
            inv = [1.0 / w for w in S[3]]
            xs = [a * r for a, r in zip(S[0], inv, strict=True)]
            ys = [a * r for a, r in zip(S[1], inv, strict=True)]
            zs = [a * r for a, r in zip(S[2], inv, strict=True)]
            tu = [
                [a - wd * s for a, wd, s in zip(Su[c], Su[3], pos, strict=True)]
                for c, pos in enumerate((xs, ys, zs))
            ]
            tv = [
                [a - wd * s for a, wd, s in zip(Sv[c], Sv[3], pos, strict=True)]
                for c, pos in enumerate((xs, ys, zs))
            ]
        else:
            xs, ys, zs = S
            tu, tv = Su, Sv
        row = [0.0] * (3 * n_j)
        row[0::3], row[1::3], row[2::3] = xs, ys, zs
        positions.extend(row)
        nrm = [0.0] * (3 * n_j)
        k = 0
        for xu, yu, zu, xv, yv, zv in zip(*tu, *tv, strict=True):
            nx = yu * zv - zu * yv
            ny = zu * xv - xu * zv
            nz = xu * yv - yu * xv
            length = sqrt(nx * nx + ny * ny + nz * nz)
            if length > 1e-10 * sqrt((xu * xu + yu * yu + zu * zu) * (xv * xv + yv * yv + zv * zv)):
                nrm[k] = nx / length
                nrm[k + 1] = ny / length
                nrm[k + 2] = nz / length
            else:
                degenerate.append(i * n_j + k // 3)
            k += 3
        normals.extend(nrm)
    return positions, normals, degenerate
