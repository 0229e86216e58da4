"""Deprecated location of the model modules, kept for a short while: MeshODENet now lives in
``meshodenet.gnn.meshodenet`` (``meshodenet.models.meshodenet`` re-exports it with a
``DeprecationWarning``); every model is listed by id in ``meshodenet.registry.MODELS``."""
