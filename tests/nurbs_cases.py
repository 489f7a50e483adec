"""Surfaces for the client_py tests, and scipy's B-splines as the independent oracle.

Random rational patches with random non-uniform clamped knots (repeated
interior knots included), exact known surfaces (bilinear patch, quarter
cylinder, sphere octant with a pole) and ``oracle``, which evaluates a
``NurbsSurface``'s point and first derivatives with ``scipy.interpolate.BSpline``
(de Boor's algorithm in compiled code, not The NURBS Book's A2.2/A2.3 that
client_py uses) on homogeneous coordinates and the quotient rule.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.interpolate import BSpline

from client_py import NurbsSurface


def random_knots(rng: np.random.Generator, n_ctrl: int, degree: int,
                 domain: tuple[float, float] = (0.0, 1.0), repeat: bool = True) -> list[float]:
    """Clamped knots with ``n_ctrl - degree - 1`` random interior knots in ``domain``.

    With ``repeat``, one interior knot (when there are any) is repeated up to
    ``degree`` times, the most a continuous surface allows.
    """
    a, b = domain
    n_inner = n_ctrl - degree - 1
    inner = sorted(rng.uniform(a, b, n_inner).tolist())
    if repeat and n_inner >= 2:
        k = int(rng.integers(0, n_inner - 1))
        mult = int(rng.integers(2, min(degree, n_inner - k) + 1)) if degree >= 2 else 1
        inner[k : k + mult] = [inner[k]] * mult
    return [a] * (degree + 1) + inner + [b] * (degree + 1)


def random_surface(rng: np.random.Generator, p: int, q: int, n_u: int | None = None,
                   n_v: int | None = None, rational: bool = True,
                   domain=((0.0, 1.0), (0.0, 1.0))) -> NurbsSurface:
    """A random rational patch: control points in ``[-1, 1]^3``, weights in ``[0.3, 3]``."""
    n_u = n_u or p + 1 + int(rng.integers(0, 6))
    n_v = n_v or q + 1 + int(rng.integers(0, 6))
    U = random_knots(rng, n_u, p, domain[0])
    V = random_knots(rng, n_v, q, domain[1])
    P = rng.uniform(-1.0, 1.0, (n_u, n_v, 3))
    W = np.exp(rng.uniform(math.log(0.3), math.log(3.0), (n_u, n_v))) if rational else None
    return NurbsSurface((p, q), (U, V), P, W)


def _basis(knots, degree: int, n_ctrl: int, t: np.ndarray, nu: int) -> np.ndarray:
    """``(m, n_ctrl)`` matrix of ``d^nu N_a(t) / dt^nu`` from scipy's BSpline."""
    spline = BSpline(np.asarray(knots, dtype=float), np.eye(n_ctrl), degree, extrapolate=False)
    return spline(np.asarray(t, dtype=float), nu=nu)  # t = last knot: scipy's last span


def oracle(surface: NurbsSurface, us, vs):
    """``S, S_u, S_v`` of ``surface`` at the points ``(us[k], vs[k])``: ``(m, 3)`` each.

    Homogeneous ``A = sum N_a(u) N_b(v) w_ab P_ab`` and ``w`` from scipy's basis,
    then ``S = A / w`` and ``S_u = (A_u - w_u S) / w`` (The NURBS Book eq. 4.7).
    """
    (p, q), (n_u, n_v) = surface.degree, surface.shape
    U, V = surface.knots
    P = np.asarray(surface.control_points, dtype=float)
    W = np.asarray(surface.weights, dtype=float)
    Pw = np.concatenate([P * W[..., None], W[..., None]], axis=2)  # (n_u, n_v, 4)
    Bu, dBu = (_basis(U, p, n_u, us, k) for k in (0, 1))
    Bv, dBv = (_basis(V, q, n_v, vs, k) for k in (0, 1))
    A = np.einsum("ka,kb,abc->kc", Bu, Bv, Pw)
    Au = np.einsum("ka,kb,abc->kc", dBu, Bv, Pw)
    Av = np.einsum("ka,kb,abc->kc", Bu, dBv, Pw)
    w, wu, wv = A[:, 3:], Au[:, 3:], Av[:, 3:]
    S = A[:, :3] / w
    return S, (Au[:, :3] - wu * S) / w, (Av[:, :3] - wv * S) / w


def oracle_normals(surface: NurbsSurface, us, vs) -> np.ndarray:
    """Unit ``S_u x S_v`` from :func:`oracle`, ``(m, 3)``."""
    _, su, sv = oracle(surface, us, vs)
    n = np.cross(su, sv)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


# ------------------------------------------------------------------ exact surfaces
def bilinear(corners) -> NurbsSurface:
    """Degree (1, 1) patch with corners ``P00, P01, P10, P11``:
    ``S(u, v) = (1-u)(1-v) P00 + (1-u) v P01 + u (1-v) P10 + u v P11``."""
    p00, p01, p10, p11 = corners
    return NurbsSurface((1, 1), ([0, 0, 1, 1], [0, 0, 1, 1]), [[p00, p01], [p10, p11]])


def quarter_cylinder(radius: float, height: float) -> NurbsSurface:
    """Rational quadratic arc (weights ``1, sqrt(2)/2, 1``) from ``(R, 0)`` to ``(0, R)``
    in ``u``, linear in ``v`` from ``z = 0`` to ``z = height``: an exact quarter cylinder."""
    r, h, c = radius, height, math.sqrt(0.5)
    arc = [(r, 0.0), (r, r), (0.0, r)]
    P = [[[x, y, 0.0], [x, y, h]] for x, y in arc]
    W = [[1.0, 1.0], [c, c], [1.0, 1.0]]
    return NurbsSurface((2, 1), ([0, 0, 0, 1, 1, 1], [0, 0, 1, 1]), P, W)


def sphere_octant(radius: float, center=(0.0, 0.0, 0.0)) -> NurbsSurface:
    """The octant ``x, y, z >= 0`` of a sphere: a quarter meridian (u, from the equator
    to the pole ``(0, 0, R)``) revolved by 90 degrees (v). The three control points
    of the pole row coincide: a collapsed edge where ``S_v = 0``."""
    r, c = radius, math.sqrt(0.5)
    profile = [(r, 0.0, 1.0), (r, r, c), (0.0, r, 1.0)]  # (radius in xy, z, weight)
    P, W = [], []
    for rho, z, wp in profile:
        ring = [(rho, 0.0), (rho, rho), (0.0, rho)]
        P.append([[center[0] + x, center[1] + y, center[2] + z] for x, y in ring])
        W.append([wp * 1.0, wp * c, wp * 1.0])
    knots = [0, 0, 0, 1, 1, 1]
    return NurbsSurface((2, 2), (knots, knots), P, W)


def dome(rational: bool, offset=(500.0, 300.0, 1000.0), n: int = 6) -> NurbsSurface:
    """A cap with a pole at ``u = 0``: row 0 collapses to the apex and row 1 lies in the
    apex's horizontal plane, so the limit normal at the pole is exactly ``+z``.
    Far from the origin (``offset``), where rounding in ``S_v`` is largest."""
    ox, oy, oz = offset
    P = []
    for i in range(n):
        rho = i / (n - 1)
        z = 1.0 if i <= 1 else 1.0 - rho * rho
        P.append([[ox + rho * math.cos(math.pi * j / (n - 1)),
                   oy + rho * math.sin(math.pi * j / (n - 1)), oz + z] for j in range(n)])
    W = None
    if rational:
        rng = np.random.default_rng(3)
        W = rng.uniform(0.5, 1.5, (n, n))
    knots = [0.0, 0.0, 0.0] + [k / (n - 2) for k in range(1, n - 2)] + [1.0, 1.0, 1.0]
    return NurbsSurface((2, 2), (knots, knots), P, W)
