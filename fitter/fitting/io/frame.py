"""The frame a scan is fitted in: its own, or moved near the origin when it lies far away.

Scanners that register to a site or a map (a terrestrial laser scanner's E57, a LAS file in
UTM coordinates) give an object of a metre some 10^6 m from the origin. Part of a fit runs
in single precision: the nearest-triangle searches (``open3d``'s Embree BVH,
``fitter.fitting.atlas.measure``) and the mesh the viewer draws (``client_py``'s float32
positions, three.js). A float32 coordinate near ``c`` is exact to about ``|c| 2^-24``
(6 x 10^-8 |c|), so an object of diagonal ``D`` at ``|c| = 10^4 D`` is drawn 6 x 10^-4 D
off (a sphere's atlas there: RMS 80 times that of the same sphere at the origin) and at
``10^6 D`` it falls apart (its atlas refused: patches collapsed to points).

So a scan whose box centre has a coordinate more than :data:`FAR` diagonals from 0 is
moved by ``-origin`` (its box centre rounded to the power of ten at or below its diagonal,
a number a person reads back: ``[5000000, 4000000, 300]``, not ``[5000000.0213, …]``; the
moved scan then lies within about one diagonal of the origin), every stage then works in
that frame, and the manifest's ``provenance.origin`` records ``origin``: a bundle coordinate plus
``origin`` is the file's. A scan nearer than that is not moved (its bundle as before).

Moving cannot restore what the file lost: a far scan written in single precision (a
float32 PLY of a unit sphere at 5 x 10^6: steps of 0.5) is fitted as well as its file
allows, and its source's ``warnings`` say so (:func:`single_precision_warning`).

The size of a scan is bounded too (:data:`SIZES`): far below a micrometre or above 10^10
units, the fit's absolute tolerances and single-precision squares under- or overflow (a
sphere of radius 10^-30 left the layout search running; one of 10^30 raised an IndexError
from the BVH); such a scan is refused naming its diagonal.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .scan import Scan, ScanError

#: a scan whose box centre is more than this many diagonals from the origin is moved
FAR = 10.0
#: the diagonals (in the scan's units) a fit accepts
SIZES = (1e-6, 1e10)
#: a far scan whose coordinates are single precision is warned of when a float32 step
#: there is more than this share of its diagonal
FLOAT32_SHARE = 1e-4


def scan_origin(name: str, lo: np.ndarray, hi: np.ndarray) -> np.ndarray | None:
    """The origin a scan of box ``lo, hi`` (each ``(3,)``) is moved by (module docstring),
    ``None`` when it is not moved.

    Raises
    ------
    ScanError
        A diagonal outside :data:`SIZES`, naming it.
    """
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    diagonal = float(np.linalg.norm(hi - lo))
    if diagonal == 0:
        return None  # coincident points: refused as such (fitter.fitting.degenerate)
    if not SIZES[0] <= diagonal <= SIZES[1]:
        raise ScanError(f"{name}: the scan's bounding box has a diagonal of {diagonal:.3g} "
                        f"units; a fit takes {SIZES[0]:g}..{SIZES[1]:g} (rescale the scan, "
                        "e.g. to millimetres or metres)")
    centre = (lo + hi) / 2
    if float(np.abs(centre).max()) <= FAR * diagonal:  # every coordinate within FAR D of 0
        return None
    # to -e decimals, e = floor(log10(D)): 1234567.9, not 1234567.9000000001 (x / 0.1 * 0.1)
    return np.round(centre, -int(np.floor(np.log10(diagonal))))


def single_precision_warning(points: np.ndarray, origin: np.ndarray, diagonal: float
                             ) -> str | None:
    """The warning for a far scan whose coordinates (an even sample of ``points (N, 3)``,
    in the file's frame) all lie on the float32 grid, not all whole numbers, when that
    grid's step at ``origin`` is over :data:`FLOAT32_SHARE` of ``diagonal``; else None."""
    sample = np.asarray(points[:: max(1, len(points) // 100_000)], np.float64)
    if (not np.array_equal(sample, sample.astype(np.float32))
            or np.array_equal(sample, np.round(sample))):
        return None
    far = float(np.abs(origin).max())
    step = float(np.spacing(np.float32(far)))
    if step <= FLOAT32_SHARE * diagonal:
        return None
    return (f"the coordinates are single precision {far:.3g} units from 0: the file holds "
            f"them to about {step:.3g} units, {100 * step / diagonal:.2g} % of the scan's "
            "diagonal (write them in double precision, or nearer the origin)")


def moved_source(source: dict, origin: np.ndarray, points: np.ndarray, diagonal: float
                 ) -> dict:
    """A copy of a scan's ``source`` moved by ``origin``: ``origin`` recorded, and
    :func:`single_precision_warning` of ``points`` (in the file's frame) added to its
    ``warnings`` when it applies."""
    lost = single_precision_warning(points, origin, diagonal)
    return dict(source, origin=[float(x) for x in origin],
                warnings=[*source.get("warnings", []), *([lost] if lost else [])])


def moved(scan: Scan, origin: np.ndarray | None) -> Scan:
    """``scan`` in the frame of ``origin`` (its points minus ``origin``, its source
    :func:`moved_source`); ``scan`` itself when ``origin`` is None."""
    if origin is None:
        return scan
    points = scan.points
    return replace(scan, points=points - origin, source=moved_source(
        scan.source, origin, points, float(np.linalg.norm(np.ptp(points, axis=0)))))


def near_origin(scan: Scan) -> Scan:
    """``scan`` checked for its size and moved near the origin when it lies far away
    (:func:`scan_origin`, :func:`moved`).

    Raises
    ------
    ScanError
        A diagonal outside :data:`SIZES`.
    """
    points = scan.points
    return moved(scan, scan_origin(scan.source.get("name", "scan"), points.min(axis=0),
                                   points.max(axis=0)))
