"""``meshbench animate RUN --split test --index I --out FILE.gif``: watch a rollout.

Draws the run's model rollout of trajectory I of the split over the ground truth, frame by
frame (at most --frames frames, evenly subsampled), with the time, the trajectory's Young's
modulus and the position RMSE at that frame, and writes an animated GIF. RUN is a run
directory (meshbench train --out RUN, or RUNS/RUN_ID of meshbench run); the test rollout that
meshbench run stored there is reused, otherwise the model is rolled out on that trajectory."""

from __future__ import annotations

import json
from pathlib import Path


def register(sub):
    p = sub.add_parser("animate", help="animated GIF of a model's rollout vs the ground truth",
                       description=__doc__)
    p.add_argument("run_dir", metavar="RUN", help="run directory (holds config.json, best.pt)")
    p.add_argument("--split", default="test", help="data split: train or test (default test)")
    p.add_argument("--index", type=int, default=0, help="trajectory of the split (default 0)")
    p.add_argument("--out", required=True, help="output .gif")
    p.add_argument("--frames", type=int, default=None,
                   help="at most this many GIF frames (default 80)")
    p.add_argument("--checkpoint", default="best", help="best or last (default best)")
    p.add_argument("--data-dir", default=None)
    p.add_argument("--device", default="auto")
    p.set_defaults(func=run)


def _config(run_dir: Path) -> dict:
    path = run_dir / "config.json"
    if not path.is_file():
        raise ValueError(f"RUN {str(run_dir)!r} is not a run directory (no config.json; "
                         "meshbench train --out DIR or meshbench run creates one)")
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"RUN {str(run_dir)!r}: config.json is unreadable ({e})") from None


def _check_args(args) -> None:
    from groundtruth.cases import SPLITS

    if Path(args.out).suffix.lower() != ".gif":
        raise ValueError(f"--out must end in .gif, got {args.out!r}")
    if args.split not in SPLITS:
        raise ValueError(f"--split must be one of {', '.join(SPLITS)}, got {args.split!r}")
    if args.checkpoint not in ("best", "last"):
        raise ValueError(f"--checkpoint must be 'best' or 'last', got {args.checkpoint!r}")
    if args.frames is not None and args.frames < 2:
        raise ValueError(f"--frames must be >= 2, got {args.frames!r}")


def _stored_prediction(run_dir: Path, args, true: dict):
    """The runner's stored test rollout when it belongs to this checkpoint and data, else
    None."""
    import numpy as np

    from benchmarks.suite.runs import PRED_FILE

    path, ck = run_dir / PRED_FILE, run_dir / f"{args.checkpoint}.pt"
    if args.split != "test" or args.checkpoint != "best" or not path.exists():
        return None
    if ck.exists() and path.stat().st_mtime_ns < ck.stat().st_mtime_ns:
        return None  # the checkpoint changed after the rollout was stored
    with np.load(path, allow_pickle=False) as z:
        pred = dict(z)
    if pred["pos"].shape != true["pos"].shape or str(pred["case_hash"]) != str(true["case_hash"]):
        return None
    return pred["pos"][args.index]


def _predict(run_dir: Path, args, true: dict):
    """The model's positions (T, N, 3) of trajectory ``args.index``."""
    from benchmarks.suite.runs import rollout_arrays

    pred = _stored_prediction(run_dir, args, true)
    if pred is not None:
        return pred
    one = {k: (v[args.index:args.index + 1] if k in ("pos", "vel", "youngs") else v)
           for k, v in true.items()}
    return rollout_arrays(run_dir, args.split, args.data_dir, args.checkpoint, args.device,
                          arrays=one)[0]["pos"][0]


def run(args):
    from benchmarks.suite import animate, figures
    from benchmarks.suite.registry import get_case
    from groundtruth import store

    _check_args(args)
    run_dir = Path(args.run_dir)
    config = _config(run_dir)
    true = store.load_split(get_case(config["case"]), args.split, args.data_dir)
    n = true["pos"].shape[0]
    if not 0 <= args.index < n:
        raise ValueError(f"--index must be in [0, {n - 1}] ({n} trajectories in the "
                         f"{args.split} split of {config['case']}), got {args.index}")
    pred = _predict(run_dir, args, true)
    animate.animate(true, pred, args.index, Path(args.out), label=config["model"],
                    color=figures._color(config["model"], 0),
                    title=f"{config['case']}: {args.split} trajectory {args.index}",
                    max_frames=args.frames or animate.MAX_FRAMES)
    print(f"wrote {args.out}")
    return 0
