"""Per-scene styles: palette (materials by role), lighting, windows, furniture choices and decor.

A style is looked up by scene id; a scene id without a style (a user's new scene) gets the
default style of its ``style.layout`` (kitchen, dining, living, hallway, loft, gazebo, mural).
Decor functions place items relative to the room's walls (back, front, left, right as seen
from inside facing the back wall) and skip any that would crowd a support.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Callable

import numpy as np

from ...config import SceneConfig
from . import _furniture as F, _paint, materials as M
from ._mesh import box, grid_plane, polygon_prism, revolve

Factory = Callable[[str], Any]


@dataclass(frozen=True)
class Style:
    hdri: str = "interior.exr"
    hdri_strength: float = 0.8
    # world yaw of the HDRI; its sun then shines from azimuth (HDRI sun azimuth - rotation): e.g. the
    # sunrise/sunset suns sit at -36 deg in their panoramas, so -216 deg makes them shine from +x toward -x
    hdri_rotation_deg: float = 0.0
    # a physical daytime sky instead of the HDRI: (sun azimuth deg, sun elevation deg, strength)
    sky: tuple[float, float, float] | None = None
    sun: tuple[float, float, float] | None = None  # (azimuth the light comes from, elevation deg, W/m^2)
    sun_colour: tuple[float, float, float] = (1.0, 0.95, 0.88)
    lamp_colour: tuple[float, float, float] = (1.0, 0.88, 0.75)
    fill_w: float = 500.0  # big soft panel over the room (the missing ceiling's lights)
    # per 1.5 m^2 of support, from 1.5 m above it; it falls straight on the support, so a pale top
    # (marble, white oak) clips above ~10 W with Standard view: keep it low and light with the sun
    support_light_w: float = 120.0
    wall_height_m: float = 2.8
    margin_m: float = 4.0
    min_half_m: float = 4.5
    back: str = "north"
    windows: tuple = ()  # (side, t, width, sill_z, top_z, (cols, rows))
    open_sides: tuple = ()
    wall_roles: dict = field(default_factory=dict)
    materials: dict[str, Factory] = field(default_factory=dict)
    support_roles: dict[str, str] = field(default_factory=dict)
    kinds: dict[str, str] = field(default_factory=dict)
    table_base: dict[str, str] = field(default_factory=dict)
    chair: str = "wood"
    chairs: bool = True
    end_chairs: bool = False
    chair_gap_m: float = 0.1  # seat centre this far beyond the table edge
    stools: bool = True
    round_stools: bool = True
    door_w: float = 0.6
    handle: str = "bar"
    drawers: bool = False
    skirting: bool = True
    floor: bool = True
    walls: bool = True
    art_palette: tuple = ((0.93, 0.9, 0.84), (0.8, 0.45, 0.3), (0.2, 0.3, 0.45), (0.85, 0.7, 0.35), (0.3, 0.3, 0.3))
    decorate: Callable | None = None


# ---------------------------------------------------------------------------------------------
# Shared decor helpers


def _rug(kit, name: str, size, xy, role: str = "rug_deco", rot: float = 0.0):
    return kit.item(name, [(F.slab_uv01((size[0], size[1], 0.004), (0, 0, 0.002)), role)], xy,
                    kit.scene.floor_z_m, rot, check=False)


def _hang(kit, name: str, make, xy, top: float, drop: float, min_drop: float = 0.1) -> float:
    """Hang ``make(drop)`` (pieces below a ceiling point) at ``xy`` from height ``top``, shortening the drop
    in 5 cm steps until it clears every support's column (scenes.CLEAR_ABOVE_M); returns the drop used."""
    while drop > min_drop and not kit.fits(make(drop), xy, top):
        drop = round(drop - 0.05, 4)
    kit.item(name, make(drop), xy, top, check=False)
    return drop


def _pendants(kit, support: str, shape: str, n: int, drop: float, radius: float = 0.18, light_w: float = 25.0):
    """``n`` pendants along a support's long axis, hanging from the wall-top height (as low as ``drop``
    while the space above the supports stays clear)."""
    s = kit.scene.support(support)
    top = kit.scene.floor_z_m + kit.style.wall_height_m
    yaw = np.radians(s.long_axis_deg)
    for k in range(n):
        d = (k - (n - 1) / 2) * s.size_m[0] / n
        x, y = s.centre_m[0] + np.cos(yaw) * d, s.centre_m[1] + np.sin(yaw) * d
        used = _hang(kit, "pendant", lambda h: F.pendant(h, shape, radius), (x, y), top, drop)
        kit.light("POINT", (x, y, top - used - 0.02), light_w, kit.style.lamp_colour, size_m=0.05, name="bulb")


def _plant(kit, side: str, t: float, kind: str = "bush", height: float = 1.2, pot_r: float = 0.17,
           offset: float = 0.35):
    return kit.on_wall(side, t, "plant", F.plant(kit.rng, pot_r, pot_r * 2.1, height, kind), offset_m=offset)


def _art(kit, side: str, t: float, z: float, w: float, h: float, role: str):
    return kit.on_wall(side, t, "art", F.picture(w, h, 0.035, role), z=z, check=False)


def _t_of(kit, side: str, x_or_y: float) -> float:
    """Fraction along wall ``side`` of the world coordinate (x for north/south walls, y otherwise)."""
    wall = kit.walls[kit.sides[side]]
    axis = 0 if abs(wall.along[0]) > 0.5 else 1
    return float((x_or_y - wall.start[axis]) / (wall.along[axis] * wall.length_m))


def _lamp(kit, side: str, t: float, offset: float = 0.4, power: float = 40.0):
    ob = kit.on_wall(side, t, "floor_lamp", F.floor_lamp(), offset_m=offset)
    if ob is not None:
        kit.light("POINT", (ob.location.x, ob.location.y, kit.scene.floor_z_m + 1.45), power, kit.style.lamp_colour,
                  size_m=0.1, name="lamp_bulb")
    return ob


# ---------------------------------------------------------------------------------------------
# The twelve scenes


def _hallway(kit) -> None:
    rng = kit.rng
    back = kit.walls[kit.sides["back"]]
    for side in ("back", "left", "right", "front"):
        kit.on_wall(side, 0.5, "wainscot", F.wainscot(kit.walls[kit.sides[side]].length_m), check=False)
    t0 = _t_of(kit, "back", 0.0)
    kit.on_wall("back", t0, "coat_rail", F.coat_rail(rng, 1.8, 5), z=1.68, check=False)
    kit.on_wall("back", t0 + 2.6 / back.length_m, "mirror", F.round_mirror(0.32), z=1.45, check=False)
    kit.on_wall("back", t0 + 2.6 / back.length_m, "console",
                F.cabinet_run(1.0, 0.32, 0.8, door_w=0.5, handle="knob", legs=True) +
                F.combine(F.table_lamp(), (0.3, 0.0, 0.8)), offset_m=0.16)
    kit.on_wall("back", t0 - 2.5 / back.length_m, "umbrella_stand",
                [(F.cyl(0.12, 0.0, 0.5, segments=18), "metal")] +
                [(F.sweep(np.array([[0.02 * k, 0.0, 0.2], [0.05 * k, 0.03, 0.95]]), np.full(2, 0.012), segments=6),
                  f"accent{k % 3}") for k in range(-1, 2)], offset_m=0.2)
    _plant(kit, "back", 0.06, "tall", 1.5)
    _plant(kit, "back", 0.94, "bush", 0.9)
    kit.on_wall("left", 0.5, "door", F.door(), check=False)
    kit.on_wall("right", 0.5, "door", F.door(), check=False)
    kit.on_wall("front", 0.25, "door", F.door(), check=False)
    kit.on_wall("front", 0.6, "shoe_cabinet", F.cabinet_run(1.4, 0.35, 0.9, door_w=0.35, handle="knob"),
                offset_m=0.18)
    for k, t in enumerate((0.52, 0.6, 0.68)):
        _art(kit, "front", t, 1.65, 0.5, 0.65, f"art{k}")
    _plant(kit, "front", 0.85, "bush", 1.1)
    for x in (-3.2, 0.0, 3.2):
        y = -1.1 if x == 0.0 else -0.9
        kit.item("pendant", F.pendant(0.45, "globe", 0.16), (x, y), kit.style.wall_height_m, check=False)
        kit.light("POINT", (x, y, kit.style.wall_height_m - 0.45), 30.0, kit.style.lamp_colour, size_m=0.1,
                  name="bulb")


def _loft(kit) -> None:
    rng = kit.rng
    t0 = _t_of(kit, "back", 0.0)
    kit.on_wall("back", t0, "shelves", F.open_shelves(2.4, [1.5, 1.92], 0.28) +
                F.shelf_items(rng, 2.3, 1.52, 0.28) + F.shelf_items(rng, 2.3, 1.94, 0.28, ("jar", "books", "bowl")),
                check=False)
    _pendants(kit, "counter", "dome", 3, 0.95, 0.2)
    kit.on_wall("front", 0.5, "sofa", F.sofa(2.4, 0.95, 3), offset_m=0.5)
    kit.on_wall("front", 0.5, "coffee_table", F.table_base(1.2, 0.6, 0.36, "frame") +
                [(F.B((1.2, 0.6, 0.04), (0, 0, 0.38)), "wood")], offset_m=1.6)
    _rug(kit, "rug", (2.6, 1.8), kit.walls[kit.sides["front"]].point(0.5, 1.5), "rug_deco")
    for t in (0.2, 0.8):  # either side of the window (the 4.85 m wall leaves about 1 m beside it)
        kit.on_wall("left", t, "bookcase", F.bookcase(rng, 0.9, 0.36, 2.1, 5), offset_m=0.2)
    _plant(kit, "back", 0.05, "tall", 1.8, 0.22)
    _plant(kit, "back", 0.95, "palm", 1.6, 0.2)
    _plant(kit, "front", 0.15, "bush", 1.0)
    _lamp(kit, "front", 0.76, 0.4, 50.0)
    kit.on_wall("right", 0.8, "art", F.picture(1.2, 0.9, 0.04, "art0"), z=1.5, check=False)
    kit.on_wall("front", 0.9, "armchair", F.armchair(0.9), offset_m=0.6)


def _kitchen_wall(kit, support: str, backsplash_top: float, uppers: bool, shelves: bool, hood: bool,
                  columns: bool) -> None:
    """Backsplash, upper cabinets or shelves, hood and tall columns behind a wall-backed counter."""
    s = kit.scene.support(support)
    info = next(i for i in kit.infos if i.cfg.name == support)
    side = next(k for k, v in kit.sides.items() if v == ("east" if info.back[0] > 0.5 else "west" if info.back[0] < -0.5
                                                         else "north" if info.back[1] > 0.5 else "south"))
    wall = kit.walls[kit.sides[side]]
    axis = 0 if abs(wall.along[0]) > 0.5 else 1
    t = _t_of(kit, side, s.centre_m[axis])
    L, top = s.size_m[0], s.centre_m[2]
    kit.on_wall(side, t, "backsplash", [(F.B((L, 0.012, backsplash_top - top), (0, -0.006, (backsplash_top + top) / 2)),
                                         "backsplash")], check=False)
    if uppers:
        kit.on_wall(side, t, "upper_cabinets", F.upper_cabinets(L, 0.35, 0.75, handle=kit.style.handle),
                    offset_m=0.0, z=backsplash_top + 0.05, check=False)
    if shelves:
        kit.on_wall(side, t, "shelves", F.open_shelves(L * 0.8, [backsplash_top + 0.15, backsplash_top + 0.55], 0.26)
                    + F.shelf_items(kit.rng, L * 0.75, backsplash_top + 0.17, 0.26, ("jar", "bowl", "vase"))
                    + F.shelf_items(kit.rng, L * 0.75, backsplash_top + 0.57, 0.26, ("bowl", "books", "jar")),
                    check=False)
    if hood:
        kit.on_wall(side, t, "hood", F.range_hood(0.9, backsplash_top + 0.1, kit.style.wall_height_m), check=False)
    if columns:
        for sgn in (-1, 1):
            tc = t + sgn * (L / 2 + 0.45 + 0.4) / wall.length_m
            kit.on_wall(side, tc, "tall_unit", F.fridge(0.8, 2.3, 0.62) if sgn > 0 else
                        F.cabinet_run(0.8, 0.62, 2.3, door_w=0.4, handle=kit.style.handle), offset_m=0.31,
                        check=False)


def _luxury_kitchen(kit) -> None:
    _kitchen_wall(kit, "back_counter", 2.25, uppers=False, shelves=False, hood=True, columns=True)
    _pendants(kit, "island", "globe", 3, 1.05, 0.14)
    _art(kit, "right", 0.75, 1.6, 1.2, 0.8, "art0")
    kit.on_wall("front", 0.7, "dining_table", F.table_base(1.0, 1.0, 0.72, "pedestal") +
                [(F.cyl(0.55, 0.72, 0.76, segments=32), "top")], offset_m=1.4)
    for a in (0, 120, 240):
        p = kit.walls[kit.sides["front"]].point(0.7, 1.4)
        r = np.radians(a)
        kit.item("chair", F.chair("upholstered"), (p[0] + 0.8 * np.cos(r), p[1] + 0.8 * np.sin(r)), 0.0, a + 90,
                 check=True)
    _plant(kit, "front", 0.1, "tall", 1.7, 0.22)
    _plant(kit, "right", 0.1, "bush", 1.0)
    _rug(kit, "rug", (2.2, 2.2), kit.walls[kit.sides["front"]].point(0.7, 1.4), "rug_deco")


def _white_kitchen(kit) -> None:
    _kitchen_wall(kit, "counter", 1.55, uppers=False, shelves=False, hood=False, columns=True)
    _pendants(kit, "counter", "cone", 2, 1.15, 0.16)
    t = _t_of(kit, "back", 0.0)
    back = kit.walls[kit.sides["back"]]
    # the space over the counter stays clear: only flat things on its wall (a rail, small prints)
    kit.on_wall("back", t - 0.45 / back.length_m, "rail", F.combine(F.utensil_rail(kit.rng, 1.1), (0, 0, 1.38)),
                check=False)
    _art(kit, "back", t + 0.75 / back.length_m, 1.25, 0.32, 0.42, "art1")
    _art(kit, "back", t + 1.1 / back.length_m, 1.3, 0.26, 0.34, "art2")
    for dx in (-3.35, 3.35):  # open shelves with crockery beside the tall units
        kit.on_wall("back", t + dx / back.length_m, "shelf", F.open_shelves(0.9, [1.05, 1.45], 0.26, 0.035) +
                    F.shelf_items(kit.rng, 0.8, 1.07, 0.26, ("bowl", "jar", "vase")) +
                    F.shelf_items(kit.rng, 0.8, 1.47, 0.26, ("books", "bowl", "jar")), check=False)
    kit.on_wall("left", 0.55, "table", F.table_base(0.9, 0.9, 0.72, "pedestal") +
                [(F.cyl(0.45, 0.72, 0.75, segments=32), "top")], offset_m=1.6)
    p = kit.walls[kit.sides["left"]].point(0.55, 1.6)
    for a in (60, 240):
        r = np.radians(a)
        kit.item("chair", F.chair("metal"), (p[0] + 0.65 * np.cos(r), p[1] + 0.65 * np.sin(r)), 0.0, a + 90)
    _plant(kit, "left", 0.15, "tall", 1.6, 0.2)
    _plant(kit, "front", 0.85, "bush", 0.8)
    _art(kit, "right", 0.45, 1.4, 0.9, 1.1, "art0")
    kit.on_wall("front", 0.4, "sideboard", F.cabinet_run(1.8, 0.45, 0.85, door_w=0.6, handle="edge") +
                F.combine(F.shelf_items(kit.rng, 1.6, 0.85, 0.0, ("vase", "bowl", "books", "jar")), (0, 0, 0)),
                offset_m=0.23)
    _art(kit, "front", 0.4, 1.45, 1.0, 0.7, "art3")
    _plant(kit, "front", 0.12, "palm", 1.3, 0.2)
    _lamp(kit, "right", 0.15, 0.35, 30.0)
    kit.on_wall("left", 0.55, "runner", [(F.slab_uv01((1.8, 1.2, 0.004), (0, 0, 0.002)), "rug_deco")],
                offset_m=1.6, check=False)


def _japandi(kit) -> None:
    rng = kit.rng
    _pendants(kit, "table", "lantern", 1, 1.2, 0.32, 45.0)
    _rug(kit, "rug", (3.0, 2.2), (0.0, 0.0), "rug_deco")
    kit.on_wall("back", 0.5, "sideboard", F.cabinet_run(2.0, 0.42, 0.6, door_w=0.5, handle="none", legs=True),
                offset_m=0.21)
    kit.on_wall("back", 0.5, "vase", F.combine(F.vase_with_stems(rng, 0.45), (-0.6, 0.0, 0.6)) +
                F.combine(F.shelf_items(rng, 0.8, 0.6, 0.0, ("bowl", "vase")), (0.5, 0.0, 0.0)), offset_m=0.21,
                check=False)
    _art(kit, "back", 0.5, 1.4, 1.4, 0.8, "art0")
    _art(kit, "left", 0.62, 1.25, 0.7, 0.5, "art1")
    _art(kit, "left", 0.8, 1.25, 0.5, 0.5, "art2")
    kit.on_wall("left", 0.5, "bench", [(F.B((1.6, 0.4, 0.05), (0, 0, 0.43)), "wood")] +
                F.table_base(1.6, 0.4, 0.41, "legs", 0.05) + F.combine(F.floor_cushion(0.4), (0.4, 0.0, 0.45)),
                offset_m=0.25)
    _plant(kit, "back", 0.12, "tall", 1.6, 0.2)
    _plant(kit, "front", 0.88, "bush", 0.7, 0.2)
    kit.on_wall("front", 0.35, "bookcase", F.bookcase(rng, 1.2, 0.3, 1.1, 2), offset_m=0.16)
    kit.on_wall("front", 0.35, "bonsai", F.combine(F.plant(rng, 0.14, 0.1, 0.5, "bush"), (0.0, 0.0, 1.1)),
                offset_m=0.16, check=False)
    kit.on_wall("front", 0.68, "tansu", F.cabinet_run(1.6, 0.4, 0.75, door_w=0.4, handle="none", drawers=True) +
                F.combine(F.table_lamp(0.45), (0.55, 0.0, 0.75)) +
                F.combine(F.shelf_items(rng, 0.8, 0.75, 0.0, ("bowl", "vase", "books")), (-0.3, 0.0, 0.0)),
                offset_m=0.2)
    _art(kit, "front", 0.68, 1.45, 0.9, 0.6, "art3")
    for t in (0.12, 0.88):
        _plant(kit, "right", t, "tall" if t < 0.5 else "palm", 1.4, 0.2)
    kit.on_wall("right", 0.5, "floor_cushions", F.combine(F.floor_cushion(0.55), (-0.5, 0.0, 0.0)) +
                F.combine(F.floor_cushion(0.55), (0.5, 0.0, 0.0)), offset_m=0.6)
    lamp = kit.on_wall("left", 0.92, "floor_lamp", F.floor_lamp(), offset_m=0.35)
    if lamp is not None:
        kit.light("POINT", (lamp.location.x, lamp.location.y, kit.scene.floor_z_m + 1.45), 30.0, kit.style.lamp_colour,
                  size_m=0.1, name="lamp_glow")


def _dining_set(kit) -> None:
    rng = kit.rng
    for side in ("back", "left", "right", "front"):
        kit.on_wall(side, 0.5, "wainscot", F.wainscot(kit.walls[kit.sides[side]].length_m, 1.0), check=False)
    _rug(kit, "rug", (3.2, 2.2), (0.0, 0.0), "rug_deco", rot=90.0)
    top = kit.scene.floor_z_m + kit.style.wall_height_m
    used = _hang(kit, "chandelier", lambda h: F.chandelier(h, 6, 0.45), (0.0, 0.0), top, 1.0)
    kit.light("POINT", (0.0, 0.0, top - used + 0.05), 60.0, kit.style.lamp_colour, size_m=0.3,
              name="chandelier_light")
    t = _t_of(kit, "back", 0.0)
    _art(kit, "back", t, 1.75, 1.3, 0.9, "art0")
    kit.on_wall("right", 0.5, "cabinet", F.bookcase(rng, 1.4, 0.42, 2.0, 4), offset_m=0.22)
    kit.on_wall("left", 0.5, "mirror", F.round_mirror(0.45), z=1.5, check=False)
    kit.on_wall("left", 0.5, "console", F.cabinet_run(1.2, 0.38, 0.85, door_w=0.4, handle="knob", legs=True),
                offset_m=0.2)
    kit.on_wall("front", 0.3, "curtains", F.curtains(1.6, 2.5, 2.5), check=False)
    kit.on_wall("front", 0.7, "curtains", F.curtains(1.6, 2.5, 2.5), check=False)
    _plant(kit, "back", 0.1, "tall", 1.5)
    _plant(kit, "back", 0.9, "tall", 1.5)
    _art(kit, "right", 0.2, 1.6, 0.6, 0.8, "art1")
    _art(kit, "right", 0.8, 1.6, 0.6, 0.8, "art2")


def _modular_flat(kit) -> None:
    rng = kit.rng
    t = _t_of(kit, "back", 0.0)
    back = kit.walls[kit.sides["back"]]
    # the space over the desk stays clear: flat prints and a pinboard there, shelves beside it
    kit.on_wall("back", t - 0.35 / back.length_m, "pinboard", F.picture(0.8, 0.55, 0.025, "cork"), z=1.22,
                check=False)
    for k, (dx, z, w, h) in enumerate(((0.35, 1.3, 0.36, 0.48), (0.72, 1.18, 0.3, 0.3), (0.45, 1.85, 0.5, 0.4))):
        _art(kit, "back", t + dx / back.length_m, z, w, h, f"art{k}")
    kit.on_wall("back", t + 2.1 / back.length_m, "cubes", F.cube_shelf(rng, 3, 4), offset_m=0.18)
    kit.on_wall("back", t - 2.1 / back.length_m, "cubes", F.cube_shelf(rng, 3, 2), offset_m=0.18)
    kit.on_wall("left", 0.5, "sofa_bed", F.sofa(2.0, 0.95, 2), offset_m=0.5)
    kit.on_wall("right", 0.45, "tv", F.tv(1.2), z=1.2, check=False)
    kit.on_wall("right", 0.45, "tv_unit", F.cabinet_run(1.6, 0.4, 0.45, door_w=0.4, handle="edge", legs=True),
                offset_m=0.2)
    kit.item("beanbag", F.pouf(0.38, 0.45), kit.walls[kit.sides["right"]].point(0.75, 1.4), 0.0)
    _plant(kit, "back", 0.04, "tall", 1.7, 0.22)
    _plant(kit, "front", 0.5, "bush", 1.0)
    _lamp(kit, "left", 0.15, 0.35, 40.0)
    _rug(kit, "rug", (2.0, 1.4), kit.walls[kit.sides["left"]].point(0.5, 1.6), "rug_deco", rot=90.0)
    kit.on_wall("front", 0.75, "bookcase", F.bookcase(rng, 1.2, 0.32, 1.5, 3), offset_m=0.17)
    _art(kit, "left", 0.5, 1.45, 1.1, 0.6, "art3")
    kit.on_wall("right", 0.2, "side_table", F.table_base(0.45, 0.45, 0.5, "legs", 0.035) +
                [(F.B((0.45, 0.45, 0.03), (0, 0, 0.515)), "top")] + F.combine(F.table_lamp(0.4), (0, 0, 0.53)),
                offset_m=0.3)


def _coastal(kit) -> None:
    rng = kit.rng
    kit.item("sofa", F.sofa(2.3, 0.95, 3), (0.0, -1.85), 0.0, 180.0)
    for sgn in (-1, 1):
        kit.item("armchair", F.armchair(0.85), (sgn * 2.05, -0.2), 0.0, -sgn * 90.0)
    _rug(kit, "rug", (3.0, 2.2), (0.0, -0.45), "rug_deco")
    t = _t_of(kit, "back", 0.0)
    _art(kit, "back", t, 1.75, 1.5, 0.8, "art0")
    for sgn in (-1, 1):
        _plant(kit, "back", t + sgn * 2.0 / kit.walls[kit.sides["back"]].length_m, "palm", 1.7, 0.22)
    kit.on_wall("left", 0.3, "curtains", F.curtains(2.0, 2.3, 2.45), check=False)
    kit.on_wall("right", 0.3, "curtains", F.curtains(2.0, 2.3, 2.45), check=False)
    kit.on_wall("front", 0.75, "bookcase", F.bookcase(rng, 1.4, 0.35, 1.8, 4), offset_m=0.18)
    _lamp(kit, "front", 0.3, 0.35, 40.0)
    side_table = (F.table_base(0.5, 0.5, 0.55, "legs", 0.04) + [(F.B((0.5, 0.5, 0.03), (0, 0, 0.565)), "top")]
                  + F.combine(F.vase_with_stems(rng, 0.3), (0, 0, 0.58)))
    kit.on_wall("left", 0.75, "side_table", side_table, offset_m=0.35)


def _gazebo(kit) -> None:
    """Open-air deck 1.2 m beyond the supports, posts and a canvas roof, sand, sea and palms."""
    rng = kit.rng
    fz = kit.scene.floor_z_m
    corners = np.concatenate([i.corners for i in kit.infos])
    (x0, y0), (x1, y1) = corners.min(0) - 1.2, corners.max(0) + 1.2
    holes = []
    for info in kit.infos:
        if info.kind in ("deck", "rug", "floor"):
            lo, hi = info.corners.min(0), info.corners.max(0)
            holes.append((lo[0], hi[0], lo[1], hi[1]))
    xs = np.unique([x0, x1] + [h[i] for h in holes for i in (0, 1)])
    ys = np.unique([y0, y1] + [h[i] for h in holes for i in (2, 3)])
    cx, cy = (xs[:-1] + xs[1:]) / 2, (ys[:-1] + ys[1:]) / 2
    keep = np.ones((len(cx), len(cy)), bool)
    for hx0, hx1, hy0, hy1 in holes:
        keep &= ~(((cx > hx0) & (cx < hx1))[:, None] & ((cy > hy0) & (cy < hy1))[None, :])
    platform = grid_plane(xs, ys, keep, fz)
    skirt = [box((x1 - x0, 0.04, 0.4), ((x0 + x1) / 2, y, fz - 0.2)) for y in (y0, y1)] + \
            [box((0.04, y1 - y0, 0.4), (x, (y0 + y1) / 2, fz - 0.2)) for x in (x0, x1)]
    kit.item("platform", [(platform, "deck"), *[(p, "deck") for p in skirt]], check=False)
    kit.item("steps", [(F.B((1.6, 0.35, 0.12), (0, y0 - 0.18, fz - 0.06 - 0.12 * k)), "deck") for k in range(2)],
             check=False)
    ang = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    # a beach 9-15 m around the gazebo (nearest the sea on the +y side), then open sea to the horizon
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    r = 12.0 + 1.2 * np.sin(3 * ang + 0.7) + 0.6 * np.sin(7 * ang + 2.0)
    beach = np.stack([cx + r * np.cos(ang), cy - 3.5 + r * np.sin(ang)], 1)
    kit.item("sand", [(polygon_prism(beach, fz - 1.0, fz - 0.4), "sand")], check=False)
    shore = np.stack([cx + (r + 1.6) * np.cos(ang), cy - 3.5 + (r + 1.6) * np.sin(ang)], 1)
    kit.item("shore", [(polygon_prism(shore, fz - 1.0, fz - 0.53), "wet_sand")], check=False)
    sea = grid_plane(np.array([-3000.0, 3000.0]), np.array([-3000.0, 3000.0]), np.ones((1, 1), bool), fz - 0.55)
    kit.item("sea", [(sea, "sea")], check=False)
    posts = []
    for px in (x0 + 0.12, x1 - 0.12):
        for py in (y0 + 0.12, y1 - 0.12):
            posts.append((F.cyl(0.09, fz, fz + 2.55, px, py, 16), "post"))
            posts.append((F.cyl(0.13, fz, fz + 0.12, px, py, 16), "post"))
    beams = [(F.B((x1 - x0, 0.12, 0.16), (0, y, fz + 2.5)), "post") for y in (y0 + 0.12, y1 - 0.12)]
    beams += [(F.B((0.12, y1 - y0, 0.16), (x, (y0 + y1) / 2, fz + 2.5)), "post") for x in (x0 + 0.12, x1 - 0.12)]
    kit.item("posts", posts + beams, check=False)
    roof = F.hip_roof((x1 - x0) / 2 + 0.45, (y1 - y0) / 2 + 0.45, fz + 2.58, fz + 3.7)
    kit.item("roof", [(roof, "roof")], ((x0 + x1) / 2, (y0 + y1) / 2), 0.0, check=False)
    for px, py in ((x0 + 0.12, y1 - 0.12), (x1 - 0.12, y1 - 0.12), (x0 + 0.12, y0 + 0.12), (x1 - 0.12, y0 + 0.12)):
        kit.item("lantern", [(F.cyl(0.07, -0.22, 0.0, segments=10), "lamp_metal"),
                             (F.cyl(0.055, -0.2, -0.03, segments=10), "shade"),
                             (F.cyl(0.003, 0.0, 0.3, segments=4), "metal")], (px, py), fz + 2.1, check=False)
    for (x, y, h, lean) in ((-7.0, 3.5, 5.5, (0.8, -0.3)), (7.5, 2.5, 6.2, (-0.6, 0.5)),
                            (-8.5, -6.0, 5.0, (0.5, 0.6)), (6.5, -8.5, 5.8, (-0.4, -0.3)),
                            (-3.5, 5.0, 4.6, (0.3, 0.5)), (3.0, -11.0, 5.2, (0.2, 0.6))):
        kit.item("palm", F.palm_tree(rng, h, lean), (cx + x, cy + y), fz - 0.4, check=False)
    for x in (-5.2, -3.9):
        kit.item("lounger", F.sun_lounger(), (cx + x, y0 - 2.3), fz - 0.4, 80.0, check=False)
    kit.item("umbrella", [(F.cyl(0.025, 0.0, 2.2), "post"),
                          (revolve(np.array([1.1, 0.0]), np.array([1.9, 2.3]), 16), "roof")], (cx - 4.55, y0 - 3.4),
             fz - 0.4, check=False)
    for px, py in ((x0 + 0.5, y1 - 0.45), (x1 - 0.5, y1 - 0.45)):
        kit.item("plant", F.plant(rng, 0.2, 0.45, 1.3, "palm"), (px, py), fz)


def _mural(kit) -> None:
    rng = kit.rng
    for k, (x, y) in enumerate(((0.0, 0.95), (0.0, -0.95), (1.4, 0.0), (-1.4, 0.0))):
        kit.item("cushion", F.floor_cushion(0.55) if k < 2 else F.pouf(0.24, 0.36), (x, y), 0.0, check=False)
    _rug(kit, "rug", (3.0, 2.4), (0.0, 0.0), "rug_deco")
    kit.on_wall("right", 0.7, "bookcase", F.bookcase(rng, 1.6, 0.35, 1.9, 4), offset_m=0.18)
    kit.on_wall("front", 0.25, "sofa", F.sofa(2.0, 0.9, 2), offset_m=0.5)
    for side, t, kind, h in (("back", 0.08, "tall", 1.7), ("back", 0.92, "palm", 1.8), ("left", 0.9, "bush", 1.1),
                             ("front", 0.7, "tall", 1.5), ("right", 0.3, "bush", 0.9), ("left", 0.1, "palm", 1.4)):
        _plant(kit, side, t, kind, h, 0.2)
    top = kit.scene.floor_z_m + kit.style.wall_height_m
    used = _hang(kit, "pendant", lambda h: F.pendant(h, "cone", 0.25), (0.0, 0.0), top, 1.1)
    kit.light("POINT", (0.0, 0.0, top - used - 0.02), 40.0, kit.style.lamp_colour, size_m=0.1, name="bulb")
    _lamp(kit, "front", 0.55, 0.35, 35.0)


def _cozy(kit) -> None:
    rng = kit.rng
    kit.item("sofa", F.sofa(2.4, 0.98, 3), (0.0, 1.55), 0.0, 0.0)
    for sgn in (-1, 1):
        kit.item("armchair", F.armchair(0.9), (sgn * 2.15, -0.1), 0.0, -sgn * 90.0 + sgn * 15)
    kit.on_wall("left", 0.5, "fireplace", F.fireplace(1.6, 1.15, 0.4), offset_m=0.0, check=False)
    fp = kit.walls[kit.sides["left"]].point(0.5, 0.35)
    kit.light("POINT", (fp[0], fp[1], kit.scene.floor_z_m + 0.3), 60.0, (1.0, 0.5, 0.2), size_m=0.3, name="fire")
    _art(kit, "left", 0.5, 1.8, 1.0, 0.7, "art0")
    kit.on_wall("right", 0.3, "bookcase", F.bookcase(rng, 1.5, 0.36, 2.2, 5), offset_m=0.18)
    kit.on_wall("right", 0.7, "bookcase", F.bookcase(rng, 1.5, 0.36, 2.2, 5), offset_m=0.18)
    kit.on_wall("back", 0.2, "curtains", F.curtains(2.0, 2.3, 2.45), check=False)
    kit.on_wall("back", 0.8, "curtains", F.curtains(2.0, 2.3, 2.45), check=False)
    _lamp(kit, "back", 0.62, 0.45, 60.0)
    _lamp(kit, "front", 0.2, 0.4, 60.0)
    _plant(kit, "back", 0.05, "tall", 1.6, 0.2)
    _plant(kit, "front", 0.9, "bush", 1.0)
    sideboard = (F.cabinet_run(1.6, 0.42, 0.8, door_w=0.4, handle="knob", legs=True)
                 + F.combine(F.table_lamp(0.55), (0.5, 0.0, 0.8)) + F.combine(F.vase_with_stems(rng, 0.35),
                                                                              (-0.4, 0.0, 0.8)))
    kit.on_wall("front", 0.55, "sideboard", sideboard, offset_m=0.21)
    side = kit.walls[kit.sides["front"]].point(0.55, 0.6)
    kit.light("POINT", (side[0] + 0.5, side[1], 1.2), 25.0, kit.style.lamp_colour, size_m=0.1, name="table_lamp")


def _warm_kitchen(kit) -> None:
    _kitchen_wall(kit, "counter", 1.55, uppers=False, shelves=True, hood=False, columns=True)
    _pendants(kit, "island", "dome", 2, 1.0, 0.22)
    _art(kit, "right", 0.35, 1.6, 0.8, 1.0, "art0")
    kit.on_wall("front", 0.5, "dresser", F.cabinet_run(1.8, 0.45, 0.9, door_w=0.45, handle="knob", drawers=True),
                offset_m=0.23)
    kit.on_wall("front", 0.5, "dresser_items", F.combine(F.shelf_items(kit.rng, 1.6, 0.9, 0.0, ("bowl", "jar", "vase")),
                                                         (0.0, -0.0, 0.0)), offset_m=0.23, check=False)
    _plant(kit, "front", 0.12, "tall", 1.6, 0.22)
    _plant(kit, "left", 0.9, "bush", 1.0)
    _rug(kit, "runner", (2.4, 0.7), (0.0, -0.66), "rug_deco")


# ---------------------------------------------------------------------------------------------
# Palettes


def _m(fn, *args, **kw) -> Factory:
    return lambda name: fn(name, *args, **kw)


def _rug_mat(seed: int, colours) -> Factory:
    colours = tuple(tuple(c) for c in colours)
    return lambda name: M.image_material(name, f"{name}_img", lambda: _paint.rug_pattern(seed, colours), roughness=0.95,
                                         sheen=0.6)


STYLES: dict[str, Style] = {
    "hallway_interior": Style(
        hdri="interior.exr", hdri_strength=0.48, margin_m=3.6, fill_w=300.0, support_light_w=30.0,
        windows=(("front", 0.8, 1.0, 0.9, 2.3, (2, 2)),),
        materials={
            "wall": _m(M.painted, (0.56, 0.63, 0.55), 0.85),
            "trim": _m(M.painted, (0.93, 0.92, 0.88), 0.45),
            "floor": _m(M.wood, (0.55, 0.38, 0.24), 0.45, planks=True, plank_m=(0.6, 0.1)),
            "top": _m(M.wood, (0.72, 0.55, 0.36), 0.45, coat=0.1),
            "wood": _m(M.wood, (0.62, 0.45, 0.28), 0.5),
            "metal": _m(M.metal, (0.05, 0.05, 0.05), 0.45),
            "cabinet": _m(M.painted, (0.9, 0.88, 0.83), 0.4),
            "cabinet_front": _m(M.painted, (0.9, 0.88, 0.83), 0.35),
            "handle": _m(M.metal, (0.75, 0.58, 0.3), 0.25),
            "rug": _rug_mat(7, [(0.68, 0.2, 0.16), (0.12, 0.2, 0.38), (0.9, 0.8, 0.6), (0.15, 0.1, 0.08)]),
            "accent0": _m(M.fabric, (0.12, 0.16, 0.3)),
            "accent1": _m(M.fabric, (0.66, 0.48, 0.28)),
            "accent2": _m(M.fabric, (0.6, 0.1, 0.1), pattern="check", second=(0.9, 0.85, 0.7), stripe_m=0.05),
            "door": _m(M.painted, (0.93, 0.92, 0.88), 0.4),
            "shade": _m(M.emissive, (1.0, 0.9, 0.75), 5.0),
        },
        decorate=_hallway),
    "modern_loft": Style(
        hdri="city.exr", hdri_strength=0.4, hdri_rotation_deg=-256.0, fill_w=180.0, support_light_w=20.0,
        windows=(("left", 0.5, 2.6, 0.45, 2.55, (4, 3)), ("right", 0.35, 2.6, 0.45, 2.55, (4, 3)),
                 ("front", 0.2, 2.0, 0.45, 2.55, (3, 3))),
        wall_roles={"back": "brick"},
        materials={
            "brick": _m(M.brick_wall, (0.55, 0.25, 0.17)),
            "wall": _m(M.painted, (0.82, 0.8, 0.76), 0.85),
            "floor": _m(M.concrete, (0.55, 0.55, 0.53), 0.4),
            "top": _m(M.wood, (0.68, 0.48, 0.3), 0.4),
            "cabinet": _m(M.painted, (0.08, 0.08, 0.09), 0.5),
            "cabinet_front": _m(M.painted, (0.1, 0.1, 0.11), 0.45),
            "handle": _m(M.metal, (0.05, 0.05, 0.05), 0.35),
            "window_frame": _m(M.painted, (0.04, 0.04, 0.04), 0.5),
            "sofa": _m(M.fabric, (0.45, 0.24, 0.12), sheen=0.2),
            "cushion": _m(M.fabric, (0.75, 0.7, 0.6)),
            "wood": _m(M.wood, (0.45, 0.3, 0.18), 0.4),
            "shelf": _m(M.metal, (0.06, 0.06, 0.06), 0.5),
            "rug_deco": _rug_mat(11, [(0.6, 0.58, 0.55), (0.2, 0.2, 0.22), (0.75, 0.4, 0.2), (0.1, 0.1, 0.1)]),
            "lamp_metal": _m(M.metal, (0.04, 0.04, 0.04), 0.4),
            "trim": _m(M.painted, (0.1, 0.1, 0.1), 0.5),
        },
        art_palette=((0.9, 0.88, 0.82), (0.1, 0.1, 0.1), (0.8, 0.25, 0.15), (0.25, 0.4, 0.6), (0.95, 0.75, 0.2)),
        decorate=_loft),
    "modern_luxury_kitchen": Style(
        hdri="courtyard.exr", hdri_strength=0.4, fill_w=150.0, support_light_w=7.0, door_w=0.55,
        windows=(("right", 0.35, 1.6, 0.9, 2.5, (2, 2)), ("right", 0.7, 1.6, 0.9, 2.5, (2, 2)),
                 ("front", 0.3, 2.4, 0.5, 2.5, (3, 2))),
        materials={
            "top": _m(M.marble, (0.88, 0.87, 0.85), 0.1),
            "backsplash": _m(M.marble, (0.8, 0.79, 0.77), 0.12),
            "cabinet": _m(M.painted, (0.08, 0.12, 0.22), 0.45),
            "cabinet_front": _m(M.painted, (0.09, 0.13, 0.24), 0.35),
            "handle": _m(M.metal, (0.85, 0.65, 0.32), 0.2),
            "lamp_metal": _m(M.metal, (0.85, 0.65, 0.32), 0.2),
            "metal": _m(M.metal, (0.85, 0.65, 0.32), 0.25),
            "floor": _m(M.tiles, (0.72, 0.7, 0.66), (0.6, 0.6, 0.58), (0.8, 0.8), 0.0, 0.3, 0.04, 0.002),
            "wall": _m(M.painted, (0.92, 0.9, 0.86), 0.85),
            "plinth": _m(M.painted, (0.05, 0.06, 0.1), 0.6),
            "chair_seat": _m(M.fabric, (0.75, 0.68, 0.58)),
            "chair_frame": _m(M.metal, (0.85, 0.65, 0.32), 0.25),
            "shade": _m(M.emissive, (1.0, 0.92, 0.8), 4.0),
            "rug_deco": _rug_mat(13, [(0.8, 0.78, 0.72), (0.15, 0.2, 0.35), (0.75, 0.6, 0.35), (0.1, 0.1, 0.15)]),
        },
        art_palette=((0.95, 0.94, 0.9), (0.1, 0.15, 0.3), (0.8, 0.62, 0.3), (0.5, 0.55, 0.6), (0.2, 0.2, 0.2)),
        decorate=_luxury_kitchen),
    "minimal_white_kitchen": Style(
        hdri="studio.exr", hdri_strength=0.2, fill_w=40.0, support_light_w=4.0, handle="edge", door_w=0.7,
        sun=(180.0, 38.0, 1.0), margin_m=3.7, min_half_m=4.1,
        windows=(("left", 0.5, 2.2, 0.8, 2.5, (2, 1)), ("right", 0.75, 1.4, 0.9, 2.4, (1, 1))),
        materials={
            "top": _m(M.marble, (0.9, 0.9, 0.89), 0.15, vein=(0.62, 0.62, 0.62)),
            "backsplash": _m(M.tiles, (0.5, 0.6, 0.58), (0.86, 0.86, 0.84), (0.2, 0.067), 0.5, 0.1, 0.03, 0.0025),
            "cabinet": _m(M.painted, (0.86, 0.86, 0.85), 0.35),
            "cabinet_front": _m(M.painted, (0.88, 0.88, 0.87), 0.3),
            "plinth": _m(M.painted, (0.85, 0.85, 0.84), 0.5),
            "floor": _m(M.wood, (0.78, 0.64, 0.46), 0.5, planks=True, plank_m=(2.0, 0.22)),
            "lamp_metal": _m(M.metal, (0.03, 0.03, 0.03), 0.45),
            "wall": _m(M.painted, (0.8, 0.78, 0.73), 0.8, variation=0.07),
            "appliance": _m(M.metal, (0.72, 0.72, 0.72), 0.3),
            "accent0": _m(M.painted, (0.2, 0.35, 0.32), 0.5),
            "accent1": _m(M.painted, (0.75, 0.45, 0.3), 0.5),
            "accent2": _m(M.painted, (0.85, 0.8, 0.6), 0.5),
            "ceramic": _m(M.painted, (0.25, 0.38, 0.36), 0.4, coat=0.4),
            "rug_deco": _rug_mat(41, [(0.78, 0.74, 0.66), (0.25, 0.38, 0.36), (0.7, 0.45, 0.3), (0.2, 0.2, 0.2)]),
            "handle": _m(M.metal, (0.8, 0.8, 0.8), 0.3),
            "wood": _m(M.wood, (0.78, 0.64, 0.46), 0.5),
            "chair_seat": _m(M.painted, (0.95, 0.95, 0.95), 0.4),
            "chair_frame": _m(M.metal, (0.1, 0.1, 0.1), 0.4),
            "ceramic2": _m(M.painted, (0.9, 0.9, 0.88), 0.3, coat=0.4),
        },
        art_palette=((0.97, 0.97, 0.96), (0.1, 0.1, 0.1), (0.85, 0.85, 0.85), (0.75, 0.65, 0.5), (0.3, 0.3, 0.3)),
        decorate=_white_kitchen),
    "modern_japandi_dining": Style(
        hdri="forest.exr", hdri_strength=0.3, hdri_rotation_deg=-25.7, fill_w=60.0, support_light_w=8.0,
        sun=(10.0, 35.0, 1.0), chair="japandi", end_chairs=True, chair_gap_m=0.22, margin_m=3.7, min_half_m=4.1,
        windows=(("right", 0.5, 3.2, 0.3, 2.5, (6, 4)), ("left", 0.25, 1.4, 0.8, 2.3, (1, 2))),
        table_base={"table": "trestle"},
        materials={
            "wall": _m(M.painted, (0.78, 0.73, 0.65), 0.9, variation=0.08),
            "floor": _m(M.wood, (0.72, 0.6, 0.44), 0.5, planks=True, plank_m=(1.8, 0.2)),
            "cushion": _m(M.fabric, (0.45, 0.5, 0.4)),
            "accent0": _m(M.fabric, (0.3, 0.28, 0.26)),
            "accent2": _m(M.fabric, (0.7, 0.45, 0.3)),
            "lamp_metal": _m(M.metal, (0.1, 0.1, 0.1), 0.5),
            "top": _m(M.wood, (0.8, 0.66, 0.46), 0.45),
            "leg": _m(M.wood, (0.76, 0.62, 0.43), 0.5),
            "wood": _m(M.wood, (0.76, 0.62, 0.43), 0.5),
            "cabinet": _m(M.wood, (0.74, 0.6, 0.42), 0.5),
            "cabinet_front": _m(M.wood, (0.76, 0.62, 0.44), 0.5),
            "chair_frame": _m(M.wood, (0.7, 0.56, 0.38), 0.5),
            "chair_seat": _m(M.rattan, (0.78, 0.66, 0.45)),
            "window_frame": _m(M.wood, (0.7, 0.56, 0.38), 0.5),
            "shade": _m(M.emissive, (1.0, 0.93, 0.82), 3.0),
            "metal": _m(M.metal, (0.1, 0.1, 0.1), 0.5),
            "ceramic": _m(M.painted, (0.2, 0.2, 0.2), 0.6),
            "ceramic2": _m(M.painted, (0.78, 0.72, 0.6), 0.7),
            "pot": _m(M.painted, (0.25, 0.24, 0.22), 0.8),
            "accent1": _m(M.fabric, (0.55, 0.6, 0.48)),
            "rug_deco": _rug_mat(17, [(0.82, 0.77, 0.67), (0.6, 0.56, 0.48), (0.7, 0.66, 0.56), (0.3, 0.3, 0.28)]),
            "trim": _m(M.wood, (0.7, 0.56, 0.38), 0.5),
        },
        art_palette=((0.92, 0.88, 0.8), (0.15, 0.15, 0.15), (0.6, 0.55, 0.45), (0.5, 0.56, 0.45), (0.75, 0.5, 0.35)),
        decorate=_japandi),
    "dining_room_set": Style(
        hdri="sunset.exr", hdri_strength=0.9, hdri_rotation_deg=-196.0, fill_w=420.0, support_light_w=70.0,
        chair="upholstered", end_chairs=True, handle="knob", table_base={"table": "legs"},
        windows=(("front", 0.3, 1.4, 0.8, 2.4, (2, 3)), ("front", 0.7, 1.4, 0.8, 2.4, (2, 3))),
        materials={
            "wall": _m(M.painted, (0.16, 0.3, 0.24), 0.85),
            "trim": _m(M.painted, (0.92, 0.9, 0.85), 0.45),
            "floor": _m(M.wood, (0.45, 0.3, 0.18), 0.4, planks=True, plank_m=(0.45, 0.09)),
            "top": _m(M.wood, (0.36, 0.2, 0.11), 0.3, coat=0.3),
            "leg": _m(M.wood, (0.34, 0.19, 0.1), 0.4),
            "cabinet": _m(M.wood, (0.36, 0.2, 0.11), 0.4),
            "cabinet_front": _m(M.wood, (0.38, 0.22, 0.12), 0.35),
            "chair_seat": _m(M.fabric, (0.36, 0.05, 0.08), sheen=0.3),
            "chair_frame": _m(M.wood, (0.3, 0.17, 0.09), 0.4),
            "handle": _m(M.metal, (0.8, 0.62, 0.3), 0.25),
            "metal": _m(M.metal, (0.8, 0.62, 0.3), 0.25),
            "curtain": _m(M.fabric, (0.72, 0.6, 0.38), sheen=0.6),
            "shelf": _m(M.wood, (0.36, 0.2, 0.11), 0.4),
            "frame": _m(M.metal, (0.8, 0.62, 0.3), 0.3),
            "shade": _m(M.emissive, (1.0, 0.8, 0.55), 8.0),
            "rug_deco": _rug_mat(19, [(0.55, 0.1, 0.1), (0.12, 0.14, 0.3), (0.85, 0.7, 0.45), (0.1, 0.06, 0.05)]),
            "window_frame": _m(M.painted, (0.92, 0.9, 0.85), 0.45),
        },
        art_palette=((0.3, 0.25, 0.18), (0.7, 0.55, 0.3), (0.2, 0.3, 0.25), (0.6, 0.2, 0.15), (0.85, 0.75, 0.55)),
        decorate=_dining_set),
    "modular_flat": Style(
        hdri="city.exr", hdri_strength=0.26, hdri_rotation_deg=-236.0, fill_w=65.0, support_light_w=6.0,
        sun=(-80.0, 35.0, 1.0), margin_m=3.7, min_half_m=4.1,
        table_base={"desk": "trestle"}, support_roles={"floor": "floor"},
        windows=(("front", 0.3, 2.4, 0.6, 2.5, (3, 1)), ("right", 0.85, 1.2, 0.8, 2.3, (1, 1))),
        materials={
            "wall": _m(M.painted, (0.62, 0.7, 0.76), 0.85, variation=0.07),
            "floor": _m(M.wood, (0.7, 0.56, 0.4), 0.5, planks=True, plank_m=(1.4, 0.18)),
            "cork": lambda n: M.image_material(n, f"{n}_img", lambda: _paint.pinboard(5), roughness=0.9),
            "frame": _m(M.painted, (0.12, 0.12, 0.13), 0.5),
            "top": _m(M.wood, (0.86, 0.76, 0.6), 0.45),
            "leg": _m(M.painted, (0.95, 0.95, 0.94), 0.4),
            "shelf": _m(M.painted, (0.95, 0.95, 0.94), 0.4),
            "sofa": _m(M.fabric, (0.2, 0.42, 0.45)),
            "cushion": _m(M.fabric, (0.9, 0.7, 0.2)),
            "accent0": _m(M.fabric, (0.92, 0.68, 0.15)),
            "accent1": _m(M.fabric, (0.2, 0.45, 0.5)),
            "accent2": _m(M.fabric, (0.85, 0.4, 0.35)),
            "chair_seat": _m(M.fabric, (0.15, 0.15, 0.16)),
            "metal": _m(M.metal, (0.6, 0.6, 0.62), 0.35),
            "cabinet": _m(M.painted, (0.95, 0.95, 0.94), 0.4),
            "cabinet_front": _m(M.painted, (0.95, 0.95, 0.94), 0.35),
            "rug_deco": _rug_mat(23, [(0.92, 0.88, 0.8), (0.2, 0.42, 0.45), (0.92, 0.68, 0.15), (0.2, 0.2, 0.2)]),
        },
        art_palette=((0.97, 0.94, 0.88), (0.92, 0.68, 0.15), (0.2, 0.42, 0.45), (0.85, 0.4, 0.35), (0.15, 0.15, 0.2)),
        decorate=_modular_flat),
    "coastal_living_room": Style(
        hdri="sunrise.exr", hdri_strength=0.42, hdri_rotation_deg=144.0, fill_w=170.0, support_light_w=9.0,
        table_base={"coffee_table": "tapered", "console": "legs"}, kinds={"console": "table"}, chairs=False,
        windows=(("left", 0.3, 2.0, 0.5, 2.45, (2, 2)), ("right", 0.3, 2.0, 0.5, 2.45, (2, 2))),
        materials={
            "wall": _m(M.tiles, (0.86, 0.87, 0.86), (0.66, 0.68, 0.68), (2.4, 0.16), 0.5, 0.6, 0.02, 0.003),
            "floor": _m(M.wood, (0.8, 0.74, 0.64), 0.55, planks=True, plank_m=(1.6, 0.18)),
            "top": _m(M.wood, (0.8, 0.76, 0.68), 0.55, contrast=0.4),
            "leg": _m(M.wood, (0.86, 0.82, 0.74), 0.55, contrast=0.4),
            "sofa": _m(M.fabric, (0.88, 0.87, 0.82)),
            "cushion": _m(M.fabric, (0.2, 0.35, 0.6), pattern="stripes", second=(0.95, 0.95, 0.92), stripe_m=0.04),
            "chair_seat": _m(M.fabric, (0.6, 0.72, 0.8)),
            "curtain": _m(M.fabric, (0.93, 0.92, 0.88), sheen=0.3),
            "pot": _m(M.rattan, (0.75, 0.6, 0.38)),
            "rug_deco": _m(M.rattan, (0.7, 0.6, 0.42)),
            "ceramic2": _m(M.glass, (0.4, 0.65, 0.85), 0.05),
            "shelf": _m(M.painted, (0.95, 0.95, 0.93), 0.5),
            "trim": _m(M.painted, (0.95, 0.95, 0.93), 0.45),
        },
        art_palette=((0.85, 0.9, 0.93), (0.2, 0.45, 0.65), (0.9, 0.85, 0.7), (0.4, 0.65, 0.75), (0.95, 0.95, 0.95)),
        decorate=_coastal),
    "beach_gazebo": Style(
        hdri="sunset.exr", hdri_strength=1.0, hdri_rotation_deg=-156.0, fill_w=0.0, support_light_w=10.0,
        sky=(200.0, 42.0, 0.1), sun=(200.0, 42.0, 3.0), sun_colour=(1.0, 0.96, 0.9),
        walls=False, floor=False, skirting=False, margin_m=3.0, table_base={"table": "legs"},
        materials={
            "deck": _m(M.wood, (0.62, 0.46, 0.3), 0.6, planks=True, plank_m=(2.4, 0.14)),
            "top": _m(M.wood, (0.9, 0.87, 0.8), 0.5, contrast=0.35),
            "leg": _m(M.painted, (0.95, 0.95, 0.93), 0.5),
            "post": _m(M.painted, (0.95, 0.94, 0.9), 0.5),
            "roof": _m(M.fabric, (0.9, 0.86, 0.76), sheen=0.2, pattern="stripes", second=(0.3, 0.55, 0.7),
                       stripe_m=0.6),
            "sand": _m(M.sand),
            "wet_sand": _m(M.sand, (0.62, 0.54, 0.42)),
            "sea": _m(M.water, (0.02, 0.27, 0.42)),
            "chair_frame": _m(M.wood, (0.55, 0.38, 0.22), 0.5),
            "cushion": _m(M.fabric, (0.25, 0.5, 0.65)),
            "wood": _m(M.wood, (0.55, 0.38, 0.22), 0.5),
            "trunk": _m(M.concrete, (0.5, 0.42, 0.32), 0.9),
            "leaves": _m(M.leaves, (0.22, 0.45, 0.15)),
            "pot": _m(M.rattan, (0.7, 0.55, 0.35)),
            "shade": _m(M.emissive, (1.0, 0.75, 0.45), 6.0),
        },
        decorate=_gazebo),
    "butterfly_mural_room": Style(
        hdri="forest.exr", hdri_strength=0.3, fill_w=70.0, support_light_w=8.0, table_base={"low_table": "legs"},
        sun=(-50.0, 38.0, 0.9), margin_m=3.7, min_half_m=4.1,
        wall_roles={"back": "mural", "left": "mural", "right": "mural", "front": "mural"},
        windows=(("right", 0.75, 1.6, 0.7, 2.4, (2, 2)), ("front", 0.75, 1.6, 0.7, 2.4, (2, 2))),
        materials={
            "mural": lambda n: M.wall_image(n, f"{n}_img", _paint.butterfly_mural, (8.4, 2.8)),
            "wall": _m(M.painted, (0.8, 0.9, 0.85), 0.85),
            "floor": _m(M.terrazzo, (0.76, 0.74, 0.7)),
            "top": _m(M.wood, (0.74, 0.58, 0.4), 0.45),
            "leg": _m(M.wood, (0.7, 0.55, 0.38), 0.5),
            "accent0": _m(M.fabric, (0.95, 0.6, 0.2)),
            "accent1": _m(M.fabric, (0.35, 0.55, 0.85)),
            "sofa": _m(M.fabric, (0.85, 0.5, 0.55)),
            "cushion": _m(M.fabric, (0.98, 0.85, 0.3)),
            "rug_deco": _rug_mat(29, [(0.95, 0.93, 0.86), (0.35, 0.6, 0.55), (0.95, 0.6, 0.25), (0.3, 0.35, 0.5)]),
            "shelf": _m(M.painted, (0.95, 0.93, 0.88), 0.45),
            "pot": _m(M.painted, (0.95, 0.93, 0.88), 0.4),
            "lamp_metal": _m(M.painted, (0.95, 0.7, 0.2), 0.4),
        },
        decorate=_mural),
    "cozy_living_room": Style(
        hdri="night.exr", hdri_strength=1.5, fill_w=300.0, support_light_w=80.0, lamp_colour=(1.0, 0.78, 0.55),
        table_base={"coffee_table": "block"}, support_roles={"rug": "rug"},
        windows=(("back", 0.5, 2.6, 0.6, 2.4, (3, 2)),),
        materials={
            "wall": _m(M.painted, (0.72, 0.58, 0.45), 0.85),
            "floor": _m(M.wood, (0.42, 0.28, 0.17), 0.45, planks=True, plank_m=(1.2, 0.12)),
            "top": _m(M.wood, (0.3, 0.17, 0.09), 0.35, coat=0.2),
            "leg": _m(M.wood, (0.28, 0.16, 0.09), 0.4),
            "sofa": _m(M.fabric, (0.62, 0.28, 0.16), sheen=0.8),
            "cushion": _m(M.fabric, (0.88, 0.66, 0.18)),
            "chair_seat": _m(M.fabric, (0.2, 0.35, 0.32)),
            "rug": _rug_mat(31, [(0.6, 0.14, 0.1), (0.12, 0.16, 0.32), (0.88, 0.72, 0.42), (0.12, 0.07, 0.05)]),
            "curtain": _m(M.fabric, (0.55, 0.2, 0.12), sheen=0.7),
            "stone": _m(M.brick_wall, (0.6, 0.42, 0.3)),
            "shelf": _m(M.wood, (0.3, 0.17, 0.09), 0.4),
            "cabinet": _m(M.wood, (0.3, 0.17, 0.09), 0.4),
            "cabinet_front": _m(M.wood, (0.32, 0.18, 0.1), 0.4),
            "shade": _m(M.emissive, (1.0, 0.75, 0.45), 6.0),
            "window_frame": _m(M.painted, (0.25, 0.18, 0.12), 0.5),
            "trim": _m(M.painted, (0.3, 0.22, 0.15), 0.5),
        },
        art_palette=((0.2, 0.15, 0.1), (0.75, 0.45, 0.2), (0.88, 0.7, 0.35), (0.4, 0.2, 0.15), (0.25, 0.35, 0.3)),
        decorate=_cozy),
    "modern_warm_kitchen": Style(
        hdri="sunrise.exr", hdri_strength=0.6, hdri_rotation_deg=-215.7, fill_w=280.0, support_light_w=25.0,
        round_stools=False, door_w=0.5,
        windows=(("left", 0.35, 1.4, 0.95, 2.4, (2, 2)), ("left", 0.7, 1.4, 0.95, 2.4, (2, 2))),
        materials={
            "top": _m(M.marble, (0.86, 0.8, 0.7), 0.3, vein=(0.7, 0.62, 0.5), vein_scale=1.2),
            "cabinet": _m(M.wood, (0.36, 0.22, 0.13), 0.45),
            "cabinet_front": _m(M.wood, (0.38, 0.23, 0.14), 0.4),
            "backsplash": _m(M.tiles, (0.42, 0.15, 0.07), (0.78, 0.72, 0.64), (0.1, 0.1), 0.0, 0.08, 0.25, 0.0015),
            "floor": _m(M.tiles, (0.68, 0.4, 0.28), (0.6, 0.55, 0.5), (0.3, 0.3), 0.0, 0.6, 0.08, 0.004),
            "wall": _m(M.painted, (0.93, 0.88, 0.8), 0.85),
            "handle": _m(M.metal, (0.85, 0.65, 0.32), 0.2),
            "lamp_metal": _m(M.metal, (0.85, 0.65, 0.32), 0.2),
            "wood": _m(M.wood, (0.7, 0.52, 0.32), 0.45),
            "appliance": _m(M.metal, (0.75, 0.75, 0.74), 0.25),
            "chair_seat": _m(M.wood, (0.7, 0.52, 0.32), 0.45),
            "chair_frame": _m(M.metal, (0.1, 0.1, 0.1), 0.4),
            "plinth": _m(M.painted, (0.2, 0.13, 0.08), 0.6),
            "ceramic2": _m(M.painted, (0.45, 0.55, 0.42), 0.3, coat=0.4),
            "rug_deco": _rug_mat(37, [(0.8, 0.68, 0.5), (0.6, 0.3, 0.2), (0.35, 0.45, 0.35), (0.25, 0.15, 0.1)]),
        },
        art_palette=((0.93, 0.88, 0.8), (0.72, 0.36, 0.22), (0.45, 0.55, 0.42), (0.85, 0.65, 0.32), (0.3, 0.2, 0.12)),
        decorate=_warm_kitchen),
}

LAYOUT_STYLES = {"kitchen": "modern_warm_kitchen", "dining": "modern_japandi_dining", "living": "coastal_living_room",
                 "hallway": "hallway_interior", "loft": "modern_loft", "gazebo": "beach_gazebo",
                 "mural": "butterfly_mural_room"}


def _generic_decor(kit) -> None:
    """Decor for a scene without a dedicated style: plants in the corners and a print on the back wall."""
    for side, t in (("back", 0.06), ("back", 0.94), ("front", 0.06), ("front", 0.94)):
        _plant(kit, side, t, "bush", 1.1)
    _art(kit, "back", 0.25, 1.6, 1.0, 0.7, "art0")


def style_for(scene: SceneConfig) -> Style:
    """The scene's style: by id, else by ``style.layout``, with generic decor for new ids."""
    if scene.id in STYLES:
        return STYLES[scene.id]
    layout = str(scene.style.get("layout", "living"))
    base = STYLES[LAYOUT_STYLES.get(layout, "coastal_living_room")]
    decorate = _gazebo if layout == "gazebo" else _generic_decor  # the gazebo decor adapts to any supports
    return replace(base, decorate=decorate, windows=(), wall_roles={}, kinds={}, support_roles={}, table_base={})


__all__ = ["Style", "STYLES", "style_for"]
