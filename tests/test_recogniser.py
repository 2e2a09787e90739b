"""The action recogniser (models/recogniser.py) and its training run (pipelines/recogniser.py).

Motions are the real fixture clip played forward, backward and at double speed (three actions),
written as a small feature store; networks are tiny. Checks: padding never reaches the embedding,
the embedding does not depend on the start position and heading, a few steps reduce the loss,
labelled-only data, the params group, and (slow) a Ray Train run of the stage's recogniser run.
"""

from __future__ import annotations

import copy
import json
import shutil
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from tolerance import float32_atol

from data.features import features_from_joints, grouped_mean_std
from data.skeleton import HUMANML3D
from data.store import StoredItem, read_split, write_split
from models.recogniser import ActionRecogniser, RecogniserConfig
from pipelines.action_evaluation import load_recogniser, recognise
from pipelines.checkpoint import skipped
from pipelines.config import ConfigError
from pipelines.recogniser import (
    action_classes,
    build,
    labelled_items,
    labelled_set,
    missing_actions,
    recogniser_config,
    step,
    training_clips,
)
from pipelines.runner import LoopSettings, StepContext
from pipelines.stage import train_unless_skipped

pytestmark = pytest.mark.usefixtures("one_thread")  # tiny networks (tests/conftest.py)

FIXTURE = Path(__file__).parent / "fixtures" / "humanml3d" / "new_joints_012314.npy"
D = 263
SECTION = {"lr": 3e-3, "hidden": 16, "layers": 2, "embed_dim": 8, "frame_stride": 2, "crop_frames": 96,
           "min_crop_ratio": 0.75,
           "loop": {"seed": 0, "batch_size": 6, "max_steps": 6, "grad_clip": 1.0, "lr_schedule": "constant",
                    "warmup_steps": 0, "min_lr_ratio": 0.0, "log_every": 3, "num_data_workers": 0,
                    "length_buckets": 0}}


def _yaw(joints: np.ndarray, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return joints @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]).T


def action_joints(action: str, k: int) -> np.ndarray:
    """The fixture clip as ``action`` (forward / backward / fast), cropped and turned by ``k``."""
    base = np.load(FIXTURE)
    clip = {"forward": base, "backward": base[::-1], "fast": base[::2]}[action]
    return _yaw(clip[(3 * k) % 20 :], 0.9 * k).astype(np.float32)


def stored(item_id: str, features: np.ndarray, action: str | None, clip_id: str | None = None) -> StoredItem:
    return StoredItem(item_id, clip_id or item_id, action, 0, features.astype(np.float32), ["a person moves"],
                      [["a/DET", "person/NOUN", "moves/VERB"]], np.zeros((1, 4), np.float32),
                      [np.zeros((3, 4), np.float16)])


def write_store(root: Path) -> Path:
    """train: 4 clips of each action + an unlabelled one; val and test: 1 of each."""
    root.mkdir(parents=True)
    splits: dict[str, list[StoredItem]] = {"train": [], "val": [], "test": []}
    for split, ks in (("train", range(4)), ("val", [4]), ("test", [5])):
        for action in ("forward", "backward", "fast"):
            for k in ks:
                feats = features_from_joints(action_joints(action, k), HUMANML3D)
                splits[split].append(stored(f"{split}-{action}-{k}", feats, action))
    splits["train"].append(stored("train-none", splits["train"][0].features, None))
    frames = np.concatenate([i.features for i in splits["train"]])
    mean, std = grouped_mean_std(frames, 22)
    np.save(root / "mean.npy", mean)
    np.save(root / "std.npy", std)
    (root / "meta.json").write_text(json.dumps({"text_encoder": {"name": "none", "path": None, "max_length": 8,
                                                                 "dim": 4, "token_dim": 4}}))
    for name, items in splits.items():
        write_split(root / f"{name}.parquet", items, D, 4, 4)
    return root


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    return write_store(tmp_path_factory.mktemp("recogniser") / "features")


def params_for(store: Path, base: Path, **section: Any) -> dict[str, Any]:
    return {"train_evaluator": {"recogniser": copy.deepcopy(SECTION) | section},
            "features": {"out": str(store)},
            "paths": {"artifacts": str(base / "artifacts"), "ray_storage": str(base / "ray_storage")},
            "ray": {"num_workers": 0, "cpus_per_worker": 1, "checkpoint_every": 3, "max_failures": 0}}


def loop_cfg(store: Path, base: Path, **section: Any) -> dict[str, Any]:
    params = params_for(store, base, **section)
    settings = LoopSettings.parse(params["train_evaluator"]["recogniser"]["loop"], "loop")
    return asdict(settings) | recogniser_config(params)


def small_model(**overrides: Any) -> ActionRecogniser:
    torch.manual_seed(0)
    cfg = RecogniserConfig(("a", "b", "c"), D, **({"hidden": 16, "embed_dim": 8} | overrides))
    return ActionRecogniser(cfg).eval()


# ---------------------------------------------------------------------------------------------
# the network


def test_config_validation_and_round_trip() -> None:
    cfg = RecogniserConfig(["walk", "run"], 263, hidden=32, layers=1, embed_dim=4, frame_stride=1)
    assert cfg.classes == ("walk", "run") and cfg.joints_num == 22 and cfg.num_classes == 2
    assert RecogniserConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    for bad in ({"classes": ["walk"]}, {"classes": ["a", "a"]}, {"feature_dim": 100}, {"hidden": 0},
                {"frame_stride": 0}, {"dropout": 1.0}):
        with pytest.raises(ValueError):
            RecogniserConfig(**({"classes": ["a", "b"]} | bad))
    with pytest.raises(ValueError, match="unknown"):
        RecogniserConfig.from_dict({"classes": ["a", "b"], "width": 3})


@pytest.mark.parametrize("stride", [1, 2, 3])
def test_embedding_ignores_padding_and_batch_neighbours(stride: int) -> None:
    model = small_model(frame_stride=stride)
    clips = [features_from_joints(action_joints(a, 1), HUMANML3D) for a in ("forward", "backward", "fast")]
    lengths = np.array([120, 77, 41])
    x = np.zeros((3, 130, D), np.float32)
    for b, (clip, n) in enumerate(zip(clips, lengths, strict=True)):
        x[b, :n] = clip[:n]
    with torch.no_grad():
        emb = model.embed(x, lengths)
        noisy = x.copy()
        for b, n in enumerate(lengths):
            noisy[b, n:] = np.random.default_rng(b).normal(0, 50, noisy[b, n:].shape)
        torch.testing.assert_close(model.embed(noisy, lengths), emb, rtol=0, atol=float32_atol(emb))  # tolerance.py
        for b, n in enumerate(lengths):  # alone, trimmed to its length: the same embedding
            torch.testing.assert_close(model.embed(x[b : b + 1, :n], [n]), emb[b : b + 1], rtol=0, atol=1e-5)
        assert model(x, lengths).shape == (3, 3) and emb.shape == (3, 8)
        assert model.embed(x[:0], np.zeros(0, int)).shape == (0, 8)
    with pytest.raises(ValueError, match="lengths"):
        model.embed(x, [131, 10, 10])
    with pytest.raises(ValueError, match="features"):
        model.embed(x[..., :100], lengths)


def test_embedding_does_not_depend_on_start_position_or_heading() -> None:
    model = small_model()
    joints = action_joints("forward", 0)
    moved = _yaw(joints, 2.3) + np.array([4.0, 0.0, -7.5], np.float32)
    a = features_from_joints(joints, HUMANML3D)[None]
    b = features_from_joints(moved.astype(np.float32), HUMANML3D)[None]
    with torch.no_grad():
        torch.testing.assert_close(model.embed(b, [a.shape[1]]), model.embed(a, [a.shape[1]]), rtol=0, atol=1e-4)
        recovered = model.joints(torch.as_tensor(b))
    np.testing.assert_allclose(recovered[0, 0, 0, [0, 2]].numpy(), 0.0, atol=1e-6)  # starts at the origin
    # normalisation statistics are undone before recovery: normalised input, same embedding
    mean, std = np.full(D, 0.3, np.float32), np.full(D, 2.0, np.float32)
    scaled = small_model()
    scaled.set_normalization(mean, std)
    with torch.no_grad():
        torch.testing.assert_close(scaled.embed((a - mean) / std, [a.shape[1]]), model.embed(a, [a.shape[1]]),
                                   rtol=0, atol=1e-4)


# ---------------------------------------------------------------------------------------------
# data and params


def test_labelled_items_keep_labelled_whole_clips_of_known_classes() -> None:
    f = np.zeros((50, D), np.float32)
    items = [stored("1", f, "walk"), stored("2", f, None), stored("1@0-20", f, "walk", clip_id="1"),
             stored("3", f, "run"), stored("4", f, "jump")]
    assert [i.item_id for i in labelled_items(items)] == ["1", "3", "4"]
    assert [i.item_id for i in labelled_items(items, ["run", "walk"])] == ["1", "3"]
    assert action_classes(items) == ("jump", "run", "walk")


def test_training_data_are_labelled_random_crops(store: Path, tmp_path: Path) -> None:
    cfg = loop_cfg(store, tmp_path)
    assert cfg["model"]["classes"] == ["backward", "fast", "forward"]
    data = training_clips(cfg)
    assert len(data) == 12  # the unlabelled clip is left out
    torch.manual_seed(0)
    for index in range(len(data)):
        item = data[index]
        n = int(data.lengths[index])
        assert item["motion"].shape == (96, D) and int(np.ceil(0.75 * n)) <= int(item["length"]) <= n <= 96
        assert torch.all(item["motion"][int(item["length"]) :] == 0)
        assert data.labels[index] == item["label"]
    val = labelled_set(read_split(store / "val.parquet"), cfg["model"]["classes"],
                       cfg["mean"], cfg["std"])
    assert len(val) == 3 and sorted(val.labels.tolist()) == [0, 1, 2]


@pytest.mark.parametrize(("change", "match"), [
    ({"hidden": 0}, "recogniser.hidden"), ({"min_crop_ratio": 1.5}, "min_crop_ratio"),
    ({"lr": -1.0}, "recogniser.lr"), ({"frame_stride": 1.5}, "frame_stride"), ({"width": 3}, "unknown"),
])
def test_bad_params_name_the_key(change: dict[str, Any], match: str, store: Path, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=match):
        recogniser_config(params_for(store, tmp_path, **change))
    params = params_for(store, tmp_path)
    del params["train_evaluator"]["recogniser"]["crop_frames"]
    with pytest.raises(ConfigError, match="missing.*crop_frames"):
        recogniser_config(params)


def test_a_few_steps_reduce_the_loss_and_the_last_reports_validation(store: Path, tmp_path: Path) -> None:
    cfg = loop_cfg(store, tmp_path) | {"max_steps": 25}
    torch.manual_seed(0)
    comps = build(cfg)
    assert len(comps.frozen["val"]) == 3
    data = training_clips(cfg)
    batch = torch.utils.data.default_collate([data[k] for k in range(len(data))])
    ctx = StepContext(cfg, comps.models, comps.optimizers, {}, comps.frozen, torch.device("cpu"), 0, 1, 1.0)
    losses = []
    for k in range(25):
        ctx.step = k
        out = step(batch, ctx)
        losses.append(float(out["loss"]))
        assert ("val_accuracy" in out) == (k == 24)
    assert losses[-1] < 0.5 * losses[0]
    assert 0.0 <= out["val_accuracy"] <= 1.0 and out["val_items"] == 3.0


# ---------------------------------------------------------------------------------------------
# the stage's run (Ray Train)


@pytest.mark.slow
def test_the_stage_trains_the_recogniser_under_ray(store: Path, tmp_path: Path, ray_cluster) -> None:
    from pipelines.stage import train
    from stages.train_evaluator import RECOGNISER

    params = params_for(store, tmp_path)
    params["ray"]["num_workers"] = 1  # on the session cluster
    result = train(RECOGNISER, params)
    assert result.out_dir == tmp_path / "artifacts" / "train_evaluator_recogniser"
    metrics = json.loads((result.out_dir / "metrics.json").read_text())
    assert metrics["step"] == 6 and metrics["val_items"] == 3 and 0 <= metrics["val_accuracy"] <= 1
    model = load_recogniser(result.out_dir)
    assert model.config.classes == ("backward", "fast", "forward") and not model.training
    cfg = loop_cfg(store, tmp_path)
    val = labelled_set(read_split(store / "val.parquet"), model.config.classes,
                       cfg["mean"], cfg["std"])
    emb, logits = recognise(model, val.features, val.lengths)
    assert emb.shape == (3, 8) and logits.shape == (3, 3)
    accuracy = float(np.mean(logits.argmax(-1) == val.labels))
    assert accuracy == pytest.approx(metrics["val_accuracy"])


def test_a_dataset_without_action_labels_skips_the_recogniser_with_its_reason(store: Path, tmp_path: Path) -> None:
    from dataclasses import replace

    from stages.train_evaluator import RECOGNISER

    assert missing_actions(params_for(store, tmp_path)) is None
    unlabelled = tmp_path / "features"
    shutil.copytree(store, unlabelled)
    items = [replace(item, action=None) for item in read_split(store / "train.parquet")]
    write_split(unlabelled / "train.parquet", items, D, 4, 4)
    params = params_for(unlabelled, tmp_path)
    assert "0 action label(s)" in missing_actions(params)
    assert train_unless_skipped(RECOGNISER, params) is None
    assert "no actions.txt" in skipped(tmp_path / "artifacts" / RECOGNISER.name)
