"""``fit_scan``: one scan in, one bundle out — the whole fit with progress reporting.

Stages (each timed, each reported to ``progress(stage, fraction)``; their names, order and
shares of the time are ``fitter.fitting.stages.STAGES``, the options ``fitter.fitting.options``):

1. load — ``fitter.fitting.io.load_scan`` (or an in-memory array);
2. project — choose the map to ``[0, 1]^2`` and the covered points
   (``fitter.fitting.parameterize``); the rest are reported, not dropped;
2b. features — (``tessera`` only) local PCA and the feature-adaptive sample
   (``fitter.fitting.features``);
3. sections — the paper's section matrix (``fitter.fitting.sections``);
4. linear — the initial B-spline, weights 1, uniform clamped knots (``fitter.fitting.fit``);
5. refine — ``paper``: Levenberg-Marquardt over ``Q`` and ``W`` on the section
   matrix (eq. 5); ``tessera``: rounds of parameter correction (foot points of
   a feature-adaptive sample of the scan itself) and linear re-fits, then the
   weights by Levenberg-Marquardt on the same orthogonal residuals, kept only when they
   lower its energy by ``RATIONAL_GAIN`` (else the B-spline, coded without weights);
6. encode — ``base.tsp`` written and read back: the error is measured on the
   quantised patch a visitor downloads;
7. error — foot-point deviation of every scan point and its statistics;
7b. detail, texture — the residual pyramid along the base normal and the colour
   pyramid in ``(u, v)`` (``fitter.fitting.detail``, ``fitter.fitting.texture``):
   ``detail/K/I_J.tsd``, ``texture/K/I_J.webp`` and the manifest's ``tiles`` tree;
8. report — ``base.tsp`` and the tiles; ``pieces.tsa``, the scan's detached pieces the
   patch cannot hold (``fitter.fitting.pieces``); the deviations of patch and pieces in
   ``error_raster.bin``, ``error.png`` and ``error.ply``; ``manifest.json``. The bundle
   directory appears by an atomic rename once complete.

With ``max_error`` the control grid grows (x1.25 per side) from ``grid`` until
the RMS deviation is at most ``max_error`` or ``FitOptions.largest_grid`` is reached.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from client_py import TrimMask, read_patch, write_patch
from client_py.bundle import PIECES_FILE
from client_py.format import MAX_CONTROL_POINTS

from . import io as scan_io
from .atlas import AtlasFitError, AtlasLayoutError, SurfaceError
from .atlas.measure import forget_scenes
from .atlas.pipeline import check_atlas_options, fit_atlas_bundle, wants_atlas
from .bundle import write_bundle
from .compact import choose_bits, drawn_cells, settle_hidden
from .degenerate import check_patch, check_scan_shape
from .detail import DEGREE as DETAIL_DEGREE
from .detail import DetailPyramid, auto_levels, fit_detail, write_layers
from .error import (
    RASTER_FILE,
    Deviations,
    deviations,
    error_raster,
    error_stats,
    write_error_ply,
    write_error_png,
)
from .features import adaptive_sample, feature_weights, surface_variation
from .fit import (
    DEFAULT_SMOOTHING,
    fit_points_linear,
    fit_section_matrix,
    project_points,
    refine_nurbs,
)
from .io.frame import near_origin
from .io.limits import InputLimits
from .io.scan import Scan, ScanError
from .memory import DEFAULT_MEMORY_BUDGET, MemoryPlan, plan_memory
from .nurbs import PatchModel
from .options import FitOptions
from .orient import find_view
from .parameterize import Coverage, choose_projection, trim_cells
from .pieces import fit_pieces, with_pieces_deviations
from .sections import section_matrix, section_shape
from .stages import check_stage
from .stream import (
    DaskBlocks,
    LargeScan,
    LocalBlocks,
    StreamedError,
    WorkingMeshError,
    fits_out_of_core,
    load_working_set,
    open_stream,
    stream_of_scan,
)
from .texture import TextureTile, fit_texture

BUNDLE_FORMAT_VERSION = 1
MIN_POINTS = 64
FEATURE_SAMPLE = 150_000  # points whose local PCA drives the sampling density
CORRECTION_ROUNDS = 3
# Thin-plate weight of the tessera fits (relative, see fitter.fitting.fit._regularised_solve): 1e-4
# tames control points that data barely supports at the rim (their range had grown to 10-50x
# the object's on the Buddha, mask and Nefertiti at 1e-6, costing bits) while changing the RMS
# by under 0.5 % on every scan of ../shared/data and the generated relief.
TESSERA_SMOOTHING = 1e-4
BITS_PROBE = 10_000  # covered points whose fit RMS sets the quantisation bits
# A tessera fit keeps its weights only when they lower the refinement's energy by at least this
# share (``_weights_kept``): weights are a fourth coded coordinate per control point. Buddha
# range scan 0's (in [0.9978, 1.0023]) lowered it by 0.04 % for 1.95 KB of its 9.2 KB base.tsp
# (the RMS of all points at level 3 1.126e-4 -> 1.131e-4); the 20,000-point generated relief's
# lower it by 14.9 %, the 6,000-point one's on a 12 x 12 grid (tests/test_pipeline.py) by 0.87 %.
RATIONAL_GAIN = 0.005

Progress = Callable[[str, float], None]


@dataclass
class Bundle:
    """A written bundle: its directory and manifest."""

    path: Path
    manifest: dict


@dataclass
class FitResult:
    """One fitted size: the decoded patch, its ``base.tsp`` bytes, every scan point's
    deviation ``dev``, statistics of the covered ones, the fit's history and trim."""

    model: PatchModel
    data: bytes
    dev: object
    stats: dict
    history: dict = field(default_factory=dict)
    trim: TrimMask | None = None  # the drawn cells, None when all are
    # out of core (fitter.fitting.stream): every original point's deviation; ``dev`` and the
    # layers are then the working set's, ``stats`` every covered point's
    full: StreamedError | None = None


class _Stages:
    """Times stages and forwards progress; a stage is one of ``fitter.fitting.stages.STAGES``."""

    def __init__(self, progress: Progress | None) -> None:
        self.progress = progress
        self.timings: dict[str, float] = {}
        self._name: str | None = None
        self._start = 0.0

    def start(self, name: str) -> None:
        check_stage(name)
        self.stop()
        self._name, self._start = name, time.perf_counter()
        self.report(0.0)

    def report(self, fraction: float, points: int | None = None) -> None:
        """``progress(stage, fraction)``, or ``progress(stage, fraction, points)`` (points done
        in a streamed pass, for a rate and an ETA) when the callable takes a third argument."""
        if self.progress is not None and self._name is not None:
            if points is not None and _takes_points(self.progress):
                self.progress(self._name, float(fraction), int(points))
            else:
                self.progress(self._name, float(fraction))

    def stop(self) -> None:
        if self._name is not None:
            self.timings[self._name] = round(self.timings.get(self._name, 0.0)
                                             + time.perf_counter() - self._start, 4)
            self.report(1.0)
            self._name = None


def _takes_points(progress: Callable) -> bool:
    import inspect

    try:
        inspect.signature(progress).bind("load", 0.0, 0)
    except TypeError:
        return False
    return True


def _load(scan: object, limits: InputLimits | None, blocks: LocalBlocks | DaskBlocks | None,
          stages: _Stages) -> tuple[Scan, LargeScan | None]:
    """The scan to fit and, for one over ``fitter.fitting.stream.STREAM_ABOVE`` points, its
    out-of-core record (the scan is then the voxel-thinned working set): a binary PLY is
    streamed from its memory map, any other large input loaded and then streamed (a mesh
    loaded so is kept whole, ``LargeScan.whole``, for an atlas's working mesh; a cloud is
    not: its working set is the atlas's)."""
    opened = open_stream(Path(scan), limits) if isinstance(scan, str | os.PathLike) else None
    whole = None
    if opened is None:
        scan = near_origin(_as_scan(scan, limits))  # far from the origin: moved near it
        if not fits_out_of_core(scan.n_points):
            return scan, None
        opened = stream_of_scan(scan)
        whole = scan if scan.faces is not None and len(scan.faces) else None
    large = load_working_set(*opened, blocks=blocks,
                             progress=lambda f, p: stages.report(f, p))
    return large.working, replace(large, whole=whole)


def _as_scan(scan: object, limits: InputLimits | None = None) -> Scan:
    if isinstance(scan, Scan):
        return scan
    if isinstance(scan, str | os.PathLike):
        return scan_io.load_scan(Path(scan), limits=limits)
    if isinstance(scan, np.ndarray):
        return Scan.from_array(scan)
    raise ScanError(f"scan must be a file path, a Scan or an (N, 3) array, got "
                    f"{type(scan).__name__}")


def _grid_sizes(options: FitOptions) -> list[tuple[int, int]]:
    """The grids a fit tries: ``grid``, then (with ``max_error``) x1.25 per side up to
    ``largest_grid`` per side and ``client_py.format.MAX_CONTROL_POINTS`` in all."""
    sizes = [tuple(options.grid)]
    if options.max_error is not None:
        while max(sizes[-1]) < options.largest_grid:
            nxt = tuple(min(options.largest_grid, max(g + 1, int(round(g * 1.25))))
                        for g in sizes[-1])
            if nxt[0] * nxt[1] > MAX_CONTROL_POINTS:
                break
            sizes.append(nxt)
    return sizes


@dataclass
class ProjectedScan:
    """A checked scan and its map to the parameter domain.

    ``N`` scan points, ``M`` of them covered (on the part of the surface a single
    patch represents).

    Attributes
    ----------
    scan : Scan
    name : str
        The input's name (``scan.source["name"]``), for messages and the title.
    diagonal : float
        Length of the scan's bounding-box diagonal, ``> 0``.
    coverage : Coverage
        The projection, the covered mask ``(N,)`` and the domain's occupancy.
    local : ndarray, shape (N, 3)
        The points in the projection's frame.
    u, v, h : ndarray, shape (N,)
        Parameters and height of each point.
    cells : ndarray of bool, shape (rows, cols)
        The trim cells of the occupied domain (``fitter.fitting.parameterize.trim_cells``).
    covered_index : ndarray of int, shape (M,)
        Indices of the covered points, ascending.
    """

    scan: Scan
    name: str
    diagonal: float
    coverage: Coverage
    local: np.ndarray
    u: np.ndarray
    v: np.ndarray
    h: np.ndarray
    cells: np.ndarray
    covered_index: np.ndarray


def _check_scan(scan: Scan, projection: str = "auto") -> tuple[str, float]:
    """The scan's name and bounding-box diagonal; a ``ScanError`` if there is nothing to fit
    (too few points, or a degenerate cloud: ``fitter.fitting.degenerate.check_scan_shape``)."""
    points = scan.points
    name = scan.source.get("name", "scan")
    if len(points) < MIN_POINTS:
        raise ScanError(f"{name}: {len(points)} points; a fit needs at least {MIN_POINTS}")
    lo, hi = points.min(axis=0), points.max(axis=0)
    diagonal = float(np.linalg.norm(hi - lo))
    if not diagonal > 0:
        raise ScanError(f"{name}: all {len(points)} points coincide; there is no surface to fit")
    check_scan_shape(points, name, projection, MIN_POINTS)
    return name, diagonal


def _unit_normals(scan: Scan) -> np.ndarray | None:
    """The scan's normals ``(N, 3)`` scaled to length 1, or None if absent or any is zero."""
    if scan.normals is None:
        return None
    normals = np.asarray(scan.normals, dtype=float)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return normals / length if np.all(length > 0) else None


def project_scan(scan: Scan, options: FitOptions) -> ProjectedScan:
    """Check ``scan`` and map it to ``[0, 1]^2`` (``fitter.fitting.parameterize``).

    Raises
    ------
    ScanError
        Fewer than ``MIN_POINTS`` points, all points equal, fewer than ``MIN_POINTS``
        distinct points, collinear points, a plane for a map that needs 3D extent
        (``fitter.fitting.degenerate``), or fewer than ``MIN_POINTS`` covered by the
        chosen projection.
    """
    name, diagonal = _check_scan(scan, options.projection)
    coverage = choose_projection(scan.points, _unit_normals(scan), options.projection)
    proj = coverage.projection
    local = proj.local(scan.points)
    u, v, h = proj.to_uvh(scan.points)
    n_covered = int(coverage.covered.sum())
    if n_covered < MIN_POINTS:
        raise ScanError(f"{name}: only {n_covered} points lie on a surface a single patch can "
                        f"represent; at least {MIN_POINTS} are needed")
    return ProjectedScan(scan, name, diagonal, coverage, local, u, v, h,
                         trim_cells(coverage.mask, proj.periodic_u),
                         np.flatnonzero(coverage.covered))


def _fit_sample(projected: ProjectedScan, options: FitOptions, stages: _Stages) -> np.ndarray:
    """Indices of the points the refinement fits: for ``tessera`` a feature-adaptive sample
    of the covered points (stage ``features``), else all covered points."""
    covered_index = projected.covered_index
    if options.method != "tessera":
        return covered_index
    stages.start("features")
    rng = np.random.default_rng([options.seed, 0xFEA7])
    probe = covered_index if len(covered_index) <= FEATURE_SAMPLE else np.sort(
        rng.choice(covered_index, FEATURE_SAMPLE, replace=False))
    weights = feature_weights(surface_variation(projected.scan.points[probe]),
                              options.feature_strength)
    return probe[adaptive_sample(weights, min(options.samples, len(probe)), options.seed)]


def _fit_one(grid: tuple[int, int], options: FitOptions, projected: ProjectedScan,
             sample: np.ndarray, stages: _Stages) -> tuple[PatchModel, dict]:
    """The patch of one control grid by ``options.method`` (stages ``sections``, ``linear``,
    ``refine``), and its history for the manifest's ``fit``."""
    proj = projected.coverage.projection
    local, u, v, h = projected.local, projected.u, projected.v, projected.h
    periodic = proj.periodic_u
    poles = proj.kind == "sphere"  # the v = 0 and v = 1 edges are points: close them
    covered = projected.coverage.covered
    deg = (options.degree, options.degree)
    model = PatchModel.uniform(grid, deg)
    stages.start("sections")
    sm = section_matrix(proj, u[covered], v[covered], h[covered],
                        section_shape(int(covered.sum()), grid))
    stages.start("linear")
    if options.method == "tessera":
        smoothing = TESSERA_SMOOTHING
    else:  # as published: no smoothing unless the section matrix has holes to bridge
        smoothing = 0.0 if sm.full else DEFAULT_SMOOTHING
    model = fit_section_matrix(model, sm.u, sm.v, sm.points, sm.valid, periodic, smoothing,
                               poles=poles)
    history: dict = {"section_matrix": list(sm.points.shape[:2]),
                     "section_holes": int((~sm.valid).sum())}
    if options.method == "linear":
        return model, history
    stages.start("refine")
    if options.method == "paper":
        UU, VV = np.meshgrid(sm.u, sm.v, indexing="ij")
        keep = sm.valid.ravel()
        model, energy = refine_nurbs(model, UU.ravel()[keep], VV.ravel()[keep],
                                     sm.points.reshape(-1, 3)[keep], iterations=8,
                                     smoothing=smoothing)
        history["energy"] = energy
        return model, history
    pts = local[sample]
    su, sv = u[sample], v[sample]
    for k in range(CORRECTION_ROUNDS):
        su, sv = project_points(model, pts, su, sv, periodic, iterations=2)
        model = fit_points_linear(model, su, sv, pts, periodic, smoothing, poles=poles)
        stages.report((k + 1) / (CORRECTION_ROUNDS + 1))
    if not periodic:  # weights change the seam's derivatives: periodic patches stay B-splines
        su, sv = project_points(model, pts, su, sv, periodic)
        rational, energy = refine_nurbs(model, su, sv, pts, iterations=8, smoothing=smoothing)
        history["energy"] = energy
        if _weights_kept(energy):
            model = rational
        else:  # the B-spline refine_nurbs started from (its energy[0]): W = 1, no weights coded
            model = fit_points_linear(model, su, sv, pts, periodic, smoothing)
            history["weights_dropped"] = True
    return model, history


def _weights_kept(energy: list[float]) -> bool:
    """Whether the refined weights lower ``E(Q, W)`` (``refine_nurbs``'s history: the
    B-spline's first, the rational patch's last) by at least :data:`RATIONAL_GAIN`."""
    return energy[-1] <= (1.0 - RATIONAL_GAIN) * energy[0]


def _encode_and_measure(model: PatchModel, history: dict, grid: tuple[int, int],
                        options: FitOptions, projected: ProjectedScan,
                        stages: _Stages) -> FitResult:
    """Quantise ``model`` into ``base.tsp`` bytes (stage ``encode``: trim to the drawn cells,
    settle hidden control points, choose the bits) and measure every scan point's
    deviation from the decoded patch (stage ``error``)."""
    proj = projected.coverage.projection
    covered_index, local = projected.covered_index, projected.local
    u, v = projected.u, projected.v
    stages.start("encode")
    probe = covered_index[:: max(1, len(covered_index) // BITS_PROBE)]
    dev = deviations(model, local[probe], u[probe], v[probe], proj.periodic_u)
    fit_rms = float(np.sqrt(np.mean(dev.d**2)))
    drawn = drawn_cells(model, projected.cells, local, fit_rms)
    trim = None if drawn.all() else TrimMask(drawn)
    model = settle_hidden(model, None if trim is None else drawn, proj.periodic_u,
                          poles=proj.kind == "sphere")
    metadata = {"transform": proj.transform, "units": projected.scan.units,
                "projection": proj.kind, "generator": "tessera fit"}
    surface = model.to_surface(trim, metadata)
    history["stray_cells"] = int(projected.cells.sum() - drawn.sum())
    if options.bits is None:
        bits, data = choose_bits(surface, dev.u, dev.v, fit_rms)
    else:
        bits, data = options.bits, write_patch(surface, bits=options.bits)
    history["bits"] = bits
    decoded = PatchModel.from_surface(read_patch(data))
    stages.start("error")
    dev = deviations(decoded, local, u, v, proj.periodic_u)
    stats = error_stats(dev.d[projected.coverage.covered], projected.diagonal,
                        projected.scan.units)
    return FitResult(decoded, data, dev, stats, history | {"grid": list(grid)}, trim)


def _retrimmed(best: FitResult, pyramid: DetailPyramid) -> FitResult:
    """``best`` with the trim of ``pyramid`` (the base's trim at the finest level's
    resolution without that level's walls, ``fitter.fitting.detail.Redraw.walls``): the
    same control points at the same bits, re-encoded with the finer mask. The deviations,
    foot points on the untrimmed surface, stay the same."""
    surface = read_patch(best.data)
    surface.trim = TrimMask(pyramid.trim)
    data = write_patch(surface, bits=best.history["bits"])
    history = best.history | {"finest_trim": list(pyramid.trim.shape),
                              "wall_cells": pyramid.wall_cells}
    if any(pyramid.level_wall_cells):
        history["level_wall_cells"] = pyramid.level_wall_cells
    return replace(best, data=data, trim=surface.trim, history=history)


def fit_base(projected: ProjectedScan, sample: np.ndarray, options: FitOptions,
             stages: _Stages) -> FitResult:
    """The base patch: fitted, encoded and measured for each grid of :func:`_grid_sizes`
    until its RMS deviation (covered points, decoded patch) is at most ``options.max_error``;
    the last one tried."""
    for grid in _grid_sizes(options):
        model, history = _fit_one(grid, options, projected, sample, stages)
        best = _encode_and_measure(model, history, grid, options, projected, stages)
        if options.max_error is None or best.stats["rms"] <= options.max_error:
            break
    return best


def plan_fit_memory(projected: ProjectedScan, options: FitOptions,
                    budget: int = DEFAULT_MEMORY_BUDGET) -> MemoryPlan:
    """The fit's two largest solves checked against ``budget`` bytes before either is built
    (``fitter.fitting.memory.plan_memory``): the base on its largest grid, and the detail
    levels (``options.detail_levels``, or the automatic depth capped to fit).

    Raises
    ------
    OptionError
        ``grid``/``max_grid`` or ``detail_levels``/``detail_spans`` over the budget.
    """
    largest = _grid_sizes(options)[-1]
    n_covered = len(projected.covered_index)
    rows = (min(options.samples, n_covered) if options.method == "tessera"
            else int(np.prod(section_shape(n_covered, largest))))
    return plan_memory(largest, options.degree, rows, options.detail_levels,
                       auto_levels(n_covered, options.detail_spans), options.detail_spans,
                       DETAIL_DEGREE, budget)


def _fit_layers(projected: ProjectedScan, best: FitResult, options: FitOptions,
                plan: MemoryPlan, stages: _Stages) -> tuple[DetailPyramid, list[TextureTile]]:
    """The residual pyramid (stage ``detail``, ``fitter.fitting.detail``, ``plan``'s levels)
    and the colour pyramid (stage ``texture``, ``fitter.fitting.texture``) over ``best``."""
    periodic = projected.coverage.projection.periodic_u
    covered = projected.coverage.covered
    stages.start("detail")
    pyramid = fit_detail(best.model, projected.local, best.dev, covered, periodic,
                         plan.detail_levels, stages.report, trim=read_patch(best.data).trim,
                         spans=options.detail_spans,
                         find_walls=projected.scan.faces is not None,
                         surface=_on_triangles(projected.scan))
    stages.start("texture")
    textures = fit_texture(projected.scan, best.dev, covered, periodic, len(pyramid.levels),
                           options.texture)
    return pyramid, textures


def _on_triangles(scan: Scan) -> np.ndarray | None:
    """``(N,)`` booleans: the points a mesh's triangles use; ``None`` for a cloud."""
    if scan.faces is None:
        return None
    used = np.zeros(len(scan.points), bool)
    used[np.asarray(scan.faces, dtype=np.int64).ravel()] = True
    return used


def object_title(scan: Scan, options: FitOptions) -> str:
    """The option ``title``, else the scan file's name."""
    return options.title or Path(scan.source.get("name", "scan")).name


def _write_drawn(folder: Path, best: FitResult, pyramid: DetailPyramid,
                 textures: list[TextureTile]) -> tuple[dict, dict]:
    """Write ``base.tsp`` and the tiles into ``folder``; returns the manifest's ``tiles``
    tree and ``files`` (name -> bytes)."""
    (folder / "base.tsp").write_bytes(best.data)
    tiles, tile_files = write_layers(folder, pyramid, textures)
    return tiles, {"base.tsp": len(best.data)} | tile_files


def _with_pieces(folder: Path, projected: ProjectedScan, best: FitResult, pieces: dict | None
                 ) -> tuple[FitResult, np.ndarray]:
    """``best`` measured against the patch with the pieces written in ``folder`` (their
    manifest entry ``pieces``, drawn with the patch at every level): each point's deviation,
    or its distance to the pieces where nearer (``pieces.with_pieces_deviations``), and the
    statistics of the points the bundle represents: the projection's covered points and
    those nearer the pieces, returned as a mask. ``best`` and the covered points as they
    are when no pieces are drawn."""
    covered = projected.coverage.covered
    if pieces is None or pieces["file"] is None:
        return best, covered
    d, nearer = with_pieces_deviations(best.dev.d, projected.scan.points,
                                       (folder / pieces["file"]).read_bytes(),
                                       pieces["resolution"])
    covered = covered | nearer
    return replace(best, dev=Deviations(d, best.dev.u, best.dev.v),
                   stats=error_stats(d[covered], projected.diagonal,
                                     projected.scan.units)), covered


def _covered_deviations(best: FitResult, covered: np.ndarray) -> Deviations:
    """The deviations of the ``covered`` points (of every original point, out of core)."""
    if best.full is not None:
        return best.full.covered_dev()
    return Deviations(best.dev.d[covered], best.dev.u[covered], best.dev.v[covered])


def _write_reports(folder: Path, projected: ProjectedScan, best: FitResult,
                   covered: np.ndarray, pyramid: DetailPyramid, options: FitOptions
                   ) -> tuple[dict, dict]:
    """Write ``error_raster.bin`` of the ``covered`` points' deviations, ``error.ply`` and
    ``error.png`` of ``best``'s into ``folder``; returns their ``files`` (name -> bytes) and
    the manifest's ``error_raster`` (``fitter.fitting.error.error_raster``)."""
    scan, units, stats = projected.scan, projected.scan.units, best.stats
    raster, raster_data = error_raster(_covered_deviations(best, covered), stats["max"])
    (folder / RASTER_FILE).write_bytes(raster_data)
    write_error_ply(folder / "error.ply", scan.points, best.dev.d, scan.source.get("origin"))
    write_error_png(folder / "error.png", best.dev, projected.local, units,
                    f"{object_title(projected.scan, options)}: RMS {stats['rms']:.4g} "
                    f"{units}, "
                    f"max {stats['max']:.4g} {units}"
                    + "".join(f"; level {lev.level}: RMS {lev.rms:.3g}"
                              for lev in pyramid.levels[-2:]))
    files = {name: (folder / name).stat().st_size
             for name in (RASTER_FILE, "error.png", "error.ply")}
    return files, raster


def build_manifest(projected: ProjectedScan, options: FitOptions, best: FitResult,
                   tiles: dict, files: dict, timings: dict, raster: dict | None,
                   plan: MemoryPlan | None = None, covered: np.ndarray | None = None) -> dict:
    """The bundle's ``manifest.json`` (``docs/format.md``, "Bundle manifest").

    Keys: ``format`` (``"tessera-bundle"``), ``format_version``
    (``BUNDLE_FORMAT_VERSION``), ``title``, ``description`` (``""`` when none), ``units``
    (the option ``units``, else what the file says); ``files`` (every file but the
    manifest -> its size in bytes); ``base`` (``file``, ``degree [p, q]``, ``grid [n_u,
    n_v]``, ``bits``, ``rational``, ``trimmed``); ``transform`` (patch frame -> scan
    frame, 4x4 row-major); ``projection`` (``kind``, ``requested``, ``coverage``,
    ``uncovered_points``, ``uncovered_bbox [[x, y, z], [x, y, z]]`` or None);
    ``provenance`` (``input``, ``bytes``, ``sha256``, ``points``, ``format``, ``files``
    for a multi-file input, ``origin`` for a scan moved near the origin,
    ``fitter.fitting.io.frame``, and ``warnings``, what the reader read and did not use);
    ``options`` (the ``FitOptions``); ``stats``
    (deviation statistics of the covered points, ``fitter.fitting.error.error_stats``)
    and ``stats_all_points``; ``fit`` (the base fit's history: ``grid``, ``bits``,
    ``section_matrix``, ``section_holes``, ``stray_cells``, ``energy``, ``weights_dropped``
    when the weights were not kept (``_weights_kept``); ``finest_trim``
    and ``wall_cells`` when the finest level's walls were trimmed, ``level_wall_cells``
    with them when a coarser level has walls); ``tiles`` (the
    detail and texture tree, ``docs/format.md`` "Manifest tiles"); ``timings`` (stage
    -> seconds); ``error_raster`` (``raster``: the file of the max ``|d|`` per ``(u, v)``
    cell, one byte each, ``fitter.fitting.error.error_raster``, its ``max`` =
    ``stats.max``; ``None`` in the staged manifest the pieces are fitted against, before
    the raster is written); ``memory``, only
    when the memory budget capped the automatic detail depth
    (``fitter.fitting.memory.MemoryPlan``: the budget, the estimates of the two largest
    solves, the detail levels kept and the depth they would have had); ``view`` (the
    object's ``up`` and ``front`` in scan coordinates and the rules that chose them,
    ``fitter.fitting.orient.find_view``).

    ``covered``: the points the bundle represents, of which ``stats``, ``error_raster`` and
    ``projection.uncovered_*`` are; default the projection's covered points (with detached
    pieces, also those the pieces draw: :func:`_with_pieces`).
    """
    scan, cov, points = projected.scan, projected.coverage, projected.scan.points
    proj = cov.projection
    covered = cov.covered if covered is None else covered
    uncovered = ~covered
    return {
        **object_fields(scan, options),
        "format": "tessera-bundle",
        "format_version": BUNDLE_FORMAT_VERSION,
        "files": dict(files),
        "base": {"file": "base.tsp", "degree": [options.degree] * 2,
                 "grid": best.history["grid"], "bits": best.history["bits"],
                 "rational": bool(not np.all(best.model.W == 1.0)),
                 "trimmed": best.trim is not None},
        "transform": proj.transform,
        "projection": {"kind": proj.kind, "requested": options.projection,
                       "coverage": round(cov.fraction, 6),
                       "uncovered_points": int(uncovered.sum()),
                       "uncovered_bbox": (
                           [points[uncovered].min(axis=0).tolist(),
                            points[uncovered].max(axis=0).tolist()]
                           if uncovered.any() else None)},
        "stats": best.stats,
        "stats_all_points": error_stats(best.dev.d, projected.diagonal, scan.units),
        "fit": best.history,
        "tiles": tiles,
        "timings": dict(timings),
        "error_raster": raster,
        # only when the budget changed the plan, so that an unchanged fit's manifest is too
        **({"memory": plan.manifest()}
           if plan is not None and plan.detail_levels_uncapped is not None else {}),
    }


def object_fields(scan: Scan, options: FitOptions) -> dict:
    """The manifest's fields of the object itself, the same for one patch and an atlas:
    ``title``, ``description`` (``""`` when none), ``units``, ``provenance``, ``options`` and
    ``view`` (``build_manifest``'s docstring)."""
    name = scan.source.get("name", "scan")
    return {
        "title": object_title(scan, options),
        "description": options.description or "",
        "units": scan.units,
        "provenance": {"input": name, "bytes": scan.source.get("bytes"),
                       "sha256": scan.source.get("sha256"), "points": int(scan.n_points),
                       "format": scan.source.get("format"),
                       # a scan moved near the origin (fitter.fitting.io.frame): by how much
                       **({"origin": scan.source["origin"]} if "origin" in scan.source
                          else {}),
                       # what the reader read and did not use (a texture not found, ...)
                       **({"warnings": list(scan.source["warnings"])}
                          if scan.source.get("warnings") else {}),
                       # a .conf registration: each file it read, with its own digest
                       **({"files": scan.source["files"]} if "files" in scan.source
                          else {})},
        "options": {k: (list(x) if isinstance(x, tuple) else x)
                    for k, x in asdict(options).items()},
        "view": find_view(scan, options.up).to_manifest(),
    }


def _amend_out_of_core(manifest: dict, projected: ProjectedScan, full: StreamedError,
                       large: LargeScan) -> None:
    """What ``build_manifest`` took from the working set, of every original point instead:
    ``stats_all_points``, the coverage and the uncovered points, ``provenance.points``; and
    the working set itself (``provenance.working_set``: ``fitter.fitting.stream``)."""
    n = large.n_points
    manifest["stats_all_points"] = error_stats(full.dev.d, projected.diagonal,
                                               projected.scan.units)
    manifest["projection"].update(coverage=round(1.0 - full.uncovered_points / n, 6),
                                  uncovered_points=full.uncovered_points,
                                  uncovered_bbox=full.uncovered_bbox)
    manifest["provenance"].update(points=n, working_set=large.source["thinning"])


def fit_scan(scan: object, out_dir: str | os.PathLike, options: FitOptions | None = None,
             progress: Progress | None = None, *, limits: InputLimits | None = None,
             memory_budget: int = DEFAULT_MEMORY_BUDGET,
             blocks: LocalBlocks | DaskBlocks | None = None) -> Bundle:
    """Fit ``scan`` (a path, a ``Scan`` or an ``(N, 3)`` array) and write the bundle
    ``out_dir`` (``manifest.json``, ``base.tsp``, ``error_raster.bin``, ``error.png``,
    ``error.ply``, tiles, ``pieces.tsa`` when the scan has detached pieces; an atlas's
    files, ``fitter.fitting.atlas.pipeline``),
    replacing a bundle there; it appears whole or not at all (``fitter.fitting.bundle``).

    ``limits`` bounds the read of a path (``fitter.fitting.io.limits``, default
    ``InputLimits()``); ``memory_budget`` (bytes) the fit's largest solves
    (``fitter.fitting.memory``). A scan over ``fitter.fitting.stream.STREAM_ABOVE`` points
    is fitted out of core (``fitter.fitting.stream``), its block passes run by ``blocks``
    (default: threads of this process; ``DaskBlocks(client)`` for a Dask cluster; the
    bundle is the same bytes either way); an atlas of such a scan is fitted to its working
    set (``LargeScan.atlas_scan``) and measured on every point
    (``fitter.fitting.atlas.pipeline.measure_every_point``).

    Raises
    ------
    ScanError
        Unreadable, empty or non-finite scans, an input over ``limits``, too few points
        to fit, a degenerate scan or patch (``fitter.fitting.degenerate``).
    OptionError
        Invalid options, or options whose solves exceed ``memory_budget``.
    """
    with threadpool_limits(limits=1, user_api="blas"):
        return _fit_scan(scan, Path(out_dir), options or FitOptions(), progress, limits,
                         memory_budget, blocks)


def _fit_scan(scan: object, out_dir: Path, options: FitOptions, progress: Progress | None,
              limits: InputLimits | None, memory_budget: int,
              blocks: LocalBlocks | DaskBlocks | None = None) -> Bundle:
    options.grid = tuple(options.grid)
    options.validate()
    check_atlas_options(options)  # an atlas asked for: before the scan is read
    stages = _Stages(progress)
    stages.start("load")
    scan, large = _load(scan, limits, blocks, stages)
    if options.units:  # the option overrides what the file says (fitter.fitting.io)
        scan = replace(scan, units=options.units)
        if large is not None:
            large = replace(large, working=scan, units=options.units, whole=None
                            if large.whole is None else replace(large.whole, units=options.units))
    atlas_refused = None
    whole = scan if large is None or large.whole is None else large.whole
    if wants_atlas(whole, options.patches, options.base):
        _check_scan(scan, options.projection)  # degenerate scans are refused alike
        try:
            fitted = scan if large is None else large.atlas_scan()
            return Bundle(out_dir, fit_atlas_bundle(fitted, out_dir, options, stages,
                                                    object_fields, large))
        except (SurfaceError, AtlasLayoutError, AtlasFitError, WorkingMeshError) as exc:
            if options.patches is not None:  # asked for an atlas: say why there is none
                raise
            atlas_refused = str(exc)  # auto: the single patch, and the manifest says why
        finally:
            forget_scenes()  # the fit's meshes are done with: their BVHs need not stay alive
    if large is not None:  # one patch: the mesh held for a working mesh is done with
        large = replace(large, whole=None)
    stages.start("project")
    projected = project_scan(scan, options)
    plan = plan_fit_memory(projected, options, memory_budget)  # before any large solve
    sample = _fit_sample(projected, options, stages)
    best = fit_base(projected, sample, options, stages)
    if large is not None:  # every original point against the chosen base
        stages.start("error")
        best.full = large.measure(best.data, projected.coverage.projection,
                                  projected.coverage.covered, stages.report)
        best.stats = error_stats(best.full.covered_dev().d, projected.diagonal, scan.units)
    check_patch(best.model, projected.name, projected.diagonal)
    pyramid, textures = _fit_layers(projected, best, options, plan, stages)
    if pyramid.trim is not None:  # the finest level's walls left out of the base's trim
        best = _retrimmed(best, pyramid)
    stages.start("report")
    with write_bundle(out_dir) as folder:
        tiles, files = _write_drawn(folder, best, pyramid, textures)
        pieces = None
        if large is None and scan.faces is not None:  # pieces are joined by the triangles
            pieces = fit_pieces(scan, folder, build_manifest(projected, options, best, tiles,
                                                             files, {}, None, plan))
            if pieces is not None and pieces["file"] is not None:
                files[PIECES_FILE] = (folder / PIECES_FILE).stat().st_size
        best, covered = _with_pieces(folder, projected, best, pieces)  # what is drawn
        reports, raster = _write_reports(folder, projected, best, covered, pyramid, options)
        files |= reports
        stages.stop()
        manifest = build_manifest(projected, options, best, tiles, files, stages.timings,
                                  raster, plan, covered)
        if pieces is not None:
            manifest["pieces"] = pieces
        if large is not None:
            _amend_out_of_core(manifest, projected, best.full, large)
        if atlas_refused is not None:
            manifest["atlas_refused"] = atlas_refused
        with open(folder / "manifest.json", "w") as fh:
            json.dump(manifest, fh, indent=1, sort_keys=True)
    return Bundle(out_dir, manifest)
