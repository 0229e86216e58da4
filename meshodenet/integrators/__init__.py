"""Time integrators of a learned field ``dz/dt = f(t, z)``, shared by the learners:
``explicit`` (the fixed-step schemes, ``odesolve`` and the ``INTEGRATORS`` registry, which also
lists the implicit schemes) and ``implicit`` (the stiffly stable schemes solved by Newton's
method, their Jacobian strategies and their adjoint gradients). Neither knows a network or an
energy: they see a field and a state."""
