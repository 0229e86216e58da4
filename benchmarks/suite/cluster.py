"""The runs of a suite on a ``dask.distributed`` cluster (``meshbench run --executor dask``).

Each run is one dask task. The task does not train in the worker process itself: it starts
the run in a fresh spawned child process exactly as the local runner does
(``procs.run_tasks`` with one job), so every guarantee of the local runner holds on the
cluster unchanged: the pinned kernel settings (``procs.REPRO_ENV``) are in the child's
environment before torch loads, plugins are loaded in the child, peak memory is the run's own,
the run directory is ``flock``-ed by the child (``procs.DirLock``), and the child is SIGKILLed
by the kernel when the worker process dies (``PR_SET_PDEATHSIG``), which drops its lock; the
next invocation (or dask's retry of the task on another worker) then resumes the run from its
``last.pt``.

Design: **workers share the data and runs directories with the client** (a shared filesystem,
mounted at the same paths, e.g. NFS or Lustre on a cluster; trivially true for workers on the
same machine). The client generates missing data before it submits the runs, the workers read
it and write their runs there, and the client reads the finished runs to write the results.
Plugin files are passed by path, so they must be on the shared filesystem too. The worker
hosts need meshbench installed in the same version (``pip install -e '.[ml,fem,cluster]'``).
"""

from __future__ import annotations

import contextlib
import multiprocessing
import socket

from benchmarks.suite import procs


@contextlib.contextmanager
def _children_allowed():
    """Dask runs tasks in daemonic worker processes by default, and ``multiprocessing``
    refuses to start children from a daemonic process; the run's child is stopped with its
    worker anyway (``PR_SET_PDEATHSIG``), which is what the flag is meant to guarantee."""
    cfg = multiprocessing.current_process()._config
    daemon = cfg.get("daemon")
    cfg["daemon"] = False
    try:
        yield
    finally:
        if daemon is not None:
            cfg["daemon"] = daemon


def remote_task(fn, args) -> tuple:
    """Executed by a dask worker: ``fn(*args)`` in a fresh spawned child process. Returns
    ``(kind, value, host)`` with ``kind``/``value`` as ``procs.run_tasks`` reports them."""
    procs.apply_repro_env()  # inherited by the child (values set on the worker win)
    out = {}
    with _children_allowed():
        procs.run_tasks({0: (fn, args)}, 1, lambda key, kind, value: out.update(
            kind=kind, value=value))
    return out.get("kind", "died"), out.get("value"), socket.gethostname()


def connect(scheduler: str | None, n_workers: int):
    """A ``distributed.Client``: to ``scheduler`` (``tcp://HOST:PORT``), or to a new
    ``LocalCluster`` of ``n_workers`` single-threaded worker processes. Returns
    ``(client, cluster or None)``."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise ValueError("--executor dask needs dask.distributed: pip install -c "
                         "constraints.txt -e '.[cluster]'") from None
    if scheduler:
        try:
            return Client(scheduler, timeout="20s"), None
        except (OSError, TimeoutError) as e:
            raise ValueError(f"--scheduler {scheduler!r}: cannot connect ({e})") from None
    # loopback only: no other machine can reach the scheduler, whose clients may submit any
    # code (docs/CLUSTER.md, "Securing a shared scheduler"); its HTTP server (health, metrics)
    # always starts, so it is bound to loopback too, on a free port, without the dashboard
    cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                           host="127.0.0.1", dashboard_address="127.0.0.1:0",
                           worker_dashboard_address=None, scheduler_kwargs={"dashboard": False})
    return Client(cluster), cluster


def run_tasks_dask(tasks: dict, on_result, scheduler: str | None = None,
                   n_workers: int = 1) -> None:
    """``procs.run_tasks`` on dask: every ``key: (fn, args)`` of ``tasks`` becomes one task
    (``remote_task``); ``on_result(key, kind, value)`` as there, for ``"ok"`` results
    ``value`` gets the worker's ``host``. A task whose workers all died (``KilledWorker``
    after dask's retries) is reported as ``"died"``; on Ctrl-C queued runs are cancelled
    (running ones stop with a ``LocalCluster``; on a remote cluster they run to their end)."""
    from distributed import as_completed

    client, cluster = connect(scheduler, n_workers)
    try:
        futures = {client.submit(remote_task, fn, args, key=f"meshbench-{key}", pure=False): key
                   for key, (fn, args) in tasks.items()}
        for fut in as_completed(futures):
            key = futures[fut]
            try:
                kind, value, host = fut.result()
            except Exception as e:  # noqa: BLE001 - KilledWorker, lost scheduler, ...
                on_result(key, "died", f"{type(e).__name__}: {e}")
                continue
            if kind == "ok" and isinstance(value, dict):
                value = {**value, "host": host}
            on_result(key, kind, value)
    finally:
        # closing the client releases its futures: the scheduler forgets the queued runs
        # (a running one finishes on its worker); a LocalCluster stops its workers
        with contextlib.suppress(Exception):
            client.close(timeout=10)
        if cluster is not None:
            with contextlib.suppress(Exception):
                cluster.close(timeout=10)


