"""``bench.peak_bound``: the largest deviation of a linear loop under a constant parameter offset
and under arbitrary signals in a box, against closed forms."""

from __future__ import annotations

import numpy as np
import pytest

from bench.peak_bound import adjoint_peaks

H = 4e-3


def test_a_first_order_loop_moves_as_its_step_response_under_either_signal() -> None:
    """``e' = -a e + p + w``: the impulse response ``e^{-a t}`` never changes sign, so a constant
    offset and the worst signal in the same box both reach ``b (1 - e^{-a t}) / a``."""
    a, t = 2.0, 3.0
    steps = int(t / H)
    Acl = np.full((steps, 1, 1), -a)
    F_p = np.ones((steps, 1, 1))
    found = adjoint_peaks(Acl, F_p, H, np.array([0.2]), np.array([0.3]), (0,), 25)
    reach = (1 - np.exp(-a * t)) / a
    assert found["constant"][0] == pytest.approx(0.2 * reach, rel=5e-3)
    assert found["signal"][0] == pytest.approx(0.2 * reach, rel=5e-3)
    assert found["gust"][0] == pytest.approx(0.3 * reach, rel=5e-3)


def test_an_oscillating_loop_moves_further_under_a_signal_than_under_a_constant() -> None:
    """``x'' = -2 zeta w x' - w^2 x + p``: a constant offset peaks at the step response's
    overshoot, ``(1 + exp(-zeta pi / sqrt(1 - zeta^2))) / w^2``; a signal that switches with the
    impulse response's sign reaches its L1 norm, more."""
    zeta, w, t = 0.1, 2.0, 8.0
    steps = int(t / H)
    Acl = np.broadcast_to(np.array([[0.0, 1.0], [-(w**2), -2 * zeta * w]]), (steps, 2, 2))
    F_p = np.broadcast_to(np.array([[0.0], [1.0]]), (steps, 2, 1))
    found = adjoint_peaks(Acl, F_p, H, np.array([1.0]), np.zeros(2), (0,), 5)
    overshoot = (1 + np.exp(-zeta * np.pi / np.sqrt(1 - zeta**2))) / w**2
    assert found["constant"][0] == pytest.approx(overshoot, rel=5e-3)
    # the L1 norm of the impulse response e^{-zeta w t} sin(w_d t) / w_d, on the grid
    w_d = w * np.sqrt(1 - zeta**2)
    s = np.arange(steps) * H
    l1 = np.sum(np.abs(np.exp(-zeta * w * s) * np.sin(w_d * s) / w_d)) * H
    assert found["signal"][0] == pytest.approx(l1, rel=5e-3)
    assert found["signal"][0] > 1.5 * found["constant"][0]
    assert found["gust"][0] == 0.0
