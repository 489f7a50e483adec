"""Running the app in a background thread, and the headless Chromium that looks at it.

Shared by the browser tests, the web benchmark and the demo: a threaded
werkzeug server on ``127.0.0.1`` and an OS-chosen port (port 0), and the launch
options for Debian's Chromium (never a downloaded browser build).
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
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


#: the viewer page's "done loading" condition: ready, or an error shown
# (null-safe: a page that a click is still navigating away from may have no body yet)
VIEWER_READY = ("!!document.body && (document.body.dataset.ready === '1' "
                "|| !!document.body.dataset.error)")


@contextmanager
def serve_collection(collection: Path) -> Iterator[LiveServer]:
    """The Tessera app over the bundles in ``collection`` (its Pyodide snapshot made, when
    on, before the first page asks for it), live while the ``with`` block runs."""
    from fitter.server import create_app

    app = create_app({"TESSERA_COLLECTION": str(collection), "TESTING": True})
    if app.extensions["tessera_snapshot"] is not None:
        app.extensions["tessera_snapshot"].ensure()
    with LiveServer(app) as live:
        yield live


@contextmanager
def open_viewer(browser, url: str, refined_timeout_ms: float = 90_000) -> Iterator[object]:
    """A Playwright page (1000 x 700, downloads accepted) on the viewer at ``url``, once it
    is ready and its first refinement drawn; ``page.errors`` collects the page's uncaught
    errors and console errors."""
    context = browser.new_context(accept_downloads=True, viewport={"width": 1000, "height": 700})
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    try:
        page.goto(url)
        page.wait_for_function(VIEWER_READY, timeout=90_000)
        page.wait_for_function("document.body.dataset.refined === '1'",
                               timeout=refined_timeout_ms)
        page.errors = errors
        yield page
    finally:
        context.close()


def download_ply(page, level: int, folder: Path) -> Path:
    """The viewer's "Download PLY" of ``level`` on ``page``, saved in ``folder`` once the
    page says its tessellation is done; returns the file."""
    page.select_option("#ply-level", str(level))
    with page.expect_download() as info:
        page.click("#download-ply")
    path = folder / info.value.suggested_filename
    info.value.save_as(path)
    page.wait_for_function("!document.body.dataset.plyBusy", timeout=60_000)
    return path
