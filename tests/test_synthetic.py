"""The embedded synthetic dataset: physics, speeds, captions, determinism, splits, mirroring."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import numpy as np
import pytest

from data.humanml3d import read_captions, read_split
from data.paraphrase_text import SHARED_WORDS, held_out_violations
from data.physics import foot_skating_ratio, skating_frames
from data.skeleton import HUMANML3D
from data.synthetic import (
    SPLITS,
    SyntheticConfig,
    _choose_kind,
    _segment,
    dataset_stats,
    generate,
    generate_motion,
    ground_speed,
    make_splits,
    mirror_joints,
    mirror_motion,
    mirror_segment,
)
from data.synthetic_library import ACTIONS, LABELS, Segment
from data.synthetic_motion import initial_state, realize, sample_body
from data.synthetic_text import (
    BASE,
    CLAUSES,
    GERUND,
    LEXICON,
    PAST,
    THIRD,
    Subject,
    describe,
    fill_template,
    mirror_caption,
    past_tense,
)
from stages import make_dataset

SMOKE = SyntheticConfig(num_motions=75, previews=1, workers=1)
SEED = 123
POS_TAGS = {"VERB", "NOUN", "DET", "ADP", "NUM", "AUX", "PRON", "ADJ", "ADV", "PART", "CCONJ", "SCONJ"}


@pytest.fixture(scope="module")
def motions():
    return list(generate(SMOKE, SEED))


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("synthetic") / "dataset"
    stats = make_dataset.build_dataset(root, SMOKE, SEED)
    return root, stats


FEW_SPLITS = {"train": 0.5, "val": 0.25, "test": 0.25}  # a motion in every split of a handful

def _files_digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


# --- bodies and physics ----------------------------------------------------------------------


def test_bone_lengths_are_constant_within_each_motion(motions):
    worst = max(float(HUMANML3D.bone_lengths_of(m.joints).std(axis=0).max()) for m in motions)
    assert worst < 1e-5


def test_bodies_vary_and_have_adult_proportions(motions):
    pelvis = np.array([m.joints[0, 0, 1] for m in motions if not m.clip_id.startswith("M")])
    standing = pelvis[pelvis > 0.8]  # motions that start standing
    assert standing.min() >= 0.88 and standing.max() <= 1.01
    legs = {round(float(HUMANML3D.bone_lengths_of(m.joints[:1])[0, 4]), 4) for m in motions}
    assert len(legs) > 20


def test_no_joint_below_the_floor(motions):
    assert min(float(m.joints[..., 1].min()) for m in motions) >= -0.01


def test_feet_rest_on_the_floor_when_standing_still(motions):
    for m in motions:
        lead_in = m.joints[: m.windows[0][0]]
        assert np.abs(lead_in[:, [10, 11], 1]).max() < 0.01, m.clip_id


def test_foot_skating_ratio_of_the_dataset_is_below_five_percent(motions):
    frames = np.concatenate([skating_frames(m.joints, HUMANML3D) for m in motions])
    assert frames.mean() < 0.05
    assert max(foot_skating_ratio(m.joints, HUMANML3D) for m in motions) < 0.2


def test_jumps_leave_the_floor_on_a_ballistic_arc():
    body = sample_body(np.random.default_rng(0))
    params = dict(reps=1, distance=0.0, height=0.3, pause=0.2)
    piece = ACTIONS["jump"].build(body, initial_state(body), params)
    joints = realize(piece.plan, body)
    lowest = joints[..., 1].min(axis=1)
    air = np.flatnonzero(lowest > 0.02)
    assert len(air) >= 6  # about half a second in the air
    root = joints[air, 0, 1].astype(np.float64)
    accel = np.diff(root, 2) * 20.0**2
    assert np.allclose(accel[1:-1], -9.81, atol=1.5)


@pytest.mark.parametrize("kind", sorted(ACTIONS))
def test_every_action_is_physically_plausible(kind):
    rng = np.random.default_rng(7)
    for _ in range(4):
        body = sample_body(rng)
        state = initial_state(body, float(rng.uniform(-3, 3)), ACTIONS[kind].postures[0])
        joints = realize(ACTIONS[kind].build(body, state, ACTIONS[kind].sample(rng)).plan, body)
        assert HUMANML3D.bone_lengths_of(joints).std(axis=0).max() < 1e-5
        assert joints[..., 1].min() >= -0.01
        assert foot_skating_ratio(joints, HUMANML3D) < 0.05


def test_walking_and_running_speeds_are_human(motions):
    speeds: dict[str, list[float]] = {"walk": [], "run": []}
    for m in motions:
        for segment, window in zip(m.segments, m.steady, strict=True):
            p = segment.params
            straight = segment.kind == "walk" and p["direction"] == "forward" and not p["veer"]
            if window is not None and (straight or segment.kind == "run"):
                speeds["walk" if straight else "run"].append(ground_speed(m.joints, window))
    assert speeds["walk"] and speeds["run"]
    assert 0.8 <= min(speeds["walk"]) and max(speeds["walk"]) <= 1.8
    assert 2.5 <= min(speeds["run"]) and max(speeds["run"]) <= 4.0


def test_locomotion_keeps_the_pelvis_up():
    """Walking and running lower the pelvis only a little (legs reach every planted foot)."""
    rng = np.random.default_rng(11)
    for kind, params in (("walk", dict(direction="forward", speed=1.78, move_time=3.0, veer=None, lead="left")),
                         ("run", dict(speed=3.95, move_time=5.0, lead="right")),
                         ("run", dict(speed=2.6, move_time=3.0, lead="left")),
                         ("jog", dict(speed=2.5, move_time=3.5, lead="left"))):
        for height in ((0.9, 0.91), (0.99, 1.0)):
            body = sample_body(rng, height)
            joints = realize(ACTIONS[kind].build(body, initial_state(body), params).plan, body)
            assert joints[:, 0, 1].min() > 0.8 * body.stand_height, (kind, params, height)


# --- library, labels, lengths ------------------------------------------------------------------


def test_library_and_labels(motions):
    assert len(ACTIONS) >= 20
    assert 12 <= len(LABELS) <= 20
    assert {m.label for m in motions} <= set(LABELS)
    assert len({m.label for m in motions}) >= 12
    assert any(len(m.segments) == 3 for m in motions) and any(len(m.segments) == 1 for m in motions)
    assert any(s.upper is not None for m in motions for s in m.segments)


def test_only_single_action_motions_carry_a_dataset_label(motions):
    """actions.txt labels are unambiguous: one segment, no upper-body action on top; others get none."""
    labelled = [m for m in motions if m.action is not None]
    for m in motions:
        single = len(m.segments) == 1 and m.segments[0].upper is None
        assert (m.action is not None) == single, (m.clip_id, m.segments)
        assert m.clip().action == m.action
        if single:
            assert m.action == m.label == m.segments[0].label
    assert 0.2 * len(motions) < len(labelled) < 0.6 * len(motions)
    assert any(len(m.segments) == 1 and m.segments[0].upper is not None and m.action is None for m in motions)
    originals = {m.clip_id: m.action for m in motions if not m.clip_id.startswith("M")}
    assert all(m.action == originals[m.clip_id[1:]] for m in motions if m.clip_id.startswith("M"))
    stats = dataset_stats(motions)
    assert sum(stats["labelled_actions"].values()) == len(labelled)
    assert stats["labelled_actions"] == {a: sum(m.action == a for m in labelled) for a in stats["labelled_actions"]}


def test_lengths_are_within_bounds(motions):
    lengths = [len(m.joints) for m in motions]
    assert min(lengths) >= SMOKE.min_joint_frames and max(lengths) <= SMOKE.max_joint_frames


# --- captions ----------------------------------------------------------------------------------

_SIDES = {"left", "right"}
_ROTATIONS = {"clockwise": "clockwise", "counterclockwise": "counterclockwise", "anticlockwise": "counterclockwise"}


def _allowed_sides(segment: Segment) -> set[str]:
    """Side words a correct caption of this segment may use."""
    p = segment.params
    sides: set[str] = set()
    if segment.kind == "circle":
        sides.add("left" if p["direction"] == "counterclockwise" else "right")
    if segment.kind == "look_around":
        sides |= _SIDES
    for key in ("side", "veer", "mode"):
        if p.get(key) in _SIDES:
            sides.add(p[key])
    if segment.kind in ("walk", "turn") and p["direction"] in _SIDES:
        sides.add(p["direction"])
    return sides | (set() if segment.upper is None else _allowed_sides(segment.upper))


def _words(text: str) -> list[str]:
    return re.findall(r"[a-z]+", text.lower())


#: Words that state a number of repetitions ("once" and "one" also say other things: "once done", "on one leg").
_COUNT_WORDS = {"twice": 2, "thrice": 3, "couple": 2, "pair": 2, "two": 2, "three": 3, "four": 4, "five": 5, "six": 6,
                "seven": 7}
#: Words of speed that only a slow or only a fast segment may use.
_SPEED_WORDS = {"slow": {"slowly", "slow", "leisurely"},
                "fast": {"quickly", "briskly", "fast", "hurriedly", "quick", "brisk", "hastily", "energetically",
                         "haste", "hurried"}}


def _reps(segments: list[Segment]) -> set[int]:
    """Repetition counts of the segments and of their upper-body actions."""
    out = set()
    for s in segments:
        out |= {s.params["reps"]} if "reps" in s.params else set()
        out |= set() if s.upper is None else _reps([s.upper])
    return out


def _check_caption(text: str, segments: list[Segment]) -> None:
    words = set(_words(text))
    allowed = set().union(*(_allowed_sides(s) for s in segments))
    assert words & _SIDES <= allowed, text
    rotations = {_ROTATIONS[w] for w in words if w in _ROTATIONS}
    assert rotations <= {s.params["direction"] for s in segments if s.kind == "circle"}, text
    if words & {"backward", "backwards"}:
        assert any(s.kind == "walk" and s.params["direction"] == "backward" for s in segments), text
    assert {_COUNT_WORDS[w] for w in words if w in _COUNT_WORDS} <= _reps(segments), text


def test_captions_state_sides_and_directions_consistently(motions):
    for m in motions:
        for c in m.captions:
            if c.is_whole_clip:
                _check_caption(c.text, m.segments)
            else:
                span = (round(c.start * 20), round(c.end * 20))
                segment = [s for s, (a, b) in zip(m.segments, m.windows, strict=True) if a == span[0]]
                assert len(segment) == 1, (m.clip_id, c)
                _check_caption(c.text, segment)


def test_sided_single_actions_name_their_side(motions):
    for m in motions:
        if len(m.segments) == 1 and m.segments[0].kind in ("kick", "punch", "wave", "hop", "throw"):
            side = m.segments[0].params["side"]
            if side in _SIDES:
                assert all(side in _words(c.text) for c in m.captions), m.clip_id


def test_captions_have_hml3d_tokens(motions):
    spans = 0
    for m in motions:
        whole = [c for c in m.captions if c.is_whole_clip]
        assert len(whole) >= 3 and len({c.text for c in whole}) == len(whole)
        for c in m.captions:
            assert c.tokens and {pos for _, pos in c.tokens} <= POS_TAGS
            for word, pos in c.tokens:
                if pos in ("NOUN", "VERB") and word in LEXICON:
                    assert LEXICON[word][1] == word or LEXICON[word][0] != pos, (word, pos, c.text)
                assert word.isalpha() and word == word.lower()
            if not c.is_whole_clip:
                spans += 1
                assert 0 <= c.start < c.end <= (len(m.joints) - 1) / 20 and (c.end - c.start) * 20 >= 40
    assert spans > 0


def _filled(segment: Segment) -> list[str]:
    """Every clause template of the segment, filled for a subject, in every verb form."""
    subject = Subject("a person", "his", "himself")
    return [" ".join(w for w, _ in fill_template(t, subject, form)) for t in CLAUSES[segment.kind](segment.params)
            for form in (THIRD, GERUND, BASE, PAST)]


@pytest.mark.parametrize("kind", sorted(ACTIONS))
def test_every_clause_template_states_the_segments_count_side_direction_and_pace(kind):
    """Each wording of each sampled segment (and of its mirror): sides, turning directions and counts are
    exactly the segment's (one repetition: "once" or nothing), adverbs of speed agree with its pace and
    a sided single action always names its side."""
    rng = np.random.default_rng(3)
    for _ in range(40):
        original = Segment(kind, ACTIONS[kind].sample(rng))
        for segment in (original, mirror_segment(original)):
            p = segment.params
            for text in _filled(segment):
                words = set(_words(text))
                _check_caption(text, [segment])
                if p.get("reps", 1) == 1:
                    assert not words & set(_COUNT_WORDS), text
                if "once" in words and kind != "turn":  # a turn may spin around once
                    assert p["reps"] == 1, text
                pace = p.get("pace")
                if pace is not None:
                    assert not words & set().union(*(w for k, w in _SPEED_WORDS.items() if k != pace)), text
                if kind in ("kick", "punch", "wave", "hop", "throw") and p["side"] in _SIDES:
                    assert p["side"] in words, text
    assert len(CLAUSES[kind](ACTIONS[kind].sample(rng))) >= 5  # many ways to say each action


def _programs(n: int) -> list[tuple[list[Segment], list[str]]]:
    """(segments, starting postures) of ``n`` action programs drawn as data/synthetic.py draws them
    (postures chained, upper-body actions on carriers), without building their motions."""
    config = SyntheticConfig()
    out = []
    for i in range(n):
        rng = np.random.default_rng([0, i])
        posture = "sit" if rng.random() < config.seated_start else "stand"
        target = 1 + int(rng.choice(len(config.actions_per_motion), p=np.asarray(config.actions_per_motion)))
        segments: list[Segment] = []
        postures: list[str] = []
        for _ in range(target):
            kind = _choose_kind(rng, posture, segments[-1].kind if segments else None)
            segments.append(_segment(rng, kind, config.mix_prob, {s.kind for s in segments}))
            postures.append(posture)
            posture = {"sit_down": "sit", "stand_up": "stand"}.get(kind, posture)
        out.append((segments, postures))
    return out


@pytest.fixture(scope="module")
def caption_sample():
    """(captions, segments) of 400 programs' captions and their mirrors: 3-5 whole-clip captions each and
    span captions of 3-second segments (the first 400 of :func:`_programs`)."""
    out = []
    for i, (segments, postures) in enumerate(_programs(400)):
        windows = [(10 + 60 * k, 70 + 60 * k) for k in range(len(segments))]
        count = int(np.random.default_rng([0, i]).integers(3, 6))
        captions = describe(segments, windows, postures, 80 + 60 * len(segments), np.random.default_rng([1, i]),
                            count, 0.3)
        for caps, segs in ((captions, segments), ([mirror_caption(c) for c in captions],
                                                  [mirror_segment(s) for s in segments])):
            for c in caps:
                out.append((c, segs if c.is_whole_clip else [segs[(round(c.start * 20) - 10) // 60]]))
    return out


#: Distinct words and distinct (word, POS) tokens of the caption sample as the grammar wrote it before it was
#: widened (commit f461315).
_NARROW_WORDS, _NARROW_TOKENS = 269, 206


def test_the_caption_vocabulary_is_wide_and_in_the_lexicon(caption_sample):
    words = {w for c, _ in caption_sample for w in _words(c.text)}
    assert len(words) >= 2.5 * _NARROW_WORDS
    assert len({token for c, _ in caption_sample for token in c.tokens}) >= 2 * _NARROW_TOKENS
    assert words <= set(LEXICON)  # inflected verbs too: the held-out checks see every written word


def test_sample_captions_state_counts_sides_and_directions(caption_sample):
    for c, segments in caption_sample:
        _check_caption(c.text, segments)
    texts = [c.text for c, _ in caption_sample]
    for phrase in ("twice", "three times", "in a row", "forwards", "after that", "is seen", "a boy", "walked"):
        assert any(phrase in t for t in texts), phrase


def test_past_tense_and_verb_forms():
    assert [past_tense(v) for v in ("walk", "step", "hurry", "stay", "wave", "run", "propel", "jog")] == [
        "walked", "stepped", "hurried", "stayed", "waved", "ran", "propelled", "jogged"]
    subject = Subject("a boy", "his", "himself")
    assert [" ".join(w for w, _ in fill_template("~hop on {poss} left foot", subject, form))
            for form in (THIRD, GERUND, BASE, PAST)] == [
        "hops on his left foot", "hopping on his left foot", "hop on his left foot", "hopped on his left foot"]
    assert "bent" not in LEXICON  # a held-out paraphrase word: "bend" is never said in the past tense


def test_verbs_and_nouns_are_lemmatised():
    from data.synthetic_text import tokens_of

    words = [("walks", "walk"), ("slowly", None), ("with", None), ("both", None), ("hands", None),
             ("three", None), ("times", None), ("left", None)]
    assert tokens_of(words) == (("walk", "VERB"), ("slowly", "ADV"), ("with", "ADP"), ("both", "DET"),
                                ("hand", "NOUN"), ("three", "NUM"), ("time", "NOUN"), ("left", "ADJ"))


# --- mirroring -------------------------------------------------------------------------------


_MIRRORED = {"left": "right", "right": "left", "clockwise": "counterclockwise", "counterclockwise": "clockwise",
             "anticlockwise": "clockwise"}


def test_mirroring_swaps_sides_in_joints_and_captions(motions):
    originals = {m.clip_id: m for m in motions if not m.clip_id.startswith("M")}
    for m in motions:
        if not m.clip_id.startswith("M"):
            continue
        base = originals[m.clip_id[1:]]
        assert np.array_equal(m.joints, mirror_joints(base.joints))
        assert [c.to_line() for c in m.captions] == [mirror_caption(c).to_line() for c in base.captions]
        for a, b in zip(base.captions, m.captions, strict=True):
            assert _words(b.text) == [_MIRRORED.get(w, w) for w in _words(a.text)]


def test_the_named_limb_moves_in_originals_and_mirrors(motions):
    checked = 0
    for m in motions:
        for segment, (a, b) in zip(m.segments, m.windows, strict=True):
            side = segment.params.get("side")
            if segment.kind not in ("kick", "wave") or side not in _SIDES:
                continue
            joints = (10, 11) if segment.kind == "kick" else (20, 21)  # left first
            height = m.joints[a:b, list(joints), 1].max(axis=0)
            assert (height[0] > height[1]) == (side == "left"), (m.clip_id, segment)
            checked += 1
    assert checked >= 4


def test_mirror_of_mirror_is_the_original(motions):
    m = next(m for m in motions if not m.clip_id.startswith("M"))
    twice = mirror_motion(mirror_motion(m))
    assert np.array_equal(twice.joints, m.joints)
    assert [c.text for c in twice.captions] == [c.text.replace("anticlockwise", "counterclockwise") for c in m.captions]


# --- determinism and speed -------------------------------------------------------------------


@pytest.mark.slow  # generates the motions three times, once in a process pool
def test_same_seed_same_motions_regardless_of_workers():
    config = SyntheticConfig(num_motions=12, workers=1)
    one = [(m.clip_id, m.joints.tobytes(), [c.to_line() for c in m.captions]) for m in generate(config, 5)]
    again = [(m.clip_id, m.joints.tobytes(), [c.to_line() for c in m.captions]) for m in generate(config, 5)]
    two = [(m.clip_id, m.joints.tobytes(), [c.to_line() for c in m.captions])
           for m in generate(SyntheticConfig(num_motions=12, workers=2), 5)]
    assert one == again == two
    other = generate_motion(6, 0, config)
    assert other.joints.tobytes() != one[0][1]


@pytest.mark.slow  # builds the dataset (with GIF previews) twice
def test_same_seed_gives_byte_identical_files(tmp_path):
    config = SyntheticConfig(num_motions=10, previews=1, workers=1, splits=FEW_SPLITS)
    make_dataset.build_dataset(tmp_path / "a", config, 9)
    make_dataset.build_dataset(tmp_path / "b", config, 9)
    digest = _files_digest(tmp_path / "a")
    assert digest == _files_digest(tmp_path / "b")
    assert any(name.endswith(".gif") for name in digest) and "stats.json" in digest


# --- the written dataset (slow: the fixture builds it, previews included) ------------------------


@pytest.mark.slow
def test_every_split_id_has_a_motion_and_captions(dataset, motions):
    root, _ = dataset
    ids = {name: (root / f"{name}.txt").read_text().split() for name in SPLITS}
    everything = [i for name in SPLITS for i in ids[name]]
    assert len(everything) == len(set(everything)) == 2 * SMOKE.num_motions
    for clip_id in everything:
        assert (root / "new_joints" / f"{clip_id}.npy").is_file()
        assert (root / "texts" / f"{clip_id}.txt").read_text().strip()
    for name in SPLITS:
        originals = [i for i in ids[name] if not i.startswith("M")]
        assert {"M" + i for i in originals} == {i for i in ids[name] if i.startswith("M")}
        assert abs(len(originals) / SMOKE.num_motions - SMOKE.splits[name]) < 0.02
    actions = dict(line.split(",") for line in (root / "actions.txt").read_text().split())
    single = {m.clip_id: m.action for m in motions if m.action is not None}  # single-action motions only
    assert actions == single and set(actions) < set(everything) and set(actions.values()) <= set(LABELS)


@pytest.mark.slow
def test_the_reader_accepts_the_dataset(dataset):
    root, _ = dataset
    items = sum(len(read_split(root, name, HUMANML3D, source="joints").items) for name in SPLITS)
    assert items > 2 * SMOKE.num_motions  # whole clips plus span items


@pytest.mark.slow
def test_the_test_clips_and_only_they_get_held_out_paraphrases(dataset):
    root, stats = dataset
    test_ids = (root / "test.txt").read_text().split()
    assert sorted(p.stem for p in (root / "paraphrases").glob("*.txt")) == sorted(test_ids)
    texts = [c.text for i in test_ids for c in read_captions(root / "paraphrases" / f"{i}.txt")]
    assert len(texts) == stats["paraphrases"]["captions"] >= SMOKE.paraphrases * len(test_ids)
    assert held_out_violations(texts, LEXICON, SHARED_WORDS) == []


@pytest.mark.slow
def test_previews_and_stats_are_written(dataset, motions):
    root, stats = dataset
    assert (root / "preview" / "contact_sheet.png").stat().st_size > 10_000
    assert len(list((root / "preview").glob("*.gif"))) == SMOKE.previews
    assert json.loads((root / "stats.json").read_text()) == stats
    assert {k: v for k, v in stats.items() if k != "paraphrases"} == dataset_stats(motions)
    assert stats["motions"] == 2 * SMOKE.num_motions and stats["foot_skating_ratio"] < 0.05
    assert stats["lowest_joint_m"] >= -0.01 and stats["vocabulary_size"] > 100
    assert {"walk_forward", "run"} <= set(stats["mean_speed_mps"])
    assert sum(stats["length_histogram"]["counts"]) == stats["motions"]


def test_a_failed_build_leaves_no_dataset(tmp_path, monkeypatch):
    def crash(*args, **kwargs):
        raise RuntimeError("boom")

    monkeypatch.setattr(make_dataset, "write_previews", crash)
    with pytest.raises(RuntimeError, match="boom"):
        make_dataset.build_dataset(tmp_path / "dataset", SyntheticConfig(num_motions=4, previews=1, workers=1,
                                                                                   splits=FEW_SPLITS), 1)
    assert list(tmp_path.iterdir()) == []


def test_stage_main_reads_params_and_never_writes_data_root(tmp_path):
    """The stage writes <paths.artifacts>/dataset; data.root (a user's real dataset) stays untouched."""
    users = tmp_path / "HumanML3D"
    users.mkdir()
    (users / "train.txt").write_text("000001\n")
    root = tmp_path / "dataset"
    make_dataset.main([f"paths.artifacts={tmp_path}", f"data.root={users}", "+synthetic.num_motions=6",
                       "+synthetic.previews=0", "+synthetic.workers=1", "+synthetic.mirror=false",
                       "synthetic.splits={train: 0.5, val: 0.25, test: 0.25}"])
    assert len((root / "train.txt").read_text().split()) + len((root / "test.txt").read_text().split()) + len(
        (root / "val.txt").read_text().split()) == 6
    assert [p.name for p in users.iterdir()] == ["train.txt"] and (users / "train.txt").read_text() == "000001\n"


def test_config_rejects_unknown_and_bad_params():
    with pytest.raises(ValueError, match="unknown synthetic params"):
        SyntheticConfig.from_params({"num_motion": 3})
    with pytest.raises(ValueError, match="splits"):
        SyntheticConfig.from_params({"splits": {"train": 0.5, "val": 0.1, "test": 0.1}})
    assert SyntheticConfig.from_params({"pelvis_height": [0.9, 0.95]}).pelvis_height == (0.9, 0.95)



@pytest.mark.parametrize(("section", "message"), [
    ({"splits": {"train": 1.2, "val": -0.2, "test": 0.0}}, "fractions in [0, 1]"),  # wrote a 32-id val split
    ({"pelvis_height": [-1.0, -0.9]}, "0 < min <= max, got [-1.0, -0.9]"),  # wrote upside-down bodies
    ({"actions_per_motion": [1.5, -0.5]}, "probabilities (>= 0) summing to 1, got [1.5, -0.5]"),
    ({"span_prob": 1.5}, "synthetic.span_prob: expected a probability in [0, 1], got 1.5"),
    ({"workers": 0}, "workers >= 1"),
])
def test_config_refuses_values_that_wrote_a_wrong_dataset(section: dict, message: str) -> None:
    """Each was accepted and wrote a dataset a later stage refused or, worse, one that read."""
    with pytest.raises(ValueError) as err:
        SyntheticConfig.from_params(section)
    assert message in str(err.value)


def test_a_split_left_empty_is_refused_before_any_motion_is_made() -> None:
    """``num_motions=10`` with the default fractions wrote an empty val.txt, which extract_features refused."""
    with pytest.raises(ValueError, match=re.escape("synthetic.splits: {'train': 0.8, 'val': 0.05, 'test': 0.15} of "
                                                   "synthetic.num_motions=10 leaves a split empty ({'train': 8, "
                                                   "'val': 0, 'test': 2})")):
        make_splits(10, SyntheticConfig().splits, 0, mirror=False)
    assert [len(ids) for ids in make_splits(20, SyntheticConfig().splits, 0, mirror=False).values()] == [16, 1, 3]


def test_a_frame_budget_with_no_room_for_an_action_is_an_error_not_a_hang() -> None:
    """``max_joint_frames=40`` drew action programs forever; a bounded number of draws names the key."""
    config = SyntheticConfig(num_motions=1, min_joint_frames=2, max_joint_frames=40, mirror=False, previews=0)
    with pytest.raises(ValueError, match=r"synthetic.max_joint_frames: 40 frames left no room for an action after "
                                         r"motion 0's lead-in and tail in 100 tries"):
        generate_motion(0, 0, config)
