"""The recorder's window: choose a start, count down, fly in real time, save or retry; and replay.

Everything the pilot does arrives as pygame events (keys, mouse, joystick axes and buttons), so a
test drives the window by posting events and calling ``update(now)`` with a scripted clock; the
real loop (``run``) calls it with the wall clock about 120 times a second. The flight itself is a
``pipeline.demonstrations.recorder.flight.Recorder``: at the first frame with ``t >= k Ts`` the
stick is read and held as ``u[k]``.

Keys: SPACE / ENTER / any stick button starts the countdown (and, after a flight, the next
attempt); a click inside Init moves the start; ESC quits (a flight in progress is dropped).
"""

from __future__ import annotations

import enum
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pygame

from pipeline.demonstrations.recorder.config import RecorderConfig
from pipeline.demonstrations.recorder.draw import GOOD, INK, MUTED, WARN, Scene
from pipeline.demonstrations.recorder.flight import (
    Flight,
    FlightStatus,
    Recorder,
    check_start,
    interpolate,
)
from pipeline.demonstrations.recorder.save import save_flight
from pipeline.io.errors import UserError
from pipeline.model.demos import Demo
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import simulate

FRAME_RATE = 120
START_KEYS = ("space", "return", "r")
QUIT_KEYS = ("escape", "q")


def start_pygame() -> None:
    """Initialise the parts of pygame the recorder uses (no audio)."""
    pygame.display.init()
    pygame.font.init()
    pygame.joystick.init()


def open_window(size: tuple[int, int], title: str) -> pygame.Surface:
    """The window's surface, or a UserError when no window can be opened."""
    try:
        surface = pygame.display.set_mode(size)
    except pygame.error as error:
        raise UserError(
            f"cannot open a window ({error})",
            expected="a display (or SDL_VIDEODRIVER=dummy for a headless run)",
        ) from None
    headless = pygame.display.get_driver() in ("dummy", "offscreen")
    if headless and os.environ.get("SDL_VIDEODRIVER") not in ("dummy", "offscreen"):
        raise UserError(
            "no display to open the recorder's window on",
            expected="a desktop session (or SDL_VIDEODRIVER=dummy to run headless on purpose)",
        )
    pygame.display.set_caption(title)
    return surface


def check_keys(config: RecorderConfig) -> None:
    """Every key name in the mapping must be a pygame key name."""
    for name in sorted(config.keys):
        try:
            pygame.key.key_code(name)
        except ValueError:
            raise UserError(
                f"unknown key name '{name}'",
                file=config.source,
                field="inputs.*.keys",
                expected="a pygame key name such as 'w', 'up', 'left', 'space'",
            ) from None


class StickInput:
    """The stick axes and held keys, kept up to date from pygame events."""

    def __init__(self, config: RecorderConfig) -> None:
        self.config = config
        self.axes: dict[int, float] = {}
        self.pressed: set[str] = set()
        self.joysticks: dict[int, pygame.joystick.JoystickType] = {}
        self.used: set[str] = set()  # devices moved since ``reset_used``

    def handle(self, event: pygame.event.Event) -> None:
        if event.type == pygame.JOYDEVICEADDED:
            joystick = pygame.joystick.Joystick(event.device_index)
            self.joysticks[joystick.get_instance_id()] = joystick
        elif event.type == pygame.JOYDEVICEREMOVED:
            self.joysticks.pop(event.instance_id, None)
            self.axes.clear()
        elif event.type == pygame.JOYAXISMOTION:
            self.axes[event.axis] = float(event.value)
            if abs(event.value) > self.config.dead_zone:
                self.used.add(self._joystick_name(event))
        elif event.type == pygame.KEYDOWN:
            name = pygame.key.name(event.key)
            self.pressed.add(name)
            if name in self.config.keys:
                self.used.add("keyboard")
        elif event.type == pygame.KEYUP:
            self.pressed.discard(pygame.key.name(event.key))

    def _joystick_name(self, event: pygame.event.Event) -> str:
        instance = getattr(event, "instance_id", getattr(event, "joy", 0))
        joystick = self.joysticks.get(instance)
        return f"joystick '{joystick.get_name()}'" if joystick else f"joystick {instance}"

    def sample(self) -> FloatArray:
        """The input ``u (m,)`` the stick and keys give now."""
        return self.config.inputs_from(self.axes, self.pressed)

    def device(self) -> str:
        """The devices used in the flight, for the CSV header."""
        if self.used:
            return " and ".join(sorted(self.used))
        names = [f"joystick '{j.get_name()}'" for j in self.joysticks.values()]
        return " and ".join(names) or "keyboard"

    def describe(self) -> str:
        """One line for the window: the raw stick axes (to find axis numbers), or the keys."""
        if self.axes:
            return "stick axes " + "  ".join(f"{a}:{v:+.2f}" for a, v in sorted(self.axes.items()))
        keys = [
            f"{m.name} {'/'.join(m.increase_keys)} + {'/'.join(m.decrease_keys)} -"
            for m in self.config.inputs
            if m.increase_keys or m.decrease_keys
        ]
        return "no stick moved yet; keyboard: " + ", ".join(keys)


class Phase(enum.Enum):
    CHOOSE = "choose a start"
    COUNTDOWN = "countdown"
    FLYING = "flying"
    ENDED = "ended"


class RecorderApp:
    """The recording window; ``update(now)`` advances it to time ``now`` (s, any origin)."""

    def __init__(
        self,
        scenario: Scenario,
        config: RecorderConfig,
        x0: FloatArray,
        reason: str,
        surface: pygame.Surface | None = None,
        save: Callable[[Scenario, Flight, str], Path] = save_flight,
    ) -> None:
        check_keys(config)
        self.scenario, self.config, self.save = scenario, config, save
        self.scene = Scene(scenario, config)
        self.surface = surface or open_window(self.scene.size, f"record {scenario.name}")
        self.x0 = check_start(scenario, x0)
        self.reason = reason
        self.stick = StickInput(config)
        self.phase = Phase.CHOOSE
        self.recorder: Recorder | None = None
        self.t_start = 0.0
        self.now = 0.0
        self.running = True
        self.saved: list[Path] = []
        self.result: list[tuple[str, tuple[int, int, int]]] = []

    # --- events ------------------------------------------------------------------------------
    def handle(self, event: pygame.event.Event) -> None:
        self.stick.handle(event)
        key = pygame.key.name(event.key) if event.type == pygame.KEYDOWN else None
        if event.type == pygame.QUIT or key in QUIT_KEYS:
            self.running = False
        elif key in START_KEYS or event.type == pygame.JOYBUTTONDOWN:
            if self.phase in (Phase.CHOOSE, Phase.ENDED):
                self.phase, self.t_start = Phase.COUNTDOWN, self.now
        elif event.type == pygame.MOUSEBUTTONDOWN and event.button == 1:
            if self.phase in (Phase.CHOOSE, Phase.ENDED):
                self.click(event.pos)

    def click(self, pixel: tuple[int, int]) -> None:
        """Move the start to the clicked position if the click is inside Init (8 px slack)."""
        i, j = self.scenario.position_index
        lower, upper = self.scenario.init_lower, self.scenario.init_upper
        p = self.scene.to_world(pixel)
        slack = 8.0 / self.scene.scale
        if np.all(p >= lower[[i, j]] - slack) and np.all(p <= upper[[i, j]] + slack):
            x0 = self.x0.copy()
            x0[[i, j]] = np.round(p, 3)
            self.x0 = np.clip(x0, lower, upper)
            self.reason = "clicked"
            self.phase, self.result = Phase.CHOOSE, []

    # --- time ----------------------------------------------------------------------------------
    def update(self, now: float) -> None:
        """Handle pending events, advance to ``now`` and draw the frame."""
        self.now = now
        for event in pygame.event.get():
            self.handle(event)
        if self.phase is Phase.COUNTDOWN and now - self.t_start >= self.config.countdown:
            self.t_start += self.config.countdown
            self.phase, self.result = Phase.FLYING, []
            self.stick.used.clear()
            self.recorder = Recorder(
                self.scenario, self.x0, self.config.goal_margin, self.config.max_duration
            )
        if self.phase is Phase.FLYING and self.running:
            self._fly(now - self.t_start)
        self.render()

    def _fly(self, t: float) -> None:
        recorder = self.recorder
        assert recorder is not None
        Ts = self.scenario.Ts
        while recorder.status is FlightStatus.FLYING and recorder.N * Ts <= t + 1e-12:
            recorder.step(self.stick.sample())
        if recorder.status is not FlightStatus.FLYING and t >= recorder.end_time:
            self._finish(recorder.flight())

    def _finish(self, flight: Flight) -> None:
        self.phase = Phase.ENDED
        again = "SPACE / a stick button: fly again   ESC: quit"
        if not flight.status.valid:
            self.result = [(flight.message, WARN), (again, INK)]
            return
        try:
            path = self.save(self.scenario, flight, self.stick.device())
        except UserError as error:
            self.result = [(f"{flight.message}, but NOT saved: {error}", WARN), (again, INK)]
            return
        self.saved.append(path)
        name = path.relative_to(self.scenario.path.parent).as_posix()
        self.result = [
            (flight.message, GOOD),
            (f"saved as {name} and listed in scenario.yaml; `make synthesize` uses it", GOOD),
            (again, INK),
        ]

    # --- drawing -------------------------------------------------------------------------------
    def render(self) -> None:
        recorder, u = self.recorder, self.stick.sample()
        x, trail, t, big = self.x0, self.x0[None, :], 0.0, None
        lines: list[tuple[str, tuple[int, int, int]]] = []
        if self.phase is Phase.CHOOSE:
            start = ", ".join(f"{v:g}" for v in self.x0)
            lines = [
                (f"start x0 = [{start}] ({self.reason})", INK),
                ("click inside Init to move it; SPACE / a stick button to start", INK),
            ]
        elif self.phase is Phase.COUNTDOWN:
            big = str(int(np.ceil(self.config.countdown - (self.now - self.t_start))))
            lines = [("get ready: the stick is live", INK)]
        elif recorder is not None:
            t = min(self.now - self.t_start, recorder.end_time)
            x = recorder.state_at(t)
            h = self.scenario.Ts / recorder.substeps
            trail = recorder.dense_xs[: int(t / h) + 1]
            k = min(int(t / self.scenario.Ts), recorder.N - 1)
            u = recorder.us[k] if self.phase is Phase.FLYING and k >= 0 else u
            lines = self.result or [
                ("flying: reach Goal without touching Unsafe", INK),
                (f"the stick is read every Ts = {self.scenario.Ts:g} s and held in between", MUTED),
            ]
        footer = (self.stick.describe(), "ESC: quit")
        self.scene.draw(self.surface, x, u, trail, t, lines, big, footer)


class ReplayApp:
    """Shows a demo flown again from its CSV: the same drawing, the held inputs as bars."""

    def __init__(
        self,
        scenario: Scenario,
        config: RecorderConfig,
        demo: Demo,
        surface: pygame.Surface | None = None,
    ) -> None:
        self.scenario, self.demo = scenario, demo
        self.scene = Scene(scenario, config)
        self.surface = surface or open_window(self.scene.size, f"replay {demo.name}")
        self.trajectory = simulate(scenario.dynamics, demo.x0, demo.us, scenario.Ts)
        self.h = float(self.trajectory.dense_ts[1])
        header = [
            line.lstrip("# ").strip()
            for line in demo.file.read_text(encoding="utf-8").splitlines()
            if line.startswith("#")
        ]
        self.origin = header[0] if header else ""
        self.t_start = 0.0
        self.running = True

    def update(self, now: float) -> None:
        for event in pygame.event.get():
            key = pygame.key.name(event.key) if event.type == pygame.KEYDOWN else None
            if event.type == pygame.QUIT or key in QUIT_KEYS:
                self.running = False
            elif key in START_KEYS or event.type == pygame.JOYBUTTONDOWN:
                self.t_start = now
        duration = self.trajectory.duration
        t = min(now - self.t_start, duration)
        x = interpolate(self.trajectory.dense_xs, self.h, t)
        k = min(int(t / self.scenario.Ts), self.demo.N - 1)
        end = ""
        if t >= duration:
            inside = bool(self.scenario.in_goal(self.trajectory.final_state))
            end = f"end: {'in' if inside else 'NOT in'} Goal; SPACE replays"
        lines = [(f"replay of {self.demo.name}", INK), (self.origin, MUTED), (end, INK)]
        trail = self.trajectory.dense_xs[: int(t / self.h) + 1]
        footer = (f"{self.demo.file}", "SPACE: replay   ESC: quit")
        self.scene.draw(self.surface, x, self.demo.us[k], trail, t, lines, None, footer)


def run_loop(app: RecorderApp | ReplayApp) -> None:
    """Call ``app.update`` with the wall clock until it stops running."""
    clock = pygame.time.Clock()
    origin = time.perf_counter()
    while app.running:
        app.update(time.perf_counter() - origin)
        pygame.display.flip()
        clock.tick(FRAME_RATE)
