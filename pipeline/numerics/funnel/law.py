"""The law as shipped inside the funnel certificate: the reference it tracks is interpolated.

Problem. The funnel ``E(t) = {x : e^T P(t) e <= rho_t^2}``, ``e = x - x_ref(t)``, ``rho_t = rho
e^{-lambda t}``, is certified about the exact nominal ``x_ref`` (the solution of ``xdot = f(x,
u_ref[k])``; its RK4 values on a grid are taken as exact, as everywhere in the pipeline). The
shipped law (``pipeline.controller``) tracks ``xhat``, the linear interpolation of ``x_ref`` on the
file's grid, with ``h_k`` the grid's spacing on sample interval ``k``:

    u = u_ref[k] + K[k] (x - xhat) = u_ref[k] + K[k] e + K[k] delta,  delta = x_ref - xhat.

(I1) Interpolation error. On a grid step inside interval ``k`` the input is held, so ``x_ref`` is
C^2 with ``xddot = f_x(x_ref, u_ref[k]) xdot``. While ``x_ref`` is in the a priori box ``B_k``,
``|xdot| <= F`` (E1 of ``funnel.bounds``) and ``f_x`` is in the hull ``conv{A_v}`` over ``Z_k``
(which holds ``B_k x {u_ref[k]}``), so by convexity ``|xddot_i| <= max_v sum_l |A_v[i, l]| F_l``.
Linear interpolation of a C^2 function between two points ``h`` apart errs by at most ``h^2 / 8
max |xddot|``:

    |delta_i(t)| <= Delta_i[k] = h_k^2 / 8  max_v sum_l |A_v[i, l]| F_l   on interval k.     (I1)

(I2) Invariance with the offset. ``de/dt = f(x_ref + e, u_ref + K e + K delta) - f(x_ref, u_ref) =
Acl e + Bbar K delta`` with ``[Abar Bbar]`` the Jacobian averaged on the segment, in the hull while
``x`` is in the funnel and the input in the widened box (I3). With ``m_k`` the largest (F2)
eigenvalue of ``Q^-1/2 L Q^-1/2`` over the vertices at both ends of the interval
(``funnel.check.certificate_margins``; ``L <= m_k Q`` at both ends gives it on the whole interval,
as (F3) does), ``P L P <= m_k P`` and

    d/dt (V e^{2 lambda t}) e^{-2 lambda t} = e^T P L P e + 2 e^T P Bbar K delta
                                            <= m_k V + 2 ||e||_P ||Bbar K delta||_P.

On the boundary ``V = rho_t^2`` this is ``rho_t (m_k rho_t + 2 w_k)`` with ``w_k`` the largest
``||Bbar K delta||_P(t)`` on the interval. ``||Bbar K delta||_P(t)`` is convex in ``Bbar`` and in
``delta`` separately and convex in ``t`` (the matrix-fractional ``v^T Q(t)^-1 v`` with ``Q`` linear
in t, eq. (F1)), so its maximum over the hull, the box ``|delta| <= Delta[k]`` and the interval is
at a hull vertex, a corner of the box and an end of the interval:

    w_k = max_v max_corners max_ends ||B_v K[k] (sigma o Delta[k])||_P,                      (I2)

and the funnel is invariant under the shipped law when ``m_k + 2 w_k / (rho e^{-lambda t_k+1}) <
0`` on every interval (``rho_t`` is smallest at the interval's end). ``LMI_MARGIN`` is required
below zero on top, for the eigenvalues' rounding. The RK4 values stand in for the exact nominal:
their estimated error (Richardson, against a grid twice as fine) moves the law's centre as the
interpolation does, and the certify stage adds it to ``Delta`` (``law_offset``'s
``centre_error``) and requires it below ``LEVEL_MARGIN`` of the radius (the levels' limits).

(I3) Inputs. The applied input is ``u_ref + K e + K delta`` with ``|K_j e| <= rho_t g_j[k]`` (E3)
and ``|K_j delta| <= sum_i |K[k, j, i]| Delta_i[k]``: the hull's input box and the input limits
take the second term as an offset.

(I4) A bounded disturbance. With ``xdot = f(x, u) + w``, ``|w_i| <= d_i`` for every measurable
``w`` (a box, ``d (n,)``, zero for states it does not act on), the error gains ``+ w`` and the
same argument gives ``+ 2 ||e||_P ||w||_P`` on the boundary: ``m_k + 2 (w_k + v_k) / rho_t < 0``
with ``v_k = max_corners max_ends ||sigma o d||_P`` (convex in ``w`` and in ``t``, as above). Unlike
(I2) it does not shrink with the grid: the funnel must be designed for it (``funnel.lmi``'s
disturbance constraint), and it bounds the level from below (``rho_t > 2 (w_k + v_k) / -m_k``).
The check uses the sharper (I5) of ``funnel.robust``, which bounds the (F2) term and the
disturbance's together (the S-procedure) instead of each at its own worst boundary point.

(I6) A held law. With ``--feedback-period h`` (``h`` divides ``Ts``) the law is evaluated at
``t_j = j h`` and held: ``u(t) = u_ref[k] + K[k] (x(t_j) - xhat(t_j))`` on ``[t_j, t_j + h)``.
The samples are aligned with 0, so ``t_j`` and ``t`` lie in the same sample interval ``k``
(same ``K[k]``, ``u_ref[k]``). With ``x(t_j) - xhat(t_j) = e(t_j) + delta(t_j)``,

    u = u_ref + K e(t) + K delta_h,   delta_h = delta(t_j) + (e(t_j) - e(t)),

the law of (I2) with the offset ``delta_h`` in place of ``delta``. While the state is in the
funnel on ``[t_j, t]`` (up to the first exit, which is what the invariance argument needs: the
boundary condition is checked with these bounds), ``|e(t_j) - e(t)| <= h Edot`` with ``Edot
(n,)`` a bound on ``|de/dt|`` there: ``de/dt = f(x, u) - f(x_ref, u_ref) + w = Abar e(t) + Bbar
(u - u_ref) + w`` with ``[Abar Bbar]`` in the hull (the segment from ``(x_ref, u_ref)`` to ``(x,
u)`` lies in the box ``Z_k``: ``x`` is in the funnel, and ``u - u_ref = K e(t_j) + K
delta(t_j)`` is inside the input box widened by (I3)'s offset, which is checked with the larger
``delta_h``). Bounding each term: ``|e_l(t)| <= ext_l = rho_k sqrt(max(Q_ll[k], Q_ll[k+1]))``
(``Q`` linear in t, ``rho_t <= rho_k = rho e^{-lambda t_k}`` on the interval), ``|u_j - u_ref_j|
<= g_j + (|K| Delta)_j`` with ``g_j = rho_k sqrt(max_ends K_j Q K_j^T)`` (E3: ``e(t_j)`` is in
the funnel) and ``Delta`` of (I1), ``|w| <= d`` (the declared additive bound, (I4); zero for the
exact model); ``Abar e + Bbar v`` is a convex combination of ``A_v e + B_v v`` over the
vertices, so

    Edot_i <= max_v [sum_l |A_v[i, l]| ext_l + sum_j |B_v[i, j]| (g_j + (|K| Delta)_j)] + d_i,
    |delta_h| <= Delta_h = Delta + h Edot                     (``LawOffset.deviation``).

Two bounds are tighter than this per-state box where the offset enters. In the inequality the
hold's part is not taken through (I2)'s Cauchy-Schwarz bound (measured on
double_integrator_hold's funnels at ``h`` = 5 ms: 12x the room, where the funnel is thin in the
velocities Init does not spread, and (I2) pairs the largest push with the weakest decay): the
error equation is ``e' = Acl e + Bbar K delta + Bbar K (e(t_j) - e(t)) + w``, and the push is
bounded componentwise, as the box ``H[k]`` (``LawOffset.hold``). With ``Bbar(t) = sum_v a_v B_v``
the loop's at ``t`` and ``[Abar(s) Bbar(s)] = sum_v' b_v' [A_v' B_v']`` at ``s`` in ``[t_j, t]``
(convex weights, the hull of interval ``k`` as above),

    Bbar(t) K (e(t_j) - e(t)) = -int_{t_j}^t Bbar(t) K e'(s) ds,
    e'(s) = Abar(s) e(s) + Bbar(s) K (e(t_j) + delta(t_j)) + w(s),

and ``Bbar(t) K e'(s) = sum_{v, v'} a_v b_v' [B_v K A_v' e(s) + B_v K B_v' K (e(t_j) +
delta(t_j)) + B_v K w(s)]``: bilinear in the two hulls' weights, so each component is at most
``sum_{v, v'} a_v b_v'`` times a bound on the pair's term, at most the largest over the vertex
pairs (one maximum over both, not one per hull). ``e(s)`` is in ``{e^T P(s) e <= rho_s^2}``,
``rho_s <= rho_k``, whose support function in a direction ``r`` is ``rho_s sqrt(r Q(s) r^T)``
(exact for a linear functional), linear in ``s`` under the root: largest at an end. So with ``r
= (B_v K A_v')[i, :]``, ``s = (B_v K B_v' K)[i, :]`` (``e(t_j)`` is in the funnel too):

    H[k]_i = h max_{v, v'} [rho_k sqrt(max_ends r Q r^T) + rho_k sqrt(max_ends s Q s^T)
                            + (|B_v K B_v' K| Delta)_i + (|B_v K| d)_i]                  (I6)

(``funnel.held``). It is at most the per-state box's ``max_v |B_v K| h Edot``: ``sqrt(r Q r^T)
<= sum_l |r_l| sqrt(Q_ll)`` (Cauchy-Schwarz), ``sqrt(s Q s^T) <= sum_j |(B_v K B_v')[i, j]|
sqrt(K_j Q K_j^T)`` (the triangle inequality in the Q-norm), ``|B_v K B_v' K| <= |B_v K| |B_v'|
|K|``, and a joint maximum is at most the product of separate ones. The inputs likewise: ``u -
u_ref - K e(t) = K delta(t_j) + K (e(t_j) - e(t))`` with ``|K_j (e(t_j) - e(t))| <= h max_v'
[rho_k sqrt(max_ends (K A_v')_j Q (K A_v')_j^T) + rho_k sqrt(max_ends (K B_v' K)_j Q (K B_v'
K)_j^T) + (|K B_v' K| Delta)_j] + h (|K| d)_j`` (``LawOffset.held_input``), and (I3)'s offset is
``|K| Delta`` plus it (the input box widened by it keeps the segment in ``Z_k``, as above).
(I5)'s S-procedure holds for every hull point and every signal in its box, so with the box ``d +
H[k]`` on interval ``k`` it covers the push too (that ``Bbar`` is also the loop's is then not
used: sound, if conservative); (I2) keeps ``Delta`` of (I1) alone. ``H`` does not shrink with the
reference grid (and it is about ``rho``, so it does not shrink with the level either): a funnel
whose (I5) fails with ``d + H`` is not certifiable at that period, on any grid. With ``h = 0``
every number is (I1)-(I5)'s. ``funnel.sampled`` (I6') bounds the same push differently: its part
linear in ``e(t)`` (``-tau Bbar K Mbar e(t)``, ``Mbar`` in the hull's closed loops) goes into
(I5)'s matrix and only a remainder ``R[k]`` (``LawOffset.remainder``, second order in ``h`` in
the state) into its box; the check takes, per interval, the smaller of the two margins (measured
on quadrotor_hill at 5 ms: (I6') fails 0-12 intervals per funnel where (I6) fails 12-32).

(I7) A measurement error. The feedback sees ``x_meas = x + eta``, ``|eta_i| <= E_i`` for every
measurable ``eta`` (the scenario's ``uncertainty.measurement``, a box, zero for states measured
exactly); the funnel stays about the true state ``x`` (``e = x - x_ref``, ``V``, the level, the
limits: nothing changes there). The law is

    u = u_ref[k] + K[k] (x + eta - xhat) = u_ref[k] + K[k] e + K[k] delta + K[k] eta,

so ``eta`` is one more bounded offset of the kind of ``delta``, and the error equation gains
``Bbar K eta``: ``e' = Acl e + Bbar K delta + Bbar K eta + w``. It is taken as (I6)'s hold is,
not through (I2): ``|(Bbar K eta)_i| <= max_v sum_l |(B_v K)[i, l]| E_l`` (``Bbar`` a convex
combination of the vertices; the segment from ``(x_ref, u_ref)`` to ``(x, u)`` lies in ``Z_k``
because ``x`` is in the funnel and ``u`` in the input box widened by (I3) with ``E``, below), so
``Bbar K eta + w`` lies in the box ``d + max_v |B_v K| E``, and (I5) holds for every hull point
and every signal in its box: the measurement's box joins ``LawOffset.hold`` (with (I6)'s when
the law is held) and (I5)'s box. (I2) keeps (I1)'s ``Delta`` alone. Inputs (I3): ``|K_j (delta +
eta)| <= sum_i |K[k, j, i]| (Delta_i + E_i)``, so ``Delta`` gains ``E`` in the input offset (in
``held_input`` too: it does not shrink with the grid). With a held law ``u - u_ref = K (e(t_j) +
delta(t_j) + eta(t_j))``, so (I6) takes ``Delta + E`` for ``Delta`` (in ``Edot``, in ``H[k]``'s
``|B_v K B_v' K| Delta`` and in ``held_input``), the per-state box is ``Delta + E + h Edot``, and
the box of the push and of ``Bbar K eta(t_j)`` together is ``max_v [h max_v' (...) + |B_v K|
E]`` (the same vertex ``v`` of ``Bbar(t)`` in both), the input's ``held_input + |K| E``. With
``E = 0`` every number is (I1)-(I6)'s.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass

import numpy as np

from pipeline.model.dynamics import FloatArray
from pipeline.numerics.funnel.held import held_rates
from pipeline.numerics.funnel.sampled import remainder_box

LMI_MARGIN = 1e-6  # 1/s: how far below 0 the (F2) eigenvalue with the law's term (I2) must be
LEVEL_MARGIN = 1e-6  # relative: a funnel's level must stay this far inside every limit
BASE_SUBSTEPS = 20  # the reference grid's RK4 steps per sample where the law needs no finer one
MAX_SUBSTEPS = 2000
SAFETY = 2.0  # the grid is made fine enough for (I2) and (I3) to use at most 1 / SAFETY of the room


@dataclass(frozen=True, kw_only=True)
class LawOffset:
    """The shipped law's offset from the certified centre, per sample interval (N intervals).

    Attributes:
      steps: (N,) the reference grid's spacing ``h_k`` (s) on each interval.
      deviation: (N, n) ``Delta``, (I1): ``|x_ref - xhat| <= Delta[k]`` on interval k (with
        ``E`` of (I7) and a held law's ``h Edot``, (I6): the per-state box of the law's offset).
      input_offset: (N, m) ``sum_i |K[k, j, i]| Delta_i[k]``, (I3) (a held law: ``Delta``
        without ``h Edot``, plus ``held_input``'s hold part).
      lmi_term: (N,) ``2 w_k / (rho e^{-lambda t_k+1})``, (I2): added to the (F2) eigenvalue.
      disturbance: (n,) the box ``|w| <= d`` on the state derivatives the funnel must hold under
        (``funnel.robust`` (I5)); zeros: the exact model.
      period: ``h`` (s) of a held law (I6); 0: continuous feedback.
      hold: (N, n) ``H[k]``, (I6), (I7): the box of the hold's term ``Bbar K (e(t_j) - e(t))``
        and the measurement's ``Bbar K eta``, joined to ``disturbance`` in (I5); None:
        continuous feedback of the exact state.
      held_input: (N, m) the bound on ``|K (e(t_j) - e(t))|`` of (I6) plus ``|K| E``, the
        hold's and the measurement's part of ``input_offset`` (it does not shrink with the
        grid); None: as ``hold``.
      measurement: (n,) ``E`` of (I7); None: the state is measured exactly.
      remainder: (N, n) the box (R) of a held law's push taken to first order into (I5)'s
        matrix (``funnel.sampled`` (I6')), with (I7)'s push; None: continuous feedback.
    """

    steps: FloatArray
    deviation: FloatArray
    input_offset: FloatArray
    lmi_term: FloatArray
    disturbance: FloatArray
    period: float = 0.0
    hold: FloatArray | None = None
    held_input: FloatArray | None = None
    measurement: FloatArray | None = None
    remainder: FloatArray | None = None

    @property
    def box(self) -> FloatArray:
        """(I5)'s box: ``disturbance (n,)``, or ``disturbance + hold`` (N, n) for a held law."""
        return self.disturbance if self.hold is None else self.disturbance + self.hold

    @property
    def sampled_box(self) -> FloatArray | None:
        """(N, n) ``funnel.sampled`` (I6')'s box: ``disturbance + remainder``; None for
        continuous feedback (``box`` is then the one box)."""
        return None if self.remainder is None else self.disturbance + self.remainder

    def robust_part(self) -> LawOffset:
        """This law without (I2)'s interpolation term and (I3)'s offset: the disturbance and
        the hold's box in (I5) (what the reference grid is chosen against)."""
        return dataclasses.replace(
            self, deviation=np.zeros_like(self.deviation),
            input_offset=np.zeros_like(self.input_offset), lmi_term=np.zeros_like(self.lmi_term),
            held_input=None,
        )  # fmt: skip

    @property
    def fixed_input(self) -> FloatArray:
        """(N, m) ``held_input``, zeros for continuous feedback."""
        return np.zeros_like(self.input_offset) if self.held_input is None else self.held_input

    @staticmethod
    def none(N: int, n: int, m: int, Ts: float) -> LawOffset:
        """No offset: a law that tracks the exact nominal (the synthesis's own check)."""
        return LawOffset(
            steps=np.full(N, Ts), deviation=np.zeros((N, n)), input_offset=np.zeros((N, m)),
            lmi_term=np.zeros(N), disturbance=np.zeros(n),
        )  # fmt: skip

    def with_disturbance(self, bound: FloatArray) -> LawOffset:
        """This offset under a disturbance box ``bound (n,)`` on the state derivatives."""
        return dataclasses.replace(self, disturbance=np.asarray(bound, dtype=np.float64))

    @property
    def disturbed(self) -> bool:
        """Whether the funnel must hold under a disturbance or a hold's box (``funnel.robust``
        (I5))."""
        return bool(np.any(self.box > 0))


def corners(bound: FloatArray) -> FloatArray:
    """(C, n) the corners of the box ``|w| <= bound (n,)``, one of each pair ``+-w`` (a norm is
    even), over the states it acts on (``bound > 0``); ``(0, n)`` without any."""
    n = len(bound)
    active = np.flatnonzero(bound > 0)
    if not len(active):
        return np.zeros((0, n))
    signs = np.array(list(itertools.product((-1.0, 1.0), repeat=len(active))))
    out = np.zeros((2 ** (len(active) - 1), n))
    out[:, active] = signs[: len(out)] * bound[active]
    return out


def grid_substeps(t: FloatArray, N: int, Ts: float) -> np.ndarray | None:
    """(N,) the number of equal steps of the grid ``t (r,)`` on each sample interval ``[k Ts, (k +
    1) Ts]``, or None when ``t`` does not hold every sample time or is not uniform inside an
    interval (to 1e-9 s)."""
    samples = np.searchsorted(t, Ts * np.arange(N + 1) - 1e-9)
    if samples[-1] >= len(t) or not np.allclose(t[samples], Ts * np.arange(N + 1), atol=1e-9):
        return None
    substeps = np.diff(samples)
    if substeps.min() < 1 or samples[0] != 0 or samples[-1] != len(t) - 1:
        return None
    for k, (a, b) in enumerate(itertools.pairwise(samples)):
        expected = k * Ts + (Ts / (b - a)) * np.arange(b - a + 1)
        if not np.allclose(t[a : b + 1], expected, rtol=0, atol=1e-9):
            return None
    return substeps


def law_offset(
    vertices: tuple[FloatArray, ...],
    rate_bound: FloatArray,
    K: FloatArray,
    P: FloatArray,
    rho: float,
    rate: float,
    Ts: float,
    substeps: np.ndarray,
    centre_error: float = 0.0,
    period: float = 0.0,
    disturbance: FloatArray | None = None,
    measurement: FloatArray | None = None,
) -> LawOffset:
    """(I1)-(I3) for a funnel ``K (N, m, n)``, ``P (N+1, n, n)``, level ``rho``, ``rate``, with its
    hull ``vertices`` (N arrays (V, n, n+m) of ``[A_v B_v]``), the nominal's rate bound
    ``rate_bound (N, n)`` (E1) and the reference grid's ``substeps (N,)`` per sample.
    ``centre_error``: the P-norm error of the RK4 values standing in for the exact nominal
    (estimated by the caller); it moves the law's centre too, so it joins ``Delta`` (a P-norm
    error ``eps`` is at most ``eps sqrt(Q_ii)`` in state ``i``). ``period > 0``: the law held
    every ``period`` s, (I6), with the additive bound ``disturbance (n,)`` in ``Edot`` (None:
    zeros); the returned ``disturbance`` is still zeros (``with_disturbance`` sets (I5)'s).
    ``measurement (n,)``: the box ``E`` of the error on the state the law sees, (I7) (None or
    zeros: the exact state)."""
    N, m, n = K.shape
    steps = Ts / np.asarray(substeps, dtype=np.float64)
    Q = np.asarray(np.linalg.inv(P), dtype=np.float64)  # (N+1, n, n)
    Q_diagonal = np.diagonal(Q, axis1=1, axis2=2)  # (N+1, n)
    centre = centre_error * np.sqrt(np.maximum(Q_diagonal[:-1], Q_diagonal[1:]))  # (N, n)
    deviation, input_offset, lmi_term = np.zeros((N, n)), np.zeros((N, m)), np.zeros(N)
    held = period > 0
    E = np.zeros(n) if measurement is None else np.asarray(measurement, dtype=np.float64)
    measured = bool(np.any(E > 0))
    hold, held_input, remainder = np.zeros((N, n)), np.zeros((N, m)), np.zeros((N, n))
    d = np.zeros(n) if disturbance is None else np.asarray(disturbance, dtype=np.float64)
    signs = np.array(list(itertools.product((-1.0, 1.0), repeat=n)))[: 2 ** (n - 1)]  # +-pairs
    for k in range(N):
        A, B = vertices[k][:, :, :n], vertices[k][:, :, n:]
        acceleration = (np.abs(A) @ rate_bound[k]).max(axis=0)  # (n,) bound on |xddot|
        deviation[k] = steps[k] ** 2 / 8 * acceleration + centre[k]  # eq. (I1)
        rho_t = rho * math.exp(-rate * Ts * (k + 1))
        w = _offset_norm(B, K[k], P, k, signs * deviation[k])  # eq. (I2), (I1)'s Delta alone
        lmi_term[k] = 2 * w / rho_t
        if measured:  # eq. (I7): eta is one more offset of the law, delta + eta
            deviation[k] = deviation[k] + E
        if held:  # eq. (I6)
            level = rho * math.exp(-rate * Ts * k)  # rho_t is largest at the interval's start
            extent = level * np.sqrt(np.maximum(Q_diagonal[k], Q_diagonal[k + 1]))  # (n,)
            spread = np.maximum(
                np.einsum("ji,il,jl->j", K[k], Q[k], K[k]),
                np.einsum("ji,il,jl->j", K[k], Q[k + 1], K[k]),
            )  # (m,) K_j Q K_j^T, linear in t: largest at an end
            reach = level * np.sqrt(np.maximum(spread, 0.0)) + np.abs(K[k]) @ deviation[k]
            speed = (np.abs(A) @ extent + np.abs(B) @ reach).max(axis=0) + d  # (n,) Edot
            push, swing = held_rates(A, B, K[k], Q[k : k + 2], level, deviation[k], d)
            # the box H[k], joined to (I5)'s, with (I7)'s push of eta(t_j) at the same vertex
            hold[k] = (period * push + np.abs(B @ K[k]) @ E).max(axis=0)
            held_input[k] = period * swing + np.abs(K[k]) @ E
            # funnel.sampled (I6'): the remainder's box, Delta + E for the offset C
            remainder[k] = remainder_box(A, B, K[k], speed, deviation[k], d, E, period)
            input_offset[k] = np.abs(K[k]) @ deviation[k] + period * swing  # eq. (I3)
            deviation[k] = deviation[k] + period * speed  # Delta_h: |e(t_j) - e(t)| <= h Edot
            continue
        if measured:  # eq. (I7): the measurement's box, joined to (I5)'s
            hold[k] = (np.abs(B @ K[k]) @ E).max(axis=0)
            held_input[k] = np.abs(K[k]) @ E
        input_offset[k] = np.abs(K[k]) @ deviation[k]  # eq. (I3)
    boxed = held or measured
    return LawOffset(
        steps=steps, deviation=deviation, input_offset=input_offset, lmi_term=lmi_term,
        disturbance=np.zeros(n), period=float(period) if held else 0.0,
        hold=hold if boxed else None, held_input=held_input if boxed else None,
        measurement=E if measured else None, remainder=remainder if held else None,
    )  # fmt: skip


def _offset_norm(B: FloatArray, K: FloatArray, P: FloatArray, k: int, offsets: FloatArray) -> float:
    """(I2)'s ``w_k``: the largest ``||B_v K delta||_P`` over the vertices ``B (V, n, m)``, the
    corners ``offsets (C, n)`` and the ends ``P[k]``, ``P[k + 1]`` of interval ``k``."""
    pushed = (B @ K) @ offsets.T  # (V, n, corners)
    return max(
        float(np.sqrt(np.einsum("vic,ij,vjc->vc", pushed, P[k + e], pushed).max())) for e in (0, 1)
    )


def law_substeps(
    offset: LawOffset, margins: FloatArray, input_room: FloatArray, Ts: float
) -> np.ndarray:
    """(N,) RK4 steps per sample for the reference grid: at least ``BASE_SUBSTEPS``, and enough
    that (I2) uses at most ``1 / SAFETY`` of what the (F2) eigenvalues ``margins (N,)`` leave below
    ``-LMI_MARGIN``, and (I3) at most ``1 / SAFETY`` of ``input_room (N, m)`` (the distance from
    the tube's inputs to their bounds). ``offset`` is (I1)-(I3) on some grid; every term scales
    with ``h_k^2`` but a held law's (I6): its box ``hold`` is in the margins already (the caller's
    (I5) with it), its input part (``held_input``) takes its share of the input room first, and
    the rest of each term is what the grid shrinks. Where the room is already gone the grid stays
    at ``BASE_SUBSTEPS`` (the funnel is not certifiable on any grid, or at that period)."""
    fixed_input = offset.fixed_input
    lmi_room = np.maximum(-margins - LMI_MARGIN, 0.0) / SAFETY
    input_room = np.maximum(input_room - fixed_input, 0.0) / SAFETY
    lmi_scaled = offset.lmi_term
    input_scaled = np.maximum(offset.input_offset - fixed_input, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        lmi_fit = np.where(lmi_scaled > 0, lmi_room / lmi_scaled, np.inf)
        input_fit = np.where(input_scaled > 0, input_room / input_scaled, np.inf)
    shrink = np.minimum(lmi_fit, input_fit.min(axis=1))  # the largest factor on h_k^2 that fits
    with np.errstate(divide="ignore"):  # shrink 0: the room is gone, BASE_SUBSTEPS is taken
        needed = np.where(
            shrink > 0,
            np.ceil(Ts / (offset.steps * np.sqrt(np.minimum(shrink, 1.0)))),
            BASE_SUBSTEPS,
        )
    return np.clip(needed, BASE_SUBSTEPS, MAX_SUBSTEPS).astype(np.int64)
