"""numpy grid evaluation kernel: the same separable evaluation as ``_kernel_python``,
vectorised, used where numpy is importable (CPython, a full Pyodide).

With the homogeneous control points stacked as ``P^w`` of shape ``(C, n_u, n_v)``
(``C = 4`` when rational: ``w x, w y, w z, w``), the grid is
``S^w_c = B_u P^w_c B_v^T`` with ``B_u[i, a] = N_a(u_i)``. ``B_u`` has only
``p + 1`` non-zeros per row, so each product is done as ``p + 1`` broadcast
multiply-adds of gathered rows (:func:`_blend`) instead of a dense ``matmul``:
``O(p)`` rather than ``O(n_u)`` work per point, the same summation order as the
pure-Python kernel, and no BLAS threads, which on a small busy machine cost
more than they save. The basis tables come vectorised from ``_numpy_basis``.

The other operations (tile fields and their sums, displacement, drawn cells,
affine maps, texture sampling) follow ``_kernel_python``'s contracts with the same arithmetic,
operation for operation (no ``matmul``, ``einsum`` or reordered sums), so
both kernels give the same bits; large grids go in blocks of
:data:`ROWS_PER_BLOCK` rows so that temporaries stay in cache.
"""

from __future__ import annotations

from array import array
from collections.abc import Sequence

import numpy as np

from ._numpy_basis import basis_arrays
from .surface import normal_tolerance


def _basis_bands(degree: int, knots, n_ctrl: int, params: Sequence[float]):
    """Window starts ``(m,)`` and basis values and derivatives ``(p + 1, m)``.

    Row ``k`` of the bands holds ``N_{s_t + k}(t)`` for each parameter ``t``
    with window start ``s_t = span(t) - p``: the non-zero diagonals of the
    basis matrix ``B[t, a] = N_a(t)``.
    """
    spans, values, derivs = basis_arrays(degree, knots, n_ctrl, params)
    return spans.astype(np.intp) - degree, values.T.copy(), derivs.T.copy()


def _blend(bands, starts, rows, axis: int) -> np.ndarray:
    """``sum_k bands[k] * rows.take(starts + k, axis)``: the banded product ``B rows``.

    ``rows`` has the control index on ``axis``; ``bands[k]`` broadcasts
    along the sampled axis that replaces it.
    """
    shape = [1] * rows.ndim
    shape[axis] = -1
    out = bands[0].reshape(shape) * rows.take(starts, axis)
    for k in range(1, len(bands)):
        out += bands[k].reshape(shape) * rows.take(starts + k, axis)
    return out


ROWS_PER_BLOCK = 32  # grid rows evaluated together: a block's temporaries stay in cache


def evaluate_grid(surface, us: Sequence[float], vs: Sequence[float], typecode: str = "f"):
    """Same contract as :func:`client_py._kernel_python.evaluate_grid`.

    The blend along ``v`` is done once for all control rows; the blend along
    ``u`` and the normals run over blocks of :data:`ROWS_PER_BLOCK` grid rows,
    so that the dozen ``(C, rows, J)`` temporaries of a block stay in cache
    (at 1025^2 whole-grid temporaries would be 34 MB each).
    """
    (p, q), (n_u, n_v) = surface.degree, surface.shape
    U, V = surface.knots
    su, Nu, dNu = _basis_bands(p, U, n_u, us)
    sv, Nv, dNv = _basis_bands(q, V, n_v, vs)
    # (C, n_u, n_v): x, y, z planes, times w and with w appended when rational
    P = np.asarray(surface.flat_points, dtype=float).reshape(n_u, n_v, 3).transpose(2, 0, 1)
    if surface.flat_weights is not None:
        w = np.asarray(surface.flat_weights, dtype=float).reshape(1, n_u, n_v)
        P = np.concatenate([P * w, w])
    T = _blend(Nv, sv, P, 2)  # blend along v: (C, n_u, J)
    Tv = _blend(dNv, sv, P, 2)
    tol0 = normal_tolerance(surface)
    dtype = np.float32 if typecode == "f" else np.float64
    n_i, n_j = len(us), len(vs)
    positions = np.empty((n_i, n_j, 3), dtype=dtype)
    normals = np.empty((n_i, n_j, 3), dtype=dtype)
    degenerate = []
    for i0 in range(0, n_i, ROWS_PER_BLOCK):
        rows = slice(i0, i0 + ROWS_PER_BLOCK)
        starts, bands, dbands = su[rows], Nu[:, rows], dNu[:, rows]
        S = _blend(bands, starts, T, 1)  # then along u: (C, rows, J)
        Su = _blend(dbands, starts, T, 1)
        Sv = _blend(bands, starts, Tv, 1)
        tol = tol0
        if len(P) == 4:
            pos = S[:3] / S[3]
            # tangents without the common positive factor 1/w (removed by normalisation)
            Su = Su[:3] - Su[3] * pos
            Sv = Sv[:3] - Sv[3] * pos
            tol = tol * S[3] * S[3]
        else:
            pos = S
        (ax, ay, az), (bx, by, bz) = Su, Sv
        nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        length = np.sqrt(nx * nx + ny * ny + nz * nz)
        ok = length > tol
        length = np.where(ok, length, np.inf)
        for c, (value, normal) in enumerate(zip(pos, (nx, ny, nz), strict=True)):
            positions[rows, :, c] = value
            normals[rows, :, c] = normal / length
        degenerate += (np.flatnonzero(~ok) + i0 * n_j).tolist()
    return (array(typecode, positions.tobytes()), array(typecode, normals.tobytes()),
            degenerate)


def field_grid(degree: int, knots_u, knots_v, n_u: int, n_v: int, coefficients,
               us: Sequence[float], vs: Sequence[float]) -> array:
    """Same contract as :func:`client_py._kernel_python.field_grid`."""
    su, Nu, _ = _basis_bands(degree, knots_u, n_u, us)
    sv, Nv, _ = _basis_bands(degree, knots_v, n_v, vs)
    C = np.asarray(coefficients, dtype=float).reshape(n_u, n_v)
    D = _blend(Nu, su, _blend(Nv, sv, C, 1), 0)
    return array("d", D.ravel().tobytes())


def displace_grid(positions, normals, displacement, n_rows: int, n_cols: int,
                  window: tuple[int, int, int, int]) -> tuple[array, array]:
    """Same contract as :func:`client_py._kernel_python.displace_grid`.

    The clamped neighbours ``X_{min(i + 1, R - 1), j}`` etc. are slices of ``X``
    padded by one repeated vertex on every side (no gathers), taken over blocks
    of :data:`ROWS_PER_BLOCK` rows; the arithmetic is the pure-Python kernel's,
    term for term, so the results are the same.
    """
    S = np.frombuffer(positions, dtype=float).reshape(n_rows, n_cols, 3)
    n = np.frombuffer(normals, dtype=float).reshape(n_rows, n_cols, 3)
    D = np.frombuffer(displacement, dtype=float).reshape(n_rows, n_cols)
    r0, r1, c0, c1 = window
    # component planes (3, rows, cols), padded: P[:, i + 1, j + 1] = X[i, j], edges repeated
    P = np.pad(np.moveaxis(S, -1, 0) + D * np.moveaxis(n, -1, 0), ((0, 0), (1, 1), (1, 1)),
               mode="edge")
    out_pos = np.empty((r1 - r0, c1 - c0, 3), dtype=np.float32)
    out_nrm = np.empty((r1 - r0, c1 - c0, 3), dtype=np.float32)
    for i0 in range(r0, r1, ROWS_PER_BLOCK):
        i1 = min(i0 + ROWS_PER_BLOCK, r1)
        ax, ay, az = P[:, i0 + 2 : i1 + 2, c0 + 1 : c1 + 1] - P[:, i0 : i1, c0 + 1 : c1 + 1]
        bx, by, bz = P[:, i0 + 1 : i1 + 1, c0 + 2 : c1 + 2] - P[:, i0 + 1 : i1 + 1, c0 : c1]
        mx, my, mz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        length = np.sqrt(mx * mx + my * my + mz * mz)
        ok = length > 0.0
        length = np.where(ok, length, 1.0)
        base = n[i0:i1, c0:c1]
        block = slice(i0 - r0, i1 - r0)
        for c, m in enumerate((mx, my, mz)):
            out_pos[block, :, c] = P[c, i0 + 1 : i1 + 1, c0 + 1 : c1 + 1]
            out_nrm[block, :, c] = np.where(ok, m / length, base[..., c])
    return array("f", out_pos.tobytes()), array("f", out_nrm.tobytes())


def add_level(total: array, n_cols: int, blocks) -> None:
    """Same contract and scheme as :func:`client_py._kernel_python.add_level` (in place on
    ``total``): the level's field assembled from the blocks in reverse order, then added
    over the rows they span."""
    if not blocks:
        return
    T = np.frombuffer(total, dtype=float).reshape(-1, n_cols)  # a writable view
    level = np.zeros(T.shape)
    for r0, r1, c0, c1, values in reversed(blocks):
        level[r0:r1, c0:c1] = np.frombuffer(values, dtype=float).reshape(r1 - r0, c1 - c0)
    lo, hi = min(block[0] for block in blocks), max(block[1] for block in blocks)
    T[lo:hi] += level[lo:hi]


def cell_indices(nu: int, nv: int, covers=None) -> array:
    """Same contract as :func:`client_py._kernel_python.cell_indices`: the drawn-cell flags
    as one boolean ``(nu - 1, nv - 1)`` array (each cover ORs its gathered mask
    ``cells[rows][:, cols]`` into its block), the drawn cells' triangles from their
    row-major indices."""
    if covers is None:
        i, j = np.divmod(np.arange((nu - 1) * (nv - 1), dtype=np.uint32), np.uint32(nv - 1))
    else:
        drawn = np.zeros((nu - 1, nv - 1), dtype=bool)
        for i0, j0, rows, cols, cells, width in covers:
            mask = np.frombuffer(cells, dtype=np.uint8).reshape(-1, width) != 0
            rows, cols = np.asarray(rows, dtype=np.intp), np.asarray(cols, dtype=np.intp)
            drawn[i0 : i0 + len(rows), j0 : j0 + len(cols)] |= mask[np.ix_(rows, cols)]
        i, j = np.nonzero(drawn)
    k = (i * nv + j).astype(np.uint32)
    corners = np.array([0, nv, 1, 1, nv, nv + 1], dtype=np.uint32)
    return array("I", (k[:, None] + corners).tobytes())


def map_vectors(values: array, matrix, offset=None, normalise: bool = False) -> array:
    """Same contract as :func:`client_py._kernel_python.map_vectors`, the same operations
    in the same order on whole columns (so the same float32 results)."""
    if normalise and offset is not None:
        raise ValueError("map_vectors normalises directions, which take no offset")
    x, y, z = np.frombuffer(values, dtype=values.typecode).reshape(-1, 3).T.astype(float)
    out = np.empty((len(x), 3), dtype=np.float32)
    cols = [a * x + b * y + c * z for a, b, c in matrix]
    if offset is not None:
        cols = [col + t for col, t in zip(cols, offset, strict=True)]
    if normalise:
        mx, my, mz = cols
        length = np.sqrt(mx * mx + my * my + mz * mz)
        length[length == 0.0] = 1.0
        cols = [col / length for col in cols]
    for r, col in enumerate(cols):
        out[:, r] = col
    return array("f", out.tobytes())


def _texel_axis(params, lo: float, hi: float, size: int, flip: bool):
    """Same as :func:`client_py._kernel_python._texel_axis` on a whole float64 array:
    ``(t0, t1, 1 - f, f)`` as arrays."""
    t = ((hi - params) if flip else (params - lo)) / (hi - lo) * size - 0.5
    t = np.minimum(np.maximum(t, 0.0), size - 1.0)
    t0 = np.minimum(t.astype(np.intp), size - 2) if size > 1 else np.zeros(len(t), np.intp)
    f = t - t0
    return t0, np.minimum(t0 + 1, size - 1), 1 - f, f


TEXELS_PER_BLOCK = 1 << 16  # values blended together: a chunk's temporaries stay small


def sample_texture(us, vs, blocks) -> array:
    """Same contract as :func:`client_py._kernel_python.sample_texture`, the same float64
    operations in the same order on arrays: per block the texels and weights of its
    rows and columns, then, a chunk of grid rows at a time, the horizontal blends
    ``p(y, x0) (1 - fx) + p(y, x1) fx`` of the image rows the columns read as one
    ``(rows read, grid rows, 3)`` array, and the vertical blend of the two of them
    each column picks."""
    us, vs = np.asarray(us, dtype=float), np.asarray(vs, dtype=float)
    out = np.zeros((len(vs), len(us), 3), dtype=np.uint8)  # column-major: filled by columns
    for r0, r1, c0, c1, (width, height, rgb, (u0, v0, u1, v1)) in blocks:
        image = np.frombuffer(rgb, dtype=np.uint8).reshape(height, width, 3)
        y0, y1, gy, fy = _texel_axis(vs[c0:c1], v0, v1, height, flip=True)
        read, ranks = np.unique(np.concatenate([y0, y1]), return_inverse=True)
        k0, k1 = ranks[: len(y0)], ranks[len(y0) :]
        rows = image[read]  # (rows read, width, 3)
        gy, fy = gy[:, None, None], fy[:, None, None]
        x0, x1, gx, fx = _texel_axis(us[r0:r1], u0, u1, width, flip=False)
        step = max(1, TEXELS_PER_BLOCK // (3 * len(read)))
        for a in range(0, r1 - r0, step):
            b = min(a + step, r1 - r0)
            h = rows[:, x0[a:b]] * gx[None, a:b, None] + rows[:, x1[a:b]] * fx[None, a:b, None]
            out[c0:c1, r0 + a : r0 + b] = (h[k0] * gy + h[k1] * fy + 0.5).astype(np.uint8)
    return array("B", out.transpose(1, 0, 2).tobytes())


def atlas_patch_grids(comps: list[list[float]], index: list[list[list[int]]], rational: bool,
                      degree: int, n: int, spans_t: Sequence[int], N: Sequence[Sequence[float]],
                      dN: Sequence[Sequence[float]], tol: float) -> list[tuple[list, list, list]]:
    """Points, unit normals and degenerate-normal vertices of atlas patches on an ``r × r``
    grid: ``S^w = B P^w B^T`` with the dense ``(r, n)`` basis matrices ``B``, ``B'`` built from
    the shared basis table (``spans_t``, ``N``, ``dN``), ``P^w`` the homogeneous control
    points ``comps`` (component-major) gathered by each patch's ``index`` ``(n, n)``.

    Returns, per patch, ``(S flat (r² 3), n flat (r² 3), [k of vertices without a normal])``
    (``client_py.atlas_mesh``'s evaluator contract).
    """
    r, d = len(spans_t), degree
    B, dB = np.zeros((r, n)), np.zeros((r, n))
    for k, span in enumerate(spans_t):
        B[k, span - d : span + 1] = N[k]
        dB[k, span - d : span + 1] = dN[k]
    H = np.asarray(comps, dtype=float).T  # (control points, C)
    P = H[np.asarray(index, dtype=np.intp)]  # (F, n, n, C), P[f, a, b] = P^w_ab
    rows = np.einsum("jb,fabc->fajc", B, P)
    drows = np.einsum("jb,fabc->fajc", dB, P)
    A = np.einsum("ia,fajc->fijc", B, rows)
    Au = np.einsum("ia,fajc->fijc", dB, rows)
    Av = np.einsum("ia,fajc->fijc", B, drows)
    if not rational:
        S, Su, Sv = A, Au, Av
        small = tol
    else:
        w = A[..., 3:]
        S = A[..., :3] / w
        Su = Au[..., :3] - Au[..., 3:] * S  # (A_u - w_u S) / w: the 1/w the unit normal drops
        Sv = Av[..., :3] - Av[..., 3:] * S
        small = tol * w[..., 0] ** 2
    cross = np.cross(Su, Sv)
    length = np.sqrt((cross**2).sum(axis=-1))
    ok = length > small
    unit = np.where(ok[..., None], cross / np.where(ok, length, 1.0)[..., None], 0.0)
    return [(S[k].reshape(-1).tolist(), unit[k].reshape(-1).tolist(),
             np.flatnonzero(~ok[k].reshape(-1)).tolist()) for k in range(len(index))]
