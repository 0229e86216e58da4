"""Building blocks shared by MeshODENet and MeshGraphNet: MLPs, the message-passing layer (its
aggregation PyTorch Geometric's ``scatter``) and the encode-process-decode network."""

from __future__ import annotations

import torch
from torch import nn

ACTIVATIONS = {"relu": nn.ReLU, "silu": nn.SiLU, "tanh": nn.Tanh}


def get_activation(name: str) -> type[nn.Module]:
    try:
        return ACTIVATIONS[name]
    except KeyError:
        raise ValueError(f"unknown activation {name!r}; valid: {', '.join(ACTIVATIONS)}") from None


def mlp(d_in: int, d_hidden: int, d_out: int, n_hidden: int, activation: str = "relu",
        layer_norm: bool = False) -> nn.Sequential:
    """``n_hidden`` hidden layers of width ``d_hidden`` with ``activation``, a linear output,
    and a ``LayerNorm`` on the output when ``layer_norm`` (MeshGraphNets' convention)."""
    act = get_activation(activation)
    dims = [d_in] + [d_hidden] * n_hidden
    layers: list[nn.Module] = []
    for a, b in zip(dims[:-1], dims[1:], strict=True):
        layers += [nn.Linear(a, b), act()]
    layers.append(nn.Linear(dims[-1], d_out))
    if layer_norm:
        layers.append(nn.LayerNorm(d_out))
    return nn.Sequential(*layers)


def scatter_sum(src: torch.Tensor, index: torch.Tensor, size: int) -> torch.Tensor:
    """``out[k] = sum of src[e] over e with index[e] == k``; ``out`` has exactly ``size`` rows,
    also when the last nodes receive no edge. (The hand-written sum the layers used before
    they were expressed with PyG; kept for ``meshbench bench --impl handwritten``.)"""
    return src.new_zeros(size, src.shape[-1]).index_add_(0, index, src)


class InteractionLayer(nn.Module):
    r"""One message-passing layer with residual edge and node updates, sum aggregation:

    .. math::
        e'_{ij} = e_{ij} + \phi_e([e_{ij}, h_i, h_j]), \qquad
        h'_j = h_j + \phi_v\big([h_j, \textstyle\sum_{i \to j} e'_{ij}]\big)

    for the directed edge ``i -> j`` (sender ``i``, receiver ``j``). The sum over the edges
    into each receiver is PyTorch Geometric's ``torch_geometric.utils.scatter`` (``reduce=
    "sum"``, ``dim_size`` = the number of nodes, so nodes without incoming edges get zeros).

    Shapes:
        - h: ``(M, d)`` node latents, e: ``(D, d)`` edge latents
        - senders, receivers: ``(D,)`` node indices in ``[0, M)``
        - returns ``(h', e')`` with the shapes of ``(h, e)``
    """

    #: the nodes sum the residual-updated edge latent (``False``: the edge MLP's output)
    aggregate_updated_edges = True
    def __init__(self, d: int, n_hidden: int, activation: str = "relu",
                 layer_norm: bool = False, message_passing: str = "pyg"):
        super().__init__()
        #: the sum at the receivers: ``"pyg"`` (``torch_geometric.utils.scatter``) or
        #: ``"handwritten"`` (``index_add_``, the code before; a model config's
        #: ``message_passing``). The fast engine (``meshodenet.gnn.fast``) reads the MLPs' weights
        #: and never calls ``forward``, so torch_geometric (1.5-4 s to import here) is
        #: imported only when this runs.
        self.message_passing = message_passing
        self.edge_mlp = mlp(3 * d, d, d, n_hidden, activation, layer_norm)
        self.node_mlp = mlp(2 * d, d, d, n_hidden, activation, layer_norm)

    def node_update(self, h: torch.Tensor, aggregated: torch.Tensor) -> torch.Tensor:
        """``h + phi_v([h, aggregated])``."""
        return h + self.node_mlp(torch.cat([h, aggregated], dim=-1))

    def forward(self, h, e, senders, receivers):
        n = h.shape[0]
        m = self.edge_mlp(torch.cat([e, h[senders], h[receivers]], dim=-1))
        e_new = e + m
        src = e_new if self.aggregate_updated_edges else m
        if self.message_passing == "handwritten":
            agg = scatter_sum(src, receivers, n)
        else:
            from torch_geometric.utils import scatter

            agg = scatter(src, receivers, dim=0, dim_size=n, reduce="sum")
        return self.node_update(h, agg), e_new


class EncodeProcessDecode(nn.Module):
    """Encoder MLPs for nodes and edges, ``n_layers`` unshared ``InteractionLayer``s, and a
    node decoder (never layer-normed).

    Shapes: node_in ``(M, d_node)``, edge_in ``(D, d_edge)``, senders/receivers ``(D,)``
    -> ``(M, d_out)``.
    """

    def __init__(self, d_node: int, d_edge: int, d_out: int, hidden: int = 128,
                 n_layers: int = 1, mlp_hidden_layers: int = 2, activation: str = "relu",
                 layer_norm: bool = False, message_passing: str = "pyg",
                 d_decoder_static: int = 0):
        super().__init__()
        args = (mlp_hidden_layers, activation, layer_norm)
        self.node_encoder = mlp(d_node, hidden, hidden, *args)
        self.edge_encoder = mlp(d_edge, hidden, hidden, *args)
        self.processor = nn.ModuleList(InteractionLayer(hidden, *args, message_passing)
                                       for _ in range(n_layers))
        #: ``d_decoder_static`` > 0: the decoder sees ``[h, decoder_static]`` (the authors'
        #: layout, ``meshodenet.gnn.features``)
        self.decoder = mlp(hidden + d_decoder_static, hidden, d_out, mlp_hidden_layers,
                           activation, False)

    def forward(self, node_in, edge_in, senders, receivers, decoder_static=None):
        h, e = self.node_encoder(node_in), self.edge_encoder(edge_in)
        for layer in self.processor:
            h, e = layer(h, e, senders, receivers)
        if decoder_static is not None:
            h = torch.cat([h, decoder_static], dim=-1)
        return self.decoder(h)
