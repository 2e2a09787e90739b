"""The one training runner: a stage's :class:`TrainSpec` run as a Ray Train job, or in-process.

A stage describes *what* to train; the runner owns *how*::

    spec = TrainSpec(build=build, dataset=dataset, step=step)
    result = run_training("train_vae", spec, params["train_vae"], params["ray"],
                          out_dir=Path("artifacts/train_vae"), storage="/abs/ray_storage")

* ``build(config) -> Components``: models (on CPU), their optimisers, optional EMA decays
  and frozen helpers (a teacher, a VAE) that are neither trained nor checkpointed.
* ``dataset(config) -> torch Dataset`` (map-style).
* ``step(batch, ctx) -> {name: loss}``: one training step. It calls ``ctx.update(loss,
  "optimiser name")`` for each optimiser it steps (zero_grad, backward, grad clipping,
  optimiser step); the runner then steps the LR schedules and EMAs and logs the losses.

The per-worker loop (:func:`train_loop`) is the same code under Ray Train and in-process:
per-rank seeding, DDP (``prepare_model``, only when world_size > 1; a spec with ``ddp=False``
keeps its models unwrapped and averages gradients in ``ctx.update`` instead), a
``DistributedSampler`` whose order is a pure function of (seed, epoch), a per-epoch seeded
``torch.Generator`` for the DataLoader, cosine-with-warm-up LR, EMA, and a checkpoint
every ``checkpoint_every`` steps holding everything needed to continue bit-exactly
(models, optimisers, schedulers, EMA, step, epoch and position in the epoch, RNG states of
every rank, loss history, start steps of every attempt).

Runner keys read from the loop config (everything else is the stage's): ``seed``,
``batch_size`` (per worker), ``max_steps``, ``grad_clip`` (0 = off), ``lr_schedule``
("cosine" | "constant"), ``warmup_steps``, ``min_lr_ratio``, ``log_every``,
``num_data_workers``, ``length_buckets`` (:class:`LoopSettings`; a stage's ``loop`` params
group holds exactly these). Ray keys: see :class:`RayOptions`.

Runs are named ``<stage>-<hash of loop config, worker count and fingerprint>``, where the
fingerprint (:mod:`pipelines.identity`) covers the code the stage imports and its inputs'
contents: an interrupted run of the same params, code and inputs resumes from Ray storage;
changed params, code or inputs start afresh from step 0. ``ray.train.report`` is
called on all ranks only at checkpoint (and ``report_every``) steps, because a report
blocks while the previous one waits for the controller's poll (2 s by default).
"""

from __future__ import annotations

import contextlib
import hashlib
import itertools
import json
import math
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from torch import nn
from torch.optim import Optimizer
from torch.utils.data import DataLoader, Dataset, DistributedSampler

from data.atomic import atomic_directory, check_output
from pipelines import checkpoint as ckpt
from pipelines import tracking
from pipelines.config import check_number, refuse
from pipelines.devices import deterministic_gpu
from pipelines.schedules import EMA, make_scheduler

#: Offset between the RNG seeds of consecutive ranks (a prime, far from small seeds).
RANK_SEED_STRIDE = 1_000_003
#: Ranks an epoch seed keeps apart (:func:`epoch_seed`: the rank is its low 10 bits).
EPOCH_SEED_RANKS = 1024
#: The largest seed torch and numpy take everywhere (a signed 64-bit integer).
INT64_MAX = 2**63 - 1


# --------------------------------------------------------------------------- stage API


@dataclass
class Components:
    """What ``TrainSpec.build`` returns.

    Attributes:
        models: trainable (and checkpointed) modules, on CPU; the runner moves them.
        optimizers: one optimiser per independently stepped group, built on
            ``models[...].parameters()``.
        ema: ``{model name: decay}`` for models that get an exponential moving average.
        frozen: helpers used by ``step`` but never trained or checkpointed (moved to the
            device if they are modules).
    """

    models: dict[str, nn.Module]
    optimizers: dict[str, Optimizer]
    ema: dict[str, float] = field(default_factory=dict)
    frozen: dict[str, Any] = field(default_factory=dict)


StepFn = Callable[[Any, "StepContext"], Mapping[str, "float | torch.Tensor"]]


class TrainingError(ValueError):
    """The training itself went wrong in a way that repeats on every attempt (e.g. a NaN loss).

    A ``ValueError``, so a stage's command line prints it as one line; never retried (see
    :func:`fit_retrying`).
    """


@dataclass(frozen=True)
class TrainSpec:
    """A stage's training recipe. Functions must be importable (module level) for Ray.

    ``ddp``: with several workers, wrap the trained models in DistributedDataParallel (the default).
    ``False`` leaves them unwrapped for steps DDP cannot run (EMDM's R1 backpropagates twice through
    its discriminator): every rank starts from rank 0's weights and :meth:`StepContext.update`
    averages each optimiser's gradients over the ranks before clipping, which is what DDP computes.
    """

    build: Callable[[dict], Components]
    dataset: Callable[[dict], Dataset]
    step: StepFn
    collate: Callable[[list], Any] | None = None
    ddp: bool = True


@dataclass
class StepContext:
    """Everything ``TrainSpec.step`` may use; ``models`` may be DDP-wrapped."""

    config: dict
    models: dict[str, nn.Module]
    optimizers: dict[str, Optimizer]
    ema: dict[str, EMA]
    frozen: dict[str, Any]
    device: torch.device
    rank: int
    world_size: int
    grad_clip: float
    step: int = 0
    epoch: int = 0
    extra_metrics: dict[str, torch.Tensor] = field(default_factory=dict)
    average_grads: bool = False  # several ranks without DDP: update() averages the gradients

    def unwrap(self, name: str) -> nn.Module:
        """``models[name]`` without its DDP wrapper."""
        return _unwrap(self.models[name])

    def update(self, loss: torch.Tensor, optimizer: str | None = None) -> None:
        """zero_grad, backward, clip (``grad_clip`` > 0) and step one optimiser.

        ``optimizer`` may be omitted when the spec has a single optimiser. The gradient
        norm is logged as ``grad_norm/<name>`` when clipping is on.
        """
        name = optimizer if optimizer is not None else _only_key(self.optimizers)
        opt = self.optimizers[name]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        params = [p for g in opt.param_groups for p in g["params"] if p.grad is not None]
        if self.average_grads:
            average_over_ranks([p.grad for p in params], self.world_size)
        if self.grad_clip > 0:
            norm = torch.nn.utils.clip_grad_norm_(params, self.grad_clip)
            self.extra_metrics[f"grad_norm/{name}"] = norm.detach()
        opt.step()


# --------------------------------------------------------------------------- settings


@dataclass(frozen=True)
class LoopSettings:
    """Runner keys of the loop config (see the module docstring)."""

    seed: int = 0
    batch_size: int = 32
    max_steps: int = 1000
    grad_clip: float = 0.0
    lr_schedule: str = "cosine"
    warmup_steps: int = 0
    min_lr_ratio: float = 0.0
    log_every: int = 50
    num_data_workers: int = 0
    length_buckets: int = 0

    @classmethod
    def from_config(cls, config: Mapping[str, Any]) -> LoopSettings:
        """Pick the runner keys out of a stage's loop config (defaults for missing ones)."""
        return cls(**{f.name: config[f.name] for f in fields(cls) if f.name in config})

    @classmethod
    def parse(cls, section: Mapping[str, Any], where: str) -> LoopSettings:
        """A stage's ``loop`` params group, validated: every key present, no other, types checked.

        Besides :data:`LOOP_BOUNDS`: ``seed`` at most :func:`max_seed` of ``max_steps`` (its epoch seeds
        fit int64), and no ``warmup_steps`` or ``min_lr_ratio`` with ``lr_schedule: constant`` (which would
        ignore them).
        ``where`` names the group in errors (e.g. ``train_vae.loop``).
        """
        names = [f.name for f in fields(cls)]
        if not isinstance(section, Mapping):
            raise ValueError(f"{where}: expected a mapping with keys {names}, got {section!r}")
        unknown = sorted(set(section) - set(names))
        missing = [name for name in names if name not in section]
        if unknown or missing:
            raise ValueError(f"{where}: unknown key(s) {unknown}, missing key(s) {missing}; "
                             f"a loop group holds exactly {names}")
        for f in fields(cls):
            value, kind = section[f.name], type(f.default)
            allowed = (int, float) if kind is float else kind  # an int is a valid float
            if isinstance(value, bool) or not isinstance(value, allowed):
                raise ValueError(f"{where}.{f.name}: expected {kind.__name__}, got {value!r}")
        if section["lr_schedule"] not in ("cosine", "constant"):
            raise ValueError(f"{where}.lr_schedule: {section['lr_schedule']!r} is not cosine or constant")
        for key, (low, high) in LOOP_BOUNDS.items():
            check_number(section, key, where, low=low, high=high, integer=isinstance(getattr(cls, key), int))
        highest = max_seed(section["max_steps"])
        if section["seed"] > highest:
            refuse(f"{where}.seed: expected an integer >= 0 and <= {highest} (with max_steps {section['max_steps']}, "
                   f"so that every epoch seed (seed*{RANK_SEED_STRIDE} + epoch)*{EPOCH_SEED_RANKS} + rank stays "
                   f"within int64), got {section['seed']!r}")
        if section["lr_schedule"] == "constant":
            for key, value in (("warmup_steps", section["warmup_steps"]), ("min_lr_ratio", section["min_lr_ratio"])):
                if value:
                    refuse(f"{where}.{key}: {value!r} has no effect with lr_schedule constant; expected 0 (or "
                           f"lr_schedule cosine)")
        return cls(**{f.name: section[f.name] for f in fields(cls)})


#: The range of each numeric key of a loop group (low, high; None: unbounded), checked by :meth:`LoopSettings.parse`.
LOOP_BOUNDS: dict[str, tuple[float, float | None]] = {
    "seed": (0, None), "batch_size": (1, None), "max_steps": (1, None), "grad_clip": (0.0, None),
    "warmup_steps": (0, None), "min_lr_ratio": (0.0, 1.0), "log_every": (1, None), "num_data_workers": (0, None),
    "length_buckets": (0, None)}


@dataclass(frozen=True)
class RayOptions:
    """The ``ray`` params section.

    Attributes:
        address: cluster to join (None: ``$RAY_ADDRESS``, else start a local one).
        num_workers: Train workers; 0 runs the loop in-process without Ray.
        use_gpu: "auto" (GPUs if the cluster has one per worker), True or False.
        cpus_per_worker: logical CPUs per worker (also its torch thread count).
        max_failures: restarts from the latest checkpoint after a worker crash (-1: no limit);
            deterministic errors are never retried (:func:`fit_retrying`).
        checkpoint_every: steps between checkpoints (not part of the run name).
        report_every: steps between metric-only reports (e.g. for Tune); 0 = only at
            checkpoints. Keep it coarse: each report may wait for the controller's poll.
        storage: Ray storage (absolute path or URI); ``run_training(storage=...)`` wins.
        local: run in-process even if ``num_workers`` > 0.
        placement_strategy: "PACK" or "SPREAD" (one worker per node where possible).
        runtime_env: passed to ``ray.init`` when this process starts or joins a cluster.
        wandb_project: W&B project name.
    """

    address: str | None = None
    num_workers: int = 1
    use_gpu: str | bool = "auto"
    cpus_per_worker: float = 1.0
    max_failures: int = 2
    checkpoint_every: int = 100
    report_every: int = 0
    storage: str | None = None
    local: bool = False
    placement_strategy: str = "PACK"
    runtime_env: dict | None = None
    wandb_project: str = "motionforge"

    @classmethod
    def from_dict(cls, cfg: Mapping[str, Any] | None) -> RayOptions:
        """Validate and convert the ``ray`` params section (unknown keys are an error)."""
        cfg = dict(cfg or {})
        unknown = set(cfg) - {f.name for f in fields(cls)}
        if unknown:
            raise ValueError(f"unknown ray option(s): {sorted(unknown)}")
        return cls(**cfg)

    @property
    def in_process(self) -> bool:
        """True when the loop runs in this process without Ray."""
        return self.local or self.num_workers == 0


@dataclass(frozen=True)
class RunInfo:
    """Per-run settings the driver hands to every worker (with absolute paths)."""

    stage: str
    run_name: str
    checkpoint_every: int
    report_every: int
    torch_threads: int
    wandb_mode: str
    wandb_dir: str | None
    wandb_project: str
    use_gpu: bool


@dataclass
class RunResult:
    """What :func:`run_training` returns."""

    run_name: str
    out_dir: Path
    metrics: dict[str, float]
    history: list[dict[str, Any]]
    attempts: list[int]
    run_path: str | None


# --------------------------------------------------------------------------- sessions


class Session(Protocol):
    """What the loop needs from its environment (Ray Train or this process)."""

    rank: int
    world_size: int
    device: torch.device

    def latest_checkpoint(self) -> contextlib.AbstractContextManager[Path | None]:
        """Directory of the checkpoint to resume from, if any."""

    def report(self, metrics: dict[str, Any], checkpoint_dir: Path | None) -> None:
        """Report metrics (all ranks) with this rank's checkpoint directory, if any."""

    def wrap(self, model: nn.Module) -> nn.Module:
        """Make a model data-parallel (identity for one process)."""


class LocalSession:
    """In-process session: rank 0 of 1; keeps the latest checkpoint in a temp dir."""

    def __init__(self, device: torch.device) -> None:
        self.rank, self.world_size, self.device = 0, 1, device
        self._root = Path(tempfile.mkdtemp(prefix="motionforge-local-"))
        self.latest: Path | None = None
        self.reports: list[dict[str, Any]] = []

    @contextlib.contextmanager
    def latest_checkpoint(self) -> Iterator[Path | None]:
        """Local runs always start fresh."""
        yield None

    def report(self, metrics: dict[str, Any], checkpoint_dir: Path | None) -> None:
        """Keep the metrics and a copy of the checkpoint (the caller deletes its own)."""
        self.reports.append(dict(metrics))
        if checkpoint_dir is not None:
            dst = self._root / f"checkpoint_{len(self.reports):06d}"
            shutil.copytree(checkpoint_dir, dst)
            if self.latest is not None:
                shutil.rmtree(self.latest)
            self.latest = dst

    def wrap(self, model: nn.Module) -> nn.Module:
        """No data parallelism in one process."""
        return model

    def close(self) -> None:
        """Delete the kept checkpoint."""
        shutil.rmtree(self._root, ignore_errors=True)


class RaySession:
    """Session inside a Ray Train worker."""

    def __init__(self) -> None:
        import ray.train
        import ray.train.torch

        context = ray.train.get_context()
        self.rank = context.get_world_rank()
        self.world_size = context.get_world_size()
        self.device = ray.train.torch.get_device()

    @contextlib.contextmanager
    def latest_checkpoint(self) -> Iterator[Path | None]:
        """The latest checkpoint that Ray restored for this attempt, if any."""
        import ray.train

        checkpoint = ray.train.get_checkpoint()
        if checkpoint is None:
            yield None
            return
        with checkpoint.as_directory() as directory:
            yield Path(directory)

    def report(self, metrics: dict[str, Any], checkpoint_dir: Path | None) -> None:
        """``ray.train.report`` (a barrier: every rank calls it the same number of times)."""
        import ray.train

        checkpoint = None if checkpoint_dir is None else ray.train.Checkpoint.from_directory(checkpoint_dir)
        ray.train.report(metrics, checkpoint=checkpoint)

    def wrap(self, model: nn.Module) -> nn.Module:
        """DDP via ``prepare_model`` when there is more than one worker."""
        if self.world_size == 1 or not any(p.requires_grad for p in model.parameters()):
            return model
        import ray.train.torch

        return ray.train.torch.prepare_model(model, move_to_device=False)


# --------------------------------------------------------------------------- the loop


@dataclass
class Position:
    """Where the run is: global step, epoch and batches already taken from that epoch."""

    step: int = 0
    epoch: int = 0
    batch: int = 0

    def advance(self, batches_per_epoch: int) -> None:
        """One step further; roll over to the next epoch at its end."""
        self.step += 1
        self.batch += 1
        if self.batch == batches_per_epoch:
            self.epoch, self.batch = self.epoch + 1, 0


@dataclass
class _Run:
    """The mutable state of one attempt of the loop on one rank."""

    models: dict[str, nn.Module]
    raw: dict[str, nn.Module]
    optimizers: dict[str, Optimizer]
    schedulers: dict[str, Any]
    emas: dict[str, EMA]
    frozen: dict[str, Any]
    pos: Position = field(default_factory=Position)
    history: list[dict[str, Any]] = field(default_factory=list)
    attempts: list[int] = field(default_factory=list)
    device: str = "cpu"

    def state(self) -> dict[str, Any]:
        """The rank-0 part of a checkpoint."""
        return {
            **asdict(self.pos),
            "models": ckpt.state_dicts(self.raw),
            "optimizers": ckpt.state_dicts(self.optimizers),
            "schedulers": ckpt.state_dicts(self.schedulers),
            "ema": ckpt.state_dicts(self.emas),
            "history": self.history,
            "attempts": self.attempts,
            "device": self.device,
        }

    def load(self, state: Mapping[str, Any]) -> None:
        """Continue from a checkpoint's rank-0 state."""
        ckpt.load_state_dicts(self.raw, state["models"])
        ckpt.load_state_dicts(self.optimizers, state["optimizers"])
        ckpt.load_state_dicts(self.schedulers, state["schedulers"])
        ckpt.load_state_dicts(self.emas, state["ema"])
        self.pos = Position(state["step"], state["epoch"], state["batch"])
        self.history = list(state["history"])
        self.attempts = list(state["attempts"])


def _only_key(mapping: Mapping[str, Any]) -> str:
    """The single key of a mapping (an error if there are several)."""
    if len(mapping) != 1:
        raise ValueError(f"name the optimiser to step, one of {sorted(mapping)}")
    return next(iter(mapping))


def _unwrap(model: nn.Module) -> nn.Module:
    """A DDP/FSDP-wrapped model's inner module."""
    return getattr(model, "module", model)


def average_over_ranks(tensors: Sequence[torch.Tensor], world_size: int) -> None:
    """Replace each tensor by its mean over the process group's ``world_size`` ranks (one all-reduce of
    a flat buffer). Every rank must pass tensors of the same shapes in the same order."""
    import torch.distributed as dist

    if not tensors:
        return
    flat = torch.cat([t.reshape(-1) for t in tensors])
    dist.all_reduce(flat)
    flat /= world_size
    offset = 0
    for t in tensors:
        t.copy_(flat[offset : offset + t.numel()].view_as(t))
        offset += t.numel()


def broadcast_from_rank0(model: nn.Module) -> None:
    """Copy rank 0's parameters and buffers to every rank, as DDP does when it wraps a model."""
    import torch.distributed as dist

    with torch.no_grad():
        for tensor in [*model.parameters(), *model.buffers()]:
            dist.broadcast(tensor, src=0)


def to_device(batch: Any, device: torch.device) -> Any:
    """Move every tensor in a (nested) batch to ``device``."""
    if isinstance(batch, torch.Tensor):
        return batch.to(device, non_blocking=True)
    if isinstance(batch, Mapping):
        return {k: to_device(v, device) for k, v in batch.items()}
    if isinstance(batch, list | tuple):
        return type(batch)(to_device(v, device) for v in batch)
    return batch


def epoch_seed(seed: int, epoch: int, rank: int) -> int:
    """Seed of ``rank``'s length buckets and DataLoader workers in ``epoch`` (distinct per epoch and rank)."""
    return (seed * RANK_SEED_STRIDE + epoch) * EPOCH_SEED_RANKS + rank


def max_seed(max_steps: int) -> int:
    """The largest loop ``seed`` whose :func:`epoch_seed` stays within int64 for every epoch a run of
    ``max_steps`` can reach (an epoch holds at least one step: epoch <= max_steps) and every rank below
    :data:`EPOCH_SEED_RANKS`; every other seed the runner derives (:func:`rank_seed` + step, the sampler's
    seed + epoch) is smaller."""
    return ((INT64_MAX - (EPOCH_SEED_RANKS - 1)) // EPOCH_SEED_RANKS - max_steps) // RANK_SEED_STRIDE


def rank_seed(seed: int, rank: int) -> int:
    """Seed of the step-level RNG of ``rank`` (distinct per rank, e.g. diffusion noise)."""
    return seed + RANK_SEED_STRIDE * (rank + 1)


def _build(spec: TrainSpec, config: dict, s: LoopSettings, session: Session) -> _Run:
    """Seed, build the components on the device, and wrap schedulers and EMAs around them."""
    ckpt.seed_everything(s.seed)  # identical initial weights on every rank
    comps = spec.build(config)
    raw = {name: m.to(session.device) for name, m in comps.models.items()}
    for name, helper in comps.frozen.items():
        if isinstance(helper, nn.Module):
            comps.frozen[name] = helper.to(session.device)
    schedulers = {
        name: make_scheduler(opt, s.lr_schedule, s.warmup_steps, s.max_steps, s.min_lr_ratio)
        for name, opt in comps.optimizers.items()
    }
    emas = {name: EMA(raw[name], decay) for name, decay in comps.ema.items()}
    return _Run(dict(raw), raw, comps.optimizers, schedulers, emas, comps.frozen)


def _restore(run: _Run, session: Session, s: LoopSettings) -> None:
    """Load the latest checkpoint (state + this rank's RNG) or seed this rank afresh."""
    with session.latest_checkpoint() as directory:
        if directory is None:
            ckpt.seed_everything(rank_seed(s.seed, session.rank))
            return
        run.load(ckpt.load_state(directory))  # rank 0's file; Ray merged all ranks' dirs
        if not ckpt.load_rng(directory, session.rank, session.device):
            ckpt.seed_everything(rank_seed(s.seed, session.rank) + run.pos.step)


def bucket_by_length(indices: Sequence[int], lengths: np.ndarray, batch_size: int, pool_batches: int,
                     seed: int) -> list[int]:
    """One epoch's item order in which every batch holds items of similar length.

    The epoch's full batches (``len(indices) // batch_size`` of them, in the sampler's random
    order) are cut into pools of ``pool_batches`` batches; each pool is sorted by length (stable)
    and cut back into batches, and the batches of the whole epoch are then shuffled with ``seed``.
    Every batch is still a random draw from a random pool, but its padding (and so the cost of a
    step on a length-trimmed batch) shrinks. The same items as the full batches of ``indices``,
    a pure function of its arguments (exact resume holds); the incomplete last batch is dropped,
    as ``drop_last`` does.
    """
    if pool_batches < 1:
        raise ValueError(f"length_buckets must be >= 1 batches per pool, got {pool_batches}")
    n = len(indices) // batch_size * batch_size
    items = np.asarray(indices[:n], dtype=np.int64)
    batches: list[np.ndarray] = []
    for start in range(0, n, pool_batches * batch_size):
        pool = items[start:start + pool_batches * batch_size]
        pool = pool[np.argsort(lengths[pool], kind="stable")]
        batches.extend(pool.reshape(-1, batch_size))
    order = np.random.default_rng(seed).permutation(len(batches))
    return [int(i) for b in order for i in batches[b]]


def _epoch_batches(dataset: Dataset, spec: TrainSpec, s: LoopSettings, session: Session,
                   pos: Position) -> Iterator[Any]:
    """The rest of epoch ``pos.epoch`` from batch ``pos.batch`` on, in its fixed order.

    A dataset's own draws (a caption, a crop) come from the torch RNG of the process that loads the
    item. In-process (``num_data_workers: 0``) that is the rank's RNG, which checkpoints save, so the
    loader starts at ``pos.batch``. DataLoader workers seed theirs afresh with each loader and take the
    batches in turn, so a resumed epoch loads its first ``pos.batch`` batches again and drops them: each
    later batch then comes from the same worker in the same RNG state as in an uninterrupted run.
    """
    sampler = DistributedSampler(dataset, num_replicas=session.world_size, rank=session.rank,
                                 shuffle=True, seed=s.seed, drop_last=True)
    sampler.set_epoch(pos.epoch)
    seed = epoch_seed(s.seed, pos.epoch, session.rank)
    indices = list(sampler)
    if s.length_buckets:
        lengths = getattr(dataset, "lengths", None)
        if lengths is None:
            raise ValueError(f"length_buckets needs a dataset with a `lengths` array; "
                             f"{type(dataset).__name__} has none")
        indices = bucket_by_length(indices, np.asarray(lengths), s.batch_size, s.length_buckets, seed)
    skip = pos.batch if s.num_data_workers else 0
    indices = indices[(pos.batch - skip) * s.batch_size:]
    generator = torch.Generator().manual_seed(seed)  # DataLoader worker seeds
    loader = DataLoader(dataset, batch_size=s.batch_size, sampler=indices, drop_last=True,
                        num_workers=s.num_data_workers, collate_fn=spec.collate, generator=generator)
    return itertools.islice(loader, skip, None)


def _batches_per_epoch(dataset: Dataset, s: LoopSettings, world_size: int) -> int:
    """Full batches per rank per epoch (an error if the dataset is too small)."""
    n = (len(dataset) // world_size) // s.batch_size  # type: ignore[arg-type]
    if n == 0:
        raise ValueError(f"dataset of {len(dataset)} items too small for {world_size} x {s.batch_size}")  # type: ignore[arg-type]
    return n


class _Window:
    """Sums of step metrics since the last log (tensors stay on device until logged)."""

    def __init__(self) -> None:
        self.sums: dict[str, Any] = {}
        self.counts: dict[str, int] = {}

    def add(self, metrics: Mapping[str, Any]) -> None:
        """Accumulate one step's detached metrics (a key may be missing on some steps)."""
        for k, v in metrics.items():
            self.sums[k] = self.sums[k] + v if k in self.sums else v
            self.counts[k] = self.counts.get(k, 0) + 1

    def pop(self) -> dict[str, float]:
        """Per-key means since the last pop, as floats; resets the window."""
        means = {k: float(v) / self.counts[k] for k, v in self.sums.items()}
        self.sums, self.counts = {}, {}
        return means


def _log_row(run: _Run, means: Mapping[str, float], progress: tracking.Progress, s: LoopSettings,
             session: Session, wandb_run: Any) -> dict[str, Any]:
    """Log the closed window's ``means``: history row, progress line and W&B on rank 0."""
    rate = progress.rate(run.pos.step)
    lr = next(iter(run.optimizers.values())).param_groups[0]["lr"] if run.optimizers else 0.0
    row = {"step": run.pos.step, "epoch": run.pos.epoch, **means, "lr": lr,
           "steps_per_s": rate, "samples_per_s": rate * s.batch_size * session.world_size}
    if session.rank == 0:
        run.history.append(row)
        # Not print(): Ray Train V2 patches print into its logger, which echoes lines twice.
        sys.stdout.write(progress.line(run.pos.step, rate, row) + "\n")
        sys.stdout.flush()
        if wandb_run is not None:
            wandb_run.log(row, step=run.pos.step)
    return row


def _checkpoint(run: _Run, session: Session, metrics: dict[str, Any]) -> None:
    """Write this rank's part of a checkpoint and report it (all ranks)."""
    with tempfile.TemporaryDirectory(prefix="motionforge-ckpt-") as tmp:
        directory = Path(tmp)
        ckpt.save_rng(directory, session.rank, session.device)
        if session.rank == 0:
            ckpt.save_state(directory, run.state())
        session.report(metrics, directory)


class FiniteGuard:
    """Stops the run at the first non-finite loss or gradient norm of any step.

    It watches each step's metrics (the stage's losses and, where clipping computes it,
    ``grad_norm/<optimiser>``) without adding work to the step. Reading a value off an accelerator
    is a host sync, so there the guard only keeps references to the steps' detached metrics and
    looks at the logging window's means, which the loop reads anyway when it writes a log row
    (every ``log_every`` steps and before every checkpoint or report): a NaN or inf in any step
    makes its window's mean non-finite, and only then are the kept steps read to find the first bad
    one. On a CPU device reading is free, so every step is checked at once. Either way the run
    stops with a :class:`TrainingError` naming the step and the metric, and nothing after the bad
    step is checkpointed or written.
    """

    def __init__(self, run_name: str, device: torch.device) -> None:
        self.run_name = run_name
        self.eager = device.type == "cpu"
        self.pending: list[tuple[int, Mapping[str, Any]]] = []

    def add(self, step: int, metrics: Mapping[str, Any]) -> None:
        """Step ``step``'s detached metrics: checked now on a CPU, else kept for :meth:`check`."""
        if self.eager:
            self._raise_first_bad([(step, metrics)])
        else:
            self.pending.append((step, metrics))

    def check(self, means: Mapping[str, float], step: int) -> None:
        """At a log row: raise if a mean of the window that ends at ``step`` is not finite."""
        pending, self.pending = self.pending, []
        bad = [name for name, value in means.items() if not math.isfinite(value)]
        if bad:
            self._raise_first_bad(pending)
            raise TrainingError(f"{self.run_name}: the mean of {bad[0]!r} over the steps up to step {step} is "
                                f"{means[bad[0]]} (finite values beyond float range); training stopped, "
                                f"no model written")

    def _raise_first_bad(self, steps: Sequence[tuple[int, Mapping[str, Any]]]) -> None:
        for step, metrics in steps:
            for name, value in metrics.items():
                value = float(value)
                if not math.isfinite(value):
                    what = "gradient norm" if name.startswith("grad_norm/") else "loss"
                    raise TrainingError(f"{self.run_name}: non-finite {what} {name!r} = {value} at step {step}; "
                                        f"training stopped, no model written")


def _train_step(spec: TrainSpec, run: _Run, ctx: StepContext, batch: Any) -> dict[str, Any]:
    """One step: the stage's step, then schedulers and EMAs; returns its metrics, detached."""
    ctx.step, ctx.epoch = run.pos.step, run.pos.epoch
    ctx.extra_metrics = {}
    out = dict(spec.step(to_device(batch, ctx.device), ctx))
    for scheduler in run.schedulers.values():
        scheduler.step()
    for name, ema in run.emas.items():
        ema.update(run.raw[name])
    return {k: v.detach() if isinstance(v, torch.Tensor) else float(v) for k, v in {**out, **ctx.extra_metrics}.items()}


def train_loop(session: Session, spec: TrainSpec, config: dict, info: RunInfo) -> None:
    """The per-worker loop (same code under Ray Train and in-process; its callers run it under
    :func:`deterministic_gpu`)."""
    s = LoopSettings.from_config(config)
    run = _build(spec, config, s, session)
    dataset = spec.dataset(config)  # before the RNG restore: any RNG it uses is used every attempt
    per_epoch = _batches_per_epoch(dataset, s, session.world_size)
    wandb_run = tracking.start_wandb(
        rank=session.rank, mode=info.wandb_mode, project=info.wandb_project,
        name=f"{info.run_name}-r{int(time.time())}", group=info.run_name,
        config={**config, "ray": asdict(info)}, directory=info.wandb_dir)
    _restore(run, session, s)
    run.attempts.append(run.pos.step)
    run.device = str(session.device)
    average_grads = not spec.ddp and session.world_size > 1
    if average_grads:
        for model in [*run.raw.values(), *(ema.module for ema in run.emas.values())]:
            broadcast_from_rank0(model)
    run.models = {name: session.wrap(m) if spec.ddp else m for name, m in run.raw.items()}
    ctx = StepContext(config, run.models, run.optimizers, run.emas, run.frozen, session.device,
                      session.rank, session.world_size, s.grad_clip, average_grads=average_grads)
    progress, window = tracking.Progress(info.stage, run.pos.step, s.max_steps), _Window()
    guard = FiniteGuard(info.run_name, session.device)
    last_checkpoint = -1
    try:
        while run.pos.step < s.max_steps:
            for batch in _epoch_batches(dataset, spec, s, session, run.pos):
                metrics = _train_step(spec, run, ctx, batch)
                guard.add(run.pos.step, metrics)
                window.add(metrics)
                run.pos.advance(per_epoch)
                last_checkpoint = _after_step(run, session, s, info, window, progress, wandb_run,
                                              last_checkpoint, guard)
                if run.pos.step >= s.max_steps:
                    break
        if last_checkpoint != run.pos.step:  # e.g. resumed at the end: report a final one
            _checkpoint(run, session, {"step": run.pos.step, **_last_curves(run.history)})
    finally:
        if wandb_run is not None:
            wandb_run.finish()


def _after_step(run: _Run, session: Session, s: LoopSettings, info: RunInfo, window: _Window,
                progress: tracking.Progress, wandb_run: Any, last_checkpoint: int, guard: FiniteGuard) -> int:
    """Log, checkpoint and report as the step count asks; returns the last checkpoint step.

    Every log row, checkpoint and report is preceded by the guard's check: nothing after a
    non-finite step is logged as a result or saved.
    """
    step = run.pos.step
    is_last = step >= s.max_steps
    do_ckpt = is_last or step % max(1, info.checkpoint_every) == 0
    do_report = info.report_every > 0 and step % info.report_every == 0
    if is_last or do_ckpt or do_report or step % max(1, s.log_every) == 0:
        means = window.pop()
        guard.check(means, step)
        row = _log_row(run, means, progress, s, session, wandb_run)
        metrics = {k: v for k, v in row.items() if isinstance(v, int | float)}
        if do_ckpt:
            _checkpoint(run, session, metrics)
            return step
        if do_report:
            session.report(metrics, None)
    return last_checkpoint


def _last_curves(history: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """The last history row (empty if none)."""
    return dict(history[-1]) if history else {}


def _threads_scope(threads: int) -> contextlib.AbstractContextManager[None]:
    """Run with ``threads`` torch intra-op threads, restoring the previous count after."""

    @contextlib.contextmanager
    def scope() -> Iterator[None]:
        previous = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            yield
        finally:
            torch.set_num_threads(previous)

    return scope()


def ray_train_fn(loop_input: dict) -> None:
    """Ray Train entry point: ``{"spec", "config", "info"}`` -> :func:`train_loop`."""
    info: RunInfo = loop_input["info"]
    session = RaySession()
    with _threads_scope(info.torch_threads), deterministic_gpu(session.device):
        train_loop(session, loop_input["spec"], loop_input["config"], info)


# --------------------------------------------------------------------------- the driver


def make_run_name(stage: str, loop_config: Mapping[str, Any], world_size: int, fingerprint: str = "") -> str:
    """``<stage>-<10 hex>``: a stable hash of what changes the result (params, workers, code and inputs)."""
    blob = json.dumps({"config": loop_config, "world_size": world_size, "fingerprint": fingerprint},
                      sort_keys=True, default=str)
    return f"{stage}-{hashlib.sha1(blob.encode()).hexdigest()[:10]}"


def resolve_storage(storage: str | os.PathLike | None) -> str:
    """Absolute Ray storage path or URI (default ``$MOTIONFORGE_RAY_STORAGE`` or ./.ray_storage)."""
    storage = storage or os.environ.get("MOTIONFORGE_RAY_STORAGE") or ".ray_storage"
    storage = str(storage)
    return storage if "://" in storage else str(Path(storage).expanduser().absolute())


def ensure_ray(address: str | None, runtime_env: dict | None = None) -> bool:
    """Connect to Ray unless already connected; True if this call did it.

    ``address`` (or ``$RAY_ADDRESS``) joins a cluster; with neither, Ray joins the cluster that
    ``ray start`` left running on this machine, if any, or else starts a local one. On a
    token-authenticated cluster the caller needs ``RAY_AUTH_MODE=token`` in its env.

    A local cluster starts lean, so that its helper processes take less CPU from the training: no
    metrics collection, no event-loop statistics. The dashboard stays: it serves the State API,
    which Ray Train's placement-group cleaner polls (without it the cleaner cannot tell a dead
    controller from a live one and warns every second). Workers' output still reaches the driver.
    """
    import ray
    from ray._private.services import canonicalize_bootstrap_address

    if ray.is_initialized():
        return False
    address = address or os.environ.get("RAY_ADDRESS") or None
    lean: dict[str, Any] = {}
    if address in (None, "local") and canonicalize_bootstrap_address(address) is None:  # ray.init will start one
        # A new dict on every call: ray.init adds its object-spilling settings to the one it gets.
        lean = {"_system_config": {"enable_metrics_collection": False, "event_stats": False}}
    ray.init(address=address, runtime_env=runtime_env, **lean)
    return True


@contextlib.contextmanager
def ray_connection(ray_cfg: Mapping[str, Any] | None) -> Iterator[None]:
    """One Ray connection for several training runs of one stage.

    :func:`run_training` connects (starting a local cluster when there is none) and shuts down
    what it started; a stage with several runs wraps them in this so the local cluster starts
    once. Nothing happens for in-process runs (``ray.num_workers: 0`` or ``ray.local``).
    """
    opts = RayOptions.from_dict(ray_cfg)
    started = not opts.in_process and ensure_ray(opts.address, opts.runtime_env)
    try:
        yield
    finally:
        if started:
            import ray

            ray.shutdown()


def decide_use_gpu(use_gpu: str | bool, num_workers: int, cluster: Mapping[str, float]) -> bool:
    """GPUs only when the cluster has one per worker; an explicit True without them raises."""
    have = cluster.get("GPU", 0) >= num_workers
    if use_gpu == "auto":
        return have
    if use_gpu and not have:
        raise ValueError(f"use_gpu=True but the cluster has {cluster.get('GPU', 0)} GPU(s) "
                         f"for {num_workers} worker(s); Ray Train would wait forever")
    return bool(use_gpu)


def _check_cpus(opts: RayOptions, cluster: Mapping[str, float]) -> None:
    """Fail fast when the workers can never be scheduled (Ray would retry forever)."""
    need = opts.num_workers * opts.cpus_per_worker
    if cluster.get("CPU", 0) < need:
        raise ValueError(f"{opts.num_workers} worker(s) x {opts.cpus_per_worker} CPU need {need} CPUs; "
                         f"the cluster has {cluster.get('CPU', 0)}")


def _run_info(stage: str, name: str, opts: RayOptions, storage: str, use_gpu: bool) -> RunInfo:
    """Worker-side settings, resolved on the driver (env vars do not reach a remote cluster)."""
    return RunInfo(
        stage=stage, run_name=name, checkpoint_every=opts.checkpoint_every,
        report_every=opts.report_every, torch_threads=max(1, round(opts.cpus_per_worker)),  # sweep trials: 1.99
        wandb_mode=os.environ.get("WANDB_MODE", "offline"), wandb_dir=tracking.default_wandb_dir(storage),
        wandb_project=opts.wandb_project, use_gpu=use_gpu)


def build_trainer(stage: str, spec: TrainSpec, loop_config: Mapping[str, Any],
                  ray_cfg: Mapping[str, Any] | RayOptions, storage: str | None = None, *,
                  callbacks: Sequence[Any] = (), run_name: str | None = None,
                  max_failures: int | None = None) -> Any:
    """A ready-to-``fit()`` ``TorchTrainer`` (Ray must be initialised).

    ``callbacks`` are Ray Train ``UserCallback``s, e.g. Tune's ``TuneReportCallback``
    when a Tune driver function wraps this; ``run_name`` overrides the params hash (e.g.
    ``f"{stage}-{trial_id}"``); ``max_failures`` overrides the options' count of Ray's own
    retries (:func:`fit_retrying` passes 0 and retries crashes itself).
    """
    import ray
    import ray.train
    from ray.train.torch import TorchTrainer

    opts = ray_cfg if isinstance(ray_cfg, RayOptions) else RayOptions.from_dict(ray_cfg)
    cluster = ray.cluster_resources()
    _check_cpus(opts, cluster)
    use_gpu = decide_use_gpu(opts.use_gpu, opts.num_workers, cluster)
    storage = resolve_storage(storage or opts.storage)
    name = run_name or make_run_name(stage, loop_config, opts.num_workers)
    info = _run_info(stage, name, opts, storage, use_gpu)
    return TorchTrainer(
        ray_train_fn,
        train_loop_config={"spec": spec, "config": dict(loop_config), "info": info},
        scaling_config=ray.train.ScalingConfig(
            num_workers=opts.num_workers, use_gpu=use_gpu,
            resources_per_worker={"CPU": opts.cpus_per_worker},
            placement_strategy=opts.placement_strategy),
        run_config=ray.train.RunConfig(
            name=name, storage_path=storage,
            failure_config=ray.train.FailureConfig(
                max_failures=opts.max_failures if max_failures is None else max_failures),
            checkpoint_config=ray.train.CheckpointConfig(num_to_keep=2),
            callbacks=list(callbacks)),
    )


#: Worker errors that recur on every attempt (bad config, wrong types, missing files, a NaN loss).
DETERMINISTIC_ERRORS: tuple[type[BaseException], ...] = (
    ValueError, TypeError, LookupError, AttributeError, ImportError, NotImplementedError, FileNotFoundError)


def deterministic_cause(error: BaseException) -> BaseException | None:
    """The first (lowest-rank) worker exception of a failed Ray Train run that retrying cannot fix.

    Ray Train hands the driver a ``WorkerGroupError`` whose ``worker_failures`` map each failed
    rank to a wrapper of the worker's own exception (``_base_exc``); None when no worker raised
    one of :data:`DETERMINISTIC_ERRORS` (a crash, a lost node, a ``RuntimeError``).
    """
    failures = getattr(error, "worker_failures", None) or {}
    for rank in sorted(failures):
        cause = getattr(failures[rank], "_base_exc", failures[rank])
        if isinstance(cause, DETERMINISTIC_ERRORS):
            return cause
    return None


def fit_retrying(make_trainer: Callable[[], Any], max_failures: int, run_name: str) -> Any:
    """``make_trainer().fit()``; after a worker crash, fitted again, at most ``max_failures`` times.

    Ray Train's ``FailureConfig(max_failures)`` restarts the worker group after *any* worker
    error, and its failure policy cannot be told which errors are deterministic (Ray 2.x builds
    its default policy internally; a callback can watch failures but not veto a retry). A config
    error or a NaN loss would then run, fail and wait through ``max_failures`` restarts. So
    ``make_trainer`` builds trainers with Ray's retries off, and this loop decides instead:

    * a worker exception in :data:`DETERMINISTIC_ERRORS` (:class:`TrainingError` included) is
      raised at once, unwrapped, so a stage prints it as its one-line error;
    * any other failure starts the run again under the same name, which resumes from its latest
      checkpoint in the Ray storage, exactly as Ray's own restart would (-1: no limit).
    """
    import ray.train

    failures = 0
    while True:
        try:
            return make_trainer().fit()
        except ray.train.TrainingFailedError as err:
            cause = deterministic_cause(err)
            if cause is not None:
                raise cause from err
            if 0 <= max_failures <= failures:
                raise
            failures += 1
            last_line = (str(err).strip().splitlines() or [type(err).__name__])[-1]
            limit = " (no limit)" if max_failures < 0 else f" of at most {max_failures}"
            sys.stderr.write(f"{run_name}: worker failure {failures}{limit} retried, "
                             f"resuming from the latest checkpoint ({last_line})\n")


def _fit_ray(stage: str, spec: TrainSpec, loop_config: Mapping[str, Any], opts: RayOptions,
             storage: str, callbacks: Sequence[Any], run_name: str | None) -> tuple[dict, str]:
    """Run on Ray (worker crashes retried by :func:`fit_retrying`); returns the final rank-0 state
    and the run's storage path."""
    import ray

    started = ensure_ray(opts.address, opts.runtime_env)
    try:
        def make_trainer() -> Any:
            return build_trainer(stage, spec, loop_config, opts, storage, callbacks=callbacks,
                                 run_name=run_name, max_failures=0)

        result = fit_retrying(make_trainer, opts.max_failures, run_name or stage)
        if result.checkpoint is None:
            raise RuntimeError(f"Ray run {result.path} finished without a checkpoint")
        with result.checkpoint.as_directory() as directory:
            return ckpt.load_state(Path(directory)), str(result.path)
    finally:
        if started:
            ray.shutdown()


def _fit_local(stage: str, spec: TrainSpec, loop_config: Mapping[str, Any], opts: RayOptions,
               storage: str, run_name: str | None) -> dict:
    """Run the same loop in this process (no Ray, no resume); returns the final state."""
    if opts.use_gpu is True and not torch.cuda.is_available():
        raise ValueError("ray.use_gpu=true but this machine has no CUDA GPU for the in-process run")
    use_gpu = opts.use_gpu in (True, "auto") and torch.cuda.is_available()
    name = run_name or make_run_name(stage, loop_config, 1)
    session = LocalSession(torch.device("cuda" if use_gpu else "cpu"))
    info = _run_info(stage, name, opts, storage, use_gpu)
    try:
        with _threads_scope(info.torch_threads), deterministic_gpu(session.device):
            train_loop(session, spec, dict(loop_config), info)
        assert session.latest is not None
        return ckpt.load_state(session.latest)
    finally:
        session.close()


def write_outputs(out_dir: Path, stage: str, state: Mapping[str, Any], loop_config: Mapping[str, Any],
                  run_meta: Mapping[str, Any], wall_time_s: float) -> dict[str, float]:
    """Atomically write ``out_dir``: model.pt, metrics.json, loss.csv, loss.png, run.json."""
    history = list(state["history"])
    metrics = summarise(history, state, wall_time_s)
    with atomic_directory(out_dir, owner=stage) as tmp:
        ckpt.save_final_model(tmp, ckpt.final_model_payload(state, loop_config))
        tracking.write_metrics_json(tmp / "metrics.json", metrics)
        tracking.write_history_csv(tmp / "loss.csv", history)
        tracking.plot_history_png(tmp / "loss.png", history, title=stage)
        (tmp / "run.json").write_text(json.dumps(dict(run_meta), indent=2, default=str) + "\n")
    return metrics


def summarise(history: Sequence[Mapping[str, Any]], state: Mapping[str, Any],
              wall_time_s: float) -> dict[str, float]:
    """metrics.json: last logged values, final step/epoch, median step rate, wall time."""
    last = {k: v for k, v in _last_curves(history).items() if k not in tracking.NON_CURVE_KEYS}
    rates = sorted(r["steps_per_s"] for r in history if r.get("steps_per_s", 0) > 0)
    return {
        **last,
        "step": state["step"],
        "epoch": state["epoch"],
        "steps_per_s": rates[len(rates) // 2] if rates else 0.0,
        "wall_time_s": round(wall_time_s, 3),
        "attempts": len(state["attempts"]),
    }


def run_training(stage: str, spec: TrainSpec, loop_config: Mapping[str, Any],
                 ray_cfg: Mapping[str, Any] | None, out_dir: Path, storage: str | None = None, *,
                 callbacks: Sequence[Any] = (), run_name: str | None = None, fingerprint: str = "") -> RunResult:
    """Train ``spec`` under Ray Train (or in-process) and write the stage's outputs.

    Args:
        stage: stage name (first part of the run name; progress and W&B label).
        spec: the stage's :class:`TrainSpec`.
        loop_config: plain dict of the stage's params (runner keys + the stage's own).
        ray_cfg: the ``ray`` params section (see :class:`RayOptions`).
        out_dir: the stage's DVC out folder, replaced atomically at the end.
        storage: Ray storage path/URI (absolute; outside DVC outs).
        callbacks: extra Ray Train callbacks (e.g. ``TuneReportCallback``).
        run_name: overrides ``<stage>-<params hash>`` (e.g. one name per Tune trial).
        fingerprint: digest of the code and inputs (:func:`pipelines.identity.fingerprint`);
            part of the run name, so a run resumes only from a run of the same code and inputs.
    """
    check_output(Path(out_dir), owner=stage)
    opts = RayOptions.from_dict(ray_cfg)
    storage = resolve_storage(storage or opts.storage)
    world = 1 if opts.in_process else opts.num_workers
    name = run_name or make_run_name(stage, loop_config, world, fingerprint)
    start = time.perf_counter()
    if opts.in_process:
        state, run_path = _fit_local(stage, spec, loop_config, opts, storage, name), None
    else:
        state, run_path = _fit_ray(stage, spec, loop_config, opts, storage, callbacks, name)
    meta = {"stage": stage, "run_name": name, "run_path": run_path, "attempts": state["attempts"],
            "device": state["device"], "fingerprint": fingerprint, "ray": asdict(opts), "config": dict(loop_config)}
    metrics = write_outputs(Path(out_dir), stage, state, loop_config, meta, time.perf_counter() - start)
    return RunResult(name, Path(out_dir), metrics, list(state["history"]), list(state["attempts"]), run_path)
