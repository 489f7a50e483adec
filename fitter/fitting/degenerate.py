"""Degenerate scans and patches: refused with a message saying what is degenerate.

A cloud that spans no surface "fits" with RMS 0 and yields a bundle that breaks its
readers (the thumbnail, ``tessera tessellate``). Before a fit, :func:`check_scan_shape`
refuses, for points ``P (N, 3)`` with covariance eigenvalues ``l1 >= l2 >= l3``
(``sigma_i = sqrt(l_i)``, computed on an even sample of at most ``SHAPE_SAMPLE`` points):

* fewer than ``min_distinct`` distinct points (e.g. 1,000 points with 2 distinct values);
* zero extent (``sigma_1 = 0``: all points equal);
* collinear points: ``sigma_2 <= FLAT * sigma_1``;
* a plane (``sigma_3 <= FLAT * sigma_1``) given to a map that needs 3D extent
  (``cylinder``, ``sphere``: their axis or centre is undetermined).

Before the bundle is written, :func:`check_patch` refuses a fitted patch with non-finite
control points or weights, weights ``<= 0``, or zero area
``A = int int |S_u x S_v| du dv`` (midpoint rule on ``AREA_SAMPLES^2`` points)
``<= FLAT^2 d^2`` for the scan's bounding-box diagonal ``d``.
"""

from __future__ import annotations

import numpy as np

from .io.scan import ScanError
from .nurbs import PatchModel

FLAT = 1e-7  # relative spread below which an axis counts as absent (float64 noise ~1e-16)
SHAPE_SAMPLE = 1_000_000
AREA_SAMPLES = 33
#: maps that need the cloud's extent in all three directions
NEEDS_3D = ("cylinder", "sphere")


def count_distinct(points: np.ndarray, enough: int) -> int:
    """Distinct rows of ``points (N, 3)``, counted exactly up to ``enough`` (a prefix is
    tried first, so a cloud with many distinct points costs one small ``unique``)."""
    rows = np.ascontiguousarray(points).view(np.dtype((np.void, points.dtype.itemsize * 3)))
    rows = rows.reshape(-1)
    prefix = rows[: 64 * enough]
    found = len(np.unique(prefix))
    return found if found >= enough or len(prefix) == len(rows) else len(np.unique(rows))


def check_scan_shape(points: np.ndarray, name: str, projection: str,
                     min_distinct: int) -> None:
    """Refuse a degenerate cloud (module docstring) before it is fitted.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Finite coordinates.
    name : str
        The scan's name, for the message.
    projection : str
        The requested map (``auto``, ``plane``, ``cylinder``, ``sphere``).
    min_distinct : int
        Distinct points a fit needs.

    Raises
    ------
    ScanError
        Saying what is degenerate: too few distinct points, zero extent, collinear, or
        planar for a map that needs 3D extent.
    """
    distinct = count_distinct(points, min_distinct)
    if distinct < min_distinct:
        raise ScanError(f"{name}: degenerate scan: {len(points):,} points but only {distinct} "
                        f"distinct; a fit needs at least {min_distinct} distinct points")
    sample = points[:: max(1, len(points) // SHAPE_SAMPLE)]
    centred = sample - sample.mean(axis=0)
    sigma = np.sqrt(np.maximum(np.linalg.eigvalsh(centred.T @ centred / len(sample)), 0))[::-1]
    if not sigma[0] > 0:
        raise ScanError(f"{name}: degenerate scan: zero extent (all points coincide)")
    if sigma[1] <= FLAT * sigma[0]:
        raise ScanError(f"{name}: degenerate scan: the points are collinear (spread "
                        f"{sigma[0]:.3g} along a line, {sigma[1]:.3g} across it); a patch "
                        "needs points spanning a surface")
    if projection in NEEDS_3D and sigma[2] <= FLAT * sigma[0]:
        raise ScanError(f"{name}: degenerate scan for projection={projection}: the points lie "
                        f"in a plane (spread {sigma[2]:.3g} out of it), so the {projection}'s "
                        "axis is undetermined; use projection=plane or auto")


def check_patch(model: PatchModel, name: str, diagonal: float) -> None:
    """Refuse a degenerate fitted patch (module docstring) before it is written.

    Raises
    ------
    ScanError
        Non-finite control points or weights, a weight ``<= 0``, or zero area.
    """
    if not (np.all(np.isfinite(model.Q)) and np.all(np.isfinite(model.W))):
        bad = int(np.count_nonzero(~np.isfinite(model.Q).all(axis=-1) | ~np.isfinite(model.W)))
        raise ScanError(f"{name}: degenerate patch: {bad} of {model.n_ctrl} control points are "
                        "not finite; nothing is written")
    if not np.all(model.W > 0):
        raise ScanError(f"{name}: degenerate patch: weights must be > 0, the smallest is "
                        f"{float(model.W.min()):.3g}; nothing is written")
    t = (np.arange(AREA_SAMPLES) + 0.5) / AREA_SAMPLES
    uu, vv = np.meshgrid(t, t, indexing="ij")
    _, su, sv = model.evaluate(uu.ravel(), vv.ravel(), derivatives=True)
    area = float(np.mean(np.linalg.norm(np.cross(su, sv), axis=1)))
    if not area > FLAT**2 * diagonal**2:
        raise ScanError(f"{name}: degenerate patch: its area is {area:.3g} (scan diagonal "
                        f"{diagonal:.3g}): the fit collapsed to a curve or a point; nothing is "
                        "written")
