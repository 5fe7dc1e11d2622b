"""A tiny valid scenario folder (a planar double integrator with one hand-made demo) and the
mutations that break it, for the tests of scenario validation."""

from __future__ import annotations

import textwrap
from collections.abc import Callable
from pathlib import Path

# States [X, Y, vX, vY], inputs [aX, aY]; Ts = 0.1. Unsafe "block" is the square [2, 3] x [2, 3],
# Goal the square [4, 5] x [0, 1], Init [0, 1] x [0, 1] at rest.
SCENARIO_YAML = textwrap.dedent(
    """\
    name: double_integrator
    description: A point mass in the plane (test fixture).
    states: [X, Y, vX, vY]
    inputs: [aX, aY]
    parameters: {k: 1.0}
    dynamics:
      X: vX
      Y: vY
      vX: k*aX
      vY: k*aY
    position: [X, Y]
    sampling_time: 0.1
    input_bounds:
      aX: [-2.0, 2.0]
      aY: [-2.0, 2.0]
    unsafe:
      block: [[2, 2], [3, 2], [3, 3], [2, 3]]
    goal:
      polygon: [[4, 0], [5, 0], [5, 1], [4, 1]]
    init:
      X: [0.0, 1.0]
      Y: [0.0, 1.0]
      vX: [0.0, 0.0]
      vY: [0.0, 0.0]
    clearance: 0.25
    operating_region:
      aX: [-2.0, 2.0]
    feedback:
      reference_state: [0, 0, 0, 0]
      reference_input: [0, 0]
      state_weights: [1, 1, 1, 1]
      input_weights: [1, 1]
      rate: 0.5
    demos:
      - file: demos/straight.csv
        x0: [0.5, 0.5, 0.0, 0.0]
    """
)


def demo_csv(aX: list[float], aY: list[float], Ts: float = 0.1) -> str:
    """A demo CSV with header ``t,aX,aY``; row k (file line k + 3) holds sample k."""
    lines = ["# hand-made test demonstration", "t,aX,aY"]
    lines += [f"{k * Ts:.10g},{a},{b}" for k, (a, b) in enumerate(zip(aX, aY, strict=True))]
    return "\n".join(lines) + "\n"


# Bang-bang in X: accelerate for 2 s, brake for 2 s; (0.5, 0.5) -> (4.5, 0.5), at rest, in Goal.
STRAIGHT = demo_csv([1.0] * 20 + [-1.0] * 20, [0.0] * 40)


def write_scenario(root: Path) -> Path:
    """Write the valid fixture scenario under ``root``; returns its YAML path."""
    (root / "demos").mkdir(parents=True)
    (root / "scenario.yaml").write_text(SCENARIO_YAML)
    (root / "demos" / "straight.csv").write_text(STRAIGHT)
    return root / "scenario.yaml"


Mutation = Callable[[Path], str]  # scenario YAML path -> what to pass to the CLI


def yaml_replace(old: str, new: str) -> Mutation:
    def mutate(path: Path) -> str:
        text = path.read_text()
        assert old in text, f"fixture does not contain {old!r}"
        path.write_text(text.replace(old, new, 1))
        return str(path)

    return mutate


def chain(*mutations: Mutation) -> Mutation:
    def mutate(path: Path) -> str:
        for mutation in mutations:
            target = mutation(path)
        return target

    return mutate
