"""Tests of the HumanML3D-layout reader and writer (data/humanml3d.py, data/humanml3d_writer.py)."""

from __future__ import annotations

import hashlib
import os
import pickle
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from data.atomic import MANIFEST
from data.humanml3d import (
    EMPTY_SPLIT,
    IMPLAUSIBLE,
    SHARED_ID,
    UNREADABLE,
    Caption,
    DatasetError,
    MotionItem,
    Problem,
    load_actions,
    read_captions,
    read_split,
    read_splits,
)
from data.humanml3d_writer import Clip, write_dataset
from data.skeleton import HUMANML3D, KIT, Skeleton

# --------------------------------------------------------------------------------------------
# Fixture helpers
# --------------------------------------------------------------------------------------------


def rest_pose(skeleton: Skeleton, scale: float = 1.0) -> np.ndarray:
    """(J, 3) rest pose of ``skeleton`` with every bone ``scale`` times its reference length."""
    offsets, rest = skeleton.offsets(), np.zeros((skeleton.joints_num, 3))
    for chain in skeleton.kinematic_chain:
        for parent, child in zip(chain[:-1], chain[1:], strict=True):
            rest[child] = rest[parent] + scale * offsets[child]
    return rest


def joints(n_frames: int, n_joints: int = 22, seed: int = 0) -> np.ndarray:
    """Random (T, J, 3) float32 joint positions with plausible bones: the rest pose of HumanML3D's
    (22 joints) or KIT's (21) skeleton, every joint jittered by 5 % of the longest bone."""
    skeleton = HUMANML3D if n_joints == 22 else KIT
    jitter = np.random.default_rng(seed).normal(scale=0.05 * skeleton.bone_lengths.max(), size=(n_frames, n_joints, 3))
    return (rest_pose(skeleton) + jitter).astype(np.float32)


def features(n_frames: int, n_joints: int = 22, seed: int = 0) -> np.ndarray:
    """Random (T, 12J-1) float32 features whose root height and root-relative joints (``ric``)
    are those of :func:`joints`, so that the bones they encode are plausible."""
    out = np.random.default_rng(seed).normal(size=(n_frames, 12 * n_joints - 1))
    pose = joints(n_frames, n_joints, seed).astype(np.float64)
    out[:, 3] = pose[:, 0, 1]
    out[:, 4 : 3 * n_joints + 1] = (pose[:, 1:] - pose[:, :1] * [1.0, 0.0, 1.0]).reshape(n_frames, -1)
    return out.astype(np.float32)


def cap(text: str = "a person walks forward", start: float = 0.0, end: float = 0.0) -> Caption:
    """A caption whose tokens are its words tagged OTHER ('walks' tagged VERB)."""
    tokens = tuple((w, "VERB" if w == "walks" else "OTHER") for w in text.split())
    return Caption(text, tokens, start, end)


def standard_clips() -> list[Clip]:
    """Four HumanML3D clips covering whole-clip captions, spans, features-only and actions."""
    return [
        Clip(
            "000001",
            [
                cap("a person walks forward"),
                cap("someone strolls ahead slowly"),
                cap("the man waves", 0.5, 2.75),  # frames [10, 55): kept
                cap("a short wave", 0.0, 1.0),  # frames [0, 20): filtered
            ],
            joints=joints(61, seed=1),
            action="walk",
        ),
        Clip("000002", [cap("a person jumps up")], joints=joints(81, seed=2), action="jump"),
        Clip("M000003", [cap("a person sits down")], features=features(50, seed=3)),
        Clip("000004", [cap("a person bows")], joints=joints(41, seed=4), features=features(45, seed=4)),
        Clip("000005", [cap("a person turns around")], joints=joints(51, seed=5)),
    ]


STANDARD_SPLITS = {"train": ["000001", "000002", "M000003"], "val": ["000004"], "test": ["000005"]}


@pytest.fixture
def dataset(tmp_path: Path) -> Path:
    """A valid dataset written by write_dataset."""
    root = tmp_path / "hml"
    write_dataset(root, standard_clips(), STANDARD_SPLITS)
    return root


def snapshot(directory: Path) -> dict[str, tuple[int, str]]:
    """Relative path -> (mtime_ns, sha1) of every file and folder below ``directory``."""
    out = {}
    for path in sorted(directory.rglob("*")):
        digest = hashlib.sha1(path.read_bytes()).hexdigest() if path.is_file() else "dir"
        out[str(path.relative_to(directory))] = (path.stat().st_mtime_ns, digest)
    return out


def save_npy(path: Path, arr: np.ndarray) -> None:
    """Overwrite a motion file with ``arr``."""
    np.save(path, arr)


def read_fails(root: Path, split: str = "train", skeleton: Skeleton = HUMANML3D, **kw: object) -> DatasetError:
    """Read a split expecting a DatasetError and return it."""
    with pytest.raises(DatasetError) as info:
        read_split(root, split, skeleton, **kw)
    return info.value


# --------------------------------------------------------------------------------------------
# Caption lines
# --------------------------------------------------------------------------------------------


def test_caption_line_round_trip() -> None:
    caption = Caption("a man walks/runs", (("a", "DET"), ("man", "NOUN"), ("walk/run", "VERB")), 1.5, 3.25)
    line = caption.to_line()
    assert line == "a man walks/runs#a/DET man/NOUN walk/run/VERB#1.5#3.25"
    assert Caption.from_line(line) == caption
    whole = Caption("a person jumps", (("a", "DET"), ("person", "NOUN"), ("jump", "VERB")))
    assert whole.to_line() == "a person jumps#a/DET person/NOUN jump/VERB#0.0#0.0"
    assert whole.is_whole_clip and not caption.is_whole_clip


def test_caption_from_line_reads_nan_as_zero_and_normalises() -> None:
    caption = Caption.from_line("  a man kicks#a/DET man/NOUN kick/VERB#nan#NaN \r\n")
    assert (caption.start, caption.end) == (0.0, 0.0)
    assert caption.text == "a man kicks"
    assert caption.tokens == (("a", "DET"), ("man", "NOUN"), ("kick", "VERB"))
    assert Caption.from_line("a man kicks##2#3").tokens == ()


@pytest.mark.parametrize(
    ("line", "reason"),
    [
        ("a man walks#a/DET#0.0", "expected 4 '#'-separated fields"),
        ("a man #walks#a/DET#0.0#0.0", "expected 4 '#'-separated fields"),
        ("a man walks#a/DET#zero#0.0", "start 'zero' is not a number"),
        ("a man walks#a/DET#0.0#1,5", "end '1,5' is not a number"),
        ("a man walks#a/DET#2.0#1.0", "start 2.0 > end 1.0"),
        ("a man walks#a/DET#-1.0#1.0", "start -1.0 is not a finite non-negative time"),
        ("a man walks#a/DET#0.0#inf", "end inf is not a finite non-negative time"),
        ("a man walks#a/DET man#0.0#0.0", "token 'man' is not word/POS"),
        ("a man walks#a/DET man/#0.0#0.0", "token 'man/' is not word/POS"),
        ("  #a/DET#0.0#0.0", "empty caption"),
    ],
)
def test_caption_from_line_errors(line: str, reason: str) -> None:
    with pytest.raises(ValueError, match=reason):
        Caption.from_line(line)


@pytest.mark.parametrize(
    ("kwargs", "reason"),
    [
        ({"text": "a#b"}, "contains '#'"),
        ({"text": "two\nlines"}, "line break"),
        ({"tokens": (("a b", "DET"),)}, "invalid token"),
        ({"tokens": (("a", "D/T"),)}, "invalid token"),
        ({"tokens": (("a",),)}, "pair"),
        ({"start": float("nan")}, "finite"),
    ],
)
def test_caption_constructor_rejects_unwritable(kwargs: dict, reason: str) -> None:
    args = {"text": "a man", "tokens": (("a", "DET"),)} | kwargs
    with pytest.raises(ValueError, match=reason):
        Caption(**args)


# --------------------------------------------------------------------------------------------
# Round trip
# --------------------------------------------------------------------------------------------


def test_round_trip_joints_captions_spans_actions(dataset: Path) -> None:
    clips = {c.clip_id: c for c in standard_clips()}
    data = read_split(dataset, "train", HUMANML3D)

    assert data.split == "train" and data.skipped == []
    assert list(data.clips) == ["000001", "000002", "M000003"]
    np.testing.assert_array_equal(data.clips["000001"].joints, clips["000001"].joints)
    assert data.clips["000001"].features is None and data.clips["000001"].joints.dtype == np.float32
    np.testing.assert_array_equal(data.clips["M000003"].features, clips["M000003"].features)
    assert data.clips["M000003"].joints is None
    assert data.clips["000001"].length == 60 and data.clips["M000003"].length == 50

    whole_000001 = tuple(clips["000001"].captions[:2])
    assert data.items == [
        MotionItem("000001", "000001", whole_000001, 0, 60, "walk"),
        MotionItem("000001@10-55", "000001", (clips["000001"].captions[2],), 10, 55, "walk"),
        MotionItem("000002", "000002", tuple(clips["000002"].captions), 0, 80, "jump"),
        MotionItem("M000003", "M000003", tuple(clips["M000003"].captions), 0, 50, None),
    ]
    assert data.items[1].length == 45
    assert data.items[0].captions[1].tokens == (("someone", "OTHER"), ("strolls", "OTHER"), ("ahead", "OTHER"),
                                                ("slowly", "OTHER"))  # fmt: skip
    # the 1 s span is a standard filter, reported with its file
    assert len(data.filtered) == 1
    assert "000001.txt" in data.filtered[0].path and "length 20 < min_frames 40" in data.filtered[0].reason
    assert load_actions(dataset) == {"000001": "walk", "000002": "jump"}


def test_written_files_follow_humanml3d_layout(dataset: Path) -> None:
    assert (dataset / "train.txt").read_text() == "000001\n000002\nM000003\n"
    assert (dataset / "texts" / "000002.txt").read_text() == (
        "a person jumps up#a/OTHER person/OTHER jumps/OTHER up/OTHER#0.0#0.0\n"
    )
    assert (dataset / "actions.txt").read_text() == "000001,walk\n000002,jump\n"
    assert sorted(p.name for p in (dataset / "new_joints").iterdir()) == ["000001.npy", "000002.npy", "000004.npy",
                                                                         "000005.npy"]
    assert sorted(p.name for p in (dataset / "new_joint_vecs").iterdir()) == ["000004.npy", "M000003.npy"]
    assert np.load(dataset / "new_joints" / "000002.npy").dtype == np.float32


def test_no_actions_file_without_actions(tmp_path: Path) -> None:
    root = tmp_path / "d"
    write_dataset(root, [Clip("a1", [cap()], joints=joints(50))], {"train": ["a1"]})
    assert not (root / "actions.txt").exists()
    assert load_actions(root) == {}
    assert read_split(root, "train", HUMANML3D).items[0].action is None


def test_source_selection(dataset: Path) -> None:
    auto = read_split(dataset, "val", HUMANML3D)  # both files exist: joints preferred
    assert auto.clips["000004"].features is None and auto.items[0].end == 40
    feats = read_split(dataset, "val", HUMANML3D, source="features")
    assert feats.clips["000004"].joints is None and feats.items[0].end == 45
    only_joints = read_split(dataset, "val", HUMANML3D, source="joints")
    assert only_joints.clips["000004"].joints.shape == (41, 22, 3)
    # train has a features-only clip: "joints" reports it missing, "features" the joints-only ones
    err = read_fails(dataset, source="joints")
    assert [p.path for p in err.problems] == [str(dataset / "new_joints" / "M000003.npy")]
    err = read_fails(dataset, source="features")
    assert len(err.problems) == 2 and all("no motion file" in p.reason for p in err.problems)


def test_read_splits(dataset: Path) -> None:
    data = read_splits(dataset, HUMANML3D)
    assert sorted(data) == ["test", "train", "val"]
    assert [i.item_id for i in data["test"].items] == ["000005"]
    (dataset / "val.txt").unlink()
    save_npy(dataset / "new_joints" / "000002.npy", joints(1))
    err = pytest.raises(DatasetError, read_splits, dataset, HUMANML3D).value
    paths = [p.path for p in err.problems]
    assert paths == [str(dataset / "new_joints" / "000002.npy"), str(dataset / "val.txt")]


# --------------------------------------------------------------------------------------------
# Atomic write
# --------------------------------------------------------------------------------------------


def nan_among_good() -> Iterator[Clip]:
    """Good clips with one NaN clip in the middle."""
    bad = joints(50, seed=9)
    bad[7, 3, 1] = np.nan
    yield Clip("g1", [cap()], joints=joints(50))
    yield Clip("bad", [cap()], joints=bad)
    yield Clip("g2", [cap()], joints=joints(50))


def test_failed_write_leaves_nothing(tmp_path: Path) -> None:
    with pytest.raises(DatasetError) as info:
        write_dataset(tmp_path / "out", nan_among_good(), {"train": ["g1", "bad", "g2"]})
    assert info.value.problems == [Problem("clip 'bad'", "joints: 1 non-finite values (NaN/inf), first in frame 7")]
    assert list(tmp_path.iterdir()) == []


def test_exception_mid_write_leaves_nothing(tmp_path: Path) -> None:
    def clips() -> Iterator[Clip]:
        yield Clip("g1", [cap()], joints=joints(50))
        raise RuntimeError("generator crashed")

    with pytest.raises(RuntimeError, match="generator crashed"):
        write_dataset(tmp_path / "out", clips(), {"train": ["g1"]})
    assert list(tmp_path.iterdir()) == []


def test_failed_write_keeps_existing_root(dataset: Path) -> None:
    before = snapshot(dataset)
    with pytest.raises(DatasetError):
        write_dataset(dataset, nan_among_good(), {"train": ["g1"]})
    assert snapshot(dataset) == before
    assert [p.name for p in dataset.parent.iterdir()] == ["hml"]


def test_successful_write_replaces_existing_root(dataset: Path) -> None:
    write_dataset(dataset, [Clip("new1", [cap("a person runs")], joints=joints(45))], {"test": ["new1"]})
    assert sorted(p.name for p in dataset.iterdir()) == [MANIFEST, "new_joint_vecs", "new_joints", "test.txt", "texts"]
    assert [i.item_id for i in read_split(dataset, "test", HUMANML3D).items] == ["new1"]
    assert [p.name for p in dataset.parent.iterdir()] == ["hml"]


def test_failed_final_rename_restores_existing_root(dataset: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    before = snapshot(dataset)
    real_rename = os.rename

    def rename(src: Path, dst: Path) -> None:
        if Path(src).name.startswith(".hml.tmp-"):
            raise OSError("disk full")
        real_rename(src, dst)

    monkeypatch.setattr(os, "rename", rename)
    with pytest.raises(OSError, match="disk full"):
        write_dataset(dataset, [good_clip()], {"train": ["c1"]})
    assert snapshot(dataset) == before
    assert [p.name for p in dataset.parent.iterdir()] == ["hml"]


def good_clip(clip_id: str = "c1", **kw: object) -> Clip:
    """A valid clip, with fields overridden by ``kw``."""
    args = {"captions": [cap()], "joints": joints(50)} | kw
    return Clip(clip_id, **args)


@pytest.mark.parametrize(
    ("clips", "splits", "expected"),
    [
        ([good_clip("a/b")], {}, "invalid clip id 'a/b'"),
        ([good_clip("..")], {}, "invalid clip id '..'"),
        ([good_clip("x@1")], {}, "invalid clip id 'x@1'"),
        ([good_clip(), good_clip()], {}, "clip 'c1': duplicate clip id"),
        ([good_clip(captions=[])], {}, "clip 'c1': no captions"),
        ([good_clip(captions=["a man walks"])], {}, "captions must be Caption objects"),
        ([good_clip(joints=None)], {}, "neither joints nor features"),
        ([good_clip(joints=joints(50)[:, :, :2])], {}, "joints: wrong shape (50, 22, 2)"),
        ([good_clip(joints=joints(1))], {}, "too short to compute features"),
        ([good_clip(features=np.full((5, 263), np.inf, np.float32))], {}, "features: 1315 non-finite"),
        ([good_clip(features=features(5)[:, :200])], {}, "features: wrong shape (5, 200)"),
        ([good_clip(joints=np.full((4, 22, 3), 1e300))], {}, "non-finite"),  # overflows float32
        ([good_clip(), good_clip("c2", joints=joints(50, 21))], {}, "21 joints, other clips have 22"),
        ([good_clip(action="")], {}, "invalid action label ''"),
        ([good_clip()], {"train": ["c1", "zz"]}, "train.txt: id 'zz' is not among the clips"),
        ([good_clip()], {"val": ["c1", "c1"]}, "val.txt: id 'c1' listed 2 times"),
        ([good_clip()], {"train": ["c1"], "val": ["c1"]}, "val.txt: id 'c1' is also in train.txt"),  # was written
    ],
)
def test_write_validation(tmp_path: Path, clips: list[Clip], splits: dict, expected: str) -> None:
    with pytest.raises(DatasetError) as info:
        write_dataset(tmp_path / "out", clips, splits)
    assert expected in str(info.value)
    assert list(tmp_path.iterdir()) == []


def test_write_validation_lists_every_problem_and_checks_skeleton(tmp_path: Path) -> None:
    clips = [good_clip("a/b"), good_clip("ok", joints=joints(50, 21)), good_clip("e", captions=[])]
    with pytest.raises(DatasetError) as info:
        write_dataset(tmp_path / "out", clips, {"train": ["ok"]}, skeleton=HUMANML3D)
    assert [p.path for p in info.value.problems] == ["clip 'a/b'", "clip 'ok'", "clip 'e'"]
    assert "wrong shape (50, 21, 3), expected (T, 22, 3)" in str(info.value)


def test_write_rejects_bad_split_name_and_file_root(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="invalid split name"):
        write_dataset(tmp_path / "out", [good_clip()], {"../train": ["c1"]})
    (tmp_path / "file").write_text("x")
    with pytest.raises(NotADirectoryError):
        write_dataset(tmp_path / "file", [good_clip()], {"train": ["c1"]})


# --------------------------------------------------------------------------------------------
# Bad input on read: each case names the file and the reason
# --------------------------------------------------------------------------------------------


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _append_bytes(path: Path, data: bytes) -> None:
    path.write_bytes(path.read_bytes() + data)


def _huge_header(path: Path) -> None:
    """A header that declares a billion frames over 64 bytes of data: numpy allocated 246 GiB before reading."""
    with open(path, "wb") as f:
        np.lib.format.write_array_header_1_0(f, {"descr": "<f4", "fortran_order": False, "shape": (10**9, 22, 3)})
        f.write(bytes(64))


def _with_nan(path: Path) -> None:
    arr = np.load(path)
    arr[3, 0, 0] = np.nan
    save_npy(path, arr)


def _append_text(path: Path, text: str) -> None:
    path.write_text(path.read_text() + text)


Corrupter = Callable[[Path], None]
J2 = "new_joints/000002.npy"
T2 = "texts/000002.txt"

BAD_INPUT: list[tuple[str, Corrupter, str, str]] = [
    ("missing motion", lambda r: (r / J2).unlink(), J2, "no motion file for split id"),
    ("truncated npy", lambda r: _truncate(r / J2), J2, "unreadable or corrupt .npy"),
    ("empty npy", lambda r: (r / J2).write_bytes(b""), J2, "reading magic string"),
    ("huge header", lambda r: _huge_header(r / J2), J2,
     "header declares 264000000000 bytes of data (shape (1000000000, 22, 3), float32), the file holds 64"),
    ("trailing bytes", lambda r: _append_bytes(r / J2, b"junk"), J2, "trailing bytes after the array data"),
    ("not npy", lambda r: (r / J2).write_bytes(b"hello, world" * 20), J2, "magic string is not correct"),
    ("pickled object", lambda r: np.save(r / J2, np.array([{}]), allow_pickle=True), J2, "Object arrays"),
    ("wrong J", lambda r: save_npy(r / J2, joints(80, 21)), J2, "wrong shape (80, 21, 3), expected (T, 22, 3)"),
    ("wrong ndim", lambda r: save_npy(r / J2, joints(80).reshape(80, 66)), J2, "wrong shape (80, 66)"),
    ("string dtype", lambda r: save_npy(r / J2, np.full((80, 22, 3), "a")), J2, "not a real number type"),
    ("nan", lambda r: _with_nan(r / J2), J2, "1 non-finite values (NaN/inf), first in frame 3"),
    ("inf", lambda r: save_npy(r / J2, np.full((80, 22, 3), -np.inf)), J2, "5280 non-finite values"),
    ("one frame", lambda r: save_npy(r / J2, joints(1)), J2, "1 frame(s): too short to compute features"),
    ("missing text", lambda r: (r / T2).unlink(), T2, "no caption file for this motion"),
    ("blank text", lambda r: (r / T2).write_text("\n  \n"), T2, "no caption lines"),
    ("field count", lambda r: _append_text(r / T2, "a man#a/DET#0.0\n"), T2 + ":2", "expected 4 '#'"),
    ("bad float", lambda r: _append_text(r / T2, "a man#a/DET#0.0#x1\n"), T2 + ":2", "end 'x1' is not a number"),
    ("start > end", lambda r: _append_text(r / T2, "a man#a/DET#3#1\n"), T2 + ":2", "start 3.0 > end 1.0"),
    ("bad token", lambda r: _append_text(r / T2, "a man#a/DET man#0#0\n"), T2 + ":2", "'man' is not word/POS"),
    ("empty caption", lambda r: _append_text(r / T2, "#a/DET#0#0\n"), T2 + ":2", "empty caption"),
    ("not utf-8", lambda r: (r / T2).write_bytes(b"caf\xe9 man#caf/NOUN#0#0\n"), T2, "not UTF-8 text (byte 3"),
    ("missing split", lambda r: (r / "train.txt").unlink(), "train.txt", "split file not found"),
    ("bad split id", lambda r: _append_text(r / "train.txt", "../etc\n"), "train.txt:4", "invalid clip id"),
    ("dup split id", lambda r: _append_text(r / "train.txt", "000001\n"), "train.txt:4", "duplicate id '000001'"),
    ("actions no comma", lambda r: _append_text(r / "actions.txt", "000009 run\n"), "actions.txt:3", "'id,label'"),
    ("actions no label", lambda r: _append_text(r / "actions.txt", "000009, \n"), "actions.txt:3", "empty action"),
    ("actions dup", lambda r: _append_text(r / "actions.txt", "000001,run\n"), "actions.txt:3", "duplicate id"),
    ("actions bad id", lambda r: _append_text(r / "actions.txt", "a/b,run\n"), "actions.txt:3", "invalid clip id"),
    ("actions not utf-8", lambda r: (r / "actions.txt").write_bytes(b"000001,\xff\n"), "actions.txt", "not UTF-8"),
]


@pytest.mark.parametrize(("corrupt", "path", "reason"), [c[1:] for c in BAD_INPUT], ids=[c[0] for c in BAD_INPUT])
def test_bad_input_raises_naming_file_and_reason(dataset: Path, corrupt: Corrupter, path: str, reason: str) -> None:
    corrupt(dataset)
    err = read_fails(dataset)
    assert len(err.problems) == 1, str(err)
    assert err.problems[0].path == str(dataset / path)
    assert reason in err.problems[0].reason
    assert f"{dataset / path}: " in str(err) and reason in str(err)


def test_wrong_feature_dim(dataset: Path) -> None:
    save_npy(dataset / "new_joint_vecs" / "M000003.npy", features(50)[:, :262])
    err = read_fails(dataset)
    assert str(err.problems[0]) == f"{dataset}/new_joint_vecs/M000003.npy: wrong shape (50, 262), expected (T, 263)"


def test_fail_mode_collects_every_problem(dataset: Path) -> None:
    _truncate(dataset / J2)
    _append_text(dataset / T2, "bad line\n")
    _append_text(dataset / "texts" / "000001.txt", "x#a/DET#2#1\n")
    (dataset / "new_joint_vecs" / "M000003.npy").unlink()
    err = read_fails(dataset)
    assert [p.path for p in err.problems] == [
        str(dataset / "texts/000001.txt:5"),
        str(dataset / J2),
        str(dataset / "texts/000002.txt:2"),
        str(dataset / "new_joints/M000003.npy"),
    ]
    assert str(err).startswith(f"4 problem(s) in split 'train' of {dataset}:\n  - ")
    assert pickle.loads(pickle.dumps(err)).problems == err.problems  # crosses Ray workers


def test_skip_mode_reports_skipped_clips(dataset: Path) -> None:
    _with_nan(dataset / J2)
    _append_text(dataset / T2, "no fields\n")
    _append_text(dataset / "train.txt", "000001\n")
    data = read_split(dataset, "train", HUMANML3D, on_error="skip")
    assert list(data.clips) == ["000001", "M000003"]
    assert [i.item_id for i in data.items] == ["000001", "000001@10-55", "M000003"]
    assert [p.path for p in data.skipped] == [str(dataset / "train.txt:4"), str(dataset / J2),
                                              str(dataset / "texts/000002.txt:2")]  # fmt: skip
    assert "non-finite" in data.skipped[1].reason


def test_skip_mode_still_fails_on_dataset_level_problems(dataset: Path) -> None:
    _append_text(dataset / "actions.txt", "broken\n")
    assert "actions.txt:3" in str(read_fails(dataset, on_error="skip"))
    (dataset / "train.txt").unlink()
    assert "split file not found" in str(read_fails(dataset, on_error="skip"))


def test_bad_options(dataset: Path) -> None:
    with pytest.raises(ValueError, match="unknown on_error 'ignore'"):
        read_split(dataset, "train", HUMANML3D, on_error="ignore")
    with pytest.raises(ValueError, match="unknown source 'both'"):
        read_split(dataset, "train", HUMANML3D, source="both")
    with pytest.raises(ValueError, match="invalid split name"):
        read_split(dataset, "../train", HUMANML3D)
    with pytest.raises(ValueError, match="min_frames < max_frames"):
        read_split(dataset, "train", HUMANML3D, min_frames=50, max_frames=50)


def test_reading_writes_nothing(dataset: Path) -> None:
    _with_nan(dataset / J2)
    _append_text(dataset / "actions.txt", "\n")
    before = snapshot(dataset.parent)
    read_split(dataset, "train", HUMANML3D, on_error="skip")
    read_fails(dataset)
    read_split(dataset, "val", HUMANML3D, source="features")
    assert snapshot(dataset.parent) == before


def test_utf8_captions_and_bom(tmp_path: Path) -> None:
    root = tmp_path / "d"
    caption = Caption("a person does a pirouette — café style", (("pirouette", "NOUN"), ("café", "NOUN")))
    write_dataset(root, [Clip("c", [caption], joints=joints(50))], {"train": ["c"]})
    assert read_split(root, "train", HUMANML3D).items[0].captions == (caption,)
    text = root / "texts" / "c.txt"
    text.write_bytes(b"\xef\xbb\xbf" + text.read_bytes())
    assert read_captions(text) == [caption]


# --------------------------------------------------------------------------------------------
# Length filters
# --------------------------------------------------------------------------------------------


def _single(tmp_path: Path, clip: Clip) -> Path:
    root = tmp_path / "d"
    write_dataset(root, [clip], {"train": [clip.clip_id]})
    return root


@pytest.mark.parametrize(
    ("kind", "n_frames", "kept"),
    [
        ("joints", 40, False),  # 39 feature frames
        ("joints", 41, True),  # 40
        ("joints", 200, True),  # 199
        ("joints", 201, False),  # 200
        ("features", 39, False),
        ("features", 40, True),
        ("features", 199, True),
        ("features", 200, False),
    ],
)
def test_clip_length_filter(tmp_path: Path, kind: str, n_frames: int, kept: bool) -> None:
    arr = joints(n_frames) if kind == "joints" else features(n_frames)
    root = _single(tmp_path, Clip("c", [cap()], **{kind: arr}))
    data = read_split(root, "train", HUMANML3D)
    length = n_frames - 1 if kind == "joints" else n_frames
    assert [(i.start, i.end) for i in data.items] == ([(0, length)] if kept else [])
    assert list(data.clips) == (["c"] if kept else [])
    assert data.skipped == []
    if not kept:
        [problem] = data.filtered
        assert problem.path == str(root / f"new_{'joints' if kind == 'joints' else 'joint_vecs'}" / "c.npy")
        assert f"length {length}" in problem.reason


def test_span_items_and_filters(tmp_path: Path) -> None:
    captions = [
        cap("span forty", 1.0, 3.0),  # [20, 60): 40 kept
        cap("span thirty nine", 1.0, 2.975),  # [20, 59): 39 filtered (int truncation)
        cap("same span again", 1.0, 3.0),  # duplicate span -> distinct deterministic id
        cap("past the end", 3.0, 10.0),  # [60, 100) clamped to the 100-frame clip
        cap("starts past the end", 6.0, 9.0),  # empty after clamping: filtered
    ]
    root = _single(tmp_path, Clip("c", captions, features=features(100)))
    data = read_split(root, "train", HUMANML3D)
    assert [(i.item_id, i.start, i.end, i.captions[0].text) for i in data.items] == [
        ("c@20-60", 20, 60, "span forty"),
        ("c@20-60~2", 20, 60, "same span again"),
        ("c@60-100", 60, 100, "past the end"),
    ]
    assert all(len(i.captions) == 1 for i in data.items)  # no whole-clip item without a 0/0 caption
    assert [p.reason.split(": ")[1] for p in data.filtered] == ["length 39 < min_frames 40",
                                                                "starts at or after the clip's end (100 frames)"]
    assert [p.reason for p in data.cut] == ["span 3.0-10.0 s = frames [60, 200): cut to [60, 100) at the clip's end: "
                                            "'past the end'"]
    # custom bounds
    data = read_split(root, "train", HUMANML3D, min_frames=39, max_frames=101)
    assert [i.item_id for i in data.items] == ["c@20-60", "c@20-59", "c@20-60~2", "c@60-100"]


def test_clip_without_usable_item_is_reported(tmp_path: Path) -> None:
    root = _single(tmp_path, Clip("c", [cap("short", 0.0, 1.0)], features=features(100)))
    data = read_split(root, "train", HUMANML3D)
    assert data.items == [] and data.clips == {}
    assert [p.reason for p in data.filtered][-1].startswith("no item left")


# --------------------------------------------------------------------------------------------
# KIT
# --------------------------------------------------------------------------------------------


def test_kit_skeleton(tmp_path: Path) -> None:
    clips = [
        Clip("k1", [cap(), cap("then jumps", 2.0, 4.0)], joints=joints(25, 21)),  # 24 frames, span [25, 50)
        Clip("k2", [cap()], joints=joints(24, 21)),  # 23 frames: filtered
        Clip("k3", [cap()], features=features(30, 21)),
    ]
    root = tmp_path / "kit"
    write_dataset(root, clips, {"train": ["k1", "k2", "k3"]}, skeleton=KIT)
    data = read_split(root, "train", KIT)
    assert [(i.item_id, i.start, i.end) for i in data.items] == [("k1", 0, 24), ("k3", 0, 30)]
    assert [p.reason for p in data.filtered] == [
        "span 2.0-4.0 s = frames [25, 50): starts at or after the clip's end (24 frames): 'then jumps'",
        "clip length 23 < min_frames 24 (feature frames)",
    ]
    assert data.clips["k3"].features.shape == (30, 251)
    err = read_fails(root, skeleton=HUMANML3D)  # 21-joint files are wrong for HumanML3D
    assert "wrong shape (25, 21, 3), expected (T, 22, 3)" in str(err) and "expected (T, 263)" in str(err)


def test_kit_span_uses_kit_fps(tmp_path: Path) -> None:
    root = _single(tmp_path, Clip("k", [cap("span", 1.0, 3.0)], features=features(60, 21)))
    [item] = read_split(root, "train", KIT).items
    assert (item.item_id, item.start, item.end) == ("k@12-37", 12, 37)


# --------------------------------------------------------------------------------------------
# Dataset integrity: shared ids, empty splits, implausible skeletons
# --------------------------------------------------------------------------------------------


def test_id_in_two_splits_fails_naming_both_lines(dataset: Path) -> None:
    _append_text(dataset / "test.txt", "000002\n")  # train.txt line 2
    err = pytest.raises(DatasetError, read_splits, dataset, HUMANML3D).value
    assert [str(p) for p in err.problems] == [
        f"{dataset}/test.txt:2: clip id '000002' is also in {dataset}/train.txt:2: a clip in two splits leaks "
        "between them"]
    assert err.problems[0].kind == SHARED_ID
    # each split read alone knows nothing of the others
    assert [i.clip_id for i in read_split(dataset, "test", HUMANML3D).items] == ["000005", "000002"]


def test_id_in_two_splits_is_kept_in_its_first_split_and_reported_in_skip_mode(dataset: Path) -> None:
    _append_text(dataset / "val.txt", "000001\n")
    _append_text(dataset / "test.txt", "000001\n")
    data = read_splits(dataset, HUMANML3D, on_error="skip")
    assert "000001" in data["train"].clips and data["train"].skipped == []
    for split, line in (("val", 2), ("test", 2)):
        assert "000001" not in data[split].clips
        [problem] = data[split].skipped
        assert (problem.path, problem.kind) == (f"{dataset}/{split}.txt:{line}", SHARED_ID)
        assert f"{dataset}/train.txt:1" in problem.reason


def test_empty_split_fails_in_both_modes(dataset: Path) -> None:
    """A split without items is bad input for the whole dataset: the stages after it need every split."""
    (dataset / "val.txt").write_text("\n")
    for mode in ("fail", "skip"):
        err = pytest.raises(DatasetError, read_splits, dataset, HUMANML3D, on_error=mode).value
        assert [str(p) for p in err.problems] == [f"{dataset}/val.txt: split 'val' is empty: the file lists no clip id"]
        assert err.problems[0].kind == EMPTY_SPLIT


def test_split_emptied_by_skipping_fails_with_what_emptied_it(dataset: Path) -> None:
    _truncate(dataset / "new_joints" / "000004.npy")  # val's only clip
    err = pytest.raises(DatasetError, read_splits, dataset, HUMANML3D, on_error="skip").value
    assert [(p.kind, p.path) for p in err.problems] == [
        (UNREADABLE, f"{dataset}/new_joints/000004.npy"), (EMPTY_SPLIT, f"{dataset}/val.txt")]
    assert err.problems[1].reason == "split 'val' has no item left: 1 problem(s) with its clips, 0 clip(s) or " \
                                     "span(s) filtered by length"


def _standing(skeleton: Skeleton, scale: float, n_frames: int = 50) -> np.ndarray:
    """``n_frames`` of :func:`rest_pose` with bones ``scale`` times the reference."""
    return np.repeat(rest_pose(skeleton, scale)[None], n_frames, axis=0).astype(np.float32)


@pytest.mark.parametrize(("scale", "plausible"), [(1.0, True), (0.21, True), (4.9, True), (0.19, False),
                                                  (5.1, False), (1000.0, False), (1e6, False)])
def test_bone_lengths_must_be_plausible(tmp_path: Path, scale: float, plausible: bool) -> None:
    root = _single(tmp_path, Clip("c", [cap()], joints=_standing(HUMANML3D, scale)))
    if plausible:
        assert list(read_split(root, "train", HUMANML3D).clips) == ["c"]
        return
    [problem] = read_fails(root).problems
    assert (problem.path, problem.kind) == (str(root / "new_joints" / "c.npy"), IMPLAUSIBLE)
    assert problem.reason == (f"implausible bone lengths: 21 of 21 bones are outside 0.2-5x the humanml3d reference "
                              f"(median ratio {scale:.3g}x), e.g. the bone to 'left_hip' is {0.103074 * scale:.4g} m "
                              f"(median over frames) against 0.1031 m: wrong unit or scale?")


def test_implausible_features_and_skip_mode(dataset: Path) -> None:
    vecs = dataset / "new_joint_vecs" / "M000003.npy"
    save_npy(vecs, np.load(vecs) * 1e6)
    err = read_fails(dataset)
    assert [(p.path, p.kind) for p in err.problems] == [(str(vecs), IMPLAUSIBLE)]
    data = read_split(dataset, "train", HUMANML3D, on_error="skip")
    assert list(data.clips) == ["000001", "000002"] and [p.path for p in data.skipped] == [str(vecs)]


def test_kit_bones_are_checked_in_millimetres(tmp_path: Path) -> None:
    root = tmp_path / "kit"
    write_dataset(root, [Clip("mm", [cap()], joints=_standing(KIT, 1.0)),
                         Clip("m", [cap()], joints=_standing(KIT, 0.001))], {"train": ["mm", "m"]}, skeleton=KIT)
    data = read_split(root, "train", KIT, on_error="skip")
    assert list(data.clips) == ["mm"]
    assert "the bone to 'bp' is 0.00011 m (median over frames) against 0.11 m" in data.skipped[0].reason
