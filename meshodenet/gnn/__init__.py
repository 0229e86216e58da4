"""The graph-network learners and what only they use: the message-passing network (``layers``,
``network``; ``fast``, its hand-written forward and backward, and ``reference``, the modules' own
forward), the node and edge features and their normalisation (``features``), the PyTorch
Geometric adapter for user models (``pyg``), and one module per registered model, config and
presets beside the model: ``meshodenet`` (MeshODENet), ``mgn`` (MeshGraphNet), ``imex``
(MeshODENet-IMEX) and ``unrolled`` (MeshGraphNet trained through its own rollouts)."""
