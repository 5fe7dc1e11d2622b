"""Shared fixtures: one full synthesis per shipped scenario per test session.

``make test`` runs the suite on two pytest-xdist workers with ``--dist loadgroup``: every test
that uses ``synthesis`` or ``synthesized`` is put in the group of its scenario
(``pytest_collection_modifyitems`` below), so each scenario is synthesized once, by one worker.
"""

from __future__ import annotations

import os
import resource
import time
from collections import defaultdict

import pytest

from pipeline.runtime.api import synthesize

E2E_SAMPLES = 1000  # quadrotor_hill: the end-to-end tests reuse its run
CI_SYNTHESIS_SAMPLES = 300  # every other shipped scenario: the CI safety check only
SAMPLES = {"quadrotor_hill": E2E_SAMPLES}
SYNTHESIS_FIXTURES = {"synthesis", "synthesized"}


def synthesis_group(scenario: str) -> str:
    """The xdist group of the tests that read ``scenario``'s session synthesis."""
    return f"synthesis-{scenario}"


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--cpu-durations",
        type=int,
        default=None,
        metavar="N",
        help="after the run, list the N tests with the most CPU time (setup, call and teardown "
        "of the worker plus its finished subprocesses; 0: all) and each worker's totals",
    )


CPU_TIME = pytest.StashKey[dict[str, float]]()


def _cpu_seconds() -> float:
    """CPU time of this process plus that of its subprocesses waited for so far (s)."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


@pytest.hookimpl(wrapper=True)
def pytest_runtest_setup(item: pytest.Item):
    return (yield from _timed(item, "setup"))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item):
    return (yield from _timed(item, "call"))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_teardown(item: pytest.Item):
    return (yield from _timed(item, "teardown"))


def _timed(item: pytest.Item, when: str):
    start = _cpu_seconds()
    try:
        return (yield)
    finally:
        item.stash.setdefault(CPU_TIME, {})[when] = _cpu_seconds() - start


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo):
    """Carry each phase's CPU time and worker in the report (xdist sends it to the controller)."""
    report = yield
    seconds = item.stash.get(CPU_TIME, {}).get(call.when)
    if seconds is not None:
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        report.user_properties.extend([("cpu_seconds", seconds), ("worker", worker)])
    return report


class _CpuTally:
    """Per test: CPU and wall seconds summed over its phases, and the worker that ran it."""

    def __init__(self) -> None:
        self.cpu: dict[str, float] = defaultdict(float)
        self.wall: dict[str, float] = defaultdict(float)
        self.worker: dict[str, str] = {}


_TALLY = _CpuTally()


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    properties = dict(report.user_properties)
    if "cpu_seconds" in properties:
        _TALLY.cpu[report.nodeid] += float(properties["cpu_seconds"])
        _TALLY.wall[report.nodeid] += report.duration
        _TALLY.worker[report.nodeid] = str(properties["worker"])


def pytest_terminal_summary(terminalreporter, config: pytest.Config) -> None:
    count = config.getoption("cpu_durations")
    if count is None or not _TALLY.cpu:
        return
    write = terminalreporter.write_line
    terminalreporter.section("CPU time per test (s; worker plus finished subprocesses)")
    ranked = sorted(_TALLY.cpu, key=_TALLY.cpu.__getitem__, reverse=True)
    for nodeid in ranked[: count or None]:
        write(
            f"{_TALLY.cpu[nodeid]:8.2f} cpu {_TALLY.wall[nodeid]:8.2f} wall "
            f"{_TALLY.worker[nodeid]:>5}  {nodeid}"
        )
    for worker in sorted(set(_TALLY.worker.values())):
        tests = [n for n in _TALLY.cpu if _TALLY.worker[n] == worker]
        cpu = sum(_TALLY.cpu[n] for n in tests)
        wall = sum(_TALLY.wall[n] for n in tests)
        write(f"worker {worker}: {len(tests)} tests, {cpu:.1f} s cpu, {wall:.1f} s wall")
    cpu, wall = sum(_TALLY.cpu.values()), sum(_TALLY.wall.values())
    write(f"all tests: {cpu:.1f} s cpu, {wall:.1f} s wall")


@pytest.hookimpl(tryfirst=True)  # before xdist's own hook reads the groups in each worker
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark each test that reads a session synthesis with its scenario's ``xdist_group``: the
    ``name`` parameter for ``synthesis(name)``, quadrotor_hill for ``synthesized`` (a test that
    calls ``synthesis("other")`` says so with its own ``xdist_group(synthesis_group("other"))``)."""
    for item in items:
        used = SYNTHESIS_FIXTURES & set(getattr(item, "fixturenames", ()))
        if not used or item.get_closest_marker("xdist_group"):  # a test may name its group
            continue
        callspec = getattr(item, "callspec", None)
        params = callspec.params if callspec is not None else {}
        if "synthesized" in used or "name" not in params:
            scenario = "quadrotor_hill"
        else:
            scenario = str(params["name"])
        item.add_marker(pytest.mark.xdist_group(synthesis_group(scenario)))
    if getattr(config.option, "loadgroup", False):
        _suffix_groups(items)


def _suffix_groups(items: list[pytest.Item]) -> None:
    """In an xdist worker under ``--dist loadgroup``: append ``@GROUP`` to each grouped test's
    node id, which is what the scheduler groups by. xdist's own hook does it by setting
    ``Node._nodeid``, which pytest 9 no longer reads (the id is ``Node._id``), so without this
    ``loadgroup`` schedules like ``load`` and each worker repeats the session syntheses."""
    from _pytest.nodeid import coerce_node_id

    for item in items:
        groups = sorted({str(m.args[0]) for m in item.iter_markers("xdist_group") if m.args})
        if groups and "@" not in item.nodeid and hasattr(item, "_id"):
            item._id = coerce_node_id(f"{item.nodeid}@{'_'.join(groups)}")


@pytest.fixture(scope="session")
def synthesis(tmp_path_factory):
    """Factory: ``synthesis(name)`` -> ``(exit_code, out)`` of ``synthesize name`` with
    ``SAMPLES.get(name, CI_SYNTHESIS_SAMPLES)`` Monte Carlo samples, run once per session."""
    runs: dict[str, tuple[int, object]] = {}

    def run(name: str):
        if name not in runs:
            out = tmp_path_factory.mktemp(name)
            result = synthesize(name, out=out, samples=SAMPLES.get(name, CI_SYNTHESIS_SAMPLES))
            runs[name] = (result.exit_code, out)
        return runs[name]

    return run


@pytest.fixture(scope="session")
def synthesized(synthesis):
    """``(exit_code, out)`` of ``synthesize quadrotor_hill`` with 1,000 Monte Carlo samples."""
    return synthesis("quadrotor_hill")
