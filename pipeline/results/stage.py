"""A stage declared: its name, its function, the frozen type of what it reads (``Inputs``) and
the type of what it returns (``Result``).

Each stage module (``stages/*.py``) declares one or more module-level ``Stage`` values beside
its function, e.g.::

    @dataclass(frozen=True, kw_only=True)
    class RadiusInputs(StageInputs):
        scenario_fields: ClassVar = ("dynamics", "goal", ...)  # what it reads of the scenario
        scenario: Scenario
        tube: Tube
        trajectories: tuple[Trajectory, ...]

    RADIUS = Stage("radius", robustness_radii, RadiusInputs, RadiusResult)

The runner (``pipeline.runtime.runner.StageRunner.run(STAGE, inputs)``) derives the cache key
from the code of the function's module (and ``code``) and every field of ``inputs``, encoded by
the artifact store's exact encoder: a ``Scenario`` field by the ``scenario_fields`` it declares
only, a ``FileInput`` by its content hash only. So the key can name nothing the stage does not
read, and what it reads is in the key (``tests/test_stage_conformance.py`` checks both).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Generic, Protocol, TypeVar

I = TypeVar("I", bound="StageInputs")  # noqa: E741
R = TypeVar("R")


@dataclass(frozen=True, kw_only=True)
class StageInputs:
    """Base of a stage's inputs: frozen, keyword-only, every field keyed.

    ``scenario_fields`` names the fields of the ``Scenario`` (field ``scenario``) that the stage
    reads, directly or through a property or method (``n``, ``state_names``: ``dynamics``;
    ``in_goal``: ``goal``, ``goal_bounds``, ``position_index``, ``dynamics``); only those are
    keyed."""

    scenario_fields: ClassVar[tuple[str, ...]] = ()


@dataclass(frozen=True, kw_only=True)
class FileInput:
    """A file a stage reads (``controller.json``): keyed by its content hash ``sha256`` only, so
    the same bytes in another folder (the staging folder, the published one) give one key."""

    path: Path
    sha256: str


@dataclass(frozen=True)
class Stage(Generic[I, R]):
    """A declared stage.

    Attributes:
      name: its artifact's name (a run may store it under another: ``radius_demos``).
      function: ``function(inputs, **context) -> Result``; ``context`` is where it runs
        (executor, progress bar, an earlier round's funnels to reuse): never part of the key,
        never a change of the result.
      inputs: the frozen ``StageInputs`` type of what it reads.
      result: the type it returns (or, for a stage returning a tuple, of each element):
        registered for the artifact store (``pipeline.runtime.registry``).
      code: project modules besides the function's own whose source the key covers (the
        modules they import, transitively, are covered too: ``pipeline.runtime.codekey``).
    """

    name: str
    function: Callable[..., R]
    inputs: type[I]
    result: type
    code: tuple[str, ...] = ()

    def __call__(self, inputs: I, **context: Any) -> R:
        if type(inputs) is not self.inputs:
            raise TypeError(
                f"stage {self.name}: inputs of type {type(inputs).__qualname__}; expected "
                f"{self.inputs.__qualname__}"
            )
        return self.function(inputs, **context)

    @property
    def modules(self) -> tuple[str, ...]:
        """The modules whose source the key covers (the function's, then ``code``)."""
        return (self.function.__module__, *self.code)


class Runner(Protocol):
    """What runs a declared stage with its cache (``pipeline.runtime.runner.StageRunner``), as
    a certificate's strategy (``stages.certificates``) sees it."""

    def run(
        self,
        stage: Stage[Any, R],
        inputs: StageInputs,
        *,
        name: str | None = None,
        rerun: bool = False,
        describe: Callable[[R], str] | None = None,
        finish: Callable[[R], R] | None = None,
        **context: Any,
    ) -> R: ...
