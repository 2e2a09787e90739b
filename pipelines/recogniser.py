"""Training of the action recogniser (:mod:`models.recogniser`), a run of the ``train_evaluator`` stage.

The action-to-motion protocol (EMDM Table 3, HumanAct12-style; :mod:`pipelines.action_evaluation`)
measures generated motions with a GRU action classifier trained on the dataset's action-labelled
items: the whole clips that carry an action label (the embedded dataset labels only single-action
motions, :mod:`data.synthetic`). This module is that run's :class:`~pipelines.runner.TrainSpec`
(:data:`SPEC`) and its params -> loop-config mapping (:func:`recogniser_config`); the stage
declares the run (``stages/train_evaluator.py``).

Params group ``train_evaluator.recogniser`` (every key required, no other)::

    lr             Adam learning rate
    hidden         GRU width H          layers: GRU layers      embed_dim: tanh embedding width E
    crop_frames    longest training crop (frames); batches are padded to it
    min_crop_ratio a training crop keeps a random window of ceil(ratio * n) .. n frames of a motion
                   of n = min(length, crop_frames) frames (1.0: whole motions, up to crop_frames)
    loop           the runner settings (pipelines/runner.py LoopSettings)

Classes are the sorted labels of the training split's labelled items; they travel in the saved
model's config (``model.classes``) with the normalisation statistics, so
:func:`build_recogniser` rebuilds the network from ``model.pt`` alone. At the last step the run
measures the accuracy on the validation split's labelled whole motions (``val_accuracy``, over
``val_items`` items of known classes); it lands in the run's ``metrics.json``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.nn import functional as F
from torch.utils.data import Dataset

from data.motion_dataset import pad_motions
from data.store import StoredItem, read_split
from models.recogniser import ActionRecogniser, RecogniserConfig
from pipelines.cli import param, repo_path
from pipelines.config import ConfigError, check_number
from pipelines.feature_store import FeatureStore
from pipelines.runner import Components, StepContext, TrainSpec

#: Keys of the ``train_evaluator.recogniser`` params group.
SECTION_KEYS = ("lr", "hidden", "layers", "embed_dim", "frame_stride", "crop_frames", "min_crop_ratio", "loop")
GROUP = "train_evaluator.recogniser"


def labelled_items(items: Sequence[StoredItem], classes: Sequence[str] | None = None) -> list[StoredItem]:
    """The whole-clip items with an action label (of ``classes`` when given), in order.

    Span items (a captioned part of a clip) are left out: a clip's action is counted once.
    """
    known = None if classes is None else set(classes)
    return [item for item in items if item.action is not None and item.item_id == item.clip_id
            and (known is None or item.action in known)]


def action_classes(items: Sequence[StoredItem]) -> tuple[str, ...]:
    """The sorted action labels of ``items``' labelled whole clips."""
    return tuple(sorted({item.action for item in labelled_items(items)}))  # type: ignore[misc]


def normalise(features: np.ndarray, mean: Sequence[float] | np.ndarray, std: Sequence[float] | np.ndarray
              ) -> np.ndarray:
    return ((features - np.asarray(mean, np.float32)) / np.asarray(std, np.float32)).astype(np.float32)


# --------------------------------------------------------------------------- data


class ActionClips(Dataset):
    """Random crops of a split's labelled motions (the recogniser's and EMDM-action's training data).

    Items: ``motion`` (crop_frames, D) features normalised with ``mean``/``std``, zero past ``length``;
    ``length``; ``label`` (index into ``classes``). A crop keeps ``ceil(min_crop_ratio n) .. n`` frames
    of an n-frame motion (n capped at ``crop_frames``). Crops use the process-global torch RNG, which
    the runner seeds per rank and checkpoints (exact resume).
    """

    def __init__(self, features_dir: str | Path, classes: Sequence[str], mean: Sequence[float] | np.ndarray,
                 std: Sequence[float] | np.ndarray, crop_frames: int, min_crop_ratio: float = 1.0,
                 split: str = "train") -> None:
        items = labelled_items(read_split(Path(features_dir) / f"{split}.parquet"), classes)
        if not items:
            raise ValueError(f"{features_dir}/{split}.parquet: no action-labelled items of {list(classes)}")
        index = {label: k for k, label in enumerate(classes)}
        self.motions = [normalise(item.features, mean, std) for item in items]
        self.labels = np.array([index[item.action] for item in items], np.int64)
        self.crop_frames = int(crop_frames)
        self.min_crop_ratio = float(min_crop_ratio)
        self.lengths = np.array([min(len(m), self.crop_frames) for m in self.motions], np.int64)  # length_buckets

    def __len__(self) -> int:
        return len(self.motions)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        motion = self.motions[index]
        n = int(self.lengths[index])
        shortest = min(n, max(1, math.ceil(self.min_crop_ratio * n)))
        length = int(torch.randint(shortest, n + 1, ()).item())
        start = int(torch.randint(0, len(motion) - length + 1, ()).item())
        out = np.zeros((self.crop_frames, motion.shape[1]), np.float32)
        out[:length] = motion[start : start + length]
        return {"motion": torch.from_numpy(out), "length": torch.tensor(length),
                "label": torch.tensor(int(self.labels[index]))}


@dataclass
class LabelledSet:
    """Whole labelled motions, padded: ``features`` (B, T, D) normalised, ``lengths`` (B,), ``labels`` (B,)."""

    features: np.ndarray
    lengths: np.ndarray
    labels: np.ndarray

    def __len__(self) -> int:
        return len(self.lengths)


def labelled_set(items: Sequence[StoredItem], classes: Sequence[str], mean: Sequence[float] | np.ndarray,
                 std: Sequence[float] | np.ndarray) -> LabelledSet:
    """The labelled whole clips of ``items`` whose action is one of ``classes``, normalised and padded."""
    chosen = labelled_items(items, classes)
    index = {label: k for k, label in enumerate(classes)}
    lengths = np.array([item.length for item in chosen], np.int64)
    motions = [normalise(item.features, mean, std) for item in chosen]
    return LabelledSet(pad_motions(motions, lengths), lengths, np.array([index[i.action] for i in chosen], np.int64))


# --------------------------------------------------------------------------- model and step


def build_recogniser(config: Mapping[str, Any]) -> ActionRecogniser:
    """A fresh recogniser from a loop config (``model``, ``mean``, ``std``); load weights onto it."""
    return ActionRecogniser(RecogniserConfig.from_dict(dict(config["model"])), config["mean"], config["std"])


def build(config: dict) -> Components:
    model = build_recogniser(config)
    frozen: dict[str, Any] = {}
    val_path = Path(config["features_dir"]) / "val.parquet"
    if val_path.is_file():
        val = labelled_set(read_split(val_path), config["model"]["classes"], config["mean"], config["std"])
        if len(val):
            frozen["val"] = val
    return Components(models={"recogniser": model},
                      optimizers={"adam": torch.optim.Adam(model.parameters(), lr=config["lr"])}, frozen=frozen)


@torch.no_grad()
def accuracy(model: ActionRecogniser, data: LabelledSet, device: torch.device | str = "cpu",
             batch: int = 256) -> float:
    """Top-1 accuracy of ``model`` on ``data`` (eval mode for the call, mode restored after)."""
    was_training = model.training
    model.eval()
    correct = 0
    try:
        for first in range(0, len(data), batch):
            x = torch.as_tensor(data.features[first : first + batch], device=device)
            logits = model(x, data.lengths[first : first + batch])
            correct += int((logits.argmax(-1).cpu().numpy() == data.labels[first : first + batch]).sum())
    finally:
        model.train(was_training)
    return correct / max(len(data), 1)


def step(batch: dict, ctx: StepContext) -> dict[str, torch.Tensor | float]:
    """Cross-entropy on a batch of crops; the validation accuracy at the last step."""
    longest = int(batch["length"].max())
    logits = ctx.models["recogniser"](batch["motion"][:, :longest], batch["length"])
    loss = F.cross_entropy(logits, batch["label"])
    ctx.update(loss)
    out: dict[str, torch.Tensor | float] = {
        "loss": loss.detach(), "accuracy": (logits.detach().argmax(-1) == batch["label"]).float().mean()}
    if ctx.step + 1 >= ctx.config["max_steps"] and "val" in ctx.frozen:
        val: LabelledSet = ctx.frozen["val"]
        out |= {"val_accuracy": accuracy(ctx.unwrap("recogniser"), val, ctx.device), "val_items": float(len(val))}
    return out


def training_clips(config: dict) -> ActionClips:
    """The recogniser's training data from its loop config."""
    return ActionClips(config["features_dir"], config["model"]["classes"], config["mean"], config["std"],
                       config["crop_frames"], config["min_crop_ratio"])


SPEC = TrainSpec(build=build, dataset=training_clips, step=step)


# --------------------------------------------------------------------------- params


def check_section(section: Any, where: str = GROUP) -> dict[str, Any]:
    """The params group, validated: exactly :data:`SECTION_KEYS`, sizes positive, ratio in (0, 1]."""
    if not isinstance(section, Mapping):
        raise ConfigError(f"{where}: expected a mapping with keys {list(SECTION_KEYS)}")
    unknown = sorted(set(section) - set(SECTION_KEYS))
    missing = [key for key in SECTION_KEYS if key not in section]
    if unknown or missing:
        raise ConfigError(f"{where}: unknown key(s) {unknown}, missing key(s) {missing}")
    for key in ("hidden", "layers", "embed_dim", "frame_stride", "crop_frames"):
        check_number(section, key, where, low=1, integer=True)
    check_number(section, "lr", where, low=0.0, low_open=True)
    check_number(section, "min_crop_ratio", where, low=0.0, low_open=True, high=1.0)
    return dict(section)


def missing_actions(params: dict[str, Any]) -> str | None:
    """Why the action stages train nothing on this dataset (fewer than 2 action labels in its training
    split: a real dataset without ``actions.txt``), or None."""
    store = FeatureStore(repo_path(params, "features.out"))
    classes = action_classes(store.split("train"))
    if len(classes) >= 2:
        return None
    return (f"{store.path}: the training split has {len(classes)} action label(s), the action stages need at "
            "least 2 (the dataset has no actions.txt)")


def recogniser_config(params: dict[str, Any]) -> dict[str, Any]:
    """The run's own loop-config keys: store path, classes and sizes (``model``), statistics, crops."""
    cfg = check_section(param(params, GROUP))
    store = FeatureStore(repo_path(params, "features.out"))
    classes = action_classes(store.split("train"))
    if len(classes) < 2:
        raise ConfigError(f"{store.path}: the training split has {len(classes)} action label(s); the recogniser "
                          "needs at least 2 (does the dataset have actions.txt?)")
    model = RecogniserConfig(classes, store.feature_dim, cfg["hidden"], cfg["layers"], cfg["embed_dim"],
                             frame_stride=cfg["frame_stride"])
    return {"features_dir": str(store.path), "model": model.to_dict(), "mean": store.mean.tolist(),
            "std": store.std.tolist(), "lr": cfg["lr"], "crop_frames": cfg["crop_frames"],
            "min_crop_ratio": cfg["min_crop_ratio"]}
