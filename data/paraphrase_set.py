"""A dataset's held-out paraphrase set, ``paraphrases/<clip id>.txt``, read per test item.

The files have the ``texts/`` format: whole-clip captions (``0.0#0.0``) for the whole-clip item and
span captions for the span items, matched by their frames as ``texts/`` spans are. Every test item
must have at least one paraphrase. ``extract_features`` reads the set to check it, so a bad file
stops the pipeline before training, not at the evaluation; the evaluation reads it again to use it
(:mod:`pipelines.paraphrase`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Protocol

from data.humanml3d import PARAPHRASES_DIR, Caption, DatasetError, Problem, parse_captions


class Item(Protocol):
    """What the set is matched on: a :class:`data.humanml3d.MotionItem` or a :class:`data.store.StoredItem`."""

    item_id: str
    clip_id: str
    start: int

    @property
    def length(self) -> int: ...


def _item_captions(captions: Sequence[Caption], item: Item, fps: float, clip_end: int) -> list[str]:
    """The texts of ``captions`` (one clip's paraphrases) that describe ``item``.

    A span caption's frames are cut at ``clip_end``, the last frame the clip's items reach, as the
    reader cuts a ``texts/`` span that runs past the clip's end: a paraphrase copied from such a caption
    then names the item it was cut to.
    """
    if item.item_id == item.clip_id:
        return [c.text for c in captions if c.is_whole_clip]
    span = (item.start, item.start + item.length)
    return [c.text for c in captions
            if not c.is_whole_clip and (int(c.start * fps), min(int(c.end * fps), clip_end)) == span]


def read_paraphrases(root: Path, items: Sequence[Item], fps: float) -> dict[str, list[str]] | None:
    """item id -> its paraphrase texts, from ``<root>/paraphrases``; None when the folder does not exist.

    Raises:
        DatasetError: listing every unreadable file, bad caption line and item without a paraphrase.
    """
    folder = Path(root) / PARAPHRASES_DIR
    if not folder.is_dir():
        return None
    by_clip: dict[str, list[Caption]] = {}
    problems: list[Problem] = []
    out: dict[str, list[str]] = {}
    clip_end: dict[str, int] = {}
    for item in items:
        clip_end[item.clip_id] = max(clip_end.get(item.clip_id, 0), item.start + item.length)
    for item in items:
        path = folder / f"{item.clip_id}.txt"
        if item.clip_id not in by_clip:
            by_clip[item.clip_id], clip_problems = parse_captions(path)
            problems += clip_problems
        texts = _item_captions(by_clip[item.clip_id], item, fps, clip_end[item.clip_id])
        if texts:
            out[item.item_id] = texts
        elif path.is_file():
            problems.append(Problem(str(path), f"no paraphrase of item {item.item_id}"))
    if problems:
        raise DatasetError(problems, f"the paraphrase set {folder}")
    return out
