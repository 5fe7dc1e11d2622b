"""Fly a controller in its scenario's model: ``xdot = f(x, clip(controller(t, x, i)))``.

``fly(controller, scenario, x0)`` selects the trajectory ``i`` for ``x0`` and integrates the
scenario's dynamics (``load_scenario(name).dynamics.f``) by RK4 with steps of at most ``step``
seconds, the law evaluated at every RK4 stage (``period = 0``: continuous feedback) or computed
at ``t_k = k period`` and held on ``[t_k, t_k + period)`` (a flight computer); by default at the
file's ``feedback_period``, the law its certificate is for (another period is flown without a
guarantee). Each sample interval ``[k Ts, (k+1) Ts)`` (or each held window) is integrated on its
own, the stage at its right end using the left limit of the piecewise-constant reference input,
as the Monte Carlo validation does (``pipeline.numerics.closed_loop.simulate``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.controller import Controller
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario, load_scenario

LEFT_LIMIT = 1e-9  # s: the last stage of a window reads the input just before its end
TERMINAL_EXTRA = 10.0  # s flown past T by default when the file has a terminal controller


@dataclass(frozen=True, kw_only=True)
class Flight:
    """One flight from ``x0``.

    Attributes:
      ts: (M,) times from 0 to ``until``; xs: (M, n) the states there; us: (M-1, m) the input
        (clipped) applied at the start of each RK4 step (held on it when ``period > 0``).
      index: the trajectory flown (``controller.trajectories[index]``, its ``name`` beside it);
      ratio: the start's coverage ratio (``< 1``: covered, the certificate applies).
      period: the feedback period flown (0: continuous).
    """

    ts: FloatArray
    xs: FloatArray
    us: FloatArray
    index: int
    ratio: float
    period: float

    @property
    def covered(self) -> bool:
        """The start lies inside a certified initial ball (``ratio < 1``)."""
        return self.ratio < 1.0


def fly(
    controller: Controller,
    scenario: str | Path | Scenario,
    x0: FloatArray,
    *,
    period: float | None = None,
    until: float | None = None,
    step: float | None = None,
) -> Flight:
    """Fly ``controller`` from ``x0 (n,)`` in ``scenario``'s model (a name, path or Scenario).

    Args:
      period: the feedback period (s): 0 evaluates the law continuously (at every RK4 stage);
        default the file's ``feedback_period`` (the law as certified).
      until: the end time (s); default the trajectory's ``T``, or ``T + 10`` s when the file has
        a terminal controller. Past ``T`` without one is a ``ValueError`` (nothing is
        certified there and the law refuses it).
      step: the largest RK4 step (s); default ``Ts / 20``.

    Returns a ``Flight``. A start that is not covered (``ratio >= 1``) is flown all the same,
    with no guarantee: check ``flight.covered``. A scenario whose state or input names differ
    from the file's, a wrong-shaped or non-finite ``x0`` or a negative ``period``, ``until`` or
    ``step`` is a ``ValueError``.
    """
    loaded = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
    if (
        tuple(loaded.state_names) != controller.state_names
        or tuple(loaded.input_names) != controller.input_names
    ):
        raise ValueError(
            f"scenario {loaded.name!r} has states {list(loaded.state_names)} and inputs "
            f"{list(loaded.input_names)}; expected the controller's {list(controller.state_names)} "
            f"and {list(controller.input_names)} (is it the scenario of {controller.source}?)"
        )
    x = np.array(x0, dtype=np.float64)
    if x.shape != (controller.n,):
        names = ", ".join(controller.state_names)
        raise ValueError(f"x0 has shape {x.shape}; expected ({controller.n},): one start ({names})")
    index, ratio = controller.select(x)
    reference = controller.trajectories[int(index)]
    T = reference.T
    if period is None:
        period = controller.feedback_period
    if until is None:
        until = T + (TERMINAL_EXTRA if controller.terminal is not None else 0.0)
    for name, value in (("period", period), ("until", until), ("step", step)):
        if value is not None and not (math.isfinite(value) and value >= 0):
            raise ValueError(f"{name} = {value}; expected a finite number >= 0 (s)")
    if until > T * (1 + 1e-9) and controller.terminal is None:
        raise ValueError(
            f"until = {until:g} s is past the trajectory's T = {T:g} s and {controller.source} "
            f"has no terminal controller; expected until <= {T:g}"
        )
    h_max = controller.Ts / 20 if step is None or step == 0 else step
    window = period if period > 0 else controller.Ts
    count = max(1, math.ceil(until / window - 1e-9))
    edges = np.minimum(window * np.arange(count + 1), until)
    f, lower, upper = loaded.dynamics.f, controller.lower, controller.upper

    def law(t: float, state: FloatArray) -> FloatArray:
        return np.clip(controller(t, state, index), lower, upper)

    ts, xs, us = [0.0], [x.copy()], []
    for start, end in zip(edges[:-1], edges[1:], strict=True):
        if end <= start:
            continue
        substeps = max(1, math.ceil((end - start) / h_max - 1e-9))
        h = (end - start) / substeps
        held = law(float(start), x) if period > 0 else None
        for j in range(substeps):
            t = start + j * h
            t_end = end - LEFT_LIMIT if j == substeps - 1 else t + h
            if held is None:
                u_start = law(t, x)
                k1 = f(x, u_start)
                k2 = f(x + h / 2 * k1, law(t + h / 2, x + h / 2 * k1))
                k3 = f(x + h / 2 * k2, law(t + h / 2, x + h / 2 * k2))
                k4 = f(x + h * k3, law(t_end, x + h * k3))
            else:
                u_start = held
                k1 = f(x, held)
                k2 = f(x + h / 2 * k1, held)
                k3 = f(x + h / 2 * k2, held)
                k4 = f(x + h * k3, held)
            x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            ts.append(float(start + (j + 1) * h))
            xs.append(x)
            us.append(u_start)
    return Flight(
        ts=np.array(ts),
        xs=np.array(xs),
        us=np.array(us).reshape(-1, controller.m),
        index=int(index),
        ratio=float(ratio),
        period=float(period),
    )
