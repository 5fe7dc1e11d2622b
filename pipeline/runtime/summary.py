"""The run's summary: headline numbers, the verdict and the kind of every claim (``summary.json``).

Claims carry their kind: *certified* (LMI and tube bounds, re-checked independently),
*statistically validated* (Monte Carlo with its bound), *falsification-searched* (worst case
found by search, no bound).
"""

from __future__ import annotations

import platform
from collections.abc import Mapping, Sequence
from importlib import metadata
from typing import Any

import numpy as np

from pipeline.model import geometry
from pipeline.model.simulate import Trajectory

KEY_PACKAGES = (
    "numpy",
    "scipy",
    "shapely",
    "cvxpy",
    "clarabel",
    "control",
    "sympy",
    "numba",
    "matplotlib",
)


def _versions() -> dict[str, str]:
    versions = {"python": platform.python_version()}
    for name in ("safety-synthesis", *KEY_PACKAGES):
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions


def summarise(
    scenario: Any,
    feedback: Any,
    demo_trajectories: Sequence[Trajectory],
    demo_radii: Sequence[Any],
    demo_coverage: Any,
    covering: Any,
    optimized: Any,
    final_trajectories: Sequence[Trajectory],
    final_radii: Sequence[Any],
    final_coverage: Any,
    controller: Any,
    certification: Any,
    montecarlo: Any,
    timings: Mapping[str, float],
    total_seconds: float,
    command: Sequence[str],
) -> dict[str, Any]:
    """Collect the stage results into one JSON-able document."""
    r_d = feedback.required_radius(scenario.clearance)
    demos = []
    for i, demo in enumerate(scenario.demos):
        opt = optimized.trajectories[i]
        before, after = demo_trajectories[i].duration, final_trajectories[i].duration
        demos.append(
            {
                "demo": demo.name,
                "start": demo.x0.tolist(),
                "T_demo": before,
                "T_optimized": after,
                "faster_percent": 100 * (1 - after / before),
                "optimized": bool(opt.success),
                "message": opt.message,
                "iterations": int(sum(t.iterations for t in opt.tries)),
                "horizons_tried": len(opt.tries),
                "seconds": opt.seconds,
                "clearance_before": demo_radii[i].nominal_clearance,
                "clearance_after": final_radii[i].nominal_clearance,
                "radius_before": demo_radii[i].radius,
                "radius_after": final_radii[i].radius,
                "binding_before": demo_radii[i].binding,
                "binding_after": final_radii[i].binding,
                "binding_time_before": demo_radii[i].binding_time,
                "binding_time_after": final_radii[i].binding_time,
            }
        )
    T_before = np.array([d["T_demo"] for d in demos])
    T_after = np.array([d["T_optimized"] for d in demos])
    reasons = []
    if not final_coverage.covered:
        gap = final_coverage.largest_gap()
        where = (
            ""
            if gap is None
            else (f"; record a new demonstration from {np.round(gap, 3).tolist()}")
        )
        reasons.append(f"coverage gap: {final_coverage.message}{where}")
    failed = [d["demo"] for d in demos if not d["optimized"]]
    if failed:
        reasons.append(f"not optimized (kept as flown): {', '.join(failed)}")
    if any(r.radius <= 0 for r in final_radii):
        reasons.append("a nominal trajectory has no robustness radius")
    if not certification.success:
        reasons.append(certification.message)
    if not montecarlo.success:
        reasons.append(f"Monte Carlo failure: {montecarlo.message}")
    # the file that ships must pass the final check; the stages' own results must agree
    certified = bool(
        certification.success
        and feedback.success
        and final_coverage.covered
        and all(r.radius > 0 for r in final_radii)
    )
    falsification = montecarlo.falsification
    return {
        "scenario": scenario.name,
        "verdict": {
            "certified": certified,
            "validated": bool(montecarlo.success),
            "text": (
                "certified and validated"
                if certified and montecarlo.success
                else "not certified: " + "; ".join(reasons)
                if not certified
                else "certified but not validated: " + "; ".join(reasons)
            ),
            "reasons": reasons,
        },
        "claims": [
            {
                "claim": f"contraction at rate {feedback.rate:g} over the operating region",
                "kind": "certified",
                "how": f"LMI ({feedback.gain} gain) solved by Clarabel, eigenvalues re-checked at "
                f"all {len(feedback.vertices)} vertices of a sound Jacobian hull "
                f"(largest eigenvalue {feedback.certified_margin:.2e} < 0)",
            },
            {
                "claim": "every start in Init lies in a tube that avoids Unsafe and ends in Goal",
                "kind": "certified" if certified else "not established",
                "how": "robustness radii on a dense grid with a bound between grid points; "
                f"Init covered by box subdivision ({final_coverage.message})",
            },
            {
                "claim": f"failure probability <= {montecarlo.failure_bound:.2e}",
                "kind": "statistically validated",
                "how": f"{montecarlo.samples} i.i.d. closed-loop runs from controller.json, "
                "one-sided 95% Clopper-Pearson bound",
            },
            {
                "claim": f"worst safety margin found {falsification.worst_margin:.3f}"
                + (f" ({falsification.binding})" if falsification.binding else ""),
                "kind": "falsification-searched",
                "how": f"Init corners, Sobol points and Nelder-Mead ({falsification.evaluations} "
                "closed-loop runs); evidence, not a bound",
            },
        ],
        "headline": {
            "T_demo_mean": float(T_before.mean()),
            "T_optimized_mean": float(T_after.mean()),
            "faster_percent_mean": float(100 * np.mean(1 - T_after / T_before)),
            "min_clearance_before": float(min(d["clearance_before"] for d in demos)),
            "min_clearance_after": float(min(d["clearance_after"] for d in demos)),
            "required_clearance": scenario.clearance,
            "coverage_before": demo_coverage.covered_fraction,
            "coverage_after": final_coverage.covered_fraction,
            "covered_before": bool(demo_coverage.covered),
            "covered_after": bool(final_coverage.covered),
            "montecarlo_samples": montecarlo.samples,
            "montecarlo_failures": int(sum(montecarlo.failures.values())),
            "failure_bound_95": montecarlo.failure_bound,
        },
        "feedback": {
            "gain": feedback.gain,
            "K": np.asarray(feedback.K).tolist(),
            "P_eigenvalues": np.linalg.eigvalsh(feedback.P).tolist(),
            "rate": feedback.rate,
            "region": {k: list(v) for k, v in feedback.region.items()},
            "required_radius": r_d,
            "covering_radius": covering.radius if covering.covered else None,
            "kept_radius": covering.kept_radius(r_d),
            "input_margin_at_r_d": feedback.input_margin(r_d).tolist(),
            "region_extent_at_r_d": feedback.region_extent(r_d),
            "vertices": len(feedback.vertices),
            "message": feedback.message,
        },
        "demos": demos,
        "montecarlo": {
            "samples": montecarlo.samples,
            "seed": montecarlo.seed,
            "failures": montecarlo.failures,
            "failure_bound_95": montecarlo.failure_bound,
            "min_clearance": montecarlo.min_clearance,
            "min_goal_margin": montecarlo.min_goal_margin,
            "max_tube_tightness": montecarlo.max_tube_tightness,
            "tube_ratio_at_T": _quantiles(montecarlo.tube_final),
            "falsification": {
                "worst_x0": falsification.worst_x0.tolist(),
                "worst_margin": falsification.worst_margin,
                "binding": falsification.binding,
                "evaluations": falsification.evaluations,
            },
            "message": montecarlo.message,
        },
        "controller": {
            "path": str(controller.path),
            "trajectories": controller.trajectories,
            "interpolation_error_P": controller.interpolation_error,
        },
        "timings": dict(timings),
        "total_seconds": total_seconds,
        "reproducibility": {
            "versions": _versions(),
            "scenario_sha256": scenario.source_hash,
            "montecarlo_seed": montecarlo.seed,
            "command": list(command),
        },
    }


def _quantiles(values: Any) -> dict[str, float] | None:
    """Median, 95th percentile and maximum of ``values (k,)``; None when empty."""
    values = np.asarray(values, dtype=np.float64)
    if values.size == 0:
        return None
    median, p95, top = np.quantile(values, [0.5, 0.95, 1.0])
    return {"median": float(median), "p95": float(p95), "max": float(top)}


def demo_table(scenario: Any, trajectories: Sequence[Trajectory]) -> str:
    """The demonstrations as flown: start, duration, the smallest distance of the dense path to
    each Unsafe set (m), and whether it ends in Goal. ``trajectories``: one per demo."""
    names = list(scenario.unsafe)
    header = f"{'demo':<12} {'start':<22} {'T (s)':>6}" + "".join(
        f" {('to ' + name)[:14]:>14}" for name in names
    )
    lines = [header + "  ends in Goal"]
    for demo, trajectory in zip(scenario.demos, trajectories, strict=True):
        positions = scenario.positions(trajectory.dense_xs)
        start = "(" + ", ".join(f"{v:.2f}" for v in scenario.positions(demo.x0)) + ")"
        clearance = "".join(
            f" {float(geometry.distance(positions, scenario.unsafe[name]).min()):>14.3f}"
            for name in names
        )
        ends = "yes" if bool(scenario.in_goal(trajectory.dense_xs[-1])) else "NO"
        lines.append(f"{demo.name:<12} {start:<22} {trajectory.duration:>6.1f}{clearance}  {ends}")
    return "\n".join(lines)


def print_summary(summary: Mapping[str, Any]) -> None:
    """The end-of-run table."""
    print(
        f"\n{'demo':<9} {'T demo':>7} {'T opt':>6} {'faster':>7} {'clear before':>13}"
        f" {'clear after':>12} {'r before':>9} {'r after':>8} {'iters':>6} {'time':>6}"
    )
    for d in summary["demos"]:
        mark = "" if d["optimized"] else "  (kept as flown)"
        print(
            f"{d['demo']:<9} {d['T_demo']:>6.1f}s {d['T_optimized']:>5.1f}s "
            f"{d['faster_percent']:>6.0f}% {d['clearance_before']:>13.3f} "
            f"{d['clearance_after']:>12.3f} {d['radius_before']:>9.3f} "
            f"{d['radius_after']:>8.3f} {d['iterations']:>6d} {d['seconds']:>5.1f}s{mark}"
        )
    print("\nradius limited by (demonstration -> optimized):")
    for d in summary["demos"]:
        before, after = (
            f"{d[f'binding_{when}']} at {d.get(f'binding_time_{when}', float('nan')):.1f} s"
            for when in ("before", "after")
        )
        print(f"  {d['demo']:<9} {before:<30} -> {after}")
    h, mc = summary["headline"], summary["montecarlo"]
    print(
        f"\nmean duration {h['T_demo_mean']:.1f} s -> {h['T_optimized_mean']:.1f} s "
        f"({h['faster_percent_mean']:.0f}% faster); min clearance "
        f"{h['min_clearance_before']:.2f} -> {h['min_clearance_after']:.2f} m "
        f"(required {h['required_clearance']:g})"
    )
    print(f"Init coverage: {h['coverage_before']:.1%} -> {h['coverage_after']:.1%}")
    fb = summary["feedback"]
    if fb.get("kept_radius", fb["required_radius"]) > fb["required_radius"]:
        print(
            f"  tubes kept at the covering radius {fb['kept_radius']:.4g} > r_d = "
            f"{fb['required_radius']:.4g} (balls of radius r_d about the demo starts miss parts"
            " of Init)"
        )
    print(
        f"Monte Carlo: {mc['samples']} runs, {h['montecarlo_failures']} failures, "
        f"failure probability <= {mc['failure_bound_95']:.2e} (95%)"
    )
    if mc.get("tube_ratio_at_T"):
        q = mc["tube_ratio_at_T"]
        print(
            f"  tube ratio at the final time: median {q['median']:.3f}, max {q['max']:.3f} "
            "(1 = the certified decay e^(-λT); below: the rate is conservative)"
        )
    for claim in summary["claims"]:
        print(f"  [{claim['kind']}] {claim['claim']}")
    if "stress" in summary:
        print(f"  [stress test, not certified] {summary['stress']['message']}")
    print(f"\nverdict: {summary['verdict']['text']}")


def stress_summary(stress: Any) -> dict[str, Any]:
    """The stress test's numbers (reported separately; never part of the certificate)."""

    def run(r: Any) -> dict[str, Any]:
        return {
            "samples": r.samples,
            "failures": r.failures,
            "failed_fraction": r.failed_fraction,
            "min_clearance": r.min_clearance,
            "min_goal_margin": r.min_goal_margin,
        }

    return {
        "kind": "stress test (not part of the certificate)",
        "message": stress.message,
        "with_feedback": run(stress.with_feedback),
        "without_feedback": run(stress.without_feedback),
    }
