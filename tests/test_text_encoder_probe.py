"""benchmarks/text_encoder_probe.py: the held-out check and the metrics, with known-answer fake encoders.

The protocol (module docstring of the benchmark): a gallery of the embedded dataset's training captions,
each with the program(s) it describes; held-out paraphrase queries scored by the action of the nearest
single-action caption and of the nearest action centroid; contrast queries scored by whether the
intended program's nearest caption beats the contrasting program's. Here the gallery is a handful of
hand-made captions and the encoders are lookup tables, so every score has a known value: an encoder that
maps each query onto its intended caption scores 1, a constant encoder scores chance (ties count as a
random tie-break). The real encoders and the full gallery run only in the ``slow`` tests.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import pytest
from bench_module import load_benchmark

from data.synthetic_library import ACTIONS
from data.synthetic_text import LEXICON
from data.text_encoders import TextEncoder, TextEncoding

probe = load_benchmark("text_encoder_probe")
Seg, GalleryItem, Query, Contrast, step = probe.Seg, probe.GalleryItem, probe.Query, probe.Contrast, probe.step


class LookupEncoder:
    """A fake :class:`TextEncoder`: each text's pooled vector comes from a table (unknown text: KeyError)."""

    name = "lookup"
    max_length = 1

    def __init__(self, table: Mapping[str, Sequence[float]]) -> None:
        self.table = {k: np.asarray(v, np.float32) for k, v in table.items()}
        self.dim = self.token_dim = len(next(iter(self.table.values())))

    def encode(self, texts: Sequence[str], batch_size: int = 64) -> TextEncoding:
        pooled = np.stack([self.table[t] for t in texts]) if texts else np.zeros((0, self.dim), np.float32)
        return TextEncoding(pooled=pooled, tokens=pooled[:, None], mask=np.ones((len(texts), 1), bool))


class ConstantEncoder(LookupEncoder):
    """Every text gets the same vector."""

    def __init__(self, dim: int = 4) -> None:
        self.dim = self.token_dim = dim

    def encode(self, texts: Sequence[str], batch_size: int = 64) -> TextEncoding:
        pooled = np.ones((len(texts), self.dim), np.float32)
        return TextEncoding(pooled=pooled, tokens=pooled[:, None], mask=np.ones((len(texts), 1), bool))


def _one(kind: str, **params) -> tuple:
    return (Seg(kind, tuple(sorted(params.items()))),)


#: text -> programs; two walk captions, a kick per side, a wave, both orders of walk/turn, a carried wave.
GALLERY = [
    GalleryItem("a person walks forward", frozenset({_one("walk", direction="forward")})),
    GalleryItem("a man strolls ahead", frozenset({_one("walk", direction="forward")})),
    GalleryItem("a person kicks with the left leg", frozenset({_one("kick", side="left", reps=1)})),
    GalleryItem("a person kicks with the right leg", frozenset({_one("kick", side="right", reps=1)})),
    GalleryItem("a person waves", frozenset({_one("wave", side="right")})),
    GalleryItem("a person walks, then turns", frozenset({(Seg("walk"), Seg("turn"))})),
    GalleryItem("a person turns, then walks", frozenset({(Seg("turn"), Seg("walk"))})),
    GalleryItem("a person walks while waving", frozenset({(Seg("walk", (), "wave"),)})),
]
QUERIES = [Query("q-walk", "walk"), Query("q-kick", "kick"), Query("q-wave", "wave")]
CONTRASTS = [
    Contrast("q-left", "side", (step("kick", side="left"),), (step("kick", side="right"),)),
    Contrast("q-right", "side", (step("kick", side="right"),), (step("kick", side="left"),)),
    Contrast("q-walk-turn", "order", (step("walk"), step("turn")), (step("turn"), step("walk"))),
    Contrast("q-turn-walk", "order", (step("turn"), step("walk")), (step("walk"), step("turn"))),
]
#: which gallery caption each query means
INTENDED = {"q-walk": 0, "q-kick": 2, "q-wave": 4, "q-left": 2, "q-right": 3, "q-walk-turn": 5, "q-turn-walk": 6}


def oracle() -> LookupEncoder:
    """One-hot per gallery caption; each query gets its intended caption's vector."""
    eye = np.eye(len(GALLERY))
    table = {item.text: eye[i] for i, item in enumerate(GALLERY)}
    table.update({q: eye[i] for q, i in INTENDED.items()})
    return LookupEncoder(table)


# --------------------------------------------------------------------------------------------- held-out check


def test_the_shipped_queries_share_no_content_word_with_the_caption_grammar():
    assert probe.held_out_violations(probe.all_query_texts(), LEXICON, probe.FUNCTION_WORDS) == []
    assert len(probe.QUERIES) == 4 * len(ACTIONS) and {q.action for q in probe.QUERIES} == set(ACTIONS)


# --------------------------------------------------------------------------------------------- programs


def test_matches_wants_the_exact_program_without_upper_body_actions():
    walk_turn = (step("walk"), step("turn"))
    assert probe.matches((Seg("walk", (("direction", "forward"),)), Seg("turn")), walk_turn)
    assert not probe.matches((Seg("turn"), Seg("walk")), walk_turn)
    assert not probe.matches((Seg("walk"),), walk_turn)
    assert not probe.matches((Seg("walk", (), "wave"), Seg("turn")), walk_turn)
    assert probe.matches(_one("kick", side="left", reps=1), (step("kick", side="left"),))
    assert not probe.matches(_one("kick", side="right", reps=1), (step("kick", side="left"),))


def test_gallery_item_action_is_the_kind_of_a_single_segment_only():
    assert [item.action for item in GALLERY] == ["walk", "walk", "kick", "kick", "wave", None, None, None]


def test_pattern_index_leaves_out_captions_that_also_describe_the_contrast():
    both = GalleryItem("a person kicks", frozenset({_one("kick", side="left"), _one("kick", side="right")}))
    gallery = [*GALLERY, both]
    left, right = (step("kick", side="left"),), (step("kick", side="right"),)
    assert probe.pattern_index(gallery, left).tolist() == [2, 8]
    assert probe.pattern_index(gallery, left, exclude=right).tolist() == [2]


# --------------------------------------------------------------------------------------------- metrics


def test_an_encoder_that_maps_each_query_onto_its_intended_caption_scores_one():
    m = probe.evaluate(oracle(), GALLERY, QUERIES, CONTRASTS)
    assert m["nn_acc"] == 1.0 and m["centroid_acc"] == 1.0
    assert m["nn_cos"] == pytest.approx(1.0)
    assert m["contrast"] == {"order": 1.0, "side": 1.0}
    assert m["uncovered_contrasts"] == []
    assert [q["nearest_single"] for q in m["per_query"]] == [GALLERY[INTENDED[q.text]].text for q in QUERIES]


def test_a_constant_encoder_scores_chance():
    m = probe.evaluate(ConstantEncoder(), GALLERY, QUERIES, CONTRASTS)
    labels = [item.action for item in GALLERY if item.action is not None]
    expected_nn = np.mean([labels.count(q.action) / len(labels) for q in QUERIES])  # random tie-break
    assert m["nn_acc"] == pytest.approx(expected_nn)
    assert m["centroid_acc"] == pytest.approx(1 / len(set(labels)))
    assert m["contrast"] == {"order": 0.5, "side": 0.5}
    assert m["nn_cos"] == pytest.approx(1.0) and m["pair_cos"] == pytest.approx(1.0)


def test_an_encoder_that_confuses_left_and_right_scores_zero_on_side():
    table = dict(oracle().table)
    table["q-left"], table["q-right"] = table["q-right"], table["q-left"]
    m = probe.evaluate(LookupEncoder(table), GALLERY, QUERIES, CONTRASTS)
    assert m["contrast"] == {"order": 1.0, "side": 0.0}
    assert m["nn_acc"] == 1.0  # the action itself is still right


def test_contrasts_whose_programs_are_missing_from_the_gallery_are_left_out_and_listed():
    missing = Contrast("q-jump", "count", (step("jump", reps=1),), (step("jump", reps=3),))
    table = dict(oracle().table, **{"q-jump": np.ones(len(GALLERY))})
    m = probe.evaluate(LookupEncoder(table), GALLERY, QUERIES, [*CONTRASTS, missing])
    assert m["uncovered_contrasts"] == ["q-jump"] and "count" not in m["contrast"]


def test_retrieval_scores_split_a_tie_between_right_and_wrong():
    gallery = np.array([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    r = probe.retrieval_scores(np.array([[1.0, 0.0]]), ["a"], gallery, ["a", "b", "b"])
    assert r["nn_acc"] == pytest.approx(0.5)  # two captions tie: one "a", one "b"
    assert r["centroid_acc"] == 1.0  # the "a" centroid is (1, 0); "b"'s is (0.71, 0.71)


def test_mcnemar_counts_the_discordant_queries_and_gives_the_exact_binomial_p():
    base = [1, 1, 1, 0, 0, 1]
    other = [0, 0, 1, 1, 0, 1]
    assert probe.mcnemar(base, other) == (2, 1, 1.0)
    assert probe.mcnemar([1] * 6, [0] * 6) == (6, 0, pytest.approx(2 / 64))
    assert probe.mcnemar([1, 0], [1, 0]) == (0, 0, 1.0)


def test_fake_encoders_fit_the_text_encoder_protocol():
    assert isinstance(oracle(), TextEncoder) and isinstance(ConstantEncoder(), TextEncoder)


# --------------------------------------------------------------------------------------------- runner


def test_run_skips_an_encoder_that_is_not_installed_and_tabulates_the_rest(tmp_path):
    def loader(name, threads, cache_dir, clip_path):
        if name == "missing":
            raise ImportError("No module named 'missing'")
        return probe.Candidate(oracle(), "none", [], [])

    messages: list[str] = []
    results = probe.run(["missing", "oracle"], GALLERY, 1, tmp_path, loader=loader, log=messages.append,
                        queries=QUERIES, contrasts=CONTRASTS)
    assert [r.name for r in results] == ["oracle"]
    assert messages[0].startswith("missing: skipped, not available here (ImportError")
    table = probe.format_table(results).splitlines()
    assert table[0].startswith("| encoder | dim |") and table[2].startswith("| oracle | 8 | none | 1.000 | 1.000 |")


def test_the_gallery_comes_from_the_dataset_generator():
    gallery = probe.build_gallery(num_motions=12)
    again = probe.build_gallery(num_motions=12)
    assert gallery == again and len(gallery) > 10
    assert [item.text for item in gallery] == sorted({item.text for item in gallery})
    for item in gallery:
        for program in item.programs:
            assert program and all(seg.kind in ACTIONS for seg in program)
    assert any(item.action is not None for item in gallery)


# --------------------------------------------------------------------------------------------- slow


@pytest.mark.slow
def test_every_contrast_has_both_programs_in_the_full_training_gallery():
    gallery = probe.build_gallery()
    vocab = [item.text for item in gallery]
    assert probe.held_out_violations(probe.all_query_texts(), vocab, probe.FUNCTION_WORDS) == []
    for c in probe.CONTRASTS:
        assert len(probe.pattern_index(gallery, c.target, c.contrast)) > 0, c.text
        assert len(probe.pattern_index(gallery, c.contrast, c.target)) > 0, c.text


@pytest.mark.slow
@pytest.mark.usefixtures("one_thread")
def test_the_packaged_minilm_runs_through_the_probe(tmp_path):
    gallery = probe.build_gallery(num_motions=40)
    results = probe.run(["minilm"], gallery, 1, tmp_path, log=lambda _: None)
    (r,) = results
    assert r.dim == 384 and 0.0 <= r.nn_acc <= 1.0 and r.sentences_per_s > 0
    assert r.weights_bytes > 10_000_000 and r.package_bytes >= r.weights_bytes
