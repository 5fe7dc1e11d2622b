"""Stage ``funnel``: the required initial sets (each start's cell of Init, else the ball slice
(I1)), funnels on the shipped double integrator's demos that hold them and pass the independent
check, unchanged trajectories' funnels reused, a perturbed funnel dropped and said so, and
the result stored and read back like every stage's."""

from __future__ import annotations

import dataclasses
import time
from types import SimpleNamespace

import numpy as np
import pytest

import stages.funnel as funnel_stage
from pipeline.io.artifacts import read_stored, save_result
from pipeline.model.scenario import load_scenario
from pipeline.model.simulate import simulate
from pipeline.numerics.funnel.cells import init_cells
from pipeline.numerics.funnel.check import check_funnel
from pipeline.numerics.verify.nominal import VERIFY_SUBSTEPS
from pipeline.runtime.registry import RESULT_TYPES
from stages.feedback import design_feedback
from stages.funnel import FunnelStageResult, initial_sets, required_sets, synthesize_funnels
from stages.radius import robustness_radius

DEMOS = 2  # the first two demos: about 1-2 s per funnel
# one worker synthesizes the module's funnels (``result``, about 2.5 s of CPU), not each
pytestmark = pytest.mark.xdist_group("funnel-stage")


@pytest.fixture(scope="module")
def inputs():
    """The shipped double integrator, its first demos' trajectories, the constant certificate's
    metric ``P (4, 4)`` and each demo's robustness radius."""
    scenario = load_scenario("double_integrator")
    tube = design_feedback(scenario).certified_tube
    trajectories = [
        simulate(scenario.dynamics, d.x0, d.us, scenario.Ts, substeps=VERIFY_SUBSTEPS)
        for d in scenario.demos[:DEMOS]
    ]
    radii = np.array([robustness_radius(scenario, tube, tr).radius for tr in trajectories])
    names = [d.name for d in scenario.demos[:DEMOS]]
    return scenario, names, trajectories, np.asarray(tube.P), radii


@pytest.fixture(scope="module")
def result(inputs):
    scenario, names, trajectories, P, radii = inputs
    done = []
    found = synthesize_funnels(scenario, names, trajectories, P, radii, progress=done.append)
    assert done == [1] * DEMOS  # one tick per funnel
    return found


def test_initial_set_is_the_balls_slice_along_init():
    """Init's free directions are x, y: ``Q_init = r^2 S (S^T P S)^-1 S^T`` is zero on the fixed
    velocities, and a point of the slice on the ball's boundary is on the ellipsoid's."""
    scenario = SimpleNamespace(init_lower=np.zeros(4), init_upper=np.array([1.0, 1.0, 0.0, 0.0]))
    rng = np.random.default_rng(1)
    M = rng.normal(size=(4, 4))
    P = M @ M.T + np.eye(4)
    Q = initial_sets(scenario, P, [0.5, 2.0])
    assert Q.shape == (2, 4, 4)
    np.testing.assert_array_equal(Q[:, 2:, :], 0.0)
    np.testing.assert_array_equal(Q[:, :, 2:], 0.0)
    np.testing.assert_allclose(Q[1], 16 * Q[0], rtol=1e-12)  # r^2 scaling
    d = np.array([0.3, -0.7, 0.0, 0.0])
    x = 2.0 * d / np.sqrt(d @ P @ d)  # ||x||_P = r = 2, in the slice
    assert x[:2] @ np.linalg.solve(Q[1][:2, :2], x[:2]) == pytest.approx(1.0, rel=1e-12)
    assert x @ P @ x == pytest.approx(4.0, rel=1e-12)


def test_funnels_hold_the_required_initial_set(inputs, result):
    scenario, names, trajectories, P, radii = inputs
    assert isinstance(result, FunnelStageResult) and result.success
    assert result.usable == (0, 1) and result.rejected == () and result.names == tuple(names)
    assert "funnels certified for 2 of 2 trajectories" in result.message
    starts = np.array([t.xs[0] for t in trajectories])
    corners = init_cells(scenario.init_lower, scenario.init_upper, starts, P)
    initial = required_sets(scenario, starts, P, radii)
    for i, (funnel, trajectory) in enumerate(zip(result.funnels, trajectories, strict=True)):
        assert funnel.success and 0 < funnel.rho <= 1
        assert check_funnel(scenario, trajectory, funnel, scenario.state_bounds) is None
        v = corners[i]  # both starts own cells: their corners are in E(0) at level 1
        assert len(v)
        np.testing.assert_allclose(initial[i], np.einsum("pi,pj->pij", v, v))
        assert np.einsum("bi,ij,bj->b", v, funnel.P[0], v).max() <= 1 + 1e-6
    np.testing.assert_array_equal(result.levels, [f.rho for f in result.funnels])
    np.testing.assert_array_equal(result.starts, np.stack([f.P[0] for f in result.funnels]))
    np.testing.assert_array_equal(result.initial_radii, radii)


def test_a_start_that_owns_no_cell_asks_for_the_ball_slice(inputs):
    """A start far outside Init owns none of its cells: its funnel is asked for the constant
    ball's slice (I1) at its radius instead."""
    scenario, _, trajectories, P, radii = inputs
    far = trajectories[0].xs[0] + np.array([50.0, 50.0, 0.0, 0.0])
    initial = required_sets(scenario, [trajectories[0].xs[0], far], P, radii)
    assert initial[0].shape[0] > 1  # the near start: its cell's corners
    np.testing.assert_array_equal(initial[1], initial_sets(scenario, P, radii)[1][None])


def test_a_funnel_the_check_rejects_is_dropped(inputs, result, monkeypatch):
    """The second funnel's metric shrunk at one sample: the independent check rejects it, the
    stage drops it (level 0 for coverage) and names it."""
    scenario, names, trajectories, P, radii = inputs
    funnels = iter(result.funnels)

    def perturbed(*_args, **_kwargs):
        funnel = next(funnels)
        if funnel is result.funnels[1]:
            metric = funnel.P.copy()
            metric[5] *= 0.5
            return dataclasses.replace(funnel, P=metric)
        return funnel

    monkeypatch.setattr(funnel_stage, "synthesize_funnel", perturbed)
    found = synthesize_funnels(scenario, names, trajectories, P, radii)
    assert found.usable == (0,) and not found.success
    assert len(found.rejected) == 1 and found.rejected[0].startswith(f"{names[1]} dropped: ")
    assert "rejected by the independent check" in found.rejected[0]
    assert found.levels[1] == 0.0 and found.levels[0] == result.funnels[0].rho
    assert "funnels certified for 1 of 2 trajectories" in found.message


def test_a_reused_funnel_is_not_synthesized_again(inputs, result, monkeypatch):
    """``reuse``: the first trajectory's funnel is given, only the second is synthesized."""
    scenario, names, trajectories, P, radii = inputs
    calls = []

    def counted(*args, **kwargs):
        calls.append(args[1])
        return result.funnels[1]

    monkeypatch.setattr(funnel_stage, "synthesize_funnel", counted)
    done = []
    found = synthesize_funnels(
        scenario, names, trajectories, P, radii, reuse=[(result.funnels[0], None), None],
        progress=done.append,
    )  # fmt: skip
    assert len(calls) == 1 and calls[0] is trajectories[1] and sum(done) == 2
    reused = found.funnels[0]
    assert reused.seconds == 0.0 and found.usable == (0, 1)  # no synthesis time spent now
    assert dataclasses.replace(reused, seconds=result.funnels[0].seconds) == result.funnels[0]
    # a funnel that was not certified is not kept by being reused
    failed = dataclasses.replace(result.funnels[0], success=False, message="(F2) fails")
    again = synthesize_funnels(
        scenario, names, trajectories, P, radii, reuse=[(failed, None), None]
    )
    assert again.usable == (1,)
    assert "reused funnel was not certified ((F2) fails)" in again.rejected[0]
    # one dropped earlier stays dropped, for the same reason, without being synthesized again
    dropped = synthesize_funnels(
        scenario, names, trajectories, P, radii, reuse=[(result.funnels[0], "(F5) fails"), None]
    )
    assert dropped.usable == (1,) and dropped.failure(0) == "(F5) fails" and len(calls) == 3
    with pytest.raises(ValueError, match="1 funnels to reuse for 2 trajectories"):
        synthesize_funnels(scenario, names, trajectories, P, radii, reuse=[None])


def test_mismatched_inputs(inputs):
    scenario, names, trajectories, P, radii = inputs
    with pytest.raises(ValueError, match="2 names, 1 trajectories and 2 radii"):
        synthesize_funnels(scenario, names, trajectories[:1], P, radii)


def test_result_is_stored_and_read_back(result, tmp_path):
    save_result(tmp_path / "funnel", "key", result)
    stored = read_stored(tmp_path / "funnel", RESULT_TYPES)
    assert stored is not None and stored.key == "key"
    back = stored.result
    assert isinstance(back, FunnelStageResult) and back.usable == result.usable
    for a, b in zip(back.funnels, result.funnels, strict=True):
        np.testing.assert_array_equal(a.P, b.P)
        np.testing.assert_array_equal(a.K, b.K)
        assert a.rho == b.rho and dict(a.limits) == dict(b.limits)
        assert len(a.vertices) == len(b.vertices)
        np.testing.assert_array_equal(a.enclosure.range, b.enclosure.range)


def test_a_funnels_time_counts_its_whole_task(inputs, result, monkeypatch):
    """``seconds`` (the stage's "s of work") is each task's wall time: the certify-style checks
    after the synthesis count too (they were dropped when a redesign failed)."""
    scenario, names, trajectories, P, radii = inputs
    funnels = iter(result.funnels)

    def slow_check(*_args, **_kwargs):
        time.sleep(0.05)
        return None, ()

    monkeypatch.setattr(
        funnel_stage, "synthesize_funnel",
        lambda *_a, **_k: dataclasses.replace(next(funnels), seconds=0.0),
    )  # fmt: skip
    monkeypatch.setattr(funnel_stage, "_accepted", slow_check)
    found = synthesize_funnels(scenario, names, trajectories, P, radii)
    assert found.usable == (0, 1)
    assert all(funnel.seconds >= 0.05 for funnel in found.funnels)
