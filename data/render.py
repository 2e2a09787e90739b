"""Stick-figure pictures of motions: GIF/MP4 animations, frame strips and contact sheets.

Every function takes global joint positions (T, J, 3) (y up, metres) of any skeleton in
:mod:`data.skeleton`; features can be turned into joints first with :func:`joints_of`, given a
recover function such as ``data.features.recover_from_ric``. Drawing uses matplotlib's Agg
canvas directly (no pyplot, no display); GIFs are written with Pillow, MP4 with ffmpeg through
matplotlib when ffmpeg is installed.

The camera is orthographic, looking down at ``elev`` degrees from ``azim`` degrees around the
vertical (0: from the front of a body facing +z; ``None``: 35 degrees off the motion's own
initial facing direction). Bones of the left side are blue, the right side
red, the spine black; the floor is a grey 0.5 m grid; the root's ground trajectory is a dashed
green line. ``render_animation`` and ``render_strip`` also draw an optional target path (T, 3)
(world positions, e.g. from :mod:`data.trajectories`) as a solid magenta line on the floor; the
camera then stays still, framing the whole target and the root's path.
"""

from __future__ import annotations

import shutil
import textwrap
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from matplotlib.animation import FFMpegWriter
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.text import Text
from PIL import Image

from data.atomic import replace_file
from data.skeleton import HUMANML3D, Skeleton

GRID_STEP = 0.5
MAX_FLOOR = 15.0  # floor grid half-size cap (m): a wild generated motion must not draw thousands of lines
#: bone colours by limb: legs red (right) and blue (left), arms orange (right) and cyan (left), the spine dark
_COLORS = {("leg", "right"): "#d62728", ("leg", "left"): "#1f77b4", ("arm", "right"): "#ff7f0e",
           ("arm", "left"): "#17becf", "spine": "#222222"}
_FLOOR_COLOR = "#bbbbbb"
_TRAJ_COLOR = "#2ca02c"
TARGET_COLOR = "#e600e6"  # magenta: no bone, floor or trajectory colour mixes into it


def joints_of(motion: np.ndarray, recover: Callable[[np.ndarray, int], np.ndarray] | None = None,
              skeleton: Skeleton = HUMANML3D) -> np.ndarray:
    """(T, J, 3) joints from joints (returned as is) or from (T, D) features via ``recover``."""
    motion = np.asarray(motion, dtype=np.float64)
    if motion.ndim == 3:
        return motion * skeleton.unit
    if recover is None:
        raise ValueError(f"motion of shape {motion.shape} looks like features: pass a recover function")
    return np.asarray(recover(motion, skeleton.joints_num), dtype=np.float64) * skeleton.unit


class Camera:
    """Orthographic projection of world points onto a screen plane (x right, y up).

    The camera sits in direction ``toward`` from the scene (azimuth about y from +z, elevation above
    the floor) and looks back at it; (right, up, toward) is a right-handed basis, so the picture is
    what a viewer there sees, not its mirror image: from the front of a HumanML3D body (azimuth 0,
    the body facing +z) its left side (+x) is on the screen's right.
    """

    def __init__(self, azim: float = 35.0, elev: float = 15.0) -> None:
        a, e = np.radians(azim), np.radians(elev)
        toward = np.array([np.sin(a) * np.cos(e), np.sin(e), np.cos(a) * np.cos(e)])  # to the camera
        self.right = np.array([np.cos(a), 0.0, -np.sin(a)])
        self.up = np.cross(toward, self.right)

    def project(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) -> (..., 2) screen coordinates."""
        return np.stack([points @ self.right, points @ self.up], axis=-1)


def _as_joints(joints: np.ndarray) -> np.ndarray:
    """float64 copy with non-finite values zeroed (a diverged generated motion still renders)."""
    return np.nan_to_num(np.asarray(joints, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)


def _floor_lines(center: np.ndarray, radius: float) -> list[np.ndarray]:
    """Grid lines (2, 3) on y = 0 covering a square of ``radius`` (capped) around ``center`` (x, z)."""
    radius = min(radius, MAX_FLOOR)
    lo = np.floor((center - radius) / GRID_STEP) * GRID_STEP
    hi = np.ceil((center + radius) / GRID_STEP) * GRID_STEP
    lines = []
    for x in np.arange(lo[0], hi[0] + 1e-9, GRID_STEP):
        lines.append(np.array([[x, 0.0, lo[1]], [x, 0.0, hi[1]]]))
    for z in np.arange(lo[1], hi[1] + 1e-9, GRID_STEP):
        lines.append(np.array([[lo[0], 0.0, z], [hi[0], 0.0, z]]))
    return lines


def _draw_floor(ax: Axes, camera: Camera, center: np.ndarray, radius: float) -> None:
    for line in _floor_lines(center, radius):
        xy = camera.project(line)
        ax.plot(xy[:, 0], xy[:, 1], color=_FLOOR_COLOR, lw=0.5, zorder=0)


def _draw_trajectory(ax: Axes, camera: Camera, joints: np.ndarray) -> None:
    ground = joints[:, 0].copy()
    ground[:, 1] = 0.0
    xy = camera.project(ground)
    ax.plot(xy[:, 0], xy[:, 1], color=_TRAJ_COLOR, lw=1.0, ls="--", zorder=1)


def _as_target(target_path: np.ndarray | None) -> np.ndarray | None:
    """float64 (T, 3) copy of a target path, or None; raises ValueError on another shape or NaN/inf."""
    if target_path is None:
        return None
    target = np.asarray(target_path, dtype=np.float64)
    if target.ndim != 2 or target.shape[1] != 3 or len(target) < 2:
        raise ValueError(f"target_path must be (T, 3) world positions with T >= 2, got shape {target.shape}")
    if not np.isfinite(target).all():
        raise ValueError("target_path has NaN or inf values")
    return target


def _draw_target(ax: Axes, camera: Camera, target: np.ndarray) -> None:
    """The target path's projection on the floor y = 0, under the root trajectory and the pose."""
    ground = target.copy()
    ground[:, 1] = 0.0
    xy = camera.project(ground)
    ax.plot(xy[:, 0], xy[:, 1], color=TARGET_COLOR, lw=2.0, zorder=1)


def chain_colors(skeleton: Skeleton) -> list[str]:
    """One colour per kinematic chain, by the limb the rest pose makes it (not by its names or its place in the
    list): a chain from the root ending off the midline is a leg, one from higher up an arm, and its side is
    the side of the body (+x, left, in the rest pose) its end lies on; a chain ending on the midline is the spine."""
    rest = skeleton.rest_directions()
    colors = []
    for chain in skeleton.kinematic_chain:
        x = rest[chain[-1], 0] - rest[chain[0], 0]
        if abs(x) < 1e-9:
            colors.append(_COLORS["spine"])
        else:
            colors.append(_COLORS[("leg" if chain[0] == 0 else "arm", "left" if x > 0 else "right")])
    return colors


def _draw_pose(ax: Axes, camera: Camera, pose: np.ndarray, skeleton: Skeleton, alpha: float = 1.0,
               lw: float = 2.0) -> list:
    """Draw one pose (J, 3); returns the line artists (one per kinematic chain, coloured by :func:`chain_colors`)."""
    artists = []
    for chain, color in zip(skeleton.kinematic_chain, chain_colors(skeleton), strict=True):
        xy = camera.project(pose[list(chain)])
        (line,) = ax.plot(xy[:, 0], xy[:, 1], color=color, lw=lw, alpha=alpha,
                          solid_capstyle="round", zorder=2)
        artists.append(line)
    return artists


def _limits(camera: Camera, center: np.ndarray, radius: float, height: float) -> tuple[float, float, float, float]:
    """Screen box (x0, x1, y0, y1) of a world box around ``center`` (x, z) of ``radius`` and ``height``."""
    box = np.array([[center[0] + dx, y, center[1] + dz] for dx in (-radius, radius) for dz in (-radius, radius)
                    for y in (0.0, height)])
    xy = camera.project(box)
    return float(xy[:, 0].min()), float(xy[:, 0].max()), float(xy[:, 1].min()), float(xy[:, 1].max())


def _setup_axes(ax: Axes, camera: Camera, center: np.ndarray, radius: float, height: float) -> None:
    """Fix the view on a box around ``center`` (x, z) of ``radius`` and ``height``."""
    x0, x1, y0, y1 = _limits(camera, center, radius, height)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.axis("off")
    ax.xaxis.set_visible(False)  # else every draw lays out the hidden ticks to place the title
    ax.yaxis.set_visible(False)


def _title(ax: Axes, caption: str | None, width: int, size: float) -> Text | None:
    if not caption:
        return None
    return ax.set_title("\n".join(textwrap.wrap(caption, width, max_lines=3, placeholder=" ...")), fontsize=size)


def facing_azimuth(joints: np.ndarray, skeleton: Skeleton = HUMANML3D, offset: float = 35.0) -> float:
    """Camera azimuth (degrees) ``offset`` degrees round from the front of the body at frame 0.

    The body's left is the face joints' named left times ``skeleton.front`` (KIT-ML's named sides are
    the other way round, and its motions face -z)."""
    r_hip, l_hip = skeleton.face_joints[:2]
    left = skeleton.front * (joints[0, l_hip] - joints[0, r_hip])
    return float(np.degrees(np.arctan2(-left[2], left[0]))) + offset


#: The animation's axes take the figure's lower part; the caption sits above them.
AXES_TOP = 0.88


def _frame_figure(size: float, dpi: int) -> tuple[Figure, Axes]:
    fig = Figure(figsize=(size, size), dpi=dpi)
    ax = fig.add_axes((0.0, 0.0, 1.0, AXES_TOP))
    return fig, ax


def _follow(joints: np.ndarray) -> np.ndarray:
    """(T, 2) camera centre following the root's ground position (smoothed)."""
    from scipy.ndimage import gaussian_filter1d

    return gaussian_filter1d(joints[:, 0, [0, 2]], sigma=5.0, axis=0, mode="nearest")


def _view(joints: np.ndarray, target: np.ndarray | None, radius: float) -> tuple[np.ndarray, float]:
    """(T, 2) camera centres (x, z) and the view radius.

    Without a target the camera follows the root at ``radius``. With one it stays on the middle of
    the bounding square of the root's path and the target, widening ``radius`` to cover it (plus 0.5 m).
    """
    if target is None:
        return _follow(joints), radius
    ground = np.concatenate([joints[:, 0, [0, 2]], target[:, [0, 2]]])
    lo, hi = ground.min(axis=0), ground.max(axis=0)
    centers = np.broadcast_to((lo + hi) / 2, (len(joints), 2))
    return centers, max(radius, float((hi - lo).max()) / 2 + 0.5)


def render_frames(joints: np.ndarray, caption: str | None = None, skeleton: Skeleton = HUMANML3D,
                  stride: int = 1, size: float = 3.2, dpi: int = 80, azim: float | None = None,
                  elev: float = 15.0, *, target_path: np.ndarray | None = None) -> list[Image.Image]:
    """One RGB image per ``stride``-th frame: the pose, the floor, the trajectory, the caption.

    The camera follows the root; given a ``target_path`` (T, 3), drawn on the floor, it stays
    still, framing the target and the root's path (see :func:`_view`). The floor grid and the
    paths are drawn once and the pose lines are updated in place, so a frame costs one canvas draw.
    The caption above the axes (where nothing else is drawn: the axes clip their artists, and the
    orthographic camera keeps their box fixed) is drawn in the first frame only and its pixels
    are copied into the others.
    """
    joints = _as_joints(joints)
    target = _as_target(target_path)
    camera = Camera(facing_azimuth(joints, skeleton) if azim is None else azim, elev)
    centers, radius = _view(joints, target, 1.5)
    height = max(float(joints[..., 1].max()) + 0.1, 2.0)
    fig, ax = _frame_figure(size, dpi)
    canvas = FigureCanvasAgg(fig)
    _setup_axes(ax, camera, centers[0], radius, height)
    middle = (centers.min(axis=0) + centers.max(axis=0)) / 2
    _draw_floor(ax, camera, middle, float(np.abs(centers - middle).max()) + radius + 0.5)
    if target is not None:
        _draw_target(ax, camera, target)
    _draw_trajectory(ax, camera, joints)
    lines = _draw_pose(ax, camera, joints[0], skeleton)
    title = _title(ax, caption, 40, 8)
    clock = ax.text(0.02, 0.02, "", transform=ax.transAxes, fontsize=7)
    images, header = [], None
    for t in range(0, len(joints), stride):
        for line, chain in zip(lines, skeleton.kinematic_chain, strict=True):
            xy = camera.project(joints[t, list(chain)])
            line.set_data(xy[:, 0], xy[:, 1])
        x0, x1, y0, y1 = _limits(camera, centers[t], radius, height)
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
        clock.set_text(f"{t / skeleton.fps:5.2f}s")  # also keeps Pillow from merging still frames
        canvas.draw()
        frame = np.asarray(canvas.buffer_rgba())[..., :3].copy()
        if header is None:  # the axes' drawn top: "equal" aspect shrinks them below AXES_TOP
            header = frame[: int(len(frame) * (1.0 - ax.get_position().y1))].copy()
            if title is not None:
                title.set_visible(False)
        else:
            frame[: len(header)] = header
        images.append(Image.fromarray(frame))
    return images


def _save_gif(images: Sequence[Image.Image], path: Path, duration_ms: int) -> None:
    """Animated GIF with one palette for all frames (fast, small, no flicker)."""
    samples = images[:: max(1, len(images) // 8)]
    width, height = samples[0].size
    montage = Image.new("RGB", (width * len(samples), height))
    for k, image in enumerate(samples):
        montage.paste(image, (k * width, 0))
    palette = montage.quantize(colors=64, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    frames = [image.quantize(palette=palette, dither=Image.Dither.NONE) for image in images]
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=duration_ms, loop=0)


def render_animation(joints: np.ndarray, path: Path | str, caption: str | None = None,
                     skeleton: Skeleton = HUMANML3D, stride: int = 2, *, target_path: np.ndarray | None = None,
                     **view: float) -> Path:
    """Write a GIF (or MP4, which needs ffmpeg) of a motion; returns the path.

    ``stride`` keeps every n-th frame (the playback speed stays real time). ``target_path`` (T, 3)
    is drawn on the floor as in :func:`render_frames`. ``view`` takes ``size``, ``dpi``, ``azim``
    and ``elev`` as in :func:`render_frames`.

    Raises:
        RuntimeError: an MP4 was asked for and ffmpeg is not installed.
        ValueError: an unknown file extension; a target path that is not (T, 3) finite positions.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".gif", ".mp4"):
        raise ValueError(f"{path}: expected a .gif or .mp4 file name")
    if suffix == ".mp4" and shutil.which("ffmpeg") is None:
        raise RuntimeError("writing MP4 needs ffmpeg on PATH; write a .gif instead")
    images = render_frames(joints, caption, skeleton, stride, target_path=target_path, **view)
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".gif":
        replace_file(path, lambda tmp: _save_gif(images, tmp, int(round(1000 * stride / skeleton.fps))))
    else:
        replace_file(path, lambda tmp: _write_mp4(images, tmp, skeleton.fps / stride))
    return path


def _write_mp4(images: Sequence[Image.Image], path: Path, fps: float) -> None:
    """Encode frames with ffmpeg through matplotlib's writer."""
    width, height = images[0].size
    fig = Figure(figsize=(width / 100, height / 100), dpi=100)
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.axis("off")
    shown = ax.imshow(images[0])
    FigureCanvasAgg(fig)
    writer = FFMpegWriter(fps=fps)
    with writer.saving(fig, str(path), dpi=100):
        for image in images:
            shown.set_data(image)
            writer.grab_frame()


def render_strip(joints: np.ndarray, path: Path | str, caption: str | None = None,
                 skeleton: Skeleton = HUMANML3D, count: int = 6, azim: float | None = None,
                 elev: float = 15.0, *, target_path: np.ndarray | None = None) -> Path:
    """PNG of ``count`` evenly spaced frames side by side (a quick look at a motion).

    Each panel follows the root; given a ``target_path`` (T, 3), drawn on the floor, every panel
    shows the same view framing the target and the root's path (see :func:`_view`).

    Raises:
        ValueError: a target path that is not (T, 3) finite positions.
    """
    joints = _as_joints(joints)
    target = _as_target(target_path)
    times = np.linspace(0, len(joints) - 1, count).round().astype(int)
    camera = Camera(facing_azimuth(joints, skeleton) if azim is None else azim, elev)
    centers, radius = _view(joints, target, 0.8)
    height = max(float(joints[..., 1].max()) + 0.1, 2.0)
    fig = Figure(figsize=(2.4 * count, 3.0), dpi=80)
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.0, top=0.86, wspace=0.0)
    for k, t in enumerate(times):
        ax = fig.add_subplot(1, count, k + 1)
        _setup_axes(ax, camera, centers[t], radius, height)
        _draw_floor(ax, camera, centers[t], radius + 0.2)
        if target is not None:
            _draw_target(ax, camera, target)
        _draw_trajectory(ax, camera, joints)
        _draw_pose(ax, camera, joints[t], skeleton)
        ax.set_title(f"{t / skeleton.fps:.1f}s", fontsize=8)
    if caption:
        fig.suptitle(textwrap.shorten(caption, 160), fontsize=9)
    return _save_png(fig, path)


def _draw_overview(ax: Axes, joints: np.ndarray, skeleton: Skeleton, caption: str | None, poses: int,
                   camera: Camera) -> None:
    """A whole motion in one panel: floor, trajectory and ``poses`` poses fading in over time."""

    ground = joints[:, 0, [0, 2]]
    center = (ground.min(axis=0) + ground.max(axis=0)) / 2
    radius = max(float(np.abs(ground - center).max()) + 0.6, 1.0)
    _setup_axes(ax, camera, center, radius, max(float(joints[..., 1].max()) + 0.1, 2.0))
    _draw_floor(ax, camera, center, radius)
    _draw_trajectory(ax, camera, joints)
    for k, t in enumerate(np.linspace(0, len(joints) - 1, poses).round().astype(int)):
        _draw_pose(ax, camera, joints[t], skeleton, alpha=0.25 + 0.75 * (k + 1) / poses, lw=1.2)
    _title(ax, caption, 34, 6.5)


def contact_sheet(motions: Sequence[np.ndarray], path: Path | str, captions: Sequence[str | None] | None = None,
                  skeleton: Skeleton = HUMANML3D, cols: int = 5, poses: int = 5, azim: float | None = None,
                  elev: float = 15.0) -> Path:
    """PNG grid with one panel per motion (see :func:`_draw_overview`), captions as titles.

    ``azim=None`` views each motion from 35 degrees off its initial facing direction.
    """
    if not motions:
        raise ValueError("contact_sheet needs at least one motion")
    captions = list(captions) if captions is not None else [None] * len(motions)
    rows = -(-len(motions) // cols)
    fig = Figure(figsize=(2.6 * cols, 2.9 * rows), dpi=80)
    for k, (motion, caption) in enumerate(zip(motions, captions, strict=True)):
        ax = fig.add_subplot(rows, cols, k + 1)
        joints = _as_joints(motion)
        camera = Camera(facing_azimuth(joints, skeleton) if azim is None else azim, elev)
        _draw_overview(ax, joints, skeleton, caption, poses, camera)
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.01, top=0.95, wspace=0.05, hspace=0.3)
    return _save_png(fig, path)


def _save_png(fig: Figure, path: Path | str) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    FigureCanvasAgg(fig)
    fig.savefig(path, format="png", metadata={"Software": None})
    return path
