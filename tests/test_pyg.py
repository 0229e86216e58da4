"""PyTorch Geometric: the reference layers sum with PyG's ``scatter`` (the same numbers as the
hand-written index_add_), and a model written in PyG, registered from a plugin file, runs
through a suite."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

pytest.importorskip("torch_geometric")

from torch_geometric.data import Batch  # noqa: E402

from meshodenet.gnn.layers import InteractionLayer  # noqa: E402
from meshodenet.gnn.mgn import GraphNetBlock  # noqa: E402
from meshodenet.mesh.data import Mesh, Trajectories  # noqa: E402
from tests.conftest import rod_arrays  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("cls", [InteractionLayer, GraphNetBlock])
def test_pyg_layer_equals_the_handwritten_one(cls):
    torch.manual_seed(0)
    layer = cls(8, 1).double()
    assert layer.message_passing == "pyg"
    h, e = torch.randn(6, 8, dtype=torch.float64), torch.randn(10, 8, dtype=torch.float64)
    snd = torch.tensor([0, 1, 2, 3, 4, 1, 2, 3, 4, 5])
    rcv = torch.tensor([1, 2, 3, 4, 5, 0, 1, 2, 3, 4])
    h1, e1 = layer(h, e, snd, rcv)
    layer.message_passing = "handwritten"
    h2, e2 = layer(h, e, snd, rcv)
    assert torch.equal(h1, h2) and torch.equal(e1, e2)  # measured bit-identical
    # by hand: the edge update sees [e, h_sender, h_receiver], the nodes sum at receivers
    m = layer.edge_mlp(torch.cat([e, h[snd], h[rcv]], -1))
    agg = torch.zeros_like(h).index_add_(0, rcv, e + m if cls is InteractionLayer else m)
    assert torch.allclose(h1, h + layer.node_mlp(torch.cat([h, agg], -1)), atol=1e-12)


def test_pyg_model_gets_a_batch_and_keeps_clamped_nodes():
    from meshodenet.gnn.pyg import D_EDGE, D_NODE, PyGModelConfig, PyGStepModel

    seen = {}

    class Net(torch.nn.Module):
        def __init__(self, d_node, d_edge, config):
            super().__init__()
            self.lin = torch.nn.Linear(d_node, 3)

        def forward(self, batch):
            seen["batch"] = batch
            return self.lin(batch.x)

    cls = type("M", (PyGStepModel,), {"name": "pyg_test", "make_net": staticmethod(Net)})
    arrays = rod_arrays(B=3, T=6)
    mesh = Mesh.from_arrays(arrays)
    data = Trajectories.from_arrays(arrays)
    model = cls(mesh, PyGModelConfig(hidden=4, layers=1), data).to(torch.float32)
    pos, vel = model.rollout(data.pos[:2, 0], data.vel[:2, 0], data.youngs[:2], data.t)
    b = seen["batch"]
    N = mesh.n_nodes
    assert isinstance(b, Batch) and b.num_graphs == 2 and b.x.shape == (2 * N, D_NODE)
    assert b.edge_attr.shape == (2 * 2 * len(mesh.edges), D_EDGE)
    assert b.pos.shape == b.vel.shape == (2 * N, 3) and b.youngs.shape == (2,)
    assert torch.equal(b.node_type[:N], torch.as_tensor(mesh.node_type))
    assert pos.shape == (2, len(data.t), N, 3) and torch.equal(pos[:, 0], data.pos[:2, 0])
    clamped = torch.as_tensor(mesh.node_type == 1)
    assert torch.equal(pos[:, :, clamped], data.pos[:2, :1, clamped].expand_as(pos[:, :, clamped]))
    loss = model.training_loss(data, torch.arange(4), torch.Generator())
    loss.backward()
    assert loss.ndim == 0 and model.net.lin.weight.grad is not None


def test_pyg_plugin_model_runs_through_a_suite(tmp_path):
    from benchmarks.cli import main

    plugin = ROOT / "docs" / "examples" / "pyg_plugin.py"
    res, runs = tmp_path / "res", tmp_path / "runs"
    assert main(["--plugin", str(plugin), "run", "--suite", "pyg_smoke", "--results", str(res),
                 "--runs-dir", str(runs), "--data-dir", str(tmp_path / "data"), "--no-progress",
                 "--no-figures"]) == 0
    rec = json.loads((runs / "rod_cantilever-pyg_gine-smoke-s0" / "record.json").read_text())
    assert rec["model"] == "pyg_gine" and rec["epochs"] == 2 and rec["test_rmse_m"] > 0
    import pandas as pd

    t = pd.read_csv(res / "pyg_smoke" / "rmse_at_step.csv")
    assert set(t["model"]) == {"pyg_gine"} and t["rmse_mean"].notna().all()
