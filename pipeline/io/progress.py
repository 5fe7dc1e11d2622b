"""Progress bars for long stages (tqdm on stderr; silent with ``-q`` or when not a terminal)."""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from tqdm import tqdm


@contextmanager
def progress_bar(total: int, unit: str, quiet: bool = False) -> Iterator[Callable[[int], None]]:
    """Yield ``advance(count)``; draws a bar of ``total`` ``unit`` unless ``quiet``."""
    if quiet or not sys.stderr.isatty():
        yield lambda _count: None
        return
    with tqdm(
        total=total, unit=f" {unit}", file=sys.stderr, leave=False, dynamic_ncols=True
    ) as bar:
        yield bar.update
