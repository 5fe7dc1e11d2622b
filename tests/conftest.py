"""Shared fixtures: one full synthesis per shipped scenario per test session.

``make test`` runs the suite on two pytest-xdist workers with xdist's own group scheduling,
``--dist loadgroup --no-loadscope-reorder``: every test that uses ``synthesis_run``,
``synthesis`` or ``synthesized`` gets its scenario's ``xdist_group`` mark
(``pytest_collection_modifyitems`` below), so each scenario is synthesized once, by one worker;
the collection is sorted so that the groups and the slow tests come first (``SCHEDULE``), and
``--no-loadscope-reorder`` makes xdist hand the groups out in that order (by default it hands
out the largest first), so that the two workers start with the long syntheses and end together.

pytest-xdist 3.8's ``loadgroup`` does not group under pytest 9.2 (pytest-dev/pytest-xdist#1386:
xdist marks a test's group in ``Node._nodeid``, which pytest 9.2 no longer reads), so the test
extra asks for ``pytest<9.2`` and ``_warn_if_ungrouped`` warns with a later one.
"""

from __future__ import annotations

import gc
import logging
import os
import resource
import shutil
import time
from collections import defaultdict
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import dataclass
from importlib.metadata import version
from io import StringIO
from pathlib import Path

import pytest
import scipy.linalg  # noqa: F401  (loads SciPy's OpenBLAS before the limit below)
from threadpoolctl import threadpool_limits

import pipeline
from pipeline.runtime.synthesis import Synthesis

# single-threaded BLAS, as in the pipeline's runs: the stage functions tests call directly
# multiply small matrices, where OpenBLAS's threads cost more than they save. threadpoolctl
# limits the libraries loaded when it is called: SciPy's own OpenBLAS (L-BFGS-B's, scipy.libs)
# is loaded first (imported after the limit, it kept 2 threads: its L-BFGS-B steps took ~2.5 ms
# instead of ~5 us on a busy machine, 16 s of CPU instead of 5 s for the stage conformance
# module's fixture)
threadpool_limits(limits=1, user_api="blas")

E2E_SAMPLES = 1000  # quadrotor_hill_flythrough: the end-to-end tests reuse its run
CI_SYNTHESIS_SAMPLES = 300  # every other shipped scenario: the CI safety check only
SAMPLES = {"quadrotor_hill_flythrough": E2E_SAMPLES}
SYNTHESIS_FIXTURES = {"synthesis_run", "synthesis", "synthesized", "synthesized_constant"}
# quadrotor_hill_flythrough ships the funnel certificate; the tests of the constant certificate's
# file (/1) and report read a run of it with --certificate constant (``synthesized_constant``), made
# from the funnel run's folder: both runs are in quadrotor_hill_flythrough's group


def synthesis_group(scenario: str) -> str:
    """The xdist group of the tests that read ``scenario``'s session synthesis."""
    return f"synthesis-{scenario}"


# the tests that read ``quadrotor_funnel_artifact`` (about 4 s of CPU), so that one worker makes it
FUNNEL_GROUP = "quadrotor-funnel"

# The order in which the scheduler hands out work: these groups, then the tests marked slow,
# then the rest. With two workers the first goes to one, the second to the other, and the third
# to whichever is free first: quadrotor_hill's synthesis (robust funnels, the longest) runs
# beside the unicycle's from the start.
SCHEDULE = (
    synthesis_group("quadrotor_hill"),
    synthesis_group("unicycle_slalom"),
    synthesis_group("quadrotor_hill_flythrough"),
    synthesis_group("double_integrator"),
    synthesis_group("double_integrator_hold"),
    FUNNEL_GROUP,
)


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--cpu-durations",
        type=int,
        default=None,
        metavar="N",
        help="after the run, list the N tests with the most CPU time (setup, call and teardown "
        "of the worker plus its finished subprocesses; 0: all) and each worker's totals. Not "
        "counted: processes reaped by init, such as the helpers of a Chromium killed with its "
        "process group (the rendering tests' browser)",
    )


CPU_TIME = pytest.StashKey[dict[str, float]]()
COMPILE_TIME = pytest.StashKey[dict[str, float]]()


def _cpu_seconds() -> float:
    """CPU time of this process plus that of its subprocesses waited for so far (s)."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


class _CompileClock:
    """CPU seconds this process spent in numba compilations (outermost ones only: a kernel's
    callees compile inside it), counted when ``--cpu-durations`` is given."""

    def __init__(self) -> None:
        self.seconds = 0.0
        self._depth = 0
        self._start = 0.0

    def install(self) -> None:
        from numba.core import event

        clock = self

        class Listener(event.Listener):
            def on_start(self, _event) -> None:
                if clock._depth == 0:
                    clock._start = time.process_time()
                clock._depth += 1

            def on_end(self, _event) -> None:
                clock._depth -= 1
                if clock._depth == 0:
                    clock.seconds += time.process_time() - clock._start

        event.register("numba:compile", Listener())


_COMPILE = _CompileClock()


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
    start, compiled = _cpu_seconds(), _COMPILE.seconds
    try:
        return (yield)
    finally:
        item.stash.setdefault(CPU_TIME, {})[when] = _cpu_seconds() - start
        item.stash.setdefault(COMPILE_TIME, {})[when] = _COMPILE.seconds - compiled


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo):
    """Carry each phase's CPU time and worker in the report (xdist sends it to the controller)."""
    report = yield
    seconds = item.stash.get(CPU_TIME, {}).get(call.when)
    if seconds is not None:
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        compiled = item.stash.get(COMPILE_TIME, {}).get(call.when, 0.0)
        report.user_properties.extend(
            [("cpu_seconds", seconds), ("compile_seconds", compiled), ("worker", worker)]
        )
    return report


class _CpuTally:
    """Per test: CPU, numba compile CPU and wall seconds summed over its phases, and the worker
    that ran it."""

    def __init__(self) -> None:
        self.cpu: dict[str, float] = defaultdict(float)
        self.compile: dict[str, float] = defaultdict(float)
        self.wall: dict[str, float] = defaultdict(float)
        self.worker: dict[str, str] = {}


_TALLY = _CpuTally()


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    properties = dict(report.user_properties)
    if "cpu_seconds" in properties:
        _TALLY.cpu[report.nodeid] += float(properties["cpu_seconds"])
        _TALLY.compile[report.nodeid] += float(properties.get("compile_seconds", 0.0))
        _TALLY.wall[report.nodeid] += report.duration
        _TALLY.worker[report.nodeid] = str(properties["worker"])


def pytest_terminal_summary(terminalreporter, config: pytest.Config) -> None:
    count = config.getoption("cpu_durations")
    if count is None or not _TALLY.cpu:
        return
    write = terminalreporter.write_line
    terminalreporter.section(
        "CPU time per test (s; worker plus finished subprocesses; of it numba compiling in the "
        "worker)"
    )
    ranked = sorted(_TALLY.cpu, key=_TALLY.cpu.__getitem__, reverse=True)
    for nodeid in ranked[: count or None]:
        write(
            f"{_TALLY.cpu[nodeid]:8.2f} cpu {_TALLY.compile[nodeid]:6.2f} compile "
            f"{_TALLY.wall[nodeid]:8.2f} wall {_TALLY.worker[nodeid]:>5}  {nodeid}"
        )
    for worker in sorted(set(_TALLY.worker.values())):
        tests = [n for n in _TALLY.cpu if _TALLY.worker[n] == worker]
        cpu = sum(_TALLY.cpu[n] for n in tests)
        compiled = sum(_TALLY.compile[n] for n in tests)
        wall = sum(_TALLY.wall[n] for n in tests)
        write(
            f"worker {worker}: {len(tests)} tests, {cpu:.1f} s cpu ({compiled:.1f} s compiling), "
            f"{wall:.1f} s wall"
        )
    cpu, wall = sum(_TALLY.cpu.values()), sum(_TALLY.wall.values())
    compiled = sum(_TALLY.compile.values())
    write(f"all tests: {cpu:.1f} s cpu ({compiled:.1f} s compiling), {wall:.1f} s wall")


@pytest.hookimpl(tryfirst=True)  # before xdist's own hook reads the groups in each worker
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark each test that reads a session synthesis with its scenario's ``xdist_group``: the
    ``name`` parameter for ``synthesis(name)``, quadrotor_hill_flythrough for ``synthesized`` (a
    test that calls ``synthesis("other")`` says so with its own
    ``xdist_group(synthesis_group("other"))``);
    each other test that reads ``quadrotor_funnel_artifact`` with ``FUNNEL_GROUP``."""
    for item in items:
        if item.get_closest_marker("xdist_group"):  # a test may name its group
            continue
        fixtures = set(getattr(item, "fixturenames", ()))
        used = SYNTHESIS_FIXTURES & fixtures
        if not used:
            if "quadrotor_funnel_artifact" in fixtures:
                item.add_marker(pytest.mark.xdist_group(FUNNEL_GROUP))
            continue
        callspec = getattr(item, "callspec", None)
        params = callspec.params if callspec is not None else {}
        if used & {"synthesized", "synthesized_constant"} or "name" not in params:
            scenario = "quadrotor_hill_flythrough"
        else:
            scenario = str(params["name"])
        item.add_marker(pytest.mark.xdist_group(synthesis_group(scenario)))


def pytest_configure(config: pytest.Config) -> None:
    if config.getoption("cpu_durations") is not None:
        _COMPILE.install()
    _warn_if_ungrouped(config)
    config.pluginmanager.register(_Schedule(), "schedule")


class _Schedule:
    """Collection order = the order in which ``--dist loadgroup --no-loadscope-reorder`` hands
    work out: the groups of ``SCHEDULE``, then tests marked ``slow``, then the rest, each in
    collection order (a stable sort)."""

    @pytest.hookimpl(trylast=True)  # after pytest's own reordering by parametrized fixtures
    def pytest_collection_modifyitems(self, items: list[pytest.Item]) -> None:
        first = {group: rank for rank, group in enumerate(SCHEDULE)}

        def rank(item: pytest.Item) -> int:
            for marker in item.iter_markers("xdist_group"):
                if marker.args and str(marker.args[0]) in first:
                    return first[str(marker.args[0])]
            return len(SCHEDULE) + (0 if item.get_closest_marker("slow") else 1)

        items.sort(key=rank)


def _warn_if_ungrouped(config: pytest.Config) -> None:
    """Under ``--dist loadgroup``, warn if this pytest-xdist cannot group with this pytest
    (pytest-dev/pytest-xdist#1386, up to xdist 3.8 at least): each worker would then repeat the
    session syntheses the other makes."""
    if config.getoption("dist", None) != "loadgroup" or "PYTEST_XDIST_WORKER" in os.environ:
        return
    xdist = tuple(int(part) for part in version("pytest-xdist").split(".")[:2])
    if pytest.version_tuple[:2] >= (9, 2) and xdist <= (3, 8):
        config.issue_config_time_warning(
            pytest.PytestConfigWarning(
                f"pytest-xdist {version('pytest-xdist')}'s --dist loadgroup does not group under "
                f"pytest {pytest.__version__} (pytest-dev/pytest-xdist#1386): each worker "
                "synthesizes every scenario it needs; install the test extra (pytest<9.2)"
            ),
            stacklevel=2,
        )


@dataclass(frozen=True, kw_only=True)
class SessionRun:
    """``pipeline.synthesize(name, samples=samples)`` as a user runs it: from the empty directory
    ``cwd`` (outputs in ``cwd/reports/NAME``), with the records the ``pipeline`` logger emitted
    at INFO and all the library printed (it should print nothing)."""

    result: Synthesis
    samples: int
    cwd: Path
    records: tuple[logging.LogRecord, ...]
    printed: str

    @property
    def out(self) -> Path:
        return self.cwd / "reports" / self.result.scenario


def _synthesize_from_empty_directory(
    name: str, where: Path, samples: int, certificate: str | None = None
) -> SessionRun:
    records: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = records.append  # type: ignore[method-assign]
    logger = logging.getLogger("pipeline")
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    printed = StringIO()
    try:
        with pytest.MonkeyPatch.context() as patch, redirect_stdout(printed):
            with redirect_stderr(printed):
                patch.chdir(where)
                result = pipeline.synthesize(name, samples=samples, certificate=certificate)
    finally:
        logger.removeHandler(handler)
        logger.setLevel(logging.NOTSET)
    return SessionRun(
        result=result,
        samples=samples,
        cwd=where,
        records=tuple(records),
        printed=printed.getvalue(),
    )


_RUNNING: list[pytest.Item] = []  # the test being run (setup, call, teardown)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None):
    _RUNNING.append(item)
    try:
        return (yield)
    finally:
        _RUNNING.pop()


def _require_group(name: str) -> None:
    """Fail the running test unless it is in ``name``'s xdist group: one that reads another
    scenario's session run (the group marks it automatically only for the ``name`` parameter and
    ``synthesized``) had that scenario synthesized a second time, by the other worker, whenever
    the scheduler gave it to the worker not running that scenario's group."""
    if not _RUNNING:
        return
    item = _RUNNING[-1]
    groups = sorted({str(m.args[0]) for m in item.iter_markers("xdist_group") if m.args})
    if synthesis_group(name) not in groups:
        pytest.fail(
            f"{item.nodeid} reads {name}'s session synthesis from xdist group(s) {groups}: mark "
            f"it @pytest.mark.xdist_group({synthesis_group(name)!r})",
            pytrace=False,
        )


@pytest.fixture(scope="session")
def synthesis_run(tmp_path_factory: pytest.TempPathFactory):
    """Factory: ``synthesis_run(name, certificate=None)`` -> the ``SessionRun`` of ``name``
    (with ``certificate``, default the scenario's) with ``SAMPLES.get(name,
    CI_SYNTHESIS_SAMPLES)`` Monte Carlo samples, run once per session (with a ``certificate``:
    on a copy of the default run's folder, so the same worker makes both: one xdist group).
    Tests that only read it share it; a test that changes files works on a copy of ``out``."""
    runs: dict[tuple[str, str | None], SessionRun] = {}

    def run(name: str, certificate: str | None = None) -> SessionRun:
        _require_group(name)
        if (name, certificate) not in runs:
            where = tmp_path_factory.mktemp(name)
            if certificate is not None:
                # as a user's second run with --certificate: in a copy of the first run's folder
                # (the stages before the certificate's reused, not computed again)
                shutil.copytree(run(name).out, where / "reports" / name)
            runs[name, certificate] = _synthesize_from_empty_directory(
                name, where, SAMPLES.get(name, CI_SYNTHESIS_SAMPLES), certificate
            )
            _freeze_the_heap()  # the run's results and the kernels it compiled or loaded
        return runs[name, certificate]

    return run


@pytest.fixture(scope="session")
def synthesis(synthesis_run):
    """Factory: ``synthesis(name)`` -> ``(exit_code, out)`` of ``synthesis_run(name)``."""

    def run(name: str) -> tuple[int, Path]:
        session = synthesis_run(name)
        return session.result.exit_code, session.out

    return run


@pytest.fixture(scope="session")
def synthesized(synthesis):
    """``(exit_code, out)`` of ``synthesize quadrotor_hill_flythrough`` with 1,000 Monte Carlo
    samples."""
    return synthesis("quadrotor_hill_flythrough")


@pytest.fixture(scope="session")
def synthesized_constant(synthesis_run):
    """``(exit_code, out)`` of ``synthesize quadrotor_hill_flythrough --certificate constant``
    (1,000 Monte Carlo samples) in a copy of ``synthesized``'s folder: the constant certificate's
    ``safety-controller/1`` and report."""
    session = synthesis_run("quadrotor_hill_flythrough", certificate="constant")
    return session.result.exit_code, session.out


@pytest.fixture(scope="session")
def funnel_artifact(tmp_path_factory):
    """``(scenario, path)``: a ``safety-controller/2`` file from real funnels (about 2 s).

    double_integrator demos 0 and 3 over their first 3 s (the full demos' funnels are slower and
    not the point here), Goal moved around where they end, and Init the box ``[0.1, 0.25] x
    [0.1, 0.55]`` at rest: each funnel's ``E(0)`` is asked to hold its half of Init (split at
    y = 0.33), so together they cover it.
    """
    import dataclasses

    import numpy as np
    from shapely.geometry import box

    from pipeline.model.scenario import load_scenario
    from pipeline.model.simulate import simulate
    from pipeline.numerics.funnel.synthesis import synthesize_funnel
    from stages.controller import emit_funnel_controller

    scenario = load_scenario("double_integrator", check_demos=False)
    demos = [scenario.demos[0], scenario.demos[3]]
    trajectories = [simulate(scenario.dynamics, d.x0, d.us[:30], scenario.Ts) for d in demos]
    ends = np.array([tr.xs[-1, :2] for tr in trajectories])
    lower, upper = np.array([0.1, 0.1, 0.0, 0.0]), np.array([0.25, 0.55, 0.0, 0.0])
    scenario = dataclasses.replace(
        scenario,
        init_lower=lower,
        init_upper=upper,
        goal=box(*(ends.min(axis=0) - 1.0), *(ends.max(axis=0) + 1.0)),
    )
    funnels = []
    for trajectory, (bottom, top) in zip(trajectories, [(0.1, 0.33), (0.33, 0.55)], strict=True):
        part_lower, part_upper = lower.copy(), upper.copy()
        part_lower[1], part_upper[1] = bottom, top
        x0 = trajectory.xs[0]
        d = 1.05 * np.maximum(np.abs(part_lower - x0), np.abs(part_upper - x0))
        # the ellipse 2 diag(d^2) holds the box x0 +- d (its corners at level 1 / 1.05^2)
        funnel = synthesize_funnel(scenario, trajectory, initial=2 * np.diag(d**2))
        assert funnel.success, funnel.message
        funnels.append(funnel)
    path = tmp_path_factory.mktemp("funnel") / "controller.json"
    emit_funnel_controller(scenario, trajectories, funnels, path)
    return scenario, path


@pytest.fixture(scope="session")
def quadrotor_funnel_artifact(tmp_path_factory):
    """``(scenario, path)``: a ``safety-controller/2`` file for quadrotor_hill_flythrough from one
    real funnel (demo 0 in full, the scenario's state bounds; about 20-25 s), the shipped scenario
    unchanged (its Init is not all covered by one funnel)."""
    from pipeline.model.scenario import load_scenario
    from pipeline.model.simulate import simulate
    from pipeline.numerics.funnel.synthesis import synthesize_funnel
    from stages.controller import emit_funnel_controller

    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    demo = scenario.demos[0]
    trajectory = simulate(scenario.dynamics, demo.x0, demo.us, scenario.Ts)
    funnel = synthesize_funnel(scenario, trajectory, state_bounds=scenario.state_bounds)
    assert funnel.success, funnel.message
    path = tmp_path_factory.mktemp("quadrotor_funnel") / "controller.json"
    emit_funnel_controller(scenario, [trajectory], [funnel], path)
    return scenario, path


def pytest_collection_finish(session: pytest.Session) -> None:
    _freeze_the_heap()  # the pipeline, numba, sympy, cvxpy, matplotlib and the test modules


# fewer young-generation collections: the default (700, 10, 10) ran ~2,750 collections for two
# modules of the double_integrator group; (20000, 20, 20) ran 51 and took ~0.6 s less CPU (of
# ~23 s; measured with gc.callbacks). Garbage cycles are freed later, not kept.
gc.set_threshold(20_000, 20, 20)


def _freeze_the_heap() -> None:
    """Take every object alive now out of the cyclic garbage collector's reach (``gc.freeze``,
    after a full collection so that no garbage is kept). Each full collection walks every object
    it tracks: with the imports and the session syntheses in the heap they cost the two workers
    19.8-21.8 s of CPU per run with an empty kernel cache, 9.5-10.7 s with these freezes
    (measured with ``gc.callbacks``). Reference counting frees frozen objects as before."""
    gc.collect()
    gc.freeze()
