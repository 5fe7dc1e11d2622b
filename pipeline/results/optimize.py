"""The result types of stage ``optimize`` (``stages/optimize.py``)."""

from __future__ import annotations

from dataclasses import dataclass, field

from pipeline.model.dynamics import FloatArray
from pipeline.numerics.optimize.descent import IterationLog, check_stall_settings
from pipeline.numerics.optimize.horizon import PARAMETERIZATIONS, SEED_MODES
from pipeline.numerics.settings import DESCENT_METHODS, EPS_D, EPS_G, EPS_I, HORIZON_SEARCHES
from pipeline.numerics.verify.nominal import Verification
from pipeline.results.base import Result

METHODS = DESCENT_METHODS
SEARCHES = HORIZON_SEARCHES


@dataclass(frozen=True, kw_only=True)
class OptimizeOptions:
    method: str = METHODS[0]
    seed_mode: str = "compress"
    parameterization: str = "feedback"
    search: str = SEARCHES[0]
    step_fraction: float = 0.1  # continuation: shorten by this fraction of the horizon
    eps_d: float = EPS_D
    eps_g: float = EPS_G
    eps_i: float = EPS_I
    eps_r: float = 0.01  # operating-region states: room for motion between penalty points
    overshoot: float = 0.01  # the descent's extra margin (m, N, rad: the constraints' units)
    max_iterations: int = 1000
    # a try stops early when its J, falling at its rate over the last ``stall_window``
    # evaluations, would end its budget above ``stall_margin`` x the goal (descent.Stall)
    stall_window: int = 100
    stall_margin: float = 100.0

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {self.method!r}")
        if self.seed_mode not in SEED_MODES:
            raise ValueError(f"seed_mode must be one of {SEED_MODES}, got {self.seed_mode!r}")
        if self.search not in SEARCHES:
            raise ValueError(f"search must be one of {SEARCHES}, got {self.search!r}")
        if not self.overshoot >= 0.0:
            raise ValueError(f"overshoot must be >= 0, got {self.overshoot!r}")
        check_stall_settings(self.stall_window, self.stall_margin)
        if self.parameterization not in PARAMETERIZATIONS:
            raise ValueError(
                f"parameterization must be one of {PARAMETERIZATIONS}, "
                f"got {self.parameterization!r}"
            )


@dataclass(frozen=True, kw_only=True)
class BisectionTry(Result):
    """One horizon tried: ``N`` samples, whether ``J`` reached 0, and at what effort."""

    N: int
    feasible: bool
    iterations: int
    cost: float
    seconds: float


@dataclass(frozen=True, kw_only=True)
class TrajectoryOptimization(Result):
    """The optimisation of one demo.

    Attributes:
      x0: (n,) its start; u: (N, m) the fastest feasible input found (the demo's if none).
      tries: every horizon tried, in order; feasible_inputs: the feasible ``(N_i, m)`` inputs
      met on the way (the paper's Fig. 2 intermediate trajectories); log: iteration log of the
      final horizon's descent (its cost is the tightened one the descent minimised).
    """

    demo: str
    x0: FloatArray
    N_demo: int
    N: int
    u: FloatArray
    Ts: float
    tries: tuple[BisectionTry, ...]
    feasible_inputs: tuple[FloatArray, ...] = field(repr=False)
    log: IterationLog = field(repr=False)
    verification: Verification | None
    seconds: float
    success: bool
    message: str

    @property
    def speedup(self) -> float:
        """Fraction of the demo's duration saved: ``1 - N / N_demo``."""
        return 1.0 - self.N / self.N_demo


@dataclass(frozen=True, kw_only=True)
class OptimizeResult(Result):
    trajectories: tuple[TrajectoryOptimization, ...]
    options: OptimizeOptions
    success: bool
    message: str
