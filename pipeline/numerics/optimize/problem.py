"""The optimal-control problem of one demo (paper §IV-A): cost ``J(u)`` and its gradient.

    minimise J(u) over u (N, m), x(0) = x0, xdot = f(x, u[k]) on [k Ts, (k+1) Ts)

with ``J`` the penalty cost of ``pipeline.numerics.optimize.penalties`` (eqs. (26), (40)-(42))
evaluated on the RK4 grid: ``s = penalty_points + 1`` RK4 substeps per sample interval, so the
penalties see the sample times and ``penalty_points`` intermediate points of every interval, and the
grid is exactly the integrator's (``trajectory(u).dense_xs``). ``J == 0.0`` exactly when every
constraint holds with its margin on that grid. The gradient is the exact derivative of ``J`` as
implemented, by the paper's forward sensitivities (``method="sensitivity"``, eq. (29)) or by the
discrete adjoint (``method="adjoint"``). ``backend="numba"`` runs compiled kernels
(``pipeline.numerics.kernels.compiled``); ``backend="numpy"`` is the reference they are tested
against.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from pipeline.model.dynamics import FloatArray
from pipeline.model.simulate import Trajectory, simulate
from pipeline.numerics.optimize.adjoint import adjoint_gradient
from pipeline.numerics.optimize.margins import MarginProfile
from pipeline.numerics.optimize.penalties import Constraints, build_constraints
from pipeline.numerics.optimize.sensitivity import (
    SensitivityPattern,
    sensitivity_gradient,
    sensitivity_pattern,
)
from pipeline.numerics.settings import EPS_D, EPS_G, EPS_I

if TYPE_CHECKING:
    from pipeline.model.scenario import Scenario

DEFAULT_PENALTY_POINTS = 3  # 4 RK4 substeps per interval (pipeline.model.simulate.DEFAULT_SUBSTEPS)
METHODS = ("sensitivity", "adjoint")
_NO_REFERENCE = np.empty((0, 0))  # the reference states of the open loop: never read
BACKENDS = ("numba", "numpy")


@dataclass(frozen=True, eq=False)
class Problem:
    """Cost and gradient of piecewise-constant inputs ``u (N, m)`` from ``x0``.

    Attributes:
      N: horizon (samples); x0: (n,) start; u_seed: (N, m) seed input.
      constraints: the §IV-A constraints as penalties (shrunk bounds, ModGoal, d').
      penalty_points: intermediate grid points per interval; substeps = penalty_points + 1.
      backend: "numba" (compiled) or "numpy" (reference).
    """

    scenario: Scenario = field(repr=False)
    x0: FloatArray
    u_seed: FloatArray = field(repr=False)
    constraints: Constraints = field(repr=False)
    penalty_points: int
    backend: str
    # Memo of what depends only on the fields above (the compiled kernels and the sensitivity
    # pattern: on scenario.dynamics; each horizon's penalty data: on constraints, N, substeps).
    # Private to this instance: init=False, so dataclasses.replace starts an empty one for a
    # problem with other fields; only with_horizon, which changes u_seed (hence N, part of the
    # data's key) and nothing else, shares it.
    _cache: dict[str, Any] = field(default_factory=dict, init=False, repr=False, compare=False)

    @property
    def N(self) -> int:
        return int(self.u_seed.shape[0])

    @property
    def Ts(self) -> float:
        return self.scenario.Ts

    @property
    def substeps(self) -> int:
        return self.penalty_points + 1

    @property
    def input_lower(self) -> FloatArray:
        """Input bounds shrunk by ``eps_i + input_margin`` (the box for L-BFGS-B): (m,) when the
        margins are constant, else (N, m) per sample with the margin profile on this horizon;
        either broadcasts against ``u (N, m)``."""
        if self.constraints.profile.M == 1:
            return self.constraints.grid(1, 1).input_lower[0]
        return self.constraints.grid(self.N, self.substeps).input_lower

    @property
    def input_upper(self) -> FloatArray:
        if self.constraints.profile.M == 1:
            return self.constraints.grid(1, 1).input_upper[0]
        return self.constraints.grid(self.N, self.substeps).input_upper

    @property
    def region(self) -> Mapping[str, tuple[float, float]]:
        """Operating region shrunk by ``region_margin``: name -> (lower, upper)."""
        return self.constraints.region

    @property
    def pattern(self) -> SensitivityPattern:
        """Structural pattern of ``Phi``, ``Gamma``; ``pattern.equations`` is Remark 3's count."""
        if "pattern" not in self._cache:
            self._cache["pattern"] = sensitivity_pattern(self.scenario.dynamics)
        return self._cache["pattern"]

    @property
    def _compiled(self) -> Any:
        """(kernels, penalty data on this horizon's grid, sensitivity pattern)."""
        from pipeline.numerics.kernels import compiled

        if "compiled" not in self._cache:
            kernels = compiled.load_kernels(self.scenario.dynamics)
            pattern = compiled.pattern_data(self.pattern, self.scenario.dynamics.sparsity_x)
            self._cache["compiled"] = (kernels, pattern)
        key = f"data N={self.N} s={self.substeps}"  # the margins on this grid
        if key not in self._cache:
            self._cache[key] = compiled.penalty_data(self.constraints, self.N, self.substeps)
        kernels, pattern = self._cache["compiled"]
        return kernels, self._cache[key], pattern

    def _input(self, u: FloatArray) -> FloatArray:
        u = np.asarray(u, dtype=np.float64)
        if u.shape != self.u_seed.shape:
            raise ValueError(
                f"input has shape {u.shape}; expected {self.u_seed.shape} (N samples x m inputs)"
            )
        if not np.all(np.isfinite(u)):
            k, j = np.argwhere(~np.isfinite(u))[0]
            raise ValueError(
                f"input is not finite at sample {k}, '{self.scenario.input_names[j]}': {u[k, j]}"
            )
        u = np.ascontiguousarray(u)
        # a read-only input (e.g. a controller file's u_ref) as a writable copy: the kernels
        # take one array type (numba compiles per read-only flag too)
        return u if u.flags.writeable else u.copy()

    def trajectory(self, u: FloatArray) -> Trajectory:
        """The RK4 states the cost sees (``dense_xs`` is the penalty grid)."""
        u = self._input(u)
        if self.backend == "numpy":
            return simulate(self.scenario.dynamics, self.x0, u, self.Ts, self.substeps)
        kernels, _, _ = self._compiled
        dense = np.empty((self.N * self.substeps + 1, self.x0.size))
        kernels.simulate_kernel(self.x0, u, self.Ts / self.substeps, self.substeps, dense)
        return Trajectory(
            ts=self.Ts * np.arange(self.N + 1, dtype=np.float64),
            xs=dense[:: self.substeps],
            us=u.copy(),
            dense_ts=(self.Ts / self.substeps) * np.arange(dense.shape[0], dtype=np.float64),
            dense_xs=dense,
        )

    def cost(self, u: FloatArray) -> float:
        """``J(u)`` (>= 0; ``+inf`` if the grid enters Unsafe or the states are not finite)."""
        u = self._input(u)
        if self.backend == "numpy":
            dense = self.trajectory(u).dense_xs
            if not np.all(np.isfinite(dense)):
                return np.inf
            return self.constraints.evaluate(dense, u, self.substeps).cost
        return self._open_loop_adjoint(u, np.empty_like(u), sweep=False)

    def _open_loop_adjoint(self, u: FloatArray, q: FloatArray, sweep: bool) -> float:
        """The compiled adjoint of the open loop at ``u (N, m)`` (only read): ``J``, and with
        ``sweep`` ``dJ/du`` into ``q (N, m)``."""
        kernels, data, _ = self._compiled
        no_gain = np.zeros((u.shape[1], self.x0.size))
        J = kernels.adjoint_kernel(
            self.x0, u, _NO_REFERENCE, no_gain, False, self.Ts / self.substeps, self.substeps,
            data, np.empty_like(u), q, sweep,
        )  # fmt: skip
        return float(J)

    def cost_and_gradient(self, u: FloatArray, method: str = "adjoint") -> tuple[float, FloatArray]:
        """``J(u)`` and ``q = dJ/du`` (N, m).

        If ``J = +inf`` because a grid state is inside Unsafe, ``q`` is the gradient of the
        finite terms; if the states are not finite, ``q`` is NaN.
        """
        u = self._input(u)
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        h = self.Ts / self.substeps
        if self.backend == "numpy":
            dense = self.trajectory(u).dense_xs
            if not np.all(np.isfinite(dense)):
                return np.inf, np.full_like(u, np.nan)
            penalized = self.constraints.evaluate(dense, u, self.substeps)
            gradient = adjoint_gradient if method == "adjoint" else sensitivity_gradient
            args = (self.scenario.dynamics, dense, u, self.Ts, self.substeps)
            return penalized.cost, gradient(*args, penalized.J_x, penalized.J_u)
        kernels, data, pattern = self._compiled
        q = np.empty_like(u)
        if method == "adjoint":
            J = self._open_loop_adjoint(u, q, sweep=True)
        else:
            J = kernels.sensitivity_kernel(
                self.x0,
                u,
                h,
                self.substeps,
                data,
                pattern.terms,
                pattern.phi_rows,
                pattern.phi_cols,
                pattern.gamma_rows,
                pattern.gamma_cols,
                q,
            )
        return float(J), q

    def gradient(self, u: FloatArray, method: str = "adjoint") -> FloatArray:
        """``q = dJ/du`` (N, m) by ``method`` ("sensitivity" or "adjoint")."""
        return self.cost_and_gradient(u, method)[1]

    def with_horizon(self, N: int, u_seed: FloatArray | None = None) -> Problem:
        """The same problem with horizon ``N`` and seed ``u_seed`` (N, m) (default: this seed
        truncated to ``N``, or padded by repeating its last row)."""
        seed = _seed(self.u_seed if u_seed is None else u_seed, N, self.scenario.m)
        problem = dataclasses.replace(self, u_seed=seed)
        object.__setattr__(problem, "_cache", self._cache)  # the kernels, compiled once
        return problem


def _seed(us: FloatArray, N: int | None, m: int) -> FloatArray:
    us = np.asarray(us, dtype=np.float64)
    if us.ndim != 2 or us.shape[1] != m or us.shape[0] < 1:
        raise ValueError(f"seed input has shape {us.shape}; expected (N, {m}) with N >= 1")
    if not np.all(np.isfinite(us)):
        raise ValueError("seed input has non-finite entries")
    if N is None:
        return us.copy()
    if int(N) != N or N < 1:
        raise ValueError(f"horizon N must be a whole number >= 1, got {N!r}")
    N = int(N)
    if N <= us.shape[0]:
        return us[:N].copy()
    return np.concatenate([us, np.repeat(us[-1:], N - us.shape[0], axis=0)])


def make_problem(
    scenario: Scenario,
    demo: int = 0,
    N: int | None = None,
    *,
    x0: FloatArray | None = None,
    u_seed: FloatArray | None = None,
    input_margin: FloatArray | float | None = None,
    region_margin: Mapping[str, float] | None = None,
    eps_d: float = EPS_D,
    eps_g: float = EPS_G,
    eps_i: float = EPS_I,
    clearance: float | None = None,
    goal_margin: Mapping[str, float] | None = None,
    region: Mapping[str, tuple[float, float]] | None = None,
    profile: MarginProfile | None = None,
    penalty_points: int = DEFAULT_PENALTY_POINTS,
    backend: str = "numba",
) -> Problem:
    """The problem of demo ``demo`` (or of an explicit ``x0`` and ``u_seed``) with horizon ``N``.

    Args:
      demo: demo index; supplies ``x0`` and/or ``u_seed`` when they are not given.
      N: horizon in samples (default: the seed's length); the seed is truncated to ``N`` or
        padded by repeating its last row.
      x0: (n,) start; u_seed: (N0, m) seed input.
      input_margin: (m,) or scalar extra shrink of the input bounds (feedback margin).
      region_margin: name -> shrink of the operating-region box (tube extent).
      eps_d, eps_g, eps_i: the margins of §IV-A (Unsafe bloated by d + eps_d, Goal shrunk by
        d + eps_g, inputs shrunk by eps_i); clearance: ``d`` (default: the scenario's);
        goal_margin: name -> shrink of Goal's extra bounds (the tube's extent).
      region: name -> (lower, upper) box the nominal stays in (default: the operating region).
      profile: margins that vary along the trajectory (``pipeline.numerics.optimize.margins``), on
      top of
        the constant ones; read on each horizon's grid by normalised time (``on_grid``).
      penalty_points: intermediate penalty points per interval = RK4 substeps - 1.
      backend: "numba" or "numpy".
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if int(penalty_points) != penalty_points or penalty_points < 0:
        raise ValueError(f"penalty_points must be a whole number >= 0, got {penalty_points!r}")
    if x0 is None or u_seed is None:
        if not scenario.demos:
            raise ValueError(
                f"scenario '{scenario.name}' has no demos; pass x0= and u_seed= explicitly"
            )
        if not 0 <= demo < len(scenario.demos):
            raise ValueError(
                f"demo {demo} does not exist; scenario '{scenario.name}' has demos"
                f" 0..{len(scenario.demos) - 1}"
            )
        chosen = scenario.demos[demo]
        x0 = chosen.x0 if x0 is None else x0
        u_seed = chosen.us if u_seed is None else u_seed
    x0 = np.array(x0, dtype=np.float64)
    if x0.shape != (scenario.n,) or not np.all(np.isfinite(x0)):
        raise ValueError(f"x0 must be {scenario.n} finite numbers, got {x0.tolist()}")
    constraints = build_constraints(
        scenario,
        input_margin=input_margin,
        region_margin=region_margin,
        eps_d=eps_d,
        eps_g=eps_g,
        eps_i=eps_i,
        clearance=clearance,
        goal_margin=goal_margin,
        region=region,
        profile=profile,
    )
    return Problem(
        scenario=scenario,
        x0=x0,
        u_seed=_seed(u_seed, N, scenario.m),
        constraints=constraints,
        penalty_points=int(penalty_points),
        backend=backend,
    )
