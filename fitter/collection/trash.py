"""Trash and restore: an object's bundle moves to ``.tessera/trash/`` and back.

A trashed object is unpublished and keeps its catalog row, so restoring brings
back the bundle, its metadata and its job history. Neither runs while the
object has a fit queued or running.
"""

from __future__ import annotations

import os
import secrets
import shutil
import time

from .catalog import Catalog, ConflictError, state_dir


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
