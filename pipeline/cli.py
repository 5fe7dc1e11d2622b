"""Command line: ``python -m pipeline COMMAND ...``.

User mistakes (``UserError``) print one line on stderr and exit with code 2, no traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from pipeline.errors import UserError

REPORTS_ROOT = Path(__file__).resolve().parents[1] / "reports"


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m pipeline", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)

    synthesize = commands.add_parser("synthesize", help="run the synthesis pipeline on a scenario")
    synthesize.add_argument("scenario", help="scenario name (scenarios/NAME) or path to its YAML")
    synthesize.add_argument("--out", type=Path, default=None, help="output folder (reports/NAME)")
    verbosity = synthesize.add_mutually_exclusive_group()
    verbosity.add_argument("-v", "--verbose", action="store_true", help="print iteration logs")
    verbosity.add_argument("-q", "--quiet", action="store_true", help="print only the verdict")

    demos = commands.add_parser("demos", help="regenerate a scenario's synthetic demonstrations")
    demos.add_argument("scenario")

    commands.add_parser("schema", help="print the scenario file's JSON Schema")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        return _run(args)
    except UserError as error:
        print(f"error: {error}", file=sys.stderr)
        return error.exit_code
    except KeyboardInterrupt:
        print("interrupted: finished artifacts are kept; re-run to resume", file=sys.stderr)
        return 130


def _run(args: argparse.Namespace) -> int:
    if args.command == "synthesize":
        from pipeline.orchestrator import synthesize

        return synthesize(args.scenario, out=args.out, verbose=args.verbose, quiet=args.quiet)
    if args.command == "demos":
        from pipeline.pilot import regenerate_demos

        regenerate_demos(args.scenario)
        return 0
    if args.command == "schema":
        from pipeline.schema import json_schema

        print(json.dumps(json_schema(), indent=2))
        return 0
    raise AssertionError(f"unhandled command {args.command!r}")
