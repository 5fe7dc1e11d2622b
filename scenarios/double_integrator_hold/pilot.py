"""double_integrator_hold is flown by double_integrator's pilot (same route, hand and starts).

Loaded by path (``pipeline.demonstrations.pilot``), so the shipped double_integrator's pilot file
is loaded by path too (from the shipped scenarios, so that a copy of this folder flies the same).
"""

from __future__ import annotations

import importlib.util
import sys

from pipeline.model.scenario import SCENARIOS_ROOT

_SOURCE = SCENARIOS_ROOT / "double_integrator" / "pilot.py"
_NAME = "double_integrator_hold_source_pilot"
_spec = importlib.util.spec_from_file_location(_NAME, _SOURCE)
assert _spec is not None and _spec.loader is not None
_module = importlib.util.module_from_spec(_spec)
sys.modules[_NAME] = _module  # its dataclasses look their module up there
_spec.loader.exec_module(_module)

CONFIG = _module.CONFIG
steering = _module.steering
