"""The action-to-motion protocol (pipelines/action_evaluation.py) with known answers.

A fake recogniser reads its embedding off the motion (the mean of the first E raw feature dims
over the valid frames) and its logits off the embedding's first C dims; test items of action c
carry a one-hot c there. So the real motions are recognised perfectly, and every generator below
has a predictable Accuracy, FID, Diversity and MultiModality.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import yaml
from torch import nn

from data.store import StoredItem
from models.recogniser import RecogniserConfig
from pipelines.action_evaluation import (
    REAL_ACTION,
    ActionGenerator,
    action_accuracy,
    action_metrics,
    draw_actions,
    evaluate_action_rows,
    per_action_multimodality,
    recognise,
)
from pipelines.config import REPO_ROOT
from pipelines.recogniser import labelled_items
from stages import evaluate as evaluate_stage

CLASSES = ("clap", "jump", "walk")
D = 23  # J = 2
E = 4  # embedding: the C one-hot dims and one noise dim
EVAL_SEED = 5


class FakeRecogniser(nn.Module):
    """The recogniser's interface with a readable embedding (module docstring)."""

    def __init__(self, mean: float = 0.0, std: float = 1.0) -> None:
        super().__init__()
        self.config = RecogniserConfig(CLASSES, D, embed_dim=E)
        self.register_buffer("mean", torch.full((D,), mean))
        self.register_buffer("std", torch.full((D,), std))

    def embed(self, features, lengths) -> torch.Tensor:
        raw = torch.as_tensor(np.asarray(features), dtype=torch.float32) * self.std + self.mean
        lengths = torch.as_tensor(np.asarray(lengths))
        valid = (torch.arange(raw.shape[1])[None] < lengths[:, None]).float()[..., None]
        return (raw[..., :E] * valid).sum(1) / lengths[:, None]

    def classify(self, embedding: torch.Tensor) -> torch.Tensor:
        return embedding[:, : len(CLASSES)]


def motion(action: str, length: int, rng: np.random.Generator) -> np.ndarray:
    x = np.zeros((length, D), np.float32)
    x[:, CLASSES.index(action)] = 1.0 + 0.1 * rng.random()
    x[:, E - 1] = rng.normal() + rng.normal(size=length)  # crops of one motion differ a little
    x[:, E:] = rng.normal(size=(length, D - E))
    return x


def item(item_id: str, action: str | None, length: int, rng: np.random.Generator, clip_id: str | None = None
         ) -> StoredItem:
    features = motion(action if action in CLASSES else "walk", length, rng)
    return StoredItem(item_id, clip_id or item_id, action, 0, features, ["x"], [["x/NOUN"]],
                      np.zeros((1, 2), np.float32), [np.zeros((1, 2), np.float16)])


class Store:
    """A FeatureSource: test items (labelled, unlabelled, spans, an unknown action) and statistics."""

    def __init__(self) -> None:
        rng = np.random.default_rng(0)
        self.mean = np.full(D, 0.25, np.float32)
        self.std = np.full(D, 2.0, np.float32)
        self.items = [item(f"{k:03d}", CLASSES[k % 3], int(rng.integers(40, 90)), rng) for k in range(30)]
        self.items += [item("n1", None, 60, rng), item("n2", None, 50, rng),
                       item("000@0-20", "clap", 20, rng, clip_id="000"), item("u1", "swim", 60, rng)]

    def split(self, name: str) -> list[StoredItem]:
        assert name == "test"
        return list(self.items)


class Recorder:
    """Deterministic generators over the replication's own draw (``seed`` is the replication)."""

    nfe = 3
    stochastic = False

    def __init__(self, name: str, store: Store, recogniser: FakeRecogniser, mode: str,
                 classes: tuple[str, ...] = CLASSES) -> None:
        self.name, self.store, self.recogniser, self.mode, self.classes = name, store, recogniser, mode, classes
        self.requests: list[list[str]] = []

    def sample_actions(self, action_ids: np.ndarray, lengths: np.ndarray, seed: int) -> np.ndarray:
        actions = [self.classes[i] for i in action_ids]
        self.requests.append(actions)
        rng = np.random.default_rng([EVAL_SEED, seed])
        d = draw_actions(labelled_items(self.store.split("test"), CLASSES), self.recogniser, rng)
        assert actions == d.actions and np.array_equal(lengths, d.lengths)
        if self.mode == "copy":  # the real crops
            raw = d.real
        elif self.mode == "constant":  # one still pose of one action, whatever is asked
            raw = np.zeros_like(d.real)
            raw[:] = motion("clap", 1, np.random.default_rng(1))
        elif self.mode == "wrong":  # a clean motion of the next action
            raw = np.stack([motion(CLASSES[(CLASSES.index(a) + 1) % 3], d.real.shape[1], np.random.default_rng(k))
                            for k, a in enumerate(actions)])
        else:  # "asked": a clean motion of the action asked for
            raw = np.stack([motion(a, d.real.shape[1], np.random.default_rng(k)) for k, a in enumerate(actions)])
        x = (raw - self.store.mean) / self.store.std
        for b, n in enumerate(lengths):
            x[b, n:] = 0.0
        return x.astype(np.float32)


@pytest.fixture(scope="module")
def setup():
    store = Store()
    recogniser = FakeRecogniser(mean=-1.0, std=0.5)  # statistics of another store: renormalised
    return store, recogniser


def evaluate(store, recogniser, generators, replications: int = 3, **kw):
    return evaluate_action_rows(generators, store, recogniser, replications, EVAL_SEED, diversity_times=15,
                                mm_times=5, **kw)


def test_generators_satisfy_the_protocol(setup) -> None:
    store, recogniser = setup
    assert isinstance(Recorder("x", store, recogniser, "copy"), ActionGenerator)


def test_real_row_and_a_copying_generator(setup) -> None:
    store, recogniser = setup
    copy = Recorder("Copy-action", store, recogniser, "copy")
    table = evaluate(store, recogniser, [copy])
    real, gen = table[REAL_ACTION], table["Copy-action"]
    keys = {"Accuracy", "FID", "Diversity", "MultiModality"}
    assert set(real) == keys | {f"{k}_ci" for k in keys}
    assert set(gen) == set(real) | {"NFE"} and gen["NFE"] == 3
    assert real["Accuracy"] == 1.0 and real["Accuracy_ci"] == 0.0
    assert gen["Accuracy"] == real["Accuracy"] and gen["FID"] == pytest.approx(real["FID"], abs=1e-9)
    assert 0 < real["FID"] < 0.5  # two independent draws of the same motions
    assert gen["Diversity"] == pytest.approx(real["Diversity"], rel=0.3) and real["Diversity"] > 0.5
    assert real["MultiModality"] > 0 and real["MultiModality"] < real["Diversity"]  # same action: closer
    # labelled whole clips of known actions only: 30 items, 10 per action, every replication
    assert len(copy.requests) == 3 and all(len(r) == 30 for r in copy.requests)
    assert all(sorted(set(r)) == list(CLASSES) and r.count("clap") == 10 for r in copy.requests)
    assert evaluate(store, recogniser, [copy]) == table  # a pure function of the seed


@pytest.mark.filterwarnings("ignore:Matrix is singular")
def test_a_constant_generator_has_no_diversity_and_one_class(setup) -> None:
    store, recogniser = setup
    table = evaluate(store, recogniser, [Recorder("Const", store, recogniser, "constant")], real=False)
    row = table["Const"]
    assert list(table) == ["Const"]
    assert row["Accuracy"] == pytest.approx(1 / 3)  # every motion is a clap; a third of the asks were
    assert row["Diversity"] == pytest.approx(0.0, abs=1e-6) and row["MultiModality"] == pytest.approx(0.0, abs=1e-6)
    assert row["FID"] > 1.0


def test_accuracy_follows_the_generators_class_order(setup) -> None:
    store, recogniser = setup
    reordered = ("walk", "clap", "jump")
    asked = Recorder("Asked", store, recogniser, "asked", classes=reordered)
    wrong = Recorder("Wrong", store, recogniser, "wrong")
    table = evaluate(store, recogniser, [asked, wrong], replications=2)
    assert table["Asked"]["Accuracy"] == 1.0 and table["Wrong"]["Accuracy"] == 0.0
    with pytest.raises(ValueError, match="cannot generate action"):
        evaluate(store, recogniser, [Recorder("Few", store, recogniser, "asked", classes=("clap", "jump"))])


def test_bad_generator_output_is_an_error(setup) -> None:
    store, recogniser = setup

    class Short(Recorder):
        def sample_actions(self, action_ids, lengths, seed):
            return super().sample_actions(action_ids, lengths, seed)[:, :10]

    with pytest.raises(ValueError, match="Short: sample_actions returned"):
        evaluate(store, recogniser, [Short("Short", store, recogniser, "copy")], real=False)
    with pytest.raises(ValueError, match="replications"):
        evaluate(store, recogniser, [], replications=0)


def test_per_action_multimodality_known_answer() -> None:
    emb = np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 5.0], [0.0, 9.0], [7.0, 7.0]])
    labels = np.array([0, 0, 1, 1, 2])  # action 2 has one motion: no pair
    rng = np.random.default_rng(0)
    assert per_action_multimodality(emb, labels, 10, rng) == pytest.approx((2.0 + 4.0) / 2)
    assert np.isnan(per_action_multimodality(emb[:1], labels[:1], 10, rng))
    same = action_metrics(emb, np.eye(3)[labels], labels, (emb.mean(0), np.cov(emb, rowvar=False, bias=False)),
                          100, 5, rng)
    assert same["Accuracy"] == 1.0 and same["FID"] == pytest.approx(0.0, abs=1e-6)


def test_action_accuracy_scores_any_normalised_batch(setup) -> None:
    store, recogniser = setup
    rng = np.random.default_rng(3)
    raw = np.stack([motion(a, 30, rng) for a in ("walk", "jump", "clap", "walk")])
    x = (raw - recogniser.mean.numpy()) / recogniser.std.numpy()
    assert action_accuracy(recogniser, x, np.array([30, 30, 20, 10]), ["walk", "jump", "clap", "jump"]) == 0.75
    emb, logits = recognise(recogniser, x, np.array([30, 30, 20, 10]))
    assert emb.shape == (4, E) and logits.shape == (4, 3)
    with pytest.raises(ValueError, match="does not know"):
        action_accuracy(recogniser, x, np.array([30] * 4), ["walk", "swim", "clap", "jump"])


def test_a_family_whose_training_stage_was_skipped_has_no_rows(tmp_path) -> None:
    params = yaml.safe_load((REPO_ROOT / "params.yaml").read_text())
    params["paths"]["artifacts"] = str(tmp_path)
    (tmp_path / "train_emdm_action").mkdir()
    (tmp_path / "train_emdm_action" / "skipped.json").write_text(json.dumps({"reason": "no action labels"}))
    assert evaluate_stage.run("emdm-action", params) == {}
    assert json.loads((tmp_path / "eval" / "emdm-action" / "metrics.json").read_text()) == {}
