"""Minimum-time optimisation: our search (gd, L-BFGS) against CasADi + IPOPT, side by side.

For every quadrotor_hill_flythrough demo start ``x0`` both solve the problem of ``stages.optimize``:

    minimise T = N Ts  over piecewise-constant u (N, m) held for Ts = 0.1 s
    s.t.  x(0) = x0, RK4 with s = 4 substeps per sample (the penalty grid x_i, i = 0..N s)
          dist(p(x_i), Unsafe_j) >= d' = d + eps_d         at every grid point      eq. (42)
          p(x_{N s}) in ModGoal = Goal shrunk by d + eps_g                          eq. (41)
          u[k] in the input box shrunk by the feedback's input margin               eq. (40)
          region states (theta) at every grid point, region inputs (u1) at every sample, in the
          operating region shrunk by the tube's extents (+ eps_r for states)

built exactly as ``optimize_demo`` builds it (``scenario.problem`` with the same margins).

IPOPT side (direct multiple shooting; variables X (n, N+1), U (m, N) and, in phase 1, T):
  1. Free final time: N = N_demo / 3 fixed and the hold ``Ts_free = T / N`` free, T in
     ``(0, T_demo]``; minimise T. Initialised from the demo compressed three times in time
     (states resampled in normalised time, rate states scaled by 3; inputs compressed as in
     ``stages.optimize.reseed``), so the first hold is about Ts.
  2. Quantisation: ``N' = ceil(T* / Ts)``, then a feasibility NLP with the hold fixed at Ts
     (zero objective, warm-started from phase 1 retimed to ``N' Ts``); N' + 1, N' + 2, ... while
     IPOPT fails. ``T_ipopt = N' Ts``; phase 1's ``T*`` is printed too (its hold is finer than Ts,
     so it is not itself a feasible answer at Ts).
  We chose this over an IPOPT bisection on N because it is the free-final-time method the issue
  names and needs two NLPs instead of ~log2(N_demo) feasibility problems. IPOPT runs with exact
  Hessians, MUMPS and ``mu_strategy = adaptive`` (the default monotone strategy took 5x more
  iterations on some demos). Without the bound ``T <= T_demo`` IPOPT sometimes wandered to local
  optima of 50-1000 s; with it every demo reached the same ~3.3 s optimum in our trials.

Clearance (the hill is a non-convex polygon): for a point outside a polygon its distance to the
polygon is the smallest distance to an edge of its boundary, so ``dist >= d'`` is imposed as one
smooth constraint per (grid point, edge): the exact point-to-segment distance squared
``|p - a - clip(t, 0, 1)(b - a)|^2 >= (d' + margin)^2`` with ``t = (p - a).(b - a) / |b - a|^2``
(squared distance to a convex set is C^1). Edge constraints alone would also hold deep inside a
polygon; consecutive grid points are closer than ``2 d'`` (speed * Ts / 4 << 2.1 m), so a grid
that starts outside cannot cross a band of width ``2 d'`` around an edge, and stays outside.
ModGoal (a convex polygon; a box here) is ``A p <= b`` from its edges. The NLP's constraints are
tightened by ``NLP_MARGIN`` so that IPOPT's solution, to its tolerance, also has our cost
``J == 0`` exactly; it is then checked with ``J`` and
``pipeline.numerics.verify.nominal.verify_nominal``.

Certification's cost (issue 16): ``T_unc`` is IPOPT's minimum time from the same start with no
tube at all (``bench.uncertified``: clearance d, Goal itself, the full input bounds and the
scenario's ``state_bounds``), and ``cert/unc`` is ``T_certified / T_unc`` with ``T_certified`` the
optimized T of the synthesized run's method (the scenario's ``optimizer``, the constant
certificate's tube: what the optimize stage returns for that demo).

Wall times: ours is ``optimize_demo`` (the whole search, after the numba kernels are loaded);
IPOPT's is every NLP build and solve of phases 1 and 2. Runs on all 9 demos (about a minute).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from bench.uncertified import KnownUncertainty, uncertified_constraints
from pipeline.model.scenario import Scenario, load_scenario
from pipeline.model.simulate import simulate
from pipeline.numerics.optimize.penalties import Constraints
from pipeline.numerics.optimize.problem import Problem, make_problem
from pipeline.numerics.verify.nominal import verify_nominal
from stages.feedback import design_feedback
from stages.optimize import ConstraintMargins, OptimizeOptions, optimize_demo, reseed

SUBSTEPS = 4
COMPRESSION = 3.0
NLP_MARGIN = 1e-5
EXTRA_SAMPLES = 6
IPOPT_OPTIONS = {
    "ipopt.print_level": 0,
    "ipopt.sb": "yes",
    "ipopt.max_iter": 3000,
    "ipopt.tol": 1e-8,
    "ipopt.mu_strategy": "adaptive",
    "print_time": False,
}


@dataclass(frozen=True)
class IpoptSolution:
    """Outcome of one NLP: ``X (N+1, n)``, ``U (N, m)``, ``T``; ``success`` from IPOPT."""

    X: np.ndarray
    U: np.ndarray
    T: float
    success: bool
    status: str
    iterations: int


@dataclass(frozen=True)
class IpoptMinimumTime:
    """Phase 1 ``T_free`` and the quantised ``N`` (``U (N, m)`` held for Ts)."""

    T_free: float
    N: int
    U: np.ndarray | None
    nlps: int
    iterations: int
    seconds: float
    message: str


class MinimumTimeNLP:
    """Direct multiple shooting of the problem above with CasADi; ``solve(N, guess, free)``."""

    def __init__(
        self,
        scenario: Scenario,
        x0: np.ndarray,
        constraints: Constraints,
        T_max: float,
        known: KnownUncertainty | None = None,
    ) -> None:
        """``known``: fly the scenario under these parameters and constant push instead of its
        nominal model (``bench.uncertified.known_uncertainty_floor``)."""
        import casadi as ca

        self.ca, self.scenario, self.x0, self.c, self.T_max = ca, scenario, x0, constraints, T_max
        n, m = scenario.n, scenario.m
        x, u = ca.SX.sym("x", n), ca.SX.sym("u", m)
        self.f = ca.Function("f", [x, u], [_casadi_field(scenario, x, u, known)])
        self.edges = _edges(constraints.unsafe.values())  # (E, 2, 2)
        self.goal_A, self.goal_b = _halfspaces(constraints.goal_region)
        lower = np.array(constraints.input_lower, dtype=np.float64)
        upper = np.array(constraints.input_upper, dtype=np.float64)
        for j, lo, hi in zip(
            constraints.region_input_index,
            constraints.region_input_lower,
            constraints.region_input_upper,
            strict=True,
        ):
            lower[j], upper[j] = max(lower[j], lo), min(upper[j], hi)
        self.u_lower, self.u_upper = lower + NLP_MARGIN, upper - NLP_MARGIN

    def _grid(self, X, U, h):
        """Continuity defects (n N,) and the RK4 grid points after x0, each (n,) SX."""
        ca = self.ca
        defects, points = [], []
        for k in range(U.shape[1]):
            x = X[:, k]
            for _ in range(SUBSTEPS):
                k1 = self.f(x, U[:, k])
                k2 = self.f(x + h / 2 * k1, U[:, k])
                k3 = self.f(x + h / 2 * k2, U[:, k])
                k4 = self.f(x + h * k3, U[:, k])
                x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
                points.append(x)
            defects.append(x - X[:, k + 1])
        return ca.vertcat(*defects), points

    def solve(self, N: int, X0: np.ndarray, U0: np.ndarray, T0: float, free: bool) -> IpoptSolution:
        """One NLP with N samples from the guess ``X0 (N+1, n)``, ``U0 (N, m)``, ``T0``;
        ``free``: minimise T (hold T / N), else the hold is Ts and the objective zero."""
        ca, sc, c = self.ca, self.scenario, self.c
        n, m = sc.n, sc.m
        X, U = ca.SX.sym("X", n, N + 1), ca.SX.sym("U", m, N)
        T = ca.SX.sym("T") if free else ca.SX(N * sc.Ts)
        defects, points = self._grid(X, U, T / (N * SUBSTEPS))
        g, lbg, ubg = [defects], [np.zeros(n * N)], [np.zeros(n * N)]
        P = ca.horzcat(*points)  # (n, N s)
        px, py = P[sc.position_index[0], :], P[sc.position_index[1], :]
        d2 = (c.unsafe_margin + NLP_MARGIN) ** 2
        for (ax, ay), (bx, by) in self.edges:  # eq. (42) as distance-squared per edge
            ex, ey = bx - ax, by - ay
            t = ca.fmin(ca.fmax(((px - ax) * ex + (py - ay) * ey) / (ex * ex + ey * ey), 0), 1)
            g.append(((px - ax - t * ex) ** 2 + (py - ay - t * ey) ** 2).T)
            lbg.append(np.full(P.shape[1], d2))
            ubg.append(np.full(P.shape[1], np.inf))
        for i, lo, hi in zip(
            c.region_state_index, c.region_state_lower, c.region_state_upper, strict=True
        ):
            g.append(P[int(i), :].T)
            lbg.append(np.full(P.shape[1], lo + NLP_MARGIN))
            ubg.append(np.full(P.shape[1], hi - NLP_MARGIN))
        end = ca.vertcat(X[sc.position_index[0], N], X[sc.position_index[1], N])
        g.append(ca.mtimes(ca.DM(self.goal_A), end))  # eq. (41): ModGoal as A p <= b
        lbg.append(np.full(len(self.goal_b), -np.inf))
        ubg.append(self.goal_b - NLP_MARGIN)

        x_lower = np.full((n, N + 1), -np.inf)
        x_upper = np.full((n, N + 1), np.inf)
        x_lower[:, 0] = x_upper[:, 0] = self.x0
        for i, lo, hi in zip(c.goal_index, c.goal_lower, c.goal_upper, strict=True):
            x_lower[int(i), N], x_upper[int(i), N] = lo, hi
        u_lower = np.repeat(self.u_lower[:, None], N, axis=1)
        u_upper = np.repeat(self.u_upper[:, None], N, axis=1)
        parts = [ca.vec(X), ca.vec(U)] + ([T] if free else [])
        lbx = [x_lower.ravel("F"), u_lower.ravel("F")] + ([[0.5]] if free else [])
        ubx = [x_upper.ravel("F"), u_upper.ravel("F")] + ([[self.T_max]] if free else [])
        guess = [X0.T.ravel("F"), U0.T.ravel("F")] + ([[T0]] if free else [])
        nlp = {"x": ca.vertcat(*parts), "f": T if free else ca.SX(0), "g": ca.vertcat(*g)}
        solver = ca.nlpsol("minimum_time", "ipopt", nlp, IPOPT_OPTIONS)
        out = solver(
            x0=np.concatenate(guess),
            lbx=np.concatenate(lbx),
            ubx=np.concatenate(ubx),
            lbg=np.concatenate(lbg),
            ubg=np.concatenate(ubg),
        )
        z = np.asarray(out["x"]).ravel()
        stats = solver.stats()
        X_opt = z[: n * (N + 1)].reshape(N + 1, n)
        U_opt = z[n * (N + 1) : n * (N + 1) + m * N].reshape(N, m)
        T_opt = float(z[-1]) if free else N * sc.Ts
        return IpoptSolution(
            X_opt,
            U_opt,
            T_opt,
            bool(stats["success"]),
            str(stats["return_status"]),
            int(stats["iter_count"]),
        )


def _casadi_field(scenario: Scenario, x, u, known: KnownUncertainty | None = None):
    """The scenario's ``f(x, u)`` (its sympy expressions) as a CasADi SX (n,); with ``known``,
    its parametric dynamics at ``known.parameters`` plus ``known.push``."""
    import casadi as ca
    import sympy

    D = scenario.dynamics if known is None else scenario.uncertainty.parametric
    functions = {
        "sin": ca.sin,
        "cos": ca.cos,
        "tan": ca.tan,
        "exp": ca.exp,
        "log": ca.log,
        "sqrt": ca.sqrt,
        "tanh": ca.tanh,
        "atan": ca.atan,
        "atan2": ca.atan2,
        "Abs": ca.fabs,
    }
    f = sympy.lambdify([*D.state_symbols, *D.input_symbols], list(D.expressions), [functions])
    if known is None:
        return ca.vertcat(*f(*ca.vertsplit(x), *ca.vertsplit(u)))
    field = ca.vertcat(*f(*ca.vertsplit(x), *ca.vertsplit(u), *known.parameters.tolist()))
    return field + ca.DM(known.push)


def _edges(polygons) -> np.ndarray:
    """Boundary segments (E, 2, 2) of polygons (exterior and holes)."""
    segments = []
    for polygon in polygons:
        for ring in [polygon.exterior, *polygon.interiors]:
            xy = np.asarray(ring.coords)
            segments += [(xy[i], xy[i + 1]) for i in range(len(xy) - 1)]
    return np.array(segments, dtype=np.float64)


def _halfspaces(polygon) -> tuple[np.ndarray, np.ndarray]:
    """``A (k, 2), b (k,)`` with ``polygon = {p : A p <= b}``; ``polygon`` must be convex."""
    from shapely.geometry.polygon import orient

    if polygon.geom_type != "Polygon" or polygon.convex_hull.area - polygon.area > 1e-9:
        raise ValueError(
            f"ModGoal must be one convex polygon for the IPOPT benchmark, got {polygon.wkt[:60]}"
        )
    xy = np.asarray(orient(polygon, 1.0).exterior.coords)  # counter-clockwise
    edge = np.diff(xy, axis=0)
    A = np.stack([edge[:, 1], -edge[:, 0]], axis=1)  # outward normals
    A /= np.linalg.norm(A, axis=1, keepdims=True)
    return A, np.einsum("ij,ij->i", A, xy[:-1])


def _retime(
    scenario: Scenario, X: np.ndarray, U: np.ndarray, T: float, N: int, T_new: float
) -> tuple[np.ndarray, np.ndarray]:
    """``X (M+1, n)``, ``U (M, m)`` over T, played over ``T_new`` with N samples."""
    tau_old, tau_new = np.linspace(0, 1, len(X)), np.linspace(0, 1, N + 1)
    X_new = np.stack([np.interp(tau_new, tau_old, column) for column in X.T], axis=-1)
    X_new[:, list(scenario.dynamics.rate_states)] *= T / T_new
    return X_new, reseed(U, N, "compress")


def ipopt_minimum_time(scenario: Scenario, demo: int, constraints: Constraints) -> IpoptMinimumTime:
    """Phases 1 and 2 of the module docstring for demo number ``demo``."""
    start = time.perf_counter()
    d, Ts = scenario.demos[demo], scenario.Ts
    T_demo = d.us.shape[0] * Ts
    nlp = MinimumTimeNLP(scenario, d.x0, constraints, T_max=T_demo)
    xs = simulate(scenario.dynamics, d.x0, d.us, Ts).xs
    N = max(2, round(d.us.shape[0] / COMPRESSION))
    X, U = _retime(scenario, xs, d.us, T_demo, N, T_demo / COMPRESSION)
    free = nlp.solve(N, X, U, T_demo / COMPRESSION, free=True)
    nlps, iterations = 1, free.iterations

    def outcome(N: int, U: np.ndarray | None, message: str) -> IpoptMinimumTime:
        seconds = time.perf_counter() - start
        return IpoptMinimumTime(free.T, N, U, nlps, iterations, seconds, message)

    if not free.success:
        return outcome(0, None, f"phase 1: {free.status}")
    N_quantised = math.ceil(free.T / Ts - 1e-9)
    for N_try in range(N_quantised, N_quantised + EXTRA_SAMPLES):
        X_try, U_try = _retime(scenario, free.X, free.U, free.T, N_try, N_try * Ts)
        fixed = nlp.solve(N_try, X_try, U_try, N_try * Ts, free=False)
        nlps, iterations = nlps + 1, iterations + fixed.iterations
        if fixed.success:
            return outcome(N_try, fixed.U, "solved")
    return outcome(0, None, f"no feasible N' in {N_quantised}..{N_try}")


def _ipopt_check(
    scenario: Scenario, problem: Problem, ipopt: IpoptMinimumTime, region: dict
) -> str:
    """Our cost ``J`` of IPOPT's input (0: feasible for our method too) and ``verify_nominal``."""
    if ipopt.U is None:
        return f"IPOPT FAILED ({ipopt.message})"
    J = problem.with_horizon(ipopt.N, ipopt.U).cost(ipopt.U)
    verification = verify_nominal(
        scenario,
        problem.x0,
        ipopt.U,
        input_lower=problem.input_lower,
        input_upper=problem.input_upper,
        region=region,
    )
    verdict = "verified" if verification.passed else f"VERIFY FAILED: {verification.message}"
    return f"J = {J:.1e}, {verdict}"


def run() -> None:
    scenario = load_scenario("quadrotor_hill_flythrough")
    Ts = scenario.Ts
    feedback = design_feedback(scenario)
    r_d = feedback.required_radius(scenario.clearance)
    margins = ConstraintMargins.of_tube(feedback.certified_tube, r_d)
    options = {m: OptimizeOptions(method=m) for m in ("gd", "lbfgs")}
    eps = options["gd"]
    region_margin = {  # as optimize_demo shrinks the region
        name: extent + (eps.eps_r if name in scenario.state_names else 0.0)
        for name, extent in margins.region_margin.items()
    }
    verify_region = {  # as optimize_demo verifies
        name: (lo + margins.region_margin.get(name, 0.0), hi - margins.region_margin.get(name, 0.0))
        for name, (lo, hi) in scenario.operating_region.items()
    }
    try:
        import casadi
    except ImportError:
        casadi = None
    for option in options.values():  # load the numba kernels outside the timings
        optimize_demo(scenario, 0, margins, option)
    print(
        f"quadrotor_hill_flythrough, {len(scenario.demos)} demos, Ts = {Ts:g} s,"
        f" RK4 {SUBSTEPS} substeps;"
        f" d' = {scenario.clearance + eps.eps_d:g}, ModGoal = Goal shrunk by"
        f" {scenario.clearance + eps.eps_g:g}, input margin"
        f" {np.round(margins.input_margin, 3).tolist()}"
    )
    if casadi is None:
        print(
            "casadi is not installed: skipping the IPOPT comparison"
            " (pip install '.[bench]' to run it); our results only"
        )
    else:
        print(f"CasADi {casadi.__version__} + IPOPT (MUMPS), direct multiple shooting")
    header = f"{'demo':<8} {'T_demo':>6} {'T_gd':>5} {'T_lbfgs':>7}"
    if casadi is not None:
        header += (
            f" {'T*_free':>7} {'T_ipopt':>7} {'gd/ip':>6} {'lb/ip':>6} {'t_gd':>6} {'t_lbfgs':>7}"
            f" {'t_ipopt':>7} {'NLPs':>4} {'iters':>5} {'tgd/ip':>6} {'tlb/ip':>6}"
            f" {'T_unc':>5} {'cert/unc':>8}  IPOPT solution"
        )
    print(header)
    rows: list[tuple[dict[str, tuple[float, float]], float, float]] = []
    certified = scenario.optimizer  # the synthesized run's method
    uncertified = uncertified_constraints(scenario)
    costs: list[float] = []
    for i, demo in enumerate(scenario.demos):
        ours = {}
        for method, option in options.items():
            start = time.perf_counter()
            result = optimize_demo(scenario, i, margins, option)
            T = result.N * Ts if result.success else np.nan
            ours[method] = (T, time.perf_counter() - start)
        T_demo = demo.us.shape[0] * Ts
        line = f"{demo.name:<8} {T_demo:>6.1f} {ours['gd'][0]:>5.1f} {ours['lbfgs'][0]:>7.1f}"
        if casadi is None:
            print(f"{line}  wall time gd {ours['gd'][1]:.2f} s, lbfgs {ours['lbfgs'][1]:.2f} s")
            continue
        problem = make_problem(
            scenario,
            demo=i,
            input_margin=margins.input_margin,
            region_margin=region_margin,
            eps_d=eps.eps_d,
            eps_g=eps.eps_g,
            eps_i=eps.eps_i,
        )
        ipopt = ipopt_minimum_time(scenario, i, problem.constraints)
        check = _ipopt_check(scenario, problem, ipopt, verify_region)
        T_ip = ipopt.N * Ts if ipopt.U is not None else np.nan
        rows.append((ours, T_ip, ipopt.seconds))
        free = ipopt_minimum_time(scenario, i, uncertified)
        T_unc = free.N * Ts if free.U is not None else np.nan
        costs.append(ours[certified][0] / T_unc)
        print(
            f"{line} {ipopt.T_free:>7.2f} {T_ip:>7.1f} {ours['gd'][0] / T_ip:>6.2f}"
            f" {ours['lbfgs'][0] / T_ip:>6.2f} {ours['gd'][1]:>6.2f} {ours['lbfgs'][1]:>7.2f}"
            f" {ipopt.seconds:>7.2f} {ipopt.nlps:>4} {ipopt.iterations:>5}"
            f" {ours['gd'][1] / ipopt.seconds:>6.2f} {ours['lbfgs'][1] / ipopt.seconds:>6.2f}"
            f" {T_unc:>5.1f} {costs[-1]:>8.2f}  {check}"
            + ("" if free.U is not None else f"; uncertified IPOPT FAILED ({free.message})")
        )
    if rows:
        _summary(rows)
        print(
            f"  (issue 16) T_certified / T_uncertified ({certified}, constant certificate):"
            f" {np.nanmin(costs):.2f}-{np.nanmax(costs):.2f}, median {np.nanmedian(costs):.2f};"
            " T_unc: IPOPT with no tube, clearance d, Goal, full input bounds, state_bounds"
            f" {dict(scenario.state_bounds)}"
        )


def _summary(rows: list[tuple[dict[str, tuple[float, float]], float, float]]) -> None:
    """Targets of issue 5, from per-demo ``(ours: method -> (T, seconds), T_ipopt, seconds)``."""
    print(
        "(T in s, nan: no verified result; t_* wall times in s; T*_free: IPOPT's free-final-time"
        " optimum with hold T*/N before quantising to Ts)"
    )
    ipopt_seconds = sum(r[2] for r in rows)
    for method, label in [("gd", "gradient descent"), ("lbfgs", "L-BFGS")]:
        ratios = np.array([r[0][method][0] / r[1] for r in rows])
        seconds = sum(r[0][method][1] for r in rows)
        met = int(np.sum(ratios <= 1.05))
        print(
            f"  [{'met' if met == len(rows) else 'MISSED'}] T_ours/T_ipopt <= 1.05 ({label}):"
            f" {met} of {len(rows)} demos; median {np.nanmedian(ratios):.2f},"
            f" worst {np.nanmax(ratios):.2f}, {int(np.sum(np.isnan(ratios)))} without a result"
        )
        time_line = (
            f"{label} wall time / IPOPT's: {seconds / ipopt_seconds:.2f} over all demos"
            f" ({seconds:.1f} s vs {ipopt_seconds:.1f} s)"
        )
        if method == "lbfgs":
            ok = seconds <= 3 * ipopt_seconds
            print(f"  [{'met' if ok else 'MISSED'}] within 3x: {time_line}")
        else:
            print(f"  (no target) {time_line}")
