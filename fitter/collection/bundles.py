"""A collection: a directory of bundle directories, each read through its ``manifest.json``.

An object's id is its bundle directory's name; only names made of letters,
digits, ``.``, ``_`` and ``-`` (not starting with ``.``) are ids, so an id can
never name a path outside the collection. A directory that is itself a bundle
(it holds ``manifest.json``) is served as a collection of that one object.
Manifests are re-read when their modification time changes, so bundles can be
added to a running server.

What the server reads of a manifest is checked here, once, by :func:`parse_manifest`
(every route then agrees on what a readable bundle is): the JSON itself (at most
:data:`MAX_MANIFEST_BYTES`, no ``NaN``/``Infinity``), ``format``/``format_version``,
and the fields the gallery, the API and the pages show — ``title``, ``units``,
``base.file`` (a name confined to the bundle, see :func:`confined_name`), ``base.grid``,
``base.degree``, ``stats``, ``provenance`` and ``files``; of an atlas (``format_version`` 2)
its ``base`` and ``tiles`` (colour too) by ``client_py.bundle.atlas_colour``, which
checks ``atlas_tiles`` first, instead of ``base.grid`` and ``base.degree``. A bundle that
fails is left out
of :meth:`Collection.bundles` and logged once per version of its manifest; asking for it
by id raises :class:`BundleError` with the reason.

The bundle's own files are read through :meth:`Bundle.read_file` (confined to the bundle
directory, regular files only, bounded in size) and counted by :meth:`Bundle.file_sizes`
(regular files only; symbolic links are never followed nor counted).
"""

from __future__ import annotations

import json
import logging
import os
import re
import stat
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from client_py.bundle import ManifestError, atlas_colour
from client_py.errors import TesseraError
from client_py.format import loads_finite_json

log = logging.getLogger(__name__)

ID_PATTERN = re.compile(r"^[A-Za-z0-9_-][A-Za-z0-9._-]{0,127}$")
MANIFEST = "manifest.json"
#: the largest manifest read (a level-6 tile tree is well under 1 MB)
MAX_MANIFEST_BYTES = 16 << 20
#: the longest file name a manifest may give (relative to its bundle)
MAX_NAME_LENGTH = 1024


class BundleError(TesseraError, ValueError):
    """A bundle directory whose manifest is missing or not a Tessera bundle manifest, or a
    bundle file that cannot be read within the bundle's rules (:meth:`Bundle.read_file`)."""


def confined_name(name: object, what: str) -> str:
    """``name`` checked to be a relative POSIX path that stays inside its bundle.

    Accepted: non-empty text of at most :data:`MAX_NAME_LENGTH` characters, segments
    separated by ``/``, none of them empty, ``.`` or ``..``, no backslash or NUL; not
    absolute. (Symbolic links are checked when the file is opened, by
    :meth:`Bundle.read_file`.)

    Raises
    ------
    BundleError
        Naming ``what`` (e.g. ``'base.file'``), the value and what is accepted.
    """
    accepted = "a relative name inside the bundle such as 'base.tsp'"
    if not isinstance(name, str) or not name:
        raise BundleError(f"{what} must be {accepted}, got {name!r}")
    if len(name) > MAX_NAME_LENGTH or "\\" in name or "\x00" in name:
        raise BundleError(f"{what} must be {accepted} (at most {MAX_NAME_LENGTH} characters, "
                          f"no backslash or NUL), got {name[:80]!r}")
    parts = name.split("/")
    if name.startswith("/") or any(part in ("", ".", "..") for part in parts):
        raise BundleError(f"{what} must be {accepted}, got {name[:80]!r}")
    return name


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _check_fields(data: dict[str, Any]) -> None:
    """Check the fields the server reads (see the module docstring); ``ValueError`` naming one."""
    for key in ("title", "units"):
        if data.get(key) is not None and not isinstance(data[key], str):
            raise ValueError(f"{key!r} must be text, got {data[key]!r}")
    base = data.get("base", {})
    if not isinstance(base, dict):
        raise ValueError(f"'base' must be an object with a 'file' name, got {base!r}")
    confined_name(base.get("file", "base.tsp"), "base.file")
    if data.get("format_version") == 2:
        try:  # an atlas: its base, tiles and colour, by the reader the browser and CLI use
            atlas_colour(data)  # checks atlas_tiles first
        except ManifestError as exc:
            raise ValueError(f"format_version 2 (atlas): {exc}") from None
    for key, least in (() if data.get("format_version") == 2 else (("grid", 1), ("degree", 1))):
        value = base.get(key)
        if value is None:
            continue
        if (not isinstance(value, list) or len(value) != 2
                or not all(isinstance(n, int) and not isinstance(n, bool) and n >= least
                           for n in value)):
            raise ValueError(f"base.{key} must be two integers >= {least}, got {value!r}")
    stats = data.get("stats", {})
    if not isinstance(stats, dict):
        raise ValueError(f"'stats' must be an object of numbers, got {stats!r}")
    for key, value in stats.items():
        if key == "units":
            if not isinstance(value, str):
                raise ValueError(f"stats.units must be text, got {value!r}")
        elif value is not None and not _is_number(value):
            raise ValueError(f"stats.{key} must be a number, got {value!r}")
    provenance = data.get("provenance", {})
    if not isinstance(provenance, dict):
        raise ValueError(f"'provenance' must be an object, got {provenance!r}")
    for key in ("bytes", "points"):
        value = provenance.get(key)
        if value is not None and not (_is_number(value) and value >= 0):
            raise ValueError(f"provenance.{key} must be a number >= 0, got {value!r}")
    if provenance.get("sha256") is not None and not isinstance(provenance["sha256"], str):
        raise ValueError(f"provenance.sha256 must be text, got {provenance['sha256']!r}")
    files = data.get("files", {})
    if not isinstance(files, dict) or not all(
            isinstance(size, int) and not isinstance(size, bool) and size >= 0
            for size in files.values()):
        raise ValueError("'files' must map names to byte sizes (integers >= 0)")


def _read_regular(path: Path, inside: Path, max_bytes: int,
                  what: str) -> tuple[bytes, os.stat_result]:
    """The bytes and ``stat`` of ``path``, a regular file under the directory ``inside`` (after
    following any symbolic links), at most ``max_bytes`` long; else :class:`BundleError`."""
    try:
        real = path.resolve(strict=True)
    except FileNotFoundError:
        raise BundleError(f"{what}: no such file") from None
    except (OSError, RuntimeError) as exc:  # RuntimeError: a symbolic link loop
        raise BundleError(f"{what}: cannot be opened ({type(exc).__name__})") from None
    if not real.is_relative_to(inside.resolve()):
        raise BundleError(f"{what}: leads outside the bundle (a symbolic link?); only files "
                          "inside the bundle are read")
    try:
        # O_NONBLOCK: opening a FIFO must not wait for a writer (fstat then refuses it)
        fd = os.open(real, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOFOLLOW", 0))
    except OSError as exc:
        raise BundleError(f"{what}: cannot be opened ({type(exc).__name__})") from None
    with os.fdopen(fd, "rb") as handle:
        info = os.fstat(handle.fileno())
        if not stat.S_ISREG(info.st_mode):
            raise BundleError(f"{what}: not a regular file; only regular files are read")
        if info.st_size > max_bytes:
            raise BundleError(f"{what}: {info.st_size} bytes; at most {max_bytes} are read")
        data = handle.read(info.st_size + 1)  # (read(n) sets n bytes aside at once)
    if len(data) > max_bytes:  # grew while being read
        raise BundleError(f"{what}: more than {max_bytes} bytes; at most {max_bytes} are read")
    return data, info


def parse_manifest(path: Path) -> dict[str, Any]:
    """The manifest at ``path``, checked to be a ``tessera-bundle`` manifest of version 1 or 2 whose
    fields the server reads are well formed (see the module docstring).

    Raises
    ------
    BundleError
        Naming the bundle and what is wrong with its manifest (never echoing its bytes).
    """
    where = f"{path.parent.name}/{path.name}"
    if not path.is_symlink() and not path.exists():
        raise BundleError(f"{where}: no manifest.json (not a Tessera bundle)")
    raw, _ = _read_regular(path, path.parent, MAX_MANIFEST_BYTES, where)
    try:
        data = loads_finite_json(raw.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise BundleError(f"{where}: unreadable manifest: not UTF-8 text "
                          f"(byte {exc.start})") from None
    except json.JSONDecodeError as exc:
        raise BundleError(f"{where}: unreadable manifest: not JSON ({exc.msg} at line "
                          f"{exc.lineno} column {exc.colno})") from None
    except ValueError as exc:  # from the two hooks: NaN, Infinity, 1e999
        raise BundleError(f"{where}: unreadable manifest: {exc}") from None
    except RecursionError:
        raise BundleError(f"{where}: unreadable manifest: nested too deeply") from None
    if not isinstance(data, dict) or data.get("format") != "tessera-bundle":
        raise BundleError(f"{where}: 'format' must be 'tessera-bundle'")
    if data.get("format_version") not in (1, 2):
        raise BundleError(f"{where}: format_version {repr(data.get('format_version'))[:40]}; "
                          "this server reads versions 1 (one patch) and 2 (an atlas)")
    try:
        _check_fields(data)
    except ValueError as exc:
        raise BundleError(f"{where}: {str(exc)[:300]}") from None
    return data


#: what ``manifest.json`` keeps for its admin and tools, never sent to a visitor
#: (:func:`served_manifest`): the fit's own records (``fit``: layouts tried, steps, detail
#: diagnostics; ``timings``), the options it was given and those it did not use, and the
#: size of every file. No viewer, 3DHOP page or PLY download reads them; the admin's pages,
#: ``tessera`` and ``fit-collection`` read the file itself.
FIT_RECORDS = ("fit", "timings", "options", "options_unused", "files")


def served_manifest(manifest: dict[str, Any]) -> bytes:
    """The ``manifest.json`` a visitor's browser is sent (``fitter.server.bundles``; the
    benchmarks count its gzip as the bytes of a visit): ``manifest`` without
    :data:`FIT_RECORDS`, and without ``stats_all_points`` where it repeats ``stats``, as
    compact JSON with sorted keys. On Stanford Lucy's default atlas the gzip of the
    manifest falls from 2,398 to 1,444 bytes, on a 1.1 M-vertex mesh from 5,822 to 3,818."""
    served = {k: v for k, v in manifest.items() if k not in FIT_RECORDS}
    if served.get("stats_all_points") == served.get("stats"):
        served.pop("stats_all_points", None)
    return json.dumps(served, sort_keys=True, separators=(",", ":")).encode()


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
        The parsed ``manifest.json``, checked by :func:`parse_manifest` (the accessors
        below rely on it).
    """

    id: str
    path: Path
    manifest: dict[str, Any]

    @property
    def title(self) -> str:
        return str(self.manifest.get("title") or self.id)

    @property
    def base(self) -> dict[str, Any]:
        """The manifest's ``base`` object (``{}`` when it has none)."""
        return self.manifest.get("base", {})

    @property
    def base_file(self) -> str:
        """Name of the base patch inside the bundle (``manifest['base']['file']``)."""
        return str(self.base.get("file", "base.tsp"))

    @property
    def units(self) -> str:
        return self.manifest.get("units") or "unknown"

    @property
    def stats(self) -> dict[str, Any]:
        return self.manifest.get("stats", {})

    @property
    def provenance(self) -> dict[str, Any]:
        return self.manifest.get("provenance", {})

    def recorded_size(self, name: str) -> int | None:
        """The byte size the manifest's ``files`` records for ``name``, or None."""
        return self.manifest.get("files", {}).get(name)

    def file_sizes(self) -> dict[str, int]:
        """Byte size of every regular file of the bundle, by name relative to it.

        Symbolic links (to files or directories, inside or outside the bundle) are
        neither followed nor counted, nor are names starting with ``.``.
        """
        sizes = {}
        for folder, subfolders, names in os.walk(self.path, followlinks=False):
            subfolders[:] = [d for d in subfolders if not d.startswith(".")]
            for name in names:
                if name.startswith("."):
                    continue
                path = Path(folder, name)
                try:
                    info = path.lstat()
                except OSError:
                    continue  # removed while listing
                if stat.S_ISREG(info.st_mode):
                    sizes[path.relative_to(self.path).as_posix()] = info.st_size
        return dict(sorted(sizes.items()))

    def read_file(self, name: str, max_bytes: int) -> tuple[bytes, os.stat_result]:
        """The bytes of the bundle's file ``name`` and its ``stat``.

        ``name`` must pass :func:`confined_name` and lead, after any symbolic links, to a
        regular file inside the bundle directory of at most ``max_bytes`` bytes and of no
        more than the size the manifest records for it.

        Raises
        ------
        BundleError
            Saying which rule the file breaks (never quoting its bytes).
        """
        confined_name(name, "file name")
        where = f"{self.id}/{name}"
        recorded = self.recorded_size(name)
        limit = max_bytes if recorded is None else min(max_bytes, recorded)
        return _read_regular(self.path / name, self.path, limit, where)


class Collection:
    """The bundles under ``root`` (see the module docstring)."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root).resolve()
        #: manifest path -> (version, manifest or its error); version: (mtime_ns, size, inode)
        self._cache: dict[Path, tuple[tuple[int, int, int] | None,
                                      dict[str, Any] | BundleError]] = {}
        self._lock = threading.Lock()

    def _manifest(self, directory: Path) -> dict[str, Any]:
        path = directory / MANIFEST
        try:
            info = path.stat()
            version: tuple[int, int, int] | None = (info.st_mtime_ns, info.st_size, info.st_ino)
        except OSError:
            version = None
        with self._lock:
            cached = self._cache.get(path)
        if cached is None or cached[0] != version:
            try:
                if version is None:
                    raise BundleError(f"{directory.name}: no manifest.json "
                                      "(not a Tessera bundle)")
                result: dict[str, Any] | BundleError = parse_manifest(path)
            except BundleError as exc:
                result = exc
                # once per version of the manifest, not once per request
                log.warning("bundle %s is not served: %s", directory.name, exc)
            cached = (version, result)
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
        """Every readable bundle, sorted by id; unreadable ones are left out (logged once per
        version of their manifest, by :meth:`_manifest`)."""
        found = []
        for directory in self._directories():
            try:
                found.append(Bundle(directory.name, directory, self._manifest(directory)))
            except BundleError:
                continue
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
