"""A discrete mechanical system: elastic energy terms, lumped mass, loads and clamps.

The state is the flat vector ``q`` of node coordinates, ``q[3*i:3*i+3] = x_i`` (m). The
equation of motion is

    M q'' + C q' + grad E(q) = F,

with diagonal lumped mass ``M`` (kg), diagonal velocity-proportional damping ``C`` (N s/m,
Stokes drag or mass-proportional damping), elastic energy ``E = sum of terms`` (J) and a
constant external force ``F`` (N: weight minus buoyancy, or gravity). Clamped dofs never move.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from groundtruth.assembly import Assembler, SystemMatrix


class EnergyTerm(Protocol):
    """One kind of elastic element. ``dofs`` is ``(n_el, d)``; ``evaluate`` returns per-element
    energy ``(n_el,)``, gradient ``(n_el, d)`` and Hessian ``(n_el, d, d)`` (``None`` when
    ``order`` is lower) for the element coordinates ``q[dofs]``."""

    dofs: np.ndarray

    def evaluate(self, xe: np.ndarray, order: int) -> tuple: ...


@dataclass
class MechanicalSystem:
    """Energy terms plus mass, damping, load and clamp, assembled on a fixed pattern.

    Attributes:
        terms: elastic energy terms.
        mass: lumped mass per node ``(N,)``, kg.
        damping: drag coefficient per node ``(N,)``, N s/m (drag = -damping * v).
        force: constant external force per node ``(N, 3)``, N.
        fixed_nodes: boolean ``(N,)``, True for clamped nodes.
        force_scale: a characteristic force (N) that scales the Newton tolerance.
        linear_solver: Newton's linear solver, one of ``groundtruth.assembly.LINEAR_SOLVERS``
            (``"auto"``: the band LU of the committed data on small meshes, a sparse
            factorization on large ones); switch with ``dataclasses.replace``.
        resting_dofs: boolean ``(3N,)`` or ``None``: dofs the physics keeps at rest exactly
            (unloaded, unmoving, uncoupled: the z of an in-plane plate), which the sparse
            solver leaves out of the factorization.
    """

    terms: list
    mass: np.ndarray
    damping: np.ndarray
    force: np.ndarray
    fixed_nodes: np.ndarray
    force_scale: float
    linear_solver: str = "auto"
    resting_dofs: np.ndarray | None = None
    assembler: Assembler = field(init=False, repr=False)

    def __post_init__(self):
        n = self.mass.shape[0]
        self.mass = np.asarray(self.mass, float)
        self.damping = np.asarray(self.damping, float)
        self.force = np.asarray(self.force, float).reshape(n, 3)
        self.fixed_nodes = np.asarray(self.fixed_nodes, bool)
        if self.damping.shape != (n,) or self.fixed_nodes.shape != (n,):
            raise ValueError(f"damping and fixed_nodes must have shape ({n},)")
        self.assembler = Assembler([t.dofs for t in self.terms], 3 * n, self.fixed_dofs,
                                   self.linear_solver, self.resting_dofs)
        # terms that may act on resting dofs only: skipped where they do (``_active_terms``)
        resting = self.resting_dofs
        self._restable = [self.assembler.sparse is not None and resting is not None
                          and hasattr(t, "flat_at_rest") and bool(resting[t.dofs[:, 2::3]].all())
                          and not resting[t.dofs[:, 0::3]].any()
                          and not resting[t.dofs[:, 1::3]].any()
                          for t in self.terms]

    @property
    def n_nodes(self) -> int:
        return self.mass.shape[0]

    @property
    def fixed_dofs(self) -> np.ndarray:
        return np.repeat(self.fixed_nodes, 3)

    @property
    def mass_dofs(self) -> np.ndarray:
        return np.repeat(self.mass, 3)

    @property
    def damping_dofs(self) -> np.ndarray:
        return np.repeat(self.damping, 3)

    @property
    def force_dofs(self) -> np.ndarray:
        return self.force.ravel()

    def energy(self, q: np.ndarray) -> float:
        """Total elastic energy (J)."""
        return float(sum(t.evaluate(q[t.dofs], 0)[0].sum() for t in self.terms))

    def _evaluate(self, q: np.ndarray, order: int) -> list:
        """Per term: ``evaluate(q[dofs], order)``, or ``None`` for a term that acts on resting
        dofs only at ``q``.

        Such a term (``flat_at_rest``: the hinges of a flat plate that stays in its plane, with
        z at rest) has gradient exactly 0 and Hessian entries only between resting dofs, which
        the sparse solver leaves out of the factorization; skipping it leaves every assembled
        value it factors, and every Newton iterate, bit for bit as they were. Only on the sparse
        path (the band LU factors the resting rows too)."""
        out = []
        for t, restable in zip(self.terms, self._restable):
            xe = q[t.dofs]
            out.append(None if restable and t.flat_at_rest(xe) else t.evaluate(xe, order))
        return out

    def gradient(self, q: np.ndarray) -> np.ndarray:
        """Gradient of the elastic energy ``(3N,)`` (N); minus the internal force."""
        out = self._evaluate(q, 1)
        return self.assembler.vector([o[1] for o in out if o is not None],
                                     [o is not None for o in out])

    def gradient_hessian(self, q: np.ndarray, diagonal: np.ndarray) -> tuple[np.ndarray, SystemMatrix]:
        """Elastic gradient and ``hessian + diag(diagonal)`` with clamped dofs as identity."""
        out = self._evaluate(q, 2)
        used = [o is not None for o in out]
        g = self.assembler.vector([o[1] for o in out if o is not None], used)
        return g, self.assembler.matrix([o[2] for o in out if o is not None], diagonal, used)

    def hessian(self, q: np.ndarray) -> np.ndarray:
        """Dense elastic Hessian (tests only); clamped dofs are not removed."""
        out = [t.evaluate(q[t.dofs], 2) for t in self.terms]
        h = np.zeros((q.size, q.size))
        for t, o in zip(self.terms, out):
            d = t.dofs
            np.add.at(h, (d[:, :, None], d[:, None, :]), o[2])
        return h

    def total_energy(self, q: np.ndarray, v: np.ndarray) -> float:
        """Kinetic + elastic + potential of the constant load (J)."""
        return 0.5 * float(v @ (self.mass_dofs * v)) + self.energy(q) - float(self.force_dofs @ q)
