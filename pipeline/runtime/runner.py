"""Run stages with cached artifacts: a stage whose inputs did not change is not recomputed.

Each stage's result is stored under ``OUT/artifacts/<stage>.json`` (+ ``.npz``) with a content
hash of its inputs (``pipeline.io.artifacts.inputs_key``). A run interrupted at any point leaves
the last good artifacts in place (every write is atomic) and the next run resumes from them.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from pipeline.io.artifacts import load_result, save_result

T = TypeVar("T")


@dataclass
class StageRecord:
    name: str
    key: str
    seconds: float
    cached: bool


@dataclass
class StageRunner:
    """Runs named stages, reusing stored results whose input key matches (unless ``force``)."""

    out: Path
    force: bool = False
    log: Callable[[str], None] = print
    records: list[StageRecord] = field(default_factory=list)

    def run(self, name: str, key: str, compute: Callable[[], T], rerun: bool = False) -> T:
        """``compute()``'s result, or the stored one when its key matches (``rerun`` forces)."""
        stem = self.out / "artifacts" / name
        if not (self.force or rerun):
            stored: Any = load_result(stem, key)
            if stored is not None:
                self.records.append(StageRecord(name, key, 0.0, True))
                self.log(f"[{name}] unchanged inputs: reusing {stem.name}.json")
                return stored  # type: ignore[no-any-return]
        self.log(f"[{name}] running")
        start = time.perf_counter()
        result = compute()
        seconds = time.perf_counter() - start
        save_result(stem, key, result)
        self.records.append(StageRecord(name, key, seconds, False))
        self.log(f"[{name}] done in {seconds:.1f} s")
        return result

    def timings(self) -> dict[str, float]:
        """Wall time per stage in this run (0 for reused results)."""
        return {record.name: record.seconds for record in self.records}
