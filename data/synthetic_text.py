"""Captions for synthetic motions: a small grammar with synonyms, paraphrases and POS tokens.

Each action has clause templates (verb phrases) that state its parameters -- side, direction,
speed, count -- in several wordings; a caption joins a subject with the clauses of the motion's
segments in time order ("..., then ...", "first ..., then ..."), or with a carrier and an
upper-body action ("... while waving ..."). Templates are plain strings: ``~walk`` is a verb
to inflect (third person or ``-ing`` form), ``{poss}`` the possessive that agrees with the
subject. Every word is in :data:`LEXICON`, which gives its spaCy-style POS tag and its lemma, so
tokens come out as HumanML3D's: NOUN and VERB lemmatised (``walks/VERB`` -> ``walk/VERB``,
``hands/NOUN`` -> ``hand/NOUN``), "left" kept, punctuation dropped.

:func:`mirror_caption` swaps left/right and clockwise/counterclockwise, as HumanML3D does for
its mirrored clips.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from data.humanml3d import Caption
from data.synthetic_library import Segment
from data.synthetic_motion import FPS

# --- lexicon ---------------------------------------------------------------------------------

_WORDS = {
    "DET": "a an the his her their its both all some that",
    "PRON": "someone them it something themselves himself herself itself",
    "AUX": "is",
    "CCONJ": "and",
    "SCONJ": "while",
    "NUM": "one two three four five six seven ninety",
    "ADP": "to in on at with from of into toward over above around up down out after before for off",
    "ADV": "forward backward backwards back ahead sideways slowly quickly briskly fast then again twice once "
           "straight around clockwise counterclockwise anticlockwise finally leisurely steadily together "
           "overhead high low deeply slightly first upward hurriedly sharply overhand most",
    "ADJ": "left right slow quick normal steady fast full half quarter high low deep small short other same few "
           "forward straight wide little complete alternating long seated",
    "NOUN": "person man woman figure human individual hand arm leg foot fist head floor ground object circle step time "
            "squat kick side seat chair place pace waist turn way bow air body front ball motion line moment "
            "chest",
    "VERB": "walk stroll step move amble stride hurry jog run sprint dash turn spin pivot circle jump leap hop "
            "squat sit take lower stand get rise crouch duck kick punch throw jab wave raise lift clap applaud "
            "bow bend straighten stretch reach look glance pick grab do perform make keep balance shuffle "
            "sidestep go come face extend lean spread veer wind box hold",
}
_PLURALS = {"hands": "hand", "arms": "arm", "feet": "foot", "steps": "step", "times": "time", "degrees": "degree",
            "squats": "squat", "kicks": "kick", "punches": "punch", "jacks": "jack", "sides": "side",
            "knees": "knee", "jumps": "jump", "fists": "fist", "shoulders": "shoulder"}
_IRREGULAR = {"do": ("does", "doing"), "run": ("runs", "running"), "sit": ("sits", "sitting"),
              "get": ("gets", "getting"), "jog": ("jogs", "jogging"), "hop": ("hops", "hopping"),
              "step": ("steps", "stepping"), "clap": ("claps", "clapping"), "squat": ("squats", "squatting"),
              "put": ("puts", "putting"), "sidestep": ("sidesteps", "sidestepping"), "grab": ("grabs", "grabbing"),
              "jab": ("jabs", "jabbing"), "go": ("goes", "going"), "swing": ("swings", "swinging")}


def verb_forms(lemma: str, irregular: Mapping[str, tuple[str, str]] = _IRREGULAR) -> tuple[str, str]:
    """(third person singular, -ing form) of a verb; ``irregular`` lists the exceptions."""
    if lemma in irregular:
        return irregular[lemma]
    third = lemma + "es" if lemma.endswith(("sh", "ch", "s", "x", "o")) else lemma + "s"
    gerund = lemma[:-1] + "ing" if lemma.endswith("e") and not lemma.endswith("ee") else lemma + "ing"
    return third, gerund


def build_lexicon(words: Mapping[str, str], plurals: Mapping[str, str],
                  irregular: Mapping[str, tuple[str, str]] = _IRREGULAR) -> dict[str, tuple[str, str]]:
    """word -> (POS, lemma) of space-separated ``words`` per POS, noun ``plurals`` -> lemma and
    every inflected form of the verbs; the first POS listed for a word wins."""
    lexicon: dict[str, tuple[str, str]] = {}
    for pos, listed in words.items():
        for word in listed.split():
            lexicon.setdefault(word, (pos, word))
    for plural, lemma in plurals.items():
        lexicon.setdefault(plural, ("NOUN", lemma))
    for lemma in words["VERB"].split():
        for form in verb_forms(lemma, irregular):
            lexicon.setdefault(form, ("VERB", lemma))
    return lexicon


LEXICON: dict[str, tuple[str, str]] = build_lexicon(_WORDS, _PLURALS)
"""word -> (POS, lemma) for every word the grammar can write."""


Word = tuple[str, str | None]
"""A written word and, for an inflected verb, its lemma (else None: looked up in the lexicon)."""


def tokens_of(words: Sequence[Word], lexicon: Mapping[str, tuple[str, str]] = LEXICON
              ) -> tuple[tuple[str, str], ...]:
    """HumanML3D tokens: alphabetic words with their POS, NOUN and VERB words lemmatised.

    Raises:
        KeyError: a word missing from ``lexicon`` (a grammar bug).
    """
    tokens = []
    for word, verb in words:
        if verb is not None:
            tokens.append((verb, "VERB"))
            continue
        word = "".join(ch for ch in word.lower() if ch.isalpha())
        if not word:
            continue
        if word not in lexicon:
            raise KeyError(f"word {word!r} is not in the lexicon")
        pos, lemma = lexicon[word]
        tokens.append((lemma if pos in ("NOUN", "VERB") else word, pos))
    return tuple(tokens)


# --- clause templates --------------------------------------------------------------------------
# A template is a string of words; "~verb" is inflected, {poss}/{refl} agree with the subject.

_PACE = {
    "slow": ("slowly", "at a slow pace", "leisurely", "slowly and steadily"),
    "normal": ("", "", "at a normal pace", "steadily", "at a steady pace"),
    "fast": ("quickly", "briskly", "fast", "at a fast pace", "hurriedly"),
}
_TIMES = {2: "twice", 3: "three times", 4: "four times", 5: "five times", 6: "six times", 7: "seven times"}
_COUNT = {1: "one", 2: "two", 3: "three", 4: "four", 5: "five", 6: "six", 7: "seven"}
_CIRCLE = {"clockwise": ("clockwise",), "counterclockwise": ("counterclockwise", "anticlockwise")}


def _times(reps: int) -> str:
    """"twice", "three times"; empty for one repetition."""
    return _TIMES.get(reps, "")


def _walk(p: Mapping) -> list[str]:
    d, pace = p["direction"], p["pace"]
    adv = _PACE[pace]
    if d == "forward" and p.get("veer"):
        s = p["veer"]
        return [f"~walk forward and ~turn {s}", f"~walk ahead and then ~turn to the {s}",
                f"~walk forward and ~veer to the {s}", f"~walk straight , then ~turn {s} and ~keep walking",
                f"~walk forward before turning to the {s}"]
    if d == "forward":
        verbs = {"slow": ("~walk", "~stroll", "~amble"), "normal": ("~walk", "~walk", "~move"),
                 "fast": ("~walk", "~stride", "~hurry")}[pace]
        adj = {"slow": "slow", "normal": "steady", "fast": "quick"}[pace]
        return [f"{v} {w} {a}" for v in verbs for w in ("forward", "straight ahead", "ahead") for a in adv] + [
            f"~take {adj} steps forward", f"~walk {adv[-1]} in a straight line"]
    if d == "backward":
        return [f"~walk backward {a}" for a in adv[:2]] + [f"~walk backwards {adv[-1]}", "~step backwards",
                                                           "~move backward", "~take a few steps back"]
    return [f"~walk sideways to the {d}", f"~sidestep to the {d}", f"~step sideways to the {d}",
            f"~shuffle to the {d}", f"~move sideways toward the {d}", f"~take side steps to the {d}"]


def _jog(p: Mapping) -> list[str]:
    return ["~jog forward", "~jog ahead", "~jog forward at a steady pace", "~go for a short jog",
            "~jog straight ahead", "~run slowly forward"]


def _run(p: Mapping) -> list[str]:
    if p["pace"] == "fast":
        return ["~run forward quickly", "~sprint forward", "~dash ahead", "~run fast", "~sprint straight ahead"]
    return ["~run forward", "~run ahead", "~run straight forward", "~run forward at a steady pace"]


def _circle(p: Mapping) -> list[str]:
    side = "left" if p["direction"] == "counterclockwise" else "right"
    verb = "~jog" if p.get("jog") else "~walk"
    return [f"{verb} in a {d} circle" for d in _CIRCLE[p["direction"]]] + [
        f"{verb} {_CIRCLE[p['direction']][0]} in a circle", f"{verb} around in a circle to the {side}",
        f"{verb} in a full circle , turning to the {side}", f"~circle around to the {side}"]


def _turn(p: Mapping) -> list[str]:
    s, angle = p["direction"], p["angle"]
    return {
        45: [f"~turn slightly to the {s}", f"~turn a little to the {s}", f"~turn slightly {s}"],
        90: [f"~turn {s}", f"~turn to the {s}", f"~turn ninety degrees to the {s}",
             f"~make a quarter turn to the {s}", f"~pivot to the {s}", f"~turn to {{poss}} {s}"],
        135: [f"~turn sharply to the {s}", f"~turn most of the way around to the {s}", f"~pivot sharply {s}"],
        180: ["~turn around", f"~turn around to the {s}", "~turn to face the other way",
              f"~make a half turn to the {s}", f"~turn all the way around to the {s}", "~turn back around"],
        360: ["~spin around in a full circle", f"~turn in a complete circle to the {s}",
              f"~make a full turn to the {s}", f"~spin around once to the {s}", "~turn around in a full circle"],
    }[angle]


def _jump(p: Mapping) -> list[str]:
    n, times = p["reps"], _times(p["reps"])
    if p["distance"] > 0:
        out = [f"~jump forward {times}", f"~leap forward {times}", f"~jump ahead {times}",
               f"~jump forward with both feet {times}"]
        return out + ([f"~do {_COUNT[n]} jumps forward"] if n > 1 else ["~do a long jump forward"])
    out = [f"~jump in place {times}", f"~jump straight up {times}", f"~jump up {times}"]
    if n > 1:
        out += ["~jump up and down", f"~do {_COUNT[n]} jumps in place"]
    return out + (["~jump high in the air"] if p["height"] > 0.24 else [])


def _hop(p: Mapping) -> list[str]:
    s, times = p["side"], _times(p["reps"])
    where = "forward " if p["distance"] > 0 else ""
    return [f"~hop {where}on {{poss}} {s} leg {times}", f"~hop {where}on the {s} foot {times}",
            f"~balance on {{poss}} {s} leg and ~hop {where}{times}", f"~hop {times} {where}on {{poss}} {s} foot",
            f"~stand on {{poss}} {s} leg and ~hop {where}"]


def _jumping_jacks(p: Mapping) -> list[str]:
    n = _COUNT[p["reps"]]
    return [f"~do {n} jumping jacks", "~do jumping jacks", f"~perform {n} jumping jacks", "~do some jumping jacks"]


def _squat(p: Mapping) -> list[str]:
    n = p["reps"]
    if n == 1:
        return ["~squat down and ~stand back up", "~do a squat", "~squat once", "~do one squat",
                "~bend {poss} knees into a squat and ~rise again"]
    return [f"~do {_COUNT[n]} squats", f"~squat {_times(n)}", f"~perform {_COUNT[n]} squats",
            f"~squat down and up {_times(n)}"]


def _sit_down(p: Mapping) -> list[str]:
    return ["~sit down", "~take a seat", "~sit down on a chair", "~lower {refl} into a seat", "~sit down on a seat"]


def _stand_up(p: Mapping) -> list[str]:
    return ["~stand up", "~get up from a chair", "~rise from {poss} seat", "~stand up from the chair",
            "~get to {poss} feet"]


def _crouch(p: Mapping) -> list[str]:
    return ["~crouch down and ~stand back up", "~crouch down low and ~rise again", "~duck down and ~come back up",
            "~get down into a crouch and then ~stand up", "~crouch low for a moment"]


def _kick(p: Mapping) -> list[str]:
    s, n = p["side"], p["reps"]
    times = _times(n)
    out = [f"~kick with {{poss}} {s} leg {times}", f"~kick forward with the {s} foot {times}",
           f"~kick {{poss}} {s} leg out in front {times}"]
    out.append(f"~do {_COUNT[n]} kicks with the {s} leg" if n > 1 else f"~do a kick with the {s} leg")
    if p["height"] >= 0.7:
        out += [f"~kick high with {{poss}} {s} leg {times}", f"~do a high kick with the {s} foot"]
    elif p["height"] < 0.45:
        out += [f"~do a low kick with {{poss}} {s} foot"]
    return out


def _punch(p: Mapping) -> list[str]:
    s, n = p["side"], p["reps"]
    if s == "both":
        return ["~punch with both hands", "~throw punches with alternating fists", f"~throw {_COUNT[n]} punches",
                "~punch forward with both fists , one after the other", "~box with both hands"]
    out = [f"~punch forward with {{poss}} {s} hand {_times(n)}", f"~jab forward with {{poss}} {s} fist {_times(n)}",
           f"~punch with the {s} arm {_times(n)}"]
    out.append(f"~throw {_COUNT[n]} punches with the {s} fist" if n > 1 else f"~throw a punch with {{poss}} {s} arm")
    return out


def _wave(p: Mapping) -> list[str]:
    s = p["side"]
    if s == "both":
        return ["~wave both hands", "~wave with both arms", "~raise both hands and ~wave", "~wave both arms",
                "~wave with both hands above {poss} shoulders"]
    return [f"~wave {{poss}} {s} hand", f"~wave with the {s} hand", f"~raise {{poss}} {s} hand and ~wave",
            f"~wave with {{poss}} {s} arm", f"~lift the {s} hand and ~wave it"]


def _raise_arms(p: Mapping) -> list[str]:
    s, d = p["side"], p["direction"]
    limbs = ["both arms", "{poss} arms", "both hands"] if s == "both" else [f"{{poss}} {s} arm", f"the {s} arm",
                                                                           f"{{poss}} {s} hand"]
    where = {"up": ["above {poss} head", "up", "overhead", "up high"],
             "forward": ["forward", "out in front", "in front of {poss} body"],
             "sideways": ["out to the side" + ("s" if s == "both" else ""), "sideways"]}[d]
    it = "them" if s == "both" else "it"
    return [f"~raise {limb} {w}" for limb in limbs for w in where[:2]] + [
        f"~lift {limbs[0]} {where[-1]}", f"~raise {limbs[1]} {where[0]} and ~lower {it} again"]


def _clap(p: Mapping) -> list[str]:
    n = p["reps"]
    if p["overhead"]:
        return ["~clap above {poss} head", "~clap {poss} hands over {poss} head",
                f"~raise {{poss}} arms and ~clap overhead {_times(n)}"]
    return [f"~clap {{poss}} hands {_times(n)}", f"~clap {_COUNT[n]} times", "~applaud", "~clap {poss} hands together",
            "~clap in front of {poss} chest"]


def _bow(p: Mapping) -> list[str]:
    if p["depth"] > 0.75:
        return ["~bow deeply", "~take a deep bow", "~bend forward deeply at the waist and ~straighten up",
                "~do a deep bow"]
    if p["depth"] < 0.55:
        return ["~bow slightly", "~do a small bow", "~bend forward slightly and ~straighten up", "~bow {poss} head"]
    return ["~bow", "~take a bow", "~bend forward at the waist and ~straighten up", "~do a bow"]


def _stretch(p: Mapping) -> list[str]:
    m = p["mode"]
    if m == "up":
        return ["~stretch {poss} arms above {poss} head", "~reach up and ~stretch", "~stretch upward",
                "~stretch both arms overhead"]
    if m == "out":
        return ["~stretch {poss} arms out to the sides", "~spread {poss} arms wide",
                "~extend both arms out to the sides", "~stretch both arms out sideways"]
    return [f"~stretch to the {m}", f"~lean to the {m} with {{poss}} arms overhead",
            f"~stretch {{poss}} body to the {m}", f"~bend to the {m} side with both arms up",
            f"~raise {{poss}} arms and ~lean {m}"]


def _look_around(p: Mapping) -> list[str]:
    a = p["first"]
    b = "right" if a == "left" else "left"
    out = ["~look around", f"~look to the {a} and then to the {b}", f"~turn {{poss}} head to the {a} and then the {b}",
           f"~glance {a} and {b}", f"~look {a} , then {b}"]
    return out + (["~look around from side to side", f"~look {a} and {b} twice"] if p["reps"] > 1 else [])


def _throw(p: Mapping) -> list[str]:
    s = p["side"]
    return [f"~throw something with {{poss}} {s} hand", f"~throw a ball overhand with the {s} arm",
            f"~make a throwing motion with {{poss}} {s} arm", f"~wind up and ~throw with the {s} hand",
            f"~throw an object forward with {{poss}} {s} hand"]


def _pick_up(p: Mapping) -> list[str]:
    s = p["side"]
    hands = "both hands" if s == "both" else f"{{poss}} {s} hand"
    out = [f"~pick something up from the floor with {hands}", f"~bend down and ~pick up an object with {hands}",
           f"~reach down to the ground and ~grab something with {hands}",
           f"~pick up something off the ground with {hands}"]
    if p["keep"]:
        out += [f"~pick something up with {hands} and ~hold it", "~pick up an object and ~keep it in front of {refl}"]
    return out


CLAUSES = {
    "walk": _walk, "jog": _jog, "run": _run, "circle": _circle, "turn": _turn, "jump": _jump, "hop": _hop,
    "jumping_jacks": _jumping_jacks, "squat": _squat, "sit_down": _sit_down, "stand_up": _stand_up,
    "crouch": _crouch, "kick": _kick, "punch": _punch, "wave": _wave, "raise_arms": _raise_arms, "clap": _clap,
    "bow": _bow, "stretch": _stretch, "look_around": _look_around, "throw": _throw, "pick_up": _pick_up,
}  # fmt: skip
"""kind -> clause templates stating a segment's parameters."""


# --- sentences -------------------------------------------------------------------------------


@dataclass(frozen=True)
class Subject:
    """Who a caption is about, with the possessive and reflexive that agree with it."""

    words: str
    possessive: str
    reflexive: str


SUBJECTS: tuple[Subject, ...] = tuple(
    Subject(words, poss, refl)
    for words, possessives, refl in (
        ("a person", ("their", "his", "the"), "themselves"),
        ("the person", ("their", "his", "the"), "themselves"),
        ("someone", ("their", "the"), "themselves"),
        ("person", ("their", "his"), "themselves"),
        ("a man", ("his", "the"), "himself"),
        ("the man", ("his",), "himself"),
        ("a woman", ("her", "the"), "herself"),
        ("the woman", ("her",), "herself"),
        ("a figure", ("its", "the"), "itself"),
        ("the figure", ("the",), "itself"),
        ("a human", ("their", "the"), "themselves"),
        ("an individual", ("their",), "themselves"),
    )
    for poss in possessives
)
THIRD, GERUND = 0, 1


def fill_template(template: str, subject: Subject, form: int,
                  irregular: Mapping[str, tuple[str, str]] = _IRREGULAR) -> list[Word]:
    """Fill a clause template for ``subject`` and inflect its verbs (``THIRD`` person or ``GERUND``)."""
    text = template.format(poss=subject.possessive, refl=subject.reflexive)
    return [(verb_forms(w[1:], irregular)[form], w[1:]) if w.startswith("~") else (w, None) for w in text.split()]


def plain_words(text: str) -> list[Word]:
    """Words written as they are (no verb to inflect)."""
    return [(w, None) for w in text.split()]


def _clause(segment: Segment, subject: Subject, rng: np.random.Generator, form: int) -> list[Word]:
    """Words describing one segment, with its upper-body action if it has one."""
    main = str(rng.choice(CLAUSES[segment.kind](segment.params)))
    if segment.upper is None:
        return fill_template(main, subject, form)
    upper = str(rng.choice(CLAUSES[segment.upper.kind](segment.upper.params)))
    pattern = int(rng.integers(3))
    if pattern == 0:
        return fill_template(main, subject, form) + plain_words("while") + fill_template(upper, subject, GERUND)
    if pattern == 1:
        return fill_template(upper, subject, form) + plain_words("while") + fill_template(main, subject, GERUND)
    return (fill_template(main, subject, form) + plain_words("and") + fill_template(upper, subject, form)
            + plain_words("at the same time"))


def _join(subject: Subject, segments: Sequence[Segment], rng: np.random.Generator) -> list[Word]:
    """One sentence about ``segments`` in time order."""
    head = plain_words(subject.words)
    if len(segments) == 1:
        if rng.random() < 0.25:
            return head + plain_words("is") + _clause(segments[0], subject, rng, GERUND)
        return head + _clause(segments[0], subject, rng, THIRD)
    if len(segments) == 2:
        pattern = int(rng.integers(5))
        first = _clause(segments[0], subject, rng, THIRD)
        if pattern == 4:
            return head + first + plain_words("before") + _clause(segments[1], subject, rng, GERUND)
        lead = plain_words("first" if pattern == 2 else "")
        link = plain_words((", then", "and then", ", then", ", and after that")[pattern])
        return head + lead + first + link + _clause(segments[1], subject, rng, THIRD)
    first, second, third = (_clause(s, subject, rng, THIRD) for s in segments)
    pattern = int(rng.integers(3))
    links = ((",", ", and then"), (", then", ", and finally"), (", then", "and then"))[pattern]
    lead = plain_words("first" if pattern == 2 else "")
    return head + lead + first + plain_words(links[0]) + second + plain_words(links[1]) + third


def fix_articles(words: list[Word]) -> list[Word]:
    """"a" or "an" as the next word needs."""
    nexts = [w for w, _ in words[1:]] + ["x"]
    pairs = zip(words, nexts, strict=True)
    return [(("an" if nxt[0] in "aeiou" else "a"), v) if w in ("a", "an") else (w, v) for (w, v), nxt in pairs]


def caption_text(words: Sequence[Word], rng: np.random.Generator) -> str:
    """Caption text of words: commas attached, sometimes a full stop."""
    text = " ".join(w for w, _ in words).replace(" ,", ",")
    return text + "." if rng.random() < 0.5 else text


def _seated(subject: Subject) -> Subject:
    """The subject, sitting ("a seated man", "someone sitting on a chair")."""
    first, *rest = subject.words.split()
    if first in ("a", "an", "the"):
        return replace(subject, words=" ".join([first, "seated", *rest]))
    return replace(subject, words=subject.words + " sitting on a chair")


def caption(segments: Sequence[Segment], rng: np.random.Generator, start: float = 0.0, end: float = 0.0,
            seated: bool = False) -> Caption:
    """A :class:`Caption` (text, tokens, span) describing segments played in order; ``seated``
    says that the subject sits at the start (and the first action does not say so)."""
    subject = SUBJECTS[int(rng.integers(len(SUBJECTS)))]
    if seated and segments[0].kind != "stand_up":
        subject = _seated(subject)
    words = fix_articles(_join(subject, segments, rng))
    return Caption(caption_text(words, rng), tokens_of(words), start, end)


def describe(segments: Sequence[Segment], windows: Sequence[tuple[int, int]], postures: Sequence[str],
             length: int, rng: np.random.Generator, count: int, span_prob: float, min_span: int = 41
             ) -> list[Caption]:
    """``count`` distinct whole-clip captions, plus span captions of single segments.

    ``postures`` are the postures ("stand"/"sit") each segment starts in. Each segment of a
    multi-segment motion lasting at least ``min_span`` frames gets, with probability
    ``span_prob``, a caption of its own covering its frames (in seconds; the span ends before the
    last frame so it stays inside the motion's ``length - 1`` feature frames).
    """
    captions: list[Caption] = []
    for _ in range(20 * count):
        candidate = caption(segments, rng, seated=postures[0] == "sit")
        if candidate.text not in {c.text for c in captions}:
            captions.append(candidate)
        if len(captions) == count:
            break
    if len(segments) > 1:
        for segment, (a, b), posture in zip(segments, windows, postures, strict=True):
            b = min(b, length - 1)
            if b - a >= min_span and rng.random() < span_prob:
                captions.append(caption([segment], rng, round(a / FPS, 2), round(b / FPS, 2), posture == "sit"))
    return captions


_MIRROR_WORDS = {"left": "right", "right": "left", "clockwise": "counterclockwise",
                 "counterclockwise": "clockwise", "anticlockwise": "clockwise"}


def _mirror_word(word: str) -> str:
    core = word.rstrip(".,")
    return _MIRROR_WORDS.get(core, core) + word[len(core):]


def mirror_caption(cap: Caption) -> Caption:
    """The caption of the mirrored motion: left/right and clockwise/counterclockwise swapped."""
    text = " ".join(_mirror_word(w) for w in cap.text.split(" "))
    tokens = tuple((_MIRROR_WORDS.get(w, w), pos) for w, pos in cap.tokens)
    return Caption(text, tokens, cap.start, cap.end)
