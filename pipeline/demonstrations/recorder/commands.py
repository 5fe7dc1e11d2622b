"""``python -m pipeline record SCENARIO [--x0 ...]`` and ``... replay SCENARIO DEMO``.

Nothing heavy is imported until a command runs (the CLI builds its parser for every command), and
pygame only when a window is opened, so the rest of the pipeline runs without it.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.io.errors import UserError

if TYPE_CHECKING:
    from pipeline.model.scenario import Scenario


def add_commands(commands: Any) -> None:
    """Add the ``record`` and ``replay`` subcommands to the CLI's subparsers."""
    record = commands.add_parser(
        "record", help="fly a scenario with a joystick or the keyboard; save valid flights as demos"
    )
    record.add_argument("scenario", help="scenario name (scenarios/NAME) or path to its YAML")
    record.add_argument(
        "--x0",
        type=float,
        nargs="+",
        default=None,
        metavar="VALUE",
        help="start state, one value per state, inside Init (default: the largest part of Init"
        " the last synthesize run left uncovered, else its middle; or click inside Init)",
    )
    replay = commands.add_parser("replay", help="show a demonstration flown again from its CSV")
    replay.add_argument("scenario")
    replay.add_argument("demo", help="demo name (recorded_01) or file (demos/recorded_01.csv)")


def _pygame() -> None:
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    try:
        import pygame  # noqa: F401
    except ImportError:
        raise UserError(
            "the recorder needs pygame, which is not installed",
            expected="pygame: .venv/bin/pip install -e '.[record]'",
        ) from None


def find_demo(scenario: Scenario, name: str) -> int:
    """Index of the demo called ``name`` (file stem, or file path relative to the scenario)."""
    for index, demo in enumerate(scenario.demos):
        relative = demo.file.relative_to(scenario.path.parent).as_posix()
        if name in (demo.name, relative, demo.file.name, str(demo.file)):
            return index
    raise UserError(
        f"no demo '{name}' in scenario '{scenario.name}'",
        expected=f"one of {[demo.name for demo in scenario.demos]}",
    )


def run(args: argparse.Namespace, registry: Mapping[str, type] | None = None) -> int:
    """Run ``record`` or ``replay``; returns the exit code. ``registry``: the stage cache's result
    types, to read the last run's coverage (where to start the next flight)."""
    _pygame()
    from pipeline.demonstrations.recorder import app
    from pipeline.demonstrations.recorder.config import load_recorder_config
    from pipeline.demonstrations.recorder.flight import check_start, suggested_start
    from pipeline.model.scenario import load_scenario

    if args.command == "record":
        scenario = load_scenario(args.scenario, check_demos=True)
        config = load_recorder_config(scenario)
        if args.x0 is not None:
            x0, reason = check_start(scenario, args.x0), "--x0"
        else:
            x0, reason = suggested_start(scenario, registry=registry)
        app.start_pygame()
        window = app.RecorderApp(scenario, config, x0, reason)
        app.run_loop(window)
        for path in window.saved:
            print(f"saved {Path(path).relative_to(scenario.path.parent).as_posix()}")
        if window.saved:
            print(f"next: make synthesize SCENARIO={scenario.name}")
        return 0
    if args.command == "replay":
        scenario = load_scenario(args.scenario, check_demos=False)
        demo = scenario.demos[find_demo(scenario, args.demo)]
        app.start_pygame()
        app.run_loop(app.ReplayApp(scenario, load_recorder_config(scenario), demo))
        return 0
    raise AssertionError(f"unhandled command {args.command!r}")
