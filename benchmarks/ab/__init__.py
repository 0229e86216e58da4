"""The A/B harness: the authors' MeshODENet code against our ``paper`` preset, on the
same training and test splits of one case, epoch by epoch, in the same units.

``python -m benchmarks.ab train --case CASE --code authors|ours --out DIR ...`` trains one
code into ``DIR`` (resumable: every epoch is checkpointed atomically) and writes ``DIR/ab.csv``,
one row per epoch (``core.COLUMNS``); ``python -m benchmarks.ab merge ...`` joins the two
directories and the authors' published training log into ``results/paper/CASE_ab.csv`` and a
figure. Commands, columns, the conversion and the trust boundary: docs/AB.md.

The authors' code is never part of this repository: ``--code authors`` imports it from the
checkout the user names with ``--authors-repo`` (``authors.load_authors``), which runs their
code with the user's permissions, and only then. Nothing in ``meshodenet`` or the rest of
``benchmarks`` imports this package.

Modules: ``core`` (columns, the authors' loss, test metrics, run configuration and state
files), ``convert`` (our store arrays in the layout of the authors' preprocessing notebook),
``authors`` (loading and running their code), ``ours`` (the ``paper`` preset through
``meshodenet.training.train.fit``), ``merge`` (the results CSV and figure), ``scatter_shim`` (their
``torch_scatter`` import served by PyG), ``__main__`` (the command line).
"""
