"""Least-squares fitting of a NURBS patch: linear B-spline fit, nonlinear NURBS refinement,
parameter correction.

Linear stage (the paper's initial solution, weights 1, fixed uniform clamped
knots, eq. 3). For data ``P_k`` at parameters ``(u_k, v_k)`` and collocation
matrix ``A`` (``A_kl = N_a(u_k) N_b(v_k)``, ``l = a n_v + b``) it solves

    min_Q ||A T q - P||^2 + lam ||L T q||^2,    Q = T q,

where ``T`` maps free to all control points (identity, or the periodic seam
closure ``Q_{n-1} = Q_0``, ``Q_{n-2} = 2 Q_0 - Q_1``, which makes the surface C1
across the seam of uniform clamped knots) and ``L`` stacks second differences
of the control net (a discrete thin-plate energy) that bridges holes. On a
full section matrix without smoothing the problem is separable:
``Q = (B_u T_u)^+ P (B_v^+)^T`` per coordinate — milliseconds for millions of
nodes.

Nonlinear stage (the paper's eq. 5): ``E(Q, W) = 1/2 sum_k ||C(u_k, v_k) - P_k||^2``
over control points and weights, by block-coordinate descent (exact ``Q`` for
fixed ``W``, Levenberg-Marquardt steps in ``omega = log W`` so weights stay
positive). The Jacobian is sparse: ``dC/dQ_l = R_l`` and
``dC/d omega_l = R_l (Q_l - C)`` with the rational basis ``R_l = w_l N_l / sum_j w_j N_j``.

Parameter correction ("fitting parameter values"): each data point's
``(u_k, v_k)`` moves to its foot point on the current surface by Gauss-Newton
on ``||S(u, v) - P_k||^2`` (Hoschek's intrinsic parameterization), so the
residuals become orthogonal distances.
"""

from __future__ import annotations

import functools

import numpy as np
import scipy.sparse as sp
from scipy.linalg import solveh_banded
from scipy.sparse.linalg import spsolve

from client_py._numpy_basis import basis_arrays

from .closest import SpanPolynomials, gauss_newton
from .nurbs import BasisRows, PatchModel

DEFAULT_SMOOTHING = 1e-6


# ------------------------------------------------------------------ structure matrices
def seam_closure(shape: tuple[int, int], periodic_u: bool,
                 poles: bool = False) -> sp.csr_matrix:
    """``T (n_u n_v, n_free)``: all control points from the free ones.

    Periodic in ``u``: rows ``n_u - 1`` and ``n_u - 2`` of the net are
    ``Q_0`` and ``2 Q_0 - Q_1`` (C1 closure). ``poles`` (a sphere map, whose
    ``v = 0`` and ``v = 1`` edges are single points in space): each of the first
    and last columns of the net is one shared free point, so the patch closes
    at its poles as a NURBS sphere does instead of fanning out where few scan
    points reach. Otherwise ``T = I``.
    """
    n_u, n_v = shape
    if not periodic_u and not poles:
        return sp.identity(n_u * n_v, format="csr")
    Tu = seam_closure_u(n_u) if periodic_u else sp.identity(n_u, format="csr")
    if not poles:
        return sp.kron(Tu, sp.identity(n_v), format="csr")
    if n_v < 4:
        raise ValueError(f"a map with poles needs at least 4 control points in v, got {n_v}")
    interior = sp.eye(n_v, n_v - 2, k=-1, format="csr")  # columns 1 .. n_v - 2
    first = np.zeros(n_v)
    first[0] = 1.0
    last = first[::-1].copy()
    ones = np.ones((n_u, 1))
    return sp.hstack([sp.kron(Tu, interior), sp.csr_matrix(np.kron(ones, first[:, None])),
                      sp.csr_matrix(np.kron(ones, last[:, None]))], format="csr")


def seam_closure_u(n_u: int) -> sp.csr_matrix:
    """The ``(n_u, n_u - 2)`` closure of one periodic direction (see :func:`seam_closure`)."""
    if n_u < 5:
        raise ValueError(f"a periodic direction needs at least 5 control points, got {n_u}")
    Tu = sp.lil_matrix((n_u, n_u - 2))
    for i in range(n_u - 2):
        Tu[i, i] = 1.0
    Tu[n_u - 2, 0], Tu[n_u - 2, 1] = 2.0, -1.0
    Tu[n_u - 1, 0] = 1.0
    return Tu.tocsr()


def second_differences(shape: tuple[int, int]) -> sp.csr_matrix:
    """``L``: second differences of the control net along ``u``, along ``v`` and mixed
    (weighted ``sqrt 2``), the discrete thin-plate energy ``||L Q||^2``."""
    n_u, n_v = shape

    def d2(n: int) -> sp.csr_matrix:
        if n < 3:
            return sp.csr_matrix((0, n))
        return sp.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(n - 2, n), format="csr")

    def d1(n: int) -> sp.csr_matrix:
        return sp.diags([-1.0, 1.0], [0, 1], shape=(n - 1, n), format="csr")

    Iu, Iv = sp.identity(n_u), sp.identity(n_v)
    return sp.vstack([sp.kron(d2(n_u), Iv), sp.kron(Iu, d2(n_v)),
                      np.sqrt(2.0) * sp.kron(d1(n_u), d1(n_v))], format="csr")


# ------------------------------------------------------------------ linear solves
@functools.lru_cache(maxsize=8)
def _thin_plate_normal(shape: tuple[int, int], periodic_u: bool,
                       poles: bool = False) -> tuple[sp.csc_matrix, float]:
    """``(L T)^T (L T)`` and its trace, the same for every solve on one control grid."""
    LT = second_differences(shape) @ seam_closure(shape, periodic_u, poles)
    LtL = (LT.T @ LT).tocsc()
    return LtL, float(LtL.diagonal().sum())


def _regularised_solve(A: sp.csr_matrix, targets: np.ndarray, periodic_u: bool,
                       smoothing: float, shape: tuple[int, int],
                       poles: bool = False) -> np.ndarray:
    """``Q = T q`` minimising ``||A T q - targets||^2 + lam ||L T q||^2`` (normal equations;
    ``lam = smoothing * tr(AtA) / tr(LtL)`` so the option is scale-free).

    Without a seam the normal matrix is banded (about ``2 n_v + 2`` wide) and
    symmetric positive definite once data or smoothing pin every control point:
    banded Cholesky, with a sparse LU for the singular case (control points no
    datum reaches and no smoothing ties) and for the seam's wrap-around coupling.
    """
    tied = periodic_u or poles
    T = seam_closure(shape, periodic_u, poles) if tied else None
    AT = (A @ T).tocsr() if tied else A
    AtA = (AT.T @ AT).tocsc()
    rhs = AT.T @ targets
    if smoothing > 0:
        LtL, trace = _thin_plate_normal(shape, periodic_u, poles)
        AtA = AtA + (smoothing * AtA.diagonal().sum() / max(trace, 1e-300)) * LtL
    q = None
    if not tied:
        try:
            q = _solve_banded_spd(AtA, np.zeros(AtA.shape[0]), rhs)
        except np.linalg.LinAlgError:
            q = None
    if q is None:
        q = spsolve(AtA.tocsc(), rhs)
    q = np.asarray(q).reshape(AtA.shape[0], -1)
    return np.asarray(T @ q) if tied else q


def fit_section_matrix(model: PatchModel, u: np.ndarray, v: np.ndarray, points: np.ndarray,
                       valid: np.ndarray, periodic_u: bool = False,
                       smoothing: float = DEFAULT_SMOOTHING, poles: bool = False) -> PatchModel:
    """Linear least-squares B-spline fit (weights 1) to a section matrix.

    ``points (m0 + 1, m1 + 1, 3)`` at the node parameters ``u (m0 + 1,)`` and
    ``v (m1 + 1,)``; only ``valid`` nodes count. The separable solve is used
    when every node is valid and ``smoothing`` is 0.
    """
    out = model.copy()
    out.W = np.ones(model.shape)
    shape = model.shape
    if valid.all() and smoothing == 0 and not poles:
        Bu = _direction_matrix(model, u, axis=0)
        Bv = _direction_matrix(model, v, axis=1)
        Tu = seam_closure_u(shape[0]).toarray() if periodic_u else np.eye(shape[0])
        left = Tu @ np.linalg.pinv(Bu @ Tu)
        right = np.linalg.pinv(Bv)
        out.Q = np.einsum("ai,ijc,bj->abc", left, points, right)
        return out
    UU, VV = np.meshgrid(u, v, indexing="ij")
    keep = valid.ravel()
    rows = model.basis_rows(UU.ravel()[keep], VV.ravel()[keep])
    A = rows.matrix(model.n_ctrl)
    Q = _regularised_solve(A, points.reshape(-1, 3)[keep], periodic_u, smoothing, shape,
                           poles)
    out.Q = Q.reshape(shape[0], shape[1], 3)
    return out


def _direction_matrix(model: PatchModel, t: np.ndarray, axis: int) -> np.ndarray:
    """Dense ``B (m, n)`` with ``B_ka = N_a(t_k)`` in direction ``axis`` (0: u, 1: v)."""
    degree, knots, n = model.degree[axis], model.knots[axis], model.shape[axis]
    spans, values, _ = basis_arrays(degree, knots, n, t)
    B = np.zeros((len(t), n))
    B[np.arange(len(t))[:, None], spans[:, None] - degree + np.arange(degree + 1)] = values
    return B


def fit_points_linear(model: PatchModel, u: np.ndarray, v: np.ndarray, points: np.ndarray,
                      periodic_u: bool = False, smoothing: float = DEFAULT_SMOOTHING,
                      rows: BasisRows | None = None, poles: bool = False) -> PatchModel:
    """Control points for scattered ``points (m, 3)`` at ``(u, v)``, weights held fixed.

    With ``W`` fixed the NURBS is linear in ``Q`` through the rational basis
    ``R_l = w_l N_l / sum_j w_j N_j``, so this is one sparse least-squares solve.
    ``rows`` may pass ``model.basis_rows(u, v)`` when it is already at hand;
    ``periodic_u`` and ``poles`` tie control points as :func:`seam_closure` says.
    """
    rows = model.basis_rows(u, v) if rows is None else rows
    w = model.W.ravel()[rows.index]
    rational = rows.value * w / np.einsum("mk,mk->m", rows.value, w)[:, None]
    A = BasisRows(rows.index, rational, rows.du, rows.dv).matrix(model.n_ctrl)
    Q = _regularised_solve(A, points, periodic_u, smoothing, model.shape, poles)
    out = model.copy()
    out.Q = Q.reshape(model.Q.shape)
    return out


# ------------------------------------------------------------------ nonlinear refinement
def refine_nurbs(model: PatchModel, u: np.ndarray, v: np.ndarray, points: np.ndarray,
                 iterations: int = 8, smoothing: float = DEFAULT_SMOOTHING,
                 weight_prior: float = 1e-3, periodic_u: bool = False
                 ) -> tuple[PatchModel, list[float]]:
    """Minimise the paper's ``E(Q, W)`` (eq. 5) with the parameters ``(u, v)`` fixed.

    Block-coordinate descent: each iteration solves exactly for ``Q`` with
    ``W`` fixed (the NURBS is linear in ``Q`` through the rational basis, see
    :func:`fit_points_linear`), then takes one Levenberg-Marquardt step in
    ``omega = log W`` with ``Q`` fixed (``W = exp(omega)`` stays positive). Both
    systems are banded (about ``2 n_v + 2`` wide), so an iteration costs two
    small banded Cholesky solves instead of one factorisation of the coupled
    ``4 n_u n_v`` system. ``weight_prior`` pulls ``omega`` weakly towards 0 so
    weights without data support stay at 1. Returns the model and the history
    of ``E`` (initial value first; the thin-plate and prior terms included).
    """
    n, shape = model.n_ctrl, model.shape
    rows = model.basis_rows(u, v)
    m, k = rows.value.shape
    row_ids = np.repeat(np.arange(m), k)
    scale = float(np.sum(rows.value**2)) / n  # typical diagonal of A^T A
    current = fit_points_linear(model, u, v, points, periodic_u, smoothing, rows)

    def evaluate(cand: PatchModel):
        w = cand.W.ravel()[rows.index]
        R = rows.value * w / np.einsum("mk,mk->m", rows.value, w)[:, None]
        Ql = cand.Q.reshape(-1, 3)[rows.index]
        C = np.einsum("mk,mkc->mc", R, Ql)
        res = C - points
        omega = np.log(cand.W.ravel())
        E = 0.5 * float(np.sum(res * res)) + 0.5 * weight_prior * scale * float(omega @ omega)
        return R, Ql, C, res, E

    R, Ql, C, res, E = evaluate(current)
    history = [E]
    mu = 1e-2
    for _ in range(iterations):
        # omega step: dC/d omega_l = R_l (Q_l - C), one (m, n) block per coordinate
        blocks = [sp.csr_matrix(((R * (Ql[:, :, c] - C[:, c:c + 1])).ravel(),
                                 (row_ids, rows.index.ravel())), shape=(m, n))
                  for c in range(3)]
        H = sum(J.T @ J for J in blocks) + weight_prior * scale * sp.identity(n)
        omega = np.log(current.W.ravel())
        grad = sum(blocks[c].T @ res[:, c] for c in range(3)) + weight_prior * scale * omega
        H = H.tocsr()
        diag = H.diagonal()
        accepted = False
        for _try in range(5):
            step = _solve_banded_spd(H, mu * diag + 1e-12 * diag.max(), -grad)
            cand = current.copy()
            cand.W = np.exp(np.clip(omega + step, -4.0, 4.0)).reshape(shape)
            cand = fit_points_linear(cand, u, v, points, periodic_u, smoothing, rows)
            R_c, Ql_c, C_c, res_c, E_c = evaluate(cand)
            if E_c < E:
                current, R, Ql, C, res, E = cand, R_c, Ql_c, C_c, res_c, E_c
                mu = max(mu / 3.0, 1e-7)
                accepted = True
                break
            mu *= 10.0
        if not accepted:
            break
        history.append(E)
        if history[-2] - history[-1] < 1e-5 * history[-2]:
            break
    return current, history


def _solve_banded_spd(H: sp.csr_matrix, damping: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve ``(H + diag(damping)) x = rhs`` for a symmetric positive definite banded ``H``
    by banded Cholesky (LAPACK ``pbtrf`` through ``solveh_banded``): the control net's
    locality keeps the band at about ``(2 n_v + 2)`` unknowns per coordinate."""
    coo = H.tocoo()
    coo.sum_duplicates()
    upper = coo.col >= coo.row
    rows, cols, vals = coo.row[upper], coo.col[upper], coo.data[upper]
    band = int((cols - rows).max()) if len(rows) else 0
    ab = np.zeros((band + 1, H.shape[0]))
    ab[band + rows - cols, cols] = vals
    ab[band] += damping
    return solveh_banded(ab, rhs, check_finite=False)


# ------------------------------------------------------------------ parameter correction
def project_points(model: PatchModel, points: np.ndarray, u: np.ndarray, v: np.ndarray,
                   periodic_u: bool = False, iterations: int = 4, tol: float = 1e-4
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Foot points ``(u, v)`` of ``points`` on ``model`` from the given start (see
    :func:`foot_points`, which also returns the surface and its tangents there)."""
    return foot_points(model, points, u, v, periodic_u, iterations, tol)[:2]


def foot_points(model: PatchModel, points: np.ndarray, u: np.ndarray, v: np.ndarray,
                periodic_u: bool = False, iterations: int = 4, tol: float = 1e-4,
                start: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
                ) -> tuple[np.ndarray, ...]:
    """Foot points: ``(u, v)`` minimising ``||S(u, v) - points||`` from the given start,
    with ``S, S_u, S_v`` there (each ``(m, 3)``). ``start`` may pass ``S, S_u, S_v`` at
    the starting parameters when the caller has them.

    Gauss-Newton steps ``[S_u S_v]^+ (P - S)`` clamped to the domain, each halved until the
    distance does not grow, until the residual is within ``tol`` radians of the normal
    (:func:`fitter.fitting.closest.gauss_newton`, on the patch's piecewise power form).
    """
    surface = SpanPolynomials(model)
    if start is not None:
        start = tuple(np.ascontiguousarray(np.asarray(x, dtype=float).T) for x in start)
    u, v, S, Su, Sv, _ = gauss_newton(
        surface, np.ascontiguousarray(np.asarray(points, dtype=float).T),
        np.array(u, dtype=float), np.array(v, dtype=float), periodic_u, start, iterations, tol)
    return u, v, np.ascontiguousarray(S.T), np.ascontiguousarray(Su.T), np.ascontiguousarray(Sv.T)
