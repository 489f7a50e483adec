"""Pyodide memory snapshots with ``client_py`` imported: the viewer's fast start.

Starting Pyodide in a browser spends most of its time initialising the Python
interpreter (several seconds on a modest machine). A memory snapshot taken after
that initialisation, and after ``import client_py.session`` (the mesh worker's
Python, which imports the rest of ``client_py``), restores in about a second
(Pyodide's experimental ``_makeSnapshot`` / ``_loadSnapshot`` options). The
snapshot is made here once, by node running ``web/tools/make-pyodide-snapshot.mjs``
against the served Pyodide package, and cached on disk under a name derived from
the Pyodide version, the ``client_py`` sources and the script, so it can never be
served stale and can be cached by browsers forever. It is sent compressed like every
runtime file (:mod:`.files`): 31 MB of memory are 6.1 MB in gzip, 4.3 MB in brotli. That
is most of a first visit, so the snapshot is off unless ``TESSERA_PYODIDE_SNAPSHOT`` is set
(see docs/benchmarks.md, "First visit"); a worker restoring it fetches no standard library
(the script drops the archive from ``sys.path`` after importing ``client_py.session``).

When node is missing or the build fails the server logs why and the pages load
Pyodide the ordinary way (``pyodide_snapshot_url`` is null in their config).
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

from . import WEB_ROOT

log = logging.getLogger(__name__)

SCRIPT = WEB_ROOT / "tools" / "make-pyodide-snapshot.mjs"
BUILD_TIMEOUT_S = 180


class SnapshotBuilder:
    """Builds (once) and locates the snapshot for one Pyodide directory and client_py version.

    Parameters
    ----------
    pyodide_dir : Path
        The npm ``pyodide`` package that the pages load.
    sources : dict
        ``client_py``'s sources document (``runtime.client_py_sources()``).
    cache_dir : Path
        Where snapshots are kept (made when the first one is built; ``create_app`` gives
        ``cache/`` in the Flask instance folder unless ``TESSERA_CACHE_DIR`` is set).
    node : str, optional
        The node executable (default: ``node`` on ``PATH``).
    """

    def __init__(self, pyodide_dir: Path, sources: dict, cache_dir: Path,
                 node: str | None = None) -> None:
        self.pyodide_dir = Path(pyodide_dir)
        self.sources = sources
        self.cache_dir = Path(cache_dir)
        self.node = node or shutil.which("node")
        self._lock = threading.Lock()
        self._failed: str | None = None
        self._building = False
        try:
            version = json.loads((self.pyodide_dir / "package.json").read_text())["version"]
        except (OSError, ValueError, KeyError):
            version = "unknown"
        digest = hashlib.sha256(f"{version}\0{sources['sha256']}\0".encode())
        digest.update(SCRIPT.read_bytes())
        self.key = f"pyodide-{version}-client_py-{digest.hexdigest()[:16]}"

    @property
    def path(self) -> Path:
        return self.cache_dir / f"{self.key}.bin"

    @property
    def failure(self) -> str | None:
        """Why the snapshot could not be made, or None."""
        return self._failed

    def ready(self) -> bool:
        return self.path.is_file()

    def ensure(self) -> Path | None:
        """The snapshot file, built now if needed; None (and a logged reason) if it cannot be."""
        if self.ready():
            return self.path
        with self._lock:
            if self.ready():
                return self.path
            if self._failed is not None:
                return None
            if self.node is None:
                self._failed = "node is not installed"
            else:
                self._failed = self._build()
            if self._failed is not None:
                log.warning("no Pyodide snapshot (pages load Pyodide the slow way): %s",
                            self._failed)
                return None
            return self.path

    def _build(self) -> str | None:
        try:
            self.cache_dir.mkdir(parents=True, exist_ok=True)
            # a folder of this build's own: server processes sharing a cache folder (several
            # WSGI workers) may build at once; the last atomic replace wins, with equal bytes
            work = tempfile.TemporaryDirectory(prefix=f"{self.key}.", dir=self.cache_dir)
        except OSError as exc:  # e.g. an instance folder this server may not write
            return f"cannot write in the cache folder {self.cache_dir}: {exc}"
        with work:
            tmp, sources = Path(work.name) / "snapshot.bin", Path(work.name) / "sources.json"
            try:
                sources.write_text(json.dumps(self.sources))
                subprocess.run([self.node, str(SCRIPT), str(self.pyodide_dir), str(sources),
                                str(tmp)], check=True, capture_output=True, text=True,
                               timeout=BUILD_TIMEOUT_S)
                tmp.replace(self.path)
            except subprocess.CalledProcessError as exc:
                return f"make-pyodide-snapshot.mjs failed: {exc.stderr.strip()[-500:]}"
            except (OSError, subprocess.SubprocessError) as exc:
                return f"make-pyodide-snapshot.mjs could not run: {exc}"
        for old in self.cache_dir.glob("pyodide-*.bin*"):
            if not old.name.startswith(self.key):  # snapshots of older client_py versions
                old.unlink(missing_ok=True)
        log.info("made the Pyodide snapshot %s", self.path)
        return None

    def start_background_build(self) -> None:
        """Build in a daemon thread, once (``tessera serve`` does this at start-up)."""
        with self._lock:
            if self._building or self.ready():
                return
            self._building = True
        threading.Thread(target=self.ensure, daemon=True, name="pyodide-snapshot").start()
