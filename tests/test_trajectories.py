"""Target pelvis paths for trajectory control: the shapes' geometry and loading a user's path."""

from __future__ import annotations

import numpy as np
import pytest

from data.trajectories import DEFAULT_SIZE, MAX_SPEED, SHAPES, load_trajectory, make_trajectory


def _steps(path: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.diff(path.astype(np.float64), axis=0), axis=1)


@pytest.mark.parametrize("shape", SHAPES)
def test_every_shape_starts_at_the_origin_heading_forward(shape):
    path = make_trajectory(shape, 121, height=0.9)
    assert path.shape == (121, 3) and path.dtype == np.float32
    np.testing.assert_allclose(path[0], [0.0, 0.9, 0.0], atol=1e-6)
    np.testing.assert_allclose(path[:, 1], 0.9, atol=1e-6)
    first = path[1] - path[0]
    assert first[2] > 0 and abs(first[0]) < first[2]  # within 45 degrees of +z


@pytest.mark.parametrize("shape", ["circle", "line"])
@pytest.mark.parametrize("frames", [2, 7, 120])
def test_smooth_shapes_move_at_constant_speed(shape, frames):
    steps = _steps(make_trajectory(shape, frames, fps=1.0))
    np.testing.assert_allclose(steps, steps.mean(), rtol=1e-5)


def test_zigzag_moves_at_constant_speed_between_corners():
    # 121 frames put the corners (s = 1/4, 3/4) on frames 30 and 90: every step is a straight one.
    steps = _steps(make_trajectory("zigzag", 121))
    np.testing.assert_allclose(steps, 3.0 * np.sqrt(13) / 3 / 120, rtol=1e-5)
    # Otherwise a step across a corner is a chord, at most ~17% shorter (the turn is 67 degrees).
    steps = _steps(make_trajectory("zigzag", 100))
    assert steps.max() <= steps.mean() * 1.01 and steps.min() >= 0.8 * steps.max()
    assert np.sum(steps < 0.999 * steps.max()) <= 2


def test_circle_is_one_full_loop_of_the_radius():
    radius = 1.5
    path = make_trajectory("circle", 80, size=radius, height=1.0)
    np.testing.assert_allclose(path[-1], path[0], atol=1e-5)
    np.testing.assert_allclose(np.hypot(path[:, 0] - radius, path[:, 2]), radius, rtol=1e-5)
    np.testing.assert_allclose(path[:, 0].max(), 2 * radius, rtol=1e-3)  # turns left, across to x = 2r
    np.testing.assert_allclose(_steps(path).sum(), 2 * np.pi * radius, rtol=1e-3)
    np.testing.assert_allclose(make_trajectory("circle", 80)[:, 0].max(), 2 * DEFAULT_SIZE["circle"], rtol=1e-3)


def test_line_goes_straight_ahead_over_its_length():
    path = make_trajectory("line", 50, size=4.0, height=0.8)
    np.testing.assert_allclose(path[-1], [0.0, 0.8, 4.0], atol=1e-6)
    np.testing.assert_allclose(path[:, 0], 0.0)
    np.testing.assert_allclose(make_trajectory("line", 50)[-1], [0.0, 0.93, DEFAULT_SIZE["line"]], atol=1e-6)


def test_zigzag_extent_and_amplitude():
    size = 6.0
    path = make_trajectory("zigzag", 121, size=size)
    x, z = path[:, 0], path[:, 2]
    assert np.all(np.diff(z) > 0)  # always forward
    np.testing.assert_allclose([z[-1], x[-1]], [size, 0.0], atol=1e-5)
    np.testing.assert_allclose([x.max(), x.min()], [size / 6, -size / 6], atol=1e-5)
    np.testing.assert_allclose([z[x.argmax()], z[x.argmin()]], [size / 4, 3 * size / 4], atol=1e-5)
    assert np.sum(np.diff(np.sign(np.diff(x))) != 0) == 2  # three straight segments


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"shape": "square", "frames": 60}, "circle, line, zigzag"),
        ({"shape": "line", "frames": 1}, "frames must be at least 2, got 1"),
        ({"shape": "line", "frames": 60, "size": 0.0}, "size must be .* got 0.0"),
        ({"shape": "circle", "frames": 60, "size": -1.0}, "size must be .* got -1.0"),
        ({"shape": "zigzag", "frames": 60, "size": float("nan")}, "size must be .* got nan"),
        ({"shape": "line", "frames": 60, "size": float("inf")}, "size must be .* got inf"),
        ({"shape": "line", "frames": 60, "fps": 0.0}, "fps must be .* got 0.0"),
        ({"shape": "line", "frames": 60, "height": float("nan")}, "height must be finite, got nan"),
        ({"shape": "circle", "frames": 10}, "m/s"),
    ],
)
def test_bad_arguments_are_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        make_trajectory(**kwargs)


def test_speed_limit():
    frames = 14  # a 2π m circle over 13 frames at 20 fps: 9.7 m/s
    assert _steps(make_trajectory("circle", frames)).sum() * 20.0 / (frames - 1) < MAX_SPEED
    with pytest.raises(ValueError, match="more frames"):
        make_trajectory("circle", frames, fps=30.0)


def test_load_trajectory_round_trip(tmp_path):
    path = make_trajectory("zigzag", 40).astype(np.float64)
    np.save(tmp_path / "zig.npy", path)
    loaded = load_trajectory(tmp_path / "zig.npy", 40, 20.0)
    assert loaded.dtype == np.float32 and loaded.shape == (40, 3)
    np.testing.assert_allclose(loaded, path, atol=1e-6)
    np.save(tmp_path / "ints.npy", np.zeros((5, 3), dtype=np.int64))
    assert load_trajectory(str(tmp_path / "ints.npy"), 5, 20.0).dtype == np.float32


@pytest.mark.parametrize(
    ("array", "match"),
    [
        (np.zeros((40, 2)), r"expected \(T, 3\) .* got shape \(40, 2\)"),
        (np.zeros((40, 3, 1)), r"got shape \(40, 3, 1\)"),
        (np.zeros(40), r"got shape \(40,\)"),
        (np.full((40, 3), "a"), "expected real numbers"),
        (np.zeros((40, 3), dtype=bool), "expected real numbers"),
        (np.where(np.arange(40)[:, None] == 7, np.nan, 0.0) * np.ones(3), r"in 1 of 40 frames \(first: frame 7"),
        (np.full((40, 3), np.inf), "NaN or inf"),
        (np.zeros((30, 3)), "length mismatch: the file has 30 frames, the motion 40"),
        # a 3 m line in millimetres: 3000 "m" over 39 frame steps at 20 fps
        (np.linspace([0, 900, 0], [0, 900, 3000], 40),
         r"moves at 1\.54e\+03 m/s on average at 20 fps, faster than 10\.0 m/s: the positions must be in metres"),
        (np.array([{"x": 1}, None], dtype=object), "not a loadable .npy array"),
    ],
)
def test_load_trajectory_errors_name_the_file(tmp_path, array, match):
    file = tmp_path / "bad.npy"
    np.save(file, array, allow_pickle=True)
    with pytest.raises(ValueError, match=match) as err:
        load_trajectory(file, 40, 20.0)
    assert str(file) in str(err.value)


def test_load_trajectory_other_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.npy"):
        load_trajectory(tmp_path / "missing.npy", 40, 20.0)
    (tmp_path / "text.npy").write_text("not an array")
    with pytest.raises(ValueError, match="text.npy is not a .npy file") as err:  # not numpy's pickle advice
        load_trajectory(tmp_path / "text.npy", 40, 20.0)
    assert "pickle" not in str(err.value)
    np.savez(tmp_path / "both.npz", a=np.zeros((40, 3)))
    with pytest.raises(ValueError, match="both.npz is an .npz archive"):
        load_trajectory(tmp_path / "both.npz", 40, 20.0)
