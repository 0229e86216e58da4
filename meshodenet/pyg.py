"""Deprecated alias of ``meshodenet.gnn.pyg``, kept for a short while: import from there."""

import warnings

from meshodenet.gnn.pyg import *  # noqa: F401,F403

warnings.warn("meshodenet.pyg is deprecated; import meshodenet.gnn.pyg instead",
              DeprecationWarning, stacklevel=2)
