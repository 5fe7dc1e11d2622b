"""Headless Chromium for the rendering tests of the HTML report: the browser found on PATH, a
skip mark without one, and the measurement of a page's figures at a given width."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from html import escape, unescape
from pathlib import Path

import pytest

# what the rendering tests run: the first of these on PATH (Chromium's headless shell before the
# full browser: the same engine for less than half the CPU); the reports need none
BROWSERS = ("chromium-headless-shell", "chromium", "chromium-browser", "google-chrome")
BROWSER = next((Path(found) for name in BROWSERS if (found := shutil.which(name))), None)
needs_browser = pytest.mark.skipif(BROWSER is None, reason="no Chromium on PATH")


def chromium(*arguments: str, profile: Path) -> subprocess.CompletedProcess[str]:
    """``BROWSER`` headless with ``arguments``, its profile in ``profile``; output captured."""
    return subprocess.run(
        [
            str(BROWSER),
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--enable-logging=stderr",
            "--v=0",
            f"--user-data-dir={profile}",
            *arguments,
        ],
        capture_output=True,
        text=True,
        timeout=180,
        check=False,
    )


MEASURE = """<script>
const out = {scroll: document.documentElement.scrollWidth, view: window.innerWidth, figures: []};
for (const svg of document.querySelectorAll("figure svg")) {
  const box = svg.getBoundingClientRect();
  const scale = box.width / svg.viewBox.baseVal.width;  // screen px per SVG unit
  const parts = [...svg.querySelectorAll('g[id*="legend_"], g[id$="-colorbar"]')].map((g) => {
    const r = g.getBoundingClientRect();
    return [g.id, r.left - box.left, r.top - box.top, box.right - r.right, box.bottom - r.bottom];
  });
  const sizes = [...svg.querySelectorAll("text")].map(
    (t) => parseFloat(getComputedStyle(t).fontSize) * scale);
  out.figures.push({id: svg.closest("figure").id, left: box.left, right: box.right, parts,
                    smallest: Math.min(...sizes)});
}
// layout: every element inside the column (main's content box), every scroll box without
// sideways overflow unless it is a table's, the stacked tables shown as cards, captions outside
const main = document.querySelector("main"), style = getComputedStyle(main);
const column = [main.getBoundingClientRect().left + parseFloat(style.paddingLeft),
                main.getBoundingClientRect().right - parseFloat(style.paddingRight)];
out.column = column;
out.wider = [...main.querySelectorAll("*")].filter((e) => !e.closest("svg") || e.tagName === "svg")
  .filter((e) => !e.closest(".table-wrap") || e.classList.contains("table-wrap"))
  .map((e) => [e.tagName + (typeof e.className === "string" ? "." + e.className : ""),
               e.getBoundingClientRect()])
  .filter(([, r]) => r.width > 0 && (r.left < column[0] - 1 || r.right > column[1] + 1))
  .map(([name, r]) => [name, r.left, r.right]);
out.tables = [...document.querySelectorAll("main table")].map((table) => {
  const wrap = table.closest(".table-wrap") || table.parentElement;
  const block = wrap.parentElement;
  const caption = table.querySelector("caption") || block.querySelector(".caption");
  return {caption: caption ? caption.textContent.slice(0, 40) : "",
          captionInWrap: caption ? wrap.contains(caption) : false,
          stack: table.classList.contains("stack"),
          display: getComputedStyle(table.querySelector("tbody tr")).display,
          overflow: wrap.scrollWidth - wrap.clientWidth};
});
document.body.setAttribute("data-measured", JSON.stringify(out));
</script>"""


def measuring_page(report: str, width: int) -> str:
    """The report in an iframe ``width`` px wide (a headless window is never narrower than
    500 px), measured by ``MEASURE`` inside it; the result copied into the outer page."""
    inner = report.replace("</body>", MEASURE + "</body>")
    return (
        f'<!doctype html><html><body style="margin:0"><iframe id="f" style="border:0;'
        f'width:{width}px;height:900px" srcdoc="{escape(inner, quote=True)}"></iframe>'
        "<script>window.onload = () => document.body.setAttribute('data-measured', "
        "document.getElementById('f').contentDocument.body.getAttribute('data-measured'));"
        "</script></body></html>"
    )


def measure_in_browser(html: str, width: int, folder: Path) -> dict:
    """The measuring script's result for ``html`` shown ``width`` px wide in headless Chromium."""
    page = folder / "measured.html"
    page.write_text(measuring_page(html, width))
    dom = chromium(
        "--window-size=1400,1000",
        "--virtual-time-budget=5000",
        "--dump-dom",
        page.as_uri(),
        profile=folder / "profile",
    )
    found = re.search(r'data-measured="([^"]*)"', dom.stdout)
    assert found, dom.stderr[-2000:]
    return json.loads(unescape(found.group(1)))


def assert_figures_fit(measured: dict, width: int) -> None:
    """Each figure inside the page, with a legend or colour bar inside it and text >= 8 px."""
    for figure in measured["figures"]:
        assert figure["left"] >= 0 and figure["right"] <= width, figure
        assert figure["parts"], f"{figure['id']}: no legend found"
        for name, *margins in figure["parts"]:
            assert min(margins) >= -1.0, f"{name} sticks out of its figure by {-min(margins)} px"
        assert figure["smallest"] >= 8.0, f"{figure['id']}: text {figure['smallest']:.1f} px"


def assert_layout(measured: dict, width: int) -> None:
    """No element wider than the column; on a phone (< 700 px) the stacked tables (claims,
    per demonstration) are cards with nothing to scroll sideways; at any width no table scrolls
    sideways at 1280 px and wider; every caption outside its table's scroll box."""
    assert not measured["wider"], f"wider than the column {measured['column']}: {measured['wider']}"
    for table in measured["tables"]:
        assert not table["captionInWrap"], table
        if table["stack"] and width < 700:
            assert table["display"] == "block" and table["overflow"] <= 1, table
        if width >= 1280:
            assert table["overflow"] <= 1, f"scrolls sideways at {width} px: {table}"
    assert measured["tables"], "no table measured"
    if width < 700:
        assert sum(table["stack"] for table in measured["tables"]) >= 2  # claims, per demo
