"""``python -m pipelines.preflight``: every stage's params checked before the pipeline runs."""

from __future__ import annotations

import os
import sys

import pytest

from pipelines import preflight
from pipelines.config import REPO_ROOT


def test_every_dvc_stage_is_a_stage_module_run_with_its_arguments() -> None:
    commands = preflight.stage_commands()
    assert {"make_dataset", "train_controlnet", "eval_motionlcm-control", "report"} <= set(commands)
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
    count = len(preflight.stage_commands())
    assert capsys.readouterr().out == f"preflight: the params of all {count} stages pass their checks\n"


def test_a_crashing_check_is_one_problem_and_leaves_argv_and_environment(tmp_path, monkeypatch) -> None:
    """A stage whose checks raise (a bug) is reported like the others instead of hiding them; what the
    module run changed in ``sys.argv`` and ``os.environ`` is undone."""
    (tmp_path / "crashing_stage.py").write_text("import os, sys\nos.environ['PREFLIGHT_PROBE'] = '1'\n"
                                                "raise TypeError(f'boom {sys.argv[1:]}')\n")
    (tmp_path / "exiting_stage.py").write_text("import sys\nsys.exit('exiting: a.b: bad\\nexiting: c: worse')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    argv = list(sys.argv)
    assert preflight.stage_problems("crash", "crashing_stage", ["x"], ["k=v"]) == [
        "crash: its checks crashed (TypeError: boom ['x', 'k=v', '--cfg'])"]
    assert preflight.stage_problems("exit", "exiting_stage", [], []) == ["exiting: a.b: bad", "exiting: c: worse"]
    assert sys.argv == argv and "PREFLIGHT_PROBE" not in os.environ


def test_help_and_unknown_options(capsys: pytest.CaptureFixture[str]) -> None:
    preflight.main(["--help"])
    assert capsys.readouterr().out.startswith("Every pipeline stage's params checked in one process")
    with pytest.raises(SystemExit) as exit_info:
        preflight.main(["--cfg"])
    assert exit_info.value.code == "preflight: unknown option(s) ['--cfg']; it takes key=value overrides and --help"


def test_each_problem_is_named_once_with_the_stages_it_stops() -> None:
    """A late stage's bad value and a shared key's: one line each, the stages that read them; the stages'
    own checks, so the lines are theirs."""
    with pytest.raises(SystemExit) as exit_info:
        preflight.main(["train_motiondiffuse.lr=-1", "ray.num_workers=abc"])
    training = ("train_evaluator, train_vae, train_mld, distill_lcm, train_controlnet, train_emdm, "
                "train_emdm_action, train_motiondiffuse")
    assert str(exit_info.value.code).splitlines() == [
        "preflight: these params would stop the pipeline or be ignored by it (fix them in conf/ or the overrides):",
        f"  ray.num_workers: expected an integer >= 0, got 'abc' ({training})",
        "  train_motiondiffuse.lr: expected a number > 0.0, got -1 (train_motiondiffuse)",
    ]


def test_a_problem_of_every_stage_says_so() -> None:
    with pytest.raises(SystemExit) as exit_info:
        preflight.main(["train_vae.lrr=1"])
    assert str(exit_info.value.code).splitlines()[1] == (
        "  unknown config key 'train_vae.lrr' in 'train_vae.lrr=1' (use +train_vae.lrr=... to add one) (every stage)")


@pytest.mark.parametrize(("override", "line"), [
    ("train_vae.loop=5", "  train_vae.loop: expected a mapping with keys ['seed', 'batch_size', 'max_steps', "
     "'grad_clip', 'lr_schedule', 'warmup_steps', 'min_lr_ratio', 'log_every', 'num_data_workers', "
     "'length_buckets'], got 5 (train_vae)"),
    ("evaluate=5", "  evaluate: expected a mapping, got 5 (eval_real, eval_baselines, eval_vae, eval_mld, "
     "eval_motionlcm, eval_motionlcm-control, eval_emdm, eval_emdm-action, eval_motiondiffuse, eval_speed)"),
])
def test_a_scalar_where_a_group_belongs_is_named_not_a_crash(override: str, line: str) -> None:
    """A loop group or the evaluate section given as a number: the stages' checks said so with a TypeError or
    an AttributeError before."""
    with pytest.raises(SystemExit) as exit_info:
        preflight.main([override])
    assert str(exit_info.value.code).splitlines()[1:] == [line]


def test_attention_heads_that_do_not_divide_the_width_are_named_for_every_model() -> None:
    """torch asserts when the network is built (for the VAE, after the evaluator trained); the checks say it
    first, naming the key and the width."""
    with pytest.raises(SystemExit) as exit_info:
        preflight.main(["train_vae.model.heads=5", "train_mld.model.heads=5", "train_controlnet.encoder.heads=5",
                        "train_emdm.model.d_heads=3", "train_motiondiffuse.model.text_heads=7",
                        "train_emdm_action.model.heads=0"])
    assert str(exit_info.value.code).splitlines()[1:] == [
        "  train_vae.model.heads: width 64 must be divisible by heads 5 (train_vae)",
        "  train_mld.model.heads: width 128 must be divisible by heads 5 (train_mld)",
        "  train_controlnet.encoder.heads: width 64 must be divisible by heads 5 (train_controlnet)",
        "  train_emdm.model.d_heads: width 64 must be divisible by d_heads 3 (train_emdm)",
        "  train_emdm_action.model.heads: expected an integer >= 1, got 0 (train_emdm_action)",
        "  train_motiondiffuse.model.text_heads: width 96 must be divisible by text_heads 7 (train_motiondiffuse)",
    ]


def test_row_names_no_family_has_are_named_before_the_pipeline_runs() -> None:
    """A misspelt row in ``evaluate.paraphrase_rows`` or ``evaluate.samples.rows`` passes every stage's checks
    and was skipped without a word; a row ``eval_speed`` does not time stopped it only after training. The
    names come from the params: with ``train_emdm.num_steps=5`` the row is ``EMDM-5``, so ``EMDM-10`` is
    unknown."""
    evaluating = ("eval_real, eval_baselines, eval_vae, eval_mld, eval_motionlcm, eval_motionlcm-control, "
                  "eval_emdm, eval_emdm-action, eval_motiondiffuse")
    captions = ("Random, Retrieval, MLD-DDIM50, MLD-DDIM1, MLD-DDIM2, MLD-DDIM4, MotionLCM-1, MotionLCM-2, "
                "MotionLCM-4, MotionLCM-Control, MotionLCM-Control-5f, MotionLCM-Control+refine, "
                "MotionLCM-1-uncontrolled, EMDM-{t}, MotionDiffuse-1000, MotionDiffuse-DDIM10")
    free = captions.replace("MotionLCM-Control, MotionLCM-Control-5f, MotionLCM-Control+refine, "
                            "MotionLCM-1-uncontrolled, ", "")
    with pytest.raises(SystemExit) as exit_info:  # a ControlNet row answers paraphrases, but draws no sample
        preflight.main(["evaluate.paraphrase_rows=[MLD-DDIM5O,MLD-DDIM50,MotionLCM-Control]",
                        "evaluate.samples.rows=[VAE,MotionLCM-Control]", "speed.rows=[EMDM-10,MLD-DDIM50]"])
    assert str(exit_info.value.code).splitlines()[1:] == [
        f"  evaluate.paraphrase_rows: unknown row(s) 'MLD-DDIM5O' (it takes the rows that answer captions: "
        f"{captions.format(t=10)}) ({evaluating})",
        f"  evaluate.samples.rows: unknown row(s) 'VAE', 'MotionLCM-Control' (it takes the rows that answer "
        f"captions without a trajectory: {free.format(t=10)}) ({evaluating})",
        "  speed.rows: unknown row(s) 'MLD-DDIM50' (it takes the rows of emdm and motiondiffuse, which eval_speed "
        "times: EMDM-10, MotionDiffuse-1000, MotionDiffuse-DDIM10) (eval_speed)",
    ]
    with pytest.raises(SystemExit) as exit_info:
        preflight.main(["train_emdm.num_steps=5"])
    assert [line.split(" (it takes")[0] for line in str(exit_info.value.code).splitlines()[1:]] == [
        "  evaluate.paraphrase_rows: unknown row(s) 'EMDM-10'", "  evaluate.samples.rows: unknown row(s) 'EMDM-10'",
        "  speed.rows: unknown row(s) 'EMDM-10'"]
    preflight.main(["train_emdm.num_steps=5", "evaluate.paraphrase_rows=[EMDM-5]", "evaluate.samples.rows=[EMDM-5]",
                    "speed.rows=[EMDM-5,MotionDiffuse-1000]"])
