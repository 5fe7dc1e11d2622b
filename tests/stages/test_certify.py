"""Stage ``certify``: the emitted controller.json is re-verified as written; tampering is caught.

A double integrator at rest (four references covering Init, exact hull: one vertex) is emitted
by the controller stage and must certify; the same file with a negative or 10x radius, a
perturbed metric or gain, a moved reference or another scenario's sampling time must not.
The quadrotor's shipped controller (the session's synthesis) is checked the same way, where the
hull has many vertices and the contraction margin is tight. A ``safety-controller/2`` file built
from real funnels (``funnel_artifact``) must certify, and not with a perturbed ``P``, ``K``,
level or ``x_ref``, held feedback, or a level past the one its constraints allow.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.model.scenario import load_scenario
from pipeline.model.simulate import simulate
from pipeline.numerics.funnel.synthesis import synthesize_funnel
from stages.certify import certify_controller
from stages.controller import emit_funnel_controller
from tests.helpers.double_integrator import emit_at_rest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def emitted(double_integrator, tmp_path):
    """``(scenario, path)``: a certified controller.json for the double integrator at rest."""
    scenario = double_integrator()
    path = tmp_path / "controller.json"
    emit_at_rest(scenario, path)
    return scenario, path


@pytest.fixture(scope="session")
def optimized_env(tmp_path_factory) -> dict[str, str]:
    """The environment of a ``python -O`` child: this tree on its path, and the ``.opt-1.pyc``
    bytecode it compiles (pip installs none: about 4 s of CPU per child for NumPy, SymPy, ...)
    written under one folder of this worker's, not into the tree or the venv, so that the
    second child reads what the first compiled."""
    prefix = tmp_path_factory.getbasetemp() / "bytecode-O"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONPYCACHEPREFIX": str(prefix)}
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    return env


def _tamper(path, change):
    document = json.loads(path.read_text())
    change(document)
    path.write_text(json.dumps(document))


def test_the_emitted_file_certifies(emitted):
    scenario, path = emitted
    result = certify_controller(scenario, path)
    assert result.success, result.message
    assert result.metric_eigenvalue > 0 and result.contraction_margin < 0 and result.vertices == 1
    assert result.radii == pytest.approx(result.verified_radii)
    assert result.covered_fraction == 1.0 and result.reference_error < 1e-12


def _scale_radius(factor):
    def change(document):
        document["trajectories"][1]["radius"] *= factor

    return change


def _perturb_P(document):
    P = np.array(document["feedback"]["P"])
    P[0, 2] = P[2, 0] = P[0, 2] + 0.3 * np.sqrt(P[0, 0] * P[2, 2])
    document["feedback"]["P"] = P.tolist()


def _perturb_K(document):
    K = np.array(document["feedback"]["K"])
    K[0, 2] = -0.2 * K[0, 2]  # the velocity gain, almost removed and of the wrong sign
    document["feedback"]["K"] = K.tolist()


def _scale_K(factor):
    def change(document):
        document["feedback"]["K"] = (factor * np.array(document["feedback"]["K"])).tolist()

    return change


def _move_reference(document):
    document["trajectories"][0]["x_ref"][5][1] += 0.01


def _other_sampling_time(document):
    document["Ts"] = 0.05
    for item in document["trajectories"]:
        item["T"] = 0.05 * len(item["u_ref"])
        item["t"] = (np.asarray(item["t"]) / 2).tolist()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (_scale_radius(-1.0), "trajectories[1].radius: found -"),
        (_scale_radius(10.0), "trajectories[1]: radius"),
        (_scale_radius(1.001), "the largest the tube allows"),
        (_perturb_P, "the contraction inequality fails"),
        (_perturb_K, "the contraction inequality fails"),
        (_move_reference, "trajectories[0]: x_ref is not the dynamics under u_ref"),
        (_other_sampling_time, "the file is not for this scenario: Ts 0.05"),
    ],
)
def test_a_tampered_file_is_not_certified(emitted, change, message):
    scenario, path = emitted
    _tamper(path, change)
    result = certify_controller(scenario, path)
    assert not result.success
    assert message in result.message, result.message


def test_a_shrunk_radius_that_leaves_init_uncovered_is_caught(emitted):
    scenario, path = emitted

    def shrink(document):
        for item in document["trajectories"]:
            item["radius"] *= 0.1

    _tamper(path, shrink)
    result = certify_controller(scenario, path)
    assert not result.success and "Init is not covered" in result.message


def test_a_missing_file_is_not_certified(double_integrator, tmp_path):
    result = certify_controller(double_integrator(), tmp_path / "controller.json")
    assert not result.success and "cannot read" in result.message


@pytest.mark.parametrize(
    "change",
    [_scale_radius(-1.0), _scale_radius(10.0), _perturb_P, _scale_K(1.05), _scale_K(0.95)],
    ids=["negative radius", "10x radius", "perturbed P", "K 5% larger", "K 5% smaller"],
)
def test_the_quadrotor_controller_certifies_and_tampering_is_caught(
    synthesized_constant, tmp_path, change
):
    """The constant certificate's file (safety-controller/1); the funnel file's tampering:
    ``test_a_quadrotor_funnel_is_rebuilt_from_the_file_and_perturbations_are_caught``."""
    from pipeline import load_scenario

    _, out = synthesized_constant
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    assert certify_controller(scenario, out / "controller.json").success
    path = tmp_path / "controller.json"
    path.write_bytes((out / "controller.json").read_bytes())
    _tamper(path, change)
    assert not certify_controller(scenario, path).success


def _coarse_reference(document):
    """Re-emit every reference on the sample times only (one RK4 step per sample): still the
    dynamics on its own grid, but its linear interpolation is far from the flight."""
    from pipeline.model.scenario import load_scenario as load

    scenario = load("quadrotor_hill_flythrough", check_demos=False)
    for item in document["trajectories"]:
        us = np.asarray(item["u_ref"])  # (N, m)
        coarse = simulate(scenario.dynamics, np.asarray(item["x0"]), us, scenario.Ts, substeps=1)
        item["t"] = coarse.dense_ts.tolist()
        item["x_ref"] = coarse.dense_xs.tolist()


def _inflate_interpolation_error(document):
    document["interpolation_error_P_norm"] = 0.5  # would loosen the Monte Carlo's tube check


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (_coarse_reference, "the interpolated x_ref is"),
        (_inflate_interpolation_error, "interpolation_error_P_norm: the file states 0.5"),
    ],
    ids=["reference on a coarse grid", "inflated interpolation error"],
)
def test_the_tracked_reference_is_measured_not_trusted(synthesized, tmp_path, change, message):
    """The law tracks the file's x_ref interpolated linearly: certify measures that against the
    dynamics on a finer grid, and the stated interpolation error against its measurement."""
    from pipeline import load_scenario

    _, out = synthesized
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    path = tmp_path / "controller.json"
    path.write_bytes((out / "controller.json").read_bytes())
    _tamper(path, change)
    result = certify_controller(scenario, path)
    assert not result.success and message in result.message


# safety-controller/2: a funnel per trajectory, rebuilt from the file and re-checked.


def test_the_funnel_file_certifies(funnel_artifact):
    scenario, path = funnel_artifact
    result = certify_controller(scenario, path)
    assert result.success, result.message
    assert "2 funnels" in result.message and result.covered_fraction == 1.0
    assert result.contraction_margin < 0 and result.vertices == 60  # linear: one per interval
    # every level within what the constraints allow, and the check measures, not echoes
    assert all(r <= v for r, v in zip(result.radii, result.verified_radii, strict=True))
    assert result.reference_error <= 1e-9


def _funnel_P(trajectory, k, scale):
    def change(document):
        P = np.asarray(document["trajectories"][trajectory]["P"])
        P[k] *= scale
        document["trajectories"][trajectory]["P"] = P.tolist()

    return change


def _funnel_K(trajectory, scale):
    def change(document):
        item = document["trajectories"][trajectory]
        item["K"] = (scale * np.asarray(item["K"])).tolist()

    return change


def _funnel_radius(scale):
    def change(document):
        for item in document["trajectories"]:
            item["radius"] *= scale

    return change


def _moved_funnel_reference(document):
    x_ref = np.asarray(document["trajectories"][0]["x_ref"])
    x_ref[len(x_ref) // 2 :, 1] += 1e-3
    document["trajectories"][0]["x_ref"] = x_ref.tolist()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (_funnel_P(0, 10, 0.5), "trajectories[0]: the funnel is not certified"),
        (_funnel_P(1, 0, 0.5), "trajectories[1]: the funnel is not certified"),
        (_funnel_P(0, 3, -1.0), "trajectories[0].P[3]: found 'smallest eigenvalue"),
        (_funnel_K(1, 3.0), "trajectories[1]: the funnel is not certified"),
        (_funnel_K(0, 0.2), "trajectories[0]: the funnel is not certified"),
        (_funnel_radius(0.5), "Init is not covered"),
        (_moved_funnel_reference, "trajectories[0]: x_ref is not the dynamics under u_ref"),
        (lambda d: d.update(feedback_period=0.03), "feedback_period 0.03 s does not divide Ts"),
        (lambda d: d.update(feedback_period=0.1), "not certifiable with the law held every 0.1 s"),
        (lambda d: d.update(metric_interpolation="linear"), "metric_interpolation: found"),
    ],
    ids=[
        "P[10] halved", "P[0] halved", "P[3] negated", "K 3x", "K 0.2x", "radius halved",
        "moved x_ref", "held feedback off the samples", "held feedback too slow", "P linear",
    ],
)  # fmt: skip
def test_a_tampered_funnel_file_is_not_certified(funnel_artifact, tmp_path, change, message):
    scenario, original = funnel_artifact
    path = tmp_path / "controller.json"
    path.write_text(original.read_text())
    _tamper(path, change)
    result = certify_controller(scenario, path)
    assert not result.success
    assert message in result.message, result.message


def test_a_funnel_level_is_certified_up_to_its_limit_and_not_beyond(funnel_artifact, tmp_path):
    """The double integrator's hull does not depend on the tube (linear), so the largest level
    is set by the constraints: just under it certifies, just over it does not."""
    scenario, original = funnel_artifact
    verified = certify_controller(scenario, original).verified_radii
    for scale, certified in ((0.999, True), (1.01, False)):
        path = tmp_path / f"controller_{scale}.json"
        path.write_text(original.read_text())

        def set_levels(document, scale=scale):
            for item, level in zip(document["trajectories"], verified, strict=True):
                item["radius"] = scale * level

        _tamper(path, set_levels)
        result = certify_controller(scenario, path)
        assert result.success == certified, result.message
        if not certified:
            assert "exceeds the limit" in result.message


def test_a_funnel_file_with_a_terminal_controller_holds_each_end_funnel(tmp_path):
    """A full double-integrator demo's funnel ends slowly in Goal: the terminal block is written
    against the end funnel ``E(T)`` (its own ``P[N]``), re-verified, and refused when the end
    funnel is made to stick out (a larger level)."""
    scenario = load_scenario("double_integrator", check_demos=False)
    demo = scenario.demos[0]
    trajectory = simulate(scenario.dynamics, demo.x0, demo.us, scenario.Ts)
    funnel = synthesize_funnel(scenario, trajectory)
    assert funnel.success, funnel.message
    path = tmp_path / "controller.json"
    written = emit_funnel_controller(scenario, [trajectory], [funnel], path)
    assert written.terminal, written.terminal_message
    result = certify_controller(scenario, path)
    assert result.terminal and 0 < result.terminal_fit <= 1
    assert not [f for f in result.failures if f.startswith("terminal")], result.failures
    # E(T) is small (the fit is mostly x_ref(T)'s offset from x_eq): P[N] / 1e4 makes it 100x
    # larger, past the terminal ellipsoid

    def bulge(document):
        P = np.asarray(document["trajectories"][0]["P"])
        P[-1] *= 1e-4
        document["trajectories"][0]["P"] = P.tolist()

    _tamper(path, bulge)
    result = certify_controller(scenario, path)
    assert "end tube is not inside the terminal ellipsoid" in result.message


def test_a_quadrotor_funnel_is_rebuilt_from_the_file_and_perturbations_are_caught(
    quadrotor_funnel_artifact, tmp_path
):
    """Nonlinear: the local hulls are rebuilt around the file's tube (pitch and thrust boxes per
    interval, many vertices); the funnel re-verifies (only Init's coverage fails: one funnel
    covers part of it), and a halved ``P[k]`` or a 1.5x gain does not."""
    scenario, original = quadrotor_funnel_artifact
    result = certify_controller(scenario, original)
    assert result.failures and all(f.startswith("Init is not covered") for f in result.failures)
    assert 0 < result.covered_fraction < 1
    assert result.contraction_margin < 0 and result.vertices > 2 * len(scenario.demos[0].us)
    assert result.radii[0] <= result.verified_radii[0]
    for change in (_funnel_P(0, 40, 0.5), _funnel_K(0, 1.5)):
        path = tmp_path / "controller.json"
        path.write_text(original.read_text())
        _tamper(path, change)
        result = certify_controller(scenario, path)
        assert "trajectories[0]: the funnel is not certified" in result.message, result.message


# certify never depends on `assert` (issue 27, item 10): the same outcome under python -O.


@pytest.mark.slow
def test_a_quadrotor_funnel_with_a_u_ref_sample_past_its_bound_is_not_certified_also_under_O(
    quadrotor_funnel_artifact, tmp_path, optimized_env
):
    """``u_ref[5]``'s thrust moved 5 N up, past the 14.9 N bound: the input box of interval 5,
    clipped to the bounds, is empty. That stopped certify on mpmath's ``AssertionError:
    endpoints must be properly ordered`` (and under ``python -O``, without the assert, gave
    "not certified" for another reason); now it is "not certified" naming the empty box, with
    the same failures under ``python -O``."""
    scenario, original = quadrotor_funnel_artifact
    path = tmp_path / "controller.json"
    path.write_text(original.read_text())

    def shift(document):
        document["trajectories"][0]["u_ref"][5][0] += 5.0

    _tamper(path, shift)
    result = certify_controller(scenario, path)
    assert not result.success
    assert re.search(r"the funnel is not certified: 1 segment\(s\): u1 in \[[\d.]+, 14\.9\]: "
                     r"not an interval", result.message), result.message  # fmt: skip
    script = (
        "import json, sys; from pipeline.model.scenario import load_scenario; "
        "from stages.certify import certify_controller; "
        "scenario = load_scenario('quadrotor_hill_flythrough', check_demos=False); "
        "print(json.dumps(certify_controller(scenario, sys.argv[1]).failures))"
    )
    optimized = subprocess.run(
        [sys.executable, "-O", "-c", script, str(path)],
        cwd=ROOT,
        env=optimized_env,
        capture_output=True,
        text=True,
        check=False,
    )
    assert optimized.returncode == 0, optimized.stderr
    assert json.loads(optimized.stdout) == list(result.failures)


@pytest.mark.slow
@pytest.mark.xdist_group("quadrotor-funnel")  # with the other -O test: one bytecode folder
def test_the_certify_tests_pass_under_python_O(optimized_env):
    """This file's tests (but those that need a session's synthesis or the quadrotor's funnel,
    20-25 s, and this one) and the hull's, with ``assert`` statements removed: pytest still
    rewrites the tests' own asserts into checks, the code under test runs as under -O."""
    selected = "not quadrotor and not tracked_reference and not under_python_O"
    run = subprocess.run(
        [sys.executable, "-O", "-m", "pytest", "-q", "-p", "no:cacheprovider", "-k", selected]
        + ["tests/stages/test_certify.py", "tests/test_hull_rounding.py"],
        cwd=ROOT,
        env=optimized_env,
        capture_output=True,
        text=True,
        check=False,
    )
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    assert re.search(r"\b(2\d|[3-9]\d) passed\b", run.stdout), run.stdout[-500:]
