"""The gunicorn worker of ``tessera serve --production``: gunicorn's ``gthread`` worker that
holds back the connections the tarpit rule names (:mod:`fitter.server.tarpit`).

gunicorn's threaded worker (``gthread``) runs one selector loop on its main thread: it
accepts connections, hands a readable connection to its pool of request threads, and when a
request is done (:meth:`finish_request`, on the main thread) puts a kept-alive connection
back on the selector to wait for its next request. This subclass changes that last step
only: a connection marked by :func:`fitter.server.tarpit.hold_connection` during its request
goes to a heap ordered by release time instead, and is handed to gunicorn's own
:meth:`finish_request` when its time comes (the selector's wait is shortened to the first
release). Until then its next request stays unread in the kernel's buffers: no request
thread, no CPU. Beyond :data:`~fitter.server.tarpit.MAX_HELD_CONNECTIONS` held at once, a
marked connection is closed instead; a stopping worker releases every held connection at
once (gunicorn then answers what arrives with ``Connection: close``).

Needs gunicorn >= 27 (its ``ThreadWorker.finish_request(conn, future)`` and
``wait_for_and_dispatch_events(timeout)``); :data:`WORKER_CLASS` is the name given to
gunicorn's ``worker_class`` setting.
"""

from __future__ import annotations

import heapq
import itertools
import time
from concurrent import futures
from typing import Any

from gunicorn.workers.gthread import ThreadWorker

from .tarpit import MAX_HELD_CONNECTIONS, take_hold

#: gunicorn's ``worker_class`` for this worker
WORKER_CLASS = f"{__name__}.TarpitThreadWorker"

if not all(hasattr(ThreadWorker, name)
           for name in ("finish_request", "wait_for_and_dispatch_events")):
    raise ImportError("fitter.server.tarpit_worker needs gunicorn >= 27.0.1 (ThreadWorker."
                      "finish_request and wait_for_and_dispatch_events); pip install -U "
                      "gunicorn")


def _kept_alive(result: futures.Future) -> bool:
    """Whether the finished request ``result`` left its connection open for another one."""
    return (not result.cancelled() and result.exception() is None
            and result.result() is True)


def _closing() -> futures.Future:
    """A finished request's result that tells gunicorn to close the connection."""
    closed: futures.Future = futures.Future()
    closed.set_result(False)
    return closed


class TarpitThreadWorker(ThreadWorker):
    """``gthread`` with held connections (see the module docstring)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        # (release time, arrival order, connection, its finished request), earliest first
        self.held: list[tuple[float, int, Any, futures.Future]] = []
        self._arrivals = itertools.count()

    def finish_request(self, conn: Any, fs: futures.Future) -> None:
        seconds = take_hold(conn.sock)
        if seconds > 0 and self.alive and _kept_alive(fs):
            if len(self.held) < MAX_HELD_CONNECTIONS:
                heapq.heappush(self.held, (time.monotonic() + seconds, next(self._arrivals),
                                           conn, fs))
                return
            fs = _closing()
        super().finish_request(conn, fs)

    def release_due(self) -> None:
        """Hand the held connections whose time has come (all, when stopping) back to
        gunicorn."""
        now = time.monotonic()
        while self.held and (self.held[0][0] <= now or not self.alive):
            _, _, conn, fs = heapq.heappop(self.held)
            super().finish_request(conn, fs)

    def wait_for_and_dispatch_events(self, timeout: float) -> None:
        self.release_due()
        if self.held:
            timeout = min(timeout, max(0.0, self.held[0][0] - time.monotonic()))
        super().wait_for_and_dispatch_events(timeout)
        self.release_due()
