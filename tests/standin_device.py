"""A stand-in accelerator for tests on machines without a GPU.

:class:`StandIn` is a torch function mode under which ``STANDIN`` (torch's ``meta`` device) behaves as a GPU
whose tensors hold their data on the CPU: ``module.to(STANDIN)``, ``tensor.to(STANDIN)`` and factory functions
with ``device=STANDIN`` give :class:`OnStandIn` tensors, whose ``device`` is ``STANDIN`` (``"cuda"`` names it
too). As CUDA does, an operation that mixes them with CPU tensors of one or more dimensions raises (and
concatenation with any CPU tensor); indexing a device tensor with CPU integer or boolean indices, packing
sequences with CPU lengths and copying a CPU tensor into a device one are allowed, and their reverses refused;
a CPU generator cannot draw on the device; ``.numpy()`` and ``np.asarray`` refuse device tensors, and
``.cpu()`` and ``.to("cpu")`` bring them back.

``StandIn.syncs`` counts, by operation, what would make the host wait for a GPU's queue to drain: a device
tensor read back (``item``, ``tolist``, ``bool``/``int``/``float``, ``.cpu()``, ``.to("cpu")``) and a CPU
tensor copied onto the device (``.to(device)``, ``copy_``, ``torch.tensor(..., device=...)``, CPU indices of
a device tensor: a copy from pageable memory waits too). A sampler whose count does not grow with its
number of steps does not wait at every step.

Their arithmetic is the CPU's, so a computation on the stand-in gives the CPU's numbers up to the kernel a
tensor subclass may take (a non-contiguous input to ``F.linear``: differences near 1e-7); a test compares the
two with a tolerance. What the stand-in cannot show: CUDA's own kernels (cuDNN, TF32, the attention backends),
its memory, and code that tests ``device.type == "cuda"``.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from typing import Any

import torch
import torch.utils._pytree as pytree
from torch.overrides import TorchFunctionMode

STANDIN = torch.device("meta")
#: Operations that may take CPU integer or boolean tensors beside device tensors, as CUDA allows: indices, and
#: the lengths and batch sizes of packed sequences (which CUDA requires on the CPU).
CPU_INTEGERS = frozenset({"__getitem__", "__setitem__", "index_put_", "_pack_padded_sequence", "_pad_packed_sequence",
                          "gru", "lstm", "rnn_tanh", "rnn_relu"})
#: Operations that may copy a CPU tensor into a device tensor (CUDA allows it).
COPYING = frozenset({"copy_", "__setitem__"})
#: Operations that refuse even a 0-dimensional CPU tensor beside device tensors.
CONCATENATING = frozenset({"cat", "concat", "concatenate", "stack", "hstack", "vstack"})
#: Indexing, which copies CPU index tensors to the device.
INDEXING = frozenset({"__getitem__", "__setitem__", "index_put_"})
#: Operations that read a device tensor back to the host.
READING_BACK = frozenset({"item", "tolist", "__bool__", "__int__", "__float__", "__index__", "cpu"})
#: Factory functions that copy host data onto the device they are given.
FROM_HOST = frozenset({"tensor", "as_tensor"})


class OnStandIn(torch.Tensor):
    """A tensor on the stand-in device (its data on the CPU)."""

    def __deepcopy__(self, memo: dict[int, Any]) -> torch.Tensor:  # copy.deepcopy of a network on the device
        copied = self.detach().clone().as_subclass(OnStandIn).requires_grad_(self.requires_grad)
        if getattr(self, "_is_param", False):
            copied = torch.nn.Parameter(copied, self.requires_grad)
        memo[id(self)] = copied
        return copied


def _target(args: tuple, kwargs: dict[str, Any]) -> torch.device | None:
    """The device a ``Tensor.to`` call asks for, or None (a dtype change only)."""
    for arg in (*args[1:], kwargs.get("device"), kwargs.get("other")):
        if isinstance(arg, str | torch.device):
            return STANDIN if torch.device(arg).type == "cuda" else torch.device(arg)
        if isinstance(arg, torch.Tensor):
            return STANDIN if type(arg) is OnStandIn else torch.device("cpu")
    return None


def _dtype(args: tuple, kwargs: dict[str, Any]) -> torch.dtype | None:
    dtypes = [a for a in (*args[1:], kwargs.get("dtype")) if isinstance(a, torch.dtype)]
    others = [a.dtype for a in (*args[1:], kwargs.get("other")) if isinstance(a, torch.Tensor)]
    return (dtypes or others or [None])[0]


def _wrap(out: Any) -> Any:
    return pytree.tree_map(lambda x: x.as_subclass(OnStandIn) if type(x) is torch.Tensor else x, out)


class StandIn(TorchFunctionMode):
    """The torch function mode that gives ``STANDIN`` its GPU-like rules, and counts the host's waits
    (module docstring)."""

    def __init__(self) -> None:
        super().__init__()
        self.syncs: Counter[str] = Counter()

    def __torch_function__(self, func, types, args=(), kwargs=None):  # noqa: ANN001 - torch's protocol
        kwargs = dict(kwargs or {})
        name = getattr(func, "__name__", "")
        with torch._C.DisableTorchFunctionSubclass():
            first = args[0] if args else None
            on_standin = type(first) is OnStandIn
            if on_standin and name in READING_BACK:
                self.syncs[name] += 1
            if name == "__get__" and getattr(getattr(func, "__self__", None), "__name__", "") == "device":
                return STANDIN if on_standin else func(*args)
            if name == "_has_compatible_shallow_copy_type":  # Module.to: make new parameters, not set .data
                return type(args[0]) is type(args[1])
            if name in ("to", "cpu", "cuda") and isinstance(first, torch.Tensor):
                target = {"cpu": torch.device("cpu"), "cuda": STANDIN}.get(name) or _target(args, kwargs)
                dtype = _dtype(args, kwargs) if name == "to" else None
                out = first if dtype is None else torch.Tensor.to(first, dtype=dtype)
                if target is None:
                    target = STANDIN if on_standin else torch.device("cpu")
                if on_standin != (target.type == STANDIN.type) and name != "cpu":  # .cpu() is counted above
                    self.syncs["to device" if target.type == STANDIN.type else "to cpu"] += 1
                return out.as_subclass(OnStandIn if target.type == STANDIN.type else torch.Tensor)
            if name in ("numpy", "__array__") and on_standin:
                raise TypeError("can't convert a stand-in device tensor to numpy: use .cpu() first")
            device = kwargs.get("device")
            factory = device is not None and torch.device(device).type in (STANDIN.type, "cuda")
            if factory:
                if name in FROM_HOST and type(first) is not OnStandIn:
                    self.syncs[f"{name} to device"] += 1
                generator = kwargs.get("generator")
                if generator is not None and generator.device.type == "cpu":
                    raise RuntimeError(f"{name}: a CPU generator cannot draw on the stand-in device")
                kwargs["device"] = "cpu"
            tensors = [x for x in pytree.tree_flatten((args, kwargs))[0] if isinstance(x, torch.Tensor)]
            mixed = any(type(x) is OnStandIn for x in tensors)
            if mixed:
                if name == "_pack_padded_sequence" and type(args[1]) is OnStandIn:
                    raise RuntimeError(f"{name}: the lengths must be a CPU tensor")
                if name in CPU_INTEGERS and not on_standin:
                    raise RuntimeError(f"{name}: a CPU tensor with indices on the stand-in device")
                if name in COPYING | INDEXING and on_standin and any(
                        type(x) is not OnStandIn and (x.dim() > 0 or name in COPYING) for x in tensors[1:]):
                    self.syncs[f"{name} from the host"] += 1  # the source or the indices (a 0-d one is read) copied
                cpu = [] if name in COPYING and on_standin else [
                    x for x in tensors if type(x) is not OnStandIn and (x.dim() > 0 or name in CONCATENATING)
                    and not (name in CPU_INTEGERS and not x.is_floating_point())]
                if cpu:
                    raise RuntimeError(f"{name}: a tensor on the stand-in device met a CPU tensor of shape "
                                       f"{tuple(cpu[0].shape)}")
            out = func(*args, **kwargs)
        if name == "_pack_padded_sequence" and mixed:  # the packed data on the device, its batch sizes on the CPU
            return _wrap(out[0]), out[1]
        return _wrap(out) if mixed or factory else out


def syncs_of(run: Callable[[], object]) -> Counter[str]:
    """What ``run()`` makes the host wait for, counted on a fresh stand-in (module docstring)."""
    with StandIn() as mode:
        run()
    return mode.syncs
