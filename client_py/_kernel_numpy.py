"""numpy grid evaluation kernel: the same separable evaluation as ``_kernel_python``
with dense basis matrices, used where numpy is importable (CPython, full Pyodide).

With ``B_u[i, a] = N_a(u_i)`` and ``B_v[j, b] = N_b(v_j)`` (and ``B'`` their
derivatives) the homogeneous grid is ``S^w = B_u P^w B_v^T`` per component.
"""

from __future__ import annotations

from array import array
from collections.abc import Sequence

import numpy as np

from .basis import basis_table


def _basis_matrices(degree: int, knots, n_ctrl: int, params: Sequence[float]):
    spans, values, derivs = basis_table(degree, knots, n_ctrl, params)
    m = len(params)
    B = np.zeros((m, n_ctrl))
    dB = np.zeros((m, n_ctrl))
    cols = np.asarray(spans)[:, None] - degree + np.arange(degree + 1)
    rows = np.arange(m)[:, None]
    B[rows, cols] = values
    dB[rows, cols] = derivs
    return B, dB


def evaluate_grid(surface, us: Sequence[float], vs: Sequence[float]):
    """Same contract as :func:`client_py._kernel_python.evaluate_grid`."""
    (p, q), (n_u, n_v) = surface.degree, surface.shape
    U, V = surface.knots
    Bu, dBu = _basis_matrices(p, U, n_u, us)
    Bv, dBv = _basis_matrices(q, V, n_v, vs)
    P = np.asarray(surface.flat_points, dtype=float).reshape(n_u, n_v, 3)
    if surface.flat_weights is not None:
        w = np.asarray(surface.flat_weights, dtype=float).reshape(n_u, n_v, 1)
        P = np.concatenate([P * w, w], axis=2)
    T = np.einsum("jb,abc->ajc", Bv, P)  # blend along v: (n_u, J, comp)
    Tv = np.einsum("jb,abc->ajc", dBv, P)
    S = np.einsum("ia,ajc->ijc", Bu, T)
    Su = np.einsum("ia,ajc->ijc", dBu, T)
    Sv = np.einsum("ia,ajc->ijc", Bu, Tv)
    if P.shape[2] == 4:
        pos = S[..., :3] / S[..., 3:]
        # tangents without the common positive factor 1/w (removed by normalisation)
        Su = Su[..., :3] - Su[..., 3:] * pos
        Sv = Sv[..., :3] - Sv[..., 3:] * pos
    else:
        pos = S
    n = np.cross(Su, Sv)
    length = np.linalg.norm(n, axis=2)
    scale = np.linalg.norm(Su, axis=2) * np.linalg.norm(Sv, axis=2)
    ok = length > 1e-10 * scale
    n = np.where(ok[..., None], n / np.where(ok, length, 1.0)[..., None], 0.0)
    degenerate = np.flatnonzero(~ok.ravel()).tolist()
    positions = array("f", pos.astype(np.float32).ravel().tobytes())
    normals = array("f", n.astype(np.float32).ravel().tobytes())
    return positions, normals, degenerate
