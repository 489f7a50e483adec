"""The one place that decides between the numpy and the pure-Python grid kernels.

numpy is an optional accelerator: it is used when importable, unless the
environment variable ``TESSERA_KERNEL`` is ``python`` (or ``numpy``, which then
must be importable). Both kernels give the same results to float32 precision;
the detail-layer and texture operations give the same bits (tests/test_layers.py). A kernel
module provides ``evaluate_grid``, ``field_grid``, ``field_grids``, ``add_level``,
``displace_grid``, ``cell_indices``, ``map_vectors`` and ``sample_texture``
(contracts in ``_kernel_python``).
"""

from __future__ import annotations

import os
from functools import cache

from . import _kernel_python


@cache
def _selected():
    """``(name, module)`` of the kernel: chosen on first use, not at import, so importing
    ``client_py`` (for its errors, say) loads no numpy."""
    wanted = os.environ.get("TESSERA_KERNEL", "").strip().lower()
    if wanted not in ("", "python", "numpy"):
        raise ValueError(f"TESSERA_KERNEL must be 'python' or 'numpy', got {wanted!r}")
    if wanted == "python":
        return "python", _kernel_python
    try:
        from . import _kernel_numpy
    except ImportError:
        if wanted == "numpy":
            raise ImportError("TESSERA_KERNEL=numpy but numpy cannot be imported") from None
        return "python", _kernel_python
    return "numpy", _kernel_numpy


def __getattr__(name: str):
    """``KERNEL_NAME``: the selected kernel's name (PEP 562: read on first use)."""
    if name == "KERNEL_NAME":
        return _selected()[0]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def backend(name: str | None = None):
    """The kernel module named ``name`` (``'python'`` or ``'numpy'``), default the selected."""
    if name is None:
        return _selected()[1]
    if name == "python":
        return _kernel_python
    if name == "numpy":
        from . import _kernel_numpy

        return _kernel_numpy
    raise ValueError(f"kernel must be 'python' or 'numpy', got {name!r}")
