"""The README's results blocks come from real runs: each is the block that
``pipeline.runtime.readme_results`` makes from a run's ``summary.json``. Checked against a fresh
synthesis in this session: the same lines in the same format (numbers aside: the README's run
has 10,000 Monte Carlo samples and its own timings), made from the current scenario file.

Which constraint limits a radius, and which margin the falsification search found smallest, are
results of the run like its numbers: an optimized nominal's binding constraint can change with
the last bits of the arithmetic (seen: quadrotor_hill's demo_08 on an AVX-512 machine), so the
shape names them ``<constraint>`` and ``<margin>`` and keeps one legend line per run of them;
that each named constraint has its legend line is checked on the README's block itself."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.model.scenario import load_scenario
from pipeline.runtime.readme_results import block_in, main, read_summary, results_block

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
NUMBER = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)(e[-+]?\d+)?%?")


CONSTRAINT = re.compile(r"\b(?:unsafe|goal bound|region|input|state) '[^']+'(?: lower| upper)?")
MARGIN = re.compile(r"\((?:clearance to Unsafe, m|Goal margin, m|input slack, input units)\)")
LEGEND = re.compile(r"^\s*\(<constraint>: .*\)$")
MARGIN_LEGEND = re.compile(r"^\s*\(input slack: .*\)$")  # printed when that margin is named


def shape(block: str) -> list[str]:
    """The block's lines with the hash and every number replaced by ``#``, constraint and
    margin names by ``<constraint>`` and ``<margin>``, a run of legend lines by one (their
    number follows the names; the margin's legend only when it is named), runs of spaces
    collapsed."""
    block = re.sub(r"`[0-9a-f]{12}`", "`#`", block)
    lines: list[str] = []
    for line in block.splitlines():
        if MARGIN_LEGEND.match(line):
            continue
        line = MARGIN.sub("(<margin>)", CONSTRAINT.sub("<constraint>", line))
        legend = LEGEND.match(line)
        line = "(<constraint>: ...)" if legend else " ".join(NUMBER.sub("#", line).split())
        if not (legend and lines and lines[-1] == line):
            lines.append(line)
    return lines


def test_shape_names_constraints_as_results_and_keeps_the_format():
    run = "  demo_08   unsafe 'hill' at 5.4 s         -> input 'u2' lower at 0.0 s"
    other = "  demo_08   unsafe 'hill' at 5.4 s         -> region 'u1' upper at 0.3 s"
    legends = "  (unsafe 'hill': touches)\n  (input 'u2' lower: clipped)"
    assert shape(f"{run}\n{legends}") == shape(f"{other}\n  (unsafe 'hill': touches)")
    slack = "found 0.034 (input slack, input units)\n    (input slack: how far)"
    assert shape(slack) == shape("found 0.1 (Goal margin, m)")
    assert shape(run) != shape(run.replace("->", "=>"))  # the format itself still counts
    assert shape(run) != shape(f"{run}\n  (unsafe 'hill': touches)")


def _constraints_without_a_legend(block: str) -> set[str]:
    """The constraints that a "radius limited by" line names and no legend line explains."""
    named = {
        m.group(0) for line in block.splitlines() if "->" in line for m in CONSTRAINT.finditer(line)
    }
    explained = {
        m.group(0)
        for line in block.splitlines()
        if (m := CONSTRAINT.match(line.strip().lstrip("(")))
    }
    return named - explained


@pytest.mark.parametrize("name", ["quadrotor_hill", "double_integrator"])
def test_readme_results_block_is_the_scripts_output_for_a_fresh_run(name, synthesis):
    code, out = synthesis(name)
    assert code == 0
    fresh = results_block(read_summary(out))
    written = block_in(README.read_text(), name)
    assert written is not None, f"README.md has no results block for {name}"
    assert shape(written) == shape(fresh)
    for block in (written, fresh):
        assert not _constraints_without_a_legend(block)
        if "(input slack, input units)" in block:  # the margin's legend follows its name
            assert "    (input slack: " in block
    # made from the scenario file as it is now (regenerate after editing it)
    sha = re.search(r"scenario file sha256 `([0-9a-f]{12})`", written)
    assert sha is not None and load_scenario(name).source_hash.startswith(sha.group(1))


@pytest.mark.xdist_group("synthesis-double_integrator")  # with its session run (conftest)
def test_the_script_replaces_only_its_block(synthesis, tmp_path, capsys):
    _, out = synthesis("double_integrator")
    block = results_block(read_summary(out))
    readme = tmp_path / "README.md"
    readme.write_text(
        "before\n<!-- results double_integrator -->\nold\n<!-- /results double_integrator -->\n"
        "after\n"
    )
    assert main([str(out), "--write", str(readme)]) == 0
    assert readme.read_text() == f"before\n{block}\nafter\n"
    assert main([str(out)]) == 0
    assert capsys.readouterr().out.endswith(block + "\n")
    assert main([str(tmp_path / "nothing")]) == 2
    assert "summary.json: cannot read" in capsys.readouterr().err


@pytest.mark.xdist_group("synthesis-double_integrator")  # with its session run (conftest)
def test_the_load_and_fly_example_runs_and_reaches_goal(synthesis, tmp_path):
    """The README's complete example, run as written where ``reports/double_integrator`` holds
    a fresh controller: it covers its start and ends in Goal."""
    _, out = synthesis("double_integrator")
    found = re.search(
        r"<!-- example fly -->\n```python\n(.*?)```\n<!-- /example fly -->",
        README.read_text(),
        flags=re.DOTALL,
    )
    assert found is not None, "README.md has no load-and-fly example"
    (tmp_path / "reports" / "double_integrator").mkdir(parents=True)
    shutil.copy(out / "controller.json", tmp_path / "reports" / "double_integrator")
    (tmp_path / "fly.py").write_text(found.group(1))
    run = subprocess.run(
        [sys.executable, "fly.py"], cwd=tmp_path, capture_output=True, text=True, timeout=120
    )
    assert run.returncode == 0, run.stderr
    printed = re.search(r"coverage ratio (\S+)\): ends at \[\s*(\S+)\s+(\S+)\]", run.stdout)
    assert printed is not None, run.stdout
    ratio, x, y = (float(v) for v in printed.groups())
    scenario = load_scenario("double_integrator")
    assert ratio < 1
    assert bool(scenario.in_goal(np.array([x, y, 0.0, 0.0]))), run.stdout


@pytest.mark.xdist_group("synthesis-double_integrator")  # with its session run (conftest)
def test_the_fly_api_example_runs_and_reaches_goal(synthesis, tmp_path):
    """The README's ``pipeline.fly`` example, run as written where ``reports/double_integrator``
    holds a fresh controller: its repr names demo_01 beside index 0, ``dynamics.f`` works on a
    batch, and the flight is covered and ends in Goal."""
    _, out = synthesis("double_integrator")
    found = re.search(
        r"<!-- example fly-api -->\n```python\n(.*?)```\n<!-- /example fly-api -->",
        README.read_text(),
        flags=re.DOTALL,
    )
    assert found is not None, "README.md has no pipeline.fly example"
    (tmp_path / "reports" / "double_integrator").mkdir(parents=True)
    shutil.copy(out / "controller.json", tmp_path / "reports" / "double_integrator")
    (tmp_path / "fly.py").write_text(found.group(1))
    run = subprocess.run(
        [sys.executable, "fly.py"], cwd=tmp_path, capture_output=True, text=True, timeout=120
    )
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert len(lines) < 17 and "0: demo_01, 1: demo_02" in run.stdout, run.stdout
    assert "(3, 4)" in lines
    printed = re.search(r"coverage ratio (\S+), in Goal at the end: (\w+)", run.stdout)
    assert printed is not None, run.stdout
    assert float(printed.group(1)) < 1 and printed.group(2) == "True"
