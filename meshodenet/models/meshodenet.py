"""Deprecated alias of ``meshodenet.gnn.meshodenet``, kept for a short while: import from there."""

import warnings

from meshodenet.gnn.meshodenet import *  # noqa: F401,F403

warnings.warn("meshodenet.models.meshodenet is deprecated; import meshodenet.gnn.meshodenet instead",
              DeprecationWarning, stacklevel=2)
