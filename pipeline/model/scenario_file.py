"""The scenario file, found and read: names and paths resolved, YAML syntax and the schema
checked (layers 1 and 2 of ``pipeline.model.scenario``).

It imports no numerics (no SymPy, SciPy or Shapely): ``python -m pipeline synthesize`` calls
``check_scenario_file`` first, so that a mistake in the file's syntax or fields is reported in
well under a second, before the ~2 s of imports that building the scenario needs.
"""

from __future__ import annotations

import difflib
import os
from pathlib import Path

import pydantic

from pipeline.io.errors import ScenarioError
from pipeline.model.safe_yaml import load_yaml
from pipeline.model.schema import ScenarioSpec, field_names


def _shipped_scenarios() -> Path:
    """The scenarios shipped with the package: ``pipeline/scenarios`` when installed (package
    data, see ``pyproject.toml``), the repository's ``scenarios/`` in a source checkout."""
    package = Path(__file__).resolve().parents[1]
    installed = package / "scenarios"
    return installed if installed.is_dir() else package.parent / "scenarios"


# A scenario name is looked up in ./scenarios (the user's own), then here; a path works anywhere.
SCENARIOS_ROOT = Path(os.environ.get("SAFETY_SCENARIOS", _shipped_scenarios()))
LOCAL_SCENARIOS = "scenarios"


def available_scenarios(root: Path = SCENARIOS_ROOT) -> list[str]:
    """Names of the scenario folders under ``root`` that hold a ``scenario.yaml``."""
    return sorted(p.parent.name for p in Path(root).glob("*/scenario.yaml"))


def resolve_scenario_path(name_or_path: str | Path, root: Path | None = None) -> Path:
    """A scenario name, folder or YAML path -> the YAML path.

    A path (file, or folder holding ``scenario.yaml``) is used as is. A name is looked up in
    ``./scenarios/NAME`` under the current directory, then in ``root`` (default: the shipped
    scenarios, ``SCENARIOS_ROOT``); an unknown name lists the known ones.
    """
    candidate = Path(name_or_path)
    # anything there but a folder is read (a FIFO, device or link loop is refused in one line)
    if os.path.lexists(candidate) and not candidate.is_dir():
        return candidate
    if os.path.lexists(candidate / "scenario.yaml"):
        return candidate / "scenario.yaml"
    roots = [Path.cwd() / LOCAL_SCENARIOS, Path(root if root is not None else SCENARIOS_ROOT)]
    for folder in roots:
        if (folder / str(name_or_path) / "scenario.yaml").is_file():
            return folder / str(name_or_path) / "scenario.yaml"
    known = ", ".join(sorted({name for folder in roots for name in available_scenarios(folder)}))
    raise ScenarioError(
        f"unknown scenario '{name_or_path}'",
        expected=f"one of: {known or 'none'} (or a path to a scenario folder or YAML file)",
    )


def parse_spec(path: Path) -> ScenarioSpec:
    """The scenario file at ``path`` as data checked against the schema (layers 1 and 2 of
    ``pipeline.model.scenario``); a ``ScenarioError`` naming the first mistake."""
    data = load_yaml(path)  # plain data only; size, aliases and duplicate keys checked
    if not isinstance(data, dict):
        raise ScenarioError(
            "not a mapping",
            file=path,
            found=type(data).__name__,
            expected="a YAML mapping of scenario fields",
        )
    try:
        return ScenarioSpec.model_validate(data)
    except pydantic.ValidationError as error:
        raise _schema_error(path, error) from None


def _schema_error(path: Path, error: pydantic.ValidationError) -> ScenarioError:
    errors = error.errors()
    # A misspelled key gives "missing X" and "unknown Y"; the unknown key is the one to name.
    extra = [e for e in errors if e["type"] == "extra_forbidden"]
    first = extra[0] if extra else errors[0]
    location = ".".join(str(part) for part in first["loc"]) or "(top level)"
    more = len(errors) - 1
    suffix = f" (and {more} more error{'s' if more > 1 else ''})" if more else ""
    kind = first["type"]
    if kind == "missing":
        return ScenarioError(
            f"missing field{suffix}",
            file=path,
            field=location,
            expected="this field (see docs/scenario-file.md)",
        )
    if kind == "extra_forbidden":
        key = str(first["loc"][-1])
        known = field_names(first["loc"][:-1])
        close = difflib.get_close_matches(key, known, n=1, cutoff=0.5)
        hint = f" (did you mean '{close[0]}'?)" if close else ""
        parent = ".".join(str(part) for part in first["loc"][:-1])
        return ScenarioError(
            f"unknown field '{key}'{hint}{suffix}",
            file=path,
            field=location,
            expected=f"one of the fields of {parent or 'the scenario'}: {', '.join(known)}",
        )
    message = first["msg"].removeprefix("Value error, ").removeprefix("Input should be ")
    return ScenarioError(
        f"invalid value{suffix}",
        file=path,
        field=location,
        found=first.get("input"),
        expected=message[:1].lower() + message[1:],
    )


def check_scenario_file(name_or_path: str | Path) -> None:
    """Raise the ``ScenarioError`` of a scenario that cannot be found, or whose YAML or schema is
    wrong; cheap (no numerics imported). ``load_scenario`` checks all of this again, and more."""
    parse_spec(resolve_scenario_path(name_or_path))
