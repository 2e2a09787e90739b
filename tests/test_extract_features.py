"""Stage extract_features on a small HumanML3D-layout dataset made from the real fixture clip, and
the feature store's checks of what it wrote (pipelines/feature_store.py).

The command-line cases run the real ``python -m stages.<name>`` and check the exit status, the one
line on stderr naming the file, and that a previous output is left byte-identical.
"""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from data.atomic import atomic_directory
from data.features import features_from_joints, grouped_mean_std
from data.humanml3d import Caption, DatasetError, Problem
from data.humanml3d_writer import Clip, write_dataset
from data.skeleton import HUMANML3D
from data.store import StoredItem, read_split, write_split
from pipelines.config import compose_params
from pipelines.feature_store import FeatureStore
from stages.extract_features import config_hash, fail_summary, filter_summary, main, run

FIXTURE = Path(__file__).parent / "fixtures" / "humanml3d" / "new_joints_012314.npy"
REPO = Path(__file__).resolve().parent.parent
GOOD_PARAPHRASE = "somebody strolls#somebody/NOUN stroll/VERB#0.0#0.0"
CAPTIONS = ["a person walks forward", "someone steps ahead slowly", "a man kicks with the left leg"]


def _yaw(joints: np.ndarray, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return joints @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]).T


def _caption(text: str, start: float = 0.0, end: float = 0.0) -> Caption:
    return Caption(text, tuple((w, "NOUN") for w in text.split()), start, end)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """9 clips: the fixture rotated and cropped; clip 0004 also has a 2.5 s span caption."""
    root = tmp_path_factory.mktemp("ds") / "dataset"
    base = np.load(FIXTURE)
    clips = []
    for k in range(9):
        joints = _yaw(base[k * 5 :], 0.7 * k).astype(np.float32)
        captions = [_caption(CAPTIONS[k % 3]), _caption(CAPTIONS[(k + 1) % 3])]
        if k == 4:
            captions.append(_caption("a person kicks", 1.0, 3.5))
        clips.append(Clip(f"{k:04d}", captions, joints=joints, action="walk"))
    write_dataset(root, clips, {"train": ["0000", "0001", "0002", "0003", "0004", "0005"],
                                "val": ["0006"], "test": ["0007", "0008"]})
    return root


def _params(root: Path, out: Path, **data) -> dict:
    params = compose_params(["dataset=synthetic"])
    params["data"].update(root=str(root), **data)
    params["features"].update(out=str(out), workers=2)
    return params


@pytest.mark.slow  # a whole extract_features stage run
def test_store_holds_reference_features_spans_and_text(dataset, tmp_path):
    out = run(_params(dataset, tmp_path / "features"))
    meta = json.loads((out / "meta.json").read_text())
    assert meta["feature_dim"] == 263 and meta["joints_num"] == 22
    assert meta["counts"]["train"]["clips"] == 6 and meta["counts"]["train"]["items"] == 7
    assert meta["counts"]["test"]["captions"] == 4
    assert meta["text_encoder"]["name"] == "minilm"
    assert meta["text_encoder"]["path"] is None, "the packaged encoder must not leave a machine path in artefacts"

    train = {item.item_id: item for item in read_split(out / "train.parquet")}
    joints = _yaw(np.load(FIXTURE)[5:], 0.7).astype(np.float32)
    np.testing.assert_allclose(train["0001"].features, features_from_joints(joints, HUMANML3D), atol=1e-6)
    span = train["0004@20-70"]
    assert span.captions == ["a person kicks"] and span.start == 20 and span.length == 50
    np.testing.assert_array_equal(span.features, train["0004"].features[20:70])
    # the same caption has the same unit-norm pooled embedding wherever it occurs
    pooled = {c: p for item in train.values() for c, p in zip(item.captions, item.text_pooled, strict=True)}
    np.testing.assert_allclose(np.linalg.norm(np.stack(list(pooled.values())), axis=1), 1.0, atol=1e-5)
    assert all(t.shape[1] == 384 and len(t) > 2 for item in train.values() for t in item.text_tokens)

    mean, std = np.load(out / "mean.npy"), np.load(out / "std.npy")
    frames = np.concatenate([train[c].features for c in ("0000", "0001", "0002", "0003", "0004", "0005")])
    np.testing.assert_allclose(mean, frames.mean(0), atol=1e-5)
    assert len(np.unique(std)) == 7  # one std per feature group
    assert not (out / "skipped.json").exists()


@pytest.mark.slow  # a whole extract_features stage run
def test_worker_count_does_not_change_the_store(dataset, tmp_path):
    serial = _params(dataset, tmp_path / "one")
    serial["features"]["workers"] = 1
    one = run(serial)
    two = run(_params(dataset, tmp_path / "two"))
    for split in ("train", "val", "test"):
        a, b = read_split(one / f"{split}.parquet"), read_split(two / f"{split}.parquet")
        assert [i.item_id for i in a] == [i.item_id for i in b]
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(x.features, y.features)
    np.testing.assert_array_equal(np.load(one / "std.npy"), np.load(two / "std.npy"))


def _exit_message(params: dict, monkeypatch) -> str:
    """What ``python -m stages.extract_features`` exits with on ``params`` (it must fail)."""
    monkeypatch.setattr("pipelines.cli.load_params", lambda argv: params)
    with pytest.raises(SystemExit) as exc:
        main([])
    return str(exc.value)


def _write_paraphrases(root: Path, lines: dict[str, str]) -> None:
    """``paraphrases/<clip id>.txt`` files of ``root``: clip id -> its one caption line."""
    (root / "paraphrases").mkdir()
    for clip_id, line in lines.items():
        (root / "paraphrases" / f"{clip_id}.txt").write_text(line + "\n")


def _corrupt_copy(dataset: Path, tmp_path: Path) -> Path:
    import shutil

    root = tmp_path / "corrupt"
    shutil.copytree(dataset, root)
    bad = root / "new_joints" / "0002.npy"
    bad.write_bytes(bad.read_bytes()[:200])  # truncated
    return root


def test_bad_input_fails_naming_the_file_and_writes_nothing(dataset, tmp_path, monkeypatch):
    root = _corrupt_copy(dataset, tmp_path)
    out = tmp_path / "features"
    message = _exit_message(_params(root, out), monkeypatch)
    assert "0002.npy" in message and "nothing written" in message
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["corrupt"]  # no temp directory left behind


def _degenerate_copy(dataset: Path, tmp_path: Path) -> Path:
    """A copy whose test clip 0007 reads but cannot be turned into features (frame 0 collapsed to a point)."""
    root = tmp_path / "copy"
    shutil.copytree(dataset, root)
    joints = np.load(root / "new_joints" / "0007.npy")
    joints[0] = joints[0, :1]
    np.save(root / "new_joints" / "0007.npy", joints)
    return root


def test_fail_mode_lists_reading_and_extraction_problems_in_one_run(dataset, tmp_path, monkeypatch):
    """A truncated file (found reading), a degenerate pose (found computing features) and a missing
    paraphrase file (test clip 0008's; 0007 is left out with its features) in one error."""
    root = _degenerate_copy(dataset, tmp_path)
    bad = root / "new_joints" / "0002.npy"
    bad.write_bytes(bad.read_bytes()[:200])
    _write_paraphrases(root, {"0007": GOOD_PARAPHRASE})
    message = _exit_message(_params(root, tmp_path / "features"), monkeypatch)
    lines = message.splitlines()
    assert lines[:2] == ["extract_features: bad input, nothing written.",
                         f"3 problem(s) in splits ['train', 'val', 'test'] of {root}:"]
    assert lines[2].startswith(f"  - {root}/new_joints/0002.npy: unreadable or corrupt .npy")
    assert lines[3].startswith(f"  - {root}/new_joints/0007.npy: feature extraction failed: ")
    assert lines[4].startswith(f"  - {root}/paraphrases/0008.txt: ")
    assert len(lines) == 5
    assert not (tmp_path / "features").exists()


@pytest.mark.parametrize("on_error", ["fail", "skip"])
def test_a_bad_paraphrase_set_stops_the_stage_before_anything_is_written(dataset, tmp_path, monkeypatch, on_error):
    """The evaluation would stop on it after every model trained: the stage checks it first, in both modes."""
    root = tmp_path / "copy"
    shutil.copytree(dataset, root)
    _write_paraphrases(root, {"0007": GOOD_PARAPHRASE, "0008": "somebody strolls#0.0#0.0"})  # 0008: no word/POS
    message = _exit_message(_params(root, tmp_path / "features", on_error=on_error), monkeypatch)
    lines = message.splitlines()
    assert lines[:2] == ["extract_features: bad input, nothing written.",
                         f"2 problem(s) in splits ['train', 'val', 'test'] of {root}:"]
    assert lines[2].startswith(f"  - {root}/paraphrases/0008.txt:1: bad caption line: ")
    assert lines[3:] == [f"  - {root}/paraphrases/0008.txt: no paraphrase of item 0008"]
    assert not (tmp_path / "features").exists()


def test_fail_mode_lists_the_other_splits_problems_with_an_emptied_split(dataset, tmp_path, monkeypatch):
    """A bad train clip and val's only clip truncated (val left empty): one run lists both (the emptied split
    once hid the other splits' problems)."""
    root = _corrupt_copy(dataset, tmp_path)  # train's 0002.npy truncated
    val = root / "new_joints" / "0006.npy"
    val.write_bytes(val.read_bytes()[:200])
    message = _exit_message(_params(root, tmp_path / "features"), monkeypatch)
    listed = [line.split(": ")[0] for line in message.splitlines()[2:]]
    assert listed == [f"  - {root}/new_joints/0002.npy", f"  - {root}/new_joints/0006.npy", f"  - {root}/val.txt"]
    assert not (tmp_path / "features").exists()


@pytest.mark.slow  # a whole extract_features stage run
def test_skip_mode_reports_what_it_skipped(dataset, tmp_path):
    root = _corrupt_copy(dataset, tmp_path)
    out = run(_params(root, tmp_path / "features", on_error="skip"))
    skipped = json.loads((out / "skipped.json").read_text())
    assert len(skipped) == 1 and skipped[0]["path"].endswith("0002.npy")
    assert (skipped[0]["split"], skipped[0]["clip_id"], skipped[0]["kind"]) == ("train", "0002", "unreadable file")
    assert {i.clip_id for i in read_split(out / "train.parquet")} == {"0000", "0001", "0003", "0004", "0005"}
    meta = json.loads((out / "meta.json").read_text())
    assert meta["skipped"] == 1 and meta["counts"]["train"]["skipped"] == 1


@pytest.mark.slow  # a whole extract_features stage run
def test_a_clip_that_fails_extraction_counts_in_its_split(dataset, tmp_path):
    """Skip mode: a clip that reads but cannot be turned into features (frame 0 collapsed to a point) is a
    problem of its own split in meta.json, not only of the total."""
    root = _degenerate_copy(dataset, tmp_path)
    out = run(_params(root, tmp_path / "features", on_error="skip"))
    meta = json.loads((out / "meta.json").read_text())
    [entry] = json.loads((out / "skipped.json").read_text())
    assert (entry["kind"], entry["split"], entry["clip_id"]) == ("feature extraction failed", "test", "0007")
    assert (meta["skipped"], meta["counts"]["test"]["skipped"], meta["counts"]["train"]["skipped"]) == (1, 1, 0)
    assert {i.clip_id for i in read_split(out / "test.parquet")} == {"0008"}


@pytest.mark.slow  # a whole extract_features stage run
def test_skip_mode_summarises_on_the_console(dataset, tmp_path, capsys):
    root = _corrupt_copy(dataset, tmp_path)
    with open(root / "test.txt", "a") as fh:
        fh.write("0001\n0003\n")  # two train clips also listed for test
    out = run(_params(root, tmp_path / "features", on_error="skip"))
    err = capsys.readouterr().err.splitlines()  # with the progress bars
    header = f"extract_features: data.on_error=skip left out 3 problem(s); all of them in {out}/skipped.json"
    assert err[err.index(header):] == [header, "  unreadable file: 1 (0002.npy)",
                                       "  id in several splits: 2 (test.txt:3, test.txt:4)"]
    assert {i.clip_id for i in read_split(out / "test.parquet")} == {"0007", "0008"}
    skipped = json.loads((out / "skipped.json").read_text())
    assert [(p["kind"], Path(p["path"]).name, p["split"], p["clip_id"]) for p in skipped] == [
        ("unreadable file", "0002.npy", "train", "0002"), ("id in several splits", "test.txt:3", "test", "0001"),
        ("id in several splits", "test.txt:4", "test", "0003")]


def test_empty_split_fails_in_one_line(dataset, tmp_path, monkeypatch):
    root = tmp_path / "copy"
    shutil.copytree(dataset, root)
    (root / "val.txt").write_text("")
    message = _exit_message(_params(root, tmp_path / "features"), monkeypatch)
    assert message == (f"extract_features: bad input, nothing written: {root}/val.txt: split 'val' is empty: "
                       "the file lists no clip id")
    assert not (tmp_path / "features").exists()


def test_a_missing_dataset_folder_says_so_in_one_line(tmp_path, monkeypatch):
    message = _exit_message(_params(tmp_path / "nowhere", tmp_path / "features"), monkeypatch)
    assert message == (f"extract_features: bad input, nothing written: {tmp_path / 'nowhere'}: no such dataset "
                       "folder: point data.root at a folder in the HumanML3D layout (see the README)")
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_a_bad_text_encoder_path_stops_the_stage_before_any_motion_is_read(dataset, tmp_path, monkeypatch):
    """The encoder is built first: on a real dataset reading the motions is the long part of the stage."""
    params = _params(dataset, tmp_path / "features")
    params["features"].update(text_encoder="clip", text_encoder_path=str(tmp_path / "no_clip"))
    monkeypatch.setattr("stages.extract_features.read_dataset", lambda *a: pytest.fail("motions read first"))
    with pytest.raises(FileNotFoundError, match="no_clip"):
        run(params)
    assert not (tmp_path / "features").exists()


def test_many_problems_are_capped_with_a_count_per_kind():
    """A wrong skeleton fails every clip: the first problems, then how many of each kind (not 29k lines)."""
    problems = [Problem(f"new_joints/{k:06d}.npy", "wrong shape", "bad motion") for k in range(30)]
    problems.append(Problem("texts/000001.txt:2", "bad caption line", "bad caption"))
    text = fail_summary(DatasetError(problems, "splits"), shown=20)
    lines = text.splitlines()
    assert lines[0] == "31 problem(s) in splits:" and len(lines) == 22
    assert lines[1] == "  - new_joints/000000.npy: wrong shape"
    assert lines[-1] == "  ... and 11 more; by kind: bad motion 30, bad caption 1"
    assert fail_summary(DatasetError(problems[:3], "splits")) == str(DatasetError(problems[:3], "splits"))


def test_filter_summary_names_the_first_clips():
    filtered = [Problem(f"/d/new_joints/{k:06d}.npy", "clip too short") for k in range(5)]
    assert filter_summary(filtered, 40, 200) == (
        "extract_features: the length filter left out 5 clip(s) or caption span(s) outside 40..199 frames "
        "(000000.npy, 000001.npy, 000002.npy, ... (2 more); counted in meta.json)")


def test_zero_std_is_refused_before_writing(dataset, tmp_path, monkeypatch):
    """Statistics are checked before the store is written (grouped_mean_std floors zeros; this is the last line)."""
    def zero_std(frames, joints_num):
        mean, std = grouped_mean_std(frames, joints_num)
        std[259:] = 0.0
        return mean, std

    monkeypatch.setattr("stages.extract_features.grouped_mean_std", zero_std)
    out = tmp_path / "features"
    params = _params(dataset, out)
    params["features"]["workers"] = 1
    with pytest.raises(ValueError) as exc:
        run(params)
    assert str(exc.value) == (f"{out}/std.npy: std is 0 for dims [259, 260, 261, 262] (4 of 263); "
                              "normalising would divide by it")
    assert not out.exists()


# --------------------------------------------------------------------------- the store's checks on read


def tiny_store(root: Path, dim: int = 263) -> Path:
    """A feature store by hand: 4 items of the fixture clip (``dim``-wide features), its statistics, meta.json."""
    feats = features_from_joints(np.load(FIXTURE), HUMANML3D)[:, :dim]
    items = [StoredItem(f"{k:04d}", f"{k:04d}", None, 0, feats[10 * k : 10 * k + 60], ["a person walks"],
                        [["a/DET", "person/NOUN", "walks/VERB"]], np.zeros((1, 4), np.float32),
                        [np.zeros((3, 4), np.float16)]) for k in range(4)]
    root.mkdir(parents=True)
    write_split(root / "train.parquet", items, dim, 4, 4)
    mean, std = grouped_mean_std(feats, 22) if dim == 263 else (feats.mean(0), feats.std(0) + 1)
    np.save(root / "mean.npy", mean)
    np.save(root / "std.npy", std)
    text_encoder = {"name": "none", "path": None, "max_length": 8, "dim": 4, "token_dim": 4}
    (root / "meta.json").write_text(json.dumps({"feature_dim": dim, "text_encoder": text_encoder}))
    return root


def test_feature_store_refuses_a_zero_std(tmp_path):
    store = tiny_store(tmp_path / "features")
    assert FeatureStore(store).feature_dim == 263
    std = np.load(store / "std.npy")
    std[[3, 100, 101]] = 0.0
    np.save(store / "std.npy", std)
    with pytest.raises(ValueError) as exc:
        FeatureStore(store)
    assert str(exc.value) == (f"{store}/std.npy: std is 0 for dims [3, 100, 101] (3 of 263); "
                              "normalising would divide by it")
    np.save(store / "std.npy", np.where(np.arange(263) == 7, np.nan, 1.0))
    with pytest.raises(ValueError, match=r"std.npy: std is not finite for dims \[7\]"):
        FeatureStore(store)


def test_feature_store_checks_statistics_against_the_feature_dim(tmp_path):
    store = tiny_store(tmp_path / "features")
    for name in ("mean", "std"):
        np.save(store / f"{name}.npy", np.ones(7, np.float32))
    with pytest.raises(ValueError) as exc:
        FeatureStore(store)
    assert str(exc.value) == f"{store}/mean.npy: mean has shape (7,), the features have 263 dims: expected (263,)"
    # without a feature_dim in meta.json the Parquet width decides
    other = tiny_store(tmp_path / "kit_wide", dim=251)
    np.save(other / "mean.npy", np.zeros(263, np.float32))
    np.save(other / "std.npy", np.ones(263, np.float32))
    (other / "meta.json").write_text(json.dumps({"text_encoder": json.loads((store / "meta.json").read_text())
                                                 ["text_encoder"]}))
    with pytest.raises(ValueError) as exc:
        FeatureStore(other)
    assert str(exc.value) == (f"{other}/train.parquet: features are (251,) per frame but {other}/mean.npy "
                              "and std.npy are (263,)")


def _tree(directory: Path) -> dict[str, bytes]:
    """Relative path -> bytes of every file below ``directory``."""
    return {str(p.relative_to(directory)): p.read_bytes() for p in sorted(directory.rglob("*")) if p.is_file()}


def _previous_output(directory: Path, owner: str) -> dict[str, bytes]:
    """A previous output of stage ``owner`` (written as stages write theirs), returned as :func:`_tree`."""
    directory.parent.mkdir(parents=True, exist_ok=True)
    with atomic_directory(directory, owner=owner) as tmp:
        (tmp / "model.pt").write_bytes(b"previous model")
        (tmp / "metrics.json").write_text('{"loss": 0.5}\n')
    return _tree(directory)


def _stage(module: str, *overrides: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "WANDB_MODE": "disabled", "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1"}
    return subprocess.run([sys.executable, "-m", module, *overrides], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=300)


@pytest.mark.slow  # a stage command in a subprocess
def test_train_vae_command_refuses_a_zero_std_store(tmp_path):
    store = tiny_store(tmp_path / "features")
    np.save(store / "std.npy", np.zeros(263, np.float32))
    before = _previous_output(tmp_path / "artifacts" / "train_vae", "train_vae")
    proc = _stage("stages.train_vae", "scale=smoke", f"features.out={store}",
                  f"paths.artifacts={tmp_path / 'artifacts'}", f"paths.ray_storage={tmp_path / 'ray'}")
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.splitlines() == [f"train_vae: {store}/std.npy: std is 0 for dims [0, 1, 2, 3, 4, 5, 6, 7, ...] "
                                        "(263 of 263); normalising would divide by it"]
    assert _tree(tmp_path / "artifacts" / "train_vae") == before
    assert not (tmp_path / "ray").exists()


@pytest.mark.slow  # a stage command in a subprocess
def test_extract_features_command_refuses_an_id_in_two_splits(dataset, tmp_path):
    root = tmp_path / "copy"
    shutil.copytree(dataset, root)
    with open(root / "test.txt", "a") as fh:
        fh.write("0001\n")  # also line 2 of train.txt
    out = tmp_path / "features"
    before = _previous_output(out, "extract_features")
    proc = _stage("stages.extract_features", "dataset=synthetic", f"data.root={root}", f"features.out={out}")
    assert proc.returncode == 1, proc.stderr
    *progress, last = proc.stderr.splitlines()  # the clips that read went through feature extraction first
    assert last == (f"extract_features: bad input, nothing written: {root}/test.txt:3: clip id '0001' is also in "
                    f"{root}/train.txt:2: a clip in two splits leaks between them")
    assert all(line.startswith("features:") for line in progress if line)
    assert _tree(out) == before


def test_the_store_hash_leaves_out_settings_that_do_not_change_its_content() -> None:
    """``features.workers`` changed meta.json's hash, and with it every training stage's input, for a store
    whose every other byte was the same; nor is the output folder content. ``data.on_error`` is: skip mode
    writes ``skipped.json``."""
    params = compose_params()
    assert config_hash(params | {"features": params["features"] | {"workers": 7, "out": "/elsewhere"}}) == (
        config_hash(params))
    other = [{"features": params["features"] | {"max_text_tokens": 16}}, {"data": params["data"] | {"root": "/d"}},
             {"data": params["data"] | {"on_error": "fail" if params["data"]["on_error"] == "skip" else "skip"}}]
    assert all(config_hash(params | change) != config_hash(params) for change in other)


def test_a_length_filter_that_keeps_no_clip_is_refused_before_the_encoder_loads(capsys) -> None:
    """``data.feature_frames_below=40`` passed ``--cfg``; the run failed after the text encoder loaded, with the
    reader's internal names (``need 1 <= min_frames < max_frames``)."""
    with pytest.raises(SystemExit) as err:
        main(["data.feature_frames_below=40", "--cfg"])
    assert "data.feature_frames_below: expected more than humanml3d's shortest clip, 40 feature frames, got 40" in (
        str(err.value.code))
    main(["data.feature_frames_below=41", "--cfg"])
