"""The funnel certificate as a run (``certificate="funnel"``, ``--certificate funnel``): on
quadrotor_hill_flythrough end to end (the shipped scenario's certificate is the funnel: its session
synthesis, tests/conftest.py, is the run), the command line's flag on a copy of its folder
(every stage reused), bad combinations refused before any work, and the report of a funnel run
(the funnel figure, the table constant vs funnel, the per-trajectory gains)."""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
from html import unescape

import numpy as np
import pytest

import pipeline
import stages.funnel
from pipeline.controller import FUNNEL_FORMAT, load
from pipeline.io.artifacts import read_stored
from pipeline.model import geometry
from pipeline.numerics.verify.cover import subdivide
from pipeline.reporting import figures
from pipeline.reporting.summary import Summary
from pipeline.runtime.cli import main
from pipeline.runtime.options import RunOptions
from pipeline.runtime.orchestrator import run_synthesis
from pipeline.runtime.registry import RESULT_TYPES
from pipeline.runtime.stored import load_report_data
from tests.helpers.browser import (
    assert_figures_fit,
    assert_layout,
    measure_in_browser,
    needs_browser,
)

SCENARIO = "quadrotor_hill_flythrough"
SAMPLES = 200  # the command line's runs on a copy (the session run has 1,000)


@pytest.fixture(scope="module")
def funnel_run(synthesis_run):
    """quadrotor_hill_flythrough's session synthesis (its scenario ships the funnel certificate) ->
    ``(result, the pipeline logger's lines)``. Read only: a test that changes files copies it."""
    session = synthesis_run(SCENARIO)
    assert session.result.summary is not None and session.result.summary.certificate == "funnel"
    return session.result, [record.getMessage() for record in session.records]


def test_funnel_run_ships_a_certified_safety_controller_2(funnel_run):
    result, lines = funnel_run
    assert result.verdict is pipeline.Verdict.CERTIFIED_AND_VALIDATED, result.message
    summary = result.summary
    assert summary is not None and summary.certificate == "funnel"
    document = json.loads(result.outputs.summary.read_text())
    assert document["certificate"] == "funnel" and document["verdict"]["certified"]
    controller = load(result.outputs.controller)
    assert controller.format == FUNNEL_FORMAT and controller.funnel
    # One funnel per shipped trajectory, each level the one the funnel stage found.
    levels = [d.funnel_level for d in summary.demos]
    assert all(level is not None and 0 < level <= 1 for level in levels)
    assert sorted(tr.radius for tr in controller.trajectories) == pytest.approx(sorted(levels))
    # The file's initial ellipsoids E_i(0) cover Init, each in its own metric P_i[0].
    cover = subdivide(
        np.stack([tr.P[0] for tr in controller.trajectories]),
        pipeline.load_scenario(SCENARIO).init_lower,
        pipeline.load_scenario(SCENARIO).init_upper,
        np.stack([tr.x0 for tr in controller.trajectories]),
        np.array([tr.radius for tr in controller.trajectories]),
    )
    assert cover.covered
    assert summary.headline.covered_after and summary.headline.coverage_after == 1.0
    stages = [line.split("]")[0][1:] for line in lines if line.startswith("[")]
    order = ["coverage_optimized", "funnel", "coverage_funnel", "controller"]
    assert [stage for stage in stages if stage in order] == order
    assert any(
        line.startswith("[funnel] ") and "funnels certified for 9 of 9" in line for line in lines
    )
    assert (result.outputs.artifacts / "funnel.json").is_file()


def test_the_summary_says_what_each_shipped_funnel_guarantees(funnel_run):
    """summary.json's ``funnels`` (issue 30, item 2) against controller.json, checked
    independently: T and level as the file says; the arrival speed as the slope of x_ref's
    positions over the file's last grid step; the extent at T as the largest position offset
    of states on the boundary of E_i(T) (sampled, and the extreme one along each axis); the
    funnel's clearance not above its nominal's and at most the closed-loop clearance plus a
    grid step's travel."""
    result, _ = funnel_run
    summary = result.summary
    law = load(result.outputs.controller)
    s = pipeline.load_scenario(SCENARIO)
    assert [f.demo for f in summary.funnels] == [tr.name for tr in law.trajectories]
    rng = np.random.default_rng(5)
    for f, tr in zip(summary.funnels, law.trajectories, strict=True):
        assert f.shipped and f.T == pytest.approx(tr.T) and f.level == pytest.approx(tr.radius)
        p = s.positions(tr.x_ref)
        slope = np.linalg.norm(p[-1] - p[-2]) / (tr.t[-1] - tr.t[-2])
        assert f.arrival_speed == pytest.approx(slope, rel=0.02)
        np.testing.assert_allclose(f.arrival, tr.x_ref[-1])
        P = tr.metric(tr.T, law.Ts)
        z = rng.normal(size=(20000, s.n))
        z /= np.linalg.norm(z, axis=1, keepdims=True)
        e = tr.radius * np.exp(-tr.rate * tr.T) * np.linalg.solve(np.linalg.cholesky(P).T, z.T).T
        offsets = np.linalg.norm(s.positions(e), axis=1)
        assert offsets.max() <= f.extent_at_T * (1 + 1e-9)
        assert offsets.max() >= 0.95 * f.extent_at_T
        nominal = min(float(geometry.distance(p, region).min()) for region in s.unsafe.values())
        assert 0 < f.clearance <= nominal
    assert min(f.clearance for f in summary.funnels) <= summary.montecarlo.min_clearance + 0.1


def test_the_nominals_are_optimized_again_against_the_funnels(funnel_run):
    """Issue 16 part 4: round 1 re-optimizes against the funnels' extents; a kept round shortens
    the total T, and the shipped nominals are the kept round's."""
    result, lines = funnel_run
    assert any(line.startswith("[reoptimize_1] ") for line in lines)
    assert any(line.startswith("[funnel_1] ") for line in lines)
    rounds = [line for line in lines if line.startswith("[round ")]
    assert rounds, "every round says whether it was kept"
    demos = result.summary.demos
    constant = sum(d.T_constant for d in demos)
    shipped = sum(d.T_optimized for d in demos)
    controller = load(result.outputs.controller)
    assert sorted(tr.t[-1] for tr in controller.trajectories) == pytest.approx(
        sorted(d.T_optimized for d in demos)
    )
    if any("kept: total T" in line for line in rounds):
        assert shipped < constant
    else:
        assert shipped == pytest.approx(constant)


def test_the_claims_say_which_certificate_and_what_certify_proved(funnel_run):
    result, _ = funnel_run
    claims = {claim.claim: claim.kind for claim in result.claims}
    funnel_claims = [c for c in claims if "funnel" in c]
    assert len(funnel_claims) == 2
    assert all(claims[c] is pipeline.ClaimKind.CERTIFIED for c in funnel_claims)
    assert not any("over the operating region" in c for c in claims)  # no constant claim
    summary = result.summary
    assert summary is not None and summary.certification.certified


def test_the_command_line_flag_selects_the_certificate(funnel_run, capsys, tmp_path):
    """``--certificate funnel`` on a copy of the API run's folder: every stage reused, the
    verdict line names the certificate; ``--certificate constant`` there ships
    ``safety-controller/1``."""
    result, _ = funnel_run
    folder = tmp_path / SCENARIO
    shutil.copytree(result.outputs.folder, folder)
    argv = ["synthesize", SCENARIO, "--out", str(folder), "--samples", str(SAMPLES)]
    assert main([*argv, "--certificate", "funnel"]) == 0
    printed = capsys.readouterr().out
    assert "[funnel] reused (inputs unchanged)" in printed
    assert "\nverdict (funnel certificate): certified and validated" in printed
    assert "\nshipped: controller.json, 9 of 9 funnels E_i(t), T " in printed  # compact view
    assert load(folder / "controller.json").format == FUNNEL_FORMAT
    assert main([*argv, "--certificate", "constant"]) == 0
    printed = capsys.readouterr().out
    assert "[funnel]" not in printed and "[optimize] reused (inputs unchanged)" in printed
    assert "\nverdict (constant certificate): certified and validated" in printed
    assert not load(folder / "controller.json").funnel
    document = json.loads((folder / "summary.json").read_text())
    assert document["certificate"] == "constant"


def test_the_funnel_certificate_refuses_a_period_that_does_not_divide_ts(tmp_path, capsys):
    """A held law with the funnel certificate (``funnel.law`` (I6)) is allowed, as with the
    constant one, when its period divides the sampling time; 0.03 s does not divide 0.1 s."""
    out = tmp_path / "out"
    argv = ["synthesize", "double_integrator", "--out", str(out), "--certificate", "funnel"]
    assert main([*argv, "--feedback-period", "0.03"]) == 2
    err = capsys.readouterr().err
    assert "--feedback-period: found 0.03 s; expected 0 (continuous feedback) or a period" in err
    assert "that divides the scenario's sampling_time 0.1 s" in err
    assert "Traceback" not in err and not out.exists()
    with pytest.raises(pipeline.UserError, match="divides the scenario's sampling_time"):
        run_synthesis(
            "double_integrator", out, RunOptions(certificate="funnel", feedback_period=0.03)
        )


def test_a_run_without_any_certified_funnel_fails_and_says_why(funnel_run, tmp_path, monkeypatch):
    """Every funnel rejected (the funnel stage run again on a copy of the run): the run fails at
    stage funnel naming the reason, and ships no controller."""
    result, _ = funnel_run
    folder = tmp_path / SCENARIO
    shutil.copytree(result.outputs.folder, folder)
    stored = read_stored(folder / "artifacts" / "funnel", RESULT_TYPES)
    assert stored is not None
    for artifact in (folder / "artifacts").glob("funnel.*"):
        artifact.unlink()  # the stage runs again: every funnel of the last run, all rejected

    def none_certified(*_args, **_kwargs):
        return dataclasses.replace(
            stored.result,
            usable=(),
            rejected=("all dropped: test",),
            success=False,
            message="no funnel certified for any of the 9 trajectories; all dropped: test",
        )

    monkeypatch.setattr(stages.funnel, "synthesize_funnels", none_certified)
    failed = run_synthesis(SCENARIO, folder, RunOptions(certificate="funnel", samples=20))
    assert failed.verdict is pipeline.Verdict.FAILED and failed.controller is None
    assert failed.message.startswith("failed: stage funnel: no funnel certified: ")
    assert "all dropped: test" in failed.message
    assert not (folder / "controller.json").exists()


@pytest.fixture(scope="module")
def funnel_report(synthesis_run, tmp_path_factory: pytest.TempPathFactory):
    """``(ReportData, report.html text, Monte Carlo samples)`` of a copy of the API's funnel
    run, synthesized again there with ``certificate="funnel"`` (every stage reused)."""
    session = synthesis_run(SCENARIO)
    folder = tmp_path_factory.mktemp("funnel_report") / SCENARIO
    shutil.copytree(session.out, folder)
    again = pipeline.synthesize(SCENARIO, out=folder, certificate="funnel", samples=session.samples)
    assert again.verdict is pipeline.Verdict.CERTIFIED_AND_VALIDATED, again.message
    scenario = pipeline.load_scenario(SCENARIO)
    data = load_report_data(scenario, folder, write_to=tmp_path_factory.mktemp("unused"))
    return data, (folder / "report.html").read_text(), session.samples


def _text(html: str) -> str:
    """The page's visible text, SVGs left out, whitespace collapsed."""
    html = re.sub(r"<svg.*?</svg>", " ", html, flags=re.S)
    return " ".join(unescape(re.sub(r"<[^>]+>", " ", html)).split())


def test_the_report_of_a_funnel_run_shows_the_funnels_and_both_certificates(funnel_report):
    data, html, samples = funnel_report
    assert data.funnel and data.law.K is None and data.law.P is None  # no feedback block
    assert html.count("<svg") == 7 and 'id="figure-funnels"' in html
    text = _text(html)
    table = text[text.index("Constant vs funnel certificate in this run") :]
    table = table[: table.index("Constant certificate per demonstration")]
    # The shipped trajectories are controller.json's: T and clearance computed from the file.
    shipped = data.law.trajectories
    T = sorted(tr.T for tr in shipped)
    span = f"{T[0]:.1f}" if f"{T[0]:.1f}" == f"{T[-1]:.1f}" else f"{T[0]:.1f}-{T[-1]:.1f}"
    funnel_row = table[table.index("funnel (K_i[k], P_i(t) per trajectory)") :]
    head = "funnel (K_i[k], P_i(t) per trajectory) shipped: controller.json (safety-controller/2)"
    assert funnel_row.startswith(f"{head} {len(shipped)} {span} ")
    shown = float(funnel_row[len(head) :].split()[2])  # min nominal clearance (m)
    # Checked on the file's x_ref points: the polyline comes no farther than its vertices, and
    # no nearer than the vertices less half the longest segment.
    s = data.scenario
    vertices = min(
        float(geometry.distance(s.positions(tr.x_ref), polygon).min())
        for tr in shipped
        for polygon in s.unsafe.values()
    )
    step = max(
        float(np.linalg.norm(np.diff(s.positions(tr.x_ref), axis=0), axis=1).max())
        for tr in shipped
    )
    assert vertices - step / 2 - 1e-3 <= shown <= vertices + 1e-3
    assert "certified and validated: certify re-checked controller.json (passed)" in funnel_row
    assert f"Monte Carlo: 0 of {samples} runs failed" in funnel_row
    constant_row = table[table.index("constant (one K, P)") : table.index("funnel (K_i[k]")]
    assert constant_row.startswith("constant (one K, P) verified by the stages, not shipped 9 ")
    assert "no controller written or re-certified from a file" in constant_row
    # The gains are per trajectory: their range is shown, the constant K is labelled as such.
    assert "Shipped gains: the gains are per trajectory and per sample interval" in text
    assert "Feedback gain K (inputs × states) of the constant certificate" in text


def test_the_report_derives_the_funnel_runs_own_summary(funnel_report):
    """``report`` derives the verdict and its numbers again (certify on controller.json, the
    Monte Carlo result of that file, Init covered by the file's E_i(0)): for an untampered run
    they are the run's own, field for field (issue 27, item 3)."""
    data, _, _ = funnel_report
    stored = json.loads((data.run_folder / "summary.json").read_text())
    assert data.summary.to_json() == Summary.from_json(stored).to_json()


def test_the_funnel_figure_draws_the_position_projection_of_each_shipped_funnel(funnel_report):
    """``funnel_tube``: the ellipse ``(p - p_ref)^T (C P_i(t)^-1 C^T)^-1 (p - p_ref) <=
    rho_i^2`` is the position shadow of ``E_i(t)``: boundary states of ``E_i(t)`` (``P_i(t)``
    from the file's metric) all land inside it and reach its boundary; at the sample times
    the metric is the file's ``P_i[k]``."""
    data, _, _ = funnel_report
    s, Ts = data.scenario, data.law.Ts
    rng = np.random.default_rng(3)
    for i in (0, len(data.law.trajectories) - 1):
        tr = data.law.trajectories[i]
        t = np.array([0.0, 0.37 * tr.T, 5 * Ts, tr.T])
        tube = figures.funnel_tube(data, i, t)
        np.testing.assert_allclose(tube.radii, tr.radius * np.exp(-tr.rate * t))
        p_ref = s.positions(np.stack([np.interp(t, tr.t, x) for x in tr.x_ref.T], axis=-1))
        np.testing.assert_allclose(tube.centres, p_ref, atol=1e-12)
        for k, P in enumerate(tr.metric(t, Ts)):
            if k == 2:
                np.testing.assert_allclose(P, tr.P[5], rtol=1e-9, atol=1e-9)
            z = rng.normal(size=(20000, s.n))
            z /= np.linalg.norm(z, axis=1, keepdims=True)
            L = np.linalg.cholesky(P)  # P = L L^T, so e = rho L^-T z has e^T P e = rho^2
            e = tube.radii[k] * np.linalg.solve(L.T, z.T).T  # (B, n)
            # and the boundary states whose position is farthest along each axis w of the
            # ellipse: e = rho P^-1 C^T w / sqrt(w^T C P^-1 C^T w), on the ellipse's boundary
            C = np.zeros((2, s.n))
            C[[0, 1], list(s.position_index)] = 1.0
            axes = np.linalg.eigh(tube.shapes[k])[1].T  # (2, 2)
            scale = np.sqrt(np.einsum("wi,ij,wj->w", axes, tube.shapes[k], axes))
            extreme = tube.radii[k] * (np.linalg.solve(P, C.T) @ axes.T / scale).T  # (2, n)
            p = s.positions(np.vstack([e, extreme]))
            value = np.einsum("bi,ij,bj->b", p, np.linalg.inv(tube.shapes[k]), p)
            value /= tube.radii[k] ** 2
            assert value.max() <= 1 + 1e-9  # every boundary state lands inside
            np.testing.assert_allclose(value[-2:], 1.0, rtol=1e-9)  # and the extremes on it


def test_the_coverage_figure_of_a_funnel_run_draws_the_shipped_initial_ellipsoids(funnel_report):
    """A third panel: each shipped E_i(0) sliced in its own metric P_i[0] from the file, centred
    on the file's x0_i, beside the constant balls (demonstrations, optimized)."""
    from matplotlib.collections import EllipseCollection
    from matplotlib.figure import Figure

    data, _, _ = funnel_report
    fig = Figure()
    figures.draw_coverage(fig, data)
    assert len(fig.axes) == 3
    shipped = fig.axes[2]
    assert shipped.get_title().startswith("shipped funnels:")
    assert "constant" not in shipped.get_title()
    collections = [c for c in shipped.collections if isinstance(c, EllipseCollection)]
    assert collections  # the slices, filled and outlined
    trajectories = data.law.trajectories
    offsets = np.asarray(collections[0].get_offsets())
    pair = list(data.coverage_demos.free[:2])
    np.testing.assert_allclose(offsets, np.stack([tr.x0[pair] for tr in trajectories]))
    # the slice of {e : e^T P_i[0] e <= rho_i^2} along the pair: (P_i[0][pair, pair])^-1 rho^2
    widths = np.asarray(collections[0].get_widths())  # the major axes (full lengths)
    expected = [
        2 * tr.radius / np.sqrt(np.linalg.eigvalsh(tr.P[0][np.ix_(pair, pair)]).min())
        for tr in trajectories
    ]
    np.testing.assert_allclose(widths, expected, rtol=1e-6)


@pytest.mark.chromium
@needs_browser
@pytest.mark.parametrize("width", [1280, 390])
def test_the_funnel_report_fits_a_desktop_and_a_phone(funnel_report, tmp_path, width):
    """The browser measurement of tests/stages/test_report.py on the funnel run's page at
    1280 and 390 px: the seven figures (the funnel figure too) inside the column, every legend
    and colour bar inside its figure, text at least 8 px; nothing wider than the column, the
    claims and per-demo tables as cards on the phone, captions outside the scroll boxes."""
    _, html, _ = funnel_report
    measured = measure_in_browser(html, width, tmp_path)
    assert measured["scroll"] <= width, "the page scrolls sideways"
    assert_layout(measured, width)
    assert [f["id"] for f in measured["figures"]][:3] == [
        "figure-overview",
        "figure-funnels",
        "figure-bisection",
    ]
    assert len(measured["figures"]) == 7
    assert_figures_fit(measured, width)
