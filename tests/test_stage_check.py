"""benchmarks/stage_check.py: its scratch folders and what it reports from a stage's log; and the training
stages' own up-front checks (``python -m stages.<stage> --cfg``) of their model groups' ranges."""

import importlib
from collections.abc import Callable, Sequence
from pathlib import Path

import pytest

from pipelines import stage
from stages import train_evaluator
from tests.bench_module import load_benchmark

stage_check = load_benchmark("stage_check")


def test_scratch_folder_links_all_but_the_fresh_outputs(tmp_path: Path) -> None:
    artifacts = tmp_path / "artifacts"
    for name in ("features", "train_vae", "train_mld"):
        (artifacts / name).mkdir(parents=True)
        (artifacts / name / "model.pt").write_text(name)
    folder = tmp_path / "scratch" / "train_mld"
    folder.mkdir(parents=True)
    (folder / "stale.log").write_text("from an earlier check")
    assert stage_check.scratch_folder(folder, artifacts, {"train_mld"}) == folder
    assert sorted(p.name for p in folder.iterdir()) == ["features", "train_vae"]
    assert (folder / "train_vae").is_symlink() and (folder / "train_vae" / "model.pt").read_text() == "train_vae"
    assert (artifacts / "train_mld" / "model.pt").read_text() == "train_mld"  # the source is untouched


def test_first_error_is_the_first_line_naming_an_exception() -> None:
    log = ("[train_mld] step 1/4\n"
           "(RayTrainWorker pid=7) AttributeError: 'DistributedDataParallel' object has no attribute 'null_text'\n"
           "ray.exceptions.RayTaskError: the worker failed\n")
    assert stage_check.first_error(log) == (
        "(RayTrainWorker pid=7) AttributeError: 'DistributedDataParallel' object has no attribute 'null_text'")
    assert stage_check.first_error("[train_vae] step 4/4 loss=0.1\ntrain_vae: final loss 0.1\n") == ""


# --------------------------------------------------------------------------- the stages' --cfg checks

#: ``python -m stages.<name> [argv]`` of every training stage, by name.
STAGE_MAINS: dict[str, Callable[[Sequence[str]], None]] = {
    name: (lambda argv, name=name: stage.main(importlib.import_module(f"stages.{name}").STAGE, argv))
    for name in ("train_vae", "train_mld", "distill_lcm", "train_controlnet", "train_emdm", "train_emdm_action",
                 "train_motiondiffuse")
} | {"train_evaluator": train_evaluator.main}


def cfg_problems(name: str, overrides: Sequence[str], capsys: pytest.CaptureFixture[str]) -> list[str]:
    """The lines ``python -m stages.<name> <overrides> --cfg`` exits with (empty when the params pass)."""
    try:
        STAGE_MAINS[name]([*overrides, "--cfg"])
    except SystemExit as exit_:
        return str(exit_.code).splitlines()
    finally:
        capsys.readouterr()  # the params printed as YAML
    return []


@pytest.mark.parametrize(("override", "message"), [
    ("train_vae.model.layers=2", "train_vae.model.layers: expected an odd integer >= 1, got 2"),
    ("train_vae.model.latent_dim=0", "train_vae.model.latent_dim: expected an integer >= 1, got 0"),
    ("train_vae.model.ff_dim=0", "train_vae.model.ff_dim: expected an integer >= 1, got 0"),
    ("train_vae.model.latent_tokens=0", "train_vae.model.latent_tokens: expected an integer >= 1, got 0"),
    ("train_vae.model.hidden_dim=0", "train_vae.model.hidden_dim: expected an integer >= 1, got 0"),
    ("train_vae.model.dropout=1.0", "train_vae.model.dropout: expected a number >= 0.0 and < 1.0, got 1.0"),
    ("train_vae.model.logvar_offset=.nan", "train_vae.model.logvar_offset: expected a finite number, got nan"),
    ("train_mld.model.layers=4", "train_mld.model.layers: expected an odd integer >= 1, got 4"),
    ("train_mld.model.ff_dim=0", "train_mld.model.ff_dim: expected an integer >= 1, got 0"),
    ("train_mld.model.time_freq_dim=1", "train_mld.model.time_freq_dim: expected an integer >= 2, got 1"),
    ("train_mld.model.freq_shift=32",
     "train_mld.model.freq_shift: expected a number < time_freq_dim // 2 = 32, got 32"),
    ("train_mld.model.dropout=-0.1", "train_mld.model.dropout: expected a number >= 0.0 and < 1.0, got -0.1"),
    ("train_controlnet.encoder.layers=2", "train_controlnet.encoder.layers: expected an odd integer >= 1, got 2"),
    ("train_controlnet.encoder.dim=0", "train_controlnet.encoder.dim: expected an integer >= 1, got 0"),
    ("train_controlnet.encoder.ff_dim=0", "train_controlnet.encoder.ff_dim: expected an integer >= 1, got 0"),
    ("train_emdm.model.layers=0", "train_emdm.model.layers: expected an integer >= 1, got 0"),
    ("train_emdm.model.d_layers=0", "train_emdm.model.d_layers: expected an integer >= 1, got 0"),
    ("train_emdm.model.z_dim=0", "train_emdm.model.z_dim: expected an integer >= 1, got 0"),
    ("train_emdm.model.mapping_layers=0", "train_emdm.model.mapping_layers: expected an integer >= 1, got 0"),
    ("train_emdm.model.d_time_dim=1", "train_emdm.model.d_time_dim: expected an integer >= 2, got 1"),
    ("train_emdm.model.skip_kernel=4", "train_emdm.model.skip_kernel: expected an odd integer >= 1, got 4"),
    ("train_emdm.model.patch_frames=3", "train_emdm.model.overlap_out: needs an even patch_frames, got 3"),
    ("train_emdm_action.model.ff_dim=0", "train_emdm_action.model.ff_dim: expected an integer >= 1, got 0"),
    ("train_motiondiffuse.model.temporal_kernel=4",
     "train_motiondiffuse.model.temporal_kernel: expected 0 or an odd integer >= 1, got 4"),
    ("train_motiondiffuse.model.ff_dim=0", "train_motiondiffuse.model.ff_dim: expected an integer >= 1, got 0"),
    ("train_evaluator.movement_window=10",
     "train_evaluator.movement_window: expected a multiple of 4 (the movement encoder's unit length), got 10"),
])
def test_an_out_of_range_model_size_is_one_line_naming_its_key(override: str, message: str,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    name = override.split(".", 1)[0]
    assert cfg_problems(name, [override], capsys) == [f"{name}: {message}"]


def test_every_bad_model_value_is_listed(capsys: pytest.CaptureFixture[str]) -> None:
    overrides = ["train_vae.model.layers=2", "train_vae.model.latent_dim=0", "train_vae.model.ff_dim=0"]
    assert cfg_problems("train_vae", overrides, capsys) == [
        "train_vae: train_vae.model.latent_dim: expected an integer >= 1, got 0",
        "train_vae: train_vae.model.ff_dim: expected an integer >= 1, got 0",
        "train_vae: train_vae.model.layers: expected an odd integer >= 1, got 2",
    ]


def test_a_learned_positional_table_must_hold_the_vae_encoder_tokens(capsys: pytest.CaptureFixture[str]) -> None:
    """The table holds the latent tokens and the longest motion the VAE encodes: a training crop, or a whole
    test motion (below ``data.feature_frames_below`` frames; a table sized for the crops alone trained, then
    failed in eval_vae and train_mld)."""
    learned = ["train_vae.model.pos_encoding=learned", "train_vae.model.latent_tokens=2"]
    message = ("train_vae: train_vae.model.max_len: the learned positional encoding holds {} positions, the encoder "
               "reads 2 x latent_tokens + the longest motion (crop_frames, or data.feature_frames_below - 1 frames) "
               "= 203")
    assert cfg_problems("train_vae", [*learned, "train_vae.model.max_len=202"], capsys) == [message.format(202)]
    assert cfg_problems("train_vae", [*learned, "train_vae.model.max_len=80", "train_vae.crop_frames=64"],
                        capsys) == [message.format(80)]
    assert cfg_problems("train_vae", [*learned, "train_vae.model.max_len=203"], capsys) == []


@pytest.mark.parametrize("overrides", [
    ["train_vae.model.hidden_dim=null"], ["train_vae.model.hidden_dim=16", "train_vae.model.layers=1"],
    ["train_mld.model.hidden_dim=null"], ["train_mld.model.freq_shift=1.0"],
    ["train_motiondiffuse.model.temporal_kernel=0"], ["train_motiondiffuse.model.text_layers=0"],
    ["train_emdm.model.skip_kernel=1", "train_emdm.model.patch_frames=2"], ["train_evaluator.movement_window=4"],
], ids=lambda overrides: " ".join(overrides))
def test_values_the_models_take_pass(overrides: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    """0 and null where the models take them (conf/config.yaml), and the edges of the ranges."""
    assert cfg_problems(overrides[0].split(".", 1)[0], overrides, capsys) == []


@pytest.mark.parametrize("profile", [[], ["scale=smoke"], ["scale=paper"], ["dataset=kit"]], ids=str)
@pytest.mark.parametrize("name", sorted(STAGE_MAINS))
def test_the_shipped_params_pass(name: str, profile: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    assert cfg_problems(name, profile, capsys) == []
