"""``python -m pipelines.preflight``: every stage's params checked before the pipeline runs."""

from __future__ import annotations

import pytest

from pipelines import preflight
from pipelines.config import REPO_ROOT


def test_every_dvc_stage_is_a_stage_module_run_with_its_arguments() -> None:
    commands = preflight.stage_commands()
    assert len(commands) == 21
    assert commands["make_dataset"] == ("stages.make_dataset", [])
    assert commands["eval_motionlcm-control"] == ("stages.evaluate", ["motionlcm-control"])
    assert all((REPO_ROOT / (module.replace(".", "/") + ".py")).is_file() for module, _ in commands.values())


def test_a_command_other_than_a_stage_module_is_refused(tmp_path) -> None:
    dvc_yaml = tmp_path / "dvc.yaml"
    dvc_yaml.write_text("stages:\n  shell:\n    cmd: bash run.sh\n")
    with pytest.raises(ValueError, match="stage 'shell' runs 'bash run.sh', not python -m stages.<module>"):
        preflight.stage_commands(dvc_yaml)


def test_the_committed_params_pass(capsys: pytest.CaptureFixture[str]) -> None:
    preflight.main([])
    assert capsys.readouterr().out == "preflight: the params of all 21 stages pass their checks\n"


def test_each_problem_is_named_once_with_the_stages_it_stops() -> None:
    """A late stage's bad value and a shared key's: one line each, the stages that read them; the stages'
    own checks, so the lines are theirs."""
    with pytest.raises(SystemExit) as exit_info:
        preflight.main(["train_motiondiffuse.lr=-1", "ray.num_workers=abc"])
    training = ("train_evaluator, train_vae, train_mld, distill_lcm, train_controlnet, train_emdm, "
                "train_emdm_action, train_motiondiffuse")
    assert str(exit_info.value.code).splitlines() == [
        "preflight: these params would stop the pipeline (fix them in conf/ or the overrides):",
        f"  ray.num_workers: expected an integer >= 0, got 'abc' ({training})",
        "  train_motiondiffuse.lr: expected a number > 0.0, got -1 (train_motiondiffuse)",
    ]


def test_a_problem_of_every_stage_says_so() -> None:
    with pytest.raises(SystemExit) as exit_info:
        preflight.main(["train_vae.lrr=1"])
    assert str(exit_info.value.code).splitlines()[1] == (
        "  unknown config key 'train_vae.lrr' in 'train_vae.lrr=1' (use +train_vae.lrr=... to add one) (every stage)")
