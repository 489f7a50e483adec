"""The atlas's base fit: every shared control point in one sparse least-squares solve.

The paper's eq. 5 for ``F`` patches at once. Working points ``x_k`` (the scan thinned to a
few 10^4, plus for a mesh area-weighted samples of its triangles, so a large triangle counts
by its area) each get a foot point ``(f_k, u_k, v_k)``; then

``min_P  Σ_k |C_{f_k}(u_k, v_k; P) - x_k|²  +  λ |L P|²  +  μ |P - P_0|²``,

``C_f(u, v) = Σ_ij N_i(u) N_j(v) P_{I_f(i, j)}`` (``I_f``: ``AtlasSurface.patch_indices``),
is linear in the ``N_cp`` unique control points ``P`` (shape ``(N_cp, 3)``): a sparse design
matrix ``A`` (``K × N_cp``, ``(d + 1)²`` entries a row) and the normal equations
``(AᵀA + λ LᵀL + μ I) P = Aᵀ X + μ P_0``, factorised once (SuperLU) for the three
coordinates. ``L`` holds second differences of every patch's control net along ``u`` and
``v`` and across every shared edge (the two patches' rows next to it), a discrete
thin-plate energy (as in the single patch's ``fitter.fitting.fit``) that keeps a patch with
few points well posed; ``μ`` (tiny) pins a piece without points to its layout.

Foot points. The first ones come from the layout triangle each point belongs to, chosen
among the nearest triangles as the nearest whose normal agrees with the point's
(``n_tri · n_x > 0.5``), never the plain nearest point: a point on the front of a thin wing
does not land on its back. On the bilinear initial atlas the point's barycentric position
in its triangle gives ``(u, v)`` in one of the triangle's three quads exactly. After each
solve, parameter correction moves every foot point by Newton point inversion (The NURBS
Book §6.1, eq. 6.6, in its Gauss-Newton form: the ``(C - x) · C_uu`` terms dropped, which
keeps the 2 × 2 system positive definite), hopping into the neighbouring patch across the
side where ``(u, v)`` leaves ``[0, 1]²`` (clamped on an open border), keeping the old foot
point where the new one is not nearer (:mod:`.patches`). Then the solve again: ``rounds``
times.

Open borders. Where the scan is open (a bust's cut rim), the points beyond the layout's
border (its decimated chords) get foot points clamped onto the patches' border, and the
border curves, pulled by them and held by the thin-plate term, stop short of the rim: the
detail, a displacement along the normal, cannot reach those points. So the scan's own
border (:func:`border_points`) enters the data term too, each of its points at its foot
point on the atlas's open border curves (:func:`border_foot_points`), found again every
round: ``+ w Σ_b |C_{f_b}(u_b, v_b) - x_b|²`` with ``(u_b, v_b)`` on a side without a
neighbour (``w`` in :func:`fit_layout`). The rim points can be held :data:`BORDER_OVERSHOOT`
median edges beyond the rim (outward in the surface's plane, :func:`border_outward`): a
border curve through a jagged rim leaves half the rim's points beyond it, clamped, and on
Laurana the points within three edges of her rim were 63 % of her level-0 squared error
(off by default: with the layout's border on the scan's, it drew skirts over the bunny's
holes).

The drawn side. Foot points pull the atlas toward the scan only where scan points land on
it; a patch that none reach (a wall across a crease, a flap turned over) stays where the
smoothing leaves it, and the visitor sees it. So from the second round on, samples of every
patch farther than :data:`REVERSE_REACH` from the scan are pulled onto its surface too
(:func:`reverse_rows`, point-to-plane): the other half of a two-sided distance,
``+ w_r Σ_f Σ_ab |C_f(u_a, v_b) - y_fab|²``. On the bunny's 1,152-patch base, with the
layout's edge flips (``layout.flip_edges``), the largest distance from the drawn base to
the scan fell from 2.67 % to 1.58 % of the diagonal and the drawn area farther than 1 %
from 0.75 % to 0.06 % (the flips alone: 1.64 % and 0.09 %). Pulling every sample, near ones
included, holds the parameterisation back: the working points' RMS rose by a further 6 % on
Lucy for the same largest distance; a weight of 4 instead of 1 made it worse (2.21 %).

Where the layout bridges a gap. A coarse layout triangle can span a groove or the gap between
two sheets (the Bali mask's carving where the relief meets its back, Lucy's drapery and
wing edges; located by slicing through the drawn base's farthest samples): its corners lie
on the scan, its inside up to 3 % of the diagonal off it, and its patches, pulled into the
groove from corners at its mouth, stay a fin or a wall (the mask's largest distance 2.85 %
of the diagonal on the base, 3.01 % at level 0, no matter the reverse term's samples,
weight or rounds: 2.4–2.5 %). After the fit, :func:`refine_far_base` splits the layout
where the base is still far and fits again, up to :data:`FAR_PASSES` times within the byte
budget (when splitting every far triangle would overflow it, the farthest ones that fit:
:func:`refined_within_budget`); a base near the scan everywhere is left as it is.

Where the layout spans an opening. The layout is decimated with its topology kept, but a
decimation of a trimmed Poisson stand-in can still lose a handle: on the 15-scan Happy
Buddha (stand-in seed 0) MeshLab's topology-preserving collapse left non-manifold edges,
and their repair (``surface.clean_mesh``) took the layout from the stand-in's 8 handles to 4.
A lost handle is an opening of the scan (the hole of the arch of the arm over the head, the
tunnel under a sleeve) that layout triangles now span from rim to rim, and their patches
are a sheet across it that no working point reaches (the Buddha's largest distance, 3.96 %
of the diagonal at level 0, and a third of its far area). Splitting such a triangle cannot
open the hole (a split keeps the topology), so :func:`refine_far_base` removes it instead:
a triangle with more than :data:`MEMBRANE_SHARE` of its drawn area farther than
:data:`MEMBRANE_REACH` from the scan *with the scan beside it* (:func:`membrane_shares`, the
rule of ``surface.stand_in_far``: the nearest surface of a sheet over an opening is the
rim, in the sheet's plane; a fin or a wall lifted off the surface has it along its normal)
and nothing of the scan across the sheet within :data:`OPENING_DEPTH` times that distance
(a sheet under a narrow bump has the bump's flank beside it, but the bump across it); the
layout is then open there, as the scan is. A wall in a closed groove or wedge has its
nearest surface beside it too, but within half the groove's width: hence the reach of
1.5 % of the diagonal, not :data:`FAR_REACH`'s 1 %, which opened the Bali mask's wedges by
the tusks (level 0 max 1.44 -> 1.77 %).

Folds. The first foot points come from flat layout triangles: on a curved part the points
crowd toward a triangle's sides in ``(u, v)`` and spread elsewhere, and a net held only by the
light thin plate follows that uneven spacing, bunched here and stretched there, until a patch
turns over inside itself (a pleat: the Jacobian ``C_u × C_v`` changes sign,
:func:`folded_patches`). Parameter correction then projects onto the pleat's outer sheets and
cannot undo it; the detail, a displacement along the base's normal, pushes its middle sheet
the wrong way, and no detail removes the tangential error around it (wrinkles in close-ups).
The folds are there after the first solve already (41 % of Lucy's 1,194 patches, 20 % of
Nefertiti's 1,152 with ``rounds = 1``), and neither the reverse rows (off: unchanged) nor
the correction makes them. So the first solve is made :data:`WARM_SMOOTHING` times stiffer
(a continuation in ``λ``): a smooth net without pleats, on which the correction finds foot
points spread as the surface is, and the later rounds at the normal ``λ`` bring the detail
back. On the default layouts (4 rounds), the working points' RMS fell 11 % (bunny), 29 %
(Nefertiti), 17 % (Lucy), and the share of base samples whose normal faces away from the
scan's from 4.2 / 2.1 / 8.9 % to 3.8 / 1.2 / 6.6 %. Through the whole bundle (the benchmark's
``score_object``, finest level, RMS of all scan points over Draco's at equal bytes): bunny
1.23 -> 1.11, Nefertiti 1.69 -> 1.61, Lucy 2.71 -> 2.45, Laurana 2.91 -> 2.05, the Bali mask
0.80 -> 0.69, every largest mesh-to-scan distance lower (Lucy 1.24 -> 1.10 %, the mask
1.61 -> 1.45 % of the diagonal), the squared error on points whose foot lies where the base
faces away from the scan from 5.9 / 15.8 / 23.3 % (Nefertiti, Lucy, mask) to 1.9 / 12.0 /
22.4 %. Stiffening only the patches found folded after each solve (``fold_stiffness``,
:func:`fold_row_weights`) removed fewer folds and raised the finest level's RMS (Nefertiti
+2.9 %, bunny +1.5 %): off by default. A sweep through the whole bundle (finest RMS over
Draco's; before: the figures above) chose two warm stages and 6 rounds. A stiffer first
solve (300 or 1000 times, or 1000, 100, 10 over three solves, :data:`WARM_STAGES`,
:func:`warm_factor`) with 6 rounds helped Lucy (2.07) but pulled the Bali mask's thin shell
off (0.69 -> 1.42 and 1.48, 0.7 % of its points beyond 0.5 % of the diagonal). 100 then 10
with 6 rounds improved all five (bunny 1.08, Nefertiti 1.60, Lucy 2.10, Laurana 1.87, mask
0.65; largest distances within 0.03 % of the diagonal of before, Lucy's 1.10 -> 1.03 %,
Nefertiti's 0.80 -> 0.71 %), once :func:`budget_bits` may give up two bits (Nefertiti's
lower RMS asked for 12 bits, 28.8 KB): the default (the :func:`warm_factor` schedule 100,
10, 1, 1, 1, 1). 6 rounds at 100 alone raised the mask (0.77, largest distance 1.45 -> 1.56
%). A point cloud keeps only the 10-times stage (:func:`cloud_warm`: the 15-scan Buddha's
fins under its unscanned pedestal bottom).

Rounding. ``base.tsa`` holds every control point on a grid of ``2^bits`` steps per axis
(:func:`budget_bits` chooses the bits). Rounded to nearest, each coordinate is off by up to
half a step on its own, and on the default bases that was 20-25 % of the drawn base's
squared error over all scan points (docs/benchmarks.md, session 15). :func:`fed_back_atlas`
rounds them with the error fed back instead: each code moved, within a step of the fit, to
the integer that best fits the last round's least squares given all the others
(:func:`grid_codes`), with the corners kept apart as the
writer keeps them and no patch left pleated that plain rounding does not pleat
(:func:`pleated_patches`); the file's format and reader are unchanged
(:func:`within_budget_fed_back` keeps the byte budget).

Weights stay 1 (polynomial patches): the NURBS weight step of the single patch is not
carried over to the shared control points yet.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from client_py.atlas import AtlasSurface
from client_py.atlas_format import AtlasWriter

from ..io.scan import Scan, ScanError
from ..io.thin import thin_to_count
from ..options import MAX_PATCHES
from ..spd import spd_lu
from .lattice import coupling_colours, lattice_descent
from .layout import (
    AtlasLayoutError,
    QuadLayout,
    bilinear_atlas,
    collapse_narrow_triangles,
    decimate,
    decimate_on_border,
    flip_edges,
    quad_layout,
    split_longest_edges,
    thin_part_weights,
)
from .patches import (
    assign_triangles,
    basis_matrix,
    control_points,
    correct_parameters,
    design_matrix,
    evaluate_patches,
    index_table,
    neighbour_table,
    signed_distances,
    triangle_to_quad,
    with_control_points,
)
from .surface import (
    LAYOUT_TRIM,
    ScanSurface,
    SurfaceError,
    border_edges,
    scan_surface,
    surface_beside,
    without_triangles,
)
from .threads import on_threads

DEFAULT_BYTE_BUDGET = 24_000
AUTO_FIRST_TRIANGLES = 48
AUTO_MAX_TRIANGLES = MAX_PATCHES // 3  # three quads per layout triangle
AUTO_MIN_GAIN = 0.95  # a doubling must bring the RMS below 95 % of the previous to be taken
AUTO_TRIAL_POINTS = 20_000
# The ladder starts at the largest doubling of AUTO_FIRST_TRIANGLES whose file, at this many
# bytes per layout triangle, is at most half the budget (ladder_start). The trials' bytes
# per triangle fall as the layout grows (.tsa's predicted control points): 53 and 57 on
# Lucy's and the 15-scan Buddha's smallest trials, 27 at 756 triangles.
AUTO_START_BYTES_PER_TRIANGLE = 60
# a doubling predicted over this many budgets is not fitted (predicted_trial_bytes)
AUTO_SKIP_OVER_BUDGET = 1.15
BASE_BITS = (8, 16)  # base.tsa's automatic quantisation bits (base_bits)
BASE_STEP_OVER_RMS = 1.2  # its quantisation step over the fit's RMS (base_bits)
# budget_bits gives up at most this many bits to meet the byte budget. 3 since .tsa v3
# (session 13): its smaller files let a trial pass the budget at 3 bits below the final
# fit's base_bits, and with 2 the Bali mask's accepted 2,304-patch base was then written
# at 11 bits, 39,324 bytes against the 24,000 budget (at 8 bits: 20,825).
BUDGET_FEWER_BITS = 3
PREDECIMATED_TRIANGLES = 20_000


class AtlasFitError(ScanError):
    """A scan the atlas fit cannot cover (no working points, a singular system)."""


# ------------------------------------------------------------------ the least-squares solve
def _side_rows(table: np.ndarray, f: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Patch ``f``'s border row on side ``k`` and the row next to it, along the side."""
    grid = table[f]
    if k == 0:
        return grid[:, 0], grid[:, 1]
    if k == 1:
        return grid[-1, :], grid[-2, :]
    if k == 2:
        return grid[:, -1], grid[:, -2]
    return grid[0, :], grid[1, :]


def smoothing_matrix(atlas: AtlasSurface, table: np.ndarray) -> sp.csr_matrix:
    """Second differences of every control net along ``u`` and ``v`` and across shared edges.

    Rows ``P[i-1][j] - 2 P[i][j] + P[i+1][j]`` (and along ``j``) per patch, and
    ``Q_f - 2 B + Q_g`` per position along an inner edge, ``B`` its border row and ``Q_f``,
    ``Q_g`` the two patches' rows next to it. Shape (rows, N_cp).
    """
    n = atlas.side
    triples = []
    for grid in table:
        for i in range(1, n - 1):
            triples.append(np.stack([grid[i - 1], grid[i], grid[i + 1]], axis=1))
            triples.append(np.stack([grid[:, i - 1], grid[:, i], grid[:, i + 1]], axis=1))
    edges = atlas.edges
    for pairs in edges.faces:
        if len(pairs) != 2:
            continue
        (f, k), (g, m) = pairs
        border_f, next_f = _side_rows(table, f, k)
        border_g, next_g = _side_rows(table, g, m)
        if edges.sides[f][k][1] != edges.sides[g][m][1]:
            border_g, next_g = border_g[::-1], next_g[::-1]
        triples.append(np.stack([next_f, border_f, next_g], axis=1))
    idx = np.concatenate(triples)
    rows = np.repeat(np.arange(len(idx)), 3)
    values = np.tile([1.0, -2.0, 1.0], len(idx))
    return sp.csr_matrix((values, (rows, idx.reshape(-1))),
                         shape=(len(idx), atlas.control_point_count))


def regularisation_weights(A: sp.csr_matrix, L: sp.csr_matrix, smoothing: float,
                           anchor: float) -> tuple[float, float]:
    """``(λ, μ)`` of :func:`solve_control_points`, scale-free.

    ``λ = smoothing · tr(AᵀA) / tr(LᵀL)`` and ``μ = anchor · tr(AᵀA) / N_cp``: a control
    point the data hold is pulled by the anchor about ``anchor`` of the way to its layout
    position ``P_0``; one the data do not hold (a patch beyond a scan's open border, a thin
    part with few points) stays near the layout instead of flaring out.
    """
    trace_a = float(A.multiply(A).sum())
    trace_l = float(L.multiply(L).sum())
    return smoothing * trace_a / max(trace_l, 1e-300), anchor * trace_a / A.shape[1]


def solve_control_points(A: sp.csr_matrix, targets: np.ndarray, L: sp.csr_matrix,
                         prior: np.ndarray, smoothing: float, anchor: float = 1e-2,
                         data_rows: int | None = None, row_weights: np.ndarray | None = None
                         ) -> np.ndarray:
    """``argmin_P |A P - X|² + λ |W L P|² + μ |P - P_0|²`` through the normal equations.

    ``(AᵀA + λ LᵀW²L + μ I) P = Aᵀ X + μ P_0``, one SuperLU factorisation for the three
    columns of ``X (K, 3)``; ``λ, μ`` from :func:`regularisation_weights` of the first
    ``data_rows`` rows of ``A`` (all by default: rows after them, such as the border
    points', do not stiffen the rest) and of the unweighted ``L``. ``W = diag(row_weights)``
    (all 1 by default) stiffens some rows of ``L`` beyond the rest (folded patches,
    :func:`fold_row_weights`).

    Raises
    ------
    AtlasFitError
        A singular system (SuperLU's factorisation fails).
    """
    lam, mu = regularisation_weights(A if data_rows is None else A[:data_rows], L, smoothing,
                                     anchor)
    if row_weights is not None:
        L = sp.diags(np.asarray(row_weights, np.float64)) @ L
    H = (A.T @ A + lam * (L.T @ L) + mu * sp.identity(A.shape[1], format="csr")).tocsc()
    rhs = A.T @ targets + mu * prior
    try:
        lu = spd_lu(H)  # SPD: mu > 0
    except RuntimeError as exc:
        raise AtlasFitError(f"the atlas's normal equations ({A.shape[1]} control points) "
                            f"are singular: {exc}") from None
    return lu.solve(np.ascontiguousarray(rhs))


# ------------------------------------------------------------------ open borders
# One open patch side's border points weigh as BORDER_WEIGHT patches' working points. The
# scan's rim points are its worst fitted (Laurana's cut base, 1.3 % of her points: 21 % of
# the finest level's squared error at 3). At 10 her finest RMS of all points went 0.1156 ->
# 0.1081 (30: 0.1070, 100: 0.1064), the bunny's 2.450e-5 -> 2.448e-5, largest distances
# within 0.01 % of the diagonal; the mask and the 15-scan Buddha unchanged (their rims lie
# beyond BORDER_REACH of the layout). At 30 the cut sphere of tests/test_atlas_fit.py fitted
# the rest of its surface 40 % worse (RMS 8.4e-4 against 6.0e-4 at 3 and at 10).
BORDER_WEIGHT = 10.0
BORDER_REACH = 0.05  # a border point farther than this share of the diagonal is not fitted
BORDER_SIDE_SAMPLES = 17  # samples per open patch side for the first border foot point
# The scan's rim points can be fitted this many median edge lengths beyond the rim, outward
# in the surface's tangent plane (border_points, border_outward): a border curve through a
# jagged rim leaves half its points beyond it, where no detail along the normal reaches them.
# Off: since the layout keeps its border on the scan's (layout.decimate_on_border) and has no
# narrow triangles (layout.collapse_narrow_triangles), 0.5 drew skirts across the bunny's
# small holes (largest distance 1.20 % at level 0) for the same RMS, and moved Laurana's
# level 0 from 74.5 KB to 88 KB, where Draco is near lossless (docs/benchmarks.md, session 14).
BORDER_OVERSHOOT = 0.0


#: triangles per chunk of :func:`median_edge`
EDGE_CHUNK = 400_000


def median_edge(vertices: np.ndarray, faces: np.ndarray) -> float:
    """The median edge length of a triangle surface (its resolution).

    Each triangle's three edges are measured in chunks of :data:`EDGE_CHUNK` triangles on
    the cores (``on_threads``: numpy releases the GIL), the median taken over all of them
    in order: the same lengths, the same median, as one pass over every triangle, which
    took 0.6-1.2 s for the dense vase's 2.24 M triangles (its 200 MB of corners allocated
    at once) against 0.3 s so."""
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)

    def lengths(lo: int) -> np.ndarray:
        tri = vertices[faces[lo:lo + EDGE_CHUNK]]
        return np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2)

    if not len(faces):
        return float(np.median(np.zeros((0, 3))))
    return float(np.median(np.concatenate(on_threads(lengths, len(faces), EDGE_CHUNK))))


def border_points(vertices: np.ndarray, faces: np.ndarray, overshoot: float = 0.0
                  ) -> np.ndarray:
    """Points along the open border of a triangle surface: every vertex of an edge that one
    triangle uses, and every such edge's midpoint, each moved ``overshoot`` (a length)
    outward across the border in the surface's tangent plane (:func:`border_outward`).
    Shape ``(B, 3)``; empty when closed."""
    border = border_edges(faces)
    vertices = np.asarray(vertices, np.float64)
    if not len(border):
        return np.empty((0, 3))
    points = np.concatenate([vertices[np.unique(border)], vertices[border].mean(axis=1)])
    if overshoot:
        points = points + overshoot * border_outward(vertices, faces)
    return points


def border_outward(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit directions out of the surface across its open border, one per point of
    :func:`border_points` (same order), shape ``(B, 3)``.

    A border edge ``(a, b)`` of triangle ``(a, b, c)`` points out along
    ``w - (w . e / |e|^2) e`` with ``e = b - a``, ``w = (a + b) / 2 - c``: in the triangle's
    plane, perpendicular to the edge, away from the triangle. A border vertex takes the
    normalised sum of its border edges' directions."""
    faces = np.asarray(faces, np.int64)
    vertices = np.asarray(vertices, np.float64)
    border = border_edges(faces)
    if not len(border):
        return np.empty((0, 3))
    # each border edge's triangle and the corner opposite it
    sides = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    opposite = np.concatenate([faces[:, 2], faces[:, 0], faces[:, 1]])
    sides = np.sort(sides, axis=1)
    key = sides[:, 0] * len(vertices) + sides[:, 1]
    order = np.argsort(key, kind="stable")
    where = np.searchsorted(key[order], border[:, 0] * len(vertices) + border[:, 1])
    c = vertices[opposite[order[where]]]
    a, b = vertices[border[:, 0]], vertices[border[:, 1]]
    e, w = b - a, 0.5 * (a + b) - c
    out = w - (np.einsum("kc,kc->k", w, e) / np.maximum(np.einsum("kc,kc->k", e, e),
                                                         1e-300))[:, None] * e
    out /= np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-300)
    ends, at = np.unique(border, return_inverse=True)
    total = np.zeros((len(ends), 3))
    np.add.at(total, at.reshape(-1, 2)[:, 0], out)
    np.add.at(total, at.reshape(-1, 2)[:, 1], out)
    total /= np.maximum(np.linalg.norm(total, axis=1, keepdims=True), 1e-300)
    return np.concatenate([total, out])


def _side_parameters(k: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(u, v)`` of the point at ``t`` along side ``k`` of a patch (the sides of
    :func:`.patches._hop`: 0 is ``v = 0``, 1 is ``u = 1``, 2 is ``v = 1``, 3 is ``u = 0``)."""
    u = np.select([k == 0, k == 1, k == 2, k == 3], [t, np.ones_like(t), t, np.zeros_like(t)])
    v = np.select([k == 0, k == 1, k == 2, k == 3], [np.zeros_like(t), t, np.ones_like(t), t])
    return u, v


def border_foot_points(table: np.ndarray, points: np.ndarray, degree: int, spans: int,
                       nb: np.ndarray, x: np.ndarray, iterations: int = 4
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Foot points of ``x (B, 3)`` on the atlas's open border curves.

    The nearest of :data:`BORDER_SIDE_SAMPLES` samples along every patch side without a
    neighbour, then Gauss-Newton along that side's curve, ``δt = C' · (x - C) / |C'|²``
    (``t`` clamped to ``[0, 1]``). Returns ``f, u, v, distance``, each ``(B,)``; all empty
    when the atlas has no open border.
    """
    open_f, open_k = np.nonzero(nb[:, :, 0] < 0)
    if not len(open_f) or not len(x):
        empty = np.empty(0)
        return empty.astype(np.int64), empty, empty, empty
    t = np.linspace(0.0, 1.0, BORDER_SIDE_SAMPLES)
    side_f = np.repeat(open_f, len(t))
    side_k = np.repeat(open_k, len(t))
    side_t = np.tile(t, len(open_f))
    (curve,) = evaluate_patches(table, points, degree, spans, side_f,
                                *_side_parameters(side_k, side_t))
    _, nearest = cKDTree(curve).query(x)
    f, k, t = side_f[nearest], side_k[nearest], side_t[nearest]
    for _ in range(iterations):
        u, v = _side_parameters(k, t)
        c, cu, cv = evaluate_patches(table, points, degree, spans, f, u, v, True)
        tangent = np.where((k % 2 == 0)[:, None], cu, cv)
        step = np.einsum("kc,kc->k", tangent, x - c) / np.maximum(
            np.einsum("kc,kc->k", tangent, tangent), 1e-300)
        t = np.clip(t + step, 0.0, 1.0)
    u, v = _side_parameters(k, t)
    (c,) = evaluate_patches(table, points, degree, spans, f, u, v)
    return f, u, v, np.linalg.norm(x - c, axis=1)


# ------------------------------------------------------------------ the drawn side
REVERSE_SAMPLES = 5  # samples per patch side of the atlas-to-scan term
REVERSE_WEIGHT = 1.0  # a patch's samples there weigh as much as its share of working points
REVERSE_REACH = 0.005  # only samples farther from the scan than this share of the diagonal


def reverse_rows(table: np.ndarray, points: np.ndarray, degree: int, spans: int,
                 scan_mesh: tuple[np.ndarray, np.ndarray], held: np.ndarray | None = None
                 ) -> tuple[sp.csr_matrix, np.ndarray, np.ndarray]:
    """Rows holding the atlas onto the scan: its own samples pulled to the scan's surface.

    ``Σ_f Σ_ab |C_f(u_a, v_b) - y_fab|²`` over a grid of :data:`REVERSE_SAMPLES` ``²``
    parameters per patch (cell centres), with the target
    ``y = c + ((q - c) · m) m`` for the sample ``c = C_f(u_a, v_b)``, ``q`` its closest point
    on the scan's triangles (``measure.closest_points_on_mesh``) and ``m`` that triangle's
    unit normal: the sample moves across the surface (point-to-plane, as in Chen &
    Medioni's registration, 1992) and keeps its place along it, so the term does not hold
    the parameterisation back. Frozen for one solve and found again every round. This is
    the other half of a two-sided distance: the foot-point term alone leaves any part of
    the atlas that no scan point projects onto (a wall across a crease, a flap turned
    over) free to stay far from the scan, where the visitor sees it and no detail reaches.
    Only the samples farther than :data:`REVERSE_REACH` of the scan's diagonal get a row:
    pulling the near ones too held the parameterisation back for no lower distance. A
    sample keeps its row in later rounds once it has had one (``held``, the rows of the
    previous rounds): one pulled near in a round would otherwise lose its row in the next,
    spring back and be far again after the last solve (an active set that only grows; on
    the Bali mask's 1,152-patch base, the largest distance fell from 2.85 % to 2.43 % of the
    diagonal, the working points' RMS unchanged).

    Parameters
    ----------
    held : ndarray of bool, shape (F r²,), optional
        The samples that had a row in an earlier round.

    Returns
    -------
    A : csr_matrix, shape (R, N_cp)
        ``R <= F r²`` rows, one per far sample (none when every sample is near).
    targets : ndarray, shape (R, 3)
    held : ndarray of bool, shape (F r²,)
        The samples with a row: ``held`` for the next round.
    """
    from .measure import closest_points_on_mesh

    r = REVERSE_SAMPLES
    t = (np.arange(r) + 0.5) / r
    n_f = len(table)
    f = np.repeat(np.arange(n_f), r * r)
    u = np.tile(np.repeat(t, r), n_f)
    v = np.tile(np.tile(t, r), n_f)
    (c,) = evaluate_patches(table, points, degree, spans, f, u, v)
    vertices, faces = scan_mesh
    _, nearest, q = closest_points_on_mesh(c, vertices, faces)
    corners = np.asarray(vertices, np.float64)[np.asarray(faces)[nearest]]
    m = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    m /= np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-300)
    target = c + m * np.einsum("kc,kc->k", q - c, m)[:, None]
    far = np.linalg.norm(q - c, axis=1) > REVERSE_REACH * float(
        np.linalg.norm(np.ptp(vertices, axis=0)))
    if held is not None:
        far = far | held
    if not far.any():
        return sp.csr_matrix((0, len(points))), np.empty((0, 3)), far
    return (design_matrix(table, len(points), degree, spans, f[far], u[far], v[far]),
            target[far], far)


# ------------------------------------------------------------------ folds
WARM_SMOOTHING = 100.0  # the first solve's smoothing, times the later rounds' (fit_layout)
WARM_STAGES = 2  # rounds solved stiffer than the rest, λ stepping down geometrically (fit_layout)
CLOUD_WARM_STAGES = 1  # a point cloud's warm stages: the last of WARM_STAGES' (cloud_warm)
FOLD_SAMPLES = 5  # samples per patch side of the fold test (borders included)
FOLD_STIFFNESS = 1.0  # thin-plate weight on folded patches' rows, times the rest's (1: off)


def folded_patches(table: np.ndarray, points: np.ndarray, degree: int, spans: int
                   ) -> np.ndarray:
    """Patches whose surface turns over inside them: the Jacobian changes sign.

    On a grid of :data:`FOLD_SAMPLES` ² parameters per patch (its border included), the
    normal ``n_ab = C_u × C_v`` at each sample against the patch's mean normal
    ``a_f = Σ_ab n_ab`` (a discrete ``∫∫ C_u × C_v du dv``, the patch's vector area): the
    patch is folded where some ``n_ab · a_f < 0``, a pleat whose middle sheet faces back
    (the map ``(u, v) → C`` reverses its orientation there, do Carmo, *Differential
    Geometry of Curves and Surfaces*, §2-4). A sample whose ``C_u × C_v`` vanishes (a
    collapsed corner) is not counted. Returns ``folded (F,)`` of bool.
    """
    r = FOLD_SAMPLES
    t = np.linspace(0.0, 1.0, r)
    n_f = len(table)
    f = np.repeat(np.arange(n_f), r * r)
    u = np.tile(np.repeat(t, r), n_f)
    v = np.tile(np.tile(t, r), n_f)
    _, du, dv = evaluate_patches(table, points, degree, spans, f, u, v, True)
    normal = np.cross(du, dv).reshape(n_f, r * r, 3)
    mean = normal.sum(axis=1, keepdims=True)
    side = np.einsum("fkc,fkc->fk", normal, np.broadcast_to(mean, normal.shape))
    scale = np.linalg.norm(normal, axis=2) * np.linalg.norm(mean, axis=2)
    return (side < -1e-6 * scale).any(axis=1)


def fold_row_weights(L: sp.csr_matrix, table: np.ndarray, stiff: np.ndarray,
                     stiffness: float) -> np.ndarray:
    """``W`` of :func:`solve_control_points`: ``sqrt(stiffness)`` on every row of ``L``
    that touches a control point of a ``stiff`` patch (its own second differences and the
    ones across its sides, so its neighbours' rows next to it too), 1 elsewhere: the
    thin-plate energy there weighs ``stiffness`` times the rest. A folded bicubic net has
    large second differences (its rows go back and forth), so the stiffer plate irons the
    pleat out, while the foot points keep the unfolded patches as they were."""
    mark = np.zeros(L.shape[1])
    mark[np.unique(table[stiff])] = 1.0
    touched = (abs(L) @ mark) > 0
    return np.where(touched, math.sqrt(stiffness), 1.0)


# ------------------------------------------------------------------ working points
def working_points(scan: Scan, surface: ScanSurface, count: int, seed: int = 0
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Points the base is fitted to, and their unit normals (from the surface).

    The scan's points voxel-thinned to about ``count`` (``fitter.fitting.io.thin``); for a
    mesh scan also ``count / 2`` samples spread over its triangles by area (Turk 1990), so a
    large triangle counts by its area and not by its three vertices. A point's normal is
    that of the surface vertex nearest to it (a mesh scan's vertex is its own).
    """
    pts = scan.points
    if len(pts) > count:
        pts = pts[thin_to_count(pts, count, slack=1.2)]
    vertex_normals = surface.vertex_normals
    _, nearest = cKDTree(surface.vertices).query(pts)
    normals = vertex_normals[nearest]
    if surface.origin == "mesh":
        samples, sample_normals = surface.sample(count // 2, np.random.default_rng(seed))
        pts = np.concatenate([pts, samples])
        normals = np.concatenate([normals, sample_normals])
    return pts, normals


# ------------------------------------------------------------------ the fit
@dataclass
class AtlasFit:
    """The fitted base atlas and what it was fitted to.

    Attributes
    ----------
    atlas : AtlasSurface
    layout : QuadLayout
    surface : ScanSurface
    triangles, patches : int
        ``T`` layout triangles and ``F = 3 T`` patches.
    points : ndarray, shape (K, 3)
        The working points.
    patch, u, v, distance : ndarray, shape (K,)
        Each working point's foot point and signed distance (positive on the side of
        ``C_u × C_v``, outward on a closed piece).
    rms : float
        The fit's RMS before its control points were rounded to ``base.tsa``'s grid (the
        trials' measure, comparable with theirs); ``distance`` is of the rounded base.
    bytes : int
        ``len(client_py.atlas_format.write_atlas(atlas, bits))``.
    bits : int
        The quantisation ``base.tsa`` is written at (:func:`budget_bits`).
    timings : dict
        Seconds per step (``surface``, ``layout``, ``points``, ``solve``, ``correct``, ...).
    trials : list of dict
        Every ``T`` tried: its RMS and bytes, the layout kept (``'plain'`` or
        ``'weighted'``) and each candidate's RMS and seconds; ``final_bytes`` and
        ``final_bits`` where its final fit was over the budget and refused
        (:func:`final_within_budget`).
    control_file : bytes or None
        A smooth base's ``base.tsa`` (``.smooth``: the control mesh ``atlas`` is derived
        from); ``None`` for a patches base, whose file :func:`base_file` writes.
    """

    atlas: AtlasSurface
    layout: QuadLayout
    surface: ScanSurface
    triangles: int
    patches: int
    points: np.ndarray
    patch: np.ndarray
    u: np.ndarray
    v: np.ndarray
    distance: np.ndarray
    rms: float
    bytes: int
    timings: dict = field(default_factory=dict)
    trials: list = field(default_factory=list)
    bits: int = 12
    control_file: bytes | None = None


def warm_factor(round_index: int, rounds: int, warm_smoothing: float, warm_stages: int
                ) -> float:
    """The smoothing factor of solve ``round_index`` of ``rounds`` (a continuation in ``λ``).

    With ``s = min(warm_stages, rounds - 1)`` warm stages, solve ``i < s`` uses
    ``warm_smoothing ** ((s - i) / s)`` times the smoothing and the later ones 1: e.g. 100, 10,
    then 1 for ``s = 2``. The last round is always at the normal ``λ``; ``rounds = 1`` has no
    warm stage.
    """
    stages = min(int(warm_stages), rounds - 1)
    if round_index >= stages:
        return 1.0
    return float(warm_smoothing) ** ((stages - round_index) / stages)


def cloud_warm() -> dict:
    """``fit_layout``'s warm start for a point cloud's surface: the last
    :data:`CLOUD_WARM_STAGES` of the :data:`WARM_STAGES` stages,
    ``warm_smoothing = WARM_SMOOTHING ** (CLOUD_WARM_STAGES / WARM_STAGES)`` (10, then 1,
    for the default 100, 10, then 1), ``{}`` (the defaults) when it keeps them all.

    A cloud's surface is a trimmed screened-Poisson reconstruction (``scan_surface``) and
    its working points are the scan's points alone, without triangle samples
    (:func:`working_points`). On the 15-scan Happy Buddha (a cloud, its layout from the
    closed stand-in), two warm stages left fins hanging below the unscanned pedestal
    bottom: the base's largest distance to the scan 4.06 -> 5.41 % of the diagonal
    (``grid_mesh`` at ``base_resolution``, 200,000 samples; 4.10 % with the stages off and
    6 rounds), the drawn area farther than 1 % 5.36 -> 5.04 %. With the 10-times stage
    alone: 4.07 %, 4.86 %, and 98.26 % of the points within 0.5 % of the diagonal (97.92 %
    without warm stages, 98.40 % with both; all with 6 rounds). Keyed to the stand-in
    layout instead, it also reached the Bali mask (a mesh on a stand-in layout) and
    doubled its finest RMS (1.06e-4 -> 2.29e-4): meshes keep both stages.
    """
    stages = min(int(CLOUD_WARM_STAGES), int(WARM_STAGES))
    if stages >= WARM_STAGES:
        return {}
    return {"warm_stages": stages,
            "warm_smoothing": float(WARM_SMOOTHING) ** (stages / WARM_STAGES)}


def round_rows(table: np.ndarray, current: np.ndarray, degree: int, spans: int,
               nb: np.ndarray, points: np.ndarray, f: np.ndarray, u: np.ndarray,
               v: np.ndarray, border: np.ndarray, reach: float,
               scan_mesh: tuple[np.ndarray, np.ndarray] | None, reverse_weight: float,
               held: np.ndarray | None = None
               ) -> tuple[sp.csr_matrix, np.ndarray, np.ndarray | None]:
    """The data rows of one round of :func:`fit_layout` on the atlas ``current (N_cp, 3)``:
    ``(A, X, held)`` of ``|A P - X|²``.

    The working points at their foot points ``(f, u, v)`` (the first ``len(points)``
    rows); the scan's ``border`` points within ``reach`` of an open border curve at their
    foot points there, each weighing ``w = BORDER_WEIGHT (K / F) / (B / S)``
    (:func:`fit_layout`); and with ``scan_mesh`` and ``reverse_weight > 0`` the
    :func:`reverse_rows` of the far samples (``held``: theirs), each weighing ``w_r =
    reverse_weight (K / F) / r²``. ``held`` returned: the samples with a reverse row
    (``None`` without ``scan_mesh``).
    """
    n_cp = len(current)
    A, targets = design_matrix(table, n_cp, degree, spans, f, u, v), points
    open_sides = int(np.sum(nb[:, :, 0] < 0))
    if len(border) and open_sides:
        bf, bu, bv, bd = border_foot_points(table, current, degree, spans, nb, border)
        near = bd <= reach
        if near.any():
            weight = BORDER_WEIGHT * (len(points) / len(table)) / (near.sum() / open_sides)
            A_border = design_matrix(table, n_cp, degree, spans, bf[near], bu[near], bv[near])
            A = sp.vstack([A, math.sqrt(weight) * A_border]).tocsr()
            targets = np.concatenate([targets, math.sqrt(weight) * border[near]])
    if scan_mesh is None or reverse_weight <= 0:
        return A, targets, None
    A_rev, y_rev, held = reverse_rows(table, current, degree, spans, scan_mesh, held)
    weight = reverse_weight * (len(points) / len(table)) / REVERSE_SAMPLES ** 2
    if len(y_rev):
        A = sp.vstack([A, math.sqrt(weight) * A_rev]).tocsr()
        targets = np.concatenate([targets, math.sqrt(weight) * y_rev])
    return A, targets, held


def fit_layout(layout: QuadLayout, points: np.ndarray, normals: np.ndarray, *,
               degree: int = 3, spans: int = 1, rounds: int = 4, smoothing: float = 0.1,
               anchor: float = 1e-3, border: np.ndarray | None = None,
               scan_mesh: tuple[np.ndarray, np.ndarray] | None = None,
               reverse_weight: float = REVERSE_WEIGHT, hold: bool = False,
               warm_smoothing: float | None = None, warm_stages: int | None = None,
               fold_stiffness: float | None = None, timings: dict | None = None
               ) -> tuple[AtlasSurface, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Fit an atlas on ``layout`` to ``points``: foot points, solve, ``rounds`` corrections.

    ``border (B, 3)``, optional: points along the scan's open border (:func:`border_points`).
    Each round they get foot points on the atlas's open border curves
    (:func:`border_foot_points`) and enter the data term with the weight ``w`` that makes one
    open side's border points weigh :data:`BORDER_WEIGHT` times a patch's working points,
    ``w = BORDER_WEIGHT (K / F) / (B / S)`` (``S`` open sides): the open border curves follow
    the scan's cut rim instead of stopping short of it where the foot points of the points
    beyond are clamped onto the border. Border points farther than :data:`BORDER_REACH` of
    the diagonal from every open border curve (a layout from a closed stand-in) are left out.

    ``scan_mesh (vertices, faces)``, optional: the scan's surface. From the second round on,
    :func:`reverse_rows` pull the atlas's own samples onto it, each patch's weighing
    ``reverse_weight`` times its share of working points, ``w_r = reverse_weight (K / F) /
    r²``; with ``hold``, a sample keeps its row once far (``reverse_rows``'s ``held``).

    ``warm_smoothing`` (default :data:`WARM_SMOOTHING`), ``warm_stages`` (default
    :data:`WARM_STAGES`): when ``rounds > 1``, the first solves' ``λ`` is up to
    ``warm_smoothing`` times ``smoothing``'s, stepping down to it (:func:`warm_factor`, the
    folds paragraph of the module; 1 turns it off).
    ``fold_stiffness`` (default :data:`FOLD_STIFFNESS`, 1: off): after each solve, the
    patches :func:`folded_patches` finds (kept from round to round) get their thin-plate
    rows weighted ``fold_stiffness`` times (:func:`fold_row_weights`) and the round is
    solved again.

    Returns
    -------
    atlas, patch, u, v, distance
        The fitted atlas and the final foot points with their unsigned distances.
    """
    timings = {} if timings is None else timings
    fold_stiffness = FOLD_STIFFNESS if fold_stiffness is None else fold_stiffness
    warm_smoothing = WARM_SMOOTHING if warm_smoothing is None else warm_smoothing
    warm_stages = WARM_STAGES if warm_stages is None else warm_stages
    clock = time.perf_counter()
    initial = bilinear_atlas(layout, degree, spans)
    table = index_table(initial)
    nb = neighbour_table(initial)
    prior = control_points(initial)
    L = smoothing_matrix(initial, table)
    t = assign_triangles(points, normals, layout.triangle_vertices, layout.triangles)
    f, u, v = triangle_to_quad(points, layout.triangle_vertices, layout.triangles, t)
    border = np.empty((0, 3)) if border is None else np.asarray(border, np.float64)
    if border.ndim != 2 or border.shape[1] != 3 or not np.all(np.isfinite(border)):
        raise ValueError(f"border must be finite points of shape (B, 3), got {border.shape}")
    reach = BORDER_REACH * float(np.linalg.norm(np.ptp(points, axis=0)))
    timings["foot_points"] = timings.get("foot_points", 0.0) + time.perf_counter() - clock
    current = prior
    dist = None
    held = None
    stiff = np.zeros(len(table), bool)
    weights = None
    for round_index in range(max(1, rounds)):
        clock = time.perf_counter()
        A, targets, held = round_rows(
            table, current, degree, spans, nb, points, f, u, v, border, reach,
            scan_mesh if round_index > 0 else None, reverse_weight, held)
        held = held if hold else None
        # a stiff first solve when later rounds follow (the folds paragraph of the module)
        warm = warm_factor(round_index, rounds, warm_smoothing, warm_stages)
        current = solve_control_points(A, targets, L, prior, warm * smoothing, anchor,
                                       len(points), weights)
        if fold_stiffness > 1:
            folded = folded_patches(table, current, degree, spans)
            if (folded & ~stiff).any():
                stiff |= folded
                weights = fold_row_weights(L, table, stiff, fold_stiffness)
                current = solve_control_points(A, targets, L, prior, warm * smoothing,
                                               anchor, len(points), weights)
        timings["solve"] = timings.get("solve", 0.0) + time.perf_counter() - clock
        clock = time.perf_counter()
        f, u, v, dist = correct_parameters(table, current, degree, spans, nb, points, normals,
                                           f, u, v)
        timings["correct"] = timings.get("correct", 0.0) + time.perf_counter() - clock
    return with_control_points(initial, current), f, u, v, dist


FAR_REACH = 0.01  # the fitted base is far where a sample is this share of the diagonal off
# (0.7 %: Lucy level 0 max 1.24 -> 1.08 %, but Laurana's base was refined too and its level 0
# went 0.81 -> 1.01 %, RMS 0.180 -> 0.182; at 1 % the bunny, Nefertiti, Laurana are not touched)
FAR_SAMPLES = 9  # samples per patch side (borders included) to find where the base is far
BUDGET_REFITS = 3  # refits refined_within_budget tries to meet the byte budget
MEMBRANE_REACH = LAYOUT_TRIM  # a sheet spans an opening where this share of the diagonal off
OPENING_DEPTH = 4  # ... with nothing of the scan across it within this times that distance
MEMBRANE_SHARE = 0.1  # ... beside the scan over more of its area: its triangle is removed
# (refine_far_base; stand-in seed 0, before the refit: the Buddha's arch triangles 0.22 and
# 0.17, the next 0.07; at most 0.03 on the Bali mask, whose 1.5-2 % walls lie in grooves and
# wedges that are closed, and 0.17 there with a 1 % reach, which opened them)
FAR_PASSES = 1  # refine_far_base at most this many times, while it gets nearer in the budget
# (3 passes: Lucy 1,194 -> 1,212 patches, base max 1.16 -> 1.10 %, but level 0 1.24 -> 1.34 %;
# the mask's second pass is refused as no nearer, not for its bytes: its refit, 404 -> 418
# triangles, takes four of the five far places of the first under 1.14 % of the diagonal
# (9² samples a patch: 1.38 -> 1.14, 1.23, 1.15, 1.02 -> under 0.86 %) but the wedge-shaped
# gap beside the tusk at the mouth's corner rises 1.36 -> 1.45 %: there the layout triangles
# (edges 7 % of the diagonal) have corners on both sheets of a gap 3-4 % wide, their patches
# almost no working points (0 to 11), and every split (of the longest chord, of the longest
# path along the surface at its middle, or a vertex put at the far sample's foot on the
# scan) leaves triangles across it: a wall between the sheets that the refit moves, never
# removes. 12 of the mask's 15 far triangles have corners on facing sheets (their scan
# normals' n_a . n_b < 0); splitting every edge across the gap (branch w20-mask, dee9df5)
# took the mask's level 0 max 1.44 -> 1.36 % and far area 0.063 -> 0.031 % (2 passes: 1.38 %,
# 0.016 %) but its RMS +13 % (+7 %) and Lucy's level 0 max 0.99 -> 1.23 % (1.18 %): not kept)


def far_patch_samples(atlas: AtlasSurface, scan_mesh: tuple[np.ndarray, np.ndarray]
                      ) -> np.ndarray:
    """Distance over the diagonal of the scan's surface from each patch's
    :data:`FAR_SAMPLES` ² grid (:func:`grid_mesh`'s vertices), shape ``(F, FAR_SAMPLES²)``."""
    from .measure import closest_points_on_mesh

    vertices, faces = scan_mesh
    grid, _ = grid_mesh(atlas, FAR_SAMPLES)
    d, _, _ = closest_points_on_mesh(grid, vertices, faces)
    diagonal = float(np.linalg.norm(np.ptp(np.asarray(vertices, np.float64), axis=0)))
    return d.reshape(len(atlas.quads), -1) / diagonal


def membrane_shares(atlas: AtlasSurface, scan_mesh: tuple[np.ndarray, np.ndarray],
                    reach: float = MEMBRANE_REACH) -> np.ndarray:
    """The share of each layout triangle's drawn area that spans an opening: shape ``(T,)``.

    Every patch on :func:`grid_mesh`'s :data:`FAR_SAMPLES` ² grid; a grid triangle counts
    (by its area) where its centroid ``p`` lies farther than ``reach`` of the diagonal
    (default :data:`MEMBRANE_REACH`, the stand-in's trim) from the scan's surface with the
    surface beside it: its closest point ``q`` on the scan's triangles off the grid
    triangle's unit normal ``n`` by more than ``acos(BESIDE_COS)``,
    ``|n · (q - p)| < BESIDE_COS |q - p|`` (``surface.surface_beside``). A sheet
    spanning an opening the scan leaves (the hole of an arch, a tunnel under an arm) has
    its nearest surface at the opening's rim, in its own plane; a patch lifted off the
    surface has it along its normal. Summed over a triangle's three patches, over their
    area. A wall across a narrow groove or wedge has its nearest surface beside it too,
    but within half the groove's width: the Bali mask's walls (1.5-2 % of the diagonal off,
    in wedges 3-4 % wide) give shares up to 0.17 at a 1 % reach and 0.043 at 1.5 %.
    """
    from .measure import closest_points_on_mesh

    vertices, faces = scan_mesh
    diagonal = float(np.linalg.norm(np.ptp(np.asarray(vertices, np.float64), axis=0)))
    grid, cells = grid_mesh(atlas, FAR_SAMPLES)
    corners = grid[cells]
    centroid = corners.mean(axis=1)
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    normal = cross / np.maximum(2.0 * area, 1e-300)[:, None]
    d, _, closest = closest_points_on_mesh(centroid, vertices, faces)
    gap = (d > reach * diagonal) & surface_beside(normal, closest - centroid, d)
    # an opening: nothing of the scan across the sheet either, on the line p ± t n for
    # |t| <= OPENING_DEPTH d, probed every d / 2 (a line through the surface passes a probe
    # within d / 4 of it); a sheet under a narrow bump has the bump's flank beside it and
    # the bump across it
    k = np.flatnonzero(gap)
    if len(k):
        steps = 2 * OPENING_DEPTH
        t = np.concatenate([-np.arange(1, steps + 1), np.arange(1, steps + 1)]) / 2.0
        probes = (centroid[k, None, :] + (t[None, :, None] * d[k, None, None])
                  * normal[k, None, :])
        dp, _, _ = closest_points_on_mesh(probes.reshape(-1, 3), vertices, faces)
        gap[k] = np.all(dp.reshape(len(k), -1) > 0.25 * d[k, None], axis=1)
    triangle = np.arange(len(cells)) // (len(cells) // len(atlas.quads)) // 3
    n_t = len(atlas.quads) // 3
    total = np.bincount(triangle, area, n_t)
    return np.bincount(triangle, area * gap, n_t) / np.maximum(total, 1e-300)


def refine_far_base(atlas: AtlasSurface, layout: QuadLayout, surface: ScanSurface,
                    points: np.ndarray, normals: np.ndarray, *,
                    scan_mesh: tuple[np.ndarray, np.ndarray], max_added: int | None = None,
                    measured: dict | None = None, **fit_options
                    ) -> tuple[AtlasSurface, QuadLayout, np.ndarray, np.ndarray, np.ndarray,
                               np.ndarray, int] | None:
    """The fit on a layout split where the fitted base lies far from the scan, or ``None``.

    Where a coarse layout triangle bridges a groove or the gap between two sheets (the
    Bali mask's carving, Lucy's drapery and wing edges), its corners lie on the surface and
    its inside up to 3 % of the diagonal off it; its patches must reach into the groove
    from corners at its mouth, and where a bicubic patch cannot bend that far it stays a
    wall or a fin that no detail (a displacement along the normal) removes. So when a
    sample of the fitted base (:func:`far_patch_samples`) lies farther than
    :data:`FAR_REACH` of the diagonal from the scan, the layout triangles of those patches,
    farthest first, get their longest edge split at the surface
    (:func:`.layout.split_longest_edges`, two more triangles an inner edge), the diagonals
    are flipped again (:func:`.layout.flip_edges`), the narrow triangles the splits and
    flips made are collapsed (:func:`.layout.collapse_narrow_triangles`, as in every layout
    candidate: on the 15-scan Happy Buddha one of 0.04 median edges collapsed a patch at
    the base's 8 bits, and the refit was refused) and the layout is fitted again
    (:func:`fit_layout`, every far sample keeping its reverse row, ``hold``). The refit is
    returned when its largest distance is lower; ``None`` when the base is near everywhere
    (the bunny, Nefertiti, Laurana: their fits are unchanged) or the refit is no nearer.
    ``max_added`` caps the triangles the splits add (the farthest first: a byte budget's
    room, :func:`refined_within_budget`). ``measured``, optional: a dict kept between calls
    on the same ``atlas`` and ``scan_mesh``, filled with the far samples and membrane shares
    (not measured again at a retry with another ``max_added``).

    A layout triangle spanning an opening of the scan (:func:`membrane_shares` over
    :data:`MEMBRANE_SHARE`; the module's paragraph on openings) is removed before the
    splits, not split: no split opens a hole. On the 15-scan Happy Buddha (session 13,
    stand-in seeds 0 / 1 / 2, level 0, against all 1,099,005 points, load 4-7 on 2 cores)
    the sheets across the arches by the head went: the largest distance from the drawn
    mesh fell from 3.96 / 3.96 / 3.06 % to 2.23 / 2.30 / 2.10 % of the diagonal (what is
    left: the tunnel under the right sleeve, whose sheet has the body across it, and fins
    on the rims), its area farther than 1 % from 1.62 / 1.94 / 1.20 % to 1.21 / 1.38 /
    1.11 %; the points within 0.5 % 99.51 / 99.55 / 99.50 -> 99.37 / 99.54 / 99.42 % and
    the RMS 2.17 / 2.25 / 2.19 -> 2.33 / 2.25 / 2.26 e-4 (the points lost lie at the
    sleeves and the robe, not at the arches: the refit's other changes), 57.3 / 52.9 /
    56.2 -> 57.0 / 53.3 / 55.0 KB. Lucy's and the Bali mask's largest shares are under
    :data:`MEMBRANE_SHARE` (nothing removed: their bundles are the same), and the bunny's
    base is near everywhere.

    Returns
    -------
    (atlas, layout, patch, u, v, distance, removed) or None
        The refit, its layout and foot points, and the number of triangles removed.
    """
    measured = {} if measured is None else measured
    if "far" not in measured:
        measured["far"] = far_patch_samples(atlas, scan_mesh).max(axis=1)
    far = measured["far"]
    if far.max() <= FAR_REACH:
        return None
    by_triangle = far.reshape(-1, 3).max(axis=1)
    if "shares" not in measured:
        measured["shares"] = membrane_shares(atlas, scan_mesh)
    gap = measured["shares"] > MEMBRANE_SHARE
    if gap.all():
        gap[:] = False  # a layout all over openings is no layout: split it instead
    vertices, triangles = without_triangles(layout.triangle_vertices, layout.triangles, gap)
    by_triangle = by_triangle[~gap]
    order = np.argsort(-by_triangle)
    order = order[by_triangle[order] > FAR_REACH]
    vertices, triangles, made = split_longest_edges(surface, vertices, triangles, order,
                                                    max_added)
    if not made and not gap.any():
        return None
    triangles, _ = flip_edges(surface, vertices, triangles)
    vertices, triangles, _ = collapse_narrow_triangles(surface, vertices, triangles)
    refined = quad_layout(vertices, triangles)
    r_atlas, f, u, v, dist = fit_layout(refined, points, normals, scan_mesh=scan_mesh,
                                        hold=True, **fit_options)
    if far_patch_samples(r_atlas, scan_mesh).max() >= far.max():
        return None
    return r_atlas, refined, f, u, v, dist, int(gap.sum())


def refined_within_budget(fitted: tuple[AtlasSurface, QuadLayout, int], surface: ScanSurface,
                          points: np.ndarray, normals: np.ndarray, *, bits: int | None,
                          byte_budget: int | None, **fit_options) -> tuple | None:
    """:func:`refine_far_base` of ``fitted = (atlas, layout, bytes)`` kept within the budget.

    Every far layout triangle is split first, and that refit is kept when its file stays
    within ``byte_budget`` (``None``: no budget): an object whose full refit fits is
    refined as before. When it does not (the 15-scan Happy Buddha: 170 of 381 triangles
    far, the refit 37 KB against 24 KB, so that the farthest, a triangle across the corner
    of an arm's loop over the head 3.8 % of the diagonal off the scan, was never split),
    the refit is done again with only the farthest triangles' splits, adding at most
    ``r + ⌊(B - b) / β⌋`` triangles: ``b`` the bytes before, ``B`` the budget, ``r`` the
    triangles the refused refit removed over openings (they stay removed; its splits made
    ``a + r`` for a layout ``a`` triangles larger), and ``β`` the bytes per triangle: the
    base's own ``b / T`` at the first retry, then ``(b' - b) / a`` of the last refused
    refit of ``b'`` bytes (up to :data:`BUDGET_REFITS` refits). Not the full refit's rate
    at the first retry: its lower RMS may ask for a bit more (the Buddha, stand-in seed 0:
    9 bits, 33.4 KB for 115 triangles more, where the base had 8 bits, 22.1 KB for 376),
    which would let the retry add 18 triangles (23.1 KB) where 31 fit (23.7 KB).

    Returns
    -------
    (rms, bytes, layout, atlas, f, u, v, bits) of the refit, or ``None`` when there is
    none (nothing far, no nearer refit, or none within the budget).
    """
    atlas, layout, size = fitted
    max_added = None
    measured: dict = {}  # the base's far samples and membrane shares, once for every retry
    for _ in range(BUDGET_REFITS):
        refined = refine_far_base(atlas, layout, surface, points, normals,
                                  max_added=max_added, measured=measured, **fit_options)
        if refined is None:
            return None
        r_atlas, r_layout, rf, ru, rv, rdist, removed = refined
        r_rms = float(np.sqrt(np.mean(rdist ** 2)))
        r_bits, r_size = budget_bits(r_atlas, r_rms, bits, byte_budget)
        if byte_budget is None or r_size <= byte_budget:
            return r_rms, r_size, r_layout, r_atlas, rf, ru, rv, r_bits
        # the bytes follow the net change of triangles; the removed ones stay removed, and
        # only the splits' triangles are scaled down
        net = r_layout.n_triangles - layout.n_triangles
        if net < 1:
            return None
        # the first retry at the base's own bytes per triangle: the full refit's may be
        # written with more bits (its lower RMS), which no retry within the budget keeps
        rate = (size / layout.n_triangles if max_added is None
                else (r_size - size) / net)
        max_added = min(net + removed - 1,
                        removed + int((byte_budget - size) / max(rate, 1e-9)))
        if max_added < 1:
            return None
    return None


LAYOUT_THREADS = 2  # layout candidates made, and fitted, at once (the machine's 2 cores)
_MESHLAB = threading.Lock()  # the candidates' decimations take turns: pymeshlab is not
# thread-safe (the fit's other MeshLab calls run on one thread, outside any pool)


def layout_candidates(surface: ScanSurface, target: int, thin_parts: bool,
                      on_border: bool = False) -> tuple[list[tuple[str, QuadLayout, float]],
                                                        list[tuple[str, Exception]]]:
    """The layouts a trial of ``target`` triangles fits: ``'plain'`` quadric decimation and,
    with ``thin_parts``, the ``'weighted'`` one (:func:`.layout.thin_part_weights`) unless
    its weights are all equal (then it is the plain one). ``on_border``: the patches'
    border curves will follow the surface's border, so the layout's border vertices are
    kept on it (:func:`.layout.decimate_on_border`).

    The two are made on :data:`LAYOUT_THREADS` threads, the same layouts in the same
    order as one after the other: neither reads the other's. MeshLab's collapses take
    turns (``pymeshlab`` crashed with two at once); the thin-part weights and the edge
    flips (``open3d``'s closest points, which release the GIL) overlap them.

    Returns
    -------
    candidates : list of (name, layout, seconds)
        The layouts that decimated to an oriented 2-manifold and the seconds each took.
    failures : list of (name, exception)
        The decimations refused (``AtlasLayoutError`` or ``SurfaceError``).
    """
    def one(name: str) -> tuple | None:
        clock = time.perf_counter()
        weights = None
        try:
            if name == "weighted":
                weights = thin_part_weights(surface, target)
                if np.ptp(weights) == 0:
                    return None
            with _MESHLAB:
                tri_vertices, triangles = (decimate_on_border if on_border else decimate)(
                    surface, target, weights)
        except (AtlasLayoutError, SurfaceError) as exc:
            return name, exc
        # no narrow triangle before the flips judge the diagonals, and none they made
        tri_vertices, triangles, _ = collapse_narrow_triangles(surface, tri_vertices,
                                                               triangles)
        triangles, _ = flip_edges(surface, tri_vertices, triangles)
        tri_vertices, triangles, _ = collapse_narrow_triangles(surface, tri_vertices,
                                                               triangles)
        return name, quad_layout(tri_vertices, triangles), time.perf_counter() - clock

    names = ("plain", "weighted") if thin_parts else ("plain",)
    made = [m for m in on_threads(lambda i: one(names[i]), len(names), 1, LAYOUT_THREADS)
            if m is not None]  # a thread's error raised
    return ([m for m in made if len(m) == 3], [m for m in made if len(m) == 2])


def base_bits(atlas: AtlasSurface, rms: float) -> int:
    """The fewest bits in ``BASE_BITS`` whose ``.tsa`` quantisation step, the control points'
    largest extent over ``2^bits - 1``, is at most ``BASE_STEP_OVER_RMS`` times ``rms``.

    Rounding every coordinate moves a bicubic atlas's surface by an RMS of about 0.26 step
    (measured on the bunny's and Nefertiti's 576-patch bases at 8..11 bits), so the base's
    RMS grows by about 4 % in quadrature at 1.2 steps per RMS, for 2..3 bits (20..30 % of
    the base's bytes) fewer than 12 bits; the detail levels, fitted to the decoded base,
    take the rest back.
    """
    extent = float(np.ptp(control_points(atlas), axis=0).max())
    for bits in range(BASE_BITS[0], BASE_BITS[1] + 1):
        if extent / ((1 << bits) - 1) <= BASE_STEP_OVER_RMS * rms:
            return bits
    return BASE_BITS[1]


# base.tsa's tangential factor (client_py.atlas_format, version 4): its edge and patch
# interior points coded in local frames, the step along the surface 3 times the step
# across it. On the fixed layouts of main 5dba071 (base only, RMS of all points), one bit
# more at 3 gave Lucy 0.858 at 22,332 bytes and Nefertiti 0.158 at 22,333 where version 3
# gave 0.896 at 23,359 and 0.169 at 22,784 (docs/benchmarks.md, session 16). None: v3.
BASE_TANGENT_FACTOR: float | None = 3.0


def base_file(atlas: AtlasSurface, bits: int, metadata: dict | None = None,
              writer: AtlasWriter | None = None) -> bytes:
    """``base.tsa``: ``client_py.atlas_format``'s writer (``writer``, made for ``atlas`` if
    not given) at ``bits`` with :data:`BASE_TANGENT_FACTOR`; version 3 when a point lies so
    far from its prediction that its frame code would pass the format's ``bits + 3`` bits
    (the writer's ``ValueError``: a net many times its corners' box, never seen on a fit)."""
    writer = writer or AtlasWriter(atlas)
    return _at_base_factor(lambda factor: writer.write(bits, metadata, factor))


def decoded_base(atlas: AtlasSurface, bits: int, writer: AtlasWriter | None = None
                 ) -> AtlasSurface:
    """The atlas a reader decodes from :func:`base_file` of ``atlas`` at ``bits``
    (``AtlasWriter.decoded``: from the writer's own codes, the file neither range-coded
    nor read)."""
    writer = writer or AtlasWriter(atlas)
    return _at_base_factor(lambda factor: writer.decoded(bits, factor))


def _at_base_factor(code: Callable[[float | None], object]):
    """``code(BASE_TANGENT_FACTOR)``, or ``code(None)`` (version 3) when that raises
    ``ValueError`` (:func:`base_file`)."""
    try:
        return code(BASE_TANGENT_FACTOR)
    except ValueError:
        if BASE_TANGENT_FACTOR is None:
            raise
        return code(None)


def atlas_bytes(atlas: AtlasSurface, bits: int | None, rms: float = 0.0) -> int:
    """Bytes of the ``.tsa`` file (:func:`base_file`) at ``bits``, or with ``bits=None``
    at :func:`base_bits` of the fit's ``rms``."""
    return len(base_file(atlas, bits or base_bits(atlas, rms)))


# The base alone is drawn with this many samples per knot span (base_resolution). 8, not 4
# (w25-baserd): the drawn base is the patches' chords between samples, and on the default
# bases (main 90503fb, grid_mesh of the file as written, ALL scan points) 4 left RMS
# 0.1919 (Nefertiti), 1.038 (Lucy), 0.2298 (Laurana) where 8 leaves 0.1830, 0.9605, 0.2119
# (16: 0.1818, 0.9502, 0.2093), for no byte: four times the base's triangles (Lucy 72,576
# -> 290,304; level 0 draws 1.16 M) and its pure-Python tessellation 0.31 -> 0.68 s of CPU
# (numpy 0.09 -> 0.13 s, load 8). 8 s + 1 and level 0's 16 m + 1 still weld (client_py's
# power-of-2 rule).
BASE_SAMPLES_PER_SPAN = 8


#: the base alone is drawn with at most about this many triangles (base_resolution)
BASE_TRIANGLES = 400_000


def base_resolution(spans: int, patches: int = 1) -> int:
    """Samples per patch side of the base alone: ``r = k s + 1``, ``k =``
    :data:`BASE_SAMPLES_PER_SPAN` per knot span, halved (``r - 1`` halved, so that the
    levels still weld to it) while the ``patches`` drawn so would pass
    :data:`BASE_TRIANGLES` triangles, ``2 F (r - 1)²``, down to ``r = 3``: a smooth base's
    many small patches (``.smooth``: 18,000 patches of 6,000 control triangles) are drawn
    with 2 x 2 quads each, where the patches base's 2,226 keep 8 x 8 (Nefertiti's smooth
    base at 6,000 triangles: RMS 0.1444 at ``r = 3``, 0.1421 at 5, 0.1417 at 9)."""
    r = BASE_SAMPLES_PER_SPAN * spans + 1
    while r > 3 and 2 * patches * (r - 1) ** 2 > BASE_TRIANGLES:
        r = (r - 1) // 2 + 1
    return r


def keeps_every_normal(atlas: AtlasSurface, bits: int, writer: AtlasWriter | None = None
                       ) -> bool:
    """Whether ``base.tsa`` at ``bits``, decoded, still has a normal at every sample the
    client draws the base at (``client_py.atlas_mesh.tessellate_atlas`` refuses a patch
    that the rounding collapsed to a line or a point: a tiny patch, such as a small piece
    of a range scan, whose extent is a few quantisation steps). ``writer``: ``atlas``'s
    when already made (:func:`decoded_base`; its codes at ``bits`` not made again). The
    tessellation's own evaluation and rule without its mesh
    (``client_py.atlas_mesh.patches_without_normal``)."""
    from client_py.atlas_mesh import patches_without_normal

    return not patches_without_normal(decoded_base(atlas, bits, writer),
                                      base_resolution(atlas.spans), kernel="numpy")


def budget_bits(atlas: AtlasSurface, rms: float, bits: int | None, byte_budget: int | None
                ) -> tuple[int, int]:
    """The bits ``base.tsa`` is written at and its size then: ``(bits, bytes)``.

    ``bits`` when given; else :func:`base_bits` of ``rms``, or one to three bits fewer
    (:data:`BUDGET_FEWER_BITS`), the most that keeps the file within ``byte_budget``
    (``None``: no budget, an explicit patch count). A step of up to ``2 BASE_STEP_OVER_RMS``
    RMS raises the base's RMS by about 18 % in quadrature (two bits, up to 4 steps per RMS:
    about 60 %), which the detail levels fitted to the decoded base take back; a base one
    bit over when its RMS just crosses a bit's threshold (Nefertiti, 6 rounds: 0.201 asked
    for 12 bits, 28.8 KB, and 11 bits were 24.7 KB) is not refused for it; missing the
    budget by a few bytes would instead leave the layout with half the patches and about
    twice the RMS (Lucy at 384 triangles: 24,103 bytes).

    Automatic bits are never so few that a patch collapses (:func:`keeps_every_normal`):
    they rise until every patch keeps its normal, and the size then counts against the
    budget like any other (on the Buddha's range scan 0, 8 bits collapsed a patch of a
    small piece of the scan; the base was refused and the fit fell back to a stand-in).
    """
    if bits is not None:
        return bits, atlas_bytes(atlas, bits)
    # each bits encoded once (the 15-scan Buddha: 0.4 s each), the layout once for all
    writer, written = AtlasWriter(atlas), {}

    def file(b: int) -> bytes:
        if b not in written:
            written[b] = base_file(atlas, b, None, writer)
        return written[b]

    chosen = base_bits(atlas, rms)
    while chosen < BASE_BITS[1] and not keeps_every_normal(atlas, chosen, writer):
        chosen += 1
    size = len(file(chosen))
    if byte_budget is None or size <= byte_budget:
        return chosen, size
    for fewer in range(chosen - 1, max(BASE_BITS[0], chosen - BUDGET_FEWER_BITS) - 1, -1):
        coarser = len(file(fewer))
        if coarser <= byte_budget and keeps_every_normal(atlas, fewer, writer):
            return fewer, coarser
    return chosen, size


def ladder_start(plan: list[int], byte_budget: int) -> int:
    """Where ``'auto'``'s ladder of layout sizes ``plan`` starts: the index of the largest
    size whose trial's file is at most half of ``byte_budget`` at
    :data:`AUTO_START_BYTES_PER_TRIANGLE` (an over-estimate of the small trials' bytes), 0
    when none is.

    A smaller layout is chosen by the full ladder only when the start's trial is over the
    budget, or gains less than ``AUTO_MIN_GAIN`` on the smaller ones; ``fit_atlas`` keeps
    the start only when it is within the budget and the next doubling gains on it (two
    trials taken), and otherwise climbs the full ladder (the trials fitted come from its
    cache). The two smallest doublings of Lucy's ladder (48 and 96 triangles: 2,531 and
    4,187 bytes) took 14.6 of its trials' 60 s of CPU.
    """
    fit = [i for i, size in enumerate(plan)
           if 2 * AUTO_START_BYTES_PER_TRIANGLE * size <= byte_budget]
    return fit[-1] if fit else 0


def predicted_trial_bytes(smaller: tuple, larger: tuple, triangles: int,
                          bits: int | None, encoded: dict | None = None
                          ) -> tuple[int, int] | None:
    """The bits and bytes :func:`budget_bits` would give a trial of ``triangles`` layout
    triangles, from two trials fitted (``(rms, bytes, layout, atlas, ...)``, the smaller
    layout first); ``None`` when they have the same size or an RMS of zero (no power law
    through them).

    Each is a power of the triangle count ``T`` through the two trials: the RMS ``r(T)``
    (two rounds of a fit whose error falls as ``T^-a``), and the bytes per control point
    at the bits asked for (a finer layout's control points are predicted closer by
    ``.tsa``'s coder: Lucy's 0.76 times as many bytes each at 9 bits per doubling from 382
    to 756 triangles, 0.75 from 756 to 1,506); the control points scale with ``T``. The
    bits are :func:`base_bits` of ``r(T)`` less :data:`BUDGET_FEWER_BITS` (the fewest
    ``budget_bits`` may give), or ``bits`` when fixed. On Lucy's 1,506-triangle trial
    (from 382 and 756): 9 bits, 32,187 bytes predicted where it was 31,534 at 9 bits.
    ``encoded``: the two files' sizes by ``(atlas id, bits)``, kept between calls (an
    encoding of Lucy's 20,000 control points takes about a second at load 10).
    """
    (rms_a, _, layout_a, atlas_a, *_), (rms_b, _, layout_b, atlas_b, *_) = smaller, larger
    t_a, t_b = layout_a.n_triangles, layout_b.n_triangles
    if t_a == t_b or min(rms_a, rms_b) <= 0:
        return None
    power = math.log(triangles / t_b) / math.log(t_b / t_a)
    rms = rms_b * (rms_b / rms_a) ** power
    if bits is None:
        bits = max(BASE_BITS[0], base_bits(atlas_b, rms) - BUDGET_FEWER_BITS)
    encoded = {} if encoded is None else encoded
    for atlas in (atlas_a, atlas_b):
        if (id(atlas), bits) not in encoded:
            encoded[id(atlas), bits] = atlas_bytes(atlas, bits)
    each_a, each_b = (encoded[id(a), bits] / a.control_point_count for a in (atlas_a, atlas_b))
    count = atlas_b.control_point_count * triangles / t_b
    return bits, round(count * each_b * (each_b / each_a) ** power)


def final_within_budget(accepted: list[tuple], trials: list[dict], points: np.ndarray,
                        normals: np.ndarray, *, bits: int | None, byte_budget: int,
                        **fit_options) -> tuple:
    """The final fit of ``'auto'``: the chosen trial's layout fitted again with every
    working point and every round, written within ``byte_budget``; when its file is not, the
    layout of the trial taken before it, and so on down to the smallest.

    ``accepted``: the tuples ``(rms, bytes, layout, atlas, f, u, v, timings, bits)`` of the
    trials taken as the best, the smallest layout first; ``trials``: the trials' records,
    where a refused final fit is noted (``final_bytes``, ``final_bits``) in the record of
    its layout. The final fit's lower RMS may ask for more bits than its trial had
    (:func:`base_bits`), more than :data:`BUDGET_FEWER_BITS` can give back, or its control
    points may simply cost a few bytes more at the same bits: its trial passed the budget,
    the final base would not. The smaller layout passed its own trial with room to spare
    (it was taken before a larger one that also passed); the smallest is kept whatever its
    size (the budget cannot be met by any layout tried).

    Returns
    -------
    (rms, bytes, layout, atlas, f, u, v, timings, bits) of the final fit.
    """
    for number in range(len(accepted) - 1, -1, -1):
        layout = accepted[number][2]
        final_timings: dict = {"layout": accepted[number][7]["layout"]}
        atlas, f, u, v, dist = fit_layout(layout, points, normals, timings=final_timings,
                                          **fit_options)
        rms = float(np.sqrt(np.mean(dist ** 2)))
        final_bits, size = budget_bits(atlas, rms, bits, byte_budget)
        if size <= byte_budget or number == 0:
            return rms, size, layout, atlas, f, u, v, final_timings, final_bits
        for trial in trials:  # the record of this layout's trial says why it was not kept
            if trial.get("triangles") == layout.n_triangles and "bytes" in trial \
                    and "final_bytes" not in trial:
                trial.update(final_bytes=size, final_bits=final_bits)
                break
    raise AssertionError("unreachable")  # the smallest layout returns


ROUND_SWEEPS = 4  # Gauss-Seidel sweeps of grid_codes (fewer once none moves)
ROUND_RATE = 0.0  # grid_codes' weight on moving a code, in step² times the median H_ii
# fed_back_atlas's extra weight on the working points' offsets across the surface (their
# full offsets weigh 1). 0: point to point, the fit's own objective. Across the surface
# alone, with a tenth of the offset along it (10 here, scaled), the base came out 2-6 %
# nearer its scan points than point to point on all five objects, but level 0 drew Lucy's
# and the Bali mask's largest distance beyond 1 % of the diagonal (1.00 and 1.16 %;
# docs/benchmarks.md, session 15): not the default.
ROUND_ACROSS = 0.0


def grid_codes(H: sp.csr_matrix, rhs: np.ndarray, x: np.ndarray, codes: np.ndarray,
               lo: np.ndarray, step: np.ndarray, fixed: np.ndarray | None = None,
               sweeps: int = ROUND_SWEEPS, rate: float = 0.0,
               colour: np.ndarray | None = None, top: int | None = None) -> np.ndarray:
    """Integer codes ``q`` (the shape of ``x``) of the values ``lo + step q`` that lower
    the quadratic ``J(p) = pᵀ H p - 2 rhsᵀ p`` of the ``M`` values ``p`` (``x`` and the
    rest read flat, in C order; ``lo``, ``step`` broadcast to ``x``) from its value at
    ``codes``, each code within ``[floor, ceil]`` of ``(x - lo) / step`` (or at its own
    ``codes`` value, when that is outside: a corner the writer rounded apart).

    Fed back by :func:`atlas.lattice.lattice_descent` (Gauss-Seidel on the lattice, one
    colour at a time, ``colour (M,)`` default :func:`coupling_colours` of ``H``; the
    formulas and references are there): each move lowers ``J`` or keeps it, so the result
    is never worse than ``codes``. ``fixed`` of bool: codes not moved. ``top``: codes
    stay within ``0..top`` (the file's grid). ``rate``: ``J + λ Σ
    |q - codes|``, ``λ = rate step²`` times the median ``H_ii`` (a soft threshold toward
    the code a value started from: fewer moves, fewer bytes). At most ``sweeps`` sweeps,
    fewer once none moves; ``sweeps = 0`` returns ``codes``. The detail coefficients are
    rounded by the same descent (``atlas.detail.quantised_blocks``).
    """
    shape = np.shape(x)
    x = np.asarray(x, np.float64).reshape(-1)
    lo = np.broadcast_to(lo, shape).reshape(-1)
    step = np.broadcast_to(step, shape).reshape(-1)
    q = np.asarray(codes, np.int64).reshape(-1)
    t = (x - lo) / step
    low = np.minimum(np.floor(t), q)
    high = np.maximum(np.ceil(t), q)
    if top is not None:  # the grid's codes: a value at its top bound can be top + 3e-14 steps
        low, high = np.clip(low, 0, top), np.clip(high, 0, top)
    if fixed is not None:
        fixed = np.asarray(fixed, bool).reshape(-1)
        low = np.where(fixed, q, low)
        high = np.where(fixed, q, high)
    H = sp.csr_matrix(H)
    diag = H.diagonal()
    colour = coupling_colours(H) if colour is None else colour
    shrink = None
    if rate > 0:  # λ = rate step² median H_ii, in steps λ / (2 H_ii step²)
        inside = diag[diag > 0]
        lam = rate * float(np.median(inside)) if len(inside) else 0.0
        shrink = lam / (2.0 * np.maximum(diag, 1e-300))
    return lattice_descent(H, rhs, q, lo, step, low, high, colour, sweeps,
                           shrink).reshape(shape)


def _put_back(q: np.ndarray, plain: np.ndarray,
              offenders: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """``q (N, 3)`` with the points ``offenders(q)`` names (indices) put back to their
    ``plain`` codes, again until it names none that differs from ``plain``."""
    q = q.copy()
    for _ in range(len(q)):
        back = offenders(q)
        back = back[np.any(q[back] != plain[back], axis=1)]
        if not len(back):
            break
        q[back] = plain[back]
    return q


def _corners_together(quads: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """``offenders`` of :func:`_put_back`: both corners of every patch side or diagonal
    that codes ``q`` make one point on all three axes (the writer keeps the plain codes of
    a patch's corners apart, ``client_py.atlas_format.keep_corners_apart``)."""
    pairs = np.array([(a, b) for a in range(4) for b in range(a + 1, 4)])
    ends = np.asarray(quads)[:, pairs].reshape(-1, 2)
    ends = ends[ends[:, 0] != ends[:, 1]]
    return lambda q: np.unique(ends[np.all(q[ends[:, 0]] == q[ends[:, 1]], axis=1)])


PLEAT_COSINE = -0.5  # ... two triangles of a patch folded over each other: n1 . n2 below this


def pleated_patches(table: np.ndarray, points: np.ndarray, degree: int, spans: int,
                    resolution: int | None = None) -> np.ndarray:
    """Patches of which two triangles sharing an edge fold over each other,
    ``n_1 · n_2 <`` :data:`PLEAT_COSINE` (more than 120° apart), with the patch drawn on a
    ``resolution²`` grid (default :func:`base_resolution`, the grid the base is drawn on)
    whose cells are cut as the client cuts them
    (``client_py.tessellate.grid_indices``: along the diagonal from ``(u + h, v)`` to
    ``(u, v + h)``): the pleats ``bench.pleats`` counts on the drawn base. Returns
    ``pleated (F,)`` of bool."""
    r, n_f = resolution or base_resolution(spans), len(table)
    t = np.linspace(0.0, 1.0, r)
    f = np.repeat(np.arange(n_f), r * r)
    (c,) = evaluate_patches(table, points, degree, spans, f, np.tile(np.repeat(t, r), n_f),
                            np.tile(np.tile(t, r), n_f))
    g = c.reshape(n_f, r, r, 3)  # g[f, a, b]: a along u
    p00, p10, p01, p11 = g[:, :-1, :-1], g[:, 1:, :-1], g[:, :-1, 1:], g[:, 1:, 1:]
    n0 = np.cross(p10 - p00, p01 - p00)  # the cell's triangles (p00, p10, p01), (p01, p10, p11)
    n1 = np.cross(p10 - p01, p11 - p01)
    n0 /= np.maximum(np.linalg.norm(n0, axis=-1, keepdims=True), 1e-300)
    n1 /= np.maximum(np.linalg.norm(n1, axis=-1, keepdims=True), 1e-300)

    def folded(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return (np.einsum("f...c,f...c->f...", a, b) < PLEAT_COSINE).reshape(n_f, -1).any(axis=1)

    # across the cell's diagonal, and the second triangle's sides p10-p11 and p01-p11 (the
    # first triangles of the cells after it along u and along v)
    return folded(n0, n1) | folded(n1[:, :-1], n0[:, 1:]) | folded(n1[:, :, :-1], n0[:, :, 1:])


def _newly_pleated(plain: np.ndarray, table: np.ndarray, lo: np.ndarray, step: np.ndarray,
                   degree: int, spans: int) -> Callable[[np.ndarray], np.ndarray]:
    """``offenders`` of :func:`_put_back`: the control nets of the patches that codes ``q``
    pleat and the ``plain`` ones do not (:func:`pleated_patches`; a net put back shares its
    border rows, so its neighbours are tested again)."""
    before = pleated_patches(table, lo + step * plain, degree, spans)
    return lambda q: np.unique(table[pleated_patches(table, lo + step * q, degree, spans)
                                     & ~before])


def fed_back_atlas(atlas: AtlasSurface, bits: int, layout: QuadLayout, points: np.ndarray,
                   f: np.ndarray, u: np.ndarray, v: np.ndarray, *, smoothing: float,
                   anchor: float, border: np.ndarray | None = None,
                   scan_mesh: tuple[np.ndarray, np.ndarray] | None = None,
                   reverse_weight: float = REVERSE_WEIGHT, sweeps: int = ROUND_SWEEPS,
                   rate: float | None = None, tangential: bool = True) -> AtlasSurface:
    """``atlas`` with its control points on ``base.tsa``'s grid at ``bits``, rounded with
    the error fed back: the file's codes of the points (``write_atlas``: to nearest, a
    patch's corners kept apart) moved by :func:`grid_codes` to lower the last round's
    objective of :func:`fit_layout`, ``|A P - X|² + λ |L P|² + μ |P - P_0|²`` with the rows
    of :func:`round_rows` at the final foot points ``(f, u, v)`` (``smoothing``, ``anchor``,
    ``border``, ``scan_mesh``, ``reverse_weight``: the fit's), plus ``c Σ_k (n_k · r_k)²``
    over the working points, ``r_k = (A P - X)_k``, ``n_k`` the unit normal at the foot
    point, ``c =`` :data:`ROUND_ACROSS` (0 by default): the drawn distance sees the offset
    across the surface, not the foot point's slide along it (Pottmann and Hofer's
    squared-distance approximation with the curvature term dropped). The ``3 N`` values
    are one vector (the three axes of a point are coupled when ``c > 0``), coloured by the
    points' colours times the axis. On main 90503fb's Nefertiti: rounded to nearest 0.1919
    at 21,877 bytes (unrounded 0.1659), ``c = 0`` 0.1784 at 22,810, ``c = 10`` with
    ``0.1 |r|²`` in place of ``|r|²`` 0.1697 at 22,207 (RMS of all points).
    ``write_atlas(result, bits)`` writes these codes (the grid is the points' bounds over
    ``2^bits - 1`` steps, and the points at the bounds are not moved). With
    :data:`BASE_TANGENT_FACTOR` (version 4) the codes are chosen in the file's local frames
    instead (:func:`frame_fed_back`; ``tangential=False``: the codes along the surface
    held at nearest), and :func:`base_file` writes them."""
    from client_py.atlas_format import file_codes

    degree, spans = atlas.degree, atlas.spans
    table = index_table(atlas)
    x = control_points(atlas)
    H, rhs, per_axis = _rounding_objective(atlas, table, x, layout, points, f, u, v,
                                           smoothing, anchor, border, scan_mesh,
                                           reverse_weight)
    rate = ROUND_RATE if rate is None else rate
    if BASE_TANGENT_FACTOR is not None:
        return frame_fed_back(atlas, bits, BASE_TANGENT_FACTOR, H, rhs, sweeps, rate,
                              tangential)
    lo, hi = x.min(axis=0), x.max(axis=0)
    top = (1 << bits) - 1
    step = np.where(hi > lo, (hi - lo) / top, 1.0)
    # the writer's codes, which do not depend on the file's numbering of the points
    plain = np.array(file_codes(x.T.tolist(), lo.tolist(), hi.tolist(), bits, atlas.quads),
                     np.int64).T
    fixed = np.zeros_like(plain, bool)
    fixed[x.argmin(axis=0), np.arange(3)] = True
    fixed[x.argmax(axis=0), np.arange(3)] = True
    colour = (3 * coupling_colours(per_axis)[:, None] + np.arange(3)).reshape(-1)
    q = grid_codes(H, rhs, x, plain, lo, step, fixed, sweeps, rate, colour, top)
    together = _corners_together(np.asarray(atlas.quads))
    pleated = _newly_pleated(plain, table, lo, step, degree, spans)
    q = _put_back(q, plain, lambda q: np.union1d(together(q), pleated(q)))
    return with_control_points(atlas, lo + step * q)


def _rounding_objective(atlas: AtlasSurface, table: np.ndarray, x: np.ndarray,
                        layout: QuadLayout, points: np.ndarray, f: np.ndarray,
                        u: np.ndarray, v: np.ndarray, smoothing: float, anchor: float,
                        border: np.ndarray | None, scan_mesh: tuple | None,
                        reverse_weight: float) -> tuple[sp.csr_matrix, np.ndarray,
                                                        sp.csr_matrix]:
    """:func:`fed_back_atlas`'s quadratic ``J(p) = pᵀ H p - 2 rhsᵀ p`` over the ``3 N``
    values ``p`` (point ``j``'s axis ``a`` at ``3 j + a``): ``(H, rhs, per_axis)``, the
    last the ``N × N`` matrix each axis has alone."""
    degree, spans = atlas.degree, atlas.spans
    initial = bilinear_atlas(layout, degree, spans)
    nb = neighbour_table(atlas)
    border = np.empty((0, 3)) if border is None else np.asarray(border, np.float64)
    reach = BORDER_REACH * float(np.linalg.norm(np.ptp(points, axis=0)))
    A, targets, _ = round_rows(table, x, degree, spans, nb, points, f, u, v, border, reach,
                               scan_mesh, reverse_weight)
    L = smoothing_matrix(atlas, table)
    k = len(points)
    lam, mu = regularisation_weights(A[:k], L, smoothing, anchor)
    per_axis = (A.T @ A + lam * (L.T @ L) + mu * sp.identity(len(x), format="csr")).tocsr()
    H = sp.kron(per_axis, sp.identity(3)).tocsr()
    rhs = (A.T @ targets + mu * control_points(initial)).reshape(-1)
    if ROUND_ACROSS > 0:
        # the working points across the surface: n_k · (A P - X)_k, n_k the unit normal at
        # the foot point, one row over the 3 N values P flattened (3 j + axis)
        _, du, dv = evaluate_patches(table, x, degree, spans, f, u, v, True)
        n = np.cross(du, dv)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        coo = A[:k].tocoo()
        across = sp.csr_matrix(((coo.data[:, None] * n[coo.row]).reshape(-1),
                                (np.repeat(coo.row, 3), (3 * coo.col[:, None] + np.arange(3))
                                 .reshape(-1))), shape=(k, 3 * len(x)))
        H = (H + ROUND_ACROSS * (across.T @ across)).tocsr()
        rhs = rhs + ROUND_ACROSS * (across.T @ np.einsum("kc,kc->k", n, targets[:k]))
    return H, rhs, per_axis


def _block_codes(H: sp.csr_matrix, rhs: np.ndarray, p: np.ndarray, at: np.ndarray,
                 offset: np.ndarray, frame: np.ndarray, start: np.ndarray,
                 fixed: np.ndarray, sweeps: int, rate: float,
                 top: int | None = None) -> np.ndarray:
    """:func:`grid_codes` of the points ``at`` alone, every other point held at ``p (N,
    3)``: point ``k = at[i]`` is ``offset_i + frame_i c_i`` (``frame (n, 3, 3)``, its
    columns the steps of the codes ``c_i``), so ``J`` restricted to them is ``cᵀ (Mᵀ
    H_II M) c - 2 (Mᵀ (rhs_I - H_I· p' - H_II offset))ᵀ c`` with ``M`` the block
    diagonal of the frames, ``I`` their values and ``p'`` the others. ``start (n, 3)``:
    the codes to start from, ``fixed (n, 3)`` of bool not moved; ``x`` of the descent the
    points' ``p`` in codes, ``M⁻¹ (p_I - offset)``. Returns the codes ``(n, 3)``."""
    values = (3 * at[:, None] + np.arange(3)).reshape(-1)
    rows = H[values]
    held = p.reshape(-1).copy()
    held[values] = 0.0
    m = len(at)
    M = sp.csr_matrix((frame.reshape(-1), (np.repeat(np.arange(3 * m), 3),
                                           np.tile(np.arange(3), 3 * m)
                                           + 3 * np.repeat(np.arange(m), 9))),
                      shape=(3 * m, 3 * m))
    H_II = rows[:, values]
    Hc = (M.T @ H_II @ M).tocsr()
    rc = M.T @ (rhs[values] - rows @ held - H_II @ offset.reshape(-1))
    x = np.linalg.solve(frame, (p[at] - offset)[..., None])[..., 0]
    return grid_codes(Hc, rc, x, start, 0.0, 1.0, fixed, sweeps, rate, None, top)


#: :func:`frame_fed_back`'s passes at most. Each pass holds at least one more patch, so the
#: patch count bounds them too (2,082-2,346 on the benchmark's objects), but each costs the
#: three stages' Gauss-Seidel sweeps over every point (1-8 s a pass on those bases at load
#: 13-20): twice the most the benchmark's objects take (2-4 passes on main c092ebc,
#: docs/benchmarks.md, session 17, w27-tidy)
PLEAT_PASSES = 8


def frame_fed_back(atlas: AtlasSurface, bits: int, factor: float, H: sp.csr_matrix,
                   rhs: np.ndarray, sweeps: int = ROUND_SWEEPS, rate: float = 0.0,
                   tangential: bool = True) -> AtlasSurface:
    """:func:`fed_back_atlas` for a version 4 ``base.tsa`` (``client_py.atlas_format.
    FrameCoder``, tangential step ``factor`` times the normal one): the codes chosen as
    the file decodes them, the layout vertices on the grid first (the extremes held, a
    patch's corners kept apart as :func:`_corners_together`), then the edge points'
    frame codes given the decoded vertices (their frames and predictions are made from
    them), then the patch interiors' given the decoded borders, each stage by
    :func:`_block_codes` with the points after it at their fitted place. A patch the
    codes pleat (:func:`pleated_patches`) and the writer's own codes (nearest) do not has
    all its points held at nearest, and the stages run again, until none is left (or
    each is held already: its neighbours' vertices still shape its edges' frames), for
    at most :data:`PLEAT_PASSES` passes: a base still pleated after them is returned as
    it was (``atlas``: the writer rounds it to nearest, which adds no pleat)."""
    from client_py.atlas_format import FrameCoder, _Predictor, frame_codes, frame_steps

    x = control_points(atlas)
    n_v, n_e = len(atlas.vertices), len(atlas.vertices) + len(atlas.edge_points)
    lo, hi = x[:n_v].min(axis=0), x[:n_v].max(axis=0)
    top = (1 << bits) - 1
    step = np.where(hi > lo, (hi - lo) / top, 1.0)  # a flat axis: every code 0
    predictor = _Predictor(atlas.quads, atlas.edges, atlas.side, n_v, bits)
    steps = frame_steps(lo.tolist(), hi.tolist(), bits, factor)
    coder = FrameCoder(predictor, atlas.quads, atlas.edges, steps)
    scale = np.array([steps[0], steps[1], steps[1]])
    plain = np.array(frame_codes(predictor, atlas.quads, atlas.edges, x.T.tolist(),
                                 lo.tolist(), hi.tolist(), bits, factor), np.int64).T
    table = index_table(atlas)
    together = _corners_together(np.asarray(atlas.quads))

    def decoded(codes: np.ndarray) -> np.ndarray:
        vertex_axes = (lo + step * codes[:n_v]).T.tolist()
        return np.array(coder.decode(vertex_axes, codes.T.tolist())).T

    before = pleated_patches(table, decoded(plain), atlas.degree, atlas.spans)
    extremes = np.zeros((n_v, 3), bool)
    extremes[x[:n_v].argmin(axis=0), np.arange(3)] = True
    extremes[x[:n_v].argmax(axis=0), np.arange(3)] = True
    held = np.zeros(len(x), bool)
    fitted = x.T.tolist()
    for _ in range(PLEAT_PASSES):
        p = x.copy()
        q = np.empty_like(plain)
        q[:n_v] = _block_codes(H, rhs, p, np.arange(n_v), np.broadcast_to(lo, (n_v, 3)),
                               np.broadcast_to(np.diag(step), (n_v, 3, 3)), plain[:n_v],
                               extremes | held[:n_v, None], sweeps, rate, top)
        q[:n_v] = _put_back(q[:n_v], plain[:n_v], together)
        p[:n_v] = lo + step * q[:n_v]
        axes = p.T.tolist()
        frame_rows = coder.frames(p[:n_v].tolist())
        frames = np.array(frame_rows).reshape(-1, 3, 3)  # frames[k, j]: axis j (n, t1, t2)
        for start, stop in ((n_v, n_e), (n_e, len(x))):
            predicted = coder.predictions(axes, start >= n_e)  # from the points before start
            pred = np.array(predicted).T
            frame = frames[start - n_v:stop - n_v].transpose(0, 2, 1) * scale
            nearest = [list(c) for c in q.T.tolist()]  # as the writer rounds: its own rule
            coder.place([list(a) for a in axes], frame_rows, start, stop, nearest, fitted,
                        predicted)
            near = np.array(nearest, np.int64).T[start:stop]
            keep = held[start:stop, None] | np.array([False, not tangential, not tangential])
            q[start:stop] = _block_codes(H, rhs, p, np.arange(start, stop), pred, frame,
                                         near, keep, sweeps, rate)
            coder.place(axes, frame_rows, start, stop, q.T.tolist(), None, predicted)
            p[start:stop] = np.array(axes).T[start:stop]
        pleats = np.flatnonzero(pleated_patches(table, p, atlas.degree, atlas.spans)
                                & ~before)
        if not len(pleats) or held[np.unique(table[pleats])].all():
            return with_control_points(atlas, p)
        held[np.unique(table[pleats])] = True
    return atlas  # still pleated: rounded to nearest by the writer, as before the feedback


ROUND_RATES = (0.0, 1.0, 4.0)  # within_budget_fed_back's rates, tried in turn


def within_budget_fed_back(atlas: AtlasSurface, size: int, bits: int, byte_budget: int | None,
                           layout: QuadLayout, points: np.ndarray, f: np.ndarray,
                           u: np.ndarray, v: np.ndarray, **options) -> tuple[AtlasSurface, int]:
    """The fitted base rounded for ``base.tsa`` with the error fed back
    (:func:`fed_back_atlas`, ``options`` its keywords) and that file's bytes: at the first
    rate of :data:`ROUND_RATES` whose file stays within ``byte_budget`` (``None``: no
    budget) or within ``size``, the bytes of the file rounded to nearest; else, or when
    the moved codes collapse a patch the client draws (:func:`keeps_every_normal`),
    ``atlas`` and ``size`` as they were (``write_atlas`` rounds it to nearest).

    Fed back, the codes are less smooth than rounded ones and their residuals cost more:
    on main 90503fb's bases (9, 8 and 9 bits) Nefertiti's, Lucy's and Laurana's
    ``base.tsa`` grew 1.5 %, 1.0 % and 2.2 % (RMS of all points 0.1919 -> 0.1697, 1.038 ->
    0.931, 0.2298 -> 0.2079; unrounded 0.1659, 0.930, 0.2048: w25-baserd), where a bit more
    costs 24 % for less (docs/benchmarks.md, session 15); a base the fit filled up to the
    budget takes a rate instead.
    """
    limit = max(size, byte_budget) if byte_budget is not None else None
    # version 4: every frame code fed back, else the codes across the surface alone (a
    # rate spends the error where v4's tangential codes would spare it: docs/benchmarks.md)
    modes = ([{"rate": rate} for rate in ROUND_RATES] if BASE_TANGENT_FACTOR is None
             else [{"rate": 0.0}, {"rate": 0.0, "tangential": False}])
    for mode in modes:
        rounded = fed_back_atlas(atlas, bits, layout, points, f, u, v, **mode, **options)
        writer = AtlasWriter(rounded)
        data = base_file(rounded, bits, None, writer)
        if limit is not None and len(data) > limit:
            continue
        # moved codes must not collapse a patch the client draws, as budget_bits' do not
        return ((rounded, len(data)) if keeps_every_normal(rounded, bits, writer)
                else (atlas, size))
    return atlas, size


def _check_arguments(patches: object, degree: object, spans: object, bits: object,
                     byte_budget: object, working_count: object, rounds: object) -> None:
    if not (patches == "auto" or (isinstance(patches, int) and not isinstance(patches, bool)
                                  and 3 <= patches <= MAX_PATCHES)):
        raise ValueError(f"patches must be 'auto' or an int in 3..{MAX_PATCHES} "
                         f"(three quads per layout triangle), got {patches!r}; one patch is "
                         "the single-patch fit (fit_scan)")
    for name, value, lo, hi in (("degree", degree, 1, 3), ("spans", spans, 1, 4),
                                ("bits", 12 if bits is None else bits, 8, 24),
                                ("rounds", rounds, 1, 20),
                                ("working_points", working_count, 1000, 2_000_000)):
        if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
            raise ValueError(f"{name} must be an int in {lo}..{hi}, got {value!r}")
    if isinstance(byte_budget, bool) or not isinstance(byte_budget, int) or byte_budget < 500:
        raise ValueError(f"byte_budget must be an int >= 500, got {byte_budget!r}")


def fit_atlas(scan: Scan, patches: int | str = "auto", *, degree: int = 3, spans: int = 1,
              bits: int | None = 12, byte_budget: int = DEFAULT_BYTE_BUDGET,
              working_count: int = 60_000, rounds: int = 6, smoothing: float = 0.1,
              anchor: float = 1e-3, thin_parts: bool = True,
              progress: Callable[[float], None] | None = None,
              surface: ScanSurface | None = None,
              layout_surface: ScanSurface | None = None,
              trial_cache: dict | None = None) -> AtlasFit:
    """Fit a whole object as an atlas of ``F = 3 T`` bicubic patches on a quad layout.

    Parameters
    ----------
    scan : Scan
        A mesh (its triangles are the surface) or a point cloud (screened Poisson).
    patches : 'auto' or int
        ``int``: about that many patches (``T = round(patches / 3)`` layout triangles; the
        decimation may end a few triangles off). ``'auto'``: ``T`` doubles from
        ``AUTO_FIRST_TRIANGLES`` while the file stays within ``byte_budget``, and the
        largest ``T`` whose working points' RMS is below ``AUTO_MIN_GAIN`` of the best of
        the smaller ones is taken (trials: ``AUTO_TRIAL_POINTS`` of the points, two rounds;
        one doubling that gains nothing does not end the search: the next may); the chosen
        layout is then fitted with all working points and ``rounds``, within the budget
        (:func:`final_within_budget`: else the layout taken before it). The ladder starts
        at :func:`ladder_start` (from ``AUTO_FIRST_TRIANGLES`` again when that start is
        over the budget or the next doubling gains nothing on it), and a doubling
        predicted over ``AUTO_SKIP_OVER_BUDGET`` budgets (:func:`predicted_trial_bytes`)
        is not fitted: ``trials`` records it as ``skipped``.
    degree, spans : int
        Per patch side (``n = spans + degree`` control points).
    bits : int or None
        Quantisation of the ``.tsa`` the bytes are counted for; ``None``: :func:`base_bits`
        of each trial's RMS.
    byte_budget : int
        Largest ``.tsa`` size ``'auto'`` accepts.
    working_count : int
        Scan points kept by voxel thinning (plus half as many triangle samples for a mesh).
    rounds : int
        Solve + parameter-correction rounds.
    smoothing, anchor : float
        ``λ`` and ``μ`` relative to the data term (:func:`regularisation_weights`). On the
        bunny (T = 250) and a sphere, ``smoothing = 0.1`` halved the RMS and cut the largest
        deviation 7x against ``0.01``: a stiffer net keeps foot points from sliding off a
        patch's border and leaving it unsupported. ``spans = 1`` at the same ``T`` cost
        10 % more RMS than 2 spans for 35 % fewer bytes.
    thin_parts : bool
        Also fit, at every trial, the layout decimated with
        :func:`.layout.thin_part_weights` (sheets thinner than a layout triangle keep
        triangles of their own) and keep whichever of it and the plain one has the lower
        trial RMS (:func:`layout_candidates`; ``trials[i]["layout"]`` names it). The
        weighted layout took the base's share of the points within 0.5 % of the diagonal
        from 95.7 % to 99.5 % on the bunny and 96.4 % to 97.9 % on Lucy at 576 patches, but
        starved Laurana's bust (its thin base rim drew triangles from the face).
    progress : callable(float), optional
        Called with the fraction done, 0..1.
    surface : ScanSurface, optional
        The scan's surface when already built (:func:`scan_surface`).
    layout_surface : ScanSurface, optional
        The surface the layout is decimated from, when not ``surface`` itself: a stand-in
        with the small handles closed (``atlas.surface.layout_stand_in``); the working
        points and their normals still come from ``surface``.
    trial_cache : dict, optional
        Trials kept between calls with the same ``scan``, ``surface``, ``layout_surface``
        and fit parameters, which differ only in ``byte_budget`` (a refit with a larger
        budget after a refusal): a target already tried is not decimated and fitted again
        (the same numbers). Filled by this call.

    Returns
    -------
    AtlasFit

    Raises
    ------
    ValueError
        An argument out of its range (named).
    SurfaceError, AtlasLayoutError, AtlasFitError
        A scan without a usable surface, layout or fit.
    """
    _check_arguments(patches, degree, spans, bits, byte_budget, working_count, rounds)
    for name, value in (("smoothing", smoothing), ("anchor", anchor)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not math.isfinite(value) or value <= 0:
            raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    report = progress or (lambda fraction: None)
    timings: dict = {}
    clock = time.perf_counter()
    if surface is None:
        surface = scan_surface(scan)
    # a cloud's fits are warm-started more gently (cloud_warm)
    warm = cloud_warm() if surface.origin != "mesh" else {}
    timings["surface"] = time.perf_counter() - clock
    report(0.15)
    clock = time.perf_counter()
    points, normals = working_points(scan, surface, working_count)
    timings["points"] = time.perf_counter() - clock
    if len(points) < 16:
        raise AtlasFitError(f"only {len(points)} working points; at least 16 are needed")
    report(0.2)
    clock = time.perf_counter()
    # every trial decimates from one intermediate mesh, not from the full scan (MeshLab's
    # collapse of 10^5 faces takes seconds each time). It may keep triangles without area,
    # which the trials' layouts may not: a working mesh of Stanford Lucy subdivided to
    # 3.2 M vertices left 2 at 20,000 triangles, and each of its trials then decimated the
    # whole 1.6 M triangles again, 52-56 s a trial
    source = surface if layout_surface is None else layout_surface
    # the open border curves follow the scan's border; a stand-in's borders are its own
    overshoot = (BORDER_OVERSHOOT * median_edge(surface.vertices, surface.faces)
                 if BORDER_OVERSHOOT else 0.0)
    border = (border_points(surface.vertices, surface.faces, overshoot)
              if layout_surface is None else None)
    scan_mesh = (surface.vertices, surface.faces)
    coarse = source
    if len(source.faces) > PREDECIMATED_TRIANGLES:
        try:
            vertices, triangles = (decimate_on_border if border is not None else decimate)(
                source, PREDECIMATED_TRIANGLES, require_area=False)
            coarse = ScanSurface(vertices, triangles, source.origin, source.pieces,
                                 source.repairs)
        except (AtlasLayoutError, SurfaceError):
            coarse = source  # every trial decimates from the full surface instead
    timings["predecimate"] = time.perf_counter() - clock
    auto = patches == "auto"
    if auto:
        plan = []
        t = AUTO_FIRST_TRIANGLES
        while t <= min(AUTO_MAX_TRIANGLES, len(coarse.faces)):
            plan.append(t)
            t *= 2
        plan = plan or [len(coarse.faces)]
        # trials on a subset, two rounds; the chosen layout is fitted again with everything
        pick = np.random.default_rng(0).permutation(len(points))[:AUTO_TRIAL_POINTS]
        trial_points, trial_normals, trial_rounds = points[pick], normals[pick], 2
    else:
        plan = [max(1, round(int(patches) / 3))]
        trial_points, trial_normals, trial_rounds = points, normals, rounds
    cache = {} if trial_cache is None else trial_cache

    def run_trial(target: int, best: tuple | None) -> tuple[dict | None, tuple | None]:
        """The trial of ``target`` triangles: its record (``None``: the decimation stopped
        at the best's size, nothing new to judge) and ``(rms, bytes, layout, atlas, f, u,
        v, timings, bits)`` of its lower-RMS layout (``None``: no layout decimated)."""
        if ("layouts", target) not in cache:
            cache["layouts", target] = layout_candidates(coarse, max(4, target), thin_parts,
                                                      border is not None)
        candidates, failures = cache["layouts", target]
        if not candidates:
            # a coarse target may not decimate to a manifold (a range scan's many borders);
            # 'auto' tries the next size, an explicit count is refused
            if not auto:
                raise failures[0][1]
            return {"triangles": target,
                    "error": "; ".join(str(exc) for _, exc in failures)}, None
        # the decimation may stop short of the target: no new size to judge then
        judged = [c for c in candidates
                  if best is None or c[1].n_triangles > best[2].n_triangles]

        def fit_trial(candidate: tuple[str, QuadLayout, float]) -> tuple:
            name, layout, layout_seconds = candidate
            trial_timings: dict = {"layout": layout_seconds}
            return (*fit_layout(layout, trial_points, trial_normals, degree=degree,
                                spans=spans, rounds=trial_rounds, smoothing=smoothing,
                                anchor=anchor, border=border, scan_mesh=scan_mesh,
                                timings=trial_timings, **warm), trial_timings)

        # the candidates' fits are independent: fitted at once (fit_layout's solves and
        # closest points release the GIL), the same numbers as one after the other
        new = [c for c in judged if ("fit", target, c[0]) not in cache]
        done = on_threads(lambda i, new=new: fit_trial(new[i]), len(new), 1, LAYOUT_THREADS)
        for c, made in zip(new, done, strict=True):
            cache["fit", target, c[0]] = made
        fitted = []
        for name, layout, _ in judged:
            atlas, f, u, v, dist, trial_timings = cache["fit", target, name]
            fitted.append((float(np.sqrt(np.mean(dist ** 2))), name, layout, atlas, f, u, v,
                           trial_timings))
        if not fitted:
            return None, None
        # one rule for the layout: of the plain and the thin-part-weighted decimation, the
        # one whose trial RMS is lower (the weights help a thin sheet, the bunny's ears, and
        # can starve the rest where few vertices are thin, Laurana's cut base)
        rms, name, layout, atlas, f, u, v, trial_timings = min(fitted, key=lambda c: c[0])
        trial_bits, size = budget_bits(atlas, rms, bits, byte_budget if auto else None)
        record = {"triangles": layout.n_triangles, "patches": len(atlas.quads),
                  "control_points": atlas.control_point_count, "bytes": size,
                  "bits": trial_bits, "rms": rms, "layout": name,
                  "rms_by_layout": {c[1]: c[0] for c in fitted},
                  "seconds_by_layout": {c[1]: sum(c[7].values()) for c in fitted},
                  "seconds": sum(sum(c[7].values()) for c in fitted)}
        return record, (rms, size, layout, atlas, f, u, v, trial_timings, trial_bits)

    def ladder(first: int) -> tuple[list[dict], list[tuple], tuple | None]:
        """The trials from ``plan[first]`` up (``'auto'``: to the first over the budget,
        fitted or predicted): ``(records, accepted, best)``. (A further trial between the
        largest within the budget and the first over it was measured in session 17 and
        dropped: it took the Bali mask's largest mesh->scan distance from 0.89 to 1.46 %
        of the diagonal, docs/benchmarks.md.)"""
        trials: list[dict] = []
        accepted: list[tuple] = []  # every trial taken as the best, the smallest first
        best, fitted, encoded = None, [], {}
        for step, target in enumerate(plan[first:], first):
            if auto and len(fitted) >= 2:
                predicted = predicted_trial_bytes(fitted[-2], fitted[-1], target, bits,
                                                  encoded)
                if predicted is not None and predicted[1] > AUTO_SKIP_OVER_BUDGET * byte_budget:
                    trials.append({"triangles": target, "skipped": "predicted over the budget",
                                   "predicted_bits": predicted[0],
                                   "predicted_bytes": predicted[1]})
                    break
            record, made = run_trial(target, best)
            report(0.2 + 0.7 * (step + 1) / len(plan))
            if record is not None:
                trials.append(record)
            if made is None:
                continue
            fitted.append(made)
            encoded[id(made[3]), made[8]] = made[1]  # its file's bytes, not encoded again
            rms, size = made[:2]
            if auto and best is not None and size > byte_budget:
                break
            if best is None or rms <= AUTO_MIN_GAIN * best[0]:
                best = made
                accepted.append(best)
            if auto and size > byte_budget:
                break
        return trials, accepted, best

    first = ladder_start(plan, byte_budget) if auto else 0
    trials, accepted, best = ladder(first)
    if first > 0 and len(accepted) < 2:
        # the start's own gain over the smaller layouts is judged only by the full ladder
        # (the trials already fitted come from the cache)
        trials, accepted, best = ladder(0)
    if best is None:
        raise AtlasLayoutError(f"no layout of {plan} triangles is an oriented 2-manifold: "
                               + "; ".join(trial["error"] for trial in trials))
    if auto:
        timings["trials"] = sum(trial.get("seconds", 0.0) for trial in trials)
        best = final_within_budget(accepted, trials, points, normals, bits=bits,
                                   byte_budget=byte_budget, degree=degree, spans=spans,
                                   rounds=rounds, smoothing=smoothing, anchor=anchor,
                                   border=border, scan_mesh=scan_mesh, **warm)
    rms, size, layout, atlas, f, u, v, trial_timings, chosen_bits = best
    clock = time.perf_counter()
    for _ in range(FAR_PASSES):
        refined = refined_within_budget(
            (atlas, layout, size), coarse, points, normals, bits=bits,
            byte_budget=byte_budget if auto else None, degree=degree,
            spans=spans, rounds=rounds, smoothing=smoothing, anchor=anchor, border=border,
            scan_mesh=scan_mesh, **warm)
        if refined is None:
            break
        rms, size, layout, atlas, f, u, v, chosen_bits = refined
    timings["refine_far"] = time.perf_counter() - clock
    clock = time.perf_counter()
    atlas, size = within_budget_fed_back(
        atlas, size, chosen_bits, byte_budget if auto else None, layout, points,
        f, u, v, smoothing=smoothing, anchor=anchor, border=border, scan_mesh=scan_mesh)
    timings["round"] = time.perf_counter() - clock
    timings.update(trial_timings)
    table = index_table(atlas)
    distance = signed_distances(table, control_points(atlas), degree, spans, points, f, u, v)
    report(1.0)
    return AtlasFit(atlas, layout, surface, layout.n_triangles, len(atlas.quads), points, f, u,
                    v, distance, rms, size, timings, trials, chosen_bits)


def grid_mesh(atlas: AtlasSurface, resolution: int, table: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
    """Every patch sampled on an ``r × r`` grid of ``(u, v)`` and cut into triangles.

    Not welded (a border sample appears once per patch that holds it, equal to it up to
    rounding); for measuring the base. Triangles are counter-clockwise seen from the side
    of ``C_u × C_v``. ``table``: the atlas's :func:`.patches.index_table`, when the caller
    has it (0.4 s for the bunny's 24,000 smooth-base patches); ``None``: found here.

    Returns
    -------
    vertices : ndarray, shape (F r², 3)
    faces : ndarray, shape (2 F (r - 1)², 3)
    """
    if isinstance(resolution, bool) or not isinstance(resolution, int) or resolution < 2:
        raise ValueError(f"resolution must be an int >= 2, got {resolution!r}")
    r, n_f = resolution, len(atlas.quads)
    t = np.linspace(0.0, 1.0, r)
    bu = basis_matrix(t, atlas.degree, atlas.spans)
    table = index_table(atlas) if table is None else table
    net = control_points(atlas)[table]  # (F, n, n, 3)
    if atlas.weights is None:
        grid = np.einsum("ai,bj,fijc->fabc", bu, bu, net)
    else:
        w = np.asarray(atlas.weights)[table]
        hom = np.einsum("ai,bj,fijc->fabc", bu, bu, net * w[..., None])
        grid = hom / np.einsum("ai,bj,fij->fab", bu, bu, w)[..., None]
    vertices = grid.reshape(-1, 3)  # vertex (f, a, b) at f r² + a r + b; a along u
    a, b = np.meshgrid(np.arange(r - 1), np.arange(r - 1), indexing="ij")
    p00 = (a * r + b).reshape(-1)
    p10, p01, p11 = p00 + r, p00 + 1, p00 + r + 1
    cells = np.concatenate([np.stack([p00, p10, p11], 1), np.stack([p00, p11, p01], 1)])
    faces = (cells[None, :, :] + (np.arange(n_f) * r * r)[:, None, None]).reshape(-1, 3)
    return vertices, faces
