"""The report stage: built from the artifacts of the session's run of quadrotor_hill_flythrough.

The HTML parses, is self-contained and holds the headline numbers of summary.json; the PDF
(typeset by Typst, a pip dependency) is written without any browser, has the title on page 1
and every section in order, on few pages, and shows the HTML's verdict and numbers; a failure
to typeset is a message and no PDF, never a stale one; a missing input is a clear error;
headless Chromium (where installed) renders the page at 1400 px and 390 px with every legend and
colour bar inside its figure, no sideways scrolling and legible figure text.
"""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
import unicodedata
from html import unescape
from html.parser import HTMLParser
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest
from pypdf import PdfReader

from pipeline.io.errors import UserError
from pipeline.model.scenario import Scenario, load_scenario
from pipeline.reporting import pdf as pdf_module
from pipeline.reporting.sections import headline_items, section_headings
from pipeline.reporting.summary import Summary
from pipeline.runtime.cli import main
from pipeline.runtime.stored import load_report_data
from stages.report import write_reports
from tests.helpers.browser import (
    assert_figures_fit,
    assert_layout,
    chromium,
    measure_in_browser,
    needs_browser,
)


@pytest.fixture(scope="module")
def run(
    synthesized_constant: tuple[int, Path], tmp_path_factory: pytest.TempPathFactory
) -> tuple[Scenario, Path]:
    """A finished run, its report written by the orchestrator: a copy of the session's
    synthesis of quadrotor_hill_flythrough with the constant certificate (tests/conftest.py; the
    funnel run's report is tested in tests/test_funnel_run.py), so that rebuilding it here changes
    nothing that other tests read."""
    out = tmp_path_factory.mktemp("report") / "quadrotor_hill_flythrough"
    shutil.copytree(synthesized_constant[1], out)
    return load_scenario("quadrotor_hill_flythrough"), out


class _Page(HTMLParser):
    """Collects tags, their attributes, the open/close balance and the visible text."""

    VOID = {"meta", "br", "img", "input", "link", "hr", "path", "use", "rect", "stop"}

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.tags: list[tuple[str, dict[str, str | None]]] = []
        self.open: list[str] = []
        self.text: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags.append((tag, dict(attrs)))
        if tag not in self.VOID:
            self.open.append(tag)

    def handle_startendtag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags.append((tag, dict(attrs)))

    def handle_endtag(self, tag: str) -> None:
        if tag in self.VOID:
            return
        assert self.open and self.open[-1] == tag, f"</{tag}> closes <{self.open[-1:]}>"
        self.open.pop()

    def handle_data(self, data: str) -> None:
        self.text.append(data)


def _parse(html: str) -> _Page:
    page = _Page()
    page.feed(html)
    page.close()
    return page


def test_html_parses_and_needs_no_network(run: tuple[Scenario, Path]) -> None:
    html = (run[1] / "report.html").read_text()
    page = _parse(html)
    assert page.open == [], f"unclosed elements {page.open}"
    names = [tag for tag, _ in page.tags]
    assert "script" not in names and "iframe" not in names
    assert names.count("svg") == 6  # every figure inlined
    # a constant run: no funnel figure, no table "constant vs funnel", no per-trajectory gains
    assert 'id="figure-funnels"' not in html and "Constant vs funnel" not in html
    assert "Shipped gains" not in html
    for tag, attrs in page.tags:
        for name in ("src", "href", "xlink:href", "action", "srcset"):
            value = (attrs.get(name) or "").strip().lower()
            assert not value.startswith(("http:", "https:", "//", "ftp:")), (tag, name, value)
        if tag == "link":
            assert attrs.get("rel") != "stylesheet", attrs
    assert "@import" not in html and "url(http" not in html
    ids = [attrs["id"] for _, attrs in page.tags if attrs.get("id")]
    assert len(ids) == len(set(ids)), "inlined SVGs share element ids"
    for _, attrs in page.tags:
        href = attrs.get("href") or attrs.get("xlink:href") or ""
        if href.startswith("#"):
            assert href[1:] in ids, f"dangling reference {href}"


def test_html_holds_the_headline_numbers_of_summary_json(run: tuple[Scenario, Path]) -> None:
    out = run[1]
    summary = json.loads((out / "summary.json").read_text())
    text = " ".join(" ".join(_parse((out / "report.html").read_text()).text).split())
    h = summary["headline"]
    expected = [
        summary["verdict"]["text"],
        f"{h['faster_percent_mean']:.0f}%",
        f"terminal time {h['T_demo_mean']:.1f} s → {h['T_optimized_mean']:.1f} s",
        "the paper: 42%",
        f"{h['min_clearance_before']:.2f} → {h['min_clearance_after']:.2f} m",
        "the paper's demo: 0.22",
        "Closed-loop clearance (Monte Carlo)",  # beside the nominal one, each labelled
        f"{summary['montecarlo']['min_clearance']:.2f} m",
        f"closest of the {summary['montecarlo']['samples']} closed-loop runs",
        f"{h['coverage_before']:.1%} → {h['coverage_after']:.1%}",
        f"{h['montecarlo_failures']} of {h['montecarlo_samples']} runs failed",
        f"≤ {h['failure_bound_95']:.2e}",
        *section_headings(),
    ]
    for item in headline_items(Summary.from_json(summary)):
        expected += [item.label, item.value, item.note]
    for claim in summary["claims"]:
        expected += [claim["claim"], claim["kind"], claim["how"]]
    for demo in summary["demos"]:
        start = ", ".join(f"{v:.2f}" for v in demo["start"][:2])  # X, Y
        expected.append(
            f"{demo['demo']} ({start}) {demo['T_demo']:.1f} {demo['T_optimized']:.1f} "
            f"{demo['faster_percent']:.0f}% {demo['clearance_before']:.3f}"
        )
    expected += [str(v) for v in summary["reproducibility"]["versions"].values()]
    expected.append(summary["reproducibility"]["scenario_sha256"])
    missing = [e for e in expected if e not in text]
    assert not missing, f"not in report.html: {missing}"
    assert "Declared uncertainty" not in text  # the exact model: no such section


def _pdf_pages(path: Path) -> list[str]:
    """The text of each page (NFKC, no zero-width spaces: where a long token may break)."""
    return [
        unicodedata.normalize("NFKC", page.extract_text()).replace("\u200b", "")
        for page in PdfReader(path).pages
    ]


def test_pdf_has_the_title_first_and_every_section_in_order(run: tuple[Scenario, Path]) -> None:
    assert (run[1] / "report.pdf").read_bytes().startswith(b"%PDF-")
    reader = PdfReader(run[1] / "report.pdf")
    texts = _pdf_pages(run[1] / "report.pdf")
    title = " ".join(texts[0].split())  # a long scenario name may wrap onto the next line
    assert title.startswith("Safety controller synthesis report: quadrotor_hill_flythrough")
    summary = json.loads((run[1] / "summary.json").read_text())
    assert f"{summary['headline']['faster_percent_mean']:.0f}%" in texts[0]
    lines = [{line.strip() for line in text.splitlines()} for text in texts]
    starts = []
    for heading in section_headings():
        pages = [k for k, page in enumerate(lines) if heading in page]
        assert pages, f"no PDF page has the heading {heading!r}"
        starts.append(pages[0])
    assert starts == sorted(starts)
    # sections flow on: no page per section, no nearly empty page before the last
    assert len(reader.pages) <= 12, len(reader.pages)
    assert all(len(text) > 600 for text in texts[:-1]), [len(t) for t in texts]


def _copy_without_pdf(run: tuple[Scenario, Path], out: Path) -> Path:
    """A copy of the run in ``out`` with an old report.pdf and none kept to reuse."""
    shutil.copytree(run[1], out)
    (out / "report.pdf").write_bytes(b"%PDF- an old report")
    for kept in (out / "artifacts" / "figures").glob("report-*.pdf"):
        kept.unlink()
    return out


def test_the_pdf_is_written_without_any_browser(
    run: tuple[Scenario, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No program on PATH at all (no Chromium, nothing): report.pdf is typeset anyway."""
    out = _copy_without_pdf(run, tmp_path / "copy")
    empty = tmp_path / "bin"
    empty.mkdir()
    monkeypatch.setenv("PATH", str(empty))
    result = write_reports(load_report_data(run[0], out))
    assert result.success and result.pdf == out / "report.pdf"
    content = (out / "report.pdf").read_bytes()
    assert content.startswith(b"%PDF-") and content.rstrip().endswith(b"%%EOF")
    pages = len(PdfReader(out / "report.pdf").pages)
    assert f"report.pdf ({pages} pages)" in result.message and pages >= 5
    title = " ".join(_pdf_pages(out / "report.pdf")[0].split())
    assert title.startswith("Safety controller synthesis report: quadrotor_hill_flythrough")


def test_a_typesetting_failure_is_a_message_and_no_stale_pdf(
    run: tuple[Scenario, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = _copy_without_pdf(run, tmp_path / "copy")

    def fail(inputs: object) -> bytes:
        raise pdf_module.TypesetError("typst: the template failed")

    monkeypatch.setattr(pdf_module, "typeset", fail)
    result = write_reports(load_report_data(run[0], out))
    assert result.success and result.pdf is None
    assert result.message.endswith("; report.pdf not written: typst: the template failed")
    assert not (out / "report.pdf").exists()  # never a stale PDF beside a new HTML
    assert (out / "report.html").stat().st_size > 0
    assert not list((out / "artifacts" / "figures").glob("report-*.pdf"))


def _words(text: str) -> str:
    """``text`` with single spaces, none after a hyphen (where a line may break)."""
    return re.sub(r"- ", "-", " ".join(text.split()))


@pytest.mark.parametrize("certificate", ["constant", "funnel"])
def test_html_and_pdf_agree_on_the_verdict_and_the_numbers(
    certificate: str, run: tuple[Scenario, Path], request: pytest.FixtureRequest
) -> None:
    """The verdict line, every headline card and the per-demonstration table as report.html
    shows them are in report.pdf's text, and the PDF states the verdict as often as the page;
    for the constant run and the funnel run (whose cards and table say what ships)."""
    out = run[1] if certificate == "constant" else request.getfixturevalue("synthesized")[1]
    html = (out / "report.html").read_text()
    pdf = _words(" ".join(_pdf_pages(out / "report.pdf")))
    verdict = re.search(r"<strong>(Verdict: [^<]*)</strong>", html)
    assert verdict, "no verdict in report.html"
    shown = [unescape(verdict.group(1))]
    cards = re.findall(r'<div class="(?:label|value|note)">([^<]*)</div>', html)
    assert len(cards) >= 18, cards
    shown += [unescape(card) for card in cards]
    if certificate == "funnel":  # the shipped funnels' cards come first
        assert cards[0] == "Shipped: controller.json" and "Arrival at T" in cards
    demos = html[re.search(r'<div class="caption" id="[^"]*">Per demonstration', html).start() :]
    demos = demos[: demos.index("</table>")]
    rows = re.findall(r"<tr>(.*?)</tr>", demos, flags=re.S)[1:]
    assert len(rows) == len(run[0].demos)
    for row in rows:  # the cells of a row, in order, on one line of the PDF's text
        cells = [unescape(c.strip()) for c in re.findall(r"<td[^>]*>(.*?)</td>", row, re.S)]
        shown.append(" ".join(cells))
    missing = [text for text in shown if _words(text) not in pdf]
    assert not missing, f"in report.html, not in report.pdf: {missing}"
    page = _words(" ".join(_parse(html).text))  # the subtitle says the verdict too
    assert pdf.count("Verdict: ") == page.count("Verdict: ") == 2
    assert pdf.count(shown[0]) == page.count(shown[0])


def test_units_and_labels_in_tables_and_figures(run: tuple[Scenario, Path]) -> None:
    """quadrotor_hill_flythrough declares units and labels: the K table, margins, the inputs
    figure's axes and the scenario figure's axes carry them; radii say they are P-norms and give
    metres."""
    html = (run[1] / "report.html").read_text()
    text = " ".join(" ".join(_parse(html).text).split())
    scenario = run[0]
    for name in scenario.input_names:  # K table rows, input margins, inputs figure titles
        assert text.count(scenario.label(name)) >= 3, scenario.label(name)
    for name in scenario.state_names:  # K table header
        assert f"{scenario.label(name)}" in text
    assert "u1 (thrust) [N]" in text and "X (horizontal position) [m]" in text
    assert "[unit of u_j] per [unit of x_i]" in text
    assert "Robustness radii in the P-norm" in text and "extent after (m)" in text
    inputs = html[html.index('id="figure-inputs"') :]
    assert ">u2 (pitch acceleration) [rad/s^2]<" in inputs[: inputs.index("</figure>")]


def test_the_scenario_figure_is_written_beside_the_report(run: tuple[Scenario, Path]) -> None:
    image = matplotlib.image.imread(run[1] / "scenario.png")
    assert image.shape[0] > 400 and image.shape[1] > 800
    assert image[..., :3].std() > 0.05  # drawn, not blank


def test_missing_artifact_is_a_clear_error(run: tuple[Scenario, Path], tmp_path: Path) -> None:
    scenario, out = run
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    (copy / "artifacts" / "optimize.json").unlink()
    with pytest.raises(UserError, match=r"optimize\.json: artifact of stage 'optimize' not found"):
        load_report_data(scenario, copy)
    assert not (copy / "report.pdf").exists() or (copy / "report.pdf").stat().st_size > 0


def test_cli_rebuilds_the_report_from_saved_artifacts(
    run: tuple[Scenario, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    out = run[1]
    stages = sorted((out / "artifacts").glob("*.npz"))
    before = {p.name: p.stat().st_mtime_ns for p in stages}
    written = [out / "report.html", out / "report.pdf"]
    reports = {p: p.stat().st_mtime_ns for p in written}
    assert main(["report", "quadrotor_hill_flythrough", "--from", str(out)]) == 0
    printed = capsys.readouterr().out
    assert str(out / "report.html") in printed
    assert str(out / "report.pdf") in printed
    assert {p.name: p.stat().st_mtime_ns for p in stages} == before  # nothing recomputed
    assert all(p.stat().st_mtime_ns > t for p, t in reports.items())  # both rewritten
    assert not list(out.glob(".report.*"))  # no temporary files left by the atomic writes


def test_a_rebuild_reuses_exactly_the_figures_whose_inputs_did_not_change(
    run: tuple[Scenario, Path], tmp_path: Path
) -> None:
    scenario, good = run
    out = tmp_path / "copy"
    shutil.copytree(good, out)
    shutil.rmtree(out / "artifacts" / "figures", ignore_errors=True)
    data = load_report_data(scenario, out)
    cold = write_reports(data)
    assert "(6 figures drawn)" in cold.message
    html, pdf = (out / "report.html").read_text(), (out / "report.pdf").read_bytes()
    figures = sorted(p.name for p in (out / "artifacts" / "figures").iterdir())
    assert sum(name.endswith(".svg") for name in figures) == 6
    assert sum(name.startswith("report-") for name in figures) == 1

    warm = write_reports(data)  # nothing changed: every figure and the PDF reused, same files
    assert "(every figure reused)" in warm.message
    assert ", reused)" in warm.message
    assert (out / "report.html").read_text() == html and (out / "report.pdf").read_bytes() == pdf
    assert sorted(p.name for p in (out / "artifacts" / "figures").iterdir()) == figures

    # another Monte Carlo result: its figure and the inputs figure (worst start) are redrawn
    other = dataclasses.replace(data, keys={**data.keys, "montecarlo": "another run"})
    assert "(2 figures drawn)" in write_reports(other).message
    assert len(list((out / "artifacts" / "figures").glob("*.svg"))) == 6  # stale ones pruned


def test_cli_report_writes_into_out_and_reads_from_from(
    run: tuple[Scenario, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``report NAME --from RUN --out DIR``: reads the run, writes the reports into DIR only."""
    source, target = run[1], tmp_path / "elsewhere"

    def files() -> dict[Path, int]:  # the run's files (its lock is taken while reading)
        return {p: p.stat().st_mtime_ns for p in source.rglob("*") if p.name != ".lock"}

    before = files()
    name = "quadrotor_hill_flythrough"
    assert main(["report", name, "--from", str(source), "--out", str(target)]) == 0
    assert str(target / "report.html") in capsys.readouterr().out
    assert {p.name for p in target.iterdir()} == {"report.html", "scenario.png", "report.pdf"}
    assert files() == before
    assert str(source) in (target / "report.html").read_text()  # names the run it shows


def test_cli_report_reads_reports_name_under_the_current_directory(
    run: tuple[Scenario, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    monkeypatch.chdir(tmp_path)
    name = "quadrotor_hill_flythrough"
    assert main(["report", name]) == 2  # no ./reports/quadrotor_hill_flythrough here
    assert str(tmp_path / "reports" / name / "summary.json") in capsys.readouterr().err


def test_cli_report_of_a_missing_run_is_one_clear_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["report", "quadrotor_hill_flythrough", "--from", str(tmp_path / "empty")]) == 2
    error = capsys.readouterr().err
    assert error.startswith("error: ") and "summary.json not found" in error
    assert "python -m pipeline synthesize quadrotor_hill_flythrough" in error
    assert error.count("\n") == 1  # one line, no traceback


@pytest.mark.chromium
@needs_browser
def test_chromium_renders_the_report(run: tuple[Scenario, Path], tmp_path: Path) -> None:
    url = (run[1] / "report.html").resolve().as_uri()
    profile = tmp_path / "profile"
    shot = tmp_path / "first_screen.png"
    first = chromium(f"--screenshot={shot}", "--window-size=1280,2000", url, profile=profile)
    assert shot.is_file(), first.stderr[-2000:]
    pixels = matplotlib.image.imread(shot)[..., :3]  # (H, W, 3) in [0, 1]
    assert pixels.shape[:2] == (2000, 1280)
    ink = np.any(pixels < 0.9, axis=-1)
    assert ink.mean() > 0.03 and pixels.std() > 0.05, "the first screen is blank"
    for line in first.stderr.splitlines():
        assert "CONSOLE" not in line and "Failed to load resource" not in line, line

    # the whole page: tall enough to hold all sections, its DOM complete after loading
    tall = tmp_path / "page.png"
    chromium(f"--screenshot={tall}", "--window-size=1280,16000", url, profile=profile)
    rows = np.flatnonzero(np.any(matplotlib.image.imread(tall)[..., :3] < 0.9, axis=(1, 2)))
    assert rows.max() > 6000, f"page content ends at {rows.max()} px"
    dom = chromium("--dump-dom", url, profile=profile)
    assert dom.returncode == 0, dom.stderr[-2000:]
    assert dom.stdout.count("<svg") == 6 and dom.stdout.rstrip().endswith("</html>")
    for key in ("summary", "scenario", "optimization", "feedback", "coverage", "reproducibility"):
        assert f'id="{key}"' in dom.stdout


@pytest.mark.chromium
@needs_browser
@pytest.mark.parametrize("width", [1280, 390])
def test_figures_fit_their_box_at_desktop_and_phone_width(
    run: tuple[Scenario, Path], tmp_path: Path, width: int
) -> None:
    """Measured by the browser on a copy of the page with a measuring script: each figure
    inside the viewport (no sideways scrolling), every legend and colour bar inside its
    figure's box, and the smallest figure text at least 8 px on screen; no element wider
    than the column, no table scrolling sideways at 1280 px, the claims and per-demo tables
    as cards on a phone, every caption outside its table's scroll box (issue 30, item 5)."""
    measured = measure_in_browser((run[1] / "report.html").read_text(), width, tmp_path)
    assert measured["view"] == width
    assert measured["scroll"] <= width, "the page scrolls sideways"
    assert len(measured["figures"]) == 6
    assert any(g[0] == "bisection-colorbar" for f in measured["figures"] for g in f["parts"])
    assert_figures_fit(measured, width)
    assert_layout(measured, width)
    # the figures fill the column (they were 640 px at most in a 1170 px column)
    for figure in measured["figures"]:
        assert figure["right"] - figure["left"] >= measured["column"][1] - measured["column"][0] - 2
