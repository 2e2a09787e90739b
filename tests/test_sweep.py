"""Ray Tune sweeps (pipelines/sweep.py, stages/sweep.py): the search-space parser, the concurrency
arithmetic, the outcome checks, and a smoke sweep of the evaluator on a tiny feature store.

The smoke sweep runs on the session's two-node simulated cluster (2 x 2 logical CPUs): a grid
of four matching-run learning rates under ASHA, one of them (-1) rejected by Adam. It is
interrupted (SIGINT, as Ctrl+C) after its first finished trial, exits non-zero without
outputs, and the same command then resumes and finishes it.
"""

from __future__ import annotations

import json
import math
import os
import signal
import sys
import time
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest
import ray
import yaml
from ray import tune
from ray.util.placement_group import placement_group, remove_placement_group

from data.store import StoredItem, write_split
from pipelines.config import compose_params
from pipelines.runner import RayOptions, run_training
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
    apply_trial,
    best_row,
    check_outcome,
    expected_trials,
    experiment_name,
    fit_concurrency,
    max_concurrent,
    orphaned_placement_groups,
    parse_dimension,
    parse_space,
    run_sweep,
    short_error,
    trial_status,
)

# Ray workers cannot import this module (tests/ is on sys.path only here): ship its code by value.
ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])

FIXTURES = Path(__file__).parent / "fixtures" / "humanml3d"
STAGE = "train_evaluator"

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
    with pytest.raises(SweepConfigError, match="trial_cpus=0"):
        SweepSettings.from_dict({"trial_cpus": 0})
    with pytest.raises(SweepConfigError, match="mode='low'"):
        SweepSettings.from_dict({"mode": "low"})


def test_committed_params_declare_a_valid_evaluator_sweep() -> None:
    params = compose_params()
    SweepSettings.from_dict(params["sweep"]["settings"])
    assert parse_space(STAGE, params["sweep"][STAGE], params[STAGE])


@pytest.mark.parametrize(("cluster", "workers", "cpw", "trial", "gpw", "expected"), [
    ({"CPU": 4}, 1, 1, 0.01, 0, 3),      # 4 / 1.01 -> 3 (the driver's 0.01 CPU counts)
    ({"CPU": 4}, 1, 1, 0.0, 0, 4),
    ({"CPU": 2}, 2, 0.5, 0.01, 0, 1),    # 2 / 1.01
    ({"CPU": 16}, 2, 1, 1, 0, 5),        # the 1-CPU-per-trial default: 16 / 3
    ({"CPU": 16}, 2, 2, 0.01, 0, 3),
    ({"CPU": 3.03}, 1, 1, 0.01, 0, 3),   # exact fit despite float rounding
    ({"CPU": 64, "GPU": 4}, 2, 1, 0.01, 1, 2),  # GPUs bind first
])
def test_max_concurrent_fits_the_cluster(cluster: dict, workers: int, cpw: float, trial: float, gpw: float,
                                         expected: int) -> None:
    assert fit_concurrency(cluster, workers, cpw, trial, gpw) == expected


def test_a_trial_that_can_never_fit_is_an_error() -> None:
    with pytest.raises(ValueError, match="needs 2.01 CPUs"):
        fit_concurrency({"CPU": 2}, 2, 1, 0.01)
    with pytest.raises(ValueError, match="GPUs"):
        fit_concurrency({"CPU": 8}, 1, 1, 0.01, gpus_per_worker=1)


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
    opts = RayOptions(num_workers=1, cpus_per_worker=1)
    assert max_concurrent(SweepSettings(), opts) == 3  # 2 nodes x 2 CPUs / (1 + 0.01)
    assert max_concurrent(SweepSettings(max_concurrent_trials=2), opts) == 2


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
    from stages import sweep

    params = smoke_params(tmp_path)
    monkeypatch.setenv("RAY_TRAIN_ENABLE_PREEMPTION_WATCHER", "0")  # one process less per trial (Tune propagates it)
    pretrain_movement_in_process(params)
    monkeypatch.setattr(sweep, "load_params", lambda argv: params)
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
    best = yaml.safe_load((out / "best_params.yaml").read_text())
    assert best == {STAGE: {"lr": winner["lr"], "margin": 10.0}}
    rows = [line for line in (out / "results.md").read_text().splitlines() if line.startswith("| ")]
    assert len(rows) == 5 and winner["trial_id"] in rows[1] and "Invalid learning rate" in rows[-1]
    assert cpus_freed(ray_cluster), "stopped or interrupted trials left resources behind"
