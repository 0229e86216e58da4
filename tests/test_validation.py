"""Bad input raises errors that name the field and the value."""

import dataclasses
import math

import pytest

from benchmarks.suite.registry import CASES, RegistryError, get_case
from groundtruth.cases import RodCase
from groundtruth.implicit import NewtonSettings


@pytest.mark.parametrize("youngs", [-1e9, 0.0, math.nan, math.inf, "abc"])
def test_bad_modulus(youngs):
    with pytest.raises(ValueError, match=r"youngs .*" + (r"'abc'" if youngs == "abc" else "")):
        RodCase().system(youngs)


@pytest.mark.parametrize("field,value", [
    ("n_nodes", 2), ("n_nodes", 2.5), ("length", -0.1), ("r0", math.nan), ("dt", 0.2),
    ("t_end", 0.15), ("youngs_train", (2e9, 1e9)), ("youngs_test", (-1.0, 1e9)),
    ("n_train", -1), ("lumping", "blob"), ("clamped_nodes", (0, 99)), ("viscosity", -1.0),
    ("id", "Rod Falling"),
])
def test_bad_case_fields_are_named(field, value):
    with pytest.raises(ValueError, match=rf"RodCase\.{field}.*{repr(value)[:6].replace('(', '.')}"):
        dataclasses.replace(RodCase(), **{field: value})


def test_unknown_case_lists_valid_ids():
    with pytest.raises(RegistryError, match=r"unknown case id 'rod_flaling'; valid ids: .*rod_falling"):
        get_case("rod_flaling")


def test_bad_solver_settings():
    with pytest.raises(ValueError, match=r"NewtonSettings\.dt .* -0\.1"):
        NewtonSettings(dt=-0.1)


def test_static_solve_needs_a_clamp():
    with pytest.raises(ValueError, match="no clamped node"):
        RodCase().solve_static(1e9)


@pytest.mark.parametrize("case_id", sorted(CASES))
def test_every_registered_case_is_consistent(case_id):
    case = CASES[case_id]
    assert case.id == case_id
    edges, cells, node_type = case.mesh()
    rest = case.rest_positions()
    assert rest.shape == (node_type.shape[0], 3) and edges.shape[1] == 2 and cells.shape[1] == 3
    assert case.t_save()[-1] == pytest.approx(case.t_end) and len(case.t_save()) == case.n_frames
    assert len(case.hash()) == 64 and case.hash() == dataclasses.replace(case).hash()
    s = case.system(case.reference_youngs)
    q0, v0 = case.initial_state()
    assert s.gradient(q0.ravel()).shape == (q0.size,)
