"""The admin upload page in Chromium: the scan goes in resumable chunks (web/src/
admin-upload-page.js) with a progress bar; a connection dropped mid-upload is retried from
the server's offset; after a reload, the same file picked again resumes where the server
stopped; the fit job is the one a one-request upload makes."""

from __future__ import annotations

import hashlib
import re

import pytest
from conftest import ADMIN_TOKEN

from fitter.collection.catalog import Catalog

CHUNK = 32 << 10
PATCH_URL = re.compile(r".*/admin/api/uploads/resumable/[0-9a-f]{32}$")


@pytest.fixture()
def upload_live(admin_app_factory):
    from live import LiveServer

    from fitter.collection.jobs import JobRunner

    app = admin_app_factory(TESSERA_UPLOAD_CHUNK_BYTES=CHUNK)
    with JobRunner(app.config["TESSERA_COLLECTION"], workers=1, poll_interval=0.05), \
            LiveServer(app) as live:
        yield app, live


def _login(page, url: str) -> None:
    page.goto(url + "/admin/upload")
    page.fill("input[name=token]", ADMIN_TOKEN)
    page.click("button[type=submit]")
    page.wait_for_url("**/admin/upload")


def _patch_offsets(page) -> list[int]:
    offsets: list[int] = []
    page.on("request", lambda r: offsets.append(int(r.headers["upload-offset"]))
            if r.method == "PATCH" and PATCH_URL.match(r.url) else None)
    return offsets


@pytest.mark.browser
def test_a_dropped_connection_and_a_reload_resume_the_upload(upload_live, page, relief_ply):
    app, live = upload_live
    data = relief_ply.read_bytes()
    assert len(data) > 5 * CHUNK  # several chunks
    page.set_default_timeout(60_000)
    _login(page, live.url)
    offsets = _patch_offsets(page)
    patches = {"n": 0}

    def flaky(route) -> None:
        """The 2nd PATCH's connection drops; from the 4th on, the network is gone."""
        if route.request.method != "PATCH":
            route.continue_()
            return
        patches["n"] += 1
        if patches["n"] == 2 or patches["n"] >= 4:
            route.abort("connectionreset")
        else:
            route.continue_()

    page.route(PATCH_URL, flaky)
    page.fill("input[name=title]", "Relief sent in chunks")
    page.fill("input[name=grid]", "12x12")
    page.select_option("select[name=method]", "linear")
    page.set_input_files("input[name=scan]", str(relief_ply))
    page.click("#upload-form button[type=submit]")
    # the drop is retried from HEAD's offset; then the network goes: the page says so
    page.wait_for_function("Number(document.getElementById('upload-progress').dataset"
                           ".retries || 0) >= 2")
    assert "; retrying in" in page.inner_text("#upload-retry")
    assert offsets[:3] == [0, CHUNK, CHUNK]  # the dropped chunk was sent again
    assert float(page.get_attribute("#upload-bar", "value") or 0) > 0
    sent_before = 2 * CHUNK
    page.unroute(PATCH_URL)

    page.reload()  # the admin reloads; the server keeps the two chunks
    page.wait_for_selector("#upload-unfinished:not([hidden])")
    assert "relief.ply" in page.inner_text("#upload-unfinished-list")
    offsets.clear()
    page.fill("input[name=title]", "Relief sent in chunks")
    page.fill("input[name=grid]", "12x12")
    page.select_option("select[name=method]", "linear")
    page.set_input_files("input[name=scan]", str(relief_ply))  # the same file again
    page.click("#upload-form button[type=submit]")
    page.wait_for_url("**/admin/jobs/*")
    assert offsets[0] == sent_before  # resumed, not restarted
    assert offsets == list(range(sent_before, len(data), CHUNK))
    page.wait_for_selector("#job[data-state=done]")
    assert page.evaluate("Object.keys(localStorage).filter(k => "
                         "k.startsWith('tessera-upload:')).length") == 0

    with Catalog(app.config["TESSERA_COLLECTION"]) as catalog:
        (job,) = catalog.jobs()
        upload = catalog.get_upload(job.upload_id)
        title = catalog.get_object(job.object_id)["title"]
    assert upload["sha256"] == hashlib.sha256(data).hexdigest()
    assert upload["original_name"] == "relief.ply" and title == "Relief sent in chunks"
    assert job.options["grid"] == [12, 12]
    partial = app.extensions["tessera_partial_uploads"].root
    assert list(partial.iterdir()) == []  # taken by the fit
