"""Where ``meshbench bench`` runs: the device's description, waiting for its queued work
before a clock is read, and its peak memory. On the CPU the waits do nothing and the peak
memory is the process's resident memory (``enginebench.peak_gb``); on a CUDA device the
kernels run asynchronously, so every timing ends with ``sync``, and the peak is
``torch.cuda.max_memory_allocated`` (tensors only, not the CUDA context). torch is imported
inside the functions: ``meshbench``'s parser loads this module before the kernel settings are
pinned (``benchmarks.suite.procs``)."""

from __future__ import annotations


def sync(device) -> None:
    """Wait until the work queued on ``device`` has run (CUDA); nothing on the CPU."""
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)


def reset_peak(device) -> None:
    """Start ``cuda_peak_gb`` afresh (CUDA); nothing on the CPU."""
    import torch

    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)


def cuda_peak_gb(device) -> float | None:
    """Peak GPU memory held by tensors since ``reset_peak``, GB; None on the CPU."""
    import torch

    if device.type != "cuda":
        return None
    sync(device)
    return torch.cuda.max_memory_allocated(device) / 1024**3


def describe(device) -> dict:
    """``device`` (its name as ``--device`` takes it), ``type``, ``name`` (the GPU's, or the
    CPU's model) and on a GPU its memory (GB), compute capability and CUDA version."""
    import torch

    out = {"device": str(device), "type": device.type, "torch": torch.__version__}
    if device.type != "cuda":
        return {**out, "name": _cpu_model()}
    p = torch.cuda.get_device_properties(device)
    return {**out, "name": p.name, "total_memory_gb": p.total_memory / 1024**3,
            "capability": f"{p.major}.{p.minor}", "cuda": torch.version.cuda,
            "multiprocessors": p.multi_processor_count}


def _cpu_model() -> str:
    import platform

    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"
