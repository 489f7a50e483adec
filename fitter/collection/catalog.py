"""The catalog of a managed collection: objects, uploads and fit jobs in SQLite.

A collection directory becomes *managed* when the admin area first runs on it:
``<collection>/.tessera/catalog.sqlite`` is created next to the bundles (the
leading dot keeps it out of the object ids, see
:data:`fitter.collection.bundles.ID_PATTERN`), with the uploads, the staging
area of running fits and the trash beside it::

    <collection>/
        <object-id>/            bundles, as `tessera fit` writes them
        .tessera/catalog.sqlite objects, uploads, jobs, settings (this module)
        .tessera/uploads/<n>/   every accepted upload, kept (never deleted by a fit)
        .tessera/staging/job-<n>/  a running fit's output before its atomic rename
        .tessera/trash/<id>.<time>/  deleted bundles, restorable

The database runs in WAL mode (readers never wait for the job workers'
progress writes) and its schema is versioned with SQLite's ``user_version``:
:data:`MIGRATIONS` is an append-only list, and opening a catalog applies the
ones it has not seen, each in one transaction. A catalog written by a newer
Tessera (a higher version than this code knows) is refused, never modified.

Every process and thread opens its own :class:`Catalog` (a ``sqlite3``
connection is not shared across threads); writes are short ``BEGIN
IMMEDIATE`` transactions with a busy timeout, so the web process and the
worker processes can write concurrently.
"""

from __future__ import annotations

import json
import math
import os
import re
import secrets
import sqlite3
import threading
import time
import unicodedata
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from client_py.bundle import fit_notes
from client_py.errors import TesseraError

from ..fitting.options import OPTION, UP_AXES
from .bundles import Bundle, BundleError, Collection

STATE_DIR = ".tessera"
CATALOG_FILE = "catalog.sqlite"
JOB_STATES = ("queued", "running", "done", "failed", "interrupted", "cancelled")
#: jobs ``retry`` may re-queue
RETRYABLE = ("failed", "interrupted", "cancelled")

#: Append-only: entry ``k`` upgrades a catalog from version ``k`` to ``k + 1``.
MIGRATIONS: list[list[str]] = [
    [  # 1: the first schema
        """CREATE TABLE settings (key TEXT PRIMARY KEY, value TEXT NOT NULL)""",
        """CREATE TABLE objects (
            id TEXT PRIMARY KEY,
            title TEXT NOT NULL,
            description TEXT NOT NULL DEFAULT '',
            provenance TEXT NOT NULL DEFAULT '',
            licence TEXT NOT NULL DEFAULT '',
            units TEXT NOT NULL DEFAULT '',
            published INTEGER NOT NULL DEFAULT 0 CHECK (published IN (0, 1)),
            bundle_path TEXT,
            input_sha256 TEXT,
            origin TEXT NOT NULL DEFAULT 'upload',
            created REAL NOT NULL,
            updated REAL NOT NULL,
            trash_path TEXT
        )""",
        """CREATE TABLE uploads (
            id INTEGER PRIMARY KEY AUTOINCREMENT,
            object_id TEXT NOT NULL REFERENCES objects(id),
            original_name TEXT NOT NULL,
            stored_path TEXT NOT NULL,
            bytes INTEGER NOT NULL,
            sha256 TEXT NOT NULL,
            format TEXT NOT NULL,
            created REAL NOT NULL
        )""",
        """CREATE TABLE jobs (
            id INTEGER PRIMARY KEY AUTOINCREMENT,
            object_id TEXT NOT NULL REFERENCES objects(id),
            upload_id INTEGER NOT NULL REFERENCES uploads(id),
            state TEXT NOT NULL CHECK (state IN ('queued', 'running', 'done', 'failed',
                                                 'interrupted', 'cancelled')),
            stage TEXT NOT NULL DEFAULT '',
            progress REAL NOT NULL DEFAULT 0,
            error TEXT,
            options TEXT NOT NULL,
            attempts INTEGER NOT NULL DEFAULT 0,
            cancel_requested INTEGER NOT NULL DEFAULT 0,
            worker_pid INTEGER,
            created REAL NOT NULL,
            started REAL,
            finished REAL
        )""",
    ],
    [  # 2: the job runner looks up queued jobs and an object's jobs
        """CREATE INDEX jobs_state ON jobs (state, id)""",
        """CREATE INDEX jobs_object ON jobs (object_id)""",
    ],
    [  # 3: the admin's up and front (JSON {"up": [x, y, z], "front": [x, y, z]}; '': the fit's)
        """ALTER TABLE objects ADD COLUMN view TEXT NOT NULL DEFAULT ''""",
    ],
]
SCHEMA_VERSION = len(MIGRATIONS)


class CatalogError(TesseraError, RuntimeError):
    """A catalog this code cannot use (newer schema, not a Tessera catalog)."""


class FieldError(TesseraError, ValueError):
    """An object field that cannot take the value given (unknown, not text, too long, a
    direction that is not three finite numbers, a front parallel to up)."""


#: the directions of an object's first view an admin may set (the manifest's ``view``)
VIEW_FIELDS = ("up", "front")
#: the least angle between front and up accepted (a smaller one leaves no front to show)
MIN_FRONT_ANGLE_DEG = 1.0


def parse_direction(value: Any, name: str) -> tuple[float, float, float]:
    """A direction as the admin gives it: three finite numbers ``[x, y, z]`` (JSON), or text
    ``"x, y, z"`` / ``"x y z"``, or an axis ``+x`` ... ``-z``; not normalised.

    Raises
    ------
    FieldError
        Naming ``name``, the value and what is accepted.
    """
    accepted = "three finite numbers [x, y, z] (or text 'x, y, z', or an axis +x ... -z)"
    if isinstance(value, str):
        text = value.strip().lower()
        if text in UP_AXES[1:]:
            axis = [0.0, 0.0, 0.0]
            axis["xyz".index(text[1])] = 1.0 if text[0] == "+" else -1.0
            return tuple(axis)
        parts = text.replace(",", " ").split()
        try:
            value = [float(p) for p in parts]
        except ValueError:
            raise FieldError(f"{name} must be {accepted}, got {text[:80]!r}") from None
    if (not isinstance(value, list | tuple) or len(value) != 3
            or not all(isinstance(c, int | float) and not isinstance(c, bool)
                       and math.isfinite(c) for c in value)):
        raise FieldError(f"{name} must be {accepted}, got {value!r:.80}")
    return tuple(float(c) for c in value)


def admin_view(row: Mapping[str, Any]) -> dict[str, Any]:
    """The manifest ``view`` of the admin's directions stored in the row's ``view`` column."""
    return {**json.loads(row["view"]), "up_source": "admin", "front_source": "admin"}


def orthonormal_view(up: tuple[float, float, float],
                     front: tuple[float, float, float]) -> dict[str, list[float]]:
    """``{"up", "front"}`` as unit vectors, ``front`` made perpendicular to ``up`` (its part
    along ``up`` removed, Gram-Schmidt): ``u = up / |up|``, ``f = (front - (front.u) u) /
    |front - (front.u) u|``; rounded to 6 decimals like ``fitter.fitting.orient.View``.

    Raises
    ------
    FieldError
        ``up`` or ``front`` of length zero, or ``front`` within
        :data:`MIN_FRONT_ANGLE_DEG` of ``up`` (naming the field).
    """
    length = math.hypot(*up)
    if not length > 0:
        raise FieldError(f"up must not be zero, got {list(up)}")
    if not math.hypot(*front) > 0:
        raise FieldError(f"front must not be zero, got {list(front)}")
    u = [c / length for c in up]
    along = sum(f * c for f, c in zip(front, u, strict=True))
    rest = [f - along * c for f, c in zip(front, u, strict=True)]
    if math.hypot(*rest) <= math.sin(math.radians(MIN_FRONT_ANGLE_DEG)) * math.hypot(*front):
        raise FieldError(f"front must not be parallel to up (at least {MIN_FRONT_ANGLE_DEG:g} "
                         f"degree apart), got front {list(front)} and up {list(up)}")
    norm = math.hypot(*rest)
    return {"up": [round(c, 6) for c in u], "front": [round(c / norm, 6) for c in rest]}


class ConflictError(TesseraError):
    """An action that the object's or job's current state does not allow (HTTP 409)."""


def state_dir(collection: str | os.PathLike) -> Path:
    """``<collection>/.tessera``: the catalog, uploads, staging and trash."""
    return Path(collection).resolve() / STATE_DIR


def catalog_path(collection: str | os.PathLike) -> Path:
    return state_dir(collection) / CATALOG_FILE


def catalog_exists(collection: str | os.PathLike) -> bool:
    """Whether ``collection`` is managed (has a catalog)."""
    return catalog_path(collection).is_file()


def slugify(text: str, limit: int = 40) -> str:
    """Lower-case ASCII letters, digits and ``-`` from ``text`` (``"object"`` when none)."""
    ascii_text = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode()
    slug = re.sub(r"[^a-z0-9]+", "-", ascii_text.lower()).strip("-")[:limit].strip("-")
    return slug or "object"


def new_object_id(title: str) -> str:
    """A fresh id: the title's slug and 6 random hex digits (always a valid object id)."""
    return f"{slugify(title)}-{secrets.token_hex(3)}"


@dataclass(frozen=True)
class Job:
    """One row of ``jobs`` (see :data:`JOB_STATES`)."""

    id: int
    object_id: str
    upload_id: int
    state: str
    stage: str
    progress: float
    error: str | None
    options: dict[str, Any]
    attempts: int
    cancel_requested: bool
    worker_pid: int | None
    created: float
    started: float | None
    finished: float | None

    def public(self) -> dict[str, Any]:
        """The JSON the admin API returns for a job."""
        return {"id": self.id, "state": self.state, "stage": self.stage,
                "progress": round(self.progress, 4), "error": self.error,
                "object": self.object_id, "upload": self.upload_id, "options": self.options,
                "attempts": self.attempts, "created": self.created, "started": self.started,
                "finished": self.finished}


def _job(row: sqlite3.Row) -> Job:
    return Job(id=row["id"], object_id=row["object_id"], upload_id=row["upload_id"],
               state=row["state"], stage=row["stage"], progress=row["progress"],
               error=row["error"], options=json.loads(row["options"]),
               attempts=row["attempts"], cancel_requested=bool(row["cancel_requested"]),
               worker_pid=row["worker_pid"], created=row["created"], started=row["started"],
               finished=row["finished"])


class Catalog:
    """A connection to ``<collection>/.tessera/catalog.sqlite``.

    Parameters
    ----------
    collection : path
        The collection directory.
    create : bool
        Create the catalog (and ``.tessera/``) when missing; otherwise a missing
        catalog is a ``FileNotFoundError``.

    Raises
    ------
    CatalogError
        The file's schema version is newer than :data:`SCHEMA_VERSION`, or it is
        not an SQLite database.
    """

    def __init__(self, collection: str | os.PathLike, create: bool = False) -> None:
        self.collection = Path(collection).resolve()
        self.dir = state_dir(self.collection)
        self.path = self.dir / CATALOG_FILE
        self.created = not self.path.is_file()
        if self.created:
            if not create:
                raise FileNotFoundError(f"{self.path}: no catalog (the collection is not "
                                        "managed; start the admin area to create one)")
            self.dir.mkdir(mode=0o700, parents=True, exist_ok=True)
        # autocommit mode: transactions are explicit (BEGIN IMMEDIATE below)
        self.conn = sqlite3.connect(self.path, timeout=30.0, isolation_level=None,
                                    check_same_thread=False)
        self.conn.row_factory = sqlite3.Row
        try:
            self.conn.execute("PRAGMA journal_mode=WAL")
            self.conn.execute("PRAGMA synchronous=NORMAL")
            self.conn.execute("PRAGMA foreign_keys=ON")
            self.migrate()
        except sqlite3.DatabaseError as exc:
            self.conn.close()
            raise CatalogError(f"{self.path}: not a usable catalog: {exc}") from None

    def close(self) -> None:
        self.conn.close()

    def __enter__(self) -> Catalog:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # ------------------------------------------------------------------ schema
    @property
    def version(self) -> int:
        return int(self.conn.execute("PRAGMA user_version").fetchone()[0])

    def migrate(self) -> None:
        """Apply the migrations this catalog has not seen, each in its own transaction."""
        version = self.version
        if version > SCHEMA_VERSION:
            raise CatalogError(f"{self.path}: schema version {version} is newer than this "
                               f"Tessera's {SCHEMA_VERSION}; upgrade Tessera to open it")
        for index in range(version, SCHEMA_VERSION):
            with self.transaction():
                if self.version != index:  # another process migrated meanwhile
                    continue
                for statement in MIGRATIONS[index]:
                    self.conn.execute(statement)
                self.conn.execute(f"PRAGMA user_version = {index + 1}")

    @contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        """``BEGIN IMMEDIATE`` ... ``COMMIT`` (``ROLLBACK`` on an exception)."""
        self.conn.execute("BEGIN IMMEDIATE")
        try:
            yield self.conn
        except BaseException:
            self.conn.execute("ROLLBACK")
            raise
        self.conn.execute("COMMIT")

    # ---------------------------------------------------------------- settings
    def get_setting(self, key: str) -> str | None:
        row = self.conn.execute("SELECT value FROM settings WHERE key = ?", (key,)).fetchone()
        return None if row is None else row[0]

    def set_setting(self, key: str, value: str) -> None:
        with self.transaction() as conn:
            conn.execute("INSERT INTO settings (key, value) VALUES (?, ?) "
                         "ON CONFLICT (key) DO UPDATE SET value = excluded.value", (key, value))

    def get_settings(self, *keys: str) -> dict[str, str]:
        """``{key: value}`` of those ``keys`` that are set, in one read (what a web process
        re-reads on each admin request to see a new token or a logout at once)."""
        marks = ",".join("?" * len(keys))
        rows = self.conn.execute(f"SELECT key, value FROM settings WHERE key IN ({marks})",
                                 keys).fetchall()
        return {row[0]: row[1] for row in rows}

    def increment_setting(self, key: str) -> int:
        """Add one to the integer setting ``key`` (absent: 0) atomically; return the new value."""
        with self.transaction() as conn:
            conn.execute("INSERT INTO settings (key, value) VALUES (?, '1') ON CONFLICT (key) "
                         "DO UPDATE SET value = CAST(value AS INTEGER) + 1", (key,))
            return int(conn.execute("SELECT value FROM settings WHERE key = ?",
                                    (key,)).fetchone()[0])

    def secret_key(self) -> str:
        """The session-signing key of this collection, made once at random."""
        key = self.get_setting("secret_key")
        if key is None:
            with self.transaction() as conn:
                conn.execute("INSERT OR IGNORE INTO settings (key, value) VALUES (?, ?)",
                             ("secret_key", secrets.token_hex(32)))
            key = self.get_setting("secret_key")
        return str(key)

    # ----------------------------------------------------------------- objects
    def add_object(self, object_id: str, title: str, *, published: bool = False,
                   bundle_path: str | None = None, units: str = "", description: str = "",
                   input_sha256: str | None = None, origin: str = "upload",
                   conn: sqlite3.Connection | None = None) -> None:
        now = time.time()
        (conn or self.conn).execute(
            "INSERT INTO objects (id, title, description, published, bundle_path, units, "
            "input_sha256, origin, created, updated) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
            (object_id, title, description, int(published), bundle_path, units, input_sha256,
             origin, now, now))

    def get_object(self, object_id: str) -> dict[str, Any] | None:
        row = self.conn.execute("SELECT * FROM objects WHERE id = ?", (object_id,)).fetchone()
        return None if row is None else dict(row)

    def objects(self, trashed: bool = False) -> list[dict[str, Any]]:
        """Every object (the trashed ones instead with ``trashed``), newest first."""
        where = "trash_path IS NOT NULL" if trashed else "trash_path IS NULL"
        rows = self.conn.execute(f"SELECT * FROM objects WHERE {where} "
                                 "ORDER BY created DESC, id").fetchall()
        return [dict(r) for r in rows]

    def published(self) -> dict[str, dict[str, Any]]:
        """``{id: row}`` of the objects the public site shows (published, fitted, not trashed)."""
        rows = self.conn.execute("SELECT * FROM objects WHERE published = 1 AND trash_path IS "
                                 "NULL AND bundle_path IS NOT NULL").fetchall()
        return {r["id"]: dict(r) for r in rows}

    #: the metadata an admin may edit, with the longest text accepted (title, description
    #: and units: the fit options' own limits, ``fitter.fitting.options.OPTIONS``)
    EDITABLE = {"title": OPTION["title"].maximum,
                "description": OPTION["description"].maximum, "provenance": 2_000,
                "licence": 500, "units": OPTION["units"].maximum}

    def update_object(self, object_id: str, fields: Mapping[str, Any]) -> None:
        """Set editable metadata (:data:`EDITABLE`), the first view's ``up`` and ``front``
        (:data:`VIEW_FIELDS`) and/or ``published`` from ``fields``.

        ``fields`` is a mapping (not keyword arguments: any key, ``object_id`` or ``self``
        included, is a field name to check, never a parameter of this method). ``up`` and
        ``front`` are read by :func:`parse_direction`; one given alone is paired with the
        other of the object's current view (:meth:`object_view`); the pair is stored made
        orthonormal (:func:`orthonormal_view`: ``front`` loses its part along ``up``). An
        empty or null ``up`` or ``front`` removes the admin's view: the fit's is shown again.

        Raises
        ------
        FieldError
            Unknown fields (all of them named), a value that is not text, text too long, an
            empty title, a ``published`` that is not a boolean, a direction that is not
            three finite numbers, zero, or a ``front`` parallel to ``up``; one direction
            given for an object whose bundle has no view to pair it with.
        ConflictError
            Publishing an object that has no bundle yet (or is in the trash).
        KeyError
            No such object.
        """
        unknown = [str(name) for name in fields if name not in self.EDITABLE
                   and name not in VIEW_FIELDS and name != "published"]
        if unknown:
            raise FieldError(f"not editable: {', '.join(repr(n[:80]) for n in unknown[:20])}; "
                             f"editable fields: {', '.join(self.EDITABLE)}, "
                             f"{', '.join(VIEW_FIELDS)}, published")
        updates: dict[str, Any] = {}
        directions = {name: fields[name] for name in VIEW_FIELDS if name in fields}
        for name, value in fields.items():
            if name in VIEW_FIELDS:
                continue
            if name == "published":
                if not isinstance(value, bool):
                    raise FieldError(f"published must be true or false, got {value!r:.80}")
                updates[name] = int(value)
                continue
            if not isinstance(value, str):
                raise FieldError(f"{name} must be text, got {type(value).__name__}")
            value = value.strip()
            if len(value) > self.EDITABLE[name]:
                raise FieldError(f"{name} is {len(value)} characters long; at most "
                                 f"{self.EDITABLE[name]} are accepted")
            if name == "title" and not value:
                raise FieldError("title must not be empty")
            if name in ("title", "units") and any(ord(c) < 32 for c in value):
                raise FieldError(f"{name} must be one line of text, got {value[:80]!r}")
            updates[name] = value
        if directions:
            updates["view"] = self._edited_view(object_id, directions)
        with self.transaction() as conn:
            row = conn.execute("SELECT bundle_path, trash_path FROM objects WHERE id = ?",
                               (object_id,)).fetchone()
            if row is None:
                raise KeyError(object_id)
            if updates.get("published") and (row["bundle_path"] is None or row["trash_path"]):
                raise ConflictError(f"object {object_id!r} has no bundle to publish yet "
                                 "(its fit has not finished, or it is in the trash)")
            if updates:
                sets = ", ".join(f"{k} = ?" for k in updates)
                conn.execute(f"UPDATE objects SET {sets}, updated = ? WHERE id = ?",
                             (*updates.values(), time.time(), object_id))

    def _edited_view(self, object_id: str, directions: Mapping[str, Any]) -> str:
        """The ``view`` column for the directions given (see :meth:`update_object`)."""
        if any(value is None or (isinstance(value, str) and not value.strip())
               for value in directions.values()):
            return ""
        given = {name: parse_direction(value, name) for name, value in directions.items()}
        row = self.get_object(object_id)
        if row is None:
            raise KeyError(object_id)
        current = self.object_view(row) or {}
        missing = [name for name in VIEW_FIELDS if name not in given and name not in current]
        if missing:
            raise FieldError(f"{missing[0]} must be given too: object {object_id!r} has no "
                             "view of its own yet (its fit has not finished, or its bundle "
                             "predates views)")
        pair = {name: given.get(name) or tuple(current[name]) for name in VIEW_FIELDS}
        return json.dumps(orthonormal_view(pair["up"], pair["front"]))

    def object_view(self, row: Mapping[str, Any]) -> dict[str, Any] | None:
        """The first view of the object ``row`` (a row of :meth:`get_object`): the admin's
        (``up``, ``front``, with ``up_source`` and ``front_source`` ``"admin"``), else its
        bundle manifest's ``view``, else None (no bundle, or one without a view)."""
        if row.get("view"):
            return admin_view(row)
        view = (self.object_manifest(row) or {}).get("view")
        return view if isinstance(view, dict) else None

    def object_manifest(self, row: Mapping[str, Any]) -> dict[str, Any] | None:
        """The bundle manifest of the object ``row`` (a row of :meth:`get_object`), None
        when it has no bundle or its bundle cannot be read."""
        if not row.get("bundle_path"):
            return None
        try:
            return Collection(self.collection).get(row["bundle_path"]).manifest
        except (KeyError, BundleError):
            return None

    def fit_notes(self, object_id: str) -> list[tuple[str, str]]:
        """What the fit of the object's current bundle says its admin should know
        (``client_py.bundle.fit_notes``: reader warnings, why no atlas was made, options an
        atlas did not use, a capped depth); none without a readable bundle."""
        return fit_notes(self.object_manifest(self.get_object(object_id) or {}) or {})

    def set_trash(self, object_id: str, trash_path: str | None) -> None:
        """Mark an object trashed (unpublishing it) or, with None, restored."""
        with self.transaction() as conn:
            conn.execute("UPDATE objects SET trash_path = ?, published = CASE WHEN ? IS NULL "
                         "THEN published ELSE 0 END, updated = ? WHERE id = ?",
                         (trash_path, trash_path, time.time(), object_id))

    def set_bundle(self, object_id: str, bundle_path: str, units: str,
                   input_sha256: str | None) -> None:
        with self.transaction() as conn:
            conn.execute("UPDATE objects SET bundle_path = ?, units = CASE WHEN units = '' "
                         "THEN ? ELSE units END, input_sha256 = ?, updated = ? WHERE id = ?",
                         (bundle_path, units, input_sha256, time.time(), object_id))

    # ----------------------------------------------------------------- uploads
    def add_upload(self, conn: sqlite3.Connection, object_id: str, original_name: str,
                   stored_path: str, nbytes: int, sha256: str, fmt: str) -> int:
        cur = conn.execute(
            "INSERT INTO uploads (object_id, original_name, stored_path, bytes, sha256, format, "
            "created) VALUES (?, ?, ?, ?, ?, ?, ?)",
            (object_id, original_name, stored_path, nbytes, sha256, fmt, time.time()))
        return int(cur.lastrowid)

    def get_upload(self, upload_id: int) -> dict[str, Any] | None:
        row = self.conn.execute("SELECT * FROM uploads WHERE id = ?", (upload_id,)).fetchone()
        return None if row is None else dict(row)

    # -------------------------------------------------------------------- jobs
    def add_job(self, conn: sqlite3.Connection, object_id: str, upload_id: int,
                options: dict[str, Any]) -> int:
        cur = conn.execute(
            "INSERT INTO jobs (object_id, upload_id, state, options, created) "
            "VALUES (?, ?, 'queued', ?, ?)",
            (object_id, upload_id, json.dumps(options, sort_keys=True), time.time()))
        return int(cur.lastrowid)

    def get_job(self, job_id: int) -> Job | None:
        row = self.conn.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return None if row is None else _job(row)

    def jobs(self, limit: int = 200) -> list[Job]:
        rows = self.conn.execute("SELECT * FROM jobs ORDER BY id DESC LIMIT ?",
                                 (limit,)).fetchall()
        return [_job(r) for r in rows]

    def jobs_of(self, object_id: str) -> list[Job]:
        rows = self.conn.execute("SELECT * FROM jobs WHERE object_id = ? ORDER BY id DESC",
                                 (object_id,)).fetchall()
        return [_job(r) for r in rows]

    def claim_next_job(self, worker_pid: int | None = None) -> Job | None:
        """Atomically move the oldest queued job to ``running`` and return it (None if none)."""
        with self.transaction() as conn:
            row = conn.execute("SELECT id FROM jobs WHERE state = 'queued' AND "
                               "cancel_requested = 0 ORDER BY id LIMIT 1").fetchone()
            if row is None:
                return None
            conn.execute("UPDATE jobs SET state = 'running', stage = 'starting', progress = 0, "
                         "error = NULL, started = ?, finished = NULL, worker_pid = ?, "
                         "attempts = attempts + 1 WHERE id = ?",
                         (time.time(), worker_pid, row["id"]))
        return self.get_job(row["id"])

    def set_worker(self, job_id: int, pid: int) -> None:
        with self.transaction() as conn:
            conn.execute("UPDATE jobs SET worker_pid = ? WHERE id = ?", (pid, job_id))

    def report_progress(self, job_id: int, stage: str, progress: float) -> None:
        with self.transaction() as conn:
            conn.execute("UPDATE jobs SET stage = ?, progress = ? WHERE id = ? AND "
                         "state = 'running'", (stage, min(max(progress, 0.0), 1.0), job_id))

    def finish_job(self, job_id: int, state: str, error: str | None = None,
                   only_if: tuple[str, ...] = ("running",)) -> bool:
        """Move a job to a final ``state`` when it is in one of ``only_if``; True if it moved."""
        if state not in JOB_STATES:
            raise ValueError(f"state must be one of {', '.join(JOB_STATES)}, got {state!r}")
        marks = ",".join("?" * len(only_if))
        progress = "1.0" if state == "done" else "progress"
        with self.transaction() as conn:
            cur = conn.execute(
                f"UPDATE jobs SET state = ?, error = ?, finished = ?, worker_pid = NULL, "
                f"progress = {progress}, stage = CASE WHEN ? = 'done' THEN 'done' ELSE stage END "
                f"WHERE id = ? AND state IN ({marks})",
                (state, error, time.time(), state, job_id, *only_if))
            return cur.rowcount == 1

    def request_cancel(self, job_id: int) -> Job | None:
        """Cancel a queued job at once; flag a running one for its runner to stop."""
        with self.transaction() as conn:
            conn.execute("UPDATE jobs SET state = 'cancelled', finished = ?, "
                         "error = 'cancelled before it started' "
                         "WHERE id = ? AND state = 'queued'", (time.time(), job_id))
            conn.execute("UPDATE jobs SET cancel_requested = 1 WHERE id = ? AND "
                         "state = 'running'", (job_id,))
        return self.get_job(job_id)

    def retry_job(self, job_id: int) -> Job | None:
        """Re-queue a ``failed``, ``interrupted`` or ``cancelled`` job (same id, same upload).

        Raises
        ------
        ConflictError
            When the job is in another state.
        """
        with self.transaction() as conn:
            row = conn.execute("SELECT state FROM jobs WHERE id = ?", (job_id,)).fetchone()
            if row is None:
                return None
            if row["state"] not in RETRYABLE:
                raise ConflictError(f"job {job_id} is {row['state']}; only "
                                 f"{', '.join(RETRYABLE)} jobs can be retried")
            conn.execute("UPDATE jobs SET state = 'queued', stage = '', progress = 0, "
                         "error = NULL, cancel_requested = 0, finished = NULL, started = NULL, "
                         "worker_pid = NULL WHERE id = ?", (job_id,))
        return self.get_job(job_id)

    def running_jobs(self) -> list[Job]:
        rows = self.conn.execute("SELECT * FROM jobs WHERE state = 'running'").fetchall()
        return [_job(r) for r in rows]

    def interrupt_running(self, reason: str) -> list[int]:
        """Mark every ``running`` job ``interrupted`` (a runner starting after a crash)."""
        with self.transaction() as conn:
            ids = [r[0] for r in conn.execute("SELECT id FROM jobs WHERE state = 'running'")]
            conn.execute("UPDATE jobs SET state = 'interrupted', error = ?, finished = ?, "
                         "worker_pid = NULL WHERE state = 'running'", (reason, time.time()))
        return ids


def adopt_bundles(catalog: Catalog, publish: bool) -> list[str]:
    """Add the collection's bundle directories the catalog does not know as objects.

    Bundles written by hand (``tessera fit``) or by ``tessera fit-collection``
    join the catalog this way; ``publish`` says whether they are public at once
    (the rule, documented in docs/admin.md: True only when the catalog is first
    created, so that managing an already public collection hides nothing).
    Returns the ids added.
    """
    known = {r[0] for r in catalog.conn.execute("SELECT id FROM objects")}
    collection = Collection(catalog.collection)
    if collection.root == catalog.collection and (collection.root / "manifest.json").is_file():
        return []  # a single bundle served as its own collection: nothing to manage
    added = []
    for bundle in collection.bundles():
        if bundle.id in known:
            continue
        provenance = bundle.manifest.get("provenance", {})
        with catalog.transaction() as conn:
            catalog.add_object(bundle.id, bundle.title, published=publish,
                               bundle_path=bundle.id, units=str(bundle.manifest.get("units", "")),
                               description=str(bundle.manifest.get("description") or ""),
                               input_sha256=provenance.get("sha256"), origin="adopted",
                               conn=conn)
        added.append(bundle.id)
    return added


class ThreadCatalogs:
    """One :class:`Catalog` per thread for a web process (``sqlite3`` connections are not
    meant to be shared between threads)."""

    def __init__(self, collection: str | os.PathLike) -> None:
        self.collection = Path(collection).resolve()
        self._local = threading.local()

    def get(self) -> Catalog:
        catalog = getattr(self._local, "catalog", None)
        if catalog is None:
            catalog = self._local.catalog = Catalog(self.collection)
        return catalog


@dataclass(frozen=True)
class CatalogBundle(Bundle):
    """A bundle of a managed collection with the catalog's metadata laid over its manifest
    (:meth:`PublishedCollection.overlay`): the manifest a visitor is served (``manifest``)
    differs from ``manifest.json`` on disk in the fields the admin edits, so the server
    sends this one (``fitter.server.bundles``)."""


class PublishedCollection(Collection):
    """A managed collection as the public sees it: published objects only, with the
    catalog's title, description, units and view (the admin's edits after the fit)."""

    def __init__(self, root: Path, catalogs: ThreadCatalogs) -> None:
        super().__init__(root)
        self.catalogs = catalogs

    def _overlay(self, bundle: Bundle, row: dict[str, Any]) -> Bundle:
        """``bundle`` with the catalog row's ``title``, ``description``, ``units`` (when
        set: ``""`` keeps the manifest's) and ``view`` (the admin's, when set: both ``up``
        and ``front``, sources ``"admin"``)."""
        manifest = dict(bundle.manifest)
        manifest["title"] = row["title"]
        manifest["description"] = row.get("description") or ""
        if row.get("units"):
            manifest["units"] = row["units"]
        if row.get("view"):
            manifest["view"] = admin_view(row)
        return CatalogBundle(bundle.id, bundle.path, manifest)

    def bundles(self) -> list[Bundle]:
        published = self.catalogs.get().published()
        return [self._overlay(b, published[b.id]) for b in super().bundles()
                if b.id in published]

    def get(self, object_id: str) -> Bundle:
        row = self.catalogs.get().get_object(object_id)
        if row is None or not row["published"] or row["trash_path"] or not row["bundle_path"]:
            raise KeyError(object_id)
        return self._overlay(super().get(object_id), row)
