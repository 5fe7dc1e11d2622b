"""Demonstration files: one CSV per flight, one row per held input sample.

Format (``#`` lines are comments and are kept as the file's header)::

    # synthetic demonstration ...
    t,ua,ub
    0.0,9.81,0.0
    0.1,10.2,-0.5

(the header is ``t`` and the scenario's input names, here two inputs ``ua``, ``ub``).

Row ``k`` holds ``u[k]`` on ``[k Ts, (k+1) Ts)``; ``t`` must equal ``k Ts``, so the flight lasts
``N Ts`` with ``N`` the number of rows. With input bounds given, every input must lie within them.
"""

from __future__ import annotations

import csv
import io
import math
import re
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.io.artifacts import atomic_write_text
from pipeline.io.errors import ScenarioError
from pipeline.io.files import TEXT_MAX_BYTES, FileRefused, read_bytes
from pipeline.model.dynamics import FloatArray
from pipeline.model.frozen import freeze_fields, reduce_fields

# A decimal number in ASCII (nan and inf too, refused below with their own message).
NUMBER = re.compile(r"[+-]?(?:(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?|nan|inf|infinity)", re.I | re.A)
TIME_TOLERANCE = 1e-6
BOUND_TOLERANCE = 1e-9


@dataclass(frozen=True)
class Demo:
    """A demonstration: ``x0 (n,)`` and held inputs ``us (N, m)``; lasts ``N Ts``. Deeply
    frozen: the arrays are read-only copies."""

    name: str
    file: Path
    x0: FloatArray
    us: FloatArray

    def __post_init__(self) -> None:
        freeze_fields(self)

    def __reduce__(self) -> tuple[object, ...]:
        return reduce_fields(self)

    @property
    def N(self) -> int:
        return int(self.us.shape[0])


def _unreadable(path: Path, reason: str | None) -> ScenarioError:
    return ScenarioError(f"cannot read demo file ({reason})", file=path, expected="a readable CSV")


def read_demo_csv(
    path: Path, input_names: Sequence[str], Ts: float, bounds: FloatArray | None = None
) -> FloatArray:
    """Read a demo CSV into inputs ``(N, m)``, with an error naming the row for any mistake.

    The file must be a regular file of at most 64 MiB (``pipeline.io.files.TEXT_MAX_BYTES``).

    Args:
      bounds: optional (m, 2) input bounds ``[lower, upper]``; a value outside is an error.
    """
    try:
        data = read_bytes(path, TEXT_MAX_BYTES)
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise _unreadable(path, "not UTF-8 text") from None
    except FileRefused as error:  # not a regular file, or larger than the cap
        raise _unreadable(path, error.reason) from None
    except OSError as error:
        raise _unreadable(path, error.strerror) from None
    limits = None if bounds is None else np.asarray(bounds, dtype=np.float64)
    key = (data, tuple(input_names), float(Ts), None if limits is None else limits.tobytes())
    with _PARSED_LOCK:
        parsed = _PARSED.get(key)
    if parsed is None:
        parsed = _parse(path, text.splitlines(), input_names, Ts, bounds)
        parsed.flags.writeable = False
        with _PARSED_LOCK:
            if len(_PARSED) >= PARSED_KEPT:
                del _PARSED[next(iter(_PARSED))]
            _PARSED[key] = parsed
    return parsed.copy()


# The inputs parsed from each demo file's bytes (with the names, Ts and bounds they were checked
# against), once per process: a scenario's demos are read on every load_scenario, and a file
# that parsed is the same inputs whatever its path (a failure is not kept: its message names
# the path)
_PARSED: dict[tuple[object, ...], FloatArray] = {}
_PARSED_LOCK = threading.Lock()
PARSED_KEPT = 256


def _parse(
    path: Path,
    lines: list[str],
    input_names: Sequence[str],
    Ts: float,
    bounds: FloatArray | None,
) -> FloatArray:
    """``read_demo_csv``'s checks and values for the file's ``lines``."""
    expected_header = ["t", *input_names]
    rows: list[list[float]] = []
    header_seen = False
    for number, line in enumerate(lines, start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        cells = [cell.strip() for cell in next(csv.reader([line]))]
        where = f"row {number}"
        if not header_seen:
            if cells != expected_header:
                raise ScenarioError(
                    "wrong header",
                    file=path,
                    field=where,
                    found=",".join(cells),
                    expected=",".join(expected_header),
                )
            header_seen = True
            continue
        if len(cells) != len(expected_header):
            raise ScenarioError(
                f"wrong column count {len(cells)}",
                file=path,
                field=where,
                found=line,
                expected=f"{len(expected_header)} columns ({','.join(expected_header)})",
            )
        bad = next((cell for cell in cells if not NUMBER.fullmatch(cell)), None)
        if bad is not None:  # float() would also take "0_5" (as 5.0) and non-ASCII digits
            raise ScenarioError(
                f"not a number: {bad!r}",
                file=path,
                field=where,
                found=line,
                expected="decimal numbers such as 0.5, -2 or 1e-3",
            )
        values = [float(cell) for cell in cells]
        for name, value in zip(expected_header, values, strict=True):
            if not math.isfinite(value):
                raise ScenarioError(
                    f"non-finite value in column '{name}'",
                    file=path,
                    field=where,
                    found=value,
                    expected="a finite number",
                )
        if bounds is not None:
            for name, value, (lower, upper) in zip(input_names, values[1:], bounds, strict=True):
                if not lower - BOUND_TOLERANCE <= value <= upper + BOUND_TOLERANCE:
                    raise ScenarioError(
                        f"input '{name}' outside its bounds",
                        file=path,
                        field=where,
                        found=value,
                        expected=f"a value in [{lower:g}, {upper:g}] (input_bounds.{name})",
                    )
        k = len(rows)
        if abs(values[0] - k * Ts) > TIME_TOLERANCE:
            raise ScenarioError(
                f"t is not a whole number of samples (sample {k}, Ts = {Ts})",
                file=path,
                field=where,
                found=values[0],
                expected=f"t = {k * Ts:g}: one row per sample, t = k*Ts",
            )
        rows.append(values[1:])
    if not rows:
        raise ScenarioError(
            "no samples", file=path, expected=f"a header {expected_header} and rows"
        )
    return np.array(rows, dtype=np.float64)


def write_demo_csv(
    path: Path, us: FloatArray, input_names: Sequence[str], Ts: float, header: str
) -> None:
    """Write inputs ``us (N, m)`` in the demo format, atomically; ``header`` becomes comments."""
    buffer = io.StringIO()
    for line in header.strip().splitlines():
        buffer.write(f"# {line}\n")
    buffer.write(",".join(["t", *input_names]) + "\n")
    for k, u in enumerate(np.asarray(us)):
        buffer.write(",".join([f"{k * Ts:.10g}", *(f"{value:.6f}" for value in u)]) + "\n")
    atomic_write_text(path, buffer.getvalue())


def demo_entry(file: str, x0: Sequence[float]) -> str:
    """One demonstration as a YAML flow mapping, ``{file: F, x0: [...]}`` (the ``demos:`` list's
    one-line form, written by the pilot and the recorder)."""
    values = ", ".join(repr(float(value) + 0.0) for value in x0)  # + 0.0: no "-0.0"
    return f"{{file: {file}, x0: [{values}]}}"
