"""Whole objects as an atlas of NURBS patches on a quad layout (issue 13, fitter side).

The pipeline, one module per step:

* :mod:`.surface` — a clean, oriented triangle surface of the scan: a mesh scan repaired
  (duplicates merged, degenerate faces dropped, non-manifold parts split, faces oriented),
  a point cloud reconstructed by screened Poisson (Kazhdan & Hoppe 2013) and trimmed where
  no scan point is near;
* :mod:`.layout` — quadric decimation (Garland & Heckbert 1997) preserving topology, each
  triangle split into three quads: the patch layout, with bilinear initial control points
  (a :class:`client_py.atlas.AtlasSurface`);
* :mod:`.patches` — the patches as arrays: batched evaluation, the design matrix, and the
  foot points of points in space (the layout triangle, then Newton point inversion across
  patch borders), shared by the fit, the detail and the colour;
* :mod:`.fit` — the base fit: one sparse least-squares solve for every shared control point
  over foot points corrected each round, the rounding of the codes, and the choice of the
  patch count within the byte budget (:func:`fit_atlas`);
* :mod:`.detail`, :mod:`.texture` — the detail and colour pyramids per patch;
  :mod:`.measure` — every scan point against the drawn mesh; :mod:`.pipeline` — the stages
  of an atlas bundle.

Beside the pipeline, not used by it yet: :mod:`.subdivision` — Catmull-Clark and Loop
subdivision as sparse maps and a control mesh fitted to a scan, the smooth base that
``python -m bench subdivision`` measures against Draco and today's base.
"""

from .fit import AtlasFit, AtlasFitError, fit_atlas
from .layout import AtlasLayoutError, quad_layout
from .surface import ScanSurface, SurfaceError, scan_surface

__all__ = ["AtlasFit", "AtlasFitError", "AtlasLayoutError", "ScanSurface", "SurfaceError",
           "fit_atlas", "quad_layout", "scan_surface"]
