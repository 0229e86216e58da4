"""``python -m benchmarks.ab equiv``: the same weights in both codes, the same trajectory:
do they compute the same vector field, loss and gradient, and do their optimizer steps stay
together? Seconds to minutes of CPU where an A/B of training curves takes hours, and an
exact answer where curves differ by seed noise (docs/AB.md, "The out-of-plane channel").

Their model is built as ``--code authors`` builds it (their seed), and its weights are copied
into our ``paper`` model (with ``--set`` settings; the authors' feature layout,
``model.layout=authors``, is needed: the same tensors in a different order) through the
symmetries that relate the two layouts: our edge features are ``[|r|, r, |u|, u]`` of
``x_receiver - x_sender``, theirs ``[u, |u|, r, |r|]`` of ``x_sender - x_receiver`` (columns
permuted, vector columns negated); our edge MLP reads ``[e, h_sender, h_receiver]``, theirs
``[h_sender, h_receiver, e]``; with our normaliser the node-type one-hot at the decoder is
normalised (``n = (o - m) / s``: their columns times ``s``, their bias plus their columns
times ``m``), with theirs it is not. Their statistics are copied into ours wherever the two
differ only in the data they are taken from (their velocities are finite differences of the
positions, ours the stored ones; their std unbiased): every feature whose std is above their
clamp (``AUTHORS_STD_MIN``); the features at their clamp, the plate's out-of-plane ones, keep
ours, so that each code's own treatment of a constant feature is what is compared.

Then on one training trajectory (the first ``--frames`` frames): the vector field at the true
states of a few frames, the whole rollout's loss in the authors' units, and each parameter's
gradient, as relative differences; with ``--steps K`` both take K optimizer steps (their Adam;
ours with the preset's learning rate and weight decay) on the first K trajectories in file order
and the fields are compared after each. Our loss is divided by ``c``, its ratio to theirs on one
whole trajectory (``1 / sqrt(s N (T - 1) / (3 T))``, ``s`` our standing-still scale: 1.012 on
the plate's 400 frames, larger on fewer frames), so that Adam's coupled weight decay weighs the
same in both; training itself uses our loss as it is.

TRUST: like ``--code authors`` this imports and runs their code from ``--authors-repo``.
"""

from __future__ import annotations

import math
from pathlib import Path

from benchmarks.ab import core

PREFIX = "neural_ode_processor.ode_func."
COLUMNS = ("what", "name", "frames", "step", "rel_diff", "norm", "sign_flips")


def their_name(ours: str) -> str:
    """Their parameter name of our ``gnn`` parameter ``ours`` (``edge_encoder.0.weight`` ->
    ``...edge_encoder.mlp.0.weight``)."""
    head, _, tail = ours.rpartition(".")
    mod, _, idx = head.rpartition(".")
    return f"{PREFIX}{mod}.mlp.{idx}.{tail}"


def to_ours(theirs: dict, onehot_mean=None, onehot_std=None, bias_shift: bool = True) -> dict:
    """Their tensors ``theirs`` (their names) as our ``gnn``'s (module docstring); the decoder's
    one-hot columns affinely mapped when our one-hot is normalised (``onehot_mean/std``; a
    gradient maps with ``bias_shift=False`` and its columns are left out of the comparison)."""
    import torch

    new = {}
    for name in ("node_encoder", "edge_encoder", "processor.0.edge_mlp", "processor.0.node_mlp",
                 "decoder"):
        for idx in (0, 2, 4):
            for tail in ("weight", "bias"):
                key = f"{name}.{idx}.{tail}"
                new[key] = theirs[their_name(key)].detach().clone()
    w = new["edge_encoder.0.weight"]
    new["edge_encoder.0.weight"] = torch.cat([w[:, 7:8], -w[:, 4:7], w[:, 3:4], -w[:, 0:3]], 1)
    w = new["processor.0.edge_mlp.0.weight"]
    d = w.shape[0]
    new["processor.0.edge_mlp.0.weight"] = torch.cat([w[:, 2 * d:], w[:, :d], w[:, d:2 * d]], 1)
    if onehot_mean is not None:
        w = new["decoder.0.weight"]
        cols = slice(w.shape[1] - 2, w.shape[1])
        if bias_shift:
            new["decoder.0.bias"] = new["decoder.0.bias"] + w[:, cols] @ onehot_mean
        w[:, cols] = w[:, cols] * onehot_std
    return new


def copy_data_stats(stats, theirs: dict, dt: float) -> None:
    """Their statistics into our ``FeatureStats`` where they are above their clamp (module
    docstring); the authors' layout: node ``[Y, one-hot (2), v (3)]``, edges ``[|r|, r, |u|,
    u]`` (ours point the other way: the vector means change sign)."""
    import torch

    from meshodenet.gnn.features import AUTHORS_FRAME_TIME, AUTHORS_STD_MIN, AUTHORS_YOUNGS_UNIT

    to_phys = AUTHORS_FRAME_TIME / dt  # their velocity unit -> m/s

    def put(norm, i, mean, std, unit=1.0) -> bool:
        """Set feature ``i`` unless their std is their clamp; whether it was set."""
        if float(std) <= AUTHORS_STD_MIN * 1.0000001:
            return False
        norm.mean[i], norm.std[i] = float(mean) * unit, float(std) * unit
        return True

    with torch.no_grad():
        put(stats.node, 0, theirs["youngs_mean"][0], theirs["youngs_std"][0], AUTHORS_YOUNGS_UNIT)
        for k in range(3):
            if put(stats.node, 3 + k, theirs["vel_mean"][k], theirs["vel_std"][k], to_phys):
                stats.acc.std[k] = stats.node.std[3 + k] / (10 * dt)
        for base, key in ((0, "mesh_edge"), (4, "edge")):
            m, s = theirs[f"{key}_mean"], theirs[f"{key}_std"]
            put(stats.edge, base, m[3], s[3])
            for k in range(3):
                put(stats.edge, base + 1 + k, -m[k], s[k])


def _field_diffs(api, ma, mo, stats, traj: dict, ours_data, b: int, frames) -> list:
    """Relative difference of the two accelerations (m/s^2) at the true states of ``frames``."""
    import torch

    f = ma.neural_ode_processor.ode_func
    dt = float(ours_data.t[1] - ours_data.t[0])
    q = core.FRAME_TIME / dt
    other = torch.cat([(traj["youngs"][0] - stats["youngs_mean"]) / stats["youngs_std"],
                       traj["one_hot_node_type"][0]], -1)
    mesh_attr = (traj["mesh_edge_attr"][0] - stats["mesh_edge_mean"]) / stats["mesh_edge_std"]
    ctx = mo.field_context(ours_data.youngs[b:b + 1].float(), torch.float32)
    out = []
    with torch.no_grad():
        for k in frames:
            pos, vel = traj["world_pos"][k], traj["velocity"][k]
            _, a = f(0.0, (pos, vel), traj["edge_index"][0], mesh_attr, other,
                     traj["node_type"][0], stats)
            a = a * q * q
            ao = mo.vector_field(torch.stack([pos, vel * q]), ctx)[1]
            out.append(float((a - ao).norm() / a.norm().clamp_min(1e-30)))
    return out


def run(case: str, repo, data_dir=None, overrides=(), frames=None, trajectory: int = 0,
        steps: int = 0, seed: int = 42, out=None, echo=print) -> list:
    """The comparison (module docstring); returns its rows (``COLUMNS``), written to ``out``
    (a CSV) when given."""
    import torch

    from benchmarks.ab import authors, ours
    from benchmarks.ab.convert import authors_stats, convert
    from meshodenet.mesh.data import Mesh, Trajectories

    core.check_count("--trajectory", trajectory, 0)
    core.check_count("--steps", steps, 0)
    torch.set_num_threads(1)
    tr = core.load_arrays(case, "train", data_dir, None, frames, "--max-train")
    if trajectory >= len(tr["youngs"]):
        raise core.ABError(f"--trajectory {trajectory}: the training split of {case} has "
                           f"{len(tr['youngs'])} trajectories")
    mesh = Mesh.from_arrays(tr, f"{case}/train.npz")
    setup = core.Setup(case=case, code="ours", epochs=1, frames=frames, seed=seed)
    spec, train_cfg, model_cfg = ours.configs(setup, mesh.kind, tuple(overrides))
    if mesh.kind != "triangle":
        raise core.ABError(f"--case {case}: the comparison maps their decoder's node-type one-hot, "
                           "which our model has on triangle meshes only (a plate case)")
    if model_cfg.layout != "authors":
        raise core.ABError(f"model.layout={model_cfg.layout!r}: the comparison copies their "
                           "weights into ours, which needs their layout (model.layout=authors)")
    if model_cfg.loss != "rms":
        raise core.ABError(f"model.loss={model_cfg.loss!r}: the gradients compare with the "
                           "authors' root loss (model.loss=rms)")
    api = authors.load_authors(repo)
    data = Trajectories.from_arrays(tr, name=f"{case}/train.npz")
    theirs_data = convert(tr)
    stats = authors_stats(theirs_data)
    ma, opt_a, _ = authors.build(api, stats, seed)
    torch.manual_seed(seed)
    mo = spec.build(mesh, model_cfg, data)
    dt = float(data.t[1] - data.t[0])
    copy_data_stats(mo.stats, stats, dt)
    raw = mo.stats.normalizer == "authors"
    m1h = None if raw else mo.stats.node.mean[1:3].float()
    s1h = None if raw else mo.stats.node.std[1:3].float()
    mo.gnn.load_state_dict(to_ours(ma.state_dict(), m1h, s1h))
    T, N = data.n_frames, mesh.n_nodes
    scale = mo._loss_scale(data, mo.horizon(T - 1))
    c = 1 / math.sqrt(scale * N * (T - 1) / (3 * T))  # ours / theirs, one whole trajectory
    echo(f"our loss / theirs on one whole trajectory: {c:.6g} (ours divided by it below)")
    b, rows = trajectory, []
    probes = sorted({1, T // 4, T // 2, T - 1})
    for k, d in zip(probes, _field_diffs(api, ma, mo, stats, theirs_data[b], data, b, probes)):
        rows.append({"what": "field", "name": f"frame {k}", "frames": T, "step": 0, "rel_diff": d})
    # the whole rollout's loss and gradient
    ma.zero_grad()
    la = authors.trajectory_loss(api, ma, stats, theirs_data[b])
    la.backward()
    mo.zero_grad()
    lo = mo.training_loss(data, torch.tensor([b]))
    (lo / c).backward()
    rows.append({"what": "loss", "name": "whole rollout", "frames": T, "step": 0,
                 "rel_diff": abs(float(lo.detach()) / c - float(la.detach())) / float(la.detach()),
                 "norm": float(la.detach())})
    ga = to_ours({n: p.grad for n, p in ma.named_parameters()}, m1h, s1h, bias_shift=False)
    wa = to_ours(dict(ma.named_parameters()), m1h, s1h)
    wd = train_cfg.weight_decay
    for name, p in mo.gnn.named_parameters():
        g_t, g_o = ga[name], p.grad
        if not raw and name == "decoder.0.weight":  # its one-hot columns do not map
            g_t, g_o, w_ = g_t[:, :-2], g_o[:, :-2], wa[name][:, :-2]
        else:
            w_ = wa[name]
        flips = (torch.sign(g_t + wd * w_) != torch.sign(g_o + wd * w_)).float().mean()
        rows.append({"what": "gradient", "name": name, "frames": T, "step": 0,
                     "rel_diff": float((g_t - g_o).norm() / g_t.norm().clamp_min(1e-30)),
                     "norm": float(g_t.norm()), "sign_flips": float(flips)})
    for row in rows:
        echo(_line(row))
    opt_o = torch.optim.Adam(mo.parameters(), lr=train_cfg.lr, weight_decay=wd)
    for step in range(1, steps + 1):
        i = (step - 1) % len(theirs_data)
        opt_a.zero_grad()
        authors.trajectory_loss(api, ma, stats, theirs_data[i]).backward()
        opt_a.step()
        opt_o.zero_grad()
        (mo.training_loss(data, torch.tensor([i])) / c).backward()
        opt_o.step()
        for k, d in zip(probes, _field_diffs(api, ma, mo, stats, theirs_data[b], data, b, probes)):
            row = {"what": "field", "name": f"frame {k}", "frames": T, "step": step, "rel_diff": d}
            rows.append(row)
            echo(_line(row))
    if out is not None:
        from meshodenet.training.train import write_rows

        write_rows(Path(out), [{k: r.get(k, math.nan) for k in COLUMNS} for r in rows], COLUMNS)
    return rows


def _line(row: dict) -> str:
    extra = ""
    if "norm" in row:
        extra = f" (|their value| {row['norm']:.3e}"
        extra += f", sign flips {row['sign_flips']:.3f})" if "sign_flips" in row else ")"
    return (f"step {row['step']} {row['what']:8s} {row['name']:30s} "
            f"rel diff {row['rel_diff']:.2e}{extra}")
