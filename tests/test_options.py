"""One source of truth per option: the CLI is derived from ``RunOptions``, the margins' defaults
come from ``pipeline.numerics.settings``."""

from __future__ import annotations

import dataclasses
import decimal
import enum
import inspect
import math
import re
import typing
from fractions import Fraction

import numpy as np
import pytest

import pipeline
from pipeline.model.schema import ScenarioSpec
from pipeline.numerics import settings
from pipeline.numerics.optimize.penalties import build_constraints
from pipeline.numerics.optimize.problem import make_problem
from pipeline.runtime.cli import _parser, main
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
    assert run["method"].values.choices == settings.DESCENT_METHODS
    assert run["search"].values.choices == settings.HORIZON_SEARCHES
    assert run["certificate"].values.choices == settings.CERTIFICATES
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

    quadrotor = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    plain = load_scenario("double_integrator", check_demos=False)
    assert method_of(quadrotor, RunOptions()) == "lbfgs"
    assert method_of(plain, RunOptions()) == "gd"
    assert method_of(quadrotor, parse("--method", "gd")) == "gd"


# --- every bad value is refused before any work, on the command line and in the API -----------

USAGE = " (usage: python -m pipeline synthesize --help)"


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--seed", "-1"], "argument --seed: found '-1'; expected a whole number >= 0"),
        (["--seed", "1.5"], "argument --seed: found '1.5'; expected a whole number >= 0"),
        (["--seed", "abc"], "argument --seed: found 'abc'; expected a whole number >= 0"),
        (
            ["--feedback-period", "1e-300"],
            "argument --feedback-period: found '1e-300'; expected 0 or a finite number of "
            "seconds >= 0.0001",
        ),
        (
            ["--feedback-period", "inf"],
            "argument --feedback-period: found 'inf'; expected 0 or a finite number of "
            "seconds >= 0.0001",
        ),
        (
            ["--samples", "0"],
            "argument --samples: found '0'; expected a whole number from 1 to 1,000,000,000",
        ),
        (
            ["--samples", "1000000000000"],
            "argument --samples: found '1000000000000'; expected a whole number from 1 to "
            "1,000,000,000",
        ),
        (
            ["--jobs", "1.5"],
            "argument --jobs: found '1.5'; expected a whole number from 1 to 1,024",
        ),
        (
            ["--method", "newton"],
            "argument --method: found 'newton'; expected one of ('gd', 'lbfgs')",
        ),
        (
            ["--executor", "5"],
            "argument --executor: found '5'; expected None, 'local', 'dask-local' or "
            "'dask://HOST:PORT'",
        ),
        (["-v", "-q"], "argument -q/--quiet: not allowed with argument -v/--verbose"),
    ],
    ids=lambda value: " ".join(value) if isinstance(value, list) else "",
)
def test_a_bad_option_is_one_line_and_exit_2_before_the_output_folder_is_touched(
    argv: list[str], message: str, tmp_path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "controller.json").write_text("{}")  # a previous run's outputs: left as they are
    with pytest.raises(SystemExit) as raised:
        main(["synthesize", "double_integrator", "--out", str(out), *argv])
    assert raised.value.code == 2
    assert capsys.readouterr().err == f"error: {message}{USAGE}\n"
    assert sorted(p.name for p in out.iterdir()) == ["controller.json"]


@pytest.mark.parametrize(
    ("keywords", "message"),
    [
        ({"seed": "abc"}, "seed='abc'; expected a whole number >= 0"),
        ({"seed": -1}, "seed=-1; expected a whole number >= 0"),
        ({"seed": 1.5}, "seed=1.5; expected a whole number >= 0"),
        ({"seed": True}, "seed=True; expected a whole number >= 0"),
        ({"samples": 0}, "samples=0; expected a whole number from 1 to 1,000,000,000"),
        ({"jobs": "2"}, "jobs='2'; expected a whole number from 1 to 1,024"),
        ({"jobs": 10**6}, "jobs=1000000; expected a whole number from 1 to 1,024"),
        (
            {"feedback_period": 10**400},
            f"feedback_period={10**400}; expected 0 or a finite number of seconds >= 0.0001",
        ),
        ({"stress": "no"}, "stress='no'; expected True or False"),
        ({"force": "no"}, "force='no'; expected True or False"),
        ({"force": 1}, "force=1; expected True or False"),
        (
            {"executor": 5},
            "executor=5; expected None, 'local', 'dask-local' or 'dask://HOST:PORT'",
        ),
        (
            {"executor": "dask"},
            "executor='dask'; expected None, 'local', 'dask-local' or 'dask://HOST:PORT'",
        ),
        (
            {"feedback_period": "0.01"},
            "feedback_period='0.01'; expected 0 or a finite number of seconds >= 0.0001",
        ),
        (
            {"feedback_period": 1e-300},
            "feedback_period=1e-300; expected 0 or a finite number of seconds >= 0.0001",
        ),
        (
            {"feedback_period": float("nan")},
            "feedback_period=nan; expected 0 or a finite number of seconds >= 0.0001",
        ),
        ({"search": None}, "search=None; expected one of ('continuation', 'bisection')"),
        ({"certificate": 1}, "certificate=1; expected one of ('constant', 'funnel')"),
    ],
    ids=lambda value: "" if isinstance(value, str) else repr(value),
)
def test_a_bad_option_is_a_value_error_before_the_output_folder_is_touched(
    keywords: dict[str, object], message: str, tmp_path
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "controller.json").write_text("{}")
    with pytest.raises(ValueError) as raised:
        pipeline.synthesize("double_integrator", out=out, **keywords)  # type: ignore[arg-type]
    assert str(raised.value) == message
    assert sorted(p.name for p in out.iterdir()) == ["controller.json"]
    with pytest.raises(ValueError, match=re.escape(message)):
        RunOptions(**keywords)  # type: ignore[arg-type]


def test_verbose_and_quiet_exclude_each_other_in_the_dataclass_too() -> None:
    with pytest.raises(ValueError, match=r"^verbose=True and quiet=True; expected at most one$"):
        RunOptions(verbose=True, quiet=True)


def test_values_are_stored_normalized() -> None:
    """``feedback_period`` is hashed into cache keys and written to ``controller.json``: an
    integer 0 from the API must be the command line's ``0.0``; NumPy scalars become Python's."""
    seed, samples = np.int64(3), np.uint16(7)
    options = RunOptions(feedback_period=0, seed=seed, samples=samples)  # type: ignore[arg-type]
    assert options == parse("--seed", "3", "--samples", "7", "--feedback-period", "0")
    assert type(options.feedback_period) is float and type(options.seed) is int
    assert type(options.samples) is int
    assert RunOptions(feedback_period=np.float64(0.01)).feedback_period == 0.01
    assert parse("--feedback-period", "1e-4").feedback_period == 1e-4  # the stated minimum
    for spec in ("local", "", "dask-local", "dask://10.0.0.5:8786"):
        assert RunOptions(executor=spec).executor == spec


def test_the_law_is_held_for_the_scenario_s_period_unless_the_command_line_sets_one(
    tmp_path, capsys
):
    """A scenario's ``feedback_period`` (its vehicle's control period) is the run's period;
    ``--feedback-period`` (also 0: continuous) overrides it; a period set by
    ``dataclasses.replace`` is checked before any work, naming the scenario's field."""
    from pipeline.io.errors import UserError
    from pipeline.model.limits import MIN_FEEDBACK_PERIOD
    from pipeline.model.scenario import load_scenario
    from pipeline.runtime.run_inputs import check_period, period_of
    from tests.helpers.scenario_files import write_scenario, yaml_replace

    path = yaml_replace("clearance: 0.25\n", "clearance: 0.25\nfeedback_period: 0.01\n")(
        write_scenario(tmp_path / "scenario")
    )
    scenario = load_scenario(path)
    assert scenario.feedback_period == 0.01
    assert period_of(scenario, parse()) == 0.01
    assert period_of(scenario, parse("--feedback-period", "0")) == 0.0
    assert period_of(scenario, RunOptions(feedback_period=0.02)) == 0.02
    assert load_scenario(write_scenario(tmp_path / "plain")).feedback_period == 0.0
    replaced = dataclasses.replace(scenario, feedback_period=0.03)
    source = f"{path}: feedback_period"
    with pytest.raises(UserError, match=r"feedback_period: found 0.03 s; expected 0 \(continuous"):
        check_period(replaced, period_of(replaced, parse()), "funnel", source)
    code = main(
        ["synthesize", str(path), "--feedback-period", "0.03", "--out", str(tmp_path / "o")]
    )
    assert code == 2 and not (tmp_path / "o").exists()
    error = capsys.readouterr().err
    assert error.startswith("error: --feedback-period: found 0.03 s; expected 0")
    assert f"a period of at least {MIN_FEEDBACK_PERIOD:g} s that divides" in error


@pytest.mark.parametrize(
    ("period", "found"),
    [
        ("0.01", "'0.01'"),
        (None, "None"),
        (False, "False"),
        (True, "True"),
        (decimal.Decimal("0.01"), "Decimal('0.01')"),
        (math.nan, "nan s"),
        (0.03, "0.03 s"),
        (10**400, "inf s"),
    ],
    ids=["text", "None", "False", "True", "Decimal", "nan", "not-dividing", "huge-int"],
)
def test_a_period_set_by_replace_is_refused_as_the_scenario_s_not_the_file_s(
    period, found, tmp_path
):
    """``dataclasses.replace(scenario, feedback_period=...)`` is checked before any work: a
    value of any type is a ``UserError`` (not a ``TypeError`` from dividing by it, nor the
    ``ValueError`` of ``RunOptions`` for an option nobody set) that names the ``Scenario``'s
    field, not the file (which says 0)."""
    scenario = pipeline.load_scenario("double_integrator")
    replaced = dataclasses.replace(scenario, feedback_period=period)
    expected = (
        f"the Scenario's feedback_period (set in Python; {scenario.path} says 0): "
        f"found {found}; expected 0 (continuous feedback)"
    )
    with pytest.raises(pipeline.UserError) as raised:
        pipeline.synthesize(replaced, out=tmp_path / "o")
    assert str(raised.value).startswith(expected)
    assert not (tmp_path / "o").exists()


def test_negative_zero_is_stored_as_zero() -> None:
    """``--feedback-period -0`` (or ``-0.0`` from the API) is continuous feedback, stored as the
    ``0.0`` that is hashed into cache keys and written to ``controller.json``."""
    for options in (parse("--feedback-period", "-0"), RunOptions(feedback_period=-0.0)):
        assert math.copysign(1.0, typing.cast(float, options.feedback_period)) == 1.0
    assert RunOptions(feedback_period=-0.0) == RunOptions(feedback_period=0.0)


class _Level(float, enum.Enum):
    """A float ``Enum``: a ``float`` to ``isinstance``, not to the exact key encoding."""

    HALF = 0.5


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("clearance", Fraction(1, 2)),
        ("Ts", decimal.Decimal("0.1")),
        ("units", {"x": object()}),
        ("clearance", _Level.HALF),
        ("init_lower", np.array([1.0, 1.0, 0.0, 0.0], dtype=object)),
    ],
    ids=["Fraction", "Decimal", "object", "float-Enum", "object-array"],
)
def test_a_field_replaced_by_a_value_without_an_exact_key_is_refused_before_any_work(
    field, value, tmp_path
):
    """A ``Scenario`` field set by ``dataclasses.replace`` to a type the cache keys cannot
    encode exactly is a ``UserError`` naming the field, before any work (it failed the first
    stage with a traceback, or for the last two raised a ``TypeError`` out of the run)."""
    scenario = pipeline.load_scenario("double_integrator")
    replaced = dataclasses.replace(scenario, **{field: value})
    with pytest.raises(pipeline.UserError, match=rf"^scenario field {field}[.\w]*: ") as raised:
        pipeline.synthesize(replaced, out=tmp_path / "o")
    assert "expected a float, an int, a string" in str(raised.value)
    assert not (tmp_path / "o").exists()
