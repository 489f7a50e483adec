"""Running the app in a background thread, and the headless Chromium that looks at it.

Shared by the browser tests, the web benchmark and the demo: a threaded
werkzeug server on ``127.0.0.1`` and an OS-chosen port (port 0), and the launch
options for Debian's Chromium (never a downloaded browser build).
"""

from __future__ import annotations

import threading
from types import TracebackType

from flask import Flask
from werkzeug.serving import BaseWSGIServer, WSGIRequestHandler, make_server

CHROMIUM_PATH = "/usr/bin/chromium"

#: ``--no-sandbox``: Chromium's sandbox needs user namespaces, absent for root in
#: containers. The rest keeps an offline machine's Chromium from reaching out
#: (and from waiting on the network). WebGL2 runs headless on SwiftShader with
#: no flag.
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-quic",
    "--disable-dev-shm-usage",
]


def chromium_launch_args() -> dict[str, object]:
    """Keyword arguments for Playwright's ``chromium.launch`` (headless Debian Chromium)."""
    return {"executable_path": CHROMIUM_PATH, "args": list(CHROMIUM_ARGS), "headless": True}


class _QuietHandler(WSGIRequestHandler):
    """Logs errors only: tests and benchmarks would drown in one line per request."""

    def log_request(self, code: int | str = "-", size: int | str = "-") -> None:
        return None


class LiveServer:
    """``app`` served on ``host:port`` by a threaded werkzeug server in a daemon thread.

    Use as a context manager; ``url`` is ``http://host:port`` (no trailing slash).
    ``quiet`` (default) leaves out the access log.
    """

    def __init__(self, app: Flask, host: str = "127.0.0.1", port: int = 0,
                 quiet: bool = True) -> None:
        handler = _QuietHandler if quiet else None
        self.server: BaseWSGIServer = make_server(host, port, app, threaded=True,
                                                  request_handler=handler)
        self.url = f"http://{host}:{self.server.server_port}"
        self._thread = threading.Thread(target=self.server.serve_forever, daemon=True,
                                        name="tessera-live-server")

    def start(self) -> LiveServer:
        self._thread.start()
        return self

    def stop(self) -> None:
        self.server.shutdown()
        self.server.server_close()
        self._thread.join(timeout=5)

    def __enter__(self) -> LiveServer:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()
