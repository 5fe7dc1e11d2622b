"""Numbers as the report and the terminal show them, formatted in one place.

A value that is None, NaN or infinite is never shown as such: it reads ``n/a (reason)``
(``formatted``). The Monte Carlo counts are told as runs failed first, then the failure kinds
(a run can fail in several ways at once, so the kinds need not add up to the runs):
``"335 of 500 runs failed; kinds: uncovered 335, clipping 34"`` (``montecarlo_counts``).
No plotting imports here: the terminal uses this module too.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

NOT_COMPUTED = "not computed"
INFINITE = "infinite"


def formatted(value: float | None, spec: str, reason: str = "") -> str:
    """``value`` by the format ``spec`` (e.g. ``".3f"``), or ``n/a (reason)`` when it is None,
    NaN or infinite (``reason`` defaults to "not computed" or "infinite")."""
    if value is None or math.isnan(value):
        return f"n/a ({reason or NOT_COMPUTED})"
    if math.isinf(value):
        return f"n/a ({reason or INFINITE})"
    return f"{value:{spec}}"


def number(value: float | None, digits: int = 3, reason: str = "") -> str:
    """``value`` with ``digits`` significant digits."""
    return formatted(value, f".{digits}g", reason)


def fixed(value: float | None, decimals: int = 2, reason: str = "") -> str:
    return formatted(value, f".{decimals}f", reason)


def percent(fraction: float | None, decimals: int = 1, reason: str = "") -> str:
    """``fraction`` (0..1) as a percentage."""
    return formatted(fraction, f".{decimals}%", reason)


def seconds(value: float | None, reason: str = "") -> str:
    text = formatted(value, ".1f", reason)
    return text if text.startswith("n/a") else f"{text} s"


def scientific(value: float | None, reason: str = "") -> str:
    return formatted(value, ".2e", reason)


def vector(values: Iterable[float], digits: int = 3) -> str:
    return "[" + ", ".join(number(float(v), digits) for v in values) + "]"


def check(flag: bool) -> str:
    return "yes" if flag else "no"


def margin(value: float, binding: str, decimals: int = 3) -> str:
    """A falsification margin and what binds it: ``"-0.012 (clearance to Unsafe, m)"``;
    ``"n/a (not covered)"`` for a start without one (uncovered or non-finite: -inf)."""
    shown = fixed(value, decimals, binding)
    return f"{shown} ({binding})" if binding and math.isfinite(value) else shown


def runs_failed(samples: int, failed: int) -> str:
    """``"335 of 500 runs failed"``: runs, each counted once however many ways it failed."""
    return f"{failed} of {samples} runs failed"


def failure_kinds(kinds: Mapping[str, int]) -> str:
    """``"kinds: uncovered 335, clipping 34"`` (the kinds that occurred; "" for none)."""
    seen = [f"{kind} {count}" for kind, count in kinds.items() if count]
    return "kinds: " + ", ".join(seen) if seen else ""


def montecarlo_counts(samples: int, failed: int, kinds: Mapping[str, int]) -> str:
    """``"335 of 500 runs failed; kinds: uncovered 335, clipping 34"`` (``"0 of 500 runs
    failed"`` without failures): the one text of the Monte Carlo counts."""
    return "; ".join(part for part in (runs_failed(samples, failed), failure_kinds(kinds)) if part)
