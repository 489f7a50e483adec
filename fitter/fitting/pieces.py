"""Detached pieces of a single-patch fit, fitted as a small atlas of their own.

A height field holds one depth over each point of its domain: a fragment of the scan seen
through a gap, behind the front surface, is drawn nowhere. On Buddha range scan 0 two such
pieces of 79 and 41 points (5 x 3 mm, 2 cm behind the front, 7.8 % and 2.6 % of the
diagonal from the drawn patch) held 95 % of the bundle's squared error over all points.

After the single patch's fit, :func:`fit_pieces` measures every scan point against the mesh
the client draws at the finest level (``client_py.bundle.tessellate_bundle`` of the staged
bundle); the points farther than :data:`PIECE_REACH` of the diagonal, joined by the scan's
triangles whose three corners are all that far (``atlas.surface.face_pieces``), are the
pieces. Those of at least :data:`MIN_PIECE_POINTS` points, when they hold at most
:data:`MAX_PIECES_SHARE` of the scan's points, are fitted together as one atlas
(``atlas.fit.fit_atlas``, about one layout triangle per piece, its bits by its RMS, on as
many working points as the pieces have, at least :data:`PIECE_WORKING_POINTS`), written
as ``pieces.tsa`` (``atlas.fit.base_file``, as a base is) and drawn with the patch at
every level, without detail (``client_py.bundle.pieces_mesh``). Smaller pieces, points on no such
triangle, and every piece when they are too many or the atlas fit refuses them stay
uncovered: the manifest's ``pieces.uncovered`` counts them with the reason
(docs/format.md, "Pieces").
A point cloud or a scan fitted out of core has no triangles to join its points: it gets
no pieces. The bundle's figures are then of what the browser draws, the patch with its
pieces (:func:`with_pieces_deviations`: ``stats``, ``stats_all_points``, the uncovered
points, ``error_raster``, ``error.ply``, ``error.png``; the gallery's thumbnail draws
them too, ``fitter.server.thumbnail.pieces_of``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from client_py.atlas_format import read_atlas
from client_py.bundle import PIECES_FILE, tessellate_bundle
from client_py.mesh_arrays import mesh_arrays

from .atlas.fit import AUTO_MAX_TRIANGLES, base_file, base_resolution, fit_atlas
from .atlas.measure import drawn_mesh, point_mesh_distance
from .atlas.surface import face_pieces
from .io.scan import Scan, ScanError

#: a scan point farther than this share of the diagonal from the drawn patch is uncovered:
#: the issue's tolerance for "within" (13: >= 99.5 % of all points within 0.5 %)
PIECE_REACH = 0.005
#: the fewest points of a piece fitted: on Buddha range scan 0 the pieces of 20-80 points
#: cost 100-150 bytes each in ``pieces.tsa``, the smaller ones held 0.3 % of its error
MIN_PIECE_POINTS = 20
#: the least working points of the pieces' atlas fit (``fit_atlas``'s ``working_count``, its
#: least allowed), else as many as the pieces' points: pieces of a few hundred points need
#: no 60,000 (Buddha range scan 0's five: 2.2 s against 10.4 s at load 16, the same
#: patches, 696 against 699 bytes, the same RMS over all points)
PIECE_WORKING_POINTS = 1000
#: pieces holding more than this share of the scan's points are not fitted: the scan is no
#: height field with a few fragments but an object for an atlas (the Bali mask forced to one
#: patch: 31 pieces, 20 % of its points, 486 patches, 121 s more at load 16)
MAX_PIECES_SHARE = 0.05


def far_pieces(faces: np.ndarray, far: np.ndarray) -> tuple[list[np.ndarray], int]:
    """The connected pieces of the ``far`` points (a mask over the scan's points) through
    the scan's triangles ``faces (M, 3)`` whose three corners are far: each piece's point
    indices (sorted), largest first; and the count of far points on no such triangle."""
    inside = faces[far[faces].all(axis=1)]
    if not len(inside):
        return [], int(far.sum())
    count, labels = face_pieces(inside, len(far))
    pieces = [np.unique(inside[labels == k]) for k in range(count)]
    pieces.sort(key=len, reverse=True)
    return pieces, int(far.sum()) - sum(len(p) for p in pieces)


def _piece_scan(scan: Scan, points: np.ndarray) -> Scan:
    """The sub-mesh of ``scan`` on ``points`` (indices): its triangles with three corners
    there, renumbered; no per-point data (the pieces carry no colour)."""
    faces = np.asarray(scan.faces, dtype=np.int64)
    number = np.full(scan.n_points, -1, dtype=np.int64)
    number[points] = np.arange(len(points))
    kept = faces[(number[faces] >= 0).all(axis=1)]
    return replace(scan, points=np.asarray(scan.points, dtype=float)[points],
                   faces=number[kept], normals=None, colors=None, uv=None, texture=None)


def drawn_distances(folder: Path, manifest: dict, points: np.ndarray) -> np.ndarray:
    """Distance of every scan point to the mesh the client draws at the bundle's finest
    level, from the bundle files staged in ``folder`` and their ``manifest``."""
    mesh = tessellate_bundle(manifest, lambda name: (folder / name).read_bytes(),
                             kernel="numpy")
    return point_mesh_distance(points, *mesh_arrays(mesh))


def with_pieces_deviations(d: np.ndarray, points: np.ndarray, data: bytes, resolution: int
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Every scan point's signed distance to what the browser draws of a patch with its
    pieces: ``d (N,)``, its deviation from the patch (``fitter.fitting.error.deviations``),
    or, where nearer, its signed distance to the pieces' mesh (``pieces.tsa``'s bytes
    ``data`` tessellated on ``resolution`` samples per patch side, as
    ``client_py.bundle.pieces_mesh`` draws it at every level: the same positions,
    ``atlas.measure.drawn_mesh``). ``points (N, 3)`` in scan coordinates (the patch frame
    is a rotation and a shift of them: the same distances). Returns the distances and the
    mask of the points nearer the pieces (the points the pieces draw)."""
    mesh = drawn_mesh(read_atlas(data)[0], resolution)
    to_pieces = point_mesh_distance(points, mesh.vertices, mesh.faces, signed=True)
    nearer = np.abs(to_pieces) < np.abs(d)
    return np.where(nearer, to_pieces, d), nearer


def _uncovered(pieces: list[np.ndarray], loose: int, reason: str) -> list[dict]:
    out = [{"pieces": len(pieces), "points": int(sum(len(p) for p in pieces)),
            "reason": reason}] if pieces else []
    if loose:
        out.append({"pieces": 0, "points": loose,
                    "reason": "on no scan triangle whose corners are all uncovered"})
    return out


def fit_pieces(scan: Scan, folder: Path, manifest: dict,
               distances: Callable[[Path, dict, np.ndarray], np.ndarray] = drawn_distances
               ) -> dict | None:
    """Fit the scan's pieces the staged single-patch bundle ``folder`` (its ``manifest``)
    does not draw, write ``pieces.tsa`` there and return the manifest's ``pieces`` entry;
    ``None`` (no entry, no file: the bundle as before) when no piece has
    :data:`MIN_PIECE_POINTS` points, or the scan has no triangles.

    The entry: ``file`` (``pieces.tsa``, or ``None`` when the pieces were not fitted: over
    :data:`MAX_PIECES_SHARE` of the points, or refused by the atlas fit), ``patches``,
    ``resolution`` (samples per patch side, drawn at every level), ``bits``, ``pieces`` and
    ``points`` fitted, ``reach`` (:data:`PIECE_REACH`), and ``uncovered``: the pieces and
    points left out, each group with its ``reason``.
    """
    if scan.faces is None or not len(scan.faces):
        return None
    points = np.asarray(scan.points, dtype=float)
    diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    far = distances(folder, manifest, points) > PIECE_REACH * diagonal
    pieces, loose = far_pieces(np.asarray(scan.faces, dtype=np.int64), far)
    fitted = [p for p in pieces if len(p) >= MIN_PIECE_POINTS]
    if not fitted:
        return None
    small = _uncovered(pieces[len(fitted):], loose,
                       f"under {MIN_PIECE_POINTS} points each")
    chosen = np.concatenate(fitted)
    entry = {"reach": PIECE_REACH, "file": None, "pieces": 0, "points": 0}
    share = len(chosen) / len(points)
    if share > MAX_PIECES_SHARE:
        return {**entry, "uncovered": _uncovered(fitted, 0, (
            f"not fitted: {100 * share:.1f} % of the scan's points, over "
            f"{100 * MAX_PIECES_SHARE:g} %: an atlas draws them (--patches auto or N)"))
            + small}
    try:
        fit = fit_atlas(_piece_scan(scan, chosen), 3 * min(len(fitted), AUTO_MAX_TRIANGLES),
                        bits=None, working_count=max(PIECE_WORKING_POINTS, len(chosen)))
    except ScanError as exc:  # SurfaceError, AtlasLayoutError, AtlasFitError: named
        return {**entry, "uncovered": _uncovered(fitted, 0, f"not fitted: {exc}") + small}
    data = base_file(fit.atlas, fit.bits, {"units": scan.units})  # as the fit rounded it
    (folder / PIECES_FILE).write_bytes(data)
    return {**entry, "file": PIECES_FILE, "pieces": len(fitted), "points": int(len(chosen)),
            "patches": len(read_atlas(data)[0].quads),
            "resolution": base_resolution(fit.atlas.spans, len(fit.atlas.quads)), "bits": fit.bits,
            "uncovered": small}
