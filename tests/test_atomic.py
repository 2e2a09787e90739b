"""Atomic directory writes: all or nothing, previous output kept on failure."""

import os
import shutil
from pathlib import Path

import pytest

from data.atomic import atomic_directory


def test_success_replaces_previous_output_and_leaves_no_temp(tmp_path):
    final = tmp_path / "out"
    final.mkdir()
    (final / "old.txt").write_text("old")
    with atomic_directory(final) as tmp:
        (tmp / "new.txt").write_text("new")
    assert sorted(p.name for p in final.iterdir()) == ["new.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["out"]
    umask = os.umask(0)
    os.umask(umask)
    assert final.stat().st_mode & 0o777 == 0o777 & ~umask


def test_failure_keeps_previous_output_and_removes_temp(tmp_path):
    final = tmp_path / "out"
    final.mkdir()
    (final / "old.txt").write_text("old")
    with pytest.raises(RuntimeError), atomic_directory(final) as tmp:
        (tmp / "half.txt").write_text("half")
        raise RuntimeError("interrupted")
    assert (final / "old.txt").read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_failed_rename_restores_previous_output(tmp_path, monkeypatch):
    final = tmp_path / "out"
    final.mkdir()
    (final / "old.txt").write_text("old")
    real_rename = Path.rename

    def flaky(self, target):
        if self.name.startswith(".out.tmp-"):
            raise OSError("disk gone")
        return real_rename(self, target)

    monkeypatch.setattr(Path, "rename", flaky)
    with pytest.raises(OSError), atomic_directory(final) as tmp:
        (tmp / "new.txt").write_text("new")
    assert (final / "old.txt").read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_previous_output_that_cannot_be_removed_is_reported(tmp_path, monkeypatch):
    final = tmp_path / "out"
    final.mkdir()
    monkeypatch.setattr(shutil, "rmtree", lambda path, ignore_errors=False: None)
    with pytest.warns(UserWarning, match="could not remove the previous out"), atomic_directory(final) as tmp:
        (tmp / "new.txt").write_text("new")
    assert (final / "new.txt").read_text() == "new"
