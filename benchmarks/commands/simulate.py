"""``meshbench simulate CASE --youngs Y [--t-end T | --static] --out FILE.npz``."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from benchmarks.suite.registry import get_case
from groundtruth.implicit import ConvergenceError


def register(sub):
    p = sub.add_parser("simulate", help="run one trajectory (or a static solve) of a case",
                       description=__doc__)
    p.add_argument("case", metavar="CASE")
    p.add_argument("--youngs", type=float, required=True, help="Young's modulus, Pa")
    p.add_argument("--t-end", type=float, default=None, help="end time, s (default: the case's)")
    p.add_argument("--static", action="store_true",
                   help="static equilibrium under the case's load (cases with a clamp)")
    p.add_argument("--out", required=True, help="output .npz (store format, B = 1)")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=run)


def run(args):
    from groundtruth import store
    from groundtruth.cases import check_youngs

    case = get_case(args.case)
    y = check_youngs(args.youngs)
    out = Path(args.out)
    if out.suffix != ".npz":
        raise ValueError(f"--out must end in .npz, got {args.out!r}")
    if args.t_end is not None and not (np.isfinite(args.t_end) and args.t_end > 0):
        raise ValueError(f"--t-end must be a positive number of seconds, got {args.t_end!r}")
    t0 = time.perf_counter()
    try:
        if args.static:
            q = case.solve_static(y)
            t, pos = np.zeros(1), q[None, None]
            vel = np.zeros_like(pos)
        else:
            t_end = case.t_end if args.t_end is None else args.t_end
            with tqdm(total=t_end, desc=f"simulate {case.id}", unit="s",
                      disable=args.no_progress, file=sys.stderr,
                      bar_format="{l_bar}{bar}| {n:.2f}/{total:.2f} s") as bar:
                res = case.simulate(y, t_end, progress=lambda t: bar.update(t - bar.n))
            t, pos, vel = res["t"], res["pos"][None], res["vel"][None]
    except (ConvergenceError, np.linalg.LinAlgError, FloatingPointError) as e:
        lo, hi = case.youngs_train
        raise ConvergenceError(f"--youngs {y:g} Pa: the solver failed ({e}); {case.id} is "
                               f"built for moduli around {lo:g}..{hi:g} Pa (its training "
                               "range): choose a modulus nearer to it") from None
    store.save_npz(out, store.trajectory_arrays(case, t, pos, vel, [y], "single"))
    kind = "static equilibrium" if args.static else f"{len(t)} frames to t = {t[-1]:g} s"
    print(f"{case.id}: wrote {kind} at Y = {y:.4g} Pa to {out} in {time.perf_counter() - t0:.1f} s")
    return 0
