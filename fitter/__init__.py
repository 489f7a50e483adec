"""fitter: the server admin's side of Tessera (CPython only).

Reads heritage scans, fits the single-patch NURBS of Ćurković, Vučina et al.,
writes bundles (``manifest.json``, ``base.tsp``, error report), and serves
collections. Depends on ``client_py`` for the patch format and the evaluator;
``client_py`` never imports ``fitter``.
"""

__version__ = "0.1.0"
