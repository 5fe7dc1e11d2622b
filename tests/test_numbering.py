"""One numbering of the trajectories everywhere (issue 31, item 5): the report, the terminal,
``repr`` and the example name trajectory ``i`` as ``controller.trajectories[i]`` does (from 0,
what ``select`` returns), with its demonstration's name beside the index."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from html import unescape
from pathlib import Path

import numpy as np
import pytest

from pipeline.controller import load
from pipeline.model.scenario import load_scenario
from pipeline.runtime.terminal import format_outputs, format_summary

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "fly_controller.py"
LABEL = re.compile(r"(\d+): (demo_\d\d)\b")


def _agree(pairs: list[tuple[str, str]], names: list[str | None]) -> None:
    """Each ``(index, name)`` printed is trajectory ``index``'s name in controller.json."""
    assert pairs
    for index, name in pairs:
        assert int(index) < len(names) and names[int(index)] == name, (index, name, names)


@pytest.mark.xdist_group("synthesis-double_integrator")  # with its session run (conftest)
def test_report_terminal_repr_and_example_number_trajectories_as_controller_json(
    synthesis_run, tmp_path
):
    session = synthesis_run("double_integrator")
    out = session.out
    controller = load(out / "controller.json")
    names = [tr.name for tr in controller.trajectories]
    assert names[0] == "demo_01"  # the file's names: index 0 is the first demonstration

    # the report: the inputs figure's trajectory, the one select gives the worst start
    text = unescape((out / "report.html").read_text())
    found = re.search(r"Reference trajectory (\d+): (demo_\d\d) of controller\.json", text)
    assert found is not None, "the report names no trajectory as index: name"
    _agree([found.groups()], names)
    summary = json.loads((out / "summary.json").read_text())
    worst = np.array(summary["montecarlo"]["falsification"]["worst_x0"])
    assert int(found.group(1)) == controller.select(worst)[0]

    # the terminal: the outputs list numbers them; the table's rows are the same names
    outputs = format_outputs(session.result)
    line = next(line for line in outputs.splitlines() if "controller.json" in line)
    _agree(LABEL.findall(line), names)
    assert "0: demo_01" in line
    table = format_summary(session.result.summary, verbose=True).splitlines()
    rows = {line.split()[0] for line in table if line.strip()}
    assert {name for name in names if name} <= rows

    # repr and the example
    _agree(LABEL.findall(repr(controller)), names)
    run = subprocess.run(
        [sys.executable, str(EXAMPLE), str(out / "controller.json")],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 0, run.stderr
    flown = re.search(r"trajectory (\d+): (demo_\d\d)", run.stdout)
    assert flown is not None, run.stdout
    _agree([flown.groups()], names)
    scenario = load_scenario("double_integrator")  # the example starts at Init's centre
    assert (
        int(flown.group(1)) == controller.select((scenario.init_lower + scenario.init_upper) / 2)[0]
    )
