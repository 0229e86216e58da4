"""A stand-in for the ``torch_scatter`` package, which the authors' code imports (PyPI's
``torch-scatter`` is source-only; docs/SOURCES.md, "The authors' MeshODENet code"): its
``scatter`` family mapped onto ``torch_geometric.utils.scatter``. ``authors.load_authors``
registers this module as ``sys.modules["torch_scatter"]`` inside the A/B process only, and only
when the real package is not installed; it is never put on ``sys.path``, and ``torch_geometric``
is imported before, so PyG's own check for ``torch_scatter`` never sees it.
"""

from __future__ import annotations

from torch_geometric.utils import scatter as _pyg_scatter


def scatter(src, index, dim=-1, out=None, dim_size=None, reduce="sum"):
    """``torch_scatter.scatter``: reduce ``src`` along ``dim`` into the slots ``index``
    (``sum``/``add``, ``mean``, ``min``, ``max``, ``mul``); ``out`` is not supported."""
    if out is not None:
        raise NotImplementedError("the torch_scatter stand-in does not write into out=")
    return _pyg_scatter(src, index, dim=dim, dim_size=dim_size, reduce=reduce)


def scatter_sum(src, index, dim=-1, out=None, dim_size=None):
    return scatter(src, index, dim, out, dim_size, "sum")


def scatter_mean(src, index, dim=-1, out=None, dim_size=None):
    return scatter(src, index, dim, out, dim_size, "mean")


scatter_add = scatter_sum
