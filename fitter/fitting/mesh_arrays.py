"""A ``client_py`` mesh as numpy arrays: the one conversion for the fitter, the server and
the benchmarks (:func:`mesh_arrays`).

``client_py`` returns its meshes (``Mesh``, ``AtlasMesh``) as stdlib ``array`` buffers:
``positions`` float32 ``x y z`` per vertex and ``indices`` unsigned ``int`` (``"I"``,
``numpy.uintc``) three per triangle. numpy only, so that the serving process (the gallery's
thumbnails, ``fitter.server.thumbnail``) imports it without the fit's modules.
"""

from __future__ import annotations

import numpy as np


def mesh_arrays(mesh) -> tuple[np.ndarray, np.ndarray]:
    """The vertices ``(V, 3)`` float64 (the drawn float32 positions, exactly) and the
    triangles ``(T, 3)`` int64 of ``mesh``, any ``client_py`` mesh with ``positions`` and
    ``indices``."""
    vertices = np.frombuffer(mesh.positions, dtype=np.float32).reshape(-1, 3).astype(float)
    faces = np.frombuffer(mesh.indices, dtype=np.uintc).reshape(-1, 3).astype(np.int64)
    return vertices, faces
