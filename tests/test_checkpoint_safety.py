"""Safe loading of checkpoints and models (pipelines/checkpoint.py).

Every ``.pt`` file we read is a pickle. These tests plant pickles whose ``__reduce__`` would create
a marker file and check that each real loader (and ``python -m stages.generate``) refuses them with
one line naming the file, and that the marker never appears (nothing ran). They check the other
malformed files too (corrupted, empty, not a dict, another format version, missing keys), and that
what we save (real model, optimiser, scheduler, EMA, RNG and config values) round-trips bit for bit
through the safe loader, the RNGs giving the same draws from torch, numpy and python ``random``.
"""

from __future__ import annotations

import pickle
import pickletools
import random
import subprocess
import sys
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from state_checks import assert_same
from torch import nn

from pipelines import checkpoint as ckpt
from pipelines.schedules import EMA, make_scheduler

REPO = Path(__file__).resolve().parent.parent
CPU = torch.device("cpu")
REFUSED = "cannot load safely: it holds a pickled io.open, which safe loading refuses (tensors and plain types only)"


class Planted:
    """An object whose unpickling creates ``marker`` (what an attacker's file would run)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[Callable[..., Any], tuple[Any, ...]]:
        return (open, (str(self.marker), "w"))


def plant(path: Path, marker: Path, payload: dict[str, Any]) -> Path:
    """Write ``payload`` plus a :class:`Planted` object as a torch file at ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({**payload, "extra": Planted(marker)}, path)
    return path


def planted_globals(path: Path) -> set[str]:
    """The ``module name`` pairs a torch file's pickle imports, read with pickletools (nothing is executed)."""
    with zipfile.ZipFile(path) as archive:
        data = archive.read(next(n for n in archive.namelist() if n.endswith("/data.pkl")))
    names, strings = set(), []
    for opcode, arg, _ in pickletools.genops(data):
        if opcode.name == "GLOBAL":
            names.add(str(arg))
        elif opcode.name in ("SHORT_BINUNICODE", "BINUNICODE", "UNICODE"):
            strings.append(arg)
        elif opcode.name == "STACK_GLOBAL" and len(strings) >= 2:
            names.add(f"{strings[-2]} {strings[-1]}")
    return names


def load_rng0(directory: Path) -> bool:
    return ckpt.load_rng(directory, 0, CPU)


# file name -> (the real loader of the directory, a payload of the right format for it)
LOADERS: dict[str, tuple[Callable[[Path], Any], dict[str, Any]]] = {
    ckpt.MODEL_FILE: (ckpt.load_final_model, {"format": ckpt.MODEL_FORMAT_VERSION, "models": {}, "ema": {},
                                              "config": {}, "step": 0}),
    ckpt.STATE_FILE: (ckpt.load_state, {"format": ckpt.FORMAT_VERSION}),
    ckpt.rng_file(0): (load_rng0, {"format": ckpt.FORMAT_VERSION}),
}


@pytest.mark.parametrize("name", list(LOADERS))
def test_crafted_pickle_is_refused_and_never_runs(name: str, tmp_path: Path) -> None:
    loader, payload = LOADERS[name]
    marker = tmp_path / "pwned"
    path = plant(tmp_path / "ckpt" / name, marker, payload)
    with pytest.raises(ValueError) as err:
        loader(path.parent)
    assert str(err.value) == f"{path}: {REFUSED}"
    assert not marker.exists()
    # The control, without running it: the file's pickle does hold the planted call.
    assert planted_globals(path) == {"io open"}  # open, the call Planted.__reduce__ plants


@pytest.mark.parametrize(("protocol", "reason"), [
    (2, REFUSED),
    (4, "cannot load safely: the restricted unpickler refused it (Unsupported operand 149)"),  # FRAME opcode
])
def test_raw_pickle_is_refused_without_warnings(protocol: int, reason: str, tmp_path: Path) -> None:
    """A plain (non-zip) pickle goes through the same restricted unpickler, and prints nothing."""
    marker = tmp_path / "pwned"
    path = tmp_path / ckpt.STATE_FILE
    path.write_bytes(pickle.dumps({"format": ckpt.FORMAT_VERSION, "x": Planted(marker)}, protocol=protocol))
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        with pytest.raises(ValueError) as err:
            ckpt.load_state(tmp_path)
    assert str(err.value) == f"{path}: {reason}"
    assert [str(w.message) for w in seen] == []
    assert not marker.exists()


def _truncated(path: Path) -> None:
    torch.save({"format": ckpt.FORMAT_VERSION, "w": torch.zeros(100)}, path)
    path.write_bytes(path.read_bytes()[:200])


MALFORMED = {
    "truncated": (_truncated, "cannot load safely: corrupted or not a torch file (RuntimeError: PytorchStreamReader "
                              "failed reading zip archive: failed finding central directory"),
    "empty": (lambda p: p.write_bytes(b""), "cannot load safely: corrupted or not a torch file (EOFError)"),
    "text": (lambda p: p.write_text("not a checkpoint\n"),
             "cannot load safely: the restricted unpickler refused it (Unsupported operand 110)"),
    "not a dict": (lambda p: torch.save([torch.zeros(2)], p), "expected a dict, found list"),
    "no format": (lambda p: torch.save({"models": {}}, p),
                  f"format None, this code reads format {ckpt.FORMAT_VERSION} (written by another motionforge "
                  "version: delete it and train again)"),
    "format 1": (lambda p: torch.save({"format": 1}, p), f"format 1, this code reads format {ckpt.FORMAT_VERSION}"),
    "missing keys": (lambda p: torch.save({"format": ckpt.FORMAT_VERSION, "models": {}, "step": 3}, p),
                     "missing keys ['optimizers', 'schedulers', 'ema', 'epoch', 'batch', 'history', 'attempts']"),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_state_is_one_clear_error(case: str, tmp_path: Path) -> None:
    write, reason = MALFORMED[case]
    path = tmp_path / ckpt.STATE_FILE
    write(path)
    with pytest.raises(ValueError) as err:
        ckpt.load_state(tmp_path)
    message = str(err.value)
    assert "\n" not in message
    assert message.startswith(f"{path}: {reason}")


def test_format_1_rng_file_names_the_refused_numpy_object(tmp_path: Path) -> None:
    """What format 1 wrote (numpy's RNG tuple, an ndarray inside) is refused, not misread."""
    path = tmp_path / ckpt.rng_file(0)
    torch.save({"torch": torch.get_rng_state(), "numpy": np.random.get_state(),  # noqa: NPY002
                "python": random.getstate()}, path)
    with pytest.raises(ValueError, match=r"rng_rank0\.pt: cannot load safely: it holds a pickled numpy\."):
        ckpt.load_rng(tmp_path, 0, CPU)


def test_model_of_another_format_is_refused(tmp_path: Path) -> None:
    torch.save({"format": ckpt.MODEL_FORMAT_VERSION + 1, "models": {}, "ema": {}, "config": {}, "step": 0},
               tmp_path / ckpt.MODEL_FILE)
    with pytest.raises(ValueError, match=rf"model\.pt: format {ckpt.MODEL_FORMAT_VERSION + 1}, this code reads "
                                         rf"format {ckpt.MODEL_FORMAT_VERSION} \("):
        ckpt.load_final_model(tmp_path)


def test_rng_states_that_do_not_fit_are_a_clear_error(tmp_path: Path) -> None:
    ckpt.save_rng(tmp_path, 0, CPU)
    path = tmp_path / ckpt.rng_file(0)
    state = torch.load(path, weights_only=True)
    state["numpy"]["key"] = state["numpy"]["key"][:10]
    torch.save(state, path)
    with pytest.raises(ValueError) as err:
        ckpt.load_rng(tmp_path, 0, CPU)
    assert str(err.value) == f"{path}: RNG states do not fit (ValueError: numpy key of shape (10,), expected (624,))"


def test_saving_a_non_plain_value_fails_naming_its_key(tmp_path: Path) -> None:
    """numpy.float64 subclasses float but pickles as a numpy object: caught at save, nothing written."""
    with pytest.raises(TypeError, match=r"^state\.pt\.history\[0\]\.loss: numpy\.float64 is not a tensor or plain"):
        ckpt.save_state(tmp_path, {"history": [{"step": 1, "loss": np.float64(0.5)}]})
    with pytest.raises(TypeError, match=r"^model\.pt\.config\.paths: pathlib\.PosixPath is not"):
        ckpt.save_final_model(tmp_path, {"config": {"paths": Path("/x")}})
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- round trips


def toy_state() -> dict[str, Any]:
    """A real rank-0 training state: a model, AdamW after two steps, its cosine schedule, an EMA."""
    torch.manual_seed(0)
    net = nn.Sequential(nn.Linear(4, 8), nn.LayerNorm(8), nn.Linear(8, 1))
    opt = torch.optim.AdamW(net.parameters(), lr=1e-2, betas=(0.9, 0.99))
    sched = make_scheduler(opt, "cosine", 1, 10, 0.1)
    ema = EMA(net, 0.9)
    for _ in range(2):
        net(torch.randn(3, 4)).pow(2).mean().backward()
        opt.step()
        sched.step()
        ema.update(net)
    return {"step": 2, "epoch": 0, "batch": 2,
            "models": {"net": net.state_dict()}, "optimizers": {"net": opt.state_dict()},
            "schedulers": {"net": sched.state_dict()}, "ema": {"net": ema.state_dict()},
            "history": [{"step": 2, "loss": 0.25, "lr": 0.01, "note": None}], "attempts": [0, 2]}


def test_state_round_trip_is_exact(tmp_path: Path) -> None:
    state = toy_state()
    ckpt.save_state(tmp_path, state)
    loaded = ckpt.load_state(tmp_path)
    assert loaded.pop("format") == ckpt.FORMAT_VERSION
    assert_same(loaded, state, "state")


def test_model_round_trip_is_exact(tmp_path: Path) -> None:
    config = {"lr": 1e-3, "model": {"latent_dim": 256, "layers": [1, 2], "dropout": None, "text": "clip"},
              "ema": True}
    payload = ckpt.final_model_payload(toy_state(), config)
    ckpt.save_final_model(tmp_path, payload)
    loaded = ckpt.load_final_model(tmp_path)
    assert_same(loaded, payload, "model")
    assert sorted(loaded["ema"]) == ["net"] and loaded["config"] == config


def draws() -> tuple[torch.Tensor, np.ndarray, list[float]]:
    """Draws from the torch, numpy and python global RNGs, Gaussian ones included."""
    return torch.rand(5), np.random.standard_normal(3), [random.random(), random.gauss(0, 1)]  # noqa: NPY002


def test_rng_round_trip_gives_the_same_draws(tmp_path: Path) -> None:
    ckpt.seed_everything(7)
    np.random.standard_normal(1)  # noqa: NPY002 (leaves numpy's second Gaussian cached)
    random.gauss(0, 1)  # leaves python's second Gaussian cached
    numpy_cached, python_cached = np.random.get_state()[3], random.getstate()[2]  # noqa: NPY002
    assert numpy_cached == 1 and python_cached is not None  # the caches are part of what must round-trip
    ckpt.save_rng(tmp_path, 0, CPU)
    expected = draws()
    ckpt.seed_everything(8)
    assert ckpt.load_rng(tmp_path, 0, CPU) is True
    got = draws()
    assert torch.equal(got[0], expected[0])
    np.testing.assert_array_equal(got[1], expected[1])
    assert got[2] == expected[2]
    assert ckpt.load_rng(tmp_path, 1, CPU) is False  # no file for rank 1


def test_a_gpu_rank_saves_and_restores_its_own_devices_cuda_state(tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """Only the rank's own GPU state is kept (not every visible GPU's by index), and it goes back to that GPU."""
    gpu = torch.device("cuda", 1)
    calls = []
    monkeypatch.setattr(torch.cuda, "get_rng_state", lambda device: calls.append(("get", device)) or
                        torch.arange(8, dtype=torch.uint8))
    monkeypatch.setattr(torch.cuda, "set_rng_state",
                        lambda state, device: calls.append(("set", device, state.tolist())))
    ckpt.save_rng(tmp_path, 0, gpu)
    assert ckpt.load_rng(tmp_path, 0, gpu) is True
    assert calls == [("get", gpu), ("set", gpu, list(range(8)))]
    assert ckpt.load_rng(tmp_path, 0, CPU) is True and len(calls) == 2  # a GPU snapshot resumed on the CPU


def test_a_cpu_snapshot_resumed_on_a_gpu_asks_for_a_fresh_seed(tmp_path: Path) -> None:
    """A CPU run's snapshot has no CUDA state; resumed on a GPU, load_rng says False (the runner then seeds
    every generator from the rank and the step) instead of leaving every rank's GPU generator alike."""
    ckpt.save_rng(tmp_path, 0, CPU)
    assert "cuda" not in ckpt.capture_rng(CPU)
    ckpt.seed_everything(3)
    before = torch.get_rng_state()
    assert ckpt.load_rng(tmp_path, 0, torch.device("cuda")) is False
    assert torch.equal(torch.get_rng_state(), before)  # nothing half-restored


# --------------------------------------------------------------------------- the command line


@pytest.mark.slow
def test_generate_refuses_a_crafted_model(tmp_path: Path, small_store: dict[str, Any]) -> None:
    """``python -m stages.generate`` on a planted ``train_mld/model.pt``: exit 1, one line, nothing ran."""
    marker = tmp_path / "pwned"
    model = plant(tmp_path / "artifacts" / "train_mld" / ckpt.MODEL_FILE, marker,
                  LOADERS[ckpt.MODEL_FILE][1])
    out = tmp_path / "walk.npy"
    proc = subprocess.run(
        [sys.executable, "-m", "stages.generate", "--model", "mld", "--text", "a person walks", "--out", str(out),
         f"paths.artifacts={tmp_path / 'artifacts'}", f"features.out={small_store['features']['out']}"],
        cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1
    assert proc.stderr == f"generate: {model}: {REFUSED}\n"
    assert not marker.exists()
    assert not out.exists()
