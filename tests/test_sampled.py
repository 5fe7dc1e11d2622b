"""Zero-order-hold feedback (``pipeline.numerics.tube.sampled``): the held tube's rate is sound.

On linear dynamics the held closed loop is exact: over one window ``e_{k+1} = Phi e_k`` with
``Phi = e^{A h} + int_0^h e^{A s} ds B K``, and inside it ``e(t_k + s) = Phi(s) e_k``. The bound
``||e(t)||_P <= e^{-lambda_h t} ||e(0)||_P`` must hold at every ``s``, for the worst ``e_k``
(the largest singular value of ``P^1/2 Phi(s) P^-1/2``), and ``lambda_h`` must tend to the
continuous rate as ``h -> 0`` with the stated first-order cost ``C1 h / 2``.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm

from pipeline.numerics.tube.contraction import contraction_rate
from pipeline.numerics.tube.sampled import held_rate
from pipeline.runtime.options import RunOptions

# double integrator in one axis, a gain and its metric from a Lyapunov equation
A = np.array([[0.0, 1.0], [0.0, 0.0]])
B = np.array([[0.0], [1.0]])
K = np.array([[-4.0, -3.0]])
P = np.array([[3.5, 0.5], [0.5, 0.5]])


def _window(s: float) -> np.ndarray:
    """``Phi(s)``: ``e(t_k + s) = Phi(s) e_k`` under the held law (augmented exponential)."""
    M = np.zeros((3, 3))
    M[:2, :2], M[:2, 2:] = A, B
    E = expm(M * s)
    return E[:2, :2] + E[:2, 2:] @ K


def _worst_growth(s: float) -> float:
    values, vectors = np.linalg.eigh(P)
    root = vectors @ np.diag(np.sqrt(values)) @ vectors.T
    inverse = vectors @ np.diag(values**-0.5) @ vectors.T
    return float(np.linalg.norm(root @ _window(s) @ inverse, 2))


@pytest.mark.parametrize("h", [0.005, 0.02, 0.05])
def test_the_held_rate_bounds_the_exact_held_closed_loop(h):
    rate = contraction_rate(P, K, A[None], B[None])
    assert rate > 0
    held = held_rate(P, K, A[None], B[None], rate, h)
    assert 0 < held.held_rate < rate
    for s in np.linspace(h / 50, h, 50):  # within one window, for the worst e_k
        assert _worst_growth(s) <= np.exp(-held.held_rate * s) * (1 + 1e-12)


def test_the_cost_of_holding_is_first_order_in_h():
    """``(lambda - lambda_h) / h`` tends to a constant (observed order 1) as ``h -> 0``."""
    rate = contraction_rate(P, K, A[None], B[None])
    cost = [
        (rate - held_rate(P, K, A[None], B[None], rate, h).held_rate) / h
        for h in (1e-3, 1e-4, 1e-5)
    ]
    assert cost[2] > 0
    assert abs(cost[1] - cost[2]) < 0.2 * abs(cost[0] - cost[1])


def test_a_period_too_long_is_not_certified():
    rate = contraction_rate(P, K, A[None], B[None])
    assert not held_rate(P, K, A[None], B[None], rate, 2.0).success


def test_feedback_period_is_an_option_and_refuses_negative_values():
    import argparse

    from pipeline.runtime.options import add_arguments, from_arguments

    parser = argparse.ArgumentParser()
    add_arguments(parser, RunOptions)
    # unset on the command line: the scenario's feedback_period (run_inputs.period_of)
    assert from_arguments(RunOptions, parser.parse_args([])).feedback_period is None
    assert from_arguments(RunOptions, parser.parse_args(["--feedback-period", "0.01"])) == (
        RunOptions(feedback_period=0.01)
    )
    with pytest.raises(SystemExit):
        parser.parse_args(["--feedback-period", "-0.01"])
