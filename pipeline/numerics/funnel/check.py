"""The funnel result and its independent check (``synthesis``'s (F1)-(F3), E1-E3).

``check_funnel`` re-verifies a funnel with numpy alone, independently of the solver that built it:
positive definite metrics, the vertex inequalities (F3) at both ends of every interval, the
nominal's enclosure (E1), the tube inside every hull box, and the level within every constraint
(``funnel.bounds.funnel_limits``). A funnel that fails it is rejected. Given the shipped law's
offset (``funnel.law``: the law tracks an interpolated reference) it checks the funnel under that
law: (F3)'s eigenvalue plus the offset's term (I2), and the inputs with their offset (I3).

Margins: the eigenvalue must be below ``-LMI_MARGIN``, the level at most ``1 - LEVEL_MARGIN``
of every limit (``funnel.law``), so that rounding cannot decide a bound.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import Trajectory
from pipeline.numerics.funnel.bounds import Enclosure, funnel_limits, rate_bound, substeps
from pipeline.numerics.funnel.law import LEVEL_MARGIN, LMI_MARGIN, LawOffset
from pipeline.numerics.funnel.robust import RobustCheck

LEVEL_SLACK = 1e-4  # rho is shrunk by this relative amount so that no bound holds with equality
# (1e-9 was too little: certify rebuilds the enclosure from the file, and its limits may be lower
# by ~1e-5 relative)
INTERPOLATION = "Q = P^-1 linear in t on each sample interval"


@dataclass(frozen=True, kw_only=True)
class HeldDesign:
    """What a held (or measured) law's funnel was designed again for (``stages.funnel``): the
    additive bound ``disturbance (n,)`` (the declared one plus the law's box), the input bounds
    ``(m,)`` kept clear of the law's input offset, the period ``h`` (0: (I6)'s box alone), the
    sample intervals whose pieces got (I6')'s rows (``synthesize_funnel``'s ``pushed``; None:
    every piece) and the multiplier its search starts at (in ``Funnel.held``: the one that
    designed that funnel). A re-optimize round with the held law's funnels (``stages.
    certificates.rounds.held_funnels``' own rounds) designs the funnel around the next, nearby
    nominal of the same trajectory with it first (a design choice: the funnel is checked as
    any other, and may differ from the one the search would find)."""

    disturbance: FloatArray
    input_lower: FloatArray
    input_upper: FloatArray
    period: float
    pushed: tuple[int, ...] | None
    from_multiplier: float


@dataclass(frozen=True, kw_only=True)
class EarlierDesign:
    """How an earlier re-optimize round designed a trajectory's kept funnel, tried first around
    its next, nearby nominal (``stages.funnel``; every funnel is checked as any other, but the
    first try is kept when it passes, and may differ from the funnel a full search would find):
    ``codesigned``, its gains were co-designed with the metric (F6)
    (``synthesize_funnel``'s ``codesign_first``); ``held``, a held law's redesign
    (``Funnel.held``; None: none)."""

    codesigned: bool = False
    held: HeldDesign | None = None

    @classmethod
    def of(cls, funnel: Funnel) -> EarlierDesign:
        """The record of ``funnel``'s design."""
        return cls(codesigned=funnel.codesigned, held=funnel.held)


@dataclass(frozen=True, kw_only=True)
class Funnel:
    """A certified (or rejected) funnel around one trajectory of N sample intervals.

    Attributes:
      K: (N, m, n) gain held on ``[t_k, t_k+1)``.
      P: (N+1, n, n) metric at ``t_k``; between samples ``P^-1`` is linear in t (INTERPOLATION).
      rho: funnel level: ``E(t) = {x : (x - x_ref)^T P(t) (x - x_ref) <= rho^2}``.
      rate: lambda (1/s) in (F2): ``V(t) <= exp(-2 lambda t) V(0)``.
      margins: (N, 2) largest eigenvalue of ``Q^-1/2 L Q^-1/2`` (F2) over the vertices at each
        interval's start and end (< 0 for a certificate).
      boxes: (N, 2, d) the hull's box per interval over ``variables`` (d names).
      vertices: N arrays (V_k, n, n+m) of hull vertices ``[A_v B_v]``.
      enclosure: the nominal's sound enclosure (``funnel.bounds.Enclosure``); None if the hulls
        failed before it was found.
      limits: constraint -> largest level it allows; ``design`` is the level at which the LMI
        program's caps (hull boxes, Unsafe, Goal, bounds) hold, ``sqrt(tau)`` (funnel.lmi): 1
        unless the required initial set could not be held whole.
      binding: the constraint that sets rho; seconds: synthesis wall time (from the funnel
        stage: its whole task, the certify-style checks and any redesign included).
      multiplier: the S-procedure multiplier ``alpha`` of the program that designed it
        (``funnel.robust`` (I5)); 0 without a disturbance. The design's record only: the
        checks search their own.
      codesigned: its gains were designed with its metric (``funnel.synthesis`` (F6)), not the
        LQR gains; the design's record too.
      held: for a held or measured law's funnel designed again for the law's box
        (``stages.funnel``), what that design was asked (None: the first design was kept); the
        design's record too.
    """

    K: FloatArray
    P: FloatArray
    rho: float
    rate: float
    margins: FloatArray = field(repr=False)
    boxes: FloatArray = field(repr=False)
    variables: tuple[str, ...]
    vertices: tuple[FloatArray, ...] = field(repr=False)
    enclosure: Enclosure | None = field(repr=False)
    limits: Mapping[str, float] = field(repr=False)
    binding: str
    seconds: float
    success: bool
    message: str
    interpolation: str = INTERPOLATION
    multiplier: float = 0.0
    codesigned: bool = False
    held: HeldDesign | None = None

    @property
    def Q(self) -> FloatArray:
        """(N+1, n, n) ``P^-1`` at the sample times."""
        return np.linalg.inv(self.P).astype(np.float64, copy=False)


def certificate_margins(
    Q: FloatArray, K: FloatArray, vertices: tuple[FloatArray, ...], rate: float, Ts: float
) -> FloatArray:
    """(N, 2) largest eigenvalue of ``Lc^-1 L(s, J_v) Lc^-T`` (``Q(s) = Lc Lc^T``) over the
    vertices at ``s = 0, 1`` of each interval, by numpy alone; ``Q (N+1, n, n)``."""
    n, N = Q.shape[1], len(K)
    margins = np.empty((N, 2))
    for k in range(N):
        D = (Q[k + 1] - Q[k]) / Ts  # eq. (F1)
        Acl = vertices[k][:, :, :n] + vertices[k][:, :, n:] @ K[k]  # (V, n, n)
        for e, Qe in enumerate((Q[k], Q[k + 1])):
            M = -D + Acl @ Qe + Qe @ np.swapaxes(Acl, 1, 2) + 2 * rate * Qe  # eq. (F2)
            L_inv = np.linalg.inv(np.linalg.cholesky(Qe))
            M = L_inv @ M @ L_inv.T
            margins[k, e] = np.linalg.eigvalsh((M + np.swapaxes(M, 1, 2)) / 2).max()
    return margins


def effective_margins(
    Q: FloatArray, K: FloatArray, funnel: Funnel, Ts: float, law: LawOffset
) -> FloatArray:
    """(N,) what must stay below ``-LMI_MARGIN`` on each interval under the shipped law: (F2)'s
    largest eigenvalue plus the interpolated reference's term (I2); under a disturbance, twice
    (I5)'s S-procedure eigenvalue ``r_k`` plus (I2) (``funnel.robust``). A held law: the smaller
    on each interval of (I6) (the hold's box joined to the disturbance's) and (I6') (its push to
    first order in (I5)'s matrix, the remainder's box joined, ``funnel.sampled``): both bound the
    same rate on interval ``k`` under the same hull and input box, so either one's bound below
    zero there is the invariance argument's step on that interval. ``Q (N+1, n, n)``."""
    if not law.disturbed:
        margins = certificate_margins(Q, K, funnel.vertices, funnel.rate, Ts).max(axis=1)
        return margins + law.lmi_term
    check = RobustCheck(Q, K, funnel.vertices, funnel.rate, Ts, funnel.rho)
    boxed = 2 * check.margins(law.box)[0] + law.lmi_term  # (I5), with (I6)'s box if held
    if law.sampled_box is None:
        return boxed
    sampled = RobustCheck(Q, K, funnel.vertices, funnel.rate, Ts, funnel.rho, law.period)
    # refine the multiplier only where neither passes yet (funnel.robust's margins)
    needed = np.where(boxed < -LMI_MARGIN, np.inf, (-LMI_MARGIN - law.lmi_term) / 2)
    r = sampled.margins(law.sampled_box, needed=needed)[0]
    return np.minimum(boxed, 2 * r + law.lmi_term)  # (I6')


def check_funnel(
    scenario: Scenario,
    trajectory: Trajectory,
    funnel: Funnel,
    state_bounds: Mapping[str, tuple[float, float]],
    law: LawOffset | None = None,
) -> str | None:
    """Re-verify ``funnel`` with numpy alone; ``None`` if it holds, else what fails
    (``checked_margins`` below, without its margins)."""
    return checked_margins(scenario, trajectory, funnel, state_bounds, law)[0]


def checked_margins(
    scenario: Scenario,
    trajectory: Trajectory,
    funnel: Funnel,
    state_bounds: Mapping[str, tuple[float, float]],
    law: LawOffset | None = None,
) -> tuple[str | None, FloatArray | None]:
    """``(failure, margins)``: ``None`` if ``funnel`` holds, else what fails, and the (N,)
    ``effective_margins`` the check computed (None when it stopped before them: a ``P`` that is
    not a metric), so that a caller reporting them does not evaluate (I5) twice.

    Checks: every ``P[k]`` symmetric positive definite; (F3) at every vertex and both ends of
    every interval, plus the law's term (I2) when ``law`` is given, below ``-LMI_MARGIN``; the a
    priori enclosure (E1: ``F h < pad`` with ``F`` recomputed from the stored vertices) and its
    box inside the hull box; the tube at level rho (inputs widened by the law's offset (I3))
    inside every hull box; rho within ``1 - LEVEL_MARGIN`` of every constraint's limit
    (funnel.bounds (a)-(d))."""
    P, K, rho, Ts = funnel.P, funnel.K, funnel.rho, scenario.Ts
    N, n = len(K), scenario.n
    law = LawOffset.none(N, n, scenario.m, Ts) if law is None else law
    if P.shape != (N + 1, n, n) or K.shape != (N, scenario.m, n):
        return (
            f"shapes P {P.shape}, K {K.shape} do not fit N = {N}, n = {n}, m = {scenario.m}",
            None,
        )
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(K)) and np.isfinite(rho)):
        return "non-finite P, K or rho", None
    if np.abs(P - np.swapaxes(P, 1, 2)).max() > 1e-9 * np.abs(P).max():
        return "P is not symmetric", None
    lowest = np.linalg.eigvalsh(P)[:, 0]
    if lowest.min() <= 0:
        return f"P[{int(np.argmin(lowest))}] is not positive definite ({lowest.min():.3g})", None
    Q = np.linalg.inv(P)
    Q = (Q + np.swapaxes(Q, 1, 2)) / 2
    effective = effective_margins(Q, K, funnel, Ts, law)  # funnel.law (I2), funnel.robust (I5)
    if effective.max() >= -LMI_MARGIN:
        k = int(np.argmax(effective))
        eigenvalue = effective[k] - law.lmi_term[k]
        box = np.asarray(law.box)
        term = {
            (True, False): "the hold's term (I6)",
            (False, True): "the measurement's term (I7)",
            (True, True): "the hold's and the measurement's term (I6, I7)",
        }.get((law.period > 0, law.measurement is not None))
        held = (
            "" if law.hold is None else f" and {term} |w_h| <= {np.round(law.hold[k], 4).tolist()}"
        )
        if law.remainder is not None:  # funnel.sampled (I6'): the smaller of the two is shown
            held += (
                f" (or the push to first order (I6') with its remainder |w_r| <= "
                f"{np.round(law.remainder[k], 4).tolist()}: the smaller)"
            )
        what = (
            f"under the disturbance |w| <= {np.round(law.disturbance, 4).tolist()}{held}, twice "
            "the S-procedure's eigenvalue (I5)"
            if law.disturbed
            else "eigenvalue"
        )
        failure = (
            f"(F2) fails on interval {k} (t = {Ts * k:.2f}-{Ts * (k + 1):.2f} s): {what} "
            f"{eigenvalue:.3g} + the interpolated reference's term {law.lmi_term[k]:.3g} is not "
            f"below -{LMI_MARGIN:g}"
        )
        if law.hold is not None and box.ndim == 2:
            check = RobustCheck(Q, K, funnel.vertices, funnel.rate, Ts, funnel.rho)
            alone = 2 * check.margins(law.disturbance, np.arange(len(K)) == k)[0][k]  # k alone
            boxed_out = alone < -LMI_MARGIN and not eigenvalue < -LMI_MARGIN  # the box's doing
            if boxed_out and law.measurement is None:
                failure += (
                    f" (without the hold {alone:.3g}): the funnel is not certifiable with the "
                    f"law held every {law.period:g} s, on any reference grid (a shorter "
                    "--feedback-period, or continuous feedback)"
                )
            elif boxed_out and law.measurement is not None:
                failure += (
                    f" (without the law's box {alone:.3g}): the funnel does not hold the "
                    f"measurement error |eta| <= {np.round(law.measurement, 4).tolist()}, on "
                    "any reference grid"
                )
        return failure, effective
    h = Ts / substeps(trajectory)
    enclosure = funnel.enclosure
    if enclosure is None:
        return "no enclosure of the nominal (the funnel's hulls failed)", effective
    s_ext = np.sqrt(
        np.maximum(np.diagonal(Q, axis1=1, axis2=2)[:-1], np.diagonal(Q, axis1=1, axis2=2)[1:])
    )
    for k in range(N):
        box = enclosure.box[k]
        pad = np.minimum(enclosure.grid_range[k, 0] - box[0], box[1] - enclosure.grid_range[k, 1])
        F = rate_bound(scenario.dynamics, trajectory, k, box, funnel.vertices[k][:, :, :n])
        if not (np.all(F * h < pad) and np.all(F <= enclosure.rate_bound[k])):
            return f"the nominal's enclosure (E1) fails on interval {k}", effective
        for d, name in enumerate(funnel.variables):
            lo, hi = funnel.boxes[k, :, d]
            if name in scenario.input_names:
                j = scenario.input_names.index(name)
                g = rho * np.sqrt(max(K[k, j] @ Q[e] @ K[k, j] for e in (k, k + 1)))
                g += law.input_offset[k, j]  # funnel.law (I3)
                inner = (trajectory.us[k, j] - g, trajectory.us[k, j] + g)
            else:
                i = scenario.state_names.index(name)
                inner = (
                    enclosure.range[k, 0, i] - rho * s_ext[k, i],
                    enclosure.range[k, 1, i] + rho * s_ext[k, i],
                )
                if not (lo <= box[0, i] and box[1, i] <= hi):
                    return (
                        f"the enclosure leaves the hull box of '{name}' on interval {k}",
                        effective,
                    )
            if not (lo <= inner[0] and inner[1] <= hi):
                return f"the tube leaves the hull box of '{name}' on interval {k}", effective
    limits = funnel_limits(scenario, trajectory, Q, K, enclosure, state_bounds, law.input_offset)
    name = min(limits, key=lambda key: limits[key][0])
    if rho > (1 - LEVEL_MARGIN) * limits[name][0]:
        return (
            f"rho {rho:.6g} exceeds the limit {limits[name][0]:.6g} of {name} less its margin "
            f"({LEVEL_MARGIN:g}, relative)"
        ), effective
    return None, effective
