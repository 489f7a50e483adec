"""The benchmark's border figures against borders known by construction."""

import numpy as np
import pytest

from bench.scoring import border_edges, border_off_scan, boundary_length


def grid(n: int, hole: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The unit square as ``n x n`` cells of two triangles, cells ``hole[0]..hole[1]-1``
    (both ways) left out."""
    t = np.linspace(0.0, 1.0, n + 1)
    u, v = np.meshgrid(t, t, indexing="ij")
    vertices = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], axis=1)
    faces = []
    for i in range(n):
        for j in range(n):
            if hole and hole[0] <= i < hole[1] and hole[0] <= j < hole[1]:
                continue
            a, b, c, d = i * (n + 1) + j, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1, \
                i * (n + 1) + j + 1
            faces += [(a, b, c), (a, c, d)]
    return vertices, np.array(faces, dtype=np.int64)


def test_border_edges_of_a_square_and_a_fin():
    vertices, faces = grid(4)
    figures = boundary_length(vertices, faces, 1e-9)
    assert figures["border_edges"] == 16
    assert figures["border_length"] == pytest.approx(4.0)
    assert figures["nonmanifold_edges"] == 0
    # a third triangle on the inner diagonal (0,0)-(0.25,0.25): that edge is used three times
    fin = np.vstack([vertices, [[0.1, 0.1, 0.3]]])
    faces = np.vstack([faces, [[0, 6, len(fin) - 1]]])
    ends, nonmanifold = border_edges(fin, faces, 1e-9)
    assert nonmanifold == 1
    assert len(ends) == 16 + 2  # and the fin's two other sides are open


def test_a_hole_where_the_scan_is_closed_is_off_its_border():
    scan = border_edges(*grid(8), 1e-9)[0]
    drawn = border_edges(*grid(8, hole=(3, 5)), 1e-9)[0]  # a 0.25 x 0.25 hole inside
    off = border_off_scan(drawn, scan, reach=0.05)
    assert off["off_length"] == pytest.approx(1.0)  # the hole's perimeter
    assert off["off_share"] == pytest.approx(1.0 / 5.0)  # of 4 outside + 1
    assert border_off_scan(scan, scan, reach=0.05)["off_share"] == 0.0
    # a drawn border beside the scan's, nearer than the reach, is on it
    shifted = scan + np.array([0.0, 0.0, 0.03])
    assert border_off_scan(shifted, scan, reach=0.05)["off_share"] == 0.0
    assert border_off_scan(shifted, scan, reach=0.02)["off_share"] == 1.0


def test_a_closed_scan_or_a_closed_drawing():
    drawn = border_edges(*grid(4), 1e-9)[0]
    empty = np.zeros((0, 2, 3))
    assert border_off_scan(drawn, empty, reach=0.1)["off_share"] == 1.0
    assert border_off_scan(empty, drawn, reach=0.1) == {"off_length": 0.0, "off_share": 0.0}


def test_a_triangle_the_weld_collapses_is_left_out():
    """Vertex 3 appears only in a triangle that the weld collapses (two corners the same):
    the border is the other triangle's three sides."""
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]])
    ends, nonmanifold = border_edges(vertices, np.array([[0, 1, 2], [3, 3, 1]]), 1e-9)
    assert len(ends) == 3 and nonmanifold == 0
    assert np.linalg.norm(ends[:, 0] - ends[:, 1], axis=1).sum() == pytest.approx(2 + 2 ** 0.5)


def test_normal_errors_against_surfaces_whose_angles_are_known():
    from bench.scoring import normal_errors

    plane = grid(40)
    # the same square tilted by 10 degrees about the x axis: every sample turned 10 degrees
    tilt = np.radians(10.0)
    turned = plane[0] @ np.array([[1, 0, 0], [0, np.cos(tilt), np.sin(tilt)],
                                  [0, -np.sin(tilt), np.cos(tilt)]])
    flat = normal_errors(turned, plane[1], *plane, count=20_000)
    assert flat["mean"] == pytest.approx(10.0, abs=1e-6)
    assert flat["p90"] == pytest.approx(10.0, abs=1e-6) and flat["steep"] == 0.0
    # a ripple z = a sin(k x) over the plane: at x the surface turns atan(a k cos(k x)); its
    # area-weighted mean by quadrature (an area element grows by sqrt(1 + slope^2))
    a, k = 0.02, 2 * np.pi * 5
    n = 400
    t = np.linspace(0.0, 1.0, n + 1)
    u, v = np.meshgrid(t, t, indexing="ij")
    ripple = np.stack([u.ravel(), v.ravel(), a * np.sin(k * u.ravel())], axis=1)
    _, faces = grid(n)
    got = normal_errors(ripple, faces, *plane, count=200_000)
    x = np.linspace(0.0, 1.0, 200_001)
    slope = a * k * np.cos(k * x)
    weight = np.sqrt(1 + slope**2)
    angle = np.degrees(np.arctan(np.abs(slope)))
    assert got["mean"] == pytest.approx(np.sum(angle * weight) / np.sum(weight), rel=0.02)
    steep = np.sum((angle > 20) * weight) / np.sum(weight)  # about 0.62
    assert got["steep"] == pytest.approx(steep, abs=0.01)


def test_normal_errors_compare_with_the_scans_smooth_normal_not_its_facets():
    """A faceted sphere's interpolated vertex normals are nearly radial: the exact sphere
    turns from them by well under a degree, from its facets by about three."""
    import trimesh

    from bench.scoring import normal_errors

    coarse = trimesh.creation.icosphere(subdivisions=3)
    fine = trimesh.creation.icosphere(subdivisions=6)
    got = normal_errors(np.asarray(fine.vertices), np.asarray(fine.faces),
                        np.asarray(coarse.vertices), np.asarray(coarse.faces), count=50_000)
    assert got["mean"] < 0.6 and got["steep"] == 0.0
    from fitter.fitting.atlas.measure import closest_points_on_mesh

    facet = np.asarray(coarse.face_normals)
    samples = np.asarray(fine.sample(20_000))
    _, triangle, _ = closest_points_on_mesh(samples, np.asarray(coarse.vertices),
                                            np.asarray(coarse.faces))
    radial = samples / np.linalg.norm(samples, axis=1, keepdims=True)
    to_facets = np.degrees(np.arccos(np.clip(np.abs((radial * facet[triangle]).sum(1)), 0, 1)))
    assert to_facets.mean() > 3 * got["mean"]
