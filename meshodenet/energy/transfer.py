"""Implicit-Energy on another mesh of its kind (``TrajectoryModel.on_mesh``): its element
energies read as densities per unit length (rods) or area (plates), so that a model trained on
one mesh rolls out on a finer one (docs/SCALE.md, "Learned models on other meshes").
``EnergyTransfer`` is a base class of ``ImplicitEnergy`` (``meshodenet.energy.model``)."""

from __future__ import annotations

import math

import torch
from torch import nn

from meshodenet.energy.core import LENGTH_POWER, TYPES, static_features
from meshodenet.mesh.data import DataError, Mesh


def element_kinds(mesh: Mesh, feats: dict) -> tuple[bool, list]:
    """``(planar, kinds)``: whether ``mesh`` stays in its plane, and the element types of
    ``TYPES`` its energy has (``feats``: ``static_features(mesh)``). A planar mesh loaded in
    its plane never leaves it (the in-plane solve): its dihedral angles stay at rest, so it
    gets no bending term."""
    planar = mesh.dims == 2
    return planar, [k for k in TYPES if k in feats and len(feats[k][0])
                    and not (k == "dihedral" and planar)]


class EnergyTransfer:
    """What ``ImplicitEnergy`` adds to ``TrajectoryModel``'s ``on_mesh``: the mesh's own
    state, the element types a mesh needs, and the energy moved onto a mesh of other element
    sizes."""

    def mesh_state_keys(self) -> set:
        """The elements, their static features, rest shapes and stiffness factors, and the
        case's masses, loads, drag and clamps: the new mesh's own on another mesh."""
        per = ("nodes", "static", "rest", "l0", "prior")
        return {f"{k}_{p}" for k in self.kinds for p in per} | {"mass", "damping", "force",
                                                                 "free"}

    def check_transfer(self, mesh: Mesh, what: str = "data") -> None:
        """``TrajectoryModel.check_transfer``, and every element type the energy of ``mesh``
        has must be one the model learned (a planar in-plane plate has no bending term)."""
        super().check_transfer(mesh, what)
        _, kinds = element_kinds(mesh, static_features(mesh))
        new = [k for k in kinds if k not in self.kinds]
        if new:
            raise DataError(f"{what} is {mesh.describe()}, whose energy has {', '.join(new)} "
                            f"elements, but model {self.name!r} trained on "
                            f"{self.mesh.describe()} learned energies of {', '.join(self.kinds)} "
                            "elements only")

    @torch.no_grad()
    def transfer(self, mesh: Mesh, what: str = "data") -> EnergyTransfer:
        """This energy on ``mesh`` (elements ``rho`` times the training mesh's size,
        ``Mesh.length_scale``; ``d`` = 1 for rods, 2 for plates): the training mesh's energy
        density of the same deformation times the new elements' measure. Every element's
        energy ``e^a 1/2 qhat^p g`` is its share of a density per unit length (rods) or area
        (plates), so ``a`` gains ``d log rho``; ``sigma`` is multiplied by ``rho^LENGTH_POWER``
        (a hinge's squared angle at a given curvature goes as ``rho^2``), so ``qhat`` is the
        training mesh's at the same deformation and ``g`` is evaluated where it was trained;
        the static features are the new elements' relative to the training mesh
        (``static_features(mesh, reference)``: sizes against its mean sizes scaled by ``rho``,
        columns standardised with its statistics); a
        ``features`` stiffness factor ``kappa`` is the training factor's least-squares fit in
        its basis (``_basis``), evaluated on the new elements (exact where no element was
        floored in training). Masses, loads and drag are the new mesh's (the case's)."""
        new = super().transfer(mesh, what)
        rho = mesh.length_scale / self.mesh.length_scale
        d = 1 if mesh.kind == "line" else 2
        feats = static_features(mesh, reference=self.mesh)
        for k in new.kinds:
            getattr(new, f"{k}_static").copy_(torch.as_tensor(feats[k][1]))
            setattr(new, f"{k}_sigma", getattr(self, f"{k}_sigma") * rho ** LENGTH_POWER[k])
            term = new.terms[k]
            term.log_stiffness = nn.Parameter(term.log_stiffness + d * math.log(rho),
                                              requires_grad=term.log_stiffness.requires_grad)
            if self.config.stiffness_prior == "features":
                getattr(new, f"{k}_prior").copy_(self._transfer_prior(new, k))
        return new

    def _transfer_prior(self, new: EnergyTransfer, kind: str) -> torch.Tensor:
        """``kappa`` of ``new``'s elements of ``kind``: this model's, fitted by least squares
        in its basis, on ``new``'s static features (floored as ``_set_stiffness`` does)."""
        return fitted_factor(getattr(self, f"{kind}_static"), getattr(self, f"{kind}_prior"),
                             getattr(new, f"{kind}_static"), self._basis_columns(kind))


def fitted_factor(static: torch.Tensor, kappa: torch.Tensor, new_static: torch.Tensor,
                  cols: list) -> torch.Tensor:
    """Per-element factors ``kappa (n,)`` fitted by least squares in the basis
    ``[1, static[:, cols]]`` of their elements' static features, evaluated on other elements:
    ``[1, new_static[:, cols]] @ c``, floored at 1e-3 of their largest (and 1e-300)."""
    def basis(f):
        return torch.cat([torch.ones_like(f[:, :1]), f[:, cols]], 1)

    c = torch.linalg.lstsq(basis(static), kappa[:, None]).solution[:, 0]
    new = basis(new_static) @ c
    return new.clamp(min=max(1e-3 * float(new.abs().max()), 1e-300))
