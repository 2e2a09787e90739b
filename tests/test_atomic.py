"""Atomic directory writes: all or nothing, previous output kept on failure, foreign data never replaced,
leftovers of killed writers tidied by the next write."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from data.atomic import MANIFEST, atomic_directory, check_output, manifest_owner, replace_file
from pipelines.config import REPO_ROOT

FIXTURE_JOINTS = Path(__file__).parent / "fixtures" / "humanml3d" / "new_joints_012314.npy"


def snapshot(directory: Path) -> dict[str, tuple[str, bytes, int]]:
    """Relative path -> (kind, bytes, mtime_ns) of ``directory`` and everything below it."""
    entries = {".": ("dir", b"", directory.stat().st_mtime_ns)}
    for path in sorted(directory.rglob("*")):
        kind = "dir" if path.is_dir() else "file"
        entries[str(path.relative_to(directory))] = (kind, b"" if path.is_dir() else path.read_bytes(),
                                                    path.stat().st_mtime_ns)
    return entries


def write_output(final: Path, owner: str, text: str = "old") -> None:
    """A previous output of ``owner``: data.txt and sub/raw.bin."""
    with atomic_directory(final, owner=owner) as tmp:
        (tmp / "data.txt").write_text(text)
        (tmp / "sub").mkdir()
        (tmp / "sub" / "raw.bin").write_bytes(bytes(range(256)))


def foreign_directory(final: Path) -> Path:
    """A user's directory: files, a subfolder and a hidden file, none of them ours."""
    final.mkdir()
    (final / "notes.txt").write_text("my notes")
    (final / ".hidden").write_bytes(b"\x00\x01")
    (final / "new_joints").mkdir()
    np.save(final / "new_joints" / "000001.npy", np.arange(12.0))
    return final


# --- writing and replacing our own output ------------------------------------------------------


def test_success_replaces_previous_output_and_leaves_no_temp(tmp_path):
    final = tmp_path / "out"
    write_output(final, "stage")
    with atomic_directory(final, owner="stage") as tmp:
        (tmp / "new.txt").write_text("new")
    assert sorted(p.name for p in final.iterdir()) == [MANIFEST, "new.txt"]
    assert json.loads((final / MANIFEST).read_text()) == {"format": 1, "owner": "stage"}
    assert [p.name for p in tmp_path.iterdir()] == ["out"]
    umask = os.umask(0)
    os.umask(umask)
    assert final.stat().st_mode & 0o777 == 0o777 & ~umask


def test_empty_directory_is_replaced(tmp_path):
    final = tmp_path / "out"
    final.mkdir()
    with atomic_directory(final, owner="stage") as tmp:
        (tmp / "new.txt").write_text("new")
    assert (final / "new.txt").read_text() == "new" and manifest_owner(final) == "stage"
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_failure_keeps_previous_output_and_removes_temp(tmp_path):
    final = tmp_path / "out"
    write_output(final, "stage")
    before = snapshot(final)
    with pytest.raises(RuntimeError), atomic_directory(final, owner="stage") as tmp:
        (tmp / "half.txt").write_text("half")
        raise RuntimeError("interrupted")
    assert snapshot(final) == before
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_failed_rename_restores_previous_output(tmp_path, monkeypatch):
    final = tmp_path / "out"
    write_output(final, "stage")
    before = snapshot(final)
    real_rename = Path.rename

    def flaky(self, target):
        if self.name.startswith(".out.tmp-"):
            raise OSError("disk gone")
        return real_rename(self, target)

    monkeypatch.setattr(Path, "rename", flaky)
    with pytest.raises(OSError), atomic_directory(final, owner="stage") as tmp:
        (tmp / "new.txt").write_text("new")
    assert snapshot(final) == before
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_previous_output_that_cannot_be_removed_is_reported(tmp_path, monkeypatch):
    final = tmp_path / "out"
    final.mkdir()
    monkeypatch.setattr(shutil, "rmtree", lambda path, ignore_errors=False: None)
    with pytest.warns(UserWarning, match="could not remove the previous out"), \
            atomic_directory(final, owner="stage") as tmp:
        (tmp / "new.txt").write_text("new")
    assert (final / "new.txt").read_text() == "new"


def test_nested_writer_leaves_the_outer_owner(tmp_path):
    """make_dataset writes through write_dataset into its own temporary directory."""
    final = tmp_path / "dataset"
    with atomic_directory(final, owner="make_dataset") as outer:
        with atomic_directory(outer, owner="write_dataset") as inner:
            (inner / "train.txt").write_text("a\n")
        assert manifest_owner(outer) == "write_dataset"
        (outer / "stats.json").write_text("{}")
    assert manifest_owner(final) == "make_dataset"
    assert sorted(p.name for p in final.iterdir()) == [MANIFEST, "stats.json", "train.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["dataset"]


# --- refusing what is not ours -----------------------------------------------------------------


def _refused(final: Path, owner: str) -> str:
    """The ValueError message of writing ``final`` as ``owner``; asserts the caller's block never ran."""
    ran = False
    with pytest.raises(ValueError) as info, atomic_directory(final, owner=owner):
        ran = True
    assert not ran, "the refusal must come before the caller's work"
    return str(info.value)


def test_foreign_directory_is_refused_and_left_byte_identical(tmp_path):
    final = foreign_directory(tmp_path / "hml")
    before = snapshot(final)
    assert _refused(final, "extract_features") == (
        f"refusing to replace {final}: it is a directory that extract_features did not write "
        f"(no {MANIFEST} inside); move it away or choose another output path")
    assert snapshot(final) == before
    assert [p.name for p in tmp_path.iterdir()] == ["hml"]


def test_unreadable_manifest_counts_as_foreign(tmp_path):
    final = tmp_path / "out"
    final.mkdir()
    (final / MANIFEST).write_text("{not json")
    before = snapshot(final)
    assert "did not write" in _refused(final, "stage")
    assert snapshot(final) == before


def test_file_at_the_path_is_refused_and_unchanged(tmp_path):
    final = tmp_path / "features"
    final.write_bytes(b"precious\x00bytes")
    mtime = final.stat().st_mtime_ns
    assert _refused(final, "extract_features") == (
        f"refusing to replace {final}: it is a file; move it away or choose another output path")
    assert final.read_bytes() == b"precious\x00bytes" and final.stat().st_mtime_ns == mtime
    assert [p.name for p in tmp_path.iterdir()] == ["features"]


def test_a_file_where_a_folder_above_should_be_is_refused_before_any_work(tmp_path):
    """``artifacts/eval`` a file: the stage that writes ``artifacts/eval/real`` stops at its check, not with a
    traceback once its work is done."""
    (tmp_path / "eval").write_text("not a folder")
    assert _refused(tmp_path / "eval" / "real", "eval_real") == (
        f"refusing to replace {tmp_path / 'eval' / 'real'}: {tmp_path / 'eval'} is a file, not a directory; "
        "move it away or choose another output path")
    with pytest.raises(ValueError, match="is a file, not a directory"):
        check_output(tmp_path / "eval" / "real" / "deeper", owner="eval_real")


def test_symbolic_link_is_refused(tmp_path):
    target = tmp_path / "target"
    write_output(target, "stage")
    before = snapshot(target)
    (tmp_path / "out").symlink_to(target)
    assert "it is a symbolic link" in _refused(tmp_path / "out", "stage")
    assert (tmp_path / "out").readlink() == target and snapshot(target) == before


def test_another_stages_output_is_refused(tmp_path):
    final = tmp_path / "out"
    write_output(final, "make_dataset")
    before = snapshot(final)
    assert _refused(final, "extract_features") == (
        f"refusing to replace {final}: it holds the output of make_dataset, not of extract_features; "
        "move it away or choose another output path")
    assert snapshot(final) == before


def test_make_dataset_refuses_a_real_dataset_before_generating(tmp_path, monkeypatch):
    """data.root pointed at the user's HumanML3D copy: make_dataset must not touch it."""
    from data.synthetic import SyntheticConfig
    from stages import make_dataset

    def no_work(*args, **kwargs):
        raise AssertionError("generation started")

    final = foreign_directory(tmp_path / "HumanML3D")
    before = snapshot(final)
    monkeypatch.setattr(make_dataset, "generate", no_work)
    with pytest.raises(ValueError, match=rf"refusing to replace {final}: .* make_dataset did not write"):
        make_dataset.build_dataset(final, SyntheticConfig(num_motions=4, previews=0, workers=1), 1)
    assert snapshot(final) == before


def test_data_that_appears_during_the_work_is_not_replaced(tmp_path):
    final = tmp_path / "out"
    with pytest.raises(ValueError, match="did not write"), atomic_directory(final, owner="stage") as tmp:
        (tmp / "new.txt").write_text("new")
        foreign_directory(final)
    assert sorted(p.name for p in final.iterdir()) == [".hidden", "new_joints", "notes.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


# --- leftovers of killed writers -----------------------------------------------------------------

#: A writer of ``argv[1]`` (owner "stage") that SIGKILLs itself at the moment ``argv[2]`` names:
#: "write" inside the block, "swap" between the two renames, "cleanup" while removing the previous
#: copy; "wait" blocks on stdin inside the block instead.
WRITER = """
import os, shutil, signal, sys
from pathlib import Path
from data.atomic import atomic_directory

final, moment = Path(sys.argv[1]), sys.argv[2]

def die(*args, **kwargs):
    os.kill(os.getpid(), signal.SIGKILL)

if moment == "swap":
    real_rename = Path.rename
    Path.rename = lambda self, target: die() if Path(target) == final else real_rename(self, target)
with atomic_directory(final, owner="stage") as tmp:
    (tmp / "data.txt").write_text("new")
    if moment == "write":
        die()
    if moment == "wait":
        sys.stdin.readline()
    if moment == "cleanup":
        shutil.rmtree = die
"""


def _killed_writer(final: Path, moment: str) -> None:
    proc = subprocess.run([sys.executable, "-c", WRITER, str(final), moment], cwd=REPO_ROOT, timeout=60)
    assert proc.returncode == -signal.SIGKILL


def _siblings(final: Path, kind: str) -> list[Path]:
    return sorted(final.parent.glob(f".{final.name}.{kind}-*"))


def test_temp_of_a_killed_writer_is_removed_by_the_next_write(tmp_path):
    final = tmp_path / "out"
    write_output(final, "stage")
    _killed_writer(final, "write")
    assert len(_siblings(final, "tmp")) == 1 and (final / "data.txt").read_text() == "old"
    (tmp_path / ".out.tmp-notes").mkdir()  # not named like ours: left alone
    with atomic_directory(final, owner="stage") as tmp:
        (tmp / "data.txt").write_text("newer")
    assert sorted(p.name for p in tmp_path.iterdir()) == [".out.tmp-notes", "out"]
    assert (final / "data.txt").read_text() == "newer"


def test_temp_of_a_live_writer_is_left_alone(tmp_path):
    final = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(final), "wait"], cwd=REPO_ROOT,
                            stdin=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 60
        while not any((tmp / "data.txt").exists() for tmp in _siblings(final, "tmp")):
            assert time.monotonic() < deadline and proc.poll() is None, "the writer did not start"
            time.sleep(0.05)
        check_output(final, owner="stage")
        assert len(_siblings(final, "tmp")) == 1
    finally:
        proc.communicate(b"\n", timeout=60)
    assert proc.returncode == 0
    assert (final / "data.txt").read_text() == "new" and [p.name for p in tmp_path.iterdir()] == ["out"]


def test_kill_between_the_renames_restores_the_previous_output(tmp_path):
    final = tmp_path / "out"
    write_output(final, "stage")
    before = snapshot(final)
    _killed_writer(final, "swap")
    assert not final.exists() and len(_siblings(final, "old")) == 1 and len(_siblings(final, "tmp")) == 1
    with pytest.warns(UserWarning, match=rf"restored {final} from \.out\.old-.*interrupted write"):
        check_output(final, owner="stage")
    assert snapshot(final) == before
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_copy_left_by_a_killed_clean_up_is_removed(tmp_path):
    final = tmp_path / "out"
    write_output(final, "stage")
    _killed_writer(final, "cleanup")
    assert (final / "data.txt").read_text() == "new" and len(_siblings(final, "old")) == 1
    check_output(final, owner="stage")
    assert (final / "data.txt").read_text() == "new" and [p.name for p in tmp_path.iterdir()] == ["out"]


# --- readers ignore the manifest -----------------------------------------------------------------


def test_identical_writes_are_byte_identical_and_fingerprint_alike(tmp_path):
    from pipelines.identity import fingerprint

    write_output(tmp_path / "a", "stage")
    write_output(tmp_path / "b", "stage")
    assert {k: v[:2] for k, v in snapshot(tmp_path / "a").items()} == \
        {k: v[:2] for k, v in snapshot(tmp_path / "b").items()}
    assert fingerprint("data.atomic", [tmp_path / "a"]) == fingerprint("data.atomic", [tmp_path / "b"])


def test_dataset_reader_ignores_the_manifest(tmp_path):
    from data.humanml3d import Caption, read_split
    from data.humanml3d_writer import Clip, write_dataset
    from data.skeleton import HUMANML3D

    joints = np.load(FIXTURE_JOINTS)[:60].astype(np.float32)
    caption = Caption("a person walks", (("a", "DET"), ("person", "NOUN"), ("walk", "VERB")))
    write_dataset(tmp_path / "hml", [Clip("0001", [caption], joints=joints)], {"train": ["0001"]})
    assert manifest_owner(tmp_path / "hml") == "write_dataset"
    assert [item.item_id for item in read_split(tmp_path / "hml", "train", HUMANML3D).items] == ["0001"]


@pytest.mark.slow  # builds the session's small feature store
def test_feature_store_reads_an_output_with_a_manifest(small_store):
    from pipelines.feature_store import FeatureStore

    store = FeatureStore(REPO_ROOT / small_store["features"]["out"])
    assert manifest_owner(store.path) == "extract_features"
    assert store.feature_dim == 263 and len(store.split("train")) > 0


@pytest.mark.slow  # a stage process (imports torch)
def test_stage_refuses_a_foreign_output_directory(small_store, tmp_path):
    foreign = foreign_directory(tmp_path / "mine")
    before = snapshot(foreign)
    proc = subprocess.run(
        [sys.executable, "-m", "stages.extract_features", "scale=smoke", f"data.root={small_store['data']['root']}",
         f"features.out={foreign}", "features.workers=1"],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1
    assert proc.stderr.strip().splitlines() == [
        f"extract_features: refusing to replace {foreign.resolve()}: it is a directory that extract_features "
        f"did not write (no {MANIFEST} inside); move it away or choose another output path"]
    assert snapshot(foreign) == before
    assert [p.name for p in tmp_path.iterdir()] == ["mine"]


def test_replace_file_keeps_the_previous_file_when_the_write_fails(tmp_path):
    path = tmp_path / "report.md"
    replace_file(path, lambda tmp: tmp.write_text("first"))
    assert path.read_text() == "first"

    def half_then_fail(tmp: Path) -> None:
        tmp.write_text("half")
        raise RuntimeError("writer died")

    with pytest.raises(RuntimeError, match="writer died"):
        replace_file(path, half_then_fail)
    assert path.read_text() == "first" and [p.name for p in tmp_path.iterdir()] == ["report.md"]
