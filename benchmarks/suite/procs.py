"""Worker processes that stop with their parent, run-directory locks, and the numerical
environment that makes CPU results reproducible across machines of the same kind.

- ``worker_init`` (the initializer of every process pool): the worker ignores SIGINT (Ctrl-C
  goes to the whole foreground process group; the parent decides what stops), turns SIGTERM
  into ``KeyboardInterrupt`` so ``finally`` blocks run, and asks Linux to SIGKILL it when
  its parent dies (``PR_SET_PDEATHSIG``), so a killed ``meshbench`` leaves no worker behind.
- ``run_tasks``: one spawned process per task, ``jobs`` at a time; on Ctrl-C the running
  ones are stopped and the queued ones never start. ``stop_pool`` does the same for a
  ``ProcessPoolExecutor`` (``generate``): cancel what is queued, terminate the workers (TERM,
  then KILL after ``grace`` seconds) instead of waiting for them.
- ``DirLock``: an advisory ``flock`` on ``DIR/.lock``; the kernel drops it when its holder
  dies, so a lock can never go stale, and the pid written in the file names the holder.
- ``remove_partial_writes``: the temporary files that a process killed in the middle of an
  atomic write left behind (a worker still busy in a slow ``fsync`` when its grace period
  ends gets SIGKILL; a SIGTERM can also land between the temporary file's creation and the
  ``try`` that removes it). Whoever holds the directory's lock deletes them: the parent
  once its stopped workers are gone (``sweep_after_stop``), a run or ``train`` when it lets
  the directory go, a generation when it starts and when it is stopped.
- ``REPRO_ENV``: the kernel-dispatch settings pinned in every worker (see docs/SUITE.md,
  "Reproducibility"): which SIMD code paths torch, MKL, oneDNN and OpenBLAS take.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import fcntl
import os
import re
import signal
import sys
import time
from pathlib import Path

#: Pinned in every worker process unless already set in the environment. They must be in
#: the environment before torch / numpy load their kernels, hence spawn-started workers.
REPRO_ENV = {
    "ATEN_CPU_CAPABILITY": "avx2",   # torch's own vectorised kernels: AVX2, not AVX-512
    "MKL_CBWR": "AVX2",              # MKL (torch's BLAS): the AVX2 code path everywhere
    "ONEDNN_MAX_CPU_ISA": "AVX2",    # oneDNN (convolutions, some linear layers)
    "OPENBLAS_CORETYPE": "Haswell",  # OpenBLAS (numpy / scipy, the ground-truth solvers)
}
#: The pins of torch's CPU kernels: skipped for a command run with ``--device cuda`` (its
#: model runs on the GPU, whose kernels they do not select). OpenBLAS's pin stays: numpy and
#: scipy (the ground-truth solvers) run on the CPU whatever the device.
TORCH_PINS = ("ATEN_CPU_CAPABILITY", "MKL_CBWR", "ONEDNN_MAX_CPU_ISA")
PR_SET_PDEATHSIG = 1


def runs_on_cuda(device) -> bool:
    """Whether ``--device device`` names a CUDA device. ``auto`` does not: whether it picks
    one is known only once torch has loaded, after the pins must be set (on a GPU the torch
    pins are then set but select nothing the model runs)."""
    return str(device).startswith("cuda")


def repro_env(device=None) -> dict:
    """The pinned settings, or ``{}`` where they do not apply (not x86-64, or
    ``MESHBENCH_NO_PIN=1``); without ``TORCH_PINS`` when ``runs_on_cuda(device)``. Values
    already in the environment win."""
    import platform

    if os.environ.get("MESHBENCH_NO_PIN") == "1" or platform.machine() not in ("x86_64", "AMD64"):
        return {}
    skip = TORCH_PINS if runs_on_cuda(device) else ()
    return {k: os.environ.get(k, v) for k, v in REPRO_ENV.items() if k not in skip}


def apply_repro_env(device=None) -> dict:
    """Put the pinned settings (``repro_env(device)``) into ``os.environ`` (for processes
    started afterwards, and for torch and numpy when they have not loaded yet)."""
    env = repro_env(device)
    os.environ.update(env)
    return env


def _raise_interrupt(signum, frame):
    # the first SIGTERM unwinds (finally blocks, temporary files); a second one kills
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    raise KeyboardInterrupt(f"signal {signum}")


def die_with_parent() -> None:
    """SIGKILL this process when its parent dies (Linux); elsewhere a no-op."""
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    except (OSError, AttributeError):
        return


def worker_init(parent_pid: int | None = None) -> None:
    """Initializer of every worker process (see the module docstring)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _raise_interrupt)
    die_with_parent()
    if parent_pid is not None and os.getppid() != parent_pid:  # parent died before prctl
        os._exit(1)


def stop_pool(pool, grace: float = 5.0) -> None:
    """Cancel queued work and stop the running workers of a ``ProcessPoolExecutor`` now
    (``stop_processes``) instead of waiting for them as ``with ProcessPoolExecutor`` does."""
    plist = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    stop_processes(plist, grace)


class WorkerDied(RuntimeError):
    """A task's process ended without a result (killed, out of memory)."""


def _task_main(queue, key, fn, args, parent_pid):
    worker_init(parent_pid)
    try:
        out = ("ok", fn(*args))
    except Exception as e:  # noqa: BLE001 - reported to the parent, which decides
        out = ("error", (type(e).__name__, str(e), isinstance(e, (ValueError, RuntimeError,
                                                                   FloatingPointError, OSError))))
    except KeyboardInterrupt:
        out = ("interrupted", None)
    queue.put((key, *out))


def run_tasks(tasks: dict, jobs: int, on_result, poll: float = 0.5, after_stop=None) -> None:
    """Run ``fn(*args)`` for every ``key: (fn, args)`` of ``tasks``, each in a fresh spawned
    process (its own peak memory, no state carried between tasks), ``jobs`` at a time, in
    order. ``on_result(key, kind, value)`` gets ``kind`` "ok" (value: the return value),
    "error" (value: (type name, message, is an expected error)) or "died" (value: the exit
    code). On any exception in the parent (Ctrl-C) the running processes are stopped
    (``stop_processes``) and the queued tasks never start. ``after_stop(key)`` is called for
    every task whose process died or was stopped, once it is gone (to clean up after it)."""
    import multiprocessing
    import queue as queue_mod

    ctx = multiprocessing.get_context("spawn")
    q = ctx.Queue()
    todo = list(tasks)
    running: dict = {}
    try:
        while todo or running:
            while todo and len(running) < jobs:
                key = todo.pop(0)
                fn, args = tasks[key]
                p = ctx.Process(target=_task_main, args=(q, key, fn, args, os.getpid()),
                                daemon=False)
                p.start()
                running[key] = p
            try:
                key, kind, value = q.get(timeout=poll)
            except queue_mod.Empty:
                for key, p in list(running.items()):
                    if not p.is_alive() and p.exitcode not in (None, 0):
                        del running[key]
                        if after_stop is not None:
                            after_stop(key)
                        on_result(key, "died", p.exitcode)
                continue
            p = running.pop(key, None)
            if p is not None:
                p.join()
            on_result(key, kind, value)
    except BaseException:
        stop_processes(list(running.values()))
        if after_stop is not None:
            for key in running:
                with contextlib.suppress(Exception):
                    after_stop(key)
        raise
    finally:
        q.close()


def stop_processes(plist, grace: float = 5.0) -> None:
    """SIGTERM (the process unwinds), after 1 s SIGTERM again (default action: it dies),
    after ``grace`` s SIGKILL."""
    for p in plist:
        with contextlib.suppress(Exception):
            p.terminate()
    for wait, last in ((1.0, False), (grace, True)):
        deadline = time.monotonic() + wait
        for p in plist:
            with contextlib.suppress(Exception):
                p.join(max(0.0, deadline - time.monotonic()))
        for p in plist:
            with contextlib.suppress(Exception):
                if p.is_alive():
                    p.kill() if last else p.terminate()
    for p in plist:
        with contextlib.suppress(Exception):
            p.join(1.0)


#: The names ``tempfile.mkstemp(prefix=f".{name}.", suffix=".tmp")`` gives: the temporary
#: files of the atomic writers (``groundtruth.store.atomic_write``,
#: ``meshodenet.training.train._atomic_bytes``), eight random characters before ``.tmp``.
PARTIAL_WRITE = re.compile(r"\..+\.[a-z0-9_]{8}\.tmp")


def remove_partial_writes(directory) -> list:
    """Delete the atomic writers' temporary files (``PARTIAL_WRITE``) directly in
    ``directory``; returns their paths. The caller must hold the directory's lock (no live
    writer may be using them)."""
    removed = []
    try:
        entries = list(Path(directory).iterdir())
    except FileNotFoundError:
        return removed
    for f in entries:
        if PARTIAL_WRITE.fullmatch(f.name) and f.is_file():
            with contextlib.suppress(FileNotFoundError):
                f.unlink()
                removed.append(f)
    return removed


def sweep_after_stop(directory, name: str = ".lock", wait: float = 5.0) -> list:
    """``remove_partial_writes(directory)`` once ``DirLock(directory, name)`` is free: the
    kernel drops a killed worker's lock only when it has really died (a process in an
    uninterruptible ``fsync`` dies when that returns), so this waits up to ``wait`` s and
    leaves the files to the next run when the lock stays busy (another live process)."""
    if not (Path(directory) / name).exists():  # never started: nothing to sweep, no lock file
        return []
    try:
        lock = DirLock(directory, name).acquire(wait=True, poll=0.05, timeout=wait)
    except LockBusy:
        return []
    try:
        return remove_partial_writes(directory)
    finally:
        lock.release()


class LockBusy(RuntimeError):
    pass


class DirLock:
    """``flock`` on ``DIR/.lock``. ``acquire(wait=False)`` raises ``LockBusy`` naming the
    holder; ``acquire(wait=True)`` waits (at most ``timeout`` s, then ``LockBusy``), calling
    ``on_wait(pid)`` once. The file stays (a
    lock file is never deleted: that would let two processes lock two different files)."""

    def __init__(self, directory, name: str = ".lock"):
        self.path = Path(directory) / name
        self.fd = None

    def holder(self) -> int | None:
        try:
            return int(self.path.read_text().strip() or 0) or None
        except (OSError, ValueError):
            return None

    def acquire(self, wait: bool = False, on_wait=None, poll: float = 0.5,
                timeout: float | None = None):
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        told = False
        deadline = None if timeout is None else time.monotonic() + timeout
        try:
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except OSError as e:
                    if e.errno not in (errno.EAGAIN, errno.EACCES):
                        raise
                    if not wait or (deadline is not None and time.monotonic() >= deadline):
                        raise LockBusy(f"{self.path.parent} is in use by process "
                                       f"{self.holder() or '?'}") from None
                    if not told and on_wait is not None:
                        on_wait(self.holder())
                        told = True
                    time.sleep(poll)
            os.ftruncate(fd, 0)
            os.write(fd, str(os.getpid()).encode())
            os.fsync(fd)
        except BaseException:
            os.close(fd)
            raise
        self.fd = fd
        return self

    def release(self) -> None:
        if self.fd is not None:
            with contextlib.suppress(OSError):
                os.ftruncate(self.fd, 0)
            os.close(self.fd)  # closing drops the flock
            self.fd = None

    def __enter__(self):
        return self.acquire() if self.fd is None else self

    def __exit__(self, *exc):
        self.release()


def peak_rss_mb() -> float:
    """Peak resident memory of *this* process in MB: ``VmHWM`` of /proc/self/status.

    Not ``getrusage(RUSAGE_SELF).ru_maxrss``: Linux carries ``ru_maxrss`` across ``fork`` +
    ``exec``, so a spawned worker reports at least its parent's resident memory at the time
    it was started (every run of a suite then showed the parent's figure)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def longest_first(run_ids: list, costs: str | Path | None) -> list:
    """``run_ids`` in the order to start them: those with a recorded training time in the
    ``runs.csv`` ``costs`` (columns ``run``, ``train_wall_time_s``) longest first, runs it
    does not record (their time unknown) before them in the suite's order; unchanged without
    ``costs`` or when it is missing or unreadable. With ``--jobs K`` the suite's longest run
    then starts at once rather than when a slot frees (the main job's plate MeshODENet run is
    three quarters of its time)."""
    import csv

    if costs is None or not Path(costs).is_file():
        return list(run_ids)
    recorded = {}
    try:
        with open(costs, newline="") as f:
            for row in csv.DictReader(f):
                try:
                    recorded[row["run"]] = float(row["train_wall_time_s"])
                except (KeyError, TypeError, ValueError):
                    continue
    except (OSError, csv.Error, UnicodeDecodeError):
        return list(run_ids)
    pos = {k: i for i, k in enumerate(run_ids)}
    return sorted(run_ids, key=lambda k: (k in recorded, -recorded.get(k, 0.0), pos[k]))
