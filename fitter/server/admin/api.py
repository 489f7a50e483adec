"""The admin JSON API, ``/admin/api/...`` (authentication: see the package docstring).

=========================================  ===================================================
``GET  /admin/api/``                       what the API offers (a list of its routes)
``POST /admin/api/uploads``                multipart: ``scan`` file, ``title``, fit options
                                           -> 202 ``{"job", "object", "job_url"}``
``POST /admin/api/uploads/resumable``      a resumable upload (tus creation): headers
                                           ``Upload-Length``, ``Upload-Metadata``; body: fit
                                           options (form or JSON) -> 201, ``Location``
``GET  /admin/api/uploads/resumable``      the unfinished resumable uploads
``HEAD|GET /admin/api/uploads/resumable/<id>``  ``Upload-Offset`` (GET: JSON too)
``PATCH /admin/api/uploads/resumable/<id>``  bytes at ``Upload-Offset`` -> 204
``DELETE /admin/api/uploads/resumable/<id>``  discard it -> 204
``POST /admin/api/uploads/resumable/<id>/fit``  fit the complete upload (body: fit options
                                           replacing those given at creation) -> 202 as above
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

from flask import current_app, request, url_for
from flask.typing import ResponseReturnValue
from werkzeug.datastructures import MultiDict

from ...collection.catalog import ConflictError, FieldError
from ...collection.resumable import (
    OFFSET_CONTENT_TYPE,
    TUS_EXTENSIONS,
    TUS_VERSION,
    PartialUpload,
    PartialUploads,
    expires_http_date,
    parse_chunk_checksum,
    parse_metadata,
)
from ...collection.trash import restore_object, trash_object
from ...collection.uploads import UploadError
from .auth import api_error, bp, state
from .service import accept_upload, new_upload_folder, object_json, parse_fit_options, queue_fit

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


# ------------------------------------------------------------------ resumable uploads
def _partials() -> PartialUploads:
    return current_app.extensions["tessera_partial_uploads"]


def _tus_headers(upload: PartialUpload | None = None, offset: int | None = None) -> dict:
    """The tus headers of an answer: the version, and the upload's offset, length, expiry."""
    headers = {"Tus-Resumable": TUS_VERSION}
    if upload is not None:
        offset = upload.offset if offset is None else offset
        headers |= {"Upload-Offset": str(offset), "Upload-Length": str(upload.length),
                    "Upload-Expires": expires_http_date(upload.last_activity()
                                                        + _partials().expire_s)}
    return headers


def _tus_error(exc: UploadError) -> ResponseReturnValue:
    response = api_error(str(exc), exc.status)
    response.headers.update(_tus_headers())
    return response


def _header_int(name: str) -> int:
    """A header that must be a non-negative decimal integer (a 400 naming it otherwise)."""
    text = request.headers.get(name)
    if text is None:
        raise UploadError(f"the {name} header is missing")
    if not text.strip().isdigit():
        raise UploadError(f"{name} must be a non-negative integer, got {text[:40]!r}")
    return int(text)


def _check_tus_version() -> None:
    version = request.headers.get("Tus-Resumable")
    if version is not None and version != TUS_VERSION:
        raise UploadError(f"Tus-Resumable {version!r} is not supported; this server speaks "
                          f"{TUS_VERSION}", status=412)


def _fit_options_from_body() -> dict | None:
    """Fit options from the request body (a form or a JSON object), validated; None for an
    empty body."""
    if request.mimetype == "application/json":
        data = request.get_json(silent=True)
        if not isinstance(data, dict):
            raise UploadError("the body must be a JSON object of fit options, e.g. "
                              '{"grid": "40x40", "title": "Relief"}')
        form = MultiDict({k: str(v).lower() if isinstance(v, bool) else
                          "" if v is None else str(v) for k, v in data.items()})
    elif request.mimetype == "application/x-www-form-urlencoded":
        form = request.form
    elif not request.content_length:
        return None
    else:
        raise UploadError(f"send the fit options as application/x-www-form-urlencoded or "
                          f"application/json, not {request.mimetype}", status=415)
    return parse_fit_options(form) if form else None


def _resumable_json(upload: PartialUpload) -> dict:
    return {**upload.public(_partials().expire_s),
            "url": url_for("admin.api_resumable", upload_id=upload.id)}


@bp.post("/api/uploads/resumable")
def api_resumable_create() -> ResponseReturnValue:
    """tus creation: ``Upload-Length`` (required), ``Upload-Metadata`` (``filename``,
    ``sha256``), the fit options in the body (checked now, before any byte is sent)."""
    try:
        _check_tus_version()
        if "Upload-Defer-Length" in request.headers:
            raise UploadError("Upload-Defer-Length is not supported: declare the size with "
                              "Upload-Length")
        length = _header_int("Upload-Length")
        metadata = parse_metadata(request.headers.get("Upload-Metadata", ""))
        options = _fit_options_from_body() or parse_fit_options(MultiDict())
        upload = _partials().create(length, metadata, options)
    except UploadError as exc:
        return _tus_error(exc)
    body = _resumable_json(upload)
    return body, 201, {**_tus_headers(upload), "Location": body["url"],
                       "Tus-Extension": TUS_EXTENSIONS}


@bp.get("/api/uploads/resumable")
def api_resumable_list() -> ResponseReturnValue:
    return {"uploads": [_resumable_json(u) for u in _partials().list()]}, _tus_headers()


@bp.get("/api/uploads/resumable/<upload_id>")
def api_resumable(upload_id: str) -> ResponseReturnValue:
    """tus ``HEAD`` (Flask answers it from this view without the body): the offset."""
    try:
        upload = _partials().get(upload_id)
    except UploadError as exc:
        return _tus_error(exc)
    return _resumable_json(upload), 200, _tus_headers(upload)


@bp.patch("/api/uploads/resumable/<upload_id>")
def api_resumable_patch(upload_id: str) -> ResponseReturnValue:
    """tus ``PATCH``: the body's bytes at ``Upload-Offset``, streamed to disk."""
    try:
        _check_tus_version()
        if request.mimetype != OFFSET_CONTENT_TYPE:
            raise UploadError(f"a chunk's Content-Type must be {OFFSET_CONTENT_TYPE}, not "
                              f"{request.mimetype or 'none'}", status=415)
        offset = _header_int("Upload-Offset")
        if request.content_length is None:
            raise UploadError("a chunk needs a Content-Length", status=411)
        checksum = request.headers.get("Upload-Checksum")
        upload = _partials().append(upload_id, offset, request.stream, request.content_length,
                                    parse_chunk_checksum(checksum) if checksum else None)
    except UploadError as exc:
        return _tus_error(exc)
    return "", 204, _tus_headers(upload)


@bp.delete("/api/uploads/resumable/<upload_id>")
def api_resumable_delete(upload_id: str) -> ResponseReturnValue:
    """tus termination."""
    try:
        _partials().remove(upload_id)
    except UploadError as exc:
        return _tus_error(exc)
    return "", 204, _tus_headers()


@bp.post("/api/uploads/resumable/<upload_id>/fit")
def api_resumable_fit(upload_id: str) -> ResponseReturnValue:
    """Fit a complete upload: the same job as a one-request upload. Options in the body
    replace those given at creation; a refused scan is deleted, as a one-request one."""
    catalog = state().catalog()
    try:
        options = _fit_options_from_body()
        folder = new_upload_folder(catalog)
        try:
            upload, received = _partials().take(upload_id, folder)
        except UploadError:
            folder.rmdir()
            raise
        job_id, object_id = queue_fit(catalog, received, options or upload.options,
                                      state().limits)
    except UploadError as exc:
        return _tus_error(exc)
    return {"job": job_id, "object": object_id,
            "job_url": url_for("admin.api_job", job_id=job_id)}, 202


@bp.get("/api/jobs")
def api_jobs() -> ResponseReturnValue:
    return {"jobs": [job.public() for job in state().catalog().jobs()]}


@bp.get("/api/jobs/<int:job_id>")
def api_job(job_id: int) -> ResponseReturnValue:
    catalog = state().catalog()
    job = catalog.get_job(job_id)
    if job is None:
        return api_error(f"no job {job_id}", 404)
    if job.state != "done":
        return job.public()
    # a finished fit: what it says its admin should know (the job page shows them)
    return {**job.public(), "notes": [{"label": label, "text": text}
                                      for label, text in catalog.fit_notes(job.object_id)]}


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
