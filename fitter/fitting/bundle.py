"""The bundle writer: a bundle folder appears at its destination whole, or not at all.

Every bundle Tessera writes, by ``fit_scan`` or by an admin job publishing into
a collection, goes through :func:`publish`: the files are complete in a folder
beside the destination (:func:`write_bundle` makes one), each file and each
folder is fsynced and given published permissions (folders ``0755``, files
``0644``), the folder takes the destination's place, an old bundle there is
removed only after the new one is in place, and the parent folder is fsynced so
that the change survives a power cut. A reader sees the old bundle or the new
one, never a mix; on a failure the old bundle stays (or is put back) and nothing
half-written is left beside it.

The destination always holds a bundle
-------------------------------------
Replacing an old bundle swaps the two folders in one step where the kernel can:
``renameat2(RENAME_EXCHANGE)`` (Linux 3.15, glibc 2.28; ext4, xfs, btrfs, tmpfs),
called through ctypes by :func:`exchange_paths`. A process killed at any moment
leaves the old bundle or the new one under the destination's name. Where the call
is missing or the file system refuses it, the fallback is two renames (the old
bundle into a parking folder ``.NAME.old.XXXXXXXX``, then the new one into place);
a kill between them leaves the destination missing and a complete old bundle
parked, and the next write to the destination puts it back first
(:func:`remove_stale_temporaries`). When the caller parks elsewhere (``aside``, the
job runner's staging folder) that recovery is the caller's.

Nothing left behind
-------------------
A fit killed while it writes leaves its hidden folder ``.NAME.XXXXXXXX`` beside
the destination. Each live one is held by its writer with an exclusive ``flock``
(released by the kernel when the process dies), and it is created under an
``flock`` on the destination's parent folder, which the clean-up holds too: so the
next write to the same destination removes exactly the temporaries of that
destination (by name pattern, owned by this user) that no live writer holds, and
two concurrent fits to one place never remove each other's folder.

Standard library only: the collection's job runner imports it.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

DIR_MODE = 0o755  # a bundle is published content: readable by the web server's user
FILE_MODE = 0o644
#: ``renameat2`` flag: swap the two names atomically (linux/fs.h)
RENAME_EXCHANGE = 2
AT_FDCWD = -100
#: errors of ``renameat2`` that mean "not here" (no syscall, or a file system without
#: the exchange): the two-rename fallback is taken
EXCHANGE_UNSUPPORTED = (errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP)
#: a file the old bundle must hold to be restored by the fallback's recovery
COMPLETE_MARKER = "manifest.json"
#: ``tempfile.mkdtemp``'s random suffix: 8 characters of ``[a-z0-9_]``
TEMP_SUFFIX = r"[a-z0-9_]{8}"


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


def _renameat2() -> ctypes._CFuncPtr | None:
    """glibc's ``renameat2`` (2.28 and later), or None where the C library lacks it."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
    except OSError:
        return None
    function = getattr(libc, "renameat2", None)
    if function is not None:
        function.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p,
                             ctypes.c_uint]
        function.restype = ctypes.c_int
    return function


RENAMEAT2 = _renameat2()


def exchange_paths(first: str | os.PathLike, second: str | os.PathLike) -> bool:
    """Swap two existing paths atomically (``renameat2(RENAME_EXCHANGE)``).

    Returns
    -------
    bool
        True when swapped; False when this system cannot (no ``renameat2`` in the C
        library, or the kernel or file system refuses the flag: ``ENOSYS``,
        ``EINVAL``, ``EOPNOTSUPP``), and nothing changed.

    Raises
    ------
    OSError
        Any other failure of the call (nothing changed either).
    """
    if RENAMEAT2 is None:
        return False
    if RENAMEAT2(AT_FDCWD, os.fsencode(first), AT_FDCWD, os.fsencode(second),
                 RENAME_EXCHANGE) == 0:
        return True
    code = ctypes.get_errno()
    if code in EXCHANGE_UNSUPPORTED:
        return False
    raise OSError(code, os.strerror(code), os.fspath(first), None, os.fspath(second))


@contextmanager
def _locked(folder: Path, blocking: bool = True) -> Iterator[int | None]:
    """Hold an exclusive ``flock`` on ``folder``; yields its descriptor, or None when
    ``blocking`` is False and another process holds it."""
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if blocking else fcntl.LOCK_NB))
        except BlockingIOError:
            yield None
            return
        yield fd
    finally:
        os.close(fd)  # closing the last descriptor releases the lock


def _temporaries(destination: Path) -> list[Path]:
    """The folders this writer may have left for ``destination``: ``.NAME.XXXXXXXX``
    (a bundle being written) and ``.NAME.old.XXXXXXXX`` (a parked old bundle), owned by
    this user, not symbolic links."""
    pattern = re.compile(rf"\.{re.escape(destination.name)}\.(old\.)?{TEMP_SUFFIX}")
    found = []
    for entry in os.scandir(destination.parent):
        if pattern.fullmatch(entry.name) and entry.is_dir(follow_symlinks=False) \
                and entry.stat(follow_symlinks=False).st_uid == os.geteuid():
            found.append(Path(entry.path))
    return sorted(found)


def remove_stale_temporaries(destination: str | os.PathLike) -> list[Path]:
    """Remove what killed writes to ``destination`` left beside it; restore a parked bundle.

    Call with the destination's parent locked (``_locked``), as :func:`write_bundle`
    and :func:`publish` do. A temporary folder (see :func:`_temporaries`) that a live
    writer holds is kept; any other is removed, except that when ``destination`` is
    missing, a parked old bundle holding ``COMPLETE_MARKER`` is first renamed back to
    ``destination`` (the fallback's recovery).

    Returns
    -------
    list of Path
        The folders removed (or emptied by the recovery).
    """
    destination = Path(destination)
    removed = []
    for folder in _temporaries(destination):
        try:
            with _locked(folder, blocking=False) as fd:
                if fd is None:
                    continue  # a live writer's folder
                parked = folder / "bundle"
                if folder.name.startswith(f".{destination.name}.old.") and \
                        not os.path.lexists(destination) and (parked / COMPLETE_MARKER).is_file():
                    os.rename(parked, destination)
                    _fsync(destination.parent)
                shutil.rmtree(folder, ignore_errors=True)
        except FileNotFoundError:
            continue  # its own writer removed it meanwhile (a failed block's clean-up)
        removed.append(folder)
    return removed


def _remove(path: Path) -> None:
    """Remove a folder tree, or a file or symbolic link (never following it)."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink()


def publish(staged: str | os.PathLike, destination: str | os.PathLike,
            aside: str | os.PathLike | None = None) -> Path:
    """Make the complete bundle folder ``staged`` appear at ``destination``.

    ``staged`` is synced (:func:`sync_tree`), then, with the destination's parent
    locked and its stale temporaries removed (:func:`remove_stale_temporaries`):

    * no bundle at ``destination``: ``staged`` is renamed to it;
    * an old bundle there: the two folders are swapped (:func:`exchange_paths`), so
      the old one is at ``staged``'s path, removed once the parent is fsynced;
    * where the swap is unavailable: the old bundle is renamed into a new folder
      ``.NAME.old.XXXXXXXX`` under ``aside`` (default: the destination's parent),
      ``staged`` to ``destination`` (if that fails, the old bundle is renamed back),
      and the parked one removed after the parent's fsync.

    ``staged``, ``destination`` and ``aside`` must be on one file system (a rename
    does not cross file systems).

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
    with _locked(parent):
        remove_stale_temporaries(destination)
        if not os.path.lexists(destination):
            os.rename(staged, destination)
            _fsync(parent)
            return destination
        if exchange_paths(staged, destination):
            _fsync(parent)
            _remove(staged)  # the old bundle (or whatever was there), now at the staged name
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
    Stale temporaries of earlier, killed writes to ``destination`` are removed first
    (:func:`remove_stale_temporaries`), and the new folder is held by an ``flock``
    until the block ends, so a concurrent write to the same place leaves it alone.
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
    destination = parent / destination.name
    with _locked(parent):  # no clean-up can see the new folder before it is held
        remove_stale_temporaries(destination)
        folder = Path(tempfile.mkdtemp(prefix=f".{destination.name}.", dir=parent))
        hold = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
        fcntl.flock(hold, fcntl.LOCK_EX)
    try:
        yield folder
        publish(folder, destination)
    finally:
        if folder.exists():  # not published: the block or the publication failed
            shutil.rmtree(folder, ignore_errors=True)
        os.close(hold)  # held until removed: no clean-up races this one
