"""Training-state checkpoints (everything needed to continue exactly) and final-model files.

A checkpoint directory holds:

* ``state.pt`` (written by rank 0): models, optimisers, schedulers, EMA, step, epoch,
  position in the epoch, the loss history and the list of attempt start steps;
* ``rng_rank<r>.pt`` (written by every rank r): that rank's torch / numpy / python RNG
  states. Ray Train merges the directories that all ranks report into one.

The final model of a stage is ``<out_dir>/model.pt`` (see :func:`final_model_payload`),
and the whole out dir is written atomically with :func:`data.atomic.atomic_directory`.
"""

from __future__ import annotations

import os
import random
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

STATE_FILE = "state.pt"
MODEL_FILE = "model.pt"
FORMAT_VERSION = 1


def rng_file(rank: int) -> str:
    """Name of the RNG-state file of ``rank`` inside a checkpoint directory."""
    return f"rng_rank{rank}.pt"


def capture_rng() -> dict[str, Any]:
    """Snapshot of the torch (CPU and CUDA), numpy and python global RNG states."""
    state: dict[str, Any] = {
        "torch": torch.get_rng_state(),
        "numpy": np.random.get_state(),  # noqa: NPY002 (the global RNG is what we snapshot)
        "python": random.getstate(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def restore_rng(state: Mapping[str, Any]) -> None:
    """Put back the RNG states that :func:`capture_rng` returned."""
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])  # noqa: NPY002
    random.setstate(state["python"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def seed_everything(seed: int) -> None:
    """Seed torch (all devices), numpy and python's ``random`` with ``seed``."""
    torch.manual_seed(seed)
    np.random.seed(seed % 2**32)  # noqa: NPY002
    random.seed(seed)


def state_dicts(objects: Mapping[str, Any]) -> dict[str, Any]:
    """``{name: obj.state_dict()}`` for a mapping of modules / optimisers / schedulers."""
    return {name: obj.state_dict() for name, obj in objects.items()}


def load_state_dicts(objects: Mapping[str, Any], states: Mapping[str, Any]) -> None:
    """Load ``states[name]`` into ``objects[name]``; the two key sets must match."""
    if set(objects) != set(states):
        raise KeyError(f"checkpoint holds {sorted(states)}, run has {sorted(objects)}")
    for name, obj in objects.items():
        obj.load_state_dict(states[name])


def _atomic_save(obj: Any, path: Path) -> None:
    """``torch.save`` to a temporary name, then rename (never leaves half a file)."""
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def save_state(directory: Path, state: Mapping[str, Any]) -> None:
    """Write the rank-0 training state into a checkpoint directory."""
    _atomic_save({"format": FORMAT_VERSION, **state}, Path(directory) / STATE_FILE)


def load_state(directory: Path) -> dict[str, Any]:
    """Read the training state that :func:`save_state` wrote (our own trusted file)."""
    state = torch.load(Path(directory) / STATE_FILE, map_location="cpu", weights_only=False)
    if state.get("format") != FORMAT_VERSION:
        raise ValueError(f"unsupported checkpoint format {state.get('format')!r} in {directory}")
    return state


def save_rng(directory: Path, rank: int) -> None:
    """Write this process's RNG states as ``rng_rank<rank>.pt``."""
    _atomic_save(capture_rng(), Path(directory) / rng_file(rank))


def load_rng(directory: Path, rank: int) -> bool:
    """Restore this rank's RNG states from a checkpoint; False if the file is missing."""
    path = Path(directory) / rng_file(rank)
    if not path.exists():
        return False
    restore_rng(torch.load(path, weights_only=False))
    return True


def final_model_payload(state: Mapping[str, Any], config: Mapping[str, Any]) -> dict[str, Any]:
    """The part of a training state that a stage ships: weights, EMA weights, config, step."""
    return {
        "format": FORMAT_VERSION,
        "models": state["models"],
        "ema": {name: ema["module"] for name, ema in state.get("ema", {}).items()},
        "config": dict(config),
        "step": state["step"],
    }


def load_final_model(out_dir: Path) -> dict[str, Any]:
    """Read ``<out_dir>/model.pt``: ``{"models", "ema", "config", "step"}``."""
    return torch.load(Path(out_dir) / MODEL_FILE, map_location="cpu", weights_only=False)
