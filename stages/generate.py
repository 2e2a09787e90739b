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

MotionDiffuse's fine-grained control (``--model motiondiffuse`` only, instead of ``--text``; one motion):

    python -m stages.generate --model motiondiffuse --part upper="a person waves" \
        --part lower="a person walks forward" --out wave_walk.gif
    python -m stages.generate --model motiondiffuse --length 120 --segment 0:70="a person walks forward" \
        --segment 50:120="a person jumps" --out walk_jump.gif

``--part NAME=TEXT`` (repeatable): body parts (``models/motiondiffuse.py`` PART_UNIONS: root, left_leg,
right_leg, torso, left_arm, right_arm, legs, arms, lower, upper, whole; at most one ``rest`` = the
dims the others leave) that must not overlap and together cover the body (Eq. 10). ``--segment
A:B=TEXT`` (repeatable): frames [A, B) follow TEXT; segments may overlap and must cover [0, --length)
(Eq. 11). Each TEXT is encoded with the store's text encoder, as ``--text`` is.
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
from models.motiondiffuse import PART_UNIONS, REST
from pipelines.cli import artifacts_dir, repo_path
from pipelines.config import load_params
from pipelines.feature_store import FeatureStore
from pipelines.motiondiffuse_family import MotionDiffuseRow, sample_body_parts, sample_time_varied
from pipelines.registry import FAMILIES, EvalContext, GenerateOptions, family

MODELS = sorted(name for name, entry in FAMILIES.items() if entry.generator is not None)
#: The family whose generator takes ``--part`` / ``--segment``.
COMPOSABLE = "motiondiffuse"
#: The atomic body parts every named part is a union of.
PART_ATOMS = frozenset(atom for atoms in PART_UNIONS.values() for atom in atoms)


def parse_parts(specs: Sequence[str]) -> list[tuple[str, str]]:
    """``--part NAME=TEXT`` specs -> [(name, text)], checked to partition the body (module docstring)."""
    parts = []
    for spec in specs:
        name, sep, text = spec.partition("=")
        name, text = name.strip(), text.strip()
        if not sep or not name or not text:
            raise ValueError(f"--part {spec!r}: expected NAME=TEXT, e.g. upper=\"a person waves\"")
        if name not in PART_UNIONS and name != REST:
            raise ValueError(f"--part {spec!r}: unknown body part {name!r}; known: {', '.join([*PART_UNIONS, REST])}")
        parts.append((name, text))
    names = [name for name, _ in parts]
    if names.count(REST) > 1:
        raise ValueError(f"--part: at most one part may be {REST!r}")
    named = [name for name in names if name != REST]
    for i, a in enumerate(named):
        for b in named[:i]:
            shared = sorted(set(PART_UNIONS[a]) & set(PART_UNIONS[b]))
            if shared:
                raise ValueError(f"--part: {b!r} and {a!r} overlap (both include {', '.join(shared)}); parts must "
                                 "be disjoint")
    covered = {atom for name in named for atom in PART_UNIONS[name]}
    if REST in names and covered == PART_ATOMS:
        raise ValueError(f"--part: {REST!r} is empty, the other parts already cover the whole body")
    if REST not in names and covered != PART_ATOMS:
        raise ValueError(f"--part: the parts leave {', '.join(sorted(PART_ATOMS - covered))} uncovered; add a part "
                         f"or {REST}=TEXT")
    return parts


def parse_segments(specs: Sequence[str], length: int) -> list[tuple[int, int, str]]:
    """``--segment A:B=TEXT`` specs -> [(A, B, text)], each 0 <= A < B <= ``length``, together covering [0, length)."""
    segments = []
    for spec in specs:
        span, sep, text = spec.partition("=")
        start, colon, end = span.partition(":")
        text = text.strip()
        try:
            a, b = int(start), int(end)
        except ValueError:
            a = b = None
        if not sep or not colon or not text or a is None or b is None:
            raise ValueError(f"--segment {spec!r}: expected A:B=TEXT with frames A < B, e.g. 0:60=\"a person walks\"")
        if not 0 <= a < b <= length:
            raise ValueError(f"--segment {spec!r}: frames [{a}, {b}) are outside 0 <= A < B <= --length {length}")
        segments.append((a, b, text))
    covered = sorted(frame for a, b, _ in segments for frame in range(a, b))
    gaps = sorted(set(range(length)) - set(covered))
    if gaps:
        raise ValueError(f"--segment: frames {gaps[0]}..{gaps[-1]} ({len(gaps)} in all) are not covered; the segments "
                         f"must cover [0, {length}) (MotionDiffuse has no unconditional model to fill gaps)")
    return segments


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


def generate_composed(ctx: EvalContext, generator: Any, parts: Sequence[tuple[str, str]],
                      segments: Sequence[tuple[int, int, str]], length: int, seed: int) -> tuple[np.ndarray, str]:
    """One motion (1, length, D) from ``--part`` or ``--segment`` prompts (encoded as ``--text`` is) and its caption."""
    if not isinstance(generator, MotionDiffuseRow):
        raise ValueError(f"--part/--segment need --model {COMPOSABLE}")
    if parts and segments:
        raise ValueError("use --part or --segment, not both")
    if parts:
        text = ctx.store.encode_prompts([t for _, t in parts])
        motion = sample_body_parts(generator, [(name, text.select([k])) for k, (name, _) in enumerate(parts)],
                                   length, seed)
        return motion, " | ".join(f"{name}: {t}" for name, t in parts)
    text = ctx.store.encode_prompts([t for _, _, t in segments])
    motion = sample_time_varied(generator, [(a, b, text.select([k])) for k, (a, b, _) in enumerate(segments)],
                                length, seed)
    return motion, " | ".join(f"{a}-{b}: {t}" for a, b, t in segments)


def generate(params: dict[str, Any], model: str, texts: Sequence[str], lengths: Sequence[int], out: Path,
             seed: int = 0, steps: int | None = None, guidance: float | None = None, trajectory: str | None = None,
             size: float | None = None, refine: bool = False, parts: Sequence[tuple[str, str]] = (),
             segments: Sequence[tuple[int, int, str]] = ()) -> list[Path]:
    """Sample ``texts`` with the registry's ``model`` and write one file per text; returns the paths.

    With ``parts`` or ``segments`` (``--model motiondiffuse``; ``texts`` empty, one length) one composed motion.
    """
    if steps is not None and steps < 1:
        raise ValueError(f"--steps {steps}: must be at least 1")
    if (parts or segments) and (texts or len(lengths) != 1 or trajectory is not None or refine):
        raise ValueError("--part/--segment make one motion: no --text, --trajectory or --refine with them")
    ctx = EvalContext(params, artifacts_dir(params), repo_path(params, "features.out"))
    generator = family(model).build_generator(ctx, GenerateOptions(steps=steps, guidance=guidance, refine=refine))
    if parts or segments:
        motion, caption = generate_composed(ctx, generator, parts, segments, int(lengths[0]), seed)
        [joints] = ctx.store.to_joints(motion, lengths)
        return [write_motion(joints, out, caption, params["data"]["skeleton"])]
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


def check_composition(parser: argparse.ArgumentParser,
                      args: argparse.Namespace) -> tuple[list[tuple[str, str]], list[tuple[int, int, str]]]:
    """``--text`` / ``--part`` / ``--segment`` checked together (``parser.error``: one line, exit status 2)."""
    if not (args.part or args.segment):
        if not args.text:
            parser.error("the following arguments are required: --text (or --part / --segment)")
        return [], []
    if args.model != COMPOSABLE:
        parser.error(f"--part/--segment: only --model {COMPOSABLE} composes prompts, not {args.model!r}")
    if args.part and args.segment:
        parser.error("--part and --segment: use one kind of composition")
    if args.text or args.trajectory is not None or args.refine:
        parser.error("--part/--segment make one motion from their own texts: no --text, --trajectory or --refine")
    try:
        return (parse_parts(args.part), []) if args.part else ([], parse_segments(args.segment, args.length))
    except ValueError as err:
        parser.error(str(err))


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Text to motion with a trained motionforge model.")
    parser.add_argument("--model", default="mld", choices=MODELS, help="model family (pipelines/registry.py)")
    parser.add_argument("--text", action="append", default=[], help="prompt (repeatable; required unless --part or "
                        "--segment)")
    parser.add_argument("--length", type=int, default=120, help="frames at 20 fps (4..196)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=None, help="sampling steps (model default if omitted)")
    parser.add_argument("--guidance", type=float, default=None)
    parser.add_argument("--trajectory", default=None,
                        help=f"pelvis path for controlled models: {', '.join(SHAPES)} or a .npy of (length, 3) metres")
    parser.add_argument("--size", type=float, default=None, help="trajectory size in metres (circle: radius)")
    parser.add_argument("--refine", action="store_true", help="controlled models: test-time refinement")
    parser.add_argument("--part", action="append", default=[], metavar="NAME=TEXT",
                        help=f"{COMPOSABLE} only: TEXT for one body part ({', '.join([*PART_UNIONS, REST])}); "
                        "repeatable, the parts must partition the body")
    parser.add_argument("--segment", action="append", default=[], metavar="A:B=TEXT",
                        help=f"{COMPOSABLE} only: TEXT for frames [A, B); repeatable, the segments must cover "
                        "[0, --length)")
    args, overrides = parser.parse_known_args(argv)
    if not 4 <= args.length <= 196:
        sys.exit(f"generate: --length {args.length} is outside 4..196 frames")
    parts, segments = check_composition(parser, args)
    lengths = [args.length] * (len(args.text) if args.text else 1)
    try:
        paths = generate(load_params(overrides), args.model, args.text, lengths, args.out, args.seed, args.steps,
                         args.guidance, args.trajectory, args.size, args.refine, parts, segments)
    except (ValueError, FileNotFoundError) as err:
        sys.exit(f"generate: {err}")
    print("\n".join(str(p) for p in paths))


if __name__ == "__main__":
    main()
