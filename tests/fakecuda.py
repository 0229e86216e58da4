"""A CUDA device emulated on the CPU, for finding device bugs without a GPU.

``FakeCuda`` is a ``TorchFunctionMode``: inside it every tensor carries a device label
(``cpu`` or ``cuda``) while its data stays on the CPU. Factories given ``device="cuda"``,
``Tensor.to("cuda")`` / ``.cuda()`` and ``nn.Module.to("cuda")`` label their results ``cuda``;
``Tensor.device`` and ``is_cuda`` report the label, so code that follows a tensor's device
(``torch.zeros(..., device=x.device)``) follows it here too. Every other op checks its tensor
arguments as CUDA does and raises ``DeviceMismatch`` where CUDA would refuse:

- tensors of both labels in one op (a 0-dim CPU tensor is allowed beside CUDA ones, and CPU
  index tensors may index a CUDA tensor, as in CUDA);
- ``.numpy()`` of a ``cuda`` tensor;
- a random factory or sampler on one device drawing from a ``torch.Generator`` of another.

Results are labelled like their tensor arguments; a parameter's ``.grad`` like the parameter.
Tensors made where the mode does not see them (``nn.Parameter`` wraps its data there: see
``label_cpu``) carry no label and are never reported: the emulation finds mixed devices, it
does not prove their absence. The ``torch.cuda`` functions of ``CUDA_STUBS`` are replaced
while the mode is active.
"""

from __future__ import annotations

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._pytree import tree_flatten, tree_map

LABEL = "_fake_device"


class DeviceMismatch(RuntimeError):
    """An op that CUDA would refuse: tensors of two devices, or a CUDA tensor to numpy."""


def label(t) -> str | None:
    return getattr(t, LABEL, None) if isinstance(t, torch.Tensor) else None


def _set(t, dev: str):
    if isinstance(t, torch.Tensor):
        setattr(t, LABEL, dev)
    return t


def _dev_type(d) -> str | None:
    """``cpu`` / ``cuda`` of a device argument (str, ``torch.device``, int), else None."""
    if isinstance(d, torch.device):
        return d.type
    if isinstance(d, str):
        return torch.device(d).type
    if isinstance(d, int) and not isinstance(d, bool):
        return "cuda"
    return None


def _name(func) -> str:
    return getattr(func, "__qualname__", None) or getattr(func, "__name__", str(func))


GETTERS = {torch.Tensor.device.__get__: lambda t: torch.device("cuda", 0)
           if label(t) == "cuda" else torch.device("cpu"),
           torch.Tensor.is_cuda.__get__: lambda t: label(t) == "cuda",
           torch.Tensor.is_cpu.__get__: lambda t: label(t) != "cuda"}
INDEXING = {torch.Tensor.__getitem__, torch.Tensor.__setitem__}
#: ops that take tensors of any devices: copies and metadata (their result keeps its label)
ANY_DEVICE = {torch.Tensor.copy_, torch._has_compatible_shallow_copy_type,
              torch.Tensor.__repr__, torch.Tensor.__format__}


#: ``torch.cuda`` functions the code under test calls, answered as by an idle 16 GiB GPU
CUDA_STUBS = {"mem_get_info": lambda device=None: (8 * 2**30, 16 * 2**30),
              "synchronize": lambda device=None: None,
              "reset_peak_memory_stats": lambda device=None: None,
              "max_memory_allocated": lambda device=None: 2**20}


def label_cpu(module: torch.nn.Module) -> torch.nn.Module:
    """Label the parameters and buffers of ``module`` ``cpu`` (a module built inside the mode
    wraps its parameters where the mode does not see it)."""
    for t in list(module.parameters()) + list(module.buffers()):
        if label(t) is None:
            _set(t, "cpu")
    return module


class FakeCuda(TorchFunctionMode):
    """See the module docstring. ``ops`` counts the ops checked."""

    def __init__(self):
        super().__init__()
        self.ops = 0

    def __enter__(self):
        self._saved = {k: getattr(torch.cuda, k) for k in CUDA_STUBS}
        for k, fn in CUDA_STUBS.items():
            setattr(torch.cuda, k, fn)
        return super().__enter__()

    def __exit__(self, *exc):
        for k, fn in self._saved.items():
            setattr(torch.cuda, k, fn)
        return super().__exit__(*exc)

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = dict(kwargs or {})
        if func in GETTERS:
            return GETTERS[func](args[0])
        if func == torch.Tensor.grad.__get__:  # made by the autograd engine: the param's
            return _set(func(*args), label(args[0])) if label(args[0]) else func(*args)
        if func == torch.Tensor.data.__set__:
            func(*args, **kwargs)
            return _set(args[0], label(args[1]) or label(args[0]) or "cpu")
        if func in ANY_DEVICE:
            return func(*args, **kwargs)
        self.ops += 1
        if func in (torch.Tensor.to, torch.Tensor.cuda, torch.Tensor.cpu):
            return self._move(func, args, kwargs)
        if func is torch.Tensor.numpy and label(args[0]) == "cuda":
            raise DeviceMismatch("can't convert a cuda tensor to numpy: .cpu() first")
        target = _dev_type(kwargs.get("device"))
        if "device" in kwargs:
            kwargs["device"] = "cpu"
        inputs = [t for t in tree_flatten((args, kwargs))[0] if isinstance(t, torch.Tensor)]
        dev = target or self._check(func, inputs)
        self._check_generator(func, kwargs.get("generator"), dev or "cpu")
        out = func(*args, **kwargs)
        if func is torch.Tensor.__setitem__:
            return out
        if dev is None and not inputs:
            dev = "cpu"
        return tree_map(lambda t: _set(t, dev) if dev else t, out)

    def _check(self, func, inputs) -> str | None:
        """The common label of ``inputs``; ``DeviceMismatch`` where CUDA would refuse."""
        labelled = [(label(t), t) for t in inputs if label(t)]
        if func in INDEXING:  # CPU index tensors may index a CUDA tensor
            first = label(inputs[0])
            rest = {d for d, t in labelled[1:] if t is not inputs[0]}
            if first == "cpu" and "cuda" in rest:
                raise DeviceMismatch(f"{_name(func)}: a CPU tensor indexed by a CUDA tensor")
            return first
        devs = {d for d, t in labelled if not (d == "cpu" and t.dim() == 0)}
        if len(devs) > 1:
            shapes = [(d, tuple(t.shape)) for d, t in labelled]
            raise DeviceMismatch(f"{_name(func)}: tensors on cpu and cuda {shapes}")
        if devs:
            return devs.pop()
        return "cpu" if labelled else None

    @staticmethod
    def _check_generator(func, gen, dev: str) -> None:
        if isinstance(gen, torch.Generator) and gen.device.type != dev:
            raise DeviceMismatch(f"{_name(func)}: a {gen.device.type} generator for a {dev} "
                                 "tensor")

    @staticmethod
    def _move(func, args, kwargs):
        """``to`` / ``cuda`` / ``cpu``: the data stays on the CPU, the result gets the target
        label (a copy when the label changes, so the source keeps its own)."""
        src = args[0]
        target = {torch.Tensor.cuda: "cuda", torch.Tensor.cpu: "cpu"}.get(func)
        rest = list(args[1:])
        for i, a in enumerate(rest):
            d = a.device if isinstance(a, torch.Tensor) else None
            t = label(a) if d is not None else _dev_type(a)
            if t is not None:
                target = t
                rest[i] = torch.device("cpu") if d is None else a
        if "device" in kwargs:
            target = _dev_type(kwargs["device"]) or target
            kwargs["device"] = "cpu"
        if func is not torch.Tensor.to:
            rest, kwargs = [], {k: v for k, v in kwargs.items() if k == "memory_format"}
            func = torch.Tensor.to
        out = func(src, *rest, **kwargs)
        target = target or label(src) or "cpu"
        if out is src and label(src) != target:
            out = src.clone()  # the source keeps its device
        return _set(out, target)
