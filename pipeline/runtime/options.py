"""The options of ``synthesize``: one frozen dataclass whose fields are the single source of
their defaults, values and help; the command line (``pipeline.runtime.cli``) is derived from it,
and the one check of each value (``Values``) serves the command line and the Python API alike.

Light on purpose (standard library and ``pipeline.numerics.settings`` only): the parser is built
for every command, and must not load the numerics.
"""

from __future__ import annotations

import argparse
import math
import numbers
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

from pipeline.model.limits import MIN_FEEDBACK_PERIOD
from pipeline.numerics.settings import CERTIFICATES, DESCENT_METHODS, HORIZON_SEARCHES

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

MONTE_CARLO_SEED = 20261122


class Values(Protocol):
    """What an option takes: the one check of its values, for the command line and the API."""

    @property
    def expected(self) -> str:
        """The values, in words (e.g. ``a whole number >= 1``)."""
        ...

    def value(self, found: object) -> Any:
        """``found`` as the option's value (normalized: ``int``, ``float``), or ``ValueError``."""
        ...

    def parse(self, text: str) -> Any:
        """The command line's ``text`` as the option's value, or ``ValueError``."""
        ...


@dataclass(frozen=True)
class Whole:
    """A whole number (``int`` or another integral type, not ``bool``) in ``[minimum,
    maximum]``."""

    minimum: int
    maximum: int | None = None

    @property
    def expected(self) -> str:
        if self.maximum is None:
            return f"a whole number >= {self.minimum}"
        return f"a whole number from {self.minimum} to {self.maximum:,}"

    def value(self, found: object) -> int:
        if isinstance(found, bool) or not isinstance(found, numbers.Integral):
            raise ValueError(self.expected)
        number = int(found)
        if number < self.minimum or (self.maximum is not None and number > self.maximum):
            raise ValueError(self.expected)
        return number

    def parse(self, text: str) -> int:
        return self.value(int(text))


@dataclass(frozen=True)
class Period:
    """Seconds, a real number (not ``bool`` or text): 0 (off), or finite and >= ``minimum``;
    with ``unset``, also ``None`` (the scenario decides)."""

    minimum: float
    unset: bool = False

    @property
    def expected(self) -> str:
        return f"0 or a finite number of seconds >= {self.minimum:g}"

    def value(self, found: object) -> float | None:
        if found is None and self.unset:
            return None
        if isinstance(found, bool) or not isinstance(found, numbers.Real):
            raise ValueError(self.expected)
        try:
            seconds = float(found)
        except OverflowError:  # an int beyond float64
            raise ValueError(self.expected) from None
        if not (seconds == 0 or self.minimum <= seconds < math.inf):
            raise ValueError(self.expected)
        return seconds if seconds != 0 else 0.0  # -0.0 too: one key, one file

    def parse(self, text: str) -> float | None:
        return self.value(float(text))


@dataclass(frozen=True)
class Flag:
    """A ``bool`` (``'no'`` or ``0`` are refused, not taken for their truth value); on the
    command line, the flag's presence."""

    @property
    def expected(self) -> str:
        return "True or False"

    def value(self, found: object) -> bool:
        if not isinstance(found, bool):
            raise ValueError(self.expected)
        return found

    def parse(self, text: str) -> bool:
        raise TypeError("a flag takes no value on the command line")


@dataclass(frozen=True)
class Choice:
    """One of ``choices``; with ``unset``, also ``None`` (the scenario decides)."""

    choices: tuple[str, ...]
    unset: bool = False

    @property
    def expected(self) -> str:
        return f"one of {self.choices}"

    def value(self, found: object) -> str | None:
        if found is None and self.unset:
            return None
        if isinstance(found, str) and found in self.choices:
            return found
        raise ValueError(self.expected)

    def parse(self, text: str) -> str | None:
        return self.value(text)


@dataclass(frozen=True)
class ExecutorSpec:
    """Where parallel work runs, as ``pipeline.io.executor.make_executor`` reads it: ``None``
    (or ``''``, ``'local'``), ``'dask-local'`` or ``'dask://HOST:PORT'``."""

    @property
    def expected(self) -> str:
        return "None, 'local', 'dask-local' or 'dask://HOST:PORT'"

    def value(self, found: object) -> str | None:
        if found is None:
            return None
        if isinstance(found, str) and (
            found in ("", "local", "dask-local") or re.fullmatch(r"dask://\S+", found)
        ):
            return found
        raise ValueError(self.expected)

    def parse(self, text: str) -> str | None:
        return self.value(text)


# The most Monte Carlo runs: 10^9 is some 10 hours of CPU on quadrotor_hill_flythrough (100,000 take
# 3.6 s), and its chunks' 400,000 seed streams take 150 MB; far beyond, they alone exhaust the
# memory.
MAX_SAMPLES = 10**9
MAX_JOBS = 1024  # worker processes: far beyond any machine's cores, below its process limits


@dataclass(frozen=True, kw_only=True)
class CommandLine:
    """How one option appears on the command line, and the values it takes.

    Attributes:
      help: the help text (the default is appended).
      values: what it takes (``Values``), checked for the command line and the API alike.
      flags: option strings (default ``--NAME`` with ``_`` as ``-``).
      group: options sharing a group exclude each other (e.g. ``-v`` and ``-q``).
    """

    help: str
    values: Values
    flags: tuple[str, ...] = ()
    group: str | None = None


def option(default: Any, help: str, values: Values, **command_line: Any) -> Any:
    """A dataclass field with ``default`` and its command-line form (``CommandLine``)."""
    spec = CommandLine(help=help, values=values, **command_line)
    return field(default=default, metadata={"cli": spec})


def _argument_type(values: Values) -> Callable[[str], Any]:
    """An ``argparse`` type: the text parsed and checked by ``values``, one line if it fails."""

    def parse(text: str) -> Any:
        try:
            return values.parse(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"found {text!r}; expected {values.expected}"
            ) from None

    return parse


@dataclass(frozen=True, kw_only=True)
class RunOptions:
    """Command-line choices of ``synthesize``. Every value is checked on construction (a bad one
    is a ``ValueError`` before any work, from the API as from the command line) and stored
    normalized (``feedback_period=0`` as ``0.0``: it is hashed into cache keys and written to
    the controller file)."""

    certificate: str | None = option(
        None,
        "what certifies the controller: one constant metric and gain for all time, or a "
        "time-varying funnel per trajectory (default: the scenario's `certificate`)",
        Choice(CERTIFICATES, unset=True),
    )
    method: str | None = option(
        None,
        "optimizer: the paper's gradient descent (gd) or L-BFGS-B (default: the scenario's "
        "`optimizer`)",
        Choice(DESCENT_METHODS, unset=True),
    )
    search: str = option(
        HORIZON_SEARCHES[0],
        "how the final time is shortened (bisection: the paper's Remark 4)",
        Choice(HORIZON_SEARCHES),
    )
    samples: int = option(100_000, "Monte Carlo closed-loop runs", Whole(1, MAX_SAMPLES))
    jobs: int = option(1, "worker processes", Whole(1, MAX_JOBS))
    executor: str | None = option(
        None,
        "where parallel work runs: local (default), dask-local, or dask://HOST:PORT",
        ExecutorSpec(),
    )
    force: bool = option(False, "rerun every stage", Flag())
    verbose: bool = option(
        False, "print iteration logs", Flag(), flags=("-v", "--verbose"), group="say"
    )
    quiet: bool = option(
        False, "print only the verdict", Flag(), flags=("-q", "--quiet"), group="say"
    )
    stress: bool = option(False, "also run the stress test (wind, noise; not certified)", Flag())
    seed: int = option(MONTE_CARLO_SEED, "seed of the Monte Carlo and stress runs", Whole(0))
    feedback_period: float | None = option(
        None,
        "certify zero-order-hold feedback recomputed every h seconds (must divide the sampling "
        f"time and be at least {MIN_FEEDBACK_PERIOD:g}; 0: continuous feedback; default: the "
        "scenario's `feedback_period`, else 0)",
        Period(MIN_FEEDBACK_PERIOD, unset=True),
    )

    def __post_init__(self) -> None:
        """Each value checked and normalized by its field's ``CommandLine.values``; at most one
        option of a ``group`` set (the command line checks that while parsing)."""
        chosen: dict[str, str] = {}
        for item in self.__dataclass_fields__.values():
            spec: CommandLine = item.metadata["cli"]
            found = getattr(self, item.name)
            try:
                value = spec.values.value(found)
            except ValueError:
                raise ValueError(
                    f"{item.name}={found!r}; expected {spec.values.expected}"
                ) from None
            object.__setattr__(self, item.name, value)
            if spec.group is not None and value:
                if spec.group in chosen:
                    raise ValueError(
                        f"{chosen[spec.group]}=True and {item.name}=True; expected at most one"
                    )
                chosen[spec.group] = item.name


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
        if isinstance(spec.values, Flag):
            target.add_argument(*flags, dest=item.name, action="store_true", help=spec.help)
            continue
        choices = spec.values.choices if isinstance(spec.values, Choice) else None
        target.add_argument(
            *flags,
            dest=item.name,
            type=_argument_type(spec.values),
            choices=choices,
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
