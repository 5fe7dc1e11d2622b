"""Saving a valid recorded flight: ``demos/recorded_NN.csv`` plus an entry in the YAML's demo list.

The scenario file is edited as text, not re-serialised, so its comments and layout are kept: one
line ``  - {file: demos/recorded_NN.csv, x0: [...]}  # comment`` is inserted after the last entry
of the ``demos:`` block (a ``demos:`` block is appended when there is none). The new text must
parse to the old demo list plus that entry; it is written atomically and the scenario is then
loaded again with every demo simulated. If anything fails, the old file is put back and the CSV
removed, so an invalid flight is never left listed as a demonstration.
"""

from __future__ import annotations

import datetime
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import yaml

from pipeline.demonstrations.recorder.flight import Flight
from pipeline.io.artifacts import atomic_write_text
from pipeline.io.errors import UserError
from pipeline.model.demos import demo_entry, write_demo_csv
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario, load_scenario

RECORDED_NAME = re.compile(r"recorded_(\d+)\.csv$")


def with_demo_entry(text: str, file: str, x0: Sequence[float], comment: str = "") -> str:
    """``text`` of a scenario file with one more entry in its ``demos:`` list (comments kept)."""
    entry = demo_entry(file, x0) + (f"  # {comment}" if comment else "")
    lines = text.splitlines(keepends=True)
    if lines and not lines[-1].endswith("\n"):
        lines[-1] += "\n"
    start = next((i for i, line in enumerate(lines) if re.match(r"demos\s*:", line)), None)
    if start is None:
        return "".join(lines) + f"demos:\n  - {entry}\n"
    head = lines[start]
    value = head.split(":", 1)[1].split("#", 1)[0].strip()
    if value == "[]":
        lines[start] = head.replace("[]", "", 1)
    elif value:
        raise UserError(
            "the demos list is written in flow style, so the recorder cannot add to it",
            field="demos",
            found=value[:40],
            expected="a block list, one '  - {file: ..., x0: [...]}' line per demo",
        )
    last, indent = start, "  "
    for i in range(start + 1, len(lines)):
        line = lines[i]
        if line.strip() and not line[0].isspace() and not line.startswith(("-", "#")):
            break  # the next top-level key
        if line.strip() and not line.lstrip().startswith("#"):
            last = i
            item = re.match(r"(\s*)-\s", line)
            indent = item.group(1) if item else indent
    lines.insert(last + 1, f"{indent}- {entry}\n")
    return "".join(lines)


def append_demo_entry(path: Path, file: str, x0: FloatArray, comment: str = "") -> None:
    """Add ``{file, x0}`` to the ``demos:`` list of the scenario file ``path``, atomically."""
    text = path.read_text(encoding="utf-8")
    new_text = with_demo_entry(text, file, np.asarray(x0).tolist(), comment)
    old = (yaml.safe_load(text) or {}).get("demos") or []
    new = (yaml.safe_load(new_text) or {}).get("demos") or []
    expected = [*old, {"file": file, "x0": [float(v) for v in x0]}]
    if new != expected:
        raise UserError(
            "could not add the demo to the scenario file's demos list (layout not understood)",
            file=path,
            field="demos",
            expected=f"a block list; add by hand: - {demo_entry(file, np.asarray(x0).tolist())}",
        )
    atomic_write_text(path, new_text)


def next_recorded_name(scenario: Scenario) -> str:
    """``demos/recorded_NN.csv`` with ``NN`` one above every recorded demo, listed or on disk."""
    folder = scenario.path.parent / "demos"
    used = [d.file.name for d in scenario.demos]
    used += [p.name for p in folder.glob("recorded_*.csv")] if folder.is_dir() else []
    numbers = [int(match.group(1)) for name in used if (match := RECORDED_NAME.search(name))]
    return f"demos/recorded_{max(numbers, default=0) + 1:02d}.csv"


def recorded_header(
    scenario: Scenario, flight: Flight, device: str, when: datetime.datetime
) -> str:
    """The CSV comment header of a recorded flight: a human, the recorder, when, which device."""
    names = ", ".join(scenario.state_names)
    return (
        f"HUMAN demonstration of scenario '{scenario.name}': recorded by a person flying the\n"
        f"recorder (python -m pipeline record {scenario.name}) on"
        f" {when:%Y-%m-%d %H:%M:%S %Z}, input device: {device}.\n"
        f"start x0 = {flight.x0.tolist()} ({names})\n"
        f"{flight.us.shape[0]} samples, {flight.message}.\n"
        f"Row k holds u[k] on [k Ts, (k+1) Ts), Ts = {scenario.Ts:g} s."
    )


def save_flight(
    scenario: Scenario, flight: Flight, device: str, when: datetime.datetime | None = None
) -> Path:
    """Write a valid ``flight`` as ``demos/recorded_NN.csv``, list it in the scenario file and
    validate the scenario; on any failure restore the file, remove the CSV and re-raise.
    Returns the CSV's path."""
    if not flight.status.valid:
        raise ValueError(f"only flights that reached Goal are saved, not: {flight.message}")
    when = when or datetime.datetime.now(datetime.UTC)
    path = scenario.path
    file = next_recorded_name(scenario)
    csv_path = path.parent / file
    old_text = path.read_text(encoding="utf-8")
    header = recorded_header(scenario, flight, device, when)
    write_demo_csv(csv_path, flight.us, scenario.input_names, scenario.Ts, header)
    try:
        comment = f"HUMAN, recorded {when:%Y-%m-%d} with {device}"
        append_demo_entry(path, file, flight.x0, comment)
        load_scenario(path, check_demos=True)
    except BaseException:
        if path.read_text(encoding="utf-8") != old_text:
            atomic_write_text(path, old_text)
        csv_path.unlink(missing_ok=True)
        raise
    return csv_path
