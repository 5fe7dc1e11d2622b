"""Drawing the recorder's window with pygame: the scenario's sets, the vehicle, time and inputs.

The map shows the part of the position plane that matters to the flight (``view.view_box``):
Unsafe red with its clearance band (Unsafe bloated by the clearance ``d``, light red), Goal green
with ModGoal (Goal shrunk by ``d``, dashed) and the recorder's landing line, Init blue; a legend
names them. The vehicle is a marker at its position and, when ``recorder.yaml`` names an
``angle_state``, a body line turned by that angle with a stub along the body's "up" (for the
planar quadrotor: rotors and thrust direction); off the map, a marker on its edge says so. The
HUD under the time gives the speed and attitude (``view.hud_lines``). Below the map, each input
is a bar over its bounds, filled from the stick's centre to the value, labelled with its name,
label and unit (``view.input_rows``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
import pygame
from shapely.geometry.base import BaseGeometry

from pipeline.demonstrations.recorder.config import RecorderConfig
from pipeline.demonstrations.recorder.view import demo_paths, hud_lines, input_rows, view_box
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
BAND = (240, 196, 188)  # the clearance band: within d of Unsafe
GOAL = (98, 176, 104)
MODGOAL = (30, 90, 40)
LANDING = (60, 130, 70)
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
Color = tuple[int, int, int]
HUD_TOP = 60  # px: the HUD's lines start under the time


class Scene:
    """The scenario's static picture and the map transform (world m <-> screen px)."""

    def __init__(self, scenario: Scenario, config: RecorderConfig) -> None:
        self.scenario, self.config = scenario, config
        self.view = view_box(scenario, demo_paths(scenario))
        self.lower, self.upper = self.view.lower, self.view.upper
        span = self.view.span
        self.scale = min(WIDTH / span[0], MAX_MAP_HEIGHT / span[1])  # px per m
        self.map_size = (int(round(span[0] * self.scale)), int(round(span[1] * self.scale)))
        hud = 14 + 34 * scenario.m + 26 * MESSAGE_LINES + 52  # bars, messages, help
        self.size = (max(self.map_size[0], 760), self.map_size[1] + hud)
        self.fonts = {size: pygame.font.Font(None, size) for size in (18, 22, 28, 44, 120)}
        self.label_width = max(
            self.fonts[22].size(label)[0] for label, _ in input_rows(scenario, None)
        )
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
        """Draw a polygon or multipolygon (filled: its holes in the background colour)."""
        for part in getattr(shape, "geoms", [shape]):
            points = self.to_screen(np.asarray(part.exterior.coords)[:-1])
            pygame.draw.polygon(surface, fill, points.tolist(), width)
            for hole in part.interiors if width == 0 else ():
                inner = self.to_screen(np.asarray(hole.coords)[:-1])
                pygame.draw.polygon(surface, BACKGROUND, inner.tolist())

    def _dashed(self, surface: pygame.Surface, shape: BaseGeometry, color: Color) -> None:
        """The outline of a polygon, dashed (8 px on, 6 off), 2 px wide."""
        for part in getattr(shape, "geoms", [shape]):
            ring = self.to_screen(np.asarray(part.exterior.coords))
            for a, b in zip(ring[:-1], ring[1:], strict=True):
                length = float(np.hypot(*(b - a)))
                for start in np.arange(0.0, length, 14.0):
                    end = min(start + 8.0, length)
                    p, q = a + (b - a) * start / length, a + (b - a) * end / length
                    pygame.draw.line(surface, color, p.tolist(), q.tolist(), 2)

    def _background(self) -> pygame.Surface:
        scenario, d = self.scenario, self.scenario.clearance
        surface = pygame.Surface(self.size)
        surface.fill(BACKGROUND)
        surface.set_clip(pygame.Rect((0, 0), self.map_size))  # sets reach beyond the view
        step = self._grid_step()
        ticks = [
            np.arange(np.ceil(lo / step) * step, hi, step)
            for lo, hi in zip(self.lower, self.upper, strict=True)
        ]
        for value in ticks[0]:
            u = self.to_screen([value, self.lower[1]])[0]
            pygame.draw.line(surface, GRID, (u, 0), (u, self.map_size[1]))
        for value in ticks[1]:
            v = self.to_screen([self.lower[0], value])[1]
            pygame.draw.line(surface, GRID, (0, v), (self.map_size[0], v))
        for region in scenario.unsafe.values():  # the clearance band, under Unsafe itself
            self._polygon(surface, geometry.bloat(region, d), BAND)
        self._polygon(surface, scenario.goal, GOAL)
        if self.config.goal_margin > 0:
            landing = geometry.shrink(scenario.goal, self.config.goal_margin)
            if not landing.is_empty:
                self._polygon(surface, landing, LANDING, 1)
        modgoal = geometry.shrink(scenario.goal, d)
        if not modgoal.is_empty:
            self._dashed(surface, modgoal, MODGOAL)
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
        for value in ticks[0]:  # tick labels over the sets
            u = self.to_screen([value, self.lower[1]])[0]
            self.text(
                surface, f"{value + 0.0:g}", (u + 4, self.map_size[1] - 16), 18, MUTED, panel=True
            )
        for value in ticks[1]:
            v = self.to_screen([self.lower[0], value])[1]
            self.text(surface, f"{value + 0.0:g}", (6, v + 2), 18, MUTED, panel=True)
        self._axes(surface)
        self._legend(surface)
        surface.set_clip(None)
        pygame.draw.line(surface, INK, (0, self.map_size[1]), (self.size[0], self.map_size[1]))
        return surface

    def _grid_step(self) -> float:
        """The grid's spacing: the smallest of 1, 2, 5, 10, ... units at least 40 px apart."""
        for step in (0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0):
            if step * self.scale >= 40:
                return step
        return 100.0

    def legend_rows(self) -> list[tuple[Color, str]]:
        """The map legend: (colour, words) per row."""
        scenario, unit = self.scenario, self.scenario.position_unit()
        d = f"{scenario.clearance:g}{f' {unit}' if unit else ''}"
        rows = [
            (UNSAFE, "Unsafe"),
            (BAND, f"clearance band: within d = {d} of Unsafe"),
            (GOAL, "Goal"),
            (MODGOAL, "ModGoal: Goal shrunk by d (dashed)"),
        ]
        if self.config.goal_margin > 0:
            margin = f"{self.config.goal_margin:g}{f' {unit}' if unit else ''}"
            rows.append((LANDING, f"a flight ends {margin} inside Goal (line)"))
        rows.append((INIT, "Init: click inside to move the start"))
        return rows

    def _legend(self, surface: pygame.Surface) -> None:
        rows = self.legend_rows()
        font = self.fonts[18]
        width = 26 + max(font.size(words)[0] for _, words in rows)
        box = pygame.Surface((width + 10, 18 * len(rows) + 8), pygame.SRCALPHA)
        box.fill((255, 255, 255, 215))
        left = self.map_size[0] - box.get_width() - 8
        surface.blit(box, (left, 8))
        for row, (color, words) in enumerate(rows):
            y = 12 + 18 * row
            pygame.draw.rect(surface, color, (left + 6, y + 2, 18, 11))
            self.text(surface, words, (left + 30, y), 18, INK)

    def _axes(self, surface: pygame.Surface) -> None:
        """The position states' names, labels and units along the map's edges."""
        i, j = self.scenario.position_index
        across = self.fonts[18].render(self.scenario.label(self.scenario.state_names[i]), True, INK)
        surface.blit(across, (self.map_size[0] - across.get_width() - 6, self.map_size[1] - 34))
        up = self.fonts[18].render(self.scenario.label(self.scenario.state_names[j]), True, INK)
        up = pygame.transform.rotate(up, 90)
        surface.blit(up, (22, (self.map_size[1] - up.get_height()) / 2))

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
        surface.set_clip(pygame.Rect((0, 0), self.map_size))
        if len(trail) > 1:
            points = self.to_screen(self.scenario.positions(trail))
            pygame.draw.lines(surface, TRAIL, False, points.tolist(), 2)
        self._vehicle(surface, x)
        surface.set_clip(None)
        self.text(surface, f"t = {t:5.2f} s", (12, 10), 44, panel=True)
        for row, words in enumerate(hud_lines(self.scenario, x, u, self.config.angle_index)):
            self.text(surface, words, (12, HUD_TOP + 24 * row), 22, panel=True)
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
        if not self.view.contains(position):  # a marker on the map's edge, towards it
            inset = 10.0 / self.scale
            edge = np.clip(position, self.lower + inset, self.upper - inset)
            where = self.to_screen(edge)
            pygame.draw.circle(surface, WARN, where.tolist(), 9, 3)
            words_at = (float(np.clip(where[0] - 40, 4, self.map_size[0] - 90)), where[1] + 12)
            self.text(surface, "off the map", words_at, 18, WARN, panel=True)
            return
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
        left = 24 + self.label_width
        width, top = self.size[0] - left - 270, self.map_size[1] + 14
        rows = input_rows(scenario, u)
        for i, mapping in enumerate(self.config.inputs):
            lower, upper = float(scenario.input_lower[i]), float(scenario.input_upper[i])
            y = top + 34 * i

            def at(value: float, lower: float = lower, upper: float = upper) -> float:
                return left + width * (value - lower) / max(upper - lower, 1e-12)

            label, value = rows[i]
            self.text(surface, label, (12, y + 4), 22)
            pygame.draw.rect(surface, BAR_BACK, (left, y, width, 22))
            if u is not None:
                a, b = sorted((at(mapping.centre), at(float(u[i]))))
                pygame.draw.rect(surface, BAR, (a, y, max(b - a, 2), 22))
            for end, color in ((mapping.low, MUTED), (mapping.high, MUTED), (mapping.centre, INK)):
                pygame.draw.line(surface, color, (at(end), y - 3), (at(end), y + 25))
            self.text(surface, value, (left + width + 14, y + 4))
