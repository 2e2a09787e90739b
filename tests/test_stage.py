"""The training-stage skeleton and a run's identity (pipelines/stage.py, pipelines/identity.py).

- A run's fingerprint covers the code its stage imports and its inputs' contents: editing an
  imported module or an input file changes it, editing an unrelated module does not.
- The runner resumes only a run of the same fingerprint: changed code trains from step 0 (and
  reaches other weights), an unchanged finished or interrupted run resumes.
- ``ray.storage`` is where a training stage's Ray run goes.
- The ``loop`` group is validated: unknown, missing or mistyped keys are errors naming the key.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import ray.cloudpickle
import torch
from torch import nn
from torch.utils.data import TensorDataset

from pipelines.checkpoint import load_final_model, skipped
from pipelines.config import REPO_ROOT
from pipelines.identity import fingerprint, module_files
from pipelines.runner import Components, LoopSettings, StepContext, TrainSpec, run_training
from pipelines.stage import TrainingStage, loop_config, ray_storage, train, train_unless_skipped

ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])

LOOP = {"seed": 1, "batch_size": 16, "max_steps": 20, "grad_clip": 1.0, "lr_schedule": "cosine",
        "warmup_steps": 2, "min_lr_ratio": 0.0, "log_every": 10, "num_data_workers": 0, "length_buckets": 0}
RAY = {"num_workers": 1, "checkpoint_every": 10, "max_failures": 0, "cpus_per_worker": 1}


def write(root: Path, rel: str, text: str) -> None:
    path = root / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


@pytest.fixture
def project(tmp_path: Path) -> Path:
    """A miniature project: a stage importing a model, a lazily imported sweep and an unrelated module."""
    for package in ("stages", "models", "pipelines", "data"):
        write(tmp_path, f"{package}/__init__.py", "")
    write(tmp_path, "stages/train_x.py", "from typing import TYPE_CHECKING\nfrom models import net\n"
          "if TYPE_CHECKING:\n    from models import typing_only\n"
          "def sweep():\n    from pipelines import sweep\n")
    write(tmp_path, "models/net.py", "import torch\nfrom data.io import load\nWIDTH = 8\n")
    write(tmp_path, "data/io.py", "def load():\n    return 1\n")
    for rel in ("models/typing_only.py", "models/other.py", "pipelines/sweep.py"):
        write(tmp_path, rel, "X = 1\n")
    return tmp_path


def test_module_files_follow_module_level_project_imports(project: Path) -> None:
    files = [str(p) for p in module_files("stages.train_x", project)]
    assert files == ["data/__init__.py", "data/io.py", "models/__init__.py", "models/net.py",
                     "stages/__init__.py", "stages/train_x.py"]


def test_fingerprint_changes_with_imported_code_and_inputs_only(project: Path, tmp_path: Path) -> None:
    inputs = tmp_path / "inputs"
    write(inputs, "a.bin", "data")
    base = fingerprint("stages.train_x", [inputs], project)
    assert fingerprint("stages.train_x", [inputs], project) == base
    write(project, "models/other.py", "X = 2\n")  # not imported
    write(project, "pipelines/sweep.py", "X = 2\n")  # imported inside a function only
    assert fingerprint("stages.train_x", [inputs], project) == base
    write(project, "data/io.py", "def load():\n    return 2\n")  # imported through models/net.py
    edited = fingerprint("stages.train_x", [inputs], project)
    assert edited != base
    write(inputs, "a.bin", "other data")
    assert fingerprint("stages.train_x", [inputs], project) != edited
    with pytest.raises(FileNotFoundError, match="missing"):
        fingerprint("stages.train_x", [tmp_path / "missing"], project)


# --------------------------------------------------------------------------- runs on Ray


def build(cfg: dict) -> Components:
    net = nn.Sequential(nn.Linear(4, 16), nn.ReLU(), nn.Linear(16, 1))
    return Components({"net": net}, {"adam": torch.optim.Adam(net.parameters(), lr=cfg["lr"])})


def dataset(cfg: dict) -> TensorDataset:
    x = torch.randn(128, 4, generator=torch.Generator().manual_seed(0))
    return TensorDataset(x, x.sum(1, keepdim=True))


def step_v1(batch: tuple, ctx: StepContext) -> dict[str, torch.Tensor]:
    x, y = batch
    loss = nn.functional.mse_loss(ctx.models["net"](x), y)
    ctx.update(loss)
    return {"loss": loss}


def step_v2(batch: tuple, ctx: StepContext) -> dict[str, torch.Tensor]:
    """``step_v1`` after an edit: the target is doubled."""
    x, y = batch
    loss = nn.functional.mse_loss(ctx.models["net"](x), 2 * y)
    ctx.update(loss)
    return {"loss": loss}


def final_weight(out: Path) -> torch.Tensor:
    return load_final_model(out)["models"]["net"]["0.weight"]


@pytest.mark.slow
def test_changed_code_trains_from_step_zero_unchanged_resumes(ray_cluster: object, tmp_path: Path) -> None:
    config = LOOP | {"lr": 1e-2}
    storage = str(tmp_path / "ray")
    first = run_training("toy", TrainSpec(build, dataset, step_v1), config, RAY, tmp_path / "a", storage,
                         fingerprint="code-v1")
    assert first.attempts == [0]
    again = run_training("toy", TrainSpec(build, dataset, step_v1), config, RAY, tmp_path / "b", storage,
                         fingerprint="code-v1")
    assert again.run_name == first.run_name
    assert again.attempts == [0, 20]  # resumed at the end: trained no step
    assert torch.equal(final_weight(tmp_path / "a"), final_weight(tmp_path / "b"))
    edited = run_training("toy", TrainSpec(build, dataset, step_v2), config, RAY, tmp_path / "c", storage,
                          fingerprint="code-v2")
    assert edited.run_name != first.run_name
    assert edited.attempts == [0]
    assert edited.metrics["step"] == 20
    assert not torch.equal(final_weight(tmp_path / "a"), final_weight(tmp_path / "c"))


def toy_config(params: dict) -> dict:
    return {"lr": params["toy"]["lr"], "data_dir": params["toy"]["data_dir"]}


@pytest.mark.slow
def test_stage_runs_in_ray_storage_with_its_fingerprint(ray_cluster: object, tmp_path: Path) -> None:
    data_dir = tmp_path / "inputs"
    write(data_dir, "x.txt", "1")
    stage = TrainingStage(name="toy_stage", module="pipelines.stage", spec=TrainSpec(build, dataset, step_v1),
                          config=toy_config, params=("toy", "paths", "ray"), inputs=("data_dir",),
                          loop_group="toy.loop")
    params = {"toy": {"lr": 1e-2, "data_dir": str(data_dir), "loop": LOOP},
              "paths": {"artifacts": str(tmp_path / "artifacts"), "ray_storage": str(tmp_path / "unused")},
              "ray": RAY | {"storage": str(tmp_path / "shared")}}
    result = train(stage, params)
    assert result.out_dir == tmp_path / "artifacts" / "toy_stage"
    assert (tmp_path / "shared" / result.run_name).is_dir()
    assert not (tmp_path / "unused").exists()
    write(data_dir, "x.txt", "2")  # a changed input is another run
    assert train(stage, params).run_name != result.run_name
    assert fingerprint("pipelines.stage", [data_dir]) in (tmp_path / "artifacts" / "toy_stage" / "run.json").read_text()


# --------------------------------------------------------------------------- the loop group


def test_loop_group_is_validated() -> None:
    assert LoopSettings.parse(LOOP, "x.loop").max_steps == 20
    with pytest.raises(ValueError, match=r"x.loop: unknown key\(s\) \['max_step'\], missing key\(s\) \['max_steps'\]"):
        LoopSettings.parse({k: v for k, v in LOOP.items() if k != "max_steps"} | {"max_step": 3}, "x.loop")
    with pytest.raises(ValueError, match="x.loop.batch_size: expected int, got '16'"):
        LoopSettings.parse(LOOP | {"batch_size": "16"}, "x.loop")
    with pytest.raises(ValueError, match="x.loop.grad_clip: expected float, got True"):
        LoopSettings.parse(LOOP | {"grad_clip": True}, "x.loop")
    assert LoopSettings.parse(LOOP | {"grad_clip": 1}, "x.loop").grad_clip == 1  # an int is a float
    for change, message in [({"max_steps": 0}, "x.loop.max_steps: expected an integer >= 1, got 0"),
                            ({"length_buckets": -2}, "x.loop.length_buckets: expected an integer >= 0, got -2"),
                            ({"min_lr_ratio": 5.0},
                             "x.loop.min_lr_ratio: expected a number >= 0.0 and <= 1.0, got 5.0"),
                            ({"grad_clip": -1.0}, "x.loop.grad_clip: expected a number >= 0.0, got -1.0"),
                            ({"log_every": 0}, "x.loop.log_every: expected an integer >= 1, got 0")]:
        with pytest.raises(ValueError) as err:
            LoopSettings.parse(LOOP | change, "x.loop")
        assert str(err.value) == message


def test_stage_config_may_not_repeat_runner_keys() -> None:
    stage = TrainingStage(name="toy", module="pipelines.stage", spec=TrainSpec(build, dataset, step_v1),
                          config=lambda params: {"lr": 1.0, "batch_size": 3}, params=("toy",))
    with pytest.raises(ValueError, match=r"repeats runner key\(s\) \['batch_size'\]"):
        loop_config(stage, {"toy": {"loop": LOOP}})
    ok = TrainingStage(name="toy", module="pipelines.stage", spec=stage.spec, config=lambda p: {"lr": 1.0},
                       params=("toy",))
    assert loop_config(ok, {"toy": {"loop": LOOP}}) == LOOP | {"lr": 1.0}


# --------------------------------------------------------------------------- a stage the data cannot feed


def test_a_skipped_stage_writes_only_its_reason_and_trains_nothing(tmp_path: Path) -> None:
    def no_config(params: dict) -> dict:
        raise AssertionError("a skipped stage builds no config")

    stage = TrainingStage(name="toy", module="pipelines.stage", spec=TrainSpec(build, dataset, step_v1),
                          config=no_config, params=("toy", "paths"), skip=lambda params: "no action labels")
    params = {"toy": {"loop": LOOP}, "paths": {"artifacts": str(tmp_path)}}
    assert train_unless_skipped(stage, params) is None
    assert [p.name for p in (tmp_path / "toy").iterdir() if not p.name.startswith(".")] == ["skipped.json"]
    assert skipped(tmp_path / "toy") == "no action labels" and skipped(tmp_path / "elsewhere") is None
    assert train_unless_skipped(stage, params) is None  # a second run replaces its own output


def test_ray_storage_paths_are_relative_to_the_repository_as_every_path_param(monkeypatch: pytest.MonkeyPatch,
                                                                             tmp_path: Path) -> None:
    monkeypatch.chdir(tmp_path)  # not the working directory: DVC runs from the root, a user anywhere
    params = {"paths": {"ray_storage": ".ray_storage"}, "ray": {"storage": None}}
    assert ray_storage(params) == str(REPO_ROOT / ".ray_storage")
    params["ray"]["storage"] = "shared/runs"
    assert ray_storage(params) == str(REPO_ROOT / "shared" / "runs")
    params["ray"]["storage"] = str(tmp_path / "abs")
    assert ray_storage(params) == str(tmp_path / "abs")
    params["ray"]["storage"] = "s3://bucket/prefix"
    assert ray_storage(params) == "s3://bucket/prefix"
