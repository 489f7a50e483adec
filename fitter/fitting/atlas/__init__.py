"""Whole objects as an atlas of NURBS patches on a quad layout (issue 13, fitter side).

The pipeline, one module per step:

* :mod:`.surface` — a clean, oriented triangle surface of the scan: a mesh scan repaired
  (duplicates merged, degenerate faces dropped, non-manifold parts split, faces oriented),
  a point cloud reconstructed by screened Poisson (Kazhdan & Hoppe 2013) and trimmed where
  no scan point is near;
* :mod:`.layout` — quadric decimation (Garland & Heckbert 1997) preserving topology, each
  triangle split into three quads: the patch layout, with bilinear initial control points
  (a :class:`client_py.atlas.AtlasSurface`);
* :mod:`.fit` — the base fit: foot points on the layout, one sparse least-squares solve for
  every shared control point, Newton parameter correction across patch borders, and the
  choice of the patch count (:func:`fit_atlas`).
"""

from .fit import AtlasFit, AtlasFitError, fit_atlas
from .layout import AtlasLayoutError, quad_layout
from .surface import ScanSurface, SurfaceError, scan_surface

__all__ = ["AtlasFit", "AtlasFitError", "AtlasLayoutError", "ScanSurface", "SurfaceError",
           "fit_atlas", "quad_layout", "scan_surface"]
