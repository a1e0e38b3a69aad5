"""Furniture and decor as lists of (Part, role) pieces in a local frame, for the scene builder.

Local frame of every item: origin on the floor (or, for wall items, on the wall surface) at the
centre of its footprint, +z up, its front facing -y and its back toward +y (a wall behind it).
A role names the material the scene style assigns ("wood", "fabric", "metal", ...), so one
generator serves every palette. Sizes are metres; randomness comes from the caller's seeded rng.
"""

from __future__ import annotations

import numpy as np

from ._mesh import (Part, box, cylinder, join, polygon_prism, revolve, rot_x, rot_y, rot_z,
                    rounded_box, sphere, sweep)

Pieces = list[tuple[Part, str]]


def B(size, centre) -> Part:
    """Axis-aligned box of ``size`` (3,) centred at ``centre`` (3,)."""
    return box(size, offset_m=centre)


def soft(size, centre, radius: float = 0.04) -> Part:
    """Rounded box (cushions, upholstery), smooth shaded, metric UVs."""
    return rounded_box(size, radius, flat_steps=1, round_steps=2, atlas=False).transformed(offset=centre)


def cyl(radius: float, z0: float, z1: float, x: float = 0.0, y: float = 0.0, segments: int = 16) -> Part:
    return cylinder(radius, z1 - z0, segments).transformed(offset=(x, y, z0))


def quad(width: float, height: float, centre, normal: str = "-y") -> Part:
    """A single rectangle with 0..1 UVs facing ``normal`` ('-y' wall art, '+z' rugs)."""
    w, h = width / 2, height / 2
    if normal == "+z":
        v = np.array([[-w, -h, 0], [w, -h, 0], [w, h, 0], [-w, h, 0]], float)
    else:  # facing -y: x to the right, z up
        v = np.array([[-w, 0, -h], [w, 0, -h], [w, 0, h], [-w, 0, h]], float)
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    return Part(v + np.asarray(centre, float), np.arange(4, dtype=np.int64), np.array([4]), uv,
                np.zeros(1, np.int64), np.zeros(1, bool))


def slab_uv01(size, centre) -> Part:
    """Box whose top face carries 0..1 UVs (a rug or print that shows one whole image)."""
    part = box(size, offset_m=centre)
    uv = part.uvs.copy()
    lo = np.asarray(centre, float) - np.asarray(size, float) / 2
    uv[:, 0] = (uv[:, 0] - lo[0]) / size[0]
    uv[:, 1] = (uv[:, 1] - lo[1]) / size[1]
    return Part(part.vertices, part.corners, part.sizes, uv, part.materials, part.smooth)


# ---------------------------------------------------------------------------------------------
# Tables, counters, storage


def table_base(length: float, width: float, underside_z: float, style: str = "legs", leg: float = 0.06) -> Pieces:
    """Legs/frame under a top of length x width whose underside is at ``underside_z``."""
    L, W, h = length, width, underside_z
    out: Pieces = []
    if style in ("legs", "tapered", "slim"):
        inset = 0.06 + leg / 2
        for sx in (-1, 1):
            for sy in (-1, 1):
                x, y = sx * (L / 2 - inset), sy * (W / 2 - inset)
                if style == "legs":
                    out.append((B((leg, leg, h), (x, y, h / 2)), "leg"))
                else:
                    r0, r1 = (leg / 2, leg / 3.2) if style == "tapered" else (leg / 3, leg / 3)
                    prof = revolve(np.array([0.0, r1, r0, 0.0]), np.array([0.0, 0.0, h, h]), 10)
                    out.append((prof.transformed(offset=(x, y, 0.0)), "leg"))
        apron = 0.09
        out += [(B((L - 2 * inset, 0.02, apron), (0, s * (W / 2 - inset), h - apron / 2)), "leg") for s in (-1, 1)]
        out += [(B((0.02, W - 2 * inset, apron), (s * (L / 2 - inset), 0, h - apron / 2)), "leg") for s in (-1, 1)]
    elif style == "trestle":
        for sx in (-1, 1):
            x = sx * (L / 2 - 0.28)
            out.append((B((0.07, W - 0.2, 0.06), (x, 0, h - 0.03)), "leg"))
            out.append((B((0.07, 0.09, h - 0.1), (x, 0, (h - 0.1) / 2 + 0.04)), "leg"))
            out.append((B((0.08, W - 0.25, 0.05), (x, 0, 0.025)), "leg"))
        out.append((B((L - 0.56, 0.05, 0.06), (0, 0, 0.3)), "leg"))
    elif style == "hairpin":
        for sx in (-1, 1):
            for sy in (-1, 1):
                x, y = sx * (L / 2 - 0.12), sy * (W / 2 - 0.1)
                for dx in (-0.05, 0.05):
                    pts = np.array([[x + dx, y, h], [x + dx * 0.2, y, 0.02]])
                    out.append((sweep(np.linspace(pts[0], pts[1], 3), np.full(3, 0.006), segments=6), "metal"))
    elif style == "pedestal":
        for sx in ((-1, 1) if L > 1.4 else (0,)):
            x = sx * (L / 4)
            out.append((cyl(0.07, 0.04, h, x=x), "leg"))
            out.append((cyl(0.28, 0.0, 0.04, x=x, segments=24), "leg"))
    elif style == "block":
        out.append((B((L - 0.3, W - 0.25, h), (0, 0, h / 2)), "leg"))
    elif style == "frame":  # metal sled frame
        for sx in (-1, 1):
            x = sx * (L / 2 - 0.05)
            out.append((B((0.03, W - 0.1, 0.03), (x, 0, 0.015)), "metal"))
            out.append((B((0.03, W - 0.1, 0.03), (x, 0, h - 0.015)), "metal"))
            for sy in (-1, 1):
                out.append((B((0.03, 0.03, h), (x, sy * (W / 2 - 0.065), h / 2)), "metal"))
    else:
        raise ValueError(f"unknown table base style '{style}'")
    return out


def cabinet_run(length: float, depth: float, height: float, door_w: float = 0.6, toe: float = 0.1,
                handle: str = "bar", drawers: bool = False, legs: bool = False) -> Pieces:
    """Base cabinets (carcass, doors or drawers, handles, plinth or legs) up to ``height``."""
    L, D, H = length, depth, height
    body_z0 = 0.16 if legs else toe
    out: Pieces = [(B((L - 0.01, D - 0.03, H - body_z0), (0, 0.015, body_z0 + (H - body_z0) / 2)), "cabinet")]
    if legs:
        for sx in (-1, 1):
            for sy in (-1, 1):
                out.append((B((0.035, 0.035, body_z0), (sx * (L / 2 - 0.06), sy * (D / 2 - 0.06), body_z0 / 2)),
                            "metal"))
    else:
        out.append((B((L - 0.05, D - 0.1, toe), (0, 0.04, toe / 2)), "plinth"))
    n = max(1, int(round(L / door_w)))
    gap = 0.004
    dw = (L - gap * (n + 1)) / n
    front_y = -(D / 2) + 0.009
    rows = [(body_z0 + gap, H - gap)] if not drawers else [
        (body_z0 + gap, body_z0 + (H - body_z0) * 0.5), (body_z0 + (H - body_z0) * 0.5 + gap, H - gap)]
    for k in range(n):
        x = -L / 2 + gap + dw / 2 + k * (dw + gap)
        for z0, z1 in rows:
            out.append((B((dw, 0.018, z1 - z0 - gap), (x, front_y, (z0 + z1) / 2)), "cabinet_front"))
            if handle == "bar":
                if drawers:
                    out.append((B((min(0.3, dw * 0.5), 0.025, 0.014), (x, front_y - 0.02, z1 - 0.06)), "handle"))
                else:
                    hx = x + (dw / 2 - 0.05) * (1 if k % 2 else -1)
                    out.append((B((0.014, 0.025, 0.22), (hx, front_y - 0.02, z1 - 0.18)), "handle"))
            elif handle == "knob":
                out.append((cyl(0.016, 0, 0.025, segments=10).transformed(rot_x(90), (x, front_y - 0.005, z1 - 0.08)),
                            "handle"))
            elif handle == "edge":  # handleless: a dark finger groove along the top
                out.append((B((dw, 0.02, 0.012), (x, front_y - 0.001, z1 - 0.006)), "plinth"))
    return out


def upper_cabinets(length: float, depth: float, height: float, door_w: float = 0.5, handle: str = "bar") -> Pieces:
    """Wall cabinets, bottom at z=0 of the local frame (the caller lifts them)."""
    out: Pieces = [(B((length, depth - 0.02, height), (0, 0.01, height / 2)), "cabinet")]
    n = max(1, int(round(length / door_w)))
    gap = 0.004
    dw = (length - gap * (n + 1)) / n
    for k in range(n):
        x = -length / 2 + gap + dw / 2 + k * (dw + gap)
        out.append((B((dw, 0.018, height - 2 * gap), (x, -depth / 2 + 0.009, height / 2)), "cabinet_front"))
        if handle == "bar":
            out.append((B((0.014, 0.025, 0.2), (x + (dw / 2 - 0.05) * (1 if k % 2 else -1), -depth / 2 - 0.012,
                                                0.15)), "handle"))
    return out


def open_shelves(length: float, levels: list[float], depth: float = 0.25, thickness: float = 0.04) -> Pieces:
    """Floating wall shelves at heights ``levels`` (m), backs against the wall (local +y)."""
    return [(B((length, depth, thickness), (0, -depth / 2, z)), "wood") for z in levels]


def shelf_items(rng, length: float, z: float, depth: float = 0.25, kinds=("jar", "bowl", "vase", "books")) -> Pieces:
    """A few jars, bowls, vases and book stacks standing on a shelf top at height ``z``."""
    out: Pieces = []
    x = -length / 2 + 0.08
    while x < length / 2 - 0.1:
        kind = kinds[int(rng.integers(len(kinds)))]
        if kind == "jar":
            r, h = rng.uniform(0.04, 0.06), rng.uniform(0.1, 0.2)
            out.append((cyl(r, z, z + h, x=x + r, y=-depth / 2, segments=14), "glass"))
            out.append((cyl(r * 0.9, z + h, z + h + 0.02, x=x + r, y=-depth / 2, segments=14), "wood"))
            x += 2 * r + rng.uniform(0.03, 0.1)
        elif kind == "bowl":
            r = rng.uniform(0.08, 0.12)
            prof = revolve(np.array([0.0, r * 0.5, r, r * 0.9, 0.0]), np.array([0, 0, r * 0.6, r * 0.6, r * 0.1]), 20)
            out.append((prof.transformed(offset=(x + r, -depth / 2, z)), "ceramic"))
            x += 2 * r + rng.uniform(0.03, 0.1)
        elif kind == "vase":
            h = rng.uniform(0.18, 0.32)
            r = h * 0.28
            prof = revolve(np.array([0.0, r * 0.8, r, r * 0.45, r * 0.5, 0.0]),
                           np.array([0.0, 0.0, h * 0.45, h * 0.85, h, h]), 18)
            out.append((prof.transformed(offset=(x + r, -depth / 2, z)), "ceramic2"))
            x += 2 * r + rng.uniform(0.04, 0.12)
        else:
            n = int(rng.integers(3, 6))
            zz = z
            for k in range(n):
                t = rng.uniform(0.025, 0.045)
                out.append((B((rng.uniform(0.16, 0.24), rng.uniform(0.12, 0.17), t),
                              (x + 0.11, -depth / 2, zz + t / 2)), f"book{k % 4}"))
                zz += t
            x += 0.26
    return out


def bookcase(rng, length: float, depth: float, height: float, shelves: int = 4) -> Pieces:
    """Open bookcase with upright books of varied height and colour."""
    t = 0.025
    out: Pieces = [(B((t, depth, height), (s * (length / 2 - t / 2), 0, height / 2)), "shelf") for s in (-1, 1)]
    out.append((B((length, 0.01, height), (0, depth / 2 - 0.005, height / 2)), "shelf"))
    levels = np.linspace(0.05, height - t, shelves + 1)
    for z in levels:
        out.append((B((length - 2 * t, depth, t), (0, 0, z + t / 2)), "shelf"))
    for z0, z1 in zip(levels[:-1], levels[1:]):
        x = -length / 2 + t + 0.01
        room_h = z1 - z0 - t
        while x < length / 2 - t - 0.05:
            if rng.random() < 0.12:
                x += rng.uniform(0.05, 0.15)
                continue
            w = rng.uniform(0.02, 0.045)
            h = room_h * rng.uniform(0.6, 0.92)
            d = depth * rng.uniform(0.7, 0.9)
            out.append((B((w, d, h), (x + w / 2, -depth / 2 + d / 2 + 0.01, z0 + t + h / 2)),
                        f"book{int(rng.integers(4))}"))
            x += w + 0.002
    return out


def cube_shelf(rng, cols: int, rows: int, cell: float = 0.36, depth: float = 0.35) -> Pieces:
    """Modular cube storage with a few coloured inserts and books."""
    t = 0.02
    L, H = cols * cell + t, rows * cell + t
    out: Pieces = []
    for c in range(cols + 1):
        out.append((B((t, depth, H), (-L / 2 + t / 2 + c * cell, 0, H / 2)), "shelf"))
    for r in range(rows + 1):
        out.append((B((L, depth, t), (0, 0, t / 2 + r * cell)), "shelf"))
    for c in range(cols):
        for r in range(rows):
            x, z = -L / 2 + t + c * cell + (cell - t) / 2, t + r * cell
            pick = rng.random()
            if pick < 0.35:
                out.append((soft((cell - 0.05, depth - 0.06, cell - 0.05), (x, -0.02, z + (cell - t) / 2), 0.02),
                            f"accent{int(rng.integers(3))}"))
            elif pick < 0.7:
                xx = x - (cell - t) / 2 + 0.02
                while xx < x + (cell - t) / 2 - 0.06:
                    w, h = rng.uniform(0.02, 0.04), rng.uniform(0.2, 0.3)
                    out.append((B((w, depth * 0.75, h), (xx + w / 2, 0, z + h / 2)), f"book{int(rng.integers(4))}"))
                    xx += w + 0.003
    return out


# ---------------------------------------------------------------------------------------------
# Seating


def chair(style: str = "wood") -> Pieces:
    """Dining chair, seat centre at the origin's (x, y), facing -y."""
    out: Pieces = []
    seat_z = 0.46
    if style == "upholstered":
        out.append((soft((0.48, 0.5, 0.08), (0, 0, seat_z - 0.04), 0.03), "chair_seat"))
        out.append((soft((0.46, 0.07, 0.44), (0, 0.23, seat_z + 0.22), 0.03), "chair_seat"))
        for sx in (-1, 1):
            for sy in (-1, 1):
                out.append((B((0.04, 0.04, seat_z - 0.08), (sx * 0.2, sy * 0.21, (seat_z - 0.08) / 2)), "chair_frame"))
        return out
    leg = 0.035
    for sx in (-1, 1):
        for sy in (-1, 1):
            h = seat_z - 0.03 if sy < 0 else (0.84 if style in ("wood", "japandi") else seat_z)
            out.append((B((leg, leg, h), (sx * 0.2, sy * 0.2, h / 2)), "chair_frame"))
    out.append((B((0.46, 0.44, 0.035), (0, 0, seat_z - 0.015)), "chair_seat" if style != "wood" else "chair_frame"))
    if style == "wood":
        for z in (0.62, 0.72, 0.8):
            out.append((B((0.4, 0.022, 0.05), (0, 0.2, z)), "chair_frame"))
    elif style == "japandi":
        out.append((B((0.4, 0.03, 0.15), (0, 0.2, 0.76)), "chair_seat"))  # back rail shows above a table top
        out.append((B((0.4, 0.022, 0.04), (0, 0.2, 0.6)), "chair_frame"))
    elif style == "metal":
        out.append((B((0.44, 0.025, 0.3), (0, 0.21, 0.7)), "chair_seat"))
        for sx in (-1, 1):
            out.append((B((0.02, 0.02, 0.42), (sx * 0.2, 0.21, 0.66)), "chair_frame"))
    return out


def office_chair() -> Pieces:
    out: Pieces = [(soft((0.5, 0.48, 0.08), (0, 0, 0.46), 0.03), "chair_seat"),
                   (soft((0.46, 0.07, 0.55), (0, 0.24, 0.82), 0.03), "chair_seat"),
                   (cyl(0.025, 0.1, 0.42), "metal"), (B((0.04, 0.04, 0.3), (0, 0.22, 0.55)), "metal")]
    for k in range(5):
        a = 2 * np.pi * k / 5
        spoke = B((0.32, 0.035, 0.03), (0, 0, 0.0))
        out.append((spoke.transformed(rot_z(np.degrees(a)), (0.16 * np.cos(a), 0.16 * np.sin(a), 0.07)), "metal"))
        castor = sphere(8, 4).scaled((0.05, 0.05, 0.05))
        out.append((castor.transformed(offset=(0.3 * np.cos(a), 0.3 * np.sin(a), 0.025)), "plinth"))
    return out


def stool(seat_z: float = 0.65, round_seat: bool = True) -> Pieces:
    out: Pieces = []
    if round_seat:
        out.append((cyl(0.18, seat_z - 0.04, seat_z, segments=24), "chair_seat"))
    else:
        out.append((soft((0.38, 0.34, 0.05), (0, 0, seat_z - 0.025), 0.015), "chair_seat"))
    for k in range(4):
        a = np.pi / 4 + k * np.pi / 2
        top = np.array([0.12 * np.cos(a), 0.12 * np.sin(a), seat_z - 0.04])
        foot = np.array([0.19 * np.cos(a), 0.19 * np.sin(a), 0.0])
        out.append((sweep(np.linspace(foot, top, 3), np.full(3, 0.014), segments=8), "chair_frame"))
    ring = sweep(np.array([[0.16 * np.cos(a), 0.16 * np.sin(a), 0.25] for a in np.linspace(0, 2 * np.pi, 17)]),
                 np.full(17, 0.008), segments=6, caps=False)
    out.append((ring, "chair_frame"))
    return out


def sofa(length: float = 2.2, depth: float = 0.92, cushions: int = 3, legs: str = "metal") -> Pieces:
    L, D = length, depth
    out: Pieces = [(soft((L, D, 0.24), (0, 0, 0.24), 0.04), "sofa"),
                   (soft((L - 0.1, 0.24, 0.5), (0, D / 2 - 0.12, 0.6), 0.06), "sofa")]
    for s in (-1, 1):
        out.append((soft((0.18, D, 0.34), (s * (L / 2 - 0.09), 0, 0.5), 0.06), "sofa"))
    cw = (L - 0.36) / cushions
    for k in range(cushions):
        x = -L / 2 + 0.18 + cw * (k + 0.5)
        out.append((soft((cw - 0.01, D - 0.3, 0.16), (x, -0.1, 0.44), 0.05), "sofa"))
        out.append((soft((cw - 0.04, 0.16, 0.42), (x, D / 2 - 0.3, 0.7), 0.07).transformed(rot_x(-12), (0, 0, 0)),
                    "sofa"))
    for s in (-1, 1):
        out.append((soft((0.42, 0.14, 0.4), (s * (L / 2 - 0.45), D / 2 - 0.42, 0.72), 0.08)
                    .transformed(rot_z(s * 8.0)), "cushion"))
    for sx in (-1, 1):
        for sy in (-1, 1):
            out.append((cyl(0.022, 0.0, 0.12, x=sx * (L / 2 - 0.08), y=sy * (D / 2 - 0.08), segments=8),
                        "metal" if legs == "metal" else "leg"))
    return out


def armchair(width: float = 0.85) -> Pieces:
    return sofa(width, 0.82, cushions=1)[:-6] + [
        (cyl(0.022, 0.0, 0.12, x=sx * (width / 2 - 0.08), y=sy * 0.33, segments=8), "leg")
        for sx in (-1, 1) for sy in (-1, 1)]


def bench_base(length: float, depth: float, underside_z: float) -> Pieces:
    """Hallway bench frame: four legs and a lower shoe shelf (shoes are added by the scene)."""
    out: Pieces = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            out.append((B((0.04, 0.04, underside_z), (sx * (length / 2 - 0.06), sy * (depth / 2 - 0.06),
                                                      underside_z / 2)), "metal"))
    out.append((B((length - 0.1, depth - 0.08, 0.025), (0, 0, 0.12)), "wood"))
    return out


def shoes(rng, n_pairs: int, x0: float, x1: float, z: float) -> Pieces:
    out: Pieces = []
    xs = np.linspace(x0, x1, n_pairs)
    for k, x in enumerate(xs):
        role = f"accent{k % 3}"
        for dx in (-0.055, 0.055):
            out.append((soft((0.095, 0.27, 0.085), (x + dx, rng.uniform(-0.03, 0.03), z + 0.0425), 0.035), role))
    return out


# ---------------------------------------------------------------------------------------------
# Walls: windows, doors, art, hooks, mirrors (local frame on the wall face, +y into the wall)


def window_frame(width: float, height: float, panes: tuple[int, int] = (2, 1), bar: float = 0.05,
                 depth: float = 0.14) -> Pieces:
    """Frame and mullions for an opening of width x height whose bottom-centre is the origin."""
    out: Pieces = [(B((width + 2 * bar, depth, bar), (0, depth / 2 - 0.02, -bar / 2)), "window_frame"),
                   (B((width + 2 * bar, depth, bar), (0, depth / 2 - 0.02, height + bar / 2)), "window_frame")]
    for s in (-1, 1):
        out.append((B((bar, depth, height), (s * (width / 2 + bar / 2), depth / 2 - 0.02, height / 2)), "window_frame"))
    cols, rows = panes
    for c in range(1, cols):
        out.append((B((bar * 0.6, 0.05, height), (-width / 2 + width * c / cols, depth / 2, height / 2)),
                    "window_frame"))
    for r in range(1, rows):
        out.append((B((width, 0.05, bar * 0.6), (0, depth / 2, height * r / rows)), "window_frame"))
    out.append((B((width + 0.12, 0.2, 0.03), (0, -0.04, -0.015)), "window_frame"))  # sill
    return out


def curtains(width: float, height: float, top_z: float) -> Pieces:
    """Two gathered curtain panels either side of a window and a rod."""
    out: Pieces = [(cyl(0.012, 0, width + 0.6, segments=8).transformed(rot_y(90), (-(width + 0.6) / 2, -0.1, top_z)),
                    "metal")]
    for s in (-1, 1):
        x0 = s * (width / 2 + 0.05)
        zs = np.linspace(0.02, top_z - 0.03, 2)
        for k in range(5):
            x = x0 + s * k * 0.07
            centres = np.stack([np.full(2, x), np.full(2, -0.1), zs], 1)
            out.append((sweep(centres, np.full(2, 0.045), segments=10), "curtain"))
    return out


def door(width: float = 0.9, height: float = 2.05) -> Pieces:
    out: Pieces = [(B((width, 0.04, height), (0, -0.02, height / 2)), "door")]
    for s in (-1, 1):
        out.append((B((0.07, 0.03, height + 0.07), (s * (width / 2 + 0.035), -0.015, (height + 0.07) / 2)), "trim"))
    out.append((B((width + 0.14, 0.03, 0.07), (0, -0.015, height + 0.035)), "trim"))
    for z0, z1 in ((0.15, 0.95), (1.1, 1.9)):  # raised panels
        out.append((B((width - 0.24, 0.012, z1 - z0), (0, -0.045, (z0 + z1) / 2)), "door"))
    out.append((sphere(10, 6).scaled((0.06, 0.06, 0.06)).transformed(offset=(width / 2 - 0.09, -0.09, 1.0)),
                "handle"))
    return out


def picture(width: float, height: float, frame: float = 0.04, art_role: str = "art0") -> Pieces:
    """Framed print, centre at the origin, hung on the wall (back at y=0)."""
    out: Pieces = [(quad(width, height, (0, -0.021, 0)), art_role)]
    for s in (-1, 1):
        out.append((B((frame, 0.03, height + 2 * frame), (s * (width / 2 + frame / 2), -0.015, 0)), "frame"))
        out.append((B((width, 0.03, frame), (0, -0.015, s * (height / 2 + frame / 2))), "frame"))
    return out


def round_mirror(radius: float) -> Pieces:
    ring = cylinder(radius + 0.03, 0.03, 32).transformed(rot_x(90), (0, 0.0, 0))
    glass = cylinder(radius, 0.005, 32).transformed(rot_x(90), (0, -0.03, 0))
    return [(ring, "frame"), (glass, "mirror")]


def coat_rail(rng, length: float, hooks: int) -> Pieces:
    """A wooden rail with hooks and a few hanging coats and bags (rail centre at the origin)."""
    out: Pieces = [(B((length, 0.025, 0.12), (0, -0.0125, 0)), "wood")]
    xs = np.linspace(-length / 2 + 0.15, length / 2 - 0.15, hooks)
    for k, x in enumerate(xs):
        out.append((B((0.015, 0.07, 0.015), (x, -0.06, 0.02)), "metal"))
        pick = k % 3
        if pick == 0:  # long coat: narrow shoulders widening to the hem, with a collar
            outline = np.array([[-0.25, -0.95], [0.25, -0.95], [0.21, -0.12], [0.12, -0.02], [-0.12, -0.02],
                                [-0.21, -0.12]])
            body = polygon_prism(outline, -0.05, 0.05).transformed(rot_x(90.0), (x, -0.12, 0.0))
            role = f"accent{(k // 3) % 2}"
            out.append((body, role))
            out.append((soft((0.18, 0.1, 0.1), (x, -0.1, 0.0), 0.04), role))
            for s in (-1, 1):
                out.append((soft((0.07, 0.08, 0.62), (x + s * 0.22, -0.13, -0.4), 0.03), role))
        elif pick == 1:  # tote bag
            out.append((soft((0.3, 0.08, 0.34), (x, -0.09, -0.25), 0.02), "accent1"))
        else:  # scarf
            out.append((soft((0.12, 0.05, 0.6), (x, -0.07, -0.28), 0.025), "accent2"))
    return out


def wainscot(length: float, height: float = 0.95, panel: float = 0.6) -> Pieces:
    """Raised panel mouldings and a chair rail on the lower wall (back at y=0)."""
    out: Pieces = [(B((length, 0.03, 0.05), (0, -0.015, height)), "trim"),
                   (B((length, 0.02, 0.12), (0, -0.01, 0.06)), "trim")]
    n = max(1, int(length / panel))
    w = length / n
    for k in range(n):
        x = -length / 2 + w * (k + 0.5)
        z0, z1 = 0.2, height - 0.12
        for s in (-1, 1):
            out.append((B((0.025, 0.015, z1 - z0), (x + s * (w / 2 - 0.08), -0.0075, (z0 + z1) / 2)), "trim"))
            out.append((B((w - 0.16, 0.015, 0.025), (x, -0.0075, z0 if s < 0 else z1)), "trim"))
    return out


# ---------------------------------------------------------------------------------------------
# Plants, lamps, decor


def plant(rng, pot_r: float = 0.16, pot_h: float = 0.35, height: float = 1.2, kind: str = "bush") -> Pieces:
    """A potted plant: tapered pot, soil and leaves ('bush', 'tall' or 'palm')."""
    out: Pieces = [(revolve(np.array([0.0, pot_r * 0.75, pot_r, pot_r * 0.95, 0.0]),
                            np.array([0.0, 0.0, pot_h, pot_h, pot_h - 0.02]), 20), "pot")]
    top = pot_h
    if kind == "bush":
        for k in range(14):
            a = rng.uniform(0, 2 * np.pi)
            r = rng.uniform(0.0, pot_r * 1.4)
            z = top + rng.uniform(0.05, height * 0.55)
            s = rng.uniform(0.16, 0.26) * height / 1.0
            out.append((sphere(10, 6).scaled((s, s * 0.9, s * 0.8)).transformed(
                offset=(r * np.cos(a), r * np.sin(a), z)), "leaves"))
    else:
        n = 16 if kind == "tall" else 12
        for k in range(n):
            a = 2 * np.pi * k / n + rng.uniform(-0.2, 0.2)
            tilt = rng.uniform(20, 65) if kind == "tall" else rng.uniform(35, 75)
            length = rng.uniform(0.25, 0.4) if kind == "tall" else rng.uniform(0.5, 0.8) * height / 1.2
            width = length * (0.45 if kind == "tall" else 0.12)
            z = top + (rng.uniform(0.2, height * 0.8) if kind == "tall" else rng.uniform(0.0, 0.15))
            leaf = sphere(12, 6).scaled((length, width, 0.012)).transformed(offset=(length / 2, 0, 0))
            leaf = leaf.transformed(rot_y(-tilt)).transformed(rot_z(np.degrees(a)), (0, 0, z))
            out.append((leaf, "leaves"))
            if kind == "tall":
                out.append((sweep(np.array([[0, 0, top], [0.3 * np.cos(a) * 0.1, 0.3 * np.sin(a) * 0.1, z]]),
                                  np.full(2, 0.008), segments=5), "wood"))
    return out


def floor_lamp(height: float = 1.6, shade_r: float = 0.22) -> Pieces:
    return [(cyl(0.15, 0.0, 0.03, segments=20), "metal"), (cyl(0.012, 0.03, height - 0.2, segments=8), "metal"),
            (revolve(np.array([shade_r, shade_r * 0.7]), np.array([height - 0.3, height]), 24), "shade")]


def table_lamp(height: float = 0.5) -> Pieces:
    return [(revolve(np.array([0.0, 0.08, 0.1, 0.04, 0.02, 0.0]), np.array([0, 0, 0.12, 0.25, 0.3, 0.3]), 16),
             "ceramic2"),
            (revolve(np.array([0.16, 0.11]), np.array([height - 0.2, height]), 20), "shade")]


def pendant(drop: float, shape: str = "dome", radius: float = 0.2) -> Pieces:
    """Ceiling pendant hanging ``drop`` metres below the local origin (the ceiling point)."""
    out: Pieces = [(cyl(0.004, -drop + radius * 0.5, 0.0, segments=6), "metal")]
    if shape == "dome":
        r = np.array([0.02, 0.03, radius * 0.6, radius * 0.95, radius])
        z = np.array([0.0, -0.02, -radius * 0.25, -radius * 0.6, -radius * 0.7])
        out.append((revolve(r, z, 24).transformed(offset=(0, 0, -drop + radius * 0.7)), "lamp_metal"))
        out.append((sphere(10, 6).scaled((0.07, 0.07, 0.07)).transformed(offset=(0, 0, -drop + 0.04)), "shade"))
    elif shape == "globe":
        out.append((sphere(20, 10).scaled((2 * radius,) * 3).transformed(offset=(0, 0, -drop)), "shade"))
        out.append((cyl(0.04, -drop + radius * 0.9, -drop + radius * 1.05, segments=12), "lamp_metal"))
    elif shape == "lantern":  # paper lantern
        prof_r = radius * np.sin(np.linspace(0.15, np.pi - 0.15, 9))
        prof_z = -drop - radius * np.cos(np.linspace(0.15, np.pi - 0.15, 9))
        out.append((revolve(prof_r, prof_z, 24), "shade"))
    elif shape == "cone":
        out.append((revolve(np.array([0.02, radius]), np.array([-drop + radius * 1.2, -drop]), 20), "lamp_metal"))
        out.append((sphere(8, 4).scaled((0.06, 0.06, 0.06)).transformed(offset=(0, 0, -drop + 0.04)), "shade"))
    return out


def chandelier(drop: float, arms: int = 6, radius: float = 0.45) -> Pieces:
    out: Pieces = [(cyl(0.01, -drop + 0.1, 0.0, segments=6), "metal"),
                   (sphere(12, 6).scaled((0.12, 0.12, 0.16)).transformed(offset=(0, 0, -drop + 0.05)), "metal")]
    for k in range(arms):
        a = 2 * np.pi * k / arms
        tip = np.array([radius * np.cos(a), radius * np.sin(a), -drop + 0.12])
        pts = np.array([[0, 0, -drop + 0.02], [tip[0] * 0.6, tip[1] * 0.6, -drop - 0.04], tip])
        out.append((sweep(pts, np.full(3, 0.01), segments=6), "metal"))
        out.append((cyl(0.035, tip[2], tip[2] + 0.03, tip[0], tip[1], 10), "metal"))
        out.append((cyl(0.012, tip[2] + 0.03, tip[2] + 0.14, tip[0], tip[1], 8), "candle"))
        out.append((sphere(6, 4).scaled((0.025, 0.025, 0.05)).transformed(offset=(tip[0], tip[1], tip[2] + 0.17)),
                    "shade"))
    return out


def vase_with_stems(rng, height: float = 0.45) -> Pieces:
    r = 0.07
    out: Pieces = [(revolve(np.array([0.0, r * 0.8, r, r * 0.5, r * 0.6, 0.0]),
                            np.array([0, 0, height * 0.3, height * 0.5, height * 0.55, height * 0.55]), 18),
                    "ceramic2")]
    for k in range(5):
        a = rng.uniform(0, 2 * np.pi)
        tip = np.array([0.12 * np.cos(a), 0.12 * np.sin(a), height * 0.55 + rng.uniform(0.2, 0.4)])
        out.append((sweep(np.array([[0, 0, height * 0.3], tip * [0.5, 0.5, 1] + [0, 0, -0.05], tip]),
                          np.full(3, 0.005), segments=5), "wood"))
        out.append((sphere(8, 4).scaled((0.06, 0.06, 0.05)).transformed(offset=tuple(tip)), "leaves"))
    return out


def fireplace(width: float = 1.5, height: float = 1.15, depth: float = 0.35) -> Pieces:
    out: Pieces = [(B((width, depth, 0.12), (0, -depth / 2, height - 0.06)), "stone"),
                   (B((width + 0.2, depth + 0.08, 0.05), (0, -depth / 2 - 0.04, height + 0.025)), "wood"),
                   (B((width + 0.3, depth + 0.3, 0.05), (0, -depth / 2 - 0.15, 0.025)), "stone")]
    for s in (-1, 1):
        out.append((B((0.3, depth, height - 0.12), (s * (width / 2 - 0.15), -depth / 2, (height - 0.12) / 2)),
                    "stone"))
    out.append((B((width - 0.6, 0.02, height - 0.12), (0, -0.01, (height - 0.12) / 2)), "soot"))
    for k in range(3):
        log = cylinder(0.05, width - 0.8, 10)
        out.append((log.transformed(rot_y(90), (-(width - 0.8) / 2, -depth / 2 + 0.05 * k, 0.1 + 0.06 * (k % 2))),
                    "wood"))
    out.append((sphere(12, 6).scaled((width - 0.8, 0.1, 0.25)).transformed(offset=(0, -depth / 2, 0.22)), "fire"))
    return out


def fridge(width: float = 0.75, height: float = 2.0, depth: float = 0.66) -> Pieces:
    return [(B((width, depth, height), (0, 0, height / 2)), "appliance"),
            (B((0.02, 0.04, 0.7), (-width / 2 + 0.06, -depth / 2 - 0.03, 1.2)), "handle"),
            (B((0.02, 0.04, 0.4), (-width / 2 + 0.06, -depth / 2 - 0.03, 0.55)), "handle"),
            (B((width - 0.01, 0.01, 0.005), (0, -depth / 2 - 0.003, 0.85)), "plinth")]


def range_hood(width: float = 0.9, bottom_z: float = 1.55, top_z: float = 2.8) -> Pieces:
    return [(B((width, 0.5, 0.12), (0, -0.25, bottom_z + 0.06)), "appliance"),
            (B((0.32, 0.28, top_z - bottom_z - 0.12), (0, -0.14, (top_z + bottom_z + 0.12) / 2)), "appliance")]


def oven_front(width: float = 0.6, z0: float = 0.15, z1: float = 0.8, front_y: float = -0.3) -> Pieces:
    return [(B((width - 0.01, 0.02, z1 - z0), (0, front_y - 0.01, (z0 + z1) / 2)), "appliance"),
            (B((width - 0.12, 0.01, (z1 - z0) * 0.5), (0, front_y - 0.022, z0 + (z1 - z0) * 0.45)), "screen"),
            (B((width - 0.12, 0.04, 0.02), (0, front_y - 0.04, z1 - 0.06)), "handle")]


def tv(width: float = 1.3) -> Pieces:
    h = width * 9 / 16
    return [(B((width, 0.04, h), (0, -0.02, 0)), "plinth"), (quad(width - 0.02, h - 0.02, (0, -0.041, 0)), "screen")]


def pouf(radius: float = 0.25, height: float = 0.4) -> Pieces:
    r = np.array([0.0, radius * 0.9, radius, radius, radius * 0.9, 0.0])
    z = np.array([0.0, 0.0, 0.05, height - 0.06, height, height])
    return [(revolve(r, z, 24), "accent0")]


def floor_cushion(size: float = 0.6) -> Pieces:
    return [(soft((size, size, 0.14), (0, 0, 0.07), 0.06), "accent1")]


def sun_lounger() -> Pieces:
    out: Pieces = [(soft((1.9, 0.62, 0.1), (0, 0, 0.32), 0.04), "cushion")]
    out.append((soft((0.62, 0.1, 0.7), (0.0, 0.0, 0.0), 0.04).transformed(rot_x(0), (0, 0, 0))
                .transformed(rot_z(90)).transformed(rot_y(-55), (-0.78, 0.0, 0.6)), "cushion"))
    for sx in (-1, 1):
        for sy in (-1, 1):
            out.append((B((0.05, 0.05, 0.27), (sx * 0.85, sy * 0.26, 0.135)), "wood"))
    out.append((B((1.9, 0.05, 0.06), (0, 0.3, 0.25)), "wood"))
    out.append((B((1.9, 0.05, 0.06), (0, -0.3, 0.25)), "wood"))
    return out


def palm_tree(rng, height: float = 5.0, lean=(0.6, 0.2)) -> Pieces:
    t = np.linspace(0, 1, 10)[:, None]
    trunk = np.hstack([lean[0] * t ** 2, lean[1] * t ** 2, height * t])
    out: Pieces = [(sweep(trunk, np.linspace(0.18, 0.11, 10), segments=10), "trunk")]
    top = trunk[-1]
    for k in range(11):
        a = 2 * np.pi * k / 11 + rng.uniform(-0.15, 0.15)
        droop = rng.uniform(-35, 15)
        length = rng.uniform(1.8, 2.6)
        frond = sphere(16, 6).scaled((length, 0.42, 0.03)).transformed(offset=(length / 2, 0, 0))
        frond = frond.transformed(rot_y(-droop)).transformed(rot_z(np.degrees(a)), tuple(top))
        out.append((frond, "leaves"))
    for k in range(4):
        a = 2 * np.pi * k / 4
        out.append((sphere(8, 6).scaled((0.16, 0.16, 0.18)).transformed(
            offset=(top[0] + 0.12 * np.cos(a), top[1] + 0.12 * np.sin(a), top[2] - 0.2)), "coconut"))
    return out


def hip_roof(half_x: float, half_y: float, eave_z: float, ridge_z: float, thickness: float = 0.08) -> Part:
    """Four-sided pyramid roof over [-half_x, half_x] x [-half_y, half_y], with a soffit underneath."""
    ridge = max(half_x - half_y, 0.0)
    v = np.array([[-half_x, -half_y, eave_z], [half_x, -half_y, eave_z], [half_x, half_y, eave_z],
                  [-half_x, half_y, eave_z], [-ridge, 0.0, ridge_z], [ridge, 0.0, ridge_z],
                  [-half_x, -half_y, eave_z - thickness], [half_x, -half_y, eave_z - thickness],
                  [half_x, half_y, eave_z - thickness], [-half_x, half_y, eave_z - thickness]], float)
    polys = [[0, 1, 5, 4], [1, 2, 5], [2, 3, 4, 5], [3, 0, 4], [6, 9, 8, 7],
             [0, 6, 7, 1], [1, 7, 8, 2], [2, 8, 9, 3], [3, 9, 6, 0]]
    corners = np.concatenate([np.array(p) for p in polys]).astype(np.int64)
    sizes = np.array([len(p) for p in polys], np.int64)
    uvs = v[corners][:, [0, 1]] + v[corners][:, [2, 2]] * np.array([0.0, 1.0])
    return Part(v, corners, sizes, uvs, np.zeros(len(polys), np.int64), np.zeros(len(polys), bool))


def combine(pieces: Pieces, offset=(0.0, 0.0, 0.0), rot_deg: float = 0.0) -> Pieces:
    """Pieces moved by a rotation about z then an offset (to nest sub-assemblies)."""
    m = rot_z(rot_deg)
    return [(p.transformed(m, offset), role) for p, role in pieces]


__all__ = ["Pieces", "B", "soft", "cyl", "quad", "slab_uv01", "combine", "join"]


def utensil_rail(rng, length: float) -> Pieces:
    """A wall rail with hanging utensils and mugs, all within 4.5 cm of the wall (local +y), centred at z=0."""
    out: Pieces = [(B((length, 0.012, 0.012), (0, -0.025, 0)), "handle")]
    for s in (-1, 1):
        out.append((B((0.02, 0.03, 0.03), (s * (length / 2 - 0.02), -0.015, 0)), "handle"))
    x = -length / 2 + 0.1
    k = 0
    while x < length / 2 - 0.1:
        if k % 4 == 3:  # a cutting board on a hook
            out.append((B((0.2, 0.015, 0.3), (x + 0.05, -0.012, -0.17)), "wood"))
            x += 0.1
        else:
            h = float(rng.uniform(0.2, 0.3))
            out.append((B((0.014, 0.01, h), (x, -0.03, -h / 2 - 0.01)), "wood"))
            out.append((B((0.06, 0.008, 0.08), (x, -0.03, -h - 0.04)), "wood" if k % 2 else "handle"))
        x += float(rng.uniform(0.13, 0.2))
        k += 1
    return out
