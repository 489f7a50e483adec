"""A cloud's normals turned to one side (fitter.fitting.atlas.surface.orient_normals):
exact normals given random signs come back outward everywhere, across a crease sharper than
90° (a cone's rim), around a handle (a torus), on an open cap and on separate pieces; and a
cloud without normals is reconstructed by Poisson with its estimated normals."""

from __future__ import annotations

import numpy as np
import pytest

from fitter.fitting.atlas.measure import point_mesh_distance
from fitter.fitting.atlas.surface import orient_normals, scan_surface
from tests.test_orient import cone_on_base


def cone_normals(points: np.ndarray) -> np.ndarray:
    """Outward unit normals of :func:`tests.test_orient.cone_on_base` ``(2, 1.0)``: ``-z``
    on its base disk (``z = -1.5``), ``(x / r, y / r, 1 / 3)`` normalised on its side (radius
    ``r = (1.5 - z) / 3``)."""
    r = np.maximum(np.hypot(points[:, 0], points[:, 1]), 1e-12)
    side = np.column_stack([points[:, 0] / r, points[:, 1] / r, np.full(len(points), 1 / 3)])
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    on_base = np.isclose(points[:, 2], -1.5)
    return np.where(on_base[:, None], [0.0, 0.0, -1.0], side)


def torus(n: int, rng: np.random.Generator, big: float = 1.0, small: float = 0.35
          ) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points of a torus about ``z`` and their outward unit normals."""
    a, b = rng.uniform(0, 2 * np.pi, (2, n))
    ring = np.column_stack([np.cos(a), np.sin(a), np.zeros(n)])
    normal = np.cos(b)[:, None] * ring + np.sin(b)[:, None] * [0.0, 0.0, 1.0]
    return big * ring + small * normal, normal


def random_signs(normals: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return normals * rng.choice([-1.0, 1.0], len(normals))[:, None]


def agreement(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", found, truth)


def test_a_cone_is_oriented_outward_across_its_sharp_rim():
    """The rim's outward normals meet at ``n_side . n_base = -0.32`` (108°): the plain
    ``n_i . n_j`` of Hoppe's propagation would flip the base against the side there."""
    rng = np.random.default_rng(0)
    points = cone_on_base(2, 1.0, n=8000).points
    truth = cone_normals(points)
    found = orient_normals(points, random_signs(truth, rng))
    assert np.allclose(np.abs(found), np.abs(truth))
    assert np.all(agreement(found, truth) > 0.99)
    # the same cloud turned inside out is still turned outward (the sign is global)
    assert np.all(agreement(orient_normals(points, -truth), truth) > 0.99)


def test_a_torus_and_two_pieces_are_each_oriented_outward():
    rng = np.random.default_rng(1)
    points, truth = torus(6000, rng)
    found = orient_normals(points, random_signs(truth, rng))
    assert np.all(agreement(found, truth) > 0.99)
    # a second torus far away, a piece of the graph of its own, given the other sign
    moved = points + [10.0, 0.0, 0.0]
    both = np.vstack([points, moved])
    truth2 = np.vstack([truth, truth])
    given = np.vstack([truth, -truth])
    assert np.all(agreement(orient_normals(both, given), truth2) > 0.99)


def test_an_open_cap_turns_to_the_side_it_bulges_to():
    rng = np.random.default_rng(2)
    d = rng.normal(size=(5000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    cap = d[d[:, 2] > 0.3]
    found = orient_normals(cap, random_signs(cap, rng))
    assert np.all(agreement(found, cap) > 0.99)


def test_estimated_normals_of_a_cone_cloud_give_its_closed_surface():
    """A cloud without normals: local PCA normals oriented by ``orient_normals``, then
    screened Poisson. A region oriented the wrong way would leave a Poisson surface that
    misses it; here every point is near the surface, which is one closed piece."""
    scan = cone_on_base(2, 1.0, n=12_000)
    surface = scan_surface(scan, poisson_depth=6)
    assert surface.repairs["normals_estimated"] is True
    assert surface.pieces == 1
    d = point_mesh_distance(scan.points, surface.vertices, surface.faces)
    assert np.percentile(d, 99) < 0.01 * surface.diagonal


@pytest.mark.parametrize("count", [1, 2])
def test_one_or_two_points_come_back_unchanged_or_paired(count):
    points = np.arange(3.0 * count).reshape(count, 3)
    normals = np.tile([0.0, 0.0, 1.0], (count, 1))
    out = orient_normals(points, normals)
    assert out.shape == (count, 3)
    assert np.allclose(np.abs(out), normals)
