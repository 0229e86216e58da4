"""``meshbench run --suite S [--only PATTERN] [--seeds K]``: run a benchmark suite.

Generates missing data, trains every run of the suite (finished runs whose configuration is
unchanged are reused; interrupted ones resume), rolls the best checkpoints out on the test
split and writes RESULTS/S/{runs,metrics,rmse_at_step}.csv, rmse_at_step.md and figures/.
A suite with resolutions (scale) writes its runs' rollouts on finer meshes instead,
RESULTS/S/transfer/ (docs/SCALE.md). With --compare-with DIR, then compares
RESULTS/S/rmse_at_step.csv (or transfer/rmse_at_step.csv) against DIR/S/'s (exit 1 on
a regression) with the per-row tolerances of DIR/S/tolerance.csv (``meshbench tolerance``);
only the rows this run produced are compared (e.g. seed 0 of a three-seed baseline); with
--jobs > 1 the runs start longest first by DIR/S/runs.csv's training times.
Suites: smoke, quick, paper, hanging, integrators, curves, scale, subdomain,
  subdomain_whole, subdomain_transfer, and those plugins register (see --list)."""

from __future__ import annotations

import sys
from pathlib import Path

from benchmarks.suite.provenance import add_allow_dirty, refuse_dirty

TOLERANCE_FILE = "tolerance.csv"


def register(sub):
    p = sub.add_parser("run", help="run a benchmark suite and write its results tables",
                       description=__doc__)
    p.add_argument("--suite", default="quick", help="suite name (default quick)")
    p.add_argument("--list", action="store_true", help="list the suites and their runs")
    p.add_argument("--only", default=None, metavar="PATTERN",
                   help="run only runs whose id matches (comma-separated substrings or globs, "
                        "e.g. 'rod_falling' or '*-mgn-*')")
    p.add_argument("--seeds", type=int, default=None, help="seeds per run (default: the suite's)")
    p.add_argument("--results", default="results", help="results root (default results/)")
    p.add_argument("--runs-dir", default="runs", help="training runs root (default runs/)")
    p.add_argument("--data-dir", default=None)
    p.add_argument("--jobs", type=int, default=1,
                   help="runs trained at once, each in its own process (default 1)")
    p.add_argument("--threads", type=int, default=1, help="torch threads per run (default 1)")
    p.add_argument("--executor", default="local", choices=("local", "dask"),
                   help="local: --jobs processes on this machine (default); dask: one task per "
                        "run on a dask.distributed cluster (docs/CLUSTER.md)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="with --executor dask: the scheduler (tcp://HOST:PORT); without it a "
                        "LocalCluster of --jobs worker processes. Workers must see the same "
                        "data and runs directories (shared filesystem)")
    p.add_argument("--device", default="auto", help="auto (CUDA if present), cpu or cuda")
    p.add_argument("--no-figures", action="store_true")
    p.add_argument("--tables-only", action="store_true",
                   help="train nothing: rewrite RESULTS/SUITE/rmse_at_step.csv, .md and the "
                        "RMSE-vs-step figures from its metrics.csv and runs.csv (a results "
                        "directory brought up to this version's tables); a suite with "
                        "resolutions: write RESULTS/SUITE/transfer/ from the rollouts stored "
                        "in the runs directory, rolling nothing out (those not stored yet "
                        "are left out and named)")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--compare-with", default=None, metavar="DIR",
                   help="afterwards compare rmse_at_step.csv with DIR/SUITE/rmse_at_step.csv "
                        "(and start the runs longest first by DIR/SUITE/runs.csv's training "
                        "times)")
    p.add_argument("--rtol", type=float, default=None,
                   help="one relative tolerance for --compare-with instead of the per-row "
                        "tolerances of DIR/SUITE/tolerance.csv (without that file: the "
                        "suite's compare_rtol)")
    add_allow_dirty(p)
    p.set_defaults(func=run)


def run(args):
    from benchmarks.suite.suites import SUITES, get_suite

    if args.list:
        for name, s in SUITES.items():
            print(f"{name}: {s.description}")
            for r in s.runs():
                print(f"    {r.run_id}")
        return 0
    suite = get_suite(args.suite)
    from benchmarks.suite.runs import pick_device

    pick_device(args.device)  # a bad --device fails here, not in every worker
    table = Path(suite.name) / ("transfer" if suite.resolutions else "") / "rmse_at_step.csv"
    if args.compare_with is not None:
        base = Path(args.compare_with) / table
        if Path(args.results).resolve() == Path(args.compare_with).resolve():
            raise ValueError("--compare-with names the --results directory itself; results "
                             "would be compared with themselves")
    from benchmarks.suite.plugins import loaded_files
    from benchmarks.suite.runner import rewrite_tables, run_suite

    refuse_dirty([args.results, args.runs_dir], args.allow_dirty)

    if args.tables_only and suite.resolutions:
        from benchmarks.suite.transfer import tables_from_stored

        paths = tables_from_stored(suite, args.results, args.runs_dir, seeds=args.seeds,
                                   only=args.only, data_dir=args.data_dir,
                                   figures=not args.no_figures)
        print(paths["markdown"].read_text())
        return 0
    if args.tables_only:
        paths = rewrite_tables(args.results, suite, data_dir=args.data_dir,
                               figures=not args.no_figures)
        print(paths["markdown"].read_text())
        return 0

    res = run_suite(suite, results_dir=args.results, runs_dir=args.runs_dir,
                    data_dir=args.data_dir, seeds=args.seeds, only=args.only, jobs=args.jobs,
                    threads=args.threads, plugin_files=loaded_files(), device=args.device,
                    progress=not args.no_progress, figures=not args.no_figures,
                    executor=args.executor, scheduler=args.scheduler,
                    costs=None if args.compare_with is None
                    else Path(args.compare_with) / suite.name / "runs.csv")
    print(res["paths"]["markdown"].read_text())
    if args.compare_with is None:
        return 0
    if not base.exists():
        print(f"meshbench run: no committed baseline {base}; nothing to compare", file=sys.stderr)
        return 0
    from benchmarks.commands.compare import report
    from benchmarks.suite.compare import compare, read_csv

    tol_file = base.parent / TOLERANCE_FILE
    use_tol = args.rtol is None and tol_file.exists()
    rtol = suite.compare_rtol if args.rtol is None else args.rtol
    new = res["paths"]["rmse_at_step"]
    result = compare(read_csv(base), read_csv(new), rtol=rtol, atol=0.0,
                     names=(str(base), str(new)),
                     tolerances=read_csv(tol_file) if use_tol else None, subset=True)
    return report(result, rtol, 0.0, str(tol_file) if use_tol else None)
