"""Atomic artifact writing: write to a temporary file beside the target, then rename.

A run that fails or is interrupted never leaves a half-written file where a good one was.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any


def _atomic(path: Path, write: Callable[[Path], None]) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(handle)
    try:
        write(Path(temporary))
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically."""
    _atomic(path, lambda temporary: temporary.write_text(text))


def atomic_write_json(path: Path, data: Any) -> None:
    """Write ``data`` as indented JSON to ``path`` atomically."""
    atomic_write_text(path, json.dumps(data, indent=2, sort_keys=False) + "\n")


def atomic_save(path: Path, save: Callable[[Path], None], suffix: str = "") -> None:
    """Call ``save(temporary_path)`` (e.g. ``fig.savefig``) and rename the result to ``path``.

    ``suffix`` is appended to the temporary name for writers that infer the format from it.
    """

    def write(temporary: Path) -> None:
        with_suffix = temporary.with_name(temporary.name + suffix)
        save(with_suffix)
        if with_suffix != temporary:
            os.replace(with_suffix, temporary)

    _atomic(path, write)


def file_hash(path: Path) -> str:
    """SHA-256 of a file's bytes, hex."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()
