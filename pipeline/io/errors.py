"""User-facing errors: a mistake in the input is reported in one line and exits with code 2."""

from __future__ import annotations

from pathlib import Path


class UserError(Exception):
    """A mistake in the user's input (scenario, demo, controller file, command line).

    The CLI prints ``str(error)`` without a traceback and exits with ``exit_code``.
    """

    exit_code = 2

    def __init__(
        self,
        message: str,
        *,
        file: str | Path | None = None,
        field: str | None = None,
        found: object = None,
        expected: str | None = None,
    ) -> None:
        parts = []
        if file is not None:
            parts.append(str(file))
        if field is not None:
            parts.append(field)
        text = message
        if found is not None:
            text += f"; found {found!r}"
        if expected is not None:
            text += f"; expected {expected}"
        self.file = None if file is None else str(file)
        self.field = field
        super().__init__(": ".join([*parts, text]))


class ScenarioError(UserError):
    """The scenario file, or a demo it lists, is invalid."""
