"""One run per output folder: an exclusive ``fcntl.flock`` on ``OUT/.lock``.

The lock file holds the holder's pid. The kernel releases the lock when the holder exits, even on
``kill -9``, so a stale lock file never blocks a later run.
"""

from __future__ import annotations

import fcntl
import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from pipeline.io.errors import UserError

LOCK_NAME = ".lock"
WAIT_SECONDS = 5.0


@contextmanager
def folder_lock(folder: Path, wait: float | None = None) -> Iterator[Path]:
    """Hold ``folder/.lock`` for the ``with`` block; wait up to ``wait`` seconds (default
    ``WAIT_SECONDS``) for another holder, then raise ``UserError`` naming its pid."""
    wait = WAIT_SECONDS if wait is None else wait
    path = Path(folder) / LOCK_NAME
    handle = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        deadline = time.monotonic() + wait
        while True:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    holder = Path(path).read_text().strip() or "unknown"
                    raise UserError(
                        f"another run (pid {holder}) is using this output folder",
                        file=folder,
                        expected="one run per folder: wait for it to end or choose another --out",
                    ) from None
                time.sleep(0.2)
        os.ftruncate(handle, 0)
        os.write(handle, f"{os.getpid()}\n".encode())
        yield path
    finally:
        os.close(handle)  # releases the lock
