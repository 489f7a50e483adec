"""Generated example scans: the built-in input of ``make demo`` and of the tests.

``relief_scan`` imitates a structured-light scan of a carved stone relief: a
slightly curved block face with a raised rosette, a chiselled groove and a
sharp-edged step, sampled at scattered points with sensor noise, tilted in
space like a real capture. ``vase_mesh`` is a whole object, the kind a visitor turns
around: the closed triangle mesh of a fluted vase with a band of bosses and two
incised lines, as a scan's reconstruction would give it. Both are synthetic, and
labelled so wherever they are used.
"""

from __future__ import annotations

import numpy as np


def relief_height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height (mm) of the example relief over its face ``[-100, 100] x [-70, 70]`` mm."""
    r = np.hypot(x + 30.0, y)
    theta = np.arctan2(y, x + 30.0)
    rosette = 6.0 * np.exp(-(r / 28.0) ** 4) * (1.0 + 0.35 * np.cos(8.0 * theta))
    groove = -2.5 * np.exp(-(((x - 45.0) / 2.5) ** 2)) * (np.abs(y) < 50.0)
    step = 3.0 / (1.0 + np.exp(-(y + 45.0) / 0.8))  # a sharp ledge across the face
    bulge = -4e-4 * (x**2 + 0.6 * y**2)  # the block face is slightly convex
    return rosette + groove + step + bulge


def relief_scan(n_points: int = 80_000, noise: float = 0.05, seed: int = 0) -> np.ndarray:
    """Scattered points ``(n_points, 3)`` in mm on the tilted example relief."""
    if n_points < 16:
        raise ValueError(f"n_points must be at least 16, got {n_points}")
    rng = np.random.default_rng(seed)
    x = rng.uniform(-100.0, 100.0, n_points)
    y = rng.uniform(-70.0, 70.0, n_points)
    z = relief_height(x, y) + rng.normal(0.0, noise, n_points)
    pts = np.column_stack([x, y, z])
    a, b = np.deg2rad(20.0), np.deg2rad(-35.0)  # the scanner saw the block at an angle
    rot_x = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    rot_z = np.array([[np.cos(b), -np.sin(b), 0], [np.sin(b), np.cos(b), 0], [0, 0, 1]])
    return pts @ (rot_z @ rot_x).T + np.array([250.0, -40.0, 1200.0])


#: the example vase's profile: radius (mm) at heights ``t H`` (foot, waist, belly, shoulder,
#: neck, lip), interpolated by a natural cubic spline
VASE_HEIGHT = 300.0
VASE_PROFILE = ((0.0, 62.0), (0.04, 64.0), (0.10, 46.0), (0.25, 80.0), (0.45, 108.0),
                (0.62, 96.0), (0.78, 44.0), (0.90, 42.0), (0.97, 56.0), (1.0, 54.0))


def vase_mesh(around: int = 256, rings: int = 160) -> tuple[np.ndarray, np.ndarray]:
    """The example vase: vertices ``(V, 3)`` in mm and triangles ``(T, 3)``, closed.

    A surface of revolution ``(r(t, θ) cos θ, r(t, θ) sin θ, t H)`` on ``rings`` x
    ``around`` vertices: the profile :data:`VASE_PROFILE` with 20 flutes on the belly
    (``r`` times ``1 + 0.03 cos 20θ`` inside a window about ``t = 0.4``), eight bosses 7 mm
    high on the shoulder and two incised lines 1.8 mm deep; a flat foot and a flat lid
    close it, each a fan about its centre. Genus 0, every edge shared by two triangles,
    counter-clockwise seen from outside.
    """
    if around < 8 or rings < 4:
        raise ValueError(f"the vase needs at least 8 vertices around and 4 rings, got "
                         f"{around} and {rings}")
    from scipy.interpolate import CubicSpline

    knots, radii = np.array(VASE_PROFILE).T
    t = np.linspace(0.0, 1.0, rings)[:, None]
    theta = np.linspace(0.0, 2 * np.pi, around, endpoint=False)[None, :]
    r = CubicSpline(knots, radii, bc_type="natural")(t) * (
        1.0 + 0.03 * np.cos(20 * theta) * np.exp(-((t - 0.40) / 0.12) ** 4))
    z = t * VASE_HEIGHT
    for k in range(8):  # the bosses: Gaussian bumps of 9 mm, arc length measured at 100 mm
        off = np.angle(np.exp(1j * (theta - 2 * np.pi * k / 8)))
        r = r + 7.0 * np.exp(-((off * 100.0) ** 2 + (z - 0.66 * VASE_HEIGHT) ** 2)
                             / (2 * 9.0 ** 2))
    for line in (0.18, 0.74):
        r = r - 1.8 * np.exp(-((z - line * VASE_HEIGHT) / 1.5) ** 2)
    vertices = np.column_stack([(r * np.cos(theta)).ravel(), (r * np.sin(theta)).ravel(),
                                np.broadcast_to(z, r.shape).ravel()])
    ring = np.arange(rings * around).reshape(rings, around)
    a, b = ring[:-1], np.roll(ring[:-1], -1, axis=1)
    c, d = ring[1:], np.roll(ring[1:], -1, axis=1)
    foot, lid = len(vertices), len(vertices) + 1
    faces = np.concatenate([
        np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3),
        np.stack([np.full(around, foot), np.roll(ring[0], -1), ring[0]], -1),
        np.stack([np.full(around, lid), ring[-1], np.roll(ring[-1], -1)], -1)])
    vertices = np.vstack([vertices, [0.0, 0.0, 0.0], [0.0, 0.0, VASE_HEIGHT]])
    return vertices, faces
