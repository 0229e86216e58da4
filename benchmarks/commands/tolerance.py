"""``meshbench tolerance --suite S [--results DIR]``: derive the comparison tolerances of a
suite from the spread of its seeds.

Reads ``DIR/S/rmse_at_step.csv`` (written by ``meshbench run --suite S --seeds K``, K >= 2;
3 recommended) and writes ``DIR/S/tolerance.csv``: for every run key without the seed and every step,
``rtol = max(floor, exp(factor * sqrt(2) * sigma_pooled) - 1)`` with ``sigma_pooled`` the
root mean square over the steps of the sample std over seeds of ln(rmse_mean).
``meshbench run --compare-with DIR`` and ``meshbench compare --tolerance`` then use it.
See docs/SUITE.md, "Reproducibility and tolerances"."""

from __future__ import annotations

from pathlib import Path

from benchmarks.suite.provenance import add_allow_dirty, refuse_dirty


def register(sub):
    p = sub.add_parser("tolerance", help="derive a suite's comparison tolerances from its seeds",
                       description=__doc__)
    p.add_argument("--suite", default="quick", help="suite name (default quick)")
    p.add_argument("--results", default="results", help="results root (default results/)")
    p.add_argument("--factor", type=float, default=None,
                   help="standard deviations of the band (default 3)")
    p.add_argument("--floor", type=float, default=None,
                   help="smallest relative tolerance (default 0.01)")
    add_allow_dirty(p)
    p.set_defaults(func=run)


def run(args):
    import pandas as pd

    from benchmarks.suite import compare as C
    from benchmarks.suite.runner import write_csv
    from benchmarks.suite.suites import get_suite

    suite = get_suite(args.suite)
    factor = C.TOLERANCE_FACTOR if args.factor is None else args.factor
    floor = C.TOLERANCE_FLOOR if args.floor is None else args.floor
    for name, v in (("--factor", factor), ("--floor", floor)):
        if not (v == v and 0 <= v < float("inf")):
            raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
    src = Path(args.results) / suite.name / "rmse_at_step.csv"
    if not src.exists():
        raise FileNotFoundError(f"{src}: no results; create them with `meshbench run --suite "
                                f"{suite.name} --seeds 3 --results {args.results}`")
    refuse_dirty(args.results, args.allow_dirty)
    try:
        tol = C.derive_tolerances(C.read_csv(src), factor, floor, name=str(src))
    except C.CompareError as e:
        raise C.CompareError(str(e).replace(
            "(meshbench run --seeds 3)", f"(create them with `meshbench run --suite "
            f"{suite.name} --seeds 3 --results {args.results}`)")) from None
    out = src.parent / "tolerance.csv"
    write_csv(out, tol, "tolerance")
    with pd.option_context("display.width", 160, "display.max_rows", 80):
        summary = tol.groupby(["case", "model", "column"])["rtol"].agg(["min", "median", "max"])
        print(summary.to_string(float_format=lambda x: f"{x:.3g}"))
    print(f"wrote {out} ({len(tol)} rows, {int(tol['n_seeds'].min())} seeds)")
    return 0
