"""Implicit-Energy's configuration (``EnergyConfig``), its initial stiffness fits
(``STIFFNESS_PRIORS``) and rollout solvers (``SOLVERS``); the model is
``meshodenet.energy.model``, which re-exports all three."""

from __future__ import annotations

from dataclasses import dataclass

from meshodenet.training.presets import check_int, check_nonnegative


@dataclass(frozen=True)
class EnergyConfig:
    """``hidden``, ``layers``: width and hidden layers of each element type's MLP;
    ``shooting``: 0 the linearised one-step loss, ``S > 0`` windows of ``S`` steps;
    ``newton_rtol``: Newton stops when no node moves by more than this times the mean rest edge
    length; ``newton_max_iter``: iterations before ``NewtonError``; ``stiffness_prior``: how
    the initial stiffness is fitted (a key of ``STIFFNESS_PRIORS``); ``exact_loss_gradient``:
    the one-step loss ``|A^{-1} r|^2`` differentiated with its matrix ``A`` on the parameters'
    graph too (its exact gradient; False, the default, holds ``A`` fixed: a cheaper surrogate
    that serves the rod and the in-plane plate but is no descent direction on
    ``plate_hanging``, docs/ENERGY.md "Training"); ``clamp_q``: each element MLP sees its
    measure ``qhat`` clamped to the range the training frames span (``g`` constant beyond it,
    so the element energy is quadratic there, never softening where no data constrained it;
    docs/ENERGY.md "Bending"); ``integrator``: the step (a key of ``INTEGRATORS``);
    ``newmark_gamma``: Newmark's ``gamma`` in [1/2, 1], ``beta = gamma^2`` (1/2: the average
    acceleration, second order, no numerical damping; above it the high frequencies decay, to
    0.71 per step at 1, first order); ``max_halvings``: a rollout's interval whose Newton
    fails is retried as two steps of half the length, up to so many times over (0: the
    failure is the rollout's; training steps never halve)."""

    hidden: int = 32
    layers: int = 2
    shooting: int = 0
    newton_rtol: float = 1e-8
    newton_max_iter: int = 30
    stiffness_prior: str = "uniform"
    exact_loss_gradient: bool = False
    clamp_q: bool = False
    integrator: str = "backward_euler"
    newmark_gamma: float = 0.5
    max_halvings: int = 0

    def __post_init__(self):
        for name, lo in (("hidden", 1), ("layers", 0), ("shooting", 0), ("newton_max_iter", 1),
                         ("max_halvings", 0)):
            check_int(self, name, lo)
        owner = type(self).__name__
        check_nonnegative(owner, "newton_rtol", self.newton_rtol)
        for name in ("exact_loss_gradient", "clamp_q"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{owner}.{name} must be a bool, got {getattr(self, name)!r}")
        if not self.newton_rtol > 0:
            raise ValueError(f"{owner}.newton_rtol must be > 0, got {self.newton_rtol!r}")
        g = self.newmark_gamma
        if isinstance(g, bool) or not isinstance(g, (int, float)) or not 0.5 <= g <= 1:
            raise ValueError(f"{owner}.newmark_gamma must be a number in [0.5, 1], got {g!r}")
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"{owner}.integrator must be one of {', '.join(INTEGRATORS)}, "
                             f"got {self.integrator!r}")
        if self.stiffness_prior not in STIFFNESS_PRIORS:
            raise ValueError(f"{owner}.stiffness_prior must be one of "
                             f"{', '.join(STIFFNESS_PRIORS)}, got {self.stiffness_prior!r}")


#: The initial stiffness (``EnergyConfig.stiffness_prior``), both least-squares fits of the
#: training frames' momentum balance with ``g = 1`` (``ImplicitEnergy._fit_log_stiffness``):
STIFFNESS_PRIORS = {
    # one stiffness per element type (a_t); the default, and the first fit there was
    "uniform": "one least-squares stiffness per element type",
    # each element's stiffness linear in its static features (a_t and a fixed factor kappa_e
    # per element, mean 1): on the plate the uniform fit explains 0.1 % of the balance and
    # starts about 770 times too soft, this one explains 99.6 % (docs/ENERGY.md)
    "features": "a least-squares stiffness per element, linear in its static features",
}


#: The step of one saved interval ``h`` (``EnergyConfig.integrator``), both solved as the
#: minimisation of ``ImplicitEnergy``'s backward-Euler form (``ImplicitEnergy._implicit_form``):
INTEGRATORS = {
    # first order, L-stable: from rest it moves a node h^2 a where the truth moves ~h^2 a / 2
    "backward_euler": "backward Euler (first order, L-stable)",
    # second order, A-stable, no numerical damping; exact from rest under a constant load;
    # carries the acceleration (docs/ENERGY.md, "What it is" and "Bending")
    "newmark": "Newmark's average acceleration (trapezoidal; second order)",
}


#: How a rollout without gradients solves its steps (``ImplicitEnergy.solver``):
SOLVERS = {
    # each trajectory its own Newton (its own chord and line-search decisions), all of the
    # batch's in one pass per iteration, converged trajectories dropping out; banded
    # Cholesky in a reverse Cuthill-McKee order; the rod hinges' derivatives by hand
    "batched": "per-trajectory Newton, banded Cholesky, one MLP pass for all elements",
    # the first solver, kept as a reference: one Newton for the whole batch (it stops when the last
    # trajectory converges), dense Cholesky, rod hinges by torch.func
    "reference": "one Newton for the batch, dense Cholesky, torch.func rod hinges",
}
