"""The emitted lookup feedback controller, formats ``safety-controller/1`` and ``/2``
(documented in docs/controller-file.md).

This module needs only NumPy and the standard library, so ``controller.json`` can be run
without the pipeline installed (copy this file). ``/1`` carries one gain ``K`` and metric ``P``
for every trajectory (the ``feedback`` block); ``/2`` (a funnel per trajectory) carries on each
trajectory ``K (N, m, n)``, the gain on sample interval ``k``, and ``P (N+1, n, n)``, the metric
at ``t_k = k Ts``, with ``Q = P^-1`` linear in t between samples (``metric_interpolation``
``"inverse-linear"``): ``P(t) = ((1 - s) P[k]^-1 + s P[k+1]^-1)^-1``, ``s = t / Ts - k``. A
``/1`` file is read as the constant case (``K[k] = K``, ``P(t) = P``). Control law:

1. ``select(x0) -> (index, ratio)``: the trajectory ``i`` minimising ``||x0 - x0_i||_{P_i(0)} /
   radius_i`` and that value. ``x0`` is covered (inside the certificate) when the ratio is
   ``< 1``; a start with ratio ``>= 1`` is outside every certified ball and nothing is claimed
   for it (``select(x0, strict=True)`` raises ``UncoveredStartError`` instead);
2. ``controller(t, x, index)``: for ``t <= T_i``, ``u = clip(u_ref_i[k] + K_i[k] (x -
   x_ref_i(t)), lower, upper)``, ``k = floor(t / Ts)``, with ``x_ref_i`` linearly
   interpolated on the trajectory's grid ``t`` (equal RK4 steps inside each sample interval,
   finer on some intervals than others); for ``t > T_i`` the terminal law ``u =
   clip(u_eq + K_T (x - x_eq))`` of the optional ``terminal`` block (its certified invariant
   ellipsoid ``(x - x_eq)^T P_T (x - x_eq) <= level`` lies in Goal and holds every end
   tube; with its optional ``disturbance (n,)`` it is invariant for ``x' = f(x, u) + w``, any
   ``|w_i| <= disturbance_i``), or ``BeyondHorizonError`` when the file has none: the law is
   never extrapolated past ``T``.

What a ``/2`` file certifies: the funnel ``E_i(t) = {x : (x - x_ref_i(t))^T P_i(t) (x - x_ref_i(t))
<= radius_i^2 e^{-2 rate_i t}}`` about the exact nominal (the solution from ``x0_i`` under
``u_ref_i``; ``t`` and ``x_ref`` carry it on a grid) is invariant under this law, its interpolation
of ``x_ref`` included: the pipeline's certify stage bounds that interpolation error soundly on
every sample interval (``interpolation_error_P_norm`` is only a measured estimate of it).

Gain convention: ``u = u_ref + K e`` with ``e = x - x_ref``, so a stabilising ``K`` is the
*negative* of ``control.lqr``'s gain (which is written ``u = -K x``).

The controller is immutable (a frozen dataclass over read-only arrays): nothing is stored by
``select``, the caller passes the selected ``index`` to every call, and ``with_gain(scale)``
returns a new controller. Both accept a batch: ``x0 (B, n)`` gives ``index (B,)``, and ``x (B,
n)`` is then controlled row by row; a single state ``(n,)`` with a scalar index works too. A NaN
or infinite component of ``x0``, ``x`` or ``t`` is a ``ValueError`` naming it (field, index,
state name), from ``select`` and the law alike: NaN would pass the clip to the actuator.

``load`` reads a regular file of at most ``MAX_BYTES`` (256 MiB; a FIFO, device or folder is
refused without waiting on it, a symbolic-link loop is one line) and validates every field of the
file; anything wrong (a missing or mistyped field, a
shape, a non-positive radius or ``Ts``, ``lower > upper``, ``P`` not positive definite, times
that do not increase, ``T`` that disagrees with ``t`` and ``u_ref``, bytes that are not UTF-8
JSON) raises ``ControllerFormatError`` naming the field. The optional fields (``terminal``,
``feedback_period``, ``interpolation_error_P_norm``, each trajectory's ``name``, the demo it
was made from; in ``/2`` also ``feedback``, each trajectory's ``rate`` and ``uncertainty``, the
declared bounds the funnels hold, with its optional ``measurement_bound``) may be absent: files
written before they existed still load.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import stat
import threading
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

FORMAT = "safety-controller/1"
FUNNEL_FORMAT = "safety-controller/2"
INVERSE_LINEAR = "inverse-linear"  # Q = P^-1 linear in t between samples
TIME_TOLERANCE = 1e-9  # relative, for t[0] = 0 and t[-1] = T
SAMPLE_TOLERANCE = 1e-6  # in samples, for T = N Ts
SYMMETRY_TOLERANCE = 1e-9  # relative, for P = P^T
MAX_BYTES = 256 * 2**20  # a controller.json read: 9 funnel trajectories take 1.5 MB


class ControllerFormatError(ValueError):
    """``controller.json`` is not a valid ``safety-controller/1`` or ``/2`` file; the message says
    where."""

    exit_code = 2


class UncoveredStartError(ValueError):
    """``select(x0, strict=True)`` on a start outside every certified initial ball."""


class BeyondHorizonError(ValueError):
    """The law was asked for ``t > T`` and the file has no certified terminal controller."""


def _named(index: np.ndarray, count: int) -> np.ndarray:
    """The trajectories ``index (...)`` names, sorted; an ``IndexError`` if one is not in
    ``0 .. count - 1``."""
    if index.size and not np.issubdtype(index.dtype, np.integer):
        raise IndexError(f"trajectory indices must be integers, found dtype {index.dtype}")
    named = index.reshape(1) if index.ndim == 0 else np.unique(index)  # one: a law call
    if len(named) and (named[0] < 0 or named[-1] >= count):
        bad = named[-1] if named[-1] >= count else named[0]
        raise IndexError(f"trajectory index {bad} out of range: the file has {count} (0..)")
    return named


def _groups(index: np.ndarray, count: int) -> list[tuple[int, np.ndarray | slice]]:
    """``(i, rows)`` for each trajectory ``i`` that ``index (...)`` names (``0 <= i < count``),
    ``rows`` selecting its entries (all at once when they name one trajectory, as in a batch
    flown around one)."""
    named = _named(index, count)
    if len(named) == 0:
        return []
    if len(named) == 1:
        return [(int(named[0]), slice(None))]
    return [(int(i), index == i) for i in named]


def _frozen(array: np.ndarray) -> np.ndarray:
    array = np.array(array, dtype=np.float64)
    array.flags.writeable = False
    return array


def _short(vector: np.ndarray) -> str:
    """``vector (k,)`` as a short list for a repr: 4 significant digits."""
    return "[" + ", ".join(f"{v:.4g}" for v in np.asarray(vector).ravel()) + "]"


def _repeated(matrix: np.ndarray, count: int) -> np.ndarray:
    """``(count, *matrix.shape)``: one matrix repeated, as a read-only view (a /1 file)."""
    return np.broadcast_to(matrix, (count, *matrix.shape))


def _finite(field: str, value: np.ndarray, expected: str, names: tuple[str, ...] = ()) -> None:
    """``ValueError`` naming the first entry of ``value (...)`` that is NaN or infinite: the
    ``field``, the entry's index and, with ``names`` (of the last axis), its component."""
    if np.isfinite(value).all():  # 1.5-3 us on a state, against ~60 us for the law's call
        return
    where = tuple(int(i) for i in np.argwhere(~np.isfinite(value))[0])
    label = field + (f"[{', '.join(map(str, where))}]" if where else "")
    if where and len(names) == value.shape[-1]:
        label += f" ({names[where[-1]]})"
    raise ValueError(f"{label} = {value[where]}; expected {expected}")


@dataclass(frozen=True, kw_only=True)
class ReferenceTrajectory:
    """One nominal trajectory with its tube ``||x - x_ref(t)||_{P(t)} <= radius e^{-rate t}``.

    Attributes:
      x0: (n,); u_ref: (N, m); t: (r,) and x_ref: (r, n) the fine grid; K: (N, m, n) the gain
      on sample interval ``k``; P: (N+1, n, n) the metric at ``t_k``; rate: lambda (1/s). In a
      ``/1`` file K and P are the ``feedback`` block's, repeated (read-only views). name: the
      demonstration it was made from (``"demo_01"``; None in a file written without names).
    """

    x0: np.ndarray
    radius: float
    T: float
    u_ref: np.ndarray
    t: np.ndarray
    x_ref: np.ndarray
    K: np.ndarray
    P: np.ndarray
    rate: float
    name: str | None = None

    def __repr__(self) -> str:
        name = "" if self.name is None else f"{self.name!r}, "
        return (
            f"ReferenceTrajectory({name}T={self.T:g} s, radius={self.radius:.4g}, "
            f"rate={self.rate:.4g}, N={len(self.u_ref)} samples, x0={_short(self.x0)})"
        )

    def metric(self, t: np.ndarray | float, Ts: float) -> np.ndarray:
        """``P(t)`` for times ``t (...)`` -> ``(..., n, n)`` (``inverse_linear``); a repeated
        metric (a ``/1`` file: a read-only view with stride 0) is returned as it is."""
        t = np.asarray(t, dtype=np.float64)
        if self.P.strides[0] == 0:
            return np.broadcast_to(self.P[0], (*t.shape, *self.P.shape[1:]))
        return inverse_linear(self.P, Ts, t)


def inverse_linear(P: np.ndarray, Ts: float, t: np.ndarray | float) -> np.ndarray:
    """The metric ``P(t)`` at times ``t (...)`` -> ``(..., n, n)`` from ``P (N+1, n, n)`` at
    ``t_k = k Ts``: ``Q = P^-1`` linear in t on each sample interval, ``P(t) = ((1 - s) Q[k] + s
    Q[k+1])^-1``, ``k = floor(t / Ts)``, ``s = t / Ts - k``, held at the ends outside
    ``[0, N Ts]``."""
    t = np.asarray(t, dtype=np.float64)
    k = np.clip(np.floor(t / Ts + 1e-9).astype(np.int64), 0, len(P) - 2)
    s = np.clip(t / Ts - k, 0.0, 1.0)[..., None, None]
    Q = np.linalg.inv(P)
    Q = (Q + np.swapaxes(Q, -1, -2)) / 2
    M = np.linalg.inv((1 - s) * Q[k] + s * Q[k + 1])
    return (M + np.swapaxes(M, -1, -2)) / 2


@dataclass(frozen=True, kw_only=True)
class TerminalController:
    """The law after ``T``: ``u = clip(u_eq + K (x - x_eq))``, certified on its ellipsoid.

    Attributes:
      x_eq: (n,) and u_eq: (m,) an equilibrium, ``f(x_eq, u_eq) = 0``, inside Goal.
      K: (m, n) gain (sign of ``u = u_eq + K e``); P: (n, n) Lyapunov matrix.
      level: the certified invariant set is ``(x - x_eq)^T P (x - x_eq) <= level``.
      disturbance: (n,) the additive bound ``|w_i| <= disturbance_i`` on ``x'`` the set was
        certified invariant for (None: the file states none, the exact model); below the
        file's ``uncertainty.additive_bound``, the declared disturbance plus the parameters'
        term at ``(x_eq, u_eq)``, the parameter intervals held in the certificate's Jacobian
        hull ((T7) of ``pipeline.numerics.terminal.check``).
    """

    x_eq: np.ndarray
    u_eq: np.ndarray
    K: np.ndarray
    P: np.ndarray
    level: float
    disturbance: np.ndarray | None = None

    def __repr__(self) -> str:
        return (
            f"TerminalController(x_eq={_short(self.x_eq)}, u_eq={_short(self.u_eq)}, "
            f"level={self.level:.4g})"
        )

    def value(self, x: np.ndarray) -> np.ndarray:
        """``V(x) = (x - x_eq)^T P (x - x_eq)`` for ``x (..., n)`` -> ``(...)``."""
        e = np.asarray(x, dtype=np.float64) - self.x_eq
        return np.einsum("...i,ij,...j->...", e, self.P, e)

    def unclipped(self, x: np.ndarray) -> np.ndarray:
        """``u_eq + K (x - x_eq)`` for ``x (..., n)`` -> ``(..., m)``."""
        return self.u_eq + (np.asarray(x, dtype=np.float64) - self.x_eq) @ self.K.T


@dataclass(frozen=True, kw_only=True)
class Controller:
    """``u = clip(u_ref_i(t) + K_i[k] (x - x_ref_i(t)))`` around trajectory ``i`` from ``select``.

    Attributes:
      K: (m, n) gain; P: (n, n) contraction metric; rate: lambda (1/s): the ``feedback`` block
        (None in a ``/2`` file without one; each trajectory carries its own K, P and rate).
      lower, upper: (m,) input bounds the law clips to.
      trajectories: the reference trajectories with their initial balls.
      interpolation_error: the file's stated P-norm error of interpolating ``x_ref`` (0 if
        absent).
      terminal: the certified law after ``T`` (None: the law refuses ``t > T``).
      feedback_period: the feedback period ``h`` (s) the certificate assumes: the state is
        measured and ``u`` recomputed every ``h`` seconds and held in between (0: continuous).
      disturbance_bound: (n,) ``b``: the funnels hold for ``x' = f(x, u) + w``, ``|w_i| <= b_i``,
        the scenario's declared disturbance and parameter intervals as one additive term (the
        file's ``uncertainty.additive_bound``); None: the exact model.
      measurement_bound: (n,) ``E``: the law may see the state with any error ``|eta_i| <=
        E_i`` (the file's ``uncertainty.measurement_bound``); None: the state measured exactly.
    """

    scenario: str
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    Ts: float
    lower: np.ndarray
    upper: np.ndarray
    K: np.ndarray | None
    P: np.ndarray | None
    rate: float | None
    trajectories: tuple[ReferenceTrajectory, ...]
    interpolation_error: float = 0.0
    terminal: TerminalController | None = None
    feedback_period: float = 0.0
    disturbance_bound: np.ndarray | None = None
    measurement_bound: np.ndarray | None = None
    source: str = "controller.json"
    format: str = FORMAT

    @property
    def funnel(self) -> bool:
        """A ``/2`` file: a time-varying gain and metric per trajectory."""
        return self.format == FUNNEL_FORMAT

    @property
    def n(self) -> int:
        return len(self.state_names)

    @property
    def m(self) -> int:
        return len(self.input_names)

    def label(self, index: int) -> str:
        """Trajectory ``index`` as every output names it (the report, the terminal, ``repr``,
        the examples): ``"0: demo_01"``, its index in ``trajectories`` (from 0, what ``select``
        returns) and the demonstration it was made from; ``"0"`` in a file without names."""
        name = self.trajectories[index].name
        return f"{index}: {name}" if name else str(index)

    def labels(self, most: int = 6) -> list[str]:
        """Every trajectory's ``label``; beyond ``most``, the first four, ``...`` and the last."""
        labels = [self.label(i) for i in range(len(self.trajectories))]
        return [*labels[:4], "...", labels[-1]] if len(labels) > most else labels

    def __repr__(self) -> str:
        """A few lines: what the file is, its trajectories (``index: name``) and its law."""
        horizons = [tr.T for tr in self.trajectories]
        span = f"{min(horizons):g}" + (
            "" if min(horizons) == max(horizons) else f"-{max(horizons):g}"
        )
        labels = self.labels()
        named = ", index: name" if any(tr.name for tr in self.trajectories) else ""
        if self.funnel:
            kind = "funnel (a gain K_i[k] and metric P_i(t) per trajectory; /2)"
        else:
            kind = f"constant (one gain K and metric P, rate {self.rate:.3g}/s; /1)"
        inputs = ", ".join(
            f"{name} in [{lo:g}, {hi:g}]"
            for name, lo, hi in zip(self.input_names, self.lower, self.upper, strict=True)
        )
        if self.terminal is None:
            terminal = "no (the law refuses t > T)"
        else:
            terminal = (
                f"yes (after T: u = u_eq + K_T (x - x_eq), x_eq {_short(self.terminal.x_eq)})"
            )
        h = self.feedback_period
        period = f"{h:g} s (held between samples)" if h > 0 else "0 (continuous)"
        if self.disturbance_bound is not None:
            kind += f", robust to |w| <= {_short(self.disturbance_bound)}"
        if self.measurement_bound is not None:
            kind += f", to measurement errors |eta| <= {_short(self.measurement_bound)}"
        return "\n".join([
            f"Controller({self.format}, scenario {self.scenario!r}, from {self.source})",
            f"  states: {', '.join(self.state_names)}; Ts {self.Ts:g} s",
            f"  inputs: {inputs}",
            f"  certificate: {kind}",
            f"  trajectories ({len(self.trajectories)}{named}): {', '.join(labels)}",
            f"  horizons T: {span} s",
            f"  terminal: {terminal}",
            f"  feedback period: {period}",
            "  use: index, ratio = c.select(x0); u = c(t, x, index)",
        ])  # fmt: skip

    def with_gain(self, scale: float) -> Controller:
        """A new controller with gain ``scale K`` (e.g. 0: the reference replayed open loop)."""
        K = None if self.K is None else _frozen(scale * self.K)
        trajectories = tuple(
            dataclasses.replace(tr, K=_frozen(scale * tr.K)) for tr in self.trajectories
        )
        return dataclasses.replace(self, K=K, trajectories=trajectories)

    def ratios(self, x0: np.ndarray) -> np.ndarray:
        """``||x0 - x0_i||_{P_i(0)} / radius_i`` for ``x0 (..., n)`` -> ``(..., k)``."""
        centres = np.stack([tr.x0 for tr in self.trajectories])  # (k, n)
        metrics = np.stack([tr.P[0] for tr in self.trajectories])  # (k, n, n)
        radii = np.array([tr.radius for tr in self.trajectories])  # (k,)
        e = np.asarray(x0, dtype=np.float64)[..., None, :] - centres  # (..., k, n)
        return np.sqrt(np.einsum("...ki,kij,...kj->...k", e, metrics, e)) / radii

    def metric(self, t: float, index: np.ndarray | int) -> np.ndarray:
        """The tube metric ``P_i(t)`` of trajectories ``index (...)`` -> ``(..., n, n)``: the
        tube is ``||x - x_ref_i(t)||_{P_i(t)} <= radius_i e^{-rate_i t}``."""
        return self._gather(index, (self.n, self.n), lambda tr: tr.metric(t, self.Ts))

    def _gather(
        self, index: np.ndarray | int, shape: tuple[int, ...], value: Callable[..., np.ndarray]
    ) -> np.ndarray:
        """``value(trajectory) (*shape)`` of trajectories ``index (...)`` -> ``(..., *shape)``."""
        index = np.asarray(index)
        out = np.empty((*index.shape, *shape))
        for i, rows in _groups(index, len(self.trajectories)):
            out[rows] = value(self.trajectories[i])
        return out

    def select(self, x0: np.ndarray, *, strict: bool = False) -> tuple[Any, Any]:
        """For initial states ``x0 (..., n)``: ``(index (...), coverage_ratio (...))``, the
        trajectory to follow and ``min_i ||x0 - x0_i||_P / radius_i``; for one state ``(n,)``
        a Python ``int`` and ``float`` (hence ``Any`` in the signature: the kind follows the
        shape, which the type does not carry).

        A ratio ``< 1`` means covered. A start with ratio ``>= 1`` lies outside every certified
        ball: it still gets the nearest trajectory (in the ratio), with no guarantee; with
        ``strict=True`` such a start raises ``UncoveredStartError`` instead. A start with a NaN
        or infinite component, or whose last dimension is not ``n``, is a ``ValueError`` naming
        it (it has no ratio to compare).
        """
        x0 = self._states("x0", x0)
        _finite("x0", x0, "a finite start", self.state_names)
        ratios = self.ratios(x0)
        index = np.argmin(ratios, axis=-1)
        ratio = np.take_along_axis(ratios, index[..., None], axis=-1)[..., 0]
        if strict and np.any(ratio >= 1.0):
            flat = np.ravel(ratio)
            k = int(np.argmax(flat >= 1.0))
            start = x0.reshape(-1, self.n)[k]
            raise UncoveredStartError(
                f"start {np.round(start, 6).tolist()} is not covered by the certificate "
                f"(coverage ratio {flat[k]:.3g} >= 1; nothing is claimed for it): start inside "
                "Init, or pass strict=False to fly the nearest trajectory without a guarantee"
            )
        if x0.ndim == 1:
            return int(index), float(ratio)
        return index, ratio

    def _states(self, field: str, x: np.ndarray) -> np.ndarray:
        """``x`` as float64 ``(..., n)``; a ``ValueError`` naming ``field`` and the expected
        shape otherwise."""
        x = np.asarray(x, dtype=np.float64)
        if x.ndim == 0 or x.shape[-1] != self.n:
            raise ValueError(
                f"{field} has shape {x.shape}; expected ({self.n},) for one state "
                f"({', '.join(self.state_names)}) or (B, {self.n}) for a batch of B"
            )
        return x

    def reference(self, t: float, index: np.ndarray | int) -> tuple[np.ndarray, np.ndarray]:
        """``(u_ref (..., m), x_ref (..., n))`` of trajectories ``index (...)`` at time ``t``."""
        index = np.asarray(index)
        u = np.empty((*index.shape, self.m))
        x = np.empty((*index.shape, self.n))
        for i, rows in _groups(index, len(self.trajectories)):
            tr = self.trajectories[i]
            k = min(int(np.floor(t / self.Ts + 1e-9)), len(tr.u_ref) - 1)
            u[rows] = tr.u_ref[max(k, 0)]
            x[rows] = [np.interp(t, tr.t, tr.x_ref[:, j]) for j in range(self.n)]
        return u, x

    def gains(self, t: float, index: np.ndarray | int) -> np.ndarray:
        """``K_i[floor(t / Ts)]`` of trajectories ``index (...)`` -> ``(..., m, n)``."""
        k = max(int(np.floor(t / self.Ts + 1e-9)), 0)
        return self._gather(index, (self.m, self.n), lambda tr: tr.K[min(k, len(tr.K) - 1)])

    def unclipped(self, t: float, x: np.ndarray, index: np.ndarray | int) -> np.ndarray:
        """``u_ref + K[k] (x - x_ref)`` before clipping, ``x (..., n)`` -> ``(..., m)``."""
        u_ref, x_ref = self.reference(t, index)
        e = np.asarray(x) - x_ref
        return u_ref + np.einsum("...ji,...i->...j", self.gains(t, index), e)

    def horizons(self, index: np.ndarray | int) -> np.ndarray:
        """``T_i`` (s) of trajectories ``index (...)`` -> ``(...)``."""
        index = np.asarray(index)
        _named(index, len(self.trajectories))  # refuses an index out of range
        return np.array([tr.T for tr in self.trajectories])[index]

    def __call__(self, t: float, x: np.ndarray, index: np.ndarray | int) -> np.ndarray:
        """The control input at time ``t`` for states ``x (..., n)`` following trajectories
        ``index (...)`` (from ``select``) -> ``(..., m)``.

        Past a trajectory's ``T`` the terminal law applies; without a terminal controller
        ``t > T`` raises ``BeyondHorizonError`` (the certificate ends at ``T``). A NaN or
        infinite ``t`` or state component is a ``ValueError`` naming it: no input is certified
        for it, and a NaN would pass through the clip to the actuator; so is a negative ``t`` and
        ``x`` whose last dimension is not ``n``.
        """
        x = self._states("x", x)
        if not math.isfinite(t):
            raise ValueError(f"t = {t}; expected a finite time (s)")
        if t < 0:
            raise ValueError(f"t = {t:g} s; expected a time >= 0 (s) since the start")
        _finite("x", x, "a finite state", self.state_names)
        T = self.horizons(index)
        after = t > T * (1 + TIME_TOLERANCE)  # (...)
        if not np.any(after):
            return np.clip(self.unclipped(t, x, index), self.lower, self.upper)
        if self.terminal is None:
            raise BeyondHorizonError(
                f"t = {t:g} s is past the trajectory's horizon T = {float(np.min(T)):g} s and "
                f"{self.source} has no terminal controller (no certified capture in Goal): the "
                "law is certified on [0, T] only"
            )
        raw = self.terminal.unclipped(x)
        if not np.all(after):
            raw = np.where(after[..., None], raw, self.unclipped(t, x, index))
        return np.clip(raw, self.lower, self.upper)


class _Reader:
    """Validates one decoded document field by field; every failure names the field."""

    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, field: str, found: object, expected: str) -> NoReturn:
        text = repr(found)
        if len(text) > 80:
            text = text[:77] + "..."
        raise ControllerFormatError(f"{self.source}: {field}: found {text}; expected {expected}")

    def mapping(self, field: str, value: object, keys: tuple[str, ...]) -> Mapping[str, Any]:
        if not isinstance(value, dict):
            self.fail(field, _kind(value), "a JSON object")
        for key in keys:
            if key not in value:
                self.fail(f"{field}.{key}".lstrip("."), "nothing (missing field)", "this field")
        return value

    def names(self, field: str, value: object) -> tuple[str, ...]:
        if not (isinstance(value, list) and value and all(isinstance(v, str) for v in value)):
            self.fail(field, _scalar_or_kind(value), "a non-empty list of names")
        if len(set(value)) != len(value):
            self.fail(field, value, "distinct names")
        return tuple(value)

    def number(self, field: str, value: object, *, positive: bool = False) -> float:
        if type(value) not in (int, float):
            self.fail(field, _scalar_or_kind(value), "a number")
        try:
            x = float(value)  # type: ignore[arg-type]
        except OverflowError:
            self.fail(field, "a number too large for float64", "a finite number")
        if not math.isfinite(x):
            self.fail(field, x, "a finite number")
        if positive and not x > 0:
            self.fail(field, x, "a number > 0")
        return x

    def array(self, field: str, value: object, shape: tuple[int | None, ...]) -> np.ndarray:
        """A finite float64 array of ``shape`` (None: any length >= 1) from nested lists."""
        rows: list[object] = [value]
        found: list[int] = []
        for depth in range(len(shape)):
            lists = [r for r in rows if isinstance(r, list)]
            if len(lists) < len(rows):
                what = "a number" if depth else _kind(value)
                self.fail(field, what, f"nested lists of shape {_shape_text(shape)}")
            lengths = {len(r) for r in lists}
            if len(lengths) > 1:
                self.fail(field, "ragged lists", f"shape {_shape_text(shape)}")
            found.append(lengths.pop() if lengths else 0)
            rows = [item for r in lists for item in r]
        if any(
            length == 0 or (size is not None and length != size)
            for length, size in zip(found, shape, strict=True)
        ):
            self.fail(field, f"shape {tuple(found)}", f"shape {_shape_text(shape)}")
        if not all(type(v) in (int, float) for v in rows):
            bad = next(v for v in rows if type(v) not in (int, float))
            self.fail(field, _scalar_or_kind(bad), "numbers")
        try:
            array = np.array(value, dtype=np.float64)
        except OverflowError:
            self.fail(field, "a number too large for float64", "finite numbers")
        if not np.all(np.isfinite(array)):
            self.fail(field, "a non-finite value", "finite numbers")
        return array


def _kind(value: object) -> str:
    return {dict: "an object", list: "a list", str: "a string", type(None): "null"}.get(
        type(value), type(value).__name__
    )


def _scalar_or_kind(value: object) -> object:
    """The value itself when it is a scalar (short to quote), else what kind of thing it is."""
    return value if isinstance(value, str | int | float | None) else _kind(value)


def _shape_text(shape: tuple[int | None, ...]) -> str:
    return (
        "("
        + ", ".join("any" if s is None else str(s) for s in shape)
        + (",)" if len(shape) == 1 else ")")
    )


def _trajectory(
    read: _Reader,
    where: str,
    item: object,
    n: int,
    m: int,
    Ts: float,
    feedback: tuple[np.ndarray, np.ndarray, float] | None,
) -> ReferenceTrajectory:
    """One trajectory; ``feedback = (K, P, rate)`` of a /1 file, None: its own (a /2 file)."""
    own = ("K", "P") if feedback is None else ()
    item = read.mapping(where, item, ("x0", "radius", "T", "u_ref", "t", "x_ref", *own))
    x0 = read.array(f"{where}.x0", item["x0"], (n,))
    radius = read.number(f"{where}.radius", item["radius"], positive=True)
    T = read.number(f"{where}.T", item["T"], positive=True)
    u_ref = read.array(f"{where}.u_ref", item["u_ref"], (None, m))
    t = read.array(f"{where}.t", item["t"], (None,))
    x_ref = read.array(f"{where}.x_ref", item["x_ref"], (len(t), n))
    tolerance = TIME_TOLERANCE * max(1.0, T)
    if len(t) < 2 or not np.all(np.diff(t) > 0):
        read.fail(f"{where}.t", "times that do not increase", "strictly increasing times")
    if abs(t[0]) > tolerance or abs(t[-1] - T) > tolerance:
        read.fail(f"{where}.t", f"[{t[0]:g} .. {t[-1]:g}]", f"times from 0 to T = {T:g}")
    N = len(u_ref)
    if abs(N * Ts - T) > SAMPLE_TOLERANCE * Ts:
        read.fail(f"{where}.u_ref", f"{N} rows", f"T / Ts = {T:g} / {Ts:g} = {T / Ts:g} rows")
    if feedback is None:
        K = _frozen(read.array(f"{where}.K", item["K"], (N, m, n)))
        P = read.array(f"{where}.P", item["P"], (N + 1, n, n))
        for k, P_k in enumerate(P):
            _metric(read, f"{where}.P[{k}]", P_k)
        P = _frozen((P + np.swapaxes(P, 1, 2)) / 2)
        rate = read.number(f"{where}.rate", item.get("rate", 0.0))
        if rate < 0:
            read.fail(f"{where}.rate", rate, "a number >= 0")
    else:
        K, P, rate = _repeated(feedback[0], N), _repeated(feedback[1], N + 1), feedback[2]
    name = item.get("name")
    if name is not None and not (isinstance(name, str) and name):
        read.fail(f"{where}.name", _scalar_or_kind(name), "a non-empty string (the demo's name)")
    return ReferenceTrajectory(
        x0=_frozen(x0), radius=radius, T=T, u_ref=_frozen(u_ref), t=_frozen(t),
        x_ref=_frozen(x_ref), K=K, P=P, rate=rate, name=name,
    )  # fmt: skip


def _terminal(read: _Reader, item: object, n: int, m: int) -> TerminalController:
    item = read.mapping("terminal", item, ("x_eq", "u_eq", "K", "P", "level"))
    P = read.array("terminal.P", item["P"], (n, n))
    _metric(read, "terminal.P", P)
    return TerminalController(
        x_eq=_frozen(read.array("terminal.x_eq", item["x_eq"], (n,))),
        u_eq=_frozen(read.array("terminal.u_eq", item["u_eq"], (m,))),
        K=_frozen(read.array("terminal.K", item["K"], (m, n))),
        P=_frozen((P + P.T) / 2),
        level=read.number("terminal.level", item["level"], positive=True),
        disturbance=(
            None
            if item.get("disturbance") is None
            else _bound(read, "terminal.disturbance", item["disturbance"], n)
        ),
    )


def _bound(read: _Reader, field: str, value: object, n: int) -> np.ndarray:
    """A bound ``(n,)`` of the file (``field``): finite and ``>= 0``, read-only."""
    bound = read.array(field, value, (n,))
    if np.any(bound < 0):
        j = int(np.argmax(bound < 0))
        read.fail(f"{field}[{j}]", float(bound[j]), "a number >= 0")
    return _frozen(bound)


def _metric(read: _Reader, field: str, P: np.ndarray) -> None:
    """``P`` must be symmetric positive definite."""
    if np.max(np.abs(P - P.T)) > SYMMETRY_TOLERANCE * np.max(np.abs(P)):
        read.fail(field, "a non-symmetric matrix", "a symmetric positive definite matrix")
    smallest = float(np.linalg.eigvalsh((P + P.T) / 2)[0])
    if not smallest > 0:
        read.fail(field, f"smallest eigenvalue {smallest:.3g}", "a positive definite matrix")


def parse(data: object, source: str = "controller.json") -> Controller:
    """Validate a decoded ``controller.json`` document (``/1`` or ``/2``) and build the
    controller."""
    read = _Reader(source)
    if isinstance(data, dict) and data.get("format") == FUNNEL_FORMAT:
        required: tuple[str, ...] = ("metric_interpolation",)
    else:
        required = ("feedback",)
    top = read.mapping(
        "(top level)" if not isinstance(data, dict) else "",
        data,
        ("format", "scenario", "state_names", "input_names", "Ts", "input_bounds", *required,
         "trajectories"),
    )  # fmt: skip
    if top["format"] not in (FORMAT, FUNNEL_FORMAT):
        read.fail("format", top["format"], f"'{FORMAT}' or '{FUNNEL_FORMAT}'")
    funnel = top["format"] == FUNNEL_FORMAT
    if funnel and top["metric_interpolation"] != INVERSE_LINEAR:
        read.fail(
            "metric_interpolation",
            _scalar_or_kind(top["metric_interpolation"]),
            f"'{INVERSE_LINEAR}' (P^-1 linear in t between samples)",
        )
    if not isinstance(top["scenario"], str):
        read.fail("scenario", _kind(top["scenario"]), "a string")
    state_names = read.names("state_names", top["state_names"])
    input_names = read.names("input_names", top["input_names"])
    n, m = len(state_names), len(input_names)
    Ts = read.number("Ts", top["Ts"], positive=True)
    bounds = read.mapping("input_bounds", top["input_bounds"], ("lower", "upper"))
    lower = read.array("input_bounds.lower", bounds["lower"], (m,))
    upper = read.array("input_bounds.upper", bounds["upper"], (m,))
    if np.any(lower > upper):
        j = int(np.argmax(lower > upper))
        read.fail(f"input_bounds.lower[{j}]", float(lower[j]), f"<= upper bound {upper[j]:g}")
    K = P = rate = None
    if top.get("feedback") is not None or not funnel:
        feedback = read.mapping("feedback", top["feedback"], ("K", "P", "rate"))
        K = _frozen(read.array("feedback.K", feedback["K"], (m, n)))
        P = read.array("feedback.P", feedback["P"], (n, n))
        _metric(read, "feedback.P", P)
        P = _frozen((P + P.T) / 2)
        rate = read.number("feedback.rate", feedback["rate"], positive=True)
    items = top["trajectories"]
    if not isinstance(items, list):
        read.fail("trajectories", _scalar_or_kind(items), "a list of trajectories")
    if not items:
        read.fail("trajectories", "an empty list", "at least one trajectory")
    shared = None if funnel else (K, P, rate)
    trajectories = tuple(
        _trajectory(read, f"trajectories[{i}]", item, n, m, Ts, shared)  # type: ignore[arg-type]
        for i, item in enumerate(items)
    )
    error = top.get("interpolation_error_P_norm", 0.0)
    error = read.number("interpolation_error_P_norm", error)
    if error < 0:
        read.fail("interpolation_error_P_norm", error, "a number >= 0")
    period = read.number("feedback_period", top.get("feedback_period", 0.0))
    if period < 0:
        read.fail("feedback_period", period, "a number >= 0 (0: continuous feedback)")
    terminal = top.get("terminal")
    terminal = None if terminal is None else _terminal(read, terminal, n, m)
    bound = measurement = None
    if top.get("uncertainty") is not None:
        block = read.mapping("uncertainty", top["uncertainty"], ("additive_bound",))
        bound = _bound(read, "uncertainty.additive_bound", block["additive_bound"], n)
        if block.get("measurement_bound") is not None:
            measurement = _bound(
                read, "uncertainty.measurement_bound", block["measurement_bound"], n
            )
    return Controller(
        scenario=top["scenario"],
        state_names=state_names,
        input_names=input_names,
        Ts=Ts,
        lower=_frozen(lower),
        upper=_frozen(upper),
        K=K,
        P=P,
        rate=rate,
        trajectories=trajectories,
        interpolation_error=error,
        terminal=terminal,
        feedback_period=period,
        disturbance_bound=bound,
        measurement_bound=measurement,
        source=source,
        format=top["format"],
    )


_LOADED: OrderedDict[tuple[str, str], Controller] = OrderedDict()  # (path, SHA-256) -> parsed
_LOADED_MAX = 4
_LOADED_LOCK = threading.Lock()


def load(path: str | Path) -> Controller:
    """Read and validate ``controller.json``; a bad file raises ``ControllerFormatError``.

    The file is read on every call; a file with the same path and the same bytes (SHA-256) as
    one of the last few loaded in this process gives that (immutable) controller again instead
    of being parsed anew (~30 ms for a 1.5 MB file): any change of the bytes is a new parse."""
    path = Path(path)
    raw = _read(path)
    key = (str(path), hashlib.sha256(raw).hexdigest())
    with _LOADED_LOCK:
        if key in _LOADED:
            _LOADED.move_to_end(key)
            return _LOADED[key]
    controller = _parse_bytes(raw, path)
    with _LOADED_LOCK:
        _LOADED[key] = controller
        while len(_LOADED) > _LOADED_MAX:
            _LOADED.popitem(last=False)
    return controller


_KINDS = {
    stat.S_IFDIR: "a folder",
    stat.S_IFIFO: "a FIFO (named pipe)",
    stat.S_IFCHR: "a character device",
    stat.S_IFBLK: "a block device",
    stat.S_IFSOCK: "a socket",
}


def _read(path: Path) -> bytes:
    """The bytes of the regular file ``path``, at most ``MAX_BYTES``: opened with
    ``O_NONBLOCK`` so that a FIFO cannot hang the open, checked with ``fstat`` before reading."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as error:
        raise ControllerFormatError(f"{path}: cannot read ({error.strerror})") from None
    status = os.fstat(fd)
    if not stat.S_ISREG(status.st_mode):
        os.close(fd)
        kind = _KINDS.get(stat.S_IFMT(status.st_mode), "not a regular file")
        raise ControllerFormatError(f"{path}: is {kind}; expected a controller.json file")
    with os.fdopen(fd, "rb") as stream:
        raw = stream.read(MAX_BYTES + 1) if status.st_size <= MAX_BYTES else b""
    if status.st_size > MAX_BYTES or len(raw) > MAX_BYTES:
        raise ControllerFormatError(
            f"{path}: larger than {MAX_BYTES // 2**20} MiB; expected a controller.json file "
            "(9 funnel trajectories take 1.5 MB)"
        )
    return raw


def _parse_bytes(raw: bytes, path: Path) -> Controller:
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as error:
        raise ControllerFormatError(
            f"{path}: not UTF-8 text (byte {error.start}); expected a JSON file"
        ) from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as error:
        raise ControllerFormatError(
            f"{path}: invalid JSON at line {error.lineno}, column {error.colno}: {error.msg}"
        ) from None
    except RecursionError:
        raise ControllerFormatError(
            f"{path}: JSON nested too deeply; expected a safety-controller document"
        ) from None
    except ValueError as error:  # e.g. an integer with more digits than Python converts
        raise ControllerFormatError(f"{path}: invalid JSON number ({error})") from None
    return parse(data, str(path))
