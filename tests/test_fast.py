"""The fast path (``meshodenet.gnn.network``, ``meshodenet.gnn.fast``) against the reference
implementation (``meshodenet.gnn.reference``) in float64: vector field, its gradients, whole
rollouts and their gradients, on the tiny rod and strip, the rod of ``rod_falling``
(batched) and the plate of the registered ``plate_cantilever`` case, for several
architectures and integrators."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from meshodenet.gnn.meshodenet import MeshODENet, MeshODENetConfig
from meshodenet.mesh.data import Mesh, Trajectories

torch.set_num_threads(1)

TOL = {"rtol": 1e-10, "atol": 1e-12}


def case_arrays(case_id, n=3, frames=6):
    from benchmarks.cost.enginebench import bench_arrays
    from benchmarks.suite.registry import get_case

    return bench_arrays(get_case(case_id), n, frames, None)[0]


def pair(arrays, config, seed=0):
    """The same float64 model twice: one on the fast path, one on the reference path."""
    data = Trajectories.from_arrays(arrays, dtype=torch.float64)
    torch.manual_seed(seed)
    fast = MeshODENet(Mesh.from_arrays(arrays), config, data).double()
    torch.manual_seed(seed)
    # the summation of the code before PyG (index_add_); PyG's scatter: test below
    ref_config = replace(config, engine="reference", message_passing="handwritten")
    ref = MeshODENet(Mesh.from_arrays(arrays), ref_config, data).double()
    with torch.no_grad():  # random biases and decoder so that nothing is trivially zero
        g = torch.Generator().manual_seed(seed + 1)
        for pf, pr in zip(fast.parameters(), ref.parameters(), strict=True):
            pf.add_(0.1 * torch.randn(pf.shape, generator=g, dtype=pf.dtype))
            pr.copy_(pf)
    assert fast.engine == "fast"
    return fast, ref, data


def perturbed_state(data, n):
    g = torch.Generator().manual_seed(3)
    x = data.pos[:n, 2].reshape(-1, 3)
    v = data.vel[:n, 2].reshape(-1, 3)
    x = x + 1e-3 * torch.randn(x.shape, generator=g, dtype=x.dtype)
    v = v + 1e-2 * torch.randn(v.shape, generator=g, dtype=v.dtype)
    return torch.stack([x, v])


def grads(model):
    return [torch.zeros_like(p) if p.grad is None else p.grad.clone() for p in model.parameters()]


def check_field(fast, ref, data, n):
    z = perturbed_state(data, n)
    w = torch.randn(z.shape, generator=torch.Generator().manual_seed(4), dtype=z.dtype)
    out = {}
    for name, m in (("fast", fast), ("ref", ref)):
        ctx = m.field_context(data.youngs[:n])
        with torch.no_grad():
            nograd = m.vector_field(z, ctx)
        zz = z.clone().requires_grad_(True)
        m.zero_grad()
        f = m.vector_field(zz, ctx)
        (f * w).sum().backward()
        out[name] = (nograd, f.detach(), zz.grad, grads(m))
    (a0, a1, az, ag), (b0, b1, bz, bg) = out["fast"], out["ref"]
    torch.testing.assert_close(a0, b0, **TOL)
    torch.testing.assert_close(a1, b1, **TOL)
    torch.testing.assert_close(az, bz, **TOL)
    for x, y in zip(ag, bg, strict=True):  # round-off relative to each tensor's scale
        torch.testing.assert_close(x, y, rtol=TOL["rtol"],
                                   atol=max(TOL["atol"], TOL["rtol"] * float(y.abs().max())))


def check_training_step(fast, ref, data, n, tol=TOL):
    samples = torch.arange(n)
    out = {}
    for name, m in (("fast", fast), ("ref", ref)):
        m.zero_grad()
        loss = m.training_loss(data, samples)
        loss.backward()
        with torch.no_grad():
            pos, vel = m.rollout(data.pos[:n, 0], data.vel[:n, 0], data.youngs[:n], data.t)
        out[name] = (loss.detach(), grads(m), pos, vel)
    (la, ga, pa, va), (lb, gb, pb, vb) = out["fast"], out["ref"]
    torch.testing.assert_close(la, lb, **tol)
    torch.testing.assert_close(pa, pb, **tol)
    torch.testing.assert_close(va, vb, **tol)
    for x, y in zip(ga, gb, strict=True):
        # round-off relative to the gradient's scale, not to each entry: entries that cancel
        # to ~1e-9 of their tensor's largest one carry that tensor's absolute round-off
        torch.testing.assert_close(x, y, rtol=tol["rtol"],
                                   atol=max(tol["atol"], tol["rtol"] * float(y.abs().max())))


CONFIGS = [
    MeshODENetConfig(hidden=16),
    MeshODENetConfig(hidden=8, layers=2, mlp_hidden_layers=1, activation="silu"),
    MeshODENetConfig(hidden=8, layers=0, mlp_hidden_layers=0, activation="tanh"),
    # the authors' code's conventions (docs/AB.md, "What differs"): velocity-only node encoder, static
    # node features at the decoder, relative positions on the edges, their output scale
    MeshODENetConfig(hidden=16, layout="authors", acc_scale="velocity", loss="rms"),
    MeshODENetConfig(hidden=8, layers=2, mlp_hidden_layers=1, layout="authors",
                     rest_position=True),
    MeshODENetConfig(hidden=8, layout="authors_nodes"),
    MeshODENetConfig(hidden=8, layout="authors_edges", activation="silu"),
    MeshODENetConfig(hidden=16, layout="authors", acc_scale="velocity", loss="rms",
                     normalizer="authors"),
]


@pytest.mark.parametrize("config", CONFIGS, ids=["relu", "silu-2layers", "tanh-0layers",
                                                 "authors", "authors-2layers-rest",
                                                 "authors-nodes", "authors-edges",
                                                 "authors-normalizer"])
def test_field_and_gradients_tiny(arrays, config):
    fast, ref, data = pair(arrays, config)
    check_field(fast, ref, data, 2)


@pytest.mark.parametrize("integrator,substeps,grad_mode", [
    ("rk4", 1, "checkpoint"), ("rk4", 2, "direct"), ("midpoint", 1, "checkpoint"),
    ("euler", 3, "checkpoint")])
def test_rollout_gradients_tiny(arrays, integrator, substeps, grad_mode):
    cfg = MeshODENetConfig(hidden=8, mlp_hidden_layers=1, integrator=integrator,
                           substeps=substeps, grad_mode=grad_mode)
    fast, ref, data = pair(arrays, cfg)
    check_training_step(fast, ref, data, 2)


@pytest.mark.parametrize("case_id,n", [("rod_falling", 1), ("rod_falling", 3),
                                       ("plate_cantilever", 1)])
def test_paper_size_on_case_graphs(case_id, n):
    """Paper-size network (hidden 128) on the real rod (alone and batched) and plate."""
    fast, ref, data = pair(case_arrays(case_id, n=3, frames=4), MeshODENetConfig())
    check_field(fast, ref, data, n)
    check_training_step(fast, ref, data, n)


@pytest.mark.parametrize("case_id,normalizer", [("rod_falling", "ours"),
                                                ("plate_cantilever", "ours"),
                                                ("plate_cantilever", "authors")])
def test_authors_layout_on_case_graphs(case_id, normalizer):
    """The authors' layout at paper size, two trajectories batched, a training step (with
    their normaliser the in-plane plate's out-of-plane direction is live)."""
    cfg = MeshODENetConfig(layout="authors", acc_scale="velocity", loss="rms",
                           normalizer=normalizer)
    fast, ref, data = pair(case_arrays(case_id, n=3, frames=4), cfg)
    check_field(fast, ref, data, 2)
    check_training_step(fast, ref, data, 2)


def test_multiple_shooting_windows_match():
    cfg = MeshODENetConfig(hidden=16, shooting=2)
    fast, ref, data = pair(case_arrays("rod_falling", n=2, frames=7), cfg)
    samples = torch.arange(fast.n_training_samples(data))
    losses = []
    for m in (fast, ref):
        m.zero_grad()
        loss = m.training_loss(data, samples, torch.Generator().manual_seed(0))
        loss.backward()
        losses.append((loss.detach(), grads(m)))
    torch.testing.assert_close(losses[0][0], losses[1][0], **TOL)
    for x, y in zip(losses[0][1], losses[1][1], strict=True):
        torch.testing.assert_close(x, y, **TOL)


def test_adjoint_and_dopri5_fall_back_to_the_reference_solvers(arrays):
    for cfg in (MeshODENetConfig(hidden=8, grad_mode="adjoint"),
                MeshODENetConfig(hidden=8, integrator="dopri5")):
        fast, ref, data = pair(arrays, cfg)
        check_training_step(fast, ref, data, 1)


def test_float32_matches_to_round_off():
    arrays = case_arrays("rod_falling", n=2, frames=11)
    data = Trajectories.from_arrays(arrays)
    torch.manual_seed(0)
    m = MeshODENet(Mesh.from_arrays(arrays), MeshODENetConfig(hidden=32), data)
    out = []
    for engine in ("fast", "reference"):
        m.config = replace(m.config, engine=engine)
        m.zero_grad()
        m.training_loss(data, torch.arange(2)).backward()
        out.append(grads(m))
    for x, y in zip(*out, strict=True):
        torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-6)


def test_field_follows_parameter_updates():
    fast, ref, data = pair(case_arrays("rod_falling", n=1, frames=3), MeshODENetConfig(hidden=8))
    ctx = fast.field_context(data.youngs[:1])
    z = perturbed_state(data, 1)
    with torch.no_grad():
        before = fast.vector_field(z, ctx)
        for p in fast.parameters():
            p.mul_(1.5)
        after = fast.vector_field(z, ctx)
        for p in ref.parameters():
            p.mul_(1.5)
        expect = ref.vector_field(z, ref.field_context(data.youngs[:1]))
    assert not torch.allclose(before, after)
    torch.testing.assert_close(after, expect, **TOL)
    with torch.no_grad():
        torch.testing.assert_close(fast.field_fn(ctx)(z), expect, **TOL)


# --- MeshGraphNet -------------------------------------------------------------------------------
def mgn_pair(arrays, config, seed=0):
    from meshodenet.gnn.mgn import MeshGraphNet

    data = Trajectories.from_arrays(arrays, dtype=torch.float64)
    models = []
    for engine in ("fast", "reference"):
        torch.manual_seed(seed)
        m = MeshGraphNet(Mesh.from_arrays(arrays), replace(config, engine=engine), data).double()
        models.append(m)
    with torch.no_grad():
        g = torch.Generator().manual_seed(seed + 1)
        for pf, pr in zip(models[0].parameters(), models[1].parameters(), strict=True):
            pf.add_(0.1 * torch.randn(pf.shape, generator=g, dtype=pf.dtype))
            pr.copy_(pf)
    return (*models, data)


@pytest.mark.parametrize("source", ["tiny", "rod_falling", "plate_cantilever"])
def test_mgn_one_step_training_and_rollout_match(arrays, source):
    from meshodenet.gnn.mgn import MeshGraphNetConfig

    arr = arrays if source == "tiny" else case_arrays(source, n=2, frames=5)
    cfg = MeshGraphNetConfig(hidden=16, layers=3, noise=0.01)
    fast, ref, data = mgn_pair(arr, cfg)
    out = []
    for m in (fast, ref):
        m.zero_grad()
        loss = m.training_loss(data, torch.arange(m.n_training_samples(data)),
                               torch.Generator().manual_seed(0))
        loss.backward()
        with torch.no_grad():
            pos, vel = m.rollout(data.pos[:, 0], data.vel[:, 0], data.youngs, data.t)
        out.append((loss.detach(), grads(m), pos, vel))
    torch.testing.assert_close(out[0][0], out[1][0], **TOL)
    for x, y in zip(out[0][1], out[1][1], strict=True):
        torch.testing.assert_close(x, y, **TOL)
    torch.testing.assert_close(out[0][2], out[1][2], **TOL)
    torch.testing.assert_close(out[0][3], out[1][3], **TOL)


def test_bench_engine_cli_json_report_and_compare(tmp_path, capsys):
    """`meshbench bench engine` end to end on the smallest setting (prints, never asserts
    speed): JSON written, --report and --compare read it back; bad input exits 2."""
    import json

    from benchmarks.cli import main

    out = tmp_path / "b.json"
    args = ["bench", "engine", "--graphs", "rod1", "--regimes", "nograd,train", "--impl",
            "reference,fast", "--rounds", "1", "--budget", "0.01", "--train-intervals", "2",
            "--no-memory", "--no-epoch", "--no-solver", "--no-mgn", "--json", str(out)]
    assert main(args) == 0
    res = json.loads(out.read_text())
    r = res["graphs"]["rod1"]["regimes"]["train"]
    assert r["fast"]["evals_per_s"] > 0 and r["reference"]["evals_per_s"] > 0
    assert res["graphs"]["rod1"]["forward_mflop_per_eval"] == pytest.approx(14.83, abs=0.01)
    capsys.readouterr()
    assert main(["bench", "engine", "--report", str(out), "--compare", str(out)]) == 0
    text = capsys.readouterr().out
    assert "rod1" in text and "x1.00" in text
    assert main(["bench", "engine", "--graphs", "rod2"]) == 2


def test_bench_compare_skips_a_graph_whose_mesh_changed():
    """A baseline measured on another mesh of the same graph name (the plate before the in-plane
    case) is not compared: its rates are of other work."""
    from benchmarks.cost.report import compare

    def res(nodes, rate, epoch_s):
        r = {"evals_per_s": rate}
        return {"graphs": {"plate": {"nodes": nodes, "directed_edges": 5 * nodes,
                                     "regimes": {"train": {"fast": r}}}},
                "epochs": {"plate_cantilever": {"fast": {"epoch_s": epoch_s, "nodes": nodes}}}}

    same = compare(res(182, 90.0, 800.0), res(182, 45.0, 1600.0))
    assert any("x2.00" in line for line in same) and any("x2.00 faster" in line for line in same)
    other = compare(res(182, 90.0, 800.0), res(150, 45.0, 1600.0))
    assert len(other) == 2 and all("not compared" in line and "150" in line for line in other)
    base = res(150, 45.0, 1600.0)
    base["surrogate"] = {"plate_cantilever": {"solver": {}, "fast": {"single_s": 1.0}}}
    new = res(182, 90.0, 800.0)
    new["surrogate"] = {"plate_cantilever": {"solver": {}, "fast": {"single_s": 2.0}}}
    assert len(compare(new, base)) == 2  # the surrogate of the changed case is skipped too


def test_pyg_scatter_reference_matches_handwritten_to_round_off():
    """The reference path's sum at the receivers through PyG's ``scatter`` (the default) against
    ``index_add_``: the two kernels accumulate in different orders, so on the paper-size field
    over a whole training rollout they agree to float64 round-off, not bit for bit (measured on
    the 3 batched rods: up to 5.2e-10 relative in 8 of 16384 entries of one weight gradient)."""
    _, ref, data = pair(case_arrays("rod_falling", n=3, frames=4), MeshODENetConfig())
    pyg = MeshODENet(ref.mesh, replace(ref.config, message_passing="pyg")).double()
    pyg.load_state_dict(ref.state_dict())
    check_training_step(pyg, ref, data, 3, tol={"rtol": 2e-9, "atol": 1e-12})


@pytest.mark.parametrize("graph", ["rod1", "rod8"])
def test_bench_authors_stand_in_counts_its_evaluations_and_trains_every_weight(graph):
    """`--impl authors`: torchdiffeq's rk4 over ``k`` intervals calls the authors' field 4k times
    (the evaluations the bench divides by), the loss reaches every weight, and a batch of rods
    is one graph of ``n`` times the nodes."""
    from benchmarks.cost.enginebench import Regime

    r = Regime(graph, "train", "authors", 3)
    f = r.authors.f
    calls = []
    hook = f.register_forward_hook(lambda *a: calls.append(1))
    assert r.run(2) == 2 * 12 and len(calls) == 24
    hook.remove()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in f.parameters())
    n = {"rod1": 1, "rod8": 8}[graph]
    assert r.authors.pos.shape == (4, 21 * n, 3) and f.edge_index.shape == (2, 40 * n)
    assert f.edge_index.max() == 21 * n - 1
    for regime in ("nograd", "fwdbwd"):
        assert Regime(graph, regime, "authors", 3).run(2) == 2


# --- the engine in the configuration ----------------------------------------------------------
@pytest.mark.parametrize("model_id", ["meshodenet", "mgn", "meshodenet_imex", "mgn_unrolled"])
def test_engine_is_a_config_field_and_old_runs_read_as_the_default(model_id, tmp_path):
    """``engine`` and ``message_passing`` are config fields (default ``fast`` / ``pyg``, as
    before they were): saved in config.json and the checkpoint, checked, and a run stored
    before they existed compares equal to today's default configuration."""
    import json
    from dataclasses import asdict

    from benchmarks.suite.runs import with_defaults
    from meshodenet.registry import get_model_spec, load_model
    from meshodenet.training.presets import PRESETS
    from meshodenet.training.train import fit
    from tests.conftest import rod_arrays

    spec = get_model_spec(model_id)
    for preset in PRESETS:
        tc, mc = spec.presets(preset, "line")
        assert (mc.engine, mc.message_passing) == ("fast", "pyg")
        new = json.loads(json.dumps({"model": model_id, "train": asdict(tc),
                                     "model_config": asdict(mc)}))
        old = json.loads(json.dumps(new))
        del old["model_config"]["engine"], old["model_config"]["message_passing"]
        assert with_defaults(old) == new
        assert spec.config_from_dict(old["model_config"]) == mc
    name = spec.config_cls.__name__
    with pytest.raises(ValueError, match=rf"{name}\.engine must be one of fast, reference; "
                                         r"got 'slow'"):
        spec.config_cls(engine="slow")
    with pytest.raises(ValueError, match=rf"{name}\.message_passing .*'torch'"):
        spec.config_cls(message_passing="torch")
    arrays = rod_arrays(B=3, T=8)
    data = Trajectories.from_arrays(arrays)
    tc, mc = spec.presets("smoke", "line")
    mc = replace(mc, engine="reference", message_passing="handwritten")
    model = spec.build(Mesh.from_arrays(arrays), mc, data.subset(torch.arange(2)))
    assert model.engine == "reference"
    fit(model, data.subset(torch.arange(2)), data.subset(torch.tensor([2])),
        replace(tc, epochs=1), tmp_path, progress=False)
    loaded, ck = load_model(tmp_path / "last.pt")
    assert ck["model_info"]["config"]["engine"] == "reference" and loaded.config == mc
    assert {m.message_passing for m in loaded.modules() if hasattr(m, "message_passing")} \
        == {"handwritten"}
