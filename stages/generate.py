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
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from data.render import render_animation, render_strip
from data.skeleton import get_skeleton
from pipelines.cli import artifacts_dir, repo_path
from pipelines.config import load_params
from pipelines.registry import FAMILIES, EvalContext, GenerateOptions, family

MODELS = sorted(name for name, entry in FAMILIES.items() if entry.generator is not None)


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
    """Sample ``texts`` with the registry's ``model`` and write one file per text; returns the paths."""
    if steps is not None and steps < 1:
        raise ValueError(f"--steps {steps}: must be at least 1")
    ctx = EvalContext(params, artifacts_dir(params), repo_path(params, "features.out"))
    generator = family(model).build_generator(ctx, GenerateOptions(steps=steps, guidance=guidance))
    lengths = np.asarray(lengths)
    motions = generator.sample(ctx.store.encode_prompts(texts), lengths, seed)
    paths = [out] if len(texts) == 1 else [out.with_name(f"{out.stem}_{k}{out.suffix}") for k in range(len(texts))]
    return [write_motion(joints, path, text, params["data"]["skeleton"])
            for joints, path, text in zip(ctx.store.to_joints(motions, lengths), paths, texts, strict=True)]


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Text to motion with a trained motionforge model.")
    parser.add_argument("--model", default="mld", choices=MODELS, help="model family (pipelines/registry.py)")
    parser.add_argument("--text", action="append", required=True, help="prompt (repeatable)")
    parser.add_argument("--length", type=int, default=120, help="frames at 20 fps (4..196)")
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
