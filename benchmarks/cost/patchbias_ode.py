"""The bias of MeshODENet's driven-halo patch loss against its whole-mesh loss
(docs/SUBDOMAIN.md, "MeshODENet on patches"): ``python -m benchmarks.cost.patchbias_ode``.

On ``plate_cantilever``'s training split (``MESHBENCH_DATA``), float64, for the ``quick``
preset's network untrained (its statistics from the split), that network with every weight
moved by seeded noise (``--noise``), and a trained checkpoint (``--checkpoint``, optional),
each with windows of ``S`` steps (``--windows``; ``shooting = S``, no release term): the
whole mesh's loss ``L`` and its gradient ``g`` over the same windows (``--traj``
trajectories evenly over the split, ``--starts`` windows evenly over each, one draw of the
offsets), and per node budget (``k`` patches) and buffer (rings solved beyond the part) the
driven-halo loss of every patch of those windows: its relative difference from ``L`` and its
gradient's cosine with ``g``. Rows to ``--out`` (CSV) and a table to stdout.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import torch

from benchmarks.cost.patchbias import _grad, perturbed
from benchmarks.cost.scalecore import write_rows

FIELDS = ("model", "window", "budget", "k", "buffer", "loss", "loss_rel_diff", "grad_cosine")


def models(mesh, data, args) -> dict:
    from meshodenet.gnn.meshodenet import MeshODENet, meshodenet_presets
    from meshodenet.registry import load_model

    torch.manual_seed(0)
    start = MeshODENet(mesh, meshodenet_presets("quick", mesh.kind)[1], data).double()
    noisy = perturbed(start, MeshODENet(mesh, start.config, data).double(), args.noise)
    out = {"untrained": start, f"untrained + noise {args.noise:g}": noisy}
    if args.checkpoint:
        out["trained"] = load_model(args.checkpoint)[0].double()
    return out


def rows_of(name, model, data, args) -> list:
    from meshodenet.subdomain import PatchTraining

    rows = []
    for S in args.windows:
        model.config = dataclasses.replace(model.config, shooting=S, shooting_epochs=0,
                                           release_weight=0.0, release_fraction=0.0)
        n_w = (data.n_frames - 1) // S
        traj = torch.linspace(0, len(data) - 1, args.traj).round().long()
        win = torch.linspace(0, n_w - 1, args.starts).round().long()
        samples = (traj[:, None] * n_w + win).reshape(-1)
        whole, g = _grad(model, model.training_loss(data, samples,
                                                    torch.Generator().manual_seed(0)))
        for budget in args.budgets:
            for buffer in args.buffers:
                pt = PatchTraining(model, budget, buffer=buffer)
                value, gp = _grad(model, pt.training_loss(data, pt.every_patch(samples),
                                                          torch.Generator().manual_seed(0)))
                rows.append(dict(model=name, window=S, budget=budget, k=pt.k, buffer=buffer,
                                 loss=whole, loss_rel_diff=value / whole - 1,
                                 grad_cosine=float(gp @ g / (gp.norm() * g.norm()))))
                print(table(rows[-1:]).splitlines()[-1], flush=True)
    return rows


def table(rows: list) -> str:
    lines = ["| model | window | budget | k | buffer | whole loss | loss rel. diff | "
             "grad cosine |", "|---" * 8 + "|"]
    for r in rows:
        lines.append(f"| {r['model']} | {r['window']} | {r['budget']} | {r['k']} | "
                     f"{r['buffer']} | {r['loss']:.4g} | {r['loss_rel_diff']:+.3g} | "
                     f"{r['grad_cosine']:.4f} |")
    return "\n".join(lines)


def main(argv=None) -> list:
    from benchmarks.suite.registry import get_case
    from groundtruth import store
    from meshodenet.mesh.data import Mesh, Trajectories

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--budgets", type=int, nargs="+", default=[91, 46, 23])
    p.add_argument("--buffers", type=int, nargs="+", default=[0, 2])
    p.add_argument("--windows", type=int, nargs="+", default=[1, 5, 10])
    p.add_argument("--traj", type=int, default=6)
    p.add_argument("--starts", type=int, default=8)
    p.add_argument("--noise", type=float, default=0.1)
    p.add_argument("--checkpoint", type=Path, default=None)
    p.add_argument("--out", type=Path, default=Path("patchbias_ode.csv"))
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    arrays = store.load_split(get_case("plate_cantilever"), "train")
    mesh = Mesh.from_arrays(arrays)
    data = Trajectories.from_arrays(arrays).to(dtype=torch.float64)
    rows = []
    for name, model in models(mesh, data, args).items():
        rows += rows_of(name, model, data, args)
    write_rows(args.out, FIELDS, rows, 6)
    print(table(rows))
    return rows


if __name__ == "__main__":
    main()
