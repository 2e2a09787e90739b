"""The held-out paraphrase protocol: reading the paraphrase set, and the twin rows it adds to the evaluation.

The evaluation world is test_evaluation's: each item's caption and motion carry a known code, the stub
evaluator embeds both as that code, and Retrieval answers a caption with its item's identical twin.
"""

from dataclasses import replace

import numpy as np
import pytest
from test_evaluation import CFG, StubEmbedder, world  # noqa: F401  (the fixture)

from data.humanml3d import Caption, DatasetError
from data.paraphrase_set import read_paraphrases
from data.skeleton import HUMANML3D
from data.store import StoredItem
from pipelines.baselines import Retrieval
from pipelines.evaluation import PARAPHRASE, Draw, Semantics, evaluate, references
from pipelines.paraphrase import paraphrase_sampler

D = HUMANML3D.feature_dim
ROWS_CFG = replace(CFG, paraphrase_rows=("Retrieval",))


def _evaluate(world, semantics):  # noqa: F811
    codes, test, train = world
    mean, std = np.zeros(D, np.float32), np.ones(D, np.float32)
    embedder = StubEmbedder(codes)
    refs = references(test, embedder, ROWS_CFG)
    return evaluate(refs, test, mean, std, embedder, HUMANML3D, ROWS_CFG, [Retrieval(train, mean, std)],
                    real=True, semantics=semantics)


def _always_right(raw: np.ndarray, d: Draw) -> float:
    """A stand-in for the recogniser's accuracy."""
    return 1.0


def test_a_paraphrase_that_says_the_same_as_the_caption_gives_the_rows_own_metrics(world):  # noqa: F811
    table = _evaluate(world, Semantics(lambda d, r: d.text, _always_right))
    row, twin = table["Retrieval"], table["Retrieval" + PARAPHRASE]
    for key in ("R_precision_top1", "R_precision_top3", "FID", "MM_Dist", "penetration_mm"):
        assert twin[key] == pytest.approx(row[key], abs=1e-9), key
    assert row["R_precision_top1"] == 1.0
    assert table["Real"]["action_accuracy"] == row["action_accuracy"] == twin["action_accuracy"] == 1.0
    assert "MultiModality" not in twin and "AITS_s" not in twin  # no MultiModality, no timing


def test_a_paraphrase_of_another_item_is_judged_against_the_original_caption(world):  # noqa: F811
    def wrong(d: Draw, r: int):
        return d.text.select(np.roll(np.arange(len(d.text)), 1))  # every row answers its neighbour's caption

    table = _evaluate(world, Semantics(wrong, lambda raw, d: None))
    assert table["Retrieval"]["R_precision_top3"] == 1.0
    assert table["Retrieval" + PARAPHRASE]["R_precision_top3"] < 0.3  # near chance (3/32), not the row's 1.0
    assert "action_accuracy" not in table["Retrieval"]  # no labelled item: no accuracy, never a made-up one


def test_no_paraphrase_set_means_no_twin_rows(world):  # noqa: F811
    table = _evaluate(world, Semantics(None, _always_right))
    assert "Retrieval" + PARAPHRASE not in table and table["Retrieval"]["action_accuracy"] == 1.0


class Halving:
    """A lossy reconstructor: every feature comes back at half its value."""

    name = "Halving"

    def reconstruct(self, motions: np.ndarray, lengths: np.ndarray) -> np.ndarray:
        return 0.5 * motions


def _is_the_draws_real_motion(raw: np.ndarray, d: Draw) -> float:
    """A stand-in for the recogniser: right exactly on the draw's real motions."""
    return float(np.allclose(raw, d.real))


def test_a_reconstruction_row_gets_the_action_accuracy_of_what_it_gives_back(world):  # noqa: F811
    codes, test, train = world
    mean, std = np.zeros(D, np.float32), np.ones(D, np.float32)
    embedder = StubEmbedder(codes)
    refs = references(test, embedder, ROWS_CFG)
    table = evaluate(refs, test, mean, std, embedder, HUMANML3D, ROWS_CFG, [], [Halving()], real=True,
                     semantics=Semantics(None, _is_the_draws_real_motion))
    assert table["Real"]["action_accuracy"] == 1.0  # Real is scored on the draw's motions
    assert table["Halving"]["action_accuracy"] == 0.0  # the reconstruction on what it gave back, not on Real's
    assert "Halving" + PARAPHRASE not in table  # a reconstruction answers no caption: no paraphrase twin


def _item(item_id: str, clip_id: str, start: int, length: int) -> StoredItem:
    return StoredItem(item_id, clip_id, None, start, np.zeros((length, D), np.float32), ["x"], [["x/NOUN"]],
                      np.zeros((1, 4), np.float32), [np.zeros((1, 4), np.float16)])


def _write(folder, clip_id: str, captions: list[Caption]) -> None:
    folder.mkdir(exist_ok=True)
    (folder / f"{clip_id}.txt").write_text("".join(c.to_line() + "\n" for c in captions))


def test_paraphrases_are_read_per_item_whole_clips_and_spans_apart(tmp_path):
    folder = tmp_path / "paraphrases"
    _write(folder, "c1", [Caption("somebody trots", (("trot", "VERB"),)), Caption("a guy lopes", (("lope", "VERB"),)),
                          Caption("a lady bounces", (("bounce", "VERB"),), 1.0, 3.0)])
    items = [_item("c1", "c1", 0, 100), _item("c1@20-60", "c1", 20, 40)]
    assert read_paraphrases(tmp_path, items, fps=20.0) == {"c1": ["somebody trots", "a guy lopes"],
                                                            "c1@20-60": ["a lady bounces"]}
    assert read_paraphrases(tmp_path / "elsewhere", items, fps=20.0) is None  # no set: no rows, no error


def test_a_span_past_the_clips_end_matches_the_item_it_was_cut_to(tmp_path):
    """``texts/``'s ``1.0#30.0`` on a 100-frame clip is the item c1@20-100; its paraphrase, copied with the same
    times, was "no paraphrase of item c1@20-100". A span that ends inside the clip is matched uncut."""
    _write(tmp_path / "paraphrases", "c1", [Caption("a guy lopes", (("lope", "VERB"),)),
                                            Caption("a lady bounces", (("bounce", "VERB"),), 1.0, 30.0),
                                            Caption("she hops", (("hop", "VERB"),), 1.0, 4.0)])
    items = [_item("c1", "c1", 0, 100), _item("c1@20-100", "c1", 20, 80), _item("c1@20-80", "c1", 20, 60)]
    assert read_paraphrases(tmp_path, items, fps=20.0) == {
        "c1": ["a guy lopes"], "c1@20-100": ["a lady bounces"], "c1@20-80": ["she hops"]}


def test_a_missing_or_incomplete_paraphrase_file_names_the_file_and_the_item(tmp_path):
    folder = tmp_path / "paraphrases"
    _write(folder, "c1", [Caption("somebody trots", (("trot", "VERB"),))])
    items = [_item("c1", "c1", 0, 100), _item("c1@20-60", "c1", 20, 40), _item("c2", "c2", 0, 50)]
    with pytest.raises(DatasetError) as err:
        read_paraphrases(tmp_path, items, fps=20.0)
    message = str(err.value)
    assert "c1.txt" in message and "no paraphrase of item c1@20-60" in message and "c2.txt" in message


class _EncodingStore:
    """Encodes a text as a one-hot of its rank, so a TextBatch says which texts it holds."""

    def encode_prompts(self, texts):
        from models.generator import TextBatch

        return TextBatch(list(texts), np.eye(len(texts), dtype=np.float32), [np.zeros((1, 4))] * len(texts))


def test_each_drawn_item_answers_one_of_its_own_paraphrases_the_same_for_every_row():
    by_item = {"a": ["a one", "a two", "a three"], "b": ["b one"], "c": ["c one", "c two"]}
    sample = paraphrase_sampler(by_item, _EncodingStore(), seed=0)
    d = Draw(None, [], np.array([40, 40, 40, 40]), np.zeros((4, 40, D)), ["c", "a", "b", "a"])  # type: ignore[arg-type]
    first = sample(d, 0)
    assert [t.split()[0] for t in first.texts] == ["c", "a", "b", "a"]
    assert first.texts == sample(d, 0).texts  # seeded by (seed, r): every row gets the same paraphrases
    seen = {tuple(sample(d, r).texts) for r in range(20)}
    assert len(seen) > 1  # replications choose afresh
    np.testing.assert_array_equal(first.pooled.argmax(1), [sorted(t for v in by_item.values() for t in v).index(t)
                                                           for t in first.texts])
