"""Resumable admin uploads (tus 1.0.0 core, creation, expiration, termination, checksum;
``fitter/collection/resumable.py``) through Flask's test client: a scan sent in chunks
becomes the same fit job as a one-request upload; a chunk cut off mid-way resumes from the
server's offset; wrong offsets, chunks past the declared size, sizes over the limit, checksum
mismatches, unfinished uploads sent for a fit, expired uploads and concurrent writers each
get their own 4xx; server memory stays bounded whatever the chunk size."""

from __future__ import annotations

import base64
import hashlib
import io
import os
import threading
import time
import tracemalloc

import pytest
from conftest import ADMIN_TOKEN
from test_admin import FAST

from fitter.collection.catalog import Catalog
from fitter.collection.jobs import JobRunner
from fitter.collection.resumable import READ_BYTES

BEARER = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
BASE = "/admin/api/uploads/resumable"


@pytest.fixture()
def client(admin_app_factory):
    """A test client of a fresh admin app (``client.application``)."""
    return admin_app_factory().test_client()


def metadata(**pairs: str) -> str:
    return ",".join(f"{k} {base64.b64encode(v.encode()).decode()}" for k, v in pairs.items())


def create(client, length: int, options=None, **meta) -> tuple[int, dict, str | None]:
    headers = {**BEARER, "Upload-Length": str(length), "Tus-Resumable": "1.0.0"}
    if meta:
        headers["Upload-Metadata"] = metadata(**meta)
    response = client.post(BASE, headers=headers, data=options or {})
    return response.status_code, response.get_json(), response.headers.get("Location")


def patch(client, url: str, offset: int, chunk: bytes, **headers):
    return client.patch(url, data=chunk, headers={
        **BEARER, "Upload-Offset": str(offset), "Tus-Resumable": "1.0.0",
        "Content-Type": "application/offset+octet-stream", **headers})


def offset_of(client, url: str) -> int:
    response = client.head(url, headers=BEARER)
    assert response.status_code == 200 and response.get_data() == b""
    return int(response.headers["Upload-Offset"])


def send(client, url: str, data: bytes, chunk: int) -> None:
    for start in range(0, len(data), chunk):
        response = patch(client, url, start, data[start:start + chunk])
        assert response.status_code == 204, response.get_json()
        assert int(response.headers["Upload-Offset"]) == min(start + chunk, len(data))


def test_a_scan_sent_in_chunks_becomes_the_same_fit_job(client, relief_ply):
    admin_app = client.application
    data = relief_ply.read_bytes()
    sha = hashlib.sha256(data).hexdigest()
    status, body, url = create(client, len(data), {**FAST, "title": "Chunked relief"},
                               filename="relief.ply", sha256=sha)
    assert status == 201 and url == body["url"] and body["offset"] == 0
    assert body["length"] == len(data) and not body["complete"]
    send(client, url, data, len(data) // 3 + 1)
    listed = client.get(BASE, headers=BEARER).get_json()["uploads"]
    assert [(u["id"], u["complete"]) for u in listed] == [(body["id"], True)]
    response = client.post(f"{url}/fit", headers=BEARER)
    assert response.status_code == 202, response.get_json()
    job = response.get_json()
    with JobRunner(admin_app.config["TESSERA_COLLECTION"], workers=1, poll_interval=0.05):
        deadline = time.monotonic() + 60
        while (state := client.get(job["job_url"], headers=BEARER).get_json())["state"] in (
                "queued", "running") and time.monotonic() < deadline:
            time.sleep(0.1)
    assert state["state"] == "done", state
    assert state["options"]["grid"] == [12, 12] and state["options"]["method"] == "linear"
    with Catalog(admin_app.config["TESSERA_COLLECTION"]) as catalog:
        upload = catalog.get_upload(catalog.get_job(job["job"]).upload_id)
        obj = catalog.get_object(job["object"])
    assert upload["sha256"] == sha and upload["bytes"] == len(data)
    assert upload["original_name"] == "relief.ply" and upload["format"] == "ply"
    assert obj["title"] == "Chunked relief"
    assert client.head(url, headers=BEARER).status_code == 404  # fitted: no longer partial


def test_a_chunk_cut_off_mid_way_keeps_its_bytes_and_the_upload_resumes(client, relief_ply):
    data = relief_ply.read_bytes()
    _, _, url = create(client, len(data), FAST, filename="relief.ply",
                       sha256=hashlib.sha256(data).hexdigest())
    assert patch(client, url, 0, data[:1000]).status_code == 204
    # the client promises 100 kB but the connection drops after 30 kB
    cut = client.patch(url, input_stream=io.BytesIO(data[1000:31_000]), headers={
        **BEARER, "Upload-Offset": "1000", "Content-Type": "application/offset+octet-stream"},
        environ_overrides={"CONTENT_LENGTH": "100000"})
    assert cut.status_code == 400
    assert "cut off after 30000 of its 100000 bytes" in cut.get_json()["error"]
    assert offset_of(client, url) == 31_000
    stale = patch(client, url, 1000, data[1000:])  # a client that did not ask
    assert stale.status_code == 409 and "offset 31000" in stale.get_json()["error"]
    send_from = offset_of(client, url)
    assert patch(client, url, send_from, data[send_from:]).status_code == 204
    assert client.post(f"{url}/fit", headers=BEARER).status_code == 202  # SHA-256 matched


def test_offsets_sizes_and_headers_are_checked(admin_app_factory, relief_ply):
    client = admin_app_factory(TESSERA_UPLOAD_MAX_BYTES=10_000).test_client()
    status, body, _ = create(client, 10_001)
    assert status == 413 and "TESSERA_UPLOAD_MAX_BYTES" in body["error"]
    assert create(client, 0)[0] == 400
    response = client.post(BASE, headers={**BEARER, "Upload-Length": "-5"})
    assert response.status_code == 400 and "Upload-Length" in response.get_json()["error"]
    response = client.post(BASE, headers=BEARER)
    assert response.status_code == 400 and "Upload-Length" in response.get_json()["error"]
    response = client.post(BASE, headers={**BEARER, "Upload-Length": "10",
                                          "Tus-Resumable": "0.2.2"})
    assert response.status_code == 412
    response = client.post(BASE, headers={**BEARER, "Upload-Length": "10",
                                          "Upload-Metadata": "colour cmVk"})
    assert response.status_code == 400 and "unknown key 'colour'" in response.get_json()["error"]
    response = client.post(BASE, headers={**BEARER, "Upload-Length": "10",
                                          "Upload-Metadata": metadata(sha256="abc")})
    assert response.status_code == 400 and "64 hex" in response.get_json()["error"]
    status, body, _ = create(client, 10, {"grid": "1x1"})  # options checked before any byte
    assert status == 400 and "grid" in body["error"]

    _, _, url = create(client, 10_000)
    response = patch(client, url, 5, b"abc")
    assert response.status_code == 409 and "not the server's offset 0" in response.get_json()[
        "error"]
    response = patch(client, url, 0, b"x" * 10_001)
    assert response.status_code == 413 and "declared length of 10000" in response.get_json()[
        "error"]
    response = client.patch(url, data=b"abc", headers={**BEARER, "Upload-Offset": "0",
                                                       "Content-Type": "text/plain"})
    assert response.status_code == 415
    response = client.patch(url, data=b"abc", headers={
        **BEARER, "Content-Type": "application/offset+octet-stream"})
    assert response.status_code == 400 and "Upload-Offset" in response.get_json()["error"]
    assert offset_of(client, url) == 0  # nothing of the refused chunks was written
    assert client.head(f"{BASE}/{'0' * 32}", headers=BEARER).status_code == 404
    assert client.head(f"{BASE}/..%2F..%2Fcatalog.sqlite", headers=BEARER).status_code == 404


def test_fitting_an_unfinished_upload_is_a_409_and_bad_content_a_400(client, relief_ply):
    admin_app = client.application
    data = relief_ply.read_bytes()
    _, _, url = create(client, len(data), filename="relief.ply")
    patch(client, url, 0, data[:5000])
    response = client.post(f"{url}/fit", headers=BEARER)
    assert response.status_code == 409
    assert f"5000 of {len(data)} bytes" in response.get_json()["error"]
    assert offset_of(client, url) == 5000  # still there, resumable
    _, _, other = create(client, 64, filename="notes.txt")
    patch(client, other, 0, b"\x00\x01" * 32)
    response = client.post(f"{other}/fit", headers=BEARER, data={"grid": "0x0"})
    assert response.status_code == 400 and "grid" in response.get_json()["error"]
    assert offset_of(client, other) == 64  # a typo in the options does not lose the upload
    response = client.post(f"{other}/fit", headers=BEARER)
    assert response.status_code == 400 and "not a scan format" in response.get_json()["error"]
    assert client.head(other, headers=BEARER).status_code == 404
    uploads = os.path.join(admin_app.config["TESSERA_COLLECTION"], ".tessera", "uploads")
    assert os.listdir(uploads) == []  # nothing of a refused upload is kept


def test_checksums_of_the_whole_file_and_of_a_chunk(client, relief_ply):
    data = relief_ply.read_bytes()
    _, _, url = create(client, len(data), sha256=hashlib.sha256(b"another file").hexdigest())
    assert patch(client, url, 0, data[:4000]).status_code == 204
    response = patch(client, url, 4000, data[4000:])
    assert response.status_code == 422
    assert hashlib.sha256(data).hexdigest() in response.get_json()["error"]
    assert client.head(url, headers=BEARER).status_code == 404  # discarded

    _, _, url = create(client, len(data))
    chunk = data[:8000]
    wrong = base64.b64encode(hashlib.sha256(b"not it").digest()).decode()
    response = patch(client, url, 0, chunk, **{"Upload-Checksum": f"sha256 {wrong}"})
    assert response.status_code == 460 and "discarded" in response.get_json()["error"]
    assert offset_of(client, url) == 0
    right = base64.b64encode(hashlib.sha1(chunk).digest()).decode()
    assert patch(client, url, 0, chunk, **{"Upload-Checksum": f"sha1 {right}"}
                 ).status_code == 204
    response = patch(client, url, 8000, data[8000:], **{"Upload-Checksum": "md5 AAAA"})
    assert response.status_code == 400 and "sha1, sha256" in response.get_json()["error"]
    assert patch(client, url, 8000, data[8000:]).status_code == 204
    assert client.post(f"{url}/fit", headers=BEARER).status_code == 202


def test_abandoned_uploads_expire_and_are_swept(admin_app_factory, tmp_path):
    app = admin_app_factory(TESSERA_UPLOAD_EXPIRE_S=3600)
    client = app.test_client()
    _, _, idle = create(client, 100)
    patch(client, idle, 0, b"x" * 40)
    _, _, swept = create(client, 100)
    partial = tmp_path / "collection" / ".tessera" / "partial"
    long_ago = time.time() - 3601
    for url in (idle, swept):
        os.utime(partial / url.rsplit("/", 1)[1] / "data.part", (long_ago, long_ago))
    response = patch(client, idle, 40, b"x" * 60)
    assert response.status_code == 410 and "TESSERA_UPLOAD_EXPIRE_S" in response.get_json()[
        "error"]
    assert client.head(idle, headers=BEARER).status_code == 404
    _, body, _ = create(client, 100)  # a creation sweeps the other expired one
    assert sorted(p.name for p in partial.iterdir()) == [body["id"]]
    expires = client.head(body["url"], headers=BEARER).headers["Upload-Expires"]
    assert expires.endswith(" GMT")
    assert client.delete(body["url"], headers=BEARER).status_code == 204  # termination
    assert list(partial.iterdir()) == []


class _HeldBody(io.BytesIO):
    """A request body that sends its first half, then waits for ``release``."""

    def __init__(self, data: bytes) -> None:
        super().__init__(data)
        self.half = len(data) // 2
        self.started, self.release = threading.Event(), threading.Event()

    def _hold(self, wanted: int) -> int:
        position = self.tell()
        if position >= self.half:
            self.started.set()
            assert self.release.wait(10)
            return wanted
        return min(wanted, self.half - position)

    def read(self, size: int = -1) -> bytes:
        return super().read(self._hold(size if size >= 0 else 1 << 40))

    def readinto(self, buffer) -> int:
        return super().readinto(memoryview(buffer)[:self._hold(len(buffer))])


def test_a_second_writer_is_refused_while_a_chunk_is_written(client, relief_ply):
    data = relief_ply.read_bytes()
    admin_app = client.application
    _, _, url = create(client, len(data))
    held = _HeldBody(data)
    results = {}

    def slow_patch() -> None:
        results["first"] = admin_app.test_client().patch(
            url, input_stream=held, headers={**BEARER, "Upload-Offset": "0",
                                            "Content-Type": "application/offset+octet-stream"},
            environ_overrides={"CONTENT_LENGTH": str(len(data))})

    thread = threading.Thread(target=slow_patch)
    thread.start()
    try:
        assert held.started.wait(10)
        second = patch(client, url, 0, data)
        assert second.status_code == 409
        assert "another request is writing" in second.get_json()["error"]
        assert client.post(f"{url}/fit", headers=BEARER).status_code == 409
        assert client.delete(url, headers=BEARER).status_code == 409
    finally:
        held.release.set()
        thread.join(10)
    assert results["first"].status_code == 204
    assert offset_of(client, url) == len(data)
    assert client.post(f"{url}/fit", headers=BEARER).status_code == 202


def test_a_large_chunk_is_written_in_bounded_memory(client):
    size = 48 << 20
    _, _, url = create(client, size)
    body = io.BytesIO(bytes(range(256)) * (size // 256))
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        response = client.patch(url, input_stream=body, headers={
            **BEARER, "Upload-Offset": "0", "Content-Type": "application/offset+octet-stream"},
            environ_overrides={"CONTENT_LENGTH": str(size)})
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    assert response.status_code == 204
    assert peak < 4 * READ_BYTES, f"{peak / 2**20:.1f} MiB held for a 48 MiB chunk"


class _ReadOnlyBody:
    """A request body as gunicorn passes it (``wsgi.input_terminated``): ``read`` only."""

    def __init__(self, data: bytes) -> None:
        self.source = io.BytesIO(data)
        self.pieces: list[int] = []

    def tell(self) -> int:  # for the test client's EnvironBuilder only
        return self.source.tell()

    def seek(self, offset: int, whence: int = 0) -> int:
        return self.source.seek(offset, whence)

    def read(self, size: int = -1) -> bytes:
        piece = self.source.read(size)
        self.pieces.append(len(piece))
        return piece


def test_a_body_without_readinto_is_read_piece_by_piece(client, relief_ply):
    data = relief_ply.read_bytes()
    _, _, url = create(client, len(data), sha256=hashlib.sha256(data).hexdigest())
    headers = {**BEARER, "Upload-Offset": "0", "Content-Type": "application/offset+octet-stream"}
    cut = _ReadOnlyBody(data[:50_000])  # the client went away after 50 kB
    response = client.patch(url, input_stream=cut, headers=headers, environ_overrides={
        "CONTENT_LENGTH": "150000", "wsgi.input_terminated": True})
    assert response.status_code == 400 and "after 50000" in response.get_json()["error"]
    body = _ReadOnlyBody(data[50_000:])
    response = client.patch(url, input_stream=body, headers={**headers, "Upload-Offset": "50000"},
                            environ_overrides={"CONTENT_LENGTH": str(len(data) - 50_000),
                                               "wsgi.input_terminated": True})
    assert response.status_code == 204, response.get_json()
    assert max(body.pieces) <= READ_BYTES
    assert client.post(f"{url}/fit", headers=BEARER).status_code == 202


def test_chunks_written_by_several_processes_still_give_the_file_s_sha256(client, relief_ply):
    """gunicorn's workers each keep their own running hashes: a chunk that reaches another
    process goes on without one, and the whole file is hashed once at the end."""
    from fitter.collection.resumable import _RunningHashes

    partials = client.application.extensions["tessera_partial_uploads"]
    data = relief_ply.read_bytes()
    for declared in (hashlib.sha256(data).hexdigest(), hashlib.sha256(b"other").hexdigest()):
        _, _, url = create(client, len(data), sha256=declared)
        for start in range(0, len(data), 70_000):
            partials._hashes = _RunningHashes()  # the next chunk lands in a fresh process
            assert patch(client, url, start, data[start:start + 70_000]).status_code in (204,
                                                                                         422)
    # the first upload matched (and is complete), the second was refused at its last byte
    (listed,) = client.get(BASE, headers=BEARER).get_json()["uploads"]
    assert listed["complete"] and client.post(f"{listed['url']}/fit",
                                              headers=BEARER).status_code == 202
