"""``python -m benchmarks.ab {train,merge,equiv}``: the A/B of the authors' MeshODENet code
against our ``paper`` preset (docs/AB.md). Bad input exits 2 with one line naming it; an
interruption (Ctrl-C, SIGTERM) exits 130 keeping every finished epoch."""

from __future__ import annotations

import argparse
import shlex
import signal
import sys
from pathlib import Path


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.ab", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    t = sub.add_parser("train", help="train one code, one row per epoch into OUT/ab.csv (resumable)")
    t.add_argument("--case", required=True, help="case id (plate_cantilever, rod_falling, ...)")
    t.add_argument("--code", required=True, help="authors (their checkout) or ours (paper preset)")
    t.add_argument("--out", required=True, type=Path, help="run directory; an existing run continues")
    t.add_argument("--authors-repo", type=Path, default=None,
                   help="checkout of github.com/leixinma/MeshODENet (--code authors; RUNS THEIR CODE)")
    t.add_argument("--epochs", type=int, default=None,
                   help="total epochs (default 25 for a triangle mesh, 50 for a rod)")
    t.add_argument("--data-dir", default=None, help="the store (default $MESHBENCH_DATA or ./data)")
    t.add_argument("--frames", type=int, default=None,
                   help="first frames of every trajectory (default: the authors' rule, at most 400)")
    t.add_argument("--seed", type=int, default=42, help="seed of both codes (the authors': 42)")
    t.add_argument("--threads", type=int, default=1, help="torch threads (default 1: one core)")
    t.add_argument("--device", default="cpu",
                   help="--code ours only: cpu (default), cuda or cuda:K; a run started on one "
                        "device goes on on another (docs/GPU.md)")
    t.add_argument("--set", dest="overrides", action="append", default=[], metavar="GROUP.FIELD=VALUE",
                   help="--code ours: override a paper-preset setting (train.* / model.*)")
    t.add_argument("--max-train", type=int, default=None,
                   help="SMOKE CHECKS ONLY: the first N training trajectories")
    t.add_argument("--max-test", type=int, default=None,
                   help="SMOKE CHECKS ONLY: the first N test trajectories")
    t.add_argument("--no-progress", action="store_true", help="no progress bars (epoch lines stay)")
    t.set_defaults(func=_train)
    m = sub.add_parser("merge", help="both runs and the published log into RESULTS/NAME_ab.csv + figure")
    m.add_argument("--case", required=True)
    m.add_argument("--authors", required=True, type=Path, help="run directory of --code authors")
    m.add_argument("--ours", required=True, type=Path, help="run directory of --code ours")
    m.add_argument("--results", type=Path, default=Path("results/paper"))
    m.add_argument("--authors-repo", type=Path, default=None,
                   help="read their whole published log from this checkout (a CSV; no code runs)")
    m.add_argument("--name", default=None, help="file stem (default plate / rod / the case id)")
    m.add_argument("--allow-smoke", action="store_true", help="merge runs on part of the data")
    m.add_argument("--variant", action="append", type=Path, default=[], metavar="DIR",
                   help="another --code ours run directory, trained with --set settings "
                        "(a bisection step; its code names what differs from the paper "
                        "preset); repeatable")
    m.set_defaults(func=_merge)
    e = sub.add_parser("equiv", help="the same weights in both codes: field, loss, gradient, steps")
    e.add_argument("--case", required=True)
    e.add_argument("--authors-repo", required=True, type=Path,
                   help="checkout of github.com/leixinma/MeshODENet (RUNS THEIR CODE)")
    e.add_argument("--data-dir", default=None, help="the store (default $MESHBENCH_DATA or ./data)")
    e.add_argument("--set", dest="overrides", action="append", default=[], metavar="GROUP.FIELD=VALUE",
                   help="override a setting of our paper preset (model.layout=authors needed)")
    e.add_argument("--frames", type=int, default=None,
                   help="first frames of every trajectory (default: the authors' rule, at most 400)")
    e.add_argument("--trajectory", type=int, default=0, help="training trajectory compared (0)")
    e.add_argument("--steps", type=int, default=0,
                   help="optimizer steps of both, on the first trajectories in file order (0)")
    e.add_argument("--seed", type=int, default=42, help="their seed, which builds the weights")
    e.add_argument("--out", type=Path, default=None, help="also write the rows to this CSV")
    e.set_defaults(func=_equiv)
    return p


def _train(args) -> int:
    from benchmarks.ab import core
    from benchmarks.suite.registry import get_case

    case = get_case(args.case)
    if args.device != "cpu" and args.code != "ours":
        raise core.ABError(f"--device {args.device!r} is for --code ours only (the harness runs "
                           "the authors' code on the CPU)")
    if args.code == "authors":
        from benchmarks.ab.authors import check_checkout

        check_checkout(args.authors_repo)
    elif args.authors_repo is not None:
        raise core.ABError("--authors-repo is for --code authors only")
    if args.overrides and args.code != "ours":
        raise core.ABError("--set is for --code ours only (the authors' protocol is fixed)")
    epochs = args.epochs
    if epochs is None:  # rods are line meshes, every other case a triangle mesh
        epochs = core.DEFAULT_EPOCHS["line" if case.kind == "rod" else "triangle"]
    setup = core.Setup(case=args.case, code=args.code, epochs=epochs, frames=args.frames,
                       seed=args.seed, threads=args.threads, max_train=args.max_train,
                       max_test=args.max_test)
    if setup.is_smoke:
        print("smoke run: --max-train / --max-test use part of the data; not an A/B result",
              file=sys.stderr)
    progress = not args.no_progress
    if args.code == "authors":
        from benchmarks.ab import authors

        authors.run(setup, args.out, args.data_dir, args.authors_repo, progress)
    else:
        from benchmarks.ab import ours

        ours.run(setup, args.out, args.data_dir, tuple(args.overrides), progress, args.device)
    print(f"done: {args.out / core.CSV_FILE}")
    return 0


def _merge(args) -> int:
    from benchmarks.ab.merge import merge

    path = merge(args.case, args.authors, args.ours, args.results, args.authors_repo,
                 args.allow_smoke, args.name, args.variant)
    print(f"wrote {path} and {path.parent / 'figures' / (path.stem + '.png')}")
    return 0


def _equiv(args) -> int:
    from benchmarks.ab import equiv
    from benchmarks.ab.authors import check_checkout

    check_checkout(args.authors_repo)
    equiv.run(args.case, args.authors_repo, args.data_dir, args.overrides, args.frames,
              args.trajectory, args.steps, args.seed, args.out)
    if args.out is not None:
        print(f"wrote {args.out}")
    return 0


def _sigterm(signum, frame):
    raise KeyboardInterrupt()


def main(argv=None) -> int:
    from benchmarks.suite import procs

    # the kernel pins of `meshbench train` (benchmarks.cli): numpy's before it loads, torch's
    # unless --device names a GPU, before torch loads
    procs.apply_repro_env("cuda")
    from benchmarks.ab.core import ABError
    from benchmarks.suite.registry import RegistryError
    from groundtruth.store import StoreError

    args = build_parser().parse_args(argv)
    procs.apply_repro_env(getattr(args, "device", "cpu"))
    old_term = signal.signal(signal.SIGTERM, _sigterm)
    try:
        return int(args.func(args) or 0)
    except (ABError, ValueError, RegistryError, StoreError, FileNotFoundError) as e:
        print(f"ab {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        again = "python -m benchmarks.ab " + " ".join(
            shlex.quote(w) for w in (sys.argv[1:] if argv is None else argv))
        print(f"ab {args.command}: interrupted; every finished epoch is kept, continue with "
              f"`{again}`", file=sys.stderr)
        return 130
    finally:
        signal.signal(signal.SIGTERM, old_term)


if __name__ == "__main__":
    sys.exit(main())
