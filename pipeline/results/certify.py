"""The result types of stage ``certify`` (``stages/certify.py``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from pipeline.results.base import Result


@dataclass(frozen=True, kw_only=True)
class CertificationResult(Result):
    """What the final check found in the emitted ``controller.json``.

    Attributes:
      path: the file checked; sha256: its content hash at the time of the check.
      metric_eigenvalue: ``lambda_min(P)`` (> 0 for a metric; a ``/2`` file: over every
        ``P_i[k]``).
      contraction_margin: the largest eigenvalue of (C)'s left side over the hull's vertices
        (< 0 for a certificate); ``vertices`` how many there were. A ``/2`` file: the largest
        eigenvalue of (F2) (``Q^-1/2 L Q^-1/2``) over every funnel's local hull vertices at
        both ends of every interval, and the vertices of all those hulls.
      radii: (k,) the radii (``/2``: funnel levels) the file claims; verified_radii: (k,) the
        largest the re-check allows for each trajectory (a claim is certified when it is not
        larger).
      reference_error: the largest ``||x_ref - simulated||_P(t) / radius`` over the
        trajectories.
      covered_fraction: the part of Init certified covered by the file's balls (volume).
      terminal: the file has a terminal block; terminal_decay: its certified ``alpha`` (1/s);
        terminal_fit: the largest end tube's share of the ellipsoid's radius (<= 1 to fit).
      terminal_box: (n,) the additive box the terminal block was re-checked under with the
        declared parameter intervals in its hull ((T7) of ``pipeline.numerics.terminal.check``);
        empty: under the whole box's additive bound (T1'), or no block.
      contraction_bound: what ``contraction_margin`` must be below (``contraction_bound``).
      disturbance_multiple: under a declared uncertainty, the largest multiple of its additive
        bound that every funnel still holds ((I5) of ``funnel.robust``; the terminal block
        is checked at the bound itself); nan without a declaration.
      failures: one line per failed check; empty when the file is certified.
    """

    path: Path
    sha256: str
    metric_eigenvalue: float
    contraction_margin: float
    vertices: int
    radii: tuple[float, ...]
    verified_radii: tuple[float, ...]
    reference_error: float
    covered_fraction: float
    failures: tuple[str, ...] = field(default=())
    success: bool
    message: str
    terminal: bool = False
    terminal_decay: float = float("nan")
    terminal_fit: float = float("nan")
    terminal_box: tuple[float, ...] = ()
    contraction_bound: float = 0.0
    disturbance_multiple: float = float("nan")
