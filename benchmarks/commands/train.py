"""``meshbench train --case C --model M --preset P --out DIR [--resume]``: train a learned model.

Validation trajectories are carved from the training split (fixed seed); the best epoch by
validation rollout RMSE is kept in ``DIR/best.pt`` and, once training ends, scored on the
test split (``DIR/test_metrics.json``). Interrupt at any time and rerun with ``--resume``."""

from __future__ import annotations

import json


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
    p.set_defaults(func=run)


def run(args):
    import torch

    from benchmarks.runs import train_run

    if args.threads < 1:
        raise ValueError(f"--threads must be >= 1, got {args.threads}")
    torch.set_num_threads(args.threads)
    from benchmarks.procs import DirLock, LockBusy

    try:  # the lock a suite's worker holds on its run directory
        lock = DirLock(args.out).acquire()
    except LockBusy as e:
        raise LockBusy(f"{e} (a meshbench run or train); wait for it to finish or choose "
                       "another --out") from None
    try:
        summary = train_run(args.case, args.model, args.preset, args.out, resume=args.resume,
                            data_dir=args.data_dir, overrides=args.overrides,
                            epochs=args.epochs, device=args.device,
                            progress=not args.no_progress)
    finally:
        lock.release()
    print(json.dumps(summary, indent=2))
    return 0
