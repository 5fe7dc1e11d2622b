"""Stages ``montecarlo`` and ``stress`` fly a ``safety-controller/2`` file (one funnel per
trajectory) as they fly ``/1``: the runs from starts inside the funnel never fail, the starts
outside it are counted as uncovered, and the stress campaign compares the funnel's feedback with
the reference flown open loop."""

from __future__ import annotations

from stages.montecarlo import validate_closed_loop
from stages.stress import stress_test


def test_monte_carlo_and_stress_fly_a_funnel_file(quadrotor_funnel_artifact):
    scenario, path = quadrotor_funnel_artifact
    result = validate_closed_loop(scenario, path, samples=400, chunk=200, seed=3)
    failures = dict(result.failures)  # a read-only view (results are frozen)
    uncovered = failures.pop("uncovered")
    assert 0 < uncovered < 400  # one funnel covers part of Init
    assert failures == dict.fromkeys(failures, 0), result.message
    assert result.min_clearance > 0
    stress = stress_test(scenario, path, samples=60, seed=1)
    assert stress.success, stress.message
    assert stress.with_feedback.samples == stress.without_feedback.samples == 60
    assert stress.with_feedback.failed_fraction < stress.without_feedback.failed_fraction


def test_the_reports_paths_are_the_first_runs_drawn_each_simulated_alone(synthesized):
    """The drawn paths come from one batch of the compiled kernel: the same paths, in the same
    order, as the oracle simulating each chunk's first two runs around each trajectory on its
    own (quadrotor_hill_flythrough's nine funnels: the batch regroups the runs by trajectory), cut
    at ``count``."""
    import numpy as np

    from pipeline.controller import load
    from pipeline.model.scenario import load_scenario
    from pipeline.numerics.closed_loop.simulate import check_runs
    from stages.montecarlo import _drawn_paths, _uniform_init

    _, out = synthesized
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    controller = load(out / "controller.json")
    chunks, streams = [60, 60], np.random.SeedSequence(4).spawn(2)
    count = 25
    paths = _drawn_paths(scenario, controller, chunks, streams, count)
    alone, owners = [], []
    for size, stream in zip(chunks, streams, strict=True):
        x0 = _uniform_init(scenario, np.random.default_rng(stream), size)
        index, _ = controller.select(x0)
        for i in np.unique(index):
            for start in x0[np.flatnonzero(index == i)[:2]]:
                _, (group,) = check_runs(scenario, controller, start[None])
                alone.append(group[0, :: max(1, group.shape[1] // 200)])
                owners.append(int(i))
    assert len(set(owners[:count])) > 2 and len(alone) > count  # several trajectories, a cut
    assert len(paths) == count
    for batched, single in zip(paths, alone[:count], strict=True):
        np.testing.assert_allclose(batched, single, rtol=0, atol=1e-9)
