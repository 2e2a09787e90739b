"""Word vocabulary, POS classes and GloVe loading (data/vocab.py): known answers."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from data.vocab import (
    NUM_POS,
    OTHER,
    POS_CLASSES,
    POS_INDEX,
    VIP_WORDS,
    WordVocab,
    load_glove,
    pos_class,
    split_token,
)

CAPTIONS = [
    ["a/DET", "man/NOUN", "walk/VERB", "forward/ADV"],
    ["the/DET", "man/NOUN", "turn/VERB", "left/ADJ", "quickly/ADV"],
    ["a/DET", "person/NOUN", "walk/VERB", "in/ADP", "a/DET", "circle/NOUN"],
]


def classes_of(onehot: np.ndarray) -> list[int]:
    assert np.all(onehot.sum(-1) == 1.0)
    return onehot.argmax(-1).tolist()


def test_pos_enumeration_matches_reference() -> None:
    assert NUM_POS == 15
    assert POS_CLASSES[:9] == ("VERB", "NOUN", "DET", "ADP", "NUM", "AUX", "PRON", "ADJ", "ADV")
    assert [POS_INDEX[k] for k in ("Loc_VIP", "Body_VIP", "Obj_VIP", "Act_VIP", "Desc_VIP", "OTHER")] == [
        9, 10, 11, 12, 13, 14,
    ]
    assert OTHER == 14
    sizes = {k: len(v) for k, v in VIP_WORDS.items()}
    assert sizes == {"Loc_VIP": 12, "Body_VIP": 13, "Obj_VIP": 10, "Act_VIP": 34, "Desc_VIP": 12}
    all_words = [w for v in VIP_WORDS.values() for w in v]
    assert len(all_words) == len(set(all_words))  # disjoint lists


def test_pos_class_vip_override_and_unknown_pos() -> None:
    assert pos_class("walk", "VERB") == POS_INDEX["Act_VIP"]
    assert pos_class("left", "ADJ") == POS_INDEX["Loc_VIP"]
    assert pos_class("hand", "NOUN") == POS_INDEX["Body_VIP"]
    assert pos_class("chair", "NOUN") == POS_INDEX["Obj_VIP"]
    assert pos_class("slowly", "ADV") == POS_INDEX["Desc_VIP"]
    assert pos_class("man", "NOUN") == POS_INDEX["NOUN"]
    assert pos_class("man", "PROPN") == OTHER
    assert pos_class("man", "CCONJ") == OTHER


def test_split_token() -> None:
    assert split_token("walk/VERB") == ("walk", "VERB")
    assert split_token("a/b/NOUN") == ("a/b", "NOUN")
    for bad in ("walk", "/VERB", "walk/"):
        with pytest.raises(ValueError, match="word/POS"):
            split_token(bad)


def test_build_orders_by_count_and_applies_min_count() -> None:
    vocab = WordVocab.build(CAPTIONS, min_count=1)
    # a: 3, man: 2, walk: 2, then the singletons alphabetically
    assert vocab.words[:6] == ["sos", "eos", "unk", "a", "man", "walk"]
    assert vocab.words[6:] == sorted(["forward", "the", "turn", "left", "quickly", "person", "in", "circle"])
    assert (vocab.sos_id, vocab.eos_id, vocab.unk_id) == (0, 1, 2)
    vocab2 = WordVocab.build(CAPTIONS, min_count=2)
    assert vocab2.words == ["sos", "eos", "unk", "a", "man", "walk"]
    assert vocab2.id_of("circle") == vocab2.unk_id
    assert "circle" not in vocab2 and "WALK" in vocab2
    with pytest.raises(ValueError):
        WordVocab.build(CAPTIONS, min_count=0)


def test_encode_known_answer() -> None:
    vocab = WordVocab.build(CAPTIONS, min_count=2)  # sos eos unk a man walk
    tokens = ["A/DET", "man/NOUN", "Walk/VERB", "left/ADJ", "man/WEIRD", "circle/NOUN", "turn/VERB"]
    word_ids, pos, sent_len = vocab.encode_tokens(tokens)
    assert word_ids.dtype == np.int64 and word_ids.shape == (22,)
    assert pos.dtype == np.float32 and pos.shape == (22, 15)
    assert sent_len == 9
    # sos, a, man, walk, left(unk), man, circle(unk), turn(unk: a VIP word, but not in the vocab), eos, pad
    assert word_ids.tolist() == [0, 3, 4, 5, 2, 4, 2, 2, 1] + [2] * 13
    assert classes_of(pos) == [OTHER, 2, 1, 12, OTHER, OTHER, OTHER, OTHER, OTHER] + [OTHER] * 13


def test_vip_override_for_known_words() -> None:
    vocab = WordVocab.build(CAPTIONS)
    word_ids, pos, sent_len = vocab.encode_tokens(["walk/VERB", "left/ADJ", "forward/ADV", "quickly/ADV"])
    assert sent_len == 6
    assert word_ids[1:5].tolist() == [vocab.id_of(w) for w in ("walk", "left", "forward", "quickly")]
    assert classes_of(pos)[:6] == [OTHER, POS_INDEX["Act_VIP"], POS_INDEX["Loc_VIP"], POS_INDEX["Loc_VIP"],
                                   POS_INDEX["Desc_VIP"], OTHER]


def test_encode_truncates_at_max_words() -> None:
    vocab = WordVocab.build([[f"w{i}/NOUN" for i in range(30)]])
    many = [f"w{i}/NOUN" for i in range(25)]
    word_ids, pos, sent_len = vocab.encode_tokens(many)
    assert sent_len == 22
    assert word_ids[0] == vocab.sos_id and word_ids[21] == vocab.eos_id
    assert word_ids[1:21].tolist() == [vocab.id_of(f"w{i}") for i in range(20)]
    assert classes_of(pos) == [OTHER] + [1] * 20 + [OTHER]
    exact = vocab.encode_tokens(many[:20])
    assert exact[2] == 22 and np.array_equal(exact[0], word_ids)
    nineteen = vocab.encode_tokens(many[:19])
    assert nineteen[2] == 21 and nineteen[0][20] == vocab.eos_id and nineteen[0][21] == vocab.unk_id
    short = vocab.encode_tokens(many, max_words=3)
    assert short[0].tolist() == [0, vocab.id_of("w0"), vocab.id_of("w1"), vocab.id_of("w2"), 1]
    assert short[2] == 5


def test_encode_empty_and_batch() -> None:
    vocab = WordVocab.build(CAPTIONS)
    word_ids, pos, sent_len = vocab.encode_tokens([])
    assert sent_len == 2 and word_ids.tolist() == [0, 1] + [2] * 20
    assert classes_of(pos) == [OTHER] * 22
    ids, onehot, lens = vocab.encode_batch([CAPTIONS[0], [], CAPTIONS[2]])
    assert ids.shape == (3, 22) and onehot.shape == (3, 22, 15) and lens.tolist() == [6, 2, 8]
    assert np.array_equal(ids[2], vocab.encode_tokens(CAPTIONS[2])[0])
    with pytest.raises(TypeError):
        vocab.encode_tokens("walk/VERB")
    with pytest.raises(ValueError, match="word/POS"):
        vocab.encode_tokens(["walk"])


def test_dict_round_trip_through_json() -> None:
    vocab = WordVocab.build(CAPTIONS, lowercase=False)
    restored = WordVocab.from_dict(json.loads(json.dumps(vocab.to_dict())))
    assert restored == vocab and restored.lowercase is False
    assert restored.id_of("Walk") == restored.unk_id  # case-sensitive vocabulary
    with pytest.raises(ValueError, match="format"):
        WordVocab.from_dict({"words": vocab.words})
    bad = vocab.to_dict() | {"words": ["eos", "sos", "unk"]}
    with pytest.raises(ValueError, match="start with"):
        WordVocab.from_dict(bad)
    dup = vocab.to_dict() | {"words": ["sos", "eos", "unk", "a", "a"]}
    with pytest.raises(ValueError, match="duplicate"):
        WordVocab.from_dict(dup)


def write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def test_load_glove_known_values_and_seeded_missing(tmp_path: Path) -> None:
    vocab = WordVocab(["sos", "eos", "unk", "walk", "man", "circle"])
    path = write(tmp_path / "vec.txt", "the 9 9 9\nWalk 0.5 -1 2\nwalk 1 2 3\n\nman -0.25 0 1e-1\nzebra 7 7 7\n")
    table = load_glove(path, vocab, seed=3)
    assert table.dtype == np.float32 and table.shape == (6, 3)
    np.testing.assert_array_equal(table[3], [0.5, -1, 2])  # lower-cased "Walk" comes first and wins
    np.testing.assert_array_equal(table[4], np.float32([-0.25, 0, 0.1]))
    expected_missing = (np.random.default_rng(3).standard_normal((6, 3)) * 0.1).astype(np.float32)
    np.testing.assert_array_equal(table[[0, 1, 2, 5]], expected_missing[[0, 1, 2, 5]])
    np.testing.assert_array_equal(load_glove(path, vocab, seed=3), table)
    assert not np.array_equal(load_glove(path, vocab, seed=4)[5], table[5])
    assert np.abs(table[[0, 1, 2, 5]]).max() < 0.6  # small


def test_load_glove_errors_name_the_file(tmp_path: Path) -> None:
    vocab = WordVocab(["sos", "eos", "unk", "walk"])
    mismatch = write(tmp_path / "mismatch.txt", "walk 1 2 3\nrun 1 2\n")
    with pytest.raises(ValueError, match=r"mismatch\.txt:2.*2 values, expected 3"):
        load_glove(mismatch, vocab)
    with pytest.raises(ValueError, match=r"mismatch\.txt:1.*3 values, expected 4"):
        load_glove(mismatch, vocab, dim=4)
    nonnum = write(tmp_path / "nonnum.txt", "run 1 2\nwalk 1 x\n")
    with pytest.raises(ValueError, match=r"nonnum\.txt:2.*non-numeric"):
        load_glove(nonnum, vocab)
    bare = write(tmp_path / "bare.txt", "walk\n")
    with pytest.raises(ValueError, match=r"bare\.txt:1.*malformed"):
        load_glove(bare, vocab)
    empty = write(tmp_path / "empty.txt", "\n\n")
    with pytest.raises(ValueError, match=r"empty\.txt.*empty"):
        load_glove(empty, vocab)
    binary = tmp_path / "binary.txt"
    binary.write_bytes(b"walk \xff\xfe 1\n")
    with pytest.raises(ValueError, match=r"binary\.txt.*UTF-8"):
        load_glove(binary, vocab)
    with pytest.raises(FileNotFoundError):
        load_glove(tmp_path / "absent.txt", vocab)
