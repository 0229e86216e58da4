"""Ground-truth validation: the DER/DEP against a FEM (crosscheck) and the plate's fidelity."""
