"""How the motions of a feature-store split travel: speed and heading change of the pelvis path.

    python benchmarks/path_stats.py [--split train] [key=value ...]

Per motion, from ``recover_from_ric`` of its features: the mean horizontal pelvis speed (m/s) and
the heading change of its path over the frames where it moves faster than ``--moving`` m/s (the
unwrapped direction of the pelvis step, last minus first). Prints quantiles of both and how many
motions turn more than 90 and 270 degrees while walking faster than ``--walking`` m/s: what a
trajectory-control model can learn to follow. Used for docs/controlnet.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data.features import recover_from_ric  # noqa: E402
from data.skeleton import get_skeleton  # noqa: E402
from pipelines.cli import repo_path  # noqa: E402
from pipelines.config import load_params  # noqa: E402
from pipelines.feature_store import FeatureStore  # noqa: E402


def path_stats(features: np.ndarray, joints_num: int, fps: float, moving: float) -> tuple[float, float]:
    """(mean horizontal pelvis speed in m/s, |heading change| in degrees while faster than ``moving`` m/s)."""
    steps = np.diff(recover_from_ric(features, joints_num)[:, 0, [0, 2]], axis=0)
    speed = np.linalg.norm(steps, axis=1) * fps
    fast = steps[speed > moving]
    if len(fast) < 2:
        return float(speed.mean()), 0.0
    heading = np.unwrap(np.arctan2(fast[:, 0], fast[:, 1]))
    return float(speed.mean()), float(np.degrees(abs(heading[-1] - heading[0])))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--split", default="train")
    parser.add_argument("--moving", type=float, default=0.4, help="m/s above which a step has a direction")
    parser.add_argument("--walking", type=float, default=0.7, help="m/s: the mean speed of a walk")
    parser.add_argument("overrides", nargs="*", help="params overrides, e.g. features.out=...")
    args = parser.parse_args()
    params = load_params(args.overrides)
    store = FeatureStore(repo_path(params, "features.out"))
    fps = get_skeleton(params["data"]["skeleton"]).fps
    items = store.split(args.split)
    stats = np.array([path_stats(item.features, store.joints_num, fps, args.moving) for item in items])
    speed, turn = stats[:, 0], stats[:, 1]
    print(f"{len(stats)} {args.split} motions")
    print("mean speed (m/s), quantiles 50/90/99:", np.percentile(speed, [50, 90, 99]).round(2).tolist())
    print("heading change while moving (degrees), quantiles 50/90/99:",
          np.percentile(turn, [50, 90, 99]).round(0).tolist())
    walking = speed > args.walking
    print(f"walking faster than {args.walking} m/s: {int(walking.sum())}; of them turning > 90 degrees: "
          f"{int((walking & (turn > 90)).sum())}, > 270 degrees: {int((walking & (turn > 270)).sum())}")


if __name__ == "__main__":
    main()
