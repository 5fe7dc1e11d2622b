"""Property: whatever is done to a valid scenario file, loading it either succeeds or raises a
``ScenarioError`` (exit 2, one line), and never hangs (each example runs under a time limit).

The mutations are the mistakes people make: a field dropped, a value of the wrong type, a key
renamed (misspelled), an interval's bounds swapped; several may be combined.
"""

from __future__ import annotations

import copy
import tempfile
from pathlib import Path
from typing import Any

import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline import ScenarioError, load_scenario
from pipeline.io.errors import UserError
from tests.helpers.scenario_files import SCENARIO_YAML, STRAIGHT
from tests.helpers.timing import time_limit

VALID = yaml.safe_load(SCENARIO_YAML)
EXAMPLE_TIME_LIMIT = 20  # s; a valid load of this fixture takes well under a second

Path_ = tuple[str | int, ...]

ODD_VALUES = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(10**30), max_value=10**30),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=20),
    st.lists(st.floats(-10, 10), max_size=4),
    st.dictionaries(st.text(max_size=5), st.integers(), max_size=3),
)


def paths(data: Any, prefix: Path_ = ()) -> list[Path_]:
    """Every path to a value inside ``data`` (dict keys and list indices), outermost first."""
    found: list[Path_] = []
    items = (
        data.items()
        if isinstance(data, dict)
        else enumerate(data)
        if isinstance(data, list)
        else ()
    )
    for key, value in items:
        found.append((*prefix, key))
        found.extend(paths(value, (*prefix, key)))
    return found


def parent_of(data: Any, path: Path_) -> Any:
    for key in path[:-1]:
        data = data[key]
    return data


@st.composite
def mutated(draw: st.DrawFn) -> Any:
    data = copy.deepcopy(VALID)
    for _ in range(draw(st.integers(1, 3))):
        where = paths(data)
        if not where:
            break
        path = draw(st.sampled_from(where))
        parent, key = parent_of(data, path), path[-1]
        kind = draw(st.sampled_from(["drop", "retype", "rename", "swap"]))
        if kind == "drop":
            del parent[key]
        elif kind == "retype":
            parent[key] = draw(ODD_VALUES)
        elif kind == "rename" and isinstance(parent, dict):
            name = str(key)
            new = draw(
                st.sampled_from(
                    [name[:-1], name + "s", name.upper(), name[1:] + name[:1], name + "_"]
                )
            )
            parent[new or "x"] = parent.pop(key)
        elif kind == "swap" and isinstance(parent[key], list) and len(parent[key]) >= 2:
            parent[key] = parent[key][::-1]
    return data


@settings(
    max_examples=80,
    deadline=None,  # time_limit below bounds each example, including a hang
    suppress_health_check=[HealthCheck.too_slow],
)
@given(mutated())
def test_mutated_scenarios_load_or_raise_scenario_error(data: Any) -> None:
    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder)
        (root / "demos").mkdir()
        (root / "demos" / "straight.csv").write_text(STRAIGHT)
        path = root / "scenario.yaml"
        path.write_text(yaml.safe_dump(data, sort_keys=False))
        try:
            with time_limit(EXAMPLE_TIME_LIMIT):
                load_scenario(path)
        except ScenarioError as error:
            message = str(error)
            assert isinstance(error, UserError) and error.exit_code == 2
            assert message.startswith(str(root)) and "\n" not in message
