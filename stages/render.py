"""Render one motion to a GIF (or MP4 with ffmpeg): ``python -m stages.render <id or file.npy>``.

The argument is a clip id of the dataset in ``data.root`` (its ``new_joints``, else its
``new_joint_vecs``, and its first caption) or a ``.npy`` file holding joints (T, J, 3) or
HumanML3D features (T, 12J-1), which are recovered to joints first. Options: ``--out`` (default
``artifacts/renders/<name>.gif``), ``--caption``, ``--root`` (default ``data.root`` of
params.yaml), ``--skeleton`` (default ``data.skeleton``), ``--stride``.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from data.humanml3d import FEATURES_DIR, JOINTS_DIR, TEXTS_DIR, array_problem, load_npy, read_captions
from data.render import joints_of, render_animation
from data.skeleton import Skeleton, get_skeleton
from pipelines.config import REPO_ROOT, load_params


def _recover(features: np.ndarray, joints_num: int) -> np.ndarray:
    from data.features import recover_from_ric  # imports torch: only when features are given

    return recover_from_ric(features, joints_num)


def find_motion(target: str, root: Path) -> tuple[np.ndarray, str | None, str]:
    """(motion array, first caption or None, name) of a ``.npy`` path or a clip id under ``root``.

    Raises:
        FileNotFoundError: neither an existing file nor a clip of the dataset.
    """
    path = Path(target)
    if path.suffix.lower() == ".npy" and path.is_file():
        return load_motion(path), None, path.stem
    for sub in (JOINTS_DIR, FEATURES_DIR):
        candidate = root / sub / f"{target}.npy"
        if candidate.is_file():
            texts = root / TEXTS_DIR / f"{target}.txt"
            caption = read_captions(texts)[0].text if texts.is_file() else None
            return load_motion(candidate), caption, target
    raise FileNotFoundError(f"{target!r} is neither a .npy file nor a clip id in {root}")


def load_motion(path: Path) -> np.ndarray:
    """A ``.npy`` motion read without unpickling (:func:`data.humanml3d.load_npy`); ValueError naming the file."""
    try:
        return load_npy(path)
    except (OSError, ValueError) as err:
        raise ValueError(f"{path}: not a readable .npy array ({err})") from None


def check_motion(motion: np.ndarray, skeleton: Skeleton, where: str) -> None:
    """ValueError naming ``where`` unless ``motion`` is ``skeleton``'s joints (T, J, 3) or features (T, 12J - 1)
    of finite real numbers, as the dataset reader checks them (:func:`data.humanml3d.array_problem`): joints_of
    would index past a wrong shape or draw NaN."""
    reason = array_problem(motion, skeleton, "joints" if motion.ndim == 3 else "features")
    if reason is not None:
        raise ValueError(f"{where}: {reason}")


def main(argv: Sequence[str] | None = None) -> Path:
    """Parse the command line, render, print and return the output path."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("motion", help="clip id of the dataset, or a .npy file (joints or features)")
    parser.add_argument("--out", type=Path, help="output .gif or .mp4")
    parser.add_argument("--caption", help="caption shown above the figure")
    parser.add_argument("--root", type=Path, help="dataset folder (default: data.root)")
    parser.add_argument("--skeleton", help="humanml3d or kit (default: data.skeleton)")
    parser.add_argument("--stride", type=int, default=2, help="draw every n-th frame (default 2)")
    args = parser.parse_args(argv)
    if args.stride < 1:
        parser.error(f"--stride {args.stride}: draw every n-th frame, n at least 1")
    try:
        data_cfg = load_params([])["data"]
        root = args.root or (REPO_ROOT / data_cfg["root"])
        skeleton = get_skeleton(args.skeleton or data_cfg["skeleton"])
        motion, caption, name = find_motion(args.motion, root)
        check_motion(motion, skeleton, args.motion)
        out = args.out or REPO_ROOT / "artifacts" / "renders" / f"{name}.gif"
        render_animation(joints_of(motion, _recover, skeleton), out, args.caption or caption, skeleton, args.stride)
    except (ValueError, OSError, RuntimeError) as err:  # a user's file or option (MP4 without ffmpeg): one line
        sys.exit(f"render: {err}")
    print(out)
    return out


if __name__ == "__main__":
    main()
