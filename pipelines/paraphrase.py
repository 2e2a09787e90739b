"""The held-out paraphrase protocol and the action-accuracy check (issue 18; :class:`pipelines.evaluation.Semantics`).

A dataset may hold a second caption set for its test motions, ``paraphrases/<clip id>.txt`` beside
``texts/``, in the same format (:mod:`data.paraphrase_set` reads it). The embedded dataset writes it
with a grammar whose vocabulary the training captions never use (:mod:`data.paraphrase_text`); users
of a real dataset may write their own. Every test item must have at least one paraphrase.

:func:`semantics` turns it and the action recogniser into the evaluation's :class:`Semantics`: in
replication r, each drawn item answers with one of its paraphrases chosen by a stream seeded by
``(evaluate.seed, r)`` (the same choice for every row), encoded once by the store's text encoder; the
action accuracy is taken over the draw's whole-clip items whose action the recogniser knows.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from data.paraphrase_set import read_paraphrases
from data.store import StoredItem
from models.generator import TextBatch
from models.recogniser import ActionRecogniser
from pipelines.action_evaluation import action_accuracy
from pipelines.evaluation import Draw, Semantics
from pipelines.feature_store import FeatureStore
from pipelines.recogniser import labelled_items

_STREAM = zlib.crc32(b"paraphrase")


def paraphrase_sampler(by_item: dict[str, list[str]], store: FeatureStore, seed: int
                       ) -> Callable[[Draw, int], TextBatch]:
    """The ``Semantics.paraphrase`` function: every paraphrase encoded once, one chosen per drawn item."""
    texts = sorted({t for item_texts in by_item.values() for t in item_texts})
    encoded = store.encode_prompts(texts)
    index = {t: k for k, t in enumerate(texts)}

    def paraphrase(d: Draw, r: int) -> TextBatch:
        rng = np.random.default_rng([seed, r, _STREAM])
        chosen = [by_item[i][int(rng.integers(len(by_item[i])))] for i in d.item_ids]
        return encoded.select([index[t] for t in chosen])

    return paraphrase


def accuracy_scorer(items: Sequence[StoredItem], recogniser: ActionRecogniser | None, mean: np.ndarray,
                    std: np.ndarray) -> Callable[[np.ndarray, Draw], float | None]:
    """The ``Semantics.action_accuracy`` function over the labelled whole-clip items of a draw (none
    without a recogniser: a dataset without action labels)."""
    labels = {} if recogniser is None else {
        item.item_id: item.action for item in labelled_items(items, recogniser.config.classes)}

    def accuracy(raw: np.ndarray, d: Draw) -> float | None:
        rows = [k for k, i in enumerate(d.item_ids) if i in labels]
        if not rows:
            return None
        features = ((raw[rows] - mean) / std).astype(np.float32)
        return action_accuracy(recogniser, features, d.lengths[rows], [labels[d.item_ids[k]] for k in rows])

    return accuracy


def semantics(root: Path, items: Sequence[StoredItem], store: FeatureStore, recogniser: ActionRecogniser | None,
              seed: int, fps: float, paraphrases: bool = True) -> Semantics:
    """The recogniser and, with ``paraphrases``, the paraphrase set of ``root`` (if it has one), as the
    evaluation uses them."""
    by_item = read_paraphrases(root, items, fps) if paraphrases else None
    sampler = None if by_item is None else paraphrase_sampler(by_item, store, seed)
    return Semantics(sampler, accuracy_scorer(items, recogniser, store.mean, store.std))
