"""Limits on scenario values that the command line checks too.

Standard library only, so that the command line and the API can state them without loading the
scenario's validation (pydantic, sympy).
"""

from __future__ import annotations

# The shortest feedback period (s), the scenario's or --feedback-period's. Monte Carlo flies the
# held law with at least one RK4 step per period, Ts / h steps per sample (1000 for Ts = 0.1 s at
# 0.1 ms, 250 times the 4 steps of continuous feedback; double_integrator, 1000 runs: certified and
# validated, 17 s of CPU), while the held rate falls short of the continuous one by about
# (lambda^2 + C1) h / 2 (pipeline.numerics.tube.sampled): a shorter hold is continuous feedback in
# all but cost (use 0).
MIN_FEEDBACK_PERIOD = 1e-4


def divides(period: float, sampling_time: float) -> bool:
    """Whether a held law's ``period`` (s, > 0) divides ``sampling_time``: ``Ts / h`` a whole
    number (to 1e-9 relative), at least 1, so that the law's windows start at every sample,
    where ``u_ref`` switches."""
    steps = sampling_time / period
    return steps >= 1 - 1e-9 and abs(steps - round(steps)) <= 1e-9 * steps


def periods_allowed(sampling_time: float, whose: str = "") -> str:
    """What a feedback period must be, in words, for a sampling time (``whose``: the owner
    named before ``sampling_time``, e.g. ``"the scenario's "``)."""
    return (
        f"0 (continuous feedback) or a period of at least {MIN_FEEDBACK_PERIOD:g} s that divides "
        f"{whose}sampling_time {sampling_time:g} s (e.g. {sampling_time / 10:g})"
    )
