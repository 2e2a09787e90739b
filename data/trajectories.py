"""Target pelvis paths for trajectory-controlled generation (MotionLCM's motion ControlNet).

A path is a (frames, 3) float32 array of pelvis positions in metres, on the axes of a body that
starts at the origin facing +z: x to its left (+x) or its right (-x), y up, z forward. Every shape
starts at (0, height, 0), heads forward (+z) and keeps the pelvis at a constant ``height``. HumanML3D's
motions start so; KIT-ML's face -z (``data.skeleton.Skeleton.front``), and ``stages.generate`` turns
the shapes half a turn for them. Frame k lies at s = k / (frames - 1) of the way along
the path, and the shapes are parametrised by arc length, so consecutive frames are equally far
apart (constant speed) and the path takes the whole clip, (frames - 1) / fps seconds.

The shapes, with ``size`` in metres (defaults in :data:`DEFAULT_SIZE`), for s in [0, 1]:

- ``circle``: one full circle of radius r = size (default 1.0 m) turning left, with its centre at
  (x, z) = (r, 0)::

      x(s) = r (1 - cos 2πs),  z(s) = r sin 2πs

  It starts tangent to +z, is 2πr long and ends where it starts.
- ``line``: straight ahead over L = size (default 3.0 m)::

      x(s) = 0,  z(s) = L s

- ``zigzag``: one period of a triangle wave along +z, of forward length L = size (default 3.0 m)
  and lateral amplitude A = L / 6 (0.5 m): three straight segments, out to the left (x = A at
  z = L/4), back across to the right (x = -A at z = 3L/4) and out back to the centre line
  (x = 0 at z = L)::

      z(s) = L s,  x(s) = A tri(s),  tri piecewise linear through (0, 0), (1/4, 1), (3/4, -1), (1, 0)

  Every segment has the same slope |dx/dz| = 4A/L = 2/3 (34 degrees off +z), so equal steps in z
  are equal steps along the path; the path is L √13 / 3 ≈ 1.2 L long.

:func:`load_trajectory` reads a user's own path from a ``.npy`` file instead.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

SHAPES = ("circle", "line", "zigzag")
DEFAULT_SIZE = {"circle": 1.0, "line": 3.0, "zigzag": 3.0}  # metres: radius, length, forward length
MAX_SPEED = 10.0  # m/s, about a sprinter's top speed: a faster path is a mistake (too few frames)
NPY_MAGIC = b"\x93NUMPY"  # the first bytes of a .npy file
ZIP_MAGIC = b"PK\x03\x04"  # of an .npz archive (refused below, with its own message)


def _circle(s: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """(x, z) of a left-turning circle through the origin: x = r (1 - cos 2πs), z = r sin 2πs."""
    angle = 2.0 * np.pi * s
    return radius * (1.0 - np.cos(angle)), radius * np.sin(angle)


def _line(s: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
    """(x, z) of a straight line ahead: x = 0, z = L s."""
    return np.zeros_like(s), length * s


def _zigzag(s: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
    """(x, z) of one triangle-wave period: z = L s, x = (L / 6) tri(s)."""
    return (length / 6.0) * np.interp(s, [0.0, 0.25, 0.75, 1.0], [0.0, 1.0, -1.0, 0.0]), length * s


_GROUND: dict[str, Callable[[np.ndarray, float], tuple[np.ndarray, np.ndarray]]] = {
    "circle": _circle,
    "line": _line,
    "zigzag": _zigzag,
}


def _check_positive(name: str, value: float) -> None:
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive finite number, got {value}")


def make_trajectory(shape: str, frames: int, *, size: float | None = None, height: float = 0.93,
                    fps: float = 20.0) -> np.ndarray:
    """(frames, 3) float32 pelvis positions (metres) along ``shape``; see the module docstring.

    Args:
        shape: one of :data:`SHAPES`.
        frames: number of frames (at least 2); the path spans them all at constant speed.
        size: the shape's size in metres (circle: radius; line and zigzag: forward length);
            ``None`` takes :data:`DEFAULT_SIZE`.
        height: the pelvis height y of every point.
        fps: frame rate, to check the speed the path asks for.

    Raises:
        ValueError: an unknown shape; frames < 2; size or fps not positive and finite; a height
            that is not finite; a path faster than :data:`MAX_SPEED`.
    """
    if shape not in SHAPES:
        raise ValueError(f"unknown trajectory shape {shape!r}: expected one of {', '.join(SHAPES)}")
    if frames < 2:
        raise ValueError(f"frames must be at least 2, got {frames}")
    size = DEFAULT_SIZE[shape] if size is None else size
    _check_positive("size", size)
    _check_positive("fps", fps)
    if not np.isfinite(height):
        raise ValueError(f"height must be finite, got {height}")
    x, z = _GROUND[shape](np.linspace(0.0, 1.0, frames), size)
    path = np.stack([x, np.full_like(x, height), z], axis=1)
    speed = np.linalg.norm(np.diff(path, axis=0), axis=1).sum() * fps / (frames - 1)
    if speed > MAX_SPEED:
        raise ValueError(f"a {shape} of size {size} m over {frames} frames at {fps} fps moves at {speed:.1f} m/s, "
                         f"faster than {MAX_SPEED} m/s: use more frames or a smaller size")
    return path.astype(np.float32)


def load_trajectory(path: str | Path, frames: int, fps: float) -> np.ndarray:
    """(frames, 3) float32 pelvis positions (metres, y up) from a ``.npy`` file.

    The file holds one (T, 3) array of real numbers with T == ``frames``, on the axes of the motions
    ``stages.generate`` writes; it is used as is (a HumanML3D motion starts at the origin facing +z with
    x to its left, a KIT-ML one facing -z: ``data.skeleton.Skeleton.front``). At ``fps`` frames a second
    its mean speed must not pass :data:`MAX_SPEED`, as the shapes' (a path in millimetres or
    centimetres would otherwise be followed as metres).

    Raises:
        FileNotFoundError: there is no such file.
        ValueError: the file is not a loadable ``.npy`` array (e.g. pickled objects or an ``.npz``
            archive), the array is not (T, 3) real numbers, has NaN or inf values, T != frames, or the
            path is faster than :data:`MAX_SPEED`.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"trajectory file {path} not found")
    with path.open("rb") as file:
        magic = file.read(len(NPY_MAGIC))
    if not magic.startswith((NPY_MAGIC, ZIP_MAGIC)):  # else numpy reads it as a pickle and says so
        raise ValueError(f"trajectory file {path} is not a .npy file (no NumPy header): save one (T, 3) array with "
                         "np.save")
    try:
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as err:
        raise ValueError(f"trajectory file {path} is not a loadable .npy array: {err}") from err
    if not isinstance(array, np.ndarray):
        array.close()
        raise ValueError(f"trajectory file {path} is an .npz archive: save one (T, 3) array with np.save")
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"trajectory file {path}: expected (T, 3) pelvis positions, got shape {array.shape}")
    if array.dtype.kind not in "iuf":
        raise ValueError(f"trajectory file {path}: expected real numbers, got dtype {array.dtype}")
    positions = array.astype(np.float32)
    bad = np.flatnonzero(~np.isfinite(positions).all(axis=1))
    if bad.size:
        raise ValueError(f"trajectory file {path}: NaN or inf values in {bad.size} of {len(positions)} frames "
                         f"(first: frame {bad[0]})")
    if len(positions) != frames:
        raise ValueError(f"trajectory file {path}: length mismatch: the file has {len(positions)} frames, "
                         f"the motion {frames}")
    if frames > 1:
        speed = float(np.linalg.norm(np.diff(positions, axis=0), axis=1).sum()) * fps / (frames - 1)
        if speed > MAX_SPEED:
            raise ValueError(f"trajectory file {path}: the pelvis moves at {speed:.3g} m/s on average at {fps:g} fps, "
                             f"faster than {MAX_SPEED} m/s: the positions must be in metres")
    return positions
