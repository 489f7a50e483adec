"""A ``client_py`` mesh as numpy arrays (:func:`mesh_arrays`): the one conversion for the
CPython side, the fitter, the server's thumbnails and the benchmarks, each of which may
import ``client_py`` (the lowest layer; the server takes nothing else of the fit).

``client_py`` returns its meshes (``Mesh``, ``AtlasMesh``) as stdlib ``array`` buffers:
``positions`` float32 ``x y z`` per vertex and ``indices`` unsigned ``int`` (``"I"``,
``numpy.uintc``) three per triangle. numpy is imported when the function is called, never
at import time (the browser's client never calls it).
"""

from __future__ import annotations


def mesh_arrays(mesh):
    """The vertices ``(V, 3)`` float64 (the drawn float32 positions, exactly) and the
    triangles ``(T, 3)`` int64 of ``mesh``, any ``client_py`` mesh with ``positions`` and
    ``indices``."""
    import numpy as np

    vertices = np.frombuffer(mesh.positions, dtype=np.float32).reshape(-1, 3).astype(float)
    faces = np.frombuffer(mesh.indices, dtype=np.uintc).reshape(-1, 3).astype(np.int64)
    return vertices, faces
