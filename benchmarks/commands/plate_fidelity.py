"""``meshbench plate-fidelity [convergence|frequency|damping|all] [--out-dir DIR]``: fidelity of
the in-plane plate case (``plate_cantilever``), docs/PLATE.md.

Writes ``DIR/convergence.csv`` (static tip deflection against Reissner's elastica, per mesh
refinement and modulus), ``DIR/frequency.csv`` (first in-plane frequency against Euler-Bernoulli
and the plane-stress continuum) and ``DIR/damping_fit.{csv,json}`` (the damping rate fitted to
the authors' digitized tip curve, ``docs/reference/authors_plate_tip.csv``).
"""

from __future__ import annotations

from benchmarks.suite.provenance import add_allow_dirty, refuse_dirty

MEASUREMENTS = ("convergence", "frequency", "damping", "all")


def register(sub):
    p = sub.add_parser("plate-fidelity", help="measure the in-plane plate's fidelity "
                       "(convergence, frequency, damping fit)", description=__doc__)
    p.add_argument("what", nargs="?", default="all", choices=MEASUREMENTS,
                   help="which measurement (default: all)")
    p.add_argument("--out-dir", default="results/plate_fidelity", help="output directory")
    add_allow_dirty(p)
    p.set_defaults(func=run)


def run(args):
    from benchmarks.validation.plate_fidelity import run_fidelity

    refuse_dirty(args.out_dir, args.allow_dirty)
    run_fidelity(args.what, args.out_dir)
    print(f"wrote {args.out_dir}")
    return 0
