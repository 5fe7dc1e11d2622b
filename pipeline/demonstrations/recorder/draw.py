"""Drawing the recorder's window with pygame: the scenario's sets, the vehicle, time and inputs.

The map shows the position plane (Unsafe red, Goal green, Init blue); the vehicle is a marker at
its position and, when ``recorder.yaml`` names an ``angle_state``, a body line turned by that
angle with a stub along the body's "up" (for the planar quadrotor: rotors and thrust direction).
Below the map, each input is a bar over its bounds, filled from the stick's centre to the value.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
import pygame
from shapely.geometry.base import BaseGeometry

from pipeline.demonstrations.recorder.config import RecorderConfig
from pipeline.model import geometry
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario

WIDTH = 1000  # px
MAX_MAP_HEIGHT = 540
BACKGROUND = (246, 245, 240)
GRID = (225, 224, 218)
INK = (30, 30, 35)
MUTED = (110, 110, 118)
UNSAFE = (206, 84, 70)
GOAL = (98, 176, 104)
INIT = (70, 118, 200)
TRAIL = (120, 120, 140)
VEHICLE = (20, 20, 28)
BAR = (70, 118, 200)
BAR_BACK = (222, 222, 228)
WARN = (190, 40, 30)
GOOD = (40, 130, 60)
BODY = 0.7  # m, half-length of the drawn body
STUB = 0.5  # m, the "up" stub
MESSAGE_LINES = 3


class Scene:
    """The scenario's static picture and the map transform (world m <-> screen px)."""

    def __init__(self, scenario: Scenario, config: RecorderConfig) -> None:
        self.scenario, self.config = scenario, config
        shapes = [*scenario.unsafe.values(), scenario.goal]
        bounds = np.array([shape.bounds for shape in shapes])
        i, j = scenario.position_index
        lower = np.minimum(bounds[:, :2].min(axis=0), scenario.init_lower[[i, j]])
        upper = np.maximum(bounds[:, 2:].max(axis=0), scenario.init_upper[[i, j]])
        pad = 0.03 * (upper - lower)
        self.lower, self.upper = lower - pad, upper + pad
        span = self.upper - self.lower
        self.scale = min(WIDTH / span[0], MAX_MAP_HEIGHT / span[1])  # px per m
        self.map_size = (int(round(span[0] * self.scale)), int(round(span[1] * self.scale)))
        hud = 14 + 34 * scenario.m + 26 * MESSAGE_LINES + 52  # bars, messages, help
        self.size = (max(self.map_size[0], 760), self.map_size[1] + hud)
        self.fonts = {size: pygame.font.Font(None, size) for size in (18, 22, 28, 44, 120)}
        self.background = self._background()

    def to_screen(self, points: npt.ArrayLike) -> FloatArray:
        """Positions ``(..., 2)`` in m -> pixels ``(..., 2)`` (y up on the map)."""
        p = (np.asarray(points, dtype=np.float64) - self.lower) * self.scale
        return np.stack([p[..., 0], self.map_size[1] - p[..., 1]], axis=-1)

    def to_world(self, pixel: Sequence[float]) -> FloatArray:
        """A pixel ``(2,)`` -> its position ``(2,)`` in m."""
        u, v = float(pixel[0]), float(pixel[1])
        return self.lower + np.array([u, self.map_size[1] - v]) / self.scale

    def text(
        self,
        surface: pygame.Surface,
        words: str,
        at: tuple[float, float],
        size: int = 22,
        color: tuple[int, int, int] = INK,
        centre: bool = False,
        panel: bool = False,
    ) -> None:
        """Draw ``words``; with ``panel``, on a translucent white box (readable over any set)."""
        if not words:
            return
        image = self.fonts[size].render(words, True, color)
        rect = image.get_rect(center=at) if centre else image.get_rect(topleft=at)
        if panel:
            box = pygame.Surface(rect.inflate(10, 4).size, pygame.SRCALPHA)
            box.fill((255, 255, 255, 210))
            surface.blit(box, rect.inflate(10, 4).topleft)
        surface.blit(image, rect)

    def _polygon(
        self,
        surface: pygame.Surface,
        shape: BaseGeometry,
        fill: tuple[int, int, int],
        width: int = 0,
    ) -> None:
        points = self.to_screen(np.asarray(shape.exterior.coords)[:-1])
        pygame.draw.polygon(surface, fill, points.tolist(), width)

    def _background(self) -> pygame.Surface:
        scenario = self.scenario
        surface = pygame.Surface(self.size)
        surface.fill(BACKGROUND)
        step = 1.0 if max(self.upper - self.lower) < 15 else 5.0
        for value in np.arange(np.ceil(self.lower[0] / step) * step, self.upper[0], step):
            (u, _), (_, v) = self.to_screen([value, self.lower[1]]), self.to_screen(self.upper)
            pygame.draw.line(surface, GRID, (u, v), (u, self.map_size[1]))
            self.text(surface, f"{value:g}", (u + 2, self.map_size[1] - 16), 18, MUTED)
        for value in np.arange(np.ceil(self.lower[1] / step) * step, self.upper[1], step):
            _, v = self.to_screen([self.lower[0], value])
            pygame.draw.line(surface, GRID, (0, v), (self.map_size[0], v))
            self.text(surface, f"{value:g}", (2, v + 2), 18, MUTED)
        self._polygon(surface, scenario.goal, GOAL)
        if self.config.goal_margin > 0:
            landing = geometry.shrink(scenario.goal, self.config.goal_margin)
            if not landing.is_empty:
                self._polygon(surface, landing, (60, 130, 70), 1)
        self.text(surface, "Goal", tuple(self._label_at(scenario.goal)), 22, INK, True)
        for name, region in scenario.unsafe.items():
            self._polygon(surface, region, UNSAFE)
            self.text(surface, f"Unsafe: {name}", tuple(self._label_at(region)), 22, INK, True)
        i, j = scenario.position_index
        lo = self.to_screen(scenario.init_lower[[i, j]])
        hi = self.to_screen(scenario.init_upper[[i, j]])
        rect = pygame.Rect(lo[0], hi[1], max(hi[0] - lo[0], 2), max(lo[1] - hi[1], 2))
        pygame.draw.rect(surface, INIT, rect.inflate(2, 2), 2)
        self.text(surface, "Init", (rect.left, rect.bottom + 3), 22, INIT)
        pygame.draw.line(surface, INK, (0, self.map_size[1]), (self.size[0], self.map_size[1]))
        return surface

    def _label_at(self, shape: BaseGeometry) -> FloatArray:
        (x0, y0), (x1, y1) = self.lower, self.upper
        view = geometry.polygon([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
        point = shape.intersection(view).representative_point()
        return self.to_screen([point.x, point.y])

    def draw(
        self,
        surface: pygame.Surface,
        x: FloatArray,
        u: FloatArray | None,
        trail: FloatArray,
        t: float,
        lines: Sequence[tuple[str, tuple[int, int, int]]] = (),
        big: str | None = None,
        footer: Sequence[str] = (),
    ) -> None:
        """One frame: the state ``x (n,)``, inputs ``u (m,)`` (or None), the path so far
        ``trail (k, n)``, the time, a ``big`` countdown over the map; under it the input bars,
        up to three message ``lines`` and the ``footer`` lines of help."""
        surface.blit(self.background, (0, 0))
        if len(trail) > 1:
            points = self.to_screen(self.scenario.positions(trail))
            pygame.draw.lines(surface, TRAIL, False, points.tolist(), 2)
        self._vehicle(surface, x)
        self.text(surface, f"t = {t:5.2f} s", (12, 10), 44, panel=True)
        top = self.map_size[1] + 14 + 34 * self.scenario.m
        for row, (words, color) in enumerate(lines[:MESSAGE_LINES]):
            self.text(surface, words, (12, top + 26 * row), 28, color)
        if big is not None:
            middle = (self.map_size[0] / 2, self.map_size[1] / 2)
            self.text(surface, big, middle, 120, INK, centre=True, panel=True)
        self._bars(surface, u)
        for row, words in enumerate(reversed(footer)):
            self.text(surface, words, (12, self.size[1] - 22 - 20 * row), 22, MUTED)

    def _vehicle(self, surface: pygame.Surface, x: FloatArray) -> None:
        position = self.scenario.positions(x)
        centre = self.to_screen(position)
        k = self.config.angle_index
        if k is not None:
            a = float(x[k])
            along = np.array([np.cos(a), np.sin(a)])
            up = np.array([-np.sin(a), np.cos(a)])
            ends = self.to_screen([position - BODY * along, position + BODY * along])
            back, front = ends.tolist()
            pygame.draw.line(surface, VEHICLE, back, front, 5)
            stub = self.to_screen(position + STUB * up)
            pygame.draw.line(surface, VEHICLE, centre.tolist(), stub.tolist(), 2)
            for end in ends:
                pygame.draw.circle(surface, VEHICLE, end, 7, 2)
        pygame.draw.circle(surface, VEHICLE, centre.tolist(), 7)

    def _bars(self, surface: pygame.Surface, u: FloatArray | None) -> None:
        scenario = self.scenario
        left, width, top = 150, self.size[0] - 420, self.map_size[1] + 14
        for i, mapping in enumerate(self.config.inputs):
            lower, upper = float(scenario.input_lower[i]), float(scenario.input_upper[i])
            y = top + 34 * i

            def at(value: float, lower: float = lower, upper: float = upper) -> float:
                return left + width * (value - lower) / max(upper - lower, 1e-12)

            self.text(surface, mapping.name, (12, y + 2), 28)
            pygame.draw.rect(surface, BAR_BACK, (left, y, width, 22))
            if u is not None:
                a, b = sorted((at(mapping.centre), at(float(u[i]))))
                pygame.draw.rect(surface, BAR, (a, y, max(b - a, 2), 22))
            for end, color in ((mapping.low, MUTED), (mapping.high, MUTED), (mapping.centre, INK)):
                pygame.draw.line(surface, color, (at(end), y - 3), (at(end), y + 25))
            value = "-" if u is None else f"{float(u[i]):+.2f}"
            self.text(surface, f"{value}   in [{lower:g}, {upper:g}]", (left + width + 14, y + 2))
