"""Suites: named lists of runs (case x model x integrator x gradient mode x seeds x preset).

A ``RunSpec`` is one training run; its ``run_id`` is the stable string that appears in every
results CSV and names its directory under ``runs/``. A ``Suite`` expands its specs over seeds.
Add a suite from a plugin file with ``register_suite``::

    from benchmarks.suite.suites import RunSpec, Suite, register_suite
    register_suite(Suite("mine", "my rod on both models", (
        RunSpec("my_rod", "meshodenet", "quick"), RunSpec("my_rod", "mgn", "quick"))))
"""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass, replace

from benchmarks.suite.registry import lookup, safe_id


@dataclass(frozen=True)
class RunSpec:
    """One training run. ``integrator`` / ``grad_mode`` override the preset's when given (for
    a model whose configuration has these fields: ``runner.check_runs``); ``overrides`` are
    extra ``train.FIELD=VALUE`` / ``model.FIELD=VALUE`` settings (as ``meshbench train
    --set``); ``tag`` distinguishes runs that differ only in ``overrides``."""

    case: str
    model: str
    preset: str = "quick"
    integrator: str | None = None
    grad_mode: str | None = None
    seed: int = 0
    overrides: tuple = ()
    tag: str = ""

    def __post_init__(self):
        for name in ("case", "model", "preset"):  # the parts of run_id, a directory name
            safe_id(getattr(self, name), f"RunSpec.{name}")
        for name in ("integrator", "grad_mode", "tag"):
            if getattr(self, name):
                safe_id(getattr(self, name), f"RunSpec.{name}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"RunSpec.seed must be an int >= 0, got {self.seed!r}")

    @property
    def run_id(self) -> str:
        parts = [self.case, self.model, self.preset]
        if self.integrator:
            parts.append(self.integrator)
        if self.grad_mode:
            parts.append(self.grad_mode)
        if self.tag:
            parts.append(self.tag)
        parts.append(f"s{self.seed}")
        return "-".join(parts)

    def all_overrides(self) -> tuple:
        out = list(self.overrides)
        if self.integrator:
            out.append(f"model.integrator={self.integrator}")
        if self.grad_mode:
            out.append(f"model.grad_mode={self.grad_mode}")
        if self.seed:
            out.append(f"train.seed={self.seed}")
        return tuple(out)


@dataclass(frozen=True)
class Suite:
    """A named list of runs; ``seeds`` is how many seeds (0..seeds-1) each spec runs with
    unless ``meshbench run --seeds`` says otherwise."""

    name: str
    description: str
    specs: tuple
    seeds: int = 1
    notes: str = ""
    compare_rtol: float = 0.0
    #: resolutions r to roll every run out at, on the test split of ``CASE@rN`` (the same
    #: case on a mesh r times finer, docs/SCALE.md): RESULTS/NAME/transfer/
    #: (``benchmarks.suite.transfer``) instead of the suite's tables; empty: none
    resolutions: tuple = ()
    #: roll every run out for ``horizon.FACTOR`` times its test trajectories and score where
    #: it settles (``benchmarks.suite.horizon``: the ``horizon_*`` rows); False leaves them
    #: out, where they would cost more than the suite (at r = 8, 2,500 whole-mesh steps and
    #: a static solve per test trajectory and run)
    horizon: bool = True

    def __post_init__(self):
        safe_id(self.name, "Suite.name")  # names RESULTS/NAME/
        from groundtruth.cases.base import check_resolution

        for r in self.resolutions:
            check_resolution(r, f"Suite.resolutions of {self.name!r}")

    def runs(self, seeds: int | None = None, only: str | None = None) -> list[RunSpec]:
        k = self.seeds if seeds is None else seeds
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise ValueError(f"--seeds must be an int >= 1, got {k!r}")
        out = [replace(s, seed=s.seed + i) for s in self.specs for i in range(k)]
        if only:
            pats = [p.strip() for p in only.split(",") if p.strip()]
            out = [r for r in out if any(fnmatch.fnmatch(r.run_id, p if any(c in p for c in "*?[")
                                                         else f"*{p}*") for p in pats)]
            if not out:
                raise ValueError(f"--only {only!r} matches no run of suite {self.name!r}; its "
                                 f"runs: {', '.join(r.run_id for r in self.runs(seeds))}")
        ids = [r.run_id for r in out]
        dup = sorted({i for i in ids if ids.count(i) > 1})
        if dup:
            raise ValueError(f"suite {self.name!r} has duplicate run ids {dup}; give them tags")
        return out


def _both(case: str, preset: str) -> tuple:
    return (RunSpec(case, "meshodenet", preset), RunSpec(case, "mgn", preset))


def _quick_models(case: str, preset: str) -> tuple:
    """MeshODENet, MGN and ours: MeshODENet-IMEX (docs/TRAINING.md), Implicit-Energy and
    Implicit-Energy with a learned dissipation (docs/ENERGY.md)."""
    return _both(case, preset) + (RunSpec(case, "meshodenet_imex", preset),
                                  RunSpec(case, "implicit_energy", preset),
                                  RunSpec(case, "implicit_energy_dissipation", preset))


SUITES: dict = {}


def register_suite(suite: Suite, overwrite: bool = False) -> Suite:
    if suite.name in SUITES and not overwrite:
        raise ValueError(f"suite {suite.name!r} is already registered; pass overwrite=True")
    SUITES[suite.name] = suite
    return suite


def get_suite(name: str) -> Suite:
    return lookup(SUITES, name, "suite")


register_suite(Suite(
    "smoke", "rod_cantilever (6 short trajectories), both models, smoke preset: about a "
    "minute, for the tests", _both("rod_cantilever", "smoke")))


def _solver(case: str) -> tuple:
    """The case's own solver at the sampling interval, a reference row (nothing is trained;
    its seeds are identical: benchmarks/suite/solver_row.py)."""
    return (RunSpec(case, "solver_h", "quick"),)


#: The quick suite's runs (the scale suite's too).
QUICK_RUNS = _quick_models("rod_falling", "quick") + _solver("rod_falling") \
    + _quick_models("plate_cantilever", "quick") + _solver("plate_cantilever")
register_suite(Suite(
    "quick", "the paper's two cases, MeshODENet, MGN, MeshODENet-IMEX, Implicit-Energy and "
    "Implicit-Energy with a learned dissipation, "
    "quick preset, and the case's solver at the sampling interval (solver_h, a reference "
    "row); the main job (data and one seed, tox -e bench, --jobs 2) from a fresh clone on a "
    "2-core CPU: docs/RESULTS.md, 'How the committed results were produced'",
    QUICK_RUNS, compare_rtol=0.05))
register_suite(Suite(
    "scale", "the quick suite's runs (the same run ids: trained runs are reused), 3 seeds, "
    "trained on the paper's meshes and rolled out on the test moduli on meshes 1, 2 and 4 "
    "times finer (CASE@rN, only their test split generated): results/scale/transfer/ "
    "(docs/SCALE.md, 'Learned models on other meshes')",
    QUICK_RUNS, seeds=3, compare_rtol=0.05, resolutions=(1, 2, 4)))
#: The sub-domain suite's overrides of Implicit-Energy's ``quick`` plate preset
#: (docs/SUBDOMAIN.md, "The subdomain suite"): patches of 2,000 inner nodes (5 METIS parts of
#: the 9,289-node mesh, each with its one-ring halo), batches of 8 (frame, patch) pairs.
#: Validation rolls the whole mesh out (about 100 s a trajectory at r = 8); every other epoch.
SUBDOMAIN_OVERRIDES = ("train.patch_nodes=2000", "train.batch_size=8", "train.val_every=2")
register_suite(Suite(
    "subdomain", "Implicit-Energy trained on patches of the r = 8 plate (plate_cantilever_few@r8: "
    "9,289 nodes, 6 training trajectories), 2,000 nodes a patch, 3 seeds, rolled out on the "
    "whole mesh on the paper's test moduli (docs/SUBDOMAIN.md, 'The subdomain suite'; its "
    "baseline, the same learner trained on the paper's mesh, is the subdomain_transfer suite)",
    (RunSpec("plate_cantilever_few@r8", "implicit_energy", "quick",
             overrides=SUBDOMAIN_OVERRIDES, tag="patches"),), seeds=3, compare_rtol=0.05,
    horizon=False))
register_suite(Suite(
    "subdomain_whole", "the subdomain suite's run trained on the whole r = 8 mesh instead of "
    "on patches (the same settings, batches of 8 whole frames), one seed: what patches cost "
    "and save against whole-graph training at r = 8 (docs/SUBDOMAIN.md)",
    (RunSpec("plate_cantilever_few@r8", "implicit_energy", "quick",
             overrides=SUBDOMAIN_OVERRIDES[1:], tag="whole"),), compare_rtol=0.05,
    horizon=False))
register_suite(Suite(
    "subdomain_transfer", "the subdomain suite's baseline: Implicit-Energy trained on the "
    "paper's plate mesh (the quick suite's runs, reused when trained), 3 seeds, rolled out on "
    "the test moduli of the same plate on a mesh 8 times finer (plate_cantilever@r8, 9,289 "
    "nodes): results/subdomain_transfer/transfer/",
    (RunSpec("plate_cantilever", "implicit_energy", "quick"),), seeds=3, compare_rtol=0.05,
    resolutions=(1, 8)))
register_suite(Suite(
    "paper", "the paper's two cases, MeshODENet and MGN, the paper's settings (GPU "
    "recommended: a MeshODENet rod run took 6 h of one core, 45-57 s per epoch, on a shared "
    "2-core CPU; docs/RESULTS.md)",
    _both("rod_falling", "paper") + _both("plate_cantilever", "paper")))
register_suite(Suite(
    "hanging", "plate_hanging (the paper's text read literally: gravity through the thickness, "
    "a heavy swinging chain), MeshODENet, MGN and Implicit-Energy (its dihedral bending term, "
    "docs/ENERGY.md), quick preset, and the case's solver at the sampling interval",
    _both("plate_hanging", "quick")
    # the one-step loss's exact gradient: its fixed-matrix surrogate is no descent direction
    # on this case; the MLPs' inputs saturating beyond the training range: without it the
    # energies after the first epoch soften where an edge is compressed beyond the data and
    # fail Newton; Newmark with gamma 0.75: backward Euler's first step from rest moves twice
    # the truth, the trapezoid (gamma 1/2) rings on the learned stiff modes; a rollout's
    # interval whose Newton fails (near-singular at the clamp) is retried as halves
    # (docs/ENERGY.md, "Bending")
    + (RunSpec("plate_hanging", "implicit_energy", "quick",
               overrides=("model.exact_loss_gradient=true", "model.clamp_q=true",
                          "model.integrator=newmark", "model.newmark_gamma=0.75",
                          "model.max_halvings=4")),)
    + _solver("plate_hanging"), compare_rtol=0.05))
register_suite(Suite(
    "integrators", "MeshODENet on rod_falling (quick preset) with euler / midpoint / rk4 / "
    "dopri5 (direct gradients), rk4 with adjoint and checkpointed gradients, and the implicit "
    "backward_euler / sdirk2 (implicit gradients; an epoch of each 5-7 times rk4's)",
    tuple(RunSpec("rod_falling", "meshodenet", "quick", integrator=i, grad_mode="direct")
          for i in ("euler", "midpoint", "rk4", "dopri5", "backward_euler", "sdirk2"))
    + (RunSpec("rod_falling", "meshodenet", "quick", integrator="rk4", grad_mode="adjoint"),
       RunSpec("rod_falling", "meshodenet", "quick", integrator="rk4",
               grad_mode="checkpoint"))))


#: The learning-curve runs' overrides of the ``quick`` preset (docs/SUITE.md, "Learning
#: curves"): budget checkpoints at about 2, 5, 15 and 45 min of one core and the end at
#: 2 h (``max_cpu_s``: a run fits in one working session of the shared machine, whose disk a
#: later session may not find), epochs beyond reach so that the CPU budget ends training. The learning
#: rate keeps the quick preset's fixed-epoch milestones: a schedule that does not depend on the
#: final budget, under which each curve run's first epochs are its quick run's. Every epoch is
#: validated (``quick`` skips some where it is cheaper to), so that each budget checkpoint is
#: the best validated model up to its budget.
CURVE_BUDGETS_S = (120, 300, 900, 2700)
CURVE_MAX_CPU_S = 7200
CURVE_OVERRIDES = ("train.epochs=1000000",
                   "train.budgets_s=" + ",".join(str(b) for b in CURVE_BUDGETS_S),
                   f"train.max_cpu_s={CURVE_MAX_CPU_S}", "train.val_every=1")

register_suite(Suite(
    "curves", "learning curves: every learned (case, model) of quick, seed 0, trained to 2 h of one "
    "core with best-so-far checkpoints at 2, 5, 15, 45 and 120 min of CPU time (16 h of "
    "one core in all; `meshbench curves` evaluates them)",
    tuple(replace(s, overrides=CURVE_OVERRIDES, tag="curves")
          for s in _quick_models("rod_falling", "quick") + _quick_models("plate_cantilever", "quick"))))
