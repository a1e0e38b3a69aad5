"""Procedural benchmark objects and task ramps as bpy mesh objects in the model frame.

``build_object`` returns one mesh object per asset: origin at the centre of its resting
bounding box, +z up, +x along the long axis, scaled so the bounding box equals
``ObjectConfig.size_m``. Each model is a few closed shells (body plus stem, crown, beak...)
of at most ~2.5k vertices, with Cycles materials whose surface detail (painted pattern,
speckles, bump) moves with the object so its points can be tracked. ``build_ramp`` makes the
exact five-face wedge the physics uses (``standin.ramp_mesh``). Each builder returns its geometry
and a function that makes its materials, so ``object_vertices`` gives the physics the exact
rendered geometry (for its collision hull) without touching Blender.
"""

from __future__ import annotations

import logging
from typing import Callable

import numpy as np

from ...config import MaterialConfig, ObjectConfig
from ...scene_spec.types import RampShape
from . import _paint, materials as M
from ._mesh import Part, Z_TO_X, box, fit, join, revolve, rounded_box, sphere, sweep, to_object
from .loader import load_mesh_object, load_mesh_vertices
from .standin import object_mesh, ramp_mesh

log = logging.getLogger(__name__)

# A builder returns its geometry (pure numpy) and a function that makes its bpy materials, so the
# physics can take the collision hull from the same geometry without Blender data being created.
Materials = Callable[[], list]


# ---------------------------------------------------------------------------------------------
# Shape helpers


def smooth_profile(points, samples: int) -> tuple[np.ndarray, np.ndarray]:
    """Catmull-Rom curve through (r, z) control points (K,2). Returns (r, z), each (samples,)."""
    p = np.asarray(points, float)
    p = np.vstack([p[0], p, p[-1]])
    segs = len(p) - 3
    t = np.linspace(0.0, segs, samples)
    i = np.minimum(t.astype(int), segs - 1)
    f = (t - i)[:, None]
    p0, p1, p2, p3 = p[i], p[i + 1], p[i + 2], p[i + 3]
    c = 0.5 * (2 * p1 + (p2 - p0) * f + (2 * p0 - 5 * p1 + 4 * p2 - p3) * f ** 2 + (3 * p1 - p0 - 3 * p2 + p3) * f ** 3)
    r = np.clip(c[:, 0], 0.0, None)
    r[0], r[-1] = p[1, 0], p[-2, 0]
    return r, c[:, 1]


def _polar_profile(rings: int, r_fn: Callable, z_fn: Callable) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Profile from polar angle theta in [0, pi] (south to north). Returns (r, z, v=theta/pi)."""
    theta = np.linspace(0.0, np.pi, rings + 1)
    r = r_fn(theta)
    r[0] = r[-1] = 0.0
    return r, z_fn(theta), theta / np.pi


def _bump_at(x: np.ndarray, width: float) -> np.ndarray:
    return np.exp(-(x / width) ** 2)


def _wrap(angle: np.ndarray) -> np.ndarray:
    return (angle + np.pi) % (2 * np.pi) - np.pi


def _stem(base, tip, r0: float, r1: float, segments: int = 8) -> Part:
    """A short stalk curving from ``base`` up and over to ``tip`` (3,) with radius r0 -> r1."""
    base, tip = np.asarray(base, float), np.asarray(tip, float)
    ctrl = base + np.array([0.0, 0.0, 0.7 * (tip - base)[2]])
    t = np.linspace(0, 1, 6)[:, None]
    centres = (1 - t) ** 2 * base + 2 * t * (1 - t) * ctrl + t ** 2 * tip
    return sweep(centres, np.linspace(r0, r1, 6), segments=segments, up=np.array([1.0, 0.0, 0.0]))


# ---------------------------------------------------------------------------------------------
# Fruit and vegetables


def apple() -> tuple[Part, Materials]:
    r, z, v = _polar_profile(24, lambda t: 0.5 * np.sin(t) * (1 - 0.07 * np.cos(t)),
                             lambda t: -0.5 * np.cos(t) - 0.14 * _bump_at(np.pi - t, 0.45) + 0.08 * _bump_at(t, 0.4))
    body = revolve(r, z, 40, radial=lambda vv, phi: 1 + 0.012 * np.cos(5 * phi) * np.sin(np.pi * vv), v_coords=v)
    stem = _stem((0, 0, 0.3), (0.05, 0.0, 0.62), 0.024, 0.017).with_material(1)
    return join([body, stem]), lambda: [
        M.skin("rb_apple", _paint.apple, roughness=0.4, coat=0.15, bump_scale=400, bump=0.05),
        M.plain("rb_apple_stem", (0.32, 0.22, 0.1), roughness=0.8)]


def orange() -> tuple[Part, Materials]:
    body = sphere(48, 24, radial=lambda v, phi: 1 + 0.006 * np.cos(7 * phi) * np.sin(np.pi * v))
    return body, lambda: [M.skin("rb_orange", _paint.orange, roughness=0.5, bump_scale=900, bump=0.3, pits=1.5)]


def lemon() -> tuple[Part, Materials]:
    r, z, v = _polar_profile(32, lambda t: 0.5 * np.sin(t) ** 1.15,
                             lambda t: -np.cos(t) * (0.5 + 0.16 * _bump_at(np.sin(t), 0.2)))
    body = revolve(r, z, 40, v_coords=v).transformed(Z_TO_X)
    return body, lambda: [M.skin("rb_lemon", _paint.lemon, roughness=0.4, coat=0.1, bump_scale=900, bump=0.3,
                                 pits=1.5)]


def kiwi() -> tuple[Part, Materials]:
    body = sphere(36, 18, radial=lambda v, phi: 1 + 0.02 * np.cos(2 * phi) * np.sin(np.pi * v)).transformed(Z_TO_X)
    return body, lambda: [M.skin("rb_kiwi", _paint.kiwi, roughness=0.95, sheen=0.5, sheen_tint=(0.6, 0.5, 0.35),
                                 bump_scale=1800, bump=0.35,
                                 specular=0.2)]


def pomegranate() -> tuple[Part, Materials]:
    body = sphere(48, 24, radial=lambda v, phi: 1 + 0.02 * np.cos(6 * phi) * np.sin(np.pi * v))
    r, z = smooth_profile([(0.0, 0.36), (0.1, 0.44), (0.13, 0.52), (0.17, 0.63), (0.11, 0.6), (0.06, 0.54),
                           (0.0, 0.53)], 14)

    def star(v, phi):
        return 1 + 0.45 * np.clip(np.cos(6 * phi), 0, None) ** 3 * np.clip((v - 0.4) / 0.4, 0, 1)
    crown = revolve(r, z, 48, radial=star).with_material(1)
    return join([body, crown]), lambda: [
        M.skin("rb_pomegranate", _paint.pomegranate, roughness=0.5, coat=0.1, bump_scale=300, bump=0.08),
        M.plain("rb_pomegranate_crown", (0.45, 0.12, 0.08), roughness=0.7)]


def pear() -> tuple[Part, Materials]:
    r, z = smooth_profile([(0.0, -0.5), (0.3, -0.48), (0.47, -0.33), (0.5, -0.12), (0.43, 0.1), (0.3, 0.3),
                           (0.23, 0.48), (0.2, 0.6), (0.1, 0.66), (0.0, 0.65)], 28)
    body = revolve(r, z, 40, v_coords=np.linspace(0, 1, len(r)))
    stem = _stem((0, 0, 0.6), (0.06, 0.0, 0.84), 0.03, 0.022).with_material(1)
    return join([body, stem]), lambda: [M.skin("rb_pear", _paint.pear, roughness=0.5, bump_scale=400, bump=0.1),
                                        M.plain("rb_pear_stem", (0.3, 0.2, 0.1), roughness=0.8)]


def mango() -> tuple[Part, Materials]:
    r, z, v = _polar_profile(28, lambda t: 0.5 * np.sin(t) * (1 - 0.12 * np.cos(t)), lambda t: -0.5 * np.cos(t))
    body = revolve(r, z, 40, v_coords=v)
    vert = body.vertices.copy()
    vert[:, 1] += 0.14 * (vert[:, 2] / 0.5) ** 2  # kidney bend (sideways once the axis is x)
    vert[:, 0] *= 0.85  # flatter top to bottom
    body = Part(vert, body.corners, body.sizes, body.uvs, body.materials).transformed(Z_TO_X)
    return body, lambda: [M.skin("rb_mango", _paint.mango, roughness=0.4, coat=0.2, bump_scale=300, bump=0.05)]


def banana() -> tuple[Part, Materials]:
    radius_m = 0.16
    ang = np.linspace(-0.62, 0.62, 28)
    arc = np.stack([radius_m * np.sin(ang), radius_m * (1 - np.cos(ang)), np.zeros_like(ang)], 1)
    s = np.linspace(0, 1, len(ang))
    radii = 0.0175 * np.clip(np.sin(np.pi * s), 0, None) ** 0.55 + 0.003
    tangent = arc[-1] - arc[-2]
    tangent /= np.linalg.norm(tangent)
    stalk = arc[-1] + tangent[None, :] * np.linspace(0.004, 0.022, 4)[:, None]
    centres = np.vstack([arc, stalk])
    radii = np.r_[radii, np.full(4, 0.0055)]
    body = sweep(centres, radii, segments=15, cross=lambda a: 1 + 0.06 * np.cos(5 * a))
    return body, lambda: [M.skin("rb_banana", _paint.banana, roughness=0.5, bump_scale=300, bump=0.05)]


def watermelon() -> tuple[Part, Materials]:
    body = sphere(48, 24, radial=lambda v, phi: 1 + 0.01 * np.cos(3 * phi) * np.sin(np.pi * v)).transformed(Z_TO_X)
    return body, lambda: [M.skin("rb_watermelon", _paint.watermelon, roughness=0.5, coat=0.1, specular=0.35, bump_scale=120,
                                 bump=0.05)]


def peach() -> tuple[Part, Materials]:
    r, z, v = _polar_profile(24, lambda t: 0.5 * np.sin(t),
                             lambda t: -0.5 * np.cos(t) - 0.07 * _bump_at(np.pi - t, 0.35) - 0.03 * _bump_at(t, 0.3))

    def crease(vv, phi):
        return 1 - 0.05 * np.exp(-(_wrap(phi) / 0.16) ** 2) * np.sin(np.pi * vv) ** 0.5
    body = revolve(r, z, 48, radial=crease, v_coords=v)
    return body, lambda: [M.skin("rb_peach", _paint.peach, roughness=0.7, sheen=0.6, sheen_tint=(1.0, 0.8, 0.7),
                                 bump_scale=1500, bump=0.15)]


def tomato() -> tuple[Part, Materials]:
    half_h = 0.42

    def fruit_z(t):
        return -half_h * np.cos(t) - 0.05 * _bump_at(np.pi - t, 0.4)
    r, z, v = _polar_profile(24, lambda t: 0.5 * np.sin(t), fruit_z)

    def lobes(vv, phi):
        return 1 + 0.03 * np.cos(5 * phi) * np.clip(vv - 0.3, 0, None) ** 1.5 * 2
    body = revolve(r, z, 60, radial=lobes, v_coords=v)
    # calyx: a thin five-pointed star that follows the top of the fruit
    rr = np.linspace(0.0, 0.24, 7)
    theta = np.pi - np.arcsin(np.clip(rr / 0.5, 0, 1))
    surface = fruit_z(theta)
    prof_r = np.r_[rr, rr[::-1][1:]]
    prof_z = np.r_[surface + 0.004, (surface + 0.022)[::-1][1:]]
    prof_z[-1] = surface[0] + 0.03

    def star(vv, phi):
        return 0.18 + 0.82 * ((1 + np.cos(5 * phi)) / 2) ** 4
    calyx = revolve(prof_r, prof_z, 60, radial=star).with_material(1)
    stem = _stem((0, 0, surface[0] + 0.01), (0.02, 0.0, surface[0] + 0.1), 0.03, 0.025).with_material(1)
    return join([body, calyx, stem]), lambda: [
        M.skin("rb_tomato", _paint.tomato, roughness=0.3, coat=0.2, bump_scale=250, bump=0.03),
        M.plain("rb_tomato_calyx", (0.2, 0.42, 0.12), roughness=0.6)]


def coconut() -> tuple[Part, Materials]:
    body = sphere(40, 20, radial=lambda v, phi: (1 + 0.04 * np.clip(np.cos(3 * phi), 0, None) ** 4
                                                 * np.sin(np.pi * v)))
    vert = body.vertices.copy()
    vert[:, 2] *= 1.0 + 0.06 * vert[:, 2]  # slightly egg-shaped
    body = Part(vert, body.corners, body.sizes, body.uvs, body.materials)
    return body, lambda: [M.skin("rb_coconut", _paint.coconut, roughness=0.9, sheen=0.5, sheen_tint=(0.8, 0.65, 0.5),
                                 bump_scale=900, bump=0.6,
                                 image_bump=0.4)]


# ---------------------------------------------------------------------------------------------
# Balls


def baseball() -> tuple[Part, Materials]:
    return sphere(48, 24), lambda: [M.skin("rb_baseball", _paint.baseball, roughness=0.6, bump_scale=600, bump=0.1,
                                           image_bump=-0.4)]


def tennis_ball() -> tuple[Part, Materials]:
    return sphere(48, 24), lambda: [M.skin("rb_tennis_ball", _paint.tennis_ball, roughness=0.95, sheen=0.8,
                                           sheen_tint=(0.9, 1.0, 0.6),
                                           bump_scale=2500, bump=0.5, image_bump=-0.3)]


def cricket_ball() -> tuple[Part, Materials]:
    return sphere(48, 24), lambda: [M.skin("rb_cricket_ball", _paint.cricket_ball, roughness=0.4, coat=0.15,
                                           bump_scale=400, bump=0.05, image_bump=0.4)]


def bouncy_ball() -> tuple[Part, Materials]:
    return sphere(32, 16), lambda: [M.skin("rb_bouncy_ball", _paint.bouncy_ball, roughness=0.2, coat=0.4,
                                           bump=0.02, variation=0.05)]


def rugby_ball() -> tuple[Part, Materials]:
    r, z, v = _polar_profile(32, lambda t: 0.5 * np.sin(t) * (0.72 + 0.28 * np.sin(t)), lambda t: -0.5 * np.cos(t))
    body = revolve(r, z, 48, v_coords=v).transformed(Z_TO_X)
    return body, lambda: [M.skin("rb_rugby_ball", _paint.rugby_ball, roughness=0.55, bump_scale=1200, bump=0.3,
                                 image_bump=-0.2)]


# ---------------------------------------------------------------------------------------------
# Cans, bottle, toys


def _material_by_height(part: Part, z_lo: float, z_hi: float, inside: int, outside: int) -> Part:
    """Assign ``inside`` to polygons whose centre height lies in [z_lo, z_hi], else ``outside``."""
    starts = np.r_[0, np.cumsum(part.sizes)[:-1]]
    zc = np.add.reduceat(part.vertices[part.corners, 2], starts) / part.sizes
    mats = np.where((zc >= z_lo) & (zc <= z_hi), inside, outside)
    return Part(part.vertices, part.corners, part.sizes, part.uvs, mats, part.smooth)


def _beverage_can(height: float) -> Part:
    """Drawn aluminium can of radius 1 and ``height``: domed base, neck, rim and a recessed lid."""
    h = height
    pts = [(0.0, 0.22), (0.5, 0.16), (0.78, 0.0), (0.9, 0.03), (0.97, 0.15), (1.0, 0.32), (1.0, h - 0.55),
           (0.97, h - 0.35), (0.9, h - 0.2), (0.82, h - 0.08), (0.83, h - 0.01), (0.81, h), (0.78, h - 0.02),
           (0.76, h - 0.1), (0.0, h - 0.1)]
    r, z = np.array(pts).T
    can = revolve(r, z, 48, v_coords=z / h)
    can = _material_by_height(can, 0.3, h - 0.5, 0, 1)
    tab = _tab(h)
    return join([can, tab])


def _tab(h: float) -> Part:
    """Pull tab lying on the lid: a flat plate and its rivet."""
    plate = box((0.55, 0.26, 0.03), offset_m=(0.18, 0.0, h - 0.085))
    rivet = box((0.12, 0.12, 0.04), offset_m=(0.0, 0.0, h - 0.08))
    return join([plate, rivet]).with_material(1)


def red_bull_can() -> tuple[Part, Materials]:
    return _beverage_can(0.135 / 0.0265), lambda: [
        M.skin("rb_energy_can", _paint.energy_can, roughness=0.25, metallic=0.6, bump_scale=300, bump=0.02,
               variation=0.04),
        M.plain("rb_can_metal", (0.85, 0.86, 0.88), roughness=0.22, metallic=1.0, variation=0.05)]


def soda_can() -> tuple[Part, Materials]:
    return _beverage_can(0.115 / 0.033), lambda: [
        M.skin("rb_soda_can", _paint.soda_can, roughness=0.22, metallic=0.55, bump_scale=300, bump=0.02,
               variation=0.04),
        M.plain("rb_can_metal", (0.85, 0.86, 0.88), roughness=0.22, metallic=1.0, variation=0.05)]


def food_can() -> tuple[Part, Materials]:
    h = 0.11 / 0.0375
    pts = [(0.0, 0.04), (0.85, 0.04), (0.92, 0.02), (0.97, 0.0), (1.03, 0.04), (1.03, 0.08), (1.0, 0.12),
           (1.0, h - 0.12), (1.03, h - 0.08), (1.03, h - 0.04), (0.97, h), (0.92, h - 0.02), (0.85, h - 0.04),
           (0.6, h - 0.05), (0.58, h - 0.03), (0.4, h - 0.03), (0.38, h - 0.05), (0.0, h - 0.05)]
    r, z = np.array(pts).T
    can = revolve(r, z, 48, v_coords=z / h)
    can = _material_by_height(can, 0.1, h - 0.1, 0, 1)
    return can, lambda: [M.skin("rb_food_can", _paint.food_can_label, roughness=0.65, bump_scale=300, bump=0.03,
                                variation=0.06),
                         M.plain("rb_tin_metal", (0.78, 0.78, 0.76), roughness=0.3, metallic=1.0, variation=0.05)]


def plastic_bottle() -> tuple[Part, Materials]:
    h = 0.21 / 0.0325
    body_pts = [(0.0, 0.1), (0.55, 0.02), (0.85, 0.0), (0.97, 0.1), (1.0, 0.3)]
    for k in range(4):  # grip ridges
        z0 = 0.6 + 0.28 * k
        body_pts += [(1.0, z0), (0.95, z0 + 0.08), (1.0, z0 + 0.16)]
    body_pts += [(1.0, 3.9), (0.97, 4.3), (0.82, 4.75), (0.58, 5.15), (0.4, 5.45), (0.36, 5.6), (0.48, 5.62),
                 (0.48, 5.68), (0.38, 5.7), (0.43, 5.72), (0.43, h - 0.03), (0.38, h), (0.0, h)]
    r, z = np.array(body_pts).T
    bottle = revolve(r, z, 40, v_coords=np.clip((z - 1.95) / 1.6, 0, 1))
    bottle = _material_by_height(bottle, 1.95, 3.55, 1, 0)
    starts = np.r_[0, np.cumsum(bottle.sizes)[:-1]]
    zc = np.add.reduceat(bottle.vertices[bottle.corners, 2], starts) / bottle.sizes
    bottle.materials[zc > 5.7] = 2
    return bottle, lambda: [M.plain("rb_clear_plastic", (0.92, 0.96, 1.0), roughness=0.04, transmission=1.0,
                                    bump=0.02, variation=0.0),
                            M.skin("rb_bottle_label", _paint.bottle_label, roughness=0.35, bump_scale=300, bump=0.02,
                                   variation=0.04),
                            M.plain("rb_bottle_cap", (0.1, 0.35, 0.85), roughness=0.35, bump=0.2, noise_scale=800)]


def large_dice() -> tuple[Part, Materials]:
    cube = rounded_box((1.0, 1.0, 1.0), 0.14, flat_steps=4, round_steps=3, atlas=True)
    return cube, lambda: [M.skin("rb_die", _paint.die, roughness=0.3, coat=0.15, bump_scale=300, bump=0.6,
                                 image_bump=0.6, variation=0.06)]


def rubiks_cube() -> tuple[Part, Materials]:
    cube = rounded_box((1.0, 1.0, 1.0), 0.05, flat_steps=6, round_steps=2, atlas=True)
    return cube, lambda: [M.skin("rb_puzzle_cube", _paint.puzzle_cube, roughness=0.45, coat=0.2, bump_scale=300,
                                 bump=0.6, image_bump=0.5, variation=0.03, roughness_from_image=-0.3)]


def toy_duck() -> tuple[Part, Materials]:
    body = sphere(36, 18).scaled((1.0, 0.72, 0.58))
    v = body.vertices.copy()
    tail = np.clip(-v[:, 0] - 0.18, 0, None)
    v[:, 2] += 1.2 * tail ** 2 * (1 + 2 * np.clip(v[:, 2], 0, None))  # upturned tail
    v[:, 2] = np.where(v[:, 2] < -0.22, -0.22 + (v[:, 2] + 0.22) * 0.3, v[:, 2])  # flat base
    body = Part(v, body.corners, body.sizes, body.uvs, body.materials)
    head = sphere(28, 14).scaled((0.46, 0.46, 0.44)).transformed(offset=(0.24, 0.0, 0.36)).with_material(3)
    beak = sphere(20, 10).scaled((0.24, 0.2, 0.09)).transformed(offset=(0.46, 0.0, 0.32)).with_material(1)
    eyes = [sphere(10, 6).scaled((0.07, 0.07, 0.07)).transformed(offset=(0.38, s * 0.12, 0.44)).with_material(2)
            for s in (-1, 1)]
    return join([body, head, beak, *eyes]), lambda: [
        M.skin("rb_duck", _paint.duck, roughness=0.3, coat=0.2, bump_scale=300, bump=0.02, variation=0.05),
        M.plain("rb_duck_beak", (0.98, 0.42, 0.05), roughness=0.3),
        M.plain("rb_duck_eye", (0.02, 0.02, 0.02), roughness=0.08, coat=1.0, variation=0.0),
        M.plain("rb_duck_head", (0.94, 0.76, 0.06), roughness=0.3, variation=0.06)]


BUILDERS: dict[str, Callable[[], tuple[Part, list]]] = {
    "apple": apple, "orange": orange, "lemon": lemon, "kiwi": kiwi, "pomegranate": pomegranate, "pear": pear,
    "mango": mango, "banana": banana, "watermelon": watermelon, "baseball": baseball, "bouncy_ball": bouncy_ball,
    "rugby_ball": rugby_ball, "red_bull_can": red_bull_can, "plastic_bottle": plastic_bottle,
    "large_dice": large_dice, "food_can": food_can, "peach": peach, "tomato": tomato, "coconut": coconut,
    "tennis_ball": tennis_ball, "toy_duck": toy_duck, "cricket_ball": cricket_ball, "rubiks_cube": rubiks_cube,
    "soda_can": soda_can,
}


def _generic(obj: ObjectConfig) -> tuple[Part, Materials]:
    """Stand-in primitive with a speckled material for an object id without a dedicated builder."""
    mesh = object_mesh(obj.shape, (1.0, 1.0, 1.0))
    uvs = np.zeros((mesh.faces.size, 2))
    part = Part(mesh.vertices, mesh.faces.reshape(-1), np.full(len(mesh.faces), 3), uvs,
                np.zeros(len(mesh.faces), np.int64), np.full(len(mesh.faces), obj.shape != "box"))
    hue = (sum(map(ord, obj.id)) % 360) / 360.0
    colour = tuple(0.55 + 0.35 * np.cos(2 * np.pi * (hue + k / 3)) for k in range(3))
    return part, lambda: [M.plain(f"rb_generic_{obj.id}", colour, roughness=0.5, noise_scale=150, bump=0.1,
                                          variation=0.35)]


def build_object(obj: ObjectConfig, name: str):
    """A mesh object for ``obj`` named ``name``, bbox centred on the origin and equal to obj.size_m."""
    if obj.mesh_path:
        return load_mesh_object(obj, name)
    builder = BUILDERS.get(obj.id)
    if builder is None:
        log.info("object '%s' (%s) has no procedural builder; using a '%s' stand-in", obj.id, obj.source, obj.shape)
        part, mats = _generic(obj)
    else:
        part, mats = builder()
    ob = to_object(fit(part, obj.size_m), name, mats())
    ob["rb_asset"] = obj.id
    return ob


def object_vertices(obj: ObjectConfig) -> np.ndarray:
    """Vertices (V,3) float64 m of the mesh ``build_object`` makes for ``obj`` (bbox centred, equal to
    obj.size_m), without creating Blender data for procedural objects; a user mesh file is imported
    (needs bpy)."""
    if obj.mesh_path:
        return load_mesh_vertices(obj)
    builder = BUILDERS.get(obj.id)
    part = _generic(obj)[0] if builder is None else builder()[0]
    return np.asarray(fit(part, obj.size_m).vertices, dtype=np.float64)


# ---------------------------------------------------------------------------------------------
# Ramps


def ramp_uvs(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Metric UVs per triangle corner: u along the face's projection of +x (grain), v across. (F*3, 2)."""
    out = np.zeros((faces.size, 2))
    for i, tri in enumerate(faces):
        p = vertices[tri]
        n = np.cross(p[1] - p[0], p[2] - p[0])
        n /= np.linalg.norm(n)
        e_u = np.array([1.0, 0.0, 0.0]) - n * n[0]
        if np.linalg.norm(e_u) < 1e-6:
            e_u = np.array([0.0, 1.0, 0.0]) - n * n[1]
        e_u /= np.linalg.norm(e_u)
        e_v = np.cross(n, e_u)
        out[3 * i: 3 * i + 3] = np.stack([p @ e_u, p @ e_v], 1)
    return out


def build_ramp(shape: RampShape, material: MaterialConfig, name: str):
    """The task wedge of ``shape`` (exactly ``standin.ramp_mesh``) with ``ramp_material(material)``."""
    mesh = ramp_mesh(shape.length_m, shape.height_m, shape.width_m)
    part = Part(mesh.vertices, mesh.faces.reshape(-1).astype(np.int64), np.full(len(mesh.faces), 3, np.int64),
                ramp_uvs(mesh.vertices, mesh.faces), np.zeros(len(mesh.faces), np.int64),
                np.zeros(len(mesh.faces), bool))
    ob = to_object(part, name, [M.ramp_material(material)])
    ob["rb_asset"] = "ramp"
    return ob


__all__ = ["build_object", "object_vertices", "build_ramp", "BUILDERS", "smooth_profile", "ramp_uvs"]
