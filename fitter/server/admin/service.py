"""What the admin pages and the admin API both do: accept an upload (in one request, or a
finished resumable one), trash and restore objects, read fit options from a form. Views only
translate these to HTTP."""

from __future__ import annotations

import os
import secrets
import shutil
import time
from pathlib import Path
from typing import Any

from werkzeug.datastructures import MultiDict

from ...collection.catalog import Catalog, new_object_id, state_dir
from ...collection.uploads import ReceivedFile, UploadError, UploadLimits, prepare_scan
from ...fitting.options import OptionError, parse_form
from .upload_stream import receive_upload

#: form fields of an upload that are not fit options (fitter.fitting.options.form_fields,
#: which has the object's title, description and units too): the file and the page form's
#: CSRF token
OTHER_FIELDS = ("scan", "csrf_token")


def parse_fit_options(form: MultiDict) -> dict[str, Any]:
    """Fit options from form fields (only those given; the rest keep FitOptions' defaults),
    read and validated by ``fitter.fitting.options.parse_form`` (the title, description and
    units among them). Returns the full options as stored in the job.

    Raises
    ------
    UploadError
        An unknown field or a bad value, naming it.
    """
    try:
        return parse_form(form, OTHER_FIELDS)
    except OptionError as exc:
        raise UploadError(str(exc)) from None


def new_upload_folder(catalog: Catalog) -> Path:
    """A new, empty ``.tessera/uploads/<time>-<random>/`` for one upload."""
    uploads = state_dir(catalog.collection) / "uploads"
    uploads.mkdir(parents=True, exist_ok=True)
    folder = uploads / f"{time.strftime('%Y%m%d-%H%M%S')}-{secrets.token_hex(4)}"
    folder.mkdir()
    return folder


def accept_upload(catalog: Catalog, environ: dict[str, Any], limits: UploadLimits,
                  csrf_check: Any = None) -> tuple[int, str]:
    """Stream an upload to disk, check it, and queue its fit: ``(job id, object id)``.

    ``csrf_check(form) -> bool``: for the page form, checked once the body is on
    disk. On any refusal the upload's folder is removed and ``UploadError`` raised.
    """
    folder = new_upload_folder(catalog)
    try:
        form, received = receive_upload(environ, folder, limits)
        if csrf_check is not None and not csrf_check(form):
            raise UploadError("the form's CSRF token is missing or wrong; reload the page and "
                              "try again")
        options = parse_fit_options(form)
    except UploadError:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    return queue_fit(catalog, received, options, limits)


def queue_fit(catalog: Catalog, received: ReceivedFile, options: dict[str, Any],
              limits: UploadLimits) -> tuple[int, str]:
    """Check a received file (in its own upload folder, :func:`new_upload_folder`) as a scan
    and queue its fit with ``options``: ``(job id, object id)``. The one step after a
    one-request upload and after a resumable one.

    Raises
    ------
    UploadError
        Not a scan, or a bad archive; the upload's folder is removed.
    """
    try:
        prepared = prepare_scan(received, limits)
    except UploadError:
        shutil.rmtree(received.path.parent, ignore_errors=True)
        raise
    original = os.path.basename(received.original_name.replace("\\", "/"))[:255]
    title = options.get("title") or Path(original).name.split(".")[0] or "Untitled scan"
    options["title"] = options.get("title") or title
    object_id = new_object_id(title)
    stored = prepared.scan_path.relative_to(state_dir(catalog.collection)).as_posix()
    with catalog.transaction() as conn:
        catalog.add_object(object_id, title, description=options.get("description") or "",
                           units=options.get("units") or "", conn=conn)
        upload_id = catalog.add_upload(conn, object_id, original, stored, received.bytes,
                                       received.sha256, prepared.format
                                       + (f"+{prepared.compression}"
                                          if prepared.compression else ""))
        job_id = catalog.add_job(conn, object_id, upload_id, options)
    return job_id, object_id


def object_json(catalog: Catalog, row: dict[str, Any], with_view: bool = False) -> dict[str, Any]:
    """An object of the catalog with its latest job, as the admin API returns it; with
    ``with_view``, its first ``view`` too (the admin's or its bundle's, ``Catalog.object_view``:
    one manifest read, so not for lists)."""
    jobs = catalog.jobs_of(row["id"])
    return {**{k: row[k] for k in ("id", "title", "description", "provenance", "licence",
                                   "units", "input_sha256", "origin", "created", "updated")},
            "published": bool(row["published"]), "has_bundle": bool(row["bundle_path"]),
            "trashed": bool(row["trash_path"]),
            "job": jobs[0].public() if jobs else None,
            **({"view": catalog.object_view(row)} if with_view else {})}
