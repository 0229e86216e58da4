"""``meshbench curves --suite S``: learning curves from the budget checkpoints of a suite.

Rolls every budget checkpoint (``RUNS/RUN_ID/budgets/best_{budget}s.pt``, written by training
with ``train.budgets_s``) out on the run's validation split and on the test split and writes
RESULTS/S/curves.csv (case, model, seed, budget_s, cpu_s, split, step, rmse; step -1: over the
whole rollout) and RESULTS/S/figures/curves_{case}.png. Resumable: checkpoints already
evaluated and unchanged are not recomputed. See docs/SUITE.md, "Learning curves"."""

from __future__ import annotations

from benchmarks.suite.provenance import add_allow_dirty, refuse_dirty


def register(sub):
    p = sub.add_parser("curves", help="learning curves (RMSE against training CPU time) from "
                       "a suite's budget checkpoints", description=__doc__)
    p.add_argument("--suite", default="curves", help="suite name (default curves)")
    p.add_argument("--only", default=None, metavar="PATTERN",
                   help="only runs whose id matches (as meshbench run --only)")
    p.add_argument("--seeds", type=int, default=None, help="seeds per run (default: the suite's)")
    p.add_argument("--results", default="results", help="results root (default results/)")
    p.add_argument("--runs-dir", default="runs", help="training runs root (default runs/)")
    p.add_argument("--data-dir", default=None)
    p.add_argument("--device", default="cpu", help="cpu (default), cuda or auto")
    p.add_argument("--no-figures", action="store_true")
    add_allow_dirty(p)
    p.set_defaults(func=run)


def run(args):
    from benchmarks.suite.curves import build_curves
    from benchmarks.suite.runs import pick_device
    from benchmarks.suite.suites import get_suite

    suite, device = get_suite(args.suite), pick_device(args.device)
    refuse_dirty(args.results, args.allow_dirty)
    out = build_curves(suite, results_dir=args.results, runs_dir=args.runs_dir,
                       data_dir=args.data_dir, seeds=args.seeds, only=args.only,
                       device=device, figures=not args.no_figures)
    print(out["curves"])
    for path in out.get("figures", []):
        print(path)
    return 0
