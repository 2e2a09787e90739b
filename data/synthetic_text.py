"""Captions for synthetic motions: a small grammar with synonyms, paraphrases and POS tokens.

Each action has clause templates (verb phrases) that state its parameters -- side, direction,
speed, count -- in many wordings: synonyms of its verbs and nouns, adverbs of speed that agree
with the segment's pace, counts ("twice", "three times in a row", "a couple of kicks"), sides
("with the left foot", "over his left shoulder") and directions ("forwards", "straight ahead").
Templates are plain strings: ``~walk`` is a verb to inflect (third person, ``-ing``, bare or past
form), ``{poss}``/``{refl}`` the possessive and reflexive that agree with the subject.

A caption (:func:`_join`) is one sentence in the present or the past tense: it opens with a
subject (a person, a boy, an old woman, a dancer, ...) in one of several structures ("a man
walks", "in this clip, a man walks", "a man is seen walking", "the video shows a man walking",
"we see a man walk", "a man starts to walk", "a man who walks", "after walking ..., a man
turns"), maybe with an adverb of manner ("casually") before a verb, and links the clauses of the
motion's segments in time order ("then", "after that", "before turning", "once done", "and
finally", ...); a carried upper-body action is said with "while", "at the same time" and the like.

Every word is in :data:`LEXICON`, which gives its spaCy-style POS tag and its lemma, so tokens
come out as HumanML3D's: NOUN and VERB lemmatised (``walks/VERB`` -> ``walk/VERB``,
``hands/NOUN`` -> ``hand/NOUN``), "left" kept, punctuation dropped. The vocabulary stays disjoint
from the held-out paraphrase grammar's (:mod:`data.paraphrase_text`) and from the text-encoder
probe's queries (``benchmarks/text_encoder_probe.py``): words such as "march", "rotate",
"somebody", "onward", "next", "using" or "by" are theirs, not this grammar's.

:func:`mirror_caption` swaps left/right and clockwise/counterclockwise, as HumanML3D does for
its mirrored clips.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from data.humanml3d import Caption
from data.synthetic_library import Segment
from data.synthetic_motion import FPS

# --- lexicon ---------------------------------------------------------------------------------

_WORDS = {
    "DET": "a an the his her their its both all some that this each",
    "PRON": "someone them it something themselves himself herself itself he she they we you who which",
    "AUX": "is was can could be will may",
    "CCONJ": "and but",
    "SCONJ": "while when",
    "NUM": "one two three four five six seven ninety hundred eighty",
    "ADP": "to in on at with from of into toward towards over above around up down out after before for off without "
           "against past than through behind like during below within",
    "ADV": "playfully happily cheerfully forward forwards backward backwards back ahead sideways slowly quickly "
           "briskly fast then again twice once thrice straight around clockwise counterclockwise anticlockwise finally "
           "leisurely steadily together overhead high low deeply slightly first upward upwards hurriedly hastily "
           "energetically sharply overhand most more partly gradually well hard forth prior also here there meanwhile "
           "thereafter soon shortly immediately directly exactly not momentarily carefully casually smoothly lightly "
           "naturally confidently overarm gracefully fluidly purposefully effortlessly comfortably neatly precisely "
           "cleanly freely courteously graciously humbly formally curiously evenly loosely quietly silently elegantly "
           "properly simply ultimately",
    "ADJ": "left right slow quick brisk normal regular moderate average comfortable natural even medium steady fast "
           "full half quarter high low deep small short other same few forward straight wide little complete "
           "alternating long seated consecutive separate light slight sharp big powerful friendly opposite upper "
           "circular airborne young old older elderly grown middle aged adult fit martial final tall last hurried "
           "careful casual cheerful animated teenage virtual digital",
    "NOUN": "person man woman figure human individual boy girl child kid teen youngster adult gentleman fellow "
            "teenager student senior dancer gymnast soldier player worker coach grandfather grandmother father mother "
            "ballerina artist model avatar humanoid mannequin robot skeleton stick male female hand arm forearm leg "
            "foot fist head neck knee shoulder floor ground area object thing ball stone snowball box cup bottle book "
            "toy circle route fashion point step stride gait walk stroll time squat kick punch jab guard combination "
            "wave leap spin bend stretch pose look side seat chair couch place pace haste hurry manner waist turn way "
            "bow air body front motion movement balance line moment second instant chest course pattern row succession "
            "total couple pair set eighth height level jog run sprint dash jump crouch stop halt applause audience "
            "camera friend weight video clip footage animation recording sequence scene example demonstration capture "
            "screen piece rendering part beginning boxer victory celebration approval respect gratitude space phone "
            "shoe sample instance snippet being performance routine action preview visualization playback viewer "
            "businessman teacher nurse referee",
    "VERB": "walk stroll amble mosey plod dawdle step move stride hurry hasten scurry head travel jog run sprint dash "
            "dart zoom shoot turn spin whirl twist pivot circle jump leap hop land launch propel squat sit ease take "
            "lower stand get rise arise pull crouch duck bob stay pause kick snap aim punch jab hit throw chuck "
            "release let pretend mime wave hail raise lift clap applaud bow thank bend straighten stretch reach look "
            "glance check crane observe pick grab gather do perform complete make keep balance shuffle sidestep sidle "
            "back set go come stop halt rest face extend lean spread veer wind box hold put bring stick swing switch "
            "give have break change seat lead appear seem decide follow start begin finish tread angle unleash fire "
            "flick point celebrate acknowledge search inspect grasp clutch transition",
}
_PLURALS = {"hands": "hand", "arms": "arm", "legs": "leg", "feet": "foot", "steps": "step", "strides": "stride",
            "times": "time", "degrees": "degree", "squats": "squat", "kicks": "kick", "punches": "punch",
            "jabs": "jab", "jacks": "jack", "sides": "side", "knees": "knee", "jumps": "jump", "leaps": "leap",
            "hops": "hop", "claps": "clap", "bends": "bend", "fists": "fist", "shoulders": "shoulder", "ways": "way",
            "motions": "motion", "repetitions": "repetition", "seconds": "second",
            "meters": "meter", "paces": "pace"}
_IRREGULAR = {"do": ("does", "doing"), "run": ("runs", "running"), "sit": ("sits", "sitting"),
              "get": ("gets", "getting"), "jog": ("jogs", "jogging"), "hop": ("hops", "hopping"),
              "step": ("steps", "stepping"), "clap": ("claps", "clapping"), "squat": ("squats", "squatting"),
              "put": ("puts", "putting"), "sidestep": ("sidesteps", "sidestepping"), "grab": ("grabs", "grabbing"),
              "jab": ("jabs", "jabbing"), "go": ("goes", "going"), "swing": ("swings", "swinging"),
              "hurry": ("hurries", "hurrying"), "scurry": ("scurries", "scurrying"), "spin": ("spins", "spinning"),
              "hit": ("hits", "hitting"), "propel": ("propels", "propelling"), "set": ("sets", "setting"),
              "have": ("has", "having"), "begin": ("begins", "beginning"), "plod": ("plods", "plodding"),
              "bob": ("bobs", "bobbing"), "snap": ("snaps", "snapping"), "let": ("lets", "letting"),
              "shoot": ("shoots", "shooting"), "stop": ("stops", "stopping")}
_PAST = {"run": "ran", "sit": "sat", "get": "got", "take": "took", "stand": "stood", "rise": "rose",
         "arise": "arose", "throw": "threw", "make": "made", "keep": "kept", "hold": "held", "go": "went",
         "come": "came", "do": "did", "spin": "spun", "leap": "leapt", "stride": "strode", "wind": "wound",
         "spread": "spread", "bring": "brought", "swing": "swung", "give": "gave", "have": "had", "break": "broke",
         "lead": "led", "begin": "began", "hit": "hit", "put": "put", "set": "set", "let": "let", "shoot": "shot",
         "stick": "stuck", "tread": "trod"}
_NO_PAST = frozenset({"bend"})
"""Verbs whose past tense the grammar never writes ("bent" is a held-out paraphrase word)."""
_VERB_FORMS = {"seen": "see", "shown": "show", "done": "do", "finished": "finish", "raised": "raise",
               "lifted": "lift", "given": "give", "captured": "capture", "filmed": "film", "recorded": "record",
               "pictured": "picture", "depicted": "depict", "see": "see", "sees": "see", "watch": "watch",
               "notice": "notice", "shows": "show", "depicts": "depict", "features": "feature", "presents": "present",
               "illustrates": "illustrate", "captures": "capture", "records": "record", "wrap": "wrap",
               "conclude": "conclude"}
"""Other verb forms the grammar writes as they are, with their lemmas: participles ("is seen walking",
"once done", "with the other leg raised") and the verbs that present a clip ("the video shows ...")."""


def verb_forms(lemma: str, irregular: Mapping[str, tuple[str, str]] = _IRREGULAR) -> tuple[str, str]:
    """(third person singular, -ing form) of a verb; ``irregular`` lists the exceptions."""
    if lemma in irregular:
        return irregular[lemma]
    third = lemma + "es" if lemma.endswith(("sh", "ch", "s", "x", "o")) else lemma + "s"
    gerund = lemma[:-1] + "ing" if lemma.endswith("e") and not lemma.endswith("ee") else lemma + "ing"
    return third, gerund


def past_tense(lemma: str, irregular: Mapping[str, tuple[str, str]] = _IRREGULAR,
               irregular_past: Mapping[str, str] = _PAST) -> str:
    """Simple past of a verb: ``irregular_past`` lists the exceptions; a doubled consonant of the
    -ing form is doubled here too (stepping -> stepped)."""
    if lemma in irregular_past:
        return irregular_past[lemma]
    doubled = verb_forms(lemma, irregular)[1][:-3]
    if len(doubled) == len(lemma) + 1 and doubled[-1] == doubled[-2]:
        return doubled + "ed"
    if lemma.endswith("e"):
        return lemma + "d"
    if lemma.endswith("y") and lemma[-2] not in "aeiou":
        return lemma[:-1] + "ied"
    return lemma + "ed"


def build_lexicon(words: Mapping[str, str], plurals: Mapping[str, str],
                  irregular: Mapping[str, tuple[str, str]] = _IRREGULAR, other_forms: Mapping[str, str] | None = None
                  ) -> dict[str, tuple[str, str]]:
    """word -> (POS, lemma) of space-separated ``words`` per POS, noun ``plurals`` -> lemma, the
    third person and -ing forms of the verbs and ``other_forms`` (past tenses, participles) ->
    their verb's lemma; the first POS listed for a word wins."""
    lexicon: dict[str, tuple[str, str]] = {}
    for pos, listed in words.items():
        for word in listed.split():
            lexicon.setdefault(word, (pos, word))
    for plural, lemma in plurals.items():
        lexicon.setdefault(plural, ("NOUN", lemma))
    for lemma in words["VERB"].split():
        for form in verb_forms(lemma, irregular):
            lexicon.setdefault(form, ("VERB", lemma))
    for form, lemma in (other_forms or {}).items():
        lexicon.setdefault(form, ("VERB", lemma))
    return lexicon


LEXICON: dict[str, tuple[str, str]] = build_lexicon(_WORDS, _PLURALS, _IRREGULAR, {
    **{past_tense(v): v for v in _WORDS["VERB"].split() if v not in _NO_PAST}, **_VERB_FORMS})
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
    "slow": ("slowly", "at a slow pace", "leisurely", "slowly and steadily", "at a leisurely pace",
             "taking {poss} time", "without hurrying", "in a slow manner", "slowly but steadily"),
    "normal": ("", "", "", "at a normal pace", "steadily", "at a steady pace", "at a regular pace",
               "at a moderate pace", "at an average pace", "at a comfortable pace", "at a natural pace",
               "at an even pace", "at a medium pace"),
    "fast": ("quickly", "briskly", "fast", "at a fast pace", "hurriedly", "at a quick pace", "at a brisk pace",
             "in a hurry", "hastily", "energetically", "with haste", "at a fast clip"),
}
"""pace -> adverbs of speed that agree with it."""
_PACE_BEFORE = {"slow": ("slowly", "leisurely"), "normal": ("steadily",),
                "fast": ("quickly", "briskly", "hastily", "hurriedly")}
"""pace -> one-word adverbs of speed said before the verb ("a man slowly walks ...")."""
_MANNER = ("carefully", "casually", "smoothly", "lightly", "naturally", "confidently", "gracefully", "fluidly",
           "purposefully", "effortlessly", "comfortably", "neatly", "precisely", "cleanly", "freely", "evenly",
           "loosely", "quietly", "silently", "elegantly", "properly", "simply", "playfully", "happily", "cheerfully")
"""Adverbs of manner that fit any action (said before its verb); a fast segment gets only _MANNER_FAST."""
_MANNER_FAST = ("smoothly", "naturally", "confidently", "fluidly", "purposefully", "effortlessly", "cleanly",
                "quietly", "properly", "simply")
_COUNT = {1: "one", 2: "two", 3: "three", 4: "four", 5: "five", 6: "six", 7: "seven"}
_CIRCLE = {"clockwise": ("clockwise",), "counterclockwise": ("counterclockwise", "anticlockwise")}


def _cross(heads: Sequence[str], tails: Sequence[str]) -> list[str]:
    """Each head with one tail and each tail with one head, in turn (not every pair: a long product
    would drown the other templates of an action); a tail goes at the head's "@", else at its end."""
    def join(head: str, tail: str) -> str:
        return head.replace("@", tail) if "@" in head else f"{head} {tail}"

    return [join(h, tails[i % len(tails)]) for i, h in enumerate(heads)] + [
        join(heads[i % len(heads)], t) for i, t in enumerate(tails)]


def _times(reps: int) -> tuple[str, ...]:
    """Ways to say a number of repetitions after a verb phrase ("twice", "three times in a row", ...);
    for one repetition nothing (most often) or "once"."""
    if reps == 1:
        return ("", "", "once")
    n = _COUNT[reps]
    out = (f"{n} times", f"{n} times in a row", f"{n} consecutive times", f"{n} times in succession",
           f"{n} times back to back", f"exactly {n} times", f"a total of {n} times", f"{n} separate times")
    return out + {2: ("twice", "twice in a row", "a couple of times"), 3: ("thrice",)}.get(reps, ())


def _number_of(reps: int, plural: str) -> tuple[str, ...]:
    """Ways to say ``reps`` (more than one) of a counted noun: "three kicks", "a couple of kicks", ..."""
    n = _COUNT[reps]
    out = (f"{n} {plural}", f"{n} {plural} in a row", f"a set of {n} {plural}", f"{n} consecutive {plural}",
           f"{n} {plural} back to back", f"a total of {n} {plural}")
    return out + ((f"a couple of {plural}", f"a pair of {plural}") if reps == 2 else ())


def _walk(p: Mapping) -> list[str]:
    d, pace = p["direction"], p["pace"]
    adv = _PACE[pace]
    if d == "forward" and p.get("veer"):
        s = p["veer"]
        return [f"~walk forward and ~turn {s}", f"~walk ahead and then ~turn to the {s}",
                f"~walk forward and ~veer to the {s}", f"~walk straight , then ~turn {s} and ~keep walking",
                f"~walk forward before turning to the {s}", f"~walk forward , veering to the {s}",
                f"~head forward and gradually ~veer {s}", f"~walk ahead and ~change course to the {s}",
                f"~walk forward and ~make a {s} turn", f"~set off forward and ~veer toward {{poss}} {s}",
                f"~walk straight ahead , then gradually ~turn toward the {s}",
                f"~walk forwards and then ~head off to the {s}"] + _cross(
            [f"~walk forward @ and ~veer off to the {s}", f"~walk ahead @ , then ~turn {s}"], [a for a in adv if a])
    if d == "forward":
        verbs = {"slow": ("~walk", "~stroll", "~amble", "~mosey", "~plod", "~dawdle", "~tread"),
                 "normal": ("~walk", "~move", "~head", "~travel"),
                 "fast": ("~walk", "~stride", "~hurry", "~hasten", "~scurry")}[pace]
        ways = ("forward", "forwards", "ahead", "straight ahead", "straight forward")
        adj = {"slow": ("slow", "careful"), "normal": ("steady", "regular", "even", "casual"),
               "fast": ("quick", "brisk", "hurried")}[pace]
        return _cross([f"{v} {w}" for v in verbs for w in ways], adv) + _cross(
            [f"{b} {v}" for b in _PACE_BEFORE[pace] for v in verbs], ways) + _cross(
            ["~walk in a straight line", "~make {poss} way forward", "~go straight ahead", "~walk a few steps forward",
             "~walk forward for a few seconds", "~walk a few meters forward",
             "~walk forward @ and then ~come to a stop", "~walk ahead @ and ~stop"], adv) + _cross(
            ["~take @ steps forward", "~walk forward with a @ gait", "~take a @ walk forward",
             "~walk forward with @ steps"], adj) + ["~take a few paces forward"] + (
            ["~take a slow stroll forward"] if pace == "slow" else
            ["~walk ahead with quick steps", "~walk forward with brisk strides"] if pace == "fast" else [])
    if d == "backward":
        return _cross([f"{v} {w}" for v in ("~walk", "~move", "~step") for w in ("backward", "backwards")] + [
            "~back up", "~move back", "~walk a few meters backward"], adv) + [
            "~take a few steps back", "~step back", "~take small steps backward", "~walk backward , facing forward",
            "~take some steps backwards", "~take a few paces back"]
    return _cross([
        f"~walk sideways to the {d}", f"~sidestep to the {d}", f"~step sideways to the {d}", f"~shuffle to the {d}",
        f"~move sideways toward the {d}", f"~take side steps to the {d}", f"~sidle to the {d}",
        f"~shuffle sideways to {{poss}} {d}", f"~move over to the {d}", f"~take a few steps to the {d}",
        f"~walk sideways toward {{poss}} {d}", f"~sidestep toward {{poss}} {d}", f"~travel sideways to the {d}",
        f"~step over to the {d}", f"~move a little way to the {d}"], adv)


def _jog(p: Mapping) -> list[str]:
    return ["~jog forward", "~jog ahead", "~jog forward at a steady pace", "~go for a short jog", "~jog straight ahead",
            "~jog forwards", "~break into a jog", "~do a light jog forward",
            "~run lightly forward", "~jog at a moderate pace", "~jog at a comfortable pace", "~run at a jogging pace",
            "~jog steadily ahead", "~jog a short way forward", "~set off at a jog", "~jog forward at a regular pace",
            "~go for a jog", "~jog ahead with light steps", "~jog forward at a natural pace",
            "~jog forward and then ~come to a stop", "~jog forward for a few seconds", "~jog a few meters forward"]


def _run(p: Mapping) -> list[str]:
    if p["pace"] == "fast":
        return ["~run forward quickly", "~sprint forward", "~dash ahead", "~run fast", "~sprint straight ahead",
                "~dart forward", "~dash forward", "~run at a fast pace", "~sprint forwards", "~run hard",
                "~break into a sprint", "~take off running", "~run forward in a hurry", "~run quickly ahead",
                "~run briskly forward", "~run forward energetically", "~sprint ahead at a quick pace",
                "~zoom forward", "~shoot forward", "~make a dash forward", "~run off at a fast pace",
                "~sprint forward and then ~come to a halt", "~run forward quickly and ~stop"]
    return ["~run forward", "~run ahead", "~run straight forward", "~run forward at a steady pace", "~run forwards",
            "~go for a run", "~break into a run", "~run at a moderate pace", "~run at a normal pace",
            "~run steadily forward", "~run straight ahead", "~run forward at a regular pace", "~take off running",
            "~run off", "~take off at a run", "~set off running", "~run forward and ~come to a halt",
            "~run ahead for a few seconds and then ~stop"]


def _circle(p: Mapping) -> list[str]:
    side = "left" if p["direction"] == "counterclockwise" else "right"
    names = _CIRCLE[p["direction"]]
    if p.get("jog"):
        verbs, adv = ("~jog", "~run lightly"), ("",)
    else:
        verbs, adv = {"slow": ("~walk", "~stroll"), "normal": ("~walk", "~move")}[p["pace"]], _PACE[p["pace"]]
    ways = [f"in a {n} circle" for n in names] + [
        f"{names[0]} in a circle", f"around in a circle to the {side}", f"in a full circle , turning to the {side}",
        f"{names[-1]} in a circular pattern", f"in a circle , going {names[0]}", f"a full circle to the {side}",
        f"in a circle toward {{poss}} {side}", f"around {names[-1]}", f"in a {names[-1]} fashion",
        f"in a circular route to the {side}", f"in a {names[0]} circle and ~come back to the starting point"]
    return _cross([f"{v} {w}" for v in verbs for w in ways], adv) + [
        f"~circle around to the {side}", f"~circle {names[-1]}", f"~go around in a {names[0]} circle",
        f"~make a {names[-1]} circle", f"~complete a full {names[0]} circle"]


def _turn(p: Mapping) -> list[str]:
    s, angle = p["direction"], p["angle"]
    return {
        45: [f"~turn slightly to the {s}", f"~turn a little to the {s}", f"~turn slightly {s}",
             f"~make a slight turn to the {s}", f"~make a small turn to the {s}", f"~turn partly to the {s}",
             f"~turn {{poss}} body slightly to the {s}", f"~pivot slightly to the {s}",
             f"~turn a little toward {{poss}} {s}", f"~face slightly to the {s}",
             f"~twist {{poss}} body slightly to the {s}", f"~make an eighth of a turn to the {s}",
             f"~angle {{poss}} body to the {s}", f"~angle {{refl}} slightly to the {s}"],
        90: [f"~turn {s}", f"~turn to the {s}", f"~turn ninety degrees to the {s}", f"~make a quarter turn to the {s}",
             f"~pivot to the {s}", f"~turn to {{poss}} {s}", f"~face {s}", f"~turn to face the {s}",
             f"~take a {s} turn", f"~make a {s} turn", f"~turn {{poss}} body to the {s}",
             f"~pivot ninety degrees {s}", f"~turn towards the {s}", f"~do a quarter turn to the {s}",
             f"~turn and ~face {s}", f"~pivot to face the {s}", f"~turn sideways to the {s}"],
        135: [f"~turn sharply to the {s}", f"~turn most of the way around to the {s}", f"~pivot sharply {s}",
              f"~make a sharp turn to the {s}", f"~turn well past ninety degrees to the {s}",
              f"~turn sharply toward {{poss}} {s}", f"~take a sharp {s} turn",
              f"~turn more than ninety degrees to the {s}"],
        180: ["~turn around", f"~turn around to the {s}", "~turn to face the other way",
              f"~make a half turn to the {s}", f"~turn all the way around to the {s}", "~turn back around",
              "~turn to face the opposite way", "~do a half turn", f"~turn a hundred and eighty degrees to the {s}",
              f"~turn around over {{poss}} {s} shoulder", f"~pivot around to the {s}",
              "~turn around and ~face the other way", f"~swing around to the {s}",
              "~turn around to face the opposite way", "~turn around and ~look behind {refl}"],
        360: ["~spin around in a full circle", f"~turn in a complete circle to the {s}",
              f"~make a full turn to the {s}", f"~spin around once to the {s}", "~turn around in a full circle",
              "~spin all the way around", f"~do a full spin to the {s}", "~make a complete turn",
              f"~turn a full circle to the {s}", "~do a complete spin", f"~spin to the {s} in a full circle",
              f"~whirl all the way around to the {s}", "~whirl around in a full circle", "~spin around in place",
              "~turn in place in a full circle"],
    }[angle]


def _jump(p: Mapping) -> list[str]:
    n = p["reps"]
    if p["distance"] > 0:
        out = _cross(["~jump forward", "~leap forward", "~jump ahead", "~jump forward with both feet", "~leap ahead",
                      "~jump forwards", "~leap forward with {poss} feet together", "~jump a short way forward",
                      "~launch {refl} forward", "~propel {refl} forward with both feet"], _times(n))
        if n > 1:
            return out + _cross(["~do @ forward", "~do @", "~take @ forward"], _number_of(n, "jumps")) + [
                f"~do {_COUNT[n]} forward jumps", f"~take {_COUNT[n]} leaps forward"]
        return out + ["~do a long jump forward", "~do a standing long jump", "~take a leap forward",
                      "~jump forward and ~land on both feet", "~do a powerful jump forward"]
    out = _cross(["~jump in place", "~jump straight up", "~jump up", "~leap up", "~leap straight up",
                  "~jump up into the air", "~leap into the air", "~jump with both feet", "~launch {refl} upward",
                  "~get airborne", "~jump up with {poss} feet together"], _times(n))
    if n > 1:
        out += ["~jump up and down"] + [f"~do {c} in place" for c in _number_of(n, "jumps")]
    else:
        out += ["~do a jump in place", "~do a jump straight up", "~jump up and ~land on both feet",
                "~take off from the ground and ~land on both feet"]
    if p["height"] > 0.24:
        out += ["~jump high in the air", "~leap high into the air", "~jump up high"]
        out += ["~do a big jump", "~do a powerful jump"] if n == 1 else [f"~do {c}" for c in _number_of(n, "big jumps")]
    elif p["height"] < 0.16:
        out += ["~do a small jump"] if n == 1 else [f"~do {c}" for c in _number_of(n, "small jumps")]
    return out


def _hop(p: Mapping) -> list[str]:
    s, n = p["side"], p["reps"]
    w = "forward " if p["distance"] > 0 else ""
    heads = [f"~hop {w}on {{poss}} {s} leg", f"~hop {w}on the {s} foot", f"~balance on {{poss}} {s} leg and ~hop {w}",
             f"~jump {w}on {{poss}} {s} foot", f"~hop {w}with {{poss}} {s} leg", f"~hop {w}on one leg , the {s} one ,",
             f"~keep {{poss}} weight on the {s} leg and ~hop {w}",
             f"~hop {w}on the {s} foot , keeping {{poss}} balance ,",
             f"~hop {w}on {{poss}} {s} foot with the other leg raised",
             f"~hop {w}on the {s} leg with the other foot lifted"]
    if w:
        heads += [f"~hop ahead on {{poss}} {s} leg", f"~hop forwards on the {s} foot"]
    return _cross(heads, _times(n)) + [
        f"~hop {_times(n)[0]} {w}on {{poss}} {s} foot", f"~stand on {{poss}} {s} leg and ~hop {w}",
        f"~hop {w}on {{poss}} {s} foot , keeping the other foot off the ground"] + _cross(
        [f"~do @ on {{poss}} {s} foot", f"~take @ {w}on the {s} leg"], _number_of(n, "hops"))


def _jumping_jacks(p: Mapping) -> list[str]:
    n = p["reps"]
    return _cross(["~do", "~perform", "~complete"], _number_of(n, "jumping jacks")) + [
        "~do jumping jacks", "~do some jumping jacks", "~perform a set of jumping jacks", f"~do {_COUNT[n]} jacks",
        f"~do {_COUNT[n]} repetitions of jumping jacks"] + _cross(
        ["~jump , spreading {poss} arms and legs ,", "~jump while spreading {poss} arms and legs"], _times(n))


def _squat(p: Mapping) -> list[str]:
    n = p["reps"]
    if n == 1:
        return ["~squat down and ~stand back up", "~do a squat", "~squat once",
                "~bend {poss} knees into a squat and ~rise again", "~lower {refl} into a squat and ~come back up",
                "~squat down and ~rise", "~do a knee bend", "~perform a squat",
                "~sit back into a squat and ~stand up again", "~squat down once and ~straighten {poss} legs",
                "~do an air squat", "~ease down into a squat and ~come back up"]
    return _cross(["~do", "~perform", "~complete"], _number_of(n, "squats")) + _cross(
        ["~squat", "~squat down and up", "~bend {poss} knees and ~squat", "~lower {refl} into a squat",
         "~squat and ~stand", "~squat down and ~rise"], _times(n)) + [
        f"~do {_COUNT[n]} knee bends", f"~do {_COUNT[n]} air squats"]


def _sit_down(p: Mapping) -> list[str]:
    return ["~sit down", "~take a seat", "~sit down on a chair", "~lower {refl} into a seat", "~sit down on a seat",
            "~sit on a chair", "~seat {refl}", "~seat {refl} on a chair", "~sit down in a chair",
            "~lower {refl} down into a chair", "~sit down on a couch", "~have a seat",
            "~bend {poss} knees and ~sit down", "~get seated", "~ease {refl} into a chair",
            "~ease {refl} down into a seat", "~sit down on a box", "~take a seat on a chair",
            "~lower {refl} down and ~sit", "~sit down on a chair behind {refl}", "~sit down and ~rest",
            "~sit down on a step"]


def _stand_up(p: Mapping) -> list[str]:
    return ["~stand up", "~get up from a chair", "~rise from {poss} seat", "~stand up from the chair",
            "~get to {poss} feet", "~rise to {poss} feet", "~get up", "~rise up from the chair", "~stand back up",
            "~get out of the chair", "~get up off the chair", "~rise from the chair", "~stand up straight",
            "~lift {refl} up from the seat", "~come to {poss} feet", "~arise from the chair",
            "~pull {refl} up from the chair", "~pull {refl} to {poss} feet", "~stand up tall",
            "~get up out of {poss} seat", "~lift {refl} out of the chair"]


def _crouch(p: Mapping) -> list[str]:
    return ["~crouch down and ~stand back up", "~crouch down low and ~rise again", "~duck down and ~come back up",
            "~get down into a crouch and then ~stand up", "~crouch low for a moment", "~crouch for a moment and ~rise",
            "~go down into a crouch", "~duck low and ~stand up again", "~lower {refl} into a crouch and ~get back up",
            "~crouch down for a second", "~bend down low and ~come back up", "~hold a low crouch for a moment",
            "~duck down for a second", "~bob down and ~come back up", "~stay low for a moment",
            "~pause in a crouch", "~crouch down for an instant", "~duck down and ~pause for a moment before rising",
            "~get low and then ~stand back up", "~crouch and ~hold the pose for a moment",
            "~crouch down momentarily"]


def _kick(p: Mapping) -> list[str]:
    s, n = p["side"], p["reps"]
    out = _cross([
        f"~kick with {{poss}} {s} leg", f"~kick forward with the {s} foot", f"~kick {{poss}} {s} leg out in front",
        f"~kick with the {s}", f"~kick out with {{poss}} {s} foot", f"~kick forward with {{poss}} {s} leg",
        f"~kick the air with {{poss}} {s} foot", f"~lift {{poss}} {s} leg and ~kick",
        f"~snap {{poss}} {s} leg forward", f"~swing {{poss}} {s} leg forward", f"~kick straight out with the {s} leg",
        f"~kick a ball with the {s} foot", f"~kick @ , leading with the {s} foot"], _times(n))
    if n > 1:
        out += _cross([f"~do @ with {{poss}} {s} leg", f"~throw @ with {{poss}} {s} leg",
                       f"~perform @ with the {s} leg", f"~aim @ with the {s} foot", f"~unleash @ with the {s} leg"],
                      _number_of(n, "kicks")) + [
            f"~do {_COUNT[n]} front kicks with the {s} foot"]
    else:
        out += [f"~do a kick with the {s} leg", f"~throw a kick with the {s} leg",
                f"~do a front kick with {{poss}} {s} leg", f"~swing {{poss}} {s} leg forward in a kick",
                f"~aim a kick with the {s} foot", f"~make a kicking motion with {{poss}} {s} leg",
                f"~kick forward with the {s} foot and then ~put it back down",
                f"~make a kicking movement with the {s} leg", f"~unleash a kick with the {s} leg",
                f"~launch a kick with {{poss}} {s} foot"]
    if p["height"] >= 0.7:
        out += _cross([f"~kick high with {{poss}} {s} leg", f"~kick {{poss}} {s} leg up high"], _times(n))
        out += ([f"~do a high kick with the {s} foot"] if n == 1 else [f"~do {_COUNT[n]} high kicks with the {s} foot"])
    elif p["height"] < 0.45:
        out += _cross([f"~kick low with the {s} foot", f"~flick {{poss}} {s} foot forward"], _times(n))
        out += ([f"~do a low kick with {{poss}} {s} foot"] if n == 1 else
                [f"~do {_COUNT[n]} low kicks with {{poss}} {s} foot"])
    return out


def _punch(p: Mapping) -> list[str]:
    s, n = p["side"], p["reps"]
    if s == "both":
        return ["~punch with both hands", "~throw punches with alternating fists", "~box with both hands",
                "~punch forward with both fists , one after the other", "~jab with both fists , one after the other",
                "~punch forward with each hand in turn", "~box in the air", "~make boxing motions with both fists",
                "~raise {poss} fists into a guard and ~punch with each hand in turn",
                f"~throw a combination of {_COUNT[n]} punches", "~punch like a boxer , switching hands each time",
                f"~do {_COUNT[n]} alternating punches"] + _cross(
            ["~throw", "~throw @ , switching hands each time", "~fire off"], _number_of(n, "punches")) + _cross(
            ["~punch the air with both fists"], _times(n))
    out = _cross([
        f"~punch forward with {{poss}} {s} hand", f"~jab forward with {{poss}} {s} fist", f"~punch with the {s} arm",
        f"~punch the air with {{poss}} {s} fist", f"~punch straight ahead with the {s} hand",
        f"~hit the air with {{poss}} {s} fist", f"~punch out with the {s} fist", f"~extend {{poss}} {s} arm in a punch",
        f"~swing {{poss}} {s} fist forward", f"~punch from a guard with the {s} hand",
        f"~jab @ with {{poss}} {s} hand", f"~jab like a boxer with the {s} hand"], _times(n))
    if n > 1:
        return out + _cross([f"~throw @ with the {s} fist", f"~do @ with {{poss}} {s} hand",
                             f"~unleash @ with the {s} fist"], _number_of(n, "punches")) + _cross(
            [f"~throw @ with the {s} hand", f"~fire off @ with {{poss}} {s} hand"], _number_of(n, "jabs")) + [
            f"~aim {_COUNT[n]} straight punches with the {s} hand"]
    return out + [f"~throw a punch with {{poss}} {s} arm", f"~throw a {s} jab", f"~throw a punch with the {s} fist",
                  f"~aim a punch with the {s} hand", f"~make a punching motion with {{poss}} {s} arm",
                  f"~throw a straight punch with the {s} hand",
                  f"~punch forward with {{poss}} {s} fist and ~pull it back",
                  f"~unleash a punch with the {s} fist", f"~fire off a jab with {{poss}} {s} hand"]


def _wave(p: Mapping) -> list[str]:
    s = p["side"]
    if s == "both":
        return ["~wave both hands", "~wave with both arms", "~raise both hands and ~wave", "~wave both arms",
                "~wave with both hands above {poss} shoulders", "~wave with both hands in the air",
                "~wave both arms above {poss} head", "~wave {poss} arms back and forth",
                "~hold both hands up and ~wave", "~wave at someone with both hands", "~give a big wave with both arms",
                "~wave both hands from side to side", "~give a friendly wave with both hands",
                "~wave at the camera with both arms", "~hail someone with both hands",
                "~give a cheerful wave with both arms"]
    return [f"~wave {{poss}} {s} hand", f"~wave with the {s} hand", f"~raise {{poss}} {s} hand and ~wave",
            f"~wave with {{poss}} {s} arm", f"~lift the {s} hand and ~wave it", f"~wave to someone with the {s} hand",
            f"~wave at someone with {{poss}} {s} hand", f"~give a wave with {{poss}} {s} hand",
            f"~hold up {{poss}} {s} hand and ~wave", f"~wave {{poss}} {s} hand back and forth",
            f"~wave {{poss}} {s} hand from side to side", f"~wave {{poss}} {s} hand in the air",
            f"~put {{poss}} {s} hand up and ~wave", f"~move {{poss}} {s} hand from side to side in a wave",
            f"~hail someone with {{poss}} {s} hand", f"~give a friendly wave with the {s} hand",
            f"~wave at the camera with {{poss}} {s} hand", f"~wave to a friend with the {s} hand",
            f"~swing {{poss}} {s} forearm from side to side in a wave",
            f"~give a cheerful wave with {{poss}} {s} hand"]


def _raise_arms(p: Mapping) -> list[str]:
    s, d = p["side"], p["direction"]
    both = s == "both"
    limbs = ["both arms", "{poss} arms", "both hands", "both of {poss} arms"] if both else [
        f"{{poss}} {s} arm", f"the {s} arm", f"{{poss}} {s} hand", f"the {s} hand"]
    sides = "sides" if both else "side"
    where = {"up": ["above {poss} head", "up", "overhead", "up high", "upward", "upwards", "into the air",
                    "straight up", "high above {poss} head", "over {poss} head"],
             "forward": ["forward", "out in front", "in front of {poss} body", "straight out in front", "to the front",
                         "forwards", "out in front of {refl}", "forward to shoulder height"],
             "sideways": [f"out to the {sides}", "sideways", f"to the {sides}", "out sideways",
                          f"out to {{poss}} {sides}", f"out to the {sides} at shoulder level"],
             }[d]
    it = "them" if both else "it"
    out = _cross([f"{v} {limb}" for v in ("~raise", "~lift") for limb in limbs], where) + [
        f"~raise {limbs[1]} {where[0]} and ~lower {it} again", f"~hold {limbs[0]} {where[1]}",
        f"~lift {limbs[2]} {where[-1]} and then ~bring {it} back down",
        f"~raise {limbs[0]} {where[1]} and ~hold {it} there for a moment"]
    if d == "up":
        return out + [f"~put {limbs[1]} up", f"~reach {limbs[0]} up high", f"~bring {limbs[1]} up over {{poss}} head",
                      f"~shoot {limbs[0]} up into the air", f"~point {limbs[0]} straight up"] + (
            ["~raise both arms in victory", "~lift {poss} arms overhead in celebration",
             "~raise both arms up to celebrate"] if both else [])
    return out + _cross([f"~extend {limbs[0]}", f"~extend {limbs[1]}"], where[:3]) + [
        f"~stick {limbs[1]} {where[1] if d == 'forward' else where[0]}", f"~raise {limbs[0]} to shoulder height",
        f"~lift {limbs[1]} to shoulder level", f"~point {limbs[0]} {where[0]}"]


def _clap(p: Mapping) -> list[str]:
    n = p["reps"]
    if p["overhead"]:
        return ["~clap above {poss} head", "~clap {poss} hands over {poss} head",
                "~clap {poss} hands high above {poss} head", "~clap high in the air"] + _cross(
            ["~raise {poss} arms and ~clap overhead", "~clap {poss} hands above {poss} head", "~clap overhead",
             "~lift {poss} hands up and ~clap", "~clap with {poss} hands raised overhead"], _times(n))
    return ["~applaud", "~clap {poss} hands together", "~clap in front of {poss} chest", "~give some applause",
            "~clap to celebrate", "~applaud in celebration"] + _cross(
        ["~clap {poss} hands", "~clap", "~applaud", "~clap {poss} hands together", "~put {poss} hands together",
         "~bring {poss} hands together", "~clap {poss} hands in front of {poss} chest",
         "~clap {poss} hands in applause",
         "~clap {poss} hands in approval"], _times(n)) + [f"~give {c}" for c in _number_of(n, "claps")]


def _bow(p: Mapping) -> list[str]:
    if p["depth"] > 0.75:
        return ["~bow deeply", "~take a deep bow", "~bend forward deeply at the waist and ~straighten up",
                "~do a deep bow", "~bow low", "~make a deep bow", "~bow down deeply", "~give a deep bow",
                "~bend deeply at the waist", "~bow deeply from the waist", "~lower {poss} upper body deeply",
                "~bow deeply to the audience", "~take a deep bow and ~hold the pose for a moment"]
    if p["depth"] < 0.55:
        return ["~bow slightly", "~do a small bow", "~bend forward slightly and ~straighten up", "~bow {poss} head",
                "~give a slight bow", "~make a little bow", "~lower {poss} head slightly", "~bow a little",
                "~lean forward slightly in a bow", "~give a small bow to the audience", "~bow {poss} head humbly"]
    return ["~bow", "~take a bow", "~bend forward at the waist and ~straighten up", "~do a bow", "~make a bow",
            "~give a bow", "~bow from the waist", "~bow forward", "~bow courteously", "~bow graciously",
            "~bend {poss} upper body forward and ~come back up", "~bow to the audience", "~bow to thank the audience",
            "~bow humbly", "~bow formally", "~bow and ~hold the pose for a moment", "~bow in respect",
            "~bow in gratitude", "~bow to acknowledge the audience"]


def _stretch(p: Mapping) -> list[str]:
    m = p["mode"]
    if m == "up":
        return ["~stretch {poss} arms above {poss} head", "~reach up and ~stretch", "~stretch upward",
                "~stretch both arms overhead", "~reach up high and ~stretch", "~stretch upward with both arms",
                "~reach {poss} arms above {poss} head and ~stretch", "~extend {poss} arms overhead in a stretch",
                "~stretch {poss} arms straight up", "~do an overhead stretch", "~stretch up tall",
                "~reach high above {poss} head and ~hold the stretch", "~do a big stretch with {poss} arms up"]
    if m == "out":
        return ["~stretch {poss} arms out to the sides", "~spread {poss} arms wide",
                "~extend both arms out to the sides",
                "~stretch both arms out sideways", "~spread both arms out wide",
                "~stretch out {poss} arms to the sides",
                "~extend {poss} arms sideways and ~stretch", "~stretch {poss} arms wide",
                "~spread {poss} arms out to the sides", "~spread {poss} arms wide and ~hold the stretch",
                "~stretch out {poss} arms at shoulder height"]
    return [f"~stretch to the {m}", f"~lean to the {m} with {{poss}} arms overhead",
            f"~stretch {{poss}} body to the {m}", f"~bend to the {m} side with both arms up",
            f"~raise {{poss}} arms and ~lean {m}", f"~lean {{poss}} body to the {m}", f"~do a side stretch to the {m}",
            f"~bend sideways to the {m}", f"~stretch sideways to the {m}", f"~lean over to the {m} and ~stretch",
            f"~bend {{poss}} upper body to the {m}", f"~lean to the {m} and ~hold the stretch for a moment",
            f"~reach over to the {m} with {{poss}} arms overhead"]


def _look_around(p: Mapping) -> list[str]:
    a = p["first"]
    b = "right" if a == "left" else "left"
    out = ["~look around", f"~look to the {a} and then to the {b}", f"~turn {{poss}} head to the {a} and then the {b}",
           f"~glance {a} and {b}", f"~look {a} , then {b}", "~glance around", "~look both ways",
           f"~glance to the {a} , then to the {b}", f"~turn {{poss}} head {a} and {b}",
           f"~look over {{poss}} {a} shoulder and then {{poss}} {b} shoulder", f"~check to the {a} and then to the {b}",
           "~look from side to side", "~look all around", "~turn {poss} head from side to side",
           f"~look first to the {a} and then to the {b}",
           f"~glance over {{poss}} {a} shoulder , then over {{poss}} {b} one",
           f"~crane {{poss}} neck to the {a} and then to the {b}", "~look around the area",
           "~observe the area around {refl}", "~take a look around", f"~take a look to the {a} and then to the {b}",
           f"~look to each side , first to the {a}", "~look around curiously", "~check both sides",
           "~search the area around {refl}", "~inspect the space around {refl}", "~look around the space"]
    if p["reps"] > 1:
        out += ["~look around from side to side"] + _cross([f"~look {a} and {b}", "~look from side to side"],
                                                           _times(p["reps"]))
    return out


def _throw(p: Mapping) -> list[str]:
    s = p["side"]
    return [f"~throw something with {{poss}} {s} hand", f"~throw a ball overhand with the {s} arm",
            f"~make a throwing motion with {{poss}} {s} arm", f"~wind up and ~throw with the {s} hand",
            f"~throw an object forward with {{poss}} {s} hand", f"~throw a ball with {{poss}} {s} hand",
            f"~throw a stone with the {s} hand", f"~chuck a ball with {{poss}} {s} arm",
            f"~pretend to throw a ball with the {s} hand", f"~mime throwing a ball with {{poss}} {s} hand",
            f"~throw something forward with the {s} arm", f"~launch a ball with {{poss}} {s} arm",
            f"~throw overhand with {{poss}} {s} arm", f"~step forward and ~throw with the {s} hand",
            f"~wind up and ~release a ball with {{poss}} {s} hand", f"~throw a snowball with {{poss}} {s} hand",
            f"~wind up and ~let a ball go with the {s} arm", f"~propel a ball forward with {{poss}} {s} arm",
            f"~throw a ball with {{poss}} {s} arm and ~follow through", f"~throw overarm with the {s} hand",
            f"~throw a ball overarm with {{poss}} {s} arm"]


def _pick_up(p: Mapping) -> list[str]:
    s = p["side"]
    hands = ["both hands"] if s == "both" else [f"{{poss}} {s} hand", f"the {s} hand"]
    out = _cross([
        "~pick something up from the floor with", "~bend down and ~pick up an object with",
        "~reach down to the ground and ~grab something with", "~pick up something off the ground with",
        "~reach down and ~grab an object with", "~bend over and ~lift something off the floor with",
        "~bend down to pick up a box with", "~grab a ball from the floor with", "~lift an object off the ground with",
        "~bend down and ~take something from the floor with", "~pick up a cup from the floor with",
        "~gather something from the ground with", "~get a book off the floor with",
        "~reach down for a toy and ~lift it with", "~raise a bottle from the ground with",
        "~bring a box up from the floor with", "~pick a thing up off the floor with",
        "~lean down and ~pick up a ball with", "~grasp an object on the floor with",
        "~pick up a phone from the floor with", "~grab a shoe off the ground with"], hands)
    if p["keep"]:
        held = "hands" if s == "both" else "hand"
        out += [f"~pick something up with {h} and ~hold it" for h in hands] + [
            "~pick up an object and ~keep it in front of {refl}", "~pick up a box and ~hold on to it",
            "~grab something from the floor and ~keep holding it",
            "~lift a ball off the ground and ~hold it against {poss} chest",
            f"~pick up a cup and ~keep it in {{poss}} {held}", "~pick up a book and ~hold it at chest height",
            "~pick up a box and ~clutch it to {poss} chest"]
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


_COMMON_SUBJECTS: tuple[Subject, ...] = tuple(
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
SUBJECTS: tuple[Subject, ...] = _COMMON_SUBJECTS + tuple(
    Subject(words, poss, refl)
    for group, poss, refl in (
        ("a boy|the boy|a young boy|a little boy|a small boy|a teenage boy|a young man|an old man|an older man|"
         "an elderly man|a grown man|an adult man|a fit man|a middle aged man|a gentleman|an elderly gentleman|"
         "a fellow|a male|this man|a grandfather|a father|a soldier|a businessman", "his", "himself"),
        ("a girl|the girl|a little girl|a young girl|a teenage girl|a young woman|an old woman|an older woman|"
         "an elderly woman|a grown woman|an adult woman|a fit woman|a middle aged woman|a female|this woman|"
         "a grandmother|a mother|a ballerina|a nurse", "her", "herself"),
        ("a child|the child|a kid|a teen|a teenager|a youngster|a student|an adult|a young adult|a senior|a dancer|"
         "the dancer|a gymnast|a player|a worker|a coach|a teacher|a referee|a boxer|a martial artist|a model|"
         "a young person|an old person|an elderly person|a middle aged person|this person|the individual|"
         "the human|a human being", "their", "themselves"),
        ("a stick figure|the stick figure|an avatar|the avatar|a humanoid|a mannequin|a robot|a skeleton|"
         "a virtual human|a digital human|an animated figure", "its", "itself"),
    )
    for words in group.split("|")
)
"""Who a caption is about; :func:`caption` draws half of its subjects from the first, most common ones."""
THIRD, GERUND = 0, 1
BASE, PAST = 2, 3
"""Verb forms: "walks", "walking", "walk" (after "to", "they", "we see a man ...") and "walked"."""


def inflect(lemma: str, form: int, irregular: Mapping[str, tuple[str, str]] = _IRREGULAR) -> str:
    """A verb in ``form`` (``THIRD``, ``GERUND``, ``BASE`` or ``PAST``)."""
    if form == BASE:
        return lemma
    if form == PAST:
        return past_tense(lemma, irregular)
    return verb_forms(lemma, irregular)[form]


def fill_template(template: str, subject: Subject, form: int,
                  irregular: Mapping[str, tuple[str, str]] = _IRREGULAR) -> list[Word]:
    """Fill a clause template for ``subject`` and inflect its verbs (see :func:`inflect`)."""
    text = template.format(poss=subject.possessive, refl=subject.reflexive)
    return [(inflect(w[1:], form, irregular), w[1:]) if w.startswith("~") else (w, None) for w in text.split()]


def plain_words(text: str) -> list[Word]:
    """Words written as they are (no verb to inflect)."""
    return [(w, None) for w in text.split()]


def _pick(rng: np.random.Generator, options: Sequence):
    return options[int(rng.integers(len(options)))]


def _template(segment: Segment, form: int, rng: np.random.Generator) -> str:
    """One of the segment's clause templates that can be said in ``form`` (see :data:`_NO_PAST`)."""
    options = CLAUSES[segment.kind](segment.params)
    if form == PAST:
        options = [t for t in options if not any(w[1:] in _NO_PAST for w in t.split() if w.startswith("~"))]
    return str(_pick(rng, options))


def _clause(segment: Segment, subject: Subject, rng: np.random.Generator, form: int) -> list[Word]:
    """Words describing one segment (maybe with an adverb of manner), with its upper-body action if it has one."""
    main = _template(segment, form, rng)
    if main.startswith("~") and not any(w.endswith("ly") for w in main.split()) and rng.random() < 0.15:
        main = f"{_pick(rng, _MANNER_FAST if segment.params.get('pace') == 'fast' else _MANNER)} {main}"
    if segment.upper is None:
        return fill_template(main, subject, form)
    upper = _template(segment.upper, form, rng)
    pattern = int(rng.integers(6))
    if pattern == 1:
        return fill_template(upper, subject, form) + plain_words("while") + fill_template(main, subject, GERUND)
    if pattern == 2:
        return (fill_template(main, subject, form) + plain_words("and") + fill_template(upper, subject, form)
                + plain_words("at the same time"))
    if pattern == 5:
        return (fill_template(main, subject, form) + plain_words(", and meanwhile")
                + fill_template(upper, subject, form))
    link = {0: "while", 3: ",", 4: "while also"}[pattern]
    return fill_template(main, subject, form) + plain_words(link) + fill_template(upper, subject, GERUND)


_TENSE = -1
"""In :data:`_OPENINGS`: the sentence's tense (``THIRD`` or ``PAST``)."""
_OPENINGS = (
    ("{S}", _TENSE, _TENSE), ("{S}", _TENSE, _TENSE), ("{S}", _TENSE, _TENSE), ("{S}", _TENSE, _TENSE),
    ("{P} {S}", _TENSE, _TENSE), ("{P} {S}", _TENSE, _TENSE), ("{S} who", _TENSE, _TENSE),
    ("{S} {is}", GERUND, GERUND), ("{S} {is}", GERUND, GERUND), ("{S} {is} seen", GERUND, GERUND),
    ("{S} {is} shown", GERUND, GERUND), ("{S} {can} be seen", GERUND, GERUND), ("{S}", GERUND, GERUND),
    ("{S} ~start to", BASE, _TENSE), ("{S} ~begin to", BASE, _TENSE), ("{S} ~start off", GERUND, _TENSE),
    ("{S} ~appear to", BASE, _TENSE), ("{S} ~seem to", BASE, _TENSE),
    ("we see {S}", GERUND, GERUND), ("we see {S}", BASE, BASE), ("we watch {S}", BASE, BASE),
    ("you can see {S}", GERUND, GERUND), ("the video shows {S}", GERUND, GERUND),
    ("this clip shows {S}", GERUND, GERUND), ("there {is} {S}", GERUND, GERUND),
    ("the footage shows {S}", GERUND, GERUND), ("the animation depicts {S}", GERUND, GERUND),
    ("this sequence shows {S}", GERUND, GERUND),
    ("the clip features {S}", GERUND, GERUND), ("the video presents {S}", GERUND, GERUND),
    ("the animation illustrates {S}", GERUND, GERUND), ("this recording captures {S}", GERUND, GERUND),
    ("the camera shows {S}", GERUND, GERUND), ("we observe {S}", GERUND, GERUND), ("one can see {S}", GERUND, GERUND),
    ("{S} {is} captured", GERUND, GERUND), ("{S} {is} filmed", GERUND, GERUND), ("{S} {is} recorded", GERUND, GERUND),
    ("{S} {is} depicted", GERUND, GERUND), ("{S} {is} pictured", GERUND, GERUND),
    ("we can see {S}", GERUND, GERUND), ("here we see {S}", GERUND, GERUND), ("the clip records {S}", GERUND, GERUND),
    ("you will see {S}", GERUND, GERUND), ("you may notice {S}", GERUND, GERUND),
    ("the viewer sees {S}", GERUND, GERUND),
)
"""How a sentence opens: words around the subject {S} (after a scene word {P}; {is} and {can} and
~verbs in the sentence's tense), the verb form of its first clause and of the clauses after it."""
_SCENES = ("in this clip ,", "in this video ,", "in the video ,", "in this animation ,", "in this recording ,",
           "in the footage ,", "in this scene ,", "in this short clip ,", "in this example ,",
           "in this demonstration ,", "in this motion capture ,", "in this motion sequence ,", "on screen ,",
           "in this piece of footage ,", "in the given clip ,", "in this rendering ,", "in this animated clip ,",
           "during this clip ,", "in the video below ,", "in this sample ,", "in this instance ,", "in this snippet ,",
           "in this short sequence ,", "within this clip ,", "in this performance ,", "in this routine ,",
           "in this action clip ,", "in this preview ,", "in this visualization ,", "in this playback ,", "here")
_FIRSTS = ("first ,", "to start ,", "to begin ,", "to begin with ,", "at the beginning ,", "in the beginning ,")
"""Scene words that open a sentence ({P}); for more than one segment also words that say the first one."""
_PRONOUNS = {"his": "he", "her": "she", "their": "they", "its": "it"}


def _link(subject: Subject, form: int, k: int, count: int, rng: np.random.Generator, previous: str = ""
          ) -> tuple[list[Word], int]:
    """Words between clauses ``k - 1`` and ``k`` of ``count`` in time order (in the sentence's ``form``; not
    the ``previous`` link's words again), and the verb form of clause ``k``."""
    links: list[tuple[str, int]] = [(", then", form), ("and then", form), (", and then", form),
                                    (", and after that", form), ("before", GERUND)]
    if form in (THIRD, PAST):
        links += [(", after that", form), (", and after this", form), ("and thereafter", form),
                  (", and soon after", form), (", and shortly after that", form), ("and immediately after that", form),
                  (", and directly after that", form), ("and not long after", form), (", and following that ,", form),
                  ("prior to", GERUND), (", and once done ,", form), (", and when finished ,", form),
                  (", and straight after that", form), (", and with that done ,", form),
                  (", and without pausing ,", form), (", and without stopping ,", form),
                  (", then ~go on to", BASE), (", and then ~decide to", BASE), (", then ~switch to", GERUND),
                  (", then ~move on to", GERUND), (", and then ~transition to", GERUND)]
        pronoun = _PRONOUNS.get(subject.possessive)
        if pronoun is not None and k == count - 1:  # the pronoun is the subject of the last clause only
            verb = BASE if pronoun == "they" and form == THIRD else form
            links += [(f", and then {pronoun}", verb), (f", then {pronoun}", verb),
                      (f", and after that {pronoun}", verb), (f", after which {pronoun}", verb)]
    if k == count - 1 == 2:
        links += [(", and finally", form), (", and finally", form), (", before finally", GERUND)]
        links += [(", and at last", form), (", and to finish ,", form), (", and to wrap up ,", form),
                  (", and to conclude ,", form), (", and for the final part ,", form), (", and ultimately", form)
                  ] if form in (THIRD, PAST) else []
    words, next_form = _pick(rng, [link for link in links if link[0] != previous])
    return fill_template(words, subject, form), next_form


def _join(subject: Subject, segments: Sequence[Segment], rng: np.random.Generator) -> list[Word]:
    """One sentence about ``segments`` in time order, in the present or the past tense.

    The sentence opens with the subject in one of :data:`_OPENINGS` ("a man ...", "in this clip, a man
    ...", "a man is seen ...", "the video shows a man ...", "we see a man ...", "a man starts to ...")
    and links the clauses with :func:`_link`; a sentence about more than one segment may instead open
    with the first one ("after walking forward, a man turns left") or, for two, end with it ("a man
    turns left after walking forward").
    """
    tense = PAST if rng.random() < 0.3 else THIRD
    head = plain_words(subject.words)
    if len(segments) > 1 and rng.random() < 0.1:
        if len(segments) == 2 and rng.random() < 0.5:
            return (head + _clause(segments[1], subject, rng, tense) + plain_words("after")
                    + _clause(segments[0], subject, rng, GERUND))
        words = plain_words("after") + _clause(segments[0], subject, rng, GERUND) + plain_words(",") + head
        words += _clause(segments[1], subject, rng, tense)
        if len(segments) == 3:
            link, form = _link(subject, tense, 2, 3, rng)
            words += link + _clause(segments[2], subject, rng, form)
        return words
    opening, first, rest = _pick(rng, _OPENINGS)
    first, rest = (tense if f == _TENSE else f for f in (first, rest))
    scene = _pick(rng, _SCENES + (_FIRSTS if len(segments) > 1 else ())) if "{P}" in opening else ""
    opening = opening.format(P=scene, S=subject.words, **{"is": "was" if tense == PAST else "is",
                                                          "can": "could" if tense == PAST else "can"})
    words = fill_template(opening, subject, tense)
    if len(segments) > 1 and first in (THIRD, PAST) and scene not in _FIRSTS and rng.random() < 0.3:
        words += plain_words(_pick(rng, ("first", "first", "at first")))
    words += _clause(segments[0], subject, rng, first)
    previous = ""
    for k in range(1, len(segments)):
        link, form = _link(subject, rest, k, len(segments), rng, previous)
        previous = " ".join(w for w, _ in link)
        words += link + _clause(segments[k], subject, rng, form)
    return words


def fix_articles(words: list[Word]) -> list[Word]:
    """"a" or "an" as the next word needs."""
    nexts = [w for w, _ in words[1:]] + ["x"]
    pairs = zip(words, nexts, strict=True)
    return [(("an" if nxt[0] in "aeiou" else "a"), v) if w in ("a", "an") else (w, v) for (w, v), nxt in pairs]


def caption_text(words: Sequence[Word], rng: np.random.Generator) -> str:
    """Caption text of words: commas attached, sometimes a full stop."""
    text = " ".join(w for w, _ in words).replace(" ,", ",")
    return text + "." if rng.random() < 0.5 else text


def _seated(subject: Subject, rng: np.random.Generator) -> Subject:
    """The subject, sitting ("a seated man", "someone sitting on a chair", "a boy seated in a chair")."""
    first, *rest = subject.words.split()
    if first in ("a", "an", "the") and rng.random() < 0.5:
        return replace(subject, words=" ".join([first, "seated", *rest]))
    where = _pick(rng, ("sitting on a chair", "sitting on a chair", "seated on a chair", "sitting in a chair",
                        "seated in a chair", "sitting on a couch"))
    return replace(subject, words=f"{subject.words} {where}")


def caption(segments: Sequence[Segment], rng: np.random.Generator, start: float = 0.0, end: float = 0.0,
            seated: bool = False) -> Caption:
    """A :class:`Caption` (text, tokens, span) describing segments played in order; ``seated``
    says that the subject sits at the start (and the first action does not say so)."""
    subject = SUBJECTS[int(rng.integers(len(_COMMON_SUBJECTS) if rng.random() < 0.5 else len(SUBJECTS)))]
    if seated and segments[0].kind != "stand_up":
        subject = _seated(subject, rng)
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
    captions = distinct_captions(lambda: caption(segments, rng, seated=postures[0] == "sit"), count)
    if len(segments) > 1:
        for segment, window, posture in zip(segments, windows, postures, strict=True):
            if min(window[1], length - 1) - window[0] >= min_span and rng.random() < span_prob:
                captions.append(caption([segment], rng, *span_seconds(window, length), posture == "sit"))
    return captions


def distinct_captions(make: Callable[[], Caption], count: int) -> list[Caption]:
    """Up to ``count`` captions of ``make`` with distinct texts (at most 20 * count tries)."""
    out: list[Caption] = []
    for _ in range(20 * count):
        candidate = make()
        if candidate.text not in {c.text for c in out}:
            out.append(candidate)
        if len(out) == count:
            break
    return out


def span_seconds(window: tuple[int, int], length: int) -> tuple[float, float]:
    """A segment's window [start, end) in frames as its span caption states it, in seconds: it ends
    before the motion's last frame, inside its ``length - 1`` feature frames."""
    start, end = window
    return round(start / FPS, 2), round(min(end, length - 1) / FPS, 2)


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
