"""What the admin pages and the admin API both do: accept an upload, trash and restore
objects, read fit options from a form. Views only translate these to HTTP."""

from __future__ import annotations

import os
import re
import secrets
import shutil
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

from werkzeug.datastructures import MultiDict

from ...collection.catalog import Catalog, new_object_id, state_dir
from ...collection.jobs import fit_options
from ...collection.uploads import UploadError, UploadLimits, prepare_scan, receive_upload

#: form fields of an upload besides the file: the object's title and the fit options
OPTION_FIELDS = {"grid", "degree", "method", "bits", "max_error", "max_grid", "projection"}
UPLOAD_FIELDS = OPTION_FIELDS | {"title", "csrf_token"}


class ConflictError(ValueError):
    """An action that the object's or job's current state does not allow (HTTP 409)."""


def _int_field(name: str, text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise UploadError(f"{name} must be an integer, got {text!r}") from None


def parse_fit_options(form: MultiDict) -> dict[str, Any]:
    """Fit options from form fields (only those given; the rest keep FitOptions' defaults),
    validated by ``FitOptions.validate``. Returns the full options as stored in the job.

    Raises
    ------
    UploadError
        An unknown field or a bad value, naming it.
    """
    unknown = sorted(set(form) - UPLOAD_FIELDS)
    if unknown:
        raise UploadError(f"unknown form field(s) {', '.join(unknown)}; accepted: scan, "
                          f"{', '.join(sorted(UPLOAD_FIELDS - {'csrf_token'}))}")
    values: dict[str, Any] = {}
    for name in OPTION_FIELDS:
        text = (form.get(name) or "").strip()
        if not text:
            continue
        if name == "grid":
            match = re.fullmatch(r"(\d+)(?:\s*[xX×]\s*(\d+))?", text)
            if match is None:
                raise UploadError(f"grid must be N or NxM such as 40x40, got {text!r}")
            values["grid"] = (int(match[1]), int(match[2] or match[1]))
        elif name in ("degree", "bits", "max_grid"):
            values[name] = _int_field(name, text)
        elif name == "max_error":
            try:
                values[name] = float(text)
            except ValueError:
                raise UploadError(f"max_error must be a number, got {text!r}") from None
        else:
            values[name] = text
    if "max_grid" not in values and "grid" in values:
        values["max_grid"] = max(128, *values["grid"])
    title = (form.get("title") or "").strip()
    if len(title) > Catalog.EDITABLE["title"]:
        raise UploadError(f"title is {len(title)} characters long; at most "
                          f"{Catalog.EDITABLE['title']} are accepted")
    if title:
        values["title"] = title
    try:
        options = fit_options(values)
    except (TypeError, ValueError) as exc:
        raise UploadError(f"fit options: {exc}") from None
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(options).items()}


def accept_upload(catalog: Catalog, environ: dict[str, Any], limits: UploadLimits,
                  csrf_check: Any = None) -> tuple[int, str]:
    """Stream an upload to disk, check it, and queue its fit: ``(job id, object id)``.

    ``csrf_check(form) -> bool``: for the page form, checked once the body is on
    disk. On any refusal the upload's folder is removed and ``UploadError`` raised.
    """
    uploads = state_dir(catalog.collection) / "uploads"
    uploads.mkdir(parents=True, exist_ok=True)
    folder = uploads / f"{time.strftime('%Y%m%d-%H%M%S')}-{secrets.token_hex(4)}"
    folder.mkdir()
    try:
        form, received = receive_upload(environ, folder, limits)
        if csrf_check is not None and not csrf_check(form):
            raise UploadError("the form's CSRF token is missing or wrong; reload the page and "
                              "try again")
        options = parse_fit_options(form)
        prepared = prepare_scan(received, limits)
    except UploadError:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    original = os.path.basename(received.original_name.replace("\\", "/"))[:255]
    title = options.get("title") or Path(original).name.split(".")[0] or "Untitled scan"
    options["title"] = options.get("title") or title
    object_id = new_object_id(title)
    stored = prepared.scan_path.relative_to(state_dir(catalog.collection)).as_posix()
    with catalog.transaction() as conn:
        catalog.add_object(object_id, title, conn=conn)
        upload_id = catalog.add_upload(conn, object_id, original, stored, received.bytes,
                                       received.sha256, prepared.format
                                       + (f"+{prepared.compression}"
                                          if prepared.compression else ""))
        job_id = catalog.add_job(conn, object_id, upload_id, options)
    return job_id, object_id


def _busy_job(catalog: Catalog, object_id: str) -> None:
    for job in catalog.jobs_of(object_id):
        if job.state in ("queued", "running"):
            raise ConflictError(f"object {object_id!r} has job {job.id} {job.state}; cancel "
                                "it first")


def trash_object(catalog: Catalog, object_id: str) -> str:
    """Move the object's bundle to ``.tessera/trash/`` and unpublish it; the trash path."""
    row = catalog.get_object(object_id)
    if row is None:
        raise KeyError(object_id)
    if row["trash_path"]:
        raise ConflictError(f"object {object_id!r} is already in the trash")
    _busy_job(catalog, object_id)
    trash = state_dir(catalog.collection) / "trash"
    target = trash / f"{object_id}.{time.strftime('%Y%m%d-%H%M%S')}.{secrets.token_hex(2)}"
    target.mkdir(parents=True)
    bundle = catalog.collection / object_id
    if bundle.is_dir():
        os.rename(bundle, target / "bundle")
    catalog.set_trash(object_id, target.relative_to(state_dir(catalog.collection)).as_posix())
    return str(target)


def restore_object(catalog: Catalog, object_id: str) -> None:
    """Bring a trashed object's bundle back into the collection (unpublished)."""
    row = catalog.get_object(object_id)
    if row is None:
        raise KeyError(object_id)
    if not row["trash_path"]:
        raise ConflictError(f"object {object_id!r} is not in the trash")
    source = state_dir(catalog.collection) / row["trash_path"]
    destination = catalog.collection / object_id
    if (source / "bundle").is_dir():
        if destination.exists():
            raise ConflictError(f"{destination} exists; move it away before restoring")
        os.rename(source / "bundle", destination)
    shutil.rmtree(source, ignore_errors=True)
    catalog.set_trash(object_id, None)


def object_json(catalog: Catalog, row: dict[str, Any]) -> dict[str, Any]:
    """An object of the catalog with its latest job, as the admin API returns it."""
    jobs = catalog.jobs_of(row["id"])
    return {**{k: row[k] for k in ("id", "title", "description", "provenance", "licence",
                                   "units", "input_sha256", "origin", "created", "updated")},
            "published": bool(row["published"]), "has_bundle": bool(row["bundle_path"]),
            "trashed": bool(row["trash_path"]),
            "job": jobs[0].public() if jobs else None}
