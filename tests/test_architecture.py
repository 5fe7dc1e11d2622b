"""The architecture is enforced: the tree shows the layers, the controller loads NumPy and the
standard library only, ``import pipeline`` is lazy. The import contracts in ``pyproject.toml``
(layers, the controller imports nothing of the package, independent stages) are checked by
import-linter in ``make lint``, which CI runs beside ``make test``; a test here checks that
wiring."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LAYERED = ("io", "model", "numerics", "results", "reporting", "runtime", "demonstrations")


def test_ci_runs_the_linters_that_check_the_contracts_and_types():
    recipe = re.search(r"^lint:.*\n((?:\t.*\n)+)", (ROOT / "Makefile").read_text(), re.M)
    assert recipe is not None, "no lint target in the Makefile"
    for tool in ("ruff check", "ruff format --check", "lint-imports", "mypy"):
        assert tool in recipe.group(1), tool
    ci = (ROOT / ".ci" / "run").read_text()
    assert re.search(r"^make\b.*\blint\b", ci, re.M) and re.search(r"^make\b.*\btest\b", ci, re.M)


def test_the_tree_shows_the_layers():
    """Every module of ``pipeline/`` lives in a layer package, except the controller and the
    entry points."""
    flat = {p.name for p in (ROOT / "pipeline").glob("*.py")}
    assert flat == {"__init__.py", "__main__.py", "controller.py"}
    for layer in LAYERED:
        assert (ROOT / "pipeline" / layer / "__init__.py").is_file(), layer


def test_controller_module_loads_numpy_and_the_standard_library_only():
    code = (
        "import sys; before = set(sys.modules); import pipeline.controller; "
        "print('\\n'.join(sorted({m.split('.')[0] for m in set(sys.modules) - before})))"
    )
    run = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True
    )
    loaded = set(run.stdout.split())
    third_party = loaded - set(sys.stdlib_module_names) - {"pipeline", "numpy"}
    assert not third_party, f"pipeline.controller pulled in {sorted(third_party)}"
    assert "pipeline" in loaded and "numpy" in loaded


def test_package_import_is_lazy_and_names_resolve():
    code = (
        "import sys, pipeline; heavy = {'sympy', 'scipy', 'pydantic', 'shapely', 'cvxpy'}; "
        "assert not heavy & set(sys.modules), sorted(heavy & set(sys.modules)); "
        "from pipeline import load_scenario, Scenario, ScenarioError, UserError; "
        "assert callable(load_scenario)"
    )
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True, timeout=120)


def test_a_scenario_mistake_is_reported_before_the_stages_are_imported():
    """``synthesize`` loads the scenario first: a typo costs the scenario module's imports, not
    the numerics' and the stages' (~2 s more)."""
    code = (
        "import sys, pipeline\n"
        "try:\n    pipeline.synthesize('no_such_scenario')\n"
        "except pipeline.ScenarioError as error:\n    assert 'unknown scenario' in str(error)\n"
        "else:\n    raise AssertionError('no error')\n"
        "heavy = {'pipeline.runtime.orchestrator', 'stages.optimize', 'cvxpy', 'matplotlib'}\n"
        "assert not heavy & set(sys.modules), sorted(heavy & set(sys.modules))\n"
    )
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True, timeout=120)
