"""Training-state checkpoints (everything needed to continue exactly) and final-model files.

A checkpoint directory holds:

* ``state.pt`` (written by rank 0): models, optimisers, schedulers, EMA, step, epoch,
  position in the epoch, the loss history and the list of attempt start steps;
* ``rng_rank<r>.pt`` (written by every rank r): that rank's torch / numpy / python RNG
  states. Ray Train merges the directories that all ranks report into one.

The final model of a stage is ``<out_dir>/model.pt`` (see :func:`final_model_payload`),
and the whole out dir is written atomically with :func:`data.atomic.atomic_directory`. A stage
that trained nothing (``pipelines.stage``: its data cannot feed it) leaves only ``skipped.json``
with the reason (:func:`skipped`).

Every file is read with ``torch.load(weights_only=True)``: a ``.pt`` file is a pickle, and an
unrestricted unpickler runs whatever code the file names. Checkpoints live in the Ray storage
(a shared path or a bucket) and models are handed around, so neither is trusted. We therefore
store only tensors and plain containers of str/int/float/bool/None (the RNG states are converted
from numpy's and python's own objects, :func:`capture_rng`), check that at save time
(:func:`check_plain`), and turn any file that does not load that way (foreign pickled objects,
corrupted bytes, another format version, not a dict) into a one-line ``ValueError`` naming the
file; nothing in it is executed.
"""

from __future__ import annotations

import json
import os
import random
import re
import warnings
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

STATE_FILE = "state.pt"
MODEL_FILE = "model.pt"
#: Format of a checkpoint directory (``state.pt`` + ``rng_rank<r>.pt``). 2: the RNG files hold
#: plain types and a format tag (1 pickled numpy arrays, which safe loading refuses).
FORMAT_VERSION = 2
#: Format of ``model.pt``; unchanged by checkpoint format 2 (it never held numpy objects).
MODEL_FORMAT_VERSION = 1
STATE_KEYS = ("models", "optimizers", "schedulers", "ema", "step", "epoch", "batch", "history", "attempts")
RNG_KEYS = ("torch", "numpy", "python")
MODEL_KEYS = ("models", "ema", "config", "step")
#: Scalar types a saved file may hold (exact types: e.g. ``numpy.float64`` subclasses float but
#: pickles as a numpy object that safe loading refuses).
PLAIN_SCALARS = (str, int, float, bool, type(None))


def rng_file(rank: int) -> str:
    """Name of the RNG-state file of ``rank`` inside a checkpoint directory."""
    return f"rng_rank{rank}.pt"


def check_plain(obj: Any, where: str = "payload") -> None:
    """TypeError naming the key path of the first value that ``weights_only`` loading would refuse.

    Allowed: tensors, dicts (str or int keys), lists, tuples and :data:`PLAIN_SCALARS`. Called
    before every save, so a run fails at its first checkpoint rather than when it resumes.
    """
    if isinstance(obj, torch.Tensor) or type(obj) in PLAIN_SCALARS:
        return
    if type(obj) in (dict, OrderedDict):
        for key, value in obj.items():
            if type(key) not in (str, int):
                raise TypeError(f"{where}: key {key!r} of type {type(key).__name__} is not str or int")
            check_plain(value, f"{where}.{key}")
        return
    if type(obj) in (list, tuple):
        for k, value in enumerate(obj):
            check_plain(value, f"{where}[{k}]")
        return
    raise TypeError(f"{where}: {type(obj).__module__}.{type(obj).__qualname__} is not a tensor or plain type")


def capture_rng(device: torch.device) -> dict[str, Any]:
    """Snapshot of the torch CPU, numpy and python global RNG states, in plain types, and the CUDA RNG
    state of ``device`` when it is a GPU (the run's own GPU only: a retried rank may be given another
    index, or see fewer GPUs, than the one that wrote the snapshot)."""
    bit_generator, key, pos, has_gauss, cached_gaussian = np.random.get_state()  # noqa: NPY002
    version, internal, gauss_next = random.getstate()
    state: dict[str, Any] = {
        "torch": torch.get_rng_state(),
        "numpy": {"bit_generator": str(bit_generator), "key": torch.from_numpy(key.astype(np.int64)),
                  "pos": int(pos), "has_gauss": int(has_gauss), "cached_gaussian": float(cached_gaussian)},
        "python": {"version": int(version), "internal": list(internal), "gauss_next": gauss_next},
    }
    if device.type == "cuda":
        state["cuda"] = torch.cuda.get_rng_state(device)
    return state


def restore_rng(state: Mapping[str, Any], device: torch.device) -> None:
    """Put back the RNG states that :func:`capture_rng` returned (the CUDA one onto ``device``).

    Raises:
        KeyError: ``device`` is a GPU and the snapshot has no CUDA state (it was taken on the CPU).
    """
    numpy_state, python_state = state["numpy"], state["python"]
    key = numpy_state["key"].numpy()
    if key.shape != (624,):  # MT19937's state; numpy reads a shorter key out of bounds
        raise ValueError(f"numpy key of shape {key.shape}, expected (624,)")
    torch.set_rng_state(state["torch"])
    np.random.set_state((  # noqa: NPY002 (the global RNG is what we restore)
        numpy_state["bit_generator"], key.astype(np.uint32), numpy_state["pos"], numpy_state["has_gauss"],
        numpy_state["cached_gaussian"]))
    random.setstate((python_state["version"], tuple(python_state["internal"]), python_state["gauss_next"]))
    if device.type == "cuda":
        torch.cuda.set_rng_state(state["cuda"], device)


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


def _atomic_save(obj: Mapping[str, Any], path: Path) -> None:
    """Check ``obj`` is plain (:func:`check_plain`), ``torch.save`` it to a temporary name, then
    rename (never leaves half a file)."""
    check_plain(obj, path.name)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def _load_failure(err: Exception) -> str:
    """One line saying why ``torch.load(weights_only=True)`` refused a file."""
    text = str(err)
    refused = re.search(r"Unsupported global: GLOBAL (\S+)", text)
    if refused:
        return f"it holds a pickled {refused.group(1)}, which safe loading refuses (tensors and plain types only)"
    unpickler = re.search(r"WeightsUnpickler error:\s*([^\n]+)", text)
    if unpickler:
        return f"the restricted unpickler refused it ({unpickler.group(1).strip()})"
    first = next((line.strip() for line in text.splitlines() if line.strip()), "")
    detail = f"{type(err).__name__}: {first[:160]}" if first else type(err).__name__
    return f"corrupted or not a torch file ({detail})"


def _safe_load(path: Path, version: int, keys: Sequence[str]) -> dict[str, Any]:
    """``torch.load(path, weights_only=True)``, checked to be a dict of format ``version`` holding ``keys``.

    Raises:
        ValueError: one line naming ``path`` and the reason (refused pickle, corrupted bytes, not a
            dict, another format version, missing keys); nothing in the file is executed.
        FileNotFoundError / OSError: the file is missing or unreadable.
    """
    try:
        with warnings.catch_warnings():  # a raw (non-zip) pickle only warns about its protocol
            warnings.filterwarnings("ignore", message="Detected pickle protocol", category=UserWarning)
            payload = torch.load(path, map_location="cpu", weights_only=True)
    except OSError:
        raise
    except Exception as err:  # malformed bytes fail in many exception types; each means "not a file we wrote"
        raise ValueError(f"{path}: cannot load safely: {_load_failure(err)}") from err
    if not isinstance(payload, dict):
        raise ValueError(f"{path}: expected a dict, found {type(payload).__name__}")
    found = payload.get("format")
    if found != version:
        raise ValueError(f"{path}: format {found!r}, this code reads format {version} (written by another "
                         "motionforge version: delete it and train again)")
    missing = [key for key in keys if key not in payload]
    if missing:
        raise ValueError(f"{path}: missing keys {missing}")
    return payload


def save_state(directory: Path, state: Mapping[str, Any]) -> None:
    """Write the rank-0 training state into a checkpoint directory."""
    _atomic_save({"format": FORMAT_VERSION, **state}, Path(directory) / STATE_FILE)


def load_state(directory: Path) -> dict[str, Any]:
    """Read the training state that :func:`save_state` wrote (safely: see the module docstring)."""
    return _safe_load(Path(directory) / STATE_FILE, FORMAT_VERSION, STATE_KEYS)


def save_rng(directory: Path, rank: int, device: torch.device) -> None:
    """Write this process's RNG states (with ``device``'s CUDA state) as ``rng_rank<rank>.pt``."""
    _atomic_save({"format": FORMAT_VERSION, **capture_rng(device)}, Path(directory) / rng_file(rank))


def load_rng(directory: Path, rank: int, device: torch.device) -> bool:
    """Restore this rank's RNG states from a checkpoint; False if the file is missing, or if ``device`` is a
    GPU and the file has no CUDA state (a run started on the CPU and resumed on GPUs): the caller then
    seeds every generator afresh, as for a missing file, rather than leave each rank's GPU generator at
    the common initial seed.

    Raises:
        ValueError: the file is not one :func:`save_rng` wrote (see :func:`_safe_load`), or its
            states do not fit the generators.
    """
    path = Path(directory) / rng_file(rank)
    if not path.exists():
        return False
    state = _safe_load(path, FORMAT_VERSION, RNG_KEYS)
    if device.type == "cuda" and "cuda" not in state:
        return False
    try:
        restore_rng(state, device)
    except (KeyError, TypeError, ValueError, AttributeError, IndexError, RuntimeError) as err:
        raise ValueError(f"{path}: RNG states do not fit ({type(err).__name__}: {err})") from err
    return True


def final_model_payload(state: Mapping[str, Any], config: Mapping[str, Any]) -> dict[str, Any]:
    """The part of a training state that a stage ships: weights, EMA weights, config, step."""
    return {
        "format": MODEL_FORMAT_VERSION,
        "models": state["models"],
        "ema": {name: ema["module"] for name, ema in state.get("ema", {}).items()},
        "config": dict(config),
        "step": state["step"],
    }


def save_final_model(out_dir: Path, payload: Mapping[str, Any]) -> None:
    """Write :func:`final_model_payload`'s ``payload`` as ``<out_dir>/model.pt``."""
    _atomic_save(payload, Path(out_dir) / MODEL_FILE)


def load_final_model(out_dir: Path) -> dict[str, Any]:
    """Read ``<out_dir>/model.pt`` (safely: see the module docstring): ``{"models", "ema", "config", "step"}``."""
    return _safe_load(Path(out_dir) / MODEL_FILE, MODEL_FORMAT_VERSION, MODEL_KEYS)


SKIPPED = "skipped.json"


def skipped(out_dir: Path) -> str | None:
    """The reason a training stage's output folder records for having trained nothing, or None."""
    path = Path(out_dir) / SKIPPED
    return json.loads(path.read_text(encoding="utf-8"))["reason"] if path.is_file() else None
