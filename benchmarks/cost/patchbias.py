"""The bias of Implicit-Energy's patch losses against its whole-mesh loss (docs/SUBDOMAIN.md,
"Implicit-Energy on patches"): ``python -m benchmarks.cost.patchbias``.

On ``plate_cantilever``'s training split (``MESHBENCH_DATA``), for the learner at its start
(the least-squares stiffness of the ``quick`` preset, built from the split), that start with
every weight moved by seeded noise (``--noise``), and a trained checkpoint (``--checkpoint``,
optional): the whole mesh's one-step loss ``L`` and its gradient ``g`` over the same samples
(``--traj`` trajectories evenly over the split, ``--frames`` frames evenly over each), and per
node budget (``k`` patches) and halo depth (element rings) the driven-halo patch loss of every
patch of those samples: its relative difference from ``L`` and its gradient's cosine with
``g``; and the residual loss's gradient cosine with ``g`` (a different loss: its value is not
compared). Rows to ``--out`` (CSV) and a table to stdout.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from benchmarks.cost.scalecore import write_rows

FIELDS = ("model", "budget", "k", "loss", "rings", "loss_rel_diff", "grad_cosine")


def _grad(model, loss) -> tuple[float, torch.Tensor]:
    model.zero_grad()
    loss.backward()
    return float(loss.detach()), torch.cat([p.grad.reshape(-1) for p in model.parameters()])


def models(mesh, data, args) -> dict:
    from meshodenet.energy.model import ImplicitEnergy, energy_presets
    from meshodenet.registry import load_model

    torch.manual_seed(0)
    start = ImplicitEnergy(mesh, energy_presets("quick", mesh.kind)[1], data)
    noisy = perturbed(start, ImplicitEnergy(mesh, start.config), args.noise)
    out = {"start": start, f"start + noise {args.noise:g}": noisy}
    if args.checkpoint:
        out["trained"] = load_model(args.checkpoint)[0]
    return out


def perturbed(start, copy, noise: float):
    """``copy`` (a model of ``start``'s kind and configuration) with ``start``'s state and
    every weight moved by seeded normal noise of scale ``noise``."""
    copy.load_state_dict(start.state_dict())
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for p in copy.parameters():
            p.add_(noise * torch.randn(p.shape, generator=g, dtype=p.dtype))
    return copy


def rows_of(name, model, data, samples, args) -> list:
    from meshodenet.subdomain import PatchTraining

    whole, g = _grad(model, model.training_loss(data, samples))
    rows = []
    for budget in args.budgets:
        for loss, rings in [("solve", r) for r in args.rings] + [("residual", 1)]:
            pt = PatchTraining(model, budget, halo=rings, loss=loss)
            value, gp = _grad(model, pt.training_loss(data, pt.every_patch(samples)))
            rows.append(dict(model=name, budget=budget, k=pt.k, loss=loss, rings=rings,
                             loss_rel_diff=value / whole - 1 if loss == "solve" else float("nan"),
                             grad_cosine=float(gp @ g / (gp.norm() * g.norm()))))
    return rows


def main(argv=None) -> list:
    from benchmarks.suite.registry import get_case
    from groundtruth import store
    from meshodenet.mesh.data import Mesh, Trajectories

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--budgets", type=int, nargs="+", default=[91, 46, 23])
    p.add_argument("--rings", type=int, nargs="+", default=[1, 2, 4])
    p.add_argument("--traj", type=int, default=6)
    p.add_argument("--frames", type=int, default=8)
    p.add_argument("--noise", type=float, default=0.1)
    p.add_argument("--checkpoint", type=Path, default=None)
    p.add_argument("--out", type=Path, default=Path("patchbias.csv"))
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    arrays = store.load_split(get_case("plate_cantilever"), "train")
    mesh, data = Mesh.from_arrays(arrays), Trajectories.from_arrays(arrays)
    B, T = data.pos.shape[:2]
    traj = torch.linspace(0, B - 1, args.traj).round().long()
    frame = torch.linspace(0, T - 2, args.frames).round().long()
    samples = (traj[:, None] * (T - 1) + frame).reshape(-1)
    rows = []
    for name, model in models(mesh, data, args).items():
        rows += rows_of(name, model, data, samples, args)
    write_rows(args.out, FIELDS, rows, 6)
    print("| model | budget | k | loss | rings | loss rel. diff | grad cosine |\n" + "|---" * 7
          + "|")
    for r in rows:
        print(f"| {r['model']} | {r['budget']} | {r['k']} | {r['loss']} | {r['rings']} | "
              f"{r['loss_rel_diff']:+.3g} | {r['grad_cosine']:.4f} |")
    return rows


if __name__ == "__main__":
    main()
