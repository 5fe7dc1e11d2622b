"""The orchestrator: wires the stages in order and writes their artifacts under ``reports/NAME``.

It holds no numerics of its own; each stage is a function from typed inputs to a typed result.
"""

from __future__ import annotations

from pathlib import Path

from pipeline import geometry
from pipeline.cli import REPORTS_ROOT
from pipeline.plotting import save_scenario_figure
from pipeline.scenario import Scenario, load_scenario
from pipeline.simulate import simulate


def demo_table(scenario: Scenario) -> list[dict[str, object]]:
    """Per-demo facts: start, duration, minimum clearance to each Unsafe set, end in Goal."""
    rows = []
    for demo in scenario.demos:
        trajectory = simulate(scenario.dynamics, demo.x0, demo.us, scenario.Ts)
        positions = scenario.positions(trajectory.dense_xs)
        clearance = {
            name: float(geometry.distance(positions, region).min())
            for name, region in scenario.unsafe.items()
        }
        rows.append(
            {
                "demo": demo.name,
                "start": scenario.positions(demo.x0).tolist(),
                "duration": trajectory.duration,
                "clearance": clearance,
                "ends_in_goal": bool(scenario.in_goal(trajectory.final_state)),
                "trajectory": trajectory,
            }
        )
    return rows


def _print_demo_table(scenario: Scenario, rows: list[dict[str, object]]) -> None:
    names = list(scenario.unsafe)
    header = (
        f"{'demo':<10} {'start':>14} {'T (s)':>6} "
        + " ".join(f"{'clear ' + n:>14}" for n in names)
        + "  in Goal"
    )
    print(header)
    print("-" * len(header))
    for row in rows:
        start = "({:.2f}, {:.2f})".format(*row["start"])
        clear = " ".join(f"{row['clearance'][n]:>14.3f}" for n in names)
        print(
            f"{row['demo']:<10} {start:>14} {row['duration']:>6.1f} {clear}  "
            f"{'yes' if row['ends_in_goal'] else 'NO'}"
        )
    print(f"required clearance d = {scenario.clearance:g}")


def synthesize(
    scenario_name: str, out: Path | None = None, verbose: bool = False, quiet: bool = False
) -> int:
    """Run the pipeline on a scenario; returns the process exit code."""
    scenario = load_scenario(scenario_name)
    out = Path(out) if out is not None else REPORTS_ROOT / scenario.name
    rows = demo_table(scenario)
    if not quiet:
        print(
            f"scenario {scenario.name}: {len(scenario.demos)} demos, all valid "
            f"(never in Unsafe, end in Goal)"
        )
        _print_demo_table(scenario, rows)
    figure = out / "scenario.png"
    save_scenario_figure(
        figure,
        scenario,
        [r["trajectory"].dense_xs for r in rows],
        [r["demo"] for r in rows],
        title=f"{scenario.name}: demonstrations",
        marker_every=int(round(1.0 / scenario.Ts)) * 4,
    )
    if not quiet:
        print(f"wrote {figure}")
    del verbose
    return 0
