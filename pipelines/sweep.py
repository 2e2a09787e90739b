"""Ray Tune sweeps over any training stage: each trial is one Ray Train run of the one runner.

A stage makes itself sweepable with a module-level ``sweep_target(params) -> SweepTarget``
(its :class:`~pipelines.runner.TrainSpec`, how params become its loop config, and an optional
prerequisite run once before the trials); ``python -m stages.sweep <stage> [overrides]``
does the rest with :func:`run_sweep`.

Params::

    sweep:
      settings: {num_samples, metric, mode, scheduler, grace_period, reduction_factor, max_t,
                 report_every, max_concurrent_trials, trial_cpus, max_failures, seed}
      # metric/mode null: the target's own (its validation metric when it has a validate hook)
      <stage>:                     # keys of params[<stage>] (dotted into groups) and how to vary them
        lr: loguniform(1e-5, 1e-3)
        loop.batch_size: choice([16, 32])
        margin: uniform(5, 15)
        loop.warmup_steps: randint(0, 100)    # upper bound excluded, as in tune.randint
        loop.seed: grid([0, 1, 2])            # every value, times num_samples
        loop.grad_clip: 0.5                   # a plain value: fixed for every trial; null: not varied

Dimension strings are parsed without ``eval`` (:func:`parse_dimension`: a function name and
Python literals read by ``ast.literal_eval``).

How it runs (DESIGN.md "Facts about the stack"; reference/pipeline_stack.md sections 2-3):

* before any work (prerequisites included) the stage's loop config is built once from params
  (its checks, its inputs), every value the space can give is put through the stage's checks
  (:func:`check_space_values`) and the cluster is checked to hold one trial; each is a
  :class:`SweepConfigError` (exit status 2 of ``stages.sweep``);
* trials are ranked by ``sweep.settings.metric`` (``mode``), by default the target's: its
  validation metric (e.g. ``val_MPJPE_mm`` of ``train_vae``), measured on the ``val`` split
  after training, else the last training ``loss``;
* each trial is :func:`trial_driver`, a Tune function trainable taking ``trial_cpus`` (e.g.
  0.01) logical CPUs; it applies the trial's values to ``params[<stage>]``, builds the loop
  config, and fits a ``TorchTrainer`` from :func:`pipelines.runner.build_trainer` named
  ``<stage>-<trial id>`` with a ``TuneReportCallback``. The runner then reports metrics
  every ``report_every`` steps, so one Tune training iteration = one report and ASHA's
  ``grace_period``/``max_t`` count reports. With a validation hook the trial reports once,
  after training: its validation metrics and its last training metrics;
* a trial takes ``ray.num_workers x ray.cpus_per_worker`` logical CPUs in all: its driver's
  ``trial_cpus`` come out of its workers' share (the driver idles while they train), so a
  2-CPU machine runs 2-CPU trials; ``max_concurrent_trials: auto`` runs as many trials at
  once as the cluster's CPUs (and GPUs) hold (:func:`fit_concurrency`);
* the Tune experiment lives at ``<storage>/sweep-<stage>-<hash>``, the hash covering the
  space, the settings and ``params[<stage>]`` (:func:`experiment_name`). Started again with
  the same arguments, an interrupted sweep is restored (``Tuner.restore``): finished trials
  are kept, unfinished ones run again (their Train runs resume from their checkpoints).
  Tune's experiment state is Ray's own pickle, so a restore trusts whoever can write the
  storage (our checkpoints there load with ``weights_only=True``; Ray's files cannot);
* the results are read back from the experiment state Tune saved, the state a restore
  resumes (after a SIGINT ``tuner.fit()`` returns normally, its in-memory grid showing the
  trials it killed as TERMINATED). Trial statuses (:func:`trial_status`): ``completed``
  (ran all its steps: :class:`SweepReportCallback` adds ``planned_steps`` to every report),
  ``stopped early`` (by ASHA), ``error``, ``unfinished``;
* a failed trial is a row of the results table with its error; :class:`SweepFailed` is
  raised only when every trial failed, :class:`SweepInterrupted` when trials are
  unfinished. Neither writes the output directory;
* :class:`PlacementGroupJanitor` removes the Train workers' placement groups that stopped
  trials leave behind when Ray Train's own cleaner cannot (several Ray instances on one
  host defeat its address autodetection; the next trial would wait forever);
* outputs (atomic): ``results.parquet`` and ``results.md`` (one row per trial: trial id,
  status, the space's keys, final metric, iterations, error) and ``best_params.yaml``
  (``{<stage>: {key: value}}`` of the best trial, for ``dvc exp run -S`` or ``conf/``).
"""

from __future__ import annotations

import ast
import copy
import hashlib
import json
import logging
import math
import numbers
import re
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq
import ray
import yaml
from ray import tune
from ray.tune.integration.ray_train import TuneReportCallback
from ray.tune.schedulers import ASHAScheduler, FIFOScheduler
from ray.tune.search.basic_variant import BasicVariantGenerator
from ray.util.placement_group import PlacementGroup, remove_placement_group

from data.atomic import atomic_directory, check_output
from pipelines.checkpoint import MODEL_FILE, load_state
from pipelines.cli import check_shared
from pipelines.config import ConfigError, check_choice, check_number
from pipelines.runner import (
    LoopSettings,
    RayOptions,
    TrainSpec,
    build_trainer,
    decide_use_gpu,
    ensure_ray,
    fit_retrying,
    run_training,
)
from pipelines.stage import ray_storage, run_fingerprint

logger = logging.getLogger(__name__)

#: Trial statuses written to the results table.
COMPLETED, STOPPED, ERROR, UNFINISHED = "completed", "stopped early", "error", "unfinished"


class SweepConfigError(ValueError):
    """A bad search space or settings entry (the message names the key)."""


class SweepError(RuntimeError):
    """A sweep that produced no usable result; ``table`` holds the trials' rows."""

    def __init__(self, message: str, table: list[dict[str, Any]]) -> None:
        super().__init__(message)
        self.table = table


class SweepFailed(SweepError):
    """Every trial failed."""


class SweepInterrupted(SweepError):
    """``tuner.fit()`` returned with unfinished trials; run the same sweep again to resume."""


# --------------------------------------------------------------------------- search space


@dataclass(frozen=True)
class Dimension:
    """One parsed search-space entry: ``kind`` in :data:`KINDS` or ``"fixed"``, and its arguments."""

    kind: str
    args: tuple[Any, ...]

    def to_tune(self) -> Any:
        """The Ray Tune domain (or the plain value for ``fixed``)."""
        if self.kind == "fixed":
            return self.args[0]
        if self.kind == "grid":
            return tune.grid_search(list(self.args[0]))
        if self.kind == "choice":
            return tune.choice(list(self.args[0]))
        return {"uniform": tune.uniform, "loguniform": tune.loguniform, "randint": tune.randint}[self.kind](*self.args)


def _is_number(value: Any) -> bool:
    """A finite real number (not a bool)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)


def _check_bounds(kind: str, args: tuple[Any, ...]) -> str | None:
    """Why ``kind(args)`` with two bounds is invalid, or None."""
    if len(args) != 2 or not all(_is_number(a) for a in args):
        return f"{kind} takes two numbers (low, high)"
    low, high = args
    if kind == "randint" and not all(isinstance(a, int) for a in args):
        return "randint takes two integers (low, high), high excluded"
    if low >= high:
        return f"{kind} needs low < high, got {low} >= {high}"
    if kind == "loguniform" and low <= 0:
        return f"loguniform needs low > 0, got {low}"
    return None


def _check_list(kind: str, args: tuple[Any, ...]) -> str | None:
    """Why ``kind(args)`` taking one list of values is invalid, or None."""
    if len(args) != 1 or not isinstance(args[0], list | tuple) or not args[0]:
        return f"{kind} takes one non-empty list, e.g. {kind}([16, 32])"
    return None


#: Dimension kinds and their argument checks.
KINDS: dict[str, Callable[[str, tuple[Any, ...]], str | None]] = {
    "uniform": _check_bounds,
    "loguniform": _check_bounds,
    "randint": _check_bounds,
    "choice": _check_list,
    "grid": _check_list,
}
_CALL = re.compile(r"^\s*([A-Za-z_]\w*)\s*\((.*)\)\s*$", re.DOTALL)


def _literal_args(body: str) -> tuple[Any, ...]:
    """The comma-separated Python literals in ``body`` (ValueError/SyntaxError if not literals)."""
    if not body.strip():
        return ()
    return tuple(ast.literal_eval(f"({body},)"))


def parse_dimension(key: str, spec: Any) -> Dimension | None:
    """Parse one ``sweep.<stage>`` entry; None for null (not varied).

    Strings are ``kind(args)`` with ``kind`` one of :data:`KINDS` (``grid_search`` is an alias
    of ``grid``) and literal arguments; numbers and booleans are fixed values. Anything else
    raises :class:`SweepConfigError` naming ``key``.
    """
    if spec is None:
        return None
    if isinstance(spec, bool | int | float):
        return Dimension("fixed", (spec,))
    if not isinstance(spec, str):
        raise SweepConfigError(f"{key}: expected a string like 'choice([16, 32])' or a number, got {spec!r}")
    match = _CALL.match(spec)
    if not match:
        raise SweepConfigError(f"{key}: {spec!r} is not of the form kind(args), kind one of {sorted(KINDS)}")
    kind = "grid" if match.group(1) == "grid_search" else match.group(1)
    if kind not in KINDS:
        raise SweepConfigError(f"{key}: unknown kind {match.group(1)!r} in {spec!r}; expected one of {sorted(KINDS)}")
    try:
        args = _literal_args(match.group(2))
    except (ValueError, SyntaxError, TypeError, MemoryError, RecursionError) as err:
        raise SweepConfigError(f"{key}: cannot read the arguments of {spec!r} (literals only): {err}") from None
    problem = KINDS[kind](kind, args)
    if problem:
        raise SweepConfigError(f"{key}: {problem}; got {spec!r}")
    return Dimension(kind, args)


def _has_key(section: Mapping[str, Any], dotted: str) -> bool:
    node: Any = section
    for part in dotted.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return False
        node = node[part]
    return True


def flatten_space(entries: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"loop": {"max_steps": 400}, "lr": spec}`` -> ``{"loop.max_steps": 400, "lr": spec}``."""
    flat: dict[str, Any] = {}
    for key, spec in entries.items():
        if isinstance(spec, Mapping):
            flat |= flatten_space(spec, f"{prefix}{key}.")
        else:
            flat[f"{prefix}{key}"] = spec
    return flat


def nest_keys(values: Mapping[str, Any]) -> dict[str, Any]:
    """``{"loop.max_steps": 400, "lr": 0.1}`` -> ``{"loop": {"max_steps": 400}, "lr": 0.1}`` (as in the params)."""
    nested: dict[str, Any] = {}
    for key, value in values.items():
        *groups, last = key.split(".")
        node = nested
        for group in groups:
            node = node.setdefault(group, {})
        node[last] = value
    return nested


def parse_space(stage: str, entries: Mapping[str, Any] | None, stage_params: Mapping[str, Any]) -> dict[str, Dimension]:
    """Parse ``sweep.<stage>``: every key must be a key of ``params[<stage>]``; null entries are dropped.

    A key of a group is written nested, as in the params (``loop: {max_steps: 400}``), so that
    ``sweep.<stage>.loop.max_steps=...`` overrides it from the command line; a dotted key
    (``loop.max_steps: 400``) means the same. The space's keys are dotted.
    """
    if not isinstance(entries, Mapping):
        raise SweepConfigError(f"sweep.{stage}: expected a mapping of {stage} keys to dimensions, got {entries!r}")
    space = {}
    for key, spec in flatten_space(entries).items():
        name = f"sweep.{stage}.{key}"
        if not _has_key(stage_params, key):
            raise SweepConfigError(f"{name}: {key!r} is not a key of the {stage!r} params")
        dim = parse_dimension(name, spec)
        if dim is not None:
            space[key] = dim
    if not any(dim.kind != "fixed" for dim in space.values()):
        raise SweepConfigError(f"sweep.{stage}: nothing to vary (declare e.g. lr: loguniform(1e-5, 1e-3))")
    return space


def param_space(space: Mapping[str, Dimension]) -> dict[str, Any]:
    """The Tune ``param_space``: ``{key: domain}``."""
    return {key: dim.to_tune() for key, dim in space.items()}


def expected_trials(space: Mapping[str, Dimension], num_samples: int) -> int:
    """Trials Tune generates: ``num_samples`` times the product of the grid sizes."""
    return num_samples * math.prod(len(dim.args[0]) for dim in space.values() if dim.kind == "grid")


# --------------------------------------------------------------------------- settings


@dataclass(frozen=True)
class SweepSettings:
    """The ``sweep.settings`` section.

    Attributes:
        num_samples: samples of the random dimensions (times every grid combination).
        metric: reported metric to optimise (the last value reported by a trial counts); None:
            the target's (:attr:`SweepTarget.metric`).
        mode: "min" or "max"; None: the target's.
        scheduler: "asha" (early stopping) or "fifo" (none).
        grace_period: ASHA: reports before a trial may be stopped.
        reduction_factor: ASHA: 1/reduction_factor of the trials go on at each rung.
        max_t: ASHA: most reports a trial may make.
        report_every: training steps between the metric reports Tune sees.
        max_concurrent_trials: "auto" (fitted to the cluster, :func:`fit_concurrency`) or a number.
        trial_cpus: logical CPUs of a trial's driver function (the Train workers have their own).
        max_failures: Tune retries of a failed trial (its Train run resumes from a checkpoint).
        seed: seed of the random search (None: unseeded).
    """

    num_samples: int = 4
    metric: str | None = None
    mode: str | None = None
    scheduler: str = "asha"
    grace_period: int = 1
    reduction_factor: int = 2
    max_t: int = 100
    report_every: int = 50
    max_concurrent_trials: int | str = "auto"
    trial_cpus: float = 0.01
    max_failures: int = 0
    seed: int | None = 0

    @classmethod
    def from_dict(cls, cfg: Mapping[str, Any] | None) -> SweepSettings:
        """Validate ``sweep.settings`` (unknown keys and impossible values are errors)."""
        cfg = dict(cfg or {})
        unknown = set(cfg) - {f.name for f in fields(cls)}
        if unknown:
            raise SweepConfigError(f"sweep.settings: unknown key(s) {sorted(unknown)}")
        settings = cls(**cfg)
        settings._validate()
        return settings

    def _validate(self) -> None:
        """Each key's type and range; a ConfigError naming ``sweep.settings.<key>``, its value and what is allowed."""
        try:
            self._check_each()
        except ConfigError as err:
            raise SweepConfigError(str(err)) from None

    def _check_each(self) -> None:
        values, where = asdict(self), "sweep.settings"
        if self.metric is not None and not (isinstance(self.metric, str) and self.metric):
            raise SweepConfigError(f"{where}.metric: expected null or a metric name, got {self.metric!r}")
        check_choice(values, "mode", where, choices=(None, "min", "max"))
        check_choice(values, "scheduler", where, choices=("asha", "fifo"))
        check_number(values, "num_samples", where, low=1, integer=True)
        check_number(values, "max_t", where, low=1, integer=True)
        check_number(values, "grace_period", where, low=1, high=self.max_t, integer=True)
        check_number(values, "reduction_factor", where, low=2)
        check_number(values, "report_every", where, low=1, integer=True)
        if self.max_concurrent_trials != "auto":
            check_number(values, "max_concurrent_trials", where, low=1, integer=True)
        check_number(values, "trial_cpus", where, low=0, low_open=True)  # Ray rejects a zero-CPU trial
        check_number(values, "max_failures", where, low=0, integer=True)
        if self.seed is not None:
            check_number(values, "seed", where, low=0, integer=True)


def fit_concurrency(cluster: Mapping[str, float], num_workers: int, cpus_per_worker: float,
                    gpus_per_worker: float = 0.0) -> int:
    """How many trials fit on ``cluster`` at once, each ``num_workers x cpus_per_worker`` CPUs (its
    driver's share included, :func:`trial_ray_options`) and ``num_workers x gpus_per_worker`` GPUs.

    Raises :class:`SweepConfigError` naming the keys when not even one trial fits (Ray would wait
    forever).
    """
    need_cpu = num_workers * cpus_per_worker
    fits = [math.floor(cluster.get("CPU", 0.0) / need_cpu + 1e-9)]
    if gpus_per_worker > 0:
        fits.append(math.floor(cluster.get("GPU", 0.0) / (num_workers * gpus_per_worker) + 1e-9))
    if min(fits) < 1:
        raise SweepConfigError(
            f"one trial needs {need_cpu:g} CPUs (ray.num_workers={num_workers} x ray.cpus_per_worker="
            f"{cpus_per_worker:g}) and {num_workers * gpus_per_worker:g} GPUs; the cluster has "
            f"{cluster.get('CPU', 0):g} CPUs and {cluster.get('GPU', 0):g} GPUs")
    return min(fits)


def experiment_name(stage: str, space: Mapping[str, Dimension], settings: SweepSettings,
                    stage_params: Mapping[str, Any], identity: str = "", workers: Mapping[str, Any] | None = None
                    ) -> str:
    """``sweep-<stage>-<10 hex>``: stable for the same space, settings, ``params[<stage>]``, code and inputs
    (``identity``, :func:`pipelines.stage.run_fingerprint`) and trial workers (``workers``). Ray Tune resumes
    an experiment of the same name, so a sweep on another feature store, other code or another worker count
    (whose trials' checkpoints would not fit) starts afresh instead of reporting the old trials."""
    blob = json.dumps({"space": {k: [d.kind, d.args] for k, d in space.items()}, "settings": asdict(settings),
                       "params": stage_params, "identity": identity, "workers": workers or {}},
                      sort_keys=True, default=str)
    return f"sweep-{stage}-{hashlib.sha1(blob.encode()).hexdigest()[:10]}"


# --------------------------------------------------------------------------- targets and trials

#: ``(params, work_dir, storage) -> loop-config overrides`` for every trial.
Prerequisite = Callable[[dict, Path, str], dict]


@dataclass(frozen=True)
class SweepTarget:
    """What a stage's ``sweep_target(params)`` returns (functions at module level, for Ray).

    Attributes:
        stage: the params section the space varies; also the Train runs' name prefix.
        spec: the swept run's training recipe.
        loop_config: ``params -> loop config`` of the swept run (called in every trial with the
            trial's values applied to ``params[stage]``).
        prerequisite: run once on the driver before the trials (e.g. a pretraining run every
            trial builds on); gets a work directory and the Ray storage and returns loop-config
            overrides applied to every trial.
        validate: ``(trial params, loop config, final training state) -> metrics`` measured on
            held-out data after a trial's training and reported to Tune once, with the last
            training metrics (e.g. ``val_FID``), so trials are ranked by a validation metric
            rather than by their training loss.
        metric: what ranks the trials unless ``sweep.settings.metric`` names another: the
            validation metric ``validate`` returns, else ``loss``.
        mode: "min" or "max" for ``metric``.
        checks: the stage's params checks (:func:`pipelines.stage.checks`: fast, no data read), run
            on every value the space can give before Ray starts (:func:`check_space_values`).
        module: the stage module, whose code (with what it imports) names the experiment.
        inputs: loop-config keys of input folders that exist before the sweep (the feature store, a
            trained model), whose contents name the experiment.
    """

    stage: str
    spec: TrainSpec
    loop_config: Callable[[dict], dict]
    prerequisite: Prerequisite | None = None
    validate: Callable[[dict, dict, dict], dict[str, float]] | None = None
    metric: str = "loss"
    mode: str = "min"
    checks: Sequence[Callable[[dict], object]] = ()
    module: str = ""
    inputs: Sequence[str] = ()


@dataclass(frozen=True)
class SweepJob:
    """Everything a trial driver needs besides its sampled values (shipped once via the object store)."""

    target: SweepTarget
    params: dict
    overrides: dict
    ray: RayOptions
    storage: str


def apply_trial(params: Mapping[str, Any], stage: str, values: Mapping[str, Any]) -> dict:
    """A copy of ``params`` with the trial's ``values`` set in ``params[stage]`` (keys dotted into groups)."""
    params = copy.deepcopy(dict(params))
    for key, value in values.items():
        *groups, last = key.split(".")
        node = params[stage]
        for group in groups:
            node = node[group]
        node[last] = value
    return params


class SweepReportCallback(TuneReportCallback):
    """``TuneReportCallback`` that also tells Tune the run's ``planned_steps``.

    A trial whose last report has ``step == planned_steps`` ran to the end; one with fewer
    steps was stopped early by the scheduler (Tune marks both ``done``).
    """

    def __init__(self, planned_steps: int) -> None:
        super().__init__()
        self.planned_steps = planned_steps

    def after_report(self, run_context: Any, metrics: list[dict[str, Any]], checkpoint: Any) -> None:
        """Forward rank 0's metrics with ``planned_steps`` added."""
        metrics = [{**metrics[0], "planned_steps": self.planned_steps}, *metrics[1:]]
        super().after_report(run_context, metrics, checkpoint)


def trial_driver(config: dict, job: SweepJob) -> None:
    """Tune function trainable: one Ray Train run of the target with this trial's values."""
    stage = job.target.stage
    params = apply_trial(job.params, stage, config)
    loop_config = job.target.loop_config(params) | job.overrides
    trial_id = tune.get_context().get_trial_id()
    planned = LoopSettings.from_config(loop_config).max_steps
    # With a validation hook the trial reports once, after training (Tune checks that every report
    # holds the ranking metric); without one, training metrics are reported as they come.
    callbacks = [SweepReportCallback(planned)] if job.target.validate is None else []
    run_name = f"{stage}-{trial_id}"

    def make_trainer() -> Any:
        return build_trainer(stage, job.target.spec, loop_config, job.ray, job.storage, callbacks=callbacks,
                             run_name=run_name, max_failures=0)

    result = fit_retrying(make_trainer, job.ray.max_failures, run_name)
    if job.target.validate is not None and result.checkpoint is not None:
        with result.checkpoint.as_directory() as directory:
            state = load_state(Path(directory))
        training = {key: value for key, value in (result.metrics or {}).items() if _is_number(value)}
        metrics = job.target.validate(params, loop_config, state)
        tune.report({**training, **metrics, "step": state["step"], "planned_steps": planned})


def train_once(stage: str, spec: TrainSpec, loop_config: Mapping[str, Any], ray_cfg: Mapping[str, Any] | None,
               out_dir: Path, storage: str | None = None, fingerprint: str = "") -> Path:
    """:func:`run_training` unless ``out_dir`` already holds a model trained with this loop config and this
    code and inputs (``fingerprint``, :func:`pipelines.stage.run_fingerprint`).

    For prerequisites: a restarted sweep does not pay for them again.
    """
    meta = Path(out_dir) / "run.json"
    if (Path(out_dir) / MODEL_FILE).exists() and meta.exists():
        done = json.loads(meta.read_text())
        if (done.get("config") == json.loads(json.dumps(dict(loop_config), default=str))
                and done.get("fingerprint") == fingerprint):
            return Path(out_dir)
    return run_training(stage, spec, loop_config, ray_cfg, out_dir, storage, fingerprint=fingerprint).out_dir


def orphaned_placement_groups(job_id: str) -> list[str]:
    """Hex ids of live placement groups of ``job_id`` whose creating actor has died.

    A stopped trial's Train controller dies with it; the workers' placement group belongs to
    the job, so Ray keeps it until the sweep ends. Uses Ray's private GCS table: the public
    one has no creator fields.
    """
    from ray._private.state import state
    from ray._raylet import ActorID
    from ray.core.generated import gcs_pb2

    removed = gcs_pb2.PlacementGroupTableData.REMOVED
    orphans = []
    for blob in state._connect_and_get_accessor().get_placement_group_table():
        pg = gcs_pb2.PlacementGroupTableData.FromString(blob)
        by_actor = not ActorID(pg.creator_actor_id).is_nil()  # a driver's groups have no creator actor
        if (pg.state != removed and by_actor and pg.creator_actor_dead and not pg.is_detached
                and pg.creator_job_id.hex() == job_id):
            orphans.append(pg.placement_group_id.hex())
    return orphans


class PlacementGroupJanitor(tune.Callback):
    """Removes the placement groups that stopped trials' Train runs leave behind, every ``interval_s``.

    Ray Train's own ``PlacementGroupCleaner`` does this, but it finds the cluster by address
    autodetection, which fails when several Ray instances run on one host; the leaked group
    then holds its CPUs and the next trial's workers wait forever.
    """

    def __init__(self, interval_s: float = 2.0) -> None:
        self.interval_s = interval_s
        self._last = 0.0
        self._broken = False

    def on_step_begin(self, iteration: int, trials: list, **info: Any) -> None:
        """Sweep the placement group table (rate-limited; never fails the experiment)."""
        if self._broken or time.monotonic() - self._last < self.interval_s:
            return
        self._last = time.monotonic()
        try:
            for pg_id in orphaned_placement_groups(ray.get_runtime_context().get_job_id()):
                remove_placement_group(PlacementGroup(ray.PlacementGroupID(bytes.fromhex(pg_id))))
                logger.warning("sweep: removed placement group %s left by a stopped trial", pg_id)
        except Exception as err:  # a private Ray API changed: keep sweeping without the janitor
            self._broken = True
            logger.warning("sweep: cannot look for leaked placement groups (%s)", err)


# --------------------------------------------------------------------------- the sweep


@dataclass
class SweepResult:
    """What :func:`run_sweep` returns."""

    out_dir: Path
    experiment_path: str
    metric: str
    table: list[dict[str, Any]]
    best: dict[str, Any]
    restored: bool


def trial_ray_options(params: Mapping[str, Any], settings: SweepSettings) -> RayOptions:
    """The ``ray`` section for trials: Train workers (never in-process) reporting every ``report_every``.

    The workers reserve ``ray.cpus_per_worker`` less their share of the driver's ``trial_cpus``
    (their torch threads stay ``ray.cpus_per_worker``): a trial takes ``num_workers x
    cpus_per_worker`` logical CPUs in all, so 2-CPU trials fit a 2-CPU machine and whole trials
    pack a node.
    """
    opts = RayOptions.from_dict(params.get("ray"))
    if opts.in_process:
        print("sweep: ray.num_workers=0/local runs no Train job; trials use 1 Ray Train worker")
        opts = replace(opts, num_workers=max(1, opts.num_workers), local=False)
    if settings.trial_cpus >= opts.cpus_per_worker:
        raise SweepConfigError(f"sweep.settings.trial_cpus={settings.trial_cpus:g} must be smaller than "
                               f"ray.cpus_per_worker={opts.cpus_per_worker:g} (it comes out of the workers' share)")
    return replace(opts, report_every=settings.report_every,
                   cpus_per_worker=opts.cpus_per_worker - settings.trial_cpus / opts.num_workers)


def max_concurrent(settings: SweepSettings, opts: RayOptions) -> int:
    """``max_concurrent_trials`` (resolving "auto" against the connected cluster) for trials of ``opts``
    (:func:`trial_ray_options`); :class:`SweepConfigError` when not even one trial fits, whatever it says."""
    cluster = ray.cluster_resources()
    try:
        gpus = 1.0 if decide_use_gpu(opts.use_gpu, opts.num_workers, cluster) else 0.0
    except ValueError as err:
        raise SweepConfigError(f"ray.use_gpu: {err}") from None
    cpus_per_worker = opts.cpus_per_worker + settings.trial_cpus / opts.num_workers  # as configured
    fits = fit_concurrency(cluster, opts.num_workers, cpus_per_worker, gpus)
    return fits if settings.max_concurrent_trials == "auto" else int(settings.max_concurrent_trials)


def _make_tuner(trainable: Any, space: Mapping[str, Dimension], settings: SweepSettings, concurrency: int,
                name: str, storage: str, callbacks: Sequence[Any]) -> tune.Tuner:
    """A fresh ``tune.Tuner`` for the sweep."""
    scheduler = FIFOScheduler() if settings.scheduler == "fifo" else ASHAScheduler(
        time_attr="training_iteration", max_t=settings.max_t, grace_period=settings.grace_period,
        reduction_factor=settings.reduction_factor)
    return tune.Tuner(
        trainable,
        param_space=param_space(space),
        tune_config=tune.TuneConfig(
            metric=settings.metric, mode=settings.mode, num_samples=settings.num_samples, scheduler=scheduler,
            search_alg=BasicVariantGenerator(max_concurrent=concurrency, random_state=settings.seed),
            reuse_actors=False),
        run_config=tune.RunConfig(name=name, storage_path=storage, callbacks=[PlacementGroupJanitor(), *callbacks],
                                  failure_config=tune.FailureConfig(max_failures=settings.max_failures)),
    )


def _fit(job: SweepJob, space: Mapping[str, Dimension], settings: SweepSettings, name: str, concurrency: int,
         callbacks: Sequence[Any]) -> tuple[tune.ExperimentAnalysis, bool]:
    """Run (or restore and finish) the Tune experiment; returns its saved state and whether it was restored.

    The results are re-read from the experiment state Tune saved: after an interrupt, the
    in-memory grid shows the trials it killed as TERMINATED, the saved state (what a restore
    resumes) as RUNNING.
    """
    trainable = tune.with_resources(tune.with_parameters(trial_driver, job=job), {"cpu": settings.trial_cpus})
    path = f"{job.storage.rstrip('/')}/{name}"
    restored = tune.Tuner.can_restore(path)
    if restored:
        print(f"sweep: resuming {path}")
        tuner = tune.Tuner.restore(path, trainable=trainable, param_space=param_space(space),
                                   resume_unfinished=True, resume_errored=False, restart_errored=False)
    else:
        print(f"sweep: {expected_trials(space, settings.num_samples)} trial(s), {concurrency} at a time -> {path}")
        tuner = _make_tuner(trainable, space, settings, concurrency, name, job.storage, callbacks)
    grid = tuner.fit()
    saved = tune.ExperimentAnalysis(grid.experiment_path, storage_filesystem=grid.filesystem,
                                    default_metric=settings.metric, default_mode=settings.mode)
    return saved, restored


def short_error(error: BaseException | None, limit: int = 300) -> str:
    """The most telling line of a (possibly wrapped) trial error, at most ``limit`` characters."""
    if error is None:
        return ""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    telling = [line for line in lines if re.match(r"^[\w.]*(Error|Exception)\b", line)]
    text = (telling or lines or [type(error).__name__])[-1]
    return text if len(text) <= limit else text[: limit - 3] + "..."


def trial_status(tune_status: str, last: Mapping[str, Any]) -> str:
    """Table status from a trial's saved Tune status and its last result."""
    if tune_status == "ERROR" or (tune_status == "TERMINATED" and "planned_steps" not in last):
        return ERROR  # failed, or ended without a single report
    if tune_status != "TERMINATED":
        return UNFINISHED
    return COMPLETED if last.get("step", 0) >= last["planned_steps"] else STOPPED


def results_table(analysis: tune.ExperimentAnalysis, keys: Sequence[str],
                  settings: SweepSettings) -> list[dict[str, Any]]:
    """One row per trial: trial_id, status, the space's keys, the final metric, iterations, error."""
    rows = []
    for trial, result in zip(analysis.trials, tune.ResultGrid(analysis), strict=True):  # same order
        last = trial.last_result or {}
        metric = last.get(settings.metric)
        rows.append({
            "trial_id": trial.trial_id,
            "status": trial_status(str(trial.status), last),
            **{key: _plain(trial.config.get(key)) for key in keys},
            settings.metric: float(metric) if _is_number(metric) else None,
            "iterations": int(last.get("training_iteration", 0)),
            "error": short_error(result.error) or ("" if "planned_steps" in last else "no result reported"),
        })
    return rows


def _plain(value: Any) -> Any:
    """numpy scalars -> Python scalars (for YAML and Parquet)."""
    return value.item() if hasattr(value, "item") and not isinstance(value, list | dict) else value


def best_row(table: Sequence[Mapping[str, Any]], metric: str, mode: str) -> dict[str, Any] | None:
    """The row with the best final ``metric`` (None if no trial reported it)."""
    scored = [row for row in table if row["status"] != ERROR and row[metric] is not None]
    if not scored:
        return None
    pick = min if mode == "min" else max
    return dict(pick(scored, key=lambda row: row[metric]))


def check_outcome(table: Sequence[Mapping[str, Any]], expected: int) -> None:
    """Raise :class:`SweepInterrupted` for unfinished trials, :class:`SweepFailed` if all failed."""
    unfinished = sum(row["status"] == UNFINISHED for row in table) + max(0, expected - len(table))
    if unfinished:
        raise SweepInterrupted(f"{unfinished} of {max(expected, len(table))} trial(s) did not finish; "
                               "run the same command again to resume", list(table))
    if all(row["status"] == ERROR for row in table):
        raise SweepFailed(f"all {len(table)} trial(s) failed", list(table))


def markdown_table(table: Sequence[Mapping[str, Any]], columns: Sequence[str]) -> str:
    """A GitHub Markdown table of ``columns`` (floats with 6 significant digits; pipes escaped)."""
    def cell(value: Any) -> str:
        if isinstance(value, float):
            return f"{value:.6g}"
        return "" if value is None else str(value).replace("|", "\\|").replace("\n", " ")

    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(cell(row.get(c)) for c in columns) + " |" for row in table]
    return "\n".join(lines) + "\n"


def _parquet_table(table: Sequence[Mapping[str, Any]]) -> pa.Table:
    """The rows as an Arrow table; a column of mixed types is written as strings."""
    try:
        return pa.Table.from_pylist(list(table))
    except (pa.ArrowInvalid, pa.ArrowTypeError):
        columns = {key: [row[key] for row in table] for key in table[0]}
        arrays = {}
        for key, values in columns.items():
            try:
                arrays[key] = pa.array(values)
            except (pa.ArrowInvalid, pa.ArrowTypeError):
                arrays[key] = pa.array([None if v is None else str(v) for v in values])
        return pa.table(arrays)


def write_outputs(out_dir: Path, stage: str, table: list[dict[str, Any]], best: Mapping[str, Any],
                  space: Mapping[str, Dimension], settings: SweepSettings, experiment_path: str) -> None:
    """Atomically write results.parquet and results.md (both best first) and best_params.yaml to ``out_dir``.

    best_params.yaml holds the best trial's values of the varied keys only: a key the space fixed (e.g. a
    shorter ``loop.max_steps`` for the sweep) is named in a comment, not carried over to the stage's params.
    """
    keys = list(space)
    varied = [key for key, dim in space.items() if dim.kind != "fixed"]
    fixed = {key: dim.args[0] for key, dim in space.items() if dim.kind == "fixed"}
    scored = sorted((r for r in table if r[settings.metric] is not None), key=lambda r: r[settings.metric],
                    reverse=settings.mode == "max")
    ordered = scored + [r for r in table if r[settings.metric] is None]
    columns = ["trial_id", "status", *keys, settings.metric, "iterations", "error"]
    header = (f"# Sweep of {stage}\n\n{len(table)} trial(s); best {settings.metric} ({settings.mode}) "
              f"{best[settings.metric]:.6g} by trial {best['trial_id']}. Experiment: `{experiment_path}`\n\n")
    best_yaml = (f"# Best of the {stage} sweep: {settings.metric} {best[settings.metric]:.6g} (trial "
                 f"{best['trial_id']}). Use with `dvc exp run -S {stage}.<key>=<value>` or copy into conf/.\n")
    if fixed:
        best_yaml += ("# Fixed for every trial, so not carried over: "
                      f"{', '.join(f'{key}={value!r}' for key, value in fixed.items())}\n")
    best_yaml += yaml.safe_dump({stage: nest_keys({key: best[key] for key in varied})}, sort_keys=False)
    with atomic_directory(out_dir, owner="sweep") as tmp:
        pq.write_table(_parquet_table(ordered), tmp / "results.parquet")
        (tmp / "results.md").write_text(header + markdown_table(ordered, columns), encoding="utf-8")
        (tmp / "best_params.yaml").write_text(best_yaml, encoding="utf-8")


def ranking_settings(settings: SweepSettings, target: SweepTarget) -> SweepSettings:
    """``settings`` with ``metric``/``mode`` resolved: the ones set there, else the target's.

    Another metric than the target's needs its own ``mode``: the target's belongs to its own metric (a
    loss ranked with an accuracy's ``max`` would pick the worst trial); a SweepConfigError says so.
    """
    if settings.metric not in (None, target.metric) and settings.mode is None:
        raise SweepConfigError(f"sweep.settings.metric={settings.metric!r}: give sweep.settings.mode too (min or "
                               f"max); {target.stage}'s mode {target.mode!r} is that of its metric {target.metric!r}")
    return replace(settings, metric=settings.metric or target.metric, mode=settings.mode or target.mode)


def dimension_values(dim: Dimension) -> list[Any]:
    """The values of ``dim`` checked before a sweep: every value of a grid or a choice, the bounds of a
    range (the upper one just inside it, as Tune draws below it)."""
    if dim.kind in ("grid", "choice"):
        return list(dim.args[0])
    if dim.kind == "fixed":
        return [dim.args[0]]
    low, high = dim.args
    return [low, high - 1] if dim.kind == "randint" else [low, math.nextafter(high, low)]


def check_space_values(target: SweepTarget, params: dict, space: Mapping[str, Dimension]) -> None:
    """Every value of :func:`dimension_values`, applied alone to ``params`` (with the space's fixed values),
    through ``target.checks``: a value the stage refuses (``lr: grid([1e-3, -1])``) is a
    :class:`SweepConfigError` naming the sweep key, before Ray starts, not a failed trial after others
    trained. The params themselves are checked first (their error is the stage's own). Values are checked
    one at a time, so a bad combination of good values is left to the trial."""
    try:
        for check in target.checks:
            check(params)
    except ValueError as err:
        raise SweepConfigError(str(err)) from None
    fixed = {key: dim.args[0] for key, dim in space.items() if dim.kind == "fixed"}
    for key, dim in space.items():
        for value in dimension_values(dim):
            trial = apply_trial(params, target.stage, fixed | {key: value})
            for check in target.checks:
                try:
                    check(trial)
                except ValueError as err:
                    raise SweepConfigError(f"sweep.{target.stage}.{key}: a trial would take {value!r}, which the "
                                           f"stage refuses: {err}") from None


def check_loop_config(target: SweepTarget, params: dict) -> dict:
    """Build the swept run's loop config once from ``params`` (returned): its checks and inputs, before any work.

    A ValueError of the stage's checks is a :class:`SweepConfigError`; a missing input (e.g. no
    feature store) stays a FileNotFoundError.
    """
    try:
        return target.loop_config(params)
    except SweepConfigError:
        raise
    except ValueError as err:
        raise SweepConfigError(str(err)) from None


@dataclass(frozen=True)
class SweepPlan:
    """A sweep checked before Ray starts (:func:`plan_sweep`): what :func:`run_sweep` runs."""

    settings: SweepSettings
    space: dict[str, Dimension]
    name: str
    opts: RayOptions
    storage: str
    out_dir: Path

    def describe(self) -> str:
        """The plan as ``--cfg`` prints it: the space, the ranking, the trials and their resources."""
        s, o = self.settings, self.opts
        cpus = o.cpus_per_worker + s.trial_cpus / o.num_workers  # as configured (the driver's share included)
        lines = [f"sweep {self.name}: {expected_trials(self.space, s.num_samples)} trial(s), ranked by {s.metric} "
                 f"({s.mode}), scheduler {s.scheduler}",
                 *(f"  {key}: {dim.kind}({', '.join(map(repr, dim.args))})" for key, dim in self.space.items()),
                 f"  each trial: {o.num_workers} Ray Train worker(s) x {cpus:g} CPU(s); storage {self.storage}; "
                 f"outputs {self.out_dir}"]
        return "\n".join(lines)


def plan_sweep(target: SweepTarget, params: dict, repo_root: Path) -> SweepPlan:
    """Every check that needs no Ray: the shared sections (``ray`` above all), ``sweep.settings``, the space
    and each value it can give (:func:`check_space_values`), the stage's params and inputs (its loop config
    is built once) and the output folder. Raises :class:`SweepConfigError` (or FileNotFoundError for a
    missing input)."""
    stage = target.stage
    problems = check_shared(params, ())
    if problems:
        raise SweepConfigError("\n".join(problems))
    sweep = params.get("sweep") or {}
    settings = ranking_settings(SweepSettings.from_dict(sweep.get("settings")), target)
    space = parse_space(stage, sweep.get(stage), params[stage])
    check_space_values(target, params, space)
    opts = trial_ray_options(params, settings)
    loop = check_loop_config(target, params)
    out_dir = repo_root / params["paths"]["artifacts"] / "sweeps" / stage
    check_output(out_dir, owner="sweep")
    identity = run_fingerprint(target.module, target.inputs, loop) if target.module else ""
    workers = {"num_workers": opts.num_workers, "cpus_per_worker": opts.cpus_per_worker, "use_gpu": opts.use_gpu}
    name = experiment_name(stage, space, settings, params[stage], identity, workers)
    return SweepPlan(settings, space, name, opts, ray_storage(params), out_dir)


def run_sweep(target: SweepTarget, params: dict, repo_root: Path, *, callbacks: Sequence[Any] = ()) -> SweepResult:
    """Sweep ``target`` as ``params['sweep']`` declares; write ``<paths.artifacts>/sweeps/<stage>/``.

    Checks everything :func:`plan_sweep` checks first, then connects to Ray like the runner (an
    initialised Ray is reused; else ``ray.address`` / ``$RAY_ADDRESS`` / a local cluster). Raises
    :class:`SweepConfigError` on a bad space or settings, :class:`SweepInterrupted` or
    :class:`SweepFailed` (nothing written) otherwise. ``callbacks`` are Tune callbacks of a new
    experiment (a restored one keeps its own).
    """
    plan = plan_sweep(target, params, repo_root)
    settings, space, opts, storage = plan.settings, plan.space, plan.opts, plan.storage
    started = ensure_ray(opts.address, opts.runtime_env)
    try:
        concurrency = max_concurrent(settings, opts)  # before the prerequisite: a trial must fit
        overrides = {}
        if target.prerequisite is not None:
            prerequisites = plan.out_dir.parent / f"{target.stage}-prerequisites"
            overrides = target.prerequisite(params, prerequisites, storage)
        job = SweepJob(target, params, overrides, opts, storage)
        analysis, restored = _fit(job, space, settings, plan.name, concurrency, callbacks)
    finally:
        if started:
            ray.shutdown()
    table = results_table(analysis, list(space), settings)
    check_outcome(table, expected_trials(space, settings.num_samples))
    best = best_row(table, settings.metric, settings.mode)
    if best is None:
        raise SweepFailed(f"no trial reported {settings.metric!r}", table)
    write_outputs(plan.out_dir, target.stage, table, best, space, settings, analysis.experiment_path)
    return SweepResult(plan.out_dir, analysis.experiment_path, settings.metric, table, best, restored)
