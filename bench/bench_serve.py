"""Serving benchmark (issue 7): ``tessera serve --production`` under a load generator.

A collection with one fitted object (the generated relief, 20,000 points, 20x20) is
made a managed collection (catalog, admin token, the object published: the public side
then checks the catalog on every bundle request, the configuration a museum runs) and
served by ``tessera serve --production`` (gunicorn, 2 processes x 4 threads, the tarpit
worker of :mod:`fitter.server.tarpit_worker`) in a subprocess. Each URL (the bundle's
``base.tsp`` and three of the viewer's static files) is loaded for a bounded time by
``wrk`` (Debian's package; :data:`WRK_THREADS` = 2 threads driving :data:`CONNECTIONS` = 16
keep-alive connections) when it is on PATH, otherwise by a small Python client (processes
with a persistent ``http.client`` connection each: a weaker generator, competing for the
same 2 cores). Every response that is not 200 and every socket error counts as an error.
Target: >= 1,000 requests/s per URL with zero errors. Writes bench/results/serve.json.
"""

from __future__ import annotations

import http.client
import json
import multiprocessing
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from bench import print_table, write_results

DURATION = 5.0  # seconds per URL
#: wrk's keep-alive connections, and the threads (event loops) that drive them
CONNECTIONS = 16
WRK_THREADS = 2
TARGET = 1000.0
TOKEN = "bench-admin-token-0123456789"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _make_collection(root: Path) -> str:
    from fitter.collection.catalog import Catalog
    from fitter.fitting.examples import relief_scan
    from fitter.fitting.options import FitOptions
    from fitter.fitting.pipeline import fit_scan

    fit_scan(relief_scan(20_000), root / "relief", FitOptions(grid=(20, 20), title="Relief"))
    with Catalog(root, create=True) as catalog:
        from fitter.collection.catalog import adopt_bundles

        adopt_bundles(catalog, publish=True)
    return "relief"


def _wrk(url: str, duration: float, threads: int = WRK_THREADS,
         connections: int = CONNECTIONS) -> dict:
    """``wrk -t threads -c connections`` on ``url`` for ``duration`` s: requests, req/s,
    errors (non-2xx/3xx answers and socket errors), p50 and p99 latency (ms)."""
    out = subprocess.run(["wrk", f"-t{threads}", f"-c{connections}", f"-d{int(duration)}s",
                          "--latency", url], capture_output=True, text=True, check=True).stdout
    rate = float(re.search(r"Requests/sec:\s+([\d.]+)", out).group(1))
    total = int(re.search(r"(\d+) requests in", out).group(1))
    non2xx = re.search(r"Non-2xx or 3xx responses:\s+(\d+)", out)
    sockets = re.search(r"Socket errors: connect (\d+), read (\d+), write (\d+), timeout (\d+)",
                        out)
    errors = (int(non2xx.group(1)) if non2xx else 0) + (
        sum(int(x) for x in sockets.groups()) if sockets else 0)
    p50 = re.search(r"50%\s+([\d.]+)(us|ms|s)", out)
    p99 = re.search(r"99%\s+([\d.]+)(us|ms|s)", out)

    def ms(match: re.Match | None) -> float | None:
        if match is None:
            return None
        scale = {"us": 1e-3, "ms": 1.0, "s": 1e3}[match.group(2)]
        return float(match.group(1)) * scale

    return {"requests": total, "rate": rate, "errors": errors, "p50_ms": ms(p50),
            "p99_ms": ms(p99)}


def _client_loop(host: str, port: int, path: str, duration: float, queue) -> None:
    count = errors = 0
    conn = http.client.HTTPConnection(host, port, timeout=10)
    end = time.perf_counter() + duration
    while time.perf_counter() < end:
        try:
            conn.request("GET", path)
            response = conn.getresponse()
            response.read()
            count += 1
            errors += response.status != 200
        except (OSError, http.client.HTTPException):
            errors += 1
            conn.close()
            conn = http.client.HTTPConnection(host, port, timeout=10)
    queue.put((count, errors))


def _python_load(url: str, duration: float) -> dict:
    match = re.match(r"http://([^:/]+):(\d+)(/.*)", url)
    host, port, path = match.group(1), int(match.group(2)), match.group(3)
    ctx = multiprocessing.get_context("spawn")
    queue = ctx.Queue()
    procs = [ctx.Process(target=_client_loop, args=(host, port, path, duration, queue))
             for _ in range(4)]
    start = time.perf_counter()
    for p in procs:
        p.start()
    results = [queue.get() for _ in procs]
    for p in procs:
        p.join()
    elapsed = time.perf_counter() - start
    total = sum(r[0] for r in results)
    return {"requests": total, "rate": total / elapsed, "errors": sum(r[1] for r in results),
            "p50_ms": None, "p99_ms": None}


@contextmanager
def production_server(root: Path, log_path: Path) -> Iterator[tuple[str, int]]:
    """``tessera serve --production`` (gunicorn, 2 processes x 4 threads) on ``root`` with
    the admin token set, until the block ends: ``(base URL, server pid)``, once
    ``/api/objects`` answers. The server's output goes to ``log_path``."""
    port = _free_port()
    env = {**os.environ, "TESSERA_ADMIN_TOKEN": TOKEN, "TESSERA_PYODIDE_SNAPSHOT": "false"}
    with open(log_path, "wb") as log:
        server = subprocess.Popen([sys.executable, "-m", "fitter.cli", "serve", str(root),
                                   "--production", "--port", str(port), "--processes", "2",
                                   "--threads", "4"],
                                  env=env, stdout=log, stderr=subprocess.STDOUT)
        base = f"http://127.0.0.1:{port}"
        try:
            deadline = time.monotonic() + 30
            while True:
                try:
                    urllib.request.urlopen(base + "/api/objects", timeout=2).read()
                    break
                except OSError:
                    if server.poll() is not None or time.monotonic() > deadline:
                        raise RuntimeError("tessera serve --production did not start: "
                                           + log_path.read_text()) from None
                    time.sleep(0.2)
            yield base, server.pid
        finally:
            server.terminate()
            try:
                server.wait(10)
            except subprocess.TimeoutExpired:  # workers stuck in a request: do not wait on
                server.kill()
                server.wait(10)


def run() -> dict:
    tool = "wrk" if shutil.which("wrk") else "python"
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "collection"
        object_id = _make_collection(root)
        with production_server(root, Path(tmp) / "serve.log") as (base, _):
            paths = [f"/bundles/{object_id}/base.tsp", "/web/src/viewer.js",
                     "/web/src/mesh-worker.js", "/web/src/style.css"]
            rows, records = [], []
            for path in paths:
                size = len(urllib.request.urlopen(base + path).read())
                result = (_wrk if tool == "wrk" else _python_load)(base + path, DURATION)
                ok = result["rate"] >= TARGET and result["errors"] == 0
                records.append({"path": path, "bytes": size, **result, "meets_target": ok})
                rows.append((path, size, result["requests"], round(result["rate"], 1),
                             result["errors"],
                             "" if result["p50_ms"] is None else round(result["p50_ms"], 2),
                             "" if result["p99_ms"] is None else round(result["p99_ms"], 2),
                             "yes" if ok else "NO"))
    print_table(f"tessera serve --production (gunicorn, 2 processes x 4 threads), {tool}, "
                f"{WRK_THREADS} threads x {CONNECTIONS} connections, {DURATION:g} s per URL; "
                f"target >= {TARGET:g} req/s, 0 errors",
                ["URL", "bytes", "requests", "req/s", "errors", "p50 ms", "p99 ms", "target"],
                rows)
    data = {"server": "gunicorn (tessera serve --production --processes 2 --threads 4)",
            "load_generator": tool, "connections": CONNECTIONS,
            "wrk_threads": WRK_THREADS if tool == "wrk" else None, "duration_s": DURATION,
            "target_rps": TARGET, "managed_collection": True, "results": records}
    write_results("serve", data)
    return data


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
