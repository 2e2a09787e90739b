"""User command: text to motion with a trained model.

    python -m stages.generate --model mld --text "a person walks forward then sits down" \\
        --length 120 --out walk.gif [--steps 50] [--guidance 7.5] [--seed 0] [key=value ...]

``--text`` may be repeated (one motion per text; ``--out`` then gets ``_<k>`` suffixes). The
output format follows the extension: ``.gif``/``.mp4`` animation, ``.png`` frame strip, ``.npy``
global joints (T, J, 3) in metres. Models are read from ``paths.artifacts`` (``dvc repro`` first).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from data.render import render_animation, render_strip
from data.skeleton import get_skeleton
from models.generator import Generator
from pipelines.config import REPO_ROOT, load_params
from pipelines.generators import MLDGenerator, encode_prompts, motions_to_joints
from stages.train_mld import load_mld
from stages.train_vae import load_vae


def mld(params: dict[str, Any], steps: int | None, guidance: float | None) -> Generator:
    artifacts = REPO_ROOT / params["paths"]["artifacts"]
    denoiser, schedule, _ = load_mld(artifacts / "train_mld")
    guidance = params["train_mld"]["guidance"] if guidance is None else guidance
    steps = steps or 50
    return MLDGenerator(f"MLD-DDIM{steps}", denoiser, load_vae(artifacts / "train_vae"), schedule, steps, guidance)


MODELS: dict[str, Callable[[dict[str, Any], int | None, float | None], Generator]] = {"mld": mld}


def write_motion(joints: np.ndarray, path: Path, caption: str, skeleton_name: str) -> Path:
    """Save one motion's joints by the path's extension."""
    skeleton = get_skeleton(skeleton_name)
    if path.suffix == ".npy":
        np.save(path, joints.astype(np.float32))
        return path
    if path.suffix == ".png":
        return render_strip(joints, path, caption, skeleton)
    if path.suffix in (".gif", ".mp4"):
        return render_animation(joints, path, caption, skeleton)
    raise ValueError(f"--out {path}: unknown extension (use .gif, .mp4, .png or .npy)")


def generate(params: dict[str, Any], model: str, texts: Sequence[str], lengths: Sequence[int], out: Path,
             seed: int = 0, steps: int | None = None, guidance: float | None = None) -> list[Path]:
    """Sample ``texts`` with ``model`` and write one file per text; returns the paths."""
    if model not in MODELS:
        raise ValueError(f"unknown model {model!r}; available: {sorted(MODELS)}")
    features = REPO_ROOT / params["features"]["out"]
    mean, std = np.load(features / "mean.npy"), np.load(features / "std.npy")
    lengths = np.asarray(lengths)
    generator = MODELS[model](params, steps, guidance)
    motions = generator.sample(encode_prompts(texts, features), lengths, seed)
    paths = [out] if len(texts) == 1 else [out.with_name(f"{out.stem}_{k}{out.suffix}") for k in range(len(texts))]
    return [write_motion(joints, path, text, params["data"]["skeleton"])
            for joints, path, text in zip(motions_to_joints(motions, lengths, mean, std), paths, texts, strict=True)]


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Text to motion with a trained motionforge model.")
    parser.add_argument("--model", default="mld", help=f"one of {sorted(MODELS)}")
    parser.add_argument("--text", action="append", required=True, help="prompt (repeatable)")
    parser.add_argument("--length", type=int, default=120, help="frames at 20 fps (40..196)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=None, help="sampling steps (model default if omitted)")
    parser.add_argument("--guidance", type=float, default=None)
    args, overrides = parser.parse_known_args(argv)
    if not 4 <= args.length <= 196:
        sys.exit(f"generate: --length {args.length} is outside 4..196 frames")
    try:
        paths = generate(load_params(overrides), args.model, args.text, [args.length] * len(args.text), args.out,
                         args.seed, args.steps, args.guidance)
    except (ValueError, FileNotFoundError) as err:
        sys.exit(f"generate: {err}")
    print("\n".join(str(p) for p in paths))


if __name__ == "__main__":
    main()
