"""Stage ``feedback``: the robustness feedback ``u = u_ref(t) + K (x - x_ref(t))`` and its
contraction certificate.

Certificate: ``P > 0`` and a rate ``lambda > 0`` with, for every vertex ``[A_i B_i]`` of a polytope
that soundly contains ``[f_x f_u]`` over the operating region (``pipeline.numerics.hull``),

    (A_i + B_i K)^T P + P (A_i + B_i K) + 2 lambda P <= -eps P.                         (C)

For two closed-loop solutions with the same reference input, ``e = x - x_ref`` obeys
``de/dt = Abar e`` with ``Abar = int_0^1 [f_x + f_u K](x_ref + s e, u_ref + s K e) ds``; when both
stay in the (convex) region, ``Abar`` lies in the hull, so ``d/dt e^T P e <= -2 lambda e^T P e``
and ``||e(t)||_P <= exp(-lambda t) ||e(0)||_P``. The certificate is accepted only after the
largest generalised eigenvalue of (C)'s left side against ``P`` is checked negative at every
vertex with numpy, independently of the solver (``pipeline.numerics.tube.contraction``, as the
certifier evaluates it).

Design. ``C`` (2, n) selects the position, ``S`` the non-degenerate directions of Init. The scale of
``P`` is fixed by ``C P^-1 C^T <= I`` (position extent <= 1 per unit radius), and we minimise

    t + w d^2 (sum_j g_j / h_j^2 + sum_i (P^-1)_ii / h_i^2)
    subject to (C),  S^T P S <= t I,  K_j P^-1 K_j^T <= g_j,

i.e. a large Init slice per unit of position extent (its semi-axes at radius ``r_d`` are at
least ``d / sqrt(t)``) plus the squared fractions of each input range ``h_j`` and each
operating-region state range ``h_i`` that the tube uses at radius ``r_d ~ d`` (half-widths).
``gain="lqr"``: ``K`` from LQR at the scenario's reference point, the LMIs linear in ``P``.
``gain="joint"``: ``Q = P^-1``, ``Y = K Q`` (all of the above is linear in ``Q, Y`` by Schur
complements). ``gain="auto"`` solves both and keeps the certified design with the lower
objective.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

import control
import cvxpy as cp
import numpy as np

from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.numerics.hull import DEFAULT_SEGMENTS, HullError, jacobian_hull
from pipeline.numerics.tube.contraction import contraction_margin
from pipeline.numerics.tube.feedback_search import RATES, tune_feedback
from pipeline.numerics.tube.geometry import Tube
from pipeline.results.feedback import FeedbackResult as FeedbackResult
from pipeline.results.stage import Stage, StageInputs

GAINS = ("auto", "lqr", "joint")
EPS = 1e-3
MIN_EIGENVALUE = 1e-6


@dataclass(frozen=True, kw_only=True)
class _Design:
    K: FloatArray
    P: FloatArray
    status: str
    objective: float


def _position_matrix(scenario: Scenario) -> FloatArray:
    C = np.zeros((2, scenario.n))
    C[0, scenario.position_index[0]] = C[1, scenario.position_index[1]] = 1.0
    return C


def _slice_matrix(scenario: Scenario) -> FloatArray:
    """S (n, D): Init's non-degenerate directions (the position if Init is a point)."""
    free = np.flatnonzero(scenario.init_upper > scenario.init_lower)
    if free.size == 0:
        return _position_matrix(scenario).T
    return np.eye(scenario.n)[:, free]


def _half_widths(scenario: Scenario) -> tuple[dict[int, float], dict[int, float]]:
    """Half-widths of the allowed ranges: inputs (bounds within the region), region states."""
    region = scenario.operating_region
    inputs = {}
    for j, name in enumerate(scenario.input_names):
        lower, upper = scenario.input_lower[j], scenario.input_upper[j]
        if name in region:
            lower, upper = max(lower, region[name][0]), min(upper, region[name][1])
        if upper > lower:
            inputs[j] = (upper - lower) / 2
    states = {
        i: (region[name][1] - region[name][0]) / 2
        for i, name in enumerate(scenario.state_names)
        if name in region and region[name][1] > region[name][0]
    }
    return inputs, states


def _scalar(x: cp.Expression) -> cp.Expression:
    return cp.reshape(x, (1, 1), order="C")


def _sym(M: cp.Expression) -> cp.Expression:
    return (M + M.T) / 2


def _solve_lqr_design(
    scenario: Scenario, K: FloatArray, A: FloatArray, B: FloatArray, rate: float, weight: float
) -> _Design | str:
    """(C) and the objective, linear in ``P`` for the fixed gain ``K (m, n)``; vertices
    ``A (V, n, n)``, ``B (V, n, m)``."""
    n = scenario.n
    C, S = _position_matrix(scenario), _slice_matrix(scenario)
    h_u, h_x = _half_widths(scenario)
    d2 = scenario.clearance**2
    P = cp.Variable((n, n), symmetric=True)
    t = cp.Variable()
    constraints = [P >> MIN_EIGENVALUE * np.eye(n)]
    for Ai, Bi in zip(A, B, strict=True):
        Acl = Ai + Bi @ K
        constraints.append(_sym(Acl.T @ P + P @ Acl + (2 * rate + EPS) * P) << 0)  # (C)
    constraints.append(cp.bmat([[P, C.T], [C, np.eye(2)]]) >> 0)  # C P^-1 C^T <= I
    constraints.append(_sym(S.T @ P @ S) << t * np.eye(S.shape[1]))
    penalty = 0.0
    for j, h in h_u.items():
        g = cp.Variable()
        constraints.append(cp.bmat([[P, K[j : j + 1].T], [K[j : j + 1], _scalar(g)]]) >> 0)
        penalty = penalty + g / h**2
    for i, h in h_x.items():
        g = cp.Variable()
        e = np.eye(n)[:, i : i + 1]
        constraints.append(cp.bmat([[P, e], [e.T, _scalar(g)]]) >> 0)
        penalty = penalty + g / h**2
    problem = cp.Problem(cp.Minimize(t + weight * d2 * penalty), constraints)
    return _solve(problem, lambda: (K, _value(P)))


def _solve_joint_design(
    scenario: Scenario, A: FloatArray, B: FloatArray, rate: float, weight: float
) -> _Design | str:
    """(C) times ``Q = P^-1`` on both sides, with ``Y = K Q``: linear in ``Q, Y``."""
    n, m = scenario.n, scenario.m
    C, S = _position_matrix(scenario), _slice_matrix(scenario)
    h_u, h_x = _half_widths(scenario)
    d2 = scenario.clearance**2
    Q = cp.Variable((n, n), symmetric=True)
    Y = cp.Variable((m, n))
    t = cp.Variable()
    constraints = [Q >> MIN_EIGENVALUE * np.eye(n)]
    for Ai, Bi in zip(A, B, strict=True):
        M = Ai @ Q + Q @ Ai.T + Bi @ Y + Y.T @ Bi.T + (2 * rate + EPS) * Q  # (C) times Q both sides
        constraints.append(_sym(M) << 0)
    constraints.append(_sym(C @ Q @ C.T) << np.eye(2))
    D = S.shape[1]
    constraints.append(cp.bmat([[t * np.eye(D), S.T], [S, Q]]) >> 0)  # S^T Q^-1 S <= t I
    penalty = 0.0
    for j, h in h_u.items():
        g = cp.Variable()
        constraints.append(cp.bmat([[_scalar(g), Y[j : j + 1]], [Y[j : j + 1].T, Q]]) >> 0)
        penalty = penalty + g / h**2
    for i, h in h_x.items():
        penalty = penalty + Q[i, i] / h**2
    problem = cp.Problem(cp.Minimize(t + weight * d2 * penalty), constraints)

    def design() -> tuple[FloatArray, FloatArray]:
        Qv = (_value(Q) + _value(Q).T) / 2
        Q_inv = np.linalg.inv(Qv).astype(np.float64, copy=False)
        return _value(Y) @ Q_inv, Q_inv

    return _solve(problem, design)


def _value(variable: cp.Variable) -> FloatArray:
    """The solved value of ``variable``; a TypeError (``_solve``: no usable solution) if none."""
    if variable.value is None:
        raise TypeError(f"the solver left {variable} without a value")
    return variable.value


def _solve(
    problem: cp.Problem, design: Callable[[], tuple[FloatArray, FloatArray]]
) -> _Design | str:
    try:
        with warnings.catch_warnings():  # stages print nothing; the status says it all
            warnings.simplefilter("ignore")
            problem.solve(solver=cp.CLARABEL)
    except cp.SolverError as error:
        return f"solver error ({error})"
    if problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
        return problem.status
    try:
        K, P = design()
    except (TypeError, np.linalg.LinAlgError):  # no value, or a singular Q
        return f"{problem.status} but no usable solution"
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(P))):
        return f"{problem.status} but non-finite K or P"
    return _Design(
        K=np.asarray(K), P=(P + P.T) / 2, status=problem.status, objective=float(problem.value)
    )


def lqr_gain(scenario: Scenario) -> FloatArray:
    """(m, n) LQR gain at the scenario's reference point, in the sign of ``u = u_ref + K e``."""
    spec = scenario.feedback
    x, u = np.array(spec.reference_state), np.array(spec.reference_input)
    A, B = scenario.dynamics.f_x(x, u), scenario.dynamics.f_u(x, u)
    K, _, _ = control.lqr(A, B, np.diag(spec.state_weights), np.diag(spec.input_weights))
    return -np.asarray(K, dtype=np.float64)


def _advice(scenario: Scenario, rate: float) -> str:
    """What to edit in the scenario file: the rate, and the operating region only over the
    variables the Jacobian depends on (narrowing any other leaves the hull unchanged)."""
    narrow = [name for name in scenario.dynamics.depends_on() if name in scenario.operating_region]
    region = f" or narrow operating_region ({', '.join(narrow)})" if narrow else ""
    return f"try a feedback.rate below {rate:g}{region}"


def _searched(scenario: Scenario, message: str) -> str:
    """A failed design's message after the search failed too: its advice (a lower rate, a
    narrower region) was tried, except a rate the file gives; name what is left."""
    narrow = [name for name in scenario.dynamics.depends_on() if name in scenario.operating_region]
    smaller = f"fly the demos over a smaller range of ({', '.join(narrow)})"
    first = message.rsplit("; try a feedback.rate", 1)[0]
    if "rate" in scenario.feedback.given:
        return (
            f"{first}; nor with the operating region narrowed around the demos: lower "
            f"feedback.rate (the search keeps a rate the file gives), or {smaller}"
        )
    return (
        f"{first}; nor in any design the search tried (rates down to {min(RATES):g} 1/s, the "
        f"operating region narrowed around the demos): the Jacobian varies too much for one "
        f"metric over what the demos use; {smaller}"
    )


def design_feedback(
    scenario: Scenario,
    *,
    gain: str = "auto",
    rate: float | None = None,
    segments: int = DEFAULT_SEGMENTS,
    margin_weight: float = 10.0,
) -> FeedbackResult:
    """Design ``K`` and certify the contraction metric ``P`` at ``rate`` (default: the
    scenario's ``feedback.rate``) over ``scenario.operating_region``; see the module docstring.
    With the scenario's ``feedback.tune`` (and no ``rate`` given) the design is searched for
    (``pipeline.numerics.tube.feedback_search``) and the result's ``tuning`` says what was chosen.

    A failed design returns ``success=False`` with a message naming the region and rate tried.
    """
    if gain not in GAINS:
        raise ValueError(f"gain must be one of {GAINS}, got {gain!r}")
    if rate is None and scenario.feedback.tune:
        chosen, tuning = tune_feedback(
            scenario, lambda s: _design(s, gain, None, segments, margin_weight)
        )
        assert isinstance(chosen, FeedbackResult)
        if tuning is None:
            return dataclasses.replace(chosen, message=_searched(scenario, chosen.message))
        return dataclasses.replace(
            chosen, tuning=tuning, message=f"{chosen.message}; {tuning.summary(scenario)}"
        )
    return _design(scenario, gain, rate, segments, margin_weight)


def _design(
    scenario: Scenario, gain: str, rate: float | None, segments: int, margin_weight: float
) -> FeedbackResult:
    """One design at ``rate`` (default: the scenario's) over its operating region."""
    if gain not in GAINS:
        raise ValueError(f"gain must be one of {GAINS}, got {gain!r}")
    rate = float(scenario.feedback.rate if rate is None else rate)
    n, m = scenario.n, scenario.m
    region = dict(scenario.operating_region)
    where = ", ".join(f"{k} in [{lo:g}, {hi:g}]" for k, (lo, hi) in region.items()) or "everywhere"

    def failed(message: str, K=None, vertices=None, status="", hull=()):
        return FeedbackResult(
            K=K,
            P=None,
            rate=rate,
            vertices=np.zeros((0, n, n + m)) if vertices is None else vertices,
            solver_status=status,
            region=region,
            state_names=scenario.state_names,
            input_names=scenario.input_names,
            success=False,
            message=message,
            hull=hull,
        )

    try:
        hull = jacobian_hull(scenario.dynamics, region, segments)
    except HullError as error:
        return failed(f"feedback: {error}")
    A, B = hull.A, hull.B
    tries: dict[str, _Design | str] = {}
    K_lqr = None
    if gain in ("auto", "lqr"):
        try:
            with warnings.catch_warnings():  # SciPy's Riccati warnings: the status says it
                warnings.simplefilter("ignore")
                K_lqr = lqr_gain(scenario)
            tries["lqr"] = _solve_lqr_design(scenario, K_lqr, A, B, rate, margin_weight)
        except (ValueError, np.linalg.LinAlgError, control.ControlArgument) as error:
            tries["lqr"] = f"LQR failed ({error})"
    if gain in ("auto", "joint"):
        tries["joint"] = _solve_joint_design(scenario, A, B, rate, margin_weight)

    certified: dict[str, tuple[_Design, float]] = {}
    notes = []
    for name, design in tries.items():
        if isinstance(design, str):
            notes.append(f"{name}: {design}")
            continue
        try:
            margin = contraction_margin(design.P, design.K, A, B, rate, normalised=True)
        except np.linalg.LinAlgError:
            notes.append(f"{name}: P is not positive definite")
            continue
        if margin < 0:
            certified[name] = (design, margin)
        else:
            notes.append(f"{name}: solver returned a P that fails the check (margin {margin:.2e})")
    status = "; ".join(f"{k}: {v if isinstance(v, str) else v.status}" for k, v in tries.items())
    if not certified:
        return failed(
            f"feedback: no contraction certificate at rate {rate:g} 1/s over {where} "
            f"({'; '.join(notes)}); {_advice(scenario, rate)}",
            K=K_lqr,
            vertices=hull.vertices,
            status=status,
            hull=hull.blocks,
        )
    name = min(certified, key=lambda k: certified[k][0].objective)
    design, margin = certified[name]
    K = design.K
    others = "".join(
        f"; {k} objective {v[0].objective:.4g}" for k, v in certified.items() if k != name
    )
    return FeedbackResult(
        K=K,
        P=design.P,
        rate=rate,
        vertices=hull.vertices,
        solver_status=design.status,
        tube=Tube(
            K=K,
            P=design.P,
            rate=rate,
            region=region,
            state_names=scenario.state_names,
            input_names=scenario.input_names,
            position_index=scenario.position_index,
        ),
        region=region,
        state_names=scenario.state_names,
        input_names=scenario.input_names,
        success=True,
        message=(
            f"certified rate {rate:g} 1/s over {where} with the {name} gain "
            f"({len(hull.vertices)} hull vertices, margin {margin:.1e} (< 0: holds), "
            f"objective {design.objective:.4g}{others})"
        ),
        gain=name,
        certified_margin=margin,
        objective=design.objective,
        hull=hull.blocks,
    )


@dataclass(frozen=True, kw_only=True)
class FeedbackInputs(StageInputs):
    """What stage ``feedback`` reads: the scenario's dynamics, region, bounds and weights."""

    scenario_fields: ClassVar = (
        "clearance",
        "dynamics",
        "feedback",
        "init_lower",
        "init_upper",
        "input_lower",
        "input_upper",
        "operating_region",
        "position_index",
    )
    scenario: Scenario


def _feedback_stage(inputs: FeedbackInputs) -> FeedbackResult:
    return design_feedback(inputs.scenario)


FEEDBACK = Stage("feedback", _feedback_stage, FeedbackInputs, FeedbackResult)
