"""``NurbsSurface``: a tensor-product NURBS patch — evaluate points, derivatives, normals.

The surface (the paper's eq. 1, The NURBS Book eq. 4.15) is

    S(u, v) = sum_i sum_j N_{i,p}(u) N_{j,q}(v) w_ij P_ij
              / sum_i sum_j N_{i,p}(u) N_{j,q}(v) w_ij

with ``P`` of shape ``(n_u, n_v, 3)``, weights ``w`` of shape ``(n_u, n_v)``,
clamped knot vectors ``U`` (``n_u + p + 1`` knots) and ``V`` (``n_v + q + 1``).
The class holds validated data and delegates the mathematics to ``basis``;
grid evaluation for tessellation lives in the kernel modules.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from .basis import basis_derivatives, find_span, validate_knots
from .trim import TrimMask

Vec3 = tuple[float, float, float]

_MAX_CONTROL_POINTS = 1 << 24  # 16.7 M: far above any patch, guards absurd input


def _as_list(value: object) -> object:
    """numpy arrays (or anything with ``tolist``) become nested lists; no numpy import."""
    return value.tolist() if hasattr(value, "tolist") else value


class NurbsSurface:
    """A NURBS surface of degree ``(p, q)`` with clamped knot vectors.

    Parameters
    ----------
    degree : (int, int)
        Degrees ``(p, q)`` in ``u`` and ``v``, each ``>= 1``.
    knots : (sequence of float, sequence of float)
        Clamped, non-decreasing knot vectors ``U`` and ``V`` with
        ``n_u + p + 1`` and ``n_v + q + 1`` knots.
    control_points : nested sequence or array, shape ``(n_u, n_v, 3)``
        Control points ``P_ij`` (Cartesian, not pre-multiplied by weights).
    weights : nested sequence or array, shape ``(n_u, n_v)``, optional
        Weights ``w_ij > 0``; ``None`` means all 1 (a non-rational B-spline).
    trim : TrimMask, optional
        Covered part of the parameter domain.
    metadata : dict, optional
        JSON-serialisable data carried by the patch file (units, transform, ...).

    Raises
    ------
    ValueError
        Naming the argument, what was found and what is accepted.
    """

    def __init__(
        self,
        degree: tuple[int, int],
        knots: tuple[Sequence[float], Sequence[float]],
        control_points: object,
        weights: object = None,
        trim: TrimMask | None = None,
        metadata: dict | None = None,
    ) -> None:
        try:
            p, q = degree
        except (TypeError, ValueError):
            raise ValueError(f"degree must be a pair (p, q), got {degree!r}") from None
        try:
            knots_u, knots_v = knots
        except (TypeError, ValueError):
            raise ValueError("knots must be a pair (U, V) of knot vectors") from None
        rows = _as_list(control_points)
        if not isinstance(rows, Sequence) or not rows or not isinstance(rows[0], Sequence):
            raise ValueError("control_points must be a non-empty (n_u, n_v, 3) nested sequence")
        n_u, n_v = len(rows), len(rows[0])
        if n_u * n_v > _MAX_CONTROL_POINTS:
            raise ValueError(f"control_points has {n_u}x{n_v} points; at most 2^24 are accepted")
        points: list[float] = []
        for i, row in enumerate(rows):
            if len(row) != n_v:
                raise ValueError(
                    f"control_points row {i} has {len(row)} points, row 0 has {n_v}; "
                    "the grid must be rectangular"
                )
            for j, pt in enumerate(row):
                if len(pt) != 3:
                    raise ValueError(
                        f"control_points[{i}][{j}] has {len(pt)} coordinates; 3 are needed"
                    )
                x, y, z = float(pt[0]), float(pt[1]), float(pt[2])
                if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
                    raise ValueError(f"control_points[{i}][{j}] = {(x, y, z)} is not finite")
                points += (x, y, z)
        flat_w: list[float] | None = None
        if weights is not None:
            wrows = _as_list(weights)
            if len(wrows) != n_u or any(len(r) != n_v for r in wrows):
                raise ValueError(f"weights must have shape ({n_u}, {n_v}) like control_points")
            flat_w = [float(w) for r in wrows for w in r]
            for k, w in enumerate(flat_w):
                if not (math.isfinite(w) and w > 0.0):
                    raise ValueError(
                        f"weights[{k // n_v}][{k % n_v}] = {w}; weights must be finite and > 0"
                    )
            if all(w == 1.0 for w in flat_w):
                flat_w = None
        if trim is not None and not isinstance(trim, TrimMask):
            raise ValueError(f"trim must be a TrimMask or None, got {type(trim).__name__}")
        self.degree = (p, q)
        self.knots = (
            validate_knots("knots[0] (U)", p, knots_u, n_u),
            validate_knots("knots[1] (V)", q, knots_v, n_v),
        )
        self.shape = (n_u, n_v)
        self._points = points
        self._weights = flat_w
        self.trim = trim
        self.metadata = dict(metadata) if metadata else {}

    # ----------------------------------------------------------------- data views
    @property
    def is_rational(self) -> bool:
        """False when every weight is 1 (then the surface is a plain B-spline)."""
        return self._weights is not None

    @property
    def domain(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """``((u_p, u_{n_u}), (v_q, v_{n_v}))``: the closed parameter rectangle."""
        (U, V), (p, q) = self.knots, self.degree
        return (U[p], U[-p - 1]), (V[q], V[-q - 1])

    @property
    def control_points(self) -> list[list[list[float]]]:
        """Control points as nested lists, shape ``(n_u, n_v, 3)``."""
        n_u, n_v = self.shape
        pts = self._points
        return [
            [pts[3 * (i * n_v + j) : 3 * (i * n_v + j) + 3] for j in range(n_v)]
            for i in range(n_u)
        ]

    @property
    def weights(self) -> list[list[float]]:
        """Weights as nested lists, shape ``(n_u, n_v)`` (all 1 when non-rational)."""
        n_u, n_v = self.shape
        flat = self._weights or [1.0] * (n_u * n_v)
        return [flat[i * n_v : (i + 1) * n_v] for i in range(n_u)]

    @property
    def flat_points(self) -> list[float]:
        """Control points flattened row-major, ``x, y, z`` per point (read-only use)."""
        return self._points

    @property
    def flat_weights(self) -> list[float] | None:
        """Weights flattened row-major, or ``None`` when all are 1 (read-only use)."""
        return self._weights

    def bounding_box(self) -> tuple[Vec3, Vec3]:
        """Axis-aligned box of the control points (it contains the surface)."""
        pts = self._points
        lo = (min(pts[0::3]), min(pts[1::3]), min(pts[2::3]))
        hi = (max(pts[0::3]), max(pts[1::3]), max(pts[2::3]))
        return lo, hi

    def transformed(self, matrix: Sequence[Sequence[float]]) -> NurbsSurface:
        """The surface under an affine map ``x -> A x + b`` (``matrix``: 3x4 or 4x4 rows).

        NURBS are affinely invariant (The NURBS Book, sec. 4.4): transforming
        the control points transforms the surface.
        """
        m = _as_list(matrix)
        if len(m) not in (3, 4) or any(len(r) != 4 for r in m[:3]):
            raise ValueError("matrix must be 3x4 or 4x4 (rows of [a, b, c, t])")
        if len(m) == 4 and list(map(float, m[3])) != [0.0, 0.0, 0.0, 1.0]:
            raise ValueError(f"matrix must be affine (last row 0, 0, 0, 1), got {m[3]}")
        (a, b, c, d), (e, f, g, h), (i, j, k, l_) = ([float(x) for x in r] for r in m[:3])
        pts = self._points
        moved: list[float] = []
        for n in range(0, len(pts), 3):
            x, y, z = pts[n], pts[n + 1], pts[n + 2]
            moved += (a * x + b * y + c * z + d, e * x + f * y + g * z + h,
                      i * x + j * y + k * z + l_)
        n_u, n_v = self.shape
        out = NurbsSurface.__new__(NurbsSurface)
        out.degree, out.knots, out.shape = self.degree, self.knots, (n_u, n_v)
        out._points, out._weights = moved, self._weights
        out.trim, out.metadata = self.trim, dict(self.metadata)
        return out

    def to_scan_frame(self) -> NurbsSurface:
        """The surface in the scan's coordinates: ``metadata['transform']`` applied.

        The fitter works in a centred, PCA-aligned frame (tight quantisation
        boxes) and stores the affine map back to the scan as a 4x4 row-major
        ``transform``; a patch without one is already in scan coordinates.
        """
        matrix = self.metadata.get("transform")
        return self if matrix is None else self.transformed(matrix)

    # ----------------------------------------------------------------- evaluation
    def _check_parameter(self, name: str, t: float, lo: float, hi: float) -> float:
        t = float(t)
        if not math.isfinite(t):
            raise ValueError(f"parameter {name} = {t} is not finite")
        slack = 1e-12 * max(1.0, abs(lo), abs(hi))
        if t < lo - slack or t > hi + slack:
            raise ValueError(f"parameter {name} = {t!r} is outside the domain [{lo}, {hi}]")
        return min(max(t, lo), hi)

    def _homogeneous_derivatives(
        self, u: float, v: float, order: int
    ) -> list[list[list[float]]]:
        """``A[k][l] = d^(k+l) S^w / du^k dv^l`` for ``k + l <= order`` (A3.6 on homogeneous
        points ``(w x, w y, w z, w)``)."""
        (du, dv), (p, q), (n_u, n_v) = self.domain, self.degree, self.shape
        U, V = self.knots
        u = self._check_parameter("u", u, *du)
        v = self._check_parameter("v", v, *dv)
        su, sv = find_span(p, U, n_u, u), find_span(q, V, n_v, v)
        Nu = basis_derivatives(p, U, su, u, order)
        Nv = basis_derivatives(q, V, sv, v, order)
        pts, wts = self._points, self._weights
        out = [[[0.0] * 4 for _ in range(order + 1)] for _ in range(order + 1)]
        for a in range(p + 1):
            row = (su - p + a) * n_v
            for b in range(q + 1):
                idx = row + sv - q + b
                w = wts[idx] if wts is not None else 1.0
                hx, hy, hz = w * pts[3 * idx], w * pts[3 * idx + 1], w * pts[3 * idx + 2]
                for k in range(order + 1):
                    for l_ in range(order + 1 - k):
                        c = Nu[k][a] * Nv[l_][b]
                        acc = out[k][l_]
                        acc[0] += c * hx
                        acc[1] += c * hy
                        acc[2] += c * hz
                        acc[3] += c * w
        return out

    def evaluate(self, u: float, v: float) -> Vec3:
        """The point ``S(u, v)`` (A4.3)."""
        x, y, z, w = self._homogeneous_derivatives(u, v, 0)[0][0]
        return (x / w, y / w, z / w)

    def derivatives(self, u: float, v: float) -> tuple[Vec3, Vec3, Vec3]:
        """``S(u, v)``, ``dS/du`` and ``dS/dv`` (rational derivatives, A4.4).

        With ``A`` the homogeneous numerator and ``w`` the denominator,
        ``S = A / w`` and ``S_u = (A_u - w_u S) / w``, ``S_v = (A_v - w_v S) / w``.
        """
        d = self._homogeneous_derivatives(u, v, 1)
        ax, ay, az, w = d[0][0]
        s = (ax / w, ay / w, az / w)
        ux, uy, uz, wu = d[1][0]
        vx, vy, vz, wv = d[0][1]
        s_u = ((ux - wu * s[0]) / w, (uy - wu * s[1]) / w, (uz - wu * s[2]) / w)
        s_v = ((vx - wv * s[0]) / w, (vy - wv * s[1]) / w, (vz - wv * s[2]) / w)
        return s, s_u, s_v

    def normal(self, u: float, v: float) -> Vec3:
        """Unit normal ``(S_u x S_v) / |S_u x S_v|``.

        Where the cross product vanishes, ``|S_u x S_v| <= normal_tolerance(self)``
        (a pole or collapsed edge, where a whole row of control points
        coincides), the normal is the limit taken from inside the domain along
        the line to the domain centre ``c``: with ``n(h)`` the normal at
        ``(u, v) + h (c - (u, v))``, the smallest ``h = 10^-9 8^k`` at which it
        exists, extrapolated to ``h = 0`` as ``2 n(h) - n(2h)`` (Richardson),
        which removes the error linear in ``h``.
        """
        tol = self.__dict__.get("_normal_tolerance")
        if tol is None:  # computed once per surface: a pole row asks for many normals
            tol = self._normal_tolerance = normal_tolerance(self)
        n = unit_normal(*self.derivatives(u, v)[1:], tol)
        if n is not None:
            return n
        (u0, u1), (v0, v1) = self.domain
        u, v = float(u), float(v)
        du, dv = 0.5 * (u0 + u1) - u, 0.5 * (v0 + v1) - v
        step = 1e-9
        while step < 0.25:
            n = unit_normal(*self.derivatives(u + du * step, v + dv * step)[1:], tol)
            if n is not None:
                far = unit_normal(*self.derivatives(u + du * 2 * step, v + dv * 2 * step)[1:])
                if far is None:
                    return n
                limit = [2.0 * a - b for a, b in zip(n, far, strict=True)]
                length = math.sqrt(sum(c * c for c in limit))
                return (limit[0] / length, limit[1] / length, limit[2] / length)
            step *= 8.0
        raise ValueError(f"the surface is degenerate around ({u}, {v}): no normal exists")

    def __repr__(self) -> str:
        kind = "rational" if self.is_rational else "non-rational"
        return (
            f"NurbsSurface(degree={self.degree}, shape={self.shape}, {kind}, "
            f"trim={self.trim!r})"
        )


# A normal is degenerate where |S_u x S_v| <= NORMAL_TOLERANCE * L_u * L_v (see normal_tolerance).
NORMAL_TOLERANCE = 1e-12


def normal_tolerance(surface: NurbsSurface) -> float:
    """``|S_u x S_v|`` at or below which ``surface`` has no usable normal.

    ``NORMAL_TOLERANCE * L_u * L_v`` with ``L_u = d / (u_b - u_a)``,
    ``L_v = d / (v_b - v_a)`` and ``d`` the diagonal of the control points'
    bounding box plus their largest coordinate magnitude: the size of
    ``S_u x S_v`` on a patch of that extent, so the test does not depend on
    scale or parametrisation, and an upper bound of the rounding noise in
    ``S_u, S_v``, which grows with the coordinates' magnitude. An absolute
    scale (not the angle between ``S_u`` and ``S_v``) is what detects a pole
    of a *rational* patch: there the computed ``S_v`` is not zero but rounding
    noise of any direction, and its angle to ``S_u`` says nothing.
    """
    lo, hi = surface.bounding_box()
    diagonal = math.sqrt(sum((b - a) ** 2 for a, b in zip(lo, hi, strict=True)))
    d = diagonal + max(abs(c) for c in lo + hi)
    (u0, u1), (v0, v1) = surface.domain
    return NORMAL_TOLERANCE * d * d / ((u1 - u0) * (v1 - v0))


def unit_normal(s_u: Sequence[float], s_v: Sequence[float], tol: float = 0.0) -> Vec3 | None:
    """Normalised ``s_u x s_v``, or ``None`` when ``|s_u x s_v| <= tol``."""
    nx = s_u[1] * s_v[2] - s_u[2] * s_v[1]
    ny = s_u[2] * s_v[0] - s_u[0] * s_v[2]
    nz = s_u[0] * s_v[1] - s_u[1] * s_v[0]
    length = math.sqrt(nx * nx + ny * ny + nz * nz)
    if not length > tol:
        return None
    return (nx / length, ny / length, nz / length)
