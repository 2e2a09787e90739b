"""The held-out paraphrase grammar: a vocabulary disjoint from the training captions', stating the same facts."""

import numpy as np
import pytest

from data import synthetic_text
from data.paraphrase_text import (
    CLAUSES,
    PARAPHRASE_LEXICON,
    SHARED_WORDS,
    held_out_violations,
    paraphrase,
    paraphrases,
    stem,
    words_of,
)
from data.synthetic import SyntheticConfig, generate_motion, mirror_motion
from data.synthetic_library import ACTIONS, Segment


def test_no_paraphrase_word_outside_the_shared_ones_is_a_training_word_in_any_form():
    assert held_out_violations(list(PARAPHRASE_LEXICON), synthetic_text.LEXICON, SHARED_WORDS) == []
    assert SHARED_WORDS >= {"left", "right", "hand", "the", "three"} and "walk" not in PARAPHRASE_LEXICON


def test_every_action_has_paraphrase_clauses():
    assert set(CLAUSES) == set(synthetic_text.CLAUSES) == set(ACTIONS)


def test_held_out_check_catches_a_leaked_word_as_it_is_and_inflected():
    vocab = ["a person kicks with the left leg", "someone walks"]
    texts = ["a guy kicked the ball with the left shin", "somebody walking", "a lady punts"]
    assert held_out_violations(texts, vocab, frozenset({"a", "the", "with", "left"})) == [
        ("a guy kicked the ball with the left shin", "kicked"),
        ("somebody walking", "walking"),
    ]
    assert held_out_violations(["left"], ["left"], allowed=frozenset()) == [("left", "left")]


def test_stem_maps_inflections_together():
    assert {stem(w) for w in ("walk", "walks", "walked", "walking")} == {"walk"}
    assert stem("rises") == stem("rise") and stem("knees") == stem("knee")


@pytest.mark.parametrize("seed", range(8))
def test_paraphrases_state_the_side_the_count_and_the_order(seed):
    rng = np.random.default_rng(seed)
    kick = Segment("kick", {"side": "left", "reps": 3, "height": 0.6})
    walk_back = Segment("walk", {"direction": "backward", "pace": "normal"})
    words = words_of(paraphrase([kick, walk_back], rng).text)
    assert "left" in words and "right" not in words and "three" in words
    kick_at = max(i for i, w in enumerate(words) if w in {"strike", "strikes", "lash", "lashes", "punt", "punts",
                                                          "striking", "lashing", "punting"})
    back_at = min(i for i, w in enumerate(words) if w in {"retreat", "retreats", "retreating", "withdraw",
                                                          "withdraws", "withdrawing", "recede", "recedes",
                                                          "receding", "reverse", "reverses", "reversing"})
    assert kick_at < back_at  # "... kicks ..., afterwards retreats", or "... before retreating"
    assert "three" not in words_of(paraphrase([Segment("kick", {"side": "right", "reps": 1, "height": 0.6})],
                                              rng).text)


def test_a_generated_motion_gets_distinct_paraphrases_for_the_clip_and_each_span():
    config = SyntheticConfig(num_motions=40, workers=1)
    motion = next(m for m in (generate_motion(0, i, config) for i in range(40))
                  if any(not c.is_whole_clip for c in m.captions))
    spans = [c for c in motion.captions if not c.is_whole_clip]
    mirrored = mirror_motion(motion)
    for m in (motion, mirrored):
        out = paraphrases(m.segments, m.windows, m.postures, len(m.joints), spans, np.random.default_rng(0), 3)
        whole = [c for c in out if c.is_whole_clip]
        assert len(whole) == 3 and len({c.text for c in whole}) == 3
        assert {(c.start, c.end) for c in out if not c.is_whole_clip} == {(c.start, c.end) for c in spans}
        assert held_out_violations([c.text for c in out], synthetic_text.LEXICON, SHARED_WORDS) == []
    bad = spans[0].__class__("x", (("x", "NOUN"),), spans[0].start + 0.05, spans[0].end)
    with pytest.raises(ValueError, match="no segment's window"):
        paraphrases(motion.segments, motion.windows, motion.postures, len(motion.joints), [bad],
                    np.random.default_rng(0), 1)
