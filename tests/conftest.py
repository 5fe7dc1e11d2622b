"""Shared fixtures: one full synthesis per shipped scenario per test session.

``make test`` runs the suite on two pytest-xdist workers with ``--dist loadgroup``: every test
that uses ``synthesis`` or ``synthesized`` is put in the group of its scenario
(``pytest_collection_modifyitems`` below), so each scenario is synthesized once, by one worker.
"""

from __future__ import annotations

import pytest

from pipeline.runtime.api import synthesize

E2E_SAMPLES = 1000  # quadrotor_hill: the end-to-end tests reuse its run
CI_SYNTHESIS_SAMPLES = 300  # every other shipped scenario: the CI safety check only
SAMPLES = {"quadrotor_hill": E2E_SAMPLES}
SYNTHESIS_FIXTURES = {"synthesis", "synthesized"}


def synthesis_group(scenario: str) -> str:
    """The xdist group of the tests that read ``scenario``'s session synthesis."""
    return f"synthesis-{scenario}"


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
    from pipeline.numerics.funnel import synthesize_funnel
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
    """``(scenario, path)``: a ``safety-controller/2`` file for quadrotor_hill from one real
    funnel (demo 0 in full, the scenario's state bounds; about 20-25 s), the shipped scenario
    unchanged (its Init is not all covered by one funnel)."""
    from pipeline.model.scenario import load_scenario
    from pipeline.model.simulate import simulate
    from pipeline.numerics.funnel import synthesize_funnel
    from stages.controller import emit_funnel_controller

    scenario = load_scenario("quadrotor_hill", check_demos=False)
    demo = scenario.demos[0]
    trajectory = simulate(scenario.dynamics, demo.x0, demo.us, scenario.Ts)
    funnel = synthesize_funnel(scenario, trajectory, state_bounds=scenario.state_bounds)
    assert funnel.success, funnel.message
    path = tmp_path_factory.mktemp("quadrotor_funnel") / "controller.json"
    emit_funnel_controller(scenario, [trajectory], [funnel], path)
    return scenario, path
