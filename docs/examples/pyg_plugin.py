"""A model written in PyTorch Geometric, benchmarked by meshbench (docs/CLUSTER.md, "Models
in PyTorch Geometric"):

    meshbench --plugin docs/examples/pyg_plugin.py run --suite pyg_smoke

``GINENet`` is built from ``torch_geometric.nn`` layers; the engine hands it a
``torch_geometric.data.Batch`` (positions, velocities, edges, node types, modulus and
normalised features ``x`` / ``edge_attr``) and trains and rolls it out as a one-step model.
"""

from torch import nn
from torch_geometric.nn import GINEConv

from benchmarks.suite.suites import RunSpec, Suite, register_suite
from meshodenet.gnn.pyg import register_pyg_model


class GINENet(nn.Module):
    """Node encoder, ``config.layers`` residual ``GINEConv`` layers with edge features, a
    decoder to the normalised acceleration. Shapes: ``batch.x (M, d_node)``,
    ``batch.edge_attr (D, d_edge)`` -> ``(M, 3)``."""

    def __init__(self, d_node: int, d_edge: int, config):
        super().__init__()
        h = config.hidden
        self.encoder = nn.Sequential(nn.Linear(d_node, h), nn.ReLU(), nn.Linear(h, h))
        self.convs = nn.ModuleList(
            GINEConv(nn.Sequential(nn.Linear(h, h), nn.ReLU(), nn.Linear(h, h)), edge_dim=d_edge)
            for _ in range(config.layers))
        self.decoder = nn.Sequential(nn.Linear(h, h), nn.ReLU(), nn.Linear(h, 3))

    def forward(self, batch):
        h = self.encoder(batch.x)
        for conv in self.convs:
            h = h + conv(h, batch.edge_index, batch.edge_attr)
        return self.decoder(h)


register_pyg_model("pyg_gine", GINENet, overwrite=True,
                   description="GINEConv network (torch_geometric.nn) as a one-step model")
register_suite(Suite("pyg_smoke", "the smoke suite's case with the PyG GINEConv model", (
    RunSpec("rod_cantilever", "pyg_gine", "smoke"),)), overwrite=True)
