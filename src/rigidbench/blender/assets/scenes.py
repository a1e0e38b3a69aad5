"""Furnished procedural environments: support surfaces, walls, furniture, clutter and lighting.

``build_environment(scene)`` lays out a room around the scene's supports:

- every support becomes a slab whose top face is exactly at ``centre_m`` z and spans ``size_m``
  (long, short) rotated by ``long_axis_deg``; its origin is the slab centre so Bullet's box,
  hull and mesh shapes all fit it. Below it stands the matching furniture (cabinets, legs...),
  which is an occluder, not part of the support;
- counters, sideboards, benches and desks back onto a wall (the side facing away from the other
  supports); the remaining walls stand ``margin_m`` beyond the supports so a camera 1.4-3 m
  away fits inside the room, and the area within ~0.4 m of each support is kept clear of
  tall clutter;
- the column above every support (its top face inset by ``CLEAR_INSET_M``, from the top up to
  ``CLEAR_ABOVE_M`` above it) holds no scene geometry, so objects dropped, bounced or thrown
  there are never hidden from above: pendants hang higher where they would enter it, chairs
  are pulled out from under table edges, and any other item reaching into it (open shelves
  over a counter, a range hood) is left out. Thin wall decor within the inset (backsplash,
  pictures) stays;
- floor-level supports (rugs, decks, floor patches) sit flush in a hole of the room floor,
  which is at ``floor_z_m`` everywhere;
- the world is one of Blender's bundled CC0 studio-light HDRIs (``style.hdri`` in the YAML may
  name another) or, for open-air styles, a physical daytime sky (``Style.sky``), plus a sun
  through the open top of the room, area lights over the supports and practical lamps. Rooms
  have no ceiling: at the benchmark's 10 degree camera elevation it is never in view, and the
  open top lets the sky light the room with little render noise.

Each scene id has a style (palette, furniture, decor) in ``_styles``; an unknown id gets the
style of its ``style.layout``. All randomness is seeded from the scene id.
"""

from __future__ import annotations

import logging
import math
import zlib
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from ...config import SceneConfig, SupportConfig
from . import _furniture as F, _paint, materials as M
from ._mesh import Part, box, grid_plane, join, rot_z, to_object
from ._styles import style_for
from .loader import import_objects

log = logging.getLogger(__name__)

HDRIS = ("interior.exr", "studio.exr", "courtyard.exr", "forest.exr", "city.exr", "night.exr", "sunrise.exr",
         "sunset.exr")
WALL_T = 0.15  # wall thickness (m)
KEEP_CLEAR_M = 0.4  # no tall clutter this close to a support's edge (chairs and stools excepted)
CLEAR_ABOVE_M = 1.5  # no scene geometry in the column this high above a support's top face
CLEAR_INSET_M = 0.05  # ... over the top face shrunk by this much on every side
CLEAR_FLOOR_M = 0.001  # the column starts this far above the top face
WINDOW_REACH_M = 0.6  # an item this close to a wall ...
WINDOW_COVER = 0.4  # ... hides a window when it spans more than this fraction of the opening's height
WINDOW_MARGIN_M = 0.1  # items slid aside keep this gap to the opening (and to the wall's ends)
WINDOW_DRESSING = frozenset({"window", "curtains", "skirting", "wainscot", "backsplash", "plant", "floor_lamp"})


def slide_clear(centre_m: float, half_m: float, length_m: float, spans: list[tuple[float, float]],
                margin_m: float = WINDOW_MARGIN_M) -> float | None:
    """Pure core of keeping windows clear: an item spanning ``centre_m`` +- ``half_m`` along a wall of
    ``length_m`` must not overlap any ``(start, end)`` span (window openings, m along the wall) nor
    leave the wall. Returns ``centre_m`` when it is clear, else the nearest centre just beside a span
    that is, or None when there is none."""
    def clear(c: float) -> bool:
        inside = margin_m + half_m - 1e-9 <= c <= length_m - margin_m - half_m + 1e-9
        return inside and all(c + half_m <= a - margin_m + 1e-9 or c - half_m >= b + margin_m - 1e-9 for a, b in spans)

    if not any(centre_m + half_m > a and centre_m - half_m < b for a, b in spans):
        return centre_m  # covers no window (staying on the wall is the caller's business, as before)
    candidates = [c for a, b in spans for c in (a - margin_m - half_m, b + margin_m + half_m) if clear(c)]
    return min(candidates, key=lambda c: abs(c - centre_m)) if candidates else None


@dataclass
class Environment:
    """What ``build_environment`` made: supports by name, all other geometry, lights and world."""

    scene_id: str
    supports: dict[str, Any]  # name -> bpy Object (slab, top face at the configured height)
    occluders: list[Any]  # walls, floor, furniture and clutter
    lights: list[Any] = field(default_factory=list)
    world: Any = None
    collection: Any = None
    room_rect_m: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)  # x0, x1, y0, y1


@dataclass
class Wall:
    side: str  # north, south, east or west
    start: np.ndarray  # (2,) inner corner at the left end, seen from inside the room
    along: np.ndarray  # (2,) unit vector left -> right
    normal: np.ndarray  # (2,) unit vector into the room
    length_m: float

    @property
    def rot_deg(self) -> float:
        """Yaw that maps an item's local +x onto ``along`` (its back, local +y, then faces the wall)."""
        return math.degrees(math.atan2(self.along[1], self.along[0]))

    def point(self, t: float, offset_m: float = 0.0) -> np.ndarray:
        """Floor point at fraction ``t`` along the wall, ``offset_m`` into the room. (2,)."""
        return self.start + self.along * t * self.length_m + self.normal * offset_m


@dataclass
class SupportInfo:
    cfg: SupportConfig
    kind: str  # counter, island, sideboard, bench, desk, table, low_table, rug, deck, floor
    back: np.ndarray | None  # (2,) unit vector toward the wall behind it, or None when free-standing
    corners: np.ndarray  # (4,2) top-face corners in the world

    @property
    def yaw_deg(self) -> float:
        return self.cfg.long_axis_deg


@dataclass(frozen=True)
class ClearColumn:
    """The space kept free above one support: an oriented box in the support's frame."""

    support: str
    centre_xy: np.ndarray  # (2,) m
    yaw_deg: float
    half_m: tuple[float, float]  # half long, half short extent (inset)
    z_m: tuple[float, float]  # bottom, top

    def polygons_inside(self, vertices: np.ndarray, corners: np.ndarray, sizes: np.ndarray) -> np.ndarray:
        """vertices (V,3) world m; corners (C,) and sizes (P,) int polygon loops. Returns (P,) bool: the
        polygon's bounding box in the support frame overlaps the column."""
        local = vertices.copy()
        local[:, :2] = (vertices[:, :2] - self.centre_xy) @ rot_z(self.yaw_deg)[:2, :2]
        starts = np.r_[0, np.cumsum(sizes)[:-1]].astype(np.int64)
        pts = local[corners]
        lo, hi = np.minimum.reduceat(pts, starts, axis=0), np.maximum.reduceat(pts, starts, axis=0)
        return ((lo[:, 0] < self.half_m[0]) & (hi[:, 0] > -self.half_m[0]) & (lo[:, 1] < self.half_m[1])
                & (hi[:, 1] > -self.half_m[1]) & (lo[:, 2] < self.z_m[1]) & (hi[:, 2] > self.z_m[0]))


def clear_column(s: SupportConfig) -> ClearColumn:
    """The column kept free of scene geometry above support ``s`` (see the module docstring)."""
    L, W = s.size_m
    top = s.centre_m[2]
    return ClearColumn(s.name, np.asarray(s.centre_m[:2], float), s.long_axis_deg,
                       (max(L / 2 - CLEAR_INSET_M, 0.0), max(W / 2 - CLEAR_INSET_M, 0.0)),
                       (top + CLEAR_FLOOR_M, top + CLEAR_ABOVE_M))


def support_corners(s: SupportConfig) -> np.ndarray:
    """Top-face corners of a support in world x, y. (4,2)."""
    L, W = s.size_m
    local = np.array([[-L / 2, -W / 2], [L / 2, -W / 2], [L / 2, W / 2], [-L / 2, W / 2]])
    return local @ rot_z(s.long_axis_deg)[:2, :2].T + np.asarray(s.centre_m[:2])


def support_kind(s: SupportConfig, overrides: dict[str, str]) -> str:
    """Furniture type under a support, from the style, its name, then its height."""
    if s.name in overrides:
        return overrides[s.name]
    name, z = s.name.lower(), s.centre_m[2]
    if z < 0.05:
        return "rug" if ("rug" in name or "runner" in name) else ("deck" if "deck" in name else "floor")
    for key, kind in (("island", "island"), ("counter", "counter"), ("sideboard", "sideboard"),
                      ("console", "sideboard"), ("bench", "bench"), ("desk", "desk"), ("coffee", "low_table"),
                      ("low", "low_table")):
        if key in name:
            return kind
    if z >= 0.85:
        return "counter"
    if z >= 0.6:
        return "table"
    return "low_table" if z >= 0.3 else "rug"


WALL_KINDS = ("counter", "sideboard", "bench", "desk")


def back_direction(s: SupportConfig, kind: str, others: list[SupportConfig]) -> np.ndarray | None:
    """Unit vector from a wall-backed support toward its wall: the short axis pointing away from the others."""
    if kind not in WALL_KINDS:
        return None
    yaw = math.radians(s.long_axis_deg)
    side = np.array([-math.sin(yaw), math.cos(yaw)])  # local +y
    centre = np.asarray(s.centre_m[:2])
    if others:
        away = centre - np.mean([o.centre_m[:2] for o in others], axis=0)
        if np.dot(away, side) < 0:
            side = -side
    if min(abs(side[0]), abs(side[1])) > 1e-3:
        return None  # a wall only for axis-aligned backs
    return np.round(side)


# ---------------------------------------------------------------------------------------------
# The builder kit


class Kit:
    """Creates bpy objects for one environment and records supports, occluders and lights."""

    def __init__(self, scene: SceneConfig, style):
        import bpy

        self.scene, self.style = scene, style
        self.collection = bpy.data.collections.new(f"env_{scene.id}")
        bpy.context.scene.collection.children.link(self.collection)
        self.rng = np.random.default_rng(zlib.crc32(scene.id.encode()))
        self.supports: dict[str, Any] = {}
        self.occluders: list[Any] = []
        self.lights: list[Any] = []
        self.keep_out: list[tuple[float, float, float, float]] = []
        self.columns: list[ClearColumn] = [clear_column(s) for s in scene.supports]
        self.walls: dict[str, Wall] = {}
        self.sides: dict[str, str] = {}  # back/front/left/right -> north/south/east/west
        self.infos: list[SupportInfo] = []
        self.room = (0.0, 0.0, 0.0, 0.0)
        self._count = 0
        self._materials: dict[str, Any] = {}

    # -- materials ------------------------------------------------------------------------

    def mat(self, role: str):
        """The style's material for ``role`` (cached per kit); unknown roles fall back to defaults.

        Roles 'art0', 'art1', ... without a style entry become abstract prints in the style's palette.
        """
        if role not in self._materials:
            name = f"rb_{self.scene.id}_{role}"
            factory = self.style.materials.get(role) or DEFAULT_MATERIALS.get(role)
            if factory is None and role.startswith("art"):
                seed = zlib.crc32(name.encode()) % 10000
                palette = self.style.art_palette
                self._materials[role] = M.image_material(name, f"{name}_img",
                                                         lambda: _paint.abstract_art(seed, palette), roughness=0.8)
                return self._materials[role]
            self._materials[role] = (factory or DEFAULT_MATERIALS["default"])(name)
        return self._materials[role]

    # -- objects --------------------------------------------------------------------------

    def _name(self, name: str) -> str:
        self._count += 1
        return f"{self.scene.id}_{name}_{self._count:03d}"

    def item(self, name: str, pieces: F.Pieces, xy=(0.0, 0.0), z: float = 0.0, rot_deg: float = 0.0,
             check: bool = True):
        """One object from ``pieces`` (merged per role) placed at (x, y, z) with yaw ``rot_deg``.

        With ``check`` the item is skipped (returns None) if its footprint comes within
        KEEP_CLEAR_M of a support, unless it is low (< 0.12 m).
        """
        if not pieces:
            return None
        roles = sorted({role for _, role in pieces})
        parts = [p.with_material(roles.index(role)) for p, role in pieces]
        merged = join(parts)
        if check and self._blocked(merged, xy, z, rot_deg):
            log.debug("scene %s: skipped %s at %s (too close to a support)", self.scene.id, name, xy)
            return None
        column = self.intruded_column(merged, xy, z, rot_deg)
        if column is not None:
            log.debug("scene %s: left out %s at (%.2f, %.2f): it reaches into the clear space above support '%s'",
                     self.scene.id, name, xy[0], xy[1], column)
            return None
        ob = to_object(merged, self._name(name), [self.mat(r) for r in roles], self.collection,
                       location=(float(xy[0]), float(xy[1]), float(z)), rotation_z_deg=rot_deg)
        self.occluders.append(ob)
        return ob

    def intruded_column(self, part: Part, xy, z: float, rot_deg: float) -> str | None:
        """Name of a support whose clear column ``part`` placed at (x, y, z) with yaw ``rot_deg`` enters, or None."""
        v = part.vertices @ rot_z(rot_deg).T + np.array([xy[0], xy[1], z])
        for column in self.columns:
            if column.polygons_inside(v, part.corners, part.sizes).any():
                return column.support
        return None

    def fits(self, pieces: F.Pieces, xy, z: float = 0.0, rot_deg: float = 0.0) -> bool:
        """Whether ``pieces``, placed at (x, y, z) with yaw ``rot_deg``, stay out of every support's clear column."""
        return self.intruded_column(join([p for p, _ in pieces]), xy, z, rot_deg) is None

    def _blocked(self, part: Part, xy, z: float, rot_deg: float) -> bool:
        v = part.vertices @ rot_z(rot_deg).T + np.array([xy[0], xy[1], z])
        if v[:, 2].max() < 0.12 + self.scene.floor_z_m:
            return False
        lo, hi = v[:, :2].min(0), v[:, :2].max(0)
        for x0, x1, y0, y1 in self.keep_out:
            if lo[0] < x1 and hi[0] > x0 and lo[1] < y1 and hi[1] > y0:
                return True
        return False

    def on_wall(self, side: str, t: float, name: str, pieces: F.Pieces, offset_m: float = 0.0, z: float = 0.0,
                check: bool = True):
        """Place ``pieces`` against wall ``side`` (back/front/left/right) at fraction ``t`` along it.

        An item that would hide a window of that wall (within WINDOW_REACH_M of it and covering more
        than WINDOW_COVER of the opening's height) slides along the wall to the nearest place beside
        the windows, or is left out where there is none; curtains, plants and the like
        (WINDOW_DRESSING) stay where they are put."""
        wall = self.walls[self.sides[side]]
        if name not in WINDOW_DRESSING and pieces:
            t = self._beside_windows(side, t, name, pieces, offset_m, z)
            if t is None:
                return None
        p = wall.point(t, offset_m)
        return self.item(name, pieces, p, z, wall.rot_deg, check=check)

    def _beside_windows(self, side: str, t: float, name: str, pieces: F.Pieces, offset_m: float,
                        z: float) -> float | None:
        wall = self.walls[self.sides[side]]
        v = join([p for p, _ in pieces]).vertices  # local frame: x along the wall, +y towards it (the back), z up
        if offset_m - float(v[:, 1].max()) > WINDOW_REACH_M:
            return t
        z0, z1 = z + float(v[:, 2].min()), z + float(v[:, 2].max())
        floor = self.scene.floor_z_m
        spans = [(wt * wall.length_m - w / 2, wt * wall.length_m + w / 2)
                 for s, wt, w, sill, top, _ in self.style.windows
                 if s == side and min(z1, floor + top) - max(z0, floor + sill) > WINDOW_COVER * (top - sill)]
        if not spans:
            return t
        x0, x1 = float(v[:, 0].min()), float(v[:, 0].max())
        centre = t * wall.length_m + (x0 + x1) / 2
        moved = slide_clear(centre, (x1 - x0) / 2, wall.length_m, spans)
        if moved is None:
            log.debug("scene %s: left out %s on the %s wall: it would hide a window", self.scene.id, name, side)
            return None
        if moved != centre:
            log.debug("scene %s: %s slid %.2f m along the %s wall, clear of a window", self.scene.id, name,
                      moved - centre, side)
        return (moved - (x0 + x1) / 2) / wall.length_m

    def light(self, kind: str, location, power_w: float, colour=(1.0, 0.9, 0.78), size_m: float = 0.5,
              size_y_m: float | None = None, rotation=(0.0, 0.0, 0.0), name: str = "lamp"):
        """A lamp ('AREA', 'POINT', 'SPOT'); area lights face down (-z) unless rotated."""
        import bpy

        data = bpy.data.lights.new(self._name(name), kind)
        data.energy = power_w
        data.color = colour
        if kind == "AREA":
            data.shape = "RECTANGLE"
            data.size = size_m
            data.size_y = size_y_m if size_y_m is not None else size_m
        else:
            data.shadow_soft_size = size_m
        ob = bpy.data.objects.new(data.name, data)
        ob.location = location
        ob.rotation_euler = rotation
        self.collection.objects.link(ob)
        self.lights.append(ob)
        return ob


# ---------------------------------------------------------------------------------------------
# Default materials (a style overrides any of these roles)


def _defaults() -> dict[str, Callable[[str], Any]]:
    return {
        "default": lambda n: M.painted(n, (0.7, 0.7, 0.68), 0.6),
        "wall": lambda n: M.painted(n, (0.86, 0.84, 0.8), 0.85),
        "floor": lambda n: M.wood(n, (0.62, 0.46, 0.3), 0.5, planks=True),
        "trim": lambda n: M.painted(n, (0.93, 0.92, 0.9), 0.5),
        "top": lambda n: M.wood(n, (0.7, 0.52, 0.34), 0.45),
        "leg": lambda n: M.wood(n, (0.5, 0.35, 0.22), 0.5),
        "wood": lambda n: M.wood(n, (0.6, 0.43, 0.27), 0.5),
        "metal": lambda n: M.metal(n, (0.08, 0.08, 0.08), 0.4),
        "lamp_metal": lambda n: M.metal(n, (0.1, 0.1, 0.1), 0.35),
        "handle": lambda n: M.metal(n, (0.7, 0.7, 0.72), 0.25),
        "cabinet": lambda n: M.painted(n, (0.9, 0.9, 0.88), 0.4),
        "cabinet_front": lambda n: M.painted(n, (0.9, 0.9, 0.88), 0.35),
        "plinth": lambda n: M.painted(n, (0.1, 0.1, 0.1), 0.6),
        "backsplash": lambda n: M.tiles(n, (0.95, 0.95, 0.93)),
        "appliance": lambda n: M.metal(n, (0.75, 0.75, 0.76), 0.25),
        "screen": lambda n: M.painted(n, (0.02, 0.02, 0.025), 0.08, variation=0.0, coat=1.0),
        "window_frame": lambda n: M.painted(n, (0.95, 0.95, 0.95), 0.4),
        "door": lambda n: M.painted(n, (0.92, 0.91, 0.88), 0.45),
        "frame": lambda n: M.wood(n, (0.3, 0.2, 0.12), 0.4),
        "mirror": lambda n: M.metal(n, (0.95, 0.95, 0.95), 0.02),
        "chair_frame": lambda n: M.wood(n, (0.55, 0.38, 0.22), 0.5),
        "chair_seat": lambda n: M.fabric(n, (0.4, 0.4, 0.42)),
        "sofa": lambda n: M.fabric(n, (0.55, 0.55, 0.56)),
        "cushion": lambda n: M.fabric(n, (0.8, 0.65, 0.3)),
        "curtain": lambda n: M.fabric(n, (0.9, 0.88, 0.82), sheen=0.3),
        "shelf": lambda n: M.wood(n, (0.72, 0.56, 0.38), 0.5),
        "book0": lambda n: M.painted(n, (0.6, 0.12, 0.1), 0.6),
        "book1": lambda n: M.painted(n, (0.12, 0.25, 0.5), 0.6),
        "book2": lambda n: M.painted(n, (0.85, 0.8, 0.65), 0.6),
        "book3": lambda n: M.painted(n, (0.2, 0.4, 0.25), 0.6),
        "accent0": lambda n: M.fabric(n, (0.75, 0.3, 0.2)),
        "accent1": lambda n: M.fabric(n, (0.2, 0.35, 0.55)),
        "accent2": lambda n: M.fabric(n, (0.85, 0.7, 0.3)),
        "pot": lambda n: M.painted(n, (0.7, 0.4, 0.28), 0.7),
        "leaves": lambda n: M.leaves(n),
        "ceramic": lambda n: M.painted(n, (0.92, 0.9, 0.86), 0.2, coat=0.5),
        "ceramic2": lambda n: M.painted(n, (0.3, 0.45, 0.55), 0.2, coat=0.5),
        "glass": lambda n: M.glass(n),
        "shade": lambda n: M.emissive(n, (1.0, 0.85, 0.65), 6.0),
        "candle": lambda n: M.painted(n, (0.95, 0.93, 0.88), 0.5),
        "stone": lambda n: M.concrete(n, (0.6, 0.58, 0.55), 0.8),
        "soot": lambda n: M.painted(n, (0.05, 0.045, 0.04), 0.9),
        "fire": lambda n: M.emissive(n, (1.0, 0.45, 0.1), 12.0),
        "rug": lambda n: M.fabric(n, (0.6, 0.5, 0.4)),
        "trunk": lambda n: M.concrete(n, (0.5, 0.4, 0.3), 0.9),
        "coconut": lambda n: M.painted(n, (0.35, 0.4, 0.15), 0.6),
    }


DEFAULT_MATERIALS = _defaults()


# ---------------------------------------------------------------------------------------------
# Layout


def _room_rect(infos: list[SupportInfo], margin_m: float, min_half_m: float) -> tuple[float, float, float, float]:
    """Room x0, x1, y0, y1: back walls touch wall-backed supports, other walls stand margin_m away."""
    pts = np.concatenate([i.corners for i in infos])
    lo, hi = pts.min(0), pts.max(0)
    centre = (lo + hi) / 2
    x0 = min(lo[0] - margin_m, centre[0] - min_half_m)
    x1 = max(hi[0] + margin_m, centre[0] + min_half_m)
    y0 = min(lo[1] - margin_m, centre[1] - min_half_m)
    y1 = max(hi[1] + margin_m, centre[1] + min_half_m)
    for info in infos:
        if info.back is None:
            continue
        edge = info.corners @ info.back  # projection of the corners on the back direction
        reach = float(edge.max()) + 0.004
        if info.back[0] > 0.5:
            x1 = reach
        elif info.back[0] < -0.5:
            x0 = -reach
        elif info.back[1] > 0.5:
            y1 = reach
        else:
            y0 = -reach
    return x0, x1, y0, y1


def _walls(room) -> dict[str, Wall]:
    x0, x1, y0, y1 = room
    return {
        "north": Wall("north", np.array([x0, y1]), np.array([1.0, 0.0]), np.array([0.0, -1.0]), x1 - x0),
        "south": Wall("south", np.array([x1, y0]), np.array([-1.0, 0.0]), np.array([0.0, 1.0]), x1 - x0),
        "east": Wall("east", np.array([x1, y1]), np.array([0.0, -1.0]), np.array([-1.0, 0.0]), y1 - y0),
        "west": Wall("west", np.array([x0, y0]), np.array([0.0, 1.0]), np.array([1.0, 0.0]), y1 - y0),
    }


_TURN = {"north": ("south", "west", "east"), "south": ("north", "east", "west"),
         "east": ("west", "north", "south"), "west": ("east", "south", "north")}


def _relative_sides(back: str) -> dict[str, str]:
    front, left, right = _TURN[back]
    return {"back": back, "front": front, "left": left, "right": right}


def _back_side(infos: list[SupportInfo], preferred: str) -> str:
    for info in infos:
        if info.back is not None:
            b = info.back
            return "east" if b[0] > 0.5 else "west" if b[0] < -0.5 else "north" if b[1] > 0.5 else "south"
    return preferred


def build_floor(kit: Kit, room, floor_z: float) -> None:
    """Room floor at floor_z with holes where floor-level supports sit flush."""
    x0, x1, y0, y1 = room
    holes = []
    for info in kit.infos:
        if info.kind in ("rug", "deck", "floor"):
            if abs(info.yaw_deg % 90.0) > 1e-6 and abs(info.yaw_deg % 90.0 - 90.0) > 1e-6:
                log.warning("scene %s: floor support '%s' is rotated by %.1f deg; the floor under it is not cut out",
                            kit.scene.id, info.cfg.name, info.yaw_deg)
                continue
            lo, hi = info.corners.min(0), info.corners.max(0)
            holes.append((lo[0], hi[0], lo[1], hi[1]))
    xs = np.unique(np.clip([x0 - WALL_T, x1 + WALL_T] + [h[i] for h in holes for i in (0, 1)], x0 - WALL_T,
                           x1 + WALL_T))
    ys = np.unique(np.clip([y0 - WALL_T, y1 + WALL_T] + [h[i] for h in holes for i in (2, 3)], y0 - WALL_T,
                           y1 + WALL_T))
    cx, cy = (xs[:-1] + xs[1:]) / 2, (ys[:-1] + ys[1:]) / 2
    keep = np.ones((len(cx), len(cy)), bool)
    for hx0, hx1, hy0, hy1 in holes:
        keep &= ~(((cx > hx0) & (cx < hx1))[:, None] & ((cy > hy0) & (cy < hy1))[None, :])
    part = grid_plane(xs, ys, keep, floor_z)
    ob = to_object(part, kit._name("floor"), [kit.mat("floor")], kit.collection)
    kit.occluders.append(ob)


def build_walls(kit: Kit, room, height_m: float, floor_z: float) -> None:
    """Four walls with window openings (style.windows) and skirting; one object per wall."""
    for side, wall in kit.walls.items():
        rel = next(k for k, v in kit.sides.items() if v == side)
        if rel in kit.style.open_sides:
            continue
        openings = sorted((t, w, sill, top, panes) for s, t, w, sill, top, panes in kit.style.windows if s == rel)
        L = wall.length_m + 2 * WALL_T
        cuts = []
        for t, w, sill, top, panes in openings:
            c = WALL_T + t * wall.length_m
            cuts.append((c - w / 2, c + w / 2, sill, top, panes))
        parts, x = [], 0.0
        for a, b, sill, top, _ in cuts:
            if a > x:
                parts.append(box((a - x, WALL_T, height_m), ((a + x) / 2, WALL_T / 2, height_m / 2)))
            parts.append(box((b - a, WALL_T, sill), ((a + b) / 2, WALL_T / 2, sill / 2)))
            parts.append(box((b - a, WALL_T, height_m - top), ((a + b) / 2, WALL_T / 2, (top + height_m) / 2)))
            x = b
        parts.append(box((L - x, WALL_T, height_m), ((L + x) / 2, WALL_T / 2, height_m / 2)))
        start = wall.start - wall.along * WALL_T
        role = kit.style.wall_roles.get(rel, "wall")
        ob = to_object(join(parts), kit._name(f"wall_{side}"), [kit.mat(role)], kit.collection,
                       location=(float(start[0]), float(start[1]), floor_z), rotation_z_deg=wall.rot_deg)
        kit.occluders.append(ob)
        for a, b, sill, top, panes in cuts:
            t = (0.5 * (a + b) - WALL_T) / wall.length_m
            kit.on_wall(rel, t, "window", F.window_frame(b - a, top - sill, panes), z=floor_z + sill, check=False)
        if kit.style.skirting:
            kit.on_wall(rel, 0.5, "skirting", [(F.B((wall.length_m, 0.015, 0.1), (0, -0.0075, 0.05)), "trim")],
                        z=floor_z, check=False)


def build_support(kit: Kit, info: SupportInfo) -> None:
    """The support slab (exact top face) and the furniture body under it."""
    s = info.cfg
    L, W = s.size_m
    cx, cy, top = s.centre_m
    thickness = {"counter": 0.04, "island": 0.04, "sideboard": 0.03, "bench": 0.045, "desk": 0.03, "table": 0.04,
                 "low_table": 0.04, "rug": 0.01, "deck": 0.15, "floor": 0.02}[info.kind]
    role = kit.style.support_roles.get(s.name, {"rug": "rug", "floor": "floor", "deck": "deck"}.get(info.kind, "top"))
    if info.kind == "rug" or role.startswith("rug"):
        slab = F.slab_uv01((L, W, thickness), (0.0, 0.0, 0.0))
    elif abs(s.long_axis_deg) < 1e-9 and role == "floor":  # continue the room floor's world-aligned pattern
        slab = box((L, W, thickness), uv_offset_m=(cx, cy, top - thickness / 2))
    else:
        slab = box((L, W, thickness))
    ob = to_object(slab, f"support_{s.name}", [kit.mat(role)], kit.collection,
                   location=(cx, cy, top - thickness / 2), rotation_z_deg=s.long_axis_deg)
    ob["rb_support"] = s.name
    ob["rb_top_z_m"] = top
    kit.supports[s.name] = ob
    # the body is built in the support frame: local +y toward its back wall (if any)
    yaw = s.long_axis_deg
    if info.back is not None:
        local_y = np.array([-math.sin(math.radians(yaw)), math.cos(math.radians(yaw))])
        if np.dot(local_y, info.back) < 0:
            yaw += 180.0
    under = top - thickness
    floor_z = kit.scene.floor_z_m
    h = under - floor_z
    body: F.Pieces = []
    extra: list[tuple[str, F.Pieces, tuple, float]] = []
    style = kit.style
    if info.kind in ("counter", "island"):
        overhang = 0.03 if info.kind == "counter" else 0.32  # islands overhang on their seating side
        depth = W - overhang
        y_off = (W - depth) / 2 if info.kind == "counter" else -(W - depth) / 2 + 0.03
        body = F.combine(F.cabinet_run(L - 0.04, depth, h, door_w=style.door_w, handle=style.handle,
                                       drawers=style.drawers), (0.0, y_off, 0.0))
        if info.kind == "island":
            yaw = _seating_yaw(info, kit.infos)
            if style.stools:
                n = max(2, int(L / 0.65))
                for k in range(n):
                    x = -L / 2 + L * (k + 0.5) / n
                    extra.append(("stool", F.stool(seat_z=min(0.75, h - 0.12), round_seat=style.round_stools),
                                  (x, W / 2 + 0.05), 0.0))
    elif info.kind == "sideboard":
        body = F.cabinet_run(L - 0.02, W - 0.02, h, door_w=0.45, handle=style.handle, drawers=True, legs=True)
    elif info.kind == "bench":
        body = F.bench_base(L, W, h) + F.shoes(kit.rng, int(L / 0.45), -L / 2 + 0.3, L / 2 - 0.3, 0.1325)
    elif info.kind in ("table", "desk", "low_table"):
        body = F.table_base(L, W, h, style.table_base.get(s.name, "legs"))
        if info.kind == "table" and style.chairs:
            per_side = max(1, int(L / 0.75))
            gap = style.chair_gap_m
            for k in range(per_side):
                x = -L / 2 + L * (k + 0.5) / per_side
                extra.append(("chair", F.chair(style.chair), (x, W / 2 + gap), 180.0))
                extra.append(("chair", F.chair(style.chair), (x, -W / 2 - gap), 0.0))
            if style.end_chairs:
                extra.append(("chair", F.chair(style.chair), (L / 2 + gap, 0.0), 90.0))
                extra.append(("chair", F.chair(style.chair), (-L / 2 - gap, 0.0), -90.0))
        if info.kind == "desk":  # pushed aside so it hides little of the desk
            extra.append(("office_chair", F.office_chair(), (L / 2 + 0.05, -W / 2 - 0.3), 35.0))
    if body:
        kit.item(f"{s.name}_body", body, (cx, cy), floor_z, yaw, check=False)
    m = rot_z(yaw)[:2, :2]
    for name, pieces, (lx, ly), rot in extra:
        out = np.array([0.0, np.sign(ly)]) if abs(ly) > W / 2 else np.array([np.sign(lx), 0.0])  # away from the edge
        for pull_m in np.arange(0.0, 0.61, 0.05):  # pull seats out until they clear every support's column
            x, y = m @ (np.array([lx, ly]) + pull_m * out) + np.array([cx, cy])
            if kit.fits(pieces, (x, y), floor_z, yaw + rot):
                break
        kit.item(name, pieces, (x, y), floor_z, yaw + rot, check=False)


def _seating_yaw(info: SupportInfo, infos: list[SupportInfo]) -> float:
    """Yaw of an island's frame so its seating overhang (local +y) faces away from the other supports."""
    yaw = info.cfg.long_axis_deg
    others = [i.cfg.centre_m[:2] for i in infos if i is not info]
    if others:
        local_y = np.array([-math.sin(math.radians(yaw)), math.cos(math.radians(yaw))])
        away = np.asarray(info.cfg.centre_m[:2]) - np.mean(others, axis=0)
        if np.dot(local_y, away) < -1e-9:
            yaw += 180.0
    return yaw


def _world(kit: Kit, hdri: str, strength: float, rotation_deg: float):
    import bpy

    if hdri not in HDRIS:
        raise ValueError(f"{kit.scene.source}: field 'style.hdri': unknown HDRI '{hdri}'; bundled: {', '.join(HDRIS)}")
    world = bpy.data.worlds.new(f"rb_world_{kit.scene.id}")
    world.use_nodes = True
    nt = world.node_tree
    nt.nodes.clear()
    coords = nt.nodes.new("ShaderNodeTexCoord")
    mapping = nt.nodes.new("ShaderNodeMapping")
    mapping.inputs["Rotation"].default_value = (0.0, 0.0, math.radians(rotation_deg))
    env = nt.nodes.new("ShaderNodeTexEnvironment")
    folder = bpy.utils.system_resource("DATAFILES", path="studiolights/world")
    env.image = bpy.data.images.load(f"{folder}/{hdri}", check_existing=True)
    bg = nt.nodes.new("ShaderNodeBackground")
    bg.inputs["Strength"].default_value = strength
    out = nt.nodes.new("ShaderNodeOutputWorld")
    nt.links.new(coords.outputs["Generated"], mapping.inputs["Vector"])
    nt.links.new(mapping.outputs["Vector"], env.inputs["Vector"])
    nt.links.new(env.outputs["Color"], bg.inputs["Color"])
    nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
    bpy.context.scene.world = world
    return world


def build_studio(scene: Any, hdri: str = "courtyard.exr", strength: float = 1.0, sun_w: float = 3.0):
    """The neutral studio that objects are looked at in (the gallery's objects sheet, the object
    colour tests, ``benchmarks/assets_preview.py``): a bundled HDRI world, a sun from 40 degrees
    off vertical and a 40 m grey floor at z = 0. Returns the floor object."""
    import bpy

    world = bpy.data.worlds.new("rb_studio")
    world.use_nodes = True
    env = world.node_tree.nodes.new("ShaderNodeTexEnvironment")
    folder = bpy.utils.system_resource("DATAFILES", path="studiolights/world")
    env.image = bpy.data.images.load(f"{folder}/{hdri}", check_existing=True)
    world.node_tree.links.new(env.outputs["Color"], world.node_tree.nodes["Background"].inputs["Color"])
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = strength
    scene.world = world
    sun = bpy.data.objects.new("rb_studio_sun", bpy.data.lights.new("rb_studio_sun", "SUN"))
    sun.data.energy, sun.data.angle = sun_w, math.radians(5)
    sun.rotation_euler = (math.radians(40), 0.0, math.radians(30))
    scene.collection.objects.link(sun)
    return to_object(box((40.0, 40.0, 0.02), offset_m=(0, 0, -0.01)), "rb_studio_floor",
                     [M.painted("rb_studio_floor", (0.55, 0.53, 0.5), 0.6)])


def _sky_world(kit: Kit, sun_azimuth_deg: float, sun_elevation_deg: float, strength: float):
    """A clear daytime sky (Cycles' physical Nishita sky, sun disc off: a SUN lamp casts the shadows)."""
    import bpy

    world = bpy.data.worlds.new(f"rb_world_{kit.scene.id}")
    world.use_nodes = True
    nt = world.node_tree
    nt.nodes.clear()
    sky = nt.nodes.new("ShaderNodeTexSky")
    sky.sky_type = "NISHITA"
    sky.sun_disc = False
    sky.sun_elevation = math.radians(sun_elevation_deg)
    sky.sun_rotation = math.radians(sun_azimuth_deg)
    sky.air_density = 1.0
    sky.dust_density = 0.2
    sky.ozone_density = 1.0
    bg = nt.nodes.new("ShaderNodeBackground")
    bg.inputs["Strength"].default_value = strength
    out = nt.nodes.new("ShaderNodeOutputWorld")
    nt.links.new(sky.outputs["Color"], bg.inputs["Color"])
    nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
    world["rb_sky"] = True
    bpy.context.scene.world = world
    return world


def build_lights(kit: Kit, height_m: float, floor_z: float) -> None:
    """Sun, a fill panel over the room and an area light over each raised support."""
    style = kit.style
    if style.sun is not None:
        az, el, strength = style.sun
        import bpy
        data = bpy.data.lights.new(kit._name("sun"), "SUN")
        data.energy = strength
        data.angle = math.radians(2.0)
        data.color = style.sun_colour
        ob = bpy.data.objects.new(data.name, data)
        # a sun light shines along its local -z; point it from (az, el) toward the room
        ob.rotation_euler = (math.radians(90.0 - el), 0.0, math.radians(az + 90.0))
        kit.collection.objects.link(ob)
        kit.lights.append(ob)
    x0, x1, y0, y1 = kit.room
    if style.fill_w > 0:
        kit.light("AREA", ((x0 + x1) / 2, (y0 + y1) / 2, floor_z + height_m - 0.05), style.fill_w, style.lamp_colour,
                  size_m=(x1 - x0) * 0.6, size_y_m=(y1 - y0) * 0.6, name="fill")
    for info in kit.infos:
        s = info.cfg
        if info.kind in ("rug", "deck", "floor") or style.support_light_w <= 0:
            continue
        L, W = s.size_m
        z = min(s.centre_m[2] + 1.5, floor_z + height_m - 0.1)
        kit.light("AREA", (s.centre_m[0], s.centre_m[1], z), style.support_light_w * (L * W) / 1.5,
                  style.lamp_colour, size_m=L * 0.8, size_y_m=W * 1.2,
                  rotation=(0.0, 0.0, math.radians(s.long_axis_deg)), name=f"light_{s.name}")


def build_environment(scene: SceneConfig):
    """Furnished environment for ``scene`` in the current bpy scene; see the module docstring."""
    import bpy

    style = style_for(scene)
    kit = Kit(scene, style)
    floor_z = scene.floor_z_m
    supports = list(scene.supports)
    for s in supports:
        kind = support_kind(s, style.kinds)
        others = [o for o in supports if o is not s]
        kit.infos.append(SupportInfo(s, kind, back_direction(s, kind, others), support_corners(s)))
    for info in kit.infos:
        lo, hi = info.corners.min(0), info.corners.max(0)
        kit.keep_out.append((lo[0] - KEEP_CLEAR_M, hi[0] + KEEP_CLEAR_M, lo[1] - KEEP_CLEAR_M, hi[1] + KEEP_CLEAR_M))
    kit.room = _room_rect(kit.infos, style.margin_m, style.min_half_m)
    kit.walls = _walls(kit.room)
    kit.sides = _relative_sides(_back_side(kit.infos, style.back))
    hdri = str(scene.style.get("hdri", style.hdri))
    if style.sky is not None and "hdri" not in scene.style:
        world = _sky_world(kit, *style.sky)
    else:
        world = _world(kit, hdri, float(scene.style.get("hdri_strength", style.hdri_strength)),
                       style.hdri_rotation_deg)
    if scene.mesh_path:
        _user_scene(kit, scene)
    else:
        if style.floor:
            build_floor(kit, kit.room, floor_z)
        if style.walls:
            build_walls(kit, kit.room, style.wall_height_m, floor_z)
    for info in kit.infos:
        build_support(kit, info)
    if not scene.mesh_path and style.decorate is not None:
        style.decorate(kit)
    build_lights(kit, style.wall_height_m, floor_z)
    bpy.context.view_layer.update()  # world matrices valid for ray casts and physics right away
    return Environment(scene.id, kit.supports, kit.occluders, kit.lights, world, kit.collection, kit.room)


def _user_scene(kit: Kit, scene: SceneConfig) -> None:
    """Geometry from the scene's mesh file as occluders (objects kept as authored)."""
    for ob in import_objects(scene.mesh_path, scene.source or f"scene '{scene.id}'"):
        for coll in list(ob.users_collection):
            coll.objects.unlink(ob)
        kit.collection.objects.link(ob)
        if ob.type == "MESH":
            kit.occluders.append(ob)
        elif ob.type == "LIGHT":
            kit.lights.append(ob)
