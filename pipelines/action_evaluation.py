"""The action-to-motion protocol (EMDM Table 3, HumanAct12-style; reference emdm_motiondiffuse.md 1.9).

Generated motions are scored with the action recogniser (:mod:`models.recogniser`, trained by
``train_evaluator``; :func:`load_recogniser`) on the test split's action-labelled whole clips
(:func:`pipelines.recogniser.labelled_items`, classes the recogniser knows). One replication r:

1. Draw (seeded by ``(seed, r)``): shuffle the labelled items and crop each to the reference crop
   length (:func:`pipelines.evaluation.crop_lengths`: 4*floor(L/4), or one unit less w.p. 1/3) at a
   random offset. Every row answers this draw's (action, length) pairs: HumanAct12's protocol
   generates per action; here the number and mix of samples is that of the labelled test set.
2. A second, independent draw of the real items gives the FID reference statistics (as the T2M
   ``Real`` row: Real-action vs reference FID is small but not zero).
3. Per row (``Real-action`` = the draw's real crops, then each :class:`ActionGenerator`):
   ``Accuracy`` (recogniser top-1 on the row's motions against the drawn actions), ``FID``
   (recogniser embeddings against the reference), ``Diversity`` (``diversity_times`` random pairs of
   all the row's embeddings, at most N - 1 pairs) and ``MultiModality`` (per action: ``mm_times``
   random pairs of distinct motions of that action, averaged over actions with >= 2 motions; as
   Action2Motion's, which HumanAct12 tables report for Real too).

Each metric is the mean over replications with ``<key>_ci`` = 1.96 std / sqrt(R)
(:func:`pipelines.evaluation.aggregate`); generator rows also carry ``NFE``. Each row draws its
pairs from its own stream seeded by its name, so a row's metrics do not depend on the other rows.

:func:`recognise` / :func:`action_accuracy` score any batch of normalised features (e.g. text-
generated motions against the action of their prompt).
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np
import torch

from data.motion_dataset import pad_motions
from data.store import StoredItem
from models import metrics as M
from models.generator import CPU
from models.recogniser import ActionRecogniser
from pipelines.checkpoint import load_final_model
from pipelines.evaluation import aggregate, crop_lengths
from pipelines.recogniser import build_recogniser, labelled_items

REAL_ACTION = "Real-action"
METRICS = ("Accuracy", "FID", "Diversity", "MultiModality")


@runtime_checkable
class ActionGenerator(Protocol):
    """An action-conditioned generator as the protocol calls it.

    Attributes:
        name: its row name (e.g. ``EMDM-action``).
        nfe: network evaluations per sample.
        stochastic: whether samples vary with the seed.
        classes: the action label of each action id it takes (its training classes, in order).
    """

    name: str
    nfe: int
    stochastic: bool
    classes: Sequence[str]

    def sample_actions(self, action_ids: np.ndarray, lengths: np.ndarray, seed: int) -> np.ndarray:
        """(B,) int action ids (into ``classes``) and (B,) lengths -> (B, max length, D) normalised
        features (the feature store's Mean/Std), zero past each length; a pure function of ``seed``."""
        ...


class FeatureSource(Protocol):
    """What the protocol reads of a feature store (:class:`pipelines.feature_store.FeatureStore`)."""

    mean: np.ndarray
    std: np.ndarray

    def split(self, name: str) -> list[StoredItem]: ...


# --------------------------------------------------------------------------- the recogniser


def load_recogniser(out_dir: str | Path, device: torch.device = CPU) -> ActionRecogniser:
    """The trained recogniser of ``train_evaluator``'s recogniser run folder, in eval mode on ``device``."""
    payload = load_final_model(Path(out_dir))
    model = build_recogniser(payload["config"])
    model.load_state_dict(payload["models"]["recogniser"])
    return model.eval().to(device)


@torch.inference_mode()
def recognise(recogniser: ActionRecogniser, features: np.ndarray, lengths: np.ndarray, batch: int = 256
              ) -> tuple[np.ndarray, np.ndarray]:
    """Embeddings (B, E) and class logits (B, C) of normalised (B, T, D) features (the recogniser's
    own Mean/Std: the training store's), anything past ``lengths``."""
    recogniser.eval()
    lengths = np.asarray(lengths)
    emb, logits = [], []
    for first in range(0, len(lengths), batch):
        e = recogniser.embed(features[first : first + batch], lengths[first : first + batch])
        emb.append(e.cpu().numpy())
        logits.append(recogniser.classify(e).cpu().numpy())
    if not emb:
        return np.zeros((0, recogniser.config.embed_dim)), np.zeros((0, recogniser.config.num_classes))
    return np.concatenate(emb).astype(np.float64), np.concatenate(logits).astype(np.float64)


def class_ids(recogniser: ActionRecogniser, actions: Sequence[str]) -> np.ndarray:
    """Recogniser class indices of action labels; an error naming any label it does not know."""
    index = {label: k for k, label in enumerate(recogniser.config.classes)}
    unknown = sorted(set(actions) - set(index))
    if unknown:
        raise ValueError(f"the recogniser does not know action(s) {unknown}; its classes: "
                         f"{list(recogniser.config.classes)}")
    return np.array([index[a] for a in actions], np.int64)


def action_accuracy(recogniser: ActionRecogniser, features: np.ndarray, lengths: np.ndarray,
                    actions: Sequence[str]) -> float:
    """Top-1 accuracy of the recogniser on normalised (B, T, D) motions against action labels."""
    target = class_ids(recogniser, actions)
    _, logits = recognise(recogniser, features, lengths)
    return float(np.mean(logits.argmax(-1) == target)) if len(target) else float("nan")


def renormalise(features: np.ndarray, mean: np.ndarray, std: np.ndarray, to_mean: np.ndarray, to_std: np.ndarray
                ) -> np.ndarray:
    """Features normalised with (mean, std) re-expressed with (to_mean, to_std) (padding included)."""
    return ((features * std + mean - to_mean) / to_std).astype(np.float32)


# --------------------------------------------------------------------------- metrics


def per_action_multimodality(emb: np.ndarray, labels: np.ndarray, times: int, rng: np.random.Generator) -> float:
    """Mean over actions with >= 2 motions of the mean distance of ``times`` random pairs of
    distinct motions of that action (pairs drawn with replacement). NaN if no action has 2."""
    per_class = []
    for label in np.unique(labels):
        members = np.flatnonzero(labels == label)
        if len(members) < 2:
            continue
        first = rng.choice(members, times)
        offset = rng.integers(1, len(members), times)  # a different member of the same action
        second = members[(np.searchsorted(members, first) + offset) % len(members)]
        per_class.append(np.linalg.norm(emb[first] - emb[second], axis=1).mean())
    return float(np.mean(per_class)) if per_class else float("nan")


def action_metrics(emb: np.ndarray, logits: np.ndarray, labels: np.ndarray, ref: tuple[np.ndarray, np.ndarray],
                   diversity_times: int, mm_times: int, rng: np.random.Generator) -> dict[str, float]:
    """Accuracy, FID against ``ref`` (mu, sigma), Diversity and per-action MultiModality of one row."""
    return {
        "Accuracy": float(np.mean(logits.argmax(-1) == labels)),
        "FID": M.frechet_distance(*M.gaussian_statistics(emb), *ref),
        "Diversity": M.diversity(emb, min(diversity_times, len(emb) - 1), rng),
        "MultiModality": per_action_multimodality(emb, labels, mm_times, rng),
    }


# --------------------------------------------------------------------------- the protocol


@dataclass
class ActionDraw:
    """One pass over the labelled test items: ``actions`` (labels), recogniser ``labels`` (ids),
    crop ``lengths`` and the ``real`` crops (B, max L, D) raw features."""

    actions: list[str]
    labels: np.ndarray
    lengths: np.ndarray
    real: np.ndarray


def draw_actions(items: Sequence[StoredItem], recogniser: ActionRecogniser, rng: np.random.Generator,
                 unit: int = 4) -> ActionDraw:
    """Shuffle ``items`` and crop each (reference crop lengths) at a random offset."""
    chosen = [items[k] for k in rng.permutation(len(items))]
    lengths = crop_lengths(np.array([item.length for item in chosen]), rng, unit)
    crops = []
    for item, length in zip(chosen, lengths, strict=True):
        start = int(rng.integers(0, item.length - length + 1))
        crops.append(item.features[start : start + length])
    actions = [item.action for item in chosen]
    return ActionDraw(actions, class_ids(recogniser, actions), lengths, pad_motions(crops, lengths))  # type: ignore[arg-type]


def row_rng(seed: int, r: int, row: str) -> np.random.Generator:
    """The pair-drawing stream of one row in one replication (as :func:`pipelines.evaluation.row_rng`)."""
    return np.random.default_rng([seed, r, zlib.crc32(row.encode())])


def generator_ids(gen: ActionGenerator, actions: Sequence[str]) -> np.ndarray:
    """The generator's own action ids of ``actions``; an error naming labels it cannot generate."""
    index = {label: k for k, label in enumerate(gen.classes)}
    unknown = sorted(set(actions) - set(index))
    if unknown:
        raise ValueError(f"{gen.name} cannot generate action(s) {unknown}; its classes: {list(gen.classes)}")
    return np.array([index[a] for a in actions], np.int64)


def evaluate_action_rows(generators: Sequence[ActionGenerator], store: FeatureSource, recogniser: ActionRecogniser,
                         replications: int, seed: int = 0, *, real: bool = True, diversity_times: int = 200,
                         mm_times: int = 20, unit_length: int = 4, split: str = "test"
                         ) -> dict[str, dict[str, float]]:
    """The protocol (module docstring): {row: {metric: mean, metric_ci: half-width, (NFE)}}.

    Args:
        generators: the action-conditioned rows; their output is normalised with ``store``'s Mean/Std.
        store: the feature store (its ``split`` items, ``mean`` and ``std``).
        recogniser: the trained recogniser (:func:`load_recogniser`).
        replications: R; seed: the draws' and pairs' seed.
        real: include the ``Real-action`` row.
        diversity_times: Diversity pairs (HumanAct12: 200; at most N - 1 are used).
        mm_times: MultiModality pairs per action (HumanAct12: 20).
        unit_length: crop unit (4).
        split: the split evaluated on.
    """
    if replications < 1:
        raise ValueError(f"replications must be >= 1, got {replications}")
    items = labelled_items(store.split(split), recogniser.config.classes)
    if len(items) < 3:
        raise ValueError(f"the {split} split has {len(items)} action-labelled item(s) of the recogniser's "
                         "classes; the protocol needs at least 3")
    mean, std = np.asarray(store.mean, np.float32), np.asarray(store.std, np.float32)
    r_mean, r_std = recogniser.mean.cpu().numpy(), recogniser.std.cpu().numpy()
    reps = []
    for r in range(replications):
        rng = np.random.default_rng([seed, r])
        d, ref_draw = draw_actions(items, recogniser, rng, unit_length), draw_actions(items, recogniser, rng,
                                                                                   unit_length)
        ref_emb, _ = recognise(recogniser, (ref_draw.real - r_mean) / r_std, ref_draw.lengths)
        ref = M.gaussian_statistics(ref_emb)
        rows: dict[str, dict[str, float]] = {}
        if real:
            emb, logits = recognise(recogniser, (d.real - r_mean) / r_std, d.lengths)
            rows[REAL_ACTION] = action_metrics(emb, logits, d.labels, ref, diversity_times, mm_times,
                                               row_rng(seed, r, REAL_ACTION))
        for gen in generators:
            x = gen.sample_actions(generator_ids(gen, d.actions), d.lengths.copy(), seed=r)
            if x.ndim != 3 or x.shape[0] != len(d.lengths) or x.shape[1] < int(d.lengths.max()):
                raise ValueError(f"{gen.name}: sample_actions returned {x.shape} for {len(d.lengths)} motions of "
                                 f"up to {int(d.lengths.max())} frames")
            emb, logits = recognise(recogniser, renormalise(x, mean, std, r_mean, r_std), d.lengths)
            rows[gen.name] = action_metrics(emb, logits, d.labels, ref, diversity_times, mm_times,
                                            row_rng(seed, r, gen.name))
        reps.append(rows)
    table = aggregate(reps) if reps[0] else {}
    for gen in generators:
        table[gen.name]["NFE"] = gen.nfe
    return table
