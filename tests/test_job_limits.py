"""A fit job reads its upload with the server's ``TESSERA_UPLOAD_*`` limits, not the CLI's
defaults: ``tessera serve`` hands ``AdminState.limits`` to the job runner, and a refusal
names the setting to raise."""

from __future__ import annotations

import io
import time

from conftest import ADMIN_TOKEN

from fitter.collection.jobs import JobRunner

BEARER = {"Authorization": f"Bearer {ADMIN_TOKEN}"}


def _job(client, job_id: int, timeout: float = 60.0) -> dict:
    deadline = time.monotonic() + timeout
    while True:
        job = client.get(f"/admin/api/jobs/{job_id}", headers=BEARER).get_json()
        if job["state"] not in ("queued", "running") or time.monotonic() > deadline:
            return job
        time.sleep(0.1)


def test_a_job_reads_its_upload_with_the_servers_point_limit(admin_app_factory, relief_ply):
    app = admin_app_factory(TESSERA_UPLOAD_MAX_POINTS=1000)
    limits = app.extensions["tessera_admin"].limits
    assert limits.max_points == 1000
    client = app.test_client()
    response = client.post("/admin/api/uploads", headers=BEARER, content_type="multipart/form-data",
                           data={"scan": (io.BytesIO(relief_ply.read_bytes()), "relief.ply"),
                                 "grid": "12x12", "method": "linear"})
    assert response.status_code in (201, 202), response.get_json()
    with JobRunner(app.config["TESSERA_COLLECTION"], workers=1, poll_interval=0.05,
                   limits=limits):
        job = _job(client, response.get_json()["job"])
    assert job["state"] == "failed"
    assert "TESSERA_UPLOAD_MAX_POINTS" in job["error"] and "1000" in job["error"].replace(",", "")
