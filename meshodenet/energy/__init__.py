"""The Implicit-Energy learner: a learned elastic energy over the mesh's edges and hinges
(``core``, with its element energies in ``elements``), the same energy in numpy for planar meshes
(``planar``), the dense and banded linear algebra of Newton's iteration (``linalg``), the learned
dissipation (``dissipation``), and the registered models that step the energy implicitly:
``model`` (Implicit-Energy, config and choices in ``config``) and ``model_dissipation``
(Implicit-Energy with dissipation)."""
