"""Stick-figure rendering: GIFs, strips, contact sheets and the ``stages.render`` command."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from PIL import Image
from test_kinematics import walk_toward_the_toes

from data.features import features_from_joints, recover_from_ric
from data.render import (
    AXES_TOP,
    TARGET_COLOR,
    Camera,
    _limits,
    _view,
    chain_colors,
    contact_sheet,
    facing_azimuth,
    joints_of,
    render_animation,
    render_frames,
    render_strip,
)
from data.skeleton import HUMANML3D, KIT
from data.synthetic import SyntheticConfig, generate_motion
from data.trajectories import make_trajectory
from stages import render as render_stage


@pytest.fixture(scope="module")
def motion():
    return generate_motion(3, 1, SyntheticConfig(num_motions=2, workers=1))


def _is_drawn(image: Image.Image) -> bool:
    """Not blank: some dark (figure) pixels on a mostly white background."""
    pixels = np.asarray(image.convert("L"), dtype=np.float64)
    return (pixels < 128).mean() > 0.002 and (pixels > 240).mean() > 0.5


def test_gif_has_one_frame_per_stride_and_shows_the_figure(tmp_path, motion):
    path = render_animation(motion.joints, tmp_path / "m.gif", motion.captions[0].text, stride=3)
    with Image.open(path) as gif:
        assert gif.n_frames == len(range(0, len(motion.joints), 3))
        assert gif.info["duration"] == 150
        firsts = []
        for k in (0, gif.n_frames // 2, gif.n_frames - 1):
            gif.seek(k)
            frame = gif.convert("RGB")
            assert _is_drawn(frame)
            firsts.append(np.asarray(frame))
    assert not np.array_equal(firsts[0], firsts[1])  # it moves


def test_the_caption_is_drawn_once_and_the_same_in_every_frame(motion):
    """The caption's pixels (above the axes) are the first frame's in every frame; below it each frame
    is exactly the frame drawn without a caption."""
    captioned = [np.asarray(image) for image in render_frames(motion.joints, "a person walks forward", stride=20)]
    plain = [np.asarray(image) for image in render_frames(motion.joints, None, stride=20)]
    drawn = np.flatnonzero((np.stack(plain) < 250).any(axis=(0, 2, 3)))  # rows any frame draws on
    rows = drawn[0]  # the caption's band: above everything the frames draw
    assert rows >= captioned[0].shape[0] * (1.0 - AXES_TOP)
    header = captioned[0][:rows]
    assert (header < 128).any()  # the caption is there
    assert len(captioned) == len(plain) > 2
    for with_caption, without in zip(captioned, plain, strict=True):
        np.testing.assert_array_equal(with_caption[:rows], header)
        np.testing.assert_array_equal(with_caption[rows:], without[rows:])


def test_mp4_needs_ffmpeg(tmp_path, motion):
    if shutil.which("ffmpeg"):
        path = render_animation(motion.joints[:20], tmp_path / "m.mp4")
        assert path.stat().st_size > 1000
    else:
        with pytest.raises(RuntimeError, match="ffmpeg"):
            render_animation(motion.joints, tmp_path / "m.mp4")
    with pytest.raises(ValueError, match="gif"):
        render_animation(motion.joints, tmp_path / "m.avi")


def test_contact_sheet_has_a_panel_per_motion(tmp_path, motion):
    motions = [motion.joints, motion.joints[::-1], motion.joints[:50]]
    path = contact_sheet(motions, tmp_path / "sheet.png", ["a", "b", None], cols=2)
    with Image.open(path) as sheet:
        assert sheet.size == (2 * 2.6 * 80, 2 * 2.9 * 80)
        assert _is_drawn(sheet)
        left, right = np.asarray(sheet.convert("L"))[:, :208], np.asarray(sheet.convert("L"))[:, 208:]
        assert (left < 128).any() and (right < 128).any()
    with pytest.raises(ValueError, match="at least one"):
        contact_sheet([], tmp_path / "empty.png")


def test_strip_of_frames(tmp_path, motion):
    path = render_strip(motion.joints, tmp_path / "strip.png", "caption", count=4)
    with Image.open(path) as strip:
        assert strip.size[0] > 3 * strip.size[1] and _is_drawn(strip)


def test_joints_of_recovers_features_with_the_given_function(motion):
    def fake_recover(features, joints_num):
        return np.zeros((len(features), joints_num, 3))

    assert joints_of(motion.joints).shape == motion.joints.shape
    assert joints_of(np.zeros((7, 263)), fake_recover).shape == (7, 22, 3)
    with pytest.raises(ValueError, match="recover"):
        joints_of(np.zeros((7, 263)))


def test_render_command_takes_a_file_or_a_clip_id(tmp_path, motion):
    file = tmp_path / "motion.npy"
    np.save(file, motion.joints)
    out = render_stage.main([str(file), "--out", str(tmp_path / "from_file.gif"), "--stride", "4"])
    assert out.stat().st_size > 10_000
    root = tmp_path / "ds"
    (root / "new_joints").mkdir(parents=True)
    (root / "texts").mkdir()
    np.save(root / "new_joints" / "000007.npy", motion.joints)
    (root / "texts" / "000007.txt").write_text(motion.captions[0].to_line() + "\n")
    out = render_stage.main(["000007", "--root", str(root), "--out", str(tmp_path / "by_id.gif"), "--stride", "4"])
    with Image.open(out) as gif:
        assert gif.n_frames == len(range(0, len(motion.joints), 4))



def test_render_command_errors_are_one_line(tmp_path, motion):
    """A missing clip, a wrong shape or a wrong output name: ``render: <reason>``, exit status 1, nothing written."""
    flat = tmp_path / "flat.npy"
    np.save(flat, np.zeros((120, 3), np.float32))
    good = tmp_path / "good.npy"
    np.save(good, motion.joints)
    cases = [(["999999", "--root", str(tmp_path)], "is neither a .npy file nor a clip id"),
             ([str(flat), "--out", str(tmp_path / "flat.gif")], "wrong shape (120, 3), expected (T, 263)"),
             ([str(good), "--out", str(tmp_path / "good.txt")], "good.txt")]
    for argv, message in cases:
        with pytest.raises(SystemExit) as exit_info:
            render_stage.main(argv)
        code = exit_info.value.code
        assert isinstance(code, str) and code.startswith("render: ") and message in code, (argv, code)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["flat.npy", "good.npy"]


def test_render_command_recovers_features(tmp_path, motion):
    features = pytest.importorskip("data.features")
    feats = features.features_from_joints(motion.joints, HUMANML3D)
    file = tmp_path / "features.npy"
    np.save(file, feats)
    out = render_stage.main([str(file), "--out", str(tmp_path / "feats.gif"), "--stride", "8"])
    with Image.open(out) as gif:
        assert gif.n_frames == len(range(0, len(feats), 8))


def test_a_diverged_motion_still_renders(tmp_path):
    wild = np.random.default_rng(0).normal(0.0, 1.0, (12, 22, 3)) * 1000.0
    wild[3] = np.nan
    path = render_animation(wild, tmp_path / "wild.gif", "diverged", stride=1)
    with Image.open(path) as gif:
        assert gif.n_frames == 12
    render_strip(wild, tmp_path / "wild.png", count=3)
    contact_sheet([wild], tmp_path / "wild_sheet.png")


def _target_pixels(image: Image.Image) -> int:
    """How many pixels have the target path's colour."""
    rgb = np.asarray(image.convert("RGB"), dtype=np.int64)
    target = np.array([int(TARGET_COLOR[k:k + 2], 16) for k in (1, 3, 5)])
    return int((np.abs(rgb - target).max(axis=-1) < 40).sum())


def test_strip_draws_the_target_path_only_when_given(tmp_path, motion):
    circle = make_trajectory("circle", len(motion.joints))
    with Image.open(render_strip(motion.joints, tmp_path / "target.png", count=3, target_path=circle)) as strip:
        assert _is_drawn(strip) and _target_pixels(strip) > 300
    with Image.open(render_strip(motion.joints, tmp_path / "plain.png", count=3)) as strip:
        assert _is_drawn(strip) and _target_pixels(strip) == 0


def test_animation_draws_the_target_path_only_when_given(tmp_path, motion):
    joints = motion.joints[:40]
    line = make_trajectory("line", len(joints))
    for target, expect_drawn in ((line, True), (None, False)):
        path = render_animation(joints, tmp_path / "m.gif", stride=8, target_path=target)
        with Image.open(path) as gif:
            assert gif.n_frames == 5
            assert (_target_pixels(gif.convert("RGB")) > 50) == expect_drawn


def test_the_view_frames_the_whole_target_path(motion):
    """With a target the camera stays still on a box holding all of it; without, it follows the root."""
    joints = motion.joints.astype(np.float64)
    camera = Camera(20.0, 15.0)
    for shape in ("circle", "line", "zigzag"):
        target = make_trajectory(shape, len(joints), size=2.5).astype(np.float64)
        centers, radius = _view(joints, target, 1.5)
        assert np.ptp(centers, axis=0).max() == 0 and radius > 1.5
        x0, x1, y0, y1 = _limits(camera, centers[0], radius, 2.0)
        ground = target * [1.0, 0.0, 1.0]
        xy = camera.project(np.concatenate([ground, joints[:, 0] * [1.0, 0.0, 1.0]]))
        assert (xy[:, 0] > x0).all() and (xy[:, 0] < x1).all() and (xy[:, 1] > y0).all() and (xy[:, 1] < y1).all()
    centers, radius = _view(joints, None, 1.5)
    assert radius == 1.5 and np.ptp(centers, axis=0).max() > 0


@pytest.mark.parametrize(
    ("target", "match"),
    [(np.zeros((10, 2)), r"\(T, 3\).*\(10, 2\)"), (np.zeros(10), r"\(10,\)"), (np.zeros((1, 3)), "T >= 2"),
     (np.full((10, 3), np.nan), "NaN")],
)
def test_a_bad_target_path_is_refused(tmp_path, motion, target, match):
    with pytest.raises(ValueError, match=match):
        render_strip(motion.joints, tmp_path / "bad.png", target_path=target)
    with pytest.raises(ValueError, match=match):
        render_animation(motion.joints, tmp_path / "bad.gif", target_path=target)


@pytest.mark.parametrize(("azim", "elev"), [(0.0, 0.0), (35.0, 15.0), (-120.0, 40.0)])
def test_the_camera_shows_the_scene_not_its_mirror_image(azim, elev):
    """(right, up, toward-the-camera) is right-handed, and from the front of a body facing +z its left side
    (+x in HumanML3D) is on the screen's right, its head up: what a viewer standing there sees."""
    camera = Camera(azim, elev)
    a, e = np.radians(azim), np.radians(elev)
    toward = np.array([np.sin(a) * np.cos(e), np.sin(e), np.cos(a) * np.cos(e)])
    assert np.linalg.det(np.stack([camera.right, camera.up, toward])) == pytest.approx(1.0)
    assert camera.up[1] > 0
    front = Camera(0.0, 0.0)
    left_hand, right_hand, head = np.array([0.7, 1.4, 0.0]), np.array([-0.7, 1.4, 0.0]), np.array([0.0, 1.7, 0.0])
    (lx, ly), (rx, _), (_, hy) = front.project(np.stack([left_hand, right_hand, head]))
    assert lx == pytest.approx(0.7) and rx == pytest.approx(-0.7) and hy > ly


def test_the_camera_looks_at_the_front_of_every_skeletons_bodies():
    """facing_azimuth(offset=0) puts the camera straight ahead of the body at frame 0, for KIT-ML's bodies too
    (they face -z, and its face joints name the sides the other way round); the default offset turns it 35°."""
    for skeleton in (HUMANML3D, KIT):
        joints = recover_from_ric(features_from_joints(walk_toward_the_toes(skeleton), skeleton), skeleton.joints_num)
        ahead = [0.0, skeleton.front]
        for offset in (0.0, 35.0):
            a = np.radians(facing_azimuth(joints, skeleton, offset=offset))
            toward = [np.sin(a), np.cos(a)]  # the camera's horizontal direction from the body (Camera)
            assert np.dot(toward, ahead) == pytest.approx(np.cos(np.radians(offset)), abs=1e-6), skeleton.name


def test_limbs_are_coloured_by_the_side_the_rest_pose_puts_them_on():
    """Left leg blue, right leg red, left arm cyan, right arm orange, judged from the rest pose, for KIT-ML's
    MMM chain order (left leg first) as for HumanML3D's (right leg first)."""
    legs_and_arms = {"left leg": "#1f77b4", "right leg": "#d62728", "left arm": "#17becf", "right arm": "#ff7f0e"}
    by_joint = [(HUMANML3D, {"left_ankle": "left leg", "right_ankle": "right leg", "left_wrist": "left arm",
                             "right_wrist": "right arm", "head": "spine"}),
                (KIT, {"l_ankle": "left leg", "r_ankle": "right leg", "l_wrist": "left arm", "r_wrist": "right arm",
                       "bun": "spine"})]
    for skeleton, limbs in by_joint:
        colors = chain_colors(skeleton)
        for joint, limb in limbs.items():
            j = skeleton.joint_names.index(joint)
            [k] = [k for k, chain in enumerate(skeleton.kinematic_chain) if j in chain[1:]]
            assert colors[k] == legs_and_arms.get(limb, "#222222"), (skeleton.name, joint)


@pytest.mark.parametrize(("array", "message"), [
    (np.zeros((40, 5, 3)), "wrong shape (40, 5, 3), expected (T, 22, 3)"),
    (np.zeros((0, 22, 3)), "0 frame(s): too short"),
    (np.zeros((40, 100)), "wrong shape (40, 100), expected (T, 263)"),
    (np.full((40, 22, 3), np.nan), "2640 non-finite values (NaN/inf), first in frame 0"),
    (np.zeros((40, 22, 3), complex), "dtype complex128 is not a real number type"),
    (np.array([{"x": 1}], dtype=object), "not a readable .npy array (Object arrays cannot be loaded"),
])
def test_render_refuses_a_motion_it_cannot_draw_in_one_line(tmp_path, array, message):
    """A wrong shape gave an IndexError traceback or a meaningless GIF, NaN drew zeros; objects are never unpickled.
    The checks are the dataset reader's (data.humanml3d.array_problem)."""
    path = tmp_path / "m.npy"
    np.save(path, array, allow_pickle=True)
    with pytest.raises(SystemExit) as exc:
        render_stage.main([str(path), "--out", str(tmp_path / "m.gif"), "--skeleton", "humanml3d"])
    assert str(exc.value.code).startswith(f"render: {path}: ") and message in str(exc.value.code)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.npy"]
