"""The atlas fit's speed-ups give the numbers of their slow references.

``solve_spd_blocks`` (a band Cholesky factorisation of each patch's block) against a dense
least-squares solve of each patch, and against SuperLU's own defaults.
"""
import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from fitter.fitting.atlas import detail as atlas_detail


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
    """``M = A^T A + mu R`` per patch, block-diagonal over 7 patches: the batched solve
    equals ``numpy.linalg.lstsq`` of the stacked
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
    got = atlas_detail.solve_spd_blocks(M, np.concatenate(rhs), m)
    want = np.concatenate(dense)
    assert np.max(np.abs(got - want)) <= 1e-9 * np.max(np.abs(want))


def test_the_band_solve_is_superlus_default_solve():
    """The same block-diagonal system through ``spsolve`` (COLAMD, partial pivoting)."""
    rng = np.random.default_rng(3)
    n = 18
    A = sp.block_diag([_patch_rows(n, 5 * n * n, rng) for _ in range(5)], format="csr")
    M = (A.T @ A + 1e-3 * sp.identity(A.shape[1])).tocsr()
    b = rng.normal(size=M.shape[0])
    got = atlas_detail.solve_spd_blocks(M, b, n * n)
    want = spla.spsolve(M.tocsc(), b)
    assert np.max(np.abs(got - want)) <= 1e-9 * np.max(np.abs(want))


def test_a_blocks_solution_does_not_depend_on_the_blocks_beside_it():
    """Each block is factored in its own band: a narrow block (the regularisation alone,
    a patch with no samples: half-width 2 n + 2) solved beside a wider one (coupled 3 n
    apart) gives the bytes it gives alone, and the caller's matrix is left as it was
    (duplicates summed on a copy)."""
    rng = np.random.default_rng(11)
    n = 10
    wide = _patch_rows(n, 4 * n * n, rng)
    far = 0.1 * (sp.eye(n * n, k=3 * n) + sp.eye(n * n, k=-3 * n))
    wide = (wide.T @ wide + far + sp.identity(n * n)).tocsr()
    narrow = (0.37 * atlas_detail.regularisation(n)).tocsr()
    b = rng.normal(size=2 * n * n)
    alone = atlas_detail.solve_spd_blocks(narrow, b[n * n:], n * n)
    pair = sp.block_diag([wide, narrow], format="csr")
    before = (pair.indptr.copy(), pair.indices.copy(), pair.data.copy())
    beside = atlas_detail.solve_spd_blocks(pair, b, n * n)
    assert beside[n * n:].tobytes() == alone.tobytes()
    assert all(np.array_equal(x, y) for x, y in zip(before, (pair.indptr, pair.indices,
                                                            pair.data), strict=True))


def test_a_block_that_is_not_positive_definite_gets_its_least_squares_solution():
    """A patch whose block is singular (no data, no regularisation: all zero but one
    coefficient) is solved by dense least squares, its neighbours in the batch as usual;
    a matrix that is not block-diagonal in the given blocks is refused by name."""
    rng = np.random.default_rng(5)
    n = 6
    good = _patch_rows(n, 4 * n * n, rng)
    good = (good.T @ good + 1e-3 * sp.identity(n * n)).tocsr()
    singular = sp.csr_matrix(([2.0], ([4], [4])), shape=(n * n, n * n))
    M = sp.block_diag([good, singular, good], format="csr")
    b = rng.normal(size=3 * n * n)
    got = atlas_detail.solve_spd_blocks(M, b, n * n)
    assert np.allclose(got[:n * n], spla.spsolve(good.tocsc(), b[:n * n]), rtol=1e-9)
    middle = np.zeros(n * n)
    middle[4] = b[n * n + 4] / 2.0
    assert np.allclose(got[n * n:2 * n * n], middle)
    assert np.allclose(got[2 * n * n:], spla.spsolve(good.tocsc(), b[2 * n * n:]), rtol=1e-9)
    coupled = M.tolil()
    coupled[n * n, 0] = 1.0  # below the diagonal only
    with pytest.raises(ValueError, match="not block-diagonal"):
        atlas_detail.solve_spd_blocks(coupled.tocsr(), b, n * n)
    with pytest.raises(ValueError, match="blocks of 7 unknowns"):
        atlas_detail.solve_spd_blocks(M, b, 7)
