"""Independent chunks of work on the machine's cores, in order (:func:`on_threads`)."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

from ..cores import usable_cores


def on_threads(work: Callable[[int], object], count: int, chunk: int, threads: int | None = None,
               progress: Callable[[float], None] | None = None) -> list:
    """``[work(lo) for lo in range(0, count, chunk)]``, on ``threads`` threads (default:
    one per core this process may run on, ``cores.usable_cores``), in that order.

    For loops whose chunks each write their own rows ``lo:lo + chunk`` of arrays made
    beforehand or return their own part, with numpy's array operations, SuperLU and the
    sparse products (which release the GIL): the numbers do not depend on the thread
    count. A chunk's error is raised here. ``progress(share done)`` after each chunk, in
    order."""
    starts = range(0, count, chunk)
    out = []
    with ThreadPoolExecutor(max(1, min(threads or usable_cores(), len(starts)))) as pool:
        for done, part in enumerate(pool.map(work, starts), start=1):
            out.append(part)
            if progress is not None:
                progress(done / len(starts))
    return out
