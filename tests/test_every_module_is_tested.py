"""Every module of ``pipeline/`` and ``stages/`` is imported by a test that exercises it, or is
named below with the test that exercises it through its caller (a static scan of the tests'
imports, well under a second). A new module without a test fails here; so does an entry below
that a direct import has made unnecessary, or that names a test that no longer exists."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("pipeline", "stages")

# module -> the test that runs it through the module that imports it
COVERED_THROUGH_CALLER = {
    "pipeline.__main__": (
        "tests/test_hostile_inputs.py::test_alias_bomb_exits_2_from_the_command_line"
    ),
    "pipeline.demonstrations.recorder.commands": "tests/test_recorder.py::test_cli_errors_exit_2",
    "pipeline.model.scenario_file": (
        "tests/test_api.py::test_a_scenario_name_is_looked_up_in_the_current_directory_first"
    ),
    "pipeline.numerics.optimize.adjoint": (
        "tests/test_gradient.py::test_gradient_matches_central_differences"
    ),
    "pipeline.numerics.closed_loop.worst_case": (
        "tests/stages/test_uncertain_montecarlo.py::"
        "test_a_gust_larger_than_the_controller_holds_fails_counted_runs"
    ),
    "pipeline.numerics.closed_loop.flight": (
        "tests/test_flight.py::test_a_covered_start_flies_into_goal_and_never_into_unsafe"
    ),
    # numba templates, compiled by pipeline.numerics.kernels.compiled
    "pipeline.numerics.kernels.loops": (
        "tests/test_kernel_cache.py::test_two_dynamics_compile_their_loops_but_share_the_dynamics_free_functions"
    ),
    # the report's parts, written by stages.report for the session's runs
    "pipeline.reporting.certificates": (
        "tests/stages/test_report.py::test_html_holds_the_headline_numbers_of_summary_json"
    ),
    "pipeline.reporting.html": (
        "tests/stages/test_report.py::test_html_holds_the_headline_numbers_of_summary_json"
    ),
    "pipeline.reporting.loop_figures": (
        "tests/stages/test_report.py::test_html_holds_the_headline_numbers_of_summary_json"
    ),
    "pipeline.reporting.plotting": (
        "tests/stages/test_report.py::test_html_holds_the_headline_numbers_of_summary_json"
    ),
    "pipeline.reporting.stage_sections": (
        "tests/stages/test_report.py::test_html_holds_the_headline_numbers_of_summary_json"
    ),
    # the funnel certificate's entry and its stages, run by every funnel scenario's synthesis
    # (quadrotor_hill's among them); their parts are tested directly (targets, rounds)
    "stages.certificates.funnel": (
        "tests/test_end_to_end.py::test_synthesis_certifies_and_validates"
    ),
    "stages.certificates.funnel_run": (
        "tests/test_end_to_end.py::test_synthesis_certifies_and_validates"
    ),
    # the LMI program of one funnel design, assembled by synthesize_funnel (its solution is
    # checked against a known answer there)
    "pipeline.numerics.funnel.program": (
        "tests/test_funnel.py::test_double_integrator_funnel_is_exact"
    ),
    # a file's references re-simulated and their interpolation measured, by certify
    "pipeline.numerics.verify.reference": (
        "tests/stages/test_certify.py::test_the_tracked_reference_is_measured_not_trusted"
    ),
}

DOTTED = re.compile(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)+")


def modules() -> set[str]:
    """The dotted names of the modules (a package by its ``__init__``'s name)."""
    found = set()
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            parts = path.relative_to(ROOT).with_suffix("").parts
            found.add(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return found


def named_by_tests() -> set[str]:
    """What the tests import (``from a.b import c`` names ``a.b`` and ``a.b.c``), and the dotted
    names they pass as strings (``monkeypatch.setattr("a.b.f", ...)``); not this file's."""
    names: set[str] = set()
    for path in (ROOT / "tests").rglob("*.py"):
        if path.resolve() == Path(__file__).resolve():
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                names.add(node.module)
                names.update(f"{node.module}.{alias.name}" for alias in node.names)
            elif isinstance(node, ast.Constant) and isinstance(node.value, str):
                if DOTTED.fullmatch(node.value):
                    names.add(node.value)
    return names


def is_named(module: str, names: set[str]) -> bool:
    """Importing ``a.b.c`` runs ``a`` and ``a.b`` too."""
    return any(name == module or name.startswith(module + ".") for name in names)


def test_every_module_is_imported_by_a_test_or_covered_through_its_caller():
    names = named_by_tests()
    untested = sorted(m for m in modules() if not is_named(m, names))
    missing = [m for m in untested if m not in COVERED_THROUGH_CALLER]
    assert not missing, (
        f"modules no test imports: {missing}; add a test that imports and exercises each, or "
        "name the test that runs it through its caller in COVERED_THROUGH_CALLER"
    )
    stale = sorted(set(COVERED_THROUGH_CALLER) - set(untested))
    assert not stale, (
        f"imported by a test now, or removed: drop {stale} from COVERED_THROUGH_CALLER"
    )


def test_the_tests_named_for_the_callers_exist():
    for module, test in COVERED_THROUGH_CALLER.items():
        file, name = test.split("::")
        assert re.search(rf"^def {name}\(", (ROOT / file).read_text(), re.M), (module, test)
