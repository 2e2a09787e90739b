"""Ray Tune sweeps (pipelines/sweep.py, stages/sweep.py): the search-space parser, the concurrency
arithmetic, the outcome checks, and a smoke sweep of the evaluator on a tiny feature store.

The smoke sweep runs on the session's two-node simulated cluster (2 x 2 logical CPUs): a grid
of four matching-run learning rates under ASHA, one of them (-1) rejected by Adam. It is
interrupted (SIGINT, as Ctrl+C) after its first finished trial, exits non-zero without
outputs, and the same command then resumes and finishes it.
"""

from __future__ import annotations

import copy
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import asdict, replace
from functools import partial
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest
import ray
import torch
import yaml
from ray import tune
from ray.util.placement_group import placement_group, remove_placement_group
from torch.utils.data import TensorDataset

from data.store import StoredItem, write_split
from pipelines.config import REPO_ROOT, apply_overrides, compose_params
from pipelines.runner import Components, LoopSettings, StepContext, TrainSpec, run_training
from pipelines.sweep import (
    COMPLETED,
    ERROR,
    STOPPED,
    UNFINISHED,
    Dimension,
    PlacementGroupJanitor,
    SweepConfigError,
    SweepFailed,
    SweepInterrupted,
    SweepSettings,
    SweepTarget,
    apply_trial,
    best_row,
    check_outcome,
    check_space_values,
    dimension_values,
    expected_trials,
    experiment_name,
    fit_concurrency,
    max_concurrent,
    nest_keys,
    orphaned_placement_groups,
    parse_dimension,
    parse_space,
    ranking_settings,
    run_sweep,
    short_error,
    trial_ray_options,
    trial_status,
)

# Ray workers cannot import this module (tests/ is on sys.path only here): ship its code by value.
ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])

FIXTURES = Path(__file__).parent / "fixtures" / "humanml3d"
STAGE = "train_evaluator"

# --------------------------------------------------------------------------- a toy target


def toy_build(cfg: dict) -> Components:
    """One weight w, from 0, by SGD at the trial's ``lr``."""
    w = torch.nn.Linear(1, 1, bias=False)
    torch.nn.init.zeros_(w.weight)
    return Components({"w": w}, {"sgd": torch.optim.SGD(w.parameters(), lr=cfg["lr"])})


def toy_dataset(cfg: dict) -> TensorDataset:
    return TensorDataset(torch.ones(8, 1))


def toy_step(batch: Any, ctx: StepContext) -> dict[str, torch.Tensor]:
    """Training loss (w - 1)^2: the larger lr, the lower."""
    (x,) = batch
    loss = ((ctx.models["w"](x) - 1.0) ** 2).mean()
    ctx.update(loss)
    return {"loss": loss.detach()}


def toy_loop_config(params: dict) -> dict:
    return asdict(LoopSettings.parse(params["toy"]["loop"], "toy.loop")) | {"lr": params["toy"]["lr"]}


def toy_validate(params: dict, loop_config: dict, state: dict) -> dict[str, float]:
    """Validation error (w + 1)^2: disagrees with the training loss (the smaller lr, the lower)."""
    return {"val_error": (float(state["models"]["w"]["weight"].item()) + 1.0) ** 2}


def toy_prerequisite(params: dict, work_dir: Path, storage: str) -> dict:
    Path(params["toy"]["marker"]).touch()
    return {}


TOY_SPEC = TrainSpec(build=toy_build, dataset=toy_dataset, step=toy_step)


def toy_target(params: dict) -> SweepTarget:
    return SweepTarget(stage="toy", spec=TOY_SPEC, loop_config=toy_loop_config, prerequisite=toy_prerequisite,
                       validate=toy_validate, metric="val_error", mode="min")


def toy_params(tmp: Path) -> dict[str, Any]:
    """Two trials (lr 0.001 and 0.1, 20 steps, both at once) of 1 worker x 1 CPU."""
    loop = {"seed": 0, "batch_size": 8, "max_steps": 20, "grad_clip": 0.0, "lr_schedule": "constant",
            "warmup_steps": 0, "min_lr_ratio": 0.0, "log_every": 1000, "num_data_workers": 0, "length_buckets": 0}
    return {
        "toy": {"lr": 0.01, "marker": str(tmp / "prerequisite-ran"), "loop": loop},
        "paths": {"artifacts": str(tmp / "artifacts"), "ray_storage": str(tmp / "ray")},
        "ray": {"num_workers": 1, "cpus_per_worker": 1, "max_failures": 0, "checkpoint_every": 1000},
        "sweep": {"settings": {"num_samples": 1, "scheduler": "fifo", "max_concurrent_trials": 2},
                  "toy": {"lr": "grid([0.001, 0.1])"}},
    }

# --------------------------------------------------------------------------- parser


@pytest.mark.parametrize(("spec", "expected"), [
    ("loguniform(1e-5, 1e-3)", Dimension("loguniform", (1e-5, 1e-3))),
    ("uniform(5, 15)", Dimension("uniform", (5, 15))),
    ("  uniform( -1.5 ,2 ) ", Dimension("uniform", (-1.5, 2))),
    ("randint(0, 100)", Dimension("randint", (0, 100))),
    ("choice([16, 32])", Dimension("choice", ([16, 32],))),
    ("choice(['cosine', 'constant'])", Dimension("choice", (["cosine", "constant"],))),
    ("grid([0.1, 1, True])", Dimension("grid", ([0.1, 1, True],))),
    ("grid_search([1, 2])", Dimension("grid", ([1, 2],))),
    (0.5, Dimension("fixed", (0.5,))),
    (False, Dimension("fixed", (False,))),
    (None, None),
])
def test_parser_known_answers(spec: Any, expected: Dimension | None) -> None:
    assert parse_dimension("sweep.s.k", spec) == expected


def test_dimensions_map_to_tune_domains() -> None:
    from ray.tune.search.sample import Categorical, Float, Integer, LogUniform

    lr = parse_dimension("k", "loguniform(1e-5, 1e-3)").to_tune()
    assert isinstance(lr, Float) and isinstance(lr.sampler, LogUniform) and (lr.lower, lr.upper) == (1e-5, 1e-3)
    steps = parse_dimension("k", "randint(1, 4)").to_tune()
    assert isinstance(steps, Integer) and (steps.lower, steps.upper) == (1, 4)
    assert parse_dimension("k", "choice([16, 32])").to_tune().categories == [16, 32]
    assert isinstance(parse_dimension("k", "choice([16, 32])").to_tune(), Categorical)
    assert parse_dimension("k", "grid([1, 2])").to_tune() == {"grid_search": [1, 2]}
    assert parse_dimension("k", 3).to_tune() == 3


@pytest.mark.parametrize(("spec", "message"), [
    ("loguniform(0, 1)", "low > 0"),
    ("uniform(2, 1)", "low < high"),
    ("uniform(1)", "two numbers"),
    ("uniform('a', 'b')", "two numbers"),
    ("randint(0.5, 3)", "two integers"),
    ("choice(16, 32)", "one non-empty list"),
    ("choice([])", "one non-empty list"),
    ("normal(0, 1)", "unknown kind 'normal'"),
    ("uniform(1, __import__('os'))", "literals only"),
    ("uniform(1,", "not of the form"),
    ("1e-3", "not of the form"),
    ("fast", "not of the form"),
    ([16, 32], "expected a string"),
])
def test_parser_errors_name_the_key(spec: Any, message: str) -> None:
    with pytest.raises(SweepConfigError, match=message) as err:
        parse_dimension("sweep.train_evaluator.lr", spec)
    assert str(err.value).startswith("sweep.train_evaluator.lr:")


def test_space_keys_must_be_stage_params_and_something_must_vary() -> None:
    stage_params = {"lr": 1e-3, "batch_size": 32, "seed": 0}
    space = parse_space("s", {"lr": "uniform(0.1, 1)", "seed": 3, "batch_size": None}, stage_params)
    assert space == {"lr": Dimension("uniform", (0.1, 1)), "seed": Dimension("fixed", (3,))}
    with pytest.raises(SweepConfigError, match="sweep.s.lrr: 'lrr' is not a key"):
        parse_space("s", {"lrr": "uniform(0.1, 1)"}, stage_params)
    with pytest.raises(SweepConfigError, match="nothing to vary"):
        parse_space("s", {"seed": 1}, stage_params)
    grouped = {"lr": 1e-3, "loop": {"batch_size": 32, "seed": 0}}
    space = parse_space("s", {"loop.batch_size": "choice([8, 16])"}, grouped)
    assert space == {"loop.batch_size": Dimension("choice", ([8, 16],))}
    with pytest.raises(SweepConfigError, match="'loop.batch' is not a key"):
        parse_space("s", {"loop.batch": "choice([8, 16])"}, grouped)
    params = {"s": grouped, "other": {"x": 1}}
    applied = apply_trial(params, "s", {"loop.batch_size": 8, "lr": 0.1})
    assert applied == {"s": {"lr": 0.1, "loop": {"batch_size": 8, "seed": 0}}, "other": {"x": 1}}
    assert params["s"]["loop"]["batch_size"] == 32  # the caller's params are not changed
    with pytest.raises(SweepConfigError, match="expected a mapping"):
        parse_space("s", None, stage_params)


def test_expected_trials_multiplies_grids_by_samples() -> None:
    space = {"a": Dimension("grid", ([1, 2, 3],)), "b": Dimension("grid", ([0, 1],)),
             "c": Dimension("uniform", (0, 1))}
    assert expected_trials(space, 2) == 12
    assert expected_trials({"c": Dimension("uniform", (0, 1))}, 5) == 5


# --------------------------------------------------------------------------- settings and arithmetic


def test_settings_validation() -> None:
    assert SweepSettings.from_dict({"num_samples": 3}).num_samples == 3
    with pytest.raises(SweepConfigError, match="unknown key"):
        SweepSettings.from_dict({"num_sample": 3})
    bad = [({"trial_cpus": 0}, "sweep.settings.trial_cpus: expected a number > 0, got 0"),
           ({"mode": "low"}, "sweep.settings.mode: expected one of [None, 'min', 'max'], got 'low'"),
           ({"num_samples": "abc"}, "sweep.settings.num_samples: expected an integer >= 1, got 'abc'"),
           ({"num_samples": 2.5}, "sweep.settings.num_samples: expected an integer >= 1, got 2.5"),
           ({"grace_period": 30, "max_t": 24}, "sweep.settings.grace_period: expected an integer >= 1 and <= 24, "
                                               "got 30"),
           ({"seed": "abc"}, "sweep.settings.seed: expected an integer >= 0, got 'abc'"),
           ({"max_concurrent_trials": 0}, "sweep.settings.max_concurrent_trials: expected an integer >= 1, got 0")]
    for settings, message in bad:
        with pytest.raises(SweepConfigError) as err:
            SweepSettings.from_dict(settings)
        assert str(err.value) == message


def test_committed_params_declare_valid_sweeps_ranked_by_validation() -> None:
    import stages.distill_lcm
    import stages.train_emdm
    import stages.train_evaluator
    import stages.train_vae

    params = compose_params()
    settings = SweepSettings.from_dict(params["sweep"]["settings"])
    assert (settings.metric, settings.mode) == (None, None)  # each stage's own
    for stage in (STAGE, "train_vae", "distill_lcm", "train_emdm"):
        assert parse_space(stage, params["sweep"][stage], params[stage])
    for module, metric, mode in ((stages.train_vae, "val_MPJPE_mm", "min"), (stages.distill_lcm, "val_FID", "min"),
                                 (stages.train_emdm, "val_FID", "min"),
                                 (stages.train_evaluator, "val_R_precision_top3", "max")):
        target = module.sweep_target(params)
        assert target.validate is not None and (target.metric, target.mode) == (metric, mode)


def test_nested_space_entries_are_dotted_keys_and_overridable() -> None:
    """``loop: {max_steps: 500}`` is the space key ``loop.max_steps``; the command line reaches it."""
    grouped = {"lr": 1e-3, "loop": {"batch_size": 32, "max_steps": 100}}
    nested = {"lr": "grid([0.1, 0.2])", "loop": {"max_steps": 500, "batch_size": None}}
    space = parse_space("s", nested, grouped)
    assert space == parse_space("s", {"lr": "grid([0.1, 0.2])", "loop.max_steps": 500}, grouped)
    assert nest_keys({"lr": 0.1, "loop.max_steps": 500, "loop.seed": 1}) == {"lr": 0.1,
                                                                              "loop": {"max_steps": 500, "seed": 1}}
    assert space == {"lr": Dimension("grid", ([0.1, 0.2],)), "loop.max_steps": Dimension("fixed", (500,))}
    with pytest.raises(SweepConfigError, match="'loop.steps' is not a key"):
        parse_space("s", {"lr": "uniform(0.1, 1)", "loop": {"steps": 5}}, grouped)
    params = apply_overrides(compose_params(), ["sweep.train_emdm.loop.max_steps=500",
                                                "sweep.train_emdm.num_steps=grid([1, 10])"])
    space = parse_space("train_emdm", params["sweep"]["train_emdm"], params["train_emdm"])
    assert space["loop.max_steps"] == Dimension("fixed", (500,))
    assert space["num_steps"] == Dimension("grid", ([1, 10],))
    composed = compose_params(["scale=smoke", "sweep.train_vae.loop.max_steps=7"])  # the Hydra path (dvc exp -S)
    assert parse_space("train_vae", composed["sweep"]["train_vae"], composed["train_vae"])["loop.max_steps"] == \
        Dimension("fixed", (7,))


@pytest.mark.parametrize(("cluster", "workers", "cpw", "gpw", "expected"), [
    ({"CPU": 4}, 1, 1, 0, 4),
    ({"CPU": 2}, 1, 2, 0, 1),           # the defaults on a 2-core laptop
    ({"CPU": 2}, 2, 0.5, 0, 2),
    ({"CPU": 16}, 2, 2, 0, 4),
    ({"CPU": 3.0000000001}, 1, 1, 0, 3),
    ({"CPU": 2.9999999999}, 1, 1, 0, 3),  # exact fit despite float rounding
    ({"CPU": 64, "GPU": 4}, 2, 1, 1, 2),  # GPUs bind first
])
def test_max_concurrent_fits_the_cluster(cluster: dict, workers: int, cpw: float, gpw: float, expected: int) -> None:
    assert fit_concurrency(cluster, workers, cpw, gpw) == expected


def test_a_trial_that_can_never_fit_is_a_config_error() -> None:
    with pytest.raises(SweepConfigError) as err:
        fit_concurrency({"CPU": 2}, 2, 2)
    assert str(err.value) == ("one trial needs 4 CPUs (ray.num_workers=2 x ray.cpus_per_worker=2) and 0 GPUs; "
                              "the cluster has 2 CPUs and 0 GPUs")
    with pytest.raises(SweepConfigError, match="and 1 GPUs; the cluster has 8 CPUs and 0 GPUs"):
        fit_concurrency({"CPU": 8}, 1, 1, gpus_per_worker=1)


def test_the_trial_driver_shares_its_workers_cpus() -> None:
    """A trial takes num_workers x cpus_per_worker in all: 2-CPU trials fit a 2-CPU machine."""
    settings = SweepSettings(trial_cpus=0.01, report_every=7)
    opts = trial_ray_options({"ray": {"num_workers": 1, "cpus_per_worker": 2}}, settings)
    assert opts.cpus_per_worker == pytest.approx(1.99) and opts.report_every == 7
    assert opts.num_workers * opts.cpus_per_worker + settings.trial_cpus == pytest.approx(2.0)
    assert round(opts.cpus_per_worker) == 2  # the workers' torch threads (pipelines.runner._run_info)
    two = trial_ray_options({"ray": {"num_workers": 2, "cpus_per_worker": 1}}, settings)
    assert two.cpus_per_worker == pytest.approx(0.995)
    in_process = trial_ray_options({"ray": {"num_workers": 0, "cpus_per_worker": 2}}, settings)
    assert in_process.num_workers == 1 and not in_process.in_process
    with pytest.raises(SweepConfigError) as err:
        trial_ray_options({"ray": {"num_workers": 1, "cpus_per_worker": 0.5}}, SweepSettings(trial_cpus=0.5))
    assert str(err.value) == ("sweep.settings.trial_cpus=0.5 must be smaller than ray.cpus_per_worker=0.5 "
                              "(it comes out of the workers' share)")


def test_trials_are_ranked_by_the_targets_metric_unless_settings_name_one() -> None:
    target = SweepTarget(stage="toy", spec=TOY_SPEC, loop_config=toy_loop_config, validate=toy_validate,
                         metric="val_error", mode="min")
    resolved = ranking_settings(SweepSettings(), target)
    assert (resolved.metric, resolved.mode) == ("val_error", "min")
    chosen = ranking_settings(SweepSettings(metric="loss", mode="max"), target)
    assert (chosen.metric, chosen.mode) == ("loss", "max")
    with pytest.raises(SweepConfigError, match=r"metric='loss': give sweep.settings.mode too"):
        ranking_settings(SweepSettings(metric="loss"), target)  # not val_error's min, silently
    assert ranking_settings(SweepSettings(metric="val_error"), target).mode == "min"
    plain = SweepTarget(stage="toy", spec=TOY_SPEC, loop_config=toy_loop_config)
    assert (ranking_settings(SweepSettings(), plain).metric, plain.mode) == ("loss", "min")


def test_experiment_name_is_stable_and_tracks_space_settings_and_params() -> None:
    space = {"lr": Dimension("uniform", (0.1, 1))}
    settings = SweepSettings()
    name = experiment_name(STAGE, space, settings, {"lr": 1})
    assert name.startswith(f"sweep-{STAGE}-") and name == experiment_name(STAGE, dict(space), settings, {"lr": 1})
    assert name != experiment_name(STAGE, {"lr": Dimension("uniform", (0.1, 2))}, settings, {"lr": 1})
    assert name != experiment_name(STAGE, space, SweepSettings(num_samples=5), {"lr": 1})
    assert name != experiment_name(STAGE, space, settings, {"lr": 2})


# --------------------------------------------------------------------------- outcome checks


def _row(trial: str, status: str, loss: float | None) -> dict[str, Any]:
    return {"trial_id": trial, "status": status, "lr": 0.1, "loss": loss, "iterations": 1, "error": ""}


def test_outcome_checks() -> None:
    rows = [_row("a", COMPLETED, 2.0), _row("b", STOPPED, 1.5), _row("c", ERROR, None)]
    check_outcome(rows, 3)
    assert best_row(rows, "loss", "min")["trial_id"] == "b"
    assert best_row(rows, "loss", "max")["trial_id"] == "a"
    with pytest.raises(SweepInterrupted, match="1 of 3"):
        check_outcome([*rows[:2], _row("c", UNFINISHED, None)], 3)
    with pytest.raises(SweepInterrupted, match="2 of 4"):
        check_outcome(rows[:2], 4)  # trials never generated
    with pytest.raises(SweepFailed, match="all 2"):
        check_outcome([_row("a", ERROR, None), _row("b", ERROR, None)], 2)


@pytest.mark.parametrize(("tune_status", "last", "expected"), [
    ("TERMINATED", {"step": 16, "planned_steps": 16}, COMPLETED),
    ("TERMINATED", {"step": 4, "planned_steps": 16}, STOPPED),  # stopped by ASHA
    ("TERMINATED", {}, ERROR),  # ended without reporting
    ("ERROR", {"step": 4, "planned_steps": 16}, ERROR),
    ("RUNNING", {"step": 4, "planned_steps": 16}, UNFINISHED),  # as saved when the sweep was interrupted
    ("PENDING", {}, UNFINISHED),
])
def test_trial_status_from_saved_state(tune_status: str, last: dict, expected: str) -> None:
    assert trial_status(tune_status, last) == expected


def test_short_error_picks_the_root_cause_line() -> None:
    error = RuntimeError("Traceback (most recent call last):\n  File x\nValueError: Invalid learning rate: -1.0\n")
    assert short_error(error) == "ValueError: Invalid learning rate: -1.0"
    assert short_error(None) == ""
    assert len(short_error(RuntimeError("x" * 1000), limit=50)) == 50


# --------------------------------------------------------------------------- smoke sweep


def _tokens(caption: str) -> list[str]:
    return [f"{word}/{'VERB' if word.endswith('s') else 'NOUN'}" for word in caption.split()]


def build_store(root: Path) -> Path:
    """A tiny feature store from the real fixture clip: 10 train crops (2 captions each) + Mean/Std."""
    features = np.load(FIXTURES / "new_joint_vecs_012314.npy").astype(np.float32)
    captions = ["a person walks forward", "someone steps ahead slowly", "a man kicks with the left leg",
                "the person turns around", "a figure jumps up"]
    items = []
    for k in range(10):
        start, length = 5 * k, 48 + 8 * (k % 4)
        texts = [captions[k % 5], captions[(k + 2) % 5]]
        items.append(StoredItem(f"{k:04d}", f"{k:04d}", "walk", 0, features[start:start + length], texts,
                                [_tokens(t) for t in texts], np.zeros((2, 4), np.float32),
                                [np.zeros((len(t.split()), 4), np.float32) for t in texts]))
    root.mkdir(parents=True)
    write_split(root / "train.parquet", items, features.shape[1], 4, 4)
    np.save(root / "mean.npy", np.load(FIXTURES / "Mean.npy"))
    np.save(root / "std.npy", np.load(FIXTURES / "Std.npy"))
    text_encoder = {"name": "test", "path": None, "max_length": 8, "dim": 4, "token_dim": 4}
    (root / "meta.json").write_text(json.dumps({"text_encoder": text_encoder}))
    return root


def smoke_params(tmp: Path) -> dict[str, Any]:
    """Smoke-profile params on the tiny store: 8 steps reported every 2 (4 iterations).

    Four trials, one at a time (on 2 cores concurrent Train start-ups only share the CPUs, and the
    order makes ASHA's decisions deterministic): lr -1 fails in Adam; 0.003 and 0.001 run to the
    end; 0.3 diverges (loss ~300 against ~50 after 2 steps) and is stopped at ASHA's first rung.
    """
    params = compose_params(["scale=smoke"])
    assert params[STAGE]["profile"] == "smoke"
    params["features"]["out"] = str(build_store(tmp / "features"))
    params["paths"].update(artifacts=str(tmp / "artifacts"), ray_storage=str(tmp / "ray"))
    params["ray"].update(max_failures=0, checkpoint_every=1000)
    params[STAGE]["movement_window"] = 16
    params[STAGE]["movement_loop"].update(batch_size=4, max_steps=4, log_every=1000)
    params[STAGE]["loop"].update(batch_size=4, max_steps=8, log_every=1000)
    params["sweep"]["settings"].update(num_samples=1, grace_period=1, reduction_factor=2, max_t=4, report_every=2,
                                       max_concurrent_trials=1)
    params["sweep"][STAGE] = {"lr": "grid([-1.0, 0.003, 0.001, 0.3])", "margin": 10.0, "loop.batch_size": None}
    return params


def test_evaluator_scores_rank_the_trials_own_validation_retrieval(tmp_path: Path) -> None:
    """``evaluator_scores`` rebuilds a trial's evaluator from its final state and scores its retrieval on
    the val split: reproducible, top 1 <= top 3, and a group larger than the split is an error naming it."""
    from models.evaluator import EvaluatorConfig
    from pipelines.evaluation import build_evaluator
    from pipelines.validation import evaluator_scores
    from stages.train_evaluator import matching_config

    params = smoke_params(tmp_path)
    store = Path(params["features"]["out"])
    (store / "val.parquet").write_bytes((store / "train.parquet").read_bytes())  # 10 items
    params["evaluate"]["group_size"] = 5
    config = matching_config(params)
    torch.manual_seed(0)
    evaluator = build_evaluator(EvaluatorConfig.from_dict(config["model"]), config["mean"], config["std"])
    state = {"models": {"evaluator": evaluator.state_dict()}}
    scores = evaluator_scores(params, config, state)
    assert set(scores) == {"val_R_precision_top1", "val_R_precision_top3"}
    assert scores == evaluator_scores(params, config, state)
    assert 0.0 <= scores["val_R_precision_top1"] <= scores["val_R_precision_top3"] <= 1.0
    with pytest.raises(RuntimeError, match="state_dict"):  # the trial's own weights, not a fresh model
        evaluator_scores(params, config, {"models": {"evaluator": {}}})
    params["evaluate"]["group_size"] = 32
    with pytest.raises(ValueError, match=r"larger than the val split \(10 items\)"):
        evaluator_scores(params, config, state)


def pretrain_movement_in_process(params: dict[str, Any]) -> None:
    """Write the sweep's prerequisite in-process (1-2 s instead of a Ray Train run); the sweep reuses it."""
    from pipelines.stage import loop_config
    from stages.train_evaluator import MOVEMENT

    out = Path(params["paths"]["artifacts"]) / "sweeps" / f"{STAGE}-prerequisites" / MOVEMENT.name
    run_training(MOVEMENT.name, MOVEMENT.spec, loop_config(MOVEMENT, params), {**params["ray"], "num_workers": 0},
                 out, params["paths"]["ray_storage"])


class InterruptOnce(tune.Callback):
    """Sends this process SIGINT when the first trial completes, once: Tune's graceful stop (as Ctrl+C)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def on_trial_complete(self, iteration: int, trials: list, trial: Any, **info: Any) -> None:
        if not self.marker.exists():
            self.marker.touch()
            os.kill(os.getpid(), signal.SIGINT)


def test_auto_concurrency_on_the_test_cluster(ray_cluster: Any) -> None:
    settings = SweepSettings()
    opts = trial_ray_options({"ray": {"num_workers": 1, "cpus_per_worker": 1}}, settings)
    assert max_concurrent(settings, opts) == 4  # 2 nodes x 2 CPUs / 1 (the driver's 0.01 included)
    assert max_concurrent(SweepSettings(max_concurrent_trials=2), opts) == 2
    big = trial_ray_options({"ray": {"num_workers": 1, "cpus_per_worker": 8}}, settings)
    with pytest.raises(SweepConfigError, match="the cluster has 4 CPUs"):
        max_concurrent(SweepSettings(max_concurrent_trials=1), big)  # checked whatever the setting


def cpus_freed(cluster: Any, timeout: float = 30.0) -> bool:
    """Wait until every logical CPU of the cluster is free again (no leaked placement group)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if ray.available_resources().get("CPU", 0) >= ray.cluster_resources().get("CPU", 0):
            return True
        time.sleep(0.2)
    return False


@ray.remote(num_cpus=0)
class _GroupMaker:
    def make(self) -> str:
        group = placement_group([{"CPU": 1}])
        ray.get(group.ready())
        return group.id.hex()


def test_janitor_removes_only_placement_groups_of_dead_actors(ray_cluster: Any) -> None:
    job = ray.get_runtime_context().get_job_id()
    own = placement_group([{"CPU": 1}])  # the driver's (like Tune's trial groups): kept
    ray.get(own.ready())
    maker = _GroupMaker.remote()
    orphan = ray.get(maker.make.remote())
    assert orphan not in orphaned_placement_groups(job)  # its creator is alive
    ray.kill(maker)
    deadline = time.monotonic() + 10
    while orphan not in orphaned_placement_groups(job) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert orphan in orphaned_placement_groups(job)
    PlacementGroupJanitor(interval_s=0).on_step_begin(0, [])
    assert orphan not in orphaned_placement_groups(job)
    assert ray.util.placement_group_table(own)["state"] == "CREATED"
    remove_placement_group(own)
    assert cpus_freed(ray_cluster)


def test_interrupted_smoke_sweep_resumes_and_writes_results(ray_cluster: Any, tmp_path: Path,
                                                            monkeypatch: pytest.MonkeyPatch,
                                                            capsys: pytest.CaptureFixture) -> None:
    import stages.train_evaluator
    from stages import sweep

    params = smoke_params(tmp_path)
    pretrain_movement_in_process(params)
    monkeypatch.setattr(sweep, "load_params", lambda argv: params)
    # Ranked by the training loss reported every 2 steps, so that ASHA has rungs to stop a trial at
    # (a validation metric is reported once, after training); validation ranking has its own tests.
    # Without the up-front value checks, the trial with lr -1 fails in training: a trial can fail in ways no
    # check sees (a bad combination of values, memory), and the failure must be a row of the table.
    by_loss = partial(replace, validate=None, metric="loss", mode="min", checks=())
    monkeypatch.setattr(sweep, "load_target", lambda name, p: by_loss(stages.train_evaluator.sweep_target(p)))
    monkeypatch.setattr(sweep, "run_sweep", partial(run_sweep, callbacks=[InterruptOnce(tmp_path / "interrupted")]))
    out = tmp_path / "artifacts" / "sweeps" / STAGE

    with pytest.raises(SystemExit) as exc:
        sweep.main([STAGE])
    assert "did not finish" in str(exc.value.code) and "run the same command again" in str(exc.value.code)
    assert not out.exists()

    sweep.main([STAGE])  # the same command resumes the experiment and finishes it
    assert "sweep: resuming" in capsys.readouterr().out

    table = pq.read_table(out / "results.parquet").to_pylist()
    by_lr = {row["lr"]: row for row in table}
    assert sorted(by_lr) == [-1.0, 0.001, 0.003, 0.3] and len(table) == 4
    assert by_lr[-1.0]["status"] == ERROR and "Invalid learning rate: -1.0" in by_lr[-1.0]["error"]
    assert [by_lr[lr]["status"] for lr in (0.003, 0.001, 0.3)] == [COMPLETED, COMPLETED, STOPPED]
    assert [by_lr[lr]["iterations"] for lr in (0.003, 0.001, 0.3)] == [4, 4, 1]
    scored = [row for row in table if row["status"] != ERROR]
    assert all(math.isfinite(row["loss"]) and not row["error"] for row in scored)

    winner = min(scored, key=lambda row: row["loss"])
    best_text = (out / "best_params.yaml").read_text()
    assert yaml.safe_load(best_text) == {STAGE: {"lr": winner["lr"]}}  # the varied key only
    assert "# Fixed for every trial, so not carried over: margin=10.0\n" in best_text
    assert [row["trial_id"] for row in table[:len(scored)]] == [row["trial_id"] for row in
                                                                sorted(scored, key=lambda row: row["loss"])]
    rows = [line for line in (out / "results.md").read_text().splitlines() if line.startswith("| ")]
    assert len(rows) == 5 and winner["trial_id"] in rows[1] and "Invalid learning rate" in rows[-1]
    assert cpus_freed(ray_cluster), "stopped or interrupted trials left resources behind"


# --------------------------------------------------------------------------- checks before any work


def _sweep_main(monkeypatch: pytest.MonkeyPatch, params: dict[str, Any], stage: str,
                target: Any = None) -> SystemExit:
    """``stages.sweep.main([stage])`` on ``params`` (and ``target``, else the stage's own); its SystemExit."""
    from stages import sweep

    monkeypatch.setattr(sweep, "load_params", lambda argv: params)
    if target is not None:
        monkeypatch.setattr(sweep, "load_target", lambda name, p: target(p))
    with pytest.raises(SystemExit) as exc:
        sweep.main([stage])
    return exc.value


def _no_ray(*args: Any, **kwargs: Any) -> None:
    raise AssertionError("Ray was started before the checks")


@pytest.mark.parametrize("argv", [["--help"], ["-h"], ["train_vae", "--help"], ["train_vae", "scale=smoke", "-h"],
                                  ["train_vae", "--cfg", "--help"], ["no_such_stage", "--help"]])
def test_help_flag_anywhere_prints_the_usage_and_runs_nothing(argv: list[str], monkeypatch: pytest.MonkeyPatch,
                                                              capsys: pytest.CaptureFixture) -> None:
    """``stages.sweep train_vae --help`` was read as the override '--help' (exit 2); it is help wherever it is."""
    from stages import sweep

    monkeypatch.setattr(sweep, "load_params", _no_ray)  # neither params nor a plan nor a sweep
    sweep.main(argv)
    captured = capsys.readouterr()
    assert captured.out == sweep.__doc__.strip() + "\n" and captured.err == ""
    assert captured.out.startswith("``python -m stages.sweep <stage> [key=value ...]``")


@pytest.mark.slow
def test_help_after_the_stage_exits_0_on_the_command_line() -> None:
    proc = subprocess.run([sys.executable, "-m", "stages.sweep", "train_vae", "--help"], cwd=REPO_ROOT,
                          capture_output=True, text=True, timeout=120)
    assert (proc.returncode, proc.stderr) == (0, ""), proc.stderr
    assert "``--help`` or ``-h``" in proc.stdout and "not of the form key=value" not in proc.stdout


def test_bad_stage_params_exit_2_before_any_work(monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                                                 capsys: pytest.CaptureFixture) -> None:
    import pipelines.sweep

    monkeypatch.setattr(pipelines.sweep, "ensure_ray", _no_ray)
    params = compose_params(["scale=smoke"])
    params["train_vae"]["joint_space"] = "local"
    exit_ = _sweep_main(monkeypatch, params, "train_vae")
    assert exit_.code == 2
    # Only our lines: a Ray actor of an earlier test in the session may still print to stderr.
    err = [line for line in capsys.readouterr().err.strip().splitlines() if line.startswith("sweep ")]
    assert len(err) == 1 and err[0].startswith("sweep train_vae: train_vae.joint_space") and "local" in err[0]


def test_bad_ray_settings_exit_2_before_ray_starts(monkeypatch: pytest.MonkeyPatch,
                                                   capsys: pytest.CaptureFixture) -> None:
    """The ``ray`` section is checked as every stage checks it, one line per key, before Ray is started."""
    import pipelines.sweep

    monkeypatch.setattr(pipelines.sweep, "ensure_ray", _no_ray)
    params = compose_params(["scale=smoke"])
    params["ray"] |= {"use_gpu": "maybe", "num_workers": -1}
    exit_ = _sweep_main(monkeypatch, params, "train_vae")
    assert exit_.code == 2
    err = [line for line in capsys.readouterr().err.strip().splitlines() if line.startswith(("sweep ", "ray."))]
    assert err == ["sweep train_vae: ray.num_workers: expected an integer >= 0, got -1",
                   "ray.use_gpu: expected one of ['auto', True, False], got 'maybe'"]


def test_dimension_values_are_every_listed_value_and_the_bounds_a_trial_can_take() -> None:
    assert dimension_values(Dimension("grid", ([1, 2, 3],))) == [1, 2, 3]
    assert dimension_values(Dimension("choice", ([[1, 2], [3, 4]],))) == [[1, 2], [3, 4]]
    assert dimension_values(Dimension("fixed", (400,))) == [400]
    assert dimension_values(Dimension("randint", (2, 5))) == [2, 4]  # high excluded
    low, high = dimension_values(Dimension("uniform", (0.0, 1.0)))
    assert low == 0.0 and high < 1.0 and high == math.nextafter(1.0, 0.0)  # Tune draws below the upper bound


def test_every_value_of_the_space_meets_the_stages_checks_before_any_trial() -> None:
    """A value the stage refuses is a config error naming the sweep key; an upper bound the trials never
    take (uniform's high) and a fixed value applied with the others are checked as the trials see them."""

    def check(params: dict) -> None:
        cfg = params["toy"]
        if not 0 <= cfg["dropout"] < 1:
            raise ValueError(f"toy.dropout: expected 0 <= dropout < 1, got {cfg['dropout']}")
        if cfg["loop"]["batch_size"] > 64 and cfg["lr"] > 0.1:
            raise ValueError("toy: lr > 0.1 needs batch_size <= 64")

    target = SweepTarget(stage="toy", spec=TOY_SPEC, loop_config=toy_loop_config, checks=[check])
    params = {"toy": {"dropout": 0.1, "lr": 0.01, "loop": {"batch_size": 16}}}
    space = {"dropout": Dimension("uniform", (0.0, 1.0)), "lr": Dimension("grid", ([0.01, 0.5],))}
    check_space_values(target, params, space)  # 1.0 itself is never drawn
    space["loop.batch_size"] = Dimension("fixed", (128,))  # with lr 0.5: refused
    with pytest.raises(SweepConfigError, match=r"^sweep\.toy\.lr: a trial would take 0\.5, which the stage refuses: "
                                               r"toy: lr > 0\.1 needs batch_size <= 64$"):
        check_space_values(target, params, space)
    space = {"dropout": Dimension("choice", ([0.0, 1.5],))}
    with pytest.raises(SweepConfigError, match=r"^sweep\.toy\.dropout: a trial would take 1\.5, .*got 1\.5$"):
        check_space_values(target, params, space)
    assert params == {"toy": {"dropout": 0.1, "lr": 0.01, "loop": {"batch_size": 16}}}  # params left as they were


def test_a_bad_value_in_a_stages_space_exits_2_before_ray_starts(monkeypatch: pytest.MonkeyPatch,
                                                                 capsys: pytest.CaptureFixture) -> None:
    """The real stages' checks, on the committed params with one bad grid value."""
    import pipelines.sweep

    monkeypatch.setattr(pipelines.sweep, "ensure_ray", _no_ray)
    params = compose_params(["scale=smoke"])
    params["sweep"]["train_vae"]["loop"]["warmup_steps"] = "choice([0, -5])"
    exit_ = _sweep_main(monkeypatch, params, "train_vae")
    assert exit_.code == 2
    err = [line for line in capsys.readouterr().err.strip().splitlines() if line.startswith("sweep ")]
    assert err == ["sweep train_vae: sweep.train_vae.loop.warmup_steps: a trial would take -5, which the stage "
                   "refuses: train_vae.loop.warmup_steps: expected an integer >= 0, got -5"]


def test_cfg_prints_the_plan_without_starting_ray(small_store: dict[str, Any], tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch,
                                                  capsys: pytest.CaptureFixture) -> None:
    """``--cfg``: every check that needs no Ray (the feature store included), then the plan; exit 0."""
    import pipelines.sweep
    from stages import sweep

    monkeypatch.setattr(pipelines.sweep, "ensure_ray", _no_ray)
    params = copy.deepcopy(small_store)
    params["paths"]["artifacts"] = str(tmp_path / "artifacts")
    params["sweep"]["settings"]["num_samples"] = 3
    params["sweep"]["train_vae"] = {"lr": "grid([0.001, 0.003])", "loop": {"max_steps": 20}}
    monkeypatch.setattr(sweep, "load_params", lambda argv: params)
    sweep.main(["train_vae", "--cfg"])
    lines = capsys.readouterr().out.splitlines()[-4:]  # after the smoke profile's in-process notice
    assert lines[0].endswith(": 6 trial(s), ranked by val_MPJPE_mm (min), scheduler asha")
    assert lines[1:3] == ["  lr: grid([0.001, 0.003])", "  loop.max_steps: fixed(20)"]
    assert lines[3].startswith(f"  each trial: 1 Ray Train worker(s) x {params['ray']['cpus_per_worker']:g} CPU(s)")
    params["sweep"]["settings"]["num_samples"] = 0
    with pytest.raises(SystemExit) as exc:
        sweep.main(["train_vae", "--cfg"])
    assert exc.value.code == 2 and "sweep.settings.num_samples: expected an integer >= 1, got 0" in \
        capsys.readouterr().err


def test_missing_feature_store_exits_1_before_any_work(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    import pipelines.sweep

    monkeypatch.setattr(pipelines.sweep, "ensure_ray", _no_ray)
    params = compose_params(["scale=smoke"])
    params["features"]["out"] = str(tmp_path / "no-store")
    exit_ = _sweep_main(monkeypatch, params, "train_vae")
    assert isinstance(exit_.code, str) and exit_.code.startswith("sweep train_vae: ")
    assert str(tmp_path / "no-store") in exit_.code


def test_a_trial_too_big_for_the_cluster_exits_2_before_the_prerequisite(
        ray_cluster: Any, monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    params = toy_params(tmp_path)
    params["ray"]["cpus_per_worker"] = 8
    exit_ = _sweep_main(monkeypatch, params, "toy", toy_target)
    assert exit_.code == 2
    assert capsys.readouterr().err == ("sweep toy: one trial needs 8 CPUs (ray.num_workers=1 x ray.cpus_per_worker=8) "
                                       "and 0 GPUs; the cluster has 4 CPUs and 0 GPUs\n")
    assert not Path(params["toy"]["marker"]).exists()


def test_best_params_are_chosen_by_the_validation_metric(ray_cluster: Any, tmp_path: Path) -> None:
    """The toy's training loss prefers lr 0.1, its validation error lr 0.001: the sweep picks 0.001 by default,
    0.1 when told to rank by the training loss (reported with the validation metrics)."""
    params = toy_params(tmp_path)
    result = run_sweep(toy_target(params), params, tmp_path)
    assert result.metric == "val_error" and Path(params["toy"]["marker"]).exists()
    best = yaml.safe_load((result.out_dir / "best_params.yaml").read_text())
    assert best == {"toy": {"lr": 0.001}}
    errors = {row["lr"]: row["val_error"] for row in pq.read_table(result.out_dir / "results.parquet").to_pylist()}
    assert errors[0.001] < 1.1 < 3.0 < errors[0.1]  # w ~ 0.04 against w ~ 1
    assert "best val_error (min)" in (result.out_dir / "results.md").read_text()

    params["sweep"]["settings"] |= {"metric": "loss", "mode": "min"}
    by_loss = run_sweep(toy_target(params), params, tmp_path / "by-loss")
    assert yaml.safe_load((by_loss.out_dir / "best_params.yaml").read_text()) == {"toy": {"lr": 0.1}}
    assert cpus_freed(ray_cluster)


def test_a_sweep_on_another_store_other_code_or_other_workers_is_another_experiment(
        small_store: dict[str, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Tune resumes an experiment of the same name: a sweep on a re-extracted feature store reported the old
    store's trials as its results, and one with another worker count resumed checkpoints of another world
    size. The name now holds the stage's code, its input folders' contents and the trial workers."""
    import pipelines.sweep
    from pipelines.config import REPO_ROOT
    from pipelines.sweep import plan_sweep
    from stages import train_vae

    params = copy.deepcopy(small_store)
    shutil.copytree(small_store["features"]["out"], tmp_path / "features")
    params["features"]["out"] = str(tmp_path / "features")
    params["paths"]["artifacts"] = str(tmp_path / "artifacts")
    params["sweep"]["train_vae"] = {"lr": "grid([0.001, 0.003])"}

    def name(p: dict[str, Any]) -> str:
        return plan_sweep(train_vae.sweep_target(p), p, REPO_ROOT).name

    first = name(params)
    assert first == name(copy.deepcopy(params))
    assert name(params | {"ray": params["ray"] | {"num_workers": 2}}) != first  # smoke: 0, trials take 1
    (tmp_path / "features" / "meta.json").write_text((tmp_path / "features" / "meta.json").read_text() + " ")
    assert name(params) != first
    store_changed = name(params)
    monkeypatch.setattr(pipelines.sweep, "run_fingerprint", lambda module, inputs, config: f"other code of {module}")
    assert name(params) not in (first, store_changed)


def test_a_prerequisite_is_trained_again_when_its_code_or_inputs_changed(tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """``train_once`` reused a prerequisite (the evaluator's movement encoder) whenever its loop config matched,
    so a sweep restarted after a code change built its trials on the old model."""
    import pipelines.sweep
    from pipelines.checkpoint import MODEL_FILE
    from pipelines.sweep import train_once

    out = tmp_path / "movement"
    out.mkdir()
    (out / MODEL_FILE).write_bytes(b"model")
    (out / "run.json").write_text(json.dumps({"config": {"lr": 0.1}, "fingerprint": "code-a"}))
    trained = []
    monkeypatch.setattr(pipelines.sweep, "run_training",
                        lambda *args, **kwargs: trained.append(kwargs["fingerprint"]) or SimpleNamespace(out_dir=out))
    assert train_once("m", None, {"lr": 0.1}, None, out, fingerprint="code-a") == out and trained == []
    train_once("m", None, {"lr": 0.1}, None, out, fingerprint="code-b")
    train_once("m", None, {"lr": 0.2}, None, out, fingerprint="code-a")
    assert trained == ["code-b", "code-a"]


@pytest.mark.parametrize("stage", ["train_evaluator", "train_vae", "distill_lcm", "train_emdm"])
def test_every_sweep_target_names_its_code_and_inputs(stage: str) -> None:
    """A target without them (distill_lcm's was) keeps its experiment name across a retrained teacher or a
    re-extracted store, so Tune resumes the old trials."""
    import importlib

    from pipelines.config import compose_params

    module = importlib.import_module(f"stages.{stage}")
    target = module.sweep_target(compose_params(["scale=smoke"]))
    assert target.module.startswith("stages.") and "features_dir" in target.inputs
