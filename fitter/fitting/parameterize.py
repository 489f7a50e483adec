"""Projection of a scan into the rectangular parameter domain ``[0, 1]^2`` (the paper's Fig. 6).

Each map sends a point to ``(u, v, h)``: two domain coordinates and a *height*
along the direction the single patch is a graph over.

- ``plane`` — the paper's choice for a relief, a block face, a mask front: the
  PCA frame of the scan; ``u, v`` the two largest axes, ``h`` the third.
- ``cylinder`` — busts and statues that wrap around an axis: ``u`` the angle
  around it (periodic, the seam closed by the fit), ``v`` the height along it,
  ``h`` the distance from it.
- ``sphere`` — compact, star-shaped objects: ``u`` longitude, ``v`` polar angle,
  ``h`` the distance from the centre.

A single patch is a graph ``h(u, v)``, so where the scan folds over the map
(two layers at the same ``(u, v)``, e.g. the back of a mask seen from its front)
only the outer layer can be represented. :func:`coverage` finds the points on
the outer layer that face outwards; the rest are reported, never silently
dropped. ``auto`` tries every map and keeps the one that covers the most points,
preferring the plane when it is within ``PLANE_PREFERENCE`` of the best (its
parameterization has the least distortion).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

KINDS = ("plane", "cylinder", "sphere")
CHOICE_SAMPLE = 500_000  # points on which the candidate maps compete
PLANE_PREFERENCE = 0.03
FRONT_TOLERANCE_CELLS = 3.0  # outer-layer slack, in bin sizes: keeps slopes up to ~70 degrees


@dataclass
class Projection:
    """A map from scan coordinates to ``(u, v, h)``.

    Attributes
    ----------
    kind : {'plane', 'cylinder', 'sphere'}
    origin : (3,) array
        Origin of the local frame, in scan coordinates.
    axes : (3, 3) array
        Rows are the local axes in scan coordinates (orthonormal, right-handed).
        ``plane``: ``e1, e2`` span the domain, ``e3`` the height. ``cylinder``,
        ``sphere``: ``e1`` is the axis (or the pole direction).
    lo, hi : (2,) arrays
        Native range of the two domain coordinates before scaling to ``[0, 1]``
        (plane: lengths; cylinder: angle ``[-pi, pi]`` and length; sphere:
        angles ``[-pi, pi]`` and ``[0, pi]``).
    """

    kind: str
    origin: np.ndarray
    axes: np.ndarray
    lo: np.ndarray = field(default_factory=lambda: np.zeros(2))
    hi: np.ndarray = field(default_factory=lambda: np.ones(2))

    @property
    def periodic_u(self) -> bool:
        return self.kind in ("cylinder", "sphere")

    @property
    def transform(self) -> list[list[float]]:
        """4x4 row-major affine map from the local (patch) frame to scan coordinates."""
        m = np.eye(4)
        m[:3, :3] = self.axes.T
        m[:3, 3] = self.origin
        return m.tolist()

    def local(self, points: np.ndarray) -> np.ndarray:
        return (np.asarray(points, dtype=float) - self.origin) @ self.axes.T

    def native(self, points: np.ndarray, local: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unscaled domain coordinates and height of scan points (``local``: their
        :meth:`local` coordinates, when the caller has them)."""
        x = self.local(points) if local is None else local
        if self.kind == "plane":
            return x[:, 0], x[:, 1], x[:, 2]
        radial = np.hypot(x[:, 1], x[:, 2])
        angle = np.arctan2(x[:, 2], x[:, 1])
        if self.kind == "cylinder":
            return angle, x[:, 0], radial
        r = np.sqrt(radial**2 + x[:, 0] ** 2)
        return angle, np.arctan2(radial, x[:, 0]), r

    def to_uvh(self, points: np.ndarray, local: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``u, v`` in ``[0, 1]`` and height ``h`` for each point ``(N, 3)`` (``local``: their
        :meth:`local` coordinates, when the caller has them)."""
        a, b, h = self.native(points, local)
        span = np.where(self.hi > self.lo, self.hi - self.lo, 1.0)
        u = np.clip((a - self.lo[0]) / span[0], 0.0, 1.0)
        v = np.clip((b - self.lo[1]) / span[1], 0.0, 1.0)
        return u, v, h

    def from_uvh(self, u: np.ndarray, v: np.ndarray, h: np.ndarray) -> np.ndarray:
        """Local-frame points ``(N, 3)`` at domain coordinates ``u, v`` and height ``h``."""
        a = self.lo[0] + np.asarray(u) * (self.hi[0] - self.lo[0])
        b = self.lo[1] + np.asarray(v) * (self.hi[1] - self.lo[1])
        if self.kind == "plane":
            return np.column_stack([a, b, h])
        if self.kind == "cylinder":
            return np.column_stack([b, h * np.cos(a), h * np.sin(a)])
        return np.column_stack([h * np.cos(b), h * np.sin(b) * np.cos(a),
                                h * np.sin(b) * np.sin(a)])

    def outward(self, points: np.ndarray) -> np.ndarray:
        """Unit direction ``(N, 3)`` of growing height at each point, in scan coordinates."""
        x = self.local(points)
        if self.kind == "plane":
            d = np.tile([0.0, 0.0, 1.0], (len(x), 1))
        elif self.kind == "cylinder":
            d = x * [0.0, 1.0, 1.0]
        else:
            d = x.copy()
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
        return d @ self.axes

    def describe(self) -> dict:
        return {"kind": self.kind, "origin": self.origin.tolist(), "axes": self.axes.tolist()}


def principal_frame(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid and PCA axes (rows, by decreasing variance, right-handed, signs fixed so each
    axis's largest component is positive: the same scan always gives the same frame)."""
    centre = points.mean(axis=0)
    cov = np.cov((points - centre).T)
    _, vecs = np.linalg.eigh(cov)
    axes = vecs[:, ::-1].T.copy()
    for k in range(2):
        if axes[k, np.argmax(np.abs(axes[k]))] < 0:
            axes[k] = -axes[k]
    axes[2] = np.cross(axes[0], axes[1])
    return centre, axes


def _rolled(axes: np.ndarray, first: int) -> np.ndarray:
    """Right-handed frame whose first axis is ``axes[first]``."""
    order = [first, (first + 1) % 3, (first + 2) % 3]
    return axes[order]


def _flipped(axes: np.ndarray) -> np.ndarray:
    """The same plane seen from the other side: height axis reversed, still right-handed."""
    return np.array([axes[1], axes[0], -axes[2]])


def candidate_projections(points: np.ndarray) -> list[Projection]:
    """Every map ``auto`` considers: the PCA plane from both sides, cylinders about each
    PCA axis, a sphere about the centroid."""
    centre, axes = principal_frame(points)
    out = [Projection("plane", centre, axes), Projection("plane", centre, _flipped(axes))]
    out += [Projection("cylinder", centre, _rolled(axes, k)) for k in range(3)]
    out.append(Projection("sphere", centre, axes))
    for proj in out:
        _set_ranges(proj, points)
    return out


def _set_ranges(proj: Projection, points: np.ndarray) -> None:
    a, b, _ = proj.native(points)
    if proj.kind == "plane":
        proj.lo, proj.hi = np.array([a.min(), b.min()]), np.array([a.max(), b.max()])
    elif proj.kind == "cylinder":
        proj.lo, proj.hi = np.array([-np.pi, b.min()]), np.array([np.pi, b.max()])
    else:
        proj.lo, proj.hi = np.array([-np.pi, 0.0]), np.array([np.pi, np.pi])


@dataclass
class Coverage:
    """Which points a single patch over ``projection`` can represent.

    ``covered`` (N,) bool: on the outer layer and (when normals are known)
    facing outwards. ``fraction`` their share; ``mask`` the covered part of the
    domain as a ``(bins, bins)`` bool grid (row = ``u``).
    """

    projection: Projection
    covered: np.ndarray
    fraction: float
    mask: np.ndarray


def coverage(proj: Projection, points: np.ndarray, normals: np.ndarray | None = None,
             bins: int | None = None) -> Coverage:
    """Points on the outer layer of ``h(u, v)``: within ``FRONT_TOLERANCE_CELLS`` bin sizes
    below the highest point of their ``(u, v)`` bin, and facing outwards if normals exist."""
    n = len(points)
    if bins is None:
        bins = int(np.clip(np.sqrt(n / 8.0), 16, 256))
    u, v, h = proj.to_uvh(points)
    iu = np.minimum((u * bins).astype(np.int64), bins - 1)
    iv = np.minimum((v * bins).astype(np.int64), bins - 1)
    cell = iu * bins + iv
    top = np.full(bins * bins, -np.inf)
    np.maximum.at(top, cell, h)
    scale = np.median(np.abs(h)) if proj.kind != "plane" else 1.0
    extent = np.max((proj.hi - proj.lo) * np.array([scale if proj.periodic_u else 1.0,
                                                    scale if proj.kind == "sphere" else 1.0]))
    tolerance = FRONT_TOLERANCE_CELLS * extent / bins
    covered = h >= top[cell] - tolerance
    if normals is not None:
        covered &= np.einsum("ij,ij->i", normals, proj.outward(points)) > -0.1
    mask = np.zeros(bins * bins, dtype=bool)
    mask[cell[covered]] = True
    return Coverage(proj, covered, float(covered.mean()) if n else 0.0,
                    mask.reshape(bins, bins))


def choose_projection(points: np.ndarray, normals: np.ndarray | None = None,
                      kind: str = "auto") -> Coverage:
    """The projection (and its coverage) a single patch should use for ``points``.

    ``kind`` forces a family (``plane``, ``cylinder``, ``sphere``); the best
    member of that family (plane side, cylinder axis) is still chosen by coverage.
    """
    if kind not in KINDS + ("auto",):
        raise ValueError(f"projection must be one of auto, {', '.join(KINDS)}; got {kind!r}")
    # the candidates compete on an even subsample of a large scan; the winner's ranges
    # and coverage are then taken over every point
    step = max(1, len(points) // CHOICE_SAMPLE)
    probe = points[::step]
    probe_normals = None if normals is None else normals[::step]
    options = [c for c in candidate_projections(probe) if kind in ("auto", c.kind)]
    results = [coverage(c, probe, probe_normals) for c in options]
    best = max(results, key=lambda r: r.fraction)
    planes = [r for r in results if r.projection.kind == "plane"]
    if kind == "auto" and planes:
        best_plane = max(planes, key=lambda r: r.fraction)
        if best_plane.fraction >= best.fraction - PLANE_PREFERENCE:
            best = best_plane
    if step == 1:
        return best
    _set_ranges(best.projection, points)
    return coverage(best.projection, points, normals)


def trim_cells(mask: np.ndarray, periodic_u: bool) -> np.ndarray:
    """Covered domain cells with one-cell scanner gaps closed; real holes (eye holes of a
    mask, a statue's missing arm) stay open."""
    if mask.all():
        return mask
    pad = 2
    grid = np.pad(mask, ((pad, pad), (0, 0)), mode="wrap" if periodic_u else "constant")
    grid = np.pad(grid, ((0, 0), (pad, pad)))
    closed = ndimage.binary_closing(grid, structure=np.ones((3, 3), bool))
    return closed[pad:-pad, pad:-pad] | mask
