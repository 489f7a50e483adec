"""The fitter's working form of a NURBS patch: numpy arrays, design matrices, batch evaluation.

``PatchModel`` holds ``Q`` ``(n_u, n_v, 3)`` and ``W`` ``(n_u, n_v)`` as arrays so the
least-squares stages can update them; it converts to and from
``client_py.NurbsSurface`` (the one evaluator and format). At scattered
parameters ``(u_k, v_k)`` a point depends on ``(p + 1)(q + 1)`` control points;
``basis_rows`` returns their flat indices and the tensor-product basis values
``N_a(u_k) N_b(v_k)`` (and their ``u``/``v`` derivatives) as dense blocks, the rows
of the sparse collocation matrix ``A`` with ``S^w = A P^w``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from client_py import NurbsSurface, TrimMask, uniform_clamped_knots
from client_py._numpy_basis import basis_arrays

CHUNK = 1 << 19  # points per batch when evaluating millions of parameters


@dataclass
class BasisRows:
    """Non-zero collocation entries for ``m`` parameter pairs.

    ``index (m, k)`` flat control-point indices ``a n_v + b``; ``value``, ``du``,
    ``dv`` ``(m, k)`` the products ``N_a N_b``, ``N'_a N_b``, ``N_a N'_b``,
    ``k = (p + 1)(q + 1)``.
    """

    index: np.ndarray
    value: np.ndarray
    du: np.ndarray | None
    dv: np.ndarray | None

    def matrix(self, n_ctrl: int, which: str = "value") -> sp.csr_matrix:
        """The sparse ``(m, n_u n_v)`` matrix of ``value``, ``du`` or ``dv``."""
        data = getattr(self, which)
        m, k = data.shape
        return sp.csr_matrix(
            (data.ravel(), self.index.ravel(), np.arange(0, m * k + 1, k)), shape=(m, n_ctrl)
        )


@dataclass
class PatchModel:
    """A NURBS patch as arrays: degrees ``(p, q)``, knots, ``Q (n_u, n_v, 3)``, ``W (n_u, n_v)``."""

    degree: tuple[int, int]
    knots: tuple[np.ndarray, np.ndarray]
    Q: np.ndarray
    W: np.ndarray

    @classmethod
    def uniform(cls, shape: tuple[int, int], degree: tuple[int, int]) -> PatchModel:
        """Zero control points, unit weights, uniform clamped knots on ``[0, 1]`` (eq. 3)."""
        n_u, n_v = shape
        knots = (np.array(uniform_clamped_knots(n_u, degree[0])),
                 np.array(uniform_clamped_knots(n_v, degree[1])))
        return cls(degree, knots, np.zeros((n_u, n_v, 3)), np.ones((n_u, n_v)))

    @classmethod
    def from_surface(cls, surface: NurbsSurface) -> PatchModel:
        n_u, n_v = surface.shape
        Q = np.asarray(surface.flat_points, dtype=float).reshape(n_u, n_v, 3)
        W = (np.ones((n_u, n_v)) if surface.flat_weights is None
             else np.asarray(surface.flat_weights, dtype=float).reshape(n_u, n_v))
        return cls(surface.degree, tuple(np.asarray(k, dtype=float) for k in surface.knots), Q, W)

    def to_surface(self, trim: TrimMask | None = None, metadata: dict | None = None
                   ) -> NurbsSurface:
        weights = None if np.all(self.W == 1.0) else self.W
        return NurbsSurface(self.degree, (self.knots[0].tolist(), self.knots[1].tolist()),
                            self.Q, weights, trim=trim, metadata=metadata)

    def copy(self) -> PatchModel:
        return PatchModel(self.degree, self.knots, self.Q.copy(), self.W.copy())

    @property
    def shape(self) -> tuple[int, int]:
        return self.Q.shape[0], self.Q.shape[1]

    @property
    def n_ctrl(self) -> int:
        return self.Q.shape[0] * self.Q.shape[1]

    def basis_rows(self, u: np.ndarray, v: np.ndarray, derivatives: bool = True) -> BasisRows:
        """Collocation entries at parameters ``u, v`` (each ``(m,)``, inside the domain);
        ``du``/``dv`` are ``None`` unless ``derivatives``."""
        (p, q), (n_u, n_v) = self.degree, self.shape
        su, Nu, dNu = basis_arrays(p, self.knots[0], n_u, u)
        sv, Nv, dNv = basis_arrays(q, self.knots[1], n_v, v)
        rows = (su[:, None] - p + np.arange(p + 1))[:, :, None] * n_v
        cols = (sv[:, None] - q + np.arange(q + 1))[:, None, :]
        m, k = len(su), (p + 1) * (q + 1)
        index = (rows + cols).reshape(m, k)
        value = (Nu[:, :, None] * Nv[:, None, :]).reshape(m, k)
        if not derivatives:
            return BasisRows(index, value, None, None)
        du = (dNu[:, :, None] * Nv[:, None, :]).reshape(m, k)
        dv = (Nu[:, :, None] * dNv[:, None, :]).reshape(m, k)
        return BasisRows(index, value, du, dv)

    def evaluate(self, u: np.ndarray, v: np.ndarray, derivatives: bool = False):
        """Points ``S (m, 3)`` and, with ``derivatives``, ``S_u, S_v (m, 3)`` (A4.4).

        Per coordinate of the homogeneous net ``(w Q, w)`` (just ``Q`` when all
        weights are 1): gather the ``(p + 1)(q + 1)`` values of each point's knot
        cell and take row dot products with the tensor basis ``N_a(u) N_b(v)``
        (and its ``u``, ``v`` derivatives) — 2-D row products, the fast kind.
        """
        u = np.asarray(u, dtype=float).ravel()
        v = np.asarray(v, dtype=float).ravel()
        if len(u) > CHUNK:
            parts = [self.evaluate(u[k:k + CHUNK], v[k:k + CHUNK], derivatives)
                     for k in range(0, len(u), CHUNK)]
            if not derivatives:
                return np.concatenate(parts)
            return tuple(np.concatenate(x) for x in zip(*parts, strict=True))
        rows = self.basis_rows(u, v, derivatives)
        rational = not np.all(self.W == 1.0)
        channels = ([*(self.Q[..., c] * self.W for c in range(3)), self.W] if rational
                    else [self.Q[..., c] for c in range(3)])
        bases = (rows.value, rows.du, rows.dv) if derivatives else (rows.value,)
        out = [np.empty((len(u), len(channels))) for _ in bases]
        for c, channel in enumerate(channels):
            values = np.take(channel.ravel(), rows.index)
            for o, basis in zip(out, bases, strict=True):
                o[:, c] = np.einsum("mk,mk->m", basis, values)
        if not rational:
            return tuple(out) if derivatives else out[0]
        C = out[0]
        w = C[:, 3:]
        S = C[:, :3] / w
        if not derivatives:
            return S
        Cu, Cv = out[1], out[2]
        return S, (Cu[:, :3] - Cu[:, 3:] * S) / w, (Cv[:, :3] - Cv[:, 3:] * S) / w
