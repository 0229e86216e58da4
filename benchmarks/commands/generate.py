"""``meshbench generate CASE... | --all``: write the ground-truth train/test trajectories."""

from __future__ import annotations

from benchmarks.suite import registry


def register(sub):
    p = sub.add_parser("generate", help="generate ground-truth trajectories of registered cases",
                       description=__doc__)
    p.add_argument("cases", nargs="*", metavar="CASE",
                   help="case ids (see --list); CASE@rN: CASE on a mesh N times finer")
    p.add_argument("--all", action="store_true", help="every registered case")
    p.add_argument("--list", action="store_true", help="list the registered cases and exit")
    p.add_argument("--data-dir", default=None,
                   help="data directory (default $MESHBENCH_DATA or ./data)")
    p.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    p.add_argument("--force", action="store_true", help="regenerate even if files are current")
    p.add_argument("--split", action="append", default=None, choices=("train", "test"),
                   help="only this split (repeatable; default both): e.g. --split test, the "
                        "test trajectories of CASE@rN to roll a model trained on CASE out on; "
                        "splits already stored are kept")
    p.add_argument("--executor", default="local", choices=("local", "dask"),
                   help="local (processes on this machine, default) or dask: one task per "
                   "trajectory on a dask.distributed cluster (docs/CLUSTER.md; workers share "
                   "the data directory)")
    p.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                   help="the dask scheduler (default with --executor dask: a LocalCluster of "
                   "--workers processes on this machine)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=run)


def run(args):
    from benchmarks.suite.generate import generate

    if args.list:
        for cid, case in sorted(registry.CASES.items()):
            finer = f", {cid}@rN" if callable(getattr(case, "refined", None)) else ""
            print(f"{cid:24s} {type(case).__name__}: {case.n_train} train + {case.n_test} test, "
                  f"{case.n_frames} frames{finer}")
        return 0
    if args.scheduler is not None and args.executor != "dask":
        raise ValueError("--scheduler needs --executor dask")
    if args.workers is not None and args.workers < 1:
        raise ValueError(f"--workers must be >= 1, got {args.workers}")
    ids = sorted(registry.CASES) if args.all else args.cases
    if not ids:
        raise ValueError("name at least one CASE or pass --all; registered: "
                         + ", ".join(sorted(registry.CASES)))
    cases = [registry.get_case(c) for c in ids]
    for case in cases:
        rep = generate(case, args.data_dir, args.workers, args.force, not args.no_progress,
                       splits=args.split or ("train", "test"), executor=args.executor,
                       scheduler=args.scheduler)
        if rep.reused:
            print(f"{case.id}: up to date in {rep.case_dir} (hash matches; --force regenerates)")
        else:
            print(f"{case.id}: wrote {rep.n_trajectories} trajectories to {rep.case_dir} "
                  f"in {rep.wall_time_s:.1f} s")
    return 0
