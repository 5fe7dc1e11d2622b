"""Every declared stage conforms (issue 28; scikit-learn's ``parametrize_with_checks`` is the
model): its inputs type is frozen and keyword-only, its result is deeply frozen and
round-trips through the artifact store, its key changes when any input field (or declared
scenario field) changes and not otherwise, and it reads no field of the scenario it does not
declare (run on a scenario that refuses those: ``tests.helpers.stage_inputs.guarded``).

Each stage runs once, on double_integrator with two demos (``stage_cases``); the report stage
is checked on its key and inputs (it is run by every synthesis test)."""

from __future__ import annotations

import dataclasses
import inspect
import typing
from collections.abc import Iterator, Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
import pytest
from shapely import affinity

from pipeline.io.artifacts import read_stored, save_result
from pipeline.model.scenario import Scenario, load_scenario
from pipeline.results.base import Result
from pipeline.results.stage import FileInput, Stage, StageInputs
from pipeline.runtime.registry import RESULT_TYPES, STAGES
from pipeline.runtime.runner import stage_key
from stages.report import REPORT, ReportInputs
from tests.helpers.stage_inputs import StageCase, small_scenario, stage_cases

# one worker runs every stage once (``cases``, about 12 s of CPU) rather than each worker
pytestmark = pytest.mark.xdist_group("stage-conformance")

RUN = [stage for stage in STAGES if stage is not REPORT]
DONOR = "unicycle_slalom"  # another scenario: other values for every field


def _id(stage: Stage[Any, Any]) -> str:
    return f"{stage.name}:{stage.inputs.__name__}"


@pytest.fixture(scope="module")
def cases(tmp_path_factory: pytest.TempPathFactory) -> dict[str, StageCase]:
    found: dict[str, StageCase] = {}
    for case in stage_cases(tmp_path_factory.mktemp("stages")):
        found.setdefault(_id(case.stage), case)  # the first run of each (coverage runs twice)
    return found


@pytest.fixture(scope="module")
def donor() -> Scenario:
    return load_scenario(DONOR, check_demos=False)


def test_every_declared_stage_is_checked(cases):
    assert {_id(stage) for stage in RUN} == set(cases)
    assert len(STAGES) >= 12 and REPORT in STAGES


@pytest.mark.parametrize("stage", STAGES, ids=_id)
def test_the_declaration_is_well_formed(stage: Stage[Any, Any]):
    inputs = stage.inputs
    assert issubclass(inputs, StageInputs) and dataclasses.is_dataclass(inputs)
    params = inputs.__dataclass_params__  # type: ignore[attr-defined]
    assert params.frozen and all(f.kw_only for f in dataclasses.fields(inputs))
    fields = {f.name for f in dataclasses.fields(Scenario)}
    assert set(inputs.scenario_fields) <= fields, inputs.scenario_fields
    assert "scenario" in {f.name for f in dataclasses.fields(inputs)}
    parameters = list(inspect.signature(stage.function).parameters.values())
    assert all(p.kind is p.KEYWORD_ONLY for p in parameters[1:])  # context only
    assert issubclass(stage.result, Result) and stage.result in RESULT_TYPES.values()


# --- the result --------------------------------------------------------------------------


def _mutable_parts(value: Any, where: str = "result") -> Iterator[str]:
    """Where ``value`` can be changed in place."""
    if isinstance(value, np.ndarray):
        if value.flags.writeable or value.base is not None:
            yield f"{where}: writable array"
    elif isinstance(value, Mapping):
        if not isinstance(value, MappingProxyType):
            yield f"{where}: {type(value).__name__}"
        for k, v in value.items():
            yield from _mutable_parts(v, f"{where}[{k!r}]")
    elif isinstance(value, (list, set, dict, bytearray)):
        yield f"{where}: {type(value).__name__}"
    elif isinstance(value, tuple):
        for i, v in enumerate(value):
            yield from _mutable_parts(v, f"{where}[{i}]")
    elif dataclasses.is_dataclass(value) and not isinstance(value, type):
        if not type(value).__dataclass_params__.frozen:  # type: ignore[attr-defined]
            yield f"{where}: a mutable {type(value).__name__}"
        for f in dataclasses.fields(value):
            yield from _mutable_parts(getattr(value, f.name), f"{where}.{f.name}")


@pytest.mark.parametrize("stage", RUN, ids=_id)
def test_the_result_is_deeply_frozen(stage, cases):
    result = cases[_id(stage)].result
    assert not list(_mutable_parts(result))


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and a.dtype == b.dtype and np.array_equal(a, b, True)
    if isinstance(a, Mapping):
        return isinstance(b, Mapping) and list(a) == list(b) and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (tuple, list)):
        return type(a) is type(b) and len(a) == len(b) and all(map(_same, a, b))
    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        names = [f.name for f in dataclasses.fields(a)]
        return type(a) is type(b) and all(_same(getattr(a, n), getattr(b, n)) for n in names)
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (np.isnan(a) and np.isnan(b))
    return type(a) is type(b) and a == b


@pytest.mark.parametrize("stage", RUN, ids=_id)
def test_the_result_round_trips_through_the_artifact_store(stage, cases, tmp_path):
    result = cases[_id(stage)].result
    sha256 = save_result(tmp_path / "stage", "key", result)
    stored = read_stored(tmp_path / "stage", RESULT_TYPES)
    assert stored is not None and stored.key == "key" and stored.sha256 == sha256
    assert _same(result, stored.result)
    assert not list(_mutable_parts(stored.result))


@pytest.mark.parametrize("stage", RUN, ids=_id)
def test_the_stage_reads_no_undeclared_field_of_the_scenario(stage, cases):
    assert cases[_id(stage)].undeclared is None


# --- the key -----------------------------------------------------------------------------


def _other(value: Any) -> Any:
    """Another value of the same kind (each change is one the key must see)."""
    if isinstance(value, np.ndarray):
        changed = np.array(value, dtype=value.dtype, copy=True)
        changed.flat[0] = changed.flat[0] + 1 if changed.size else 0
        return changed if changed.size else np.zeros(1, dtype=value.dtype)
    if isinstance(value, bool):
        return not value
    if isinstance(value, (int, float)):
        return value + 1
    if isinstance(value, str):
        return value + " (other)"
    if isinstance(value, Path):
        return value.with_name("other.json")
    if isinstance(value, FileInput):
        return dataclasses.replace(value, sha256="0" * 64)
    if isinstance(value, tuple):
        return (_other(value[0]), *value[1:]) if value else (0,)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        for f in dataclasses.fields(value):
            try:
                return dataclasses.replace(value, **{f.name: _other(getattr(value, f.name))})
            except (TypeError, ValueError):  # a field its type validates: try the next
                continue
    raise AssertionError(f"no other value for a {type(value).__name__}")


def _other_scenario(scenario: Scenario, name: str, donor: Scenario) -> Scenario:
    """``scenario`` with field ``name`` changed."""
    value = getattr(scenario, name)
    if name == "spec":
        changed: Any = value.model_copy(update={"description": "another description"})
    elif name == "feedback":
        changed = value.model_copy(update={"rate": value.rate * 1.5})
    elif name == "dynamics":
        changed = donor.dynamics
    elif name == "demos":
        changed = value[:1]
    elif name == "position_index":
        changed = value[::-1]
    elif name == "path":
        changed = Path("/elsewhere/scenario.yaml")
    elif name == "uncertainty":
        changed = dataclasses.replace(value, disturbance=value.disturbance + 0.5)
    elif isinstance(value, Mapping):
        changed = {k: _bump(v) for k, v in value.items()} or {scenario.state_names[0]: (0.0, 1.0)}
    else:
        changed = _bump(value)
    return dataclasses.replace(scenario, **{name: changed})


def _bump(value: Any) -> Any:
    """Another value: a number, array or bound moved by 0.5, a polygon moved by 0.5 in X, a
    string extended."""
    if isinstance(value, str):
        return value + "x"
    if isinstance(value, tuple):
        return tuple(v + 0.5 for v in value)
    if isinstance(value, (int, float, np.ndarray)):
        return value + 0.5
    return affinity.translate(value, 0.5, 0.0)


@pytest.mark.parametrize("stage", STAGES, ids=_id)
def test_the_key_changes_with_every_input_and_only_then(stage, cases, donor, tmp_path):
    inputs = _inputs(stage, cases, tmp_path)
    key = stage_key(stage, inputs)
    assert stage_key(stage, dataclasses.replace(inputs)) == key  # a copy: the same key
    for f in dataclasses.fields(inputs):
        if f.name == "scenario":
            continue
        changed = dataclasses.replace(inputs, **{f.name: _other(getattr(inputs, f.name))})
        assert stage_key(stage, changed) != key, f.name
    scenario = inputs.scenario  # type: ignore[attr-defined]
    declared = type(inputs).scenario_fields
    for name in declared:
        changed = dataclasses.replace(inputs, scenario=_other_scenario(scenario, name, donor))
        assert stage_key(stage, changed) != key, f"scenario.{name}"
    for f in dataclasses.fields(Scenario):
        if f.name not in declared:  # what the stage does not read leaves its key alone
            changed = dataclasses.replace(inputs, scenario=_other_scenario(scenario, f.name, donor))
            assert stage_key(stage, changed) == key, f"scenario.{f.name}"


def _inputs(stage: Stage[Any, Any], cases: dict[str, StageCase], folder: Path) -> StageInputs:
    if stage is REPORT:
        path = folder / "controller.json"
        return ReportInputs(
            scenario=small_scenario(),
            results=(("feedback", "0" * 64), ("montecarlo", "1" * 64)),
            controller=FileInput(path=path, sha256="2" * 64),
        )
    return cases[_id(stage)].inputs


def test_a_file_input_is_keyed_by_its_bytes_not_its_place(cases):
    case = cases[_id(next(s for s in STAGES if s.name == "montecarlo"))]
    inputs = case.inputs
    moved = dataclasses.replace(
        inputs,
        controller=dataclasses.replace(inputs.controller, path=Path("/elsewhere/controller.json")),
    )
    assert stage_key(case.stage, moved) == stage_key(case.stage, inputs)


def test_an_array_of_the_same_bytes_in_another_shape_is_another_key(cases):
    case = cases[_id(next(s for s in STAGES if s.name == "coverage"))]
    inputs = case.inputs
    centers = inputs.centers
    reshaped = dataclasses.replace(inputs, centers=centers.reshape(centers.shape[::-1]))
    assert reshaped.centers.tobytes() == centers.tobytes()
    assert stage_key(case.stage, reshaped) != stage_key(case.stage, inputs)


def test_every_certificate_name_has_its_strategy():
    """The scenario's ``certificate`` names, ``--certificate``'s choices (standard library only:
    ``pipeline.numerics.settings``) and the strategies are one list."""
    from pipeline.model.scenario import CertificateName
    from pipeline.numerics.settings import CERTIFICATES as CHOICES
    from stages.certificates import CERTIFICATES

    assert typing.get_args(CertificateName) == CHOICES == tuple(CERTIFICATES)
    assert all(CERTIFICATES[name].name == name for name in CHOICES)


def test_every_result_type_is_deeply_frozen_and_stored_ones_are_registered():
    """Each type in the results layer is a ``Result`` (but the optimizer's options); all but
    the certify check's (never stored: it re-verifies the file on every run) are in the
    artifact store's registry."""
    from pipeline.results import (
        certify,
        controller,
        coverage,
        feedback,
        funnel,
        montecarlo,
        optimize,
        radius,
        report,
        stress,
    )

    modules = (certify, controller, coverage, feedback, funnel, montecarlo, optimize, radius)
    found = [
        cls
        for module in (*modules, report, stress)
        for cls in vars(module).values()
        if isinstance(cls, type) and cls.__module__ == module.__name__
    ]
    scalars_only = optimize.OptimizeOptions  # frozen, of strings and numbers: nothing to freeze
    assert found and all(issubclass(cls, Result) or cls is scalars_only for cls in found)
    stored = [cls for cls in found if cls is not certify.CertificationResult]
    assert all(cls in RESULT_TYPES.values() for cls in stored)
