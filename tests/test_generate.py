"""``python -m stages.generate``: prompt files, output names, options checked before any model is loaded.

The option checks run against the small feature store and an artefacts folder without models: each
bad option must end the command with status 1 and exactly one line naming the option (or the file
and line) before it would have looked for a model (whose absence would be another message), and
write nothing; every case in process, four of them as a subprocess. The end-to-end test samples a
prompt file and ``--text`` with a tiny untrained MLD into BVH files named by position and words.
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import torch

from data.bvh import read_bvh
from data.skeleton import HUMANML3D, KIT
from models.mld import MLDConfig, MLDDenoiser
from models.vae import MotionVAE, MotionVAEConfig
from pipelines.checkpoint import final_model_payload, save_final_model
from pipelines.config import load_params
from pipelines.feature_store import FeatureStore
from stages import generate
from stages.generate import Prompt

REPO = Path(__file__).resolve().parent.parent


# --------------------------------------------------------------------------------------------------
# Prompt files and output names (in process)
# --------------------------------------------------------------------------------------------------


def test_prompt_file_lines_lengths_comments(tmp_path: Path) -> None:
    path = tmp_path / "prompts.txt"
    path.write_text("# a comment\na person walks forward\n\n  a person jumps | 80  \na | b | 60\n")
    assert generate.parse_prompt_file(path, 120) == [
        Prompt("a person walks forward", 120, f"{path}:2"), Prompt("a person jumps", 80, f"{path}:4"),
        Prompt("a | b", 60, f"{path}:5")]


@pytest.mark.parametrize(("text", "message"), [
    ("a person walks\na person jumps | fast\n",
     "{path}:2: length 'fast' is not a whole number of frames (expected TEXT | LENGTH)"),
    ("a person walks\n | 60\n", "{path}:2: no text before '|' (expected TEXT or TEXT | LENGTH)"),
    ("a person walks | -5\n", "{path}:1: length '-5' is not a whole number of frames (expected TEXT | LENGTH)"),
    ("# only a comment\n\n", "--prompts {path}: no prompts (every line is blank or a # comment)"),
])
def test_bad_prompt_lines_name_file_and_line(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "prompts.txt"
    path.write_text(text)
    with pytest.raises(ValueError) as err:
        generate.parse_prompt_file(path, 120)
    assert str(err.value) == message.format(path=path)


def test_output_names(tmp_path: Path) -> None:
    prompts = [Prompt("A person walks, then sits down!", 60, "x"), Prompt("???", 60, "y")]
    assert generate.output_paths(tmp_path / "out", "bvh", prompts) == [
        tmp_path / "out" / "00_a_person_walks_then_sits_down.bvh", tmp_path / "out" / "01_motion.bvh"]
    assert generate.output_paths(tmp_path / "out", None, prompts[:1]) == [tmp_path / "out" / "00_a_person_walks_then_"
                                                                                            "sits_down.gif"]
    assert generate.output_paths(tmp_path / "walk.BVH", None, prompts[:1]) == [tmp_path / "walk.BVH"]
    eleven = generate.output_paths(tmp_path / "out", "npy", prompts[:1] * 101)
    assert eleven[0].name == "000_a_person_walks_then_sits_down.npy" and eleven[-1].name.startswith("100_")
    assert not (tmp_path / "out").exists()
    # a trailing slash (directory=True) makes a dotted name a directory; --format is case-blind
    assert generate.output_paths(tmp_path / "runs.v2", "GIF", prompts[:1], directory=True) == [
        tmp_path / "runs.v2" / "00_a_person_walks_then_sits_down.gif"]
    assert not (tmp_path / "runs.v2").exists()


def test_a_prompt_file_with_a_byte_order_mark_and_a_length_in_other_digits(tmp_path: Path) -> None:
    """Windows editors start UTF-8 files with a BOM: the first line stays a comment. A length is ASCII digits
    (``str.isdigit`` takes "²", which ``int`` refuses without naming the line)."""
    path = tmp_path / "prompts.txt"
    path.write_bytes("\ufeff# my prompts\r\na person walks | 60\r\n".encode())
    assert generate.parse_prompt_file(path, 120) == [Prompt("a person walks", 60, f"{path}:2")]
    path.write_text("a person walks | \u00b2\n")
    with pytest.raises(ValueError, match=rf"^{path}:1: length '\u00b2' is not a whole number of frames"):
        generate.parse_prompt_file(path, 120)


def test_output_paths_that_cannot_be_written_fail_before_sampling(tmp_path: Path) -> None:
    """A path that is a directory, or under a file, is refused while nothing has been sampled."""
    prompts = [Prompt("a person walks", 60, "x"), Prompt("a person jumps", 60, "y")]
    (tmp_path / "out" / "01_a_person_jumps.npy").mkdir(parents=True)
    with pytest.raises(ValueError, match=r"01_a_person_jumps.npy is a directory"):
        generate.output_paths(tmp_path / "out", "npy", prompts)
    (tmp_path / "file.npy").write_bytes(b"")
    with pytest.raises(ValueError, match=r"file.npy is a file, not a directory"):
        generate.output_paths(tmp_path / "file.npy" / "deeper" / "x.npy", None, prompts[:1])
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["01_a_person_jumps.npy"]
    # a bare extension is a missing file name, not a hidden directory (it became ".bvh/00_....gif")
    with pytest.raises(ValueError, match=r"--out .*\.bvh: a file name is missing before \.bvh"):
        generate.output_paths(tmp_path / ".bvh", None, prompts[:1])
    locked = tmp_path / "locked.npy"
    locked.write_bytes(b"")
    locked.chmod(0o444)
    real_access = os.access
    with pytest.MonkeyPatch.context() as mp:  # as a user other than root (root may write anything)
        mp.setattr(os, "access", lambda path, mode: Path(path) != locked and real_access(path, mode))
        with pytest.raises(ValueError, match=r"locked.npy exists and is read-only"):
            generate.output_paths(locked, None, prompts[:1])
    with pytest.raises(ValueError, match=r"the file name 'x{250}.npy' is too long \(at most 246 bytes\)"):
        generate.output_paths(tmp_path / ("x" * 250 + ".npy"), None, prompts[:1])


def test_outputs_appear_together_or_not_at_all(tmp_path: Path) -> None:
    """Every file is written under a temporary name and renamed when all are written: a motion that fails to
    write (a BVH of non-finite joints) leaves neither its file nor the one written before it. An upper-case
    .NPY is the file named (np.save on a name appends .npy)."""
    import numpy as np

    good = np.zeros((5, HUMANML3D.joints_num, 3), np.float32)
    bad = np.full_like(good, np.nan)
    out = tmp_path / "out"
    jobs = [(good, out / "00_a.npy", "a", "humanml3d", None), (bad, out / "01_b.bvh", "b", "humanml3d", None)]
    with pytest.raises(ValueError, match=rf"^cannot write: {out / '01_b.bvh'}: the joint positions are not all"):
        generate.write_all(jobs)  # the error names the file asked for, not its temporary name
    assert sorted(p.name for p in out.iterdir()) == []
    (out / "01_b.npy").mkdir()  # taken after the checks: the second rename fails, the first is taken back
    jobs[1] = (good, out / "01_b.npy", "b", "humanml3d", None)
    with pytest.raises(OSError, match=rf"^cannot write: .*Is a directory: '{out / '01_b.npy'}'"):
        generate.write_all(jobs)
    assert sorted(p.name for p in out.iterdir()) == ["01_b.npy"]
    assert generate.write_all([(good, tmp_path / "x.NPY", "x", "humanml3d", None)]) == [tmp_path / "x.NPY"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "x.NPY"]
    np.testing.assert_array_equal(np.load(tmp_path / "x.NPY"), good)


def test_a_motion_that_is_not_finite_is_refused_naming_its_prompt_and_the_causes() -> None:
    import numpy as np

    request = generate.Request("mld", [Prompt("walk", 5, "--text 'walk'")], [Path("w.npy")],
                               generate.GenerateOptions(guidance=1e30))
    nan = np.full((5, HUMANML3D.joints_num, 3), np.nan)
    with pytest.raises(ValueError, match=r"^--text 'walk': the model's motion is not finite \(NaN or infinity\): "
                                         r"check --guidance 1e\+30; nothing written$"):
        generate.check_finite(nan, request.prompts[0], request)
    generate.check_finite(np.zeros_like(nan), request.prompts[0], request)


def test_steps_of_a_family_generate_does_not_know_are_left_to_the_family() -> None:
    """A family added after this module (README, "Adding a model") checks ``--steps`` itself when loaded."""
    params = load_params([])
    generate.check_steps("lcm", 4, params)  # no KeyError
    with pytest.raises(ValueError, match="--steps 0: must be at least 1"):
        generate.check_steps("lcm", 0, params)
    with pytest.raises(ValueError, match=r"--steps 1001: MLD samples with DDIM over 1..1000 steps"):
        generate.check_steps("mld", 1001, params)


def test_length_range_is_the_training_split(small_store: dict[str, Any]) -> None:
    store = FeatureStore(small_store["features"]["out"])
    lengths = [item.length for item in store.split("train")]
    assert generate.length_range(store) == (min(lengths), max(lengths))


# --------------------------------------------------------------------------------------------------
# Options checked before any model (subprocess: exit status 1, one line, nothing written)
# --------------------------------------------------------------------------------------------------


def run_cli(args: list[str], params: dict[str, Any], artifacts: Path, env: dict[str, str] | None = None
            ) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "stages.generate", *args, f"paths.artifacts={artifacts}",
                           f"features.out={params['features']['out']}"],
                          cwd=REPO, capture_output=True, text=True, timeout=300, env=env)


@pytest.fixture(scope="module")
def bounds(small_store: dict[str, Any]) -> tuple[int, int]:
    return generate.length_range(FeatureStore(small_store["features"]["out"]))


def cases(tmp: Path, store: str, low: int, high: int) -> list[tuple[list[str], str]]:
    """(arguments, the expected stderr line) for each kind of bad option."""
    prompts = tmp / "prompts.txt"
    prompts.write_text(f"a person walks | {low}\n# a comment\na person jumps | ten\n")
    long = tmp / "long.txt"
    long.write_text(f"a person walks\n\na person jumps | {high + 1}\n")
    known = "emdm, emdm-action, mld, motiondiffuse, motionlcm, motionlcm-control"
    walks = ["--text", "a person walks"]
    return [
        ([*walks, "--steps", "0", "--out", str(tmp / "w.gif")], "--steps 0: must be at least 1"),
        ([*walks, "--model", "motionlcm", "--steps", "3", "--out", str(tmp / "w.gif")],
         "--steps 3: MotionLCM samples with 1, 2, 4 steps"),
        ([*walks, "--model", "emdm", "--steps", "50", "--out", str(tmp / "w.gif")],
         "--steps 50: EMDM samples with the 10 steps it was trained with (train_emdm.num_steps)"),
        (["--text", "walk", "--model", "emdm-action", "--steps", "4", "--out", str(tmp / "w.gif")],
         "--steps 4: EMDM-action samples with the 10 steps it was trained with (train_emdm_action.num_steps)"),
        ([*walks, "--length", str(low - 1), "--out", str(tmp / "w.gif")],
         f"--text 'a person walks': length {low - 1} is outside {low}..{high} frames, the lengths of the training "
         f"motions ({store})"),
        (["--prompts", str(long), "--out", str(tmp / "out")],
         f"{long}:3: length {high + 1} is outside {low}..{high} frames, the lengths of the training motions ({store})"),
        (["--prompts", str(prompts), "--out", str(tmp / "out")],
         f"{prompts}:3: length 'ten' is not a whole number of frames (expected TEXT | LENGTH)"),
        ([*walks, "--out", str(tmp / "w.mp4")],
         f"--out {tmp / 'w.mp4'}: writing MP4 needs ffmpeg on PATH, which is not installed; write a .gif instead"),
        ([*walks, "--format", "mp4", "--out", str(tmp / "out")],
         "--format mp4: writing MP4 needs ffmpeg on PATH, which is not installed; write a .gif instead"),
        ([*walks, "--out", str(tmp / "w.avi")], f"--out {tmp / 'w.avi'}: unknown format 'avi'; use gif, mp4, png, npy, "
                                                "bvh"),
        ([*walks, "--format", "avi", "--out", str(tmp / "out")],
         "--format avi: unknown format 'avi'; use gif, mp4, png, npy, bvh"),
        ([*walks, "--format", "bvh", "--out", str(tmp / "w.gif")], f"--out {tmp / 'w.gif'} and --format bvh disagree; "
                                                                   "give one of them"),
        ([*walks, "--text", "a person jumps", "--out", str(tmp / "w.gif")],
         f"--out {tmp / 'w.gif'}: 2 prompts are written into a directory; give a directory (and --format)"),
        ([*walks, "--model", "nope", "--out", str(tmp / "w.gif")],
         f"--model: unknown model family 'nope'; choose one of {known}"),
        ([*walks, "--model", "vae", "--out", str(tmp / "w.gif")],
         f"--model: model family 'vae' has no generator (it is evaluated only); choose one of {known}"),
        (["--text", "  ", "--out", str(tmp / "w.gif")], "--text '  ': empty prompt"),
        ([*walks, "--guidance", "nan", "--out", str(tmp / "w.gif")], "--guidance nan: must be a finite number, at "
                                                                     "least 0"),
        ([*walks, "--size", "2", "--out", str(tmp / "w.gif")],
         "--size: it sizes a --trajectory shape, and no --trajectory is given"),
        ([*walks, "--model", "motionlcm-control", "--trajectory", "line", "--size", "-1", "--out", str(tmp / "w.gif")],
         "--size -1.0: must be a positive number of metres"),
        ([*walks, "--out", str(prompts / "w.npy")], f"--out {prompts / 'w.npy'}: {prompts} is a file, not a directory"),
        ([*walks, "--out", f"{prompts}/"], f"--out {prompts}: exists and is not a directory"),
        ([*walks, "--out", str(tmp / "w.gif"), "sample.mld_guidance=abc"],
         "sample.mld_guidance: expected a number >= 0.0, got 'abc'"),
        # after the cases above (test_bad_options_through_the_command picks some by position)
        ([*walks, "--trajectory", "line", "--out", str(tmp / "w.gif")],
         "--trajectory/--refine need a controlled model (motionlcm-control), not 'mld'"),
        ([*walks, "--model", "motionlcm", "--refine", "--out", str(tmp / "w.gif")],
         "--trajectory/--refine need a controlled model (motionlcm-control), not 'motionlcm'"),
        ([*walks, "--model", "motionlcm-control", "--out", str(tmp / "w.gif")],
         "--model motionlcm-control follows a trajectory: pass --trajectory (circle, line, zigzag or a .npy)"),
        ([*walks, "--seed", "-1", "--out", str(tmp / "w.gif")],
         f"--seed -1: must be a whole number from 0 to {2**64 - 1} (prompt k samples with --seed + k)"),
        ([*walks, "--text", "a person jumps", "--seed", str(2**64 - 1), "--out", str(tmp / "out")],
         f"--seed {2**64 - 1}: must be a whole number from 0 to {2**64 - 2} (prompt k samples with --seed + k)"),
        ([*walks, "--out", ""], "--out is empty: give a file (walk.gif) or a directory (out/)"),
    ]


def test_bad_options_end_before_any_model(small_store: dict[str, Any], bounds: tuple[int, int], tmp_path: Path,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """In process, every case: ``main`` exits with the case's one-line message; nothing is written."""
    no_ffmpeg = tmp_path / "bin"
    no_ffmpeg.mkdir()
    monkeypatch.setenv("PATH", str(no_ffmpeg))
    store = str(Path(small_store["features"]["out"]).resolve())
    overrides = [f"paths.artifacts={tmp_path / 'artifacts'}", f"features.out={store}"]
    for args, message in cases(tmp_path, store, *bounds):
        with pytest.raises(SystemExit) as exit_info:
            generate.main([*args, *overrides])
        assert exit_info.value.code == f"generate: {message}", args
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bin", "long.txt", "prompts.txt"]


def test_bad_options_through_the_command(small_store: dict[str, Any], bounds: tuple[int, int],
                                         tmp_path: Path) -> None:
    """As a command (steps, length, MP4 without ffmpeg, model): status 1, exactly one line, no traceback."""
    artifacts, no_ffmpeg = tmp_path / "artifacts", tmp_path / "bin"
    no_ffmpeg.mkdir()
    env = dict(os.environ, PATH=str(no_ffmpeg))
    store = str(Path(small_store["features"]["out"]).resolve())
    chosen = [cases(tmp_path, store, *bounds)[k] for k in (0, 3, 6, 12)]
    for args, message in chosen:
        proc = run_cli(args, small_store, artifacts, env)
        assert (proc.returncode, proc.stderr, proc.stdout) == (1, f"generate: {message}\n", ""), args
    assert not artifacts.exists() and not (tmp_path / "w.gif").exists() and not (tmp_path / "w.mp4").exists()


def test_help_documents_out_prompts_and_lengths() -> None:
    text = generate.build_parser().format_help()
    for words in ("--prompts FILE", "TEXT | LENGTH", "(HumanML3D: 40..196)", "NN_<words>.<format>", ".bvh",
                  "at least 1"):
        assert words in " ".join(text.split()), words


# --------------------------------------------------------------------------------------------------
# End to end with a tiny untrained MLD
# --------------------------------------------------------------------------------------------------


def save_tiny_mld(artifacts: Path) -> None:
    """Untrained one-layer VAE and MLD denoiser as ``train_vae`` / ``train_mld`` outputs."""
    torch.manual_seed(0)
    vae = MotionVAEConfig(latent_dim=16, layers=1, heads=2, ff_dim=32, dropout=0.0)
    mld = MLDConfig(latent_dim=16, layers=1, heads=2, ff_dim=32, dropout=0.0, time_freq_dim=16)
    schedule = {"beta_schedule": "scaled_linear", "num_train_timesteps": 1000, "beta_start": 0.00085,
                "beta_end": 0.012}
    for stage, name, model, config in (("train_vae", "vae", MotionVAE(vae), {}),
                                       ("train_mld", "denoiser", MLDDenoiser(mld), schedule)):
        cfg = dataclasses.asdict(vae if name == "vae" else mld)
        (artifacts / stage).mkdir(parents=True)
        save_final_model(artifacts / stage, final_model_payload({"models": {name: model.state_dict()}, "step": 0},
                                                                {"model": cfg, **config}))


@pytest.mark.slow
def test_prompt_file_and_texts_to_bvh(small_store: dict[str, Any], bounds: tuple[int, int], tmp_path: Path) -> None:
    """``--text`` first, then the file's prompts, each with its length, one BVH per prompt; the same seed
    writes the same files again."""
    low, high = bounds
    save_tiny_mld(tmp_path / "artifacts")
    prompts = tmp_path / "prompts.txt"
    prompts.write_text(f"# two prompts\na person walks forward | {low}\n\na person jumps\n")
    args = ["--text", "A person waves!", "--prompts", str(prompts), "--length", str(high), "--steps", "2",
            "--format", "bvh"]
    proc = run_cli([*args, "--out", str(tmp_path / "out")], small_store, tmp_path / "artifacts")
    assert proc.returncode == 0, proc.stderr
    names = ["00_a_person_waves.bvh", "01_a_person_walks_forward.bvh", "02_a_person_jumps.bvh"]
    assert proc.stdout.splitlines() == [str(tmp_path / "out" / name) for name in names]
    for name, length in zip(names, (high, low, high), strict=True):
        motion = read_bvh(tmp_path / "out" / name)
        assert motion.positions.shape[0] == length and motion.frame_time == 1 / HUMANML3D.fps
    again = run_cli([*args, "--out", str(tmp_path / "again")], small_store, tmp_path / "artifacts")
    assert again.returncode == 0, again.stderr
    for name in names:
        assert (tmp_path / "again" / name).read_bytes() == (tmp_path / "out" / name).read_bytes()


def test_kit_outputs_are_drawn_and_saved_in_metres_and_paths_read_in_metres(tmp_path: Path) -> None:
    """KIT-ML's joints are millimetres: .npy and the drawings get metres, .bvh keeps the skeleton's millimetres,
    and a trajectory given in metres becomes a hint in millimetres (what its ControlNet was trained on): a shape
    leads ahead of the body (KIT-ML's face -z), a .npy stays on the axes generate writes."""
    import types

    import numpy as np

    from data.trajectories import make_trajectory

    joints = np.random.default_rng(0).normal(size=(12, KIT.joints_num, 3)) * 300.0 + [0.0, 900.0, 0.0]
    saved = generate.write_motion(joints, tmp_path / "m.npy", "c", "kit")
    np.testing.assert_allclose(np.load(saved), joints * 0.001, rtol=1e-6)
    drawn = {}
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(generate, "render_strip", lambda j, path, caption, skeleton, target_path: drawn.update(
            joints=j, target=target_path) or path)
        generate.write_motion(joints, tmp_path / "m.png", "c", "kit", target_path=joints[:, 0])
    np.testing.assert_allclose(drawn["joints"], joints * 0.001)
    np.testing.assert_allclose(drawn["target"], joints[:, 0] * 0.001)
    bvh = generate.write_motion(joints, tmp_path / "m.bvh", "c", "kit")
    assert np.abs(read_bvh(bvh).joints(KIT.joint_names)[:, 0] - joints[:, 0]).max() < 1e-3  # mm, as written
    store = types.SimpleNamespace(meta={"skeleton": "kit"}, mean=np.full(KIT.joints_num * 12 - 1, 950.0))
    path = generate.pelvis_path("line", 30, store, size=2.0)  # ahead of a KIT body: toward -z
    ahead = make_trajectory("line", 30, size=2.0, height=0.95) * [-1.0, 1.0, -1.0]
    np.testing.assert_allclose(path, ahead * 1000.0, rtol=1e-6)
    assert path[-1, 2] == pytest.approx(-2000.0)
    np.save(tmp_path / "p.npy", np.linspace([0.0, 0.9, 0.0], [1.0, 0.9, 2.0], 30))
    np.testing.assert_allclose(generate.pelvis_path(str(tmp_path / "p.npy"), 30, store)[-1], [1000.0, 900.0, 2000.0])
