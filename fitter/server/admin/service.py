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
from ...collection.uploads import UploadError, UploadLimits, prepare_scan
from .upload_stream import receive_upload

#: form fields of an upload besides the file: the object's title and the fit options
OPTION_FIELDS = {"grid", "degree", "method", "bits", "max_error", "max_grid", "projection"}
UPLOAD_FIELDS = OPTION_FIELDS | {"title", "csrf_token"}


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


def object_json(catalog: Catalog, row: dict[str, Any]) -> dict[str, Any]:
    """An object of the catalog with its latest job, as the admin API returns it."""
    jobs = catalog.jobs_of(row["id"])
    return {**{k: row[k] for k in ("id", "title", "description", "provenance", "licence",
                                   "units", "input_sha256", "origin", "created", "updated")},
            "published": bool(row["published"]), "has_bundle": bool(row["bundle_path"]),
            "trashed": bool(row["trash_path"]),
            "job": jobs[0].public() if jobs else None}
