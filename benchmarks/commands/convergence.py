"""``meshbench convergence CASE [--r 1,2,4,8] [--youngs Y] [--t-end T] [--out-dir DIR]``.

Mesh convergence of a case's ground truth (``benchmarks.validation.convergence``): the case's
trajectory at every resolution ``CASE@rN``, its probe point's displacement compared between
neighbouring resolutions. Writes ``DIR/convergence_CASE.csv`` (the probe's displacement at
every saved frame and r), ``DIR/convergence_CASE.png`` and updates
``DIR/convergence_summary.csv`` (one row per case and r). Trajectories are cached in
``--cache`` (default ``build/convergence``), so an interrupted study resumes.
"""

from __future__ import annotations

import sys
from pathlib import Path

from benchmarks.suite.provenance import add_allow_dirty, refuse_dirty


def register(sub):
    p = sub.add_parser("convergence", help="mesh convergence of a case's ground truth over r",
                       description=__doc__)
    p.add_argument("case", metavar="CASE", help="a refinable case id (without @rN)")
    p.add_argument("--r", default="1,2,4,8", help="comma-separated resolutions (default 1,2,4,8)")
    p.add_argument("--youngs", type=float, default=None,
                   help="Young's modulus, Pa (default: the case's reference modulus)")
    p.add_argument("--t-end", type=float, default=None,
                   help="simulated time, s (default: the case's t_end)")
    p.add_argument("--out-dir", default="results/scale", help="output directory")
    p.add_argument("--cache", default="build/convergence",
                   help="trajectory cache (resume); '' for none")
    p.add_argument("--no-progress", action="store_true")
    add_allow_dirty(p)
    p.set_defaults(func=run)


def _resolutions(text: str) -> list[int]:
    try:
        rs = [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        rs = []
    if not rs or min(rs) < 1:
        raise ValueError(f"--r must be comma-separated positive integers, got {text!r}")
    return rs


def run(args):
    from benchmarks.suite.registry import get_case
    from benchmarks.validation import convergence as cv
    from groundtruth import store
    from groundtruth.cases import check_youngs

    rs = _resolutions(args.r)
    if "@" in args.case:
        raise ValueError(f"CASE must be a base case id without '@rN', got {args.case!r}")
    case = get_case(args.case)
    if not hasattr(case, "refined"):
        raise ValueError(f"case {args.case!r} cannot be refined (no refined(r))")
    youngs = None if args.youngs is None else check_youngs(args.youngs)
    if args.t_end is not None and not args.t_end > 0:
        raise ValueError(f"--t-end must be positive, got {args.t_end!r}")
    out = Path(args.out_dir)
    refuse_dirty(str(out), args.allow_dirty)
    sha = store.git_sha(exclude=[str(out)])
    say = None if args.no_progress else (lambda m: print(m, file=sys.stderr, flush=True))
    summary, frames = cv.convergence(args.case, rs, youngs, args.t_end,
                                     Path(args.cache) if args.cache else None, say)
    for row in summary:
        row["git_sha"] = sha
    cv.write_frames(out / f"convergence_{args.case}.csv", frames)
    cv.plot(out / f"convergence_{args.case}.png", frames, args.case)
    cv.update_summary(out / "convergence_summary.csv", summary)
    for row in summary:
        diff = "" if row["next_r"] is None else (
            f"  vs r = {row['next_r']}: max {100 * row['rel_diff']:.3f} %, "
            f"final {100 * row['final_rel_diff']:.3f} %")
        print(f"{args.case} r = {row['r']:3d} ({row['nodes']} nodes): max |u| "
              f"{row['max_displacement_m']:.6g} m, {row['cpu_s_per_step']:.4g} CPU s/step "
              f"({row['linear_solver']}){diff}")
    print(f"wrote {out}/convergence_{args.case}.csv, .png and convergence_summary.csv")
    return 0
