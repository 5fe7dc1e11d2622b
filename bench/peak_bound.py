"""How far a shipped funnel's flights actually move under the uncertainty, against what a quadratic
certificate of the same bound needs (issue 29: where the robust funnel's size goes).

Along each shipped nominal, with its shipped gains ``K(t)``, the closed loop linearised about the
nominal is ``e' = Acl(t) e + F_p(t) dp + w(t)``, ``Acl = f_x + f_u K``, ``F_p = df/dp`` (the
parametric dynamics' Jacobian in the parameters, ``scenario.uncertainty.parametric``). From
``e(0) = 0`` the position error at ``t_f`` is ``c^T e(t_f) = int_0^t_f lambda(s)^T (F_p dp + w)
ds`` with the adjoint ``lambda' = -Acl^T lambda``, ``lambda(t_f) = c`` (``c`` selecting X or
Y). Its largest value over the declared sets, exact for the linear model:

  constant:  the parameters constant, anywhere in their box, no gust:
             ``sum_j |int lambda^T F_p,j ds| |dp_j|``;
  signal:    the parameters' effect taken as an arbitrary signal in its own box along the
             nominal (``b_p = |F_p| |dp|``), as the additive bound (U1) takes it:
             ``int |lambda|^T b_p ds``;
  gust:      the declared disturbance box alone: ``int |lambda|^T d ds``;

each maximised over ``t_f`` at the sample times. Beside them, the position half-extent of the
frozen-time invariant ellipsoid of ``Acl(t_k)`` for the box ``b_p + d`` (``funnel.robust.
invariant_ellipsoid``, Boyd et al. section 6.1.3, least position extent; the largest over the
samples): about what an invariant quadratic form must hold for that box; and the shipped funnel's
own half-extent at ``T`` (its level times ``sqrt((P(T)^-1)_ii)``, the start's cell of Init
included). A linear estimate, not a certificate: it says how much of a robust funnel's size is
the quadratic form's, and how much the flight's.

Run: ``python -m bench.peak_bound SCENARIO CONTROLLER_JSON [SCALE ...]`` (default scales 1 and
issue 29's bound where ``ASKED`` has it, else 1), e.g. ``python -m bench.peak_bound quadrotor_hill
reports/quadrotor_hill/controller.json``. About a second per demo.
"""

from __future__ import annotations

import sys

import numpy as np

from bench.bench_known_floor import ASKED
from pipeline.controller import ReferenceTrajectory, load
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario, load_scenario
from pipeline.numerics.funnel.robust import invariant_ellipsoid

SUBSTEPS = 20  # adjoint steps per sample


def _linearised(
    scenario: Scenario, reference: ReferenceTrajectory
) -> tuple[FloatArray, FloatArray, float]:
    """``(Acl (M, n, n), F_p (M, n, q), h)`` on a grid of ``SUBSTEPS`` per sample, held on each
    step: the shipped gains about the reference interpolated, at the nominal parameters."""
    uncertainty = scenario.uncertainty
    if uncertainty.parametric is None:
        raise ValueError(f"{scenario.name} declares no uncertain parameters")
    N, h = len(reference.K), scenario.Ts / SUBSTEPS
    t = np.arange(N * SUBSTEPS) * h
    x = np.stack([np.interp(t, reference.t, reference.x_ref[:, j]) for j in range(scenario.n)], -1)
    k = np.minimum((t / scenario.Ts).astype(int), N - 1)
    u = reference.u_ref[k]
    A, B = scenario.dynamics.f_x(x, u), scenario.dynamics.f_u(x, u)
    p0 = np.broadcast_to(uncertainty.parameter_nominal, (len(t), len(uncertainty.parameter_names)))
    F_p = uncertainty.parametric.f_u(x, np.concatenate([u, p0], axis=1))[:, :, scenario.m :]
    return A + B @ reference.K[k], F_p, h


def adjoint_peaks(
    Acl: FloatArray,
    F_p: FloatArray,
    h: float,
    dp: FloatArray,
    gust: FloatArray,
    outputs: tuple[int, ...],
    every: int,
) -> dict[str, FloatArray]:
    """Name -> ``(len(outputs),)``: the largest ``|e_i(t_f)|`` of the module docstring
    ("constant", "signal", "gust") over ``t_f`` at every ``every``-th step, for ``e' = Acl e +
    F_p dp + w`` from ``e(0) = 0`` with ``Acl (M, n, n)``, ``F_p (M, n, q)`` held on steps of
    ``h``, the parameters' half-widths ``dp (q,)`` and the gust box ``gust (n,)``, for each state
    ``i`` of ``outputs``."""
    b_p = np.abs(F_p) @ dp  # (M, n)
    found = {name: np.zeros(len(outputs)) for name in ("constant", "signal", "gust")}
    for f in range(every, len(Acl) + 1, every):
        for o, i in enumerate(outputs):
            lam = np.zeros((f + 1, Acl.shape[1]))
            lam[f, i] = 1.0
            for s in range(f - 1, -1, -1):  # lambda' = -Acl^T lambda backwards (Heun)
                k1 = Acl[s].T @ lam[s + 1]
                lam[s] = lam[s + 1] + h * (k1 + Acl[s].T @ (lam[s + 1] + h * k1)) / 2
            L = np.abs(lam[:f])
            values = {
                "constant": np.abs(np.einsum("si,sij->j", lam[:f], F_p[:f]) * h) @ dp,
                "signal": float((L * b_p[:f]).sum() * h),
                "gust": float((L @ gust).sum() * h),
            }
            for name, value in values.items():
                found[name][o] = max(found[name][o], value)
    return found


def peaks(
    scenario: Scenario, reference: ReferenceTrajectory, dp: FloatArray, gust: FloatArray
) -> dict[str, FloatArray]:
    """Name -> ``(2,)`` the largest X and Y deviation of the module docstring (``adjoint_peaks``'
    "constant", "signal", "gust"), the frozen invariant ellipsoid's ("quadratic") and the
    shipped funnel's half-extent at ``T`` ("funnel at T"), for the parameters' half-widths ``dp
    (q,)`` and the gust box ``gust (n,)``."""
    Acl, F_p, h = _linearised(scenario, reference)
    position = tuple(scenario.position_index)
    found = adjoint_peaks(Acl, F_p, h, dp, gust, position, SUBSTEPS)
    b_p = np.abs(F_p) @ dp  # (M, n)
    weight = np.zeros((scenario.n, scenario.n))
    weight[position, position] = 1.0
    extents = [
        np.sqrt(np.diag(Q)[list(position)])
        for s in range(0, len(Acl), SUBSTEPS)
        if (Q := invariant_ellipsoid(Acl[s], b_p[s] + gust, weight)) is not None
    ]
    found["quadratic"] = np.max(extents, axis=0) if extents else np.full(2, np.inf)
    Q_T = np.linalg.inv(reference.P[-1])
    found["funnel at T"] = reference.radius * np.sqrt(np.diag(Q_T)[list(position)])
    return found


def run_for(name: str, path: str, bounds: dict[str, tuple[FloatArray, FloatArray]]) -> None:
    """The table of the module docstring for the funnels of ``path``, one row per demo and bound
    (label -> parameters' half-widths ``(q,)``, gust box ``(n,)``)."""
    scenario = load_scenario(name, check_demos=False)
    controller = load(path)
    print(
        f"{name} ({path}): largest X / Y deviation (m), linearised about each shipped nominal\n"
        f"{'bound':<10} {'demo':<8} {'constant':>13} {'signal':>13} {'gust':>13} "
        f"{'quadratic':>13} {'funnel at T':>13}"
    )
    for label, (dp, gust) in bounds.items():
        for reference in controller.trajectories:
            found = peaks(scenario, reference, dp, gust)
            cells = " ".join(f"{v[0]:>6.3f}/{v[1]:<6.3f}" for v in found.values())
            print(f"{label:<10} {reference.name or '':<8} {cells}", flush=True)


def _half_widths(lower: FloatArray, upper: FloatArray, nominal: FloatArray) -> FloatArray:
    """``(q,)`` each interval's half-width about its nominal value (the larger side)."""
    return np.maximum(np.asarray(upper) - nominal, nominal - np.asarray(lower))


def _declared(scenario: Scenario, scale: float) -> tuple[FloatArray, FloatArray]:
    """``scale`` times the declaration: the parameters' half-widths ``(q,)`` and the
    disturbance box ``(n,)``."""
    u = scenario.uncertainty
    half = _half_widths(u.parameter_lower, u.parameter_upper, u.parameter_nominal)
    return scale * half, scale * np.asarray(u.disturbance)


def main(argv: list[str]) -> int:
    if len(argv) < 2:
        print(__doc__.split("Run: ")[1].split(". About")[0], file=sys.stderr)
        return 2
    name, path, *scales = argv
    scenario = load_scenario(name, check_demos=False)
    if scenario.uncertainty.parametric is None:
        print(f"{name} declares no uncertain parameters: nothing to compare", file=sys.stderr)
        return 2
    try:
        multiples = [float(s) for s in scales or ["1"]]
    except ValueError:
        print(f"SCALE must be numbers, got {scales}", file=sys.stderr)
        return 2
    bounds = {f"{s:g}x": _declared(scenario, s) for s in multiples}
    if not scales and name in ASKED:
        parameters, disturbance = ASKED[name]
        names = scenario.uncertainty.parameter_names
        lower, upper = np.array([parameters[p] for p in names]).T
        half = _half_widths(lower, upper, scenario.uncertainty.parameter_nominal)
        gust = np.array([disturbance.get(s, 0.0) for s in scenario.state_names])
        bounds["issue 29"] = (half, gust)
    run_for(name, path, bounds)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
