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
from functools import lru_cache

import numpy as np

from ._kernel_python import check_panel
from ._numpy_basis import basis_arrays
from .surface import normal_tolerance


def _basis_bands(degree: int, knots, n_ctrl: int, params: Sequence[float]):
    """Window starts ``(m,)`` and basis values and derivatives ``(p + 1, m)``.

    Row ``k`` of the bands holds ``N_{s_t + k}(t)`` for each parameter ``t``
    with window start ``s_t = span(t) - p``: the non-zero diagonals of the
    basis matrix ``B[t, a] = N_a(t)``. Kept per ``(p, knots, n, params)``
    (:func:`_cached_bands`): every patch of an atlas sums tiles on the same
    grid, so the same few dozen bands recur thousands of times.
    """
    return _cached_bands(degree, tuple(knots), n_ctrl, tuple(params))


@lru_cache(maxsize=512)
def _cached_bands(degree: int, knots: tuple, n_ctrl: int, params: tuple):
    """:func:`_basis_bands` of hashable arguments; the arrays are read-only (shared)."""
    spans, values, derivs = basis_arrays(degree, knots, n_ctrl, params)
    bands = spans.astype(np.intp) - degree, values.T.copy(), derivs.T.copy()
    for band in bands:
        band.flags.writeable = False
    return bands


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


def field_grids(degree: int, knots_u, knots_v, n_u: int, n_v: int, coefficients,
                us: Sequence[float], vs: Sequence[float]) -> list[array]:
    """Same contract as :func:`client_py._kernel_python.field_grids`: :func:`field_grid` of
    each (vectorised per tile already)."""
    return [field_grid(degree, knots_u, knots_v, n_u, n_v, c, us, vs) for c in coefficients]


def displace_grid(positions, normals, displacement, n_rows: int, n_cols: int,
                  window: tuple[int, int, int, int], panel: int | None = None,
                  with_positions: bool = True) -> tuple[array, array]:
    """Same contract as :func:`client_py._kernel_python.displace_grid`.

    The clamped neighbours ``X_{min(i + 1, R - 1), j}`` etc. are slices of ``X``
    padded by one repeated vertex on every side (no gathers), taken over blocks
    of :data:`ROWS_PER_BLOCK` rows (with panels, the left and right neighbours
    are copies with each panel's end columns clamped); the arithmetic is the
    pure-Python kernel's, term for term, so the results are the same.
    """
    check_panel(n_cols, panel)
    S = np.frombuffer(positions, dtype=float).reshape(n_rows, n_cols, 3)
    n = np.frombuffer(normals, dtype=float).reshape(n_rows, n_cols, 3)
    D = np.frombuffer(displacement, dtype=float).reshape(n_rows, n_cols)
    r0, r1, c0, c1 = window
    # component planes (3, rows, cols), padded: P[:, i + 1, j + 1] = X[i, j], edges repeated
    P = np.pad(np.moveaxis(S, -1, 0) + D * np.moveaxis(n, -1, 0), ((0, 0), (1, 1), (1, 1)),
               mode="edge")
    right, left = P[:, :, 2:], P[:, :, :-2]  # X_{i, j + 1}, X_{i, j - 1}, rows padded
    if panel is not None and panel < n_cols:  # clamped at each panel's own ends
        right, left, inner = right.copy(), left.copy(), P[:, :, 1:-1]
        right[:, :, panel - 1 :: panel] = inner[:, :, panel - 1 :: panel]
        left[:, :, ::panel] = inner[:, :, ::panel]
    out_pos = np.empty((r1 - r0, c1 - c0, 3), dtype=np.float32)
    out_nrm = np.empty((r1 - r0, c1 - c0, 3), dtype=np.float32)
    for i0 in range(r0, r1, ROWS_PER_BLOCK):
        i1 = min(i0 + ROWS_PER_BLOCK, r1)
        ax, ay, az = P[:, i0 + 2 : i1 + 2, c0 + 1 : c1 + 1] - P[:, i0 : i1, c0 + 1 : c1 + 1]
        bx, by, bz = right[:, i0 + 1 : i1 + 1, c0:c1] - left[:, i0 + 1 : i1 + 1, c0:c1]
        mx, my, mz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        length = np.sqrt(mx * mx + my * my + mz * mz)
        ok = length > 0.0
        length = np.where(ok, length, 1.0)
        base = n[i0:i1, c0:c1]
        block = slice(i0 - r0, i1 - r0)
        for c, m in enumerate((mx, my, mz)):
            out_pos[block, :, c] = P[c, i0 + 1 : i1 + 1, c0 + 1 : c1 + 1]
            out_nrm[block, :, c] = np.where(ok, m / length, base[..., c])
    return (array("f", out_pos.tobytes() if with_positions else b""),
            array("f", out_nrm.tobytes()))


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


def cell_indices(nu: int, nv: int, covers=None, vetoes=None) -> array:
    """Same contract as :func:`client_py._kernel_python.cell_indices`: the drawn-cell flags
    as one boolean ``(nu - 1, nv - 1)`` array (each cover ORs its gathered mask
    ``cells[rows][:, cols]`` into its block, each veto, in order, sets its block of a
    second array, which then clears the drawn cells it holds), the drawn cells' triangles
    from their row-major indices."""
    if covers is None:
        i, j = np.divmod(np.arange((nu - 1) * (nv - 1), dtype=np.uint32), np.uint32(nv - 1))
    else:
        drawn = np.zeros((nu - 1, nv - 1), dtype=bool)
        for i0, j0, rows, cols, cells, width in covers:
            drawn[i0 : i0 + len(rows), j0 : j0 + len(cols)] |= _gather(rows, cols, cells, width)
        if vetoes:
            veto = np.zeros_like(drawn)
            for i0, j0, rows, cols, cells, width in vetoes:
                veto[i0 : i0 + len(rows), j0 : j0 + len(cols)] = _gather(rows, cols, cells,
                                                                         width)
            drawn &= ~veto
        i, j = np.nonzero(drawn)
    k = (i * nv + j).astype(np.uint32)
    corners = np.array([0, nv, 1, 1, nv, nv + 1], dtype=np.uint32)
    return array("I", (k[:, None] + corners).tobytes())


def _gather(rows, cols, cells: bytes, width: int) -> np.ndarray:
    """A cover's mask ``cells`` (``width`` columns) at its ``rows`` and ``cols``, as booleans."""
    mask = np.frombuffer(cells, dtype=np.uint8).reshape(-1, width) != 0
    return mask[np.ix_(np.asarray(rows, dtype=np.intp), np.asarray(cols, dtype=np.intp))]


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
    grid (:func:`atlas_patch_arrays`), per patch ``(S flat (r² 3), n flat (r² 3), [k of
    vertices without a normal])`` as lists (``client_py.atlas_mesh``'s evaluator contract).
    """
    S, unit, bad = atlas_patch_arrays(comps, index, rational, degree, n, spans_t, N, dN, tol)
    return [(S[k].reshape(-1).tolist(), unit[k].reshape(-1).tolist(), bad[k])
            for k in range(len(index))]


#: patches evaluated together by :func:`atlas_patch_arrays`: their ``(F, r, r, 4)``
#: temporaries stay a few MB at the finest resolution, not a GB for a thousand patches
PATCHES_PER_BLOCK = 32


def atlas_patch_arrays(comps: list[list[float]], index: list[list[list[int]]], rational: bool,
                       degree: int, n: int, spans_t: Sequence[int], N: Sequence[Sequence[float]],
                       dN: Sequence[Sequence[float]], tol: float
                       ) -> tuple[np.ndarray, np.ndarray, list[list[int]]]:
    """Points ``S (F, r, r, 3)``, unit normals ``(F, r, r, 3)`` and, per patch, the vertices
    ``k = i r + j`` without a normal (``|C_u x C_v| <= tol``, normal left 0) of ``F`` atlas
    patches on an ``r × r`` grid: ``S^w = B P^w B^T`` with the dense ``(r, n)`` basis
    matrices ``B``, ``B'`` built from the shared basis table (``spans_t``, ``N``, ``dN``),
    ``P^w`` the homogeneous control points ``comps`` (component-major) gathered by each
    patch's ``index`` ``(n, n)``; in blocks of :data:`PATCHES_PER_BLOCK` patches, each
    evaluated alike whatever else is in its block.
    """
    r, d = len(spans_t), degree
    B, dB = np.zeros((r, n)), np.zeros((r, n))
    for k, span in enumerate(spans_t):
        B[k, span - d : span + 1] = N[k]
        dB[k, span - d : span + 1] = dN[k]
    H = np.asarray(comps, dtype=float).T  # (control points, C)
    gather = np.asarray(index, dtype=np.intp).reshape(len(index), n, n)
    points = np.empty((len(index), r, r, 3))
    normals = np.empty((len(index), r, r, 3))
    bad: list[list[int]] = []
    for first in range(0, len(index), PATCHES_PER_BLOCK):
        block = slice(first, first + PATCHES_PER_BLOCK)
        P = H[gather[block]]  # (F, n, n, C), P[f, a, b] = P^w_ab
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
        points[block] = S
        normals[block] = np.where(ok[..., None], cross / np.where(ok, length, 1.0)[..., None],
                                  0.0)
        bad += [np.flatnonzero(~row).tolist() for row in ok.reshape(len(ok), -1)]
    return points, normals, bad


def _unit_rows(x: np.ndarray) -> np.ndarray:
    """Each row of ``x (m, 3)`` over its length, ``(0, 0, 0)`` where that is 0:
    ``client_py.atlas_mesh._unit``'s arithmetic, operation for operation."""
    length = np.sqrt(x[:, 0] * x[:, 0] + x[:, 1] * x[:, 1] + x[:, 2] * x[:, 2])
    zero = length == 0.0
    out = x / np.where(zero, 1.0, length)[:, None]
    out[zero] = 0.0
    return out


def _difference_normals(X: np.ndarray, base: np.ndarray) -> np.ndarray:
    """:func:`displace_grid`'s normals of whole grids ``X (F, r, r, 3)`` with no
    displacement, ``base (F, r, r, 3)`` the normals kept at poles: the same arithmetic on
    every patch at once, as float32."""
    P = np.pad(X + 0.0 * base, ((0, 0), (1, 1), (1, 1), (0, 0)), mode="edge")
    ax, ay, az = np.moveaxis(P[:, 2:, 1:-1] - P[:, :-2, 1:-1], -1, 0)
    bx, by, bz = np.moveaxis(P[:, 1:-1, 2:] - P[:, 1:-1, :-2], -1, 0)
    m = np.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], axis=-1)
    length = np.sqrt(m[..., 0] * m[..., 0] + m[..., 1] * m[..., 1] + m[..., 2] * m[..., 2])
    ok = length > 0.0
    return np.where(ok[..., None], m / np.where(ok, length, 1.0)[..., None],
                    base).astype(np.float32)


def weld_atlas(plan) -> tuple[array, array, array, array, array]:
    """``client_py.atlas_mesh``'s welded mesh of a whole atlas from its weld plan
    (``atlas_mesh._WeldPlan``: the layout's vertex numbering, the evaluated grids and
    displacements per resolution, the seams' in-between vertices and the fans), with the
    pure-Python weld's arithmetic operation for operation and its sums in its order (one
    sequential ``bincount`` over the border samples in patch order), so that both give
    the same bytes. Returns float32 positions, normals and ``(u, v)``, then the triangles
    and the vertices' patches, as ``array``; without ``plan.shading`` the normals are empty
    and none of their work is done (the drawn normals by differences, the interior copies,
    the border sums), the rest is the same arithmetic on the same numbers, so the same
    bytes.
    """
    count, n_border, shade = plan.count, plan.n_border, plan.shading
    positions = np.zeros((count, 3))
    normals = np.zeros((count, 3)) if shade else None
    uvs = np.zeros((count, 2))
    owners = np.zeros(count, dtype=np.uint32)
    samples = []  # per group: the border samples' patch, node, flag, point, normal, shift, u, v
    ids_of = []  # per group: (F, r, r) global vertex of every sample
    bases = []  # per group: the unit normals of its grids, with the limit normal at poles
    for group in plan.groups:
        r, count_g = group.r, len(group.patches)
        points, base, poles = group.grid
        base = base.copy() if any(poles) else base
        for g, row in enumerate(poles):
            for k, normal in zip(row, group.pole_normals[g], strict=True):
                base[g, k // r, k % r] = normal
        bases.append(base)
        params = np.asarray(group.params, dtype=float)
        sides = np.frombuffer(group.sides, dtype=np.uint32).astype(np.intp).reshape(count_g, 4, r)
        ids = np.empty((count_g, r, r), dtype=np.intp)
        inner = (r - 2) ** 2
        ids[:, 1:-1, 1:-1] = (np.asarray(group.face_base, dtype=np.intp)[:, None]
                              + np.arange(inner)).reshape(count_g, r - 2, r - 2)
        ids[:, :, 0], ids[:, -1, :] = sides[:, 0], sides[:, 1]  # SIDES order: v = 0, u = 1,
        ids[:, :, -1], ids[:, 0, :] = sides[:, 2], sides[:, 3]  # v = 1, u = 0
        ids_of.append(ids)
        shifted = np.array([d is not None for d in group.displacements])
        D = np.zeros((count_g, r, r))
        for g, disp in enumerate(group.displacements):
            if disp is not None:
                D[g] = np.frombuffer(disp, dtype=float).reshape(r, r)
        # interior vertices: each patch's own block, displaced along its normal
        if inner:
            at = ids[:, 1:-1, 1:-1].reshape(-1)
            P, n = points[:, 1:-1, 1:-1], base[:, 1:-1, 1:-1]
            P = np.where(shifted[:, None, None, None], P + D[:, 1:-1, 1:-1, None] * n, P)
            positions[at] = P.reshape(-1, 3)
            if shade:
                normals[at] = n.reshape(-1, 3)
            uvs[at, 0] = np.repeat(params[1:-1], r - 2)[None, :].repeat(count_g, 0).ravel()
            uvs[at, 1] = np.tile(params[1:-1], (count_g, r - 2)).ravel()
            owners[at] = np.repeat(np.asarray(group.patches, dtype=np.uint32), inner)
        slots = np.asarray(group.border_slots, dtype=np.intp)
        pick = np.asarray(group.border_picks, dtype=np.intp)
        flags = np.frombuffer(group.evaluated, dtype=np.uint8).reshape(count_g, 4 * r)
        samples.append((np.repeat(np.asarray(group.patches, dtype=np.int64), len(slots)),
                        sides.reshape(count_g, 4 * r)[:, pick].reshape(-1),
                        flags[:, pick].reshape(-1).astype(bool),
                        points.reshape(count_g, r * r, 3)[:, slots].reshape(-1, 3),
                        base.reshape(count_g, r * r, 3)[:, slots].reshape(-1, 3),
                        D.reshape(count_g, r * r)[:, slots].reshape(-1),
                        np.tile(params[slots // r], count_g), np.tile(params[slots % r], count_g)))
    # border samples in the pure-Python weld's order: patch by patch, then along its border
    patch_of, node, evaluated, point, normal, shift, u, v = (np.concatenate(x)
                                                               for x in zip(*samples, strict=True))
    order = np.argsort(patch_of, kind="stable")
    patch_of, node, evaluated, point, normal, shift, u, v = (
        x[order] for x in (patch_of, node, evaluated, point, normal, shift, u, v))
    on, at = node[evaluated], evaluated
    direction = np.stack([np.bincount(on, normal[at, c], n_border) for c in range(3)], 1)
    shifts = np.bincount(on, shift[at], n_border)
    samplers = np.bincount(on, minlength=n_border)
    nodes, first = np.unique(node, return_index=True)  # each vertex's first sampler
    if len(nodes) != n_border:
        raise AssertionError("a border vertex no patch samples")
    owners[:n_border] = patch_of[first]
    uvs[:n_border, 0], uvs[:n_border, 1] = u[first], v[first]
    sampled = evaluated[first]
    moved = sampled & (shifts != 0.0)
    place = point[first]
    place[moved] = place[moved] + (shifts[moved] / samplers[moved])[:, None] \
        * _unit_rows(direction[moved])
    positions[:n_border][sampled] = place[sampled]
    between, a, b, s = (np.asarray(x) for x in plan.between)
    if len(between):  # on the segment of their coarse side's evaluated neighbours
        s = s.astype(float)[:, None]
        positions[between] = (1 - s) * positions[a] + s * positions[b]
    if shade and not plan.by_differences:  # the welded vertex's normal: its samplers' sum
        shading = np.stack([np.bincount(node, normal[:, c], n_border) for c in range(3)], 1)
    elif shade:  # normals of the displaced, welded surface
        shaded_samples = []
        for group, ids, base in zip(plan.groups, ids_of, bases, strict=True):
            r, count_g = group.r, len(group.patches)
            slots = np.asarray(group.border_slots, dtype=np.intp)
            shaded = np.empty((count_g, r * r, 3), dtype=np.float32)
            for first_patch in range(0, count_g, PATCHES_PER_BLOCK):
                block = slice(first_patch, first_patch + PATCHES_PER_BLOCK)
                shaded[block] = _difference_normals(positions[ids[block]], base[block]
                                                    ).reshape(-1, r * r, 3)
            normals[ids[:, 1:-1, 1:-1].reshape(-1)] = shaded.reshape(count_g, r, r, 3)[
                :, 1:-1, 1:-1].reshape(-1, 3)
            shaded_samples.append(shaded[:, slots].reshape(-1, 3).astype(float))
        shaded = np.concatenate(shaded_samples)[order]
        shading = np.stack([np.bincount(node, shaded[:, c], n_border) for c in range(3)], 1)
    if shade:
        normals[:n_border] = _unit_rows(shading)
    # triangles, patch by patch: whole cells, or the fans given at resolution changes
    triangles = {}
    for group, ids in zip(plan.groups, ids_of, strict=True):
        r = group.r
        cells = np.frombuffer(cell_indices(r, r), dtype=np.uint32).astype(np.intp)
        flat = ids.reshape(len(group.patches), r * r)
        for g, f in enumerate(group.patches):
            triangles[f] = plan.fans[f] if f in plan.fans else flat[g, cells]
    indices = np.concatenate([np.asarray(triangles[f], dtype=np.uint32)
                              for f in sorted(triangles)])
    extra_positions, extra_normals, extra_uvs, extra_owners = plan.extra
    if extra_owners:
        positions = np.concatenate([positions, np.reshape(extra_positions, (-1, 3))])
        if shade:
            normals = np.concatenate([normals, np.reshape(extra_normals, (-1, 3))])
        uvs = np.concatenate([uvs, np.reshape(extra_uvs, (-1, 2))])
        owners = np.concatenate([owners, np.asarray(extra_owners, dtype=np.uint32)])
    with np.errstate(over="ignore"):  # beyond float32: inf, as the pure-Python packing
        out = [array("f", x.astype(np.float32).tobytes()) if x is not None else array("f")
               for x in (positions, normals, uvs)]
    return (*out, array("I", indices.astype(np.uint32).tobytes()),
            array("I", owners.tobytes()))


def join_patch_arrays(parts: Sequence[tuple]) -> tuple[np.ndarray, np.ndarray, list]:
    """One :func:`atlas_patch_arrays` result of several, patches in order."""
    return (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
            [row for p in parts for row in p[2]])
