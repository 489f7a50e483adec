"""A collection: a directory of bundle directories, each read through its ``manifest.json``.

An object's id is its bundle directory's name; only names made of letters,
digits, ``.``, ``_`` and ``-`` (not starting with ``.``) are ids, so an id can
never name a path outside the collection. A directory that is itself a bundle
(it holds ``manifest.json``) is served as a collection of that one object.
Manifests are re-read when their modification time changes, so bundles can be
added to a running server.
"""

from __future__ import annotations

import json
import logging
import re
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from client_py.errors import TesseraError

log = logging.getLogger(__name__)

ID_PATTERN = re.compile(r"^[A-Za-z0-9_-][A-Za-z0-9._-]{0,127}$")
MANIFEST = "manifest.json"


class BundleError(TesseraError, ValueError):
    """A bundle directory whose manifest is missing or not a Tessera bundle manifest."""


@dataclass(frozen=True)
class Bundle:
    """One object of the collection.

    Attributes
    ----------
    id : str
        The bundle directory's name.
    path : Path
        The bundle directory.
    manifest : dict
        The parsed ``manifest.json``.
    """

    id: str
    path: Path
    manifest: dict[str, Any]

    @property
    def title(self) -> str:
        return str(self.manifest.get("title") or self.id)

    @property
    def base_file(self) -> str:
        """Name of the base patch inside the bundle (``manifest['base']['file']``)."""
        return str(self.manifest.get("base", {}).get("file", "base.tsp"))

    def file_sizes(self) -> dict[str, int]:
        """Byte size of every regular file of the bundle, by name relative to it."""
        sizes = {}
        for item in sorted(self.path.rglob("*")):
            if item.is_file() and not item.name.startswith("."):
                sizes[item.relative_to(self.path).as_posix()] = item.stat().st_size
        return sizes


def parse_manifest(path: Path) -> dict[str, Any]:
    """The manifest at ``path``, checked to be a ``tessera-bundle`` manifest of version 1.

    Raises
    ------
    BundleError
        Naming the file and what is wrong with it.
    """
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise BundleError(f"{path}: no manifest.json (not a Tessera bundle)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BundleError(f"{path}: unreadable manifest: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != "tessera-bundle":
        raise BundleError(f"{path}: 'format' must be 'tessera-bundle'")
    if data.get("format_version") != 1:
        raise BundleError(f"{path}: format_version {data.get('format_version')!r}; "
                          "this server reads version 1")
    base = data.get("base", {})
    if not isinstance(base, dict) or not isinstance(base.get("file", "base.tsp"), str):
        raise BundleError(f"{path}: 'base' must be an object with a 'file' name")
    return data


class Collection:
    """The bundles under ``root`` (see the module docstring)."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root).resolve()
        self._cache: dict[Path, tuple[int, dict[str, Any] | BundleError]] = {}
        self._lock = threading.Lock()

    def _manifest(self, directory: Path) -> dict[str, Any]:
        path = directory / MANIFEST
        try:
            mtime = path.stat().st_mtime_ns
        except OSError:
            raise BundleError(f"{directory.name}: no manifest.json "
                              "(not a Tessera bundle)") from None
        with self._lock:
            cached = self._cache.get(path)
        if cached is None or cached[0] != mtime:
            try:
                result: dict[str, Any] | BundleError = parse_manifest(path)
            except BundleError as exc:
                result = exc
            cached = (mtime, result)
            with self._lock:
                self._cache[path] = cached
        if isinstance(cached[1], BundleError):
            raise cached[1]
        return cached[1]

    def _directories(self) -> list[Path]:
        if (self.root / MANIFEST).is_file():
            return [self.root]
        return sorted(p for p in self.root.iterdir() if p.is_dir() and ID_PATTERN.match(p.name))

    def bundles(self) -> list[Bundle]:
        """Every readable bundle, sorted by id; unreadable ones are logged and left out."""
        found = []
        for directory in self._directories():
            try:
                found.append(Bundle(directory.name, directory, self._manifest(directory)))
            except BundleError as exc:
                log.warning("skipping %s", exc)
        return found

    def get(self, object_id: str) -> Bundle:
        """The bundle named ``object_id``.

        Raises
        ------
        KeyError
            When no such bundle exists (or the id is not a valid name).
        BundleError
            When the directory exists but is not a readable bundle.
        """
        if not ID_PATTERN.match(object_id):
            raise KeyError(object_id)
        if (self.root / MANIFEST).is_file():
            directory = self.root if object_id == self.root.name else None
        else:
            directory = self.root / object_id
        if directory is None or not directory.is_dir():
            raise KeyError(object_id)
        return Bundle(object_id, directory, self._manifest(directory))
