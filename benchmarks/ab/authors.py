"""``--code authors``: the authors' MeshODENet code, imported from the user's checkout of their
public repository (https://github.com/leixinma/MeshODENet) and trained with their protocol on
our data (``convert``), one epoch at a time, resumable.

TRUST: ``load_authors`` imports ``models`` and ``Train`` from the checkout, which runs their code
in this process with your permissions. It happens only when ``--authors-repo`` names that
checkout; nothing else in meshbench imports it.

What is theirs (called, never copied): ``models.MeshODENet`` (vector field, rk4 rollout,
``loss``), ``Train.split_trajectory_with_tspan_and_weights`` (their whole-trajectory time span;
with one segment it keeps the whole trajectory, weight 1), ``Train.build_optimizer`` (Adam) and
``Train.MultiStageScheduler``. What is ours: the loop that calls them epoch by epoch in their
order (per trajectory in file order: zero_grad, forward, their loss, backward, step; then the
test rollouts, then the scheduler's step), the settings of their ``main()`` (``PROTOCOL``,
``LR_STAGES``, seeds), the state file that makes a run resumable, and the test metrics.
"""

from __future__ import annotations

import hashlib
import importlib.util
import random
import sys
from pathlib import Path
from types import SimpleNamespace

from benchmarks.ab import core

#: The files of their repository the harness imports (``Train.py`` and the ``models`` package).
REQUIRED = ("Train.py", "models/__init__.py", "models/mesh_ode_net.py", "models/ode_function.py",
            "models/processor.py", "models/mlp.py")
#: Their ``parse_args`` defaults: hidden 128, 1 processor layer, Adam lr 1e-4, weight decay 5e-4,
#: one segment (whole trajectories), batch 1 (one trajectory per optimizer step).
PROTOCOL = {"hidden_dim": 128, "num_layers": 1, "opt": "adam", "lr": 1e-4, "weight_decay": 5e-4,
            "num_segments": 1, "min_length": 0, "time_step": core.FRAME_TIME}
#: Their ``main()``'s learning-rate stages (epochs per stage).
LR_STAGES = ({"epochs": 200, "lr": 1e-4, "weight_decay": 5e-4},
             {"epochs": 200, "lr": 1e-5, "weight_decay": 5e-4},
             {"epochs": 200, "lr": 1e-6, "weight_decay": 5e-4})
STATE_FILE = "authors_state.pt"


def check_checkout(repo) -> Path:
    """``repo`` as a resolved path if it holds the files the harness imports, else ``ABError``
    naming the path, what is missing and how to get a checkout."""
    if repo is None or str(repo) == "":
        raise core.ABError("--code authors needs --authors-repo PATH: a checkout of "
                           "https://github.com/leixinma/MeshODENet (docs/AB.md)")
    path = Path(repo).expanduser()
    if not path.is_dir():
        raise core.ABError(f"--authors-repo {str(repo)!r}: no such directory; clone their "
                           "repository there (git clone https://github.com/leixinma/MeshODENet "
                           f"{repo}), outside this repository")
    missing = [f for f in REQUIRED if not (path / f).is_file()]
    if missing:
        raise core.ABError(f"--authors-repo {str(repo)!r}: not a checkout of the authors' "
                           f"MeshODENet code (missing {', '.join(missing)})")
    return path.resolve()


def code_hashes(repo: Path) -> dict:
    """sha256 of each imported file: a resumed run must use the same code."""
    return {f: hashlib.sha256((repo / f).read_bytes()).hexdigest() for f in REQUIRED}


def load_authors(repo) -> SimpleNamespace:
    """Import their ``models`` and ``Train`` from the checkout ``repo`` (THIS RUNS THEIR CODE);
    ``torch_scatter`` is served by ``scatter_shim`` when it is not installed. Returns their
    ``MeshODENet``, ``split`` (the time-span function), ``build_optimizer``, ``Scheduler`` and
    ``scatter`` (``installed`` or ``shim``)."""
    repo = check_checkout(repo)
    import torch_geometric.nn  # noqa: F401 - PyG checks for torch_scatter once, before the shim

    from benchmarks.ab import scatter_shim

    if "torch_scatter" not in sys.modules and importlib.util.find_spec("torch_scatter") is None:
        sys.modules["torch_scatter"] = scatter_shim
    scatter = "shim" if sys.modules.get("torch_scatter") is scatter_shim else "installed"
    for name in ("models", "Train"):
        mod = sys.modules.get(name)
        if mod is not None and not str(getattr(mod, "__file__", "")).startswith(str(repo)):
            raise core.ABError(f"a module {name!r} from {getattr(mod, '__file__', '?')} is already "
                               "imported; run the A/B in a fresh process")
    sys.path.insert(0, str(repo))
    try:
        import models
        import Train
    finally:
        sys.path.remove(str(repo))
    if not str(models.__file__).startswith(str(repo)):
        raise core.ABError(f"--authors-repo {repo}: 'models' was imported from {models.__file__}")
    return SimpleNamespace(MeshODENet=models.MeshODENet,
                           split=Train.split_trajectory_with_tspan_and_weights,
                           build_optimizer=Train.build_optimizer,
                           Scheduler=Train.MultiStageScheduler, scatter=scatter)


def seed_all(seed: int) -> None:
    """What their ``main()`` seeds: torch, Python's ``random`` and numpy."""
    import numpy as np
    import torch

    torch.manual_seed(seed)
    random.seed(seed)
    np.random.seed(seed)


def build(api: SimpleNamespace, stats: dict, seed: int):
    """Their model, optimizer and scheduler as their ``train()`` builds them."""
    seed_all(seed)
    model = api.MeshODENet(hidden_dim=PROTOCOL["hidden_dim"], output_dim=3,
                           node_size=stats["node_size"].item(), edge_size=stats["edge_size"].item(),
                           num_layers=PROTOCOL["num_layers"])
    args = SimpleNamespace(opt=PROTOCOL["opt"], lr=PROTOCOL["lr"],
                           weight_decay=PROTOCOL["weight_decay"])
    opt = api.build_optimizer(args, model.parameters())
    return model, opt, api.Scheduler(opt, [dict(s) for s in LR_STAGES])


def whole(api: SimpleNamespace, traj: dict) -> list:
    """``(segment, t_span, weight)`` of their split with one segment: the whole trajectory."""
    seg, spans, weights, _ = api.split(traj, num_segments=PROTOCOL["num_segments"],
                                       min_length=PROTOCOL["min_length"],
                                       time_step_len=PROTOCOL["time_step"])
    return list(zip(seg, spans, weights))


def trajectory_loss(api, model, stats, traj: dict):
    """Their training loss of one trajectory (the weighted sum over its one segment), as their
    loop forms it; differentiable."""
    import torch

    loss = torch.tensor(0.0)
    for seg, t_span, w in whole(api, traj):
        pred, _ = model(seg, stats, t_span)
        loss = loss + torch.tensor(w) * model.loss(pred, seg)
    return loss


def train_epoch(api, model, opt, stats, train: list, bar=None) -> float:
    """One pass over ``train`` in file order, one optimizer step per trajectory; the mean of
    their trajectory losses."""
    model.train()
    total = 0.0
    for traj in train:
        opt.zero_grad()
        loss = trajectory_loss(api, model, stats, traj)
        loss.backward()
        total += loss.item()
        opt.step()
        if bar is not None:
            bar.update(1)
            bar.set_postfix_str(f"loss {loss.item():.4g}", refresh=False)
    return total / len(train)


def predict(api, model, stats, trajs: list):
    """``(pred (B, T, N, 3), their losses (B,))``: rollouts of ``trajs`` without gradients."""
    import torch

    model.eval()
    preds, losses = [], []
    with torch.no_grad():
        for traj in trajs:
            (seg, t_span, _), = whole(api, traj)
            pred, _ = model(seg, stats, t_span)
            preds.append(pred.float())
            losses.append(float(model.loss(pred, seg)))
    model.train()
    return torch.stack(preds), losses


def evaluate(api, model, stats, test: list, true, case: str, epoch: int) -> tuple[dict, float]:
    """The epoch's row with its test metrics filled; and their own loss function's test loss
    (float32, a cross-check of ``core.authors_loss``)."""
    clock = core.Clock()
    pred, theirs = predict(api, model, stats, test)
    row = core.empty_row(case, "authors", epoch)
    row.update(core.test_metrics(pred, true))
    row["test_wall_s"], row["test_cpu_s"] = clock.seconds()
    row["peak_rss_mb"] = core.peak_rss_mb()
    return row, sum(theirs) / len(theirs)


def _state(model, opt, sched, epoch: int, rows: list) -> dict:
    import torch

    version, keys, gauss = random.getstate()
    return {"epoch": epoch, "model": model.state_dict(), "optimizer": opt.state_dict(),
            "scheduler": [sched.current_stage, sched.epoch_in_stage, sched.total_epochs],
            "torch_rng": torch.get_rng_state(), "python_rng": [version, list(keys), gauss],
            "numpy_rng": core.numpy_rng_state(), "rows": rows}


def _restore(state: dict, model, opt, sched) -> list:
    import torch

    model.load_state_dict(state["model"])
    opt.load_state_dict(state["optimizer"])
    sched.current_stage, sched.epoch_in_stage, sched.total_epochs = state["scheduler"]
    torch.set_rng_state(state["torch_rng"])
    version, keys, gauss = state["python_rng"]
    random.setstate((version, tuple(keys), gauss))
    core.set_numpy_rng_state(state["numpy_rng"])
    return list(state["rows"])


def run(setup: core.Setup, out: Path, data_dir=None, repo=None, progress: bool = True) -> list:
    """Train their model on ``setup.case`` into ``out`` up to ``setup.epochs`` (continuing
    ``out/authors_state.pt`` when it is there); returns the rows of ``ab.csv``."""
    import torch
    from tqdm import tqdm

    from benchmarks.ab.convert import authors_stats, convert

    repo = check_checkout(repo)
    torch.set_num_threads(setup.threads)
    tr = core.load_arrays(setup.case, "train", data_dir, setup.max_train, setup.frames, "--max-train")
    te = core.load_arrays(setup.case, "test", data_dir, setup.max_test, setup.frames, "--max-test")
    api = load_authors(repo)
    setup = setup.with_extra(code_sha256=code_hashes(repo), torch_scatter=api.scatter,
                        protocol=PROTOCOL, lr_stages=list(LR_STAGES))
    core.check_resume(out, setup, core.data_id(tr, te))
    train, test = convert(tr), convert(te)
    true = torch.as_tensor(te["pos"], dtype=torch.float32)
    stats = authors_stats(train)
    model, opt, sched = build(api, stats, setup.seed)
    path = out / STATE_FILE
    start = 0
    if path.exists():
        state = core.load_state(path)
        start, rows = state["epoch"], _restore(state, model, opt, sched)
    else:
        row, _ = evaluate(api, model, stats, test, true, setup.case, 0)
        rows = [core.standing_still_row(setup.case, true), row]
        core.save_state(path, _state(model, opt, sched, 0, rows))
    core.write_csv(out, rows)
    core.record_session(out, start)
    n_nodes = true.shape[2]
    for epoch in range(start, setup.epochs):
        clock, lr = core.Clock(), opt.param_groups[0]["lr"]
        with tqdm(total=len(train), desc=f"authors epoch {epoch + 1}", unit="traj", leave=False,
                  disable=not progress, file=sys.stderr, dynamic_ncols=True) as bar:
            loss = train_epoch(api, model, opt, stats, train, bar)
        wall, cpu = clock.seconds()
        row, theirs = evaluate(api, model, stats, test, true, setup.case, epoch + 1)
        sched.step()
        row.update(train_loss=loss, lr=lr, wall_s=wall, cpu_s=cpu)
        rows.append(row)
        core.save_state(path, _state(model, opt, sched, epoch + 1, rows))
        core.write_csv(out, rows)
        print(core.progress_line(row, setup.epochs, n_nodes) + f" (their loss function: "
              f"{theirs:.4g})", flush=True)
    return rows

