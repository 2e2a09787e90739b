"""User command: text to motion with a trained model.

    python -m stages.generate --model mld --text "a person walks forward then sits down" \\
        --length 120 --out walk.gif [--steps 50] [--guidance 7.5] [--seed 0] [key=value ...]
    python -m stages.generate --model mld --prompts prompts.txt --out out/ --format bvh

    python -m stages.generate --model motionlcm-control --text "a person walks" \\
        --trajectory circle [--size 1.5] [--refine] --out circle.gif
    python -m stages.generate --model emdm-action --text wave --text jump --out out/

Prompts. ``--text`` (repeatable) and ``--prompts FILE`` (one prompt per line, ``TEXT`` or
``TEXT | LENGTH``; blank lines and lines starting with ``#`` are skipped; a prompt without a
length gets ``--length``) are generated together: the models and the text encoder are loaded once,
and prompt ``k`` (its position, from 0) is sampled on its own with seed ``--seed + k``, so a motion
depends on its text, length and seed only, not on the other prompts of the run. For
``--model emdm-action`` each prompt is one of ``train_emdm_action``'s action labels (an unknown
label's error lists them).

Outputs. ``--out`` with a format's extension is one file (one prompt); otherwise it is a
directory that receives ``NN_<words>.<format>`` per prompt, ``NN`` its position from 00 (the
``--text`` prompts first, then the file's), ``<words>`` the start of its text, and the format
``--format`` (default gif). Formats: ``.gif``/``.mp4`` animation, ``.png`` frame strip, ``.npy``
global joints (T, J, 3) in metres (KIT-ML's millimetres converted), ``.bvh`` the skeleton's joint rotations
in its own units (:mod:`data.bvh`; KIT-ML: millimetres). Existing files are replaced. Every file is
written under a temporary name and renamed once all are written, so a failed run leaves none of
them; a motion that is not finite (NaN, e.g. from an extreme ``--guidance``) fails before any write.
Models are read from ``paths.artifacts`` (``dvc repro`` first).

Everything that can be checked without a model is checked before loading one (one line, exit
status 1): the model name, the prompts (none empty), ``--part``/``--segment``, ``--steps`` (at least
1 and what the family samples with; the trained step counts are read from params, and the family
checks the loaded model again), ``--guidance``, ``--seed``, ``--size``, ``--trajectory`` and ``--refine``
against the family (a trajectory for a controlled family only, and one for it), each length against the feature
store's training motions (its shortest to its longest), the shared params sections (``sample``
overrides), the output names and formats (MP4 needs ffmpeg on PATH) and that the outputs can be
written. An ``--out`` ending in ``/`` is a directory whatever its name.

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
import math
import os
import re
import shutil
import sys
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq

from data.bvh import write_bvh
from data.control import CONTROL_JOINTS
from data.physics import foot_skating_ratio
from data.render import joints_of, render_animation, render_strip
from data.skeleton import get_skeleton
from data.trajectories import SHAPES, load_trajectory, make_trajectory
from models.generator import Hint
from models.motiondiffuse import PART_UNIONS, REST
from models.motionlcm import TIMESTEPS as LCM_STEPS
from pipelines.cli import check_shared, repo_path
from pipelines.config import load_params
from pipelines.devices import deterministic_gpu
from pipelines.feature_store import FeatureStore
from pipelines.motiondiffuse_family import MotionDiffuseRow, sample_body_parts, sample_time_varied
from pipelines.registry import FAMILIES, EvalContext, GenerateOptions, family

MODELS = sorted(name for name, entry in FAMILIES.items() if entry.generator is not None)
#: The family whose generator takes ``--part`` / ``--segment``.
COMPOSABLE = "motiondiffuse"
#: The atomic body parts every named part is a union of.
PART_ATOMS = frozenset(atom for atoms in PART_UNIONS.values() for atom in atoms)
#: Output formats, by file extension (module docstring).
FORMATS = ("gif", "mp4", "png", "npy", "bvh")
DEFAULT_FORMAT = "gif"
#: Suffixes of the formats drawn with matplotlib (seconds per motion; written in parallel).
DRAWN = (".gif", ".mp4", ".png")
#: The largest seed torch's generators take (prompt k samples with ``--seed + k``); negative seeds, which
#: torch maps onto large ones, are refused.
MAX_SEED = 2**64 - 1
#: The longest file name most file systems take, in bytes.
NAME_MAX = 255
#: Network evaluations per motion from which the command says that sampling takes a while.
SLOW_NFE = 200


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


@dataclass(frozen=True)
class Prompt:
    """One motion to generate: its text, its length in frames and where it was given (for messages)."""

    text: str
    length: int
    source: str


def parse_prompt_file(path: Path, default_length: int) -> list[Prompt]:
    """``--prompts`` file: ``TEXT`` or ``TEXT | LENGTH`` per line; blank and ``#`` lines skipped.

    ValueError naming the file and line of a bad one (an empty text, a length that is not an integer).
    """
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()  # -sig: a byte-order mark is not text
    except FileNotFoundError:
        raise FileNotFoundError(f"--prompts {path}: no such file") from None
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(f"--prompts {path}: cannot read ({err})") from err
    prompts = []
    for number, line in enumerate(lines, 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{path}:{number}"
        text, bar, length = line.rpartition("|") if "|" in line else (line, "", "")
        text, length = text.strip(), length.strip()
        if not text:
            raise ValueError(f"{where}: no text before '|' (expected TEXT or TEXT | LENGTH)")
        if bar and not re.fullmatch(r"[0-9]+", length):
            raise ValueError(f"{where}: length {length!r} is not a whole number of frames (expected TEXT | LENGTH)")
        prompts.append(Prompt(text, int(length) if bar else default_length, where))
    if not prompts:
        raise ValueError(f"--prompts {path}: no prompts (every line is blank or a # comment)")
    return prompts


def length_range(store: FeatureStore) -> tuple[int, int]:
    """The shortest and longest motion of the store's training split, in frames (the lengths the models saw).

    Read from the Parquet column statistics (no motion is loaded), or the column when they are missing.
    """
    path = store.path / "train.parquet"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no training split in the feature store (run `dvc repro extract_features`)")
    meta = pq.read_metadata(path)
    column = meta.schema.names.index("length")
    stats = [meta.row_group(g).column(column).statistics for g in range(meta.num_row_groups)]
    if stats and all(s is not None and s.has_min_max for s in stats):
        return min(int(s.min) for s in stats), max(int(s.max) for s in stats)
    lengths = pq.read_table(path, columns=["length"]).column("length").to_numpy()
    if len(lengths) == 0:
        raise ValueError(f"{path}: the training split is empty")
    return int(lengths.min()), int(lengths.max())


def check_dataset_lengths(params: dict[str, Any], prompts: Sequence[Prompt]) -> None:
    """Every prompt's length within the feature store's training motions (:func:`length_range`); ValueError
    naming the first one outside."""
    store = FeatureStore(repo_path(params, "features.out"))
    low, high = length_range(store)
    for prompt in prompts:
        if not low <= prompt.length <= high:
            raise ValueError(f"{prompt.source}: length {prompt.length} is outside {low}..{high} frames, the lengths "
                             f"of the training motions ({store.path})")


def allowed_steps(model: str, params: dict[str, Any]) -> tuple[Callable[[int], bool], str]:
    """What ``--steps`` family ``model`` samples with: a test and its description (the trained step counts
    from params; the family checks the loaded model again)."""
    if model == "motionlcm":
        return (lambda n: n in LCM_STEPS), f"MotionLCM samples with {', '.join(map(str, sorted(LCM_STEPS)))} steps"
    if model == "motionlcm-control":
        return (lambda n: n == 1), "the ControlNet samples with one MotionLCM step"
    if model in ("emdm", "emdm-action"):
        stage, what = ("train_emdm", "EMDM") if model == "emdm" else ("train_emdm_action", "EMDM-action")
        trained = params[stage]["num_steps"]
        return (lambda n: n == trained), f"{what} samples with the {trained} steps it was trained with " \
                                         f"({stage}.num_steps)"
    stage = {"mld": "train_mld", "motiondiffuse": "train_motiondiffuse"}.get(model)
    if stage is None:  # a family added later checks its steps when its model is loaded
        return (lambda n: True), ""
    total = params[stage]["num_train_timesteps"]
    if model == "motiondiffuse":
        return (lambda n: 1 <= n <= total), (f"MotionDiffuse samples with DDIM over 1..{total - 1} steps or DDPM over "
                                             f"all {total} ({stage}.num_train_timesteps)")
    return (lambda n: 1 <= n <= total), f"MLD samples with DDIM over 1..{total} steps ({stage}.num_train_timesteps)"


def check_steps(model: str, steps: int | None, params: dict[str, Any]) -> None:
    if steps is None:
        return
    if steps < 1:
        raise ValueError(f"--steps {steps}: must be at least 1")
    allowed, description = allowed_steps(model, params)
    if not allowed(steps):
        raise ValueError(f"--steps {steps}: {description}")


def check_format(fmt: str, where: str) -> None:
    """ValueError when ``fmt`` is unknown or its encoder is missing (MP4 needs ffmpeg)."""
    if fmt not in FORMATS:
        raise ValueError(f"{where}: unknown format {fmt!r}; use {', '.join(FORMATS)}")
    if fmt == "mp4" and shutil.which("ffmpeg") is None:
        raise ValueError(f"{where}: writing MP4 needs ffmpeg on PATH, which is not installed; write a .gif instead")


def output_paths(out: Path, fmt: str | None, prompts: Sequence[Prompt], directory: bool = False) -> list[Path]:
    """One path per prompt: ``out`` itself when it names a file, else ``out/NN_<words>.<format>`` (module docstring).

    ``directory`` (``--out`` ends with a slash): ``out`` is a directory whatever its name. Checks the format
    (:func:`check_format`) and that every path can be written (:func:`check_writable`); creates nothing.
    """
    fmt = None if fmt is None else fmt.lower()
    suffix = out.suffix.lower().lstrip(".")
    bare = out.name.lower().lstrip(".")
    if not directory and not out.is_dir() and out.name.startswith(".") and bare in FORMATS:
        raise ValueError(f"--out {out}: a file name is missing before .{bare} (e.g. motion.{bare})")
    if suffix and not directory and not out.is_dir():
        check_format(suffix, f"--out {out}")
        if fmt is not None and fmt != suffix:
            raise ValueError(f"--out {out} and --format {fmt} disagree; give one of them")
        if len(prompts) > 1:
            raise ValueError(f"--out {out}: {len(prompts)} prompts are written into a directory; give a directory "
                             "(and --format)")
        paths = [out]
    else:
        fmt = fmt or DEFAULT_FORMAT
        check_format(fmt, f"--format {fmt}")
        if out.exists() and not out.is_dir():
            raise ValueError(f"--out {out}: exists and is not a directory")
        width = max(2, len(str(len(prompts) - 1)))
        paths = [out / f"{k:0{width}d}_{slug(p.text)}.{fmt}" for k, p in enumerate(prompts)]
    check_writable(out, paths)
    return paths


def check_writable(out: Path, paths: Sequence[Path]) -> None:
    """ValueError naming ``--out`` when a path is a directory or a read-only file, its name (or its temporary
    name, :func:`partial_path`) is too long, or its nearest existing ancestor is a file or not writable (so
    that nothing fails after sampling)."""
    for path in paths:
        if path.is_dir():
            raise ValueError(f"--out {out}: {path} is a directory")
        if path.exists() and not os.access(path, os.W_OK):
            raise ValueError(f"--out {out}: {path} exists and is read-only")
        if len(partial_path(path).name.encode()) > NAME_MAX:
            raise ValueError(f"--out {out}: the file name {path.name!r} is too long (at most "
                             f"{NAME_MAX - len(partial_path(path).name.encode()) + len(path.name.encode())} bytes)")
    folder = paths[0].parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise ValueError(f"--out {out}: {folder} is a file, not a directory")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ValueError(f"--out {out}: cannot write into {folder} (permission denied)")


def partial_path(path: Path) -> Path:
    """Where ``path`` is written before the rename that publishes every output together (:func:`write_all`)."""
    return path.with_name(f".{path.stem}.partial{path.suffix}")


def slug(text: str, limit: int = 40) -> str:
    """The start of a prompt as a file-name part: lower-case words joined by ``_``."""
    words = re.findall(r"[a-z0-9]+", text.lower())
    return "_".join(words)[:limit].rstrip("_") or "motion"


def write_motion(joints: np.ndarray, path: Path, caption: str, skeleton_name: str,
                 target_path: np.ndarray | None = None) -> Path:
    """Save one motion's joints (the dataset's units) in the format of the path's extension (``target_path``:
    drawn on the floor). ``.npy`` and the drawings are in metres, ``.bvh`` in the skeleton's own units (its
    offsets'): millimetres for KIT-ML."""
    skeleton = get_skeleton(skeleton_name)
    fmt = path.suffix.lower().lstrip(".")
    if fmt == "bvh":
        return write_bvh(joints, skeleton, path, skeleton.fps)
    metres = joints_of(joints, skeleton=skeleton)
    target = None if target_path is None else target_path * skeleton.unit
    if fmt == "npy":
        with open(path, "wb") as file:  # np.save on a name would append .npy to "x.NPY"
            np.save(file, metres.astype(np.float32))
        return path
    if fmt == "png":
        return render_strip(metres, path, caption, skeleton, target_path=target)
    return render_animation(metres, path, caption, skeleton, target_path=target)


def pelvis_path(trajectory: str, length: int, store: FeatureStore, size: float | None = None) -> np.ndarray:
    """``--trajectory`` in the dataset's units (the hints the ControlNet was trained on), from metres.

    A shape of :data:`data.trajectories.SHAPES`, at the mean pelvis height, leads ahead of the body: it is
    turned half a turn about y where the dataset's motions face -z (``Skeleton.front``, KIT-ML). A ``.npy``
    file is taken on the axes of the motions ``generate`` writes, as they are.
    """
    skeleton = get_skeleton(store.meta["skeleton"])
    if trajectory in SHAPES:
        path = make_trajectory(trajectory, length, size=size, height=float(store.mean[3]) * skeleton.unit,
                               fps=skeleton.fps)
        return path * np.array([skeleton.front, 1.0, skeleton.front], dtype=path.dtype) / skeleton.unit
    if trajectory.lower().endswith(".npy"):
        if size is not None:
            raise ValueError("--size applies to the shapes, not to a .npy trajectory")
        return load_trajectory(trajectory, length, skeleton.fps) / skeleton.unit
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


@dataclass(frozen=True)
class Request:
    """A checked ``stages.generate`` call (:func:`plan`): what to sample and where each motion goes."""

    model: str
    prompts: list[Prompt]
    paths: list[Path]
    options: GenerateOptions
    seed: int = 0
    trajectory: str | None = None
    size: float | None = None
    parts: Sequence[tuple[str, str]] = ()
    segments: Sequence[tuple[int, int, str]] = ()


def plan(params: dict[str, Any], model: str, prompts: Sequence[Prompt], out: Path, fmt: str | None = None,
         seed: int = 0, steps: int | None = None, guidance: float | None = None, trajectory: str | None = None,
         size: float | None = None, refine: bool = False, parts: Sequence[tuple[str, str]] = (),
         segments: Sequence[tuple[int, int, str]] = (), directory: bool = False) -> Request:
    """Check the request's options without a model (module docstring); ValueError on the first problem.

    With ``parts`` or ``segments`` (``--model motiondiffuse``) ``prompts`` holds the one motion's length.
    The lengths are checked against the dataset by :func:`check_dataset_lengths` (the command does).
    ``directory``: ``out`` names a directory (:func:`output_paths`).
    """
    entry = FAMILIES.get(model)
    if entry is None or entry.generator is None:
        with_generator = ", ".join(sorted(name for name, e in FAMILIES.items() if e.generator is not None))
        what = f"model family {model!r} has no generator (it is evaluated only)" if entry else \
            f"unknown model family {model!r}"
        raise ValueError(f"--model: {what}; choose one of {with_generator}")
    if not prompts:
        raise ValueError("no prompt: give --text, --prompts or (motiondiffuse) --part / --segment")
    if (parts or segments) and (len(prompts) != 1 or trajectory is not None or refine):
        raise ValueError("--part/--segment make one motion: no --text, --prompts, --trajectory or --refine with them")
    for prompt in prompts:
        if not (parts or segments) and not prompt.text.strip():
            raise ValueError(f"{prompt.source}: empty prompt")
        if prompt.length < 1:
            raise ValueError(f"{prompt.source}: length {prompt.length} must be at least 1 frame")
    check_steps(model, steps, params)
    if not 0 <= seed <= MAX_SEED - (len(prompts) - 1):
        raise ValueError(f"--seed {seed}: must be a whole number from 0 to {MAX_SEED - (len(prompts) - 1)} (prompt k "
                         "samples with --seed + k)")
    if entry.controlled and trajectory is None:
        raise ValueError(f"--model {model} follows a trajectory: pass --trajectory ({', '.join(SHAPES)} or a .npy)")
    if not entry.controlled and (trajectory is not None or refine):
        controlled = ", ".join(sorted(name for name, e in FAMILIES.items() if e.controlled))
        raise ValueError(f"--trajectory/--refine need a controlled model ({controlled}), not {model!r}")
    if guidance is not None and not (math.isfinite(guidance) and guidance >= 0):
        raise ValueError(f"--guidance {guidance}: must be a finite number, at least 0")
    if size is not None:
        if trajectory is None:
            raise ValueError("--size: it sizes a --trajectory shape, and no --trajectory is given")
        if not (math.isfinite(size) and size > 0):
            raise ValueError(f"--size {size}: must be a positive number of metres")
    paths = output_paths(out, fmt, prompts, directory)
    return Request(model, list(prompts), paths, GenerateOptions(steps=steps, guidance=guidance, refine=refine), seed,
                   trajectory, size, parts, segments)


def prompt_path(trajectory: str, prompt: Prompt, store: FeatureStore, size: float | None) -> np.ndarray:
    """``--trajectory`` at one prompt's length (:func:`pelvis_path`); an error names the prompt."""
    try:
        return pelvis_path(trajectory, prompt.length, store, size)
    except ValueError as err:
        raise ValueError(f"{prompt.source}: {err}") from None


def check_finite(joints: np.ndarray, prompt: Prompt, request: Request) -> None:
    """ValueError naming the prompt when its motion holds NaN or infinity (nothing is written then)."""
    if not np.isfinite(joints).all():
        causes = [f"--guidance {request.options.guidance:g}"] if request.options.guidance is not None else []
        causes += [f"--trajectory {request.trajectory}"] if request.trajectory is not None else []
        why = f": check {' and '.join(causes)}" if causes else ""
        raise ValueError(f"{prompt.source}: the model's motion is not finite (NaN or infinity){why}; nothing written")


def sample_all(ctx: EvalContext, generator: Any, request: Request,
               targets: Sequence[np.ndarray | None]) -> list[np.ndarray]:
    """Every prompt's joints: prompt ``k`` sampled on its own with seed ``request.seed + k`` (and ``targets[k]``,
    its pelvis path, for a controlled model), so that its motion does not depend on the other prompts."""
    joints = []
    for k, (prompt, target) in enumerate(zip(request.prompts, targets, strict=True)):
        # encoded alone too: in a batch, padding to the longest prompt may move the embedding's last bits
        text, lengths, seed = ctx.store.encode_prompts([prompt.text]), np.array([prompt.length]), request.seed + k
        if target is None:
            motions = generator.sample(text, lengths, seed)
        else:
            motions = generator.sample(text, lengths, seed, hint=pelvis_hint(target, 1, ctx.store.joints_num))
        [motion] = ctx.store.to_joints(motions, lengths)
        check_finite(motion, prompt, request)
        joints.append(motion)
    return joints


def run_request(params: dict[str, Any], request: Request) -> list[Path]:
    """Load the model once, sample every prompt and write one file per prompt; returns the paths."""
    ctx = EvalContext.from_params(params)
    skeleton = params["data"]["skeleton"]
    targets = [None if request.trajectory is None else prompt_path(request.trajectory, prompt, ctx.store, request.size)
               for prompt in request.prompts]
    generator = family(request.model).build_generator(ctx, request.options)
    if getattr(generator, "nfe", 0) >= SLOW_NFE:
        print(f"{generator.name}: {generator.nfe} network evaluations per motion (and per --part or --segment); "
              "on a CPU this takes minutes", file=sys.stderr, flush=True)
    if request.parts or request.segments:
        [prompt] = request.prompts
        with deterministic_gpu(ctx.device):
            motion, caption = generate_composed(ctx, generator, request.parts, request.segments, prompt.length,
                                                request.seed)
        [joints] = ctx.store.to_joints(motion, [prompt.length])
        check_finite(joints, prompt, request)
        return write_all([(joints, request.paths[0], caption, skeleton, None)])
    with deterministic_gpu(ctx.device):
        all_joints = sample_all(ctx, generator, request, targets)
    bones = get_skeleton(skeleton)
    jobs = []
    for joints, path, prompt, target in zip(all_joints, request.paths, request.prompts, targets, strict=True):
        if target is not None:
            error = bones.unit * np.linalg.norm(joints[:, CONTROL_JOINTS["pelvis"]] - target, axis=-1).mean()
            skating = foot_skating_ratio(joints, bones)
            print(f"{path.name}: pelvis {error:.3f} m from the trajectory on average; feet skating in "
                  f"{skating:.0%} of frame pairs")
        jobs.append((joints, path, prompt.text, skeleton, target))
    return write_all(jobs)


def _write_job(job: tuple[np.ndarray, Path, str, str, np.ndarray | None]) -> Path:
    return write_motion(*job)


def write_all(jobs: Sequence[tuple[np.ndarray, Path, str, str, np.ndarray | None]]) -> list[Path]:
    """:func:`write_motion` for every job (drawn formats, seconds per motion, on one process per core), each to
    its :func:`partial_path`, then every file renamed to its path: a failure leaves no output, and an error
    names the file. Returns the paths in order."""
    paths = [job[1] for job in jobs]
    for folder in {path.parent for path in paths}:
        folder.mkdir(parents=True, exist_ok=True)
    partial = [(joints, partial_path(path), *rest) for joints, path, *rest in jobs]
    workers = min(len(jobs), len(os.sched_getaffinity(0)))
    published: list[Path] = []
    try:
        if workers < 2 or not any(path.suffix.lower() in DRAWN for path in paths):
            for job in partial:
                _write_job(job)
        else:
            with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("fork")) as pool:
                list(pool.map(_write_job, partial))
        for job, path in zip(partial, paths, strict=True):
            os.replace(job[1], path)
            published.append(path)
    except (OSError, ValueError) as err:
        for path in published:  # a rename that failed takes back the ones before it
            path.unlink(missing_ok=True)
        message = str(err)
        for job, path in zip(partial, paths, strict=True):  # name the file asked for, not its temporary name
            message = message.replace(str(job[1]), str(path))
        raise type(err)(f"cannot write: {message}") from err
    finally:
        for job in partial:
            job[1].unlink(missing_ok=True)
    return paths


def generate(params: dict[str, Any], model: str, texts: Sequence[str], lengths: Sequence[int], out: Path,
             seed: int = 0, steps: int | None = None, guidance: float | None = None, trajectory: str | None = None,
             size: float | None = None, refine: bool = False, parts: Sequence[tuple[str, str]] = (),
             segments: Sequence[tuple[int, int, str]] = (), fmt: str | None = None) -> list[Path]:
    """Sample ``texts`` (with ``lengths``) with the registry's ``model`` and write one file per text.

    With ``parts`` or ``segments`` (``--model motiondiffuse``; ``texts`` empty, one length) one composed motion.
    The lengths are not checked against the dataset (tiny test models sample any length); the command does.
    """
    prompts = [Prompt(text, int(n), f"--text {text!r}") for text, n in zip(texts, lengths, strict=True)] \
        if texts else [Prompt("", int(lengths[0]), "--length")]
    return run_request(params, plan(params, model, prompts, out, fmt, seed, steps, guidance, trajectory, size, refine,
                                    parts, segments))


def check_composition(args: argparse.Namespace) -> tuple[list[tuple[str, str]], list[tuple[int, int, str]]]:
    """``--text`` / ``--part`` / ``--segment`` checked together; ValueError on the first problem."""
    prompts = getattr(args, "prompts", None)  # absent from a Namespace built without --prompts
    if not (args.part or args.segment):
        if not args.text and prompts is None:
            raise ValueError("no prompt: give --text or --prompts (or, for motiondiffuse, --part / --segment)")
        return [], []
    if args.model != COMPOSABLE:
        raise ValueError(f"--part/--segment: only --model {COMPOSABLE} composes prompts, not {args.model!r}")
    if args.part and args.segment:
        raise ValueError("--part and --segment: use one kind of composition")
    if args.text or prompts is not None or args.trajectory is not None or args.refine:
        raise ValueError("--part/--segment make one motion from their own texts: no --text, --prompts, --trajectory "
                         "or --refine")
    return (parse_parts(args.part), []) if args.part else ([], parse_segments(args.segment, args.length))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m stages.generate", description="Text to motion with a trained motionforge model.",
        epilog="key=value arguments override params (e.g. paths.artifacts=/elsewhere/artifacts).")
    parser.add_argument("--model", default="mld", help=f"model family: {', '.join(MODELS)} (default mld)")
    parser.add_argument("--text", action="append", default=[],
                        help="a prompt (repeatable); for emdm-action an action label, e.g. walk")
    parser.add_argument("--prompts", type=Path, default=None, metavar="FILE",
                        help="a file of prompts, one per line: TEXT or TEXT | LENGTH; blank lines and # comments "
                        "are skipped")
    parser.add_argument("--length", type=int, default=120,
                        help="frames at the dataset's fps (HumanML3D: 20) for prompts without one (default 120); "
                        "every length must lie within the feature store's training motions (HumanML3D: 40..196), "
                        "the error says the range")
    parser.add_argument("--out", required=True,
                        help="a file whose extension is the format (.gif, .mp4, .png, .npy, .bvh; one prompt), or a "
                        "directory receiving NN_<words>.<format> per prompt (a trailing / makes it one)")
    parser.add_argument("--format", dest="fmt", default=None, metavar="FORMAT",
                        help=f"{', '.join(FORMATS)}: the format of the files written into a directory --out "
                        f"(default {DEFAULT_FORMAT})")
    parser.add_argument("--seed", type=int, default=0, help="sampling seed (default 0)")
    parser.add_argument("--steps", type=int, default=None,
                        help="sampling steps, at least 1 (default: the model's: MLD 50, MotionLCM 1, EMDM its trained "
                        "steps, MotionDiffuse DDPM over all its steps)")
    parser.add_argument("--guidance", type=float, default=None,
                        help="classifier-free guidance scale (default: the sample section of params)")
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
    return parser


def attach_dashed_values(argv: Sequence[str]) -> list[str]:
    """``--segment -5:60=TEXT`` as ``--segment=-5:60=TEXT``: argparse reads a value starting with ``-`` and
    not a plain number as an option, and would report "expected one argument" instead of the range error.
    Also for the option's unambiguous abbreviations (``--seg``), which argparse accepts."""
    out: list[str] = []
    for arg in argv:
        if out and out[-1].startswith("--seg") and "--segment".startswith(out[-1]) and re.match(r"-\d", arg):
            out[-1] = f"{out[-1]}={arg}"
        else:
            out.append(arg)
    return out


def main(argv: Sequence[str] | None = None) -> None:
    parser = build_parser()
    args, overrides = parser.parse_known_args(attach_dashed_values(sys.argv[1:] if argv is None else argv))
    unknown = [arg for arg in overrides if arg.startswith("-")]
    if unknown:
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    try:
        if not args.out.strip():  # Path("") is the working directory
            raise ValueError("--out is empty: give a file (walk.gif) or a directory (out/)")
        parts, segments = check_composition(args)
        params = load_params(overrides)
        problems = check_shared(params, ())
        if problems:
            raise ValueError("\n".join(problems))
        if parts or segments:
            prompts = [Prompt("", args.length, "--length")]
        else:
            prompts = [Prompt(text, args.length, f"--text {text!r}") for text in args.text]
            if args.prompts is not None:
                prompts += parse_prompt_file(args.prompts, args.length)
        request = plan(params, args.model, prompts, Path(args.out), args.fmt, args.seed, args.steps, args.guidance,
                       args.trajectory, args.size, args.refine, parts, segments,
                       directory=args.out.endswith(("/", os.sep)))
        check_dataset_lengths(params, prompts)
        paths = run_request(params, request)
    except (ValueError, OSError) as err:
        sys.exit(f"generate: {err}")
    print("\n".join(str(p) for p in paths))


if __name__ == "__main__":
    main()
