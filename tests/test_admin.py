"""The admin area through Flask's test client: the secret guards every route, uploads are
checked and refused with clear messages, jobs run in worker processes and report progress,
publishing decides what the public sees, trash and restore, the catalog's migrations, and
``tessera admin set-token``. The live-server and kill -9 tests are in test_admin_live.py."""

from __future__ import annotations

import gzip
import io
import os
import re
import sqlite3
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
from conftest import ADMIN_TOKEN
from werkzeug.routing import IntegerConverter

from fitter.cli import main
from fitter.collection.catalog import MIGRATIONS, SCHEMA_VERSION, Catalog, CatalogError
from fitter.collection.jobs import JobRunner
from fitter.collection.uploads import UploadError, UploadLimits, safe_member_path, sniff_format
from fitter.demo import write_scan_ply
from fitter.fitting.options import fit_options
from fitter.fitting.pipeline import fit_scan

BEARER = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
FAST = {"grid": "12x12", "method": "linear"}  # a fit of a second or so


def upload(client, data: bytes, name: str = "relief.ply", headers=BEARER, **fields):
    form = {"scan": (io.BytesIO(data), name), **fields}
    return client.post("/admin/api/uploads", headers=headers, data=form,
                        content_type="multipart/form-data")


def wait_for_job(client, job_id: int, timeout: float = 60.0, until=("queued", "running")):
    deadline = time.monotonic() + timeout
    while True:
        job = client.get(f"/admin/api/jobs/{job_id}", headers=BEARER).get_json()
        if job["state"] not in until or time.monotonic() > deadline:
            return job
        time.sleep(0.1)


def csrf_of(client, path: str = "/admin/login") -> str:
    page = client.get(path).get_data(as_text=True)
    return re.search(r'name="csrf_token" value="([^"]+)"', page).group(1)


def login(client, token: str = ADMIN_TOKEN):
    return client.post("/admin/login", data={"token": token, "csrf_token": csrf_of(client)})


def _url_for_rule(rule) -> str:
    """A concrete URL for a rule: ``1`` for integer arguments, ``x`` for the others."""
    values = {}
    for arg in rule.arguments:
        converter = rule._converters[arg]
        values[arg] = 1 if isinstance(converter, IntegerConverter) else "x"
    return rule.build(values)[1]


def _admin_rules(app):
    rules = [r for r in app.url_map.iter_rules() if r.endpoint.startswith("admin.")]
    assert len(rules) >= 20  # the API and the pages are all there
    for rule in rules:
        for method in sorted(rule.methods - {"HEAD", "OPTIONS"}):
            yield rule, method, _url_for_rule(rule)


@pytest.fixture()
def admin_app(admin_app_factory):
    return admin_app_factory()


@pytest.fixture()
def client(admin_app):
    return admin_app.test_client()


@pytest.fixture()
def runner(admin_app):
    with JobRunner(admin_app.config["TESSERA_COLLECTION"], workers=1, poll_interval=0.05) as r:
        yield r


# ------------------------------------------------------------------------ the secret
def test_every_admin_route_refuses_without_the_secret_and_with_a_wrong_one(admin_app):
    client = admin_app.test_client()
    for rule, method, url in _admin_rules(admin_app):
        if rule.endpoint == "admin.login":
            continue
        for headers in ({}, {"Authorization": "Bearer wrong-token-wrong-token"},
                        {"Authorization": f"Basic {ADMIN_TOKEN}"}):
            response = client.open(url, method=method, headers=headers)
            where = f"{method} {url} with {headers or 'nothing'}"
            if url.startswith("/admin/api/"):
                assert response.status_code == 401, where
                assert response.headers["WWW-Authenticate"].startswith("Bearer")
            else:
                assert response.status_code == 302, where
                assert response.headers["Location"].startswith("/admin/login"), where
    # a wrong secret in the login form: no session, the pages still redirect
    wrong = admin_app.test_client()
    assert login(wrong, "not-the-admin-token-at-all").status_code == 401
    for rule, method, url in _admin_rules(admin_app):
        if rule.endpoint != "admin.login" and not url.startswith("/admin/api/"):
            assert wrong.open(url, method=method).status_code == 302, f"{method} {url}"
    # a session from before the secret changed is void
    old = admin_app.test_client()
    assert login(old).status_code == 302
    assert old.get("/admin/").status_code == 200
    state = admin_app.extensions["tessera_admin"]
    state.token_hash, state._verified = "pbkdf2:sha256:1$x$y", set()
    assert old.get("/admin/").status_code == 302
    assert old.get("/admin/api/jobs").status_code == 401


def test_without_a_secret_the_admin_area_is_off_and_the_public_site_works(admin_app_factory):
    app = admin_app_factory(TESSERA_ADMIN_TOKEN="")
    client = app.test_client()
    for _, method, url in _admin_rules(app):
        assert client.open(url, method=method, headers=BEARER).status_code == 404, url
    assert client.get("/").status_code == 200
    assert client.get("/api/objects").get_json() == []


def test_a_short_secret_is_refused(admin_app_factory):
    with pytest.raises(ValueError, match="at least 16 characters"):
        admin_app_factory(TESSERA_ADMIN_TOKEN="short")


def test_login_sets_a_strict_httponly_cookie_and_forms_need_the_csrf_token(client):
    assert client.get("/admin/login").status_code == 200
    response = login(client)
    assert response.status_code == 302 and response.headers["Location"] == "/admin/"
    cookie = next(v for k, v in response.headers.items() if k == "Set-Cookie")
    assert "HttpOnly" in cookie and "SameSite=Strict" in cookie
    assert client.get("/admin/").status_code == 200
    assert client.post("/admin/rescan").status_code == 400  # no CSRF token
    assert client.post("/admin/rescan", data={"csrf_token": "forged"}).status_code == 400
    token = csrf_of(client, "/admin/")
    assert client.post("/admin/rescan", data={"csrf_token": token}).status_code == 302
    # the API with the session (the job page's polling) needs the CSRF header to change things
    assert client.get("/admin/api/jobs").status_code == 200
    assert client.post("/admin/api/jobs/1/cancel").status_code == 403
    assert client.post("/admin/api/jobs/1/cancel",
                       headers={"X-CSRF-Token": token}).status_code == 404
    # no open redirect through the login form
    client.post("/admin/logout", data={"csrf_token": token})
    redirect = client.post("/admin/login", data={"token": ADMIN_TOKEN, "next": "//evil.test/",
                                                 "csrf_token": csrf_of(client)})
    assert redirect.headers["Location"] == "/admin/"


def test_set_token_stores_only_a_hash_and_the_login_accepts_it(tmp_path, monkeypatch, capsys,
                                                              admin_app_factory):
    collection = tmp_path / "collection"
    collection.mkdir()
    secret = "a-secret-set-from-the-command-line"
    monkeypatch.setattr("sys.stdin", io.StringIO(secret + "\n"))
    assert main(["admin", "set-token", str(collection)]) == 0
    database = (collection / ".tessera" / "catalog.sqlite").read_bytes()
    assert secret.encode() not in database
    with Catalog(collection) as catalog:
        assert catalog.get_setting("admin_token_hash").startswith(("scrypt:", "pbkdf2:"))
    app = admin_app_factory(collection, TESSERA_ADMIN_TOKEN="")
    client = app.test_client()
    assert client.get("/admin/api/jobs", headers={"Authorization": f"Bearer {secret}"}
                      ).status_code == 200
    assert login(client, secret).status_code == 302
    monkeypatch.setattr("sys.stdin", io.StringIO("short\n"))
    assert main(["admin", "set-token", str(collection)]) == 2
    assert "at least 16 characters" in capsys.readouterr().err
    assert main(["admin", "set-token", "--generate", str(collection)]) == 0
    generated = capsys.readouterr().out.strip()
    assert len(generated) >= 32 and generated != secret


# --------------------------------------------------------------------- upload round trip
def test_upload_fit_publish_round_trip(admin_app, client, runner, relief_ply):
    response = upload(client, relief_ply.read_bytes(), "Relief scan.PLY", title="Relief",
                      **FAST)
    assert response.status_code == 202, response.get_json()
    body = response.get_json()
    job_id, object_id = body["job"], body["object"]
    assert re.fullmatch(r"relief-[0-9a-f]{6}", object_id)
    seen = set()
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        job = client.get(f"/admin/api/jobs/{job_id}", headers=BEARER).get_json()
        seen.add((job["state"], job["stage"]))
        if job["state"] not in ("queued", "running"):
            break
        time.sleep(0.05)
    assert job["state"] == "done", job
    assert job["progress"] == 1.0 and job["error"] is None and job["object"] == object_id
    assert {stage for state, stage in seen if state == "running"} & {"load", "linear", "error"}
    # stored under a generated name; the client's name is metadata only
    collection = Path(admin_app.config["TESSERA_COLLECTION"])
    stored = [p.name for p in (collection / ".tessera" / "uploads").rglob("*") if p.is_file()]
    assert stored == ["scan.ply"]
    with Catalog(collection) as catalog:
        assert catalog.get_upload(1)["original_name"] == "Relief scan.PLY"
    # the bundle is complete and equals a direct fit of the same file
    direct = fit_scan(relief_ply, collection.parent / "direct", fit_options(job["options"]))
    assert (collection / object_id / "base.tsp").read_bytes() == (
        direct.path / "base.tsp").read_bytes()
    # hidden until published
    assert client.get("/api/objects").get_json() == []
    assert client.get(f"/objects/{object_id}/").status_code == 404
    assert client.get(f"/bundles/{object_id}/base.tsp").status_code == 404
    edit = client.patch(f"/admin/api/objects/{object_id}", headers=BEARER,
                        json={"published": True, "title": "Carved relief"})
    assert edit.status_code == 200 and edit.get_json()["published"] is True
    listed = client.get("/api/objects").get_json()
    assert [o["id"] for o in listed] == [object_id]
    assert listed[0]["title"] == "Carved relief"
    assert b"Carved relief" in client.get("/").data
    assert client.get(f"/objects/{object_id}/").status_code == 200
    assert client.get(f"/bundles/{object_id}/base.tsp").data == (
        collection / object_id / "base.tsp").read_bytes()
    # unpublish hides it again
    client.patch(f"/admin/api/objects/{object_id}", headers=BEARER, json={"published": False})
    assert client.get("/api/objects").get_json() == []


def test_the_admin_pages_upload_follow_and_publish(admin_app, client, runner, relief_ply):
    login(client)
    token = csrf_of(client, "/admin/upload")
    response = client.post("/admin/upload", content_type="multipart/form-data",
                           data={"scan": (io.BytesIO(relief_ply.read_bytes()), "r.ply"),
                                 "title": "Page upload", "csrf_token": token, **FAST})
    assert response.status_code == 302
    job_url = response.headers["Location"]
    job_id = int(job_url.rsplit("/", 1)[1])
    assert wait_for_job(client, job_id)["state"] == "done"
    page = client.get(job_url).get_data(as_text=True)
    assert 'id="admin-config"' in page and f"/admin/api/jobs/{job_id}" in page
    assert '<section id="job-notes" hidden>' in page  # nothing to say of this fit
    assert client.get(f"/admin/api/jobs/{job_id}").get_json()["notes"] == []
    object_id = client.get(f"/admin/api/jobs/{job_id}").get_json()["object"]
    assert 'id="fit-notes"' not in client.get(f"/admin/objects/{object_id}").get_data(
        as_text=True)  # nothing to say of this fit
    assert client.post(f"/admin/objects/{object_id}/publish",
                       data={"csrf_token": token}).status_code == 302
    assert [o["id"] for o in client.get("/api/objects").get_json()] == [object_id]
    edit = client.post(f"/admin/objects/{object_id}",
                       data={"csrf_token": token, "title": "Renamed", "description": "A relief",
                             "provenance": "generated", "licence": "CC0", "units": "mm"})
    assert edit.status_code == 302
    assert client.get("/api/objects").get_json()[0]["title"] == "Renamed"
    # an upload form without its CSRF token is refused and leaves nothing behind
    refused = client.post("/admin/upload", content_type="multipart/form-data",
                          data={"scan": (io.BytesIO(relief_ply.read_bytes()), "r.ply")})
    assert refused.status_code == 400 and b"CSRF" in refused.data
    uploads = Path(admin_app.config["TESSERA_COLLECTION"]) / ".tessera" / "uploads"
    assert len(list(uploads.iterdir())) == 1


def test_the_object_and_job_pages_give_the_fits_notes(admin_app, client, runner):
    """What the reader did not use (two unknown columns of an .xyz upload) is on the
    object's page and on its finished job's page and JSON (which the page shows live); an
    object without notes has none."""
    from fitter.fitting.examples import relief_scan

    login(client)
    points = relief_scan(3000)
    text = "\n".join(" ".join(f"{x:.9g}" for x in (*p, 1, 2)) for p in points) + "\n"
    response = upload(client, text.encode(), "relief.xyz", **FAST)
    assert response.status_code == 202, response.get_data(as_text=True)
    job = response.get_json()["job"]
    assert wait_for_job(client, job)["state"] == "done"
    object_id = client.get(f"/admin/api/jobs/{job}").get_json()["object"]
    page = client.get(f"/admin/objects/{object_id}").get_data(as_text=True)
    assert '<ul class="fit-notes" id="fit-notes">' in page
    assert "<strong>warning</strong>: 2 unrecognised columns were not kept" in page
    notes = client.get(f"/admin/api/jobs/{job}").get_json()["notes"]
    assert [n["label"] for n in notes] == ["warning"]
    assert notes[0]["text"].startswith("2 unrecognised columns were not kept")
    job_page = client.get(f"/admin/jobs/{job}").get_data(as_text=True)
    assert '<section id="job-notes" >' in job_page or '<section id="job-notes">' in job_page
    assert "<strong>warning</strong>: 2 unrecognised columns were not kept" in job_page


# ----------------------------------------------------------------------- refusals
def _zip(members: dict[str, bytes], compression=zipfile.ZIP_DEFLATED) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression) as archive:
        for name, data in members.items():
            archive.writestr(zipfile.ZipInfo(name), data, compress_type=compression)
    return buffer.getvalue()


def _ply_bytes(points: np.ndarray, tmp_path: Path) -> bytes:
    path = tmp_path / "cloud.ply"
    write_scan_ply(path, points)
    return path.read_bytes()


def test_an_upload_over_the_limit_is_a_413(admin_app_factory, relief_ply):
    app = admin_app_factory(TESSERA_UPLOAD_MAX_BYTES=64 * 1024)
    client = app.test_client()
    response = upload(client, relief_ply.read_bytes())
    assert response.status_code == 413
    assert "larger than the limit of 64.0 KiB" in response.get_json()["error"]
    assert client.get("/api/objects").status_code == 200
    uploads = Path(app.config["TESSERA_COLLECTION"]) / ".tessera" / "uploads"
    assert not any(uploads.iterdir())  # nothing half-written is kept


@pytest.mark.parametrize("case, message", [
    ("zip bomb", "decompression bomb"),
    ("gzip bomb", "decompression bomb"),
    ("dot-dot member", "leads out of its folder"),
    ("absolute member", "absolute path"),
    ("windows absolute member", "absolute path"),
    ("two scans in a zip", "exactly one scan"),
    ("empty file", "is empty"),
    ("wrong format", "not a scan format"),
    ("corrupt gzip", "corrupt or truncated"),
])
def test_bad_uploads_are_refused_with_their_own_message(client, tmp_path, relief_ply, case,
                                                        message):
    ply = relief_ply.read_bytes()
    data = {
        "zip bomb": lambda: _zip({"scan.xyz": b"0" * (50 << 20)}),
        "gzip bomb": lambda: gzip.compress(b"ply\n" + b"\0" * (50 << 20)),
        "dot-dot member": lambda: _zip({"../../etc/scan.ply": ply}),
        "absolute member": lambda: _zip({"/tmp/scan.ply": ply}),
        "windows absolute member": lambda: _zip({"C:\\scan.ply": ply}),
        "two scans in a zip": lambda: _zip({"a.ply": ply, "b.ply": ply}),
        "empty file": lambda: b"",
        "wrong format": lambda: b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 8,
        "corrupt gzip": lambda: gzip.compress(ply)[:-200],
    }[case]()
    response = upload(client, data, "scan.ply")
    assert response.status_code == 400, response.get_json()
    assert message in response.get_json()["error"]
    assert client.get("/api/objects").status_code == 200  # the server keeps serving
    assert client.get("/admin/api/jobs", headers=BEARER).get_json()["jobs"] == []


def test_scans_that_cannot_be_fitted_end_as_failed_jobs(client, runner, tmp_path):
    rng = np.random.default_rng(1)
    nan_cloud = rng.normal(size=(500, 3))
    nan_cloud[::7] = np.nan
    flat = np.zeros((500, 3))
    cases = {"nan.ply": (_ply_bytes(nan_cloud, tmp_path), "non-finite"),
             "point.ply": (_ply_bytes(flat, tmp_path), "coincide"),
             "few.xyz": (b"1 2 3\n4 5 6\n7 8 9\n", "at least")}
    jobs = {name: upload(client, data, name, **FAST).get_json()["job"]
            for name, (data, _) in cases.items()}
    for name, (_, message) in cases.items():
        job = wait_for_job(client, jobs[name])
        assert job["state"] == "failed", (name, job)
        assert message in job["error"], (name, job["error"])
    assert client.get("/").status_code == 200


def test_the_upload_page_shows_every_fit_option_of_the_table_with_its_default(client):
    login(client)
    page = client.get("/admin/upload").get_data(as_text=True)
    for name in ("detail_levels", "detail_spans", "texture", "max_grid", "max_error", "grid",
                 "degree", "method", "bits", "projection", "samples", "seed",
                 "feature_strength"):
        assert f'name="{name}"' in page, name
    assert 'name="grid" value="40x40"' in page
    assert 'name="detail_spans" value="16" min="4" max="64"' in page
    assert re.search(r'<select name="texture">\s*<option selected>yes</option>', page)
    assert 'name="max_grid" value="" placeholder="max(128, largest grid side)"' in page


def test_fit_options_are_checked_at_upload(client, relief_ply):
    data = relief_ply.read_bytes()
    bad = upload(client, data, grid="40y40")
    assert bad.status_code == 400 and "grid must be N or NxM" in bad.get_json()["error"]
    bad = upload(client, data, degree="9")
    assert bad.status_code == 400 and "degree must be an integer in 1..5" in bad.get_json()[
        "error"]
    bad = upload(client, data, colour="red")
    assert bad.status_code == 400 and "unknown form field(s) colour" in bad.get_json()["error"]
    bad = client.post("/admin/api/uploads", headers=BEARER, data=b"{}",
                      content_type="application/json")
    assert bad.status_code == 400 and "multipart/form-data" in bad.get_json()["error"]


def test_gzip_and_zip_uploads_are_accepted(client, runner, relief_ply):
    ply = relief_ply.read_bytes()
    ids = [upload(client, gzip.compress(ply), "relief.ply.gz", **FAST).get_json()["job"],
           upload(client, _zip({"folder/relief.ply": ply, "folder/readme.txt": b"hi"}),
                  "relief.zip", **FAST).get_json()["job"]]
    for job_id in ids:
        assert wait_for_job(client, job_id)["state"] == "done"


# ------------------------------------------------------------------------ jobs
def test_cancel_stops_the_running_fit_and_leaves_no_bundle(admin_app, client, runner,
                                                           tmp_path):
    from fitter.fitting.examples import relief_scan

    big = _ply_bytes(relief_scan(150_000), tmp_path)
    job_id = upload(client, big, grid="40x40", method="tessera").get_json()["job"]
    job = wait_for_job(client, job_id, until=("queued",))
    assert job["state"] == "running"
    pid = None
    deadline = time.monotonic() + 10
    while pid is None and time.monotonic() < deadline:
        pid = runner._running.get(job_id) and runner._running[job_id].process.pid
        time.sleep(0.05)
    response = client.post(f"/admin/api/jobs/{job_id}/cancel", headers=BEARER)
    assert response.status_code == 200 and response.get_json()["state"] == "cancelled"
    with pytest.raises(ProcessLookupError):  # the worker process itself is gone
        for _ in range(50):
            os.kill(pid, 0)
            time.sleep(0.1)
    collection = Path(admin_app.config["TESSERA_COLLECTION"])
    assert [p.name for p in collection.iterdir()] == [".tessera"]
    assert not any((collection / ".tessera" / "staging").glob("*"))
    assert client.post(f"/admin/api/jobs/{job_id}/cancel", headers=BEARER).status_code == 200
    done = client.post(f"/admin/api/jobs/{job_id}/retry", headers=BEARER)
    assert done.status_code == 202 and done.get_json()["state"] == "queued"
    client.post(f"/admin/api/jobs/{job_id}/cancel", headers=BEARER)
    assert client.post("/admin/api/jobs/999/retry", headers=BEARER).status_code == 404


def test_retry_is_only_for_ended_jobs(client, runner, relief_ply):
    job_id = upload(client, relief_ply.read_bytes(), **FAST).get_json()["job"]
    assert wait_for_job(client, job_id)["state"] == "done"
    response = client.post(f"/admin/api/jobs/{job_id}/retry", headers=BEARER)
    assert response.status_code == 409 and "only failed" in response.get_json()["error"]


# ----------------------------------------------------------------- trash and publishing
def test_delete_moves_to_the_trash_and_restore_brings_it_back(admin_app, client, runner,
                                                              relief_ply):
    body = upload(client, relief_ply.read_bytes(), **FAST).get_json()
    assert wait_for_job(client, body["job"])["state"] == "done"
    object_id = body["object"]
    collection = Path(admin_app.config["TESSERA_COLLECTION"])
    patch = (collection / object_id / "base.tsp").read_bytes()
    client.patch(f"/admin/api/objects/{object_id}", headers=BEARER, json={"published": True})
    assert client.delete(f"/admin/api/objects/{object_id}", headers=BEARER).status_code == 200
    assert not (collection / object_id).exists()
    assert client.get("/api/objects").get_json() == []
    trashed = client.get("/admin/api/objects?trash=1", headers=BEARER).get_json()["objects"]
    assert [o["id"] for o in trashed] == [object_id]
    again = client.patch(f"/admin/api/objects/{object_id}", headers=BEARER,
                         json={"published": True})
    assert again.status_code == 409 and "trash" in again.get_json()["error"]
    assert client.post(f"/admin/api/objects/{object_id}/restore",
                       headers=BEARER).status_code == 200
    assert (collection / object_id / "base.tsp").read_bytes() == patch
    assert client.get("/api/objects").get_json() == []  # restored unpublished
    assert client.patch(f"/admin/api/objects/{object_id}", headers=BEARER,
                        json={"published": True}).status_code == 200
    assert len(client.get("/api/objects").get_json()) == 1


def test_a_managed_collection_keeps_its_public_bundles_and_hides_new_ones(
        tmp_path, admin_app_factory, relief_ply):
    from fitter.fitting.options import FitOptions

    collection = tmp_path / "collection"
    options = FitOptions(grid=(12, 12), method="linear")
    fit_scan(relief_ply, collection / "old", options)
    from fitter.server import create_app

    plain = create_app({"TESSERA_COLLECTION": str(collection), "TESSERA_PYODIDE_SNAPSHOT": False})
    assert [o["id"] for o in plain.test_client().get("/api/objects").get_json()] == ["old"]
    app = admin_app_factory(collection)  # the catalog is made: what was public stays public
    assert [o["id"] for o in app.test_client().get("/api/objects").get_json()] == ["old"]
    fit_scan(relief_ply, collection / "new", options)  # e.g. by tessera fit-collection
    app = admin_app_factory(collection)
    client = app.test_client()
    assert [o["id"] for o in client.get("/api/objects").get_json()] == ["old"]
    assert client.get("/objects/new/").status_code == 404
    objects = client.get("/admin/api/objects", headers=BEARER).get_json()["objects"]
    assert {o["id"]: o["published"] for o in objects} == {"old": True, "new": False}
    # without a token the catalog still decides what is public
    off = admin_app_factory(collection, TESSERA_ADMIN_TOKEN="")
    assert [o["id"] for o in off.test_client().get("/api/objects").get_json()] == ["old"]


# ------------------------------------------------------------------------ catalog
def test_catalog_migrates_an_old_schema_and_refuses_a_newer_one(tmp_path):
    root = tmp_path / "c"
    (root / ".tessera").mkdir(parents=True)
    conn = sqlite3.connect(root / ".tessera" / "catalog.sqlite")
    for statement in MIGRATIONS[0]:
        conn.execute(statement)
    conn.execute("PRAGMA user_version = 1")
    conn.commit()
    conn.close()
    with Catalog(root) as catalog:
        assert catalog.version == SCHEMA_VERSION
        assert catalog.conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        indexes = {r[0] for r in catalog.conn.execute(
            "SELECT name FROM sqlite_master WHERE type = 'index'")}
        assert {"jobs_state", "jobs_object"} <= indexes
        catalog.conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    with pytest.raises(CatalogError, match="newer than this Tessera"):
        Catalog(root)
    with pytest.raises(FileNotFoundError, match="not managed"):
        Catalog(tmp_path / "elsewhere")


def test_a_runner_start_marks_running_jobs_interrupted(tmp_path):
    root = tmp_path / "c"
    with Catalog(root, create=True) as catalog:
        with catalog.transaction() as conn:
            catalog.add_object("a-1", "A", conn=conn)
            upload_id = catalog.add_upload(conn, "a-1", "a.ply", "uploads/x/scan.ply", 1, "0",
                                           "ply")
            job_id = catalog.add_job(conn, "a-1", upload_id, {"grid": [12, 12]})
        assert catalog.claim_next_job().state == "running"
    (root / ".tessera" / "staging" / f"job-{job_id}" / "a-1").mkdir(parents=True)
    with JobRunner(root, workers=1) as runner:
        assert runner.active
        with Catalog(root) as catalog:
            job = catalog.get_job(job_id)
        assert job.state == "interrupted" and "retry" in job.error
        assert not (root / ".tessera" / "staging").exists()
        second = JobRunner(root, workers=1).start()  # one runner per collection
        assert not second.active


# ------------------------------------------------------------------------ sniffing
def test_formats_are_sniffed_from_the_content(relief_ply):
    head = relief_ply.read_bytes()[:4096]
    assert sniff_format(head, name_hint="scan.obj") == ".ply"
    assert sniff_format(b"# comment\nv 1 2 3\nv 4 5 6\nf 1 2 3\n") == ".obj"
    assert sniff_format(b"OFF\n3 1 0\n0 0 0\n") == ".off"
    assert sniff_format(b"solid x\n facet normal 0 0 1\n") == ".stl"
    binary_stl = b"\0" * 80 + (2).to_bytes(4, "little") + b"\0" * 100
    assert sniff_format(binary_stl, total_size=len(binary_stl)) == ".stl"
    assert sniff_format(b"glTF\x02\0\0\0") == ".glb"
    assert sniff_format(b"1.0 2.0 3.0\n4 5 6\n") == ".xyz"
    assert sniff_format(b"1.0 2.0 3.0 0.5\n4 5 6 0.5\n", name_hint="s.PTS.gz") == ".pts"
    assert sniff_format(b"\x89PNG\r\n\x1a\n\0\0") is None
    assert sniff_format(b"hello world\nthis is text\n") is None


def test_zip_member_names_are_checked():
    assert str(safe_member_path("a/./b/scan.ply")) == "a/b/scan.ply"
    for name in ("../x.ply", "a/../../x.ply", "/etc/x", "\\\\server\\x", "C:/x", "d:x", "..\\x"):
        with pytest.raises(UploadError):
            safe_member_path(name)
    assert UploadLimits().max_bytes == 4 << 30


# ------------------------------------------------------------------------ errors in kind (H2)
@pytest.fixture()
def adopted(tmp_path, admin_app_factory, web_collection):
    """An admin app over a collection holding a copy of relief (adopted and published)."""
    import shutil

    collection = tmp_path / "collection"
    shutil.copytree(web_collection / "relief", collection / "relief",
                    ignore=shutil.ignore_patterns("error.ply", "error.png"))
    return admin_app_factory(collection, PROPAGATE_EXCEPTIONS=False)


@pytest.mark.parametrize("fields, named", [
    ({"object_id": "x"}, "'object_id'"),
    ({"self": 1}, "'self'"),
    ({"fields": {}, "title": "t"}, "'fields'"),
    ({"colour": "red", "size": 3}, "'colour', 'size'"),
])
def test_patch_with_a_key_named_like_a_parameter_is_a_400_naming_it(adopted, fields, named):
    response = adopted.test_client().patch("/admin/api/objects/relief", headers=BEARER,
                                           json=fields)
    assert response.status_code == 400 and response.is_json
    assert f"not editable: {named}" in response.get_json()["error"]


def test_patch_published_must_be_a_boolean(adopted):
    client = adopted.test_client()
    response = client.patch("/admin/api/objects/relief", headers=BEARER,
                            json={"published": "yes"})
    assert response.status_code == 400
    assert "published must be true or false, got 'yes'" in response.get_json()["error"]
    assert client.patch("/admin/api/objects/relief", headers=BEARER,
                        json={"published": False}).get_json()["published"] is False


def test_catalog_update_object_takes_its_fields_as_a_mapping(adopted):
    from fitter.collection.catalog import FieldError

    with Catalog(Path(adopted.config["TESSERA_COLLECTION"])) as catalog:
        catalog.update_object("relief", {"title": "Relief", "published": True})
        assert catalog.get_object("relief")["title"] == "Relief"
        with pytest.raises(FieldError, match="not editable: 'object_id'"):
            catalog.update_object("relief", {"object_id": "other"})


def test_an_admin_error_is_json_under_the_api_and_a_page_elsewhere(adopted):
    def boom():
        raise RuntimeError("a bug")

    adopted.view_functions["admin.api_jobs"] = boom
    adopted.view_functions["admin.jobs"] = boom
    client = adopted.test_client()
    api = client.get("/admin/api/jobs", headers=BEARER)
    assert api.status_code == 500 and api.is_json and "failed" in api.get_json()["error"]
    login(client)
    page = client.get("/admin/jobs")
    assert page.status_code == 500 and page.mimetype == "text/html"
    assert "Something went wrong" in page.get_data(as_text=True)
    wrong_method = client.put("/admin/api/jobs", headers=BEARER)
    assert wrong_method.status_code == 405 and wrong_method.is_json


def test_admin_responses_are_no_store_and_never_framed(adopted):
    client = adopted.test_client()
    for response in (client.get("/admin/login"), client.get("/admin/api/jobs", headers=BEARER),
                     client.get("/admin/api/jobs")):
        assert "no-store" in response.headers["Cache-Control"]
        assert response.headers["X-Frame-Options"] == "DENY"
        assert "frame-ancestors 'none'" in response.headers["Content-Security-Policy"]
        assert response.headers["X-Content-Type-Options"] == "nosniff"
    public = client.get("/objects/relief/")
    assert public.status_code == 200 and "X-Frame-Options" not in public.headers
