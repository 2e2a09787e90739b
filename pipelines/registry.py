"""The model registry: one entry per model family, read by ``evaluate``, ``generate`` and the report.

An entry names the family's module and, in it, the functions that build its evaluation rows
(``rows(ctx) -> [Generator | Reconstructor]``), that name its rows answering captions without loading
a model (``text_rows(params) -> [name]``: what ``evaluate.paraphrase_rows``, ``evaluate.samples.rows``
and ``speed.rows`` may name, checked by ``pipelines.preflight``) and, for ``stages.generate --model
<name>``, its generator (``generator(ctx, options) -> Generator``). Modules are imported by name when used, so
``stages/evaluate.py`` imports no model code itself: the DVC stage ``eval_<name>`` depends on the
code of its own family only, and retraining one family re-evaluates only that family.

Adding a family: a model module in ``models/``, a training stage, a module in ``pipelines/`` with
its loaders and ``rows``/``generator`` functions, an entry here, and its ``eval_<name>`` stage in
``dvc.yaml`` (``tests/test_dvc_deps.py`` tells you its exact deps and params).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import torch

from models.generator import CPU, Generator, Reconstructor
from pipelines.cli import artifacts_dir, repo_path
from pipelines.devices import sampling_device
from pipelines.feature_store import FeatureStore

#: Training runs whose output folder is written by a DVC stage of another name.
WRITTEN_BY = {"train_evaluator_movement": "train_evaluator", "train_evaluator_recogniser": "train_evaluator"}


@dataclass
class EvalContext:
    """What a family's functions may use: the params its stage may read, artefacts, the feature store and the
    device its networks run on (:func:`pipelines.devices.sampling_device`; the rows take and return NumPy arrays
    on the host)."""

    params: dict[str, Any]
    artifacts: Path
    features: Path
    device: torch.device = CPU

    @classmethod
    def from_params(cls, params: dict[str, Any]) -> EvalContext:
        """A stage's context: ``paths.artifacts``, ``features.out`` and the device ``sample.device`` names."""
        return cls(params, artifacts_dir(params), repo_path(params, "features.out"),
                   sampling_device(params["sample"]["device"]))

    @cached_property
    def store(self) -> FeatureStore:
        return FeatureStore(self.features)

    def trained(self, stage: str) -> Path:
        """A training run's output folder; FileNotFoundError naming the command when it is missing."""
        out = self.artifacts / stage
        if not (out / "model.pt").is_file():
            producer = WRITTEN_BY.get(stage, stage)
            raise FileNotFoundError(f"{out}/model.pt is missing: run `dvc repro {producer}` first")
        return out


@dataclass(frozen=True)
class GenerateOptions:
    """``stages.generate`` options a family may honour (None: the family's default)."""

    steps: int | None = None
    guidance: float | None = None
    refine: bool = False


@dataclass(frozen=True)
class ModelFamily:
    """One registry entry.

    Attributes:
        name: ``stages.generate --model`` name, DVC stage ``eval_<name>``, folder ``artifacts/eval/<name>``.
        module: the module holding the functions below.
        rows: function name in ``module``: ``(EvalContext) -> list of Generator / Reconstructor``, or of
            :class:`pipelines.action_evaluation.ActionGenerator` (scored by the action-to-motion protocol).
        text_rows: function name in ``module``: ``(params) -> names of the rows that answer captions``, in
            ``rows``' order, from params alone (no model loaded); None for a family with no such row.
        train_stages: training stages whose outputs the rows load (the eval stage's data deps).
        params: params keys the rows read (beyond ``stages/evaluate.py``'s own).
        generator: function name in ``module``: ``(EvalContext, GenerateOptions) -> Generator``, or None.
        controlled: its generator follows a pelvis trajectory (``stages.generate --trajectory``, ``--refine``).
        description: one line for ``--help`` and the README.
    """

    name: str
    module: str
    rows: str
    text_rows: str | None = None
    train_stages: tuple[str, ...] = ()
    params: tuple[str, ...] = ()
    generator: str | None = None
    controlled: bool = False
    description: str = ""

    def _function(self, attr: str) -> Callable[..., Any]:
        return getattr(importlib.import_module(self.module), attr)

    def build_rows(self, ctx: EvalContext) -> list[Generator | Reconstructor]:
        return self._function(self.rows)(ctx)

    def text_row_names(self, params: dict[str, Any]) -> list[str]:
        return [] if self.text_rows is None else self._function(self.text_rows)(params)

    def build_generator(self, ctx: EvalContext, options: GenerateOptions) -> Generator:
        if self.generator is None:
            raise ValueError(f"model family {self.name!r} has no generator (it is evaluated only)")
        return self._function(self.generator)(ctx, options)


FAMILIES: dict[str, ModelFamily] = {family.name: family for family in (
    ModelFamily("baselines", "pipelines.baselines", "rows", "row_names",
                description="Random and Retrieval: real training motions, no model"),
    ModelFamily("vae", "pipelines.mld_family", "vae_rows", train_stages=("train_vae",),
                description="MLD's motion VAE: reconstruction of the test motions"),
    ModelFamily("mld", "pipelines.mld_family", "mld_rows", "mld_row_names", train_stages=("train_vae", "train_mld"),
                params=("sample.mld_guidance",), generator="mld_generator",
                description="MLD: latent diffusion, DDIM with classifier-free guidance"),
    ModelFamily("motionlcm", "pipelines.mld_family", "motionlcm_rows", "motionlcm_row_names",
                train_stages=("train_vae", "train_mld", "distill_lcm"), params=("sample.motionlcm_guidance",),
                generator="motionlcm_generator", description="MotionLCM: the MLD teacher distilled, 1-4 steps"),
    ModelFamily("motionlcm-control", "pipelines.controlnet_family", "controlnet_rows", "controlnet_row_names",
                train_stages=("train_vae", "train_mld", "distill_lcm", "train_controlnet"),
                params=("sample.motionlcm_guidance", "sample.control_refine_steps", "sample.control_refine_lr",
                        "sample.control_refine_project", "sample.control_refine_batch"),
                generator="controlnet_generator", controlled=True,
                description="MotionLCM's ControlNet: one step, following a pelvis trajectory"),
    ModelFamily("emdm", "pipelines.emdm_family", "emdm_rows", "emdm_row_names", train_stages=("train_emdm",),
                params=("sample.emdm_guidance", "sample.motion_batch"), generator="emdm_generator",
                description="EMDM: a denoising-diffusion GAN in motion space, 10 steps"),
    ModelFamily("emdm-action", "pipelines.emdm_family", "emdm_action_rows", train_stages=("train_emdm_action",),
                params=("sample.emdm_action_guidance", "sample.motion_batch"), generator="emdm_action_generator",
                description="EMDM conditioned on action labels: the action-to-motion protocol"),
    ModelFamily("motiondiffuse", "pipelines.motiondiffuse_family", "motiondiffuse_rows", "motiondiffuse_row_names",
                train_stages=("train_motiondiffuse",),
                params=("sample.motiondiffuse_guidance", "sample.motiondiffuse_ddpm_items",
                        "sample.motiondiffuse_ddpm_replications", "sample.motion_batch"),
                generator="motiondiffuse_generator",
                description="MotionDiffuse: DDPM with a linear-attention transformer, 1000 steps (and DDIM 10)"),
)}


def family(name: str) -> ModelFamily:
    """The registry entry ``name``; ValueError listing the known ones otherwise."""
    if name not in FAMILIES:
        raise ValueError(f"unknown model family {name!r}; known: {', '.join(FAMILIES)}")
    return FAMILIES[name]
