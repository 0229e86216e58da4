"""``meshbench run --executor dask``: a LocalCluster of 2 worker processes gives the local
runner's results; a scheduler and 2 workers started by hand on 127.0.0.1 run a suite (worker
host in runs.csv, reuse, one failing run reported while the other's result is kept); a worker
killed mid-run leaves a run that the next invocation resumes (slow)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from benchmarks.suite.compare import compare, read_csv

pytest.importorskip("distributed")
pytest.importorskip("torch")

TINY = "rod_tiny_cluster"
PLUGIN = f"""
from benchmarks.suite.registry import register_case
from benchmarks.suite.suites import RunSpec, Suite, register_suite
from groundtruth.cases import RodCase

register_case(RodCase(id="{TINY}", n_train=4, n_test=2, t_end=0.5), overwrite=True)
register_suite(Suite("cluster_pair", "two short runs", (
    RunSpec("{TINY}", "meshodenet", "smoke"), RunSpec("{TINY}", "mgn", "smoke"))),
    overwrite=True)
register_suite(Suite("cluster_fail", "a good run and one that fails", (
    RunSpec("{TINY}", "mgn", "smoke"),
    RunSpec("{TINY}", "meshodenet", "smoke", overrides=("model.hidden=0",)))), overwrite=True)
register_suite(Suite("cluster_long", "a run long enough to kill its worker", (
    RunSpec("{TINY}", "meshodenet", "smoke", overrides=("train.epochs=25",)),)),
    overwrite=True)
"""
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
BIN = Path(sys.executable).parent


def meshbench(root: Path, *args, timeout=300, check=True):
    cmd = [sys.executable, "-m", "benchmarks.cli", "--plugin", str(root / "plugin.py"), *args,
           "--data-dir", str(root / "data"), "--no-progress", "--no-figures"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=ENV)
    if check:
        assert r.returncode == 0, r.stderr[-3000:]
    return r


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    root = tmp_path_factory.mktemp("cluster")
    (root / "plugin.py").write_text(PLUGIN)
    r = subprocess.run([sys.executable, "-m", "benchmarks.cli", "--plugin", str(root / "plugin.py"),
                        "generate", TINY, "--data-dir", str(root / "data"), "--workers", "1",
                        "--no-progress"], capture_output=True, text=True, env=ENV, timeout=120)
    assert r.returncode == 0, r.stderr
    return root


class HandCluster:
    """``dask scheduler`` and ``dask worker`` processes on 127.0.0.1, each its own session."""

    def __init__(self, tmp: Path, n_workers: int):
        self.file = tmp / "scheduler.json"
        self.procs = [self._start([str(BIN / "dask"), "scheduler", "--host", "127.0.0.1",
                                   "--port", "0", "--no-dashboard", "--scheduler-file",
                                   str(self.file)], tmp / "scheduler.log")]
        deadline = time.monotonic() + 60
        while not self.file.exists() and time.monotonic() < deadline:
            time.sleep(0.2)
        self.address = json.loads(self.file.read_text())["address"]
        self.workers = [self.add_worker(tmp, k) for k in range(n_workers)]

    @staticmethod
    def _start(cmd, log: Path):
        return subprocess.Popen(cmd, stdout=log.open("w"), stderr=subprocess.STDOUT, env=ENV,
                                start_new_session=True)

    def add_worker(self, tmp: Path, k: int):
        p = self._start([str(BIN / "dask"), "worker", self.address, "--nthreads", "1",
                         "--nworkers", "1", "--host", "127.0.0.1", "--no-dashboard",
                         "--name", f"w{k}-{time.monotonic_ns()}"], tmp / f"worker{k}.log")
        self.procs.append(p)
        from distributed import Client

        with Client(self.address, timeout="30s") as c:
            c.wait_for_workers(len([q for q in self.procs[1:] if q.poll() is None]), timeout=60)
        return p

    def kill(self, p):
        os.killpg(p.pid, signal.SIGKILL)  # the worker and its nanny
        p.wait(10)

    def close(self):
        for p in reversed(self.procs):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        for p in self.procs:
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)


def test_local_cluster_of_two_workers_matches_the_local_runner(root):
    common = ["--suite", "cluster_pair", "--only", "mgn"]  # one run each: ~25 s together
    meshbench(root, "run", *common, "--results", str(root / "res_local"), "--runs-dir",
              str(root / "runs_local"), "--jobs", "2")
    r = meshbench(root, "run", *common, "--executor", "dask", "--jobs", "2", "--results",
                  str(root / "res_dask"), "--runs-dir", str(root / "runs_dask"))
    assert "trained in" in r.stderr
    a = read_csv(root / "res_local/cluster_pair/rmse_at_step.csv")
    b = read_csv(root / "res_dask/cluster_pair/rmse_at_step.csv")
    assert compare(a, b, rtol=1e-12).ok  # same kernels, same numbers
    runs = pd.read_csv(root / "res_dask/cluster_pair/runs.csv")
    assert (runs["host"] == socket.gethostname()).all()
    assert (runs["peak_rss_mb"] > 50).all()  # each run in its own process


@pytest.mark.slow
def test_hand_started_scheduler_and_two_workers(root, tmp_path):
    cl = HandCluster(tmp_path, 2)
    try:
        args = ["run", "--executor", "dask", "--scheduler", cl.address, "--results",
                str(root / "res_hand"), "--runs-dir", str(root / "runs_hand")]
        r = meshbench(root, *args, "--suite", "cluster_fail", check=False)
        assert r.returncode == 2, r.stderr[-2000:]
        assert "1 run(s) of suite 'cluster_fail' failed" in r.stderr
        assert "model.hidden" in r.stderr or "hidden" in r.stderr
        assert "Traceback" not in r.stderr
        good = root / "runs_hand" / f"{TINY}-mgn-smoke-s0"
        assert (good / "record.json").exists()  # the other run's result is kept
        r = meshbench(root, *args, "--suite", "cluster_pair")
        assert f"{TINY}-mgn-smoke-s0: reused" in r.stderr  # finished on the cluster, reused
        runs = pd.read_csv(root / "res_hand/cluster_pair/runs.csv")
        assert (runs["host"] == socket.gethostname()).all()
    finally:
        cl.close()


@pytest.mark.slow
def test_worker_killed_mid_run_is_resumed_by_the_next_invocation(root, tmp_path):
    from meshodenet.training.train import load_checkpoint

    cl = HandCluster(tmp_path, 1)
    runs = root / "runs_kill"
    run = runs / f"{TINY}-meshodenet-smoke-train.epochs=25-s0"
    args = ["--plugin", str(root / "plugin.py"), "run", "--suite", "cluster_long", "--executor",
            "dask", "--scheduler", cl.address, "--results", str(root / "res_kill"),
            "--runs-dir", str(runs), "--data-dir", str(root / "data"), "--no-progress",
            "--no-figures"]
    client = subprocess.Popen([sys.executable, "-m", "benchmarks.cli", *args], env=ENV,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline:
            dirs = list(runs.glob(f"{TINY}-meshodenet-*"))
            if dirs and (dirs[0] / "last.pt").exists():
                run = dirs[0]
                break
            time.sleep(0.1)
        else:
            raise AssertionError("no epoch finished")
        cl.kill(cl.workers[0])  # worker and nanny: the run's child dies with them
        epoch = load_checkpoint(run / "last.pt")["epoch"]
        assert 1 <= epoch < 25 and not (run / "record.json").exists()
        client.send_signal(signal.SIGINT)  # Ctrl-C of the waiting client: stops, exit 130
        _, err = client.communicate(timeout=60)
        assert client.returncode == 130, err[-2000:]
        cl.add_worker(tmp_path, 1)
        r = subprocess.run([sys.executable, "-m", "benchmarks.cli", *args], env=ENV,
                           capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr[-3000:]
        rec = json.loads((run / "record.json").read_text())
        assert rec["resumed"] is True and rec["epochs"] == 25
        # the killed session could not record itself (SIGKILL); the resuming one trained
        # only the epochs the killed one had not finished
        sessions = json.loads((run / "sessions.json").read_text())
        assert sessions[-1]["resumed"] is True and sessions[-1]["epochs_run"] == 25 - epoch
    finally:
        if client.poll() is None:
            client.kill()
        cl.close()


def test_local_cluster_listens_on_loopback_only():
    """The LocalCluster the suite starts: every socket it listens on (scheduler, its HTTP
    server, nanny, worker) is bound to 127.0.0.1, and no dashboard is served."""
    import urllib.error
    import urllib.request

    import psutil

    from benchmarks.suite.cluster import connect

    client, cluster = connect(None, 1)
    try:
        assert cluster.scheduler_address.startswith("tcp://127.0.0.1:")
        port = client.scheduler_info()["services"]["dashboard"]  # dask's name for HTTP
        with pytest.raises(urllib.error.HTTPError, match="404"):
            urllib.request.urlopen(f"http://127.0.0.1:{port}/status", timeout=10)
        me = psutil.Process()
        listening = [c.laddr for p in [me, *me.children(recursive=True)]
                     for c in p.net_connections("inet") if c.status == psutil.CONN_LISTEN]
        assert len(listening) >= 4, listening  # scheduler + HTTP, nanny, worker
        assert {a.ip for a in listening} == {"127.0.0.1"}, listening
    finally:
        client.close()
        cluster.close()


def test_generate_on_a_local_cluster_matches_local_generation(root, tmp_path):
    """`meshbench generate --executor dask`: one task per trajectory; the same files."""
    import numpy as np

    r = subprocess.run([sys.executable, "-m", "benchmarks.cli", "--plugin", str(root / "plugin.py"),
                        "generate", TINY, "--data-dir", str(tmp_path / "data"), "--executor",
                        "dask", "--workers", "2", "--no-progress"], capture_output=True, text=True,
                       env=ENV, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    for split in ("train", "test"):
        with np.load(root / "data" / TINY / f"{split}.npz") as a, \
                np.load(tmp_path / "data" / TINY / f"{split}.npz") as b:
            assert np.array_equal(a["pos"], b["pos"]) and np.array_equal(a["vel"], b["vel"])


def test_generate_scheduler_needs_dask(tmp_path):
    r = subprocess.run([sys.executable, "-m", "benchmarks.cli", "generate", "rod_falling",
                        "--scheduler", "tcp://127.0.0.1:1", "--data-dir", str(tmp_path)],
                       capture_output=True, text=True, env=ENV, timeout=120)
    assert r.returncode == 2 and "--scheduler needs --executor dask" in r.stderr
