"""fitter.fitting.error: the foot-point deviations (against scipy.optimize) and their
evaluator (against the patch's own), the z-buffered scan view and the coloured error PLY."""

from __future__ import annotations

import matplotlib
import numpy as np
import pytest
import trimesh

from fitter.fitting.closest import ClosestPoints, SpanPolynomials
from fitter.fitting.error import _depth_view, deviations, write_error_ply
from fitter.fitting.io.thin import VoxelGrid
from fitter.fitting.nurbs import PatchModel


def test_depth_view_shows_the_nearest_point_of_each_pixel():
    rng = np.random.default_rng(0)
    points = rng.uniform(0, 1, (3000, 3))
    d = rng.normal(size=3000)
    view, extent = _depth_view(points, d, width=24)
    rows, cols = view.shape
    assert extent == (points[:, 0].min(), points[:, 0].max(),
                      points[:, 1].min(), points[:, 1].max())
    expected = np.full((rows, cols), np.nan)
    best = np.full((rows, cols), -np.inf)
    x0, x1, y0, y1 = extent
    for (x, y, z), dk in zip(points, d, strict=True):  # reference: one point at a time
        c = min(int((x - x0) / (x1 - x0) * cols), cols - 1)
        r = min(int((y - y0) / (y1 - y0) * rows), rows - 1)
        if z > best[r, c]:
            best[r, c], expected[r, c] = z, dk
    np.testing.assert_array_equal(view, expected)


def test_error_ply_colours_and_keeps_the_deviation(tmp_path):
    d = np.array([-2.0, -1.0, 0.0, 1.0, 2.0] + [0.5] * 95)
    points = np.column_stack([np.arange(100.0), np.zeros(100), np.zeros(100)])
    write_error_ply(tmp_path / "e.ply", points, d)
    mesh = trimesh.load(tmp_path / "e.ply", process=False)
    raw = mesh.metadata["_ply_raw"]["vertex"]["data"]
    np.testing.assert_array_equal(raw["quality"], d.astype(np.float32))
    rgb = np.column_stack([raw["red"], raw["green"], raw["blue"]]).astype(int)
    limit = np.percentile(np.abs(d), 99)
    cmap = matplotlib.colormaps["coolwarm"]
    for k in range(5):  # within one step of the 256-colour table
        want = np.array(cmap(np.clip(0.5 + 0.5 * d[k] / limit, 0, 1))[:3]) * 255
        assert np.abs(rgb[k] - want).max() <= 3


def test_error_ply_reads_back_through_trimesh_with_the_same_points_colours_and_quality(
        tmp_path):
    """error.ply through trimesh (an independent reader) and against the record layout
    written with numpy's structured dtype (the independent reference of the body bytes)."""
    rng = np.random.default_rng(5)
    n = 20_000
    points = rng.normal(size=(n, 3)) * [50.0, 30.0, 5.0] + [250.0, -40.0, 1200.0]
    d = rng.normal(scale=0.1, size=n)
    write_error_ply(tmp_path / "e.ply", points, d)
    data = (tmp_path / "e.ply").read_bytes()
    cloud = trimesh.load(tmp_path / "e.ply", process=False)
    assert not hasattr(cloud, "faces") or len(cloud.faces) == 0
    np.testing.assert_array_equal(np.asarray(cloud.vertices), points.astype(np.float32))
    raw = cloud.metadata["_ply_raw"]["vertex"]["data"]
    np.testing.assert_array_equal(raw["quality"], d.astype(np.float32))
    rgb = np.column_stack([raw["red"], raw["green"], raw["blue"]])
    lut = (matplotlib.colormaps["coolwarm"](np.linspace(0, 1, 256))[:, :3] * 255).round()
    limit = np.percentile(np.abs(d), 99)
    index = np.rint(np.clip(0.5 + 0.5 * d / limit, 0, 1) * 255).astype(int)
    np.testing.assert_array_equal(rgb, lut.astype(np.uint8)[index])
    record = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"),
                       ("green", "u1"), ("blue", "u1"), ("quality", "<f4")])
    expected = np.empty(n, record)
    expected["x"], expected["y"], expected["z"] = points.T
    expected["red"], expected["green"], expected["blue"] = rgb.T
    expected["quality"] = d
    assert data[data.index(b"end_header\n") + len(b"end_header\n"):] == expected.tobytes()
    assert b"element face" not in data[: data.index(b"end_header\n")]


def _curved_patch(rational: bool, degree: tuple[int, int] = (2, 3)) -> PatchModel:
    """A wavy, strongly curved patch (a quarter tube with ripples) on non-uniform knots."""
    rng = np.random.default_rng(5)
    model = PatchModel.uniform((9, 8), degree)
    n_u, n_v = model.shape
    knots_u = model.knots[0].copy()
    inner = slice(degree[0] + 1, n_u)
    knots_u[inner] = np.sort(rng.uniform(0.05, 0.95, n_u - degree[0] - 1))
    model.knots = (knots_u, model.knots[1])
    a = np.linspace(0.0, 0.5 * np.pi, n_u)[:, None]
    y = np.linspace(0.0, 3.0, n_v)[None, :]
    model.Q[..., 0] = np.cos(a) * (1.0 + 0.15 * np.sin(4 * y))
    model.Q[..., 1] = y + 0 * a
    model.Q[..., 2] = np.sin(a) * (1.0 + 0.15 * np.sin(4 * y))
    if rational:
        model.W[:] = rng.uniform(0.6, 1.6, model.W.shape)
    return model


def _points_off(model: PatchModel, rng: np.random.Generator, m: int, largest: float
                ) -> tuple[np.ndarray, ...]:
    """``m`` points at random ``(u, v)`` of ``model``, moved along its normal by up to
    ``largest`` either way: the points ``(m, 3)``, ``u``, ``v`` and the offsets."""
    u, v = rng.random(m), rng.random(m)
    S, Su, Sv = model.evaluate(u, v, derivatives=True)
    normal = np.cross(Su, Sv)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    offset = rng.uniform(-largest, largest, m)
    return S + offset[:, None] * normal, u, v, offset


def _reference_distances(model: PatchModel, points: np.ndarray) -> np.ndarray:
    """The distance from each point to ``model`` by scipy: the best of L-BFGS-B runs
    (bounded to the domain) from the 2 nearest vertices of a 100 x 100 tessellation."""
    from scipy.optimize import minimize

    g = np.linspace(0, 1, 100)
    GU, GV = (x.ravel() for x in np.meshgrid(g, g, indexing="ij"))
    grid = model.evaluate(GU, GV)
    out = []
    for point in points:
        def squared(x: np.ndarray, point: np.ndarray = point) -> float:
            return float(np.sum((model.evaluate(x[:1], x[1:]) - point) ** 2))

        starts = np.argsort(np.sum((grid - point) ** 2, axis=1))[:2]
        out.append(min(minimize(squared, [GU[k], GV[k]], method="L-BFGS-B",
                                bounds=[(0, 1), (0, 1)],
                                options={"ftol": 1e-15, "gtol": 1e-12}).fun for k in starts))
    return np.sqrt(out)


@pytest.mark.parametrize("rational", [False, True])
def test_span_polynomials_equal_the_patch_evaluator(rational):
    model = _curved_patch(rational, (3, 2))
    rng = np.random.default_rng(1)
    u, v = rng.random(5000), rng.random(5000)
    u[:4], v[:4] = [0.0, 1.0, model.knots[0][4], 1.0], [0.0, 1.0, 0.5, model.knots[1][3]]
    expected = model.evaluate(u, v, derivatives=True)
    got = SpanPolynomials(model).evaluate(u, v)
    for e, g in zip(expected, got, strict=True):
        np.testing.assert_allclose(g.T, e, rtol=0, atol=1e-11 * np.abs(e).max())


@pytest.mark.parametrize("rational", [False, True])
def test_deviations_are_the_distances_scipy_finds(rational):
    """Foot-point distances against an independent reference (scipy.optimize from the
    nearest vertices of a tessellation) on 60 points at up to 0.3 from a curved patch,
    starting from deliberately poor parameters (a projection that is off by up to 0.2)."""
    model = _curved_patch(rational)
    rng = np.random.default_rng(2)
    m = 60
    points, u, v, offset = _points_off(model, rng, m, 0.3)
    u0 = np.clip(u + rng.uniform(-0.2, 0.2, m), 0, 1)
    v0 = np.clip(v + rng.uniform(-0.2, 0.2, m), 0, 1)
    dev = deviations(model, points, u0, v0, chunk=32, threads=2)
    reference = _reference_distances(model, points)
    np.testing.assert_allclose(np.abs(dev.d), reference, rtol=1e-5, atol=1e-9)
    # the foot point is a point of the patch at that distance, on the normal's side
    foot = model.evaluate(dev.u, dev.v)
    np.testing.assert_allclose(np.linalg.norm(points - foot, axis=1), np.abs(dev.d),
                               rtol=1e-12, atol=1e-12)
    inside = np.abs(offset) > 1e-3
    assert np.all(np.sign(dev.d[inside]) == np.sign(offset[inside]))


@pytest.mark.parametrize("rational", [False, True])
def test_voxel_candidates_answer_as_the_tree_does(rational):
    """The tessellation vertex nearer than a bound, from each point's voxel candidates
    (``ClosestPoints.cell_candidates``, the streamed error pass) and from the k-d tree alone:
    the same points and vertices, and so the same foot points to the last bit."""
    model = _curved_patch(rational)
    rng = np.random.default_rng(8)
    m = 20_000
    points, u, v, _ = _points_off(model, rng, m, 0.05)
    grid = VoxelGrid.over(points.min(axis=0), points.max(axis=0), 0.006)
    keys = np.unique(grid.keys(points))
    np.testing.assert_array_equal(grid.keys(grid.centres(keys)), keys)
    closest = ClosestPoints(model)
    candidates, reach = closest.cell_candidates(grid.centres(keys), grid.half_diagonal)
    voxel = np.searchsorted(keys, grid.keys(points))
    near = candidates[voxel], reach[voxel]
    bound = rng.uniform(0.0, 0.03, m)  # on either side of the reach (about 0.01 here)
    assert 0.2 < np.mean(bound <= near[1]) < 0.8
    by_tree = closest._nearer_vertices(points, bound)
    by_cells = closest._nearer_vertices(points, bound, near)
    assert len(by_tree[0]) > 1000
    for a, b in zip(by_tree, by_cells, strict=True):
        np.testing.assert_array_equal(a, b)
    u0 = np.clip(u + rng.uniform(-0.1, 0.1, m), 0, 1)
    v0 = np.clip(v + rng.uniform(-0.1, 0.1, m), 0, 1)
    plain = deviations(closest, points, u0, v0, chunk=4096, threads=2)
    fast = deviations(closest, points, u0, v0, chunk=4096, threads=2, near=near)
    for a, b in ((plain.d, fast.d), (plain.u, fast.u), (plain.v, fast.v)):
        np.testing.assert_array_equal(a, b)
