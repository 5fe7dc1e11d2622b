"""Numbers that agree (issue 30, item 3): every number report.html shows twice is the same number
(the headline cards against the tables and the Monte Carlo section), for the session's funnel run
of quadrotor_hill_flythrough and its constant-certificate run; runs failed and failure kinds are
told apart, by one text, in the terminal and the report; no infinity is shown; the captions are true
for the certificate that ran; the paper's numbers are quoted for the paper's scenario only."""

from __future__ import annotations

import dataclasses
import json
import math
import re
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from pipeline.model.scenario import load_scenario
from pipeline.reporting.numbers import (
    fixed,
    formatted,
    margin,
    montecarlo_counts,
    number,
    percent,
    scientific,
    seconds,
)
from pipeline.reporting.sections import build_sections, headline_items
from pipeline.reporting.summary import Summary
from pipeline.runtime import stored
from pipeline.runtime.stored import load_report_data
from pipeline.runtime.terminal import format_summary

INFINITY = re.compile(r"(?<![\w.])[-+]?inf(inity)?(?![\w])|\bnan\b", re.IGNORECASE)


def test_the_counts_text_tells_runs_failed_from_failure_kinds() -> None:
    kinds = {"unsafe": 0, "goal": 0, "clipping": 34, "uncovered": 335}
    assert montecarlo_counts(500, 335, kinds) == (
        "335 of 500 runs failed; kinds: clipping 34, uncovered 335"
    )
    assert montecarlo_counts(500, 0, dict.fromkeys(kinds, 0)) == "0 of 500 runs failed"


def test_non_finite_numbers_read_n_a_with_the_reason() -> None:
    assert formatted(-math.inf, ".3f", "not covered") == "n/a (not covered)"
    assert formatted(math.inf, ".3f") == "n/a (infinite)"
    assert formatted(math.nan, ".3f") == "n/a (not computed)"
    assert formatted(None, ".3f") == "n/a (not computed)"
    for shown in (
        number(-math.inf),
        fixed(math.inf),
        percent(math.nan),
        scientific(math.inf),
        seconds(-math.inf),
    ):
        assert shown.startswith("n/a (") and not INFINITY.search(shown), shown
    assert seconds(2.04) == "2.0 s" and fixed(-0.0123, 3) == "-0.012"
    assert margin(-math.inf, "not covered") == "n/a (not covered)"
    assert margin(0.0334, "input slack, input units") == "0.033 (input slack, input units)"


class _Report(HTMLParser):
    """report.html's headline cards (label -> (value, note)), tables (caption, header, rows),
    paragraphs and verdict text; SVG content skipped."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.cards: dict[str, tuple[str, str]] = {}
        self.tables: list[tuple[str, list[str], list[list[str]]]] = []
        self.paragraphs: list[str] = []
        self.figure_captions: list[str] = []
        self.text: list[str] = []
        self._field: str | None = None  # the card's div being read
        self._card: dict[str, str] = {}
        self._cell: list[str] | None = None
        self._svg = 0
        self._caption = False  # inside a table's caption (a div before its scroll box)
        self._pending = ""  # the caption read, for the next table

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        classes = (dict(attrs).get("class") or "").split()
        if tag == "svg":
            self._svg += 1
        elif tag == "div" and "card" in classes:
            self._card = {}
        elif tag == "div" and self._card is not None and classes[:1] in (["label"], ["value"]):
            self._field = classes[0]
        elif tag == "div" and classes[:1] == ["note"]:
            self._field = "note"
        elif tag == "div" and classes[:1] == ["caption"]:
            self._caption, self._cell = True, []
        elif tag == "table":
            self.tables.append((self._pending, [], []))
            self._pending = ""
        elif tag == "tr" and self.tables:
            self.tables[-1][2].append([])
        if tag in ("caption", "td", "th", "p", "figcaption") or self._field:
            self._cell = []

    def handle_endtag(self, tag: str) -> None:
        if tag == "svg":
            self._svg -= 1
            return
        text = " ".join("".join(self._cell or []).split())
        if tag == "div" and self._caption:
            self._pending, self._caption, self._cell = text, False, None
            return
        if tag == "div" and self._field:
            self._card[self._field] = text
            self._field, self._cell = None, None
            if "note" in self._card:
                self.cards[self._card["label"]] = (self._card["value"], self._card["note"])
                self._card = {}
        elif tag == "caption":
            caption, header, rows = self.tables[-1]
            self.tables[-1] = (text, header, rows)
        elif tag in ("td", "th"):
            row = self.tables[-1][2][-1]
            row.append(text)
        elif tag == "p":
            self.paragraphs.append(text)
        elif tag == "figcaption":
            self.figure_captions.append(text)
        if tag in ("caption", "td", "th", "p", "figcaption"):
            self._cell = None

    def handle_data(self, data: str) -> None:
        if self._svg:
            return
        self.text.append(data)
        if self._cell is not None:
            self._cell.append(data)

    def table(self, caption: str) -> tuple[list[str], list[list[str]]]:
        """The header and body rows of the table whose caption starts with ``caption``."""
        found = [t for t in self.tables if t[0].startswith(caption)]
        assert len(found) == 1, f"{len(found)} tables captioned {caption!r}"
        _, _, rows = found[0]
        return rows[0], rows[1:]

    def row(self, caption: str, first: str) -> list[str]:
        """The row of that table whose first cell starts with ``first``."""
        _, rows = self.table(caption)
        (row,) = [r for r in rows if r[0].startswith(first)]
        return row


def _read(out: Path) -> _Report:
    report = _Report()
    report.feed((out / "report.html").read_text())
    report.close()
    return report


def _value(text: str) -> float:
    """The first number in ``text``."""
    found = re.search(r"[-+]?\d+(\.\d+)?(e[-+]?\d+)?", text)
    assert found, text
    return float(found.group(0))


def _cross_check(out: Path) -> tuple[_Report, Summary]:
    """Every number shown twice in ``out``'s report.html agrees; returns the parsed report."""
    report = _read(out)
    summary = Summary.from_json(json.loads((out / "summary.json").read_text()))
    h, mc = summary.headline, summary.montecarlo
    text = " ".join(" ".join(report.text).split())
    # Monte Carlo: the card, the section's paragraph, the kinds table (and its caption)
    value, note = report.cards["Monte Carlo"]
    counts = montecarlo_counts(h.montecarlo_samples, h.montecarlo_failures, mc.failures)
    assert value == counts.split(";")[0]
    assert f"Result: {counts};" in text
    header, kinds = report.table("Failures by kind")
    assert f"({counts};" in [t[0] for t in report.tables if t[0].startswith("Failures")][0]
    assert {k: int(v) for k, v in kinds} == {k: int(v) for k, v in mc.failures.items()}
    failed = int(value.split()[0])
    assert failed <= h.montecarlo_samples and failed >= max(mc.failures.values(), default=0)
    bound = scientific(h.failure_bound_95)
    assert f"≤ {bound}" in note
    assert report.row("Margins", "failure probability")[1] == bound
    claims = report.table("Claims")[1]
    assert [c for c in claims if c[0] == f"failure probability <= {bound}"], claims
    # the closed-loop clearance: the card (2 decimals) and the margins table (3)
    card = _value(report.cards["Closed-loop clearance (Monte Carlo)"][0])
    table = _value(report.row("Margins", "minimum clearance to Unsafe")[1])
    assert card == pytest.approx(round(table, 2), abs=0.0051)
    # Init coverage: the card against the coverage table (and, funnel run, what ships)
    header, demos = report.table("Per demonstration")
    text_columns = ("level set by", "optimized")
    column = {
        name: [_value(d[header.index(name)]) for d in demos]
        for name in header[2:]
        if name not in text_columns
    }
    low, high = (_value(p) for p in report.cards["Nominal clearance to Unsafe"][0].split("→"))
    faster_note = report.cards["Faster (mean over demos)"][1]
    times = re.search(r"terminal time ([\d.]+) s → ([\d.]+) s", faster_note)
    assert times, report.cards
    faster = _value(report.cards["Faster (mean over demos)"][0])
    assert faster == pytest.approx(np.mean(column["faster"]), abs=1.0)
    assert float(times[1]) == pytest.approx(np.mean(column["T demo (s)"]), abs=0.1)
    if summary.certificate == "funnel":
        shown = report.cards["Init coverage"][0]
        assert report.row("Coverage certificate", "shipped funnels")[2] == shown
        shipped = report.row("Constant vs funnel", "funnel")
        assert shipped[5] == shown and f"Monte Carlo: {counts}" in shipped[6]
        assert f"cover {shown} of Init" in " ".join(report.figure_captions)
        # what ships: the cards against the per-demo table of the shipped funnels
        assert float(times[2]) == pytest.approx(np.mean(column["T shipped (s)"]), abs=0.1)
        assert high == pytest.approx(min(column["nominal clearance (m)"]), abs=0.0051)
        assert low == pytest.approx(min(d.clearance_before for d in summary.demos), abs=0.0051)
        funnel = _value(report.cards["Funnel clearance to Unsafe"][0].lstrip("≥ "))
        assert funnel == pytest.approx(min(column["funnel clearance (m)"]), abs=0.0051)
        speeds = column["arrival speed (m/s)"]
        arrival = report.cards["Arrival at T"][0]
        assert arrival.startswith(f"{min(speeds):.1f}") and f"{max(speeds):.1f} m/s" in arrival
        T = column["T shipped (s)"]
        value = report.cards["Shipped: controller.json"][0]
        assert f"T {min(T):.1f}" in value and value.endswith(f"{max(T):.1f} s")
        extent = re.search(r"at most ([\d.]+) m", report.cards["Arrival at T"][1])
        assert extent and float(extent[1]) == pytest.approx(
            max(column["extent at T (m)"]), abs=0.0051
        )
    else:
        before, after = (float(p.strip(" %")) for p in report.cards["Init coverage"][0].split("→"))
        assert report.row("Coverage certificate", "demonstrations")[2] == f"{before:.1f}%"
        assert report.row("Coverage certificate", "optimized")[2] == f"{after:.1f}%"
        assert float(times[2]) == pytest.approx(np.mean(column["T opt (s)"]), abs=0.1)
        assert low == pytest.approx(min(column["clearance before (m)"]), abs=0.0051)
        assert high == pytest.approx(min(column["clearance after (m)"]), abs=0.0051)
    # the wall time: the card and the timings table's total
    total = _value(report.row("Wall time per stage", "total")[1])
    assert _value(report.cards["Wall time"][0]) == pytest.approx(total, abs=0.051)
    # the verdict: the verdict box and summary.json
    assert f"Verdict: {summary.text}" in text
    # no infinity or NaN anywhere in the text
    assert not INFINITY.search(text), INFINITY.search(text)
    return report, summary


def test_every_number_shown_twice_agrees_in_the_funnel_run(synthesized) -> None:
    code, out = synthesized
    report, summary = _cross_check(out)
    assert summary.certificate == "funnel"
    # ModGoal: the shipped nominals need not end in it (their funnels at T lie in Goal)
    (scene,) = [p for p in report.paragraphs if p.startswith("Unsafe: ")]
    assert "the shipped nominals (funnel certificate) need not end in it" in scene
    assert "E_i(T), must lie in Goal" in scene
    (monte_carlo,) = [p for p in report.paragraphs if "initial states drawn" in p]
    assert "error inside its funnel E_i(t)" in monte_carlo


def test_every_number_shown_twice_agrees_in_the_constant_run(synthesized_constant) -> None:
    code, out = synthesized_constant
    report, summary = _cross_check(out)
    assert summary.certificate == "constant"
    (scene,) = [p for p in report.paragraphs if p.startswith("Unsafe: ")]
    assert (
        "ModGoal: Goal shrunk by d (dashed), where the optimized trajectories must end. " in scene
    )
    assert "funnel" not in scene
    (monte_carlo,) = [p for p in report.paragraphs if "initial states drawn" in p]
    assert "error inside the predicted tube" in monte_carlo


def test_the_paper_is_quoted_for_its_own_scenario_only(synthesized) -> None:
    _, out = synthesized
    summary = Summary.from_json(json.loads((out / "summary.json").read_text()))
    notes = " ".join(item.note for item in headline_items(summary))
    assert "the paper: 42%" in notes and "the paper's demo: 0.22" in notes
    custom = dataclasses.replace(summary, scenario="my_quadrotor")
    assert "paper" not in " ".join(f"{i.value} {i.note}" for i in headline_items(custom))


def test_a_failing_monte_carlo_counts_runs_and_shows_no_infinity(
    synthesized, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """As in the issue: 335 of 1000 runs fail, some in two ways (uncovered 335, clipping 34),
    and the falsification's worst start is uncovered (margin -inf). The card, the terminal, the
    verdict's reasons and the Monte Carlo section say "335 of 1000 runs failed", never 369;
    the worst margin reads "n/a (not covered)"."""
    _, out = synthesized
    read = stored._read_stages

    def failing(*args, **kwargs):
        results, keys = read(*args, **kwargs)
        mc = results["montecarlo"]
        kinds = dict.fromkeys(mc.failures, 0) | {"uncovered": 335, "clipping": 34}
        results["montecarlo"] = dataclasses.replace(
            mc,
            failures=kinds,
            failed_x0=np.zeros((335, mc.failed_x0.shape[1])),
            success=False,
            falsification=dataclasses.replace(
                mc.falsification, worst_margin=-math.inf, binding="not covered"
            ),
        )
        return results, keys

    monkeypatch.setattr(stored, "_read_stages", failing)
    data = load_report_data(load_scenario("quadrotor_hill_flythrough"), out, write_to=tmp_path)
    summary = data.summary
    samples = summary.montecarlo.samples
    counts = f"{335} of {samples} runs failed; kinds: clipping 34, uncovered 335"
    assert summary.headline.montecarlo_failures == 335
    assert f"Monte Carlo failure: {counts}" in summary.reasons
    terminal = format_summary(summary, data.scenario)
    assert f"Monte Carlo: {counts}; failure probability" in terminal
    assert "worst safety margin found n/a (not covered)" in terminal
    assert not INFINITY.search(terminal), INFINITY.search(terminal)
    shown = []
    for section in build_sections(data):
        for block in section.blocks:
            if block.kind == "headlines":
                shown += [f"{i.label}: {i.value} ({i.note})" for i in block.items]
            elif block.kind == "table":
                shown += [block.caption, *(" | ".join(row) for row in block.rows)]
            elif block.kind in ("paragraph", "figure"):
                shown.append(getattr(block, "text", "") or block.caption)
            elif block.kind == "verdict":
                shown += [block.text, *block.reasons]
    text = "\n".join(shown)
    assert f"Monte Carlo: 335 of {samples} runs failed (kinds: clipping 34, uncovered 335" in text
    assert f"Result: {counts};" in text and f"Failures by kind ({counts};" in text
    (card,) = [line for line in shown if line.startswith("Monte Carlo: ")]
    assert card.startswith(f"Monte Carlo: 335 of {samples} runs failed (")  # not 369 = 335 + 34
    assert "worst safety margin found n/a (not covered)" in text
    assert "falsification: worst margin found | n/a (not covered)" in text
    assert not INFINITY.search(text), INFINITY.search(text)


def _blocks(out: Path, tmp_path: Path) -> list[tuple[str, str, str]]:
    """``(section key, kind, caption or text)`` of every figure, table and paragraph of the
    report of the run in ``out`` (rebuilt from its artifacts into ``tmp_path``)."""
    data = load_report_data(load_scenario("quadrotor_hill_flythrough"), out, write_to=tmp_path)
    return [
        (section.key, block.kind, getattr(block, "caption", "") or getattr(block, "text", ""))
        for section in build_sections(data)
        for block in section.blocks
        if block.kind in ("figure", "table", "paragraph")
    ]


# both runs are quadrotor_hill_flythrough's session runs, read through request.getfixturevalue: the
# conftest does not see them, so the test names their group (else another worker runs the
# synthesis again: 28 s of CPU)
@pytest.mark.xdist_group("synthesis-quadrotor_hill_flythrough")
@pytest.mark.parametrize("certificate", ["constant", "funnel"])
def test_every_caption_is_true_for_the_certificate_that_ran(
    certificate: str, request: pytest.FixtureRequest, tmp_path: Path
) -> None:
    """Issue 30, items 2-4: each caption read for the run's certificate. A funnel run's
    captions outside section "Seed and comparison" describe what ships, and any that names
    the constant certificate says it is not shipped (or the seed); the constant certificate's
    tables (radii, its gain K and certificate) are in that section only; the funnels are drawn
    as outlines with the arrival arrows. A constant run names no funnel and has no seed
    section. Both: the step-size panel is described only under gradient descent, the
    Monte Carlo caption says the dotted d line is not a closed-loop requirement."""
    fixture = "synthesized" if certificate == "funnel" else "synthesized_constant"
    out = request.getfixturevalue(fixture)[1]
    blocks = _blocks(out, tmp_path)
    captions = {key: [text for k, kind, text in blocks if k == key] for key, _, _ in blocks}
    method = json.loads((out / "artifacts" / "optimize.json").read_text())
    lbfgs = '"method": "lbfgs"' in json.dumps(method)
    (optimization,) = [t for k, kind, t in blocks if kind == "figure" and k == "optimization"]
    assert ("step size" in optimization) is not lbfgs, optimization
    (montecarlo,) = [t for k, kind, t in blocks if kind == "figure" and k == "montecarlo"]
    assert "not a closed-loop requirement" in montecarlo
    robustness = ("Robustness radii", "Constant certificate per demonstration", "Certificate")
    if certificate == "constant":
        assert "seed" not in captions
        for key, _kind, text in blocks:
            assert "funnel" not in text.lower(), (key, text)
        assert any(t.startswith("Robustness radii") for t in captions["coverage"])
        return
    assert list(captions)[-2:] == ["seed", "reproducibility"]
    for key, kind, text in blocks:
        if key in ("seed", "reproducibility"):
            continue
        if "constant certificate" in text:  # named only as the seed, or not shipped
            assert re.search(r"not shipped|seed|constant certificate's optimized", text), (
                key,
                text,
            )
        if kind == "table":
            assert not text.startswith(robustness), (key, text)
    seed = captions["seed"]
    assert any(
        t.startswith("Constant certificate per demonstration (the seed, not shipped)") for t in seed
    )
    assert any(
        t.startswith("Feedback gain K (inputs × states) of the constant certificate") for t in seed
    )
    assert seed[0].startswith("Not shipped.")
    (demos,) = [t for t in captions["summary"] if t.startswith("Per demonstration")]
    assert demos.startswith("Per demonstration: the shipped funnel of controller.json")
    figures = [t for _, kind, t in blocks if kind == "figure"]
    shipped = [t for t in figures if t.startswith(("All demonstrations", "The shipped funnels"))]
    assert len(shipped) == 2, figures
    for caption in shipped:  # the overview and the funnel figure
        assert "outline" in caption and "arrives" in caption and "shaded" not in caption
