"""Benchmark of the extract_features stage's two costs, measured side by side in one run.

1. HumanML3D feature extraction in clips/s on 1 and 2 worker processes (target: 2 workers
   >= 1.7x the clips/s of 1). Clips are the real HumanML3D fixture clip 012314, each rotated
   about y by a different angle, moved, and cropped to a different length (40..169 frames).
2. Text encoding in captions/s with the default frozen MiniLM encoder.

Usage: ``python benchmarks/extract_features.py [--clips 400] [--captions 1000]``
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from data.skeleton import HUMANML3D
from data.text_encoders import build_text_encoder
from stages.extract_features import compute_clip_features

FIXTURE = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "humanml3d" / "new_joints_012314.npy"


def make_jobs(n: int, seed: int = 0) -> list:
    """``n`` (clip_id, joints, skeleton) jobs made from the fixture clip."""
    rng = np.random.default_rng(seed)
    base = np.load(FIXTURE).astype(np.float64)
    jobs = []
    for k in range(n):
        yaw = rng.uniform(-np.pi, np.pi)
        rot = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
        length = int(rng.integers(41, base.shape[0] + 1))
        start = int(rng.integers(0, base.shape[0] - length + 1))
        joints = base[start : start + length] @ rot.T + np.array([rng.uniform(-2, 2), 0, rng.uniform(-2, 2)])
        jobs.append((f"{k:06d}", joints.astype(np.float32), HUMANML3D))
    return jobs


def clips_per_second(jobs: list, workers: int) -> float:
    start = time.perf_counter()
    results = compute_clip_features(jobs, workers, progress=False)
    elapsed = time.perf_counter() - start
    assert all(err is None for _, _, err in results)
    return len(jobs) / elapsed


def captions_per_second(n: int) -> float:
    verbs = ["walks", "runs", "jumps", "turns", "waves", "kicks", "squats", "sits down"]
    ways = ["slowly", "quickly", "forward", "to the left", "in a circle", "twice", "with the right hand"]
    rng = np.random.default_rng(1)
    texts = [f"a person {rng.choice(verbs)} {rng.choice(ways)} then {rng.choice(verbs)} #{k}" for k in range(n)]
    encoder = build_text_encoder("minilm")
    encoder.encode(texts[:64])  # warm-up
    start = time.perf_counter()
    encoder.encode(texts, batch_size=64)
    return n / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clips", type=int, default=400)
    parser.add_argument("--captions", type=int, default=1000)
    args = parser.parse_args()
    jobs = make_jobs(args.clips)
    clips_per_second(jobs[:20], 1)  # warm-up (imports, caches)
    one = clips_per_second(jobs, 1)
    two = clips_per_second(jobs, 2)
    caps = captions_per_second(args.captions)
    print(f"features, 1 worker : {one:8.1f} clips/s")
    print(f"features, 2 workers: {two:8.1f} clips/s  (speed-up {two / one:.2f}x, target >= 1.70x)")
    print(f"text encoding      : {caps:8.1f} captions/s (MiniLM, batch 64)")


if __name__ == "__main__":
    main()
