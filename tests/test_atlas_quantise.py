"""The detail's quantisation fed back through its own least squares (``quantised_blocks``).

The objective is rebuilt here from its documented parts (``fitter.fitting.detail``'s
collocation rows and regularisation, each patch's ``mu_f``), not from ``_BatchSystem``,
and every claim is checked on it: lower than plain rounding, no single lattice move lowers
it, the shared border ring rounded untouched.
"""
import numpy as np
import pytest

from client_py import layers
from fitter.fitting import detail as single
from fitter.fitting.atlas import detail as atlas_detail

SPANS, LEVEL, F = 4, 0, 3


def _samples(count: int = 900, seed: int = 2):
    """``count`` samples per patch of ``F`` patches at random ``(u, v)``, a smooth offset
    plus noise, weights between 0.5 and 2 (a fifth of them 0: left out)."""
    rng = np.random.default_rng(seed)
    patch = np.repeat(np.arange(F), count)
    u, v = rng.random(F * count), rng.random(F * count)
    s = np.sin(5 * u + patch) * np.cos(4 * v) + 0.05 * rng.normal(size=F * count)
    w = rng.uniform(0.5, 2.0, F * count) * (rng.random(F * count) > 0.2)
    zeros = np.zeros(F * count)
    samples = atlas_detail.AtlasSamples(patch, u, v, s, zeros, np.arange(F + 1) * count,
                                        zeros, np.ones(F * count), w)
    return samples, w


def _objective(samples, weights, q, step, rate=0.0):
    """``sum w (A c - s)^2 + sum_f mu_f c_f^T R c_f + lambda sum |q|`` (interior ``q``) with
    ``c = step q``, ``mu_f = max(tr(A_f^T W A_f) / n^2, mu_floor)`` (the module docstring of
    ``_solve_blocks``) and ``lambda = rate step^2`` times the median diagonal entry of the
    normal matrix over the interior coefficients (``quantised_blocks``)."""
    n = (SPANS << LEVEL) + atlas_detail.DEGREE
    knots = np.array(layers.level_knots(atlas_detail.DEGREE, SPANS, LEVEL))
    R = single.regularisation(n).toarray()
    floor = atlas_detail.MU_FLOOR * weights.sum() / F / (n * n) / (atlas_detail.DEGREE + 1) ** 2
    inner = ~atlas_detail.border_ring(n).reshape(-1)
    total, diagonal = 0.0, []
    for f in range(F):
        mine = samples.patch == f
        A = single.collocation_matrix(atlas_detail.DEGREE, knots, n, samples.u[mine],
                                      samples.v[mine]).toarray()
        c = step * q[f].reshape(-1)
        w = weights[mine]
        mu = max(float(np.sum(w[:, None] * A * A)) / (n * n), floor)
        total += float(np.sum(w * (A @ c - samples.s[mine]) ** 2) + mu * c @ R @ c)
        diagonal.append((np.sum(w[:, None] * A * A, axis=0) + mu * np.diag(R))[inner])
    lam = rate * step * step * float(np.median(np.concatenate(diagonal)))
    return total + lam * float(np.abs(q[:, inner.reshape(n, n)]).sum())


@pytest.fixture(scope="module")
def problem():
    samples, w = _samples()
    c, _ = atlas_detail._solve_blocks(samples, samples.s, LEVEL, SPANS, weights=w)
    step = 0.35 * float(np.abs(c).max())  # coarse: a few levels, where feedback matters
    return samples, w, c, step


def test_plain_rounding_without_sweeps(problem):
    samples, w, c, step = problem
    q = atlas_detail.quantised_blocks(samples, samples.s, LEVEL, SPANS, c, step,
                                      np.full(F, np.inf), weights=w, sweeps=0, rate=1.0)
    np.testing.assert_array_equal(q, np.rint(c / step))


@pytest.mark.parametrize("rate, share", [(0.0, np.inf), (2.0, np.inf), (1.0, 0.3), (2.0, 0.3)])
def test_feedback_leaves_no_better_single_move(problem, rate, share):
    """Converged sweeps: no interior coefficient moved by one step within its bound
    (``share`` of the largest coefficient) lowers the (penalised) objective; the border ring
    is plain rounding; without the rate the objective is well below rounding's, and the rate
    zeroes more values."""
    samples, w, c, step = problem
    limit = np.full(F, share * float(np.abs(c).max()))
    rounded = np.rint(c / step).astype(np.int64)
    q = atlas_detail.quantised_blocks(samples, samples.s, LEVEL, SPANS, c, step, limit,
                                      weights=w, sweeps=50, rate=rate)
    ring = atlas_detail.border_ring(c.shape[1])
    np.testing.assert_array_equal(q[:, ring], rounded[:, ring])
    j_fed = _objective(samples, w, q, step, rate)
    if rate == 0:
        assert j_fed < 0.95 * _objective(samples, w, rounded, step)
    else:
        plain = atlas_detail.quantised_blocks(samples, samples.s, LEVEL, SPANS, c, step,
                                              limit, weights=w, sweeps=50, rate=0)
        assert np.count_nonzero(q) < np.count_nonzero(plain)
    most = np.rint(limit / step)
    for f, a, b in zip(*np.nonzero(~ring[None].repeat(F, axis=0)), strict=True):
        for move in (-1, 1):
            other = q.copy()
            other[f, a, b] += move
            if abs(other[f, a, b]) > most[f]:
                continue  # outside the patch's bound: not a move the fit may make
            assert _objective(samples, w, other, step, rate) >= j_fed * (1 - 1e-12)


def test_feedback_keeps_within_the_bound(problem):
    samples, w, c, step = problem
    limit = np.array([0.5, 1.0, 2.0]) * step
    q = atlas_detail.quantised_blocks(samples, samples.s, LEVEL, SPANS, np.zeros_like(c),
                                      step, limit, weights=w)
    inner = ~atlas_detail.border_ring(c.shape[1])
    assert np.all(np.abs(q[:, inner] * step) <= limit[:, None] + 1e-12)


def test_one_colour_shares_no_term_of_the_objective():
    """The colouring ``(a mod s, b mod s)`` with ``s = coupling_stride()``: two different
    coefficients of one colour have a zero entry in the normal matrix of the drawn rows
    (three nodes half a span apart per sample, as ``DrawnModel``) and the regularisation."""
    n = (SPANS << LEVEL) + atlas_detail.DEGREE
    knots = np.array(layers.level_knots(atlas_detail.DEGREE, SPANS, LEVEL))
    rng = np.random.default_rng(4)
    u, v = rng.random(4000), rng.random(4000)
    h = 1.0 / (2 * SPANS)
    A = sum(single.collocation_matrix(atlas_detail.DEGREE, knots, n, np.clip(u + du, 0, 1),
                                      np.clip(v + dv, 0, 1))
            for du, dv in ((0, 0), (h, 0), (0, h)))
    M = (A.T @ A + single.regularisation(n)).toarray()
    s = atlas_detail.coupling_stride()
    a, b = np.divmod(np.arange(n * n), n)
    colour = (a % s) * s + b % s
    same = (colour[:, None] == colour[None, :]) & ~np.eye(n * n, dtype=bool)
    assert np.all(M[same] == 0)
    # and the stride is the least that works: one less couples some pair
    colour = (a % (s - 1)) * (s - 1) + b % (s - 1)
    same = (colour[:, None] == colour[None, :]) & ~np.eye(n * n, dtype=bool)
    assert np.any(M[same] != 0)


def _strip_slots(n: int) -> np.ndarray:
    """``G (F, n, n)`` of ``F`` patches side by side in ``u``: patch ``f``'s last column of
    coefficients is patch ``f + 1``'s first (one shared slot each), as ``shared_index``
    numbers a welded level's slots."""
    width = F * (n - 1) + 1
    a, b = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    return np.stack([a * width + f * (n - 1) + b for f in range(F)])


def _welded_objective(samples, weights, q, step, rate, G):
    """:func:`_objective` without its rate, plus ``lambda`` times ``|q|`` of every interior
    value and of every border slot once (a welded pack codes a shared slot once)."""
    n = q.shape[1]
    ring = atlas_detail.border_ring(n)
    slots = {}
    for f in range(F):
        for g, value in zip(G[f][ring], q[f][ring], strict=True):
            assert slots.setdefault(int(g), int(value)) == value  # one value a slot
    with_rate = _objective(samples, weights, q, step, rate)
    without = _objective(samples, weights, q, step, 0.0)
    lam_inner = with_rate - without  # lambda * sum |q| over the interiors
    inner_sum = float(np.abs(q[:, ~ring]).sum())
    lam = lam_inner / inner_sum if inner_sum else 0.0
    return without + lam * (inner_sum + sum(abs(v) for v in slots.values()))


@pytest.fixture(scope="module")
def welded(problem):
    """The independent fits bounded per patch, then their shared slots set to the mean (as
    ``_solve_level``), the bound ``limit (F,)`` and the slots ``G``."""
    samples, w, _, step = problem
    c, weight = atlas_detail._solve_blocks(samples, samples.s, LEVEL, SPANS, weights=w)
    limit = np.array([0.4, 1.0, 0.4]) * float(np.abs(c).max())  # 1, 3 and 1 steps
    c = np.clip(c, -limit[:, None, None], limit[:, None, None])
    G = _strip_slots(c.shape[1])
    return atlas_detail._share_borders(c, weight, G), limit, G


@pytest.mark.parametrize("rate", [0.0, 1.0])
def test_shared_ring_moves_as_one_and_lowers_the_objective(problem, welded, rate):
    """With the shared slots, the ring moves too: every slot keeps one integer in all its
    patches, within the least of their bounds (or its rounded start), and the penalised
    objective (each slot's rate once) is below that of the ring rounded; the interiors are
    converged again after the ring moved (no single step of one lowers it)."""
    samples, w, _, step = problem
    c, limit, G = welded
    kwargs = dict(weights=w, sweeps=50, rate=rate)
    plain = atlas_detail.quantised_blocks(samples, samples.s, LEVEL, SPANS, c, step, limit,
                                          **kwargs)
    q = atlas_detail.quantised_blocks(samples, samples.s, LEVEL, SPANS, c, step, limit,
                                      shared=G, **kwargs)
    ring = atlas_detail.border_ring(c.shape[1])
    assert np.any(q[:, ring] != plain[:, ring])  # the ring did move
    j = _welded_objective(samples, w, q, step, rate, G)  # also checks one value a slot
    assert j < _welded_objective(samples, w, plain, step, rate, G)
    most = np.rint(limit / step)
    least = {}  # each slot's bound: the least of its patches', or its rounded start
    for f in range(F):
        for g, start in zip(G[f][ring], plain[f][ring], strict=True):
            least[int(g)] = min(least.get(int(g), np.inf), most[f])
            least[int(g)] = max(least[int(g)], abs(start))
    assert any(least[g] < max(most) for g in least)  # a bound that binds
    for f in range(F):
        for g, value in zip(G[f][ring], q[f][ring], strict=True):
            assert abs(value) <= least[int(g)]
    for f, a, b in zip(*np.nonzero(~ring[None].repeat(F, axis=0)), strict=True):
        for move in (-1, 1):
            other = q.copy()
            other[f, a, b] += move
            if abs(other[f, a, b]) <= most[f]:
                assert _welded_objective(samples, w, other, step, rate, G) >= j * (1 - 1e-12)


def test_shared_ring_moves_each_slot_to_its_best_integer(problem, welded):
    """The ring's own descent (interiors held), run to convergence: no single step of one
    slot, in all its patches at once, lowers the objective (``J`` alone: rate 0)."""
    samples, w, _, step = problem
    c, _, G = welded
    q0 = atlas_detail.quantised_blocks(samples, samples.s, LEVEL, SPANS, c, step,
                                       np.full(F, np.inf), weights=w, sweeps=50, rate=0.0)
    system = atlas_detail._BatchSystem(samples, samples.s, LEVEL, SPANS, w, None, None, None)
    q = atlas_detail._ring_descent(q0, G, system.per_batch,
                                   lambda first: system.normal(first)[:2], step,
                                   np.full(F, np.inf), 0.0, 50)
    ring = atlas_detail.border_ring(c.shape[1])
    np.testing.assert_array_equal(q[:, ~ring], q0[:, ~ring])
    j = _welded_objective(samples, w, q, step, 0.0, G)
    for g in np.unique(G[:, ring]):
        for move in (-1, 1):
            other = q.copy()
            other[G == g] += move
            assert _welded_objective(samples, w, other, step, 0.0, G) >= j * (1 - 1e-12)
