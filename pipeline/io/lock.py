"""One run per output folder: an exclusive ``fcntl.flock`` on ``OUT/.lock``.

The lock file holds the holder's pid. The kernel releases the lock when the holder exits, even on
``kill -9``, so a stale lock file never blocks a later run. While held, the folder is an output
root (``pipeline.io.files.output_root``): nothing under it is opened through a link. The lock file
itself is opened without following a link (``O_NOFOLLOW``) and must be a regular file: a link,
FIFO or folder named ``.lock`` is refused in one line, and no file outside the folder is written.
"""

from __future__ import annotations

import errno
import fcntl
import os
import stat
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from pipeline.io.errors import UserError
from pipeline.io.files import PathRefused, kind_of, output_root, printable

LOCK_NAME = ".lock"
WAIT_SECONDS = 5.0
_FLAGS = os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC


def _refused(path: Path, kind: str) -> PathRefused:
    return PathRefused(
        f"is {kind}; the run's lock is a regular file it writes its pid into (no link followed)",
        file=printable(str(path)),
        expected="a regular file or nothing: remove it",
    )


def _open_lock(folder: int, path: Path) -> int:
    """``.lock`` in the folder ``folder`` (a descriptor), created if missing, not followed."""
    try:
        handle = os.open(LOCK_NAME, _FLAGS, 0o644, dir_fd=folder)
    except OSError as error:
        if error.errno in (errno.ELOOP, errno.EISDIR, errno.ENXIO):
            kind = kind_of(os.lstat(LOCK_NAME, dir_fd=folder).st_mode)
            raise _refused(path, kind) from None
        raise
    mode = os.fstat(handle).st_mode
    if not stat.S_ISREG(mode):
        os.close(handle)
        raise _refused(path, kind_of(mode))
    return handle


def _acquire(handle: int, folder: Path, wait: float) -> None:
    """``flock`` the lock file ``handle``, retrying for ``wait`` seconds; then ``UserError``."""
    deadline = time.monotonic() + wait
    while True:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            if time.monotonic() >= deadline:
                holder = os.pread(handle, 64, 0).decode(errors="replace").strip() or "unknown"
                raise UserError(
                    f"another run (pid {holder}) is using this output folder",
                    file=folder,
                    expected="one run per folder: wait for it to end or choose another --out",
                ) from None
            time.sleep(0.2)


@contextmanager
def folder_lock(folder: Path, wait: float | None = None) -> Iterator[Path]:
    """Hold ``folder/.lock`` for the ``with`` block; wait up to ``wait`` seconds (default
    ``WAIT_SECONDS``) for another holder, then raise ``UserError`` naming its pid."""
    wait = WAIT_SECONDS if wait is None else wait
    path = Path(folder) / LOCK_NAME
    with output_root(folder) as root:
        handle = _open_lock(root, path)
        try:
            _acquire(handle, folder, wait)
            os.ftruncate(handle, 0)
            os.pwrite(handle, f"{os.getpid()}\n".encode(), 0)
            yield path
        finally:
            os.close(handle)  # releases the lock
