"""One source of truth per option: the CLI is derived from ``RunOptions``, the margins' defaults
come from ``pipeline.numerics.settings``."""

from __future__ import annotations

import dataclasses
import inspect
import typing

import pytest

from pipeline.model.schema import ScenarioSpec
from pipeline.numerics import settings
from pipeline.numerics.penalties import build_constraints
from pipeline.numerics.problem import make_problem
from pipeline.runtime.cli import _parser
from pipeline.runtime.options import RunOptions, from_arguments
from stages.optimize import OptimizeOptions


def parse(*argv: str) -> RunOptions:
    return from_arguments(RunOptions, _parser().parse_args(["synthesize", "NAME", *argv]))


def test_cli_defaults_are_the_dataclass_defaults() -> None:
    assert parse() == RunOptions()


def test_every_option_reaches_the_dataclass() -> None:
    options = parse(
        "--method", "lbfgs", "--search", "bisection", "--samples", "7", "--jobs", "2",
        "--executor", "dask-local", "--force", "-q", "--stress", "--seed", "3",
        "--certificate", "funnel",
    )  # fmt: skip
    assert options == RunOptions(
        certificate="funnel",
        method="lbfgs",
        search="bisection",
        samples=7,
        jobs=2,
        executor="dask-local",
        force=True,
        quiet=True,
        stress=True,
        seed=3,
    )
    assert {f.name for f in dataclasses.fields(RunOptions)} <= set(vars(_parser().parse_args(
        ["synthesize", "NAME"]
    )))  # fmt: skip


@pytest.mark.parametrize(
    "argv",
    [
        ["--method", "newton"],
        ["--search", "linear"],
        ["--samples", "0"],
        ["-v", "-q"],
        ["--certificate", "tube"],
    ],
    ids=["method", "search", "samples", "verbose and quiet", "certificate"],
)
def test_bad_choices_exit_2(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as raised:
        parse(*argv)
    assert raised.value.code == 2
    assert "error:" in capsys.readouterr().err


def test_choices_come_from_the_optimizer() -> None:
    run = {f.name: f.metadata["cli"] for f in dataclasses.fields(RunOptions)}
    assert run["method"].choices == settings.DESCENT_METHODS
    assert run["search"].choices == settings.HORIZON_SEARCHES
    assert run["certificate"].choices == settings.CERTIFICATES
    assert RunOptions().method is None  # the scenario's `optimizer` decides
    assert ScenarioSpec.model_fields["optimizer"].default == OptimizeOptions().method
    assert RunOptions().search == OptimizeOptions().search


@pytest.mark.parametrize(
    ("name", "value"),
    [("eps_d", settings.EPS_D), ("eps_g", settings.EPS_G), ("eps_i", settings.EPS_I)],
)
def test_margin_defaults_have_one_source(name: str, value: float) -> None:
    assert getattr(OptimizeOptions(), name) == value
    for function in (build_constraints, make_problem):
        assert inspect.signature(function).parameters[name].default == value


def test_certificate_kinds_are_the_scenario_schemas() -> None:
    """``--certificate`` offers exactly the kinds a scenario's ``certificate`` may name; unset
    (None), the scenario's own kind is used."""
    hint = typing.get_type_hints(ScenarioSpec)["certificate"]
    assert typing.get_args(hint) == settings.CERTIFICATES
    assert parse().certificate is None and RunOptions(certificate=None).certificate is None
    assert parse("--certificate", "constant").certificate == "constant"
    with pytest.raises(ValueError, match=r"certificate='tube'; expected one of"):
        RunOptions(certificate="tube")


def test_the_scenario_chooses_the_optimizer_unless_the_command_line_does() -> None:
    from pipeline.model.scenario import load_scenario
    from pipeline.runtime.run_inputs import method_of

    quadrotor = load_scenario("quadrotor_hill", check_demos=False)
    plain = load_scenario("double_integrator", check_demos=False)
    assert method_of(quadrotor, RunOptions()) == "lbfgs"
    assert method_of(plain, RunOptions()) == "gd"
    assert method_of(quadrotor, parse("--method", "gd")) == "gd"
