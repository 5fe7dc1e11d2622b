"""report.pdf's writer (``pipeline.reporting.typeset``) without a run: every text, however
hostile to Typst's markup (``#``, ``$``, ``*``, ``_``, ``<``, ``@``, backslashes, brackets,
quotes, a line starting like a heading or a list), comes out verbatim; the figures' SVGs are
embedded with their text; the same content gives the same bytes."""

from __future__ import annotations

import io
import os
import unicodedata
from pathlib import Path

import pytest
from pypdf import PdfReader

from pipeline.io.files import output_root
from pipeline.reporting import typeset
from pipeline.reporting.content import (
    Figure,
    Headline,
    Headlines,
    Paragraph,
    Section,
    Table,
    Verdict,
)
from pipeline.reporting.figure_cache import FigureStore
from pipeline.reporting.pdf import PdfOutcome, write_pdf

HOSTILE = (
    '#panic("injected") #read("/etc/passwd")',
    "$x^2$ *bold* _under_ <label> @ref `raw` ~ tilde",
    "back\\slash \\n \\\\ [bracket] ]) } { #{1 + 1}",
    '" quote "), text("injected',
    "// not a comment /* nor this */",
    "= not a heading",
    "- not a list",
    "+ not an enumeration",
    "1. not numbered",
    "a 'quoted' name: → ≤ ρ λ ✓ ✗ ² σ_min",
    "hill#1_$x$ \u00e9t\u00e9",
)
NAME = "scenario #1: *x* $y$ <z> @w \\ [v]"
LONG = "f" * 64  # a digest: wraps in the column, comes out whole


def _plot(fig: object) -> None:
    ax = fig.subplots()  # type: ignore[attr-defined]
    ax.plot([0, 1], [0, 1])
    ax.set_xlabel("figure-text-marker")


def _sections() -> list[Section]:
    return [
        Section(
            "summary",
            1,
            f"Summary of {NAME}",
            (
                Paragraph(f"Scenario {NAME}: " + HOSTILE[0]),
                Verdict(False, "not certified: " + HOSTILE[1], HOSTILE[2:4]),
                Headlines(tuple(Headline(h, f"{k} %", h) for k, h in enumerate(HOSTILE[4:7]))),
                Table(
                    ("claim", "kind", "how"),
                    (
                        (HOSTILE[7], "certified", HOSTILE[8]),
                        (LONG, "no such kind", "1.23"),
                    ),
                    HOSTILE[9],
                    numeric=(False, False, True),
                    badges=1,
                ),
            ),
        ),
        Section(
            "figure",
            2,
            HOSTILE[10],
            (
                Figure("plot", HOSTILE[5] + " " + HOSTILE[6], _plot, (3.0, 2.0), "inputs"),
                Paragraph(HOSTILE[4], "note"),
            ),
        ),
    ]


def _text(pdf: bytes) -> str:
    pages = PdfReader(io.BytesIO(pdf)).pages
    text = " ".join(unicodedata.normalize("NFC", page.extract_text()) for page in pages)
    return " ".join(text.replace("\u200b", "").split())


@pytest.fixture(scope="module")
def written(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    folder = tmp_path_factory.mktemp("typeset")
    store = FigureStore(folder / "figures")
    sections = _sections()
    for section in sections:
        for block in section.blocks:
            if isinstance(block, Figure):
                store.svg(block)
    outcome = write_pdf(
        store,
        folder / "report.pdf",
        title=f"Report: {NAME}",
        subtitle=HOSTILE[0],
        sections=sections,
        colophon=HOSTILE[2],
    )
    store.close()
    assert outcome.path == folder / "report.pdf", outcome.message
    return folder / "report.pdf", _text(outcome.path.read_bytes())


def test_every_hostile_text_comes_out_verbatim(written: tuple[Path, str]) -> None:
    path, text = written
    assert path.read_bytes().startswith(b"%PDF-")
    assert text.startswith(f"Report: {NAME}")
    for hostile in (*HOSTILE, NAME, f"1. Summary of {NAME}", LONG, "figure-text-marker"):
        assert " ".join(hostile.split()) in text, hostile
    assert "Verdict: not certified: " + HOSTILE[1] in text
    assert text.count("injected") == 3  # subtitle, paragraph, reason: shown, never run


def test_the_same_content_gives_the_same_pdf(written: tuple[Path, str]) -> None:
    sections = _sections()
    store = FigureStore(None)
    svgs = {"plot": store.svg(sections[1].blocks[0])}  # type: ignore[arg-type]
    store.close()
    inputs = typeset.document_inputs("Report", "", sections, "", svgs)
    assert typeset.typeset(inputs) == typeset.typeset(inputs)


def test_a_figure_fits_the_column_and_the_page() -> None:
    assert typeset.figure_width((5.2, 4.0)) == pytest.approx(5.2 * 25.4)  # as drawn
    assert typeset.figure_width((10.0, 4.0)) == typeset.COLUMN  # no wider than the column
    tall = typeset.figure_width((5.2, 12.0))  # no taller than the page leaves room for
    assert tall * 12.0 / 5.2 == pytest.approx(typeset.TALLEST)


def test_a_figure_without_its_svg_is_an_error() -> None:
    with pytest.raises(ValueError, match=r"no SVG for the figures \['plot'\]"):
        typeset.document_inputs("Report", "", _sections(), "", {})


def test_a_long_token_breaks_within_the_column() -> None:
    """A digest or a path has no space to break at: it breaks every few characters instead of
    running off the page (600 narrow letters are about four lines of the column)."""
    inputs = typeset.document_inputs(
        "Report", "", [Section("s", 1, "S", (Paragraph("digest " + "f" * 600),))], "", {}
    )
    text = PdfReader(io.BytesIO(typeset.typeset(inputs))).pages[0].extract_text()
    runs = [len(line) for line in text.replace("\u200b", "").split() if set(line) == {"f"}]
    assert sum(runs) == 600 and len(runs) >= 3 and max(runs) < 200, runs


def test_a_path_that_is_not_utf8_is_shown_with_its_byte_escaped() -> None:
    """A run folder named with byte 0xff (a lone surrogate once decoded) in the text and in a
    figure's SVG: Typst takes only valid Unicode (the report stage failed with
    UnicodeEncodeError); the byte is shown as \\xff, as in report.html."""
    odd = os.fsdecode(b"/tmp/out\xff")
    figure = Figure("plot", "caption", _plot, (3.0, 2.0), "inputs")
    store = FigureStore(None)
    svg = store.svg(figure).replace("figure-text-marker", f"marker {odd}")
    store.close()
    section = Section("s", 1, "S", (Paragraph(f"run {odd}"), figure))
    inputs = typeset.document_inputs("Report", "", [section], f"from {odd}", {"plot": svg})
    text = _text(typeset.typeset(inputs))
    assert text.count("/tmp/out\\xff") == 3, text  # the paragraph, the figure, the colophon


def test_a_kept_pdf_that_is_a_link_is_neither_read_nor_written_through(tmp_path: Path) -> None:
    """The kept PDF (``artifacts/figures/report-DIGEST.pdf``) swapped for a link to a file
    outside the output folder: it is typeset again and replaced by a file; the link's target is
    neither copied into report.pdf nor written."""
    out, outside = tmp_path / "out", tmp_path / "outside.pdf"
    out.mkdir()
    outside.write_bytes(b"not the report")
    sections = [Section("s", 1, "S", (Paragraph("text"),))]

    def write() -> PdfOutcome:
        store = FigureStore(out / "figures")
        try:
            return write_pdf(
                store, out / "report.pdf", title="R", subtitle="", sections=sections, colophon=""
            )
        finally:
            store.close()

    with output_root(out):  # as in a run (folder_lock)
        write()
        [kept] = (out / "figures").glob("report-*.pdf")
        kept.unlink()
        kept.symlink_to(outside)
        outcome = write()
    assert outcome.path == out / "report.pdf" and not outcome.reused, outcome.message
    assert (out / "report.pdf").read_bytes().startswith(b"%PDF-")
    assert not kept.is_symlink() and kept.read_bytes() == (out / "report.pdf").read_bytes()
    assert outside.read_bytes() == b"not the report"
