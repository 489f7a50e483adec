"""The admin JSON API, ``/admin/api/...`` (authentication: see the package docstring).

=========================================  ===================================================
``GET  /admin/api/``                       what the API offers (a list of its routes)
``POST /admin/api/uploads``                multipart: ``scan`` file, ``title``, fit options
                                           -> 202 ``{"job", "object", "job_url"}``
``GET  /admin/api/jobs``                   the latest jobs
``GET  /admin/api/jobs/<id>``              ``{"state", "stage", "progress", "error",
                                           "object", ...}``
``POST /admin/api/jobs/<id>/cancel``       stop it (a running fit's process is killed)
``POST /admin/api/jobs/<id>/retry``        re-queue a failed, interrupted or cancelled job
``GET  /admin/api/objects``                every object of the catalog (``?trash=1``: trash)
``GET|PATCH|DELETE /admin/api/objects/<id>``  read; edit metadata (title, description,
                                           units, ..., ``up``/``front`` ``[x, y, z]``) /
                                           ``published``; trash
``POST /admin/api/objects/<id>/restore``   out of the trash
=========================================  ===================================================
"""

from __future__ import annotations

import time

from flask import request, url_for
from flask.typing import ResponseReturnValue

from ...collection.catalog import ConflictError, FieldError
from ...collection.trash import restore_object, trash_object
from ...collection.uploads import UploadError
from .auth import api_error, bp, state
from .service import accept_upload, object_json

CANCEL_WAIT = 5.0  # seconds a cancel request waits to report the job stopped


@bp.get("/api/")
def api_root() -> ResponseReturnValue:
    return {"routes": sorted(str(rule) for rule in _admin_rules())}


def _admin_rules() -> list:
    from flask import current_app

    return [r for r in current_app.url_map.iter_rules() if r.endpoint.startswith("admin.api")]


@bp.post("/api/uploads")
def api_upload() -> ResponseReturnValue:
    try:
        job_id, object_id = accept_upload(state().catalog(), request.environ, state().limits)
    except UploadError as exc:
        return api_error(str(exc), exc.status)
    return {"job": job_id, "object": object_id,
            "job_url": url_for("admin.api_job", job_id=job_id)}, 202


@bp.get("/api/jobs")
def api_jobs() -> ResponseReturnValue:
    return {"jobs": [job.public() for job in state().catalog().jobs()]}


@bp.get("/api/jobs/<int:job_id>")
def api_job(job_id: int) -> ResponseReturnValue:
    job = state().catalog().get_job(job_id)
    if job is None:
        return api_error(f"no job {job_id}", 404)
    return job.public()


@bp.post("/api/jobs/<int:job_id>/cancel")
def api_cancel(job_id: int) -> ResponseReturnValue:
    catalog = state().catalog()
    job = catalog.request_cancel(job_id)
    if job is None:
        return api_error(f"no job {job_id}", 404)
    if job.state in ("done", "failed", "interrupted"):
        return api_error(f"job {job_id} is {job.state}; there is nothing to cancel", 409)
    deadline = time.monotonic() + CANCEL_WAIT
    while job.state == "running" and time.monotonic() < deadline:
        time.sleep(0.1)
        job = catalog.get_job(job_id)
    return job.public(), (200 if job.state == "cancelled" else 202)


@bp.post("/api/jobs/<int:job_id>/retry")
def api_retry(job_id: int) -> ResponseReturnValue:
    try:
        job = state().catalog().retry_job(job_id)
    except ConflictError as exc:
        return api_error(str(exc), 409)
    if job is None:
        return api_error(f"no job {job_id}", 404)
    return job.public(), 202


@bp.get("/api/objects")
def api_objects() -> ResponseReturnValue:
    catalog = state().catalog()
    trash = request.args.get("trash", "0") not in ("", "0", "false")
    return {"objects": [object_json(catalog, row) for row in catalog.objects(trashed=trash)]}


@bp.get("/api/objects/<object_id>")
def api_object(object_id: str) -> ResponseReturnValue:
    catalog = state().catalog()
    row = catalog.get_object(object_id)
    if row is None:
        return api_error(f"no object {object_id!r}", 404)
    return object_json(catalog, row, with_view=True)


@bp.patch("/api/objects/<object_id>")
def api_edit_object(object_id: str) -> ResponseReturnValue:
    data = request.get_json(silent=True)
    if not isinstance(data, dict) or not data:
        return api_error("send a JSON object of fields to change, e.g. {\"published\": true}",
                         400)
    catalog = state().catalog()
    try:
        catalog.update_object(object_id, data)  # unknown keys: a FieldError naming them
    except KeyError:
        return api_error(f"no object {object_id!r}", 404)
    except FieldError as exc:
        return api_error(str(exc), 400)
    except ConflictError as exc:
        return api_error(str(exc), 409)
    return object_json(catalog, catalog.get_object(object_id), with_view=True)


def _move(object_id: str, move) -> ResponseReturnValue:
    """Trash or restore an object (``move(catalog, id)``); its JSON, or 404/409."""
    catalog = state().catalog()
    try:
        move(catalog, object_id)
    except KeyError:
        return api_error(f"no object {object_id!r}", 404)
    except ConflictError as exc:
        return api_error(str(exc), 409)
    return object_json(catalog, catalog.get_object(object_id))


@bp.delete("/api/objects/<object_id>")
def api_delete_object(object_id: str) -> ResponseReturnValue:
    return _move(object_id, trash_object)


@bp.post("/api/objects/<object_id>/restore")
def api_restore_object(object_id: str) -> ResponseReturnValue:
    return _move(object_id, restore_object)
