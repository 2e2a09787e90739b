"""Tests of the training runner (pipelines/runner.py) on a tiny MLP and random data.

Exactness is checked bit for bit (``torch.equal``) against an uninterrupted in-process
reference run: a 1-worker Ray Train run, a run whose worker raises once at a step, and a
run whose driver process is SIGKILLed and started again all reach the same weights.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import psutil
import pytest
import ray.cloudpickle
import torch
from torch import nn
from torch.utils.data import Dataset, TensorDataset

from pipelines.checkpoint import STATE_FILE, load_final_model, rng_file
from pipelines.config import ConfigError, every_problem
from pipelines.runner import (
    Components,
    FiniteGuard,
    LoopSettings,
    Position,
    RayOptions,
    RunResult,
    StepContext,
    TrainingError,
    TrainSpec,
    _epoch_batches,
    _fit_local,
    _Window,
    bucket_by_length,
    decide_use_gpu,
    epoch_seed,
    fit_retrying,
    make_run_name,
    max_seed,
    run_training,
)
from pipelines.schedules import EMA, CosineWarmup
from pipelines.tracking import CHECKOUT, default_wandb_dir

# Ray workers cannot import this test module (pytest puts tests/ on sys.path only here):
# ship its functions by value.
ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])

TESTS_DIR = Path(__file__).resolve().parent
REPO = TESTS_DIR.parent
STAGE = "toy"

# --------------------------------------------------------------------------- the toy spec


def build(cfg: dict) -> Components:
    """Tiny MLP with dropout (uses the RNG), AdamW and an EMA; ``attempts_file`` gets a line per call."""
    if cfg.get("attempts_file"):
        with open(cfg["attempts_file"], "a") as fh:
            fh.write("attempt\n")
    hidden = cfg.get("hidden", 32)
    net = nn.Sequential(nn.Linear(8, hidden), nn.ReLU(), nn.Dropout(0.1), nn.Linear(hidden, 1))
    return Components({"net": net}, {"net": torch.optim.AdamW(net.parameters(), lr=cfg["lr"])}, ema={"net": 0.9})


def dataset(cfg: dict) -> TensorDataset:
    """256 random regression pairs (fixed by their own generator)."""
    x = torch.randn(256, 8, generator=torch.Generator().manual_seed(123))
    return TensorDataset(x, x.sum(1, keepdim=True))


def _test_hooks(ctx: StepContext) -> None:
    """Test-only behaviour driven by config keys: fail once, record nodes and steps, go slowly."""
    cfg = ctx.config
    if cfg.get("steps_file"):
        with open(cfg["steps_file"], "a") as fh:
            fh.write(f"{ctx.step}\n")
    marker = cfg.get("fail_marker")
    if marker and ctx.step == cfg["fail_at_step"] and not os.path.exists(marker):
        Path(marker).touch()
        raise RuntimeError(f"injected failure at step {ctx.step}")
    if cfg.get("nodes_dir") and ctx.step == 0:
        node = ray.get_runtime_context().get_node_id()
        Path(cfg["nodes_dir"], f"rank{ctx.rank}.txt").write_text(node)
    if cfg.get("step_sleep"):
        time.sleep(cfg["step_sleep"])


def step(batch: Any, ctx: StepContext) -> dict[str, torch.Tensor]:
    """MSE on noisy inputs (noise from the per-rank torch RNG).

    ``nan_loss_at``: the loss is NaN from that step on; ``nan_grad_at``: from that step on the
    loss stays finite but its gradient is NaN (d sqrt(x)/dx at 0 times 0).
    """
    _test_hooks(ctx)
    x, y = batch
    x = x + 0.01 * torch.randn_like(x)
    loss = nn.functional.mse_loss(ctx.models["net"](x), y)
    if ctx.step >= ctx.config.get("nan_loss_at", BIG):
        loss = loss * float("nan")
    if ctx.step >= ctx.config.get("nan_grad_at", BIG):
        loss = loss + torch.sqrt(0.0 * ctx.models["net"][0].weight.sum())
    ctx.update(loss)
    return {"loss": loss}


SPEC = TrainSpec(build=build, dataset=dataset, step=step)
BASE = {"seed": 3, "batch_size": 16, "max_steps": 40, "lr": 1e-2, "grad_clip": 1.0,
        "warmup_steps": 5, "log_every": 10}  # 16 batches per epoch: checkpoints fall mid-epoch
RAY1 = {"num_workers": 1, "checkpoint_every": 10, "max_failures": 2}
BIG = 10**9  # a step never reached


def weights(out_dir: Path) -> dict[str, torch.Tensor]:
    """All final tensors (model and EMA) of a run's out dir, flattened by name."""
    payload = load_final_model(out_dir)
    flat = {f"models.{m}.{k}": v for m, sd in payload["models"].items() for k, v in sd.items()}
    flat.update({f"ema.{m}.{k}": v for m, sd in payload["ema"].items() for k, v in sd.items()})
    return flat


def assert_bit_identical(a: Path, b: Path) -> None:
    """Both out dirs hold exactly the same tensors."""
    wa, wb = weights(a), weights(b)
    assert wa.keys() == wb.keys()
    different = [k for k in wa if not torch.equal(wa[k], wb[k])]
    assert not different, f"tensors differ: {different}"


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> RunResult:
    """Uninterrupted in-process run of BASE (the exactness reference)."""
    root = tmp_path_factory.mktemp("reference")
    return run_training(STAGE, SPEC, BASE, {"num_workers": 0, "checkpoint_every": 10},
                        root / "out", str(root / "storage"))


# --------------------------------------------------------------------------- in-process


def test_in_process_run_is_deterministic(reference: RunResult, tmp_path: Path) -> None:
    """Two in-process runs give identical weights, whatever the checkpoint interval."""
    again = run_training(STAGE, SPEC, BASE, {"local": True, "checkpoint_every": 7},
                         tmp_path / "out", str(tmp_path / "storage"))
    assert again.run_name == reference.run_name
    assert_bit_identical(reference.out_dir, again.out_dir)


def test_outputs(reference: RunResult) -> None:
    """metrics.json keys, one CSV row per logged step, a PNG, a loadable final model."""
    out = reference.out_dir
    metrics = json.loads((out / "metrics.json").read_text())
    assert {"loss", "grad_norm/net", "step", "epoch", "steps_per_s", "wall_time_s", "attempts"} <= metrics.keys()
    assert metrics["step"] == BASE["max_steps"] and metrics["attempts"] == 1
    with open(out / "loss.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["step"]) for r in rows] == [10, 20, 30, 40] == [h["step"] for h in reference.history]
    assert float(rows[-1]["loss"]) == pytest.approx(metrics["loss"])
    png = (out / "loss.png").read_bytes()
    assert png.startswith(b"\x89PNG") and len(png) > 1000
    payload = load_final_model(out)
    model = build(payload["config"]).models["net"]
    model.load_state_dict(payload["models"]["net"])
    assert model.eval()(torch.zeros(2, 8)).shape == (2, 1)
    run_json = json.loads((out / "run.json").read_text())
    assert payload["step"] == BASE["max_steps"] and run_json["attempts"] == [0]
    assert run_json["device"] == "cpu"  # where it trained (a GPU run says cuda or cuda:<i>)
    assert not list(out.parent.glob(".out.*")), "temporary folders left behind"


# --------------------------------------------------------------------------- non-finite guard


def _lines(path: Path) -> list[str]:
    return path.read_text().split() if path.exists() else []


@pytest.mark.parametrize(("key", "what", "name"), [("nan_loss_at", "loss", "loss"),
                                                   ("nan_grad_at", "gradient norm", "grad_norm/net")])
def test_non_finite_step_stops_the_run_at_once_and_writes_nothing(tmp_path: Path, key: str, what: str,
                                                                    name: str) -> None:
    """NaN from step 3 on: the run stops after step 3 (CPU: checked every step) naming it; no outputs."""
    cfg = {**BASE, key: 3, "steps_file": str(tmp_path / "steps.txt")}
    with pytest.raises(TrainingError) as info:
        run_training(STAGE, SPEC, cfg, {"num_workers": 0, "checkpoint_every": 10}, tmp_path / "out",
                     str(tmp_path / "storage"))
    run_name = make_run_name(STAGE, cfg, 1)
    assert str(info.value) == (f"{run_name}: non-finite {what} {name!r} = nan at step 3; "
                               "training stopped, no model written")
    assert _lines(tmp_path / "steps.txt") == ["0", "1", "2", "3"]
    assert not (tmp_path / "out").exists()


def test_guard_on_an_accelerator_waits_for_the_next_log_row() -> None:
    """Off the CPU the guard reads nothing per step: a NaN shows in the window's mean at the log row,
    and only then are the kept steps read to name the first bad one."""
    guard, window = FiniteGuard("toy-run", torch.device("cuda")), _Window()  # CUDA never touched
    steps = [{"loss": 1.0, "grad_norm/net": 0.5}, {"loss": 2.0, "grad_norm/net": float("inf")},
             {"loss": float("nan"), "grad_norm/net": 0.5}]
    for step, values in enumerate(steps):
        metrics = {name: torch.tensor(value) for name, value in values.items()}
        guard.add(step, metrics)  # no error yet: nothing is read
        window.add(metrics)
    with pytest.raises(TrainingError, match=r"^toy-run: non-finite gradient norm 'grad_norm/net' = inf at step 1;"):
        guard.check(window.pop(), step=3)
    guard.add(3, {"loss": torch.tensor(1.0)})
    guard.check({"loss": 1.0}, step=4)  # the bad window is gone: a good one passes
    guard.add(4, {"loss": torch.tensor(3e38)})
    guard.add(5, {"loss": torch.tensor(3e38)})
    with pytest.raises(TrainingError, match=r"^toy-run: the mean of 'loss' over the steps up to step 6 is inf"):
        guard.check({"loss": float("inf")}, step=6)  # finite steps whose sum overflowed


class _FakeTrainer:
    """A trainer whose fit() raises the next of ``errors`` (a Ray worker-group error) or returns "done"."""

    def __init__(self, errors: list[BaseException], calls: list[int]) -> None:
        self.errors, self.calls = errors, calls

    def fit(self) -> str:
        self.calls.append(1)
        if self.errors:
            raise self.errors.pop(0)
        return "done"


def _worker_error(exc: BaseException) -> BaseException:
    """What Ray Train 2.x hands the driver when a worker raises ``exc``."""
    from ray.train import WorkerGroupError
    from ray.train.v2._internal.exceptions import UserExceptionWithTraceback

    return WorkerGroupError(f"rank 0: {exc!r}", {0: UserExceptionWithTraceback(exc, f"Traceback...\n{exc!r}")})


@pytest.mark.parametrize("error", [TrainingError("toy: non-finite loss"), ValueError("bad config key"),
                                   TypeError("str + int"), KeyError("lr"), FileNotFoundError("no such file")])
def test_deterministic_worker_errors_are_not_retried(error: BaseException) -> None:
    calls: list[int] = []
    errors = [_worker_error(error)]
    with pytest.raises(type(error)) as info:
        fit_retrying(lambda: _FakeTrainer(errors, calls), max_failures=2, run_name="toy-run")
    assert str(info.value) == str(error) and len(calls) == 1


def test_crashes_are_retried_up_to_max_failures(capsys: pytest.CaptureFixture[str]) -> None:
    from ray.train import WorkerGroupError

    calls: list[int] = []
    errors = [_worker_error(RuntimeError("worker died")) for _ in range(2)]
    assert fit_retrying(lambda: _FakeTrainer(errors, calls), max_failures=2, run_name="toy-run") == "done"
    assert len(calls) == 3
    first_note = capsys.readouterr().err.splitlines()[0]
    assert first_note == ("toy-run: worker failure 1 of at most 2 retried, resuming from the latest checkpoint "
                          "(rank 0: RuntimeError('worker died'))")
    calls.clear()
    errors = [_worker_error(RuntimeError("worker died")) for _ in range(3)]
    with pytest.raises(WorkerGroupError):
        fit_retrying(lambda: _FakeTrainer(errors, calls), max_failures=2, run_name="toy-run")
    assert len(calls) == 3
    calls.clear()  # -1: no limit
    capsys.readouterr()
    errors = [_worker_error(RuntimeError("worker died")) for _ in range(4)]
    assert fit_retrying(lambda: _FakeTrainer(errors, calls), max_failures=-1, run_name="toy-run") == "done"
    assert len(calls) == 5 and capsys.readouterr().err.splitlines()[0].startswith(
        "toy-run: worker failure 1 (no limit) retried, resuming")


def _batch_spread(batches: np.ndarray, lengths: np.ndarray) -> float:
    """Mean padding per item of length-trimmed batches (longest minus mean length)."""
    return float(np.mean([lengths[b].max() - lengths[b].mean() for b in batches]))


def test_length_buckets_group_similar_lengths_and_keep_the_epochs_items() -> None:
    rng = np.random.default_rng(0)
    lengths = rng.integers(40, 197, size=300)
    indices = [int(i) for i in rng.permutation(300)]
    n = 300 // 16 * 16
    order = bucket_by_length(indices, lengths, batch_size=16, pool_batches=4, seed=1)
    assert sorted(order) == sorted(indices[:n])  # the same items as the sampler's full batches
    batches = np.array(order).reshape(-1, 16)
    pools = [set(indices[i:i + 64]) for i in range(0, n, 64)]
    assert all(any(set(b.tolist()) <= pool for pool in pools) for b in batches)  # each from one pool
    random_batches = np.array(indices[:n]).reshape(-1, 16)
    assert _batch_spread(batches, lengths) < 0.4 * _batch_spread(random_batches, lengths)
    assert order == bucket_by_length(indices, lengths, 16, 4, seed=1)
    assert order != bucket_by_length(indices, lengths, 16, 4, seed=2)
    # one batch per pool: exactly the sampler's batches, each sorted, in a shuffled order
    single = np.array(bucket_by_length(indices, lengths, 16, 1, seed=1)).reshape(-1, 16)
    assert sorted(sorted(b) for b in single.tolist()) == sorted(sorted(b) for b in random_batches.tolist())
    with pytest.raises(ValueError, match="length_buckets"):
        bucket_by_length(indices, lengths, 16, 0, seed=1)


def test_bucketed_epoch_resumes_mid_epoch_in_the_same_order() -> None:
    """A loader restarted at batch k of an epoch serves exactly batches k.. of the whole epoch."""
    data = dataset({})
    data.lengths = np.random.default_rng(5).integers(1, 100, size=len(data))
    settings = LoopSettings(seed=3, batch_size=16, length_buckets=4)
    session = SimpleNamespace(rank=0, world_size=1)
    full = list(_epoch_batches(data, SPEC, settings, session, Position(epoch=2, batch=0)))
    tail = list(_epoch_batches(data, SPEC, settings, session, Position(epoch=2, batch=5)))
    assert len(full) == 16 and len(tail) == 11
    assert all(torch.equal(a[0], b[0]) for a, b in zip(full[5:], tail, strict=True))
    other_epoch = list(_epoch_batches(data, SPEC, settings, session, Position(epoch=3, batch=0)))
    assert not torch.equal(full[0][0], other_epoch[0][0])
    with pytest.raises(ValueError, match="lengths"):
        _epoch_batches(dataset({}), SPEC, settings, session, Position())


class _DrawingDataset(Dataset):
    """Items ``[index, a draw of the loading process's torch RNG]``, as a caption or crop choice is."""

    def __len__(self) -> int:
        return 64

    def __getitem__(self, index: int) -> torch.Tensor:
        return torch.tensor([float(index), float(torch.rand(()))])


def test_an_epoch_resumed_with_data_workers_draws_what_the_whole_epoch_drew() -> None:
    """With ``num_data_workers`` > 0 the draws come from each worker's RNG, seeded afresh with each loader; a
    loader started at batch 5 gave its batches to other workers in other states (the whole run drifted after
    a restart). The resumed epoch replays the first batches, so batches 5.. are the whole epoch's."""
    settings = LoopSettings(seed=3, batch_size=4, num_data_workers=2)
    session = SimpleNamespace(rank=0, world_size=1)
    full = list(_epoch_batches(_DrawingDataset(), SPEC, settings, session, Position(epoch=1, batch=0)))
    tail = list(_epoch_batches(_DrawingDataset(), SPEC, settings, session, Position(epoch=1, batch=5)))
    assert len(full) == 16 and len(tail) == 11
    assert all(torch.equal(a, b) for a, b in zip(full[5:], tail, strict=True))
    draws = torch.cat(full)[:, 1]
    assert len(set(draws.tolist())) == len(draws)  # the draws are random, so equality is not by accident


#: A valid loop params group (cosine; 1200 steps).
LOOP_GROUP = {"seed": 0, "batch_size": 16, "max_steps": 1200, "grad_clip": 0.0, "lr_schedule": "cosine",
              "warmup_steps": 0, "min_lr_ratio": 0.0, "log_every": 50, "num_data_workers": 0, "length_buckets": 0}
INT64_MAX = 2**63 - 1
SEED_ERROR = ("x.loop.seed: expected an integer >= 0 and <= {top} (with max_steps 1200, so that every epoch seed "
              "(seed*1000003 + epoch)*1024 + rank stays within int64), got {seed}")


def test_largest_allowed_seed_keeps_every_epoch_seed_within_int64() -> None:
    """The loop check bounds the seed so that the last epoch's seed of the last rank fits int64 (torch and
    numpy seeds); the next seed would not, and is refused naming the key and the bound."""
    top = max_seed(1200)
    assert top == (2**53 - 1 - 1200) // 1_000_003 == 9_007_172_233
    assert LoopSettings.parse(LOOP_GROUP | {"seed": top}, "x.loop").seed == top
    assert epoch_seed(top, 1200, 1023) <= INT64_MAX < epoch_seed(top + 1, 1200, 1023)
    assert epoch_seed(top, 0, 0) == top * 1_000_003 * 1024  # the formula every trained artefact was seeded with
    # through the runner's loader: the last rank of 1024, at epoch max_steps, bucketed (numpy) and torch-seeded
    data = TensorDataset(torch.arange(1024 * 16.0))
    data.lengths = np.random.default_rng(0).integers(1, 100, size=len(data))
    settings = LoopSettings(seed=top, batch_size=16, max_steps=1200, length_buckets=1)
    [batch] = list(_epoch_batches(data, SPEC, settings, SimpleNamespace(rank=1023, world_size=1024),
                                 Position(step=1199, epoch=1200)))
    assert batch[0].shape == (16,)
    with pytest.raises(ConfigError) as info:
        LoopSettings.parse(LOOP_GROUP | {"seed": top + 1}, "x.loop")
    assert str(info.value) == SEED_ERROR.format(top=top, seed=top + 1)


def test_a_constant_schedule_refuses_a_warm_up_it_would_ignore() -> None:
    constant = LOOP_GROUP | {"lr_schedule": "constant"}
    assert LoopSettings.parse(constant, "x.loop").lr_schedule == "constant"
    assert LoopSettings.parse(LOOP_GROUP | {"warmup_steps": 50}, "x.loop").warmup_steps == 50  # cosine warms up
    with pytest.raises(ConfigError) as info:
        LoopSettings.parse(constant | {"warmup_steps": 50}, "train_vae.loop")
    assert str(info.value) == ("train_vae.loop.warmup_steps: 50 has no effect with lr_schedule constant; "
                               "expected 0 (or lr_schedule cosine)")
    with pytest.raises(ConfigError) as info:  # a floor it would ignore too
        LoopSettings.parse(constant | {"min_lr_ratio": 0.1}, "x.loop")
    assert str(info.value) == ("x.loop.min_lr_ratio: 0.1 has no effect with lr_schedule constant; expected 0 (or "
                               "lr_schedule cosine)")
    with pytest.raises(ConfigError) as info, every_problem():  # a stage's checks list both, one line each
        LoopSettings.parse(constant | {"warmup_steps": 1, "seed": max_seed(1200) + 1}, "x.loop")
    assert str(info.value).splitlines() == [
        SEED_ERROR.format(top=max_seed(1200), seed=max_seed(1200) + 1),
        "x.loop.warmup_steps: 1 has no effect with lr_schedule constant; expected 0 (or lr_schedule cosine)"]


def test_changed_params_give_a_fresh_run_name() -> None:
    """Same params -> same name (resume); changed params or world size -> new name."""
    name = make_run_name(STAGE, BASE, 1)
    assert name == make_run_name(STAGE, dict(reversed(BASE.items())), 1)
    assert name != make_run_name(STAGE, {**BASE, "lr": 2e-2}, 1)
    assert name != make_run_name(STAGE, BASE, 2)
    assert name.startswith(f"{STAGE}-")


def test_gpu_decision_never_hangs() -> None:
    """auto -> GPUs only if there is one per worker; an impossible True raises."""
    assert decide_use_gpu("auto", 1, {"CPU": 2}) is False
    assert decide_use_gpu("auto", 2, {"CPU": 2, "GPU": 2}) is True
    assert decide_use_gpu(False, 1, {"GPU": 1}) is False
    with pytest.raises(ValueError, match="wait forever"):
        decide_use_gpu(True, 2, {"GPU": 1})
    with pytest.raises(ValueError, match="unknown ray option"):
        RayOptions.from_dict({"num_worker": 1})


@pytest.mark.skipif(torch.cuda.is_available(), reason="the machine has a GPU")
def test_an_in_process_run_refuses_use_gpu_true_without_a_gpu(tmp_path: Path) -> None:
    opts = RayOptions.from_dict({"num_workers": 0, "use_gpu": True})
    with pytest.raises(ValueError, match="use_gpu=true but this machine has no CUDA GPU"):
        _fit_local(STAGE, SPEC, BASE, opts, str(tmp_path), None)


def test_wandb_runs_go_to_the_dvc_workspace(monkeypatch: pytest.MonkeyPatch) -> None:
    """W&B adds ``wandb/`` to its dir: runs land in the workspace's ``wandb/`` (``$DVC_ROOT`` under
    ``dvc exp run --temp``, whose checkout is deleted), a shared storage's, or ``$WANDB_DIR``."""
    monkeypatch.delenv("WANDB_DIR", raising=False)
    monkeypatch.delenv("DVC_ROOT", raising=False)
    assert default_wandb_dir(str(CHECKOUT / ".ray_storage")) == str(CHECKOUT)
    assert default_wandb_dir("s3://bucket/runs") == str(CHECKOUT)
    assert default_wandb_dir("/shared/ray_storage") == "/shared/ray_storage"
    monkeypatch.setenv("DVC_ROOT", "/work/repo")  # as DVC sets it in .dvc/tmp/exps/<tmp>/ copies
    assert default_wandb_dir(str(CHECKOUT / ".ray_storage")) == "/work/repo"
    monkeypatch.setenv("WANDB_DIR", "/elsewhere")
    assert default_wandb_dir(str(CHECKOUT / ".ray_storage")) == "/elsewhere"


def test_cosine_warmup_and_ema() -> None:
    """Linear warm-up to the base LR, cosine down to min_ratio; EMA moves by 1 - decay."""
    sched = CosineWarmup(warmup_steps=4, total_steps=14, min_ratio=0.1)
    assert [sched(i) for i in range(4)] == [0.25, 0.5, 0.75, 1.0]
    assert sched(9) == pytest.approx(0.55) and sched(14) == pytest.approx(0.1) == sched(100)
    net = nn.Linear(2, 1)
    ema = EMA(net, decay=0.75)
    with torch.no_grad():
        before = ema.module.weight.clone()
        net.weight.add_(4.0)
    ema.update(net)
    assert torch.allclose(ema.module.weight, before + 1.0)
    assert not ema.module.weight.requires_grad


# --------------------------------------------------------------------------- Ray Train


def test_ray_one_worker_matches_in_process(ray_cluster: Any, reference: RunResult, tmp_path: Path) -> None:
    """A 1-worker Ray Train run is bit-identical to the in-process run."""
    result = run_training(STAGE, SPEC, BASE, RAY1, tmp_path / "out", str(tmp_path / "storage"))
    assert result.run_name == reference.run_name and result.attempts == [0]
    assert result.run_path == str(tmp_path / "storage" / result.run_name)
    assert_bit_identical(reference.out_dir, result.out_dir)


def test_exact_resume_after_worker_failure(ray_cluster: Any, reference: RunResult, tmp_path: Path) -> None:
    """The worker raises once at step 25; Ray restarts from step 20 and ends identical."""
    cfg = {**BASE, "fail_at_step": 25, "fail_marker": str(tmp_path / "failed.marker")}
    result = run_training(STAGE, SPEC, cfg, RAY1, tmp_path / "out", str(tmp_path / "storage"))
    assert (tmp_path / "failed.marker").exists()
    assert result.attempts == [0, 20]
    assert_bit_identical(reference.out_dir, result.out_dir)


def test_ray_nan_loss_fails_once_without_retry(ray_cluster: Any, tmp_path: Path) -> None:
    """Through Ray Train with max_failures=2: one attempt, the worker's one-line error, no outputs."""
    cfg = {**BASE, "nan_loss_at": 3, "attempts_file": str(tmp_path / "attempts.txt")}
    with pytest.raises(TrainingError) as info:
        run_training(STAGE, SPEC, cfg, RAY1, tmp_path / "out", str(tmp_path / "storage"))
    assert str(info.value) == (f"{make_run_name(STAGE, cfg, 1)}: non-finite loss 'loss' = nan at step 3; "
                               "training stopped, no model written")
    assert _lines(tmp_path / "attempts.txt") == ["attempt"]
    assert not (tmp_path / "out").exists()


DRIVER = textwrap.dedent("""
    import json, sys
    from pathlib import Path
    sys.path[:0] = [{tests!r}, {repo!r}]
    import test_runner as t
    from pipelines.runner import run_training
    cfg, ray_cfg, out, storage = json.loads(sys.argv[1]), json.loads(sys.argv[2]), sys.argv[3], sys.argv[4]
    run_training(t.STAGE, t.SPEC, cfg, ray_cfg, Path(out), storage)
""")


def _wait_for_checkpoint(run_dir: Path, proc: subprocess.Popen, timeout: float = 60.0) -> None:
    """Block until Ray's snapshot in ``run_dir`` lists a checkpoint."""
    deadline = time.monotonic() + timeout
    snapshot = run_dir / "checkpoint_manager_snapshot.json"
    while time.monotonic() < deadline:
        assert proc.poll() is None, f"driver exited early with {proc.returncode}"
        try:
            if json.loads(snapshot.read_text())["checkpoint_results"]:
                return
        except (FileNotFoundError, json.JSONDecodeError, KeyError):
            pass
        time.sleep(0.05)
    raise TimeoutError(f"no checkpoint in {run_dir} after {timeout} s")


def _wait_for_free_cpus(total: float, timeout: float = 30.0) -> None:
    """Block until the killed driver's workers have released their CPUs."""
    import ray

    deadline = time.monotonic() + timeout
    while ray.available_resources().get("CPU", 0) < total and time.monotonic() < deadline:
        time.sleep(0.1)


def test_exact_resume_after_driver_sigkill(ray_cluster: Any, reference: RunResult, tmp_path: Path) -> None:
    """SIGKILL the driver after the first checkpoint; starting it again resumes exactly."""
    import ray

    storage, out = tmp_path / "storage", tmp_path / "out"
    cfg = {**BASE, "step_sleep": 0.05}
    ray_cfg = {**RAY1, "address": ray_cluster.address}
    script = tmp_path / "driver.py"
    script.write_text(DRIVER.format(tests=str(TESTS_DIR), repo=str(REPO)))
    proc = subprocess.Popen([sys.executable, str(script), json.dumps(cfg), json.dumps(ray_cfg), str(out),
                             str(storage)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        _wait_for_checkpoint(storage / make_run_name(STAGE, cfg, 1), proc)
        children = psutil.Process(proc.pid).children(recursive=True)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
    for child in children:  # orphans of the killed driver, by pid
        if child.is_running():
            child.kill()
    assert not out.exists(), "a killed stage must not leave an out dir"
    _wait_for_free_cpus(ray.cluster_resources()["CPU"])

    result = run_training(STAGE, SPEC, cfg, RAY1, out, str(storage))
    assert result.attempts[0] == 0 and result.attempts[-1] > 0, result.attempts
    assert_bit_identical(reference.out_dir, result.out_dir)


def test_two_node_cluster_run(ray_cluster: Any, tmp_path: Path) -> None:
    """Two workers SPREAD over the two simulated nodes train, checkpoint and export."""
    nodes_dir = tmp_path / "nodes"
    nodes_dir.mkdir()
    cfg = {**BASE, "max_steps": 20, "nodes_dir": str(nodes_dir)}
    ray_cfg = {"num_workers": 2, "checkpoint_every": 10, "placement_strategy": "SPREAD"}
    result = run_training(STAGE, SPEC, cfg, ray_cfg, tmp_path / "out", str(tmp_path / "storage"))
    node_ids = {p.read_text() for p in nodes_dir.iterdir()}
    assert len(node_ids) == 2, "workers did not land on two nodes"
    assert result.metrics["step"] == 20 and (tmp_path / "out" / "model.pt").exists()
    latest = sorted(p for p in Path(result.run_path).glob("checkpoint_*") if p.is_dir())[-1]
    assert {STATE_FILE, rng_file(0), rng_file(1)} <= {p.name for p in latest.iterdir()}


def test_without_ddp_two_workers_train_what_ddp_trains(ray_cluster: Any, tmp_path: Path) -> None:
    """A spec with ``ddp=False`` (EMDM's: R1 backpropagates twice) keeps its models unwrapped, and
    ``ctx.update`` averages the gradients over the workers: the same weights as DDP's, bit for bit
    (with two ranks, (a + b) / 2 and a / 2 + b / 2 round alike), and not one worker's."""
    cfg = {**BASE, "max_steps": 12}
    two = {"num_workers": 2, "checkpoint_every": 12}
    ddp = run_training(STAGE, SPEC, cfg, two, tmp_path / "ddp", str(tmp_path / "s_ddp"))
    averaged = run_training(STAGE, replace(SPEC, ddp=False), cfg, two, tmp_path / "avg", str(tmp_path / "s_avg"))
    assert_bit_identical(ddp.out_dir, averaged.out_dir)
    one = run_training(STAGE, replace(SPEC, ddp=False), cfg, {**two, "num_workers": 1}, tmp_path / "one",
                       str(tmp_path / "s_one"))
    first_layer = "models.net.0.weight"
    assert not torch.equal(weights(one.out_dir)[first_layer], weights(averaged.out_dir)[first_layer])
