"""Re-verify a ``safety-controller/2`` file's funnels from the file's data alone.

The references: ``verify.reference``; the terminal block: ``verify.terminal``; the bounds each
block is re-checked under: ``verify.declared``.

``recheck_funnel`` (``/2``). The file carries, per trajectory, ``x_ref`` (re-simulated by
``verify.reference.check_reference`` from ``x0`` and ``u_ref``), ``K (N, m, n)``, ``P (N+1, n, n)``
(``Q = P^-1`` linear in t between samples, eq. (F1) of ``pipeline.numerics.funnel.synthesis``), the
level ``rho`` and the rate ``lambda``; not the hulls the synthesis used. Rebuilt here, independently
of the synthesis's boxes and its solver:

1. per sample interval ``k``, the nominal's a priori box ``B_k = grid_k +- pad`` (E1 of
   ``funnel.bounds``: ``F h < pad`` with ``F`` from the hull below, ``pad`` grown until it holds);
2. the box ``Z_k`` of the variables the Jacobian depends on: a state's ``B_k`` widened by the
   tube's extent ``rho s_i[k]``, an input's ``u_ref[k] +- rho g_j[k]`` (E3), clipped to the
   scenario's state and input bounds (sound: the limits re-checked below keep the tube inside
   them), and a sound hull of ``[f_x f_u]`` over ``Z_k`` (``pipeline.numerics.hull``, outward
   rounded);
3. the shipped law's offset (``funnel.law``): it tracks ``x_ref`` interpolated on the file's grid,
   whose error (I1) enters the inequality (I2) and the inputs (I3); the input boxes of step 2 are
   widened by ``OFFSET_ALLOWANCE`` times the offset (I3) of hulls without it, and the offset of
   the hulls so built must fit that allowance;
   With ``feedback_period h > 0`` the law is held every ``h`` s: its offset (I6) (``h Edot``,
   the additive bound in ``Edot``) joins (I3)'s, and its push joins the disturbance's box in
   (I5); a declared measurement error (I7) likewise (its box ``E`` in the offset, its push in
   (I5)'s box);
4. ``funnel.check.check_funnel`` on the funnel so rebuilt, under that law: ``P[k]`` positive
   definite, (F3) plus (I2) at every vertex at both ends of every interval (numpy eigenvalues),
   the enclosure (E1) and the tube inside every hull box, ``rho`` within the limits of Unsafe,
   the inputs, the state bounds and Goal at ``T`` (``funnel.bounds.funnel_limits``).

Steps 1-2 run on a uniform RK4 grid of ``BASE_SUBSTEPS`` per sample (the nominal is the same
whatever grid the file carries its reference on).

A hull over a box is sound for any number of segments, so ``SEGMENTS`` are tried in turn and the
funnel is accepted when one of them certifies it (a finer hull is tighter, not always a subset).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass

import numpy as np

from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import Trajectory, simulate
from pipeline.numerics.funnel.bounds import funnel_limits, tube_extents
from pipeline.numerics.funnel.check import Funnel, checked_margins, effective_margins
from pipeline.numerics.funnel.law import (
    BASE_SUBSTEPS,
    LMI_MARGIN,
    LawOffset,
    law_offset,
    law_substeps,
)
from pipeline.numerics.funnel.pieces import piece_hulls
from pipeline.numerics.funnel.robust import RobustCheck
from pipeline.numerics.hull import HullError

SEGMENTS = (1, 4)
WIDEN = 1e-9  # relative widening of the tube's extent in the hull boxes (rounding of E3)
PAD_ROUNDS = 8
OFFSET_ALLOWANCE = 2.0  # the input boxes hold this multiple of the law's input offset (step 3)


@dataclass(frozen=True, kw_only=True)
class ShippedFunnel:
    """One funnel as ``controller.json`` carries it: ``K (N, m, n)``, ``P (N+1, n, n)``, the
    level ``rho`` and ``rate``."""

    K: FloatArray
    P: FloatArray
    rho: float
    rate: float

    @property
    def Q(self) -> FloatArray:
        """(N+1, n, n) ``P^-1``, symmetrized."""
        Q = np.linalg.inv(self.P)
        return (Q + np.swapaxes(Q, 1, 2)) / 2


@dataclass(frozen=True, kw_only=True)
class FunnelRecheck:
    """The re-verification of one funnel.

    Attributes:
      failure: what fails (None: certified); margin: the largest eigenvalue of (F2) over the
        vertices at both ends of every interval, or under a disturbance twice (I5)'s, plus the
        law's term (I2) (< 0 for a certificate); vertices: hull vertices
        over all intervals; radius: the largest level the constraints allow (>= rho to pass);
        binding: the constraint that sets it; disturbance_multiple: the largest ``s`` for which
        (I5) still holds with ``s`` times the disturbance checked (``funnel.robust``: found by
        bisection, nothing else depends on it; ``inf`` without a disturbance; below 1 when the
        funnel does not hold the one checked; NaN when not asked for; ``enough`` itself where
        the funnel holds it, certify asking no more); failing: the sample intervals where that
        margin is not below ``-LMI_MARGIN`` (where a redesign must do better,
        ``stages.funnel``).
    """

    failure: str | None
    margin: float
    vertices: int
    radius: float
    binding: str
    disturbance_multiple: float = float("inf")
    failing: tuple[int, ...] = ()


def rebuild_funnel(
    scenario: Scenario,
    trajectory: Trajectory,
    shipped: ShippedFunnel,
    state_bounds: Mapping[str, tuple[float, float]],
    segments: int,
    input_offset: FloatArray | None = None,
) -> Funnel:
    """The ``shipped`` funnel around ``trajectory`` with hulls and enclosure rebuilt by steps
    1-2 of the module docstring (``funnel.pieces.piece_hulls`` on pieces of one sample interval,
    with the file's ``Q`` at level ``rho (1 + WIDEN)`` as the extents, the inputs widened by
    ``input_offset (N, m)`` (step 3), and no arc caps).

    Raises:
      HullError: no hull over a box, or no a priori enclosure within ``PAD_ROUNDS``.
    """
    K, N = shipped.K, len(shipped.K)
    variables, boxes, vertices, enclosure = piece_hulls(
        scenario, trajectory, shipped.Q, K, state_bounds,
        shipped.rho * (1 + WIDEN), segments, np.arange(N + 1), tight=False,
        pad_rounds=PAD_ROUNDS, input_offset=input_offset,
    )  # fmt: skip
    return Funnel(
        K=K, P=shipped.P, rho=shipped.rho, rate=shipped.rate, margins=np.full((N, 2), np.nan),
        boxes=boxes,
        variables=variables, vertices=vertices, enclosure=enclosure, limits={},
        binding="", seconds=0.0, success=True, message="rebuilt from controller.json",
    )  # fmt: skip


class Rebuilt:
    """``rebuild_funnel(scenario, trajectory, shipped, state_bounds, segments, input_offset)``
    for one funnel, each ``(segments, input_offset)`` once: ``recheck_as_shipped`` rebuilds the
    same hulls for ``reference_substeps`` and ``recheck_funnel`` (a deterministic function of
    these arguments; a failure is not kept, it is raised again)."""

    def __init__(
        self,
        scenario: Scenario,
        trajectory: Trajectory,
        shipped: ShippedFunnel,
        state_bounds: Mapping[str, tuple[float, float]],
    ) -> None:
        self._rebuild = functools.partial(
            rebuild_funnel, scenario, trajectory, shipped, state_bounds
        )
        self._funnels: dict[tuple[int, bytes | None], Funnel] = {}

    def __call__(self, segments: int, input_offset: FloatArray | None = None) -> Funnel:
        key = (segments, None if input_offset is None else _key(input_offset))
        if key not in self._funnels:
            self._funnels[key] = self._rebuild(segments, input_offset)
        return self._funnels[key]


def _key(values: FloatArray) -> bytes:
    """The exact value of ``values`` (shape and bits) as a dictionary key."""
    values = np.ascontiguousarray(values, dtype=np.float64)
    return repr(values.shape).encode() + values.tobytes()


def _under_law(
    scenario: Scenario,
    trajectory: Trajectory,
    shipped: ShippedFunnel,
    state_bounds: Mapping[str, tuple[float, float]],
    segments: int,
    substeps: np.ndarray,
    centre_error: float = 0.0,
    disturbance: FloatArray | None = None,
    period: float = 0.0,
    measurement: FloatArray | None = None,
    rebuilt: Rebuilt | None = None,
) -> tuple[Funnel, LawOffset]:
    """Steps 1-3: the funnel rebuilt with its input boxes widened by ``OFFSET_ALLOWANCE`` times the
    law's input offset (I3) found on hulls without it, and the law's offset on the hulls so built
    for a reference grid of ``substeps (N,)`` per sample, under the additive bound ``disturbance
    (n,)`` when given ((I5)), the law held every ``period`` s when it is > 0 ((I6), with the
    same bound in ``Edot``), the law seeing the state with an error in the box ``measurement
    (n,)`` when given ((I7)). ``rebuilt``: the funnels already rebuilt for the same
    ``scenario``, ``trajectory``, ``shipped`` and ``state_bounds`` (``Rebuilt``).

    Raises:
      HullError: no hull or enclosure, or the offset outgrew the widening.
    """
    rebuild = Rebuilt(scenario, trajectory, shipped, state_bounds) if rebuilt is None else rebuilt

    def offset(funnel: Funnel) -> LawOffset:
        if funnel.enclosure is None:
            raise HullError("no a priori enclosure of the nominal")
        return law_offset(
            funnel.vertices, funnel.enclosure.rate_bound, shipped.K, shipped.P, shipped.rho,
            shipped.rate, scenario.Ts, substeps, centre_error, period, disturbance, measurement,
        )  # fmt: skip

    plain = rebuild(segments)
    allowance = OFFSET_ALLOWANCE * offset(plain).input_offset
    funnel = rebuild(segments, allowance)
    law = offset(funnel)
    if np.any(law.input_offset > allowance):
        raise HullError(
            "the interpolated reference's input offset (I3) outgrew its hull box"
            + (f" (the law held every {period:g} s, (I6))" if period > 0 else "")
        )
    if disturbance is not None:
        law = law.with_disturbance(disturbance)
    return funnel, law


def recheck_funnel(
    scenario: Scenario,
    trajectory: Trajectory,
    shipped: ShippedFunnel,
    state_bounds: Mapping[str, tuple[float, float]],
    substeps: np.ndarray,
    centre_error: float = 0.0,
    disturbance: FloatArray | None = None,
    period: float = 0.0,
    measurement: FloatArray | None = None,
    *,
    multiple: bool = True,
    enough: float = math.inf,
    rebuilt: Rebuilt | None = None,
) -> FunnelRecheck:
    """Steps 1-4 of the module docstring for one ``shipped`` funnel around the nominal
    ``trajectory`` (a uniform RK4 grid), its law tracking the reference on a grid of ``substeps
    (N,)`` per sample, for ``x' = f(x, u) + w`` with ``|w| <= disturbance (n,)`` when given
    (``pipeline.numerics.uncertainty``; (I5)), the law held every ``period`` s when it is > 0
    (``funnel.law`` (I6)), the law seeing the state within ``measurement (n,)`` when given
    ((I7)). The margin reported is (F2)'s eigenvalue plus (I2),
    or under a disturbance twice (I5)'s plus (I2) (``funnel.check.effective_margins``).
    ``multiple``: also find the disturbance multiple it holds (a bisection of (I5) searches;
    the design's acceptance (``stages.funnel``) does not need it), searched no higher than
    ``enough`` (``RobustCheck.multiple``; certify reports the smallest over its funnels).
    ``rebuilt``: as ``_under_law``'s."""
    K, Q = shipped.K, shipped.Q
    failures: list[str] = []
    last = FunnelRecheck(failure="", margin=float("nan"), vertices=0, radius=0.0, binding="")
    for segments in SEGMENTS:
        try:
            funnel, law = _under_law(
                scenario, trajectory, shipped, state_bounds, segments, substeps, centre_error,
                disturbance, period, measurement, rebuilt,
            )  # fmt: skip
        except (HullError, np.linalg.LinAlgError) as error:
            failures.append(f"{segments} segment(s): {error}")
            continue
        failure, margins = checked_margins(scenario, trajectory, funnel, state_bounds, law)
        if margins is None:  # P is no metric: (F2)'s margins as effective_margins gives them
            margins = effective_margins(Q, K, funnel, scenario.Ts, law)
        enclosure = funnel.enclosure
        if enclosure is None:  # _under_law raises first; narrows the type
            raise HullError("no a priori enclosure of the nominal")
        limits = funnel_limits(
            scenario, trajectory, Q, K, enclosure, state_bounds, law.input_offset
        )
        binding = min(limits, key=lambda key: limits[key][0])
        held = functools.partial(  # the law's offset under another additive bound in (I6)
            law_offset, funnel.vertices, enclosure.rate_bound, K, shipped.P, shipped.rho,
            shipped.rate, scenario.Ts, substeps, centre_error, period, measurement=measurement,
        )  # fmt: skip
        last = FunnelRecheck(
            failure=failure,
            margin=float(margins.max()),
            vertices=sum(len(v) for v in funnel.vertices),
            radius=limits[binding][0],
            binding=binding,
            disturbance_multiple=(
                disturbance_multiple(Q, K, funnel, scenario.Ts, law, held, enough)
                if multiple
                else float("nan")
            ),
            failing=tuple(int(k) for k in np.flatnonzero(margins >= -LMI_MARGIN)),
        )
        if failure is None:
            return last
        failures.append(f"{segments} segment(s): {failure}")
    return dataclasses.replace(last, failure="; ".join(failures))


def disturbance_multiple(
    Q: FloatArray,
    K: FloatArray,
    funnel: Funnel,
    Ts: float,
    law: LawOffset,
    held: Callable[[FloatArray], LawOffset] | None = None,
    enough: float = math.inf,
) -> float:
    """The largest ``s`` for which ``funnel`` (``Q (N+1, n, n)``) still holds under ``s`` times
    the law's disturbance box with its (I2) term (``funnel.robust`` (I5)); ``inf`` without one.
    A held law's box (``funnel.law`` (I6)) grows with the disturbance (``Edot``): ``held(bound)``,
    the law's offset under another additive bound, gives it again for each ``s`` (the input
    boxes are not widened for it: like the rest of the multiple, (I5) and (I2) alone). A
    measurement's box ((I7), in ``hold``) is held at its declared size: the multiple is of the
    additive bound. A held law: the larger of (I6)'s multiple and (I6')'s (``funnel.sampled``,
    its remainder's box grown likewise): each holds on every interval at its own ``s``, so the
    per-interval smaller margin of ``effective_margins`` does too (a lower bound on its
    multiple). ``enough``: as ``RobustCheck.multiple``'s."""
    check = RobustCheck(Q, K, funnel.vertices, funnel.rate, Ts, funnel.rho)
    if law.hold is None or held is None:
        return check.multiple(law.disturbance, law.lmi_term, enough=enough)
    offset, zeros = held, np.zeros_like(law.hold)

    def grown(box: Callable[[LawOffset], FloatArray | None]) -> Callable[[float], FloatArray]:
        """``s`` -> the law's ``box`` (``hold`` or ``remainder``) under ``s`` times the bound."""

        def at(s: float) -> FloatArray:
            value = box(offset(s * law.disturbance))
            return zeros if value is None else value

        return at

    box = grown(lambda grow: grow.hold)
    if law.remainder is None:
        return check.multiple(law.disturbance, law.lmi_term, box, enough)
    sampled = RobustCheck(Q, K, funnel.vertices, funnel.rate, Ts, funnel.rho, law.period)
    remainder = grown(lambda grow: grow.remainder)
    pushed = sampled.multiple(law.disturbance, law.lmi_term, remainder, enough)
    # (I6)'s set of multiples is an interval from 0 too: where it fails at (I6')'s multiple, its
    # own is below it and the larger of the two is (I6')'s (its bisection is not needed)
    if pushed >= enough or not check.holds_at(pushed, law.disturbance, law.lmi_term, box):
        return pushed
    return max(check.multiple(law.disturbance, law.lmi_term, box, enough), pushed)


def reference_substeps(
    scenario: Scenario,
    trajectory: Trajectory,
    shipped: ShippedFunnel,
    state_bounds: Mapping[str, tuple[float, float]],
    disturbance: FloatArray | None = None,
    period: float = 0.0,
    measurement: FloatArray | None = None,
    *,
    rebuilt: Rebuilt | None = None,
) -> np.ndarray:
    """(N,) RK4 steps per sample on which to ship a funnel's reference so that the law's offset
    fits what (F2) and the inputs leave (``funnel.law.law_substeps``), from the first hull of
    ``SEGMENTS`` on which the funnel holds for the exact nominal (and the additive bound
    ``disturbance (n,)``, which takes its share of (F2) first, (I5)); ``BASE_SUBSTEPS``
    everywhere when none does (it will not be certified). ``trajectory``: the nominal on a
    uniform grid. ``period > 0``: the law held every ``period`` s, whose (I6) term takes its
    share first and does not shrink with the grid, as a measurement's (I7) (``measurement
    (n,)``). ``rebuilt``: as ``_under_law``'s."""
    K, Q = shipped.K, shipped.Q
    for funnel, law in _base_laws(
        scenario, trajectory, shipped, state_bounds, disturbance, period, measurement, rebuilt
    ):
        # (I5) with the disturbance and a held law's box, without the interpolation's term
        robust = law.robust_part()
        failure, margins = checked_margins(scenario, trajectory, funnel, state_bounds, robust)
        if failure is not None or margins is None:
            continue
        _, g, _ = tube_extents(Q, K, scenario.position_index)
        room = (
            np.minimum(trajectory.us - scenario.input_lower, scenario.input_upper - trajectory.us)
            - shipped.rho * g
        )
        return law_substeps(law, margins, room, scenario.Ts)
    return np.full(len(K), BASE_SUBSTEPS)


def _base_laws(
    scenario: Scenario,
    trajectory: Trajectory,
    shipped: ShippedFunnel,
    state_bounds: Mapping[str, tuple[float, float]],
    disturbance: FloatArray | None,
    period: float,
    measurement: FloatArray | None,
    rebuilt: Rebuilt | None = None,
) -> Iterator[tuple[Funnel, LawOffset]]:
    """``_under_law`` on a reference grid of ``BASE_SUBSTEPS``, for each of ``SEGMENTS`` whose
    hull can be built, in that order."""
    base = np.full(len(shipped.K), BASE_SUBSTEPS)
    for segments in SEGMENTS:
        try:
            yield _under_law(
                scenario, trajectory, shipped, state_bounds, segments, base, 0.0, disturbance,
                period, measurement, rebuilt,
            )  # fmt: skip
        except (HullError, np.linalg.LinAlgError):
            continue


@dataclass(frozen=True, kw_only=True)
class HeldLawBounds:
    """The boxes of a held or measured law over a funnel's intervals (their largest), a design
    aid: ``hold (n,)`` ``H[k]`` of ``funnel.law`` (I6) (with (I7)'s push), ``held_input (m,)``
    its input part, ``remainder (n,)`` the box (R) of ``funnel.sampled`` (I6') (None: not held,
    only measured)."""

    hold: FloatArray
    held_input: FloatArray
    remainder: FloatArray | None


def held_law_bounds(
    scenario: Scenario,
    trajectory: Trajectory,
    shipped: ShippedFunnel,
    state_bounds: Mapping[str, tuple[float, float]],
    disturbance: FloatArray | None,
    period: float,
    measurement: FloatArray | None = None,
) -> HeldLawBounds | None:
    """The largest ``H[k]``, ``held_input`` and (R) over the intervals of the law held every
    ``period`` s (``funnel.law`` (I6), ``funnel.sampled`` (I6')), with the measurement's box
    ``measurement (n,)`` when given (I7), on the first hull of ``SEGMENTS`` that can be built:
    what a funnel designed for the additive bound ``disturbance + H`` (or ``disturbance + R``
    with (I6')'s pairs) leaves room for, and the part of the input offset that does not shrink
    with the reference grid; None without a hull or a held or measured law. A design aid
    (``stages.funnel``): nothing is certified by it."""
    for _, law in _base_laws(
        scenario, trajectory, shipped, state_bounds, disturbance, period, measurement
    ):
        if law.hold is not None and law.held_input is not None:
            return HeldLawBounds(
                hold=np.asarray(law.hold.max(axis=0), dtype=np.float64),
                held_input=np.asarray(law.held_input.max(axis=0), dtype=np.float64),
                remainder=(
                    None
                    if law.remainder is None
                    else np.asarray(law.remainder.max(axis=0), dtype=np.float64)
                ),
            )
    return None


def recheck_as_shipped(
    scenario: Scenario,
    trajectory: Trajectory,
    shipped: ShippedFunnel,
    state_bounds: Mapping[str, tuple[float, float]],
    disturbance: FloatArray | None = None,
    period: float = 0.0,
    measurement: FloatArray | None = None,
    *,
    multiple: bool = True,
) -> FunnelRecheck:
    """``recheck_funnel`` as the certify stage will run it on the emitted file: the nominal from
    ``trajectory``'s start and inputs on a uniform grid of ``BASE_SUBSTEPS``, the law tracking the
    reference on the grid the controller stage ships (``reference_substeps``), under the additive
    bound ``disturbance (n,)`` when given, held every ``period`` s when it is > 0 (I6), seeing
    the state within ``measurement (n,)`` when given (I7). ``multiple``: as ``recheck_funnel``'s.
    The two rebuild the same hulls (the nominal, funnel and bounds are the same): once each."""
    nominal = simulate(
        scenario.dynamics, trajectory.xs[0], trajectory.us, scenario.Ts, BASE_SUBSTEPS
    )
    rebuilt = Rebuilt(scenario, nominal, shipped, state_bounds)
    substeps = reference_substeps(
        scenario, nominal, shipped, state_bounds, disturbance, period, measurement,
        rebuilt=rebuilt,
    )  # fmt: skip
    return recheck_funnel(
        scenario, nominal, shipped, state_bounds, substeps, disturbance=disturbance,
        period=period, measurement=measurement, multiple=multiple, rebuilt=rebuilt,
    )  # fmt: skip
