"""Sparse symmetric positive definite solves: SuperLU used as a Cholesky factorisation.

The fits' normal equations (``A^T A`` plus a positive smoothing or ridge term) are
symmetric positive definite. SuperLU's defaults (COLAMD column order, partial pivoting)
treat them as general matrices; a symmetric order without pivoting is the same solution
to rounding and, on the single patch's detail levels, two orders of magnitude faster
(:func:`spd_lu`). Where unknowns come in groups at the same nodes (a control point's
``x, y, z``), :func:`node_order` orders the nodes.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

SUPERNODE_COLUMNS = 1  # SuperLU's relax and panel size in spd_lu: single-column supernodes


def spd_lu(M: sp.spmatrix, permc_spec: str = "MMD_AT_PLUS_A", single_columns: bool = True):
    """SuperLU of a symmetric positive definite ``M`` as a Cholesky factorisation in LU
    form: a symmetric fill-reducing order (minimum degree on ``M^T + M``, or ``"NATURAL"``
    for a matrix already permuted) and no pivoting, which an SPD matrix does not need
    (Golub & Van Loan, *Matrix Computations*, 4th ed., 4.2).

    Supernodes are kept to single columns (``relax = panel_size =``
    :data:`SUPERNODE_COLUMNS`): these factors have some 50 non-zeros a column, too few
    for SuperLU's dense supernode updates to pay for their bookkeeping. Measured on the
    15-scan Happy Buddha: a 21,412-control-point base system 0.36 s with SuperLU's
    defaults (COLAMD, partial pivoting), 0.12 s here with default supernodes, 0.10 s
    with single columns (an atlas's detail batches, which were solved so too until
    session 24, now take a band Cholesky per patch: ``atlas.detail.solve_spd_blocks``).
    The solutions agree to 4e-15 relative. A single
    patch's detail level is one 2-D grid with some 365 non-zeros a factor column, where
    SuperLU's own supernodes pay: ``single_columns=False`` keeps them (level 4, 66,564
    unknowns: 3.1 CPU-s against 5.0; level 3 the same, 0.42 against 0.46; session 18).

    Raises ``RuntimeError`` (SuperLU's) on an exactly singular matrix.
    """
    supernodes = ({"relax": SUPERNODE_COLUMNS, "panel_size": SUPERNODE_COLUMNS}
                  if single_columns else {})
    return splu(M.tocsc(), permc_spec=permc_spec, diag_pivot_thresh=0.0,
                options={"SymmetricMode": True}, **supernodes)


def node_order(pattern: sp.spmatrix, unknowns: int) -> np.ndarray:
    """A symmetric fill-reducing order, ``perm`` of shape ``(k m,)``, for a matrix over
    ``k = unknowns`` unknowns at each of ``m`` nodes (unknown ``c m + i``: node ``i``'s
    ``c``-th) whose nodes are coupled as the non-zeros of ``pattern (m, m)``: minimum
    degree on the node graph (SuperLU's, as :func:`spd_lu` orders), each node's unknowns
    kept together. Factor ``M[perm][:, perm]`` with ``permc_spec="NATURAL"``; a coupling
    of ``M`` outside ``pattern`` costs fill, not correctness.

    Ordered so, the three coordinates of a control mesh fit's normal equations
    (``atlas.subdivision.fit_control_points``: the bunny's 4,088 control points) have 3 %
    fewer factor non-zeros than minimum degree on all ``3 m`` unknowns gives, in natural
    supernodes of three columns and more: a round's factorisation took 0.87 times as long
    (median of 8, session 30), and the order is found once for all rounds.
    """
    graph = sp.csr_matrix(pattern, copy=True)
    graph.data = np.ones_like(graph.data, dtype=float)
    # strictly diagonally dominant, hence SPD: only its pattern matters to the order
    degree = np.asarray(graph.sum(axis=1)).ravel()
    node = spd_lu(graph + sp.diags(degree + 1.0), single_columns=False)
    first = np.argsort(node.perm_c)  # perm_c[i]: the place of node i
    m = len(first)
    return (first[:, None] + m * np.arange(unknowns)[None, :]).reshape(-1)
