"""Command line: ``python -m pipeline COMMAND ...``, a thin layer over the Python API
(``pipeline.synthesize``): it shows the ``pipeline`` logger's lines and prints the result.

User mistakes (``UserError``) print one line on stderr and exit with code 2, no traceback.
Ctrl-C prints one line and exits with code 130 (a second Ctrl-C while the run stops is ignored).
Outputs go to ``./reports/NAME`` under the current directory unless ``--out DIR``.
"""

from __future__ import annotations

import argparse
import errno
import json
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from types import FrameType
from typing import NoReturn

from pipeline.controller import ControllerFormatError
from pipeline.io.errors import UserError
from pipeline.io.files import printable
from pipeline.runtime.options import RunOptions, add_arguments, from_arguments

SCENARIO_HELP = (
    "scenario name (./scenarios/NAME, else the shipped one) or the path of its folder or YAML"
)


class _Parser(argparse.ArgumentParser):
    """A wrong command line is one line too (``error: argument --seed: found '-1'; expected
    ...``), with where to find the usage instead of printing it; exit code 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"error: {message} (usage: {self.prog} --help)\n")


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="python -m pipeline", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)

    synthesize = commands.add_parser("synthesize", help="run the synthesis pipeline on a scenario")
    synthesize.add_argument("scenario", help=SCENARIO_HELP)
    synthesize.add_argument(
        "--out", type=Path, default=None, help="output folder (default: ./reports/NAME)"
    )
    add_arguments(synthesize, RunOptions)

    demos = commands.add_parser("demos", help="regenerate a scenario's synthetic demonstrations")
    demos.add_argument("scenario")

    new = commands.add_parser("new", help="start ./scenarios/NAME from a shipped scenario")
    new.add_argument("name", help="the new scenario's name (a letter, then letters, digits, _)")
    new.add_argument(
        "--like", default="double_integrator", help="the shipped scenario to start from"
    )

    report = commands.add_parser(
        "report", help="rebuild report.html and report.pdf from a finished run's artifacts"
    )
    report.add_argument("scenario", help=SCENARIO_HELP)
    report.add_argument(
        "--from",
        dest="source",
        type=Path,
        default=None,
        help="the finished run's folder to read (default: ./reports/NAME)",
    )
    report.add_argument(
        "--out", type=Path, default=None, help="where to write the reports (default: --from)"
    )

    commands.add_parser("schema", help="print the scenario file's JSON Schema")

    from pipeline.demonstrations.recorder.commands import add_commands

    add_commands(commands)  # record, replay
    return parser


WRITE_FAILURES = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES)
INTERRUPTED = "interrupted: finished artifacts are kept; re-run to resume"
# Seconds the run has to unwind after Ctrl-C (workers ended, lock released: under 6 s) before the
# process ends itself: a KeyboardInterrupt raised inside a library's critical section can leave
# a lock held that the unwinding or the interpreter's exit then waits on forever
INTERRUPT_GRACE = 30.0
_said_interrupted = threading.Event()


def _interrupted(signum: int, frame: FrameType | None) -> None:
    """The first SIGINT: ignore the next ones, then stop the command (``KeyboardInterrupt``);
    if it has not ended ``INTERRUPT_GRACE`` seconds later, end the process (``_give_up``)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    watchdog = threading.Timer(INTERRUPT_GRACE, _give_up)
    watchdog.daemon = True
    watchdog.start()
    raise KeyboardInterrupt


def _give_up() -> None:
    """The interrupted run did not end in time: say so once and exit 130 at once (the kernel
    releases the folder's lock with the process; nothing half-written is published)."""
    if not _said_interrupted.is_set():
        print(INTERRUPTED, file=sys.stderr, flush=True)
    os._exit(130)


@contextmanager
def _one_interrupt() -> Iterator[None]:
    """While open, only the first Ctrl-C acts: a second one, while the first unwinds the run
    (workers ended, the folder's lock released), could cut that short or, once the command has
    returned, kill the interpreter while it joins its threads (exit -2 instead of 130). After
    an interrupt SIGINT stays ignored (the process is ending), else the old handler is back."""
    previous = signal.getsignal(signal.SIGINT)
    if previous is not signal.default_int_handler or (
        threading.current_thread() is not threading.main_thread()
    ):  # Ctrl-C already handled otherwise (or ignored), or not ours to handle
        yield
        return
    signal.signal(signal.SIGINT, _interrupted)
    try:
        yield
    finally:
        if signal.getsignal(signal.SIGINT) is _interrupted:
            signal.signal(signal.SIGINT, previous)


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    with _one_interrupt():
        return _main(args)


def _main(args: argparse.Namespace) -> int:
    try:
        return _run(args)
    except (UserError, ControllerFormatError) as error:
        print(f"error: {error}", file=sys.stderr)
        return error.exit_code
    except BrokenPipeError:
        return 0
    except OSError as error:  # the machine, not the input: a full disk, a folder gone read-only
        if error.errno not in WRITE_FAILURES:
            raise
        where = f" {error.filename}" if error.filename else ""
        print(
            f"error: cannot write{where}: {error.strerror}; free space or choose another --out "
            "(finished artifacts are kept; re-run to resume)",
            file=sys.stderr,
        )
        return 2
    except KeyboardInterrupt:
        print(INTERRUPTED, file=sys.stderr, flush=True)
        _said_interrupted.set()
        return 130


def _run(args: argparse.Namespace) -> int:
    if args.command == "synthesize":
        from pipeline.model.scenario_file import check_scenario_file

        check_scenario_file(args.scenario)  # syntax and fields in < 1 s, before the numerics
        from pipeline.runtime.api import synthesize
        from pipeline.runtime.terminal import format_done, format_result, show_progress, units_of

        options = from_arguments(RunOptions, args)
        computed = {  # every option but how much to print
            name: getattr(options, name)
            for name in RunOptions.__dataclass_fields__
            if name not in ("verbose", "quiet")
        }
        started = time.monotonic()
        with show_progress(verbose=options.verbose, quiet=options.quiet):
            result = synthesize(args.scenario, out=args.out, **computed)
        scenario = None if options.quiet else units_of(args.scenario)
        print(
            printable(
                format_result(
                    result, scenario=scenario, quiet=options.quiet, verbose=options.verbose
                )
            )
        )
        if not options.quiet:
            print(f"\n{format_done(result, time.monotonic() - started)}")
        return result.exit_code
    if args.command == "demos":
        from pipeline.demonstrations.pilot import describe_demos, regenerate_demos
        from pipeline.model.scenario import load_scenario, resolve_scenario_path

        path = resolve_scenario_path(args.scenario)
        demos = regenerate_demos(path)
        print(printable(describe_demos(demos, load_scenario(path, check_demos=False).Ts, path)))
        return 0
    if args.command == "new":
        from pipeline.runtime.scaffold import new_scenario, next_steps

        print(printable(next_steps(new_scenario(args.name, like=args.like), args.like)))
        return 0
    if args.command == "report":
        from pipeline.runtime.orchestrator import rebuild_reports

        written = rebuild_reports(args.scenario, source=args.source, out=args.out)
        files = [written.html, *([written.pdf] if written.pdf is not None else [])]
        print(printable(f"{written.message}:" + "".join(f"\n  {path}" for path in files)))
        return 0
    if args.command == "schema":
        from pipeline.model.schema import json_schema

        print(json.dumps(json_schema(), indent=2))
        return 0
    if args.command in ("record", "replay"):
        from pipeline.demonstrations.recorder.commands import run
        from pipeline.runtime.registry import RESULT_TYPES

        return run(args, RESULT_TYPES)
    raise AssertionError(f"unhandled command {args.command!r}")
