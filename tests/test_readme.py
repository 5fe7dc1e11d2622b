"""The README (the guide) and its reference pages in ``docs/``, checked as a reader uses them.

Their results blocks come from real runs: each is the block that
``pipeline.runtime.readme_results`` makes from a run's ``summary.json`` (quadrotor_hill's in the
README, double_integrator's in ``docs/results.md``). Checked against a fresh synthesis in this
session: the same lines in the same format (numbers aside: the written run has 100,000 Monte
Carlo samples and its own timings), made from the current scenario file.

Which constraint limits a radius, and which margin the falsification search found smallest, are
results of the run like its numbers: an optimized nominal's binding constraint can change with
the last bits of the arithmetic (seen: quadrotor_hill_flythrough's demo_08 on an AVX-512 machine),
so the shape names them ``<constraint>`` and ``<margin>`` and keeps one legend line per run of them;
that each named constraint has its legend line is checked on the written block itself.

The rest is checked without running anything long: the examples run on a fresh run, every Python
block compiles, every YAML block parses (a complete scenario file loads), every ``python -m
pipeline`` line parses with the command line's parser, every link and every path in backticks
names a file that exists, and every field of the scenario file is in its reference."""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from pipeline.model.scenario import load_scenario
from pipeline.model.schema import ScenarioSpec
from pipeline.runtime.cli import _parser
from pipeline.runtime.readme_results import block_in, main, read_summary, results_block

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
PAGES = [README, *DOCS]
RESULTS = {"quadrotor_hill": "README.md", "double_integrator": "docs/results.md"}  # make readme
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


@pytest.mark.parametrize("name", sorted(RESULTS))
def test_results_block_is_the_scripts_output_for_a_fresh_run(name, synthesis):
    code, out = synthesis(name)
    assert code == 0
    fresh = results_block(read_summary(out), RESULTS[name])
    written = block_in((ROOT / RESULTS[name]).read_text(), name)
    assert written is not None, f"{RESULTS[name]} has no results block for {name}"
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
    readme = tmp_path / "README.md"
    block = results_block(read_summary(out), str(readme))  # the file it names is the one written
    readme.write_text(
        "before\n<!-- results double_integrator -->\nold\n<!-- /results double_integrator -->\n"
        "after\n"
    )
    assert main([str(out), "--write", str(readme)]) == 0
    assert readme.read_text() == f"before\n{block}\nafter\n"
    assert main([str(out)]) == 0
    assert capsys.readouterr().out.endswith(results_block(read_summary(out)) + "\n")
    assert main([str(tmp_path / "nothing")]) == 2
    assert "summary.json: cannot read" in capsys.readouterr().err


@pytest.mark.xdist_group("synthesis-double_integrator")  # with its session run (conftest)
def test_the_load_and_fly_example_runs_and_reaches_goal(synthesis, tmp_path):
    """docs/controller-file.md's NumPy-only program, run as written where
    ``reports/double_integrator`` holds a fresh controller: it covers its start and ends in Goal."""
    _, out = synthesis("double_integrator")
    found = re.search(
        r"<!-- example fly -->\n```python\n(.*?)```\n<!-- /example fly -->",
        (ROOT / "docs" / "controller-file.md").read_text(),
        flags=re.DOTALL,
    )
    assert found is not None, "docs/controller-file.md has no load-and-fly example"
    (tmp_path / "reports" / "double_integrator").mkdir(parents=True)
    shutil.copy(out / "controller.json", tmp_path / "reports" / "double_integrator")
    (tmp_path / "fly.py").write_text(found.group(1))
    run = subprocess.run(
        [sys.executable, "fly.py"], cwd=tmp_path, capture_output=True, text=True, timeout=120
    )
    assert run.returncode == 0, run.stderr
    printed = re.search(
        r"trajectory (\d+): demo_\d\d \(coverage ratio (\S+)\): ends at \[\s*(\S+)\s+(\S+)\]",
        run.stdout,
    )
    assert printed is not None, run.stdout
    ratio, x, y = (float(v) for v in printed.groups()[1:])
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


def _blocks(page: Path, language: str) -> list[str]:
    """The fenced code blocks of ``page`` in ``language``."""
    return re.findall(rf"^```{language}\n(.*?)^```$", page.read_text(), flags=re.DOTALL | re.M)


def _anchor(heading: str) -> str:
    """GitHub's anchor of a Markdown heading: lower case, punctuation dropped, spaces to ``-``."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    return {_anchor(h) for h in re.findall(r"^#+ (.*)$", page.read_text(), flags=re.M)}


def test_the_readme_is_a_guide_that_links_every_reference_page():
    lines = README.read_text().splitlines()
    assert len(lines) <= 300, f"README.md has {len(lines)} lines: move reference to docs/"
    steps = [line for line in lines if re.match(r"## \d\. ", line)]
    assert [step[3] for step in steps] == [str(k) for k in range(1, len(steps) + 1)]
    assert len(steps) >= 6
    for page in DOCS:
        assert f"(docs/{page.name})" in README.read_text(), f"README.md does not link {page.name}"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_links_and_paths_name_files_that_exist(page):
    """Each relative link (and its ``#anchor``) and each repository path in backticks resolves:
    a page moved or a module renamed leaves no dangling reference."""
    text = page.read_text()
    missing = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"https?://", target):
            continue
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.exists():
            missing.append(target)
        elif anchor and file.suffix == ".md" and anchor not in _anchors(file):
            missing.append(target)
    top = "pipeline|stages|tests|scenarios|examples|bench|docs|\\.ci"
    for path in re.findall(rf"`((?:{top})/[\w./-]*\w/?)`", text):
        if not (ROOT / path).exists() and not re.search(r"NAME|STAGE", path):
            missing.append(path)
    assert not missing, f"{page.name}: {missing}"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_python_blocks_compile_and_yaml_blocks_load(page, tmp_path):
    for block in _blocks(page, "python"):
        compile(block, str(page), "exec")
    for block in _blocks(page, "yaml"):
        data = yaml.safe_load(block)
        assert isinstance(data, dict), block
        if "name" in data:  # a complete scenario file: it loads as one
            folder = tmp_path / data["name"]
            folder.mkdir()
            (folder / "scenario.yaml").write_text(block)
            assert load_scenario(folder, check_demos=False).name == data["name"]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_command_lines_parse(page):
    """Every concrete ``python -m pipeline ...`` line (not a usage line with placeholders) in a
    shell block is one the command line accepts."""
    parser = _parser()
    commands = [
        line.split("#")[0].split("python -m pipeline ", 1)[1]
        for block in _blocks(page, "sh")
        for line in block.splitlines()
        if line.startswith("python -m pipeline ") and not re.search(r"\[|[A-Z]{3,}", line)
    ]
    for command in commands:
        try:
            parser.parse_args(shlex.split(command))
        except SystemExit:
            pytest.fail(f"{page.name}: `python -m pipeline {command}` does not parse")
    if page == README:
        assert len(commands) >= 4


def test_every_scenario_field_has_a_row_in_the_reference():
    rows = [
        line.split("|")[1]  # the field column: `name`, `goal.polygon`, `units`, `labels`
        for line in (ROOT / "docs" / "scenario-file.md").read_text().splitlines()
        if line.startswith("| `")
    ]
    undocumented = [
        f for f in ScenarioSpec.model_fields if not any(re.search(rf"`{f}[`.]", r) for r in rows)
    ]
    assert not undocumented, undocumented
