"""Generated example scans: the built-in input of ``make demo`` and of the tests.

``relief_scan`` imitates a structured-light scan of a carved stone relief: a
slightly curved block face with a raised rosette, a chiselled groove and a
sharp-edged step, sampled at scattered points with sensor noise, tilted in
space like a real capture. It is synthetic, and labelled so wherever it is used.
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
