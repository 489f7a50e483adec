"""The worker's standard library: Pyodide's ``python_stdlib.zip`` cut to what it can import.

Pyodide's loader fetches ``python_stdlib.zip`` (2.5 MB, its members deflated already, so
HTTP compression gains nothing) and mounts it on ``sys.path``. The mesh worker imports
``client_py.session`` and nothing else, so most of the archive (``unittest``, ``email``,
``xml``, ``tkinter`` ...) is never read. :func:`trimmed_stdlib` keeps the *import closure*:

    K = closure(R),  R = client_py's imports ∪ ROOTS,
    closure(S) = S ∪ closure(imports(S))

(with every module of Pyodide's own packages, :data:`ROOT_PACKAGES`) where
``imports(m)`` is every ``import`` / ``from ... import`` statement anywhere in module
``m``'s source (top level or inside a function, ``try`` or ``if``: an import made late is
still in the archive), each with its parent packages, and ``ROOTS`` are the modules
Pyodide's own start-up imports plus the codecs of :data:`CODECS` (codecs are looked up by
name at run time, never by a statement; the code-page tables, 0.3 MB, are left out). The
result is about 6.5 MB of source, written once per Pyodide archive and ``client_py``
version in the cache folder (in a background thread when the server starts), and served
like any runtime file. Its members are *stored*, not deflated: HTTP compression of the whole
archive then shares one dictionary across the modules, 1.36 MB in brotli (quality 9) or
1.59 MB in gzip against 1.73 MB for the same members deflated one by one (Pyodide 314.0.7's
stdlib, measured for issue 14); zipimport reads stored members without inflating them.
"""

from __future__ import annotations

import hashlib
import logging
import re
import threading
import zipfile
from collections.abc import Iterable
from pathlib import Path

log = logging.getLogger(__name__)

#: The codecs kept: Unicode, ASCII, Latin-1 and the escapes Python itself uses.
CODECS = ("aliases", "utf_8", "utf_8_sig", "utf_16", "utf_16_le", "utf_16_be", "utf_32",
          "utf_32_le", "utf_32_be", "ascii", "latin_1", "charmap", "raw_unicode_escape",
          "unicode_escape", "punycode", "idna")
#: What Pyodide's bootstrap imports by itself (the ``site`` machinery, the codecs), besides
#: every module of :data:`ROOT_PACKAGES`.
ROOTS = ("site", "sitecustomize", "encodings", *(f"encodings.{codec}" for codec in CODECS))
#: Packages whose every module is a root: Pyodide's C core imports them by name
#: (``_pyodide.docstring``, ``_pyodide.jsbind`` ...).
ROOT_PACKAGES = ("_pyodide", "pyodide")


def imported_names(source: bytes | str, module: str, is_package: bool) -> set[str]:
    """Every module name ``module``'s source may import, with the parents of each.

    ``from . import x`` is resolved against ``module`` (a package resolves against itself);
    ``from a import b`` gives ``a`` and ``a.b`` (``b`` may be a submodule). The statements are
    found line by line (:func:`import_statements`), not with :mod:`ast`: the archive is
    Pyodide's Python, which may be newer than the server's (3.14's ``except A, B:`` does not
    parse in 3.11), and text-matching can only find more (an ``import`` inside a string),
    never less.
    """
    statements = import_statements(source)
    found: set[str] = set()
    for level, base_module, aliases in statements:
        if level is None:  # import a.b, c
            found.update(aliases)
            continue
        if level:
            parts = module.split(".") if is_package else module.split(".")[:-1]
            parts = parts[:len(parts) - (level - 1)]
            base = ".".join(parts + ([base_module] if base_module else []))
        else:
            base = base_module or ""
        found.add(base)
        found.update(f"{base}.{alias}" for alias in aliases)
    names = set()
    for name in found:
        parts = name.split(".")
        names.update(".".join(parts[:k]) for k in range(1, len(parts) + 1) if parts[0])
    return names


_IMPORT = re.compile(r"^\s*import\s+([\w.]+(?:\s+as\s+\w+)?(?:\s*,\s*[\w.]+(?:\s+as\s+\w+)?)*)",
                     re.M)
_FROM = re.compile(r"^\s*from\s+(\.*)([\w.]*)\s+import\s+(?:\(([^)]*)\)|([\w \t,*]+))", re.M)
_COMMENT = re.compile(r"#[^\n]*")


def import_statements(source: bytes | str) -> list[tuple[int | None, str | None, list[str]]]:
    """``(level, module, names)`` of each import statement of ``source``, found by line
    (level None: a plain ``import a, b``; else the number of leading dots of ``from``)."""
    text = source.decode("utf-8", "replace") if isinstance(source, bytes) else source
    text = _COMMENT.sub("", text)  # a comment inside a parenthesised list of names
    statements: list[tuple[int | None, str | None, list[str]]] = []
    for match in _IMPORT.finditer(text):
        names = [item.split()[0] for item in match.group(1).split(",") if item.strip()]
        statements.append((None, None, names))
    for match in _FROM.finditer(text):
        listed = match.group(3) or match.group(4)
        names = [item.split()[0] for item in listed.split(",")
                 if item.strip() and item.strip() != "*"]  # `from a import *`: a alone
        statements.append((len(match.group(1)), match.group(2) or None, names))
    return statements


def import_closure(archive: zipfile.ZipFile, roots: Iterable[str]) -> set[str]:
    """The member names of ``archive`` (``.py`` files) that modules ``roots`` can reach."""
    members = set(archive.namelist())

    def source_of(name: str) -> str | None:
        path = name.replace(".", "/")
        for candidate in (f"{path}.py", f"{path}/__init__.py"):
            if candidate in members:
                return candidate
        return None

    kept: set[str] = set()
    seen: set[str] = set()
    pending = list(roots)
    for package in ROOT_PACKAGES:  # every module of these packages, by its member name
        pending += [m.removesuffix(".py").removesuffix("/__init__").replace("/", ".")
                    for m in members if m.startswith(f"{package}/") and m.endswith(".py")]
    while pending:
        name = pending.pop()
        if name in seen:
            continue
        seen.add(name)
        member = source_of(name)
        if member is None:  # a built-in module, or not in the standard library
            continue
        kept.add(member)
        pending.extend(imported_names(archive.read(member), name,
                                      member.endswith("/__init__.py")))
    return kept


def client_py_imports(sources: dict) -> set[str]:
    """Module names imported by ``client_py``'s files (the ``/client_py/sources.json``
    document: ``{"package", "files": {relative path: source}}``)."""
    names = set(ROOTS)
    for relative, text in sources["files"].items():
        module = f"{sources['package']}." + relative.removesuffix(".py").replace("/", ".")
        is_package = relative.endswith("__init__.py")
        module = module.removesuffix(".__init__")
        names |= imported_names(text, module, is_package)
    return names


def write_trimmed(full: Path, roots: Iterable[str], out: Path) -> int:
    """Write the members of the archive ``full`` that ``roots`` reach to ``out``; their count."""
    with zipfile.ZipFile(full) as archive:
        kept = import_closure(archive, roots)
        tmp = out.with_name(f"{out.name}.tmp")
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED) as trimmed:
            for name in sorted(kept):
                trimmed.writestr(archive.getinfo(name), archive.read(name),
                                 compress_type=zipfile.ZIP_STORED)
    tmp.replace(out)
    return len(kept)


class TrimmedStdlib:
    """The trimmed archive for one Pyodide directory and one ``client_py`` sources document.

    Parameters
    ----------
    pyodide_dir : Path
        The npm ``pyodide`` package (its ``python_stdlib.zip``).
    sources : dict
        ``client_py``'s sources document.
    cache_dir : Path
        Where the archive is written.
    """

    def __init__(self, pyodide_dir: Path, sources: dict, cache_dir: Path) -> None:
        self.full = Path(pyodide_dir) / "python_stdlib.zip"
        self.sources = sources
        self.cache_dir = Path(cache_dir)
        self._lock = threading.Lock()
        try:
            stat = self.full.stat()
            version = f"{stat.st_size}-{stat.st_mtime_ns}"
        except OSError:
            version = "missing"
        digest = hashlib.sha256(f"{version}\0{sources['sha256']}\0".encode())
        digest.update(Path(__file__).read_bytes())  # a new rule here: a new archive
        self.key = digest.hexdigest()[:16]

    @property
    def path(self) -> Path:
        return self.cache_dir / f"python_stdlib-{self.key}.zip"

    def start_background_build(self) -> None:
        """Write the archive in a daemon thread unless it is there (the first worker to ask
        for it then waits less, or not at all)."""
        if not self.path.is_file():
            threading.Thread(target=self.ensure, daemon=True, name="trimmed-stdlib").start()

    def ensure(self) -> Path:
        """The trimmed archive, written now if needed; the full one when it cannot be
        written (a read-only cache: logged)."""
        if self.path.is_file():
            return self.path
        with self._lock:
            if not self.path.is_file():
                try:
                    self.cache_dir.mkdir(parents=True, exist_ok=True)
                    count = write_trimmed(self.full, client_py_imports(self.sources), self.path)
                except OSError as exc:
                    log.warning("cannot write the trimmed standard library in %s (%s): the "
                                "worker gets the whole python_stdlib.zip", self.cache_dir, exc)
                    return self.full
                log.info("made %s: %d modules", self.path, count)
                for old in self.cache_dir.glob("python_stdlib-*.zip"):
                    if old != self.path:  # archives of older Pyodide or client_py versions
                        old.unlink(missing_ok=True)
        return self.path
