"""How a Tessera command ends its process: Python's exit handlers, then ``os._exit``.

pymeshlab's plugins bring their own copies of GnuTLS and libtasn1. When the process ends
normally, the C runtime runs every loaded library's unload destructors, and at theirs glibc
found its heap inconsistent and aborted: "malloc_consolidate(): unaligned fastbin chunk
detected", exit status 134, after the command had done its work. This happened in 1 to 5
of 6 runs of ``tessera fit`` on a sphere, or of the colour tests, with pymeshlab 2025.7 and
2023.12 alike (session 30; gdb's backtrace ends in ``_dl_fini`` -> libgnutls -> libtasn1
-> ``free``). Which library left the heap so is not known.

A command's entry point therefore calls :func:`exit_now`. It runs Python's ``atexit``
handlers, flushes the standard streams, and ends the process with ``os._exit``, which skips
only the C libraries' unload. The fit job workers (``fitter.collection.jobs``) end this way
already: multiprocessing ends its children with ``os._exit``.
"""

from __future__ import annotations

import atexit
import os
import sys


def exit_now(code: int | None) -> None:
    """End the process with ``code`` (``None``: 0) once Python's exit handlers have run."""
    atexit._run_exitfuncs()  # what the interpreter's own exit would run first
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe or stream: nothing more to write
            pass
    os._exit(0 if code is None else int(code))
