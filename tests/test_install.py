"""The package as a user installs it: ``pip install .`` (not editable) into a fresh virtual
environment, then ``python -m pipeline synthesize`` from an unrelated directory.

The environment borrows the running interpreter's site-packages (NumPy, SciPy, ...; not its
editable ``safety-synthesis``) so that the test is fast and needs no network.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import site
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NOT_SHIPPED = ("*.egg-info", ".*", "__pycache__", "build", "dist", "reports", "tests", "bench")


def _packages_in_tree() -> set[str]:
    found = set()
    for top in ("pipeline", "stages"):
        for init in (ROOT / top).rglob("__init__.py"):
            found.add(".".join(init.parent.relative_to(ROOT).parts))
    return found


def test_pyproject_lists_every_package_and_ships_the_scenarios():
    """``pyproject.toml`` lists the packages (to map ``scenarios/`` to ``pipeline.scenarios``):
    a package added to the tree must be added there, or a non-editable install lacks it."""
    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert set(setuptools["packages"]) == _packages_in_tree() | {"pipeline.scenarios"}
    assert setuptools["package-dir"] == {"pipeline.scenarios": "scenarios"}


def test_the_build_warns_about_nothing_of_this_package_and_ships_its_data(tmp_path: Path) -> None:
    """The wheel built by this interpreter's setuptools (as pip builds it on a first install):
    no warning names a package or folder of this project (a data folder not declared, such as
    the templates or a scenario's folder, was one warning of about 40 lines each), and the
    package data declared in ``pyproject.toml`` is in it."""
    source = tmp_path / "source"
    shutil.copytree(ROOT, source, ignore=shutil.ignore_patterns(*NOT_SHIPPED))
    build = subprocess.run(
        [
            sys.executable,
            "-W",
            "always",
            "-c",
            f"from setuptools import build_meta; print(build_meta.build_wheel({str(tmp_path)!r}))",
        ],
        cwd=source,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert build.returncode == 0, build.stderr[-3000:]
    warnings = [
        line
        for line in build.stderr.splitlines()
        if "warning" in line.lower() and re.search(r"'(pipeline|stages|scenarios)\b", line)
    ]
    assert not warnings, "\n".join(warnings)
    wheel = tmp_path / build.stdout.strip().splitlines()[-1]
    names = set(zipfile.ZipFile(wheel).namelist())
    for name in (
        "pipeline/reporting/templates/report.html.j2",
        "pipeline/reporting/templates/report.typ",
        "pipeline/scenarios/scenario.schema.json",
        "pipeline/scenarios/quadrotor_hill_flythrough/scenario.yaml",
        "pipeline/scenarios/quadrotor_hill_flythrough/demos/demo_01.csv",
        "stages/report.py",
    ):
        assert name in names, name


def _environment(tmp_path: Path) -> Path:
    """A virtual environment without pip that sees this interpreter's site-packages."""
    venv = tmp_path / "venv"
    subprocess.run(
        [sys.executable, "-m", "venv", "--system-site-packages", "--without-pip", str(venv)],
        check=True,
        timeout=120,
    )
    python = venv / "bin" / "python"
    own = subprocess.run(
        [str(python), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    # plain paths: the editable install's finder (a .pth of this interpreter) is not run there
    (Path(own) / "borrowed.pth").write_text("\n".join(site.getsitepackages()) + "\n")
    return python


@pytest.mark.slow
def test_a_non_editable_install_synthesizes_from_another_directory(tmp_path: Path) -> None:
    source = tmp_path / "source"
    shutil.copytree(ROOT, source, ignore=shutil.ignore_patterns(*NOT_SHIPPED))
    python = _environment(tmp_path)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "SAFETY_SCENARIOS")}
    install = [sys.executable, "-m", "pip", "--python", str(python), "install", "--quiet"]
    subprocess.run(
        [*install, "--no-deps", "--no-build-isolation", "--no-index", str(source)],
        check=True,
        env=env,
        timeout=300,
    )
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    where = subprocess.run(
        [str(python), "-c", "import pipeline; print(pipeline.__file__)"],
        cwd=elsewhere,
        env=env,
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    package = Path(where).parent
    assert package.is_relative_to(tmp_path / "venv"), where  # the installed copy, not ROOT
    assert (package / "scenarios" / "double_integrator" / "scenario.yaml").is_file()

    run = subprocess.run(
        [str(python), "-m", "pipeline", "synthesize", "double_integrator", "--samples", "200"],
        cwd=elsewhere,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    out = elsewhere / "reports" / "double_integrator"
    assert f"outputs in {out}" in run.stdout
    for name in ("summary.json", "controller.json", "report.html", "report.pdf"):
        assert (out / name).is_file(), name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["verdict"]["kind"] == "certified and validated"
    assert not list(package.rglob("summary.json"))  # nothing written into site-packages
    assert sorted(p.name for p in elsewhere.iterdir()) == ["reports"]
