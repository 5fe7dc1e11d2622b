"""The README's results blocks come from real runs: each is the block that
``pipeline.runtime.readme_results`` makes from a run's ``summary.json``. Checked against a fresh
synthesis in this session: the same lines in the same format (numbers aside: the README's run
has 10,000 Monte Carlo samples and its own timings), made from the current scenario file."""

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


def shape(block: str) -> list[str]:
    """The block's lines with the hash and every number replaced by ``#`` and runs of spaces
    collapsed."""
    block = re.sub(r"`[0-9a-f]{12}`", "`#`", block)
    return [" ".join(NUMBER.sub("#", line).split()) for line in block.splitlines()]


@pytest.mark.parametrize("name", ["quadrotor_hill", "double_integrator"])
def test_readme_results_block_is_the_scripts_output_for_a_fresh_run(name, synthesis):
    code, out = synthesis(name)
    assert code == 0
    fresh = results_block(read_summary(out))
    written = block_in(README.read_text(), name)
    assert written is not None, f"README.md has no results block for {name}"
    assert shape(written) == shape(fresh)
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
