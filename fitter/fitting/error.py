"""The geometric error between the scan and the fitted patch (the paper's Fig. 5 and 9).

Every scan point's deviation is its signed foot-point distance: the distance to
the closest point of the patch (found by :class:`fitter.fitting.closest.ClosestPoints`
from the better of two starts: the point's own projection parameters and the
nearest vertex of a dense tessellation where that is nearer), positive on the side the
patch normal points to. Statistics: RMS, mean absolute, max (the one-sided Hausdorff
distance from the scan), P95, P99, in scan units and relative to the scan's
bounding-box diagonal. Reports: ``error.png`` (a heat map over the parameter
domain and over a render of the object, with a colour bar in scan units) and
``error.ply`` (the scan coloured by deviation, the signed value kept as a
``quality`` property as MeshLab does).
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from client_py.bundle import origin_comments
from client_py.ply import write_points_ply

from .closest import ClosestPoints
from .cores import usable_cores
from .nurbs import PatchModel

CHUNK = 1 << 16  # points per task of the foot-point search (fewer numpy calls than 2^14)
RASTER_FILE = "error_raster.bin"  # the bundle's file of its error raster (one patch or an atlas)
RASTER_SIDE = (8, 64)  # least and most cells per side of a single patch's error raster
RASTER_POINTS_PER_CELL = 4  # about this many covered points per cell, within RASTER_SIDE
RASTER_EMPTY = 255  # the raster's code of a cell without a scan point
RASTER_CHUNK = 1 << 22  # points per chunk of the raster's cell maxima


@dataclass
class Deviations:
    """Per-point signed deviation ``d (N,)`` and foot-point parameters ``u, v (N,)``."""

    d: np.ndarray
    u: np.ndarray
    v: np.ndarray


def deviations(model: PatchModel | ClosestPoints, points: np.ndarray, u0: np.ndarray,
               v0: np.ndarray, periodic_u: bool = False, chunk: int = CHUNK,
               threads: int | None = None,
               near: tuple[np.ndarray, np.ndarray] | None = None) -> Deviations:
    """Signed foot-point distance of every point ``(N, 3)`` (patch frame) to ``model``
    (:class:`fitter.fitting.closest.ClosestPoints` from the projection parameters
    ``u0, v0 (N,)``; or that search itself, built once for many calls), positive on the
    side ``S_u x S_v`` points to. ``near``: each point's tessellation vertex candidates and
    their reach (``ClosestPoints.cell_candidates``), the same result with fewer tree queries.

    Chunks of ``chunk`` points (small enough for the kernel's temporaries to stay in
    cache) run on ``threads`` threads (default: one per core): the work is numpy on whole
    arrays, which releases the GIL.
    """
    closest = model if isinstance(model, ClosestPoints) else ClosestPoints(model, periodic_u)
    d = np.empty(len(points))
    us = np.empty(len(points))
    vs = np.empty(len(points))

    def one_chunk(s: int) -> None:
        p = points[s:s + chunk]
        u, v, S, n = closest(p, u0[s:s + chunk], v0[s:s + chunk],
                             None if near is None else (near[0][s:s + chunk],
                                                        near[1][s:s + chunk]))
        r = p - S
        dist = np.sqrt(np.einsum("ij,ij->i", r, r))
        d[s:s + chunk] = np.where(np.einsum("ij,ij->i", r, n) < 0, -dist, dist)
        us[s:s + chunk], vs[s:s + chunk] = u, v

    starts = range(0, len(points), chunk)
    workers = min(threads or usable_cores(), len(starts))
    if workers <= 1:
        for s in starts:
            one_chunk(s)
    else:
        with ThreadPoolExecutor(workers) as pool:
            list(pool.map(one_chunk, starts))  # list(): re-raise a chunk's error here
    return Deviations(d, us, vs)


def error_stats(d: np.ndarray, bbox_diagonal: float, units: str) -> dict:
    """RMS, mean absolute, signed mean (bias), max, P95, P99 of ``|d|``; relative values
    divide by ``bbox_diagonal``."""
    a = np.abs(d)
    if len(a) == 0:
        raise ValueError("no deviations to summarise: the scan has no covered point")
    stats = {
        "rms": float(np.sqrt(np.mean(d * d))),
        "mean": float(a.mean()),
        "bias": float(d.mean()),
        "max": float(a.max()),
        "p95": float(np.percentile(a, 95)),
        "p99": float(np.percentile(a, 99)),
        "points": int(len(d)),
        "bbox_diagonal": float(bbox_diagonal),
        "units": units,
    }
    for key in ("rms", "mean", "max", "p95", "p99"):
        stats[f"{key}_relative"] = stats[key] / bbox_diagonal if bbox_diagonal > 0 else 0.0
    return stats


def error_raster(dev: Deviations, max_deviation: float) -> tuple[dict, bytes]:
    """The manifest's ``error_raster`` and the bundle's file :data:`RASTER_FILE`: the largest
    ``|d|`` of the covered points in each of ``rows x cols`` cells of the ``(u, v)`` domain
    (row ``i`` = ``u`` in ``[i/rows, (i+1)/rows)``, row-major), quantised to one byte of
    ``max_deviation``.

    ``code = round(254 |d|_cell / max_deviation)`` in ``0..254``, ``255`` for a cell no
    covered point falls in (a hole of the scan, or a part of the patch the scan does not
    cover); the file is the zlib stream (RFC 1950) of the ``rows cols`` codes, fetched by a
    viewer only when its error map is shown (until session 17 the codes were the manifest's
    ``data``, base64: 3.6 KB of Buddha range scan 0's 8.0 KB manifest as served, downloaded
    before any level was drawn). ``max_deviation`` is the statistics' ``max``
    (``error_stats``), so the cell holding the worst point decodes to exactly that value and
    a viewer's colour scale ends where its panel's ``max`` does. ``rows = cols =
    clip(floor(sqrt(N / 4)), 8, 64)`` for ``N`` covered points: about four points per cell, so
    a cell's value is a measurement, not an interpolation. A viewer interpolates the cell
    values bilinearly at its vertices (``web/src/error-map.js``). Returns the manifest entry
    and the file's bytes.
    """
    n = len(dev.d)
    side = int(np.clip(int(np.sqrt(n / RASTER_POINTS_PER_CELL)), *RASTER_SIDE))
    codes = raster_codes(None, dev.u, dev.v, dev.d, 1, side, max_deviation)
    return raster_file(codes, side, max_deviation)


def raster_file(codes: np.ndarray, side: int, max_deviation: float,
                patches: int | None = None) -> tuple[dict, bytes]:
    """The manifest's ``error_raster`` and the bytes of :data:`RASTER_FILE` for the codes of
    :func:`raster_codes`: their zlib stream (RFC 1950), and with ``patches`` (an atlas's,
    ``fitter.fitting.atlas.pipeline.atlas_error_raster``) the patch count, the codes patch
    after patch."""
    data = zlib.compress(codes.tobytes(), 9)
    order = "patch after patch, rows x cols each" if patches is not None else "rows x cols"
    entry = {"file": RASTER_FILE, "rows": side, "cols": side, "statistic": "max |d|",
             "max": float(max_deviation), "bytes": len(data),
             "encoding": f"zlib of uint8 codes, {order} (row = u); code k < 255: "
                         "k / 254 max; 255: no scan point"}
    return (entry if patches is None else {**entry, "patches": int(patches)}), data


def raster_codes(patch: np.ndarray | None, u: np.ndarray, v: np.ndarray, d: np.ndarray,
                 patches: int, side: int, max_deviation: float) -> np.ndarray:
    """The error raster's one-byte codes, ``(patches side side,)`` ``uint8``: for each patch
    (``patch (N,)`` of each point, ``None``: all patch 0; its foot ``u, v (N,)`` in
    ``[0, 1]``) ``side x side`` cells (row ``i`` = ``u`` in ``[i/side, (i+1)/side)``,
    row-major, patch after patch), each the largest ``|d|`` of the points whose foot falls in
    it, ``round(254 |d| / max_deviation)``, and :data:`RASTER_EMPTY` where none falls. The
    rule of :func:`error_raster` (one patch) and of an atlas's ``error_raster``
    (``fitter.fitting.atlas.pipeline``); taken in chunks of :data:`RASTER_CHUNK` points."""
    # the maxima in the deviations' own precision (exact either way): np.maximum.at is
    # several times faster on equal types
    precision = np.result_type(np.asarray(d).dtype, np.float32)
    largest = np.full(patches * side * side, -1.0, precision)
    for s in range(0, len(d), RASTER_CHUNK):  # in chunks: 10^8 points' int64 cells were 2.4 GB
        cell = _cells(u[s:s + RASTER_CHUNK], side) * side
        cell += _cells(v[s:s + RASTER_CHUNK], side)
        if patch is not None:
            cell += np.asarray(patch[s:s + RASTER_CHUNK], dtype=np.intp) * (side * side)
        np.maximum.at(largest, cell, np.abs(d[s:s + RASTER_CHUNK]).astype(largest.dtype))
    largest = largest.astype(np.float64)
    scale = 254.0 / max_deviation if max_deviation > 0 else 0.0
    codes = np.where(largest >= 0, np.rint(np.clip(largest, 0, None) * scale), RASTER_EMPTY)
    return codes.astype(np.uint8)


def _cells(t: np.ndarray, side: int) -> np.ndarray:
    """The cell ``floor(t side)`` of each parameter ``t`` in ``[0, 1]``, clipped to ``0 ..
    side - 1`` (``intp``)."""
    cell = (np.asarray(t) * side).astype(np.intp)
    np.clip(cell, 0, side - 1, out=cell)
    return cell


def _colour_limit(d: np.ndarray) -> float:
    limit = float(np.percentile(np.abs(d), 99)) if len(d) else 0.0
    return limit if limit > 0 else 1.0


def write_error_ply(path: Path, points_scan: np.ndarray, d: np.ndarray,
                    origin: Sequence[float] | None = None) -> None:
    """Binary PLY of the scan points ``(N, 3)`` coloured by signed deviation ``d (N,)``
    (blue - white - red at +-P99), with the deviation as float ``quality`` (no faces;
    written by :func:`client_py.ply.write_points_ply`); ``origin``: what the scan was moved
    by (``fitter.fitting.io.frame``), named in the header as the bundle's PLY names it."""
    import matplotlib

    lut = (matplotlib.colormaps["coolwarm"](np.linspace(0.0, 1.0, 256))[:, :3] * 255).round()
    limit = _colour_limit(d)
    rgb = lut.astype(np.uint8)[np.rint(np.clip(0.5 + 0.5 * d / limit, 0.0, 1.0) * 255)
                               .astype(np.intp)]
    data = write_points_ply(
        np.ascontiguousarray(points_scan, dtype=np.float32), colors=rgb,
        properties={"quality": np.ascontiguousarray(d, dtype=np.float32)},
        comments=["Tessera error report: quality = signed deviation from the patch, "
                  "scan units",
                  f"colour scale: blue -{limit:.6g} .. white 0 .. red +{limit:.6g}",
                  *origin_comments(origin)])
    Path(path).write_bytes(data)


def _depth_view(points: np.ndarray, d: np.ndarray, width: int = 480
                ) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """The deviation of the nearest point per pixel, seen along the patch frame's third axis
    (the largest ``z`` wins, a z-buffer), at about two points per covered pixel; ``NaN``
    where no point falls. Returns the image ``(rows, cols)`` and its ``(x0, x1, y0, y1)``."""
    lo, hi = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    span = np.maximum(hi - lo, 1e-300)
    aspect = span[1] / span[0]
    cols = int(np.clip(np.sqrt(len(d) / 2.0 / max(aspect, 1e-3)), 16, width))
    rows = int(np.clip(round(cols * aspect), 16, 2 * width))
    ix = np.minimum(((points[:, 0] - lo[0]) / span[0] * cols).astype(np.int64), cols - 1)
    iy = np.minimum(((points[:, 1] - lo[1]) / span[1] * rows).astype(np.int64), rows - 1)
    pixel = iy * cols + ix
    nearest = np.full(rows * cols, -np.inf)
    np.maximum.at(nearest, pixel, points[:, 2])
    front = np.flatnonzero(points[:, 2] == nearest[pixel])  # ties: the last point listed
    view = np.full(rows * cols, np.nan)
    view[pixel[front]] = d[front]
    return view.reshape(rows, cols), (lo[0], hi[0], lo[1], hi[1])


def write_error_png(path: Path, dev: Deviations, points_local: np.ndarray, units: str,
                    title: str) -> None:
    """Two panels: mean signed deviation over the ``(u, v)`` domain, and the scan seen
    along the patch frame's third axis, each pixel coloured by the deviation of its
    nearest point (:func:`_depth_view`); one colour bar."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    limit = _colour_limit(dev.d)
    res = int(np.clip(np.sqrt(len(dev.d) / 6.0), 32, 200))  # a few points per pixel
    iu = np.minimum((dev.u * res).astype(np.int64), res - 1)
    iv = np.minimum((dev.v * res).astype(np.int64), res - 1)
    cell = iu * res + iv
    count = np.bincount(cell, minlength=res * res)
    total = np.bincount(cell, weights=dev.d, minlength=res * res)
    heat = np.where(count > 0, total / np.maximum(count, 1), np.nan).reshape(res, res)

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.8), dpi=100,
                             gridspec_kw={"width_ratios": [1, 1.25]})
    kw = {"cmap": "coolwarm", "vmin": -limit, "vmax": limit}
    axes[0].imshow(heat.T, origin="lower", extent=(0, 1, 0, 1), interpolation="nearest", **kw)
    axes[0].set_xlabel("u")
    axes[0].set_ylabel("v")
    axes[0].set_title("deviation over the parameter domain")
    view, extent = _depth_view(points_local, dev.d)
    image = axes[1].imshow(view, origin="lower", extent=extent, interpolation="nearest", **kw)
    axes[1].set_aspect("equal")
    axes[1].set_axis_off()
    axes[1].set_title("deviation on the scan")
    bar = fig.colorbar(image, ax=axes, shrink=0.85)
    bar.set_label(f"signed deviation ({units}); colour range = P99 of |d|")
    fig.suptitle(title)
    fig.savefig(path, metadata={"Software": "Tessera", "CreationDate": None})
    plt.close(fig)
