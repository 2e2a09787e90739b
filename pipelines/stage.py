"""The skeleton every training stage shares: params -> loop config -> the runner -> outputs.

A training stage module is its :class:`~pipelines.runner.TrainSpec` plus the mapping from params
to the stage's own part of the loop config, declared as a :class:`TrainingStage`::

    STAGE = TrainingStage(name="train_vae", module=__name__, spec=SPEC, config=stage_config,
                          inputs=("features_dir",))

    if __name__ == "__main__":
        main(STAGE)

This module supplies the rest, the same for every stage:

- the runner keys come from the stage's ``loop`` params group (``train_vae.loop``), validated by
  :meth:`LoopSettings.parse`: an unknown or missing key is an error, never a silent default;
- the output folder is ``<paths.artifacts>/<name>``; Ray storage is ``ray.storage`` when set (a
  shared path or URI on a cluster), else ``paths.ray_storage``;
- the run's fingerprint (:func:`pipelines.identity.fingerprint`) covers the code the stage module
  imports and the contents of the input folders named by ``inputs`` (loop-config keys), so changed
  code or inputs train from step 0 and an interrupted identical run resumes;
- the stage sees only the params keys it declares (``params``), the list its DVC stage declares
  (``tests/test_dvc_deps.py``): reading any other key is an error, so the two cannot drift;
- :func:`main` turns user errors (bad params, missing files) into one line and exit status 1;
- a stage whose ``skip`` gives a reason (e.g. a real dataset without action labels for the action
  stages) trains nothing: its output folder holds only ``skipped.json`` with the reason, so DVC still
  has its output and the evaluation leaves the rows that need it out
  (:func:`pipelines.checkpoint.skipped`).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from data.atomic import atomic_directory
from pipelines.checkpoint import SKIPPED
from pipelines.cli import artifacts_dir, param, run_main
from pipelines.config import REPO_ROOT
from pipelines.identity import fingerprint
from pipelines.runner import LoopSettings, RunResult, TrainSpec, resolve_storage, run_training


@dataclass(frozen=True)
class TrainingStage:
    """One training run of a stage.

    Attributes:
        name: run name prefix and output folder ``<paths.artifacts>/<name>``; usually the DVC stage.
        module: the stage's module (``__name__``); the code it imports is part of the run's identity.
        spec: what to train (build, dataset, step).
        config: ``params -> the stage's own loop-config keys`` (paths absolute, sizes resolved).
        params: the params keys (dotted) the stage reads; its DVC ``params`` list, and all it is given.
        inputs: loop-config keys holding input folders whose contents are part of the run's identity
            (an optional input's key may be missing or None: then it is not read).
        loop_group: dotted params key of the runner settings (default ``<name>.loop``).
        check: validates the stage's own params section before any work starts (a ValueError
            naming the key); the ``loop`` group and the shared sections are checked anyway.
        skip: a reason not to train with these params (the data cannot feed the stage), or None.
    """

    name: str
    module: str
    spec: TrainSpec
    config: Callable[[dict[str, Any]], dict[str, Any]]
    params: tuple[str, ...]
    inputs: tuple[str, ...] = ()
    loop_group: str = ""
    check: Callable[[dict[str, Any]], object] | None = None
    skip: Callable[[dict[str, Any]], str | None] | None = None

    @property
    def loop_key(self) -> str:
        return self.loop_group or f"{self.name}.loop"


def ray_storage(params: dict[str, Any]) -> str:
    """Ray storage for runs and sweeps: ``ray.storage`` if set (a URI, or a path), else ``paths.ray_storage``; a
    relative path is relative to the repository, as every path param is (not to the working directory)."""
    storage = param(params, "ray").get("storage") or param(params, "paths.ray_storage")
    return resolve_storage(storage if "://" in storage else REPO_ROOT / Path(storage).expanduser())


def module_name(name: str) -> str:
    """``name``, or the real name of the module run as ``python -m <module>`` when it is ``__main__``."""
    if name == "__main__":
        spec = getattr(sys.modules["__main__"], "__spec__", None)
        if spec is None:
            raise ValueError("a training stage runs as `python -m stages.<name>`, not as a script path")
        return spec.name
    return name


def run_fingerprint(module: str, inputs: Sequence[str], config: Mapping[str, Any]) -> str:
    """The code and inputs a run is named by: ``module``'s code and the folders ``config[key]`` of ``inputs``
    (an optional input that is None left out), :func:`pipelines.identity.fingerprint`."""
    return fingerprint(module_name(module), [config[key] for key in inputs if config.get(key) is not None])


def loop_config(stage: TrainingStage, params: dict[str, Any]) -> dict[str, Any]:
    """The runner's loop config: the validated ``loop`` group plus the stage's own keys."""
    settings = LoopSettings.parse(param(params, stage.loop_key), stage.loop_key)
    own = stage.config(params)
    clash = sorted(set(own) & set(asdict(settings)))
    if clash:
        raise ValueError(f"{stage.name}: its config repeats runner key(s) {clash}; they belong in {stage.loop_key}")
    return asdict(settings) | own


def train(stage: TrainingStage, params: dict[str, Any], config: dict[str, Any] | None = None) -> RunResult:
    """Run ``stage`` (``config``: a ready loop config, else built from params) and write its outputs."""
    config = loop_config(stage, params) if config is None else config
    digest = run_fingerprint(stage.module, stage.inputs, config)
    result = run_training(stage.name, stage.spec, config, dict(param(params, "ray")),
                          artifacts_dir(params) / stage.name, ray_storage(params), fingerprint=digest)
    print(f"{stage.name}: final loss {result.metrics.get('loss', float('nan')):.4f} after "
          f"{result.metrics.get('step', 0)} steps -> {result.out_dir}")
    return result


def train_unless_skipped(stage: TrainingStage, params: dict[str, Any]) -> RunResult | None:
    """:func:`train`, or, when ``stage.skip`` gives a reason, an output folder holding only that reason."""
    reason = stage.skip(params) if stage.skip is not None else None
    if reason is None:
        return train(stage, params)
    with atomic_directory(artifacts_dir(params) / stage.name, owner=stage.name) as tmp:
        (tmp / SKIPPED).write_text(json.dumps({"stage": stage.name, "reason": reason}, indent=2) + "\n")
    print(f"{stage.name}: trained nothing: {reason}")
    return None


def checks(stage: TrainingStage) -> list[Callable[[dict[str, Any]], object]]:
    """The up-front checks of ``stage``'s params: its ``loop`` group, then its own section."""
    loop = [lambda params: LoopSettings.parse(param(params, stage.loop_key), stage.loop_key)]
    return loop + ([stage.check] if stage.check is not None else [])


def main(stage: TrainingStage, argv: Sequence[str] | None = None) -> None:
    """``python -m stages.<name> [key=value ...] [--cfg] [--help]`` for a training stage."""
    run_main(stage.name, lambda params: train_unless_skipped(stage, params), stage.params, argv, checks(stage))
