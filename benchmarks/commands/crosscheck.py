"""``meshbench crosscheck CASE [--default-only] [--out-dir DIR]``: DER/DEP vs scikit-fem.

Runs the case's registered cross-check (the default resolution and the refinement study),
writes ``DIR/CASE.csv`` (tip trajectories of both solvers at the default resolution),
updates ``DIR/summary.csv`` (one row per case and resolution) and draws ``DIR/CASE.png``.
"""

from __future__ import annotations

import sys

from benchmarks.suite.provenance import add_allow_dirty, refuse_dirty


def register(sub):
    p = sub.add_parser("crosscheck", help="compare a case's solver with the scikit-fem continuum",
                       description=__doc__)
    p.add_argument("case", metavar="CASE", help="case id with a registered cross-check")
    p.add_argument("--out-dir", default="results/crosscheck", help="output directory")
    p.add_argument("--default-only", action="store_true",
                   help="only the default resolution (no refinement study or variants)")
    p.add_argument("--youngs", type=float, default=None,
                   help="Young's modulus, Pa (default: the case's reference modulus)")
    p.add_argument("--no-progress", action="store_true")
    add_allow_dirty(p)
    p.set_defaults(func=run)


def run(args):
    from benchmarks.validation.crosscheck import get_crosscheck, run_crosscheck
    from groundtruth.cases import check_youngs

    youngs = None if args.youngs is None else check_youngs(args.youngs)
    check = get_crosscheck(args.case, youngs)
    refuse_dirty(args.out_dir, args.allow_dirty)
    res = [check.default] if args.default_only else None
    say = None if args.no_progress else (lambda m: print(m, file=sys.stderr, flush=True))
    rows = run_crosscheck(check, args.out_dir, res, progress=say)
    default = next((r for r in rows if r["variant"] == "default"), None)
    for r in rows:
        print(f"{r['case']} {r['variant']:12s} ref_nodes={r['ref_nodes']:4d} "
              f"fem={r['fem_nx']}x{r['fem_ny']} {r['integrator']:15s} nu={r['poisson']:.2f} "
              f"l2_rel={r['l2_rel']:.3e} max_shape_rel={r['max_shape_rel']:.3e}")
    if default is not None:
        ok = default["l2_rel"] <= check.target_l2
        print(f"{check.case_id}: default l2_rel = {default['l2_rel']:.3e} "
              f"({'meets' if ok else 'MISSES'} the target {check.target_l2:g}); "
              f"wrote {args.out_dir}")
    return 0
