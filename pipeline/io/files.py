"""Files in and out of the pipeline: nothing inside an output folder follows a link, no read is
unbounded, any valid file name works.

- **No link followed inside an output folder.** While a run holds an output folder
  (``output_root``, entered by ``pipeline.io.lock.folder_lock``), every folder on the way to a
  path under it is opened from the held folder's descriptor with ``O_NOFOLLOW``, and so is the
  file itself: a symbolic link, or a file where a folder belongs, planted there before or during
  the run is refused in one line (``PathRefused``, exit 2), never followed, so no write, delete
  or read leaves the folder. Writes, renames (``replace``) and deletes (``unlink``,
  ``remove_files``) go through those descriptors (``dir_fd``): a folder swapped for a link after
  it was opened cannot redirect them. The held folder itself,
  and every path outside one, may be a link (the user's own choice of path).
- **Bounded reads** (``read_bytes``, ``read_text``, ``open_regular``): only a regular file is
  read (a FIFO, device, socket or folder is refused; opened with ``O_NONBLOCK``, so that a FIFO
  cannot hang the open), of at most a stated number of bytes (checked with ``fstat`` before
  reading, and again while reading), and a symbolic-link loop is one line (``FileRefused``).
  The caps: ``TEXT_MAX_BYTES`` (64 MiB: ``summary.json``, ``inputs.json``, a demo CSV, a cached
  figure), ``ARTIFACT_MAX_BYTES`` (1 GiB: a stage artifact's ``.json`` or ``.npz``, a typeset
  PDF); elsewhere a scenario file (1 MB, ``pipeline.model.safe_yaml``) and ``controller.json``
  (256 MiB, ``pipeline.controller.MAX_BYTES``).
- **Any valid name** (``printable``): a name with bytes that are not UTF-8 is held by Python as
  lone surrogates (``os.fsdecode``); text files are written with those bytes restored
  (``surrogateescape``, as ``os.fsencode`` does), and text meant to be read shows them as
  ``\\xNN``.
"""

from __future__ import annotations

import errno
import os
import re
import stat
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from pipeline.io.errors import UserError

MiB = 2**20
TEXT_MAX_BYTES = 64 * MiB  # summary.json, inputs.json, a demo CSV, a cached figure
ARTIFACT_MAX_BYTES = 1024 * MiB  # a stage artifact's .json or .npz (expanded: 4x), a PDF

_FOLDER = os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC
_READ = os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC

# the output folders held by this process: (absolute path, descriptor), innermost last
_ROOTS: list[tuple[str, int]] = []
_ROOTS_LOCK = threading.Lock()


class PathRefused(UserError):
    """A path inside an output folder is not what the run writes there (a link, a file where a
    folder belongs, a folder where a file belongs): refused in one line, exit 2."""


class FileRefused(ValueError):
    """A file that cannot be read as one: not a regular file, larger than its cap, a link
    inside an output folder, or a symbolic-link loop (one line naming the file)."""

    def __init__(self, path: str | Path, reason: str) -> None:
        self.path, self.reason = Path(path), reason
        super().__init__(f"{printable(str(path))}: {reason}")


class FileTooLarge(FileRefused):
    """A file larger than the cap of what reads it."""


_SURROGATE = re.compile("[\ud800-\udfff]")


def _escaped(match: re.Match[str]) -> str:
    code = ord(match.group())
    return f"\\x{code - 0xDC00:02x}" if 0xDC80 <= code <= 0xDCFF else f"\\u{code:04x}"


def printable(text: str) -> str:
    """``text`` with each byte of a file name that is not UTF-8 (a lone surrogate from
    ``os.fsdecode``) written as ``\\xNN`` (any other lone surrogate as ``\\uNNNN``): valid
    UTF-8 for a page or a terminal."""
    return _SURROGATE.sub(_escaped, text)


def kind_of(mode: int) -> str:
    """What an ``st_mode`` is, in words ("a FIFO", "a folder", ...)."""
    kinds = {
        stat.S_IFREG: "a regular file",
        stat.S_IFDIR: "a folder",
        stat.S_IFLNK: "a symbolic link",
        stat.S_IFIFO: "a FIFO (named pipe)",
        stat.S_IFCHR: "a character device",
        stat.S_IFBLK: "a block device",
        stat.S_IFSOCK: "a socket",
    }
    return kinds.get(stat.S_IFMT(mode), "not a regular file")


@contextmanager
def output_root(folder: Path) -> Iterator[int]:
    """Hold ``folder`` for the ``with`` block (yields its descriptor): every path under it is
    opened from this descriptor without following links (see the module docstring). The
    folder itself is opened following a link: the user named it."""
    fd = os.open(folder, _FOLDER)
    entry = (os.path.abspath(folder), fd)
    with _ROOTS_LOCK:
        _ROOTS.append(entry)
    try:
        yield fd
    finally:
        with _ROOTS_LOCK:
            _ROOTS.remove(entry)
        os.close(fd)


def _root_of(path: str) -> tuple[str, int] | None:
    """The innermost held output folder that ``path`` (absolute) is in, or None."""
    with _ROOTS_LOCK:
        found = [
            (root, fd)
            for root, fd in _ROOTS
            if path == root or path.startswith(root.rstrip(os.sep) + os.sep)
        ]
    return max(found, key=lambda entry: len(entry[0])) if found else None


def open_folder(folder: Path | str, create: bool = False) -> int:
    """A descriptor of ``folder`` (``create``: made where missing), every component under a
    held output folder opened without following links; the caller closes it.

    Raises ``PathRefused`` for a link or a non-folder inside a held output folder, and
    ``FileNotFoundError`` for a missing folder (without ``create``)."""
    path = os.path.abspath(folder)
    root = _root_of(path)
    if root is None:  # not in an output folder: the user's path, links followed
        if create:
            os.makedirs(path, exist_ok=True)
        return os.open(path, _FOLDER)
    base, current = os.dup(root[1]), root[0]
    for part in Path(os.path.relpath(path, root[0])).parts:
        if part != ".":
            current = os.path.join(current, part)
            base = _open_below(base, part, create, current)  # closes the folder above
    return base


def _open_below(base: int, part: str, create: bool, path: str) -> int:
    """Folder ``part`` (at ``path``) under descriptor ``base``, which is closed here; refused
    if it is a link or not a folder."""
    try:
        try:
            return os.open(part, _FOLDER | os.O_NOFOLLOW, dir_fd=base)
        except FileNotFoundError:
            if not create:
                raise
            try:
                os.mkdir(part, 0o777, dir_fd=base)
            except FileExistsError:
                pass  # made meanwhile: opened (and checked) below
            return os.open(part, _FOLDER | os.O_NOFOLLOW, dir_fd=base)
    except OSError as error:
        if error.errno not in (errno.ENOTDIR, errno.ELOOP):
            raise
        raise PathRefused(
            f"is {kind_of(os.lstat(part, dir_fd=base).st_mode)} inside the output folder, where "
            "the run keeps a folder (it follows no link there)",
            file=printable(path),
            expected="a folder: remove it, the next run makes it again",
        ) from None
    finally:
        os.close(base)


def _open_in_folder(path: Path | str, flags: int, mode: int = 0o644) -> tuple[int, bool]:
    """``os.open(path, flags)`` through its folder's descriptor (``open_folder``), with
    ``O_NOFOLLOW`` inside a held output folder; returns the descriptor and whether it was."""
    absolute = os.path.abspath(path)
    inside = _root_of(absolute) is not None
    folder = open_folder(os.path.dirname(absolute))
    try:
        nofollow = os.O_NOFOLLOW if inside else 0
        return os.open(os.path.basename(absolute), flags | nofollow, mode, dir_fd=folder), inside
    finally:
        os.close(folder)


def open_regular(path: Path | str) -> int:
    """A descriptor open for reading on the regular file ``path`` (the caller closes it);
    ``FileRefused`` for anything else (see the module docstring), ``OSError`` (e.g.
    ``FileNotFoundError``) when it cannot be opened."""
    try:
        fd, inside = _open_in_folder(path, _READ)
    except OSError as error:
        if error.errno != errno.ELOOP:
            raise
        if _root_of(os.path.abspath(path)) is not None:
            reason = "is a symbolic link inside the output folder (not followed)"
            raise FileRefused(path, reason) from None
        raise FileRefused(path, "is a symbolic-link loop") from None
    mode = os.fstat(fd).st_mode
    if not stat.S_ISREG(mode):
        os.close(fd)
        raise FileRefused(path, f"is {kind_of(mode)}; expected a regular file")
    return fd


def _size(limit: int) -> str:
    return f"{limit // MiB} MiB" if limit >= MiB else f"{limit:,} bytes"


def read_bytes(path: Path | str, limit: int) -> bytes:
    """The bytes of the regular file ``path``, at most ``limit`` of them (more is
    ``FileRefused``, said before reading when ``fstat`` shows it)."""
    fd = open_regular(path)
    with os.fdopen(fd, "rb") as stream:
        size = os.fstat(fd).st_size
        data = stream.read(limit + 1) if size <= limit else b""
    if size > limit or len(data) > limit:
        found = f"{max(size, len(data)):,} bytes" if size > limit else "still growing"
        raise FileTooLarge(path, f"is {found}; expected at most {_size(limit)}")
    return data


def read_text(path: Path | str, limit: int) -> str:
    """``read_bytes`` decoded as UTF-8 (``FileRefused`` if it is not)."""
    data = read_bytes(path, limit)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as error:
        raise FileRefused(path, f"is not UTF-8 text (byte {error.start})") from None


def is_regular(path: Path | str) -> bool:
    """Is ``path`` a regular file (not followed if a link inside an output folder)?"""
    try:
        os.close(open_regular(path))
    except (OSError, FileRefused):
        return False
    return True


def unlink(path: Path | str) -> None:
    """Delete ``path`` (a link itself, never its target) through its folder's descriptor;
    nothing if it is missing."""
    absolute = os.path.abspath(path)
    try:
        folder = open_folder(os.path.dirname(absolute))
    except FileNotFoundError:
        return
    try:
        os.unlink(os.path.basename(absolute), dir_fd=folder)
    except FileNotFoundError:
        pass
    finally:
        os.close(folder)


def replace(source: Path | str, target: Path | str) -> None:
    """``os.replace(source, target)`` through the descriptors of both folders
    (``open_folder``): inside a held output folder no link on either way is followed, so a
    folder swapped for a link cannot redirect the move (``PathRefused``)."""
    source, target = os.path.abspath(source), os.path.abspath(target)
    origin = open_folder(os.path.dirname(source))
    try:
        destination = open_folder(os.path.dirname(target))
        try:
            os.replace(
                os.path.basename(source),
                os.path.basename(target),
                src_dir_fd=origin,
                dst_dir_fd=destination,
            )
        finally:
            os.close(destination)
    finally:
        os.close(origin)


def remove_files(folder: Path | str, remove: Callable[[str], bool]) -> list[str]:
    """Delete the regular files of ``folder`` whose name ``remove`` accepts (links and folders
    are left alone), through one descriptor; returns their names."""
    try:
        fd = open_folder(folder)
    except FileNotFoundError:
        return []
    try:
        with os.scandir(fd) as entries:
            names = [e.name for e in entries if e.is_file(follow_symlinks=False) and remove(e.name)]
        for name in names:
            try:
                os.unlink(name, dir_fd=fd)
            except FileNotFoundError:
                pass
        return names
    finally:
        os.close(fd)
