"""The compiled kernels' cache: one process at a time compiles a kernel module (the others wait
and read numba's disk cache), and a factor of 1.0 does not make a new kernel module."""

from __future__ import annotations

import fcntl
import threading
from pathlib import Path

import numpy as np
import pytest
import sympy

from pipeline.model.dynamics import Dynamics
from pipeline.model.scenario import load_scenario
from pipeline.numerics.kernels.compiled import dynamics_source, exact_units, load_kernels
from tests.test_scenario import write_scenario


def test_a_kernel_waits_while_another_process_compiles_its_module(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The lock held (as by another process): the first call of a kernel, which compiles it,
    waits; once the lock is released it compiles and returns the right value."""
    monkeypatch.setenv("SAFETY_KERNEL_CACHE", str(tmp_path))
    v, u = sympy.symbols("v u", real=True)
    kernels = load_kernels(Dynamics.from_expressions([v], [u], [u - 0.318309886 * v]))
    (source,) = tmp_path.glob("kernels_*.py")
    results: list[bool] = []
    with source.with_suffix(".lock").open("ab") as other:
        fcntl.flock(other, fcntl.LOCK_EX)
        first = threading.Thread(
            target=lambda: results.append(kernels.all_finite(np.array([0.0, np.nan])))
        )
        first.start()
        first.join(1.0)
        assert first.is_alive() and not results, "compiled while another process held the lock"
    first.join(60.0)
    assert results == [False]


@pytest.mark.parametrize(
    ("expression", "expected"),
    [
        ("1.0*x", "x"),
        ("-1.0*x*y", "-x*y"),
        ("sin(1.0*x) - 1.0", "sin(x) - 1.0"),  # a bare 1.0 only as the whole expression
        ("-1.0", "-1"),
        ("2.0*x + 1.0", "2.0*x + 1.0"),  # only unit factors, and bare +-1.0
        ("x**(-1.0)", "x**(-1.0)"),  # pow(x, -1.0) is not 1/x to the last bit
    ],
)
def test_exact_units_drops_only_factors_of_one(expression: str, expected: str) -> None:
    x, y = sympy.symbols("x y")
    parsed = sympy.sympify(expression, locals={"x": x, "y": y}, evaluate=True)
    assert str(exact_units(parsed)) == expected


def test_a_parameter_of_one_shares_the_kernels_of_the_scenario_without_it(tmp_path: Path) -> None:
    """The test fixture's ``vX: k*aX`` with ``k: 1.0`` compiles to the shipped double
    integrator's ``vX: aX`` kernel source (one compiled module for both)."""
    fixture = load_scenario(write_scenario(tmp_path / "fixture"), check_demos=False)
    assert (
        fixture.dynamics.expressions[2]
        != load_scenario("double_integrator").dynamics.expressions[2]
    )
    shipped = load_scenario("double_integrator", check_demos=False)
    assert dynamics_source(fixture.dynamics) == dynamics_source(shipped.dynamics)
