"""Stabilised shooting: the same cost, over inputs that a sampled feedback keeps near a reference.

The quadrotor is a chain of integrators from pitch acceleration to position, so open loop a
change of ``u[k]`` early in a 15-s flight moves the end by metres: ``J(u)`` is badly conditioned
and the plain descent of §III-B crawls (measured on quadrotor_hill_flythrough: 4 of 9 demos stall).
As in Hauser's projection-operator method, the descent here runs over ``v (N, m)`` with the held
input

    u[k] = v[k] + G (x(k Ts) - z[k])

where ``G (m, n)`` is the robustness feedback's gain and ``z (N, n)`` the seed's sampled states.
The cost is the problem's ``J(u(v))``; its gradient ``dJ/dv`` is the discrete RK4 adjoint with the
feedback chained in at every sample time (``adjoint_kernel`` of ``kernels.loops``, ``feedback``
on). Since ``u(v)`` is itself piecewise constant, the optimum is an ordinary nominal input ``u``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.model.dynamics import FloatArray
from pipeline.numerics.optimize.problem import Problem


@dataclass(frozen=True, eq=False)
class StabilisedProblem:
    """``J(u(v))`` over ``v (N, m)``; ``inputs(v)`` gives the nominal ``u (N, m)``.

    Attributes:
      problem: the open-loop problem (cost, constraints, horizon).
      gain: (m, n) feedback gain ``G``; reference: (N, n) sampled states ``z``.
    """

    problem: Problem
    gain: FloatArray = field(repr=False)
    reference: FloatArray = field(repr=False)

    @classmethod
    def around(cls, problem: Problem, gain: FloatArray, u: FloatArray) -> StabilisedProblem:
        """Stabilise around the trajectory of ``u (N, m)``: at ``v = u`` the inputs are ``u``.

        ``gain`` is copied: a frozen result's gain is read-only, and numba types a read-only
        array apart from a writable one, so passing it as given compiled ``adjoint_kernel`` (and
        its ``rollout_grid`` and ``adjoint_sweep``) a second time per scenario (~1.9 s of CPU)."""
        reference = problem.trajectory(u).xs[:-1]
        return cls(
            problem, np.array(gain, dtype=np.float64, order="C"), np.ascontiguousarray(reference)
        )

    @property
    def input_lower(self) -> FloatArray:
        return self.problem.input_lower

    @property
    def input_upper(self) -> FloatArray:
        return self.problem.input_upper

    def _run(self, v: FloatArray, sweep: bool = True) -> tuple[float, FloatArray, FloatArray]:
        problem = self.problem
        v = problem._input(v)
        kernels, data, _ = problem._compiled
        u, q = np.empty_like(v), np.empty_like(v)
        h = problem.Ts / problem.substeps
        J = kernels.adjoint_kernel(
            problem.x0, v, self.reference, self.gain, True, h, problem.substeps, data, u, q, sweep
        )
        return float(J), q, u

    def inputs(self, v: FloatArray) -> FloatArray:
        """The nominal held input ``u (N, m)`` that ``v (N, m)`` produces."""
        return self._run(v, sweep=False)[2]

    def cost(self, v: FloatArray) -> float:
        return self._run(v, sweep=False)[0]

    def cost_and_gradient(self, v: FloatArray, method: str = "adjoint") -> tuple[float, FloatArray]:
        """``J(u(v))`` and ``dJ/dv (N, m)``; only the adjoint method exists here."""
        if method != "adjoint":
            raise ValueError(f"stabilised shooting has only the adjoint gradient, got {method!r}")
        J, q, _ = self._run(v)
        return J, q
