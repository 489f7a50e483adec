"""The tarpit rule: a connection that presented a refused admin token is held back a while.

A refused token costs the server little (a quarter of a public request, answered before
Flask by :class:`fitter.server.admin.auth.CheapRefusals`), but a client that sends the next
one the moment the refusal arrives, on many connections at once, still takes most of two
cores from the public routes: 32 closed-loop connections of cheap refusals outnumber 16 of
public requests whatever each refusal costs. So the answer to a refused token is given at
once, and then **that connection's next request is not read for** :data:`REFUSED_HOLD_S`
seconds. A held connection sits in the kernel's socket buffers: it costs no request thread,
no process and no CPU (under ``tessera serve --production`` the gunicorn worker of
:mod:`fitter.server.tarpit_worker` keeps it aside and puts it back on its poller when the
time is up). A client that keeps its connection alive is thus answered at most once per
:data:`REFUSED_HOLD_S` per connection, right token or wrong; other connections, including
other connections from the same address (a museum's visitors behind one NAT), are not
slowed. A client that opens a new connection for every token pays a TCP handshake per guess
and meets the per-address limiter as before.

This module holds the rule and the per-process register the application writes into; it
imports only the standard library, so the application runs the same without gunicorn (under
the development server or the test client, :func:`hold_connection` has no socket to mark
and does nothing).
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from typing import Any

#: seconds a connection that presented a refused admin token waits before its next request
#: is read
REFUSED_HOLD_S = 1.0
#: connections one server process holds at once; a refused connection beyond is closed
MAX_HELD_CONNECTIONS = 512
#: the WSGI environ key under which gunicorn passes the request's client socket
SOCKET_ENVIRON_KEY = "gunicorn.socket"

_holds: dict[int, float] = {}  # id(client socket) -> seconds, until its request finishes
_lock = threading.Lock()


def hold_connection(environ: Mapping[str, Any], seconds: float = REFUSED_HOLD_S) -> None:
    """Mark the connection of the request ``environ`` to be held ``seconds`` after its response.

    Called for every refused admin token. Without a gunicorn socket in ``environ`` (the
    development server, the test client) there is nothing to hold and nothing happens.

    Raises
    ------
    ValueError
        When ``seconds`` is not a positive finite number.
    """
    if not 0 < seconds < float("inf"):
        raise ValueError(f"seconds must be a positive finite number, got {seconds!r}")
    sock = environ.get(SOCKET_ENVIRON_KEY)
    if sock is None:
        return
    with _lock:
        _holds[id(sock)] = max(seconds, _holds.get(id(sock), 0.0))


def take_hold(sock: object) -> float:
    """The seconds ``sock``'s connection is to be held (0: none), and forget the mark.

    Called once by the server worker when each request on ``sock`` has finished, so a mark
    never outlives its request (and a later socket with the same ``id`` starts clean).
    """
    with _lock:
        return _holds.pop(id(sock), 0.0)
