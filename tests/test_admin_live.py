"""The admin area on a live server: ``kill -9`` of ``tessera serve`` in the middle of a fit
(the job comes back ``interrupted``, no partial bundle, the upload kept, ``retry`` finishes
it), and an admin's whole path in Chromium: log in, upload through the form, watch the job
page reach ``done``, publish, find the object in the gallery and open its viewer."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
import uuid
from pathlib import Path

import pytest
from conftest import ADMIN_TOKEN
from live import VIEWER_READY

from fitter.demo import write_scan_ply
from fitter.fitting.examples import relief_scan

BEARER = {"Authorization": f"Bearer {ADMIN_TOKEN}"}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _request(url: str, method: str = "GET", body: bytes | None = None,
             headers: dict | None = None) -> tuple[int, dict]:
    request = urllib.request.Request(url, data=body, method=method,
                                     headers={**BEARER, **(headers or {})})
    try:
        with urllib.request.urlopen(request, timeout=30) as response:
            return response.status, json.loads(response.read() or b"null")
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read() or b"null")


def _multipart(fields: dict[str, str], filename: str, data: bytes) -> tuple[bytes, str]:
    boundary = uuid.uuid4().hex
    parts = [f'--{boundary}\r\nContent-Disposition: form-data; name="{k}"\r\n\r\n{v}\r\n'.encode()
             for k, v in fields.items()]
    parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="scan"; '
                 f'filename="{filename}"\r\nContent-Type: application/octet-stream\r\n\r\n'
                 .encode() + data + b"\r\n")
    parts.append(f"--{boundary}--\r\n".encode())
    return b"".join(parts), f"multipart/form-data; boundary={boundary}"


class ServeProcess:
    """``tessera serve COLLECTION`` in a subprocess with the admin token, one fit worker."""

    def __init__(self, collection: Path, log: Path) -> None:
        self.port = _free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        env = {**os.environ, "TESSERA_ADMIN_TOKEN": ADMIN_TOKEN,
               "TESSERA_PYODIDE_SNAPSHOT": "false"}
        self.log = open(log, "ab")  # noqa: SIM115 - closed in stop()
        self.process = subprocess.Popen(
            [sys.executable, "-m", "fitter.cli", "serve", str(collection), "--port",
             str(self.port), "--fit-workers", "1"],
            env=env, stdout=self.log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 30
        while True:
            try:
                urllib.request.urlopen(self.url + "/api/objects", timeout=2).read()
                break
            except OSError:
                if self.process.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"tessera serve did not start: {log.read_text()}") from None
                time.sleep(0.1)

    def stop(self, sig: int = signal.SIGTERM) -> None:
        if self.process.poll() is None:
            self.process.send_signal(sig)
            self.process.wait(10)
        self.log.close()


def _wait(url: str, job_id: int, until, timeout: float = 90.0) -> dict:
    deadline = time.monotonic() + timeout
    while True:
        _, job = _request(f"{url}/admin/api/jobs/{job_id}")
        if until(job) or time.monotonic() > deadline:
            return job
        time.sleep(0.1)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie (dead, not yet reaped by its parent) counts as gone; so does a process reaped
    # between the signal and the read (its /proc entry vanishes: ENOENT or ESRCH)
    try:
        state = Path(f"/proc/{pid}/stat").read_text().split(") ")[1]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return not state.startswith("Z")


def test_kill_9_of_the_server_mid_fit_then_restart_and_retry(tmp_path):
    collection = tmp_path / "collection"
    collection.mkdir()
    scan = tmp_path / "relief.ply"
    write_scan_ply(scan, relief_scan(60_000))  # a fit of a few seconds: time to kill it
    server = ServeProcess(collection, tmp_path / "serve.log")
    try:
        body, content_type = _multipart({"grid": "24x24", "title": "Killed"}, "relief.ply",
                                        scan.read_bytes())
        status, created = _request(server.url + "/admin/api/uploads", "POST", body,
                                   {"Content-Type": content_type})
        assert status == 202, created
        job_id = created["job"]
        job = _wait(server.url, job_id, lambda j: j["stage"] in ("refine", "error", "report")
                    or j["state"] not in ("queued", "running"))
        assert job["state"] == "running", job  # caught in the middle of the fit
        import sqlite3

        with sqlite3.connect(collection / ".tessera" / "catalog.sqlite") as conn:
            worker = conn.execute("SELECT worker_pid FROM jobs WHERE id = ?",
                                  (job_id,)).fetchone()[0]
        assert worker and _alive(worker)
        server.process.send_signal(signal.SIGKILL)
        server.process.wait(10)
    finally:
        server.stop()
    deadline = time.monotonic() + 10
    while _alive(worker) and time.monotonic() < deadline:  # the orphaned worker exits too
        time.sleep(0.1)
    assert not _alive(worker)
    time.sleep(0.5)
    assert [p.name for p in collection.iterdir()] == [".tessera"]  # no bundle, whole or half
    uploads = list((collection / ".tessera" / "uploads").rglob("scan.ply"))
    assert len(uploads) == 1 and uploads[0].read_bytes() == scan.read_bytes()

    server = ServeProcess(collection, tmp_path / "serve.log")
    try:
        _, job = _request(f"{server.url}/admin/api/jobs/{job_id}")
        assert job["state"] == "interrupted" and "retry" in job["error"]
        assert not any((collection / ".tessera" / "staging").glob("job-*"))
        status, job = _request(f"{server.url}/admin/api/jobs/{job_id}/retry", "POST")
        assert status == 202 and job["state"] == "queued"
        job = _wait(server.url, job_id, lambda j: j["state"] not in ("queued", "running"))
        assert job["state"] == "done", job
        assert job["attempts"] == 2
        manifest = json.loads((collection / created["object"] / "manifest.json").read_text())
        assert manifest["provenance"]["points"] == 60_000
        assert manifest["title"] == "Killed"
    finally:
        server.stop()


# --------------------------------------------------------------------------- browser
@pytest.fixture()
def admin_live(admin_app_factory, tmp_path):
    from live import LiveServer

    from fitter.collection.jobs import JobRunner

    app = admin_app_factory(TESSERA_PYODIDE_SNAPSHOT=True, TESSERA_CACHE_DIR=str(
        Path(__file__).resolve().parents[1] / "build" / "cache"))
    if app.extensions["tessera_snapshot"] is not None:
        app.extensions["tessera_snapshot"].ensure()  # cached across the suite
    with JobRunner(app.config["TESSERA_COLLECTION"], workers=1, poll_interval=0.05), \
            LiveServer(app) as live:
        yield live


@pytest.mark.browser
def test_admin_uploads_publishes_and_the_viewer_reaches_ready(admin_live, page, relief_ply):
    page.set_default_timeout(60_000)
    page.goto(admin_live.url + "/admin/upload")
    assert "/admin/login" in page.url  # the pages need a login
    page.fill("input[name=token]", ADMIN_TOKEN)
    page.click("button[type=submit]")
    page.wait_for_url("**/admin/upload")
    page.fill("input[name=title]", "Relief from the admin")
    page.set_input_files("input[name=scan]", str(relief_ply))
    page.fill("input[name=grid]", "12x12")
    page.select_option("select[name=method]", "linear")
    page.click("#upload-form button[type=submit]")
    page.wait_for_url("**/admin/jobs/*")
    page.wait_for_selector("#job[data-state=done]")  # the page's own polling shows the end
    assert page.inner_text("#job-percent") == "100%"
    assert page.locator("#job-notes").is_hidden()  # nothing to say of this fit
    page.click("#job-object-link")
    page.click("#publish-toggle")
    page.wait_for_selector("#viewer-link")
    page.goto(admin_live.url + "/")
    cards = page.locator(".card h2")
    assert cards.all_inner_texts() == ["Relief from the admin"]
    page.click(".card a")
    page.wait_for_function(VIEWER_READY)  # after the click's navigation, not before it
    assert page.evaluate("document.body.dataset.error") is None
    assert page.evaluate("document.body.dataset.ready") == "1"
