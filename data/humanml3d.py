"""Reader of the HumanML3D dataset layout, with the records and checks its writer shares.

The writer is :mod:`data.humanml3d_writer`. Layout under a dataset ``root`` (HumanML3D's, see
DESIGN.md "Dataset layout")::

    new_joints/<id>.npy       (T, J, 3) float32 global joint positions   } at least one
    new_joint_vecs/<id>.npy   (T, 12J-1) float32 features                 } of the two
    texts/<id>.txt            one caption per line: ``caption#word/POS ...#start#end``
    train.txt val.txt test.txt   clip ids, one per line
    actions.txt               optional ``id,label`` lines (written by the synthetic generator)

Loading follows HumanML3D's ``Text2MotionDatasetV2`` (reference A.7):

* A clip's *feature length* is ``T - 1`` for ``new_joints`` (features are computed on frame
  pairs) and ``T`` for ``new_joint_vecs``. A clip is kept only if
  ``min_frames <= length < max_frames``.
* A caption with ``start == end == 0`` describes the whole clip; the whole-clip item exists
  only if there is at least one such caption, and it carries all of them.
* Any other caption is its own item covering feature frames
  ``[int(start * fps), int(end * fps))`` (clamped to the clip, like Python slicing), kept only
  if its length is within the same bounds. The reference hard-codes 20 fps here; we use the
  skeleton's fps, which is the same for HumanML3D (KIT-ML's captions carry no spans).
* Item ids are deterministic: ``clip_id`` for the whole-clip item and
  ``f"{clip_id}@{start}-{end}"`` for a span (``~2``, ``~3``... appended when several captions
  share one span). HumanML3D instead prefixes a random letter ``A``..``W`` and ``_``.

Motions outside the length bounds are a standard filter, not bad input: they are listed in
:attr:`SplitData.filtered`. Bad input (missing, corrupt or mis-shaped files, non-finite values,
unparsable captions...) is always a :class:`Problem`; ``on_error="fail"`` collects every problem
of the split and raises one :class:`DatasetError`, ``on_error="skip"`` drops the bad clips and
lists their problems in :attr:`SplitData.skipped`. Dataset-level problems (a missing split file,
a malformed ``actions.txt``, a split left without any item) raise in both modes. Reading never
writes.

Caveat: HumanML3D's own ``new_joints`` are ``recover_from_ric(new_joint_vecs)`` and so have as
many frames as the features; reading them with ``source="joints"`` counts one frame fewer than
the reference loader does. Use ``source="features"`` to reproduce the reference filter on real
HumanML3D data.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from data.skeleton import Skeleton

JOINTS_DIR = "new_joints"
FEATURES_DIR = "new_joint_vecs"
TEXTS_DIR = "texts"
PARAPHRASES_DIR = "paraphrases"  # optional held-out captions of the test clips (pipelines/paraphrase.py)
ACTIONS_FILE = "actions.txt"
SPLITS: tuple[str, ...] = ("train", "val", "test")
SOURCES: tuple[str, ...] = ("auto", "joints", "features")
ON_ERROR: tuple[str, ...] = ("fail", "skip")
DEFAULT_MAX_FRAMES = 200

# Problem kinds of the reader (Problem.kind), the categories of skip mode's summary.
UNREADABLE = "unreadable file"
MISSING = "missing file"
BAD_MOTION = "bad motion array"
IMPLAUSIBLE = "implausible skeleton"
BAD_CAPTION = "bad caption"
BAD_SPLIT_LINE = "bad split-file line"
SHARED_ID = "id in several splits"
EMPTY_SPLIT = "empty split"
PROBLEM_KINDS = (UNREADABLE, MISSING, BAD_MOTION, IMPLAUSIBLE, BAD_CAPTION, BAD_SPLIT_LINE, SHARED_ID, EMPTY_SPLIT)

# A clip's bones must be within these factors of the skeleton's reference lengths (median over
# frames, per bone). Retargeted data (HumanML3D's new_joints, new_joint_vecs) matches the
# reference to float precision and raw captures of adults stay well within 0.5-2x; the bounds
# are generous so that only a wrong unit or scale (mm read as m is 1000x, a 1e6 scale) or a
# broken skeleton is caught.
BONE_RATIO_RANGE = (0.2, 5.0)
BONE_CHECK_FRAMES = 16

# Clip ids become file names and split-file lines: letters, digits, '_', '-', '.', not starting
# with '.'. '@' and '~' are reserved for span item ids, ',' for actions.txt.
_CLIP_ID_RE = re.compile(r"[A-Za-z0-9_\-][A-Za-z0-9_\-.]*")
_SPLIT_NAME_RE = re.compile(r"[A-Za-z0-9_\-]+")
_FORBIDDEN_IN_TEXT = ("#", "\n", "\r")


# --------------------------------------------------------------------------------------------
# Captions
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Caption:
    """One line of a ``texts/<id>.txt`` file.

    Attributes:
        text: the caption (leading/trailing whitespace is stripped; must be non-empty and must
            not contain ``#`` or line breaks).
        tokens: ``(word, POS)`` pairs (spaCy tags in HumanML3D); may be empty.
        start, end: span in seconds; ``start == end == 0`` means the whole clip.

    Raises:
        ValueError: on construction, if the caption cannot be written as one valid line.
    """

    text: str
    tokens: tuple[tuple[str, str], ...]
    start: float = 0.0
    end: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.text, str):
            raise ValueError(f"caption text must be a str, got {type(self.text).__name__}")
        text = self.text.strip()
        if not text:
            raise ValueError("empty caption")
        if any(ch in text for ch in _FORBIDDEN_IN_TEXT):
            raise ValueError(f"caption text contains '#' or a line break: {text!r}")
        object.__setattr__(self, "text", text)
        object.__setattr__(self, "tokens", _normalise_tokens(self.tokens))
        start, end = _check_time(self.start, "start"), _check_time(self.end, "end")
        if start > end:
            raise ValueError(f"start {start} > end {end}")
        object.__setattr__(self, "start", start)
        object.__setattr__(self, "end", end)

    @property
    def is_whole_clip(self) -> bool:
        """True for a ``0.0#0.0`` caption, which describes the whole clip."""
        return self.start == 0.0 and self.end == 0.0

    def to_line(self) -> str:
        """Serialise as ``"text#w/POS w/POS#start#end"`` (no newline); inverse of from_line."""
        tokens = " ".join(f"{word}/{pos}" for word, pos in self.tokens)
        return f"{self.text}#{tokens}#{self.start!r}#{self.end!r}"

    @classmethod
    def from_line(cls, line: str) -> Caption:
        """Parse one caption line; NaN times read as 0 (HumanML3D).

        Raises:
            ValueError: with the reason (field count, bad float, start > end, bad token, ...).
        """
        fields = line.strip().split("#")
        if len(fields) != 4:
            raise ValueError(f"expected 4 '#'-separated fields (caption#tokens#start#end), got {len(fields)}")
        text, tokens, start, end = fields
        return cls(text, _parse_tokens(tokens), _parse_time(start, "start"), _parse_time(end, "end"))


def _normalise_tokens(tokens: Iterable[Sequence[str]]) -> tuple[tuple[str, str], ...]:
    """Tuple-of-pairs copy of ``tokens``; raises ValueError on a pair that cannot be written."""
    out = []
    for token in tokens:
        if len(token) != 2 or not all(isinstance(part, str) for part in token):
            raise ValueError(f"token must be a (word, POS) pair of str, got {token!r}")
        word, pos = token
        if not word or not pos or "/" in pos or _has_space_or_hash(word) or _has_space_or_hash(pos):
            raise ValueError(f"invalid token {word!r}/{pos!r}")
        out.append((word, pos))
    return tuple(out)


def _has_space_or_hash(s: str) -> bool:
    return "#" in s or any(ch.isspace() for ch in s)


def _parse_tokens(field_text: str) -> tuple[tuple[str, str], ...]:
    """Parse ``"w/POS w/POS"``; the POS is after the last '/'. Raises ValueError."""
    pairs = []
    for token in field_text.split():
        word, sep, pos = token.rpartition("/")
        if not sep or not word or not pos:
            raise ValueError(f"token {token!r} is not word/POS")
        pairs.append((word, pos))
    return tuple(pairs)


def _parse_time(field_text: str, name: str) -> float:
    """Parse a start/end field in seconds; NaN reads as 0. Raises ValueError."""
    try:
        value = float(field_text)
    except ValueError:
        raise ValueError(f"{name} {field_text!r} is not a number") from None
    return 0.0 if math.isnan(value) else value


def _check_time(value: float, name: str) -> float:
    """Return ``value`` as a float if it is a finite, non-negative time. Raises ValueError."""
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} {value!r} is not a number") from None
    if not math.isfinite(value) or value < 0:
        raise ValueError(f"{name} {value} is not a finite non-negative time")
    return value


# --------------------------------------------------------------------------------------------
# Records
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Problem:
    """A defect in the input: ``path`` is the file at fault (``file:line`` for a line).

    ``kind`` is a short category (one of :data:`PROBLEM_KINDS` for the reader's problems), under
    which skip mode summarises what it dropped; ``clip_id`` names the clip the problem drops (None
    for a problem of no one clip, such as a bad split-file line). Neither is part of equality.
    """

    path: str
    reason: str
    kind: str = field(default="bad input", compare=False)
    clip_id: str | None = field(default=None, compare=False)

    def __str__(self) -> str:
        return f"{self.path}: {self.reason}"


class DatasetError(Exception):
    """Bad dataset input; ``problems`` lists every defect found and ``str()`` shows them all."""

    def __init__(self, problems: Sequence[Problem], context: str = "dataset") -> None:
        super().__init__(list(problems), context)
        self.problems: list[Problem] = list(problems)
        self.context = context

    def __str__(self) -> str:
        lines = [f"{len(self.problems)} problem(s) in {self.context}:"]
        lines += [f"  - {problem}" for problem in self.problems]
        return "\n".join(lines)


@dataclass(frozen=True)
class MotionItem:
    """One training/evaluation item (HumanML3D's ``data_dict`` entry).

    Attributes:
        item_id: ``clip_id`` for the whole-clip item; ``f"{clip_id}@{start}-{end}"`` for a span
            (``~k`` appended for the k-th caption on the same span). Deterministic, unlike
            HumanML3D's random-letter prefix.
        clip_id: the clip in :attr:`SplitData.clips`.
        captions: all whole-clip captions for the whole-clip item; the one caption of a span.
        start, end: range ``[start, end)`` in the clip's *feature* frames. For a clip read from
            ``new_joints`` feature frame ``i`` spans joint frames ``i`` and ``i + 1``, so the
            joints are ``joints[start : end + 1]``.
        action: the clip's action label, if any.
    """

    item_id: str
    clip_id: str
    captions: tuple[Caption, ...]
    start: int
    end: int
    action: str | None

    @property
    def length(self) -> int:
        """Number of feature frames."""
        return self.end - self.start


@dataclass
class LoadedClip:
    """A clip's motion as read: exactly one of ``joints`` / ``features`` is set (float32)."""

    joints: np.ndarray | None = None
    features: np.ndarray | None = None

    @property
    def length(self) -> int:
        """Length in feature frames: ``T - 1`` for joints, ``T`` for features."""
        if self.joints is not None:
            return len(self.joints) - 1
        assert self.features is not None
        return len(self.features)


@dataclass
class SplitData:
    """Result of :func:`read_split`.

    Attributes:
        split: split name.
        clips: clip id -> motion, for every clip that has at least one item.
        items: items in split-file order (whole-clip item first, then spans in line order).
        skipped: problems of the clips dropped by ``on_error="skip"`` (empty in fail mode).
        filtered: clips and spans dropped by the standard length filter (not errors).
        cut: caption spans that run past their clip's end and were cut to it, as the reference loader cuts
            them (kept, not errors).
    """

    split: str
    clips: dict[str, LoadedClip] = field(default_factory=dict)
    items: list[MotionItem] = field(default_factory=list)
    skipped: list[Problem] = field(default_factory=list)
    filtered: list[Problem] = field(default_factory=list)
    cut: list[Problem] = field(default_factory=list)


# --------------------------------------------------------------------------------------------
# Validation shared by the reader and the writer
# --------------------------------------------------------------------------------------------


def clip_id_problem(clip_id: object) -> str | None:
    """Why ``clip_id`` is not a valid clip id, or None if it is."""
    if not isinstance(clip_id, str):
        return f"clip id must be a str, got {type(clip_id).__name__}"
    if not _CLIP_ID_RE.fullmatch(clip_id):
        return f"invalid clip id {clip_id!r} (allowed: letters, digits, '_', '-', '.'; not leading '.')"
    return None


def check_split_name(split: str) -> None:
    """Raise ValueError unless ``split`` is a plain split name (file ``<split>.txt``)."""
    if not isinstance(split, str) or not _SPLIT_NAME_RE.fullmatch(split) or split == "actions":
        raise ValueError(f"invalid split name {split!r}")


def array_problem(arr: np.ndarray, skeleton: Skeleton | None, kind: str) -> str | None:
    """Why ``arr`` is not a valid joints/features array, or None. ``kind``: joints|features."""
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        return f"dtype {arr.dtype} is not a real number type"
    if kind == "joints":
        shape_reason = _joints_shape_problem(arr.shape, skeleton)
    else:
        shape_reason = _features_shape_problem(arr.shape, skeleton)
    if shape_reason:
        return shape_reason
    bad = ~np.isfinite(arr)
    if bad.any():
        frame = int(np.argwhere(bad)[0][0])
        return f"{int(bad.sum())} non-finite values (NaN/inf), first in frame {frame}"
    return None


def to_float32(arr: np.ndarray) -> np.ndarray:
    """float32 copy; values beyond float32's range become inf (and are then reported)."""
    with np.errstate(over="ignore"):
        return arr.astype(np.float32)


def _joints_shape_problem(shape: tuple[int, ...], skeleton: Skeleton | None) -> str | None:
    """Why ``shape`` is not (T>=2, J, 3), or None."""
    joints = skeleton.joints_num if skeleton else None
    expected = f"(T, {joints if joints else 'J'}, 3)"
    if len(shape) != 3 or shape[2] != 3 or (joints is not None and shape[1] != joints):
        return f"wrong shape {shape}, expected {expected}"
    if shape[0] < 2:
        return f"{shape[0]} frame(s): too short to compute features (need T >= 2)"
    return None


def _features_shape_problem(shape: tuple[int, ...], skeleton: Skeleton | None) -> str | None:
    """Why ``shape`` is not (T>=1, 12J-1), or None."""
    dim = skeleton.feature_dim if skeleton else None
    if len(shape) != 2 or (dim is not None and shape[1] != dim) or (dim is None and shape[1] % 12 != 11):
        return f"wrong shape {shape}, expected (T, {dim if dim else '12J-1'})"
    if shape[0] < 1:
        return "0 frames"
    return None


# --------------------------------------------------------------------------------------------
# Reading files
# --------------------------------------------------------------------------------------------


def load_npy(path: Path) -> np.ndarray:
    """Read a plain ``.npy`` array (no pickles, no ``.npz``, no trailing bytes).

    Raises:
        ValueError: the file is not a complete, well-formed ``.npy`` array.
        OSError: the file cannot be read.
    """
    with open(path, "rb") as f:
        try:
            version = np.lib.format.read_magic(f)
            read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                           else np.lib.format.read_array_header_2_0)
            shape, _, dtype = read_header(f)
            declared = math.prod(shape) * dtype.itemsize  # checked before read_array allocates it
            left = os.fstat(f.fileno()).st_size - f.tell()
            if not dtype.hasobject and declared > left:
                raise ValueError(f"truncated: the header declares {declared} bytes of data (shape {shape}, "
                                 f"{dtype}), the file holds {left}")
            f.seek(0)
            arr = np.lib.format.read_array(f, allow_pickle=False)
        except EOFError as exc:
            raise ValueError(f"truncated: {exc}") from None
        if f.read(1):
            raise ValueError("trailing bytes after the array data")
    return arr


def _read_motion(path: Path, skeleton: Skeleton, kind: str) -> tuple[np.ndarray | None, Problem | None]:
    """Load and validate one motion file; returns (float32 array, None) or (None, Problem)."""
    try:
        arr = load_npy(path)
    except (OSError, ValueError) as exc:
        return None, Problem(str(path), f"unreadable or corrupt .npy: {exc}", UNREADABLE)
    reason = array_problem(arr, skeleton, kind)
    if reason is None and arr.dtype != np.float32:
        arr = to_float32(arr)
        reason = array_problem(arr, skeleton, kind)  # float64 -> float32 may overflow to inf
    if reason is not None:
        return None, Problem(str(path), reason, BAD_MOTION)
    reason = bone_length_problem(arr, skeleton, kind)
    if reason is not None:
        return None, Problem(str(path), reason, IMPLAUSIBLE)
    return arr, None


def bone_lengths(arr: np.ndarray, skeleton: Skeleton, kind: str) -> np.ndarray:
    """(T, J) bone lengths of a joints array, or of the joints a features array encodes (root 0).

    Features hold joints 1..J-1 relative to the root's ground position (``ric``, dims
    ``4 : 3J + 1``) and the root height (dim 3): the root sits at ``(0, height, 0)`` in that frame,
    and bone lengths do not depend on the frame.
    """
    if kind == "joints":
        return skeleton.bone_lengths_of(arr)
    j = skeleton.joints_num
    ric = arr[:, 4 : 3 * j + 1].reshape(len(arr), j - 1, 3).astype(np.float64)
    root = np.zeros((len(arr), 1, 3))
    root[:, 0, 1] = arr[:, 3]
    return skeleton.bone_lengths_of(np.concatenate([root, ric], axis=1))


def bone_length_problem(arr: np.ndarray, skeleton: Skeleton, kind: str) -> str | None:
    """Why a valid joints/features array's skeleton is implausible (:data:`BONE_RATIO_RANGE`), or None.

    Each bone's median length over the frames is compared with the skeleton's reference length.
    The median is taken over at most :data:`BONE_CHECK_FRAMES` evenly spaced frames: a scale
    shows in every frame, and reading stays cheap next to loading the file.
    """
    low, high = BONE_RATIO_RANGE
    frames = arr[:: -(-len(arr) // BONE_CHECK_FRAMES)]
    median = np.sort(bone_lengths(frames, skeleton, kind)[:, 1:], axis=0)[len(frames) // 2]  # (upper) median
    ratio = median / skeleton.bone_lengths[1:]
    bad = np.flatnonzero((ratio < low) | (ratio > high))
    if bad.size == 0:
        return None
    first, unit = bad[0], skeleton.unit
    return (f"implausible bone lengths: {bad.size} of {len(ratio)} bones are outside {low:g}-{high:g}x the "
            f"{skeleton.name} reference (median ratio {np.median(ratio[bad]):.3g}x), e.g. the bone to "
            f"{skeleton.joint_names[first + 1]!r} is {median[first] * unit:.4g} m (median over frames) against "
            f"{skeleton.bone_lengths[first + 1] * unit:.4g} m: wrong unit or scale?")


def _decode_text(path: Path, missing: str) -> tuple[str | None, Problem | None]:
    """Read a UTF-8 text file (BOM allowed); returns (text, None) or (None, Problem).

    ``missing`` is the Problem reason used when the file does not exist.
    """
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        return None, Problem(str(path), missing, MISSING)
    except OSError as exc:
        return None, Problem(str(path), f"unreadable: {exc}", UNREADABLE)
    try:
        return raw.decode("utf-8-sig"), None
    except UnicodeDecodeError as exc:
        return None, Problem(str(path), f"not UTF-8 text (byte {exc.start}: {exc.reason})", UNREADABLE)


def _content_lines(text: str) -> list[tuple[int, str]]:
    """(1-based line number, stripped line) of the non-blank lines, split on '\\n' only."""
    return [(n, line.strip()) for n, line in enumerate(text.split("\n"), 1) if line.strip()]


def parse_captions(path: Path) -> tuple[list[Caption], list[Problem]]:
    """Read ``texts/<id>.txt``: its captions and one Problem per defect (``file:line``).

    Blank lines are ignored; a file without any caption line is a problem.
    """
    text, problem = _decode_text(path, "no caption file for this motion")
    if problem:
        return [], [problem]
    captions, problems = [], []
    for lineno, line in _content_lines(text):
        try:
            captions.append(Caption.from_line(line))
        except ValueError as exc:
            problems.append(Problem(f"{path}:{lineno}", f"bad caption line: {exc}", BAD_CAPTION))
    if not captions and not problems:
        problems.append(Problem(str(path), "no caption lines", BAD_CAPTION))
    return captions, problems


def read_captions(path: Path) -> list[Caption]:
    """Captions of one text file; raises DatasetError listing every bad line."""
    captions, problems = parse_captions(Path(path))
    if problems:
        raise DatasetError(problems, str(path))
    return captions


def parse_split_ids(root: Path, split: str) -> tuple[list[str], list[Problem]]:
    """Ids of ``<root>/<split>.txt`` in order, plus problems of bad or repeated ids.

    Raises:
        DatasetError: the split file is missing, unreadable or not UTF-8.
    """
    lines, problems = _split_id_lines(root, split)
    return list(lines), problems


def _split_id_lines(root: Path, split: str) -> tuple[dict[str, int], list[Problem]]:
    """{clip id: line number} of ``<root>/<split>.txt`` in file order, plus bad-line problems."""
    check_split_name(split)
    path = Path(root) / f"{split}.txt"
    text, problem = _decode_text(path, "split file not found")
    if problem:
        raise DatasetError([problem], f"split {split!r}")
    problems: list[Problem] = []
    first_line: dict[str, int] = {}
    for lineno, clip_id in _content_lines(text):
        reason = clip_id_problem(clip_id)
        if reason is None and clip_id in first_line:
            reason = f"duplicate id {clip_id!r} (first on line {first_line[clip_id]})"
        if reason:
            problems.append(Problem(f"{path}:{lineno}", reason, BAD_SPLIT_LINE))
            continue
        first_line[clip_id] = lineno
    return first_line, problems


def read_split_ids(root: Path, split: str) -> list[str]:
    """Ids of a split file; raises DatasetError on a missing file or any bad line."""
    ids, problems = parse_split_ids(root, split)
    if problems:
        raise DatasetError(problems, f"split {split!r}")
    return ids


def parse_actions(root: Path) -> tuple[dict[str, str], list[Problem]]:
    """``actions.txt`` as {clip_id: label} (empty if absent) plus one Problem per bad line."""
    path = Path(root) / ACTIONS_FILE
    if not path.exists():
        return {}, []
    text, problem = _decode_text(path, "file not found")
    if problem:
        return {}, [problem]
    actions: dict[str, str] = {}
    problems: list[Problem] = []
    for lineno, line in _content_lines(text):
        clip_id, sep, label = (part.strip() for part in line.partition(","))
        reason = _action_line_problem(clip_id, sep, label, actions)
        if reason:
            problems.append(Problem(f"{path}:{lineno}", reason))
        else:
            actions[clip_id] = label
    return actions, problems


def _action_line_problem(clip_id: str, sep: str, label: str, seen: Mapping[str, str]) -> str | None:
    """Why an ``id,label`` line is malformed, or None."""
    if not sep:
        return "expected 'id,label'"
    if not label:
        return "empty action label"
    reason = clip_id_problem(clip_id)
    if reason:
        return reason
    if clip_id in seen:
        return f"duplicate id {clip_id!r}"
    return None


def load_actions(root: Path) -> dict[str, str]:
    """``actions.txt`` as {clip_id: label}; {} if absent; raises DatasetError if malformed."""
    actions, problems = parse_actions(root)
    if problems:
        raise DatasetError(problems, ACTIONS_FILE)
    return actions


# --------------------------------------------------------------------------------------------
# read_split
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Bounds:
    """Length filter ``low <= n < high`` in feature frames."""

    low: int
    high: int

    def reason(self, length: int) -> str | None:
        """Why ``length`` is filtered out, or None if it is kept."""
        if length < self.low:
            return f"length {length} < min_frames {self.low}"
        if length >= self.high:
            return f"length {length} >= max_frames {self.high}"
        return None


def _motion_path(root: Path, clip_id: str, source: str) -> tuple[str, Path] | Problem:
    """(kind, path) of the clip's motion file for ``source``, or a Problem if there is none."""
    joints = root / JOINTS_DIR / f"{clip_id}.npy"
    features = root / FEATURES_DIR / f"{clip_id}.npy"
    if source in ("auto", "joints") and joints.is_file():
        return "joints", joints
    if source in ("auto", "features") and features.is_file():
        return "features", features
    if source == "auto":
        return Problem(str(joints), f"no motion file for split id (neither {joints} nor {features})", MISSING)
    return Problem(str(joints if source == "joints" else features), "no motion file for split id", MISSING)


def _load_clip(
    root: Path, clip_id: str, skeleton: Skeleton, source: str
) -> tuple[LoadedClip | None, list[Caption], list[Problem]]:
    """Motion and captions of one clip, with every problem found in either."""
    problems: list[Problem] = []
    loaded = None
    located = _motion_path(root, clip_id, source)
    if isinstance(located, Problem):
        problems.append(located)
    else:
        kind, path = located
        arr, problem = _read_motion(path, skeleton, kind)
        if problem:
            problems.append(problem)
        else:
            loaded = LoadedClip(joints=arr) if kind == "joints" else LoadedClip(features=arr)
    captions, caption_problems = parse_captions(root / TEXTS_DIR / f"{clip_id}.txt")
    return loaded, captions, problems + caption_problems


def _span_frames(caption: Caption, fps: float) -> tuple[int, int]:
    """Feature-frame range of a span caption before any cut to its clip: ``int(start*fps), int(end*fps)``."""
    return int(caption.start * fps), int(caption.end * fps)


def _clip_items(
    clip_id: str,
    length: int,
    captions: Sequence[Caption],
    action: str | None,
    bounds: _Bounds,
    fps: float,
    text_path: Path,
) -> tuple[list[MotionItem], list[Problem], list[Problem]]:
    """Items of one clip that passed the clip-length filter, the filtered spans and the spans cut to the clip.

    A span is ``motion[int(start*fps):int(end*fps)]`` as in the reference loader, so a span that runs past
    the clip's end is cut to it (and reported as cut); one that starts at or after the end is filtered.
    """
    whole = tuple(c for c in captions if c.is_whole_clip)
    items = [MotionItem(clip_id, clip_id, whole, 0, length, action)] if whole else []
    filtered: list[Problem] = []
    cut: list[Problem] = []
    used: dict[str, int] = {}
    for caption in captions:
        if caption.is_whole_clip:
            continue
        first, last = _span_frames(caption, fps)
        start, end = min(first, length), min(last, length)
        span = f"span {caption.start}-{caption.end} s = frames [{first}, {last})"
        after_end = f"starts at or after the clip's end ({length} frames)"
        reason = after_end if first >= length else bounds.reason(end - start)
        if reason:
            filtered.append(Problem(str(text_path), f"{span}: {reason}: {caption.text!r}"))
            continue
        if last > length:
            cut.append(Problem(str(text_path), f"{span}: cut to [{start}, {end}) at the clip's end: {caption.text!r}"))
        base = f"{clip_id}@{start}-{end}"
        used[base] = used.get(base, 0) + 1
        item_id = base if used[base] == 1 else f"{base}~{used[base]}"
        items.append(MotionItem(item_id, clip_id, (caption,), start, end, action))
    return items, filtered, cut


def _check_options(source: str, on_error: str, min_frames: int, max_frames: int) -> None:
    """Raise ValueError on an unknown option value or empty length bounds."""
    if source not in SOURCES:
        raise ValueError(f"unknown source {source!r}; expected one of {SOURCES}")
    if on_error not in ON_ERROR:
        raise ValueError(f"unknown on_error {on_error!r}; expected one of {ON_ERROR}")
    if not 1 <= min_frames < max_frames:
        raise ValueError(f"need 1 <= min_frames < max_frames, got {min_frames}, {max_frames}")


def read_split(
    root: Path,
    split: str,
    skeleton: Skeleton,
    *,
    source: str = "auto",
    on_error: str = "fail",
    min_frames: int | None = None,
    max_frames: int = DEFAULT_MAX_FRAMES,
    exclude: Mapping[str, Problem] | None = None,
) -> SplitData:
    """Read one split of a HumanML3D-layout dataset into clips and items.

    Args:
        root: dataset root.
        split: split name; reads ``<root>/<split>.txt``.
        skeleton: expected skeleton (joint count, feature dim, fps, default min_frames).
        source: ``"joints"`` reads ``new_joints``, ``"features"`` reads ``new_joint_vecs``,
            ``"auto"`` reads ``new_joints/<id>.npy`` when it exists and otherwise
            ``new_joint_vecs/<id>.npy`` (decided per clip).
        on_error: ``"fail"`` raises one DatasetError listing every problem of the split;
            ``"skip"`` drops bad clips and lists their problems in ``SplitData.skipped``.
        min_frames: minimum feature length (default ``skeleton.min_frames``).
        max_frames: exclusive maximum feature length.
        exclude: ids not to read, each with the problem to report instead (:func:`read_splits`
            passes the ids already in an earlier split).

    Raises:
        ValueError: unknown ``source``/``on_error``, invalid split name or bounds.
        DatasetError: bad input (see module docstring); always for a missing split file or a
            malformed actions.txt.
    """
    low = skeleton.min_frames if min_frames is None else min_frames
    _check_options(source, on_error, low, max_frames)
    root = Path(root)
    bounds = _Bounds(low, max_frames)
    ids, problems = parse_split_ids(root, split)
    actions, action_problems = parse_actions(root)
    data = SplitData(split=split)
    for clip_id in ids:
        if exclude and clip_id in exclude:
            problems.append(replace(exclude[clip_id], clip_id=clip_id))
            continue
        loaded, captions, clip_problems = _load_clip(root, clip_id, skeleton, source)
        if clip_problems:
            problems += [replace(problem, clip_id=clip_id) for problem in clip_problems]
            continue
        assert loaded is not None
        _add_clip(data, root, clip_id, loaded, captions, actions.get(clip_id), bounds, skeleton.fps)
    if action_problems or (problems and on_error == "fail"):
        raise DatasetError(action_problems + problems, f"split {split!r} of {root}")
    data.skipped = problems
    return data


def _add_clip(
    data: SplitData,
    root: Path,
    clip_id: str,
    loaded: LoadedClip,
    captions: Sequence[Caption],
    action: str | None,
    bounds: _Bounds,
    fps: float,
) -> None:
    """Apply the length filters to a valid clip and add it and its items to ``data``."""
    motion_dir = JOINTS_DIR if loaded.joints is not None else FEATURES_DIR
    motion_path = str(root / motion_dir / f"{clip_id}.npy")
    reason = bounds.reason(loaded.length)
    if reason:
        data.filtered.append(Problem(motion_path, f"clip {reason} (feature frames)"))
        return
    text_path = root / TEXTS_DIR / f"{clip_id}.txt"
    items, filtered, cut = _clip_items(clip_id, loaded.length, captions, action, bounds, fps, text_path)
    data.filtered += filtered
    data.cut += cut
    if not items:
        data.filtered.append(Problem(motion_path, "no item left: no whole-clip caption and every span filtered"))
        return
    data.clips[clip_id] = loaded
    data.items += items


def read_splits(
    root: Path, skeleton: Skeleton, splits: Sequence[str] = SPLITS, **options: object
) -> dict[str, SplitData]:
    """:func:`read_split` for several splits, checked as a set of splits.

    Beyond each split's own problems: a clip id listed in more than one split (it would leak
    from training into evaluation) is a problem of every split after the first that lists it,
    and a split without any item is a problem of its split file. In fail mode one DatasetError
    lists every problem of every split; in skip mode a shared id is read only in its first split
    and its problem is listed in the split's ``skipped``. A split without any item is an error in
    both modes (the stages after it need every split), listing every split's problems.
    """
    root = Path(root)
    shared = shared_ids(root, splits)
    result: dict[str, SplitData] = {}
    by_split: list[list[Problem]] = []  # each split's problems, in order, for the error
    failed = False
    for split in splits:
        try:
            data = read_split(root, split, skeleton, exclude=shared.get(split), **options)  # type: ignore[arg-type]
        except DatasetError as exc:
            by_split.append(exc.problems)
            failed = True
            continue
        empty = [] if data.items else [_empty_split_problem(root, data)]
        by_split.append([*data.skipped, *empty])  # in skip mode the other splits' skipped clips are listed too
        failed = failed or bool(empty)
        result[split] = data
    if failed:
        raise DatasetError(list(dict.fromkeys(p for problems in by_split for p in problems)),
                           f"splits {list(splits)} of {root}")
    return result


def shared_ids(root: Path, splits: Sequence[str]) -> dict[str, dict[str, Problem]]:
    """Per split, the ids an earlier split already lists, each with its problem (``file:line``).

    Split files that cannot be read are left out (:func:`read_split` reports them).
    """
    first: dict[str, tuple[str, int]] = {}
    shared: dict[str, dict[str, Problem]] = {}
    for split in splits:
        try:
            lines, _ = _split_id_lines(root, split)
        except DatasetError:
            continue
        for clip_id, lineno in lines.items():
            if clip_id not in first:
                first[clip_id] = (split, lineno)
                continue
            other, other_line = first[clip_id]
            shared.setdefault(split, {})[clip_id] = Problem(
                f"{root / f'{split}.txt'}:{lineno}",
                f"clip id {clip_id!r} is also in {root / f'{other}.txt'}:{other_line}: "
                f"a clip in two splits leaks between them", SHARED_ID)
    return shared


def _empty_split_problem(root: Path, data: SplitData) -> Problem:
    """The problem of a split that has no item, with what became of its ids."""
    if not data.skipped and not data.filtered:
        reason = f"split {data.split!r} is empty: the file lists no clip id"
    else:
        reason = (f"split {data.split!r} has no item left: {len(data.skipped)} problem(s) with its clips, "
                  f"{len(data.filtered)} clip(s) or span(s) filtered by length")
    return Problem(str(root / f"{data.split}.txt"), reason, EMPTY_SPLIT)
