"""The report's account of the law in time: the feedback period and the terminal controller,
with the scenario's labels and units (``pipeline.reporting.law``).

A double integrator at rest in a Goal around Init (the terminal tests' case), its units and a
label declared, gets a certified terminal block; the report shows its equilibrium, its gain
with units, its invariant set, and the held feedback rate that controller.json records.
"""

from __future__ import annotations

import json
import textwrap
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from pipeline.controller import load
from pipeline.model.scenario import Scenario, load_scenario
from pipeline.reporting.law import gain_table, law, law_items
from tests.helpers.double_integrator import DOUBLE_INTEGRATOR, emit_at_rest

UNITS = """\
units: {X: m, Y: m, vX: m/s, vY: m/s, aX: m/s^2, aY: m/s^2}
labels: {aX: horizontal acceleration}
"""


def _scenario(tmp_path: Path) -> Scenario:
    path = tmp_path / "double_integrator" / "scenario.yaml"
    path.parent.mkdir()
    goal = "[[-1, 1], [2, 1], [2, 4], [-1, 4]]"
    text = DOUBLE_INTEGRATOR % {"goal": goal, "region": "{aX: [-100.0, 100.0]}", "rate": 0.5}
    path.write_text(textwrap.dedent(text) + UNITS)
    return load_scenario(path, check_demos=False)


def _data(tmp_path: Path, period: float) -> Any:
    """What ``law`` reads of ``ReportData``, for a controller.json with a terminal block."""
    scenario = _scenario(tmp_path)
    path = tmp_path / "controller.json"
    result = emit_at_rest(scenario, path, radius_floor=1.2)
    assert result.terminal, result.terminal_message
    document = json.loads(path.read_text())
    document["feedback_period"] = period
    path.write_text(json.dumps(document))
    return SimpleNamespace(
        scenario=scenario,
        controller=result,
        controller_path=path,
        law=load(path),
        feedback=SimpleNamespace(rate=0.5),
    )


def test_the_terminal_controller_and_the_held_rate_are_shown_with_units(tmp_path: Path) -> None:
    data = _data(tmp_path, period=0.05)
    terminal = data.law.terminal
    table, gains = law(data)
    rows = dict(table.rows)
    assert "every h = 0.05 s (20 Hz)" in rows["feedback period"]
    assert f"rate λ = {load(data.controller_path).rate:.4g} 1/s" in rows["feedback period"]
    assert rows["after T"] == data.controller.terminal_message
    x = terminal.x_eq
    assert rows["terminal equilibrium x_eq"].startswith(f"X = {x[0]:.4g} m, Y = {x[1]:.4g} m")
    assert f"<= {terminal.level:.4g}" in rows["certified invariant set"]
    assert gains.header == ("K", "X [m]", "Y [m]", "vX [m/s]", "vY [m/s]")
    assert [row[0] for row in gains.rows] == ["aX (horizontal acceleration) [m/s^2]", "aY [m/s^2]"]
    np.testing.assert_allclose(
        [[float(v) for v in row[1:]] for row in gains.rows], terminal.K, rtol=1e-3, atol=1e-9
    )
    after, rate = law_items(data)
    assert (after.value, rate.value) == ("terminal controller", "20 Hz")


def test_continuous_feedback_and_no_terminal_block(tmp_path: Path) -> None:
    data = _data(tmp_path, period=0.0)
    document = json.loads(data.controller_path.read_text())
    del document["terminal"]
    data.controller_path.write_text(json.dumps(document))
    data.law = load(data.controller_path)
    data.controller = SimpleNamespace(terminal=False, terminal_message="")
    (table,) = law(data)
    rows = dict(table.rows)
    assert rows["feedback period"].startswith("continuous")
    assert rows["after T"] == "no terminal controller; the law refuses t > T"
    after, rate = law_items(data)
    assert (after.value, rate.value) == ("the law stops at T", "continuous")


def test_a_gain_entry_below_rounding_is_shown_as_zero(tmp_path: Path) -> None:
    scenario = _scenario(tmp_path)
    table = gain_table(scenario, np.array([[2.0, 1e-12, 0, 0], [0, 0, 0, -3.5]]), "K")
    assert table.rows[0][1:3] == ("2", "0") and table.rows[1][4] == "-3.5"
    assert "[unit of u_j] per [unit of x_i]" in table.caption
