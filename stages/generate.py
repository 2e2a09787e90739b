"""User command: text to motion with a trained model.

    python -m stages.generate --model mld --text "a person walks forward then sits down" \\
        --length 120 --out walk.gif [--steps 50] [--guidance 7.5] [--seed 0] [key=value ...]

    python -m stages.generate --model motionlcm-control --text "a person walks" \\
        --trajectory circle [--size 1.5] [--refine] --out circle.gif

``--text`` may be repeated (one motion per text; ``--out`` then gets ``_<k>`` suffixes). The
output format follows the extension: ``.gif``/``.mp4`` animation, ``.png`` frame strip, ``.npy``
global joints (T, J, 3) in metres. Models are read from ``paths.artifacts`` (``dvc repro`` first).

``--trajectory`` (controlled models only): a pelvis path, ``circle``/``line``/``zigzag``
(:mod:`data.trajectories`, ``--size`` metres) or a ``.npy`` of (length, 3) pelvis positions in
metres, every frame controlled, at the dataset's mean pelvis height for the shapes. The animation
draws the path on the floor, and the pelvis' mean distance to it is printed.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from data.control import CONTROL_JOINTS
from data.render import render_animation, render_strip
from data.skeleton import get_skeleton
from data.trajectories import SHAPES, load_trajectory, make_trajectory
from models.generator import ControlledGenerator, Hint
from pipelines.cli import artifacts_dir, repo_path
from pipelines.config import load_params
from pipelines.feature_store import FeatureStore
from pipelines.registry import FAMILIES, EvalContext, GenerateOptions, family

MODELS = sorted(name for name, entry in FAMILIES.items() if entry.generator is not None)


def write_motion(joints: np.ndarray, path: Path, caption: str, skeleton_name: str,
                 target_path: np.ndarray | None = None) -> Path:
    """Save one motion's joints by the path's extension (``target_path``: drawn on the floor)."""
    skeleton = get_skeleton(skeleton_name)
    if path.suffix == ".npy":
        np.save(path, joints.astype(np.float32))
        return path
    if path.suffix == ".png":
        return render_strip(joints, path, caption, skeleton, target_path=target_path)
    if path.suffix in (".gif", ".mp4"):
        return render_animation(joints, path, caption, skeleton, target_path=target_path)
    raise ValueError(f"--out {path}: unknown extension (use .gif, .mp4, .png or .npy)")


def pelvis_path(trajectory: str, length: int, store: FeatureStore, size: float | None = None) -> np.ndarray:
    """``--trajectory``: a shape of :data:`data.trajectories.SHAPES` at the mean pelvis height, or a ``.npy`` file."""
    if trajectory in SHAPES:
        return make_trajectory(trajectory, length, size=size, height=float(store.mean[3]))
    if trajectory.endswith(".npy"):
        if size is not None:
            raise ValueError("--size applies to the shapes, not to a .npy trajectory")
        return load_trajectory(trajectory, length)
    raise ValueError(f"--trajectory {trajectory!r}: use one of {', '.join(SHAPES)} or a .npy file")


def pelvis_hint(path: np.ndarray, count: int, joints_num: int) -> Hint:
    """``count`` copies of a (T, 3) pelvis path as a hint controlling the pelvis on every frame."""
    joints = np.zeros((count, len(path), joints_num, 3), np.float32)
    mask = np.zeros((count, len(path), joints_num), bool)
    joints[:, :, CONTROL_JOINTS["pelvis"]], mask[:, :, CONTROL_JOINTS["pelvis"]] = path, True
    return Hint(joints, mask)


def generate(params: dict[str, Any], model: str, texts: Sequence[str], lengths: Sequence[int], out: Path,
             seed: int = 0, steps: int | None = None, guidance: float | None = None, trajectory: str | None = None,
             size: float | None = None, refine: bool = False) -> list[Path]:
    """Sample ``texts`` with the registry's ``model`` and write one file per text; returns the paths."""
    if steps is not None and steps < 1:
        raise ValueError(f"--steps {steps}: must be at least 1")
    ctx = EvalContext(params, artifacts_dir(params), repo_path(params, "features.out"))
    generator = family(model).build_generator(ctx, GenerateOptions(steps=steps, guidance=guidance, refine=refine))
    lengths = np.asarray(lengths)
    text = ctx.store.encode_prompts(texts)
    target = None
    if isinstance(generator, ControlledGenerator):
        if trajectory is None:
            raise ValueError(f"--model {model} follows a trajectory: pass --trajectory ({', '.join(SHAPES)} or a .npy)")
        target = pelvis_path(trajectory, int(lengths.max()), ctx.store, size)
        motions = generator.sample(text, lengths, seed, hint=pelvis_hint(target, len(texts), ctx.store.joints_num))
    elif trajectory is not None or refine:
        raise ValueError(f"--trajectory/--refine need a controlled model (motionlcm-control), not {model!r}")
    else:
        motions = generator.sample(text, lengths, seed)
    paths = [out] if len(texts) == 1 else [out.with_name(f"{out.stem}_{k}{out.suffix}") for k in range(len(texts))]
    written = []
    for joints, path, caption in zip(ctx.store.to_joints(motions, lengths), paths, texts, strict=True):
        if target is not None:
            error = np.linalg.norm(joints[:, CONTROL_JOINTS["pelvis"]] - target[: len(joints)], axis=-1).mean()
            print(f"{path.name}: pelvis {error:.3f} m from the trajectory on average")
        written.append(write_motion(joints, path, caption, params["data"]["skeleton"], target))
    return written


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Text to motion with a trained motionforge model.")
    parser.add_argument("--model", default="mld", choices=MODELS, help="model family (pipelines/registry.py)")
    parser.add_argument("--text", action="append", required=True, help="prompt (repeatable)")
    parser.add_argument("--length", type=int, default=120, help="frames at 20 fps (4..196)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=None, help="sampling steps (model default if omitted)")
    parser.add_argument("--guidance", type=float, default=None)
    parser.add_argument("--trajectory", default=None,
                        help=f"pelvis path for controlled models: {', '.join(SHAPES)} or a .npy of (length, 3) metres")
    parser.add_argument("--size", type=float, default=None, help="trajectory size in metres (circle: radius)")
    parser.add_argument("--refine", action="store_true", help="controlled models: test-time refinement")
    args, overrides = parser.parse_known_args(argv)
    if not 4 <= args.length <= 196:
        sys.exit(f"generate: --length {args.length} is outside 4..196 frames")
    try:
        paths = generate(load_params(overrides), args.model, args.text, [args.length] * len(args.text), args.out,
                         args.seed, args.steps, args.guidance, args.trajectory, args.size, args.refine)
    except (ValueError, FileNotFoundError) as err:
        sys.exit(f"generate: {err}")
    print("\n".join(str(p) for p in paths))


if __name__ == "__main__":
    main()
