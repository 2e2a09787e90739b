"""Held-out paraphrases of the synthetic motions: a second grammar whose vocabulary training never sees.

The paraphrase protocol (``pipelines/paraphrase.py``; issue 18) asks every headline model for the
test motions again, from captions worded by this module instead of :mod:`data.synthetic_text`. The
grammar states the same facts of each segment -- the action, its side, direction, speed and count,
the order of the segments and an upper-body action on top -- so a caption that says three bounces
describes a motion with three jumps, but in words the training captions never use: every word of
:data:`PARAPHRASE_LEXICON` outside :data:`SHARED_WORDS` is absent from the training grammar's
:data:`~data.synthetic_text.LEXICON`, also after stripping inflections (:func:`held_out_violations`;
a test checks the whole vocabulary). :data:`SHARED_WORDS` are what no paraphrase of a motion can avoid
or swap: articles, pronouns, prepositions and conjunctions, numbers, "left"/"right" and the body-part
nouns (hand, arm, leg, foot, head, fist, knee).

Choices, where the paraphrases could go either way:

- Counts are said with numbers ("in a series of three", "three knee dips"), never "twice" or
  "three times" (training words); one repetition is not said.
- Turning directions are said with sides ("toward the left", "leftward"), never "clockwise".
- A motion that starts seated says so in its subject ("a lady on a stool"), as the training
  captions' "a seated man" does; "seated" and "sitting" are training words.

:func:`paraphrases` writes HumanML3D :class:`~data.humanml3d.Caption` lines (text, POS tokens and
span), so the set is read with the dataset's own caption reader.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable, Mapping, Sequence

import numpy as np

from data.humanml3d import Caption
from data.synthetic_library import Segment
from data.synthetic_text import (
    GERUND,
    THIRD,
    Subject,
    Word,
    build_lexicon,
    caption_text,
    distinct_captions,
    fill_template,
    fix_articles,
    plain_words,
    span_seconds,
    tokens_of,
)

# --- lexicon ---------------------------------------------------------------------------------

_WORDS = {
    "DET": "a an the his her their both some",
    "PRON": "somebody something it them themselves himself herself",
    "AUX": "is",
    "CCONJ": "and",
    "SCONJ": "while whilst",
    "NUM": "one two three four five six seven",
    "ADP": "to on at with of into toward over up down out off by via through along onto behind in before around",
    "ADV": "onward frontward rearward laterally leftward rightward unhurriedly lazily gently calmly "
           "rapidly swiftly speedily briefly afterwards next subsequently initially later lastly "
           "eventually simultaneously aloft skyward vertically steeply almost completely far profoundly politely "
           "broadly horizontally repeatedly away outward only",
    "ADJ": "left right relaxed ordinary great top flat easy single upright bent imaginary whole tiny star",
    "NOUN": "hand arm leg foot head fist knee guy lady athlete performer character actor subject tempo speed "
            "distance ring loop tad bit direction revolution spot series heel hip torso position stool bench "
            "posture huddle target blow greeting hello palm item carpet surroundings bounce dip nod",
    "VERB": "advance march proceed saunter trudge wander hustle rush retreat withdraw recede slide shift drift scoot "
            "trot lope race bolt charge hurtle trace loop rotate swivel twirl spring bound lunge soar bounce "
            "execute exercise sink dip drop recover settle plop perch push climb hoist leave hunker pop strike lash "
            "punt fling nudge shadowbox spar deliver smack greet signal flap elevate slap cheer incline fold "
            "lengthen limber tilt tip open peer gaze scan toss lob pitch hurl stoop collect retrieve scoop carry "
            "cover reverse curve bear end return nod use close",
}
_PLURALS = {"hands": "hand", "arms": "arm", "legs": "leg", "feet": "foot", "fists": "fist", "knees": "knee",
            "heels": "heel", "hips": "hip", "palms": "palm", "blows": "blow", "dips": "dip", "bounces": "bounce"}
_IRREGULAR = {"spring": ("springs", "springing"), "sink": ("sinks", "sinking"), "dip": ("dips", "dipping"),
              "drop": ("drops", "dropping"), "plop": ("plops", "plopping"), "pop": ("pops", "popping"),
              "spar": ("spars", "sparring"), "flap": ("flaps", "flapping"), "slap": ("slaps", "slapping"),
              "tip": ("tips", "tipping"), "scan": ("scans", "scanning"), "shadowbox": ("shadowboxes", "shadowboxing"),
              "trot": ("trots", "trotting")}
_BODY = {"hand", "hands", "arm", "arms", "leg", "legs", "foot", "feet", "head", "fist", "fists", "knee", "knees"}

PARAPHRASE_LEXICON: dict[str, tuple[str, str]] = build_lexicon(_WORDS, _PLURALS, _IRREGULAR)
"""word -> (POS, lemma) for every word the paraphrase grammar can write."""

#: Words a paraphrase may share with the training captions (module docstring).
SHARED_WORDS: frozenset[str] = frozenset(
    {w for w, (pos, _) in PARAPHRASE_LEXICON.items() if pos in ("DET", "PRON", "AUX", "CCONJ", "SCONJ", "ADP", "NUM")}
    | {"left", "right"} | _BODY
)


def words_of(text: str) -> list[str]:
    """Lower-case alphabetic words of ``text``."""
    return re.findall(r"[a-z]+", text.lower())


def stem(word: str) -> str:
    """A crude stem that maps inflections together: walks/walked/walking/walk -> walk, rises/rise -> ris."""
    for suffix in ("ing", "ed", "es", "s"):
        if word.endswith(suffix) and len(word) - len(suffix) >= 3:
            word = word[: -len(suffix)]
            break
    return word[:-1] if word.endswith("e") and len(word) > 3 else word


def held_out_violations(texts: Iterable[str], vocabulary: Iterable[str], allowed: frozenset[str]
                        ) -> list[tuple[str, str]]:
    """(text, word) for each word of ``texts`` not in ``allowed`` that occurs in ``vocabulary``, as it
    is or by :func:`stem`."""
    vocab = {w for v in vocabulary for w in words_of(v)}
    stems = {stem(w) for w in vocab}
    return [(text, word) for text in texts for word in words_of(text)
            if word not in allowed and (word in vocab or stem(word) in stems)]


# --- clause templates ------------------------------------------------------------------------
# As data.synthetic_text's: "~verb" is inflected, {poss}/{refl} agree with the subject.

_PACE = {"slow": ("unhurriedly", "at a relaxed tempo", "lazily", "gently"),
         "normal": ("", "", "at an ordinary tempo", "calmly"),
         "fast": ("rapidly", "swiftly", "at great speed", "speedily")}
_NUMBER = {1: "one", 2: "two", 3: "three", 4: "four", 5: "five", 6: "six", 7: "seven"}


def _count(reps: int) -> str:
    """How a paraphrase says a number of repetitions (nothing for one)."""
    return "" if reps == 1 else f"in a series of {_NUMBER[reps]}"


def _ward(side: str) -> str:
    """"leftward" or "rightward"."""
    return f"{side}ward"


def _walk(p: Mapping) -> list[str]:
    d, pace = p["direction"], p["pace"]
    if d == "forward" and p.get("veer"):
        s = p["veer"]
        return [f"~advance and ~curve off to the {s}", f"~march onward and ~bear {_ward(s)}",
                f"~proceed onward and ~curve toward the {s}"]
    if d == "forward":
        verbs = {"slow": ("~saunter", "~trudge", "~wander"), "normal": ("~advance", "~march", "~proceed"),
                 "fast": ("~hustle", "~rush", "~march")}[pace]
        return [f"{v} {w} {a}" for v in verbs for w in ("onward", "frontward") for a in _PACE[pace]] + [
            f"~cover some distance on foot {_PACE[pace][0]}"]
    if d == "backward":
        return [f"~retreat {a}" for a in _PACE[pace][:2]] + ["~withdraw rearward", "~recede rearward",
                                                            "~reverse away on foot"]
    return [f"~slide laterally toward the {d}", f"~shift over to the {d}", f"~drift {_ward(d)}",
            f"~scoot over to the {d}"]


def _jog(p: Mapping) -> list[str]:
    return ["~trot onward", "~lope onward", "~trot along at an easy tempo", "~lope along"]


def _run(p: Mapping) -> list[str]:
    if p["pace"] == "fast":
        return ["~bolt onward", "~race off at top speed", "~charge onward flat out", "~race off rapidly"]
    return ["~race onward", "~hurtle onward", "~race along"]


def _circle(p: Mapping) -> list[str]:
    side = "left" if p["direction"] == "counterclockwise" else "right"
    if p.get("jog"):
        return [f"~trot around a ring toward the {side}", f"~trot in a loop toward the {side}"]
    return [f"~loop around toward the {side}", f"~wander in a ring toward the {side}",
            f"~trace a ring {_ward(side)}", f"~trace a loop toward the {side}"]


def _turn(p: Mapping) -> list[str]:
    s, angle = p["direction"], p["angle"]
    return {
        45: [f"~rotate a bit toward the {s}", f"~swivel a tad toward the {s}", f"~rotate a tad {_ward(s)}"],
        90: [f"~swivel toward the {s}", f"~rotate {_ward(s)}", f"~swivel {_ward(s)}", f"~rotate toward the {s}"],
        135: [f"~swivel steeply toward the {s}", f"~rotate almost completely toward the {s}"],
        180: ["~reverse direction", f"~reverse direction via the {s}", "~swivel to gaze behind",
              f"~rotate {_ward(s)} to gaze behind"],
        360: ["~twirl a whole revolution", f"~twirl a whole revolution toward the {s}",
              f"~rotate {_ward(s)} through a whole revolution"],
    }[angle]


def _jump(p: Mapping) -> list[str]:
    n = _count(p["reps"])
    if p["distance"] > 0:
        return [f"~spring onward {n}", f"~bound onward {n}", f"~lunge onward off both feet {n}"]
    out = [f"~bounce on the spot {n}", f"~spring skyward {n}", f"~bound vertically {n}"]
    return out + (["~soar skyward"] if p["height"] > 0.24 and p["reps"] == 1 else [])


def _hop(p: Mapping) -> list[str]:
    s, n = p["side"], _count(p["reps"])
    where = "onward " if p["distance"] > 0 else ""
    return [f"~bounce {where}on {{poss}} {s} leg only {n}", f"~spring {where}on a single {s} foot {n}",
            f"~bound {where}on one {s} leg {n}"]


def _jumping_jacks(p: Mapping) -> list[str]:
    n = _NUMBER[p["reps"]]
    return [f"~execute {n} star bounces", "~bounce while opening and closing {poss} arms and legs",
            f"~exercise with {n} star bounces"]


def _squat(p: Mapping) -> list[str]:
    n = p["reps"]
    if n == 1:
        return ["~sink {poss} hips and ~return upright", "~drop {poss} hips toward the heels and ~recover",
                "~dip into a bent knee position and ~recover"]
    return [f"~execute {_NUMBER[n]} knee dips", f"~sink {{poss}} hips and ~recover {_count(n)}"]


def _sit_down(p: Mapping) -> list[str]:
    return ["~settle onto a bench", "~plop down onto a stool", "~perch on a stool", "~settle {refl} onto a bench"]


def _stand_up(p: Mapping) -> list[str]:
    return ["~push off a stool to an upright posture", "~climb off the bench", "~hoist {refl} off a stool",
            "~leave the bench and ~end upright"]


def _crouch(p: Mapping) -> list[str]:
    return ["~hunker down briefly and ~recover", "~drop into a huddle briefly and ~recover",
            "~hunker down and ~pop upright afterwards"]


def _kick(p: Mapping) -> list[str]:
    s, n = p["side"], _count(p["reps"])
    out = [f"~strike out with {{poss}} {s} foot {n}", f"~lash out using {{poss}} {s} leg {n}",
           f"~punt an imaginary target using the {s} foot {n}"]
    if p["height"] >= 0.7:
        out.append(f"~fling {{poss}} {s} leg up over the hips {n}")
    elif p["height"] < 0.45:
        out.append(f"~nudge the {s} foot outward {n}")
    return out


def _punch(p: Mapping) -> list[str]:
    s, n = p["side"], p["reps"]
    if s == "both":
        return ["~shadowbox", "~spar using {poss} fists one by one", f"~deliver {_NUMBER[n]} blows using both fists"]
    out = [f"~deliver a blow using {{poss}} {s} fist {_count(n)}", f"~smack an imaginary target using the {s} fist "
           f"{_count(n)}"]
    return out + ([f"~deliver {_NUMBER[n]} blows using the {s} fist"] if n > 1 else [])


def _wave(p: Mapping) -> list[str]:
    s = p["side"]
    if s == "both":
        return ["~greet somebody using both hands aloft", "~signal hello using both arms",
                "~flap both hands in greeting"]
    return [f"~signal hello using {{poss}} {s} hand", f"~greet somebody using the {s} hand",
            f"~flap {{poss}} {s} hand in greeting"]


def _raise_arms(p: Mapping) -> list[str]:
    s, d = p["side"], p["direction"]
    limbs = ["both arms", "{poss} arms"] if s == "both" else [f"{{poss}} {s} arm", f"the {s} arm"]
    where = {"up": ["skyward", "aloft"], "forward": ["frontward", "horizontally frontward"],
             "sideways": ["laterally", "outward laterally"]}[d]
    it = "them" if s == "both" else "it"
    return [f"~hoist {limb} {w}" for limb in limbs for w in where] + [
        f"~elevate {limbs[0]} {where[0]}", f"~hoist {limbs[1]} {where[1]} and ~drop {it} afterwards"]


def _clap(p: Mapping) -> list[str]:
    n = _count(p["reps"])
    if p["overhead"]:
        return ["~slap {poss} palms aloft", "~slap {poss} palms up over {poss} head", "~cheer by slapping {poss} "
                "palms aloft"]
    return [f"~slap {{poss}} palms {n}", "~cheer by slapping {poss} palms", f"~smack {{poss}} palms {n}"]


def _bow(p: Mapping) -> list[str]:
    if p["depth"] > 0.75:
        return ["~incline {poss} torso far down", "~fold at the hips profoundly", "~fold far over at the hips"]
    if p["depth"] < 0.55:
        return ["~incline {poss} torso a tiny bit", "~nod politely", "~dip {poss} torso a tad"]
    return ["~incline {poss} torso", "~fold at the hips politely", "~incline {poss} torso politely"]


def _stretch(p: Mapping) -> list[str]:
    m = p["mode"]
    if m == "up":
        return ["~lengthen {poss} arms skyward", "~limber up with {poss} arms aloft", "~lengthen {poss} torso skyward"]
    if m == "out":
        return ["~open {poss} arms broadly", "~open both arms laterally", "~lengthen {poss} arms laterally"]
    return [f"~tilt {{poss}} torso toward the {m} with arms aloft", f"~tip {{poss}} torso {_ward(m)} with arms aloft",
            f"~tilt {{poss}} torso {_ward(m)}"]


def _look_around(p: Mapping) -> list[str]:
    a = p["first"]
    b = "right" if a == "left" else "left"
    out = ["~scan {poss} surroundings", f"~peer {_ward(a)} and afterwards {_ward(b)}",
           f"~gaze {_ward(a)} and next {_ward(b)}"]
    return out + (["~scan {poss} surroundings repeatedly"] if p["reps"] > 1 else [])


def _throw(p: Mapping) -> list[str]:
    s = p["side"]
    return [f"~toss an item using {{poss}} {s} hand", f"~lob an imaginary item using the {s} arm",
            f"~pitch something using {{poss}} {s} hand", f"~hurl an item using {{poss}} {s} arm"]


def _pick_up(p: Mapping) -> list[str]:
    s = p["side"]
    hands = "both hands" if s == "both" else f"{{poss}} {s} hand"
    out = [f"~stoop and ~collect an item using {hands}", f"~scoop an item off the carpet using {hands}",
           f"~stoop and ~retrieve something using {hands}"]
    return out + ([f"~collect an item using {hands} and ~carry it"] if p["keep"] else [])


CLAUSES: dict[str, Callable[[Mapping], list[str]]] = {
    "walk": _walk, "jog": _jog, "run": _run, "circle": _circle, "turn": _turn, "jump": _jump, "hop": _hop,
    "jumping_jacks": _jumping_jacks, "squat": _squat, "sit_down": _sit_down, "stand_up": _stand_up,
    "crouch": _crouch, "kick": _kick, "punch": _punch, "wave": _wave, "raise_arms": _raise_arms, "clap": _clap,
    "bow": _bow, "stretch": _stretch, "look_around": _look_around, "throw": _throw, "pick_up": _pick_up,
}  # fmt: skip
"""kind -> paraphrase clause templates stating a segment's parameters."""

SUBJECTS: tuple[Subject, ...] = (
    Subject("somebody", "their", "themselves"), Subject("a guy", "his", "himself"),
    Subject("the guy", "his", "himself"), Subject("a lady", "her", "herself"), Subject("the lady", "her", "herself"),
    Subject("an athlete", "their", "themselves"), Subject("the performer", "their", "themselves"),
    Subject("a character", "their", "themselves"), Subject("an actor", "his", "himself"),
    Subject("the subject", "their", "themselves"),
)


def _fill(template: str, subject: Subject, form: int) -> list[Word]:
    """:func:`~data.synthetic_text.fill_template` with this grammar's irregular verbs."""
    return fill_template(template, subject, form, _IRREGULAR)


def _clause(segment: Segment, subject: Subject, rng: np.random.Generator, form: int) -> list[Word]:
    """Words describing one segment, with its upper-body action if it has one."""
    main = str(rng.choice(CLAUSES[segment.kind](segment.params)))
    if segment.upper is None:
        return _fill(main, subject, form)
    upper = str(rng.choice(CLAUSES[segment.upper.kind](segment.upper.params)))
    pattern = int(rng.integers(3))
    if pattern == 0:
        return _fill(main, subject, form) + plain_words("whilst") + _fill(upper, subject, GERUND)
    if pattern == 1:
        return _fill(upper, subject, form) + plain_words("while") + _fill(main, subject, GERUND)
    return _fill(main, subject, form) + plain_words("and simultaneously") + _fill(upper, subject, form)


def _join(subject: Subject, segments: Sequence[Segment], rng: np.random.Generator) -> list[Word]:
    """One sentence about ``segments`` in time order."""
    head = plain_words(subject.words)
    if len(segments) == 1:
        if rng.random() < 0.25:
            return head + plain_words("is") + _clause(segments[0], subject, rng, GERUND)
        return head + _clause(segments[0], subject, rng, THIRD)
    if len(segments) == 2:
        pattern = int(rng.integers(4))
        first = _clause(segments[0], subject, rng, THIRD)
        if pattern == 3:
            return head + first + plain_words("before") + _clause(segments[1], subject, rng, GERUND)
        lead = plain_words("initially" if pattern == 2 else "")
        link = plain_words((", afterwards", "and next", ", and later")[pattern])
        return head + lead + first + link + _clause(segments[1], subject, rng, THIRD)
    first, second, third = (_clause(s, subject, rng, THIRD) for s in segments)
    pattern = int(rng.integers(2))
    links = ((", next", ", and lastly"), (", subsequently", ", and eventually"))[pattern]
    lead = plain_words("initially" if pattern == 1 else "")
    return head + lead + first + plain_words(links[0]) + second + plain_words(links[1]) + third


def _on_stool(subject: Subject) -> Subject:
    """The subject, sitting at the start ("a lady on a stool")."""
    return Subject(f"{subject.words} on a stool", subject.possessive, subject.reflexive)


def paraphrase(segments: Sequence[Segment], rng: np.random.Generator, start: float = 0.0, end: float = 0.0,
               seated: bool = False) -> Caption:
    """A held-out :class:`Caption` describing segments played in order (as
    :func:`data.synthetic_text.caption`, with this module's grammar)."""
    subject = SUBJECTS[int(rng.integers(len(SUBJECTS)))]
    if seated and segments[0].kind != "stand_up":
        subject = _on_stool(subject)
    words = fix_articles(_join(subject, segments, rng))
    return Caption(caption_text(words, rng), tokens_of(words, PARAPHRASE_LEXICON), start, end)


def paraphrases(segments: Sequence[Segment], windows: Sequence[tuple[int, int]], postures: Sequence[str],
                length: int, spans: Iterable[Caption], rng: np.random.Generator, count: int) -> list[Caption]:
    """``count`` distinct whole-clip paraphrases of a motion, and ``count`` of each span caption's segment.

    ``spans`` are the motion's span captions (:func:`data.synthetic_text.describe` writes them with the
    segment's window in seconds); each gets paraphrases of its segment with the same span, so they
    belong to the same dataset item.
    """
    out = distinct_captions(lambda: paraphrase(segments, rng, seated=postures[0] == "sit"), count)
    bounds = {span_seconds(window, length): k for k, window in enumerate(windows)}
    for span in spans:
        k = bounds.get((span.start, span.end))
        if k is None:
            raise ValueError(f"span {span.start}-{span.end} s of {span.text!r} is no segment's window")
        out += distinct_captions(lambda k=k, span=span: paraphrase([segments[k]], rng, span.start, span.end,
                                                           postures[k] == "sit"), count)
    return out
