"""Pausing CPython's cyclic garbage collector while a mesh or a base is built.

The builders of :mod:`client_py.smooth_base` and :mod:`client_py.atlas_mesh` make millions
of small tuples and lists with no reference cycle among them; their growth alone sets off
full collections that find nothing. At ``T = 10,000`` control triangles those took 0.9-1.0
s of the 2.2-3.2 s the smooth base's rows took (1.6 s with the collector paused); in the
welded atlas mesh of 24,000 small patches about a fifth of the time (docs/benchmarks.md,
"Session 32: the viewer's zoom on the smooth default"; CPython 3.11).
"""

from __future__ import annotations

import contextlib
import gc
from collections.abc import Iterator


@contextlib.contextmanager
def without_cyclic_gc() -> Iterator[None]:
    """Pause the cyclic collector, restoring its state after, also on an exception (a
    collector the caller had paused stays paused). Usable as a decorator."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()
