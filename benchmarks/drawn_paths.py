"""How closely the ControlNet follows drawn pelvis paths of several speeds and curves.

    python benchmarks/drawn_paths.py [--samples 16] [--length 120] [--model motionlcm-control] [key=value ...]

The evaluation scores the ControlNet on the test motions' own paths, which their captions describe
and which move as the training motions do; a user draws others. This runs
each case of :data:`CASES` (a caption and a shape of :mod:`data.trajectories`, on every frame of
``--length`` frames) ``--samples`` times in one batch (seed 0, the noise differs per sample) through
``stages.generate``'s generator, and prints per case: the path's speed, the mean pelvis distance to
the path frame by frame (m, the evaluation's Avg. err), the horizontal distance to the nearest point
of the path (m: the shape followed whatever the timing; a drawn path keeps one speed from the first
frame to the last, which real walks, starting and stopping, do not), the horizontal distance
between the last frame and the path's end (m), the generated pelvis's mean horizontal speed (m/s:
does it keep the path's pace or the caption's?) and the feet skating ratio. ``--model motionlcm``
gives the same numbers without control, as a reference. Point ``paths.artifacts`` at another
artifacts folder to compare ControlNets. Used for docs/controlnet.md.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data.control import CONTROL_JOINTS  # noqa: E402
from data.physics import foot_skating_ratio  # noqa: E402
from data.skeleton import get_skeleton  # noqa: E402
from models.generator import ControlledGenerator  # noqa: E402
from pipelines.cli import artifacts_dir, repo_path  # noqa: E402
from pipelines.config import load_params  # noqa: E402
from pipelines.registry import EvalContext, GenerateOptions, family  # noqa: E402
from stages.generate import pelvis_hint, pelvis_path  # noqa: E402

#: (caption, shape, size in metres): lines at four speeds, two zigzags, two circles, and a caption
#: that does not say what the path does.
CASES = (
    ("a person walks forward slowly", "line", 2.0),
    ("a person walks forward", "line", 3.0),
    ("a person walks forward", "line", 5.0),
    ("a person walks forward quickly", "line", 7.0),
    ("a person walks forward", "zigzag", 3.0),
    ("a person walks forward", "zigzag", 5.0),
    ("a person walks in a circle", "circle", 0.5),
    ("a person walks in a circle", "circle", 1.0),
    ("a person walks forward", "circle", 1.0),
)


def horizontal_speed(points: np.ndarray, fps: float) -> float:
    """Mean horizontal speed (m/s) of a track of points (T, 3)."""
    return float(np.linalg.norm(np.diff(points[:, [0, 2]], axis=0), axis=1).mean() * fps)


def path_measures(pelvis: np.ndarray, path: np.ndarray, fps: float) -> dict[str, float]:
    """A generated pelvis (T, 3) against a path (T, 3), in metres and m/s: ``error`` the mean distance
    frame by frame; ``off_path`` the mean horizontal distance to the path's nearest point (its frames
    taken as points); ``end`` the horizontal distance from the last frame to the path's end;
    ``speed`` the mean horizontal speed."""
    ground, target = pelvis[:, [0, 2]], path[:, [0, 2]]
    return {
        "error": float(np.linalg.norm(pelvis - path, axis=-1).mean()),
        "off_path": float(np.linalg.norm(ground[:, None] - target[None], axis=-1).min(1).mean()),
        "end": float(np.linalg.norm(ground[-1] - target[-1])),
        "speed": horizontal_speed(pelvis, fps),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=16)
    parser.add_argument("--length", type=int, default=120)
    parser.add_argument("--model", default="motionlcm-control")
    parser.add_argument("overrides", nargs="*")
    args = parser.parse_args()
    torch.set_num_threads(2)
    params = load_params(args.overrides)
    ctx = EvalContext(params, artifacts_dir(params), repo_path(params, "features.out"))
    generator = family(args.model).build_generator(ctx, GenerateOptions())
    controlled = isinstance(generator, ControlledGenerator)
    skeleton = get_skeleton(params["data"]["skeleton"])
    fps = float(skeleton.fps)
    pelvis = CONTROL_JOINTS["pelvis"]
    lengths = np.full(args.samples, args.length)
    every: list[dict[str, float]] = []  # every case's samples
    for caption, shape, size in CASES:
        path = pelvis_path(shape, args.length, ctx.store, size)  # dataset units, ahead of the body (generate's)
        text = ctx.store.encode_prompts([caption] * args.samples)
        if controlled:
            motions = generator.sample(text, lengths, 0, hint=pelvis_hint(path, args.samples, ctx.store.joints_num))
        else:
            motions = generator.sample(text, lengths, 0)
        joints = ctx.store.to_joints(motions, lengths)
        metres = path * skeleton.unit  # the measures are in metres (KIT-ML stores millimetres)
        measures = [path_measures(j[:, pelvis] * skeleton.unit, metres, fps) for j in joints]
        mean = {key: float(np.mean([m[key] for m in measures])) for key in measures[0]}
        every += measures
        print(json.dumps({
            "caption": caption, "shape": shape, "size": size,
            "path_speed": round(horizontal_speed(metres, fps), 3),
            "error_m": round(mean["error"], 3), "error_sd": round(float(np.std([m["error"] for m in measures])), 3),
            "off_path_m": round(mean["off_path"], 3), "end_m": round(mean["end"], 3), "speed": round(mean["speed"], 3),
            "skating": round(float(np.mean([foot_skating_ratio(j, skeleton) for j in joints])), 3),
        }), flush=True)
    print(json.dumps({"model": args.model, "artifacts": str(artifacts_dir(params)),
                      **{f"mean_{key}_m": round(float(np.mean([m[key] for m in every])), 3)
                         for key in ("error", "off_path", "end")}}))


if __name__ == "__main__":
    main()
