"""Sampled realisations of a declared uncertainty for closed-loop runs: parameters and gusts.

A run under the declared uncertainty (``pipeline.model.uncertainty``) flies

    x' = f(x, u, p) + w(t),

``p`` the uncertain parameters, constant during the run, and ``w`` a gust: piecewise constant,
a new value every ``period`` seconds (``GUST_PERIOD``, 0.5 s) of absolute time since the run's
start (``w(t) = gusts[floor(t / period)]``, held past the last). Both stay in the declared sets,
so each such run is one admissible flight and a failure among them contradicts a certificate
that holds the declaration. Three kinds of draw (``sample``), each run drawing its kind first:

- uniform: ``p`` uniform in its box, each gust uniform in the disturbance box;
- bang-bang corners: ``p`` at a random corner of its box, each gust at a random corner of the
  disturbance box (the extremes a worst case is made of);
- the falsification's worst case (``stages.montecarlo.falsify``): its corner parameters and its
  gust sign sequence, from the run's own start.

A declared measurement error (``uncertainty.measurement``) is drawn the same way, on the same
periods: ``eta(t) = errors[floor(t / period)]`` added to the state the law sees (uniform in its
box, or at random corners for the corner and worst-case runs). It is drawn only when declared,
after everything else: without one the draws and the random stream are as before.

The runs stay i.i.d. (a mixture of the three), so a Clopper-Pearson bound on their failure rate
is valid for that mixture. The simulators apply ``w`` on whole RK4 steps: step ``j`` (times
``[t_j, t_j + h)``) uses the gust at ``t_j`` (a gust switching inside a step takes effect at the
step's end, which is again an admissible signal).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.model.dynamics import Dynamics, FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.uncertainty import Uncertainty

GUST_PERIOD = 0.5  # s: a new gust value every half second
CORNER_SHARE = 0.25  # of the runs: bang-bang at random corners
WORST_SHARE = 0.25  # of the runs: the falsification's worst bang-bang case (else corners)
GUST_ROUNDING = 1e-9  # floor((t0 + j h) / period + 1e-9), in both simulators


@dataclass(frozen=True, kw_only=True)
class Draws:
    """Per-run parameters and gusts (``B`` runs, ``q`` parameters, ``G`` gusts, ``n`` states).

    Attributes:
      parameters: (B, q) the uncertain parameters' values (``q = 0``: none).
      gusts: (B, G, n) the gust values; ``G = 0``: no gusts.
      start: (B,) the run's time (s) at the simulation's start (``T_i`` when continuing past
        ``T``): step ``j`` uses gust ``floor((start + j h) / period)``, at most ``G - 1``.
      period: the gust period (s).
      errors: (B, G, n) the measurement errors ``eta`` on the same periods as the gusts (added to
        the state the law sees); None: the state is measured exactly.
    """

    parameters: FloatArray
    gusts: FloatArray
    start: FloatArray
    period: float = GUST_PERIOD
    errors: FloatArray | None = None

    @classmethod
    def none(cls, runs: int, n: int) -> Draws:
        """No parameters and no gusts for ``runs`` runs (the exact model)."""
        return cls(
            parameters=np.zeros((runs, 0)), gusts=np.zeros((runs, 0, n)), start=np.zeros(runs)
        )

    def rows(self, rows: np.ndarray) -> Draws:
        """The draws of runs ``rows`` (an index array or mask)."""
        return Draws(
            parameters=self.parameters[rows],
            gusts=self.gusts[rows],
            start=self.start[rows],
            period=self.period,
            errors=None if self.errors is None else self.errors[rows],
        )

    def started(self, start: FloatArray) -> Draws:
        """The same draws simulated from times ``start (B,)``."""
        return Draws(
            parameters=self.parameters,
            gusts=self.gusts,
            start=np.asarray(start, dtype=np.float64),
            period=self.period,
            errors=self.errors,
        )

    def gust_index(self, t: float) -> np.ndarray:
        """(B,) the gust in force at simulation time ``t`` (from each run's ``start``)."""
        index = np.floor((self.start + t) / self.period + GUST_ROUNDING).astype(np.int64)
        return np.clip(index, 0, max(self.gusts.shape[1] - 1, 0))

    def gust(self, t: float) -> FloatArray:
        """(B, n) ``w`` at simulation time ``t``; zeros without gusts."""
        B, G, n = self.gusts.shape
        if G == 0:
            return np.zeros((B, n))
        return self.gusts[np.arange(B), self.gust_index(t)]

    def error(self, t: float) -> FloatArray | float:
        """(B, n) ``eta`` at simulation time ``t`` (the gusts' periods); 0.0 without errors."""
        if self.errors is None or self.errors.shape[1] == 0:
            return 0.0
        B, G, _ = self.errors.shape
        index = np.floor((self.start + t) / self.period + GUST_ROUNDING).astype(np.int64)
        return self.errors[np.arange(B), np.clip(index, 0, G - 1)]


def flown_dynamics(scenario: Scenario, draws: Draws | None) -> Dynamics:
    """The dynamics the runs are simulated with: ``f(x, (u, p))`` with uncertain parameters,
    else the scenario's ``f(x, u)``."""
    parametric = scenario.uncertainty.parametric
    if draws is None or draws.parameters.shape[1] == 0 or parametric is None:
        return scenario.dynamics
    return parametric


def gust_count(horizon: float, period: float = GUST_PERIOD) -> int:
    """Gusts covering ``[0, horizon]`` s."""
    return int(math.floor(horizon / period + GUST_ROUNDING)) + 1


def corners(uncertainty: Uncertainty, parameter_signs: FloatArray, gust_signs: FloatArray) -> Draws:
    """Bang-bang draws: parameters at the corners ``parameter_signs (B, q)`` (+1 upper, -1 lower)
    and gusts ``gust_signs (B, G, n) * disturbance`` (+-1 each)."""
    parameters = np.where(
        np.asarray(parameter_signs) > 0, uncertainty.parameter_upper, uncertainty.parameter_lower
    )
    gusts = np.asarray(gust_signs, dtype=np.float64) * uncertainty.disturbance
    return Draws(parameters=parameters, gusts=gusts, start=np.zeros(len(gusts)))


def sample(
    uncertainty: Uncertainty,
    rng: np.random.Generator,
    runs: int,
    horizon: float,
    worst: Draws | None = None,
    period: float = GUST_PERIOD,
) -> Draws:
    """``runs`` i.i.d. draws over ``[0, horizon]`` s: each run uniform (``1 - CORNER_SHARE -
    WORST_SHARE`` of them on average), at random corners, or the falsification's ``worst``
    (one run's draws; without it those runs draw corners too). Consumes ``rng`` in a fixed order
    whatever the kinds drawn."""
    q, n = len(uncertainty.parameter_names), len(uncertainty.disturbance)
    G = gust_count(horizon, period)
    kind = rng.random(runs)
    lower, upper = uncertainty.parameter_lower, uncertainty.parameter_upper
    parameters = lower + (upper - lower) * rng.random((runs, q))
    gusts = uncertainty.disturbance * rng.uniform(-1.0, 1.0, size=(runs, G, n))
    bang = corners(
        uncertainty,
        rng.choice([-1.0, 1.0], size=(runs, q)),
        rng.choice([-1.0, 1.0], size=(runs, G, n)),
    )
    corner = kind < CORNER_SHARE + (WORST_SHARE if worst is None else 0.0)
    parameters[corner], gusts[corner] = bang.parameters[corner], bang.gusts[corner]
    if worst is not None:
        chosen = kind >= 1.0 - WORST_SHARE
        parameters[chosen] = worst.parameters[0]
        # the worst sequence, its last gust held if it is shorter than this horizon
        worst_gusts = worst.gusts[0][np.minimum(np.arange(G), worst.gusts.shape[1] - 1)]
        gusts[chosen] = worst_gusts
    errors = None
    if uncertainty.measured:  # drawn last: without a measurement error the stream is as before
        E = uncertainty.measurement
        errors = E * rng.uniform(-1.0, 1.0, size=(runs, G, n))
        bang_errors = E * rng.choice([-1.0, 1.0], size=(runs, G, n))
        at_corners = corner if worst is None else corner | (kind >= 1.0 - WORST_SHARE)
        errors[at_corners] = bang_errors[at_corners]
    return Draws(
        parameters=parameters, gusts=gusts, start=np.zeros(runs), period=period, errors=errors
    )
