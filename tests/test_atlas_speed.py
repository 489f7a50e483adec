"""The atlas fit's speed-ups give the numbers of their slow references.

``solve_spd_blocks`` (SuperLU without pivoting, single-column supernodes) against a dense
least-squares solve of each patch, and against SuperLU's own defaults; ``concurrent_map``
(a trial's two layouts fitted at once) against the serial loop, including a whole
``fit_atlas`` with one and with two threads.
"""
import threading

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import trimesh

from fitter.fitting.atlas import detail as atlas_detail
from fitter.fitting.atlas import fit as fit_module
from fitter.fitting.io.scan import make_scan, new_source


def _patch_rows(n: int, count: int, rng: np.random.Generator) -> sp.csr_matrix:
    """Rows of ``count`` samples on an ``(n, n)`` grid, each touching the 3 x 3 nodes around
    a random cell (a degree-2 field's support), random positive values."""
    i = rng.integers(0, n - 2, count)
    j = rng.integers(0, n - 2, count)
    cols = ((i[:, None, None] + np.arange(3)[None, :, None]) * n
            + j[:, None, None] + np.arange(3)[None, None, :]).reshape(count, 9)
    values = rng.random((count, 9)) + 0.05
    rows = np.repeat(np.arange(count), 9)
    return sp.csr_matrix((values.reshape(-1), (rows, cols.reshape(-1))), shape=(count, n * n))


@pytest.mark.parametrize("n, interior", [(10, False), (10, True), (18, False), (18, True)])
def test_block_solve_is_each_patchs_dense_least_squares(n, interior):
    """``M = A^T A + mu R`` per patch, block-diagonal over 7 patches: the batched solve in
    the patch order of ``block_order`` equals ``numpy.linalg.lstsq`` of the stacked
    ``[A; sqrt(mu) R^(1/2)]`` system, patch by patch (the regularisation's Cholesky factor
    gives the square root)."""
    rng = np.random.default_rng(n + interior)
    keep = np.flatnonzero(~atlas_detail.border_ring(n).reshape(-1)) if interior \
        else np.arange(n * n)
    m = len(keep)
    R = atlas_detail.regularisation(n).toarray()[np.ix_(keep, keep)]
    blocks, rhs, dense = [], [], []
    for _ in range(7):
        A = _patch_rows(n, 6 * n * n, rng)[:, keep]
        r = rng.normal(size=A.shape[0])
        mu = 1e-2 * float(A.multiply(A).sum()) / m
        blocks.append(A.T @ A + sp.csr_matrix(mu * R))
        rhs.append(A.T @ r)
        stacked = np.vstack([A.toarray(), np.sqrt(mu) * np.linalg.cholesky(R).T])
        dense.append(np.linalg.lstsq(stacked, np.r_[r, np.zeros(m)], rcond=None)[0])
    M = sp.block_diag(blocks, format="csr")
    got = atlas_detail.solve_spd_blocks(M, np.concatenate(rhs),
                                        atlas_detail.block_order(n, interior))
    want = np.concatenate(dense)
    assert np.max(np.abs(got - want)) <= 1e-9 * np.max(np.abs(want))


def test_single_column_supernodes_are_superlus_default_solve():
    """``SUPERNODE_COLUMNS`` changes how SuperLU groups its work, not the solution: the
    same system through ``spsolve`` (COLAMD, partial pivoting, default supernodes)."""
    rng = np.random.default_rng(3)
    n = 18
    A = sp.block_diag([_patch_rows(n, 5 * n * n, rng) for _ in range(5)], format="csr")
    M = (A.T @ A + 1e-3 * sp.identity(A.shape[1])).tocsr()
    b = rng.normal(size=M.shape[0])
    got = atlas_detail.solve_spd_blocks(M, b, atlas_detail.block_order(n, False))
    want = spla.spsolve(M.tocsc(), b)
    assert np.max(np.abs(got - want)) <= 1e-9 * np.max(np.abs(want))
    assert atlas_detail.SUPERNODE_COLUMNS == 1


def test_concurrent_map_keeps_order_and_the_first_error():
    seen = set()

    def job(k, delay):
        seen.add(threading.get_ident())
        threading.Event().wait(delay)
        if k in (1, 2):
            raise ValueError(f"job {k}")
        return k * k

    assert fit_module.concurrent_map(job, [(0, 0.05), (3, 0.0), (4, 0.01)]) == [0, 9, 16]
    with pytest.raises(ValueError, match="job 1"):  # job 2 fails first in time, 1 in order
        fit_module.concurrent_map(job, [(1, 0.05), (2, 0.0)])
    assert fit_module.concurrent_map(job, [], threads=2) == []
    assert fit_module.concurrent_map(job, [(5, 0.0)], threads=1) == [25]


def test_a_fit_with_its_trials_on_two_threads_is_the_serial_fit(monkeypatch):
    """The auto fit of a bunny-like shape with thin parts (both layouts at every trial) on
    two threads: trials, control points and foot points bit for bit those of one thread."""
    mesh = trimesh.creation.icosphere(subdivisions=3)
    mesh.vertices[:, 2] *= np.where(mesh.vertices[:, 0] > 0.3, 0.15, 1.0)  # a thin sheet
    source = new_source("sheet", None, "array", compression=None, reader="array")
    scan = make_scan("sheet", np.asarray(mesh.vertices), faces=np.asarray(mesh.faces),
                     source=source)
    options = {"working_count": 1500, "rounds": 1, "byte_budget": 6000}
    fits = []
    for threads in (1, 2):
        monkeypatch.setattr(fit_module, "TRIAL_THREADS", threads)
        fits.append(fit_module.fit_atlas(scan, "auto", **options))
    one, two = fits
    assert any(len(t.get("rms_by_layout", {})) == 2 for t in one.trials)
    strip = [{k: v for k, v in t.items() if not k.startswith("seconds")} for t in one.trials]
    assert strip == [{k: v for k, v in t.items() if not k.startswith("seconds")}
                     for t in two.trials]
    assert np.array_equal(fit_module.control_points(one.atlas),
                          fit_module.control_points(two.atlas))
