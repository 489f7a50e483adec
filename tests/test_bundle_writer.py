"""fitter.fitting.bundle, the one bundle writer: a bundle appears whole or not at all, with
published permissions, every file and folder fsynced, an old bundle replaced only once the
new one is in place; and the admin jobs' publication into a collection goes through it."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from fitter.collection.jobs import publish_bundle, staging_dir
from fitter.fitting import bundle as bundle_writer
from fitter.fitting.bundle import publish, write_bundle


def make_bundle(folder: Path, text: str) -> Path:
    (folder / "detail" / "0").mkdir(parents=True, exist_ok=True)
    (folder / "manifest.json").write_text(text)
    (folder / "detail" / "0" / "0_0.tsd").write_text(text)
    return folder


def tree(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): p.read_text()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def two_renames(monkeypatch):
    """The documented fallback where renameat2's exchange is unavailable: the tests that
    watch its two renames run it (the swap is tested below)."""
    monkeypatch.setattr(bundle_writer, "RENAMEAT2", None)


def test_write_bundle_publishes_with_published_permissions(tmp_path):
    old_umask = os.umask(0o077)  # a private umask must not leak into published content
    try:
        with write_bundle(tmp_path / "out" / "b") as folder:
            make_bundle(folder, "new")
            assert folder.parent == tmp_path / "out" and folder.name.startswith(".b.")
            assert not (tmp_path / "out" / "b").exists()  # nothing visible before the end
    finally:
        os.umask(old_umask)
    out = tmp_path / "out" / "b"
    assert tree(out) == {"manifest.json": "new", "detail/0/0_0.tsd": "new"}
    for path in [out, *out.rglob("*")]:
        mode = stat.S_IMODE(path.stat().st_mode)
        assert mode == (0o755 if path.is_dir() else 0o644), (path, oct(mode))
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["b"]


def test_every_file_and_folder_and_the_parent_are_fsynced(tmp_path, monkeypatch):
    synced: list[str] = []
    real_fsync = os.fsync

    def recording_fsync(fd: int) -> None:
        synced.append(os.readlink(f"/proc/self/fd/{fd}"))
        real_fsync(fd)

    monkeypatch.setattr(bundle_writer.os, "fsync", recording_fsync)
    staged = make_bundle(tmp_path / "staged", "x")
    files = sorted(str(p) for p in staged.rglob("*") if p.is_file())
    folders = {str(p) for p in [staged, *staged.rglob("*")] if p.is_dir()}
    publish(staged, tmp_path / "dest")
    # the staged files, then its folders, then (after the rename) the parent folder
    assert synced[: len(files)] == files
    assert set(synced[len(files) : -1]) == folders and len(synced) == len(files) + len(folders) + 1
    assert synced[-1] == str(tmp_path)


def test_an_old_bundle_is_replaced_and_removed_only_after(tmp_path, monkeypatch, two_renames):
    dest = make_bundle(tmp_path / "dest", "old")
    (dest / "only-old.txt").write_text("old")
    seen_during_rename = []
    real_rename = os.rename

    def watching_rename(src, dst):
        real_rename(src, dst)
        seen_during_rename.append(sorted(p.name for p in tmp_path.iterdir()))

    monkeypatch.setattr(bundle_writer.os, "rename", watching_rename)
    with write_bundle(dest) as folder:
        make_bundle(folder, "new")
    assert tree(dest) == {"manifest.json": "new", "detail/0/0_0.tsd": "new"}
    # after the first rename the old bundle is parked beside, not deleted
    assert any(name.startswith(".dest.old.") for name in seen_during_rename[0])
    assert [p.name for p in tmp_path.iterdir()] == ["dest"]  # parking removed after


def test_a_failure_in_the_block_leaves_the_old_bundle_and_no_temporary_folder(tmp_path):
    dest = make_bundle(tmp_path / "dest", "old")
    with pytest.raises(RuntimeError, match="fit failed"):
        with write_bundle(dest) as folder:
            make_bundle(folder, "half")
            raise RuntimeError("fit failed")
    assert tree(dest) == {"manifest.json": "old", "detail/0/0_0.tsd": "old"}
    assert [p.name for p in tmp_path.iterdir()] == ["dest"]


def test_a_failed_second_rename_puts_the_old_bundle_back(tmp_path, monkeypatch, two_renames):
    dest = make_bundle(tmp_path / "dest", "old")
    real_rename = os.rename
    calls = []

    def failing_rename(src, dst):
        calls.append((Path(src), Path(dst)))
        if len(calls) == 2:  # the staged bundle into place
            raise OSError(28, "No space left on device")
        real_rename(src, dst)

    monkeypatch.setattr(bundle_writer.os, "rename", failing_rename)
    with pytest.raises(OSError, match="No space left"):
        with write_bundle(dest) as folder:
            make_bundle(folder, "new")
    assert tree(dest) == {"manifest.json": "old", "detail/0/0_0.tsd": "old"}
    assert [p.name for p in tmp_path.iterdir()] == ["dest"]


def test_publish_refuses_a_missing_staged_folder(tmp_path):
    with pytest.raises(ValueError, match="is not a folder"):
        publish(tmp_path / "missing", tmp_path / "dest")


def test_a_job_publishes_into_the_collection_and_parks_the_old_bundle_in_staging(
        tmp_path, monkeypatch, two_renames):
    """The jobs' crash-safety contract: between the two renames the old bundle is in the
    job's staging folder (which the supervisor clears if the worker dies), never in the
    collection; afterwards the collection holds the new bundle and nothing else."""
    collection = tmp_path / "collection"
    dest = make_bundle(collection / "obj", "old")
    staging = staging_dir(collection, 3)
    staged = make_bundle(staging / "obj", "new")
    parked = []
    real_rename = os.rename

    def watching_rename(src, dst):
        if Path(src) == dest:
            parked.append(Path(dst))
        real_rename(src, dst)

    monkeypatch.setattr(bundle_writer.os, "rename", watching_rename)
    publish_bundle(staged, dest)
    assert len(parked) == 1 and parked[0].parent.parent == staging
    assert tree(dest) == {"manifest.json": "new", "detail/0/0_0.tsd": "new"}
    assert sorted(p.name for p in collection.iterdir()) == [".tessera", "obj"]
    assert list(staging.iterdir()) == []


# ------------------------------------------------- the swap, kills and stale temporaries (issue 15)

def test_exchange_paths_swaps_two_folders_in_one_step(tmp_path):
    first, second = make_bundle(tmp_path / "a", "a"), make_bundle(tmp_path / "b", "b")
    assert bundle_writer.exchange_paths(first, second)  # Linux, glibc >= 2.28, ext4
    assert tree(first)["manifest.json"] == "b" and tree(second)["manifest.json"] == "a"
    with pytest.raises(FileNotFoundError, match="No such file"):
        bundle_writer.exchange_paths(first, tmp_path / "missing")


def test_an_old_bundle_is_swapped_out_and_never_leaves_the_name_empty(tmp_path, monkeypatch):
    dest = make_bundle(tmp_path / "dest", "old")
    renamed, swapped = [], []
    real_exchange = bundle_writer.exchange_paths

    def watching_exchange(first, second):
        assert real_exchange(first, second)
        swapped.append(tree(dest))  # right after the swap: the new bundle, whole
        return True

    monkeypatch.setattr(bundle_writer, "exchange_paths", watching_exchange)
    monkeypatch.setattr(bundle_writer.os, "rename", lambda *a: renamed.append(a))
    with write_bundle(dest) as folder:
        make_bundle(folder, "new")
    assert swapped == [{"manifest.json": "new", "detail/0/0_0.tsd": "new"}]
    assert renamed == []  # no moment without a bundle at dest
    assert tree(dest) == {"manifest.json": "new", "detail/0/0_0.tsd": "new"}
    assert [p.name for p in tmp_path.iterdir()] == ["dest"]


def test_a_failed_swap_leaves_the_old_bundle_and_nothing_beside(tmp_path, monkeypatch):
    dest = make_bundle(tmp_path / "dest", "old")

    def failing_exchange(first, second):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(bundle_writer, "exchange_paths", failing_exchange)
    with pytest.raises(OSError, match="No space left"):
        with write_bundle(dest) as folder:
            make_bundle(folder, "new")
    assert tree(dest) == {"manifest.json": "old", "detail/0/0_0.tsd": "old"}
    assert [p.name for p in tmp_path.iterdir()] == ["dest"]


def test_a_job_swaps_the_old_bundle_into_its_staging_folder(tmp_path, monkeypatch):
    collection = tmp_path / "collection"
    dest = make_bundle(collection / "obj", "old")
    staging = staging_dir(collection, 4)
    staged = make_bundle(staging / "obj", "new")
    swaps = []
    real_exchange = bundle_writer.exchange_paths

    def watching_exchange(first, second):
        swaps.append((Path(first), Path(second)))
        return real_exchange(first, second)

    monkeypatch.setattr(bundle_writer, "exchange_paths", watching_exchange)
    publish_bundle(staged, dest)
    assert swaps == [(staged, dest)]  # the old bundle went to the job's staging folder
    assert tree(dest) == {"manifest.json": "new", "detail/0/0_0.tsd": "new"}
    assert sorted(p.name for p in collection.iterdir()) == [".tessera", "obj"]
    assert list(staging.iterdir()) == []


#: a writer killed (SIGKILL) at one step; argv: destination, kill point, "fallback"|"swap"
KILLED_WRITER = r"""
import os, shutil, signal, sys
from pathlib import Path
from fitter.fitting import bundle as writer

destination, point, mode = Path(sys.argv[1]), sys.argv[2], sys.argv[3]
if mode == "fallback":
    writer.RENAMEAT2 = None

def die():
    os.kill(os.getpid(), signal.SIGKILL)

def after(function, name):
    def wrapped(*args, **kwargs):
        result = function(*args, **kwargs)
        if point == name:
            die()
        return result
    return wrapped

renames = []
real_rename = os.rename
def rename(src, dst):
    real_rename(src, dst)
    renames.append(dst)
    if point == f"rename-{len(renames)}":
        die()

writer.os.rename = rename
writer.sync_tree = after(writer.sync_tree, "synced")
writer.exchange_paths = after(writer.exchange_paths, "swapped")
real_rmtree = shutil.rmtree
def rmtree(path, *args, **kwargs):
    if point == "removing":  # half of the old bundle removed, then killed
        os.remove(next(Path(path).rglob("manifest.json")))
        die()
    real_rmtree(path, *args, **kwargs)
writer.shutil.rmtree = rmtree
with writer.write_bundle(destination) as folder:
    (folder / "detail" / "0").mkdir(parents=True)
    (folder / "manifest.json").write_text("new")
    (folder / "detail" / "0" / "0_0.tsd").write_text("new")
    if point == "writing":
        die()
"""


def run_killed_writer(dest: Path, point: str, mode: str) -> None:
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", KILLED_WRITER, str(dest), point, mode],
                          cwd=Path(__file__).resolve().parent.parent, capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == -9, (point, mode, done.returncode, done.stderr)


@pytest.mark.parametrize("mode,point", [
    ("swap", "writing"), ("swap", "synced"), ("swap", "swapped"), ("swap", "removing"),
    ("fallback", "writing"), ("fallback", "rename-1"), ("fallback", "rename-2"),
    ("fallback", "removing")])
def test_a_writer_killed_at_any_step_leaves_a_bundle_and_the_next_write_cleans_up(
        tmp_path, mode, point):
    dest = make_bundle(tmp_path / "dest", "old")
    run_killed_writer(dest, point, mode)
    left = sorted(p.name for p in tmp_path.iterdir() if p.name != "dest")
    assert left and all(name.startswith(".dest.") for name in left)  # the kill left these
    if (mode, point) == ("fallback", "rename-1"):
        # the one window of the two renames: the old bundle parked whole, dest missing
        assert not dest.exists() and any(name.startswith(".dest.old.") for name in left)
    else:
        assert tree(dest)["manifest.json"] in ("old", "new")  # a whole bundle, old or new
        assert set(tree(dest)) == {"manifest.json", "detail/0/0_0.tsd"}
    expected = "new" if point in ("swapped", "rename-2", "removing") else "old"
    with write_bundle(dest) as folder:
        # the next write first removed the leftovers and put a parked bundle back
        assert tree(dest) == {"manifest.json": expected, "detail/0/0_0.tsd": expected}
        assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["dest", folder.name])
        make_bundle(folder, "next")
    assert tree(dest) == {"manifest.json": "next", "detail/0/0_0.tsd": "next"}
    assert [p.name for p in tmp_path.iterdir()] == ["dest"]


def test_a_concurrent_writer_s_folder_is_kept_and_only_ours_are_removed(tmp_path):
    import subprocess
    import sys

    dest = make_bundle(tmp_path / "dest", "old")
    (tmp_path / ".other.abcdefgh").mkdir()  # another destination's temporary
    (tmp_path / ".dest.not-ours-pattern").mkdir()  # not a name this writer makes
    live = subprocess.Popen(  # a fit to the same place, still writing
        [sys.executable, "-c", "import sys\nfrom fitter.fitting.bundle import write_bundle\n"
         "with write_bundle(sys.argv[1]) as folder:\n"
         "    print(folder.name, flush=True)\n    sys.stdin.read()\n"
         "    raise SystemExit(3)\n", str(dest)],
        cwd=Path(__file__).resolve().parent.parent, stdin=subprocess.PIPE,
        stdout=subprocess.PIPE, text=True)
    try:
        live_folder = live.stdout.readline().strip()
        run_killed_writer(dest, "writing", "swap")  # a killed fit: a stale folder
        stale = {p.name for p in tmp_path.iterdir()} - {"dest", live_folder, ".other.abcdefgh",
                                                        ".dest.not-ours-pattern"}
        assert len(stale) == 1
        with write_bundle(dest) as folder:
            make_bundle(folder, "new")
            names = {p.name for p in tmp_path.iterdir()}
            assert live_folder in names and not stale & names  # the live one is kept
    finally:
        live.communicate("", timeout=30)
    assert live.returncode == 3  # its block failed on purpose: its folder removed by itself
    assert sorted(p.name for p in tmp_path.iterdir()) == [".dest.not-ours-pattern",
                                                          ".other.abcdefgh", "dest"]
    assert tree(dest)["manifest.json"] == "new"
