"""fitter.fitting.compact: hidden control points and automatic quantisation bits."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import BSpline

from client_py import TrimMask, read_patch, write_patch
from fitter.fitting.compact import (
    DRAWN_MARGIN,
    choose_bits,
    harmonic_fill,
    settle_hidden,
    visible_control_points,
)
from fitter.fitting.nurbs import PatchModel


def disc_cells(rows: int = 64, cols: int = 64, radius: float = 0.3) -> np.ndarray:
    r = (np.arange(rows) + 0.5) / rows - 0.5
    c = (np.arange(cols) + 0.5) / cols - 0.5
    return (r[:, None] ** 2 + c[None, :] ** 2) < radius**2


def wild_model(shape=(16, 14), seed=0) -> PatchModel:
    rng = np.random.default_rng(seed)
    model = PatchModel.uniform(shape, (2, 2))
    model.Q = rng.normal(size=(*shape, 3))
    model.W = np.exp(rng.normal(0, 0.2, shape))
    return model


def test_visible_control_points_match_basis_supports():
    """Reference: a control point is visible when its scipy B-spline basis function is
    non-zero somewhere in a drawn cell (cells dilated by the tessellation margin)."""
    model = wild_model()
    cells = disc_cells()
    visible = visible_control_points(model, cells)
    rows, cols = cells.shape
    grow = int(np.ceil(DRAWN_MARGIN * rows))
    drawn = np.zeros_like(cells)
    for r, c in zip(*np.nonzero(cells), strict=True):
        drawn[max(r - grow, 0):r + grow + 1, max(c - grow, 0):c + grow + 1] = True
    t = (np.arange(8 * rows) + 0.5) / (8 * rows)  # points inside every cell
    inside = drawn[(t * rows).astype(int)][:, (t * cols).astype(int)]
    for axis, n in enumerate(model.shape):
        knots = model.knots[axis]
        basis = np.stack([BSpline(knots, np.eye(n)[a], 2)(t) for a in range(n)])
        if axis == 0:
            nonzero_u = basis > 0
        else:
            nonzero_v = basis > 0
    expected = np.einsum("ak,bl,kl->ab", nonzero_u, nonzero_v, inside) > 0
    assert visible.sum() < visible.size  # the test means something
    assert np.array_equal(visible, expected)


def test_settle_hidden_keeps_the_drawn_surface_and_shrinks_the_box():
    model = wild_model()
    model.Q[0, 0] += 1000.0  # a far-out control point in a corner no cell draws
    cells = disc_cells()
    settled = settle_hidden(model, cells)
    rng = np.random.default_rng(1)
    u, v = rng.uniform(0, 1, (2, 20000))
    drawn = cells[(u * cells.shape[0]).astype(int), (v * cells.shape[1]).astype(int)]
    assert np.allclose(settled.evaluate(u[drawn], v[drawn]), model.evaluate(u[drawn], v[drawn]),
                       rtol=0, atol=1e-12)
    visible = visible_control_points(model, cells)
    lo, hi = model.Q[visible].min(axis=0), model.Q[visible].max(axis=0)
    assert np.all(settled.Q >= lo - 1e-12) and np.all(settled.Q <= hi + 1e-12)
    assert np.ptp(settled.Q[..., 0]) < 10 < np.ptp(model.Q[..., 0])
    # at equal bits the drawn surface survives quantisation far better: the box is smaller
    trim = TrimMask(cells)
    exact = model.evaluate(u[drawn], v[drawn])

    def quantised_error(m: PatchModel) -> float:
        q = PatchModel.from_surface(read_patch(write_patch(m.to_surface(trim), bits=12)))
        return float(np.abs(q.evaluate(u[drawn], v[drawn]) - exact).max())

    assert quantised_error(settled) < 0.01 * quantised_error(model)


def test_harmonic_fill_reproduces_linear_functions():
    """The discrete Laplacian vanishes on linear functions: known values of one are
    extended exactly, whatever the shape of the unknown region."""
    a, b = np.meshgrid(np.arange(12.0), np.arange(9.0), indexing="ij")
    linear = np.stack([2 * a - 3 * b + 1, 0.5 * a + b], axis=-1)
    known = np.zeros((12, 9), bool)
    known[0, :] = known[:, 0] = known[-1, :] = known[:, -1] = True
    known[5, 4] = True
    scrambled = np.where(known[..., None], linear, 1e6)
    assert np.allclose(harmonic_fill(scrambled, known), linear, atol=1e-9)


def test_no_trim_changes_nothing():
    model = wild_model()
    assert settle_hidden(model, None) is model


@pytest.mark.parametrize("fit_rms", [1e-1, 1e-3])
def test_choose_bits_is_the_fewest_within_tolerance(fit_rms):
    model = wild_model()
    surface = model.to_surface()
    rng = np.random.default_rng(2)
    u, v = rng.uniform(0, 1, (2, 5000))
    bits, data = choose_bits(surface, u, v, fit_rms)
    exact = model.evaluate(u, v)

    def moved_rms(k: int) -> float:
        d = PatchModel.from_surface(read_patch(write_patch(surface, bits=k))).evaluate(u, v)
        return float(np.sqrt(np.mean(np.sum((d - exact) ** 2, axis=1))))

    assert data == write_patch(surface, bits=bits)
    assert moved_rms(bits) <= 0.1 * fit_rms
    assert bits == 8 or moved_rms(bits - 1) > 0.1 * fit_rms


def test_drawn_cells_drop_where_the_surface_strays_from_the_scan():
    """A flat patch with one control point pulled 5 units up, against a scan of the flat
    plane: the cells under that control point's support go, the rest stay."""
    from fitter.fitting.compact import drawn_cells

    model = PatchModel.uniform((12, 12), (2, 2))
    g = np.linspace(0, 1, 12)
    model.Q[..., 0], model.Q[..., 1] = np.meshgrid(g * 10, g * 10, indexing="ij")
    model.Q[6, 6, 2] = 5.0
    t = np.linspace(0, 10, 301)
    X, Y = np.meshgrid(t, t, indexing="ij")
    scan = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    cells = np.ones((40, 40), bool)
    kept = drawn_cells(model, cells, scan, fit_rms=0.01)
    r, c = np.nonzero(~kept)
    # control point 6 of 12 (degree 2, 10 spans) scales the spans 4..6: domain [0.4, 0.7)
    assert len(r) > 0
    assert r.min() >= 0.4 * 40 - 1 and (r.max() + 1) <= 0.7 * 40 + 1
    assert c.min() >= 0.4 * 40 - 1 and (c.max() + 1) <= 0.7 * 40 + 1
    assert kept[:10].all() and kept[:, :10].all() and kept[30:].all()
