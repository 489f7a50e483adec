"""The fitting library: scan readers, the fit's stages, its options and the bundle writer.

CPython only (numpy, scipy, trimesh). Imports ``client_py`` (the patch and tile
formats, the evaluator) and nothing else of Tessera. Nothing is imported here,
so ``fitter.fitting.options`` stays cheap for the server's admin form.

=================  ===========================================================
``io``             scan readers (PLY, OBJ, STL, OFF, glTF, XYZ, ``.conf``), thinning
``parameterize``   the map to ``[0, 1]^2`` and its covered region
``sections``       the paper's section matrix
``features``       local PCA: where the scan has detail
``nurbs``/``fit``  B-spline and NURBS least squares, parameter correction
``compact``        quantisation bits, drawn cells, hidden control points
``detail``         the displacement pyramid; ``texture``: the colour pyramid
``error``          deviation of every scan point, heat maps
``pieces``         a single patch's detached pieces, a small atlas drawn with it
``cores``          the cores this process may run on: threads and batches; stdlib only
``options``        THE table of fit options (``FitOptions``, CLI, admin form); no numpy
``stages``         the fit's stages in order, with their progress weights; no numpy
``pipeline``       ``fit_scan``: one scan in, one bundle out
``bundle``         the one bundle writer: temporary folder, fsync, atomic rename
``examples``       generated example surfaces (the demo, tests, benchmarks)
=================  ===========================================================
"""
