"""Deprecated alias of ``meshodenet.training.train``, kept for a short while: import from there."""

import warnings

from meshodenet.training.train import *  # noqa: F401,F403

warnings.warn("meshodenet.train is deprecated; import meshodenet.training.train instead",
              DeprecationWarning, stacklevel=2)
