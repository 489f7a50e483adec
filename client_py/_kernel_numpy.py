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


def evaluate_grid(surface, us: Sequence[float], vs: Sequence[float], typecode: str = "f"):
    """Same contract as :func:`client_py._kernel_python.evaluate_grid`."""
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
    S = _blend(Nu, su, T, 1)  # then along u: (C, I, J)
    Su = _blend(dNu, su, T, 1)
    Sv = _blend(Nu, su, Tv, 1)
    tol = normal_tolerance(surface)
    if len(P) == 4:
        pos = S[:3] / S[3]
        # tangents without the common positive factor 1/w (removed by normalisation)
        Su = Su[:3] - Su[3] * pos
        Sv = Sv[:3] - Sv[3] * pos
        tol = tol * S[3] * S[3]
    else:
        pos = S
    (ax, ay, az), (bx, by, bz) = Su, Sv
    n = np.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx])
    length = np.sqrt(np.einsum("cij,cij->ij", n, n))
    ok = length > tol
    n /= np.where(ok, length, np.inf)
    degenerate = np.flatnonzero(~ok).tolist()
    dtype = np.float32 if typecode == "f" else np.float64
    positions = array(typecode, np.moveaxis(pos, 0, -1).astype(dtype).tobytes())
    normals = array(typecode, np.moveaxis(n, 0, -1).astype(dtype).tobytes())
    return positions, normals, degenerate


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
    """Same contract as :func:`client_py._kernel_python.displace_grid`."""
    S = np.frombuffer(positions, dtype=float).reshape(n_rows, n_cols, 3)
    n = np.frombuffer(normals, dtype=float).reshape(n_rows, n_cols, 3)
    X = S + np.frombuffer(displacement, dtype=float).reshape(n_rows, n_cols, 1) * n
    r0, r1, c0, c1 = window
    rows, cols = np.arange(r0, r1), np.arange(c0, c1)
    up, down = np.minimum(rows + 1, n_rows - 1), np.maximum(rows - 1, 0)
    right, left = np.minimum(cols + 1, n_cols - 1), np.maximum(cols - 1, 0)
    a = X[up][:, cols] - X[down][:, cols]
    b = X[rows][:, right] - X[rows][:, left]
    (ax, ay, az), (bx, by, bz) = np.moveaxis(a, -1, 0), np.moveaxis(b, -1, 0)
    m = np.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], axis=-1)
    length = np.sqrt(np.einsum("ijc,ijc->ij", m, m))[..., None]
    m = np.where(length > 0.0, m / np.where(length > 0.0, length, 1.0), n[r0:r1, c0:c1])
    return (array("f", X[r0:r1, c0:c1].astype(np.float32).tobytes()),
            array("f", m.astype(np.float32).tobytes()))
