"""A held law's (I5) margin with the hold's push as a box (``funnel.law`` (I6)) against the push
taken to first order into (I5)'s matrix (``funnel.sampled`` (I6')), on a shipped funnel file.

For every trajectory of ``controller.json`` (a continuous-law funnel file) and every period ``h``
the funnel is rebuilt as the certify stage rebuilds it (``recertify._under_law``: the hull on
the first of ``SEGMENTS`` that builds, the law's offset on the file's reference grid, the
scenario's declared additive bound and measurement box) and, per sample interval, both margins
``2 r_k + lmi_term_k`` are evaluated (< -LMI_MARGIN holds). Printed per trajectory and period: the
worst interval's margin of each and how many intervals fail. Run: ``python -m bench.bench_sampled
CONTROLLER_JSON [h ...]`` (no file: skipped in ``make bench``, which has none to read).

Measured on quadrotor_hill's continuous-law file (9 funnels, 35-38 intervals, 1 segment,
the file's reference grid), funnels passing on every interval, (I6) box / (I6'): h = 1 ms 2/9 /
8/9; 2 ms 0/9 / 6/9; 5 ms 0/9 / 2/9 (failing intervals per funnel 12-32 / 0-12); 10 ms 0/9 /
0/9. (I6') was below (I6) on all 329 intervals at 1 ms and at 5 ms (by at least 0.002 and
0.011). Keeping only the pairs ``v = v'`` (unsound, a probe) moves the 5 ms margins by under
0.002: what is left is the first-order term itself, not the two hulls' independence.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from pipeline.controller import load
from pipeline.model.scenario import load_scenario
from pipeline.model.simulate import simulate
from pipeline.numerics.funnel.law import BASE_SUBSTEPS, LMI_MARGIN, grid_substeps
from pipeline.numerics.funnel.robust import RobustCheck
from pipeline.numerics.uncertainty import held_state_bounds
from pipeline.numerics.verify.declared import checked_bound, checked_measurement
from pipeline.numerics.verify.recertify import SEGMENTS, ShippedFunnel, _under_law

PERIODS = (0.001, 0.002, 0.005, 0.01)


def margins(path: Path, periods: tuple[float, ...], only: set[int] | None = None) -> list[dict]:
    """One row per (trajectory, period): the worst margins and failing intervals of both."""
    controller = load(path)
    scenario = load_scenario(controller.scenario)
    bounds = held_state_bounds(scenario)
    disturbance, _ = checked_bound(scenario, controller.disturbance_bound, "uncertainty")
    measurement, _ = checked_measurement(scenario, controller.measurement_bound)
    rows = []
    for i, tr in enumerate(controller.trajectories):
        if only is not None and i not in only:
            continue
        shipped = ShippedFunnel(K=tr.K, P=tr.P, rho=tr.radius, rate=tr.rate)
        nominal = simulate(scenario.dynamics, tr.x0, tr.u_ref, scenario.Ts, BASE_SUBSTEPS)
        substeps = grid_substeps(tr.t, len(tr.K), scenario.Ts)
        for h in periods:
            for segments in SEGMENTS:
                try:
                    funnel, law = _under_law(
                        scenario, nominal, shipped, bounds, segments, substeps,
                        0.0, disturbance, h, measurement,
                    )  # fmt: skip
                    break
                except Exception as error:  # noqa: BLE001 - a bench: report and go on
                    print(f"trajectory {i} h {h:g} segments {segments}: {error}")
            else:
                continue
            Q = shipped.Q
            start = time.perf_counter()
            old = RobustCheck(Q, tr.K, funnel.vertices, tr.rate, scenario.Ts, tr.radius)
            box = law.box
            before = 2 * old.margins(box)[0] + law.lmi_term
            middle = time.perf_counter()
            new = RobustCheck(Q, tr.K, funnel.vertices, tr.rate, scenario.Ts, tr.radius, h)
            sampled = law.disturbance + (0.0 if law.remainder is None else law.remainder)
            after = 2 * new.margins(sampled)[0] + law.lmi_term
            end = time.perf_counter()
            rows.append(
                {
                    "trajectory": i,
                    "h": h,
                    "segments": segments,
                    "box": float(before.max()),
                    "box_fail": int((before >= -LMI_MARGIN).sum()),
                    "sampled": float(after.max()),
                    "sampled_fail": int((after >= -LMI_MARGIN).sum()),
                    "N": len(tr.K),
                    "lmi_term": float(law.lmi_term.max()),
                    "box_alone": float((before - law.lmi_term).max()),
                    "sampled_alone": float((after - law.lmi_term).max()),
                    "hold": np.round(np.asarray(box).max(axis=0), 3).tolist(),
                    "remainder": np.round(sampled.max(axis=0), 3).tolist(),
                    "seconds": (middle - start, end - middle),
                    "per_interval": (before, after),
                }  # fmt: skip
            )
            r = rows[-1]
            print(
                f"traj {i} h {1000 * h:g} ms ({segments} seg, N {r['N']}): box {r['box']:+.4f} "
                f"({r['box_fail']} fail) | sampled {r['sampled']:+.4f} "
                f"({r['sampled_fail']} fail) | without (I2) {r['box_alone']:+.4f} / "
                f"{r['sampled_alone']:+.4f} | lmi_term {r['lmi_term']:.2g} | box {r['hold']} | "
                f"R+d {r['remainder']} | {r['seconds'][0]:.1f} s / {r['seconds'][1]:.1f} s",
                flush=True,
            )
    return rows


def run() -> None:
    """``make bench``: nothing to read without a file."""
    if len(sys.argv) < 2 or not sys.argv[1].endswith(".json"):
        print("bench_sampled: give a controller.json (python -m bench.bench_sampled FILE [h ...])")
        return
    periods = tuple(float(h) for h in sys.argv[2:]) or PERIODS
    margins(Path(sys.argv[1]), periods)


if __name__ == "__main__":
    run()
