"""The report's section "Declared uncertainty" (``pipeline.reporting.uncertainty``).

A funnel run of double_integrator with a declared gust of 0.02 m/s^2 on vx' and vy' and the
stress test (300 Monte Carlo samples, about 25 s) writes the section into report.html and
report.pdf with the declared numbers, the derived additive bound, certify's disturbance multiple
and the stress test's failure rate from the run's own results; the same report without the
declaration has no such section; a declaration four times as large changes the numbers and
the certify check under it is not called certified. The derived bound by source is checked
against hand-computed values on quadrotor_hill's declaration (no run).
"""

from __future__ import annotations

import dataclasses
import shutil
import unicodedata
from html import unescape
from pathlib import Path

import numpy as np
import pytest
from pypdf import PdfReader

import pipeline
from pipeline.model.scenario import Scenario, load_scenario
from pipeline.numerics.uncertainty import additive_bound
from pipeline.reporting import uncertainty
from pipeline.reporting.content import Paragraph, Table, number, percent
from pipeline.reporting.data import ReportData
from pipeline.reporting.sections import build_sections, section_headings
from pipeline.runtime.stored import load_report_data
from stages.certify import certify_controller

GUST = 0.02  # m/s^2 on vx' and vy'


def _text(blocks: tuple) -> str:
    """The words of a section's paragraphs and tables, single-spaced."""
    parts = []
    for block in blocks:
        if isinstance(block, Paragraph):
            parts.append(block.text)
        elif isinstance(block, Table):
            parts += [block.caption, *block.header, *(cell for row in block.rows for cell in row)]
    return " ".join(" ".join(parts).split())


def _declaring(scenario: Scenario, **declared: np.ndarray) -> Scenario:
    return dataclasses.replace(
        scenario, uncertainty=dataclasses.replace(scenario.uncertainty, **declared)
    )


@pytest.fixture(scope="module")
def gusty(tmp_path_factory: pytest.TempPathFactory) -> tuple[Scenario, Path, ReportData]:
    """A finished funnel run of double_integrator declaring ``GUST``, with the stress test:
    its scenario, folder (report written by the run) and ``ReportData`` read back."""
    folder = tmp_path_factory.mktemp("gusty") / "double_integrator"
    shutil.copytree(load_scenario("double_integrator", check_demos=False).path.parent, folder)
    path = folder / "scenario.yaml"
    path.write_text(
        path.read_text()
        + f"\ncertificate: funnel\nuncertainty:\n  disturbance: {{vx: {GUST}, vy: {GUST}}}\n"
    )
    result = pipeline.synthesize(path, out=folder / "out", samples=300, stress=True)
    assert result.success, result.message
    scenario = load_scenario(path)
    data = load_report_data(scenario, folder / "out", write_to=tmp_path_factory.mktemp("unused"))
    return scenario, folder / "out", data


pytestmark = pytest.mark.xdist_group("report-uncertainty")  # one worker makes the run


@pytest.mark.slow
def test_the_section_shows_the_declaration_the_bound_and_the_runs_margins(gusty) -> None:
    _, out, data = gusty
    html = (out / "report.html").read_text()
    text = " ".join(unicodedata.normalize("NFKC", unescape(html)).split())
    headings = section_headings(funnel=True, declared=True)
    assert headings[2] == "3. Declared uncertainty"
    positions = [text.find(h) for h in headings]
    assert -1 not in positions and positions == sorted(positions), headings
    check, stress, mc = data.certification, data.stress, data.montecarlo
    assert check.success and stress is not None and stress.beyond_declared == 2.0
    assert 1 < check.disturbance_multiple < 100
    runs = stress.with_feedback
    expected = [
        "|d_vx| <= 0.02 m/s^2",  # declared, in the derivative's unit
        "|d_vy| <= 0.02 m/s^2",
        "|w_vx| <= 0.02 m/s^2, |w_vy| <= 0.02 m/s^2",  # the derived bound
        "derived by the pipeline, not declared",
        "outward-rounded interval arithmetic",
        "b = 0 for x, y",
        "certify re-checked controller.json under it: certified",
        # certify's multiple, from this run's check of controller.json
        f"{number(check.disturbance_multiple, 4)} × b",
        f"certified: the shipped funnels' invariance inequality (I5) still holds with "
        f"{number(check.disturbance_multiple, 4)} times",
        # the stress test, from this run's result, labelled
        "stress test: 2 × the declaration",
        f"{percent(runs.failed_fraction)} of {runs.samples} runs failed",
        "not certified (sampled, no bound)",
        f"each of the {mc.samples} closed-loop runs (seed {mc.seed}) drew a gust on vx', vy' "
        "uniform in its box, piecewise constant with a new value every 0.5 s",
        f"(its search: {mc.falsification.evaluations} closed-loop runs)",
        "statistically validated",
    ]
    missing = [e for e in expected if e not in text]
    assert not missing, f"not in report.html: {missing}"
    # the PDF is written and has the section, after the scenario's
    pages = [page.extract_text() for page in PdfReader(out / "report.pdf").pages]
    pdf = unicodedata.normalize("NFKC", " ".join(pages))
    assert pdf.find("3. Declared uncertainty") > pdf.find("2. Scenario and trajectories") > 0
    assert "derived by the pipeline, not declared" in " ".join(pdf.split())


@pytest.mark.slow
def test_an_exact_model_report_has_no_such_section(gusty) -> None:
    scenario, _, data = gusty
    exact = dataclasses.replace(data, scenario=_declaring(scenario, disturbance=np.zeros(4)))
    sections = build_sections(exact)
    assert [s.heading for s in sections] == list(section_headings(funnel=True))
    assert "uncertainty" not in {s.key for s in sections}
    assert "The constant certificate that seeds it is not shipped (section 8," in _text(
        sections[0].blocks
    )
    declared = build_sections(data)
    assert "(section 9," in _text(declared[0].blocks)  # the seed's number follows the section


@pytest.mark.slow
def test_a_larger_declaration_changes_the_numbers_and_is_not_called_certified(gusty) -> None:
    scenario, out, data = gusty
    shown = _text(uncertainty.section(data))
    stronger = _declaring(scenario, disturbance=np.array([0.0, 0.0, 4 * GUST, 4 * GUST]))
    check = certify_controller(stronger, out / "controller.json")
    assert not check.success  # the file holds 0.02, the scenario now declares 0.08
    larger = _text(
        uncertainty.section(dataclasses.replace(data, scenario=stronger, certification=check))
    )
    assert "|w_vx| <= 0.02 m/s^2" in shown and "|w_vx| <= 0.02 m/s^2" not in larger
    assert "|d_vx| <= 0.08 m/s^2" in larger and "|w_vx| <= 0.08 m/s^2" in larger
    assert "under it: not certified" in larger and "under it: certified" not in larger
    assert "certified: the shipped funnels'" not in larger
    assert "not certified (controller.json is not certified)" in larger


@pytest.mark.slow
def test_a_terminal_rechecked_by_t7_is_described_with_its_box(gusty) -> None:
    """Where certify re-checked the terminal block by (T7), the section says how it holds the
    parameters and with which box; otherwise it says nothing of (T7)."""
    _, _, data = gusty
    t7 = dataclasses.replace(
        data,
        certification=dataclasses.replace(data.certification, terminal_box=(0, 0, 0.03, 0.04)),
    )
    text = _text(uncertainty.section(t7))
    assert "holds the parameters another way (T7)" in text
    assert "their shift at the hover, |w_vx| <= 0.03 m/s^2, |w_vy| <= 0.04 m/s^2" in text
    assert "(T7)" not in _text(uncertainty.section(data))


def test_the_derived_bound_by_source_on_quadrotor_hill() -> None:
    """wX in [-0.6, -0.4] enters vX' as mu (wX - vX), mu = 0.5: alone 0.5 * 0.1 = 0.05 on vX;
    m in [0.995, 1.005] enters as u1/m (-sin theta, cos theta): alone u1/m^2 * 0.005 with u1 <=
    14.9, m >= 0.995 (the mean value's xi) and |sin theta| <= sin 0.8 (theta's state bound)."""
    scenario = load_scenario("quadrotor_hill", check_demos=False)
    bound = uncertainty.derived_bound(scenario)
    names = list(scenario.uncertainty.parameter_names)
    wX, m = bound.each[names.index("wX")], bound.each[names.index("m")]
    vX, vY = scenario.state_names.index("vX"), scenario.state_names.index("vY")
    assert wX[vX] == pytest.approx(0.05, rel=1e-6) and wX[vY] == 0
    heavy = 14.9 / 0.995**2 * 0.005
    assert m[vX] == pytest.approx(heavy * np.sin(0.8), rel=1e-6)
    assert m[vY] == pytest.approx(heavy, rel=1e-6)
    assert bound.gust[vX] == bound.gust[vY] == 0.05
    # together: at most the terms alone added (the one expression of (U1)), at least each
    assert np.all(bound.parameters <= wX + m + 1e-12)
    assert np.all(bound.parameters >= np.maximum(wX, m) - 1e-12)
    assert np.array_equal(bound.total, additive_bound(scenario))
    assert np.all(bound.total >= bound.gust + bound.parameters - 1e-12)


def test_the_declared_table_has_a_row_per_item_with_units_and_nominals() -> None:
    scenario = load_scenario("quadrotor_hill", check_demos=False)
    measured = _declaring(scenario, measurement=np.array([0.02, 0.0, 0.0, 0.0, 0.0, 0.0]))
    table = uncertainty.declared_table(measured, uncertainty.derived_bound(measured))
    rows = {row[0]: row[1:] for row in table.rows}
    assert list(rows) == [
        "gust on vX'",
        "gust on vY'",
        "parameter wX (constant, unknown)",
        "parameter m (constant, unknown)",
        "measurement error on X",
    ]
    assert rows["gust on vX'"][0] == "|d_vX| <= 0.05 m/s^2"
    assert rows["parameter wX (constant, unknown)"][:2] == ("[-0.6, -0.4]", "-0.5")
    assert rows["parameter m (constant, unknown)"][:2] == ("[0.995, 1.005]", "1")
    assert rows["parameter wX (constant, unknown)"][2] == (
        "alone (the others nominal): |Δf_vX| <= 0.05 m/s^2"
    )
    assert rows["measurement error on X"][0] == "|eta_X| <= 0.02 m"
    assert "not in the additive bound" in rows["measurement error on X"][2]
    # no measurement declared: no such row
    plain = uncertainty.declared_table(scenario, uncertainty.derived_bound(scenario))
    assert not [row for row in plain.rows if row[0].startswith("measurement")]
