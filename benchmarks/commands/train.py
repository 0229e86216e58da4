"""``meshbench train --case C --model M --preset P --out DIR [--resume]``: train a learned model.

Validation trajectories are carved from the training split (fixed seed); the best epoch by
validation rollout RMSE is kept in ``DIR/best.pt`` and, once training ends, scored on the
test split (``DIR/test_metrics.json``). Interrupt at any time and rerun with ``--resume``."""

from __future__ import annotations

import datetime
import json
import typing


def register(sub):
    p = sub.add_parser("train", help="train a learned simulator (meshodenet, ...) on a case",
                       description=__doc__)
    p.add_argument("--case", required=True, help="case id (meshbench generate --list)")
    p.add_argument("--model", default="meshodenet", help="model id (default meshodenet)")
    p.add_argument("--preset", default="quick", help="paper, quick or smoke (default quick)")
    p.add_argument("--out", required=True, help="run directory")
    p.add_argument("--resume", action="store_true", help="continue the run in --out exactly")
    p.add_argument("--epochs", type=int, default=None, help="override the preset's epochs")
    p.add_argument("--set", dest="overrides", action="append", default=[],
                   metavar="GROUP.FIELD=VALUE",
                   help="override a setting, e.g. --set model.hidden=64 --set train.lr=1e-3")
    p.add_argument("--data-dir", default=None)
    p.add_argument("--device", default="auto", help="auto (CUDA if present), cpu or cuda")
    p.add_argument("--threads", type=int, default=1,
                   help="torch CPU threads (default 1: these graphs are small, and on a shared "
                        "machine a second thread costs more than it gives)")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--ddp", action="store_true",
                   help="data-parallel over the processes of `torchrun --nproc-per-node K -m "
                        "benchmarks.cli train ...` (implied when torchrun sets WORLD_SIZE > 1): "
                        "each batch split over the ranks, gradients all-reduced; gloo on CPU, "
                        "NCCL on CUDA; rank 0 validates and writes (docs/CLUSTER.md)")
    p.set_defaults(func=run)


#: How long the ranks wait for each other once training has ended: rank 0 alone rolls the
#: best model out on the test split while the others wait (minutes for a paper-size run;
#: gloo's default 30 min would cut a long one short).
FINISH_TIMEOUT_S = 7 * 24 * 3600


def _init_distributed(args):
    """Join torchrun's process group; returns (rank, world, device name, finish group): the
    last is a gloo group with a long timeout whose barrier ends the run (``_leave``)."""
    import os

    import torch
    import torch.distributed as dist

    world = int(os.environ.get("WORLD_SIZE", "1"))
    if not args.ddp and world <= 1:
        return 0, 1, args.device, None
    if "RANK" not in os.environ or "MASTER_ADDR" not in os.environ:
        raise ValueError("--ddp: not started by torchrun (RANK / MASTER_ADDR are not set); "
                         "use `torchrun --nproc-per-node K -m benchmarks.cli train ...`")
    from benchmarks.suite.runs import pick_device

    device = args.device
    cuda = pick_device(device).type == "cuda"
    if cuda:
        local = int(os.environ.get("LOCAL_RANK", "0"))
        torch.cuda.set_device(local)
        device = f"cuda:{local}"
    dist.init_process_group("nccl" if cuda else "gloo")
    finish = dist.new_group(backend="gloo", timeout=datetime.timedelta(seconds=FINISH_TIMEOUT_S))
    return dist.get_rank(), dist.get_world_size(), device, finish


def _leave(finish, code: int) -> typing.NoReturn:
    """End a torchrun worker whose run finished: wait at ``finish``'s barrier until every
    rank is done (rank 0 evaluates the test split after the others have stopped training),
    destroy the process groups, flush, and leave with ``os._exit``. A rank that left through
    the interpreter's normal exit while a peer still held its gloo connections was seen to
    abort in C++ teardown (SIGABRT, "terminate called without an active exception", 4 in 90
    runs of tests/test_ddp.py; torchrun then killed rank 0 mid-evaluation): after the barrier
    no rank uses the group any more, and ``os._exit`` runs none of the C++ static
    destructors or interpreter finalisation in which the abort happened. Every file of the
    run is written and closed by then (atomic writes, fsync); the lock is released."""
    import os
    import sys

    import torch.distributed as dist

    dist.barrier(group=finish)
    dist.destroy_process_group()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def run(args):
    import torch

    from benchmarks.suite.runs import pick_device, train_run

    if args.threads < 1:
        raise ValueError(f"--threads must be >= 1, got {args.threads}")
    pick_device(args.device)  # a bad --device fails before the run directory is created
    torch.set_num_threads(args.threads)
    from benchmarks.suite.procs import DirLock, LockBusy, remove_partial_writes

    rank, world, device, finish = _init_distributed(args)
    lock, summary = None, None
    try:
        if rank == 0:
            try:  # the lock a suite's worker holds on its run directory
                lock = DirLock(args.out).acquire()
            except LockBusy as e:
                raise LockBusy(f"{e} (a meshbench run or train); wait for it to finish or "
                               "choose another --out") from None
        summary = train_run(args.case, args.model, args.preset, args.out, resume=args.resume,
                            data_dir=args.data_dir, overrides=args.overrides,
                            epochs=args.epochs, device=device,
                            progress=not args.no_progress)
    finally:
        if lock is not None:  # left by a process killed mid-write, or by an interrupt
            remove_partial_writes(args.out)  # between a write's mkstemp and its try
            lock.release()
        if world > 1 and summary is None:  # an error: no barrier, a peer may never come
            torch.distributed.destroy_process_group()
    if rank == 0:
        print(json.dumps(summary, indent=2))
    if world > 1:
        _leave(finish, 0)
    return 0
