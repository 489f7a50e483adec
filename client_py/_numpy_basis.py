"""Vectorised B-spline basis over arrays of parameters (numpy): spans, values, first derivatives.

The array form of ``client_py.basis``: span search (The NURBS Book A2.1, as a
``searchsorted``), the non-zero basis functions (A2.2, the triangular scheme
run over all parameters at once) and their first derivatives from the
degree ``p - 1`` functions of the same scheme (eq. 2.7):

    N'_{i,p}(t) = p N_{i,p-1}(t) / (u_{i+p} - u_i) - p N_{i+1,p-1}(t) / (u_{i+p+1} - u_{i+1}).

Used by the numpy kernel and by the fitter's least-squares design matrices;
imported only where numpy is available.
"""

from __future__ import annotations

import numpy as np


def find_spans(degree: int, knots: np.ndarray, n_ctrl: int, t: np.ndarray) -> np.ndarray:
    """Span index ``i`` with ``u_i <= t < u_{i+1}`` for each ``t`` (A2.1); ``t = u_n`` maps
    to the last non-empty span ``n - 1``. Shape of ``t``, integer."""
    spans = np.searchsorted(knots, t, side="right") - 1
    return np.clip(spans, degree, n_ctrl - 1)


def basis_arrays(
    degree: int, knots, n_ctrl: int, t
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Spans ``(m,)``, basis values ``(m, p + 1)`` and first derivatives ``(m, p + 1)``.

    ``values[k, r] = N_{spans[k] - p + r, p}(t_k)``, likewise ``derivs``.
    """
    knots = np.asarray(knots, dtype=float)
    t = np.asarray(t, dtype=float).ravel()
    p = degree
    spans = find_spans(p, knots, n_ctrl, t)
    m = t.shape[0]
    left = np.empty((p + 1, m))
    right = np.empty((p + 1, m))
    values = np.ones((1, m))
    lower = values
    for j in range(1, p + 1):
        left[j] = t - knots[spans + 1 - j]
        right[j] = knots[spans + j] - t
        lower = values
        values = np.empty((j + 1, m))
        saved = np.zeros(m)
        for r in range(j):
            temp = lower[r] / (right[r + 1] + left[j - r])
            values[r] = saved + right[r + 1] * temp
            saved = left[j - r] * temp
        values[j] = saved
    derivs = np.zeros((p + 1, m))
    for r in range(p + 1):
        i = spans - p + r
        if r >= 1:
            span_len = knots[i + p] - knots[i]
            derivs[r] += p * lower[r - 1] / np.where(span_len > 0, span_len, 1.0)
        if r <= p - 1:
            span_len = knots[i + p + 1] - knots[i + 1]
            derivs[r] -= p * lower[r] / np.where(span_len > 0, span_len, 1.0)
    return spans, values.T.copy(), derivs.T.copy()
