"""Out-of-core fitting: a scan larger than ``STREAM_ABOVE`` points is fitted on a voxel-thinned
working set, and every one of its points is measured in a streamed pass.

Peak memory then depends on the point count ``N`` only through a few bytes a point of
output, never through a float64 copy of the cloud:

1. *bounds* — one pass over the :class:`~fitter.fitting.io.points.PointStream` (a binary PLY
   stays memory-mapped float32): the box, an even sample, and (beside it) the file's SHA-256;
2. *thinning* — the voxel edge ``h`` at which the cloud occupies about
   ``WORKING_SET_POINTS`` voxels (``fitter.fitting.io.thin.voxel_size_for``), then two
   passes in blocks of ``BLOCK_POINTS``: the voxel sums, the point nearest each centroid
   (the rule of ``fitter.fitting.io.thin.voxel_thin_indices``); the representatives are the
   working set, a ``Scan`` every later stage fits as it would a small scan (its PCA frame,
   map, coverage, sample, detail pyramid, ``error.png`` and ``error.ply``);
3. *error* — once the base is chosen, the signed foot-point deviation of every original point
   (``fitter.fitting.error.deviations``, block by block, the tree query of most points
   answered by their voxel's nearest tessellation vertices) from the decoded ``base.tsp``. A
   point counts as covered when its voxel's representative is (one rule, the working set's
   coverage, instead of a second outer-layer test). The pass keeps ``d``, ``u``, ``v`` as
   float32 and a covered flag: 13 bytes a point (1.3 GB for 10^8), from which the
   manifest's ``stats``, ``stats_all_points``, ``error_raster``/grid and the uncovered count
   and box are computed by the same functions as for a small scan.

``error.ply`` and ``error.png`` show the working set (one point per voxel: about a million,
16 MB of PLY, enough for a picture) rather than all ``N`` points (1.6 GB of PLY for 10^8);
their colours use the working set's scale, the statistics every point.

The block passes (2 and 3) run on threads here (numpy releases the GIL) or on Dask
(:class:`DaskBlocks`: ``tessera fit --workers N`` or ``--scheduler tcp://HOST:8786``). Their
results do not depend on who ran them: sums are merged in block order, minima are
order-free, per-point outputs land at their index. So the bundle is byte-identical either way.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from client_py import read_patch

from .closest import ClosestPoints
from .cores import usable_cores
from .error import Deviations, deviations
from .io.frame import moved_source, scan_origin
from .io.limits import InputBudget, InputLimits
from .io.points import PointStream, ReaderStream, file_sha256
from .io.scan import Scan, ScanError, make_scan
from .io.thin import VoxelGrid, VoxelIndex, VoxelNearest, VoxelSums, voxel_size_for
from .nurbs import PatchModel
from .parameterize import Projection

#: scans with more points than this are fitted out of core
STREAM_ABOVE = 3_000_000
#: the working set's size the voxel edge aims at
WORKING_SET_POINTS = 800_000
#: about as many of a large scan's own points its atlas's detail levels are fitted to
#: (``LargeScan.detail_scan``, ``fitter.fitting.atlas.detail.fit_atlas_detail``'s ``original``)
DETAIL_POINTS = 4_000_000
#: the voxel sums are taken again with a larger voxel when more voxels than this are
#: occupied (noise makes a scan thicker than a surface at a fine voxel): below 4 x 512^2
#: points the detail pyramid keeps five levels (``fitter.fitting.detail.auto_levels``), whose
#: finest solve takes about 0.5 GB (``fitter.fitting.memory``), not six (1.8 GB)
WORKING_SET_MOST = 1_000_000
#: points per block of the streamed passes (float64 temporaries of ~100 MB a block)
BLOCK_POINTS = 1 << 21
#: points of the even sample the voxel edge is estimated on
VOXEL_SAMPLE = 1 << 20

#: progress(fraction, points_done) of one pass
PassProgress = Callable[[float, int], None]


class LocalBlocks:
    """Runs a pass's blocks on ``threads`` threads of this process, results in block order.

    A :class:`PointStream` among the shared arguments is passed as a copy that maps the file
    for this pass only: the mapped pages leave the process's resident memory with it (a
    binary PLY of 10^8 points would otherwise hold 1.2 GB of it until the fit ends)."""

    def __init__(self, threads: int | None = None) -> None:
        self.threads = max(1, threads or usable_cores())

    def map(self, function: Callable, blocks: Sequence[tuple[int, int]],
            *shared: object) -> Iterator:
        shared = tuple(unmapped(x) if isinstance(x, PointStream) else x for x in shared)
        with ThreadPoolExecutor(self.threads) as pool:
            yield from pool.map(lambda block: function(*block, *shared), blocks)


def unmapped(stream: PointStream) -> PointStream:
    """A copy of ``stream`` without its file map (it maps the file again when read)."""
    return copy.copy(stream)  # PointStream.__getstate__ leaves the map behind


class DaskBlocks:
    """Runs a pass's blocks as tasks of a Dask ``distributed.Client``, results in block order
    (the shared arguments are scattered to the workers once per pass)."""

    def __init__(self, client: object) -> None:
        self.client = client

    def map(self, function: Callable, blocks: Sequence[tuple[int, int]],
            *shared: object) -> Iterator:
        # hash=False: a second pass scattering equal data must not share (and lose) the key
        scattered = [self.client.scatter(x, broadcast=True, hash=False) for x in shared]
        futures = [self.client.submit(function, start, stop, *scattered, pure=False)
                   for start, stop in blocks]
        for future in futures:  # in order: the merges are the same as LocalBlocks'
            yield future.result()
            future.release()


@dataclass
class StreamedError:
    """Every original point's deviation from the decoded base (float32) and its covered flag;
    the uncovered points' count and box in scan coordinates."""

    dev: Deviations
    covered: np.ndarray
    uncovered_points: int
    uncovered_bbox: list | None

    def covered_dev(self) -> Deviations:
        c = self.covered
        return Deviations(self.dev.d[c], self.dev.u[c], self.dev.v[c])


def _sums_block(start: int, stop: int, stream: PointStream, grid: VoxelGrid) -> VoxelSums:
    return VoxelSums.of(stream.read(start, stop)[0], grid)


def _nearest_block(start: int, stop: int, stream: PointStream, index: VoxelIndex,
                   centroids: np.ndarray) -> tuple:
    return VoxelNearest.of_block(stream.read(start, stop)[0], start, index, centroids)


def _error_block(start: int, stop: int, stream: PointStream, patch: bytes,
                 projection: Projection, index: VoxelIndex, voxel_covered: np.ndarray,
                 voxel_near: tuple[np.ndarray, np.ndarray]) -> tuple:
    """One block of the error pass: ``d, u, v`` (float32), covered flags, and the uncovered
    points' count, minimum and maximum corner (scan coordinates). ``voxel_near`` is each
    voxel's tessellation vertex candidates and their reach (``ClosestPoints.cell_candidates``)."""
    points, _ = stream.read(start, stop)
    closest = ClosestPoints(PatchModel.from_surface(read_patch(patch)), projection.periodic_u)
    local = projection.local(points)
    u, v, _ = projection.to_uvh(points, local)
    voxel = index.positions(points)
    dev = deviations(closest, local, u, v, threads=1,
                     near=(np.take(voxel_near[0], voxel, axis=0), voxel_near[1][voxel]))
    covered = voxel_covered[voxel]
    out = points[~covered]
    box = (out.min(axis=0), out.max(axis=0)) if len(out) else None
    return (dev.d.astype(np.float32), dev.u.astype(np.float32), dev.v.astype(np.float32),
            covered, len(out), box)


@dataclass
class LargeScan:
    """A scan fitted out of core: its stream, the working set and the voxel grid that made it.

    Attributes
    ----------
    stream : PointStream
    source : dict
        The input's provenance (with ``thinning``: voxel edge, points before and after).
    units : str
    grid : VoxelGrid
    sums : VoxelSums
        Keys and counts of every occupied voxel (``K``).
    representative : ndarray of int, shape (K,)
        The working set's index of each voxel's representative.
    working : Scan
        The working set (float64, ``K`` points).
    blocks : LocalBlocks or DaskBlocks
    whole : Scan or None
        The scan itself when a reader loaded a mesh whole (its triangles are what
        :meth:`atlas_scan` reduces), else ``None`` (a cloud, or streamed from its file).
    bounds : tuple of ndarray, shape (3,), or None
        The box ``lo, hi`` of every point (pass 1).
    """

    stream: PointStream
    source: dict
    units: str
    grid: VoxelGrid
    sums: VoxelSums
    representative: np.ndarray
    working: Scan
    blocks: LocalBlocks | DaskBlocks
    whole: Scan | None = None
    bounds: tuple[np.ndarray, np.ndarray] | None = None

    def atlas_scan(self) -> Scan:
        """The scan an atlas is fitted to (``fitter.fitting.atlas.pipeline``): a mesh's
        :func:`working_mesh`, a cloud's working set (its surface is then the atlas's
        Poisson stand-in, as for any cloud)."""
        if self.whole is not None:  # a mesh (_load keeps no cloud whole)
            return working_mesh(self.whole)
        return self.working

    def detail_scan(self, count: int | None = None) -> Scan:
        """The points an atlas's detail levels are fitted to (``fit_atlas_detail``'s
        ``original``): a mesh's own vertices (:attr:`whole`; the detail thins them to its
        sample bound), a cloud's points thinned by the rule of the working set to about
        ``count`` (default :data:`DETAIL_POINTS`): two more streamed passes, at a voxel edge
        ``sqrt(K / count)`` times the working set's (a surface's occupied voxels go as
        ``h^-2``), larger while more than ``1.2 count`` voxels are occupied; all of them
        when there are no more than ``count``."""
        if self.whole is not None:  # a mesh (_load keeps no cloud whole)
            return self.whole
        count = int(DETAIL_POINTS if count is None else count)
        stream = self.stream
        if stream.count <= count:
            points, normals = unmapped(stream).read(0, stream.count)
        else:
            lo, hi = self.bounds if self.bounds is not None else (
                self.grid.lo, self.grid.lo + self.grid.dims * self.grid.size)
            size = self.grid.size * float(np.sqrt(len(self.sums.keys) / count))
            _, _, kept = thin_stream(stream, lo, hi, size, self.blocks, most=int(1.2 * count))
            points, normals = unmapped(stream).take(kept)
        return make_scan(self.working.source.get("name", "scan"), np.asarray(points, float),
                         normals=normals, units=self.units, source=dict(self.source))

    @property
    def n_points(self) -> int:
        return self.stream.count

    def measure(self, patch: bytes, projection: Projection, covered_working: np.ndarray,
                progress: PassProgress | None = None) -> StreamedError:
        """The error pass (module docstring, step 3) of the decoded ``patch`` bytes over every
        point; ``covered_working (K,)`` is the working set's coverage."""
        n = self.n_points
        d, u, v = (np.empty(n, np.float32) for _ in range(3))
        covered = np.empty(n, bool)
        voxel_covered = covered_working[self.representative]
        closest = ClosestPoints(PatchModel.from_surface(read_patch(patch)),
                                projection.periodic_u)
        voxel_near = closest.cell_candidates(
            projection.local(self.grid.centres(self.sums.keys)), self.grid.half_diagonal)
        lo, hi, outside = np.full(3, np.inf), np.full(3, -np.inf), 0
        blocks = self.stream.blocks(BLOCK_POINTS)
        # a table of its own (not kept with the scan: up to 192 MB while the detail is fitted)
        results = self.blocks.map(_error_block, blocks, self.stream, patch, projection,
                                  VoxelIndex(self.grid, self.sums.keys), voxel_covered,
                                  voxel_near)
        for k, ((start, stop), (bd, bu, bv, bc, count, box)) in enumerate(
                zip(blocks, results, strict=True)):
            d[start:stop], u[start:stop], v[start:stop], covered[start:stop] = bd, bu, bv, bc
            if box is not None:
                lo, hi, outside = np.minimum(lo, box[0]), np.maximum(hi, box[1]), outside + count
            if progress is not None:
                progress((k + 1) / len(blocks), stop)
        bbox = [lo.tolist(), hi.tolist()] if outside else None
        return StreamedError(Deviations(d, u, v), covered, outside, bbox)


class WorkingMeshError(ScanError):
    """A large mesh that cannot be reduced to a working mesh (:func:`working_mesh`): ``fit
    --patches auto`` then fits one patch and the manifest's ``atlas_refused`` says why."""


def welded(points: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mesh with its coincident vertices (equal coordinates, to the bit) made one and its
    triangles that then repeat a vertex dropped: a triangle soup (STL, an unwelded export)
    becomes a connected surface. The same arrays when nothing coincides."""
    rows = np.ascontiguousarray(points, np.float64)
    keys = rows.view(np.dtype((np.void, rows.dtype.itemsize * 3))).ravel()
    unique, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    if len(unique) == len(rows):
        return points, faces
    order = np.argsort(first)  # the kept vertices in their first appearance's order
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    faces = rank[inverse.ravel()][faces]
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) \
        & (faces[:, 2] != faces[:, 0])
    return rows[np.sort(first)], faces[keep]


def working_mesh(scan: Scan, vertices: int | None = None) -> Scan:
    """A large mesh's working set: the mesh reduced to about ``vertices`` (default
    :data:`WORKING_SET_POINTS`) vertices by ``fast_simplification`` (Garland & Heckbert's
    quadric error metric, *Surface simplification using quadric error metrics*, SIGGRAPH
    1997, collapsed by Forstmann's threshold sweep): the surface an atlas's layout and base
    are fitted to in memory; its detail levels are fitted to the scan's own vertices (up to
    :data:`DETAIL_POINTS`), and every original vertex is measured against the drawn levels
    in a streamed pass. A collapse keeps the quadric's best position: the example vase's
    4.48 M vertices lie 0.0009 mm RMS (largest 0.0047 mm, its height 300 mm) from the 0.8 M
    of its working mesh, made in 9.5 s. Coincident vertices are welded first
    (:func:`welded`: a triangle soup would be collapsed triangle by triangle), and a mesh
    with no more than twice ``vertices`` triangles is its own working mesh. Per-vertex
    colours (a texture's, sampled at each vertex's ``uv``, first, as the atlas's colour
    stage takes it; else the scan's RGB) go to each working vertex from the original
    vertex nearest to it.

    Raises
    ------
    WorkingMeshError
        A mesh the reduction cannot take (its message).
    """
    import fast_simplification
    from scipy.spatial import cKDTree

    target = int(WORKING_SET_POINTS if vertices is None else vertices)
    name = scan.source.get("name", "scan")
    started = time.perf_counter()
    reduced_vertices, reduced = welded(scan.points, np.asarray(scan.faces, np.int64))
    if len(reduced) > 2 * target:
        try:
            reduced_vertices, reduced = fast_simplification.simplify(
                np.ascontiguousarray(reduced_vertices, np.float64),
                np.ascontiguousarray(reduced), target_count=2 * target)
        except (ValueError, RuntimeError, MemoryError) as exc:
            raise WorkingMeshError(f"{name}: its {len(reduced):,} triangles could not be "
                                   f"reduced to a working mesh ({exc})") from exc
    reduced_vertices = np.asarray(reduced_vertices, np.float64)
    reduced = np.asarray(reduced, np.int64)
    if len(reduced) == 0:
        raise WorkingMeshError(f"{name}: no triangle is left of its {len(scan.faces):,} once "
                               "its coincident vertices are welded")
    colours = scan.colors
    if scan.uv is not None and scan.texture is not None:
        from .texture import sample_image

        colours = np.clip(np.rint(sample_image(np.asarray(scan.texture.convert("RGB")),
                                               scan.uv)), 0, 255).astype(np.uint8)
    if colours is not None:
        _, nearest = cKDTree(scan.points).query(reduced_vertices, workers=-1)
        colours = np.asarray(colours)[nearest]
    source = dict(scan.source, working_set={
        "rule": "quadric edge collapse to about twice as many triangles as WORKING_SET_POINTS "
                "(fitter.fitting.stream.working_mesh)",
        "points_before": int(scan.n_points), "points_after": int(len(reduced_vertices)),
        "triangles_before": int(len(scan.faces)), "triangles_after": int(len(reduced)),
        "seconds": round(time.perf_counter() - started, 3)})
    return make_scan(name, reduced_vertices, colors=colours, faces=reduced, units=scan.units,
                     source=source)


def fits_out_of_core(n_points: int) -> bool:
    """Whether a scan of ``n_points`` is fitted out of core (over ``STREAM_ABOVE``)."""
    return n_points > STREAM_ABOVE


def open_stream(path: Path, limits: InputLimits | None = None
                ) -> tuple[PointStream | ReaderStream, dict, str] | None:
    """The stream of a scan file the out-of-core path can read without loading it (an
    uncompressed binary PLY point cloud, an E57 or LAS/LAZ file, over ``STREAM_ABOVE``
    points: ``fitter.fitting.io.open_point_stream``), else ``None``."""
    from .io import open_point_stream

    opened = open_point_stream(path, InputBudget(limits), STREAM_ABOVE)
    if opened is None or not fits_out_of_core(opened[0].count):
        return None
    return opened


def stream_of_scan(scan: Scan) -> tuple[PointStream, dict, str]:
    """An in-memory scan as a stream (a large scan another reader loaded whole)."""
    return (PointStream.from_arrays(scan.source.get("name", "scan"), scan.points, scan.normals),
            dict(scan.source), scan.units)


def _bounds_block(start: int, stop: int, stream: PointStream, step: int
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    points, _ = stream.read(start, stop)
    # a copy: a view would keep the whole block alive until the sample is joined
    return points.min(axis=0), points.max(axis=0), points[::step].copy()


def _bounds(stream: PointStream, blocks: LocalBlocks | DaskBlocks,
            progress: PassProgress | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pass 1: the box ``lo, hi (3,)`` and an even sample of about ``VOXEL_SAMPLE`` points
    (every ``step``-th point: a block starts at a multiple of ``step``)."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    step = max(1, -(-stream.count // VOXEL_SAMPLE))
    sample = []
    spans = stream.blocks(BLOCK_POINTS - BLOCK_POINTS % step)
    for k, (low, high, part) in enumerate(blocks.map(_bounds_block, spans, stream, step)):
        lo, hi = np.minimum(lo, low), np.maximum(hi, high)
        sample.append(part)
        if progress is not None:
            progress((k + 1) / len(spans), spans[k][1])
    return lo, hi, np.concatenate(sample)


def thin_stream(stream: PointStream, lo: np.ndarray, hi: np.ndarray, size: float,
                blocks: LocalBlocks | DaskBlocks, progress: PassProgress | None = None,
                most: int | None = None) -> tuple[VoxelIndex, VoxelSums, np.ndarray]:
    """Passes 2a and 2b: the voxel grid of edge ``size`` (as the index of its occupied
    voxels, ``index.grid``), its sums, and the representatives' indices (ascending), by the
    rule of ``voxel_thin_indices``. With ``most``, the sums are taken again at
    ``size sqrt(K / (0.9 most))`` while ``K > most`` voxels are occupied."""
    spans = stream.blocks(BLOCK_POINTS)
    while True:
        grid = VoxelGrid.over(lo, hi, size)
        sums = VoxelSums.empty()
        for k, part in enumerate(blocks.map(_sums_block, spans, stream, grid)):
            sums = sums.merged(part)
            if progress is not None:
                progress(0.5 * (k + 1) / len(spans), spans[k][1])
        if most is None or len(sums.keys) <= most:
            break
        size *= float(np.sqrt(len(sums.keys) / (0.9 * most)))
    nearest = VoxelNearest.empty(len(sums.keys))
    index = VoxelIndex(grid, sums.keys)
    for k, part in enumerate(blocks.map(_nearest_block, spans, stream, index,
                                        sums.centroids())):
        nearest.update(*part)
        if progress is not None:
            progress(0.5 + 0.5 * (k + 1) / len(spans), spans[k][1])
    return index, sums, nearest.kept()


def load_working_set(stream: PointStream, source: dict, units: str,
                     blocks: LocalBlocks | DaskBlocks | None = None,
                     progress: PassProgress | None = None) -> LargeScan:
    """Passes 1 and 2 (module docstring): the working set of a large scan.

    Raises
    ------
    ScanError
        A cloud without extent (every point equal) or with non-finite coordinates.
    """
    blocks = blocks or LocalBlocks()
    name = stream.name
    started = time.perf_counter()
    with ThreadPoolExecutor(1) as hashing:
        digest = hashing.submit(file_sha256, stream.path) if stream.path else None
        lo, hi, sample = _bounds(stream, blocks, None if progress is None
                                 else lambda f, p: progress(0.2 * f, p))
        if digest is not None:
            source["sha256"] = source["files"][0]["sha256"] = digest.result()
            source["bytes"] = source["files"][0]["bytes"] = stream.path.stat().st_size
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ScanError(f"{name}: non-finite coordinates (NaN or inf) in the points")
    if not np.linalg.norm(hi - lo) > 0:
        raise ScanError(f"{name}: all {stream.count} points coincide; there is no surface to fit")
    origin = scan_origin(name, lo, hi)  # far from the origin: every later pass reads it moved
    if origin is not None:
        source = moved_source(source, origin, sample, float(np.linalg.norm(hi - lo)))
        stream.origin = origin
        lo, hi, sample = lo - origin, hi - origin, sample - origin
    index, sums, kept = thin_stream(
        stream, lo, hi, voxel_size_for(sample, stream.count, WORKING_SET_POINTS, lo, hi),
        blocks, None if progress is None else lambda f, p: progress(0.2 + 0.8 * f, p),
        WORKING_SET_MOST)
    grid, size = index.grid, index.grid.size
    points, normals = unmapped(stream).take(kept)
    representative = np.empty(len(sums.keys), np.int64)  # the working set's point of a voxel
    representative[index.positions(points)] = np.arange(len(kept))
    source = dict(source, thinning={
        "voxel_size": size, "points_before": stream.count, "points_after": int(len(kept)),
        "rule": "one point per voxel, the nearest to its centroid (fitter.fitting.stream)",
        "seconds": round(time.perf_counter() - started, 3)})
    working = make_scan(name, points, normals=normals, units=units, source=source)
    return LargeScan(stream, source, units, grid, sums, representative, working, blocks,
                     bounds=(lo, hi))

