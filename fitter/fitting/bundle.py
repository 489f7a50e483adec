"""The bundle writer: a bundle folder appears at its destination whole, or not at all.

Every bundle Tessera writes, by ``fit_scan`` or by an admin job publishing into
a collection, goes through :func:`publish`: the files are complete in a folder
beside the destination (:func:`write_bundle` makes one), each file and each
folder is fsynced and given published permissions (folders ``0755``, files
``0644``), the folder is renamed into place, an old bundle there is moved aside
first and removed only after the new one is in place, and the parent folder is
fsynced so that the rename survives a power cut. A reader sees the old bundle
or the new one, never a mix; on a failure the old bundle stays (or is put
back) and nothing half-written is left beside it.

Standard library only: the collection's job runner imports it.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

DIR_MODE = 0o755  # a bundle is published content: readable by the web server's user
FILE_MODE = 0o644


def _fsync(path: Path) -> None:
    """fsync a file or a folder (a folder's fsync makes its entries durable)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def sync_tree(folder: Path) -> None:
    """Give every file under ``folder`` mode ``FILE_MODE`` and every folder (``folder``
    too) ``DIR_MODE``, then fsync the files, then the folders, deepest first."""
    folder = Path(folder)
    files, folders = [], [folder]
    for path in sorted(folder.rglob("*")):
        if path.is_symlink():
            raise ValueError(f"bundle folder {folder} holds a symbolic link {path}; a bundle "
                             f"holds files and folders only")
        (folders if path.is_dir() else files).append(path)
    for path in files:
        path.chmod(FILE_MODE)
        _fsync(path)
    for path in sorted(folders, key=lambda p: len(p.parts), reverse=True):
        path.chmod(DIR_MODE)
        _fsync(path)


def publish(staged: str | os.PathLike, destination: str | os.PathLike,
            aside: str | os.PathLike | None = None) -> Path:
    """Make the complete bundle folder ``staged`` appear at ``destination`` by a rename.

    ``staged`` is synced (:func:`sync_tree`) and renamed to ``destination``; an old
    bundle there is first renamed into a new temporary folder under ``aside``
    (default: the destination's parent), and removed once the new bundle is in
    place and the parent folder fsynced. If the second rename fails, the old bundle
    is renamed back. ``staged``, ``destination`` and ``aside`` must be on one file
    system (a rename does not cross file systems).

    Returns
    -------
    Path
        ``destination``.
    """
    staged, destination = Path(staged), Path(destination)
    if not staged.is_dir():
        raise ValueError(f"staged bundle {staged} is not a folder")
    sync_tree(staged)
    parent = destination.parent
    if not destination.exists():
        os.rename(staged, destination)
        _fsync(parent)
        return destination
    parking = Path(tempfile.mkdtemp(prefix=f".{destination.name}.old.",
                                    dir=parent if aside is None else Path(aside)))
    old = parking / "bundle"
    os.rename(destination, old)
    try:
        os.rename(staged, destination)
    except BaseException:  # undo the first rename, then let the failure through
        os.rename(old, destination)
        os.rmdir(parking)
        raise
    _fsync(parent)
    shutil.rmtree(parking)
    return destination


@contextmanager
def write_bundle(destination: str | os.PathLike) -> Iterator[Path]:
    """A new folder to write a bundle into, published to ``destination`` when the block ends.

    The folder is a hidden temporary one beside ``destination`` (same file system,
    so the rename of :func:`publish` is atomic); the parent is created if needed.
    If the block raises, or the publication fails, the folder is removed and an old
    bundle at ``destination`` is untouched.

    Examples
    --------
    >>> with write_bundle(out_dir) as folder:  # doctest: +SKIP
    ...     (folder / "base.tsp").write_bytes(data)
    ...     (folder / "manifest.json").write_text(text)
    """
    destination = Path(destination)
    parent = destination.resolve().parent
    parent.mkdir(parents=True, exist_ok=True)
    folder = Path(tempfile.mkdtemp(prefix=f".{destination.name}.", dir=parent))
    try:
        yield folder
        publish(folder, destination)
    finally:
        if folder.exists():  # not published: the block or the publication failed
            shutil.rmtree(folder, ignore_errors=True)
