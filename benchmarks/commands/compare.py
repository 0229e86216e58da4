"""``meshbench compare BASELINE.csv NEW.csv [--rtol R] [--atol A]``: regression check.

Exit 0 when every value is within tolerance, 1 on a regression (with a table of the rows that
moved), 2 on a malformed file (missing columns, duplicate keys, rows present in one file only)."""

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
    p.add_argument("--no-default-ignore", action="store_true",
                   help="compare provenance columns too (wall time, memory, versions, ...)")
    p.set_defaults(func=run)


def run(args):
    from benchmarks.compare import compare, read_csv

    old, new = read_csv(args.baseline), read_csv(args.new)
    keys = [k.strip() for k in args.keys.split(",")] if args.keys else None
    res = compare(old, new, args.rtol, args.atol, keys, args.ignore,
                  not args.no_default_ignore, names=(args.baseline, args.new))
    return report(res, args.rtol, args.atol)


def report(res, rtol: float, atol: float) -> int:
    """Print a comparison's outcome; 0 when within tolerance, 1 on a regression."""
    import pandas as pd

    print(f"compared {res.n_rows} rows on keys {res.keys}; values {res.values}"
          + (f"; ignored {res.ignored}" if res.ignored else ""))
    if res.ok:
        print(f"OK: every value within rtol={rtol:g}, atol={atol:g}")
        return 0
    with pd.option_context("display.max_rows", 60, "display.width", 160,
                           "display.float_format", "{:.6g}".format):
        print(f"REGRESSION: {len(res.moved)} values moved beyond rtol={rtol:g}, "
              f"atol={atol:g}:")
        print(res.moved.to_string(index=False))
    return 1
