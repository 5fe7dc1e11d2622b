"""The options of ``synthesize``: one frozen dataclass whose fields are the single source of
their defaults, choices and help; the command line (``pipeline.runtime.cli``) is derived from it.

Light on purpose (standard library and ``pipeline.numerics.settings`` only): the parser is built
for every command, and must not load the numerics.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TypeVar

from pipeline.numerics.settings import CERTIFICATES, DESCENT_METHODS, HORIZON_SEARCHES

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

MONTE_CARLO_SEED = 20261122


@dataclass(frozen=True, kw_only=True)
class CommandLine:
    """How one option appears on the command line.

    Attributes:
      help: the help text (the default is appended).
      flags: option strings (default ``--NAME`` with ``_`` as ``-``).
      choices: allowed values; parse: text -> value (default: the default's type).
      group: options sharing a group exclude each other (e.g. ``-v`` and ``-q``).
    """

    help: str
    flags: tuple[str, ...] = ()
    choices: tuple[str, ...] | None = None
    parse: Callable[[str], Any] | None = None
    group: str | None = None


def option(default: Any, help: str, **command_line: Any) -> Any:
    """A dataclass field with ``default`` and its command-line form (``CommandLine``)."""
    return field(default=default, metadata={"cli": CommandLine(help=help, **command_line)})


def positive_int(text: str) -> int:
    """``text`` as a whole number >= 1 (an ``argparse`` type)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, found {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, found {value}")
    return value


def period(text: str) -> float:
    """``text`` as a feedback period in seconds, a finite number >= 0 (an ``argparse`` type)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, found {text!r}") from None
    if not (value >= 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number of seconds >= 0, found {text}")
    return value


@dataclass(frozen=True, kw_only=True)
class RunOptions:
    """Command-line choices of ``synthesize``."""

    certificate: str | None = option(
        None,
        "what certifies the controller: one constant metric and gain for all time, or a "
        "time-varying funnel per trajectory (default: the scenario's `certificate`)",
        choices=CERTIFICATES,
        parse=str,
    )
    method: str | None = option(
        None,
        "optimizer: the paper's gradient descent (gd) or L-BFGS-B (default: the scenario's "
        "`optimizer`)",
        choices=DESCENT_METHODS,
        parse=str,
    )
    search: str = option(
        HORIZON_SEARCHES[0],
        "how the final time is shortened (bisection: the paper's Remark 4)",
        choices=HORIZON_SEARCHES,
    )
    samples: int = option(100_000, "Monte Carlo closed-loop runs", parse=positive_int)
    jobs: int = option(1, "worker processes", parse=positive_int)
    executor: str | None = option(
        None,
        "where parallel work runs: local (default), dask-local, or dask://HOST:PORT",
        parse=str,
    )
    force: bool = option(False, "rerun every stage")
    verbose: bool = option(False, "print iteration logs", flags=("-v", "--verbose"), group="say")
    quiet: bool = option(False, "print only the verdict", flags=("-q", "--quiet"), group="say")
    stress: bool = option(False, "also run the stress test (wind, noise; not certified)")
    seed: int = option(MONTE_CARLO_SEED, "seed of the Monte Carlo and stress runs", parse=int)
    feedback_period: float = option(
        0.0,
        "certify zero-order-hold feedback recomputed every h seconds (must divide the sampling "
        "time; 0: continuous feedback)",
        parse=period,
    )

    def __post_init__(self) -> None:
        """The command line checks these while parsing; the Python API (``pipeline.synthesize``)
        relies on this: a value outside its choices, or a count below 1, is a ``ValueError``."""
        for item in self.__dataclass_fields__.values():
            spec: CommandLine = item.metadata["cli"]
            value = getattr(self, item.name)
            unset = value is None and item.default is None  # None: the scenario decides
            if spec.choices is not None and value not in spec.choices and not unset:
                raise ValueError(f"{item.name}={value!r}; expected one of {spec.choices}")
            if spec.parse is positive_int and (type(value) is not int or value < 1):
                raise ValueError(f"{item.name}={value!r}; expected a whole number >= 1")


def add_arguments(parser: argparse.ArgumentParser, options: type[DataclassInstance]) -> None:
    """One argument per field of the dataclass ``options`` that has a ``CommandLine``."""
    groups: dict[str, Any] = {}
    for item in options.__dataclass_fields__.values():
        spec: CommandLine | None = item.metadata.get("cli")
        if spec is None:
            raise TypeError(f"{options.__name__}.{item.name} has no command-line form")
        flags = spec.flags or (f"--{item.name.replace('_', '-')}",)
        target: Any = parser
        if spec.group is not None:
            if spec.group not in groups:
                groups[spec.group] = parser.add_mutually_exclusive_group()
            target = groups[spec.group]
        if item.default is False:
            target.add_argument(*flags, dest=item.name, action="store_true", help=spec.help)
            continue
        target.add_argument(
            *flags,
            dest=item.name,
            type=spec.parse or type(item.default),
            choices=spec.choices,
            default=item.default,
            help=f"{spec.help} (default: {item.default})"
            if item.default is not None
            else spec.help,
        )


Options = TypeVar("Options", bound="DataclassInstance")


def from_arguments(options: type[Options], arguments: argparse.Namespace) -> Options:
    """An ``options`` instance from the parsed ``arguments`` (its fields' names)."""
    values: Mapping[str, Any] = vars(arguments)
    return options(**{name: values[name] for name in options.__dataclass_fields__})
