"""A stand-in accelerator for tests on machines without a GPU.

:class:`StandIn` is a torch function mode under which ``STANDIN`` (torch's ``meta`` device) behaves as a GPU
whose tensors hold their data on the CPU: ``module.to(STANDIN)``, ``tensor.to(STANDIN)`` and factory functions
with ``device=STANDIN`` give :class:`OnStandIn` tensors, whose ``device`` is ``STANDIN``. As CUDA does, an
operation that mixes them with CPU tensors of one or more dimensions raises (indexing with a CPU integer or
boolean tensor, packing sequences with CPU lengths and copying a CPU tensor into them are allowed, as CUDA
allows them), and ``.numpy()``
refuses them; ``.cpu()`` and ``.to("cpu")``
bring them back. Their arithmetic is the CPU's, so a computation run on the stand-in gives the CPU's numbers
bit for bit: a test can compare the two.
"""

from __future__ import annotations

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
            return torch.device(arg)
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
    """The torch function mode that gives ``STANDIN`` its GPU-like rules (module docstring)."""

    def __torch_function__(self, func, types, args=(), kwargs=None):  # noqa: ANN001 - torch's protocol
        kwargs = dict(kwargs or {})
        name = getattr(func, "__name__", "")
        with torch._C.DisableTorchFunctionSubclass():
            first = args[0] if args else None
            on_standin = type(first) is OnStandIn
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
                return out.as_subclass(OnStandIn if target.type == STANDIN.type else torch.Tensor)
            if name == "numpy" and on_standin:
                raise TypeError("can't convert a stand-in device tensor to numpy: use .cpu() first")
            factory = kwargs.get("device") is not None and torch.device(kwargs["device"]).type == STANDIN.type
            if factory:
                kwargs["device"] = "cpu"
            tensors = [x for x in pytree.tree_flatten((args, kwargs))[0] if isinstance(x, torch.Tensor)]
            mixed = any(type(x) is OnStandIn for x in tensors)
            if mixed:
                cpu = [] if name in COPYING and on_standin else [
                    x for x in tensors if type(x) is not OnStandIn and x.dim() > 0
                    and not (name in CPU_INTEGERS and not x.is_floating_point())]
                if cpu:
                    raise RuntimeError(f"{name}: a tensor on the stand-in device met a CPU tensor of shape "
                                       f"{tuple(cpu[0].shape)}")
            out = func(*args, **kwargs)
        if name == "_pack_padded_sequence" and mixed:  # the packed data on the device, its batch sizes on the CPU
            return _wrap(out[0]), out[1]
        return _wrap(out) if mixed or factory else out
