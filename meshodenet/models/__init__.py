"""The registered models, one module each (config dataclass, presets, model side by side):
``meshodenet`` (MeshODENet), ``mgn`` (MeshGraphNet), ``imex`` (MeshODENet-IMEX),
``unrolled`` (MeshGraphNet trained through its own rollouts), ``energy``
(Implicit-Energy: a learned energy stepped by backward Euler); ``common`` holds what they
share. ``meshodenet.registry.MODELS`` lists them by id."""
