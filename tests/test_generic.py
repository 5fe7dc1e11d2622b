"""The core is not shaped like any one scenario: ``pipeline/`` and ``stages/`` never name a
shipped scenario's states or inputs.

The rule, checked on the raw text of every ``pipeline/**/*.py`` and ``stages/**/*.py`` (code,
strings, comments and docstrings alike):

1. A state or input name of two or more characters (``theta``, ``vX``, ``u1``, ``psi``,
   ``turn_rate``, ...) never appears as a whole word. Anything vehicle-specific lives with its
   scenario: the dynamics in ``scenario.yaml``, the synthetic pilot's route and steering law in
   ``scenarios/NAME/pilot.py`` (loaded by path).
2. A one-letter name (``x``, ``y``, ``v``, ``X``, ``Y``) is exempt from rule 1: one letters are
   the paper's mathematical symbols, which STYLE.md asks the numerical code to use (``x`` the
   state vector, ``u`` the input, ``X`` the RK4 grid, ``Y = K Q`` in the LMI), so no scenario can
   claim them. What would tie the core to such a name is looking a state up by it, so no name of
   any length may be a string literal used as an index: ``.index("X")``, ``["X"]``.

No allow-list is needed.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from pipeline import available_scenarios, load_scenario

ROOT = Path(__file__).resolve().parents[1]
CORE = ("pipeline", "stages")


def _names() -> dict[str, list[str]]:
    """Every state and input name of the shipped scenarios -> the scenarios that use it."""
    names: dict[str, list[str]] = {}
    for scenario_name in available_scenarios():
        scenario = load_scenario(scenario_name, check_demos=False)
        for name in (*scenario.state_names, *scenario.input_names):
            names.setdefault(name, []).append(scenario_name)
    return names


def _whole_word(name: str) -> re.Pattern[str]:
    return re.compile(rf"(?<![A-Za-z0-9_]){re.escape(name)}(?![A-Za-z0-9_])")


def _lookup(name: str) -> re.Pattern[str]:
    return re.compile(rf"""(?:\.index\(|\[)\s*["']{re.escape(name)}["']\s*[)\]]""")


def violations(text: str, names: dict[str, list[str]]) -> list[str]:
    """``"line N: 'name' (scenarios)"`` for every place ``text`` breaks the rule."""
    found = []
    for number, line in enumerate(text.splitlines(), start=1):
        for name, scenarios in names.items():
            if (len(name) > 1 and _whole_word(name).search(line)) or _lookup(name).search(line):
                found.append(f"line {number}: '{name}' ({', '.join(scenarios)}): {line.strip()}")
    return found


def test_every_shipped_scenario_is_checked():
    names = _names()
    assert {"quadrotor_hill_flythrough", "double_integrator", "unicycle_slalom"} <= set(
        available_scenarios()
    )
    assert {"theta", "vX", "u1", "psi", "turn_rate", "ux"} <= set(names)


@pytest.mark.parametrize(
    ("text", "caught"),
    [
        ("i_theta = names.index('theta')", True),
        ("# steer with u1 (thrust)", True),
        ('"""pitch rate omega"""', True),
        ("x0[index('X')] = 1.0", False),  # no `.index(`: an ordinary call
        ("i = scenario.state_names.index('X')", True),
        ("position = state['y']", True),
        ("X = np.empty((N, n)); Y = K @ Q", False),  # one-letter maths symbols
        ("theta_des = 1.0; vXY = 2; u12 = 3", False),  # not whole words
        ("marker='x'", False),
    ],
)
def test_the_rule_catches_what_it_should(text, caught):
    names = {"theta": ["q"], "u1": ["q"], "omega": ["q"], "X": ["q"], "y": ["d"], "x": ["d"]}
    assert bool(violations(text, names)) == caught


def test_core_names_no_state_or_input_of_a_shipped_scenario():
    names = _names()
    report = []
    for folder in CORE:
        for path in sorted((ROOT / folder).rglob("*.py")):
            for hit in violations(path.read_text(encoding="utf-8"), names):
                report.append(f"{path.relative_to(ROOT)}: {hit}")
    assert not report, "scenario-specific names in the core:\n" + "\n".join(report)
