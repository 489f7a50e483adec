"""The smooth base: a triangle control mesh fitted to the scan, drawn as Catmull-Clark patches.

The patches base (:mod:`.fit`) stores every bicubic patch's control net, about nine points a
patch, and its patches join C0. This base stores only a triangle *control mesh*, ``.tsa``
version 6 (``client_py.control_mesh``), from which every reader derives
the same atlas (``client_py.smooth_base``): one Catmull-Clark step makes each triangle
three quads, and each quad is drawn as Loop & Schaefer's bicubic approximation of the
Catmull-Clark limit surface (*Approximating Catmull-Clark subdivision surfaces with bicubic
patches*, ACM TOG 2008), so the detail pyramid, the welded tessellation and the viewer take
it as any atlas. Both stages are linear, so the atlas's control points are ``M V`` of the
control points ``V`` (``M = A S``, the rows of ``client_py.smooth_base``), and the drawn
surface sampled on a grid per patch is ``B M V``: the fit
(:func:`fitter.fitting.atlas.subdivision.fit_control_points`, a squared-distance
minimisation) moves ``V``.

The control mesh is the scan's surface decimated (:func:`.layout.decimate`: quadric edge
collapse, the mesh Draco would code), so its vertices are dense where the shape turns. At
the patches base's bytes it drew Nefertiti, Lucy and Laurana at 0.57-0.75 times the RMS of
quadric decimation + Draco, where the patches base drew 1.69-2.01 times (``python -m bench
subdivision``, docs/benchmarks.md, session 28). In the product (``tessera fit``; ``python
-m bench atlas``, ``bench/results/atlas.json``, session 31) the base draws the six meshes of
the benchmark at 0.32-0.98 times Draco's RMS at its bytes, and their level 0 at 0.33-0.89,
but the bunny's at 1.01 (a floor of points in no triangle). It is the default base since
session 31 (``--base patches`` fits the other; docs/benchmarks.md, "Session 31"). Still
worse than the patches base: its colour on a dense texture (its level-0 mesh draws 4 texels
a patch side; the Bali mask's colour 6.03 mean |dRGB| at 100.1 KB against the patches
base's 5.35 at 129.0 KB, ``bench/results/atlas_colour.json``, session 32).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import numpy as np
import scipy.sparse as sp

from client_py.atlas import AtlasSurface
from client_py.control_mesh import read_control_mesh, write_control_mesh
from client_py.smooth_base import SmoothBase, base_atlas, smooth_atlas, smooth_base

from ..options import MAX_PATCHES
from .detail import OFFSET_LIMIT, PULL_REACH
from .fit import AtlasFit, AtlasFitError, grid_mesh, working_points
from .layout import AtlasLayoutError, decimate, quad_layout
from .measure import barycentric, closest_points_on_mesh
from .patches import (
    bernstein_matrix,
    control_points,
    correct_parameters,
    index_table,
    neighbour_table,
    signed_distances,
)
from .subdivision import Subdivided, fit_control_points
from .surface import ScanSurface, border_edges, scan_surface

#: samples per patch side of the drawn surface the control points are fitted to (its
#: triangles, 2 (r - 1)^2 a patch, are what the closest points are found on)
FIT_RESOLUTION = 4
FIT_ROUNDS = 4
#: from the second round on, a drawn vertex of a mesh's fit farther than this share of the
#: diagonal from its nearest working point has its reverse row weighed :data:`FAR_WEIGHT`
#: times (``fit_control_points``' far rows). The Bali mask's control mesh (its stand-in
#: decimated) bridges a fold by a tusk, and the drawn fin there, reached by no working
#: point, stood 1.04 % of the diagonal off the scan (1.047 % at level 0). Weighed 3 times:
#: 0.91 % (0.881 %), level 0's RMS of all points +2.8 %; 2 times: 1.02 % (0.994 %); 3 times
#: past 0.9 %: 0.991 % (1.005 %), RMS +3.5 %. The bunny's, Lucy's and Laurana's bundles are
#: byte-identical (why not from the first round: ``fit_control_points``). Over a cloud's
#: stand-in the 15-scan Buddha's level 0 went 1.12 -> 1.19 %: a mesh's only
#: (docs/benchmarks.md, session 34)
FAR_REACH = 0.0075
FAR_WEIGHT = 3.0
#: the smooth base's ``.tsa`` bytes with ``--patches auto``: the most control
#: triangles, :data:`MAX_TRIANGLES`, at 12 bits. Manifest included, against quadric
#: decimation + Draco at the same bytes (session 29, RMS of all points): Nefertiti's base
#: at 9,000 triangles 0.81 times Draco's RMS, at 4,500 0.96, at 3,000 0.83; Lucy's 0.74 at
#: 9,000 and 1.05 at 3,000 (10 bits), where the patches base drew 1.69 and 2.01 times
SMOOTH_BYTE_BUDGET = 16_000
#: bytes of ``.tsa`` per control triangle, to size the first trial: version 5's figure
#: (Nefertiti decimated to 6,000 triangles: 12,006 bytes at 12 bits), which sizes it
#: conservatively for version 6: the fitted bases of session 31 (8,000 triangles, 10-12
#: bits) took 1.3-1.6 bytes a triangle in version 6, 2.2 on Buddha scan 0's ragged rim
#: (docs/benchmarks.md, "Session 31: the control mesh's point and triangle coders")
BYTES_PER_TRIANGLE = 2.0
#: trials of fewer triangles when a fitted control mesh's file is over the byte budget
BUDGET_ATTEMPTS = 3
#: knot spans per patch side of a smooth base's detail level 0 (the patches base's 8 over
#: about 2,200 patches; a smooth base has 3 a control triangle)
SMOOTH_DETAIL_SPANS = 2
#: the detail's quantisation step over the RMS each level leaves on a smooth base
#: (``fitter.fitting.atlas.detail.STEP_FACTOR``: 2 on a patches base): Nefertiti's level 0
#: at 9,000 control triangles took 103.3 KB for RMS 0.0170 at 2 (1.8 times Draco's RMS at
#: those bytes, which code the whole scan there), 75.8 KB for 0.0212 at 4 (0.63 times) and
#: 61.2 KB for 0.0268 at 6 (0.63 times)
SMOOTH_STEP_FACTOR = 4.0
#: knot spans per patch side of the detail over a cloud's surface (its Poisson stand-in):
#: the 15-scan Happy Buddha's level 0 at 2 spans did not lower the held-out samples' RMS by
#: ``detail.MIN_GAIN`` (2 %), so the cloud kept no detail level; at 1 span it lowered it by
#: 3.7 % (1.414e-4 -> 1.362e-4) and the RMS of all points by 16 % (2.21e-4 -> 1.85e-4, the
#: level at 32.4 KB), session 30. The smooth base already follows the registration's
#: surface closer than the patches base did (held-out RMS 1.41e-4 against 3.05e-4)
SMOOTH_CLOUD_SPANS = 1
#: the largest normal offset the detail fits on a smooth base, in median patch sides
#: (``fitter.fitting.atlas.detail.OFFSET_LIMIT``, 0.2, was set on the patches base's ten
#: times fewer, larger patches: a third of the reach here). At 0.2 the Bali mask's level 0
#: left 17 % of its points, 38 % of its squared error, at 80 % or more of the base's
#: distance (the samples in its eyes and mouth were not fitted); at 0.6 its RMS of all
#: points went 1.16e-4 -> 5.59e-5 at 53.2 KB instead of 63.0 KB, Lucy's 0.145 -> 0.125,
#: Nefertiti's 0.0220 -> 0.0201, the bunny's 2.04e-5 -> 2.07e-5 at 7 % fewer bytes; the
#: mask's largest mesh -> scan distance 0.92 % -> 1.02 %, brought back by
#: :data:`SMOOTH_PULL_REACH` (session 31). A mesh's only:
#: on the 15-scan Happy Buddha's cloud it lowered the RMS 1.85e-4 -> 1.63e-4 but drew a
#: point 1.05 % of the diagonal off the scan (0.97 % at 0.2), past the 1 % a visitor may see
SMOOTH_OFFSET_LIMIT = 0.6
#: a drawn node of a smooth base's detail farther than this share of the diagonal from the
#: scan is pulled toward it (``fitter.fitting.atlas.detail.PULL_REACH``, 0.75 % on the
#: patches base). With the wider offset limit the Bali mask's level 0 drew a point 1.02 %
#: of the diagonal off the scan (its base 0.95 %: a hook on the mask's rim); pulled from
#: 0.5 %, 0.97 %, at the same RMS of all points (5.60e-5) and bytes; Buddha scan 0's
#: 0.81 % became 0.75 % and Lucy's level 0 stayed the same (session 31). A mesh's only: the
#: 15-scan Happy Buddha's cloud went from 0.97 % to 1.00 %
SMOOTH_PULL_REACH = 0.005


def smooth_detail(surface: ScanSurface) -> dict:
    """``fitter.fitting.atlas.detail.fit_detail_pyramid``'s options for a smooth base over
    ``surface``: its spans (:data:`SMOOTH_DETAIL_SPANS` on a mesh's own triangles,
    :data:`SMOOTH_CLOUD_SPANS` on a cloud's stand-in), its step factor, its offset limit
    (:data:`SMOOTH_OFFSET_LIMIT` on a mesh, the patches base's on a cloud), the reach past
    which its drawn nodes are pulled to the scan (:data:`SMOOTH_PULL_REACH` on a mesh, the
    patches base's on a cloud), and its patches kept in the order of its file's control
    triangles."""
    if surface.origin == "mesh":
        spans, limit, reach = SMOOTH_DETAIL_SPANS, SMOOTH_OFFSET_LIMIT, SMOOTH_PULL_REACH
    else:
        spans, limit, reach = SMOOTH_CLOUD_SPANS, OFFSET_LIMIT, PULL_REACH
    return {"spans": spans, "step_factor": SMOOTH_STEP_FACTOR, "keep_order": True,
            "offset_limit": limit, "pull_reach": reach}


#: the scan's open border is weighted in the control mesh's decimation
#: (:func:`border_weights`) when its vertices are at most this share of the control mesh's
#: points (about half its triangles)
BORDER_SHARE = 0.125
#: the weight of an open-border vertex's collapse quadric (MeshLab maps the weights' range
#: onto 1..100, so any weight above 1 is the full 100)
BORDER_WEIGHT = 100.0


def border_weights(source: ScanSurface, triangles: int) -> np.ndarray | None:
    """Per-vertex weights of ``source``'s decimation to about ``triangles`` control
    triangles (:func:`.layout.decimate`'s ``weights``): :data:`BORDER_WEIGHT` on the
    vertices of the scan's own open border, 1 elsewhere; ``None`` (plain decimation) for a
    cloud's stand-in, a closed surface, or a border of more than :data:`BORDER_SHARE` of the
    control points.

    The drawn border is the limit curve of the control mesh's border, and the detail moves
    it only along the normal, so scan points beyond it stay as far as the border's control
    points leave them. On Laurana's cut base (318 border vertices) the plain decimation kept
    107 control edges along it, and the 0.8 % of points whose closest drawn point was on the
    border held 65 % of level 0's squared error; weighted, 249 edges, and the RMS of all
    points 0.164 -> 0.158 at the base, 0.0459 -> 0.0250 at level 0 (with
    :data:`SMOOTH_OFFSET_LIMIT`). Buddha scan 0's ragged rim (8,233 border edges against
    about 4,000 control points) took the budget from the surface when weighted: RMS 1.1e-4 ->
    1.8e-4 at the base, and a drawn point 1.6 % of the diagonal off the scan (session 31)."""
    if source.origin != "mesh":
        return None
    ends = border_edges(source.faces)
    on_border = np.zeros(len(source.vertices), bool)
    on_border[ends.ravel()] = True
    count = int(np.count_nonzero(on_border))
    if count == 0 or count > BORDER_SHARE * triangles / 2:
        return None
    return np.where(on_border, BORDER_WEIGHT, 1.0)


#: the quantisation step of the control points over the fit's RMS (:func:`control_bits`)
STEP_OVER_RMS = 1.5
CONTROL_BITS = (8, 16)
#: the most control triangles (``--patches`` as a patches base's: three patches a triangle):
#: the derived atlas's control points, about 27 a triangle, stay within the ``.tsa`` limit
#: of 2^18
MAX_TRIANGLES = MAX_PATCHES // 3


def rows_matrix(rows: Sequence[Sequence[tuple[int, float]]], columns: int) -> sp.csr_matrix:
    """The sparse matrix whose row ``j`` is ``sum w e_i`` over ``rows[j]``'s ``(i, w)``."""
    lengths = np.fromiter((len(r) for r in rows), np.int64, len(rows))
    indptr = np.concatenate([[0], np.cumsum(lengths)])
    flat = [entry for row in rows for entry in row]
    indices = np.fromiter((i for i, _ in flat), np.int64, len(flat))
    data = np.fromiter((w for _, w in flat), np.float64, len(flat))
    return sp.csr_matrix((data, indices, indptr), shape=(len(rows), columns))


def smooth_matrix(n: int, base: SmoothBase) -> sp.csr_matrix:
    """``M = A S`` (shape ``(N_cp, n)``): the derived atlas's control points (the order of
    ``AtlasSurface``: vertices, edge points, face points) from the ``n`` control points."""
    S = rows_matrix(base.step_rows, n)
    return (rows_matrix(base.acc_rows, S.shape[0]) @ S).tocsr()


def sample_matrix(table: np.ndarray, n_control: int, resolution: int
                  ) -> tuple[sp.csr_matrix, np.ndarray]:
    """Every bicubic patch of the index table ``table (F, 4, 4)`` sampled on an ``r x r`` grid:
    the rows over the atlas's ``n_control`` control points (``B_i(u) B_j(v)``, The NURBS Book
    eq. 1.8) and the grid's triangles, vertex ``(f, a, b)`` at ``f r² + a r + b`` as
    :func:`.fit.grid_mesh` numbers them."""
    r, n_f = resolution, len(table)
    b = bernstein_matrix(np.linspace(0.0, 1.0, r), 3)  # (r, 4)
    weights = np.einsum("ai,bj->abij", b, b).reshape(r * r, 16)  # (r², 16)
    data = np.broadcast_to(weights, (n_f, r * r, 16)).reshape(-1)
    indices = np.broadcast_to(table.reshape(n_f, 1, 16), (n_f, r * r, 16)).reshape(-1)
    indptr = np.arange(0, n_f * r * r * 16 + 1, 16)
    B = sp.csr_matrix((data, indices, indptr), shape=(n_f * r * r, n_control))
    a, c = np.meshgrid(np.arange(r - 1), np.arange(r - 1), indexing="ij")
    p00 = (a * r + c).reshape(-1)
    p10, p01, p11 = p00 + r, p00 + 1, p00 + r + 1
    cells = np.concatenate([np.stack([p00, p10, p11], 1), np.stack([p00, p11, p01], 1)])
    faces = (cells[None] + (np.arange(n_f) * r * r)[:, None, None]).reshape(-1, 3)
    return B, faces


def fit_control_mesh(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray,
                     rounds: int = FIT_ROUNDS, resolution: int = FIT_RESOLUTION,
                     far_reach: float | None = None) -> tuple[np.ndarray, list[float]]:
    """Control points (starting from ``vertices (n, 3)``) of the control mesh ``triangles
    (T, 3)`` whose drawn atlas fits ``points (N, 3)``: ``fit_control_points`` on the atlas
    sampled at ``resolution`` per patch side, with far rows past ``far_reach`` (``None``:
    none) weighed :data:`FAR_WEIGHT` times. Returns the points and the RMS history."""
    base = smooth_base(len(vertices), triangles.tolist())
    M = smooth_matrix(len(vertices), base)
    # the layout's numbering is all the fit needs of the atlas: M V is its control points
    table = index_table(base_atlas(base, (M @ vertices).tolist()))
    B, faces = sample_matrix(table, M.shape[0], resolution)
    drawn = Subdivided("acc", 1, len(vertices), (triangles,), (B @ M).tocsr(), faces)
    return fit_control_points(points, vertices, drawn, rounds=rounds, far_reach=far_reach,
                              far_weight=FAR_WEIGHT)


def control_bits(vertices: np.ndarray, rms: float) -> int:
    """The fewest bits in ``CONTROL_BITS`` whose quantisation step (the control points'
    largest extent over ``2^bits - 1``) is at most ``STEP_OVER_RMS`` times ``rms``."""
    extent = float(np.ptp(vertices, axis=0).max())
    for bits in range(CONTROL_BITS[0], CONTROL_BITS[1] + 1):
        if extent / ((1 << bits) - 1) <= STEP_OVER_RMS * rms:
            return bits
    return CONTROL_BITS[1]


def foot_points(atlas: AtlasSurface, points: np.ndarray, normals: np.ndarray,
                resolution: int = FIT_RESOLUTION) -> tuple[np.ndarray, ...]:
    """Each point's foot point on ``atlas``: the closest point of its grid mesh, then
    Gauss-Newton steps (:func:`.patches.correct_parameters`). Returns ``f, u, v`` and the
    signed distance, each (N,)."""
    table = index_table(atlas)
    vertices, faces = grid_mesh(atlas, resolution, table)
    _, tri, foot = closest_points_on_mesh(points, vertices, faces)
    r = resolution
    per_patch = 2 * (r - 1) ** 2
    f = tri // per_patch
    corners = faces[tri] - (f * r * r)[:, None]
    w = barycentric(foot, *(vertices[faces[tri, k]] for k in range(3)))
    a = sum(w[:, k] * (corners[:, k] // r) for k in range(3)) / (r - 1)
    b = sum(w[:, k] * (corners[:, k] % r) for k in range(3)) / (r - 1)
    cps = control_points(atlas)
    f, u, v, _ = correct_parameters(table, cps, 3, 1, neighbour_table(atlas), points, normals,
                                    f, np.clip(a, 0, 1), np.clip(b, 0, 1))
    return f, u, v, signed_distances(table, cps, 3, 1, points, f, u, v)


def fit_smooth_atlas(scan, *, byte_budget: int, surface: ScanSurface | None = None,
                     layout_surface: ScanSurface | None = None, bits: int | None = None,
                     triangles: int | None = None, working_count: int = 60_000,
                     rounds: int = FIT_ROUNDS,
                     progress: Callable[[float], None] | None = None) -> AtlasFit:
    """Fit the smooth base of ``scan`` within ``byte_budget`` bytes of ``.tsa`` version 6.

    The control mesh is the surface (or ``layout_surface``, a stand-in with small handles
    closed) decimated to ``T`` triangles, its open border weighted (:func:`border_weights`):
    ``triangles`` when given, else
    ``byte_budget / BYTES_PER_TRIANGLE`` (at most :data:`MAX_TRIANGLES`), then up to
    :data:`BUDGET_ATTEMPTS` times fewer in proportion when the file is over the budget. Its
    points are fitted to the working points (:func:`fit_control_mesh`; a mesh's with its far
    drawn vertices pulled harder, :data:`FAR_REACH`), quantised at
    ``bits`` (``None``: :func:`control_bits` of the fit's RMS) and read back.

    Returns
    -------
    AtlasFit
        The fit of the decoded atlas: its ``layout`` the control mesh's quad split, ``rms``
        the working points' before quantisation, ``bits``, ``bytes``, ``trials``, and the
        file as ``control_file``.

    Raises
    ------
    AtlasLayoutError, AtlasFitError
        No decimation is an oriented 2-manifold, or the file stays over the budget.
    """
    report = progress or (lambda fraction: None)
    timings: dict = {}
    clock = time.perf_counter()
    surface = surface if surface is not None else scan_surface(scan)
    points, normals = working_points(scan, surface, working_count)
    if len(points) < 16:
        raise AtlasFitError(f"only {len(points)} working points; at least 16 are needed")
    timings["points"] = time.perf_counter() - clock
    source = layout_surface if layout_surface is not None else surface
    target = triangles or int(min(MAX_TRIANGLES, byte_budget / BYTES_PER_TRIANGLE))
    trials: list[dict] = []
    for attempt in range(BUDGET_ATTEMPTS):
        report(0.1 + 0.8 * attempt / BUDGET_ATTEMPTS)
        clock = time.perf_counter()
        vertices, faces = decimate(source, max(4, target), border_weights(source, target))
        timings["layout"] = time.perf_counter() - clock
        clock = time.perf_counter()
        fitted, history = fit_control_mesh(
            points, vertices, faces, rounds=rounds,
            far_reach=FAR_REACH if surface.origin == "mesh" else None)
        timings["solve"] = time.perf_counter() - clock
        chosen = bits or control_bits(fitted, history[-1])
        data = write_control_mesh(fitted, faces, chosen, {"units": scan.units or "unknown"})
        trials.append({"triangles": int(len(faces)), "control_points": int(len(vertices)),
                       "bits": chosen, "bytes": len(data), "rms": history[-1],
                       "rms_by_round": history, "seconds": timings["layout"] + timings["solve"]})
        if triangles is not None or len(data) <= byte_budget:
            break
        target = int(len(faces) * byte_budget / len(data) * 0.97)
    else:
        raise AtlasFitError(f"the control mesh stayed over the budget of {byte_budget} bytes "
                            f"after {BUDGET_ATTEMPTS} attempts: {trials[-1]['bytes']} bytes "
                            f"at {trials[-1]['triangles']} triangles")
    clock = time.perf_counter()
    decoded, decoded_triangles, _ = read_control_mesh(data)
    atlas = smooth_atlas(decoded, decoded_triangles)
    f, u, v, distance = foot_points(atlas, points, normals)
    timings["foot_points"] = time.perf_counter() - clock
    report(1.0)
    layout = quad_layout(np.asarray(decoded, np.float64),
                         np.asarray(decoded_triangles, np.int64))
    return AtlasFit(atlas, layout, surface, len(layout.triangles), len(atlas.quads), points,
                    f, u, v, distance, history[-1], len(data), timings, trials, chosen, data)


__all__ = ["fit_smooth_atlas", "smooth_detail", "fit_control_mesh", "smooth_matrix",
           "sample_matrix", "control_bits", "AtlasLayoutError"]
