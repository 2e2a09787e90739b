"""The embedded dataset: procedurally generated motions with captions, in the HumanML3D layout.

A stand-in for HumanML3D so that every stage and metric has real work to do without
downloading anything (DESIGN.md, "The embedded dataset"). Each motion is

- a random adult body (:func:`data.synthetic_motion.sample_body`),
- a program of 1-3 actions from the library (:data:`data.synthetic_library.ACTIONS`) that follow
  each other from posture to posture ("walks forward, then turns around and sits down"); a
  carrier action (walking, jogging, circling, turning) may take an upper-body action on top
  ("walks while waving the right hand"),
- realised by leg IK + forward kinematics with planted feet (:mod:`data.synthetic_motion`),
- described by 3-5 paraphrased captions and, for long segments, span captions
  (:mod:`data.synthetic_text`),
- labelled, for statistics and previews, with the action class of its longest segment
  (:attr:`SyntheticMotion.label`); its *dataset* action label (``actions.txt``,
  :attr:`SyntheticMotion.action`) is set only for single-action motions (below).

Single-action rule (the action-to-motion protocol needs unambiguous labels): a motion gets a
dataset action label only when its program is exactly one segment **without** an upper-body
action on top. A carrier with a carried action ("walks while waving") is left unlabelled, like
every multi-action motion: the carried action changes what the motion looks like (its arms
move as in the ``wave`` class while its legs walk), so neither class describes it alone. The
idle lead-in and lead-out around the segment are not actions.

Motion ``i`` depends only on ``(seed, i)`` (its own :class:`numpy.random.SeedSequence`), so
the result does not depend on the number of worker processes. Mirrored copies (``M`` + id)
swap left and right in joints and captions, as HumanML3D's do, and share their original's split.
"""

from __future__ import annotations

import multiprocessing
from collections import Counter
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field, fields, replace

import numpy as np
from scipy.ndimage import gaussian_filter1d

from data.humanml3d import Caption
from data.humanml3d_writer import Clip
from data.physics import floating, ground_penetration, skating_frames
from data.skeleton import HUMANML3D
from data.synthetic_library import ACTIONS, Segment, build_segment
from data.synthetic_motion import FPS, Piece, State, assemble, initial_state, sample_body, style_noise
from data.synthetic_postures import build_idle
from data.synthetic_text import describe, mirror_caption

SPLITS = ("train", "val", "test")
CARRIED = ("wave", "raise_arms", "clap", "punch", "look_around")  # upper-body actions a carrier can take
_SPLIT_STREAM = 7_777_777  # SeedSequence key of the split shuffle (motions use their index)
PROGRAM_TRIES = 100  # draws of a motion's actions before its frame budget is called too small


@dataclass(frozen=True)
class SyntheticConfig:
    """Parameters of the generator (the ``synthetic:`` section of params.yaml).

    Attributes:
        num_motions: motions generated; mirroring adds as many again.
        min_joint_frames / max_joint_frames: length bounds of every motion in joint frames (feature
            extraction yields one frame fewer).
        actions_per_motion: probabilities of 1, 2, 3... actions in a motion.
        mix_prob: probability that a carrier action takes an upper-body action on top.
        span_prob: probability that a long segment of a multi-action motion gets a span caption.
        captions_per_motion: [min, max] whole-clip captions per motion.
        paraphrases: held-out paraphrases (data/paraphrase_text.py) written per test item (0: none).
        seated_start: probability that a motion starts seated.
        pelvis_height: [min, max] standing pelvis height of the bodies (m).
        style: amount of personal posture and drift added to the upper body (0: none).
        mirror: also write left/right mirrored copies.
        splits: split fractions of the (original) motions, mirrors follow their originals.
        previews: preview GIFs rendered by make_dataset (0: no previews, no contact sheet).
        workers: generator processes.
    """

    num_motions: int = 1000
    min_joint_frames: int = 44
    max_joint_frames: int = 196
    actions_per_motion: tuple[float, ...] = (0.4, 0.4, 0.2)
    mix_prob: float = 0.3
    span_prob: float = 0.4
    captions_per_motion: tuple[int, int] = (3, 5)
    paraphrases: int = 3
    seated_start: float = 0.05
    pelvis_height: tuple[float, float] = (0.9, 1.0)
    style: float = 1.0
    mirror: bool = True
    splits: Mapping[str, float] = field(default_factory=lambda: {"train": 0.8, "val": 0.05, "test": 0.15})
    previews: int = 6
    workers: int = 2

    def __post_init__(self) -> None:
        if self.num_motions < 1:
            raise ValueError("synthetic.num_motions must be >= 1")
        for key in ("mix_prob", "span_prob", "seated_start"):
            if not 0.0 <= getattr(self, key) <= 1.0:
                raise ValueError(f"synthetic.{key}: expected a probability in [0, 1], got {getattr(self, key)!r}")
        if not 0.0 < self.pelvis_height[0] <= self.pelvis_height[1]:
            raise ValueError(f"synthetic.pelvis_height must be [min, max] metres with 0 < min <= max, got "
                             f"{list(self.pelvis_height)}")
        if self.style < 0 or self.previews < 0 or self.workers < 1:
            raise ValueError(f"synthetic: need style >= 0, previews >= 0 and workers >= 1, got {self.style!r}, "
                             f"{self.previews!r} and {self.workers!r}")
        if not 2 <= self.min_joint_frames < self.max_joint_frames:
            raise ValueError("synthetic: need 2 <= min_joint_frames < max_joint_frames")
        if (set(self.splits) != set(SPLITS) or not all(0.0 <= f <= 1.0 for f in self.splits.values())
                or abs(sum(self.splits.values()) - 1.0) > 1e-6):
            raise ValueError(f"synthetic.splits must give fractions in [0, 1] of {SPLITS} summing to 1, got "
                             f"{dict(self.splits)}")
        if (not self.actions_per_motion or min(self.actions_per_motion) < 0
                or abs(sum(self.actions_per_motion) - 1.0) > 1e-6):
            raise ValueError(f"synthetic.actions_per_motion must be probabilities (>= 0) summing to 1, got "
                             f"{list(self.actions_per_motion)}")
        lo, hi = self.captions_per_motion
        if not 1 <= lo <= hi:
            raise ValueError("synthetic.captions_per_motion must be [min, max] with 1 <= min <= max")
        if isinstance(self.paraphrases, bool) or not isinstance(self.paraphrases, int) or self.paraphrases < 0:
            raise ValueError(f"synthetic.paraphrases must be an integer >= 0, got {self.paraphrases!r}")

    @classmethod
    def from_params(cls, section: Mapping | None) -> SyntheticConfig:
        """Config from a params section; missing keys take defaults, unknown keys are errors."""
        section = dict(section or {})
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(section) - known)
        if unknown:
            raise ValueError(f"unknown synthetic params {unknown}; known: {sorted(known)}")
        for key in ("actions_per_motion", "captions_per_motion", "pelvis_height"):
            if key in section:
                section[key] = tuple(section[key])
        return cls(**section)


@dataclass
class SyntheticMotion:
    """One generated motion with everything known about it.

    Attributes:
        clip_id: file stem (``M``-prefixed for a mirrored copy).
        joints: (T, 22, 3) float32 global joint positions.
        captions: whole-clip and span captions.
        label: action class of the longest segment (statistics, previews; every motion has one).
        segments: the actions in order, with their parameters.
        windows: [start, end) frames of each segment.
        steady: steady-speed frames of each locomotion segment (else None).
        postures: the posture ("stand"/"sit") each segment starts in.
    """

    clip_id: str
    joints: np.ndarray
    captions: list[Caption]
    label: str
    segments: list[Segment]
    windows: list[tuple[int, int]]
    steady: list[tuple[int, int] | None]
    postures: list[str]

    @property
    def action(self) -> str | None:
        """The dataset action label: the segment's class for a single-action motion, else None."""
        return single_action_label(self.segments)

    def clip(self) -> Clip:
        """The motion as a dataset clip (action label only for single-action motions)."""
        return Clip(self.clip_id, self.captions, joints=self.joints, action=self.action)


def motion_id(index: int) -> str:
    """HumanML3D-style zero-padded id."""
    return f"{index:06d}"


def _rng(seed: int, index: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(index)]))


def _choose_kind(rng: np.random.Generator, posture: str, previous: str | None) -> str:
    """A library action that can start from ``posture`` (not the previous one again)."""
    kinds = [k for k, a in ACTIONS.items() if posture in a.postures and k != previous]
    weights = np.array([ACTIONS[k].weight for k in kinds])
    return kinds[int(rng.choice(len(kinds), p=weights / weights.sum()))]


def _segment(rng: np.random.Generator, kind: str, mix_prob: float, next_kinds: set[str]) -> Segment:
    """A segment of ``kind`` with sampled parameters and maybe an upper-body action on top."""
    params = ACTIONS[kind].sample(rng)
    upper = None
    if ACTIONS[kind].carries and rng.random() < mix_prob:
        options = [k for k in CARRIED if k not in next_kinds and (kind != "jog" or k in ("wave", "look_around"))]
        upper_kind = options[int(rng.integers(len(options)))]
        upper = Segment(upper_kind, ACTIONS[upper_kind].sample(rng))
    return Segment(kind, params, upper)


def _program(rng: np.random.Generator, body, state: State, config: SyntheticConfig, budget: int
             ) -> tuple[list[Segment], list[Piece]]:
    """Segments (and their pieces) that chain posture to posture and fit in ``budget`` frames."""
    target = 1 + int(rng.choice(len(config.actions_per_motion), p=np.asarray(config.actions_per_motion)))
    segments: list[Segment] = []
    pieces: list[Piece] = []
    used = 0
    for _ in range(12 * target):
        if len(segments) == target:
            break
        kind = _choose_kind(rng, state.posture, segments[-1].kind if segments else None)
        segment = _segment(rng, kind, config.mix_prob, {s.kind for s in segments})
        piece = build_segment(body, state, segment)
        if used + len(piece.plan) > budget:
            continue
        segments.append(segment)
        pieces.append(piece)
        used += len(piece.plan)
        state = piece.end
    return segments, pieces


def _label(segments: Sequence[Segment], windows: Sequence[tuple[int, int]]) -> str:
    """Action class of the longest segment."""
    lengths = [b - a for a, b in windows]
    return segments[int(np.argmax(lengths))].label


def single_action_label(segments: Sequence[Segment]) -> str | None:
    """The class of a one-segment program without an upper-body action on top, else None."""
    if len(segments) == 1 and segments[0].upper is None:
        return segments[0].label
    return None


def generate_motion(seed: int, index: int, config: SyntheticConfig) -> SyntheticMotion:
    """Motion ``index`` of the dataset of ``seed`` (independent of every other motion)."""
    rng = _rng(seed, index)
    body = sample_body(rng, config.pelvis_height)
    posture = "sit" if rng.random() < config.seated_start else "stand"
    state = initial_state(body, float(rng.uniform(-np.pi, np.pi)), posture)
    lead_in = build_idle(body, state, {"duration": float(rng.uniform(0.2, 0.6))})
    tail = int(rng.integers(4, 12))
    budget = config.max_joint_frames - len(lead_in.plan) - tail
    for _ in range(PROGRAM_TRIES):
        segments, pieces = _program(rng, body, state, config, budget)
        if segments:
            break
    else:
        raise ValueError(f"synthetic.max_joint_frames: {config.max_joint_frames} frames left no room for an action "
                         f"after motion {index}'s lead-in and tail in {PROGRAM_TRIES} tries; raise it "
                         f"(the default is {SyntheticConfig.max_joint_frames})")
    end_state = pieces[-1].end
    length = len(lead_in.plan) + sum(len(p.plan) for p in pieces)
    tail = max(tail, config.min_joint_frames - length)
    lead_out = build_idle(body, end_state, {"duration": tail / FPS})
    all_pieces = [lead_in, *pieces, lead_out]
    n = sum(len(p.plan) for p in all_pieces)
    joints = assemble(body, all_pieces, style_noise(rng, n, config.style))
    starts = np.cumsum([len(p.plan) for p in all_pieces])
    windows = [(int(starts[k]), int(starts[k + 1])) for k in range(len(pieces))]
    steady = [None if p.steady is None else (p.steady[0] + a, p.steady[1] + a) for p, (a, _) in zip(pieces, windows,
                                                                                                   strict=True)]
    count = int(rng.integers(config.captions_per_motion[0], config.captions_per_motion[1] + 1))
    postures = [state.posture] + [p.end.posture for p in pieces[:-1]]
    captions = describe(segments, windows, postures, len(joints), rng, count, config.span_prob)
    return SyntheticMotion(motion_id(index), joints, captions, _label(segments, windows), segments, windows, steady,
                           postures)


# --- mirroring -------------------------------------------------------------------------------

_SWAP = {"left": "right", "right": "left", "clockwise": "counterclockwise", "counterclockwise": "clockwise"}
_SIDED_KEYS = ("side", "direction", "veer", "first", "mode", "lead")


def mirror_segment(segment: Segment) -> Segment:
    """The segment with sides and turning directions swapped."""
    params = {k: (_SWAP.get(v, v) if k in _SIDED_KEYS and isinstance(v, str) else v) for k, v in segment.params.items()}
    upper = None if segment.upper is None else mirror_segment(segment.upper)
    return Segment(segment.kind, params, upper)


def mirror_joints(joints: np.ndarray) -> np.ndarray:
    """Negate x and swap the left/right joints (HumanML3D's mirroring)."""
    out = joints.copy()
    out[..., 0] *= -1
    for a, b in HUMANML3D.mirror_pairs:
        out[:, [a, b]] = out[:, [b, a]]
    return out


def mirror_motion(motion: SyntheticMotion) -> SyntheticMotion:
    """The ``M``-prefixed mirrored copy of a motion."""
    return replace(
        motion,
        clip_id="M" + motion.clip_id,
        joints=mirror_joints(motion.joints),
        captions=[mirror_caption(c) for c in motion.captions],
        segments=[mirror_segment(s) for s in motion.segments],
    )


# --- the whole dataset -----------------------------------------------------------------------


def _generate_with_mirror(args: tuple[int, int, SyntheticConfig]) -> list[SyntheticMotion]:
    seed, index, config = args
    motion = generate_motion(seed, index, config)
    return [motion, mirror_motion(motion)] if config.mirror else [motion]


def generate(config: SyntheticConfig, seed: int) -> Iterator[SyntheticMotion]:
    """All motions (each original followed by its mirror), in index order, on ``config.workers``."""
    tasks = [(seed, i, config) for i in range(config.num_motions)]
    if config.workers <= 1:
        for task in tasks:
            yield from _generate_with_mirror(task)
        return
    with multiprocessing.get_context("spawn").Pool(config.workers) as pool:  # no fork of a threaded parent
        for motions in pool.imap(_generate_with_mirror, tasks, chunksize=8):
            yield from motions


def split_counts(num_motions: int, fractions: Mapping[str, float]) -> dict[str, int]:
    """Original motions per split: val and test rounded, train the rest."""
    n_val = int(round(fractions["val"] * num_motions))
    n_test = int(round(fractions["test"] * num_motions))
    return {"train": num_motions - n_val - n_test, "val": n_val, "test": n_test}


def make_splits(num_motions: int, fractions: Mapping[str, float], seed: int, mirror: bool
                ) -> dict[str, list[str]]:
    """Split ids by a seeded shuffle of the originals; a mirror joins its original's split. ValueError when a
    split would be empty."""
    counts = split_counts(num_motions, fractions)
    if min(counts.values()) < 1:  # extract_features refuses an empty split
        raise ValueError(f"synthetic.splits: {dict(fractions)} of synthetic.num_motions={num_motions} leaves a "
                         f"split empty ({counts}); every split needs a motion")
    order = np.random.default_rng(np.random.SeedSequence([int(seed), _SPLIT_STREAM])).permutation(num_motions)
    n_val, n_test = counts["val"], counts["test"]
    parts = {"val": order[:n_val], "test": order[n_val : n_val + n_test], "train": order[n_val + n_test :]}
    splits = {}
    for name in SPLITS:
        ids = [motion_id(i) for i in sorted(parts[name])]
        splits[name] = ids + ["M" + i for i in ids] if mirror else ids
    return splits


# --- statistics ------------------------------------------------------------------------------

LENGTH_BINS = (40, 60, 80, 100, 120, 140, 160, 180, 200)


def locomotion_key(segment: Segment) -> str | None:
    """Name under which a locomotion segment's speed is reported (None: not locomotion)."""
    if segment.kind == "walk":
        d = segment.params["direction"]
        if segment.params.get("veer"):
            return "walk_turning"
        return "walk_" + ("sideways" if d in ("left", "right") else d)
    if segment.kind == "circle":
        return "jog_circle" if segment.params.get("jog") else "walk_circle"
    return segment.kind if segment.kind in ("jog", "run") else None


def ground_speed(joints: np.ndarray, window: tuple[int, int]) -> float:
    """Mean horizontal pelvis speed (m/s) over frames [a, b), sway smoothed out."""
    a, b = window
    xz = gaussian_filter1d(joints[:, 0, [0, 2]].astype(np.float64), 3.0, axis=0, mode="nearest")[a:b]
    return float(np.linalg.norm(np.diff(xz, axis=0), axis=1).sum() * FPS / max(b - a - 1, 1))


def dataset_stats(motions: Sequence[SyntheticMotion]) -> dict:
    """Statistics of a generated dataset (stats.json): counts, vocabulary, lengths, speeds, physics."""
    per_action: dict[str, dict[str, int]] = {}
    words: set[str] = set()
    speeds: dict[str, list[float]] = {}
    skating = pairs = 0
    lengths = []
    for m in motions:
        entry = per_action.setdefault(m.label, {"motions": 0, "captions": 0})
        entry["motions"] += 1
        entry["captions"] += len(m.captions)
        words.update(w for c in m.captions for w, _ in c.tokens)
        lengths.append(len(m.joints))
        frames_ = skating_frames(m.joints, HUMANML3D)
        skating += int(frames_.sum())
        pairs += len(frames_)
        for segment, window in zip(m.segments, m.steady, strict=True):
            key = locomotion_key(segment)
            if key is not None and window is not None:
                speeds.setdefault(key, []).append(ground_speed(m.joints, window))
    counts, _ = np.histogram(lengths, bins=LENGTH_BINS)
    return {
        "motions": len(motions),
        "captions": sum(len(m.captions) for m in motions),
        "span_captions": sum(not c.is_whole_clip for m in motions for c in m.captions),
        "actions": {k: per_action[k] for k in sorted(per_action)},
        "labelled_actions": dict(sorted(Counter(m.action for m in motions if m.action is not None).items())),
        "segments": dict(sorted(Counter(s.kind for m in motions for s in m.segments).items())),
        "vocabulary_size": len(words),
        "length_histogram": {"bin_edges": list(LENGTH_BINS), "counts": counts.tolist()},
        "frames": {"min": int(min(lengths)), "max": int(max(lengths)), "mean": round(float(np.mean(lengths)), 2)},
        "mean_speed_mps": {k: round(float(np.mean(v)), 3) for k, v in sorted(speeds.items())},
        "speed_range_mps": {k: [round(float(min(v)), 3), round(float(max(v)), 3)] for k, v in sorted(speeds.items())},
        "foot_skating_ratio": round(skating / max(pairs, 1), 5),
        "lowest_joint_m": round(float(min(m.joints[..., 1].min() for m in motions)), 5),
        "ground_penetration_m": round(float(np.mean([ground_penetration(m.joints, HUMANML3D) for m in motions])), 6),
        "floating_m": round(float(np.mean([floating(m.joints, HUMANML3D) for m in motions])), 6),
    }
