"""``meshbench rollout --run DIR --split test --out FILE.npz``: predicted trajectories.

Rolls the run's best model out from the initial state of every trajectory of the split and
writes them in the store's format (``meshbench export --file FILE.npz`` shows them in
ParaView); prints the position RMSE and the no-motion baseline's."""

from __future__ import annotations

import json


def register(sub):
    p = sub.add_parser("rollout", help="roll a trained model out over a split",
                       description=__doc__)
    p.add_argument("--run", required=True, help="run directory of meshbench train")
    p.add_argument("--split", default="test", choices=["train", "test"])
    p.add_argument("--file", default=None, help="roll out this store-format .npz instead")
    p.add_argument("--out", required=True, help="output .npz")
    p.add_argument("--checkpoint", default="best", choices=["best", "last"])
    p.add_argument("--data-dir", default=None)
    p.add_argument("--device", default="auto")
    p.set_defaults(func=run)


def run(args):
    from benchmarks.suite.runs import rollout_run

    metrics = rollout_run(args.run, args.out, args.split, args.data_dir, args.checkpoint,
                          args.device, args.file)
    print(json.dumps(metrics, indent=2))
    print(f"wrote {metrics['n_trajectories']} predicted trajectories to {args.out}")
    return 0
