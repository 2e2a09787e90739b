"""Stage extract_features on a small HumanML3D-layout dataset made from the real fixture clip."""

import json
from pathlib import Path

import numpy as np
import pytest

from data.features import features_from_joints
from data.humanml3d import Caption
from data.humanml3d_writer import Clip, write_dataset
from data.skeleton import HUMANML3D
from data.store import read_split
from pipelines.config import compose_params
from stages.extract_features import main, run

FIXTURE = Path(__file__).parent / "fixtures" / "humanml3d" / "new_joints_012314.npy"
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
    params = _params(root, out)
    monkeypatch.setattr("pipelines.cli.load_params", lambda argv: params)
    with pytest.raises(SystemExit) as exc:
        main([])
    assert "0002.npy" in str(exc.value) and "nothing written" in str(exc.value)
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["corrupt"]  # no temp directory left behind


@pytest.mark.slow  # a whole extract_features stage run
def test_skip_mode_reports_what_it_skipped(dataset, tmp_path):
    root = _corrupt_copy(dataset, tmp_path)
    out = run(_params(root, tmp_path / "features", on_error="skip"))
    skipped = json.loads((out / "skipped.json").read_text())
    assert len(skipped) == 1 and skipped[0]["path"].endswith("0002.npy")
    assert {i.clip_id for i in read_split(out / "train.parquet")} == {"0000", "0001", "0003", "0004", "0005"}
    assert json.loads((out / "meta.json").read_text())["skipped"] == 1
