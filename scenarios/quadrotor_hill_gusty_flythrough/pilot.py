"""How the synthetic pilot flies quadrotor_hill_gusty_flythrough: quadrotor_hill_flythrough's pilot
(its route and steering, ``scenarios/quadrotor_hill_flythrough/pilot.py``, loaded rather than
copied), started where Init spreads in velocity and pitch: flight 1 from Init's centre, flights
2-9 from the 8 corners of (vX, vY, theta) in [-0.2, 0.2] m/s x [-0.2, 0.2] m/s x [-0.05, 0.05]
rad, each at the position cell centre on the side its velocity points to (X 2 -+ 0.667 m, Y 2.5
-+ 0.333 m)."""

import dataclasses
import importlib.util
import itertools
import sys
from pathlib import Path

from pipeline.model.scenario import SCENARIOS_ROOT


def _hill_pilot():
    """The module ``quadrotor_hill_flythrough/pilot.py`` beside this scenario, else in the
    scenarios folder (a copy of this scenario elsewhere still finds it)."""
    beside = Path(__file__).resolve().parents[1] / "quadrotor_hill_flythrough" / "pilot.py"
    path = beside if beside.is_file() else SCENARIOS_ROOT / "quadrotor_hill_flythrough" / "pilot.py"
    spec = importlib.util.spec_from_file_location("_quadrotor_hill_pilot", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses in the file look their module up here
    try:
        spec.loader.exec_module(module)
    finally:
        del sys.modules[spec.name]
    return module


_HILL = _hill_pilot()
CORNERS = tuple(
    (2.0 + 0.667 * sx, 2.5 + 0.333 * sy, 0.05 * st, 0.2 * sx, 0.2 * sy, 0.0)
    for sx, sy, st in itertools.product((-1, 1), repeat=3)
)
CONFIG = dataclasses.replace(_HILL.CONFIG, grid=(), extra_starts=CORNERS)
steering = _HILL.steering
