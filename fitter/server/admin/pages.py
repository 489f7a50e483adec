"""The admin pages: login, object list, upload form, jobs with live progress, metadata edit,
publish / unpublish, trash and restore. Every change is a POST form with a CSRF token; the
job page polls ``/admin/api/jobs/<id>`` with the session (web/src/admin-job.js)."""

from __future__ import annotations

import time
from typing import Any
from urllib.parse import urlsplit

from flask import (
    abort,
    current_app,
    flash,
    redirect,
    render_template,
    request,
    session,
    url_for,
)
from flask.typing import ResponseReturnValue

from ...collection.catalog import VIEW_FIELDS, ConflictError, FieldError, adopt_bundles
from ...collection.trash import restore_object, trash_object
from ...collection.uploads import UploadError
from ...fitting.options import FORM_GROUPS, form_fields
from .auth import bp, client_address, csrf_ok, csrf_token, logged_in, state
from .service import accept_upload, object_json


def _safe_next(target: str | None) -> str:
    """A redirect target inside the admin area (never another host: no open redirect)."""
    default = url_for("admin.objects")
    if not target:
        return default
    parts = urlsplit(target)
    if parts.scheme or parts.netloc or not parts.path.startswith(url_for("admin.objects")):
        return default
    return target


@bp.route("/login", methods=["GET", "POST"])
def login() -> ResponseReturnValue:
    """The only admin page open without the secret (see ``PUBLIC_ENDPOINTS``)."""
    if request.method == "GET":
        if logged_in():
            return redirect(_safe_next(request.args.get("next")))
        return render_template("admin_login.html", next=request.args.get("next", ""))
    if not csrf_ok(request.form.get("csrf_token")):
        return render_template("admin_login.html", error="The form expired; try again.",
                               next=request.form.get("next", "")), 400
    result = state().check(request.form.get("token", ""), client_address())
    if not result.ok:
        error = "Wrong admin token." if result.status == 401 else (
            f"Too many wrong tokens from this address: try again in {result.retry_after} s."
            if result.status == 429 else
            f"The server is busy checking other logins: try again in {result.retry_after} s.")
        headers = {"Retry-After": str(result.retry_after)} if result.retry_after else {}
        return render_template("admin_login.html", error=error,
                               next=request.form.get("next", "")), result.status, headers
    session.clear()
    session["admin"] = state().fingerprint
    csrf_token()  # a fresh CSRF token for the logged-in session
    return redirect(_safe_next(request.form.get("next")))


@bp.post("/logout")
def logout() -> ResponseReturnValue:
    """End the admin's sessions: the session version in the catalog moves on, so this
    cookie, a copy of it, and every other admin session cookie are void at once."""
    state().end_sessions()
    session.clear()
    return redirect(url_for("admin.login"))


@bp.get("/")
def objects() -> ResponseReturnValue:
    catalog = state().catalog()
    rows = [object_json(catalog, row) for row in catalog.objects()]
    return render_template("admin_objects.html", objects=rows)


@bp.post("/rescan")
def rescan() -> ResponseReturnValue:
    added = adopt_bundles(state().catalog(), publish=False)
    flash(f"{len(added)} new bundle(s) found and added unpublished: {', '.join(added)}"
          if added else "No new bundles in the collection folder.")
    return redirect(url_for("admin.objects"))


def _upload_defaults() -> dict[str, Any]:
    """The upload form's fit option fields by group (``fitter.fitting.options``, the table
    the CLI reads too), the size limit, and the config of its script (web/src/
    admin-upload-page.js: the resumable upload API, the jobs page, the chunk size)."""
    fields = form_fields()
    groups = [(legend, [f for f in fields if f["group"] == group])
              for group, legend in FORM_GROUPS]
    return {"groups": [(legend, members) for legend, members in groups if members],
            "max_bytes": state().limits.max_bytes,
            "script": {"endpoint": url_for("admin.api_resumable_create"),
                       "jobs_page": url_for("admin.jobs"),
                       "chunk_bytes": int(current_app.config["TESSERA_UPLOAD_CHUNK_BYTES"])}}


@bp.route("/upload", methods=["GET", "POST"])
def upload() -> ResponseReturnValue:
    if request.method == "GET":
        return render_template("admin_upload.html", defaults=_upload_defaults())
    try:
        job_id, _ = accept_upload(state().catalog(), request.environ, state().limits,
                                  csrf_check=lambda form: csrf_ok(form.get("csrf_token")))
    except UploadError as exc:
        return render_template("admin_upload.html", defaults=_upload_defaults(),
                               error=str(exc)), exc.status
    return redirect(url_for("admin.job", job_id=job_id))


@bp.get("/jobs")
def jobs() -> ResponseReturnValue:
    return render_template("admin_jobs.html", jobs=[j.public() for j in state().catalog().jobs()])


@bp.get("/jobs/<int:job_id>")
def job(job_id: int) -> ResponseReturnValue:
    catalog = state().catalog()
    found = catalog.get_job(job_id)
    if found is None:
        abort(404, description=f"no job {job_id}")
    config = {"job_url": url_for("admin.api_job", job_id=job_id),
              "object_url": url_for("admin.edit_object", object_id=found.object_id)}
    notes = catalog.fit_notes(found.object_id) if found.state == "done" else []
    return render_template("admin_job.html", job=found.public(), config=config, notes=notes)


@bp.post("/jobs/<int:job_id>/cancel")
def cancel_job(job_id: int) -> ResponseReturnValue:
    if state().catalog().request_cancel(job_id) is None:
        abort(404, description=f"no job {job_id}")
    return redirect(url_for("admin.job", job_id=job_id))


@bp.post("/jobs/<int:job_id>/retry")
def retry_job(job_id: int) -> ResponseReturnValue:
    try:
        if state().catalog().retry_job(job_id) is None:
            abort(404, description=f"no job {job_id}")
    except ConflictError as exc:
        flash(str(exc))
    return redirect(url_for("admin.job", job_id=job_id))


def _object_or_404(object_id: str) -> dict[str, Any]:
    catalog = state().catalog()
    row = catalog.get_object(object_id)
    if row is None:
        abort(404, description=f"no object {object_id!r} in the catalog")
    return object_json(catalog, row)


def _direction_text(vector: list[float] | None) -> str:
    """A direction as the edit form shows it (``"0, 1, 0"``; ``""`` for none), which
    ``fitter.collection.catalog.parse_direction`` reads back."""
    return "" if vector is None else ", ".join(f"{c:.6g}" for c in vector)


def _view_texts(object_id: str) -> dict[str, Any]:
    """The object's first view for the form: ``up``/``front`` as text and their sources."""
    catalog = state().catalog()
    view = catalog.object_view(catalog.get_object(object_id) or {}) or {}
    return {name: _direction_text(view.get(name)) for name in VIEW_FIELDS} | {
        "source": view.get("up_source")}


@bp.route("/objects/<object_id>", methods=["GET", "POST"])
def edit_object(object_id: str) -> ResponseReturnValue:
    obj = _object_or_404(object_id)
    error = None
    if request.method == "POST":
        fields = {k: request.form.get(k, "") for k in ("title", "description", "provenance",
                                                       "licence", "units")}
        shown = _view_texts(object_id)
        # a direction is sent only when the admin changed its text: saving the title does
        # not turn the fit's view into the admin's
        fields |= {name: request.form[name] for name in VIEW_FIELDS
                   if name in request.form and request.form[name].strip() != shown[name]}
        try:
            state().catalog().update_object(object_id, fields)
        except FieldError as exc:
            error = str(exc)
        else:
            flash("Saved.")
            return redirect(url_for("admin.edit_object", object_id=object_id))
    catalog = state().catalog()
    jobs = [j.public() for j in catalog.jobs_of(object_id)]
    viewer_url = url_for("objects.viewer", object_id=object_id) if obj["published"] else None
    return render_template("admin_object.html", obj=obj, jobs=jobs, error=error,
                           viewer_url=viewer_url, view=_view_texts(object_id),
                           notes=catalog.fit_notes(object_id),
                           limits=catalog.EDITABLE), (400 if error else 200)


@bp.post("/objects/<object_id>/publish")
def publish_object(object_id: str) -> ResponseReturnValue:
    return _set_published(object_id, True)


@bp.post("/objects/<object_id>/unpublish")
def unpublish_object(object_id: str) -> ResponseReturnValue:
    return _set_published(object_id, False)


def _set_published(object_id: str, published: bool) -> ResponseReturnValue:
    _object_or_404(object_id)
    try:
        state().catalog().update_object(object_id, {"published": published})
    except ConflictError as exc:
        flash(str(exc))
    return redirect(_safe_next(request.form.get("next")) if request.form.get("next")
                    else url_for("admin.edit_object", object_id=object_id))


def _move(object_id: str, move, done: str, back: str) -> ResponseReturnValue:
    """Trash or restore an object (``move(catalog, id)``), flash the outcome, go ``back``."""
    _object_or_404(object_id)
    try:
        move(state().catalog(), object_id)
        flash(f"{object_id} {done}")
    except ConflictError as exc:
        flash(str(exc))
    return redirect(url_for(back))


@bp.post("/objects/<object_id>/delete")
def delete_object(object_id: str) -> ResponseReturnValue:
    return _move(object_id, trash_object, "moved to the trash (restorable).", "admin.objects")


@bp.post("/objects/<object_id>/restore")
def restore(object_id: str) -> ResponseReturnValue:
    return _move(object_id, restore_object, "restored (unpublished).", "admin.trash")


@bp.get("/trash")
def trash() -> ResponseReturnValue:
    catalog = state().catalog()
    return render_template("admin_trash.html",
                           objects=[object_json(catalog, r) for r in catalog.objects(True)])


@bp.app_template_filter("admin_when")
def _when(timestamp: float | None) -> str:
    return time.strftime("%Y-%m-%d %H:%M", time.localtime(timestamp)) if timestamp else "—"

