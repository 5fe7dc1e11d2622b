"""Cache keys (issue 28): one exact, prefix-free encoding of a stage's inputs (the artifact
store's), a scenario keyed on its fields rather than its file, and a deeply frozen ``Scenario``
that ``pipeline.synthesize`` takes as given (``dataclasses.replace(scenario, clearance=...)``)."""

from __future__ import annotations

import dataclasses
import enum
import pickle
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import sympy
from shapely import affinity

import pipeline
from pipeline.io.artifacts import inputs_key
from pipeline.model.dynamics import Dynamics
from pipeline.model.scenario import Scenario, load_scenario
from pipeline.model.scenario_data import LOCATIONS
from pipeline.runtime.run_inputs import NOT_NUMERICAL, scenario_key

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def scenario() -> Scenario:
    return load_scenario("double_integrator", check_demos=False)


# --- the encoding -------------------------------------------------------------------------------


def test_same_bytes_in_another_shape_or_dtype_is_another_key():
    a = np.arange(6.0)
    arrays = [
        a.reshape(2, 3),
        a.reshape(3, 2),
        a.reshape(6, 1),
        np.arange(6).reshape(6, 1),  # the same values as integers
        a.view(np.int64).reshape(6, 1),  # the same bytes as integers
        a.astype(np.float32).reshape(2, 3),
    ]
    keys = {inputs_key(x) for x in arrays}
    assert len(keys) == len(arrays)
    assert inputs_key(a.reshape(2, 3)) == inputs_key(np.arange(6.0).reshape(2, 3))


def test_a_long_array_inside_a_container_is_hashed_whole():
    a = np.zeros(2000)
    b = a.copy()
    b[1000] = 1.0  # NumPy's printed summary ("...") of the two is the same
    assert str(a) == str(b)
    for wrap in (lambda x: [x], lambda x: {"u": x}, lambda x: (1, [x])):
        assert inputs_key(wrap(a)) != inputs_key(wrap(b))
        assert inputs_key(wrap(a)) == inputs_key(wrap(a.copy()))


def test_parts_do_not_run_into_each_other():
    assert inputs_key("ab", "c") != inputs_key("a", "bc")
    # two arrays whose bytes, joined by one separator byte, are the same stream
    second = np.frombuffer(bytes([1, 2, 3, 4, 5, 6, 7, 0]), dtype=np.float64)
    moved = np.frombuffer(bytes([0, 1, 2, 3, 4, 5, 6, 7]), dtype=np.float64)
    one, three = np.array([1.0]), np.array([3.0])
    assert inputs_key(one, np.concatenate([second, three])) != inputs_key(
        np.concatenate([one, moved]), three
    )
    assert inputs_key(["a"], "b") != inputs_key(["a", "b"])


def test_types_are_part_of_the_key():
    values = [1, 1.0, True, "1", np.float64(1.0), np.float32(1.0), np.int64(1), (1,), [1], None]
    assert len({inputs_key(v) for v in values}) == len(values)
    assert inputs_key(-0.0) != inputs_key(0.0)
    assert inputs_key(0.1) != inputs_key(0.1 + 2**-56) and 0.1 + 2**-56 != 0.1
    assert inputs_key({"a": 1, "b": 2}) != inputs_key({"b": 2, "a": 1})  # order is data
    assert inputs_key(Path("a/b")) != inputs_key("a/b")


class Colour(enum.Enum):
    RED = 1


class Level(enum.IntEnum):
    ONE = 1


@pytest.mark.parametrize(
    ("value", "named"),
    [
        ({1, 2}, "set"),
        (object(), "object"),
        (Colour.RED, "Colour"),
        (Level.ONE, "Level"),  # an int subclass: not the int 1
        (sympy.Symbol("x"), "Symbol"),
        (np.array(["a"]), "<U1"),
        (np.array([1 + 2j]), "complex"),
        (np.array([None]), "object array"),
        ([np.zeros(3), b"bytes"], "bytes"),
    ],
)
def test_a_value_without_an_exact_encoding_is_refused(value, named):
    with pytest.raises(TypeError, match=named):
        inputs_key("stage", value)


# --- the scenario's key: its fields, not its file -----------------------------------------------


def _other(value: Any, name: str) -> Any:
    """Another value of a scenario field, of the same type."""
    if isinstance(value, float):
        return value * (1 + 1e-12) if value else 1e-12  # 0.0 (a continuous feedback_period)
    if isinstance(value, str):
        return value + "x"
    if isinstance(value, np.ndarray):
        changed = value.copy()
        changed.flat[-1] += 1e-9
        return changed
    if name == "position_index":
        return value[::-1]
    if name == "goal":
        return affinity.translate(value, 1e-9)
    if name == "unsafe":
        return {k: affinity.scale(v, 1.0 + 1e-12) for k, v in value.items()}
    if name in ("goal_bounds", "operating_region", "state_bounds"):
        return {**value, "vx": (-3.0, 3.0 + 1e-12)}
    if name in ("units", "labels"):
        return {**value, "x": "other"}
    if name == "dynamics":
        x, y, vx, vy = value.state_symbols
        ux, uy = value.input_symbols
        f = (vx, vy, ux, uy - sympy.Float(1e-12))
        return Dynamics.from_expressions(value.state_symbols, value.input_symbols, f)
    if name == "demos":
        first = value[0]
        return (dataclasses.replace(first, us=_other(first.us, "us")), *value[1:])
    if name == "feedback":
        return value.model_copy(update={"rate": value.rate * (1 + 1e-12)})
    if name == "spec":
        return value.model_copy(update={"description": "another description"})
    if name == "uncertainty":  # a gust of 1e-12 on the first state
        return dataclasses.replace(
            value, disturbance=value.disturbance + np.eye(len(value.disturbance))[0] * 1e-12
        )
    raise AssertionError(f"no other value for field {name}: add one (a new Scenario field)")


def test_every_field_of_a_scenario_is_in_its_key_but_where_it_was_read_from(scenario):
    key = scenario_key(scenario)
    for field in dataclasses.fields(Scenario):
        if field.name in LOCATIONS:
            continue
        changed = dataclasses.replace(
            scenario, **{field.name: _other(getattr(scenario, field.name), field.name)}
        )
        assert scenario_key(changed) != key, field.name
    moved = dataclasses.replace(scenario, path=Path("/elsewhere/scenario.yaml"), source_hash="0")
    assert scenario_key(moved) == key  # a copied folder, a comment in the file: same values


def test_a_replaced_clearance_is_another_key_for_the_numerical_stages(scenario):
    changed = dataclasses.replace(scenario, clearance=0.25)
    assert scenario_key(changed, *NOT_NUMERICAL) != scenario_key(scenario, *NOT_NUMERICAL)
    described = dataclasses.replace(
        scenario, spec=scenario.spec.model_copy(update={"description": "other"})
    )
    assert scenario_key(described, *NOT_NUMERICAL) == scenario_key(scenario, *NOT_NUMERICAL)
    assert scenario_key(described) != scenario_key(scenario)  # the report's key
    with pytest.raises(ValueError, match="descripton"):
        scenario_key(scenario, "descripton")


def test_a_field_without_an_exact_encoding_is_named(scenario):
    odd = dataclasses.replace(scenario, units={"x": object()})
    with pytest.raises(TypeError, match=r"scenario field units\.x: cannot key a object"):
        scenario_key(odd)


# --- deep immutability --------------------------------------------------------------------------


def test_a_scenario_cannot_be_changed_in_place(scenario):
    with pytest.raises(ValueError, match="read-only"):
        scenario.init_lower[0] = 99.0
    for array in (scenario.input_upper, scenario.demos[0].us, scenario.dynamics.sparsity_x):
        with pytest.raises(ValueError, match="read-only"):
            array[0] = 0
    for mapping in (scenario.operating_region, scenario.unsafe, scenario.units):
        with pytest.raises(TypeError, match="does not support item assignment"):
            mapping["x"] = (0.0, 1.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        scenario.clearance = 0.1  # type: ignore[misc]


def test_replace_copies_and_freezes_what_it_is_given(scenario):
    lower, region = np.zeros(4), {"ux": (-1.0, 1.0)}
    changed = dataclasses.replace(scenario, init_lower=lower, operating_region=region)
    lower[0], region["uy"] = 5.0, (0.0, 1.0)  # the caller's objects, not the scenario's
    assert changed.init_lower[0] == 0.0 and dict(changed.operating_region) == {"ux": (-1.0, 1.0)}
    assert not changed.init_lower.flags.writeable
    again = pickle.loads(pickle.dumps(changed))  # as an executor's worker receives it
    assert scenario_key(again) == scenario_key(changed)
    assert not again.init_lower.flags.writeable and not again.demos[0].us.flags.writeable
    with pytest.raises(TypeError):
        again.operating_region["ux"] = (0.0, 0.0)  # type: ignore[index]


def test_the_workers_run_the_scenario_they_are_given(scenario):
    """A worker process gets the (pickled) scenario, not the file's: a sweep over
    ``dataclasses.replace`` optimizes each replaced scenario."""
    from stages.feedback import design_feedback
    from stages.optimize import ConstraintMargins, OptimizeOptions, optimize, optimize_demo

    class InAnotherProcess:  # what ProcessExecutor does to each task, without the processes
        def map(self, function, items, done=None):
            return [function(pickle.loads(pickle.dumps(item))) for item in items]

    feedback = design_feedback(scenario)
    margins = ConstraintMargins.of_tube(
        feedback.certified_tube, feedback.required_radius(scenario.clearance)
    )
    options = OptimizeOptions()
    slower = dataclasses.replace(scenario, input_upper=0.9 * scenario.input_upper)
    here = optimize_demo(slower, 0, margins, options)
    there = optimize(slower, margins, options, demos=[0], executor=InAnotherProcess())
    assert np.array_equal(there.trajectories[0].u, here.u)
    assert not np.array_equal(here.u, optimize_demo(scenario, 0, margins, options).u)


# --- done when: a replaced scenario into a folder holding the unchanged scenario's run ----------


@pytest.mark.slow
@pytest.mark.xdist_group("synthesis-double_integrator")  # reads the session's run
def test_a_replaced_scenario_into_an_old_run_folder_is_a_fresh_run(synthesis_run, tmp_path):
    session = synthesis_run("double_integrator")
    assert session.result.exit_code == 0
    changed = dataclasses.replace(load_scenario("double_integrator"), clearance=0.4)
    old = tmp_path / "old"
    shutil.copytree(session.out, old)  # the unchanged scenario's run (clearance 0.5)
    reused = pipeline.synthesize(changed, out=old, samples=session.samples)
    fresh = pipeline.synthesize(changed, out=tmp_path / "fresh", samples=session.samples)
    assert reused.exit_code == fresh.exit_code == 0
    shipped = (old / "controller.json").read_bytes()
    assert shipped == (tmp_path / "fresh" / "controller.json").read_bytes()
    assert shipped != (session.out / "controller.json").read_bytes()  # the clearance matters
