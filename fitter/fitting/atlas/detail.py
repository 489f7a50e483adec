"""The atlas's detail pyramid: per patch displacement tiles, one welded field across borders.

The base atlas (:mod:`.fit`) leaves what its bicubic patches cannot bend to: fur, eyes,
lips, chisel marks. As for the single patch (``fitter.fitting.detail``) and as in
displaced subdivision surfaces (Lee, Moreton, Hoppe, SIGGRAPH 2000), the detail is a scalar
displacement along the base's unit normal, ``X = C_f + D_f n_f``, with ``D_f = sum_k D_{f,k}``
and level ``k`` of patch ``f`` a uniform B-spline field of degree ``p`` with ``m 2^k`` spans
per side over the patch's own ``[0, 1]^2`` (``client_py.layers.level_knots``), cut into
``2^k x 2^k`` tiles of ``(m + p)^2`` coefficients.

Samples. The field is fitted to the scan's *surface*: for a mesh, its vertices (weight 1)
and area-weighted samples of its triangles (Turk, *Generating random points in triangles*,
Graphics Gems 1990), as many as ``SAMPLES_PER_CELL`` per knot cell of the finest level,
together weighing ``TRIANGLE_SHARE`` of the vertices; for a cloud, its points. Each
sample ``x`` gets a foot point ``(f, u, v)`` on the base by
the base fit's own projection (:func:`.patches.assign_triangles`,
:func:`.patches.triangle_to_quad`, then Newton point inversion with hops across borders,
:func:`.patches.correct_parameters`), in chunks of ``CHUNK`` samples, and splits into its
normal offset ``s = (x - C) . n`` and squared tangential remainder ``t^2 = |x - C|^2 - s^2``
(``fitter.fitting.detail.DetailSamples``).

Levels. Level ``k`` is fitted to what levels ``0..k-1`` left OF THE DRAWN MESH, with the
single patch's objective per patch (``fitter.fitting.detail``: weighted least squares, ridge
and thin-plate terms scaled by ``mu_f = tr(A_f^T W A_f) / n^2``), all patches in one
block-diagonal solve per batch. The rows are not the field's collocation but the mesh the
client draws at the level's resolution (two vertices per span), linearised at each sample
(:class:`DrawnModel`: the sample's drawn triangle, its nodes' displacement directions,
averaged on patch borders as the client averages them, and the base's chord).

Far nodes. Where the base is a web across the mouth of a pocket (a layout triangle whose
corners lie on the scan and whose inside does not: Lucy's drapery folds, the Bali mask's
cavities), no sample's offset holds the field there (the pocket's samples are beyond
``OFFSET_LIMIT`` or face away), and the field is what the samples around it and the
shared border coefficients extrapolate: on Lucy (main 43b3669) the detail moved the places
of level 0 farther than 1 % of the diagonal from the scan by 0.31 % of it (median; 82 %
away from the scan), from 0.87 % to 1.02 % (largest 1.00 -> 1.03 %). So, as the base's
reverse rows (:func:`.fit.reverse_rows`), each level also holds the mesh it draws onto the
scan: every node of the level's drawn grid whose position ``X`` (the base and the levels
before) lies farther than ``PULL_REACH`` (``pull_reach``) of the diagonal from the
scan's surface gets the row ``D_f(node) = (q - X) . d`` (:func:`far_node_rows`: ``q``
its closest scan point, ``d`` its drawn direction, so the node moves toward ``q`` as far
as a displacement along ``d`` can), weighing ``PULL_WEIGHT`` times the fitted samples'
mean weight per node. On Lucy the level-0 largest distance is 0.99 % and the far area 0
(was 1.03 %, 0.0015 %), the RMS of all points 0.1 % lower; on the mask 1.44 % and
0.063 % (was 1.48 %, 0.091 %); the 15-scan Happy Buddha's 4.14 % and 4.65 % become 4.07 %
and 4.26 % (RMS +0.4 %); the bunny's, Nefertiti's and Laurana's packs are byte-identical
(no node that far). The nodes' closest points cost Lucy's detail 1 CPU-s of 9. Leaving
out the samples whose foot point is farther than 3 times the base's RMS instead (as the
base's far patches): Lucy 1.00 %,
but the mask's RMS +15 %; a reach of 0.5 % with weight 1: Lucy 1.00 % at RMS +0.8 %, the
mask 1.44 % at +1.9 %; clipping coefficients at once the residual (``COEFFICIENT_REACH``)
changed nothing.

Folds. The client draws node ``i`` at ``C_i + D_i d_i``: ``d_i`` the patch's unit normal
inside it, the mean of its patches' normals on a border. Where the base creases between
patches (its joins are C0), the directions turn by half the crease within one drawn cell and
cross at about a cell's width on the crease's hollow side, and a larger displacement
there turns the drawn triangle over against the base (the pleats of ``bench.pleats``):
on main 90503fb's level 0 (drawn at 17, every object's base as the benchmark fits it)
82-97 % of the area turned over lies in the patches' border ring of cells (23-27 % of all
triangles); on Lucy, Laurana and the 15-scan Happy Buddha its triangles' corner directions
are 39-55 degrees apart (median; 2-9 over all triangles) and its displacement 0.66-0.82 of a
drawn edge (docs/benchmarks.md, "Pleats (session 15, w25-pleats)"). So after a
level's welded solve, :func:`fold_node_rows` finds the drawn triangles that keep less than
``FOLD_KEEP`` of their base triangle's facing area (a base triangle turned against its own
patch, a pleat of the base, is left alone) and gives each of their nodes the row
``D_k(node) = s D_k(node)``, ``s`` the share of the level's displacement with which the
triangle keeps ``FOLD_KEEP`` (:func:`fold_shrink`; a node's smallest over its triangles),
weighing ``FOLD_WEIGHT`` times the fitted samples' mean weight per node; the level is
solved again with them, ``FOLD_PASSES`` times: only the patches given rows, and the
interiors whose shared border ring moved (:func:`_solve_level`; each patch is its own block,
so the others' numbers are the first solve's, to the bit). Level 0 turned over, main ->
these rows (the same bases, load 6-12): Lucy 1.93 -> 0.37 %, Laurana 0.159 -> 0.017 %,
Nefertiti 0.28 -> 0.04 %, the 15-scan Happy Buddha 5.2 -> 1.8 %, the bunny 0.10 -> 0.015 %,
the Bali mask 0.73 -> 0.15 %, at RMS of all points +1.4, +0.2, +0.3, +3.1, -0.2 and +1.0 %;
at a weight of 10, Lucy's 0.30 % cost +7.9 %. What stays turned is mostly a pleat of the
base (27 % on Lucy) and triangles turned by the slope of the field between oblique
directions (37 %).

Welded borders. The client draws a border vertex at the mean of its patches'
displacements (``client_py.atlas_mesh``); two independent fields would differ there and
leave a crease. A clamped field's value on a side depends only on its border row of
coefficients (The NURBS Book §3.4, as the base's border curves), and neighbours' level-``k``
fields have the same knots along their common side. So, as the base shares its border
control points, every level shares its border coefficients: after the independent solve
(its coefficients clipped to twice the patch's largest residual, :func:`bounded_by_residual`),
each border coefficient (corner: every patch at the layout vertex; edge row: both patches,
read reversed where a side runs ``hi -> lo``) is set to the mean of the patches' values
weighted by their data (the diagonal of ``A_f^T A_f`` there), and each patch's interior is
solved again with its border ring held. With one quantisation step per level
(``fitter.fitting.detail.quantisation_step`` of the level's RMS over all samples), the
neighbours' tiles hold the same integers on their common border and ``D_f = D_g`` there
exactly: the mean the client takes is each side's own value (no seam).

Quantisation. The border ring is rounded to the level's step; each patch's interior is then
quantised with the rounding error fed back through the level's own least squares and a
weight on the integers' size, its rate (:func:`quantised_blocks`): plain rounding had been
28 % of Laurana's and 26 % of Lucy's level-0 squared error of all points. Then, on a
mesh, the ring's shared slots move the same way, each as one value under the terms of
every patch that holds it (:func:`_ring_descent`), and the interiors again. The shared mean
of two independent fits is not the welded field's least squares, and the ring's plain
rounding spent bytes: with the ring moved, level 0 of the smooth default (bytes a visitor
downloads, RMS of all points; docs/benchmarks.md, session 33) went bunny 77.0 -> 73.9 KB
and 2.03e-5 -> 1.97e-5, Nefertiti 75.5 -> 68.6 KB and 0.0201 -> 0.0150, Lucy 59.4 -> 54.9
KB and 0.124 -> 0.104, Laurana 67.7 -> 63.5 KB and 0.0250 -> 0.0209. Not over a cloud's
stand-in (its Poisson surface spans the gaps between the registered sheets): the 15-scan
Happy Buddha's level 0 then drew a point 1.09 % of the diagonal off the scan (1.44 % with a
slot's bound the largest of its patches'), against 0.98 % with the ring rounded.

Depth. Levels ``0..L-1`` with ``L`` the smallest count whose finest knot spacing, the
median patch side over ``m 2^(L-1)``, reaches the scan's median edge length (mesh) or
point spacing (cloud); capped so the finest level is drawn at two vertices per span within
the client's ``ATLAS_MAX_RESOLUTION`` samples per patch side (``m 2^(L-1) <= 64``), at
``client_py.layers.MAX_LEVEL + 1`` levels, and so its coefficients stay within
``MAX_COEFFICIENTS`` (about 100 bytes each while fitted: the memory bound). For a cloud, a
finer level can draw the scan's noise rather than its surface: its nearest-neighbour
spacing is that of its overlapping sheets together, finer than any one scan resolves. So a
cloud's automatic depth is also checked on data the fit has not seen (hold-out
validation, as in choosing a smoothing spline's parameter by cross-validation: Hastie,
Tibshirani & Friedman, *The Elements of Statistical Learning*, §7.10): a pseudo-random one
in ``HELD_OUT`` of the fitted samples is left out of every solve, and the pyramid stops
before the first level that does not bring their RMS ``sqrt(mean(e^2))`` below
``(1 - MIN_GAIN)`` times that of the levels before it (the base, for level 0): judged
first on the level's unrounded solve (a level refused there costs no fold rows and no
rounding; rounding only adds to the held-out error), then on its rounded coefficients. A
level is not tried at all when its shared coefficients (:func:`shared_count`) are more
than ``1 / MIN_SAMPLES_PER_UNKNOWN`` of the fitted samples: a least squares with about as
many unknowns as equations draws the noise, whatever the held-out samples would say. The
manifest's ``tiles.detail.held_out`` gives the RMS after each level tried (unrounded for a
level refused before rounding) and the level ``not_tried``, if any. A mesh is not
checked so: its triangles are the surface its makers published, its edge length the
resolution they chose, and every vertex is a scan point that a held-out share would leave
unfitted (the bunny's finest RMS of all points rose 7 %).

Drawn cells. Where the scan lacks a part (a registration's rims, the unscanned tunnel under
the 15-scan Happy Buddha's sleeve and the gap under its robe) the base is extrapolated over
it, and no level can bring that surface back to a scan that is not there: at those places
level -1 and level 0 were as far (1.5-2.3 % of the diagonal; docs/benchmarks.md, session
14). So each level stops drawing them, by the single patch's rule for a range image's walls
(``client_py.layers.DetailTile``, ``walls``: the finest applied tile's walls mask leaves
cells out), written in the level's packs (``client_py.atlas_detail``, version 5). A
cloud's only (a registration, a point cloud: its surface, the Poisson stand-in, closes
every gap; ``DRAWN_MESHES`` says why not a mesh's). After level ``k`` is fitted, the mesh
a client draws of it (levels ``0..k`` at the level's
resolution ``R_k``, :func:`.measure.drawn_mesh`) is cut into its cells, and a cell is left
out (:func:`far_cells`) when

* it reaches farther than ``DRAWN_REACH`` of the scan points' diagonal from the scan's
  surface (a mesh's triangles, a cloud's points: what bench.scoring measures a drawn mesh
  against) at a point of its triangles, sampled on lattices made finer until the
  distance's Lipschitz bound decides (:func:`reaching_cells`), and
* every scan point within ``DRAWN_REACH`` of that mesh whose closest point lies on it there
  (its *holders*) is as near, within ``HANDOVER_SLACK`` of the reach, to the mesh without
  the cells left out, or stays on the same side of the issue's two bounds: within
  ``HANDOVER_WITHIN`` of the reach (0.5 % of the diagonal) if it was, else within the reach
  (1 %): its closest point is handed over to a cell that stays.

So every such scan point keeps its distance to the drawn mesh (the panel's measure, the
benchmark's every-point RMS and share within 0.5 %) within 0.05 % of the diagonal or within
the bound it met: no cell a scan point is drawn by goes unless another draws it as near or
within the same bound, only what reaches out past the scan with no scan point to show (a
cloud's outliers, farther, are not fitted either). The bounds came in session 34: the
15-scan Buddha's level 0 kept three cells with a corner 1.04-1.12 % off the scan for their
holders, one of them for a single point that their loss took from 0.56 to 0.89 %; with the
bounds its largest distance fell from 1.12 % to 0.998 % at the same RMS of all points
(1.8513e-4 -> 1.8516e-4, docs/benchmarks.md, "Session 34"). On the
15-scan Buddha (default fit, seed 0, session 15, load 4-16) level 0's cells at the far
places are large (the largest distance from a corner to their centre 0.5-1.7 % of the
diagonal at the farthest ones), and half of those reaching beyond 1 % also come within 1 %
of the scan at one end: a cell left out only where all of it is farther than a reach (1 %:
3,118 cells; 0.5 %: 16,567) kept the largest distance at 2.00 % (1.71 %), where this rule
(7,501 cells) brings it from 2.10 % to 1.52 % and the drawn area beyond 1 % from 1.2 % to
0.02 %, for 1.4 KB of masks (docs/benchmarks.md, session 15). On main 5dba071's level 0 (max
1.06 %), 53 cells still reached past 1 % (a lattice of 8 steps a side measured, 7,168 left
out): 44 only between the points of the one lattice of 4 then sampled (1.00-1.05 %), and 9
holding scan points, at 1.03-1.14 %: fins, webs of the Poisson surface across a thin gap
standing on a scanned sheet (or pointing at a stray cluster of points 0.8-1.1 % off the
rest), their far end mostly a node 1.1 % off the scan beside its drawn direction (where the
pull rows cannot bring it in: ``(q - X) . d`` small), their holders at their root, 0.00-0.14
% from them and at most 0.036 % farther from the sheet's own cells. With both rules, 88 more
cells go and no drawn point reaches past 1 % (a lattice of 12 steps measured), the RMS of
all points +0.001 %, the share within 0.5 % the same (docs/benchmarks.md, session 16). Every
tile over a cell a coarser level left out carries a walls mask too, all clear if need be, so
that each level decides its own cells. Only triangles go: the vertices, and so the borders
patches share where both sides are drawn, stay as they were (``client_py.atlas_mesh``), and
a pack none of whose tiles carries a mask is written as before, byte for byte (version 4).

Groups and packs. Patches are renumbered in the k-d tree order of their centres
(:func:`spatial_order`), and the order is halved as the tree halves it until each half's
finest-level pack stays within ``PACK_BYTES``, its patches drawn at the finest level within
``GROUP_VERTICES`` and their number within ``GROUP_PATCHES``: each group is a box of the
tree, a compact piece of the object (the viewer's unit of refinement; along the Morton
curve, which cut Stanford Lucy into runs of 226 patches, their bounding spheres were
411-863 units across a 1,924-unit diagonal, most of them the statue's height; now 204-360
for 16 groups of 141-142); every level's tiles of a group
travel in one welded pack (``client_py.atlas_detail``, version 3: a border coefficient that
an earlier patch of the pack holds in the same shared slot, ``shared_index``, is coded once:
the bunny's level 0 18 % smaller), with the pack's ``geometric_error`` (max
sample error of the group after levels ``0..k``, as OGC 3D Tiles) and each group's bounding
sphere (the control points' hull widened by the largest displacement).
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from dataclasses import fields as data_fields
from itertools import accumulate

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from client_py import layers
from client_py._numpy_basis import basis_arrays
from client_py.atlas import AtlasSurface, ring_positions
from client_py.atlas_detail import (
    MAX_PACK_VALUES,
    PACK_HEADER,
    WALLS_FREE_VERSION,
    pack_capacity,
    pack_name,
    write_pack,
)
from client_py.bundle import ATLAS_MAX_RESOLUTION, atlas_level_resolution
from client_py.format import CRC_SIZE, TILE_HEADER_SIZE, TILE_VERSION, write_detail_tile

from ..cores import usable_cores
from ..detail import (
    STEP_FACTOR,
    DetailSamples,
    coarsened,
    collocation_matrix,
    level_tiles,
    normal_split,
    quantisation_step,
    regularisation,
)
from ..io.scan import Scan
from ..io.thin import thin_to_count
from ..options import OptionError
from .fit import AtlasFit, median_edge
from .lattice import coupling_colours, lattice_descent
from .patches import (
    control_points,
    correct_parameters,
    evaluate_patches,
    index_table,
    neighbour_table,
)
from .threads import on_threads

DEGREE = 2
SPANS = 8  # spans per tile side: on the bunny, 8 reached 0.27 mm RMS in 49 KB, 4 in 112 KB
SAMPLES_PER_CELL = 6.0  # surface samples per knot cell of the finest level
# The triangle samples' total weight over the mesh vertices' (weight 1 each). The error is
# that of the scan's points, the vertices: a field pulled to the flat triangles between them
# cuts their corners (bunny level 0, RMS of all points: 4.32e-5 with every sample alike,
# 3.03e-5 at 0.05, 3.17e-5 at 0.2, 3.38e-5 at 0.5, 3.01e-5 vertices alone); the triangles
# still hold the field where vertices are sparse, as the issue asks of a mesh.
TRIANGLE_SHARE = 0.2
MEDIAN_TRIANGLES = 1_000_000  # a large mesh's median edge is taken over about this many
MAX_SAMPLES = 1_000_000  # ~100 bytes each while fitted; projection runs in chunks
CHUNK = 100_000
NEWTON_ITERATIONS = 8
MAX_COEFFICIENTS = 6_000_000  # of the finest level, all patches
PACK_BYTES = 24_000  # the finest level's pack of a group stays within this
# ... its patches drawn at the finest level within GROUP_VERTICES vertices (patches times
# the level's samples per patch side squared), and at most GROUP_PATCHES patches. The
# viewer refines group by group within a budget of drawn vertices (MAX_VERTICES in
# web/src/atlas-layer.js, which a test holds at 4 finest groups or more), so that a close
# view of one part of the object shows that part's detail. Stanford Lucy (2,268 patches,
# level 0 at 17 x 17 samples) was 3 groups of 445-925 patches, each the height of the
# statue: her base alone (184 k vertices at 9 x 9) and any one group at level 0 passed the
# then 250 k budget, and no zoom ever showed her detail. Each group costs the manifest
# about 22 bytes gzipped and each pack 9 (the dense vase's 2,280 patches cut to 256 groups
# of 8-9, 65,536 vertices at 65 x 65, made its manifest 16 KB larger and its packs 17 KB).
GROUP_VERTICES = 250_000
#: the most patches of ``SPANS`` spans a side in a group: of ``m`` spans, ``(SPANS / m)²``
#: times as many (a smooth base's small patches, ``.smooth``), the same cells of the drawn grid
GROUP_PATCHES = 256
MU_FLOOR = 0.25
OFFSET_LIMIT = 0.2  # largest |s| fitted, in median patch sides (0.5 drew flaps on Lucy; 0.1 left
# out 0.7 % of her points, 27 % of her level-0 squared error: docs/benchmarks.md session 14)
MIN_FACING = 0.5  # least n . n_x of a fitted sample (its base normal against its own)
# The least d . n the drawn model credits a node (DrawnModel): a border node's direction d
# (the mean of its patches' normals) can be oblique to a sample's normal n where the base
# creases between patches (on Lucy the median crease is 25 degrees, a tenth over 130). With
# d . n exact, the fit moved such nodes far along d to fit the samples along n, and their
# sideways motion, which the model does not see, drew flaps (Lucy level 0: drawn area
# farther than 1 % of the diagonal 3.1 %, largest 6.0 %); at 0.8 it is 0.42 %, 1.98 %
# (before the drawn model: 0.48 %, 1.96 %) and the RMS 0.623 (exact 0.548, 1 everywhere
# 0.644; these three measured with a coarser quantisation step, 3 times the RMS).
MIN_DIRECTION = 0.8
COEFFICIENT_REACH = 2.0  # an independent fit's coefficients within this times its residual
BATCH_UNKNOWNS = 250_000  # unknowns per batch of the block-diagonal solves
QUANTISE_SWEEPS = 4  # Gauss-Seidel sweeps of quantised_blocks (0: plain rounding)
QUANTISE_RATE = 1.0  # quantised_blocks' weight of |q| (a rate proxy), in median data weights
# Held-out samples (a cloud's automatic depth only): one in HELD_OUT of the fitted samples
# stays out of every level's solve, and a level is kept only if it brings their RMS down by
# MIN_GAIN of the levels before it (module docstring, "Depth"). On the 15-scan Happy Buddha
# (a cloud of overlapping registered range scans) the held-out RMS went 3.05e-4 (base),
# 1.84e-4 (level 0), 1.95e-4 (1), 2.80e-4 (2) while the fitted samples' fell to 1.29e-4:
# levels 1 and 2 drew the registration's noise as a speckle.
HELD_OUT = 10
MIN_HELD = 1000  # fewer held-out samples decide nothing: every auto level is kept
MIN_GAIN = 0.02
# ... and a level with fewer than this many fitted samples per coefficient is not tried: its
# least squares has almost as many unknowns as equations and follows the noise. The 15-scan
# Happy Buddha's level 0 had 2.9 per coefficient counted as F n^2, about 3.5 per shared one
# (held-out RMS -27 %), its level 1 0.89, about 1.0 (+30 %, refused after its nodes, far rows
# and solve: about 13 s of the fit's wall on 2 cores).
MIN_SAMPLES_PER_UNKNOWN = 2.0
# Far drawn nodes (module docstring, "Far nodes"): those farther than PULL_REACH of the
# diagonal from the scan are pulled toward it, each row weighing PULL_WEIGHT times the fitted
# samples' mean weight per node (0: off). Lucy level 0, max / RMS of all points: 0.5 % and 1:
# 0.997 % / 0.4416; 0.75 % and 1: 1.017 % / 0.4368; 0.75 % and 10: 0.992 % / 0.4376 (the
# mask 1.436 % / 1.0587e-4; without: 1.031 % / 0.4381, 1.483 % / 1.0592e-4).
# The mask's remaining places (measure.far_places) are webs on base layout edges across
# gaps, the scan beside them, where (q - X) . d is small. Two variants measured on main
# 732fe1f's mask base (level 0, 400,000 samples of the drawn mesh; was max 1.423 %, far
# area 0.052 %, RMS 1.0587e-4) and not kept: the target t minimising the distance of
# X + t d to the scan (a line search over t within 3 times the node's distance: 220 of 236
# far nodes move) 1.452 %, 0.066 %, 1.0580e-4; the coefficient bound of
# bounded_by_residual also reaching the pulls' |target| 1.453 %, 0.100 %, 1.0584e-4.
PULL_REACH = 0.0075
PULL_WEIGHT = 10.0
# Drawn cells (module docstring): a level leaves out a cell of its drawn mesh that reaches
# farther than DRAWN_REACH of the scan points' bounding-box diagonal from the scan's surface
# and holds no scan point's closest drawn point (0: off). 1 % is the issue's bound on the
# largest distance from the drawn mesh to the scan, and the manifest's "uncovered" distance.
DRAWN_REACH = 0.01
CELL_LATTICE = 4  # steps a side of the lattice far_cells samples a cell's triangles on first
FINEST_LATTICE = 32  # reaching_cells' finest lattice (twice as fine each time, from 4)
# A reaching cell holding scan points' closest drawn points goes when each of them loses at
# most this share of DRAWN_REACH to the mesh without it (module docstring, "Drawn cells"):
# 0.05 is 0.05 % of the diagonal, a quarter of the 15-scan Buddha's level-0 RMS of all points.
HANDOVER_SLACK = 0.05
# ... or when each ends within this share of DRAWN_REACH of the mesh without it if it was
# within it, else within DRAWN_REACH: 0.5 is the 0.5 % of the diagonal within which issue 13
# asks 99.5 % of the scan points to lie, 1 % the farthest it lets the drawn mesh reach
HANDOVER_WITHIN = 0.5
# Whether a mesh's levels leave cells out too (module docstring, "Drawn cells"): no. A
# mesh's triangles are the surface its makers published, holes and borders included, and
# its layout follows its border (layout.decimate_on_border); a closed one must stay
# watertight. With it on, the Bali mask's level 0 (its scan closed) left out the 4 cells
# around one drawn vertex 1.07 % of the diagonal off the scan, a spike at a patch corner
# that no vertex of the scan is drawn by: a hole in a closed mesh; the bunny's none
# (session 15).
DRAWN_MESHES = False
# Fold rows (module docstring, "Folds"): after a level's solve, the drawn triangles that keep
# less than FOLD_KEEP of their base triangle's facing area get rows shrinking the level's
# displacement at their nodes until they keep it, each weighing FOLD_WEIGHT times the fitted
# samples' mean weight per node, and the level is solved again, FOLD_PASSES times (0: off).
# Lucy level 0 (main 90503fb's base), turned over / RMS of all points: without 1.93 % /
# 0.1998; weight 1: 0.37 % / 0.2026; weight 10: 0.30 % / 0.2156.
FOLD_PASSES = 1
FOLD_KEEP = 0.1
FOLD_WEIGHT = 1.0


# ------------------------------------------------------------------ patch order
def morton_order(centres: np.ndarray, bits: int = 10) -> np.ndarray:
    """Indices sorting ``centres (F, 3)`` along the Morton (Z-order) curve of their box.

    Each coordinate is quantised to ``bits`` bits over the box and the bits interleaved
    (x, y, z from the most significant down); consecutive indices are near in space.
    """
    lo, hi = centres.min(axis=0), centres.max(axis=0)
    grid = np.floor((centres - lo) / np.maximum(hi - lo, 1e-300) * ((1 << bits) - 1))
    grid = grid.astype(np.int64)
    code = np.zeros(len(centres), np.int64)
    for bit in range(bits - 1, -1, -1):
        for axis in range(3):
            code = (code << 1) | ((grid[:, axis] >> bit) & 1)
    return np.argsort(code, kind="stable")


def _middle(start: int, stop: int) -> int:
    """Where the k-d tree halves the run ``[start, stop)`` of the patches: the one rule of
    :func:`spatial_order` and :func:`_groups`, so that every group is a box of the tree."""
    return (start + stop) // 2


def spatial_order(centres: np.ndarray, leaf: int = 4) -> np.ndarray:
    """A permutation of ``centres (F, 3)`` in k-d tree order (Bentley, *Multidimensional
    binary search trees*, 1975): the run ``[a, b)`` (first the whole) is sorted along its
    box's longest side and halved at :func:`_middle`, the lower half first, each half
    again, down to runs of at most ``leaf``, which keep their order. Every run that
    halving makes is a box of the tree, a compact piece of the object: :func:`_groups`
    cuts the patches along the same halves. Stable sorts: the same order on every machine."""
    centres = np.asarray(centres, np.float64)
    order = np.arange(len(centres))
    runs = [(0, len(centres))]
    while runs:
        start, stop = runs.pop()
        if stop - start <= leaf:
            continue
        run = order[start:stop]
        axis = int(np.argmax(np.ptp(centres[run], axis=0)))
        order[start:stop] = run[np.argsort(centres[run, axis], kind="stable")]
        middle = _middle(start, stop)
        runs += [(start, middle), (middle, stop)]
    return order


def renumber_patches(atlas: AtlasSurface, order: np.ndarray) -> AtlasSurface:
    """``atlas`` with patch ``order[k]`` renumbered ``k``: ``quads`` and the blocks of
    ``face_points`` (and their weights) permuted; vertices and edges (numbered by their
    vertices, ``client_py.atlas.atlas_edges``) unchanged, so the surface is the same."""
    inner = (atlas.side - 2) ** 2
    order = [int(f) for f in order]
    if sorted(order) != list(range(len(atlas.quads))):
        raise ValueError(f"order must be a permutation of the {len(atlas.quads)} patches")
    quads = [atlas.quads[f] for f in order]
    face_points = [p for f in order for p in atlas.face_points[f * inner:(f + 1) * inner]]
    weights = None
    if atlas.weights is not None:
        head = len(atlas.vertices) + len(atlas.edge_points)
        faces = atlas.weights[head:]
        weights = atlas.weights[:head] + [w for f in order
                                          for w in faces[f * inner:(f + 1) * inner]]
    return AtlasSurface(atlas.degree, atlas.spans, atlas.vertices, quads, atlas.edge_points,
                        face_points, weights)


# ------------------------------------------------------------------ shared coefficients
def shared_count(atlas: AtlasSurface, n: int) -> int:
    """The shared coefficients of a level of ``(n, n)`` per patch (:func:`shared_index`'s
    slots): ``V + E (n - 2) + F (n - 2)^2`` for the atlas's ``V`` vertices, ``E`` edges and
    ``F`` patches."""
    inner = n - 2
    return len(atlas.vertices) + len(atlas.edges.edges) * inner + len(atlas.quads) * inner ** 2


def shared_index(atlas: AtlasSurface, n: int) -> np.ndarray:
    """``G[f, a, b]``: the shared slot of coefficient ``(a, b)`` of patch ``f``'s ``(n, n)``
    grid, by the atlas's own rule for ``n`` per side (the ring: ``AtlasSurface.border_slots``
    at ``client_py.atlas.ring_positions``, which the packs use too): layout vertices, then
    ``n - 2`` slots per edge from its lower vertex, then the ``(n - 2)^2`` interior slots per
    patch. Shape ``(F, n, n)``."""
    inner, count = n - 2, len(atlas.quads)
    grid = np.empty((count, n, n), np.int64)
    first = shared_count(atlas, n) - count * inner * inner
    grid[:, 1:n - 1, 1:n - 1] = first + np.arange(count * inner * inner).reshape(
        count, inner, inner)
    a, b = np.array(ring_positions(n)).T
    grid[:, a, b] = [atlas.border_slots(f, n) for f in range(count)]
    return grid


def border_ring(n: int) -> np.ndarray:
    """``(n, n)`` booleans: the outermost row and column on every side."""
    ring = np.zeros((n, n), bool)
    ring[0, :] = ring[-1, :] = ring[:, 0] = ring[:, -1] = True
    return ring


# ------------------------------------------------------------------ samples
@dataclass
class AtlasSamples:
    """Surface samples sorted by patch: foot points and their split (module docstring).

    Attributes
    ----------
    patch, u, v, s, t2 : ndarray, shape (N,)
        Patch, foot point, normal offset, squared tangential remainder; sorted by ``patch``.
    offsets : ndarray, shape (F + 1,)
        Patch ``f``'s samples are ``offsets[f]:offsets[f + 1]``.
    distance : ndarray, shape (N,)
        ``|x - C|`` at the foot point.
    facing : ndarray, shape (N,)
        ``n . n_x``: the base's unit normal at the foot point against the sample's own.
    weight : ndarray, shape (N,)
        The sample's weight in the least-squares fit (:func:`surface_samples`).
    foot, normal : ndarray, shape (N, 3), optional
        The base's point ``C(u, v)`` and unit normal there, as :func:`project_samples`
        evaluated them last (:meth:`DrawnModel.feet` takes them).
    """

    patch: np.ndarray
    u: np.ndarray
    v: np.ndarray
    s: np.ndarray
    t2: np.ndarray
    offsets: np.ndarray
    distance: np.ndarray
    facing: np.ndarray
    weight: np.ndarray
    foot: np.ndarray | None = None
    normal: np.ndarray | None = None

    def of(self, f: int) -> DetailSamples:
        """Patch ``f``'s samples as ``fitter.fitting.detail.DetailSamples``."""
        lo, hi = self.offsets[f], self.offsets[f + 1]
        return DetailSamples(self.u[lo:hi], self.v[lo:hi], self.s[lo:hi], self.t2[lo:hi])

    def error(self, displacement: np.ndarray) -> np.ndarray:
        """``e = sqrt((s - D)^2 + t^2)`` per sample."""
        return np.sqrt((self.s - displacement) ** 2 + self.t2)


def median_spacing(scan: Scan, fit: AtlasFit, original: Scan | None = None) -> float:
    """The scan's resolution: median edge length of its surface (a mesh), or the median
    distance of a point to its nearest neighbour (a cloud, on a subset of 200,000 of them).

    ``original``: the points the detail is fitted to when they are not ``scan``'s (a large
    scan's, ``fitter.fitting.stream.LargeScan.detail_scan``): a mesh's median edge, over an
    even subset of :data:`MEDIAN_TRIANGLES` of its triangles; a cloud's median distance from
    200,000 of its points to their nearest other point among all of them."""
    surface = fit.surface
    if original is not None and original.faces is not None and len(original.faces):
        faces = np.asarray(original.faces)
        return median_edge(np.asarray(original.points, float),
                           faces[:: max(1, len(faces) // MEDIAN_TRIANGLES)])
    if original is not None:
        points = np.asarray(original.points, float)
        probe = points[np.random.default_rng(0).choice(len(points), min(len(points), 200_000),
                                                       replace=False)]
        d, _ = cKDTree(points).query(probe, k=2, workers=-1)
        return float(np.median(d[:, 1]))
    if surface.origin == "mesh":
        return median_edge(surface.vertices, surface.faces)
    points = scan.points
    if len(points) > 200_000:
        points = points[np.random.default_rng(0).choice(len(points), 200_000, replace=False)]
    d, _ = cKDTree(points).query(points, k=2, workers=-1)
    return float(np.median(d[:, 1]))


def surface_samples(scan: Scan, fit: AtlasFit, count: int, seed: int = 0,
                    original: Scan | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points of the scan's surface to fit the detail to, their unit normals and weights.

    A mesh: its (cleaned) vertices, weight 1, and ``count - V`` area-weighted samples of
    its triangles, together weighing ``TRIANGLE_SHARE`` of the vertices (each
    ``TRIANGLE_SHARE V / (count - V)``: :data:`TRIANGLE_SHARE` says why); a cloud: its
    points, voxel-thinned to about ``count`` when more, weight 1. A point's normal is that
    of the surface vertex nearest to it (a mesh vertex's own; a triangle sample's is its
    triangle's). Shapes ``(N, 3)``, ``(N, 3)``, ``(N,)``.

    ``original``: a large scan's own points (``fitter.fitting.stream.LargeScan.detail_scan``:
    a mesh's vertices, of which ``scan`` is the reduced working mesh; a cloud's points,
    thinned less than its working set), taken as a cloud's points are: the samples are then
    the scan's own points, not the working set's.
    """
    surface = fit.surface
    if surface.origin == "mesh" and original is None:
        points, normals = surface.vertices, surface.vertex_normals
        weights = np.ones(len(points))
        extra = count - len(points)
        if extra > 0:
            samples, sample_normals = surface.sample(extra, np.random.default_rng(seed))
            points = np.concatenate([points, samples])
            normals = np.concatenate([normals, sample_normals])
            weights = np.concatenate([weights, np.full(extra, TRIANGLE_SHARE * len(weights)
                                                       / extra)])
        return points, normals, weights
    points = scan.points if original is None else np.asarray(original.points, float)
    if len(points) > count:
        points = points[thin_to_count(points, count, slack=1.2)]
    _, nearest = cKDTree(surface.vertices).query(points, workers=-1)
    return points, surface.vertex_normals[nearest], np.ones(len(points))


def project_samples(atlas: AtlasSurface, fit: AtlasFit, points: np.ndarray,
                    normals: np.ndarray, chunk: int = CHUNK, candidates: int = 8,
                    progress: Callable[[float], None] | None = None,
                    threads: int | None = None,
                    weights: np.ndarray | None = None) -> AtlasSamples:
    """Foot points of ``points (N, 3)`` on ``atlas`` and their split, in chunks of
    ``chunk`` samples on ``threads`` threads (default: one per core); the result does not
    depend on either. ``weights (N,)`` (default 1) travel with the samples.

    The first foot point is that of a nearby working point of the base fit (``fit.points``
    with their converged ``fit.patch, u, v``): among the ``candidates`` nearest, the nearest
    whose base normal agrees with the sample's (``n . n_x > 0.5``, so a sample on the front
    of a thin wing does not start on its back; the nearest when none agrees). Then
    ``NEWTON_ITERATIONS`` Gauss-Newton steps with hops (:func:`.patches.correct_parameters`).
    The base's point and unit normal at each foot point, evaluated for the split, are kept
    (``AtlasSamples.foot``, ``normal``: :meth:`DrawnModel.feet` needs no evaluation of its
    own, 0.8-1.7 CPU-s of the 15-scan Happy Buddha's 834,718 samples).
    ``atlas`` is ``fit.atlas`` or a :func:`renumber_patches` of it (matched by its quads).

    The chunks take the samples along the Morton curve of their positions
    (:func:`morton_order`), and each result goes back to its sample's place: every
    sample's foot point is its own computation, the same numbers in any order, but
    neighbours then query the k-d tree one after another (a mesh's triangle samples come
    in random order: on 870,000 such samples of a sphere against 80,000 working points,
    the queries took 1.2 CPU-s instead of 3.1, the ordering 0.4).
    """
    old_index = {tuple(q): f for f, q in enumerate(fit.atlas.quads)}
    new_of_old = np.empty(len(atlas.quads), np.int64)
    for f, q in enumerate(atlas.quads):
        new_of_old[old_index[tuple(q)]] = f
    table, cps = index_table(atlas), control_points(atlas)
    nb = neighbour_table(atlas)
    d, s = atlas.degree, atlas.spans
    seed_f = new_of_old[np.asarray(fit.patch, np.int64)]
    seed_u, seed_v = np.asarray(fit.u, float), np.asarray(fit.v, float)
    _, su, sv = evaluate_patches(table, cps, d, s, seed_f, seed_u, seed_v, derivatives=True)
    seed_n = _cross(su, sv)
    seed_n /= np.maximum(np.linalg.norm(seed_n, axis=1, keepdims=True), 1e-300)
    tree = cKDTree(fit.points)
    k = min(candidates, len(fit.points))

    walk = morton_order(points) if len(points) else np.zeros(0, np.int64)

    def one_chunk(start: int) -> tuple[np.ndarray, ...]:
        at = walk[start:start + chunk]
        x, nx = points[at], normals[at]
        _, near = tree.query(x, k=k)
        near = near.reshape(len(x), k)
        agree = np.einsum("kc,kjc->kj", nx, seed_n[near]) > 0.5
        pick = near[np.arange(len(x)), np.where(agree.any(axis=1), np.argmax(agree, axis=1), 0)]
        f, u, v = seed_f[pick], seed_u[pick], seed_v[pick]
        f, u, v, dist = correct_parameters(table, cps, d, s, nb, x, nx, f, u, v,
                                           iterations=NEWTON_ITERATIONS)
        c, cu, cv = evaluate_patches(table, cps, d, s, f, u, v, derivatives=True)
        off, t2 = normal_split(x, c, cu, cv)
        n = _cross(cu, cv)
        facing = np.einsum("kc,kc->k", n, nx) / np.maximum(np.linalg.norm(n, axis=1), 1e-300)
        return f, u, v, off, t2, dist, facing, c, _unit(n)

    # the chunks are independent and their work is numpy on whole arrays, which releases
    # the GIL: one thread per core (as fitter.fitting.error.deviations), in order
    parts = on_threads(one_chunk, len(points), chunk, threads, progress)
    place = np.empty_like(walk)
    place[walk] = np.arange(len(walk))  # sample i's results are at place[i]
    f, u, v, off, t2, dist, facing, foot, normal = (np.concatenate(c)[place]
                                                    for c in zip(*parts, strict=True))
    order = np.argsort(f, kind="stable")
    f = f[order]
    offsets = np.searchsorted(f, np.arange(len(atlas.quads) + 1))
    weights = np.ones(len(points)) if weights is None else np.asarray(weights, float)
    return AtlasSamples(f, u[order], v[order], off[order], t2[order], offsets, dist[order],
                        facing[order], weights[order], foot[order], normal[order])


# ------------------------------------------------------------------ the drawn mesh
def drawn_triangles(u: np.ndarray, v: np.ndarray, resolution: int
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The drawn triangle of each ``(u, v) (N,)`` on a patch's ``r x r`` vertex grid
    (``r = resolution``, nodes ``(a / (r - 1), b / (r - 1))``) and its barycentric weights:
    node rows ``a (N, 3)``, columns ``b (N, 3)``, weights ``beta (N, 3)`` (sum 1).

    The client cuts cell ``(i, j)`` along its diagonal from node ``(i + 1, j)`` to
    ``(i, j + 1)`` (``client_py.tessellate.grid_indices``): with ``alpha = u (r - 1) - i``,
    ``gamma = v (r - 1) - j``, the triangle ``(i, j), (i + 1, j), (i, j + 1)`` holds
    ``alpha + gamma <= 1`` with weights ``(1 - alpha - gamma, alpha, gamma)``, and
    ``(i + 1, j + 1), (i + 1, j), (i, j + 1)`` the rest with ``(alpha + gamma - 1,
    1 - gamma, 1 - alpha)``.
    """
    cells = resolution - 1
    x, y = np.asarray(u, float) * cells, np.asarray(v, float) * cells
    i = np.clip(np.floor(x).astype(np.int64), 0, cells - 1)
    j = np.clip(np.floor(y).astype(np.int64), 0, cells - 1)
    alpha, gamma = x - i, y - j
    upper = alpha + gamma > 1.0
    a = np.stack([np.where(upper, i + 1, i), i + 1, i], axis=1)
    b = np.stack([np.where(upper, j + 1, j), j, j + 1], axis=1)
    beta = np.where(upper[:, None],
                    np.stack([alpha + gamma - 1.0, 1.0 - gamma, 1.0 - alpha], axis=1),
                    np.stack([1.0 - alpha - gamma, alpha, gamma], axis=1))
    return a, b, beta


def node_index(t: np.ndarray, resolution: int) -> np.ndarray:
    """The grid index ``a`` of drawn-node parameters ``t = a / (r - 1)`` (``r =
    resolution``), same shape, int64."""
    return np.rint(np.asarray(t) * (resolution - 1)).astype(np.int64)


def node_basis(degree: int, knots: np.ndarray, n: int, resolution: int
               ) -> tuple[np.ndarray, np.ndarray]:
    """A level's B-spline basis (``n`` functions per side over ``knots``) at the ``r``
    node parameters ``a / (r - 1)`` of a patch's drawn grid (``r = resolution``): each
    parameter's span ``(r,)`` and the products ``N_{s_a - p + x}(u_a) N_{s_b - p + y}(v_b)``
    of every node ``(a, b)`` at index ``a r + b``, shape ``(r², (p + 1)²)``, ``x`` then
    ``y`` (:func:`fitter.fitting.detail.collocation_matrix`'s row entries, in its order).
    ``client_py._numpy_basis.basis_arrays`` computes each parameter on its own, so these
    are the numbers of a collocation matrix at the nodes, computed once per parameter."""
    span, basis, _ = basis_arrays(degree, knots, n, np.arange(resolution) / (resolution - 1))
    products = basis[:, None, :, None] * basis[None, :, None, :]
    return span, products.reshape(resolution * resolution, -1)


def evaluate_at_nodes(coefficients: np.ndarray, level: int, spans: int, patch: np.ndarray,
                      u: np.ndarray, v: np.ndarray, resolution: int,
                      chunk: int = 500_000) -> np.ndarray:
    """:func:`evaluate_fields` at nodes of the patches' ``r x r`` drawn grids (``u = a /
    (r - 1)``, ``v = b / (r - 1)``, ``r = resolution``), the same numbers: the basis once
    per node parameter (:func:`node_basis`), and each node's ``(p + 1)²`` terms added in
    the collocation row's order from 0, as the sparse product adds them. On the 15-scan
    Happy Buddha's 2.55 M level-1 nodes (random coefficients), level 0's field in 0.27 CPU-s
    instead of 1.9 (load 2)."""
    F, n, _ = coefficients.shape
    knots = np.array(layers.level_knots(DEGREE, spans, level))
    span, products = node_basis(DEGREE, knots, n, resolution)
    local = (np.arange(DEGREE + 1)[:, None] * n + np.arange(DEGREE + 1)).reshape(-1)
    flat = coefficients.reshape(-1)
    out = np.empty(len(u))
    for lo in range(0, len(u), chunk):
        a, b = node_index(u[lo:lo + chunk], resolution), node_index(v[lo:lo + chunk], resolution)
        first = (span[a] - DEGREE) * n + span[b] - DEGREE + patch[lo:lo + chunk] * (n * n)
        node = a * resolution + b
        total = np.zeros(len(a))
        for term, step in zip(products.T, local, strict=True):
            total += term[node] * flat[first + step]
        out[lo:lo + chunk] = total
    return out


def _unit(rows: np.ndarray) -> np.ndarray:
    return rows / np.maximum(np.linalg.norm(rows, axis=1, keepdims=True), 1e-300)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a × b`` of 3-vectors along the last axis: ``np.cross``'s numbers to the bit
    (``a_y b_z - a_z b_y``, ...), in a sixth to an eighth of its time on millions of
    rows (the detail of a 2.24 M-triangle scan spent 8.5 s in ``np.cross``)."""
    a, b = np.asarray(a), np.asarray(b)
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), np.result_type(a, b))
    for k, (i, j) in enumerate(((1, 2), (2, 0), (0, 1))):
        np.subtract(a[..., i] * b[..., j], a[..., j] * b[..., i], out=out[..., k])
    return out


def node_frames(atlas: AtlasSurface, resolution: int, patch: np.ndarray, a: np.ndarray,
                b: np.ndarray, chunk: int = CHUNK) -> tuple[np.ndarray, np.ndarray]:
    """The base position ``C_f(node)`` and the displacement direction ``d`` the client
    draws node ``(a, b)`` of patch ``f``'s ``r x r`` grid with (``r = resolution``;
    ``patch, a, b (K,)``), shapes ``(K, 3)``: ``d`` the base's unit normal there, or on a
    border node the normalised sum of the unit normals of every patch that samples it
    (``client_py.atlas_mesh``; :class:`DrawnModel`).

    Each node is evaluated once: the border sums take the unit normals of the nodes asked
    for (a node's normal is its own computation, the same numbers in any batch) and
    evaluate only the border nodes not among them (none for :func:`level_nodes`)."""
    table, cps = index_table(atlas), control_points(atlas)
    d, spans = atlas.degree, atlas.spans
    F, r = len(atlas.quads), resolution
    G = shared_index(atlas, r)
    node_c = np.empty((len(patch), 3))
    node_d = np.empty((len(patch), 3))

    def frames(lo: int) -> None:
        hi = lo + chunk
        node_c[lo:hi], cu, cv = evaluate_patches(table, cps, d, spans, patch[lo:hi],
                                                 a[lo:hi] / (r - 1), b[lo:hi] / (r - 1),
                                                 derivatives=True)
        node_d[lo:hi] = _unit(_cross(cu, cv))

    on_threads(frames, len(patch), chunk)
    # border nodes' directions: the sum of every sampling patch's unit normal per slot
    t = np.arange(r)
    last = np.full(r, r - 1)
    rim_a = np.concatenate([t, t, 0 * t, last])
    rim_b = np.concatenate([0 * t, last, t, t])
    rf = np.repeat(np.arange(F), len(rim_a))
    ra, rb = np.tile(rim_a, F), np.tile(rim_b, F)
    asked = (np.asarray(patch, np.int64) * r + a) * r + b
    order = np.argsort(asked, kind="stable")
    rim_key = (rf * r + ra) * r + rb
    at = np.minimum(np.searchsorted(asked[order], rim_key), max(len(asked) - 1, 0))
    known = (asked[order][at] == rim_key) if len(asked) else np.zeros(len(rim_key), bool)
    normal = np.empty((len(rim_key), 3))
    normal[known] = node_d[order[at[known]]]
    if not known.all():
        _, cu, cv = evaluate_patches(table, cps, d, spans, rf[~known], ra[~known] / (r - 1),
                                     rb[~known] / (r - 1), derivatives=True)
        normal[~known] = _unit(_cross(cu, cv))
    total = np.zeros((int(G.max()) + 1, 3))
    np.add.at(total, G[rf, ra, rb], normal)
    total = _unit(total)
    rim = (a == 0) | (a == r - 1) | (b == 0) | (b == r - 1)
    node_d[rim] = total[G[patch[rim], a[rim], b[rim]]]
    return node_c, node_d


@dataclass
class DrawnModel:
    """The mesh the client draws at one level's resolution, linearised at the samples.

    The client draws node ``(a, b)`` of patch ``f``'s ``r x r`` grid at
    ``C_f(node) + D_f(node) d_i`` (``client_py.atlas_mesh``): ``d_i`` the base's unit
    normal there, or on a border node the normalised sum of the unit normals of the patches
    that sample it (and ``D`` the mean of their displacements: equal, by the borders'
    shared coefficients). A sample ``x`` with foot point ``C(u, v)``, unit normal ``n`` and
    offset ``s = (x - C) . n`` lies over the drawn triangle of nodes ``i = 1..3`` with
    weights ``beta_i`` (:func:`drawn_triangles`); its offset from that triangle along
    ``n`` is

        ``y - sum_i w_i D(node_i)``,  ``y = s + (C(u, v) - sum_i beta_i C_i) . n``,
        ``w_i = beta_i max(d_i . n, MIN_DIRECTION)``

    (``y - s``: the base's own chord; the floor: :data:`MIN_DIRECTION`). A level fitted to
    these rows fits what is drawn
    (two vertices per span: the quadratic field drawn as its chords; the border's averaged
    directions where the base creases between patches), not the smooth field the client
    never draws: on the bunny, the field's RMS over all points drawn at 17 nodes per
    patch side was 3.17e-5 and 2.79e-5 at 65 (the chords' share).

    Attributes
    ----------
    resolution : int
    u, v : ndarray, shape (N, 3)
        Each sample's three nodes as its patch's parameters ``a / (r - 1)``, ``b / (r - 1)``.
    weight : ndarray, shape (N, 3)
        ``w_i``.
    target : ndarray, shape (N,)
        ``y``.
    """

    resolution: int
    u: np.ndarray
    v: np.ndarray
    weight: np.ndarray
    target: np.ndarray
    node: np.ndarray
    node_patch: np.ndarray
    node_u: np.ndarray
    node_v: np.ndarray

    @staticmethod
    def feet(atlas: AtlasSurface, samples: AtlasSamples, chunk: int = CHUNK
             ) -> tuple[np.ndarray, np.ndarray]:
        """Each sample's foot point ``C(u, v)`` and the base's unit normal ``n`` there, shapes
        ``(N, 3)``: the same at every level, so :meth:`of` takes them once computed; those
        :func:`project_samples` kept (``samples.foot``, ``samples.normal``: each point's own
        evaluation, the same numbers) when it has them."""
        if samples.foot is not None and samples.normal is not None:
            return samples.foot, samples.normal
        table, cps = index_table(atlas), control_points(atlas)
        foot = np.empty((len(samples.u), 3))
        normal = np.empty((len(samples.u), 3))

        def one(lo: int) -> None:
            hi = lo + chunk
            foot[lo:hi], cu, cv = evaluate_patches(table, cps, atlas.degree, atlas.spans,
                                                   samples.patch[lo:hi], samples.u[lo:hi],
                                                   samples.v[lo:hi], derivatives=True)
            normal[lo:hi] = _unit(_cross(cu, cv))

        on_threads(one, len(samples.u), chunk)
        return foot, normal

    @classmethod
    def of(cls, atlas: AtlasSurface, samples: AtlasSamples, resolution: int,
           chunk: int = CHUNK, feet: tuple[np.ndarray, np.ndarray] | None = None,
           frames: LevelNodes | None = None) -> DrawnModel:
        """The model of ``atlas``'s mesh drawn at ``resolution`` nodes per patch side
        (``feet``: :meth:`feet`, computed here when not given).

        Each node some sample's triangle uses is evaluated once (``node``: the index of
        sample ``k``'s node ``i`` among them), not once per sample that uses it: the same
        numbers, a third of the evaluations at the finest level and far fewer below.
        ``frames``: the level's :class:`LevelNodes` at this resolution, whose positions and
        directions (:func:`node_frames` of every node) are taken instead of evaluating the
        samples' nodes again: the same numbers (each node's frame is its own)."""
        r = resolution
        a, b, beta = drawn_triangles(samples.u, samples.v, r)
        # the nodes the samples' triangles use, each once: position and displacement direction
        # np.unique(keys, return_inverse=True) of keys below F r²: a mark per node, O(N)
        keys = (samples.patch[:, None] * r + a) * r + b
        used = np.zeros(len(atlas.quads) * r * r, bool)
        used[keys] = True
        nodes = np.flatnonzero(used)
        node = (np.cumsum(used) - 1)[keys]
        nf, na, nb = nodes // (r * r), nodes // r % r, nodes % r
        if frames is not None:  # all_nodes' order: node (f, a, b) at index (f r + a) r + b
            if frames.resolution != r or frames.patches != len(atlas.quads):
                raise ValueError(f"frames of {frames.patches} patches at {frames.resolution} "
                                 f"nodes a side for a model at {r} of {len(atlas.quads)}")
            node_c, node_d = frames.position[nodes], frames.direction[nodes]
        else:
            node_c, node_d = node_frames(atlas, r, nf, na, nb, chunk)
        foot, normal = feet if feet is not None else cls.feet(atlas, samples, chunk)
        weight = np.empty_like(beta)
        target = samples.s.copy()

        def one(lo: int) -> None:
            hi = lo + chunk
            c, n = foot[lo:hi], normal[lo:hi]
            for i in range(3):
                at = node[lo:hi, i]
                weight[lo:hi, i] = beta[lo:hi, i] * np.maximum(
                    np.einsum("kc,kc->k", node_d[at], n), MIN_DIRECTION)
                target[lo:hi] += beta[lo:hi, i] * np.einsum("kc,kc->k", c - node_c[at], n)

        on_threads(one, len(samples.u), chunk)
        return cls(r, a / (r - 1), b / (r - 1), weight, target, node, nf, na / (r - 1),
                   nb / (r - 1))

    def rows(self, degree: int, knots: np.ndarray, n: int, lo: int, hi: int,
             block: np.ndarray, blocks: int) -> sp.csr_matrix:
        """Samples ``lo:hi``'s rows ``sum_i w_i N(node_i)`` over the level's coefficients
        (the rows of :func:`fitter.fitting.detail.collocation_matrix` with ``block``,
        ``blocks``, weighted and summed).

        The nodes' basis products are computed once per node (:func:`node_basis`). A row's
        three nodes are at most ``g`` spans apart (``g = 1`` at two nodes per span), so its
        entries lie in a window of ``(p + 1 + g)^2`` coefficients: each node's
        ``w_i N_a(u_i) N_b(v_i)`` is added into it, node after node (``(w_0 x_0 + w_1 x_1) +
        w_2 x_2``, as the sum of the three weighted collocation matrices adds them), and the
        window's non-zeros are the row's entries, in ascending columns. On a 15-scan Happy
        Buddha level-0 batch (1,173 patches, 408,505 rows) 0.53 CPU-s instead of 1.10 for
        the three matrices' weighted sum; the same matrix, bit for bit
        (``tests/test_atlas_detail_fit.py``)."""
        r, m, p = self.resolution, hi - lo, degree
        span, products = node_basis(p, knots, n, r)
        a, b = node_index(self.u[lo:hi], r), node_index(self.v[lo:hi], r)  # (m, 3)
        first_a, first_b = span[a] - p, span[b] - p  # each node's first coefficient
        corner_a = first_a.min(axis=1, initial=n)  # the window's first row and column
        corner_b = first_b.min(axis=1, initial=n)
        first_a -= corner_a[:, None]
        first_b -= corner_b[:, None]
        side = int(max(first_a.max(initial=0), first_b.max(initial=0))) + p + 1
        local = (np.arange(p + 1)[:, None] * side + np.arange(p + 1)).reshape(-1)
        window = np.zeros(m * side * side)
        start = np.arange(m) * (side * side)
        for i in range(3):  # node after node: (w_0 x_0 + w_1 x_1) + w_2 x_2
            at = (start + first_a[:, i] * side + first_b[:, i])[:, None] + local
            window[at] += self.weight[lo:hi, i, None] * products[a[:, i] * r + b[:, i]]
        window = window.reshape(m, side * side)
        entry = window != 0
        corner = corner_a * n + corner_b + np.asarray(block, np.int64) * (n * n)
        columns = (corner[:, None] + (np.arange(side)[:, None] * n + np.arange(side))
                   .reshape(-1))[entry]
        indptr = np.concatenate([[0], np.cumsum(entry.sum(axis=1))])
        return sp.csr_matrix((window[entry], columns, indptr), shape=(m, blocks * n * n))

    def drawn(self, coefficients: np.ndarray, level: int, spans: int) -> np.ndarray:
        """``sum_i w_i D(node_i)`` of level ``level``'s field ``coefficients (F, n, n)``
        (``D`` evaluated once per node, :func:`evaluate_at_nodes`)."""
        at_nodes = evaluate_at_nodes(coefficients, level, spans, self.node_patch, self.node_u,
                                     self.node_v, self.resolution)
        return sum(self.weight[:, i] * at_nodes[self.node[:, i]] for i in range(3))


@dataclass
class PullRows:
    """Drawn nodes far from the scan, each pulled toward its closest scan point
    (:func:`far_node_rows`), sorted by patch.

    Attributes
    ----------
    patch, u, v : ndarray, shape (R,)
        The node's patch and its parameters ``a / (r - 1)``, ``b / (r - 1)``.
    target : ndarray, shape (R,)
        ``(q - X) . d``: the level's displacement that brings the node ``X`` (the base and
        the levels before) nearest to ``q`` along its direction ``d``.
    offsets : ndarray, shape (F + 1,)
        Patch ``f``'s rows are ``offsets[f]:offsets[f + 1]``.
    weight : float or ndarray, shape (R,)
        Each row's weight in the sum of squares.
    """

    patch: np.ndarray
    u: np.ndarray
    v: np.ndarray
    target: np.ndarray
    offsets: np.ndarray
    weight: float | np.ndarray


def all_nodes(patches: int, resolution: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every node ``(f, a, b)`` of the ``r x r`` grids of ``patches`` patches
    (``r = resolution``), node ``(f, a, b)`` at index ``(f r + a) r + b``; each ``(F r²,)``."""
    r = resolution
    return (np.repeat(np.arange(patches), r * r), np.tile(np.repeat(np.arange(r), r), patches),
            np.tile(np.arange(r), patches * r))


def grid_triangles(patches: int, resolution: int) -> np.ndarray:
    """The client's triangles over :func:`all_nodes` (``client_py.tessellate.grid_indices``
    of one patch's ``r x r`` grid, the client's own cut), patch after patch, shape
    ``(2 F (r - 1)², 3)``."""
    from client_py.tessellate import grid_indices

    r = resolution
    cell = np.asarray(grid_indices(r, r, kernel="python"), np.int64).reshape(-1, 3)
    return (np.arange(patches)[:, None, None] * r * r + cell[None]).reshape(-1, 3)


def fold_shrink(before: np.ndarray, step: np.ndarray, keep: float) -> np.ndarray:
    """The largest share ``s`` in ``[0, 1]`` of a level's displacement ``step (T, 3, 3)``
    (per triangle, per corner) with which each triangle ``before + s step`` (corners
    ``before (T, 3, 3)``: the base and the levels before) keeps ``keep`` of its facing
    area: ``g(s) = N(s) . N(0) >= keep |N(0)|²``, ``N(s)`` the triangle's area vector.

    ``g(s) = α + β s + γ s²`` with ``E_i`` the edges of ``before`` and ``e_i`` those of
    ``step`` (``i = 1, 2``): ``α = |N(0)|²``, ``β = (E_1 × e_2 + e_1 × E_2) . N(0)``,
    ``γ = (e_1 × e_2) . N(0)``. ``s = 1`` where ``g(1) >= keep α`` (or ``α = 0``), else the
    smallest root of ``g(s) = keep α`` in ``(0, 1)``: ``g`` starts above it and ends below,
    so one exists. Returns ``(T,)``."""
    E1, E2 = before[:, 1] - before[:, 0], before[:, 2] - before[:, 0]
    e1, e2 = step[:, 1] - step[:, 0], step[:, 2] - step[:, 0]
    n0 = _cross(E1, E2)
    alpha = np.einsum("tc,tc->t", n0, n0)
    beta = np.einsum("tc,tc->t", _cross(E1, e2) + _cross(e1, E2), n0)
    gamma = np.einsum("tc,tc->t", _cross(e1, e2), n0)
    c0 = (1.0 - keep) * alpha  # g(s) - keep α = c0 + β s + γ s²
    s = np.ones(len(alpha))
    low = (c0 + beta + gamma < 0) & (alpha > 0)
    b, g, c = beta[low], gamma[low], c0[low]
    disc = np.sqrt(np.maximum(b * b - 4.0 * g * c, 0.0))
    flat = np.abs(g) <= 1e-12 * (np.abs(b) + c)
    # the smaller positive root: for γ ≠ 0, 2c / (-b ± disc) (stable form), c > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = np.where(flat, -c / b, 2.0 * c / (-b + disc))
        r2 = np.where(flat, np.inf, 2.0 * c / (-b - disc))
    roots = np.where((r1 > 0) & np.isfinite(r1), r1, np.inf)
    roots = np.minimum(roots, np.where((r2 > 0) & np.isfinite(r2), r2, np.inf))
    s[low] = np.clip(roots, 0.0, 1.0)
    return s


@dataclass
class LevelNodes:
    """Every node of the mesh drawn at one level's resolution (:func:`all_nodes` order),
    made once per level for its far rows and its fold rows (:func:`level_nodes`).

    Attributes
    ----------
    patches, resolution : int
        ``F`` and ``r``.
    patch, u, v : ndarray, shape (F r²,)
        The node's patch and its parameters ``a / (r - 1)``, ``b / (r - 1)``.
    position, direction : ndarray, shape (F r², 3)
        ``C_f(node)`` and the direction ``d`` the client draws it with (:func:`node_frames`).
    before : ndarray, shape (F r²,)
        The levels before's displacement there, ``sum_j D_j(node)``.
    """

    patches: int
    resolution: int
    patch: np.ndarray
    u: np.ndarray
    v: np.ndarray
    position: np.ndarray
    direction: np.ndarray
    before: np.ndarray


def level_nodes(atlas: AtlasSurface, fields: list[np.ndarray], level: int, spans: int,
                chunk: int = CHUNK) -> LevelNodes:
    """:class:`LevelNodes` of the mesh drawn at level ``level``'s resolution with the levels
    before it (``fields``)."""
    F, r = len(atlas.quads), atlas_level_resolution(spans, level)
    f, a, b = all_nodes(F, r)
    c, d = node_frames(atlas, r, f, a, b, chunk)
    u, v = a / (r - 1), b / (r - 1)
    before = sum((evaluate_at_nodes(q, j, spans, f, u, v, r) for j, q in enumerate(fields)),
                 np.zeros(len(f)))
    return LevelNodes(F, r, f, u, v, c, d, before)


def fold_node_rows(nodes: LevelNodes, coefficients: np.ndarray, level: int, spans: int,
                   weight: float, keep: float = FOLD_KEEP) -> PullRows:
    """Rows against the drawn triangles that turn over (module docstring, "Folds").

    The mesh drawn at level ``level``'s resolution with the levels before it (``nodes``:
    :func:`level_nodes`) and this level's ``coefficients (F, n, n)``; a drawn triangle that
    keeps less than
    ``keep`` of the base's drawn triangle at the same nodes (area vectors ``N_k . N_b <
    keep |N_b|²``: turned over, or nearly, so that rounding the level may turn it), where
    the base triangle faces its patch's way (``N_b . a_f > 0``, ``a_f = Σ N_b`` over the
    patch: a pleat of the base itself is left to the base), gets rows ``D_k(node) = s
    D_k(node)`` at its three nodes, ``s`` from :func:`fold_shrink` with the base and the
    levels before as ``before`` (at level 0 the base itself; the smallest ``s`` of the
    node's triangles), each weighing ``weight``."""
    F, r = nodes.patches, nodes.resolution
    f, u, v, c, d = nodes.patch, nodes.u, nodes.v, nodes.position, nodes.direction
    own = evaluate_at_nodes(coefficients, level, spans, f, u, v, r)
    cell = grid_triangles(1, r)
    share = np.ones(len(f))
    per_chunk = max(1, CHUNK // (r * r))  # patches a chunk: their nodes are theirs alone

    def chunk(first: int) -> None:
        last = min(F, first + per_chunk)
        lo, hi = first * r * r, last * r * r
        tri = grid_triangles(last - first, r)  # this chunk's nodes, from lo
        pc = c[lo:hi]
        base_area = _cross(pc[tri[:, 1]] - pc[tri[:, 0]], pc[tri[:, 2]] - pc[tri[:, 0]])
        owner = np.repeat(np.arange(last - first), len(cell))
        # bincount: np.add.at's sums, in the same order, 5 times faster
        patch_area = np.column_stack([np.bincount(owner, base_area[:, k],
                                                  minlength=last - first) for k in range(3)])
        x = pc + nodes.before[lo:hi, None] * d[lo:hi]
        step = own[lo:hi, None] * d[lo:hi]
        y = x + step
        drawn_area = _cross(y[tri[:, 1]] - y[tri[:, 0]], y[tri[:, 2]] - y[tri[:, 0]])
        kept = np.einsum("tc,tc->t", drawn_area, base_area)
        turned = ((kept < keep * np.einsum("tc,tc->t", base_area, base_area))
                  & (np.einsum("tc,tc->t", base_area, patch_area[owner]) > 0))
        tri = tri[turned]
        s = fold_shrink(x[tri], step[tri], keep)
        np.minimum.at(share[lo:hi], tri.reshape(-1), np.repeat(s, 3))

    on_threads(chunk, F, per_chunk)
    at = np.flatnonzero(share < 1.0)
    return PullRows(f[at], u[at], v[at], share[at] * own[at],
                    np.searchsorted(f[at], np.arange(F + 1)), weight)


def merged_rows(first: PullRows | None, second: PullRows) -> PullRows:
    """The rows of both, sorted by patch (stable: ``first``'s before), each keeping its
    weight."""
    if first is None:
        return second
    patch = np.concatenate([first.patch, second.patch])
    order = np.argsort(patch, kind="stable")
    patch = patch[order]
    weight = np.concatenate([np.broadcast_to(first.weight, first.target.shape),
                             np.broadcast_to(second.weight, second.target.shape)])
    return PullRows(patch, np.concatenate([first.u, second.u])[order],
                    np.concatenate([first.v, second.v])[order],
                    np.concatenate([first.target, second.target])[order],
                    np.searchsorted(patch, np.arange(len(first.offsets))), weight[order])


def far_node_rows(nodes: LevelNodes, scan_mesh: tuple[np.ndarray, np.ndarray], reach: float,
                  weight: float) -> PullRows:
    """The nodes of the mesh drawn at a level's resolution with the levels before it
    (``nodes``: :func:`level_nodes`) that lie farther than ``reach`` from the scan's
    surface ``scan_mesh (vertices, faces)``, each with the row ``D_f(node) = (q - X) . d``
    (module docstring, "Far nodes"): ``X = C + sum_j D_j d`` the drawn node, ``q`` its
    closest point on the scan's triangles, ``d`` its direction (:func:`node_frames`). Only
    the nodes farther than ``reach`` are measured exactly (:func:`.measure.farther_than`)."""
    from .measure import farther_than

    f, d = nodes.patch, nodes.direction
    x = nodes.position + d * nodes.before[:, None]
    vertices, faces = scan_mesh
    far, _, q = farther_than(x, vertices, faces, reach)
    target = np.einsum("kc,kc->k", q - x[far], d[far])
    return PullRows(f[far], nodes.u[far], nodes.v[far], target,
                    np.searchsorted(f[far], np.arange(nodes.patches + 1)), weight)


# ------------------------------------------------------------------ drawn cells
def scan_distance(scan: Scan) -> Callable[[np.ndarray], np.ndarray]:
    """``distance(positions (m, 3)) -> (m,)``: each position's distance to the scan's
    surface, a mesh's triangles (:func:`.measure.closest_points_on_mesh`) or a cloud's
    nearest point (a KD-tree of all its points), in chunks of ``CHUNK`` positions."""
    from .measure import closest_points_on_mesh

    points = np.asarray(scan.points, dtype=float)
    if scan.faces is not None and len(scan.faces):
        faces = np.asarray(scan.faces)

        def one(x: np.ndarray) -> np.ndarray:
            return closest_points_on_mesh(x, points, faces)[0]
    else:
        tree = cKDTree(points)

        def one(x: np.ndarray) -> np.ndarray:
            return tree.query(x, workers=-1)[0]
    return lambda x: np.concatenate([one(x[lo:lo + CHUNK]) for lo in range(0, len(x), CHUNK)]
                                    or [np.zeros(0)])


def lattice_weights(steps: int, corners: bool = True) -> np.ndarray:
    """Barycentric weights ``(a, b, c) / n`` (``a + b + c = n = steps``) of a triangle's
    lattice of ``steps`` steps a side, shape ``(S, 3)``; without the three corners if
    ``corners`` is false."""
    n = steps
    return np.array([(a, b, n - a - b) for a in range(n + 1) for b in range(n + 1 - a)
                     if corners or max(a, b, n - a - b) < n], float) / n


def reaching_cells(cells: np.ndarray, distance: Callable[[np.ndarray], np.ndarray],
                   reach: float, lattice: int = CELL_LATTICE, finest: int = FINEST_LATTICE
                   ) -> np.ndarray:
    """Which of ``cells (C, 2, 3, 3)`` (each cell's two triangles' corners) reach farther
    than ``reach`` from the scan (``distance``), shape ``(C,)``.

    A triangle reaches farther where a point of its lattice of ``n`` steps a side
    (:func:`lattice_weights`) does, ``n = lattice`` first. Every point of the triangle lies
    in one of the lattice's ``n²`` small triangles, within ``h = e / (n sqrt 3)`` of one of
    its corners (``e`` the triangle's longest edge: a triangle's point farthest from its
    corners is its circumcentre, at ``e / (2 sin A) <= e / sqrt 3`` when acute, or on its
    longest edge, at ``<= e / 2``), and a distance to a set is 1-Lipschitz: so a triangle
    whose lattice stays within ``reach - h`` does not reach farther, and one whose lattice
    stays within ``reach`` but not within ``reach - h`` is sampled again on a lattice twice
    as fine, until ``finest`` steps (then taken as within ``reach``, by at most
    ``e / (finest sqrt 3)``). On the 15-scan Happy Buddha's level 0 (main 5dba071), the
    lattice of 4 alone left 44 cells reaching 1.00-1.05 % of the diagonal (a lattice of 8
    a side measured), one of them the third farthest place of the drawn mesh (1.01 %)."""
    out = np.zeros(len(cells), bool)
    corners = np.asarray(cells, dtype=float).reshape(-1, 3, 3)  # triangle after triangle
    edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(axis=1)
    open_ = np.arange(len(corners))
    n = lattice
    while len(open_):
        x = np.einsum("sk,mkc->msc", lattice_weights(n), corners[open_])
        largest = distance(x.reshape(-1, 3)).reshape(len(open_), -1).max(axis=1)
        out[open_[largest > reach] // 2] = True
        unsure = (largest <= reach) & (largest > reach - edges[open_] / (n * math.sqrt(3)))
        open_ = open_[unsure & ~out[open_ // 2]]
        n *= 2
        if n > finest:
            break
    return out


def far_cells(vertices: np.ndarray, faces: np.ndarray, patches: int, resolution: int,
              points: np.ndarray, distance: Callable[[np.ndarray], np.ndarray], reach: float,
              lattice: int = CELL_LATTICE, slack: float = HANDOVER_SLACK,
              within: float | None = HANDOVER_WITHIN) -> np.ndarray:
    """``(F, r - 1, r - 1)`` booleans: the cells of an atlas mesh drawn at ``r =
    resolution`` samples per patch side that reach farther than ``reach`` from the scan and
    whose near scan points keep their distance to the mesh without them (module
    docstring, "Drawn cells").

    The mesh, ``vertices (V, 3)`` and ``faces (T, 3)``: patch after patch, cell ``(i, j)``
    row-major in ``u``, its triangles ``(a, b, d)``, ``(d, b, c)`` with ``a = (i, j)``, ``b
    = (i + 1, j)``, ``c = (i + 1, j + 1)``, ``d = (i, j + 1)`` (``client_py.atlas_mesh``
    with every cell). ``points (N, 3)``: the scan's points; ``distance``: to the scan's
    surface (:func:`scan_distance`).

    Reaching farther: :func:`reaching_cells` (``lattice`` steps a side first), for the
    cells with ``dist(c) + rho > reach`` (``c`` the mean of the four corners, ``rho`` their
    largest distance from it: every point of the cell is within ``rho`` of ``c``), their
    corners first (shared by neighbours). The closest point on the mesh of a scan point
    ``p`` within ``reach`` of it lies in a cell only if ``dist(p, c) <= rho + reach``; the
    closest points (:func:`.measure.closest_points_on_mesh`) are found for the points that
    near a reaching cell's centre (with those cells' largest ``rho``). A reaching cell
    holding some of them (their *holders*) is left out only if each holder's distance to
    the mesh without the cells left out grows by at most ``slack`` times ``reach``, or ends
    within ``within`` times ``reach`` if it was, else within ``reach`` (the closest-point
    role handed to a cell that stays; ``within = None``: the slack alone); a cell a holder
    loses more by stays, and the others are tried again without it, until no holder loses
    more. So every scan point within ``reach`` of the mesh keeps its distance within
    ``slack reach`` or the bound it met (a farther one, such as an outlier left out of the
    fit, may lose more).

    Raises
    ------
    ValueError
        A mesh that is not ``F`` whole grids of ``r x r`` samples.
    """
    from .measure import closest_points_on_mesh

    cells = resolution - 1
    if len(faces) != 2 * patches * cells * cells:
        raise ValueError(f"a mesh of {len(faces)} triangles is not {patches} patches of "
                         f"{cells}x{cells} whole cells")
    tri = np.asarray(faces).reshape(-1, 2, 3)
    corners = vertices[np.stack([tri[:, 0, 0], tri[:, 0, 1], tri[:, 1, 2], tri[:, 0, 2]], 1)]
    centre = corners.mean(axis=1)
    rho = np.linalg.norm(corners - centre[:, None], axis=2).max(axis=1)
    far = np.zeros(len(centre), bool)
    maybe = np.flatnonzero(distance(centre) + rho > reach)
    if len(maybe):  # the corners first (shared by neighbours), then the lattices
        ends, at = np.unique(tri[maybe][:, [0, 1], :].reshape(len(maybe), -1),
                             return_inverse=True)
        far[maybe] = (distance(vertices[ends]) > reach)[at.reshape(len(maybe), -1)].any(axis=1)
        maybe = maybe[~far[maybe]]
    if len(maybe):
        far[maybe] = reaching_cells(vertices[tri[maybe]], distance, reach, lattice)
    stray = np.flatnonzero(far)
    if len(stray):  # the holders of a near scan point's closest point on the mesh
        bound = float(rho[stray].max()) + reach
        gap, _ = cKDTree(centre[stray]).query(points, distance_upper_bound=bound, workers=-1)
        near = points[gap <= bound]
        found = [closest_points_on_mesh(near[lo:lo + CHUNK], vertices, faces)[:2]
                 for lo in range(0, len(near), CHUNK)]
        held = np.concatenate([d for d, _ in found] or [np.zeros(0)])
        hit = np.concatenate([t for _, t in found] or [np.zeros(0, np.int64)]) // 2
        mine = far[hit] & (held <= reach)  # a farther point (an outlier) may lose more
        holders, held, hit = near[mine], held[mine], hit[mine]
        if len(hit):  # the cells within a holder's reach once the slack is added
            # the farthest each may end: the slack, or the bound of the issue's two it meets
            bound = (held + slack * reach if within is None
                     else np.where(held <= within * reach, within * reach, reach))
            radius = float(np.maximum(held + slack * reach, bound).max() + rho.max())
            gap, _ = cKDTree(holders).query(centre, distance_upper_bound=radius, workers=-1)
            local = np.flatnonzero(gap <= radius)
        while len(hit):  # hand the role over where the holders lose at most the slack
            drawn = local[~far[local]]
            if not len(drawn):
                lost = np.ones(len(hit), bool)
            else:
                d, _, _ = closest_points_on_mesh(holders, vertices, tri[drawn].reshape(-1, 3))
                lost = (d > held + slack * reach) & (d > bound)
            if not lost.any():
                break
            far[hit[lost]] = False
            keep = far[hit]
            holders, held, hit, bound = holders[keep], held[keep], hit[keep], bound[keep]
    return far.reshape(patches, cells, cells)


def level_far_cells(atlas: AtlasSurface, tiles: list[dict], level: int, spans: int,
                    points: np.ndarray, distance: Callable[[np.ndarray], np.ndarray],
                    reach: float) -> np.ndarray:
    """:func:`far_cells` of the mesh drawn at level ``level`` (``tiles``: per level ``0..
    level``, ``{patch: [(tile, bytes, error)]}``, drawn with every cell: walls masks put
    aside) at its resolution (``client_py.bundle.atlas_level_resolution``)."""
    from dataclasses import replace

    from .measure import drawn_mesh

    detail: dict = {}
    for made in tiles[: level + 1]:
        for f, some in made.items():
            detail.setdefault(f, []).extend(replace(t, walls=None) for t, _, _ in some)
    r = atlas_level_resolution(spans, level)
    mesh = drawn_mesh(atlas, r, detail)
    return far_cells(mesh.vertices, mesh.faces, len(atlas.quads), r, points, distance, reach)


# ------------------------------------------------------------------ depth
def patch_sides(atlas: AtlasSurface, samples: int = 9) -> np.ndarray:
    """Mean length of each patch's four border curves (polylines of ``samples`` points),
    shape (F,)."""
    table, cps = index_table(atlas), control_points(atlas)
    t = np.linspace(0.0, 1.0, samples)
    zeros, ones = np.zeros_like(t), np.ones_like(t)
    total = np.zeros(len(atlas.quads))
    F = len(atlas.quads)
    for uu, vv in ((t, zeros), (ones, t), (t, ones), (zeros, t)):
        f = np.repeat(np.arange(F), samples)
        (c,) = evaluate_patches(table, cps, atlas.degree, atlas.spans, f, np.tile(uu, F),
                                np.tile(vv, F))
        c = c.reshape(F, samples, 3)
        total += np.linalg.norm(np.diff(c, axis=1), axis=2).sum(axis=1)
    return total / 4


def most_levels(patches: int, spans: int = SPANS) -> tuple[int, str]:
    """The most levels ``L`` an atlas of ``patches`` patches holds (module docstring,
    "Depth"): each level's knots drawn at two vertices a span within the client's
    ``ATLAS_MAX_RESOLUTION`` samples per patch side, at most ``MAX_LEVEL + 1`` levels, and
    the finest level's ``patches (m 2^(L-1) + p)^2`` coefficients within
    ``MAX_COEFFICIENTS``; with why level ``L`` is not held."""
    for level in range(layers.MAX_LEVEL + 1):
        finer = spans << level
        if 2 * finer + 1 > ATLAS_MAX_RESOLUTION:
            return level, (f"level {level} would be drawn at {2 * finer + 1} samples a patch "
                           f"side, over the viewer's {ATLAS_MAX_RESOLUTION}")
        if patches * (finer + DEGREE) ** 2 > MAX_COEFFICIENTS:
            return level, (f"level {level} would have {patches * (finer + DEGREE) ** 2:,} "
                           f"coefficients, over {MAX_COEFFICIENTS:,}")
    return layers.MAX_LEVEL + 1, f"a pyramid has at most {layers.MAX_LEVEL + 1} levels"


def auto_levels(side: float, spacing: float, patches: int, spans: int = SPANS) -> int:
    """Levels ``0..L-1``: the fewest whose finest knot spacing ``side / (m 2^(L-1))``
    reaches ``spacing``, within :func:`most_levels` (at least 1)."""
    most = max(1, most_levels(patches, spans)[0])
    levels = 1
    while side / (spans << (levels - 1)) > spacing and levels < most:
        levels += 1
    return levels


def held_out(count: int, seed: int = 0) -> np.ndarray:
    """``(count,)`` booleans: a fixed pseudo-random one in ``HELD_OUT`` of the samples."""
    return np.random.default_rng(seed).integers(0, HELD_OUT, count) == 0


def fit_samples(samples: AtlasSamples, spacing: float, side: float,
                offset_limit: float = OFFSET_LIMIT) -> np.ndarray:
    """The samples a displacement along the normal can explain, ``(N,)`` booleans: a
    foot point that is an orthogonal projection (tangential remainder ``t`` within the
    scan's ``spacing``: not clamped on an open border or stuck at a fold), an offset
    ``|s|`` within ``offset_limit`` median patch ``side``s (a larger one would be a spike, not
    detail: the base missed that part), and a base normal at the foot point that agrees with
    the sample's own (``n . n_x >= MIN_FACING``): a sample of the back of a thin part
    projected onto its front would pull the front through it (on Lucy, 0.5 cut the drawn
    area farther than 1 % of the diagonal from the scan from 4.3 % to 3.0 % at the finest
    level, and the RMS a little). The others still count in every error figure."""
    return ((samples.t2 <= spacing * spacing) & (np.abs(samples.s) <= offset_limit * side)
            & (samples.facing >= MIN_FACING))


# ------------------------------------------------------------------ one level
def solve_spd_blocks(M: sp.spmatrix, rhs: np.ndarray, size: int) -> np.ndarray:
    """``M^-1 rhs`` for a block-diagonal symmetric positive definite ``M`` of equal blocks
    of ``size`` unknowns: each block's band Cholesky factorisation ``M_b = U^T U`` and two
    triangular solves in the block's own order (LAPACK ``dpbtrf``/``dpbtrs``; Golub & Van
    Loan, *Matrix Computations*, 4th ed., 4.3.5).

    A patch's unknowns are its ``(n, n)`` grid row by row (or the inside of its border
    ring, row by row), and a coefficient meets only those within ``max(p + 1, 2)`` of it
    along ``u`` and ``v`` (a drawn triangle's three nodes' supports, :class:`DrawnModel`,
    and the smoothing's second differences), so a block is a band of half-width about
    ``3 n``: 105 at level 2 (``n = 34``). Dense band kernels on that band beat SuperLU's
    sparse factorisation of the same blocks under a minimum-degree order (session 24,
    216 level-2 patches of random rows: 0.30 s against 1.1 s; 771 level-1 patches 0.35 s
    against 1.0 s), and each block is solved alone, so its numbers do not depend on the
    batch it is in. A block that is not numerically positive definite (``dpbtrf`` stops
    at a pivot <= 0: no patch's ``A^T A + mu R`` with ``mu > 0`` should be) is solved by
    dense least squares, its minimum-norm solution.
    ``tests/test_atlas_solve.py`` holds it to each patch's dense least squares."""
    from scipy.linalg import lapack

    M = sp.csr_matrix(M, copy=True)  # summing duplicates must not change the caller's
    M.sum_duplicates()
    blocks = M.shape[0] // size
    if blocks * size != M.shape[0] or M.shape[0] != M.shape[1] or len(rhs) != M.shape[0]:
        raise ValueError(f"a block-diagonal system of blocks of {size} unknowns was expected, "
                         f"got a matrix {M.shape} and {len(rhs)} right-hand sides")
    coo = M.tocoo()
    if np.any(coo.row // size != coo.col // size):
        raise ValueError(f"the matrix is not block-diagonal in blocks of {size} unknowns")
    upper = coo.col >= coo.row
    row, col, data = coo.row[upper], coo.col[upper], coo.data[upper]
    block = row // size
    local_row, local_col = row - block * size, col - block * size
    bounds = np.searchsorted(block, np.arange(blocks + 1))  # row-sorted: each block's run
    out = np.empty((blocks, size))
    right = np.asarray(rhs, np.float64).reshape(blocks, size)
    for b in range(blocks):
        lo, hi = bounds[b], bounds[b + 1]
        i, j = local_row[lo:hi], local_col[lo:hi]
        width = int((j - i).max(initial=0))  # the block's own: its numbers are its own
        # LAPACK's upper band storage, ab[w + i - j, j], in Fortran order (factored in place)
        band = np.zeros((width + 1, size), order="F")
        band[width + i - j, j] = data[lo:hi]
        factor, info = lapack.dpbtrf(band, lower=0, overwrite_ab=1)
        if info == 0:
            out[b], info = lapack.dpbtrs(factor, right[b], lower=0)
        if info != 0:
            dense = M[b * size:(b + 1) * size, b * size:(b + 1) * size].toarray()
            out[b] = np.linalg.lstsq(dense, right[b], rcond=None)[0]
    return out.reshape(-1)


class _BatchSystem:
    """The normal equations of one level's fit, a batch of patches at a time: ``M = A^T A +
    diag(mu_f) (x) R`` and ``A^T r`` (:func:`_solve_blocks` says what ``A``, ``r``, ``mu_f``,
    ``weights``, ``model``, ``rows`` and ``pull`` are), shared by the solves and by
    :func:`quantised_blocks` so that both minimise the same objective."""

    def __init__(self, samples: AtlasSamples, residual: np.ndarray, level: int, spans: int,
                 weights: np.ndarray | None, model: DrawnModel | None, rows: dict | None,
                 pull: PullRows | None) -> None:
        self.samples, self.residual, self.weights = samples, residual, weights
        self.model, self.rows, self.pull = model, rows, pull
        F = len(samples.offsets) - 1
        self.F = F
        self.n = n = (spans << level) + DEGREE
        self.knots = np.array(layers.level_knots(DEGREE, spans, level))
        self.R = regularisation(n).tocsr()
        # the typical patch's data weight per coefficient: a patch with few samples is held
        # to at least MU_FLOOR of it, so its field stays smooth instead of swinging
        total = float(np.sum(weights)) if weights is not None else float(len(samples.u))
        per_sample = total / max(F, 1) / (n * n)
        self.mu_floor = max(MU_FLOOR * per_sample / ((DEGREE + 1) ** 2), 1e-12)
        # batches of at most BATCH_UNKNOWNS, as many as a multiple of the cores this process
        # may run on (cores.usable_cores), of equal size, so that the solves keep every core
        # busy to the end (the 15-scan Happy Buddha's level 1, 2,346 patches of 771 a batch
        # at most: 4 of 587, not 3 of 771 and one of 33, which one core solved alone); a
        # level within one (every level 0 of the benchmark's objects) in one batch per core.
        # Each patch's block is solved alone, the same numbers in any batch
        # (quantised_blocks keeps one lambda for a level within one, one per batch beyond)
        self.rate_batch = max(1, BATCH_UNKNOWNS // (n * n))
        cores = usable_cores()
        rounds = -(-F // (self.rate_batch * cores))  # batches per core
        self.per_batch = max(1, -(-F // (rounds * cores)))

    def normal(self, first: int) -> tuple[sp.csr_matrix, np.ndarray, np.ndarray]:
        """Patches ``first:first + per_batch``'s ``M``, ``A^T r`` and ``diag(A^T A)``."""
        last = min(self.F, first + self.per_batch)
        A, r = self._batch_rows(first)
        return self._equations(A, r, last - first)

    def normal_of(self, patches: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray, np.ndarray]:
        """:meth:`normal` of the patches ``patches`` (ascending, within :attr:`per_batch`),
        block ``i`` patch ``patches[i]``: each block's rows are those it has in its own batch,
        in the same order (the weighted data rows kept in ``rows``, then its ``pull`` rows),
        so each block's ``M``, ``A^T r`` and solution are the full batch's, to the bit."""
        nn = self.n * self.n
        offsets = self.samples.offsets
        spans, values = [], []
        for first in np.unique(patches // self.per_batch * self.per_batch):
            mine = patches[(patches >= first) & (patches < first + self.per_batch)]
            A, r, _ = self._data_rows(int(first))
            lo = offsets[first]
            take = np.concatenate([np.arange(offsets[f], offsets[f + 1]) for f in mine]) - lo
            part = A[take]
            block = np.searchsorted(patches, first + part.indices // nn)
            spans.append(sp.csr_matrix((part.data, block * nn + part.indices % nn,
                                        part.indptr), shape=(len(take), len(patches) * nn)))
            values.append(r[take])
        pull = self.pull
        if pull is not None:
            take = np.concatenate([np.arange(pull.offsets[f], pull.offsets[f + 1])
                                   for f in patches])
            if len(take):
                root = np.sqrt(np.broadcast_to(pull.weight, pull.target.shape)[take])
                spans.append(sp.diags(root) @ collocation_matrix(
                    DEGREE, self.knots, self.n, pull.u[take], pull.v[take],
                    block=np.searchsorted(patches, pull.patch[take]), blocks=len(patches)))
                values.append(root * pull.target[take])
        return self._equations(sp.vstack(spans).tocsr(), np.concatenate(values), len(patches))

    def _data_rows(self, first: int) -> tuple[sp.csr_matrix, np.ndarray, int]:
        """Patches ``first:first + per_batch``'s weighted sample rows and residual, and their
        count ``m``: the batch's rows kept in ``rows`` (:meth:`_batch_rows`: the first ``m``
        are the samples'), or made."""
        entry = None if self.rows is None else self.rows.get(first)
        if entry is not None:
            return entry[0], entry[1], entry[2]
        samples, n, knots = self.samples, self.n, self.knots
        last = min(self.F, first + self.per_batch)
        lo, hi = samples.offsets[first], samples.offsets[last]
        count = last - first
        if self.model is None:
            A = collocation_matrix(DEGREE, knots, n, samples.u[lo:hi], samples.v[lo:hi],
                                   block=samples.patch[lo:hi] - first, blocks=count)
        else:
            A = self.model.rows(DEGREE, knots, n, lo, hi, samples.patch[lo:hi] - first, count)
        r = self.residual[lo:hi]
        if self.weights is not None:
            root = np.sqrt(self.weights[lo:hi])
            A, r = sp.diags(root) @ A, root * r
        return A, r, hi - lo

    def _batch_rows(self, first: int) -> tuple[sp.csr_matrix, np.ndarray]:
        """Patches ``first:first + per_batch``'s rows ``A`` and right-hand side ``r``: the
        weighted samples' rows, then ``pull``'s rows of these patches. Kept in ``rows`` with
        the ``pull`` they were made with; a later ``pull`` (more rows: the fold rows) keeps
        the sample rows and appends its own."""
        entry = None if self.rows is None else self.rows.get(first)
        if entry is not None and entry[3] is self.pull:
            return entry[0], entry[1]
        A, r, data = self._data_rows(first)
        if A.shape[0] > data:  # the rows of an earlier pull after them
            A, r = A[:data], r[:data]
        last = min(self.F, first + self.per_batch)
        count = last - first
        pull = self.pull
        if pull is not None and pull.offsets[last] > pull.offsets[first]:
            plo, phi = pull.offsets[first], pull.offsets[last]
            root = np.sqrt(np.broadcast_to(pull.weight, pull.target.shape)[plo:phi])
            A = sp.vstack([A, sp.diags(root) @ collocation_matrix(
                DEGREE, self.knots, self.n, pull.u[plo:phi], pull.v[plo:phi],
                block=pull.patch[plo:phi] - first, blocks=count)]).tocsr()
            r = np.concatenate([r, root * pull.target[plo:phi]])
        if self.rows is not None:
            self.rows[first] = A, r, data, pull
        return A, r

    def _equations(self, A: sp.csr_matrix, r: np.ndarray, count: int
                   ) -> tuple[sp.csr_matrix, np.ndarray, np.ndarray]:
        """``M``, ``A^T r`` and ``diag(A^T A)`` of ``count`` patches' rows ``A``."""
        n = self.n
        AtA = (A.T @ A).tocsr()
        diag = AtA.diagonal()
        mu = np.maximum(diag.reshape(count, n * n).sum(axis=1) / (n * n), self.mu_floor)
        M = (AtA + sp.kron(sp.diags(mu), self.R)).tocsr()
        return M, A.T @ r, diag


def _solve_blocks(samples: AtlasSamples, residual: np.ndarray, level: int, spans: int,
                  fixed: np.ndarray | None = None, weights: np.ndarray | None = None,
                  threads: int | None = None, model: DrawnModel | None = None,
                  rows: dict | None = None, pull: PullRows | None = None,
                  patches: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Every patch's level-``level`` coefficients ``(F, n, n)`` fitted to ``residual``
    (``fitter.fitting.detail.fit_level``'s objective per patch), and the data weight
    ``diag(A_f^T A_f)`` of each coefficient, ``(F, n, n)``.

    With ``fixed (F, n, n)`` the border ring holds those values and only the interior is
    solved: ``M_II c_I = A_I^T r - M_IB c_B`` (the same quadratic, minimised with ``c_B``
    given). ``model``: the rows are those of the drawn mesh (:class:`DrawnModel`), not
    the field's own collocation. ``weights (N,)``: each sample's weight ``w`` in the sum
    of squares,
    ``sum w (A c - r)^2`` (0: left out; default 1). ``mu_f`` is
    at least ``MU_FLOOR`` of the mean patch's (a patch with few or no samples gets the
    smoothest field through its border, or zero, rather than one swinging between them).
    The patches are solved in batches of about ``BATCH_UNKNOWNS`` unknowns
    (:func:`solve_spd_blocks`), the batches on ``threads`` threads (default: one per
    core; LAPACK and the sparse products release the GIL); the result does not depend
    on the thread count. ``rows``: a dict that keeps each batch's weighted rows and
    residual, filled by the first call given it and read by the next (the border-held
    solve has the independent solve's rows: on the 15-scan Happy Buddha they were a third
    of the solves' CPU time); the same numbers either way. ``pull``: the far drawn nodes'
    rows (:func:`far_node_rows`), appended to their patch's, each weighing
    ``pull.weight``.

    ``patches`` (ascending): only these patches are solved, the results' rows in that
    order, shapes ``(len(patches), n, n)``; ``rows`` must hold their batches' rows (a
    solve of every patch given the same ``rows`` made them): each patch's numbers are those
    of the solve of every patch, to the bit (:meth:`_BatchSystem.normal_of`; the re-solve
    after the fold rows, :func:`_solve_level`).
    """
    F = len(samples.offsets) - 1
    n = (spans << level) + DEGREE
    ring = border_ring(n).reshape(-1)
    free = np.flatnonzero(~ring) if fixed is not None else np.arange(n * n)
    held = np.flatnonzero(ring)
    chosen = np.arange(F) if patches is None else np.asarray(patches, np.int64)
    out = np.zeros((len(chosen), n, n))
    weight = np.zeros((len(chosen), n, n))
    system = _BatchSystem(samples, residual, level, spans, weights, model, rows, pull)

    def one_batch(first: int) -> None:
        last = min(len(chosen), first + system.per_batch)
        count = last - first
        M, rhs, diag = (system.normal(first) if patches is None
                        else system.normal_of(chosen[first:last]))
        weight[first:last] = diag.reshape(count, n, n)
        if fixed is None:
            out[first:last] = solve_spd_blocks(M, rhs, n * n).reshape(count, n, n)
            return
        cols_free = (np.arange(count)[:, None] * n * n + free[None, :]).reshape(-1)
        cols_held = (np.arange(count)[:, None] * n * n + held[None, :]).reshape(-1)
        c_held = fixed[chosen[first:last]].reshape(count, n * n)[:, held].reshape(-1)
        M_rows = M[cols_free]  # taken once for both column sets
        M_free = M_rows[:, cols_free]
        b = rhs[cols_free] - M_rows[:, cols_held] @ c_held
        c = np.zeros(count * n * n)
        c[cols_free] = solve_spd_blocks(M_free, b, len(free))
        c[cols_held] = c_held
        out[first:last] = c.reshape(count, n, n)

    on_threads(one_batch, len(chosen), system.per_batch, threads)
    return out, weight


def coupling_stride(degree: int = DEGREE) -> int:
    """The least index distance (along ``u`` or ``v``) at which two coefficients of one
    patch share no term of the level's objective: ``max(p + 1, 2) + 1`` (a patch's normal
    matrix couples coefficients within ``max(p + 1, 2)`` of each other along ``u`` and
    ``v``: a drawn triangle's three nodes' supports and the smoothing's second
    differences)."""
    return max(degree + 1, 2) + 1


def quantised_blocks(samples: AtlasSamples, residual: np.ndarray, level: int, spans: int,
                     coefficients: np.ndarray, step: float, limit: np.ndarray,
                     weights: np.ndarray | None = None, model: DrawnModel | None = None,
                     rows: dict | None = None, pull: PullRows | None = None,
                     sweeps: int | None = None, rate: float | None = None,
                     threads: int | None = None, shared: np.ndarray | None = None
                     ) -> np.ndarray:
    """The level's integer coefficients ``q (F, n, n)``: ``rint(c / step)`` of the fitted
    ``coefficients``, then each value moved to the integer that minimises the level's own
    objective (:func:`_solve_blocks`, :class:`_BatchSystem`) given all the others:
    :func:`atlas.lattice.lattice_descent` on the lattice ``step Z`` (the formulas and
    references are there), ``J(c) = c^T M c - 2 b^T c``.

    The sweeps minimise ``J + lambda sum |q|`` (anchored at 0), ``|q|`` standing for the
    integer's bits (the packs code a zero flag and the magnitude in unary bins,
    ``client_py.atlas_detail``), ``lambda = rate step^2 m`` with ``m`` the median ``M_ii``
    of the batch's interior (one median per batch of at most :data:`BATCH_UNKNOWNS`,
    :class:`_BatchSystem`, so a level of several such batches has a ``lambda`` each; a
    level within one, solved in one batch per core, has the median of them all), within
    the patch's bound
    ``|q_i| <= Q_f =
    rint(limit_f / step)`` (:func:`bounded_by_residual`, ``limit (F,)``, the bound plain
    rounding of a bounded value keeps): a coefficient the samples hardly see (small
    ``M_ii``) is zeroed sooner. Rounding alone adds ``step^2 / 12`` of noise to every
    coefficient, which the drawn surface shows where the samples are (Laurana level 0: 28 %
    of the squared error of all points, Lucy 26 %, docs/benchmarks.md session 14).

    Each patch's interior is moved first, its border ring held. Coefficients
    ``coupling_stride`` apart in ``u`` or ``v`` share no term of ``J``, so one colour of the
    ``stride^2`` colouring ``(a mod stride, b mod stride)`` is updated at once, exactly as
    one at a time. At most ``sweeps`` (default :data:`QUANTISE_SWEEPS`) sweeps over the
    colours, fewer once none moves. The batches on ``threads`` threads (default: one per
    core), each writing only its own patches' rows, as :func:`_solve_blocks`.

    The border ring: its values are the shared slots' means, equal on both sides of a
    border (:func:`_share_borders`), and their integers must stay equal. Without ``shared``
    it is plain rounding. With ``shared (F, n, n)`` (:func:`shared_index`) each of its
    slots is then moved as one value, the interiors held (:func:`_ring_descent`), and the
    interiors moved again from the new ring: each step lowers ``J + lambda sum |q|`` or
    keeps it (module docstring, "Quantisation": what it gains, and why a cloud's ring
    stays rounded).
    """
    sweeps = QUANTISE_SWEEPS if sweeps is None else sweeps
    rate = QUANTISE_RATE if rate is None else rate
    F, n, _ = coefficients.shape
    q = np.rint(coefficients / step)
    if sweeps <= 0:
        return q.astype(np.int64)
    system = _BatchSystem(samples, residual, level, spans, weights, model, rows, pull)
    stride = coupling_stride()
    a, b = np.divmod(np.arange(n * n), n)
    # the border ring not moved: colour -1
    colour = np.where(border_ring(n).reshape(-1), -1, (a % stride) * stride + b % stride)
    bound = np.rint(limit / step)  # (F,): each patch's largest |q|

    def equations(first: int) -> tuple[sp.csr_matrix, np.ndarray, np.ndarray, np.ndarray]:
        """The batch's ``M``, ``A^T r``, ``diag(M)`` and its interior values moved."""
        count = min(F, first + system.per_batch) - first
        M, rhs, _ = system.normal(first)
        diag = M.diagonal()
        return M, rhs, diag, np.flatnonzero((np.tile(colour, count) >= 0) & (diag > 0))

    def weight_of(diag: np.ndarray) -> float:
        # the rate's weight: lambda = rate * step^2 * the median data weight of a coefficient
        return rate * step * step * float(np.median(diag)) if len(diag) else 0.0

    def descend(first: int, M: sp.csr_matrix, rhs: np.ndarray, diag: np.ndarray,
                inside: np.ndarray, lam: float) -> None:
        last = min(F, first + system.per_batch)
        count = last - first
        high = np.repeat(bound[first:last], n * n)
        # lambda in steps, lambda / (2 M_ii step^2) (this order of operations kept: the bytes)
        shrink = np.zeros(len(diag))
        shrink[inside] = lam / (2.0 * diag[inside] * step * step)
        q[first:last] = lattice_descent(M, rhs, q[first:last].reshape(-1), 0.0, step, -high,
                                        high, np.tile(colour, count), sweeps, shrink,
                                        0).reshape(count, n, n)

    lams: dict[int, float] = {}  # per batch
    if F <= system.rate_batch:  # one lambda over the level's batches
        made = on_threads(equations, F, system.per_batch, threads)
        lam = weight_of(np.concatenate([diag[inside] for _, _, diag, inside in made]))
        lams = dict.fromkeys(range(0, F, system.per_batch), lam)

        def normal(first: int) -> tuple[sp.csr_matrix, np.ndarray]:
            return made[first // system.per_batch][:2]

        def interiors() -> None:
            on_threads(lambda first: descend(first, *made[first // system.per_batch], lam), F,
                       system.per_batch, threads)
    else:
        def normal(first: int) -> tuple[sp.csr_matrix, np.ndarray]:
            return system.normal(first)[:2]

        def one_batch(first: int) -> None:
            M, rhs, diag, inside = equations(first)
            lams[first] = weight_of(diag[inside])
            descend(first, M, rhs, diag, inside, lams[first])

        def interiors() -> None:
            on_threads(one_batch, F, system.per_batch, threads)
    interiors()
    if shared is None:
        return q.astype(np.int64)
    # a slot's rate weight: the level's lambda (the median of the batches' when they differ)
    q = _ring_descent(q, shared, system.per_batch, normal, step, bound,
                      float(np.median(list(lams.values()))), sweeps)
    interiors()
    return q.astype(np.int64)


def _ring_descent(q: np.ndarray, shared: np.ndarray, per_batch: int,
                  normal: Callable[[int], tuple[sp.csr_matrix, np.ndarray]], step: float,
                  bound: np.ndarray, lam: float, sweeps: int) -> np.ndarray:
    """``q (F, n, n)`` with its border ring's shared slots (``shared (F, n, n)``:
    :func:`shared_index`) moved by :func:`atlas.lattice.lattice_descent`, the interiors held
    (:func:`quantised_blocks`).

    With ``c_f = step q_f`` split into ring ``r`` and interior ``i``, the batches' ``J =
    sum_f c_f^T M_f c_f - 2 b_f^T c_f`` (``normal(first)``: the batch's ``M`` and ``b``) is,
    in the ring's slots ``s`` (``c_r = P s``, ``P`` a 0/1 matrix picking each ring value's
    slot), ``s^T H s - 2 g^T s`` plus a constant, ``H = sum P^T M_rr P`` and ``g = sum P^T
    (b_r - M_ri c_i)``: a slot's terms are those of every patch that holds it. Its rate
    ``lambda |q_s|`` counts once (a welded pack codes a shared slot once), its bound is the
    least of its patches' ``bound (F,)`` (it is a coefficient of each), or its start where
    that is larger (the rounded shared mean of bounded values: the descent never ends worse
    than it began), and the slots are coloured by :func:`atlas.lattice.coupling_colours`
    of ``H``."""
    F, n, _ = q.shape
    nn = n * n
    ring = border_ring(n).reshape(-1)
    at_ring, at_inner = np.flatnonzero(ring), np.flatnonzero(~ring)
    slot_ids, slot_of = np.unique(shared.reshape(F, nn)[:, at_ring], return_inverse=True)
    slot_of = slot_of.reshape(F, len(at_ring))
    count = len(slot_ids)
    H = sp.csr_matrix((count, count))
    g = np.zeros(count)
    for first in range(0, F, per_batch):
        last = min(F, first + per_batch)
        M, rhs = normal(first)
        local = np.arange(last - first)[:, None] * nn
        rows, inner = (local + at_ring).reshape(-1), (local + at_inner).reshape(-1)
        M_ring = M[rows]
        slots = slot_of[first:last].reshape(-1)
        P = sp.csr_matrix((np.ones(len(slots)), (np.arange(len(slots)), slots)),
                          shape=(len(slots), count))
        H = H + P.T @ M_ring[:, rows] @ P
        np.add.at(g, slots, rhs[rows] - M_ring[:, inner] @ (
            step * q[first:last].reshape(-1, nn)[:, at_inner].reshape(-1)))
    H = H.tocsr()
    codes = np.zeros(count, np.int64)
    codes[slot_of] = q.reshape(F, nn)[:, at_ring]  # equal in every patch of a slot
    high = np.full(count, np.inf)
    np.minimum.at(high, slot_of, np.broadcast_to(bound[:, None], slot_of.shape))
    high = np.maximum(high, np.abs(codes))  # never out of bounds at the start: never worse
    diag = H.diagonal()
    shrink = np.zeros(count)
    seen = diag > 0
    shrink[seen] = lam / (2.0 * diag[seen] * step * step)
    moved = lattice_descent(H, g, codes, 0.0, step, -high, high, coupling_colours(H), sweeps,
                            shrink, 0)
    out = q.reshape(F, nn).copy()
    out[:, at_ring] = moved[slot_of]
    return out.reshape(F, n, n)


def bounded_by_residual(coefficients: np.ndarray, samples: AtlasSamples,
                        residual: np.ndarray, use: np.ndarray,
                        reach: float = COEFFICIENT_REACH) -> np.ndarray:
    """Each patch's coefficients ``(F, n, n)`` clipped to ``+-reach R_f``, ``R_f`` the
    largest ``|residual|`` of its fitted samples (``use``); 0 for a patch without any.

    Applied to the independent fits before their borders are shared: a border coefficient
    that a patch's own samples hardly hold (they lie on one side of it, or the drawn rows
    of :class:`DrawnModel` reach it through one node) can come out far beyond anything the
    samples ask, and the shared mean carries it to the neighbour. On Nefertiti, border
    coefficients of 32 where the samples' offsets stay within 2.6 drew a flap 1.52 % of the
    diagonal from the scan; clipped at twice the residual, the largest distance of the
    drawn mesh to the scan is 0.88 % (Laurana 1.58 -> 1.20 %, Lucy 1.96 -> 1.82 %) and the
    RMS over all points moves by under 1.5 %.
    """
    limit = reach * _largest_residual(samples, residual, use)[:, None, None]
    return np.clip(coefficients, -limit, limit)


def _largest_residual(samples: AtlasSamples, residual: np.ndarray, use: np.ndarray
                      ) -> np.ndarray:
    """Each patch's largest ``|residual|`` over its fitted samples ``use``, shape (F,)."""
    bound = np.zeros(len(samples.offsets) - 1)
    np.maximum.at(bound, samples.patch[use], np.abs(residual[use]))
    return bound


def _share_borders(coefficients: np.ndarray, weight: np.ndarray, G: np.ndarray) -> np.ndarray:
    """Each shared border slot of ``G (F, n, n)`` set to the data-weighted mean of the
    patches' values there (module docstring); interior values unchanged."""
    ring = border_ring(G.shape[1])
    slots = G[:, ring]
    w = weight[:, ring] + 1e-12 * max(float(weight.mean()), 1e-300)
    total = np.zeros(G.max() + 1)
    norm = np.zeros(G.max() + 1)
    np.add.at(total, slots, w * coefficients[:, ring])
    np.add.at(norm, slots, w)
    out = coefficients.copy()
    out[:, ring] = total[slots] / norm[slots]
    return out


def evaluate_fields(coefficients: np.ndarray, level: int, spans: int, patch: np.ndarray,
                    u: np.ndarray, v: np.ndarray, chunk: int = 500_000) -> np.ndarray:
    """``D_{f,k}(u, v)`` of every patch's ``(n, n)`` grid at samples ``(patch, u, v)``."""
    F, n, _ = coefficients.shape
    knots = np.array(layers.level_knots(DEGREE, spans, level))
    flat = coefficients.reshape(-1)
    out = np.empty(len(u))
    for lo in range(0, len(u), chunk):
        hi = lo + chunk
        A = collocation_matrix(DEGREE, knots, n, u[lo:hi], v[lo:hi], block=patch[lo:hi],
                               blocks=F)
        out[lo:hi] = A @ flat
    return out


def border_jump(atlas: AtlasSurface, fields: list[np.ndarray], spans: int,
                per_span: int = 4) -> dict:
    """``|D_f - D_g|`` of the summed levels ``fields`` (coefficients ``(F, n_k, n_k)`` of
    levels ``0..k``) at ``per_span`` points per finest span along every shared edge:
    RMS and max."""
    finest = spans << (len(fields) - 1)
    t = np.linspace(0.0, 1.0, per_span * finest + 1)
    ends: tuple[list, list] = ([], [])  # (patch, u, v) per side of every shared edge
    for pairs in atlas.edges.faces:
        if len(pairs) != 2:
            continue
        same = atlas.edges.sides[pairs[0][0]][pairs[0][1]][1] == \
            atlas.edges.sides[pairs[1][0]][pairs[1][1]][1]
        for out, (f, k), par in zip(ends, pairs, (t, t if same else 1.0 - t), strict=True):
            zero, one = np.zeros_like(par), np.ones_like(par)
            uu, vv = ((par, zero), (one, par), (par, one), (zero, par))[k]
            out.append((np.full(len(par), f), uu, vv))
    if not ends[0]:
        return {"rms": 0.0, "max": 0.0, "samples": 0}
    pf, pu, pv = (np.concatenate(a) for a in zip(*ends[0], strict=True))
    qf, qu, qv = (np.concatenate(a) for a in zip(*ends[1], strict=True))
    a = sum(evaluate_fields(c, k, spans, pf, pu, pv) for k, c in enumerate(fields))
    b = sum(evaluate_fields(c, k, spans, qf, qu, qv) for k, c in enumerate(fields))
    jump = np.abs(a - b)
    return {"rms": float(np.sqrt(np.mean(jump ** 2))), "max": float(jump.max()),
            "samples": int(len(jump))}


# ------------------------------------------------------------------ the pyramid
@dataclass
class DetailPyramid:
    """The atlas's detail pyramid as fitted, before its packs are coded
    (:func:`fit_detail_pyramid`; :func:`pack_pyramid` codes them).

    Everything a drawn mesh needs is here (``atlas``, ``tiles``, ``levels[k]["resolution"]``,
    :meth:`detail_up_to`), so the error report can tessellate and measure the levels while
    the packs, pure-Python range coding under the GIL, are written beside it
    (``atlas.pipeline.fit_atlas_bundle``).

    Attributes
    ----------
    atlas : AtlasSurface
        The base with its patches renumbered (:func:`renumber_patches`): write THIS as
        ``base.tsa``; the tiles' patch indices refer to it.
    order : ndarray, shape (F,)
        ``atlas``'s patch ``k`` is ``fit.atlas``'s patch ``order[k]``.
    tiles : list of dict of int to list of DetailTile
        ``tiles[k][f]``: patch ``f``'s level-``k`` tiles (for ``client_py.atlas_mesh``).
    levels : list of dict
        Per level ``level``, ``rms``, ``max`` (sample errors after levels ``0..k``),
        ``resolution``, ``step``, ``walls`` and ``border_jump`` (``{rms, max}`` of
        ``|D_f - D_g|`` on shared borders after levels ``0..k``); :class:`AtlasDetail`'s
        also ``bytes`` (its packs) and ``packs``.
    samples : int
    spacing : float
        The scan's median edge length / point spacing the depth aims at.
    patch_side : float
        Median patch side length.
    timings : dict
        Seconds per step.
    spans : int
        Spans per tile side.
    base : tuple of float
        The samples' RMS and max error over the base alone.
    worst : list of ndarray, shape (F,)
        Per level, the largest sample error of each patch after levels ``0..k``.
    reach : ndarray, shape (F,)
        Each patch's largest displacement, ``sum_k max |D_k|`` (its group's bounding sphere).
    held_out : dict or None
        The manifest's ``tiles.detail.held_out`` (module docstring, "Depth").
    """

    atlas: AtlasSurface
    order: np.ndarray
    tiles: list
    levels: list
    samples: int
    spacing: float
    patch_side: float
    timings: dict
    spans: int
    base: tuple[float, float]
    worst: list
    reach: np.ndarray
    held_out: dict | None

    def detail_up_to(self, level: int) -> dict:
        """``{patch: [tiles of levels 0..level]}`` for ``client_py.atlas_mesh``."""
        out: dict = {}
        for k in range(level + 1):
            for f, tiles in self.tiles[k].items():
                out.setdefault(f, []).extend(tiles)
        return out


@dataclass
class AtlasDetail(DetailPyramid):
    """The atlas's detail pyramid, ready for the bundle: a :class:`DetailPyramid` with its
    packs (:func:`pack_pyramid`).

    Attributes
    ----------
    tree : dict
        The manifest's ``tiles.detail`` (docs: the module docstring and the manifest spec).
    files : dict of str to bytes
        ``pack_name(k, g)`` -> the pack's bytes.
    """

    tree: dict = field(default_factory=dict)
    files: dict = field(default_factory=dict)


@dataclass
class WeldedSolve:
    """One level's welded solve (:func:`_solve_level`), kept for a re-solve with more rows.

    Attributes
    ----------
    coefficients : ndarray, shape (F, n, n)
        The welded coefficients, before quantisation.
    free, weight : ndarray, shape (F, n, n)
        The independent solve's coefficients and data weights ``diag(A_f^T A_f)``.
    shared : ndarray, shape (F, n, n)
        The border ring's shared values the interior was solved with.
    rows : dict
        The batches' rows (:class:`_BatchSystem`), for the quantisation and a re-solve.
    """

    coefficients: np.ndarray
    free: np.ndarray
    weight: np.ndarray
    shared: np.ndarray
    rows: dict


def _solve_level(samples: AtlasSamples, residual: np.ndarray, level: int, spans: int,
                 fit_weight: np.ndarray, use: np.ndarray, model: DrawnModel, G: np.ndarray,
                 pull: PullRows | None, again: WeldedSolve | None = None,
                 changed: np.ndarray | None = None) -> WeldedSolve:
    """One level's welded coefficients ``(F, n, n)`` before quantisation and the batches'
    rows (module docstring, "Welded borders"): the independent solve, its border
    coefficients bounded and shared (``G``: :func:`shared_index`), the interior solved again
    with the border ring held.

    ``again``: the solve before ``pull`` gained rows at the patches ``changed`` (``(F,)``
    booleans: the fold rows). Each patch's independent solve is its own block, so only
    the ``changed`` patches are solved again; the border slots are shared again, and only the
    patches whose shared ring moved (the ``changed`` and their neighbours across the slots
    their ring shares) have their interior solved again. Every other patch's numbers are
    ``again``'s, which a solve of every patch would give again: the same coefficients, to
    the bit (``tests/test_atlas_detail_fit.py``)."""
    rows = {} if again is None else again.rows  # the batches' rows, made once for all solves
    solve = functools.partial(_solve_blocks, samples, residual, level, spans,
                              weights=fit_weight, model=model, rows=rows, pull=pull)
    if again is None:
        free, weight = solve()
    else:
        redo = np.flatnonzero(changed)
        free, weight = again.free.copy(), again.weight.copy()
        if len(redo):
            free[redo], weight[redo] = solve(patches=redo)
    shared = _share_borders(bounded_by_residual(free, samples, residual, use), weight, G)
    if again is None:
        c, _ = solve(fixed=shared)
    else:
        ring = border_ring(shared.shape[1])
        redo = np.flatnonzero(changed | (shared[:, ring] != again.shared[:, ring]).any(axis=1))
        c = again.coefficients.copy()
        if len(redo):
            c[redo], _ = solve(fixed=shared, patches=redo)
    # the interior's re-solve can overshoot as the independent fit did (the bunny: an 8 mm
    # spike from 0.7 mm offsets at a corner of a patch): the same bound, the border ring kept
    # (shared, bounded already, and equal on both sides of a border)
    inner = ~border_ring(c.shape[1])
    c[:, inner] = bounded_by_residual(c, samples, residual, use)[:, inner]
    return WeldedSolve(c, free, weight, shared, rows)


def _tick(timings: dict, name: str, clock: float) -> float:
    """Add the seconds since ``clock`` to ``timings[name]``; returns the time now."""
    now = time.perf_counter()
    timings[name] = timings.get(name, 0.0) + now - clock
    return now


def _rounded(x: float) -> float:
    return float(f"{x:.6g}")


def _rounded_up(x: float, digits: int = 3) -> float:
    """``x >= 0`` rounded up to ``digits`` significant digits: a bound stays a bound (a
    group's radius, a pack's ``geometric_error``) in fewer of the manifest's bytes. ``x``
    itself where no such number is at least ``x`` (not finite, or beyond the decimal
    steps of a double); 0 for ``x <= 0``."""
    if x <= 0:
        return 0.0
    if not math.isfinite(x):
        return x
    step = 10.0 ** (math.floor(math.log10(x)) - digits + 1)
    if not step > 0:
        return x
    for extra in (0, 1):  # x / step may round down to a whole number just under x
        up = float(f"{(math.ceil(x / step) + extra) * step:.{digits}g}")
        if up >= x:
            return up
    return x


def _bounding_sphere(points: np.ndarray, reach: float) -> tuple[list[float], float]:
    """A sphere holding ``points (n, 3)`` widened by ``reach``, short to write: its centre
    the box's middle rounded to a hundredth of the radius's order of magnitude (as it is
    for a radius of 0), its radius measured from that centre and rounded up to 3
    significant digits."""
    middle = 0.5 * (points.min(axis=0) + points.max(axis=0))
    spread = float(np.linalg.norm(points - middle, axis=1).max()) + reach
    step = 10.0 ** (math.floor(math.log10(spread)) - 2) if spread > 0 else 0.0
    centre = [float(x) for x in middle]
    if step > 0 and all(math.isfinite(x / step) for x in centre):
        centre = [float(f"{round(x / step) * step:.12g}") for x in centre]
    radius = float(np.linalg.norm(points - np.asarray(centre), axis=1).max()) + reach
    return centre, _rounded_up(radius)


def check_levels(levels: int, patches: int | None, spans: int = SPANS) -> None:
    """Refuse ``levels`` detail levels that an atlas of ``patches`` patches cannot hold
    (:func:`most_levels`; ``None``: any atlas, before its patches are known): before the
    first level is fitted, not after memory runs out.

    Raises
    ------
    OptionError
        Naming ``detail_levels``, the most levels this atlas holds and why.
    """
    most, why = most_levels(1 if patches is None else patches, spans)
    if levels > most:
        atlas = "an atlas" if patches is None else f"an atlas of {patches:,} patches"
        raise OptionError(f"detail_levels {levels}: {atlas} with {spans} spans a tile holds "
                          f"at most {most} levels ({why})")


def _check_positive(name: str, value: object, unit: str) -> None:
    if not (isinstance(value, int | float) and not isinstance(value, bool)
            and math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a finite number > 0{unit}, got {value!r}")


def _check_arguments(levels: object, spans: object, step_factor: object,
                     offset_limit: object = OFFSET_LIMIT,
                     pull_reach: object = PULL_REACH) -> None:
    if levels is not None and (isinstance(levels, bool) or not isinstance(levels, int)
                               or not 0 <= levels <= layers.MAX_LEVEL + 1):
        raise ValueError(f"levels must be None (automatic) or an int in "
                         f"0..{layers.MAX_LEVEL + 1}, got {levels!r}")
    if isinstance(spans, bool) or not isinstance(spans, int) or spans not in (1, 2, 4, 8, 16):
        raise ValueError(f"spans must be one of 1, 2, 4, 8, 16 spans per tile side, got {spans!r}")
    _check_positive("step_factor", step_factor, "")
    _check_positive("offset_limit", offset_limit, " (median patch sides)")
    _check_positive("pull_reach", pull_reach, " (of the diagonal)")


def _check_pack_bytes(pack_bytes: object) -> None:
    if isinstance(pack_bytes, bool) or not isinstance(pack_bytes, int) or pack_bytes < 1000:
        raise ValueError(f"pack_bytes must be an int >= 1000, got {pack_bytes!r}")


def fit_atlas_detail(fit: AtlasFit, scan: Scan, levels: int | None = None, *,
                     spans: int = SPANS, step_factor: float = STEP_FACTOR,
                     max_samples: int = MAX_SAMPLES, pack_bytes: int = PACK_BYTES,
                     progress: Callable[[float], None] | None = None,
                     original: Scan | None = None, keep_order: bool = False,
                     offset_limit: float = OFFSET_LIMIT,
                     pull_reach: float = PULL_REACH) -> AtlasDetail:
    """Fit the detail pyramid of ``fit``'s atlas to ``scan``'s surface (module docstring)
    and code its packs: :func:`pack_pyramid` of :func:`fit_detail_pyramid`.

    Parameters
    ----------
    fit : AtlasFit
        The base (:func:`.fit.fit_atlas`), with its surface and layout.
    scan : Scan
        The scan ``fit`` was fitted to (its points for a cloud).
    levels : int, optional
        ``L``: levels ``0..L-1``; ``None``: :func:`auto_levels`; 0: no detail.
    spans : int
        ``m``, spans per tile side (2, 4, 8 or 16).
    step_factor : float
        Quantisation step over the level's remaining RMS (``fitter.fitting.detail``).
    max_samples : int
        Most surface samples (the memory bound: about 100 bytes each).
    pack_bytes : int
        A group's finest-level pack stays within this (a group of one patch may exceed it).
    progress : callable(float), optional
        The fraction done, 0..1.
    original : Scan, optional
        A large scan's own points (``fitter.fitting.stream.LargeScan.detail_scan``), of
        which ``scan`` is the working set: the levels are fitted to them (thinned to about
        ``max_samples``), and their depth reaches their spacing, not the working set's.
    keep_order : bool
        The patches keep their numbers (a smooth base's are its control triangles', which
        its file fixes in a walk across their edges:
        ``client_py.control_mesh.traversal_order``); else they are renumbered in
        :func:`spatial_order`.
    offset_limit : float
        The largest normal offset fitted, in median patch sides (:func:`fit_samples`; a
        smooth base's patches are smaller: ``.smooth.SMOOTH_OFFSET_LIMIT``).
    pull_reach : float
        A drawn node farther than this share of the diagonal from the scan is pulled toward
        it (module docstring, "Far nodes"; ``.smooth.SMOOTH_PULL_REACH``).

    Returns
    -------
    AtlasDetail
    """
    _check_pack_bytes(pack_bytes)
    return pack_pyramid(fit_detail_pyramid(fit, scan, levels, spans=spans,
                                           step_factor=step_factor, max_samples=max_samples,
                                           progress=progress, original=original,
                                           keep_order=keep_order, offset_limit=offset_limit,
                                           pull_reach=pull_reach),
                        pack_bytes)


def fit_detail_pyramid(fit: AtlasFit, scan: Scan, levels: int | None = None, *,
                       spans: int = SPANS, step_factor: float = STEP_FACTOR,
                       max_samples: int = MAX_SAMPLES,
                       progress: Callable[[float], None] | None = None,
                       original: Scan | None = None, keep_order: bool = False,
                       offset_limit: float = OFFSET_LIMIT,
                       pull_reach: float = PULL_REACH) -> DetailPyramid:
    """:func:`fit_atlas_detail`'s pyramid (the same parameters but ``pack_bytes``), its
    packs not yet coded (:func:`pack_pyramid`)."""
    _check_arguments(levels, spans, step_factor, offset_limit, pull_reach)
    if isinstance(max_samples, bool) or not isinstance(max_samples, int) or max_samples < 1000:
        raise ValueError(f"max_samples must be an int >= 1000, got {max_samples!r}")
    report = progress or (lambda fraction: None)
    timings: dict = {}
    clock = time.perf_counter()
    base = fit.atlas
    table0, cps0 = index_table(base), control_points(base)
    centres = cps0[table0].reshape(len(base.quads), -1, 3).mean(axis=1)
    order = np.arange(len(centres)) if keep_order else spatial_order(centres)
    atlas = renumber_patches(base, order)
    F = len(atlas.quads)
    sides = patch_sides(atlas)
    side = float(np.median(sides))
    spacing = median_spacing(scan, fit, original)
    is_mesh = fit.surface.origin == "mesh"  # the scan's own triangles (not a cloud's stand-in)
    validate = levels is None and not is_mesh  # see "Depth"
    if levels is None:
        levels = auto_levels(side, spacing, F, spans)
    else:
        check_levels(levels, F, spans)
    finest_cells = F * (spans << max(levels - 1, 0)) ** 2
    source = scan if original is None else original
    count = int(min(max_samples, max(SAMPLES_PER_CELL * finest_cells, len(source.points))))
    points, normals, weights = surface_samples(scan, fit, count, original=original)
    timings["setup"] = time.perf_counter() - clock
    clock = time.perf_counter()
    samples = project_samples(atlas, fit, points, normals,
                              progress=lambda x: report(0.4 * x), weights=weights)
    timings["project"] = time.perf_counter() - clock
    use = fit_samples(samples, spacing, side, offset_limit)
    held = use & held_out(len(use)) if validate else np.zeros(len(use), dtype=bool)
    if held.sum() < MIN_HELD:
        held[:] = False
    fit_weight = np.where(use & ~held, samples.weight, 0.0)
    e = samples.error(np.zeros_like(samples.s))
    base_rms, base_max = float(np.sqrt(np.mean(e ** 2))), float(e.max(initial=0.0))
    held_rms = [float(np.sqrt(np.mean(e[held] ** 2)))] if held.any() else []
    untried = None  # the level not tried for want of samples, if any
    fields: list[np.ndarray] = []
    per_level_tiles: list[dict] = []
    level_rows: list[dict] = []
    worst_of_patch: list[np.ndarray] = []  # per level: max e of each patch's samples
    timings.update(nodes=0.0, model=0.0, far_rows=0.0, solve=0.0, fold_rows=0.0, quantise=0.0,
                   tiles=0.0)  # the levels' steps, summed
    clock = time.perf_counter()
    feet = DrawnModel.feet(atlas, samples)
    scan_mesh = (fit.surface.vertices, fit.surface.faces)
    diagonal = float(np.linalg.norm(np.ptp(np.asarray(fit.surface.vertices, float), axis=0)))
    scan_points = np.asarray(scan.points, dtype=float)
    reach = DRAWN_REACH * float(np.linalg.norm(np.ptp(scan_points, axis=0)))
    distance = scan_distance(scan) if DRAWN_REACH > 0 and (DRAWN_MESHES or not is_mesh) \
        else None
    taken: list[np.ndarray] = []  # per level, the cells it leaves out (F, W_k, W_k)
    # per patch: the fitted samples' weight, shared by the r^2 nodes of each level below
    per_patch = float(np.sum(fit_weight)) / F
    fitted_count = int(np.count_nonzero(use & ~held))
    for k in range(levels):
        n = (spans << k) + DEGREE
        unknowns = shared_count(atlas, n)
        if held.any() and unknowns * MIN_SAMPLES_PER_UNKNOWN > fitted_count:
            levels = k  # too few samples to fit it ("Depth"): not tried
            untried = {"level": k, "unknowns": unknowns, "fitted_samples": fitted_count}
            break
        G = shared_index(atlas, n)
        nodes = level_nodes(atlas, fields, k, spans) if PULL_WEIGHT > 0 or FOLD_PASSES else None
        clock = _tick(timings, "nodes", clock)
        model = DrawnModel.of(atlas, samples, atlas_level_resolution(spans, k), feet=feet,
                              frames=nodes)
        residual = model.target - sum((model.drawn(c, j, spans)
                                       for j, c in enumerate(fields)), np.zeros(len(e)))
        clock = _tick(timings, "model", clock)
        per_node = per_patch / atlas_level_resolution(spans, k) ** 2
        pull = (far_node_rows(nodes, scan_mesh, pull_reach * diagonal, PULL_WEIGHT * per_node)
                if PULL_WEIGHT > 0 else None)
        clock = _tick(timings, "far_rows", clock)

        solved = _solve_level(samples, residual, k, spans, fit_weight, use, model, G, pull)
        c = solved.coefficients
        if held.any():  # refused before its fold rows and rounding ("Depth"): their cost spared
            unrounded = residual - model.drawn(c, k, spans)
            held_rms.append(float(np.sqrt(np.mean(unrounded[held] ** 2 + samples.t2[held]))))
            if held_rms[-1] > (1.0 - MIN_GAIN) * held_rms[-2]:
                levels = k
                clock = _tick(timings, "solve", clock)
                break
            held_rms.pop()
        for _ in range(FOLD_PASSES if FOLD_WEIGHT > 0 else 0):  # module docstring, "Folds"
            clock = _tick(timings, "solve", clock)
            fold = fold_node_rows(nodes, c, k, spans, FOLD_WEIGHT * per_node)
            clock = _tick(timings, "fold_rows", clock)
            if not len(fold.patch):
                break
            pull = merged_rows(pull, fold)
            solved = _solve_level(samples, residual, k, spans, fit_weight, use, model, G, pull,
                                  again=solved, changed=np.diff(fold.offsets) > 0)
            c = solved.coefficients
        clock = _tick(timings, "solve", clock)
        fitted = residual - model.drawn(c, k, spans)
        rms_fit = float(np.sqrt(np.average(fitted[use] ** 2 + samples.t2[use],
                                           weights=samples.weight[use]))) if use.any() else 0.0
        step = quantisation_step(rms_fit, float(np.abs(c).max(initial=0.0)),
                                 float(np.abs(residual[use]).max(initial=0.0)), step_factor)
        limit = COEFFICIENT_REACH * _largest_residual(samples, residual, use)
        q = quantised_blocks(samples, residual, k, spans, c, step, limit, weights=fit_weight,
                             model=model, rows=solved.rows, pull=pull,
                             shared=G if is_mesh else None)  # "Quantisation"
        del solved, nodes
        clock = _tick(timings, "quantise", clock)
        fields.append(q * step)
        residual = residual - model.drawn(fields[-1], k, spans)
        e = np.sqrt(residual ** 2 + samples.t2)
        if held.any():
            held_rms.append(float(np.sqrt(np.mean(e[held] ** 2))))
            if held_rms[-1] > (1.0 - MIN_GAIN) * held_rms[-2]:
                fields.pop()
                levels = k  # this level draws noise: the pyramid stops before it
                break
        worst = np.zeros(F)
        np.maximum.at(worst, samples.patch, e)
        worst_of_patch.append(worst)
        clock = _tick(timings, "model", clock)
        tiles: dict = {}
        for f in range(F):
            lo, hi = samples.offsets[f], samples.offsets[f + 1]
            made = level_tiles(q[f], step, k, DEGREE, spans, samples.u[lo:hi],
                               samples.v[lo:hi], e[lo:hi], encode=False)
            if made:
                tiles[f] = made
        per_level_tiles.append(tiles)
        clock = _tick(timings, "tiles", clock)
        walls = 0
        if distance is not None:  # module docstring, "Drawn cells"
            far = level_far_cells(atlas, per_level_tiles, k, spans, scan_points, distance,
                                  reach)
            keep = np.zeros((F, 1 << k, 1 << k), bool)  # tiles over a coarser level's walls
            for cells in taken:
                for f in np.flatnonzero(cells.any(axis=(1, 2))):
                    keep[f] |= coarsened(cells[f], 1 << k)
            for f in map(int, np.flatnonzero(far.any(axis=(1, 2)) | keep.any(axis=(1, 2)))):
                lo, hi = samples.offsets[f], samples.offsets[f + 1]
                tiles[f] = level_tiles(q[f], step, k, DEGREE, spans, samples.u[lo:hi],
                                       samples.v[lo:hi], e[lo:hi], encode=False,
                                       walls=(far[f], keep[f]))
            taken.append(far)
            walls = int(far.sum())
            clock = _tick(timings, "cells", clock)
        level_rows.append({"level": k, "rms": float(np.sqrt(np.mean(e ** 2))),
                           "max": float(e.max(initial=0.0)), "step": step,
                           "resolution": atlas_level_resolution(spans, k),
                           "border_jump": border_jump(atlas, fields, spans),
                           "walls": walls})
        report(0.4 + 0.5 * (k + 1) / max(levels, 1))
        clock = _tick(timings, "tiles", clock)
    reach = sum(np.abs(c).max(axis=(1, 2)) for c in fields) if fields else np.zeros(F)
    held_record = None
    if held_rms:
        held_record = {"share": _rounded(float(held.sum()) / max(int(use.sum()), 1)),
                       "rms": [_rounded(x) for x in held_rms], "min_gain": MIN_GAIN,
                       **({"not_tried": untried} if untried else {})}
    report(1.0)
    return DetailPyramid(atlas, order, [{f: [t for t, _, _ in made] for f, made in
                                         tiles.items()} for tiles in per_level_tiles],
                         level_rows, len(samples.u), spacing, side, timings, spans,
                         (base_rms, base_max), worst_of_patch, reach, held_record)


def pack_pyramid(pyramid: DetailPyramid, pack_bytes: int = PACK_BYTES) -> AtlasDetail:
    """``pyramid`` with its packs (module docstring, "Groups and packs"): the patches cut
    into groups whose finest-level pack stays within ``pack_bytes`` (:func:`_groups`, by
    the finest tiles' own ``.tsd`` bytes), whose finest drawn mesh stays within
    ``GROUP_VERTICES`` and which hold at most ``GROUP_PATCHES`` patches, every level's
    tiles of a group coded as one welded pack (``client_py.atlas_detail.write_pack``), and
    the manifest's ``tiles.detail`` (``tree``). Pure Python (the client's coder) and a deterministic
    function of ``pyramid``: the same bytes whenever and on whichever thread it runs."""
    _check_pack_bytes(pack_bytes)
    clock = time.perf_counter()
    atlas, spans, tiles_of = pyramid.atlas, pyramid.spans, pyramid.tiles
    F, levels = len(atlas.quads), len(pyramid.tiles)
    # the finest level's own .tsd bytes size the groups (_groups) alone
    finest = ({f: [(t, write_detail_tile(t), None) for t in made]
               for f, made in tiles_of[-1].items()} if levels else {})
    walls_side = max((t.walls.rows for tiles in tiles_of for made in tiles.values()
                      for t in made if t.walls is not None), default=0)
    drawn = pyramid.levels[-1]["resolution"] ** 2 if levels else 1
    groups = _groups(finest, F, pack_bytes, max(levels - 1, 0), spans, walls_side,
                     max(1, min(GROUP_PATCHES * (SPANS // spans) ** 2, GROUP_VERTICES // drawn)))
    files: dict[str, bytes] = {}
    packs = []
    level_rows = [dict(row) for row in pyramid.levels]
    for k, tiles in enumerate(tiles_of):
        total, count_k = 0, 0
        for g, (first, size) in enumerate(groups):
            mine = {f: tiles[f] for f in range(first, first + size) if f in tiles}
            if not mine:
                continue
            data = write_pack(k, mine, atlas)
            name = pack_name(k, g)
            files[name] = data
            total += len(data)
            count_k += 1
            packs.append({"level": k, "group": g, "bytes": len(data), "geometric_error":
                          _rounded_up(float(pyramid.worst[k][first:first + size].max()))})
        level_rows[k]["bytes"] = total
        level_rows[k]["packs"] = count_k
    table, cps = index_table(atlas), control_points(atlas)
    group_rows = []
    for first, size in groups:
        centre, radius = _bounding_sphere(cps[table[first:first + size]].reshape(-1, 3),
                                          float(np.max(pyramid.reach[first:first + size])))
        group_rows.append({"first": int(first), "count": int(size), "center": centre,
                           "radius": radius})
    versions = {PACK_HEADER.unpack_from(data)[1] for data in files.values()}
    base_rms, base_max = pyramid.base
    tree = {"format": "tsdp", "format_version": max(versions, default=WALLS_FREE_VERSION),
            "tile_format_version": TILE_VERSION, "degree": DEGREE, "spans_per_tile": spans,
            "base": {"rms": _rounded(base_rms), "max": _rounded(base_max)},
            "levels": [{"level": r["level"], "rms": _rounded(r["rms"]),
                        "max": _rounded(r["max"]), "bytes_total": r["bytes"],
                        "packs": r["packs"], "resolution": r["resolution"],
                        **({"walls": r["walls"]} if r["walls"] else {})}
                       for r in level_rows],
            "groups": group_rows, "packs": packs}
    if pyramid.held_out:
        tree["held_out"] = pyramid.held_out
    timings = {**pyramid.timings, "packs": time.perf_counter() - clock}
    fitted = {f.name: getattr(pyramid, f.name) for f in data_fields(DetailPyramid)}
    return AtlasDetail(**{**fitted, "levels": level_rows, "timings": timings}, tree=tree,
                       files=files)


def _groups(finest: dict, patches: int, pack_bytes: int, level: int = 0,
            spans: int = SPANS, walls: int = 0, most: int | None = None
            ) -> list[tuple[int, int]]:
    """Contiguous ``(first, count)`` runs of patches: :func:`spatial_order`'s halves (the
    whole run, halved at :func:`_middle` while it does not fit), each of at most ``most``
    patches (default: any number) whose finest-level (``level``) tiles stay within
    ``pack_bytes`` in a pack (``client_py.atlas_detail``: one range-coded stream, so a tile
    costs about its ``.tsd`` coded bytes without the tile's own header and CRC, less the
    border slots a welded pack does not repeat, which this bound does not count; 28 bytes
    of pack framing) and within the values a pack may hold
    (:func:`client_py.atlas_detail.pack_capacity` <= ``MAX_PACK_VALUES``, its walls masks
    ``walls`` cells a side: the largest of any level, so that no level's pack of the run,
    at ``4^k`` tiles a patch, holds more). A single patch is a group whatever it holds."""
    framing = TILE_HEADER_SIZE + CRC_SIZE
    cost = [sum(len(data) - framing for _, data, _ in finest.get(f, [])) for f in range(patches)]
    before = [0, *accumulate(cost)]

    def fits(first: int, stop: int) -> bool:
        count = stop - first
        return count == 1 or (28 + before[stop] - before[first] <= pack_bytes
                              and pack_capacity(level, count, DEGREE, spans, walls=walls)
                              <= MAX_PACK_VALUES and (most is None or count <= most))

    groups, runs = [], [(0, patches)]
    while runs:
        first, stop = runs.pop()
        if fits(first, stop):
            groups.append((first, stop - first))
        else:
            middle = _middle(first, stop)
            runs += [(middle, stop), (first, middle)]  # the lower half next
    return groups
