"""A headless Chromium that prints pages to PDF, driven over the DevTools protocol on a pipe.

Started before the report's figures are drawn, so that its start-up (about a second, most of the
cost of printing) runs on the other core meanwhile; ``print_pdf`` then loads the written page
and prints it (``Page.printToPDF``, the page's own ``@page`` size). The protocol runs over
``--remote-debugging-pipe``: JSON messages ending in a NUL byte, the browser reading fd 3 and
writing fd 4. No network port is opened; the profile is a private temporary folder.
"""

from __future__ import annotations

import base64
import json
import os
import select
import signal
import tempfile
import time
from pathlib import Path
from typing import Any

FLAGS = (
    "--headless",
    "--no-sandbox",  # as root (CI, containers) Chromium refuses to start otherwise
    "--disable-gpu",
    "--no-first-run",
    "--disable-extensions",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--remote-debugging-pipe",
)


class BrowserError(RuntimeError):
    """The browser failed to start, exited, or did not answer in time."""


class Printer:
    """One headless ``browser`` process (``close`` ends it); ``timeout`` s for everything."""

    def __init__(self, browser: Path, profile: Path, timeout: float) -> None:
        self.name = browser.name
        self.deadline = time.monotonic() + timeout
        self._log = tempfile.TemporaryFile()  # the browser's stderr, for the error message
        to_browser, self._to_browser = os.pipe()
        self._from_browser, from_browser = os.pipe()
        null = os.open(os.devnull, os.O_RDWR)
        try:
            self.pid = os.posix_spawn(
                str(browser),
                [str(browser), *FLAGS, f"--user-data-dir={profile}", "about:blank"],
                os.environ,
                file_actions=[
                    (os.POSIX_SPAWN_DUP2, null, 0),
                    (os.POSIX_SPAWN_DUP2, null, 1),
                    (os.POSIX_SPAWN_DUP2, self._log.fileno(), 2),
                    (os.POSIX_SPAWN_DUP2, to_browser, 3),
                    (os.POSIX_SPAWN_DUP2, from_browser, 4),
                ],
                setsid=True,  # its helper processes in their own group, ended with it
            )
        finally:
            for fd in (null, to_browser, from_browser):
                os.close(fd)
        self._buffer = b""
        self._id = 0
        self.code: int | None = None

    def _fail(self, what: str) -> BrowserError:
        self.close()
        self._log.seek(0)
        lines = self._log.read().decode(errors="replace").strip().splitlines()
        exited = f"exited with code {self.code}" if self.code and self.code > 0 else "failed"
        return BrowserError(f"{self.name} {exited} ({what}): {(lines or ['no output'])[-1]}")

    def _message(self) -> dict[str, Any]:
        while b"\0" not in self._buffer:
            left = self.deadline - time.monotonic()
            ready, _, _ = select.select([self._from_browser], [], [], max(left, 0.0))
            if not ready:
                raise self._fail("no answer in time")
            chunk = os.read(self._from_browser, 1 << 20)
            if not chunk:
                raise self._fail("closed the pipe")
            self._buffer += chunk
        message, self._buffer = self._buffer.split(b"\0", 1)
        decoded: dict[str, Any] = json.loads(message)
        return decoded

    def _send(self, method: str, session: str | None = None, **params: Any) -> int:
        self._id += 1
        message: dict[str, Any] = {"id": self._id, "method": method, "params": params}
        if session is not None:
            message["sessionId"] = session
        try:
            os.write(self._to_browser, json.dumps(message).encode() + b"\0")
        except OSError as error:
            raise self._fail(f"{method}: {error}") from None
        return self._id

    def _call(self, method: str, session: str | None = None, **params: Any) -> dict[str, Any]:
        sent = self._send(method, session, **params)
        while True:
            message = self._message()
            if message.get("id") == sent:
                if "error" in message:
                    raise self._fail(f"{method}: {message['error'].get('message')}")
                result: dict[str, Any] = message.get("result", {})
                return result

    def print_pdf(self, page: Path) -> bytes:
        """The file ``page`` loaded and printed: the PDF's bytes."""
        target = self._call("Target.createTarget", url="about:blank")["targetId"]
        session = self._call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        self._call("Page.enable", session)
        self._send("Page.navigate", session, url=page.resolve().as_uri())
        while True:  # wait for the page (its inline SVGs) to have loaded
            message = self._message()
            if message.get("method") == "Page.loadEventFired":
                break
            if "error" in message:
                raise self._fail(f"Page.navigate: {message['error'].get('message')}")
        printed = self._call(
            "Page.printToPDF",
            session,
            printBackground=True,
            preferCSSPageSize=True,
            displayHeaderFooter=False,
        )
        return base64.b64decode(printed["data"])

    def close(self) -> None:
        """End the browser (and its helpers) and release the pipes; safe to call twice."""
        if self.code is None:
            try:
                os.killpg(self.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            _, status = os.waitpid(self.pid, 0)
            self.code = os.waitstatus_to_exitcode(status)
            for fd in (self._to_browser, self._from_browser):
                os.close(fd)
