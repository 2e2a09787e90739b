"""Writer of the HumanML3D dataset layout (:func:`write_dataset`), and the :class:`Clip` it writes.

The layout, its records and the checks shared with the reader are in :mod:`data.humanml3d`. A
dataset is validated as a whole and written atomically: either every clip and split file is
written, or nothing is and the previous dataset stays.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data.atomic import atomic_directory
from data.humanml3d import (
    ACTIONS_FILE,
    FEATURES_DIR,
    JOINTS_DIR,
    TEXTS_DIR,
    Caption,
    DatasetError,
    Problem,
    array_problem,
    check_split_name,
    clip_id_problem,
    to_float32,
)
from data.skeleton import Skeleton


@dataclass
class Clip:
    """One motion with its captions, as given to :func:`write_dataset`.

    Attributes:
        clip_id: file stem (letters, digits, ``_``, ``-``, ``.``; not starting with ``.``).
        captions: at least one caption.
        joints: (T, J, 3) global joint positions, written to ``new_joints/``.
        features: (T', 12J-1) features, written to ``new_joint_vecs/``.
        action: optional action label, written to ``actions.txt``.
    """

    clip_id: str
    captions: list[Caption]
    joints: np.ndarray | None = None
    features: np.ndarray | None = None
    action: str | None = None


# --------------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------------


def _clip_problems(clip: object, seen: set[str], skeleton: Skeleton | None, dims: dict[str, int]) -> list[Problem]:
    """Every reason ``clip`` cannot be written; ``dims`` pins J / feature dim across clips."""
    if not isinstance(clip, Clip):
        return [Problem(repr(clip)[:80], f"not a Clip: {type(clip).__name__}")]
    where = f"clip {clip.clip_id!r}"
    reasons = [clip_id_problem(clip.clip_id)]
    if isinstance(clip.clip_id, str) and clip.clip_id in seen:
        reasons.append("duplicate clip id")
    reasons.append(_captions_problem(clip.captions))
    reasons.append(_action_problem(clip.action))
    if clip.joints is None and clip.features is None:
        reasons.append("neither joints nor features")
    for kind, arr in (("joints", clip.joints), ("features", clip.features)):
        if arr is not None:
            reasons.append(_writearray_problem(kind, arr, skeleton, dims))
    return [Problem(where, reason) for reason in reasons if reason]


def _captions_problem(captions: object) -> str | None:
    """Why a clip's caption list cannot be written, or None."""
    if not isinstance(captions, list | tuple) or not captions:
        return "no captions"
    if not all(isinstance(c, Caption) for c in captions):
        return "captions must be Caption objects"
    return None


def _action_problem(action: object) -> str | None:
    """Why an action label cannot be written to actions.txt, or None."""
    if action is None:
        return None
    if not isinstance(action, str) or not action.strip() or action != action.strip() or "\n" in action:
        return f"invalid action label {action!r}"
    return None


def _writearray_problem(kind: str, arr: object, skeleton: Skeleton | None, dims: dict[str, int]) -> str | None:
    """Why a joints/features array cannot be written, or None; records the first J / dim seen."""
    if not isinstance(arr, np.ndarray):
        return f"{kind} must be a numpy array, got {type(arr).__name__}"
    reason = array_problem(arr, skeleton, kind)
    if reason is None and arr.dtype != np.float32:
        reason = array_problem(to_float32(arr), skeleton, kind)
    if reason is None and skeleton is None:
        joints = arr.shape[1] if kind == "joints" else (arr.shape[1] + 1) // 12
        first = dims.setdefault("J", joints)
        if joints != first:
            reason = f"wrong shape {arr.shape}: {joints} joints, other clips have {first}"
    return f"{kind}: {reason}" if reason else None


def _split_problems(splits: Mapping[str, Sequence[str]], written: set[str]) -> list[Problem]:
    """Ids in the splits that are not written clips, ids repeated within a split, and ids in two splits (the
    reader refuses a clip in two splits: it leaks between training and test)."""
    problems = []
    first_split: dict[str, str] = {}
    for split, ids in splits.items():
        for clip_id in dict.fromkeys(ids):
            if first_split.setdefault(clip_id, split) != split:
                problems.append(Problem(f"{split}.txt", f"id {clip_id!r} is also in {first_split[clip_id]}.txt"))
        counts: dict[str, int] = {}
        for clip_id in ids:
            counts[clip_id] = counts.get(clip_id, 0) + 1
        for clip_id, count in counts.items():
            if clip_id not in written:
                problems.append(Problem(f"{split}.txt", f"id {clip_id!r} is not among the clips"))
            if count > 1:
                problems.append(Problem(f"{split}.txt", f"id {clip_id!r} listed {count} times"))
    return problems


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


def _write_clip(tmp: Path, clip: Clip) -> None:
    """Write one validated clip's motion files and caption file under ``tmp``."""
    for sub, arr in ((JOINTS_DIR, clip.joints), (FEATURES_DIR, clip.features)):
        if arr is not None:
            with open(tmp / sub / f"{clip.clip_id}.npy", "wb") as f:
                np.lib.format.write_array(f, np.ascontiguousarray(arr, dtype=np.float32), allow_pickle=False)
    text = "".join(caption.to_line() + "\n" for caption in clip.captions)
    (tmp / TEXTS_DIR / f"{clip.clip_id}.txt").write_text(text, encoding="utf-8")


def _write_lines(path: Path, lines: Iterable[str]) -> None:
    """Write ``lines`` one per line, UTF-8, '\\n' endings."""
    path.write_text("".join(f"{line}\n" for line in lines), encoding="utf-8")


def _write_into(
    tmp: Path, clips: Iterable[Clip], splits: Mapping[str, Sequence[str]], skeleton: Skeleton | None
) -> None:
    """Validate and write everything into ``tmp``; raises DatasetError listing every problem."""
    for sub in (JOINTS_DIR, FEATURES_DIR, TEXTS_DIR):
        (tmp / sub).mkdir()
    problems: list[Problem] = []
    written: set[str] = set()
    actions: dict[str, str] = {}
    dims: dict[str, int] = {}
    for clip in clips:
        clip_problems = _clip_problems(clip, written, skeleton, dims)
        if isinstance(clip, Clip) and isinstance(clip.clip_id, str):
            written.add(clip.clip_id)
        if clip_problems:
            problems += clip_problems
        elif not problems:  # once anything is wrong, only validate the rest
            _write_clip(tmp, clip)
            if clip.action is not None:
                actions[clip.clip_id] = clip.action
    problems += _split_problems(splits, written)
    if problems:
        raise DatasetError(problems, "write_dataset input")
    for split, ids in splits.items():
        _write_lines(tmp / f"{split}.txt", ids)
    if actions:
        _write_lines(tmp / ACTIONS_FILE, (f"{k},{v}" for k, v in actions.items()))


def write_dataset(
    root: Path,
    clips: Iterable[Clip],
    splits: Mapping[str, Sequence[str]],
    *,
    skeleton: Skeleton | None = None,
) -> None:
    """Write a HumanML3D-layout dataset atomically (:func:`data.atomic.atomic_directory`).

    Everything is written into a temporary directory beside ``root`` (``.<name>.tmp-*``), which
    is renamed to ``root`` only once every clip and split is valid and written; an existing
    ``root`` is replaced only then. On any failure the temporary directory is removed and an
    existing ``root`` is untouched.

    Args:
        root: dataset directory to create or replace.
        clips: clips to write (may be a generator; consumed once).
        splits: split name -> ids, written to ``<split>.txt`` in the given order.
        skeleton: if given, arrays must match its joint count / feature dim exactly; otherwise
            they must agree with each other.

    Raises:
        ValueError: invalid split name, or ``root`` holds data this writer did not write.
        NotADirectoryError: ``root`` exists and is not a directory.
        DatasetError: bad ids (invalid, duplicate, unknown in a split), empty captions,
            non-finite or mis-shaped arrays, invalid action labels -- all of them listed.
    """
    root = Path(root)
    for split in splits:
        check_split_name(split)
    if root.exists() and not root.is_dir():
        raise NotADirectoryError(f"{root} exists and is not a directory")
    with atomic_directory(root, owner="write_dataset") as tmp:
        _write_into(tmp, clips, splits, skeleton)
