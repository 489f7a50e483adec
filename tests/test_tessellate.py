"""tessellate_grid and the two grid kernels: counts, positions and normals against scipy,
the kernels against each other, orientation, uvs, trimming, degenerate normals."""

from __future__ import annotations

import os
import subprocess
import sys
from array import array

import numpy as np
import pytest
from nurbs_cases import (
    dome,
    oracle,
    oracle_normals,
    quarter_cylinder,
    random_surface,
    sphere_octant,
)

from client_py import Mesh, NurbsSurface, TrimMask, tessellate_grid
from client_py._kernel import KERNEL_NAME, backend
from client_py.tessellate import grid_indices, trimmed_grid_indices

KERNELS = ["python", "numpy"]


def grid_params(surface, nu, nv):
    """The parameters tessellate_grid promises: uniform over the domain, ends exact."""
    (u0, u1), (v0, v1) = surface.domain
    us, vs = np.linspace(u0, u1, nu), np.linspace(v0, v1, nv)
    uu, vv = np.meshgrid(us, vs, indexing="ij")
    return uu.ravel(), vv.ravel()


def as_np(values, width):
    return np.frombuffer(memoryview(values), dtype=values.typecode).reshape(-1, width)


def test_counts_and_buffers():
    s = random_surface(np.random.default_rng(0), 2, 3, 6, 7)
    mesh = tessellate_grid(s, 9, 5)
    assert isinstance(mesh, Mesh)
    assert mesh.vertex_count == 45 and len(mesh.positions) == 135 and len(mesh.normals) == 135
    assert len(mesh.uvs) == 90 and mesh.colors is None
    assert mesh.triangle_count == 2 * 8 * 4 and len(mesh.indices) == 3 * 64
    # buffer protocol, as Pyodide's getBuffer needs: float32 and uint32, no copy
    for arr, fmt in ((mesh.positions, "f"), (mesh.normals, "f"), (mesh.uvs, "f"),
                     (mesh.indices, "I")):
        view = memoryview(arr)
        assert view.format == fmt and view.itemsize == 4 and view.contiguous
    idx = np.array(mesh.indices)
    assert idx.min() == 0 and idx.max() == 44
    # every grid edge is used: each cell's two triangles cover its four corners
    assert len(np.unique(idx)) == 45


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize(("p", "q"), [(1, 1), (2, 2), (3, 1), (4, 3)])
def test_positions_and_normals_match_scipy(kernel, p, q):
    rng = np.random.default_rng(10 * p + q)
    s = random_surface(rng, p, q, domain=((-2.0, 3.0), (0.5, 0.75)))
    nu, nv = 13, 17
    mesh = tessellate_grid(s, nu, nv, kernel=kernel)
    us, vs = grid_params(s, nu, nv)
    ref = oracle(s, us, vs)[0]
    pos = as_np(mesh.positions, 3).astype(float)
    # float32 output: within half a float32 ulp of the float64 oracle (plus rounding in it)
    assert np.all(np.abs(pos - ref) <= np.spacing(np.abs(ref).astype(np.float32)) + 1e-12)
    nrm = as_np(mesh.normals, 3).astype(float)
    assert np.abs(nrm - oracle_normals(s, us, vs)).max() <= 1e-6
    assert np.abs(np.linalg.norm(nrm, axis=1) - 1).max() <= 1e-6
    uv = as_np(mesh.uvs, 2)
    assert np.array_equal(uv[:, 0], us.astype(np.float32))
    assert np.array_equal(uv[:, 1], vs.astype(np.float32))


@pytest.mark.parametrize(("p", "q", "rational"), [(1, 2, False), (2, 2, True), (3, 4, True)])
def test_kernels_agree(p, q, rational):
    rng = np.random.default_rng(p + q)
    s = random_surface(rng, p, q, 12, 9, rational=rational)
    (u0, u1), (v0, v1) = s.domain
    us = np.linspace(u0, u1, 31).tolist()
    vs = np.concatenate([np.linspace(v0, v1, 20), rng.uniform(v0, v1, 7)]).tolist()
    py, nq = backend("python"), backend("numpy")
    pos_a, nrm_a, bad_a = py.evaluate_grid(s, us, vs, "d")
    pos_b, nrm_b, bad_b = nq.evaluate_grid(s, us, vs, "d")
    assert bad_a == bad_b == []
    assert np.abs(np.array(pos_a) - np.array(pos_b)).max() <= 1e-9
    assert np.abs(np.array(nrm_a) - np.array(nrm_b)).max() <= 1e-9
    # float64 against the oracle too, and the float32 outputs against each other
    uu, vv = np.meshgrid(us, vs, indexing="ij")
    ref = oracle(s, uu.ravel(), vv.ravel())[0]
    assert np.abs(np.array(pos_a).reshape(-1, 3) - ref).max() <= 1e-10
    f_a, f_b = tessellate_grid(s, 31, 20, "python"), tessellate_grid(s, 31, 20, "numpy")
    assert np.abs(np.array(f_a.positions) - np.array(f_b.positions)).max() <= 1e-6 * (
        1 + np.abs(ref).max())
    assert np.abs(np.array(f_a.normals) - np.array(f_b.normals)).max() <= 1e-6
    assert f_a.indices == f_b.indices and f_a.uvs == f_b.uvs


@pytest.mark.parametrize("kernel", KERNELS)
def test_triangles_turn_about_the_vertex_normals(kernel):
    s = random_surface(np.random.default_rng(4), 2, 2, 5, 5)
    # a gentle surface: z varies little over a 10 x 10 domain, so no fold flips a triangle
    P = np.array(s.control_points)
    P[..., 0], P[..., 1] = np.meshgrid(np.linspace(0, 10, 5), np.linspace(0, 10, 5),
                                       indexing="ij")
    s = NurbsSurface(s.degree, s.knots, P, s.weights)
    mesh = tessellate_grid(s, 20, 30, kernel=kernel)
    pos, nrm = as_np(mesh.positions, 3), as_np(mesh.normals, 3)
    tri = np.array(mesh.indices).reshape(-1, 3)
    a, b, c = pos[tri[:, 0]], pos[tri[:, 1]], pos[tri[:, 2]]
    face = np.cross(b - a, c - a)
    face /= np.linalg.norm(face, axis=1, keepdims=True)
    vertex = nrm[tri].mean(axis=1)
    assert np.einsum("ij,ij->i", face, vertex).min() > 0.9


@pytest.mark.parametrize("kernel", KERNELS)
def test_quarter_cylinder_mesh_is_on_the_circle(kernel):
    mesh = tessellate_grid(quarter_cylinder(7.0, 2.0), 64, 3, kernel=kernel)
    pos = as_np(mesh.positions, 3).astype(float)
    assert np.abs(np.hypot(pos[:, 0], pos[:, 1]) - 7.0).max() <= 2e-6  # float32 of 7
    nrm = as_np(mesh.normals, 3).astype(float)
    radial = np.column_stack([pos[:, :2] / 7.0, np.zeros(len(pos))])
    assert min(np.abs(nrm - radial).max(), np.abs(nrm + radial).max()) <= 1e-6


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("surface", ["sphere", "dome", "rational dome"])
def test_degenerate_normals_are_finite_and_point_the_right_way(kernel, surface):
    s = {"sphere": lambda: sphere_octant(3.0), "dome": lambda: dome(False),
         "rational dome": lambda: dome(True)}[surface]()
    nu = nv = 9
    mesh = tessellate_grid(s, nu, nv, kernel=kernel)
    nrm = as_np(mesh.normals, 3).astype(float)
    assert np.isfinite(nrm).all()
    assert np.abs(np.linalg.norm(nrm, axis=1) - 1).max() <= 1e-6
    pole = nrm.reshape(nu, nv, 3)[-1 if surface == "sphere" else 0]  # the collapsed row
    up = np.array([0.0, 0.0, 1.0])
    inside = nrm.reshape(nu, nv, 3)[nu // 2, nv // 2]
    side = np.sign(inside @ (as_np(mesh.positions, 3)[nu // 2 * nv + nv // 2] if surface ==
                             "sphere" else up))
    assert np.abs(pole - side * up).max() <= 1e-5


@pytest.mark.parametrize("kernel", KERNELS)
def test_trim_mask_leaves_out_cells(kernel):
    cells = [[1, 1, 0, 0], [1, 0, 0, 1], [1, 1, 1, 1]]
    rng = np.random.default_rng(8)
    base = random_surface(rng, 2, 2, 6, 6)
    s = NurbsSurface(base.degree, base.knots, base.control_points, base.weights,
                     trim=TrimMask(cells))
    nu, nv = 13, 9
    mesh = tessellate_grid(s, nu, nv, kernel=kernel)
    assert mesh.vertex_count == nu * nv  # vertices stay: indices keep their meaning
    kept = set()
    for t in np.array(mesh.indices).reshape(-1, 6):
        i, j = divmod(int(t[0]), nv)
        assert list(t) == [t[0], t[0] + nv, t[0] + 1, t[0] + 1, t[0] + nv, t[0] + nv + 1]
        kept.add((i, j))
    expected = {(i, j) for i in range(nu - 1) for j in range(nv - 1)
                if cells[int((i + 0.5) / (nu - 1) * 3)][int((j + 0.5) / (nv - 1) * 4)]}
    assert kept == expected and 0 < len(kept) < (nu - 1) * (nv - 1)


def test_grid_indices_without_trim_is_the_two_triangle_split():
    idx = np.array(grid_indices(3, 4)).reshape(-1, 3)
    assert idx.tolist()[:2] == [[0, 4, 1], [1, 4, 5]]
    assert len(idx) == 2 * 2 * 3
    assert grid_indices(3, 4, lambda i, j: True) == grid_indices(3, 4)


@pytest.mark.parametrize(("nu", "nv", "match"), [(1, 5, "nu = 1; a grid needs 2 to 8192"),
                                                 (5, 9000, "nv = 9000"),
                                                 (2.5, 5, "nu must be an integer, got 2.5"),
                                                 (True, 5, "nu must be an integer")])
def test_bad_grid_sizes(nu, nv, match):
    with pytest.raises(ValueError, match=match):
        tessellate_grid(quarter_cylinder(1.0, 1.0), nu, nv)


def test_bad_surface_and_kernel():
    with pytest.raises(ValueError, match="surface must be a NurbsSurface, got list"):
        tessellate_grid([], 4, 4)
    with pytest.raises(ValueError, match="kernel must be 'python' or 'numpy', got 'fortran'"):
        tessellate_grid(quarter_cylinder(1.0, 1.0), 4, 4, kernel="fortran")


def test_kernel_selection_by_environment():
    assert KERNEL_NAME in ("python", "numpy")
    code = "from client_py._kernel import KERNEL_NAME; print(KERNEL_NAME)"
    for wanted in ("python", "numpy"):
        env = dict(os.environ, TESSERA_KERNEL=wanted)
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                             text=True, check=True)
        assert out.stdout.strip() == wanted
    env = dict(os.environ, TESSERA_KERNEL="gpu")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.returncode != 0 and "TESSERA_KERNEL must be 'python' or 'numpy'" in out.stderr


def test_float64_output_on_request():
    s = quarter_cylinder(1.0, 1.0)
    pos, nrm, bad = backend("python").evaluate_grid(s, [0.0, 0.3], [0.0, 1.0], "d")
    assert isinstance(pos, array) and pos.typecode == "d" and bad == []
    assert abs(np.hypot(pos[6], pos[7]) - 1.0) <= 1e-15


@pytest.mark.parametrize(("rows", "cols", "nu", "nv"), [(1, 1, 2, 2), (3, 4, 5, 9), (7, 5, 40, 33),
                                                        (64, 64, 30, 100), (1, 9, 17, 3)])
def test_trimmed_indices_are_the_covered_cells(rows, cols, nu, nv):
    """The run-based trimming equals the definition: cell (i, j) is kept where the mask
    covers its centre."""
    rng = np.random.default_rng(rows * cols + nu)
    mask = TrimMask(rng.random((rows, cols)) < 0.6)
    def keep(i, j):
        return mask.covers((i + 0.5) / (nu - 1), (j + 0.5) / (nv - 1))
    assert trimmed_grid_indices(nu, nv, mask) == grid_indices(nu, nv, keep)


@pytest.mark.parametrize("kernel", KERNELS)
def test_cell_indices_of_overlapping_covers_are_their_union(kernel):
    """Covers (mask rows and columns per cell row and column, over blocks of cells) drawn
    as their union, row-major, against a cell-by-cell numpy reference."""
    rng = np.random.default_rng(12)
    nu, nv = 23, 31
    covers, expected = [], np.zeros((nu - 1, nv - 1), bool)
    for _ in range(5):
        i0, j0 = int(rng.integers(0, nu - 2)), int(rng.integers(0, nv - 2))
        i1, j1 = int(rng.integers(i0 + 1, nu)), int(rng.integers(j0 + 1, nv))
        height, width = (int(x) for x in rng.integers(1, 7, 2))
        mask = rng.random((height, width)) < 0.5
        rows = rng.integers(0, height, i1 - i0).tolist()
        cols = rng.integers(0, width, j1 - j0).tolist()
        covers.append((i0, j0, rows, cols, mask.astype(np.uint8).tobytes(), width))
        expected[i0:i1, j0:j1] |= mask[np.ix_(rows, cols)]
    got = np.array(backend(kernel).cell_indices(nu, nv, covers)).reshape(-1, 6)
    k = got[:, 0].astype(np.int64)
    assert np.array_equal(got, np.stack([k, k + nv, k + 1, k + 1, k + nv, k + nv + 1], 1))
    assert np.all(np.diff(k) > 0)
    drawn = np.zeros_like(expected)
    drawn[k // nv, k % nv] = True
    assert np.array_equal(drawn, expected) and 0 < expected.sum() < expected.size
    assert backend(kernel).cell_indices(nu, nv) == grid_indices(nu, nv, lambda i, j: True)


@pytest.mark.parametrize("kernel", KERNELS)
def test_trimmed_indices_in_both_kernels(kernel):
    rng = np.random.default_rng(3)
    mask = TrimMask(rng.random((9, 14)) < 0.5)
    nu, nv = 40, 27

    def keep(i, j):
        return mask.covers((i + 0.5) / (nu - 1), (j + 0.5) / (nv - 1))

    assert trimmed_grid_indices(nu, nv, mask, kernel) == grid_indices(nu, nv, keep)
