"""The emitted lookup feedback controller, format ``safety-controller/1`` (see the README).

This module needs only NumPy and the standard library, so ``controller.json`` can be run
without the pipeline installed (copy this file). Control law:

1. ``select(x0)``: choose the trajectory ``i`` minimising ``||x0 - x0_i||_P / radius_i``
   (``x0`` is covered when that value is ``< 1``);
2. ``__call__(t, x)``: ``u = clip(u_ref_i[floor(t / Ts)] + K (x - x_ref_i(t)), lower, upper)``
   with ``x_ref_i`` linearly interpolated on the trajectory's fine grid ``t``.

Both accept a batch: ``x0 (B, n)`` selects one trajectory per row, and ``x (B, n)`` is then
controlled row by row; a single state ``(n,)`` works too.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

FORMAT = "safety-controller/1"


class ControllerFormatError(ValueError):
    """``controller.json`` is not a valid ``safety-controller/1`` file; the message says where."""

    exit_code = 2


@dataclass(frozen=True)
class ReferenceTrajectory:
    """One nominal trajectory: ``x0 (n,)``, ``u_ref (N, m)``, ``t (k,)``, ``x_ref (k, n)``."""

    x0: np.ndarray
    radius: float
    T: float
    u_ref: np.ndarray
    t: np.ndarray
    x_ref: np.ndarray


class Controller:
    """``u = u_ref_i(t) + K (x - x_ref_i(t))`` around the trajectory selected at the start."""

    def __init__(self, data: dict[str, Any], source: str = "controller.json") -> None:
        self.data = data
        self.source = source
        self.state_names = list(data["state_names"])
        self.input_names = list(data["input_names"])
        self.Ts = float(data["Ts"])
        self.lower = np.asarray(data["input_bounds"]["lower"], dtype=np.float64)
        self.upper = np.asarray(data["input_bounds"]["upper"], dtype=np.float64)
        self.K = np.asarray(data["feedback"]["K"], dtype=np.float64)
        self.P = np.asarray(data["feedback"]["P"], dtype=np.float64)
        self.rate = float(data["feedback"]["rate"])
        self.trajectories = tuple(
            ReferenceTrajectory(
                x0=np.asarray(item["x0"], dtype=np.float64),
                radius=float(item["radius"]),
                T=float(item["T"]),
                u_ref=np.asarray(item["u_ref"], dtype=np.float64),
                t=np.asarray(item["t"], dtype=np.float64),
                x_ref=np.asarray(item["x_ref"], dtype=np.float64),
            )
            for item in data["trajectories"]
        )
        self._selected: np.ndarray | None = None

    @property
    def n(self) -> int:
        return len(self.state_names)

    def coverage_ratio(self, x0: np.ndarray) -> np.ndarray:
        """``min_i ||x0 - x0_i||_P / radius_i`` for ``x0 (..., n)`` -> ``(...)``; < 1 is covered."""
        return np.min(self._ratios(np.asarray(x0, dtype=np.float64)), axis=-1)

    def _ratios(self, x0: np.ndarray) -> np.ndarray:
        centres = np.stack([tr.x0 for tr in self.trajectories])  # (k, n)
        radii = np.array([tr.radius for tr in self.trajectories])  # (k,)
        e = x0[..., None, :] - centres  # (..., k, n)
        return np.sqrt(np.einsum("...i,ij,...j->...", e, self.P, e)) / radii

    def select(self, x0: np.ndarray) -> np.ndarray:
        """Choose the trajectory for each initial state ``x0 (..., n)``; -> indices ``(...)``."""
        index = np.argmin(self._ratios(np.asarray(x0, dtype=np.float64)), axis=-1)
        self._selected = index
        return index

    def follow(self, index: np.ndarray) -> None:
        """Track trajectories ``index (...)`` without selecting (e.g. to test one trajectory)."""
        self._selected = np.asarray(index)

    def reference(self, t: float, index: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(u_ref (..., m), x_ref (..., n))`` of the selected trajectories at time ``t``."""
        index = self._require_selection() if index is None else np.asarray(index)
        u = np.empty((*index.shape, len(self.input_names)))
        x = np.empty((*index.shape, self.n))
        for i, tr in enumerate(self.trajectories):
            rows = index == i
            if not np.any(rows):
                continue
            k = min(int(np.floor(t / self.Ts + 1e-9)), len(tr.u_ref) - 1)
            u[rows] = tr.u_ref[max(k, 0)]
            x[rows] = [np.interp(t, tr.t, tr.x_ref[:, j]) for j in range(self.n)]
        return u, x

    def unclipped(self, t: float, x: np.ndarray) -> np.ndarray:
        """``u_ref + K (x - x_ref)`` before clipping, ``x (..., n)`` -> ``(..., m)``."""
        u_ref, x_ref = self.reference(t)
        return u_ref + (np.asarray(x) - x_ref) @ self.K.T

    def __call__(self, t: float, x: np.ndarray) -> np.ndarray:
        """The control input at time ``t`` for states ``x (..., n)`` -> ``(..., m)``."""
        return np.clip(self.unclipped(t, x), self.lower, self.upper)

    def _require_selection(self) -> np.ndarray:
        if self._selected is None:
            raise RuntimeError("call select(x0) with the initial state(s) before controlling")
        return self._selected


def _check(data: Any, source: str) -> None:
    def fail(field: str, found: object, expected: str) -> None:
        raise ControllerFormatError(f"{source}: {field}: found {found!r}; expected {expected}")

    if not isinstance(data, dict):
        fail("(top level)", type(data).__name__, "a JSON object")
    if data.get("format") != FORMAT:
        fail("format", data.get("format"), f"'{FORMAT}'")
    required = [
        "scenario",
        "state_names",
        "input_names",
        "Ts",
        "input_bounds",
        "feedback",
        "trajectories",
    ]
    for key in required:
        if key not in data:
            fail(key, "nothing (missing field)", "this required field")
    n, m = len(data["state_names"]), len(data["input_names"])

    def shape(field: str, value: object, expected: tuple[int | None, ...]) -> None:
        try:
            array = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            fail(field, value if not isinstance(value, list) else "ragged list", "numbers")
        if array.ndim != len(expected) or any(
            e is not None and s != e for s, e in zip(array.shape, expected, strict=True)
        ):
            fail(field, f"shape {array.shape}", f"shape {expected} (None: any length)")
        if not np.all(np.isfinite(array)):
            fail(field, "a non-finite value", "finite numbers")

    shape("Ts", data["Ts"], ())
    for key in ("lower", "upper"):
        shape(f"input_bounds.{key}", data["input_bounds"].get(key), (m,))
    for key in ("K", "P", "rate"):
        if key not in data["feedback"]:
            fail(f"feedback.{key}", "nothing (missing field)", "this required field")
    shape("feedback.K", data["feedback"]["K"], (m, n))
    shape("feedback.P", data["feedback"]["P"], (n, n))
    shape("feedback.rate", data["feedback"]["rate"], ())
    if not data["trajectories"]:
        fail("trajectories", "an empty list", "at least one trajectory")
    for i, item in enumerate(data["trajectories"]):
        where = f"trajectories[{i}]"
        for key in ("x0", "radius", "T", "u_ref", "t", "x_ref"):
            if key not in item:
                fail(f"{where}.{key}", "nothing (missing field)", "this required field")
        shape(f"{where}.x0", item["x0"], (n,))
        shape(f"{where}.radius", item["radius"], ())
        shape(f"{where}.u_ref", item["u_ref"], (None, m))
        shape(f"{where}.t", item["t"], (None,))
        shape(f"{where}.x_ref", item["x_ref"], (len(item["t"]), n))


def load(path: str | Path) -> Controller:
    """Read and validate ``controller.json``; a bad file raises ``ControllerFormatError``."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except OSError as error:
        raise ControllerFormatError(f"{path}: cannot read ({error.strerror})") from None
    except json.JSONDecodeError as error:
        raise ControllerFormatError(
            f"{path}: invalid JSON at line {error.lineno}, column {error.colno}: {error.msg}"
        ) from None
    _check(data, str(path))
    return Controller(data, str(path))
