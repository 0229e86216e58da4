"""``meshbench compare BASELINE.csv NEW.csv [--rtol R] [--atol A] [--tolerance FILE] [--subset]``:
regression check.

Exit 0 when every value is within tolerance, 1 on a regression (with a table of the rows that
moved), 2 on a malformed file (missing columns, duplicate keys, rows present in one file only).
``--tolerance results/SUITE/tolerance.csv`` (from ``meshbench tolerance``) gives every row and
column its own relative tolerance; ``--subset`` compares only the baseline's rows that NEW has
(e.g. a one-seed re-run against a three-seed baseline), and NEW's rows of a metric the
baseline has no row of (a metric added since, e.g. ``horizon_*``) are reported, not compared."""

from __future__ import annotations


def register(sub):
    p = sub.add_parser("compare", help="compare a results CSV against a baseline",
                       description=__doc__)
    p.add_argument("baseline")
    p.add_argument("new")
    p.add_argument("--rtol", type=float, default=1e-6, help="relative tolerance (default 1e-6)")
    p.add_argument("--atol", type=float, default=0.0, help="absolute tolerance (default 0)")
    p.add_argument("--keys", default=None,
                   help="comma-separated key columns (default: the non-float columns)")
    p.add_argument("--ignore", action="append", default=[], metavar="COL",
                   help="also ignore this column (repeatable)")
    p.add_argument("--tolerance", default=None, metavar="FILE",
                   help="per-row relative tolerances (tolerance.csv of meshbench tolerance); "
                        "then only the columns it covers are compared")
    p.add_argument("--subset", action="store_true",
                   help="baseline rows missing from NEW are not an error, nor rows of NEW "
                        "whose metric the baseline lacks entirely")
    p.add_argument("--no-default-ignore", action="store_true",
                   help="compare provenance columns too (wall time, memory, versions, ...)")
    p.set_defaults(func=run)


def run(args):
    from benchmarks.suite.compare import compare, read_csv

    old, new = read_csv(args.baseline), read_csv(args.new)
    keys = [k.strip() for k in args.keys.split(",")] if args.keys else None
    tol = None if args.tolerance is None else read_csv(args.tolerance)
    res = compare(old, new, args.rtol, args.atol, keys, args.ignore,
                  not args.no_default_ignore, names=(args.baseline, args.new), tolerances=tol,
                  subset=args.subset)
    return report(res, args.rtol, args.atol, args.tolerance)


def report(res, rtol: float, atol: float, tolerance=None) -> int:
    """Print a comparison's outcome; 0 when within tolerance, 1 on a regression."""
    import pandas as pd

    print(f"compared {res.n_rows} rows on keys {res.keys}; values {res.values}"
          + (f"; ignored {res.ignored}" if res.ignored else ""))
    if res.new_metric_rows:
        print(f"not compared: {res.new_metric_rows} rows of metrics the baseline has no row of")
    within = (f"the per-row tolerances of {tolerance} (rtol={rtol:g} elsewhere)"
              if tolerance else f"rtol={rtol:g}") + f", atol={atol:g}"
    if res.ok:
        print(f"OK: every value within {within}")
        return 0
    with pd.option_context("display.max_rows", 60, "display.width", 160,
                           "display.float_format", "{:.6g}".format):
        print(f"REGRESSION: {len(res.moved)} values moved beyond {within}:")
        print(res.moved.to_string(index=False))
    return 1
