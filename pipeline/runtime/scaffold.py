"""``python -m pipeline new NAME [--like TEMPLATE]``: a new scenario folder to start from.

The template is a shipped scenario, so it is known to certify: ``scenarios/NAME/scenario.yaml``
is its file renamed, with a guide to the fields on top and an empty ``demos:`` block, and
``scenarios/NAME/pilot.py`` is its steering law with a minimal ``CONFIG`` (only the
``PilotConfig`` fields without a default, or whose template value differs from it; the others
are listed with their meaning in a comment). Both are written into a temporary folder beside the
target, renamed into place: a failure leaves nothing half-made.
"""

from __future__ import annotations

import dataclasses
import os
import re
import secrets
import shutil
from pathlib import Path

from pipeline.demonstrations.pilot import PILOT_FILE, PilotConfig, load_pilot
from pipeline.io.errors import UserError
from pipeline.model.scenario import LOCAL_SCENARIOS, available_scenarios, load_scenario
from pipeline.model.scenario_file import (
    _shipped_scenarios,  # the templates: not SCENARIOS_ROOT, which SAFETY_SCENARIOS may move
)

TEMPLATES = ("double_integrator", "unicycle_slalom", "quadrotor_hill_flythrough")
NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]{0,63}")

# What each PilotConfig field means, for the comments of the written pilot.py.
PILOT_FIELDS = {
    "waypoints": "the route in the position plane (m); the last one is the landing aim",
    "waypoint_jitter": "std of each flight's random waypoint deviation (m)",
    "cruise_speed": "speed the pilot asks for between waypoints (m/s)",
    "capture_radius": "switch to the next waypoint within this distance of it (m)",
    "k_position": "approach gain at the last waypoint (1/s): v_des = k_position * distance",
    "variant_flights": "flight numbers (1-based) that move waypoint variant_waypoint",
    "variant_waypoint": "index of the waypoint those flights move",
    "variant_shift": "how far they move it (m), e.g. a corner cut closer to an obstacle",
    "variant_note": "a line for the CSV header of those flights",
    "delay": "reaction delay (samples): the pilot acts on the state it saw this long ago",
    "noise": "std of the hand's noise, one per channel of the steering law",
    "noise_memory": "AR(1) coefficient of the hand's noise, in [0, 1): how slowly it varies",
    "stick_step": "stick resolution, one per input (inputs are rounded to it)",
    "stick_range": "comfortable (lower, upper) per input, clipped to input_bounds",
    "goal_margin": "stop only this far inside Goal (m)",
    "stop_speed": "and only slower than this (steering.speed; m/s)",
    "max_duration": "give up after this long (s)",
    "grid": "(state, cells) pairs: one flight from each cell centre of this grid over Init",
    "extra_starts": "more start states (n values each) after the grid's",
}
DROPPED = ("variant_flights", "variant_waypoint", "variant_shift", "variant_note")

YAML_GUIDE = """\
# Scenario '{name}', started from the shipped '{like}' by `python -m pipeline new`.
# Edit this file and pilot.py to your system, then run
#   python -m pipeline demos {name}
# (the synthetic pilot flies the demos and fills in demos:) and
#   python -m pipeline synthesize {name}
# The fields (every one: docs/scenario-file.md, or python -m pipeline schema):
#   states, inputs, dynamics  names in order; one expression per state: d(state)/dt
#   position                  the two states of the position plane (Unsafe and Goal live there)
#   sampling_time             Ts (s): each input is held for Ts
#   input_bounds              [lower, upper] per input
#   unsafe, goal              named polygons to avoid; the polygon to end in (position plane)
#   init                      [lower, upper] per state: where flights start
#   clearance                 d (m): the distance to Unsafe every certified tube keeps
#   operating_region          bounds on what the Jacobian depends on: the feedback's
#                             contraction certificate holds there (the search may narrow it
#                             around what the demos use, never widen it)
#   feedback                  auto: the feedback stage designs it, searching the rate, the LQR
#                             weights and the region; a field you set is kept as given (e.g.
#                             feedback: {{rate: 0.2}}); feedback: {{tune: false}}: no search
#   feedback_period           optional: your controller's period h (s) >= 1e-4, dividing Ts:
#                             the law is certified evaluated every h s and held in between
#                             (default 0: continuous feedback)
#   demos                     keep it last: `demos` rewrites it (or list your CSVs: file, x0)
# ----- below: the '{like}' scenario, renamed -----
"""

PILOT_HEADER = '''\
"""The synthetic pilot of scenario '{name}', started from the shipped '{like}'.

``python -m pipeline demos {name}`` flies one demo from each cell of ``CONFIG.grid`` over
Init, along ``CONFIG.waypoints``, steered by ``steering(scenario)`` (the pilot's model:
``pipeline/demonstrations/pilot.py``).

{steering}"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.demonstrations.pilot import PilotConfig
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario

'''


def new_scenario(name: str, like: str = TEMPLATES[0], where: Path | None = None) -> Path:
    """Write ``where/NAME`` (default ``./scenarios/NAME``) from the shipped scenario ``like``;
    returns the folder. A UserError for a bad name, an unknown template or an existing folder."""
    if not NAME.fullmatch(name):
        raise UserError(
            f"invalid scenario name '{name}'",
            expected="a letter, then letters, digits or '_' (at most 64), e.g. my_robot",
        )
    if like not in TEMPLATES:
        raise UserError(
            f"unknown template --like '{like}'", expected=f"one of: {', '.join(TEMPLATES)}"
        )
    shipped = _shipped_scenarios()
    if name in available_scenarios(shipped):
        raise UserError(
            f"'{name}' is a shipped scenario's name", expected="another name (yours would hide it)"
        )
    root = Path.cwd() / LOCAL_SCENARIOS if where is None else Path(where)
    target = root / name
    if os.path.lexists(target):
        raise UserError(
            f"{target} already exists", expected="a new name, or remove that folder first"
        )
    files = {
        "scenario.yaml": _scenario_text(name, like, shipped / like / "scenario.yaml"),
        PILOT_FILE: _pilot_text(name, like, shipped / like),
    }
    made_root = not root.exists()
    root.mkdir(parents=True, exist_ok=True)
    staging = root / f".{name}.{secrets.token_hex(4)}.tmp"  # mkdir: the umask's mode, not 0700
    staging.mkdir()
    try:
        (staging / "demos").mkdir()
        for file, text in files.items():
            (staging / file).write_text(text)
        os.rename(staging, target)  # atomic: the folder appears whole or not at all
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        if made_root and not any(root.iterdir()):
            root.rmdir()
        raise
    return target


def next_steps(folder: Path, like: str) -> str:
    """What ``new`` prints: what it wrote and the next commands."""
    name = folder.name
    try:
        shown = folder.resolve().relative_to(Path.cwd().resolve())
    except ValueError:
        shown = folder
    return (
        f"wrote {shown}/scenario.yaml and {shown}/{PILOT_FILE} (from the shipped '{like}')\n"
        f"next: edit them to your system, then\n"
        f"  python -m pipeline demos {name}\n"
        f"  python -m pipeline synthesize {name}"
    )


def _scenario_text(name: str, like: str, path: Path) -> str:
    """The shipped YAML renamed, the guide on top, its ``demos:`` block emptied."""
    text = path.read_text()
    text = re.sub(r"^name: .*$", f"name: {name}", text, count=1, flags=re.MULTILINE)
    text = re.sub(
        r"^description: .*$",
        f"description: {name}, from the '{like}' template (describe your system here)",
        text,
        count=1,
        flags=re.MULTILINE,
    )
    text = re.sub(  # the template's explicit design: a new system starts from the search
        r"^feedback:\n(?:[ #].*\n)*",
        "feedback: auto            # designed and tuned by the feedback stage (see the guide)\n",
        text,
        count=1,
        flags=re.MULTILINE,
    )
    demos = re.search(r"^demos:", text, flags=re.MULTILINE)
    assert demos is not None, f"{path} has no demos: block"
    return (
        YAML_GUIDE.format(name=name, like=like)
        + text[: demos.start()]
        + f"demos: []  # filled in by: python -m pipeline demos {name}\n"
    )


def _pilot_text(name: str, like: str, folder: Path) -> str:
    """The template's steering law under a minimal ``CONFIG`` (see the module docstring)."""
    source = (folder / PILOT_FILE).read_text()
    config = load_pilot(load_scenario(folder, check_demos=False)).config
    docstring = source.split('"""')[1]
    steering = docstring[docstring.index("Steering law") :].strip() + "\n"
    law = source[source.index("\n@dataclass") + 1 :]
    required, chosen, defaulted = [], [], []
    for field in dataclasses.fields(PilotConfig):
        value = getattr(config, field.name)
        if field.name in DROPPED:
            value = field.default  # the template's flights are all plain
        if field.name == "grid":  # a first run: at most 2 cells per state
            value = tuple((state, min(cells, 2)) for state, cells in value)
        meaning = PILOT_FIELDS[field.name]
        if field.default is dataclasses.MISSING:
            required.append(f"    # {meaning}\n    {field.name}={value!r},")
        elif value != field.default:
            chosen.append(
                f"    # {meaning}; default {field.default!r}\n    {field.name}={value!r},"
            )
        else:
            defaulted.append(f"#   {field.name} = {field.default!r}: {meaning}")
    return (
        PILOT_HEADER.format(name=name, like=like, steering=steering)
        + "CONFIG = PilotConfig(\n    # ----- must be set -----\n"
        + "\n".join(required)
        + ("\n    # ----- set for this vehicle -----\n" + "\n".join(chosen) if chosen else "")
        + "\n)\n# Defaulted (set any of them above to change it):\n"
        + "\n".join(defaulted)
        + "\n\n\n"
        + law
    )
