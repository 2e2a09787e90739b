"""Stage ``extract_features``: a HumanML3D-layout dataset -> the feature store.

``python -m stages.extract_features [key=value ...]`` reads ``data.root`` (all three splits),
computes HumanML3D features from global joints in parallel processes (or validates precomputed
``new_joint_vecs``), the grouped Mean/Std over the train split, and the frozen text encoder's
embeddings of every caption; then writes atomically to ``features.out``::

    train.parquet  val.parquet  test.parquet   one row per motion item (data/store.py)
    mean.npy  std.npy                          (D,) float32, grouped as HumanML3D does
    meta.json                                  dataset, dims, counts, encoder, config hash
    skipped.json                               only with data.on_error=skip: what and why

With ``data.on_error=fail`` (default) any bad input makes the stage list every problem and exit
non-zero, writing nothing: the problems of reading the files and the clips whose features cannot
be computed, in one run (the motions that read are put through feature extraction before the
stage fails). Bad input includes the dataset as a whole: a clip id in two splits, an empty split
(:func:`data.humanml3d.read_splits`), a bad held-out paraphrase set (:mod:`data.paraphrase_set`,
an error in both modes), and statistics that cannot normalise (a zero std). With
``data.on_error=skip`` the bad clips are left out, listed in ``skipped.json`` (each problem with
its split and clip id) and summarised on the console, one line per kind of problem.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time
from collections import defaultdict
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from data.atomic import atomic_directory, check_output
from data.features import check_stats, features_from_joints, grouped_mean_std
from data.humanml3d import SPLITS, DatasetError, MotionItem, Problem, SplitData, read_splits
from data.paraphrase_set import read_paraphrases
from data.skeleton import SKELETONS, Skeleton, get_skeleton
from data.store import StoredItem, write_split
from data.text_encoders import TextEncoder, build_text_encoder
from pipelines.cli import run_main
from pipelines.config import REPO_ROOT, is_integer, refuse

FEATURE_VERSION = 1  # bump when the feature computation changes
ENCODE_CHUNK = 1024  # captions per encoder call: bounds the (N, L, H) token array in memory

PARAMS = ("data", "features")


def read_dataset(root: Path, skeleton: Skeleton, data_cfg: dict[str, Any]) -> dict[str, SplitData]:
    """Read every split, checked as a set (:func:`read_splits`), always in skip mode: the bad clips'
    problems are in each split's ``skipped``, and :func:`run` raises them in fail mode together with
    the feature extraction's, so one run lists them all. Dataset-level problems (a missing split
    file, an empty split) raise here in both modes."""
    return read_splits(root, skeleton, SPLITS, source=data_cfg["source"], on_error="skip",
                       max_frames=data_cfg["feature_frames_below"])


def _features_job(job: tuple[str, np.ndarray, Skeleton]) -> tuple[str, np.ndarray | None, str | None]:
    clip_id, joints, skeleton = job
    try:
        return clip_id, features_from_joints(joints, skeleton), None
    except ValueError as err:
        return clip_id, None, str(err)


def compute_clip_features(
    jobs: Sequence[tuple[str, np.ndarray, Skeleton]], workers: int, progress: bool = True
) -> list[tuple[str, np.ndarray | None, str | None]]:
    """Run :func:`features_from_joints` over (clip_id, joints, skeleton) jobs on ``workers`` processes.

    Returns (clip_id, features or None, error or None) in job order; the result does not depend
    on ``workers``.
    """
    bar = tqdm(total=len(jobs), desc="features", unit="clip", disable=not progress)
    results = []
    if workers <= 1:
        for job in jobs:
            results.append(_features_job(job))
            bar.update()
    else:
        chunk = max(1, len(jobs) // (workers * 8))
        with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("fork")) as pool:
            for result in pool.map(_features_job, jobs, chunksize=chunk):
                results.append(result)
                bar.update()
    bar.close()
    return results


def paraphrase_problems(root: Path, test_items: Sequence[MotionItem], fps: float) -> list[Problem]:
    """The problems of the held-out paraphrase set (:func:`data.paraphrase_set.read_paraphrases`), an error in
    both modes: checked here so that a bad paraphrase file stops the pipeline before training, not at the
    evaluation that reads it."""
    try:
        read_paraphrases(root, test_items, fps)
    except DatasetError as err:
        return err.problems
    return []


def clip_features(
    splits: dict[str, SplitData], root: Path, skeleton: Skeleton, workers: int
) -> tuple[dict[str, np.ndarray], list[Problem]]:
    """Features of every clip of every split; failures become Problems naming the clip's file and id."""
    feats, jobs = {}, []
    for data in splits.values():
        for clip_id, clip in data.clips.items():
            if clip.joints is not None:
                jobs.append((clip_id, clip.joints, skeleton))
            else:
                feats[clip_id] = clip.features
    problems = []
    for clip_id, features, error in compute_clip_features(jobs, workers):
        if error is None:
            feats[clip_id] = features
        else:
            problems.append(Problem(str(root / "new_joints" / f"{clip_id}.npy"), f"feature extraction failed: {error}",
                                    "feature extraction failed", clip_id))
    return feats, problems


def encode_captions(splits: dict[str, SplitData], encoder: TextEncoder, batch_size: int) -> dict[str, tuple]:
    """Encode each distinct caption once: text -> (pooled (E,), token embeddings (n, H) float16)."""
    texts = sorted({c.text for data in splits.values() for item in data.items for c in item.captions})
    result = {}
    for first in tqdm(range(0, len(texts), ENCODE_CHUNK), desc="text", unit="chunk", disable=not texts):
        chunk = texts[first : first + ENCODE_CHUNK]
        enc = encoder.encode(chunk, batch_size=batch_size)
        for k, text in enumerate(chunk):
            result[text] = (enc.pooled[k], enc.tokens[k][enc.mask[k]].astype(np.float16))
    return result


def build_items(data: SplitData, feats: dict[str, np.ndarray], text: dict[str, tuple]) -> list[StoredItem]:
    """Store rows for one split: each item's feature span and its captions' embeddings."""
    rows = []
    for item in data.items:
        if item.clip_id not in feats:  # its clip failed feature extraction (reported, skip mode)
            continue
        captions = [c.text for c in item.captions]
        rows.append(StoredItem(
            item_id=item.item_id,
            clip_id=item.clip_id,
            action=item.action,
            start=item.start,
            features=feats[item.clip_id][item.start : item.end],
            captions=captions,
            tokens=[[f"{w}/{p}" for w, p in c.tokens] for c in item.captions],
            text_pooled=np.stack([text[c][0] for c in captions]).astype(np.float32),
            text_tokens=[text[c][1] for c in captions],
        ))
    return rows


#: ``features`` keys that do not change what the store holds: where it goes and how many processes extract
#: it (the clips' features do not depend on it). Every ``data`` key does (``on_error``: skip mode writes
#: ``skipped.json``).
NOT_CONTENT = ("out", "workers")


def config_hash(params: dict[str, Any]) -> str:
    """Hash of everything that determines the store's content (``NOT_CONTENT`` left out)."""
    features = {key: value for key, value in params["features"].items() if key not in NOT_CONTENT}
    relevant = {"data": params["data"], "features": features, "version": FEATURE_VERSION}
    return hashlib.sha256(json.dumps(relevant, sort_keys=True).encode()).hexdigest()[:16]


def _problem_dicts(problems: Sequence[tuple[str, Problem]]) -> list[dict[str, str | None]]:
    """``skipped.json``'s entries: each problem's split, clip id (None for a bad split-file line), file,
    kind and reason."""
    return [{"split": split, "clip_id": p.clip_id, "path": p.path, "kind": p.kind, "reason": p.reason}
            for split, p in problems]


def files_by_kind(problems: Sequence[Problem]) -> dict[str, list[str]]:
    """The problems' file names (``file`` or ``file:line``), grouped by kind in order of first appearance."""
    by_kind: dict[str, list[str]] = defaultdict(list)
    for problem in problems:
        by_kind[problem.kind].append(Path(problem.path).name)
    return by_kind


def skip_summary(problems: Sequence[Problem], skipped_json: Path, shown: int = 3) -> str:
    """Console lines of skip mode: a header naming ``skipped_json``, then per kind of problem its
    count and first few files (``file`` or ``file:line``)."""
    by_kind = files_by_kind(problems)
    lines = [f"extract_features: data.on_error=skip left out {len(problems)} problem(s); "
             f"all of them in {skipped_json}"]
    for kind, names in by_kind.items():
        more = f", ... ({len(names) - shown} more)" if len(names) > shown else ""
        lines.append(f"  {kind}: {len(names)} ({', '.join(names[:shown])}{more})")
    return "\n".join(lines)


def filter_summary(filtered: Sequence[Problem], low: int, below: int, shown: int = 3) -> str:
    """One console line: how many clips and spans the length filter left out, and the first few (by file)."""
    names = [Path(p.path).name for p in filtered]
    more = f", ... ({len(names) - shown} more)" if len(names) > shown else ""
    return (f"extract_features: the length filter left out {len(filtered)} clip(s) or caption span(s) outside "
            f"{low}..{below - 1} frames ({', '.join(names[:shown])}{more}; counted in meta.json)")


def fail_summary(err: DatasetError, shown: int = 20) -> str:
    """The error of fail mode: its first ``shown`` problems, then how many there are of each kind."""
    if len(err.problems) <= shown:
        return str(err)
    lines = str(err).splitlines()[: shown + 1]
    lines.append(f"  ... and {len(err.problems) - shown} more; by kind: "
                 + ", ".join(f"{kind} {len(names)}" for kind, names in files_by_kind(err.problems).items()))
    return "\n".join(lines)


def run(params: dict[str, Any]) -> Path:
    """Extract features as configured; returns the output directory."""
    data_cfg, feat_cfg = params["data"], params["features"]
    root = (REPO_ROOT / data_cfg["root"]).resolve()
    out = (REPO_ROOT / feat_cfg["out"]).resolve()
    check_output(out, owner="extract_features")
    skeleton = get_skeleton(data_cfg["skeleton"])
    start = time.perf_counter()
    if not root.is_dir():
        raise DatasetError([Problem(str(root), "no such dataset folder: point data.root at a folder in the HumanML3D "
                                               "layout (see the README)")])

    # the text encoder first: a bad encoder path stops the stage before the motions are read
    encoder = build_text_encoder(
        feat_cfg["text_encoder"], path=feat_cfg["text_encoder_path"], max_length=feat_cfg["max_text_tokens"]
    )
    splits = read_dataset(root, skeleton, data_cfg)
    feats, failed = clip_features(splits, root, skeleton, feat_cfg["workers"])
    split_of = {clip_id: split for split, data in splits.items() for clip_id in data.clips}
    skipped = [(split, p) for split, data in splits.items() for p in data.skipped]
    skipped += [(split_of[p.clip_id], p) for p in failed]
    failing = [p for _, p in skipped] if data_cfg["on_error"] == "fail" else []
    failing += paraphrase_problems(root, [item for item in splits["test"].items if item.clip_id in feats],
                                   skeleton.fps)
    if failing:
        raise DatasetError(failing, f"splits {list(SPLITS)} of {root}")
    train_clips = {item.clip_id for item in splits["train"].items if item.clip_id in feats}
    if not train_clips:
        raise DatasetError([Problem(str(root / "train.txt"), "no usable training motion")])
    mean, std = grouped_mean_std(np.concatenate([feats[c] for c in sorted(train_clips)]), skeleton.joints_num)
    check_stats(mean, std, out, skeleton.feature_dim)  # before anything is written

    text = encode_captions(splits, encoder, feat_cfg["text_batch_size"])

    counts = {}
    with atomic_directory(out, owner="extract_features") as tmp:
        for split, data in splits.items():
            rows = build_items(data, feats, text)
            write_split(tmp / f"{split}.parquet", rows, skeleton.feature_dim, encoder.dim, encoder.token_dim)
            counts[split] = {
                "clips": len({r.clip_id for r in rows}),
                "items": len(rows),
                "captions": sum(len(r.captions) for r in rows),
                "frames": int(sum(r.length for r in rows)),
                "filtered": len(data.filtered),
                "skipped": sum(s == split for s, _ in skipped),  # problems
            }
        np.save(tmp / "mean.npy", mean.astype(np.float32))
        np.save(tmp / "std.npy", std.astype(np.float32))
        if data_cfg["on_error"] == "skip":
            (tmp / "skipped.json").write_text(json.dumps(_problem_dicts(skipped), indent=1))
        meta = {
            "dataset": data_cfg["name"],
            "root": str(data_cfg["root"]),
            "skeleton": skeleton.name,
            "joints_num": skeleton.joints_num,
            "feature_dim": skeleton.feature_dim,
            "fps": skeleton.fps,
            "counts": counts,
            "skipped": len(skipped),
            "text_encoder": encoder.describe(),
            "config_hash": config_hash(params),
            "feature_version": FEATURE_VERSION,
        }
        (tmp / "meta.json").write_text(json.dumps(meta, indent=2))
    if skipped:
        sys.stderr.write(skip_summary([p for _, p in skipped], out / "skipped.json") + "\n")
    untagged = sorted({item.clip_id for data in splits.values() for item in data.items
                       for caption in item.captions if not caption.tokens})
    if untagged:  # allowed (the text encoders read the text), but the evaluator reads the tokens
        sys.stderr.write(f"extract_features: captions of {len(untagged)} clip(s) have no word/POS tokens, which the "
                         f"T2M evaluator reads as an empty sentence (first: {', '.join(untagged[:3])})\n")
    filtered = [p for data in splits.values() for p in data.filtered]
    if filtered:
        print(filter_summary(filtered, skeleton.min_frames, data_cfg["feature_frames_below"]))
    cut = [p for data in splits.values() for p in data.cut]
    if cut:
        names = [Path(p.path).name for p in cut]
        print(f"extract_features: {len(cut)} caption span(s) run past their clip's end and were cut to it, as the "
              f"reference loader cuts them (first: {', '.join(names[:3])})")
    print(f"extract_features: {sum(c['items'] for c in counts.values())} items, "
          f"{len(text)} distinct captions in {time.perf_counter() - start:.1f} s -> {out}")
    return out


def check_section(params: dict[str, Any]) -> None:
    """``data.feature_frames_below`` above the skeleton's shortest clip (else the length filter keeps nothing),
    checked before the text encoder loads."""
    data_cfg = params["data"]
    below = data_cfg["feature_frames_below"]
    if not is_integer(below) or data_cfg["skeleton"] not in SKELETONS:
        return  # the shared checks name a non-integer or an unknown skeleton
    shortest = get_skeleton(data_cfg["skeleton"]).min_frames
    if below <= shortest:
        refuse(f"data.feature_frames_below: expected more than {data_cfg['skeleton']}'s shortest clip, "
               f"{shortest} feature frames, got {data_cfg['feature_frames_below']!r}")


def main(argv: Sequence[str] | None = None) -> None:
    os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")
    try:
        run_main("extract_features", run, PARAMS, argv, checks=[check_section])
    except DatasetError as err:
        if len(err.problems) == 1:
            sys.exit(f"extract_features: bad input, nothing written: {err.problems[0]}")
        sys.exit(f"extract_features: bad input, nothing written.\n{fail_summary(err)}")


if __name__ == "__main__":
    main()
