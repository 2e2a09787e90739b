"""Stage ``make_dataset``: the embedded synthetic dataset (HumanML3D layout) in ``<paths.artifacts>/dataset``.

``python -m stages.make_dataset [key=value ...]`` generates ``synthetic.num_motions`` motions
(plus mirrors) from ``seed`` (data/synthetic.py) and writes, atomically::

    new_joints/<id>.npy  texts/<id>.txt  train.txt val.txt test.txt  actions.txt
    paraphrases/<id>.txt         held-out paraphrases of the test clips (data/paraphrase_text.py)
    stats.json                   counts, vocabulary, lengths, speeds, foot skating, floor contact
    preview/<id>.gif             a few motions as animations, with their first caption
    preview/contact_sheet.png    one panel per action class (no preview/ when synthetic.previews=0)

Everything is built in a temporary sibling directory that replaces the output only when
complete, so an interrupted run never leaves a dataset that looks finished. The output is always
``<paths.artifacts>/dataset`` (the stage's DVC out), never ``data.root``: with a real dataset
(``dataset=humanml3d``) ``data.root`` is the user's copy, which this stage must not touch. The
``synthetic`` dataset config points ``data.root`` here.
"""

from __future__ import annotations

import json
import time
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from data.atomic import atomic_directory, check_output
from data.humanml3d import PARAPHRASES_DIR
from data.humanml3d_writer import write_dataset
from data.paraphrase_text import paraphrases
from data.render import contact_sheet, render_animation
from data.skeleton import HUMANML3D
from data.synthetic import SyntheticConfig, SyntheticMotion, dataset_stats, generate, make_splits
from pipelines.cli import artifacts_dir, run_main
from pipelines.config import check_fields

SHEET_PANELS = 20
PARAPHRASE_STREAM = zlib.crc32(b"paraphrase")


def preview_motions(motions: Sequence[SyntheticMotion], count: int) -> list[SyntheticMotion]:
    """Up to ``count`` original motions with distinct action labels, in id order."""
    chosen: dict[str, SyntheticMotion] = {}
    for motion in motions:
        if not motion.clip_id.startswith("M") and motion.label not in chosen:
            chosen[motion.label] = motion
        if len(chosen) == count:
            break
    return list(chosen.values())


def write_previews(folder: Path, motions: Sequence[SyntheticMotion], gifs: int) -> None:
    """GIFs of ``gifs`` motions and a contact sheet of one motion per action class."""
    folder.mkdir(parents=True, exist_ok=True)
    for motion in preview_motions(motions, gifs):
        render_animation(motion.joints, folder / f"{motion.clip_id}.gif", motion.captions[0].text)
    sheet = preview_motions(motions, SHEET_PANELS)
    contact_sheet([m.joints for m in sheet], folder / "contact_sheet.png",
                  [f"[{m.label}] {m.captions[0].text}" for m in sheet], HUMANML3D)


def write_paraphrases(folder: Path, motions: Sequence[SyntheticMotion], clip_ids: Sequence[str], seed: int,
                      count: int) -> dict[str, int]:
    """``count`` held-out paraphrases of each item of the ``clip_ids`` motions, one caption file per
    clip; returns their number and vocabulary size. Each clip's stream is seeded by ``seed`` and its
    id, apart from the training captions' streams, which stay as they are."""
    folder.mkdir()
    wanted, words, total = set(clip_ids), set(), 0
    for m in motions:
        if m.clip_id not in wanted:
            continue
        rng = np.random.default_rng([seed, PARAPHRASE_STREAM, zlib.crc32(m.clip_id.encode())])
        spans = [c for c in m.captions if not c.is_whole_clip]
        captions = paraphrases(m.segments, m.windows, m.postures, len(m.joints), spans, rng, count)
        (folder / f"{m.clip_id}.txt").write_text("".join(c.to_line() + "\n" for c in captions), encoding="utf-8")
        words.update(w for c in captions for w, _ in c.tokens)
        total += len(captions)
    return {"captions": total, "vocabulary_size": len(words)}


def build_dataset(root: Path, config: SyntheticConfig, seed: int) -> dict:
    """Generate, write, preview and describe the dataset in ``root`` atomically; returns the stats."""
    check_output(root, owner="make_dataset")
    start = time.perf_counter()
    splits = make_splits(config.num_motions, config.splits, seed, config.mirror)
    total = config.num_motions * (2 if config.mirror else 1)
    motions = list(tqdm(generate(config, seed), total=total, desc="make_dataset", unit="motion"))
    generated = time.perf_counter()
    stats = dataset_stats(motions)
    with atomic_directory(root, owner="make_dataset") as tmp:
        write_dataset(tmp, (m.clip() for m in motions), splits, skeleton=HUMANML3D)
        if config.paraphrases > 0:
            stats["paraphrases"] = write_paraphrases(tmp / PARAPHRASES_DIR, motions, splits["test"], seed,
                                                     config.paraphrases)
        if config.previews > 0:
            write_previews(tmp / "preview", motions, config.previews)
        (tmp / "stats.json").write_text(json.dumps(stats, indent=2) + "\n", encoding="utf-8")
    written = "written with previews" if config.previews else "written"
    print(f"make_dataset: {total} motions in {generated - start:.1f}s, {written} in "
          f"{time.perf_counter() - start:.1f}s -> {root}")
    return stats


PARAMS = ("seed", "synthetic", "paths.artifacts")
OUT = "dataset"


def check_section(params: dict[str, Any]) -> None:
    """The ``synthetic`` section checked before any work: types (SyntheticConfig's fields), then its ranges."""
    check_fields(params["synthetic"], SyntheticConfig, "synthetic")
    config = SyntheticConfig.from_params(params["synthetic"])
    make_splits(config.num_motions, config.splits, 0, mirror=False)  # no split left empty


def run(params: dict[str, Any]) -> dict[str, Any]:
    """The stage with params: the dataset under ``<paths.artifacts>/dataset``; returns its statistics."""
    config = SyntheticConfig.from_params(params["synthetic"])
    return build_dataset(artifacts_dir(params) / OUT, config, int(params["seed"]))


def main(argv: Sequence[str] | None = None) -> None:
    """Run the stage with params.yaml and ``key=value`` overrides."""
    run_main("make_dataset", run, PARAMS, argv, checks=[check_section])


if __name__ == "__main__":
    main()
