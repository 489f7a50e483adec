"""``fitter.fitting.spd.spd_lu``, SuperLU as a Cholesky factorisation, against SuperLU's
general solve (``spsolve``: COLAMD, partial pivoting) and a dense solve."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from fitter.fitting.detail import regularisation
from fitter.fitting.spd import node_order, spd_lu


@pytest.mark.parametrize("single_columns", [True, False])
def test_spd_lu_solves_like_superlus_defaults_and_names_a_singular_matrix(single_columns):
    """On a random sparse SPD matrix, with single-column supernodes or SuperLU's own: the
    solution of ``spsolve``; an exactly singular one raises, as the default factorisation
    does (``solve_control_points`` names it ``AtlasFitError``)."""
    rng = np.random.default_rng(5)
    B = sp.random(400, 400, density=0.01, random_state=rng, format="csr")
    M = (B.T @ B + 1e-2 * sp.identity(400)).tocsc()
    b = rng.normal(size=(400, 3))
    got = spd_lu(M, single_columns=single_columns).solve(b)
    want = spla.spsolve(M, b)
    assert np.max(np.abs(got - want)) <= 1e-9 * np.max(np.abs(want))
    singular = sp.diags(np.r_[np.ones(399), 0.0]).tocsc()
    with pytest.raises(RuntimeError):
        spd_lu(singular, single_columns=single_columns)


def test_a_detail_level_with_few_points_is_solved_as_the_dense_system():
    """A detail level's system where few points hold the coefficients (the case where
    partial pivoting left the diagonal): a 34 x 34 grid's regularisation plus the normal
    rows of 300 random points, against numpy's dense solve."""
    rng = np.random.default_rng(8)
    n = 34
    A = sp.random(300, n * n, density=9 / (n * n), random_state=rng, format="csr")
    M = (A.T @ A + 1e-3 * regularisation(n)).tocsc()
    b = rng.normal(size=n * n)
    want = np.linalg.solve(M.toarray(), b)
    got = spd_lu(M, single_columns=False).solve(b)
    assert np.max(np.abs(got - want)) <= 1e-8 * np.max(np.abs(want))


def test_node_order_keeps_each_nodes_unknowns_together_and_solves_as_spsolve():
    """Three unknowns at each of 200 nodes, coupled along a random node pattern: the order
    is a permutation that places a node's three unknowns side by side, and the system
    permuted by it and factored in natural order has ``spsolve``'s solution."""
    rng = np.random.default_rng(11)
    m = 200
    G = sp.random(m, m, density=0.02, random_state=rng, format="csr")
    pattern = (G + G.T + sp.identity(m)).tocsr()
    C = sp.random(3 * m, 3 * m, density=0.002, random_state=rng, format="csr")
    M = (sp.kron(np.ones((3, 3)), pattern @ pattern.T) + C.T @ C
         + sp.identity(3 * m)).tocsr()
    perm = node_order(pattern, 3)
    assert sorted(perm.tolist()) == list(range(3 * m))
    assert np.array_equal(perm.reshape(m, 3) % m, np.repeat(perm[::3] % m, 3).reshape(m, 3))
    b = rng.normal(size=3 * m)
    got = np.empty(3 * m)
    got[perm] = spd_lu(M[perm][:, perm], permc_spec="NATURAL").solve(b[perm])
    want = spla.spsolve(M.tocsc(), b)
    assert np.max(np.abs(got - want)) <= 1e-9 * np.max(np.abs(want))
