"""B-spline knot vectors, span search and basis functions.

Plain functions named after The NURBS Book (L. Piegl, W. Tiller, 2nd ed., 1997),
each citing its algorithm; argument order is always (degree, knots, ...).
Standard library only: this module runs in Pyodide.

A knot vector ``U = (u_0, ..., u_{m})`` of a degree-``p`` B-spline with ``n``
control points has ``m + 1 = n + p + 1`` knots. Tessera uses clamped vectors
only: the first and last ``p + 1`` knots are equal, so the surface interpolates
its corner control points and the parameter domain is ``[u_p, u_n]``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence


def uniform_clamped_knots(
    n_ctrl: int, degree: int, start: float = 0.0, end: float = 1.0
) -> list[float]:
    """Uniform clamped knot vector (the paper's eq. 3).

    ``U = (a,...,a, a + h, a + 2h, ..., b - h, b,...,b)`` with ``p + 1`` copies
    of each end and ``h = (b - a) / (n - p)``: ``n + p + 1`` knots in all.

    Parameters
    ----------
    n_ctrl : int
        Number of control points ``n`` in this direction, ``n >= degree + 1``.
    degree : int
        Degree ``p >= 1``.
    start, end : float
        Parameter domain ``[a, b]``.
    """
    if degree < 1:
        raise ValueError(f"degree must be >= 1, got {degree}")
    if n_ctrl < degree + 1:
        raise ValueError(
            f"n_ctrl must be >= degree + 1 = {degree + 1} for degree {degree}, got {n_ctrl}"
        )
    spans = n_ctrl - degree
    inner = [start + (end - start) * i / spans for i in range(1, spans)]
    return [float(start)] * (degree + 1) + inner + [float(end)] * (degree + 1)


def is_uniform_clamped(degree: int, knots: Sequence[float], tol: float = 1e-12) -> bool:
    """True when ``knots`` equals :func:`uniform_clamped_knots` on its own domain."""
    n_ctrl = len(knots) - degree - 1
    if n_ctrl < degree + 1:
        return False
    ref = uniform_clamped_knots(n_ctrl, degree, knots[0], knots[-1])
    scale = max(1.0, abs(knots[0]), abs(knots[-1]))
    return all(abs(a - b) <= tol * scale for a, b in zip(ref, knots, strict=True))


def validate_knots(
    name: str, degree: int, knots: Sequence[float], n_ctrl: int
) -> tuple[float, ...]:
    """Check a clamped knot vector and return it as a tuple of floats.

    Raises ``ValueError`` naming ``name`` when the count is not ``n + p + 1``, a
    knot is not finite, the knots decrease, the ends are not clamped
    (``p + 1`` equal knots) or an interior knot repeats more than ``p`` times
    (the surface would not be continuous there).
    """
    if isinstance(degree, bool) or not isinstance(degree, int) or degree < 1:
        raise ValueError(f"degree for {name} must be an integer >= 1, got {degree!r}")
    try:
        values = tuple(float(k) for k in knots)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a sequence of numbers: {exc}") from None
    expected = n_ctrl + degree + 1
    if len(values) != expected:
        raise ValueError(
            f"{name} has {len(values)} knots; {n_ctrl} control points of degree {degree} "
            f"need n + p + 1 = {expected}"
        )
    for i, k in enumerate(values):
        if not math.isfinite(k):
            raise ValueError(f"{name}[{i}] is {k}; knots must be finite")
    for i in range(1, len(values)):
        if values[i] < values[i - 1]:
            raise ValueError(
                f"{name} decreases at index {i} ({values[i - 1]} > {values[i]}); "
                "knots must be non-decreasing"
            )
    first, last = values[0], values[-1]
    if not last > first:
        raise ValueError(f"{name} spans an empty domain [{first}, {last}]")
    if values[degree] != first or values[-degree - 1] != last:
        raise ValueError(
            f"{name} is not clamped: its first and last {degree + 1} knots must be equal "
            f"(got {list(values[: degree + 1])} ... {list(values[-degree - 1 :])})"
        )
    run = 1
    for i in range(degree + 2, len(values) - degree - 1):
        run = run + 1 if values[i] == values[i - 1] else 1
        if run > degree:
            raise ValueError(
                f"{name}: interior knot {values[i]} repeats more than degree = {degree} "
                "times; the surface would break there"
            )
    return values


def find_span(degree: int, knots: Sequence[float], n_ctrl: int, t: float) -> int:
    """Knot span index ``i`` with ``u_i <= t < u_{i+1}`` (The NURBS Book A2.1).

    At the end of the domain ``t = u_n`` the last non-empty span ``n - 1`` is
    returned, so the surface is defined on the closed domain.
    """
    if t >= knots[n_ctrl]:
        return n_ctrl - 1
    if t <= knots[degree]:
        return degree
    low, high = degree, n_ctrl
    mid = (low + high) // 2
    while t < knots[mid] or t >= knots[mid + 1]:
        if t < knots[mid]:
            high = mid
        else:
            low = mid
        mid = (low + high) // 2
    return mid


def basis_functions(degree: int, knots: Sequence[float], span: int, t: float) -> list[float]:
    """Non-zero basis functions ``N_{span-p,p}(t) ... N_{span,p}(t)`` (A2.2)."""
    basis = [1.0] + [0.0] * degree
    left = [0.0] * (degree + 1)
    right = [0.0] * (degree + 1)
    for j in range(1, degree + 1):
        left[j] = t - knots[span + 1 - j]
        right[j] = knots[span + j] - t
        saved = 0.0
        for r in range(j):
            temp = basis[r] / (right[r + 1] + left[j - r])
            basis[r] = saved + right[r + 1] * temp
            saved = left[j - r] * temp
        basis[j] = saved
    return basis


def basis_derivatives(
    degree: int, knots: Sequence[float], span: int, t: float, order: int
) -> list[list[float]]:
    """Basis functions and their derivatives up to ``order`` (A2.3).

    Returns ``ders`` with ``ders[k][j] = d^k/dt^k N_{span-p+j,p}(t)`` for
    ``k = 0..order`` (derivatives above the degree are zero).
    """
    p = degree
    ndu = [[0.0] * (p + 1) for _ in range(p + 1)]
    ndu[0][0] = 1.0
    left = [0.0] * (p + 1)
    right = [0.0] * (p + 1)
    for j in range(1, p + 1):
        left[j] = t - knots[span + 1 - j]
        right[j] = knots[span + j] - t
        saved = 0.0
        for r in range(j):
            ndu[j][r] = right[r + 1] + left[j - r]  # lower triangle: knot differences
            temp = ndu[r][j - 1] / ndu[j][r]
            ndu[r][j] = saved + right[r + 1] * temp  # upper triangle: basis functions
            saved = left[j - r] * temp
        ndu[j][j] = saved
    ders = [[0.0] * (p + 1) for _ in range(order + 1)]
    for j in range(p + 1):
        ders[0][j] = ndu[j][p]
    a = [[0.0] * (p + 1) for _ in range(2)]
    for r in range(p + 1):
        s1, s2 = 0, 1
        a[0][0] = 1.0
        for k in range(1, min(order, p) + 1):
            d = 0.0
            rk, pk = r - k, p - k
            if r >= k:
                a[s2][0] = a[s1][0] / ndu[pk + 1][rk]
                d = a[s2][0] * ndu[rk][pk]
            j1 = 1 if rk >= -1 else -rk
            j2 = k - 1 if r - 1 <= pk else p - r
            for j in range(j1, j2 + 1):
                a[s2][j] = (a[s1][j] - a[s1][j - 1]) / ndu[pk + 1][rk + j]
                d += a[s2][j] * ndu[rk + j][pk]
            if r <= pk:
                a[s2][k] = -a[s1][k - 1] / ndu[pk + 1][r]
                d += a[s2][k] * ndu[r][pk]
            ders[k][r] = d
            s1, s2 = s2, s1
    factor = float(p)
    for k in range(1, min(order, p) + 1):
        for j in range(p + 1):
            ders[k][j] *= factor
        factor *= p - k
    return ders


def basis_table(
    degree: int, knots: Sequence[float], n_ctrl: int, params: Sequence[float]
) -> tuple[list[int], list[list[float]], list[list[float]]]:
    """Spans, basis values and first derivatives at many parameters.

    The separable tables a grid evaluation needs: for each ``t_k`` in
    ``params``, ``spans[k]`` (A2.1), ``values[k][j] = N_{spans[k]-p+j,p}(t_k)``
    and ``derivs[k][j] = N'_{spans[k]-p+j,p}(t_k)`` (A2.3), ``j = 0..p``.
    """
    spans, values, derivs = [], [], []
    for t in params:
        span = find_span(degree, knots, n_ctrl, t)
        ders = basis_derivatives(degree, knots, span, t, 1)
        spans.append(span)
        values.append(ders[0])
        derivs.append(ders[1])
    return spans, values, derivs
