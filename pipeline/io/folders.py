"""Where a run writes: under the directory the user runs from, never beside the package.

``python -m pipeline synthesize NAME`` (and ``pipeline.synthesize``) write ``./reports/NAME``
unless told ``--out DIR``; ``report`` and the recorder read the same place by default. An
installed package (``pip install .``) therefore never writes into ``site-packages``.
"""

from __future__ import annotations

from pathlib import Path

REPORTS_FOLDER = "reports"


def default_output_folder(scenario_name: str) -> Path:
    """``./reports/NAME`` under the current working directory (absolute)."""
    return Path.cwd() / REPORTS_FOLDER / scenario_name
