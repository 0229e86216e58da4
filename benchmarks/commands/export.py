"""``meshbench export CASE --split S --index I --out FILE.xdmf``: a ParaView time series.

``--file F.npz`` exports any file in the store format instead (a `simulate` output or a
model's rollout)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from benchmarks.suite.registry import get_case


def register(sub):
    p = sub.add_parser("export", help="write a trajectory as an XDMF time series for ParaView",
                       description=__doc__)
    p.add_argument("case", metavar="CASE", nargs="?", help="case id (omit with --file)")
    p.add_argument("--split", default="test", choices=["train", "test"])
    p.add_argument("--index", type=int, default=0, help="trajectory index within the file")
    p.add_argument("--file", default=None, help="export this .npz instead of the case's split")
    p.add_argument("--data-dir", default=None)
    p.add_argument("--out", required=True, help="output .xdmf (an .h5 is written beside it)")
    p.set_defaults(func=run)


def run(args):
    from groundtruth import store

    if args.file:
        data = store.load_npz(Path(args.file))
    elif args.case:
        data = store.load_split(get_case(args.case), args.split, args.data_dir)
    else:
        raise ValueError("give a CASE (with --split/--index) or --file FILE.npz")
    B = data["pos"].shape[0]
    if not 0 <= args.index < B:
        raise ValueError(f"--index must be in [0, {B}), got {args.index}")
    out = Path(args.out)
    if out.suffix != ".xdmf":
        raise ValueError(f"--out must end in .xdmf, got {args.out!r}")
    write_xdmf(out, data, args.index)
    print(f"wrote {data['pos'].shape[1]} frames of {str(data['case'])} "
          f"(index {args.index}, Y = {data['youngs'][args.index]:.4g} Pa) to {out}")
    return 0


def write_xdmf(out: Path, data: dict, index: int) -> None:
    """XDMF + HDF5 pair. meshio's writer puts the .h5 in the working directory while its
    reader (and ParaView) look beside the .xdmf, so write from the output's directory."""
    out = Path(out).resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    cwd = os.getcwd()
    try:
        os.chdir(out.parent)
        _write_series(out, data, index)
    finally:
        os.chdir(cwd)


def _write_series(out: Path, data: dict, index: int) -> None:
    import meshio

    rest = data["rest_pos"]
    cells = [("triangle", data["cells"])] if data["cells"].size else [("line", data["edges"])]
    with meshio.xdmf.TimeSeriesWriter(str(out)) as writer:
        writer.write_points_cells(rest, cells)
        for k, t in enumerate(data["t"]):
            pos = data["pos"][index, k]
            writer.write_data(float(t), point_data={
                "displacement": pos - rest, "velocity": data["vel"][index, k],
                "node_type": data["node_type"].astype(np.float64)})
