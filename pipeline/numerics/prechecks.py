"""Pre-checks: scenario mistakes that doom the feedback stage, found before any stage runs.

Each raises one ``ScenarioError`` naming the file, the field, the value and what would work:

1. The Jacobian hull over ``operating_region`` must exist (``pipeline.numerics.hull``): every
   variable the Jacobian depends on bounded, every entry bounded over the box.
2. The declared uncertainty has a bound (``pipeline.numerics.uncertainty``): every variable the
   dynamics' sensitivity to an uncertain parameter depends on is bounded.
   Every demo input named in ``operating_region`` stays inside its interval there.
3. An uncontrollable mode at the reference. With ``A = f_x(x*, u*)``, ``B = f_u(x*, u*)`` at
   ``feedback.reference_state``/``reference_input``, take the controllable subspace
   ``R = span[B, AB, ..., A^{n-1} B]`` (A-invariant) and an orthonormal basis ``N`` of its
   complement: in the basis ``[R, N]``, ``A = [[A_c, *], [0, A_u]]`` with ``A_u = N^T A N`` and
   ``B = [B_c; 0]``. A left eigenvector ``w_u`` of ``A_u`` (eigenvalue ``mu``) gives ``w = N w_u``
   with ``w^T A = mu w^T`` and ``w^T B = 0`` (the PBH test fails at ``mu``), and ``w^T (A + B K)
   = mu w^T`` for every gain ``K``. When the reference lies in the operating region, its Jacobian
   lies in the hull, and the feedback certificate ``(A + B K)^T P + P (A + B K) + 2 lambda P < 0``
   (affine in ``[A B]``, so it holds on the hull) forces every eigenvalue of ``A + B K`` below
   ``-lambda``; so ``Re mu >= -lambda`` means no certificate exists at ``feedback.rate``, and
   ``Re mu >= 0`` that the reference is not even stabilisable. A reference outside the region
   says nothing about it and is not checked.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pipeline.io.errors import ScenarioError
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.numerics.hull import HullError, jacobian_hull
from pipeline.numerics.uncertainty import additive_bound

RANK_TOLERANCE = 1e-9  # relative to the largest singular value of [A B] (and at least 1)


def check_scenario(scenario: Scenario) -> None:
    """Run the pre-checks of the module docstring; a ``ScenarioError`` for the first that fails."""
    _check_hull(scenario)
    _check_uncertainty(scenario)
    _check_demo_inputs(scenario)
    _check_reference(scenario)


def _check_hull(scenario: Scenario) -> None:
    try:
        jacobian_hull(scenario.dynamics, scenario.operating_region)
    except HullError as error:
        raise ScenarioError(
            f"the feedback's Jacobian hull is unbounded or cannot be built: {error}",
            file=scenario.path,
            field="operating_region",
            found=dict(scenario.operating_region),
            expected="a finite interval for every variable the Jacobian depends on "
            f"({', '.join(scenario.dynamics.depends_on()) or 'none'}) over which each entry is "
            "bounded",
        ) from None


def _check_uncertainty(scenario: Scenario) -> None:
    try:
        additive_bound(scenario)
    except HullError as error:
        raise ScenarioError(
            f"the declared parameters' effect cannot be bounded: {error}",
            file=scenario.path,
            field="uncertainty.parameters",
            found=dict(scenario.uncertainty.parameters),
            expected="parameters whose effect on the dynamics is bounded over the state and "
            "input bounds (pipeline.numerics.uncertainty)",
        ) from None


def _check_demo_inputs(scenario: Scenario) -> None:
    for j, name in enumerate(scenario.input_names):
        if name not in scenario.operating_region:
            continue
        lower, upper = scenario.operating_region[name]
        for demo in scenario.demos:
            outside = np.flatnonzero((demo.us[:, j] < lower) | (demo.us[:, j] > upper))
            if outside.size:
                k = int(outside[0])
                raise ScenarioError(
                    f"demo '{demo.name}' leaves the operating region: input '{name}' = "
                    f"{demo.us[k, j]:g} at t = {k * scenario.Ts:.2f} s (demo file {demo.file})",
                    file=scenario.path,
                    field=f"operating_region.{name}",
                    found=[lower, upper],
                    expected=f"an interval holding every demo's '{name}' (the demos use "
                    f"[{min(d.us[:, j].min() for d in scenario.demos):g}, "
                    f"{max(d.us[:, j].max() for d in scenario.demos):g}]), or demos inside it",
                )


def uncontrollable_modes(A: FloatArray, B: FloatArray) -> list[tuple[complex, FloatArray]]:
    """The uncontrollable modes of ``(A (n, n), B (n, m))``: ``(mu, w)`` with ``w (n,)`` a unit
    left eigenvector (real part, for a complex ``mu``) that no input moves (module docstring)."""
    n = A.shape[0]
    scale = max(1.0, float(np.linalg.norm(np.hstack([A, B]), 2)))
    R = np.zeros((n, 0))
    block = B
    for _ in range(n):  # grow R by A^k B until it stops growing
        U, s, _ = np.linalg.svd(np.hstack([R, block]), full_matrices=False)
        grown = U[:, s > RANK_TOLERANCE * scale * max(1.0, float(s.max(initial=0.0)))]
        if grown.shape[1] == R.shape[1]:
            break
        R, block = grown, A @ grown
    if R.shape[1] == n:
        return []
    U, _, _ = np.linalg.svd(R, full_matrices=True)
    N = U[:, R.shape[1] :]  # (n, n - r) orthonormal complement of R
    mus, W = np.linalg.eig((N.T @ A @ N).T)  # left eigenvectors of A_u
    modes = []
    for mu, w_u in zip(mus, W.T, strict=True):
        w = np.real(N @ w_u)
        if np.linalg.norm(w) < 1e-12:  # a purely imaginary eigenvector: take its other part
            w = np.imag(N @ w_u)
        w = w / np.linalg.norm(w)
        modes.append((complex(mu), w * np.sign(w[np.argmax(np.abs(w))])))
    return modes


def direction(w: FloatArray, names: Sequence[str]) -> str:
    """``w (n,)`` as a combination of the state names: ``"0.71 X + 0.71 Y"``."""
    terms = [f"{c:.2g} {name}" for c, name in zip(w, names, strict=True) if abs(c) >= 5e-3]
    text = " + ".join(terms).replace("+ -", "- ")
    return text.removeprefix("1 ") if len(terms) == 1 else text


def _check_reference(scenario: Scenario) -> None:
    spec = scenario.feedback
    x, u = np.array(spec.reference_state), np.array(spec.reference_input)
    values = dict(zip((*scenario.state_names, *scenario.input_names), (*x, *u), strict=True))
    inside = all(lo <= values[k] <= hi for k, (lo, hi) in scenario.operating_region.items())
    if not inside:
        return
    A = np.asarray(scenario.dynamics.f_x(x, u), dtype=np.float64)
    B = np.asarray(scenario.dynamics.f_u(x, u), dtype=np.float64)
    rate = float(spec.rate)
    for mu, w in uncontrollable_modes(A, B):
        if mu.real < -rate - 1e-9:
            continue
        stable = "not stabilisable" if mu.real >= -1e-9 else f"not contractible at rate {rate:g}"
        value = f"{mu.real + 0.0:.3g}" + (f" ± {abs(mu.imag):.3g}i" if mu.imag else "")
        raise ScenarioError(
            f"{stable} at the reference: no input moves the direction "
            f"{direction(w, scenario.state_names)} (an uncontrollable mode, eigenvalue {value}; "
            f"the certificate needs every mode below -feedback.rate = {-rate:g})",
            file=scenario.path,
            field="feedback.reference_state",
            found=[float(v) for v in x],
            expected="dynamics in which an input moves that direction at the reference (e.g. a "
            "quantity held constant, such as a speed, made an input), or another reference_state "
            "where one does",
        )
