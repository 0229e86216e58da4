"""The glue asks the registries: one error type for every unknown id, and a run's integrator /
gradient mode checked against its model's configuration, whatever the model."""

import pytest

from benchmarks.suite.registry import RegistryError, get_case
from benchmarks.suite.suites import RunSpec, get_suite

pytest.importorskip("torch")


def test_one_error_type_for_every_registry():
    from meshodenet.registry import get_model_spec

    for lookup, kind in ((get_case, "case"), (get_model_spec, "model"),
                         (get_suite, "suite")):
        with pytest.raises(RegistryError, match=f"unknown {kind} id 'nope'; valid ids: "):
            lookup("nope")


@pytest.mark.parametrize("model", ["meshodenet", "mgn", "meshodenet_imex", "mgn_unrolled"])
def test_integrator_only_for_a_model_whose_configuration_has_one(model):
    import dataclasses

    from benchmarks.suite.runner import check_runs
    from meshodenet.registry import get_model_spec

    fields = {f.name for f in dataclasses.fields(get_model_spec(model).config_cls)}
    spec = RunSpec("rod_cantilever", model, "smoke", integrator="euler", grad_mode="direct")
    if {"integrator", "grad_mode"} <= fields:
        check_runs([spec])
    else:
        with pytest.raises(ValueError, match=f"integrator='euler' but model '{model}' has no "
                                             "integrator"):
            check_runs([spec])
    check_runs([RunSpec("rod_cantilever", model, "smoke")])
    with pytest.raises(RegistryError, match="unknown model id 'nope'"):
        check_runs([RunSpec("rod_cantilever", "nope", "smoke")])
