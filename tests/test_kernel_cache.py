"""The compiled kernels' cache: one process at a time compiles a kernel module (the others wait
and read numba's disk cache), a factor of 1.0 does not make a new kernel module, the functions of
``shared`` compile once for every dynamics, and an edit of ``shared`` gives new kernel modules."""

from __future__ import annotations

import fcntl
import hashlib
import threading
import weakref
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import sympy
from numba.core import event

from pipeline.model.dynamics import Dynamics
from pipeline.model.scenario import load_scenario
from pipeline.numerics.kernels import compiled, shared
from pipeline.numerics.kernels.compiled import dynamics_source, exact_units, load_kernels
from tests.helpers.scenario_files import write_scenario


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
        out = np.empty(1)
        first = threading.Thread(  # f_eval: defined in the generated module, not in shared
            target=lambda: results.append(kernels.f_eval(np.zeros(1), np.ones(1), out) or out[0])
        )
        first.start()
        first.join(1.0)
        assert first.is_alive() and not results, "compiled while another process held the lock"
    first.join(60.0)
    assert results == [1.0]


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


class _Compiles(event.Listener):
    """Counts numba's compilations (not loads from its disk cache) by function name."""

    def __init__(self) -> None:
        self.count: Counter[str] = Counter()

    def on_start(self, ev: event.Event) -> None:
        self.count[ev.data["dispatcher"].py_func.__name__] += 1

    def on_end(self, ev: event.Event) -> None:
        pass


def test_two_dynamics_compile_their_loops_but_share_the_dynamics_free_functions(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``rollout_grid`` (generated per dynamics) compiles once per module; ``all_finite``,
    which it calls, from ``shared``, at most once in the process (none if already compiled)."""
    monkeypatch.setenv("SAFETY_KERNEL_CACHE", str(tmp_path))
    v, u = sympy.symbols("v u", real=True)
    compiles = _Compiles()
    with event.install_listener("numba:compile", compiles):
        for rate in (0.125, 0.25):
            kernels = load_kernels(Dynamics.from_expressions([v], [u], [u - rate * v]))
            U, X, Y = np.empty((3, 1)), np.empty((7, 1)), np.empty((6, 4, 1))
            one = np.ones((3, 1))
            zero = np.zeros((3, 1))
            assert kernels.rollout_grid(np.zeros(1), one, zero, one, True, 0.1, 2, U, X, Y)
            assert U[0, 0] == 1.0 and U[1, 0] > 1.0  # u = 1 + x, x grows from 0
    assert compiles.count["rollout_grid"] == 2
    assert compiles.count["all_finite"] <= 1


def test_an_edit_of_the_shared_functions_gives_new_kernel_modules(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """numba's cache of a generated kernel holds the shared functions it calls but checks only
    the generated file: the module's name (its cache key) hashes ``shared``'s source too, as this
    process imported it (the code it links)."""
    monkeypatch.setenv("SAFETY_KERNEL_CACHE", str(tmp_path / "cache"))
    v, u = sympy.symbols("v u", real=True)
    dynamics = Dynamics.from_expressions([v], [u], [u - 0.375 * v])
    before = load_kernels(dynamics)
    monkeypatch.setattr(shared, "SOURCE", shared.SOURCE + "\n# an edit\n")
    fresh: weakref.WeakKeyDictionary[Dynamics, Any] = weakref.WeakKeyDictionary()
    monkeypatch.setattr(compiled, "_BY_DYNAMICS", fresh)
    after = load_kernels(dynamics)
    assert after.__name__ != before.__name__
    assert len(list((tmp_path / "cache").glob("kernels_*.py"))) == 2


def test_numba_keys_its_cache_of_shared_on_the_file_contents() -> None:
    """``shared`` is an ordinary module: numba's own cache of it is fresh only while its stamp
    matches, and numba (0.68 here) stamps a file by the SHA-256 of its bytes, so an edit of
    ``shared.py`` recompiles it and a ``touch`` does not (fails if a numba version stamps
    otherwise, e.g. by modification time and size as older ones did)."""
    stamp = shared.all_finite._cache._impl.locator.get_source_stamp()
    assert stamp == hashlib.sha256(Path(shared.__file__).read_bytes()).digest()


def test_threads_asking_at_once_get_one_module(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The Monte Carlo stage's side thread and its chunks may ask for the kernels at the same
    moment: the module is generated and imported once."""
    monkeypatch.setenv("SAFETY_KERNEL_CACHE", str(tmp_path))
    monkeypatch.setattr(compiled, "_LOADED", {})
    monkeypatch.setattr(compiled, "_BY_DYNAMICS", weakref.WeakKeyDictionary())
    v, u = sympy.symbols("v u", real=True)
    dynamics = Dynamics.from_expressions([v], [u], [u - 0.25 * v])
    executed = Counter[str]()
    original = compiled.importlib.util.module_from_spec

    def counted(spec: Any) -> Any:
        executed[spec.name] += 1
        return original(spec)

    monkeypatch.setattr(compiled.importlib.util, "module_from_spec", counted)
    start = threading.Barrier(4)
    modules: list[Any] = []

    def ask() -> None:
        start.wait()
        modules.append(load_kernels(dynamics))

    threads = [threading.Thread(target=ask) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(modules) == 4 and all(m is modules[0] for m in modules)
    assert list(executed.values()) == [1]
