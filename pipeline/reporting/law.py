"""The controller's law for people: gains with their units, the feedback period (zero-order
hold) and what the law does after the nominal horizon ``T`` (read from controller.json)."""

from __future__ import annotations

import numpy as np

from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.reporting.content import Headline, Table, number
from pipeline.reporting.data import ReportData


def law_items(data: ReportData) -> tuple[Headline, ...]:
    """What the controller does after ``T`` and at which feedback period (controller.json)."""
    period = data.law.feedback_period
    after = data.controller
    return (
        Headline(
            "After T",
            "terminal controller" if after.terminal else "the law stops at T",
            "certified invariant set in Goal: safe for all time"
            if after.terminal
            else "controller.json refuses t > T (no certified terminal controller)",
        ),
        Headline(
            "Feedback rate",
            "continuous" if period == 0 else f"{1 / period:.4g} Hz",
            "the certificate assumes u recomputed continuously"
            if period == 0
            else f"u recomputed every h = {period:g} s and held (zero-order hold), certified",
        ),
    )


def labelled(s: Scenario, x: FloatArray) -> str:
    """A state ``x (n,)`` as ``name = value unit`` pairs."""
    return ", ".join(
        f"{name} = {number(float(v), 4)}" + (f" {s.unit(name)}" if s.unit(name) else "")
        for name, v in zip(s.state_names, np.asarray(x), strict=True)
    )


def gain_table(s: Scenario, K: FloatArray, caption: str) -> Table:
    """A gain ``K (m, n)`` (``u = ... + K e``) with the inputs' and states' labels and units:
    entry ``(j, i)`` is in (unit of input j) per (unit of state i)."""
    K = np.asarray(K)
    scale = np.abs(K).max() if K.size else 0.0
    return Table(
        ("K", *(s.label(name) for name in s.state_names)),
        tuple(
            (
                s.label(name),
                *(number(float(v), 4) if abs(v) > 1e-9 * scale else "0" for v in row),
            )
            for name, row in zip(s.input_names, K, strict=True)
        ),
        f"{caption}; entry (u_j, x_i) in [unit of u_j] per [unit of x_i]",
        numeric=(False, *([True] * s.n)),
    )


def held_rate(data: ReportData) -> str:
    """The tube's rate of the held law in controller.json's ``feedback`` block, or where the
    file has none (a ``safety-controller/2`` file) that each trajectory carries its own."""
    rate = data.law.rate
    return "per trajectory (controller.json)" if rate is None else f"{rate:.4g} 1/s"


def law(data: ReportData) -> tuple:
    """The feedback period (zero-order hold) and the law after ``T`` (controller.json)."""
    s, result = data.scenario, data.controller
    controller = data.law
    h = controller.feedback_period
    gain = "K_i[k]" if controller.K is None else "K"
    period = (
        f"continuous: the certificate assumes u = u_ref + {gain} e recomputed continuously"
        if h == 0
        else f"zero-order hold: the state measured and u recomputed every h = {h:g} s "
        f"({1 / h:.4g} Hz) and held in between; the tube's rate λ = {held_rate(data)} "
        f"is certified for the held law (continuous: {data.feedback.rate:g} 1/s)"
    )
    rows: list[tuple[str, str]] = [
        ("feedback period", period),
        ("after T", result.terminal_message or "no terminal controller; the law refuses t > T"),
    ]
    terminal = controller.terminal
    if terminal is None:
        return (Table(("item", "value"), tuple(rows), "The law in time"),)
    rows += [
        ("terminal equilibrium x_eq", labelled(s, terminal.x_eq)),
        (
            "terminal input u_eq",
            ", ".join(
                f"{name} = {number(float(v), 4)} {s.unit(name)}".rstrip()
                for name, v in zip(s.input_names, terminal.u_eq, strict=True)
            ),
        ),
        ("certified invariant set", f"(x - x_eq)^T P_T (x - x_eq) <= {number(terminal.level, 4)}"),
    ]
    return (
        Table(("item", "value"), tuple(rows), "The law in time"),
        gain_table(s, terminal.K, "Terminal gain K_T after T, u = u_eq + K_T (x - x_eq)"),
    )
