"""Run stages with cached artifacts: a stage whose inputs did not change is not recomputed.

``StageRunner.run(STAGE, inputs)`` runs a declared stage (``pipeline.results.stage.Stage``).
Its result is stored under ``OUT/artifacts/<stage>.json`` (+ ``.npz``) with a key derived from
the declaration (``stage_key``: ``pipeline.runtime.codekey.code_key`` of its code and every field
of its inputs, by the artifact store's exact encoder) and a content hash. An artifact that is
corrupt, edited, or names a type outside ``pipeline.runtime.registry.RESULT_TYPES`` is refused
in one line and recomputed. A run
interrupted at any point leaves the last good artifacts in place (every write is atomic) and the
next run resumes from them.

Each stage says one line on the ``pipeline`` logger when it ends: its wall time (or that it was
reused) and what it found.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from pipeline.io.artifacts import ArtifactError, Stored, inputs_key, read_stored, save_result
from pipeline.model.scenario import Scenario
from pipeline.results.stage import FileInput, Stage, StageInputs
from pipeline.runtime.codekey import code_key
from pipeline.runtime.registry import RESULT_TYPES
from pipeline.runtime.run_inputs import scenario_slice

T = TypeVar("T")
log = logging.getLogger(__name__)


def warn(text: str) -> None:
    """One warning line (shown even with ``-q``)."""
    log.warning(text)


def read_checked(
    stem: Path, warn: Callable[[str], None] = warn, registry: Mapping[str, type] = RESULT_TYPES
) -> Stored | None:
    """The stored artifact ``stem``, or ``None`` when it is missing or refused (said in one
    line through ``warn``)."""
    try:
        return read_stored(stem, registry)
    except ArtifactError as error:
        warn(f"[{stem.name}] artifact refused, recomputing: {error}")
        return None


def key_data(inputs: StageInputs) -> dict[str, Any]:
    """Field name -> what the key encodes of it: a ``Scenario`` by the fields the inputs type
    declares (``scenario_fields``), a ``FileInput`` by its content hash, anything else as it is
    (the artifact store's exact encoder refuses what it cannot encode exactly)."""
    data: dict[str, Any] = {}
    for field_ in dataclasses.fields(inputs):
        value = getattr(inputs, field_.name)
        if isinstance(value, Scenario):
            value = scenario_slice(value, type(inputs).scenario_fields)
        elif isinstance(value, FileInput):
            value = {"sha256": value.sha256}
        data[field_.name] = value
    return data


def stage_key(stage: Stage[Any, Any], inputs: StageInputs) -> str:
    """The cache key of ``stage`` on ``inputs``: its code (``stage.modules`` and what they
    import) and ``key_data(inputs)``."""
    if type(inputs) is not stage.inputs:
        raise TypeError(
            f"stage {stage.name}: inputs of type {type(inputs).__qualname__}; expected "
            f"{stage.inputs.__qualname__}"
        )
    return inputs_key(code_key(*stage.modules), key_data(inputs))


@dataclass(frozen=True, kw_only=True)
class StageRecord:
    name: str
    key: str
    sha256: str
    seconds: float
    cached: bool


@dataclass
class StageRunner:
    """Runs named stages, reusing stored results whose input key matches (unless ``force``).

    ``current`` names the stage being computed (for the summary of a failed run).
    """

    out: Path
    force: bool = False
    records: dict[str, StageRecord] = field(default_factory=dict)
    current: str = "load"

    def run(
        self,
        stage: Stage[Any, T],
        inputs: StageInputs,
        *,
        name: str | None = None,
        rerun: bool = False,
        describe: Callable[[T], str] | None = None,
        finish: Callable[[T], T] | None = None,
        **context: Any,
    ) -> T:
        """``stage(inputs, **context)``, stored as ``name`` (default ``stage.name``) under
        ``stage_key(stage, inputs)``, or the stored result when that key matches (``rerun``
        forces). ``context`` (executor, progress bar) is not keyed: it never changes a result.
        ``finish`` is applied to a computed result before it is stored (the orchestrator names
        a staged file by where it is published).
        """

        def compute() -> T:
            result = stage(inputs, **context)
            return result if finish is None else finish(result)

        return self.run_keyed(
            name or stage.name, stage_key(stage, inputs), compute, rerun, describe
        )

    def run_keyed(
        self,
        name: str,
        key: str,
        compute: Callable[[], T],
        rerun: bool = False,
        describe: Callable[[T], str] | None = None,
    ) -> T:
        """``compute()``'s result, or the stored one when its key matches (``rerun`` forces).

        Logs one line: ``[name] 1.2 s: what describe(result) says`` (or ``reused``)."""
        stem = self.out / "artifacts" / name
        self.current = name
        if not (self.force or rerun):
            stored = read_checked(stem)
            if stored is not None and stored.key == key:
                self.records[name] = StageRecord(
                    name=name, key=key, sha256=stored.sha256, seconds=0.0, cached=True
                )
                _say(name, "reused (inputs unchanged)", stored.result, describe)
                return stored.result
        start = time.perf_counter()
        result = compute()
        seconds = time.perf_counter() - start
        sha256 = save_result(stem, key, result)
        self.records[name] = StageRecord(
            name=name, key=key, sha256=sha256, seconds=seconds, cached=False
        )
        _say(name, f"{seconds:.1f} s", result, describe)
        return result

    def digest(self, name: str) -> str:
        """The content hash of stage ``name``'s result in this run (a key for what reads it)."""
        return self.records[name].sha256

    def timings(self) -> dict[str, float]:
        """Wall time per stage in this run (0 for reused results)."""
        return {record.name: record.seconds for record in self.records.values()}


def _say(name: str, how: str, result: T, describe: Callable[[T], str] | None) -> None:
    what = "" if describe is None else describe(result)
    log.info(f"[{name}] {how}" + (f": {what}" if what else ""))
