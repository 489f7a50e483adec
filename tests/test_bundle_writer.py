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


def test_an_old_bundle_is_replaced_and_removed_only_after(tmp_path, monkeypatch):
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


def test_a_failed_second_rename_puts_the_old_bundle_back(tmp_path, monkeypatch):
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
        tmp_path, monkeypatch):
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
