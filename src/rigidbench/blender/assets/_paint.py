"""Numpy painters for object and decor textures: (H, W, 3) float sRGB in [0, 1], row 0 at the top.

Each painter evaluates a colour function at the 3D point that every texel maps to (a unit
sphere for round objects, a unit cylinder for cans and bottles, cube-face tiles for the die and
the puzzle cube), so patterns are seamless and undistorted at the UV seams. Randomness comes
from fixed seeds; every painter is cached, so a texture is computed once per process.
"""

from __future__ import annotations

import functools

import numpy as np

# ---------------------------------------------------------------------------------------------
# Texel geometry


def sphere_points(h: int, w: int) -> np.ndarray:
    """Unit-sphere point of each texel for sphere UVs (u = azimuth / 2 pi, v = 0 south ... 1 north). (h,w,3)."""
    u = (np.arange(w) + 0.5) / w
    v = 1.0 - (np.arange(h) + 0.5) / h
    phi = 2 * np.pi * u[None, :]
    theta = np.pi * v[:, None]
    rho = np.sin(theta)
    return np.stack([rho * np.cos(phi), rho * np.sin(phi), np.broadcast_to(-np.cos(theta), (h, w))], -1)


def uv_grid(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Texel-centre (u, v), each (h,w), v = 1 at the top row."""
    u = (np.arange(w) + 0.5) / w
    v = 1.0 - (np.arange(h) + 0.5) / h
    return np.broadcast_to(u[None, :], (h, w)), np.broadcast_to(v[:, None], (h, w))


def cylinder_points(h: int, w: int, aspect: float) -> np.ndarray:
    """Point on a unit-radius cylinder of height 2 * ``aspect`` for each texel. (h,w,3)."""
    u, v = uv_grid(h, w)
    phi = 2 * np.pi * u
    return np.stack([np.cos(phi), np.sin(phi), (2 * v - 1) * aspect], -1)


# ---------------------------------------------------------------------------------------------
# Pattern primitives


def fbm(points: np.ndarray, seed: int, freq: float, octaves: int = 4, terms: int = 6) -> np.ndarray:
    """Smooth 3D noise from random sinusoids; points (...,3). Returns (...) roughly in [-1, 1]."""
    rng = np.random.default_rng(seed)
    dirs = rng.normal(size=(octaves * terms, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    phases = rng.uniform(0, 2 * np.pi, octaves * terms)
    octave = np.repeat(np.arange(octaves), terms)
    dirs *= (freq * 2.0 ** octave)[:, None]
    weights = 0.5 ** octave / np.sqrt(terms) / (2 - 0.5 ** (octaves - 1)) * 1.4
    flat = np.ascontiguousarray(points.reshape(-1, 3), dtype=np.float32)
    waves = np.sin(flat @ dirs.T.astype(np.float32) + phases.astype(np.float32))
    return (waves @ weights.astype(np.float32)).reshape(points.shape[:-1]).astype(np.float64)


def smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def blend(base: np.ndarray, colour, weight: np.ndarray) -> np.ndarray:
    """base: (h,w,3); colour: rgb or (h,w,3); weight: (h,w) in [0,1]. Returns (h,w,3)."""
    return base * (1 - weight[..., None]) + np.asarray(colour, float) * weight[..., None]


def fill(h: int, w: int, colour) -> np.ndarray:
    return np.broadcast_to(np.asarray(colour, float), (h, w, 3)).copy()


def fibonacci_sphere(n: int) -> np.ndarray:
    """n roughly evenly spread unit vectors. (n,3)."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(1 - z * z)
    phi = np.pi * (1 + 5 ** 0.5) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def dots(points: np.ndarray, centres: np.ndarray, radius: float, soft: float = 0.5) -> np.ndarray:
    """Soft discs of ``radius`` (chord units) around ``centres`` (N,3). points (h,w,3). Returns (h,w)."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(centres).query(points.reshape(-1, 3))
    d = d.reshape(points.shape[:-1])
    return 1 - smoothstep(radius * (1 - soft), radius, d)


def random_unit(n: int, seed: int) -> np.ndarray:
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def seam_curve(a: float = 0.75, samples: int = 1500) -> np.ndarray:
    """The two-lobed ball seam on the unit sphere (tennis ball / baseball). (samples,3).

    x = a cos t + b cos 3t, y = a sin t - b sin 3t, z = 2 sqrt(ab) sin 2t with a + b = 1 lies
    exactly on the unit sphere.
    """
    b = 1 - a
    t = np.linspace(0, 2 * np.pi, samples, endpoint=False)
    return np.stack([a * np.cos(t) + b * np.cos(3 * t), a * np.sin(t) - b * np.sin(3 * t),
                     2 * np.sqrt(a * b) * np.sin(2 * t)], 1)


def curve_frame(points: np.ndarray, curve: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance (chord units) to a closed curve on the sphere and arc position along it.

    points: (h,w,3); curve: (S,3) closed. Returns (signed_distance (h,w), arc_m (h,w)).
    """
    from scipy.spatial import cKDTree

    flat = points.reshape(-1, 3)
    _, idx = cKDTree(curve).query(flat)
    tangent = np.roll(curve, -1, 0) - np.roll(curve, 1, 0)
    side = np.cross(curve, tangent)
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    offset = flat - curve[idx]
    signed = np.einsum("ij,ij->i", offset, side[idx])
    along = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=1))][idx]
    return signed.reshape(points.shape[:-1]), along.reshape(points.shape[:-1])


# ---------------------------------------------------------------------------------------------
# A tiny 5x7 bitmap font for printed labels


_FONT = {
    "A": "01110 10001 10001 11111 10001 10001 10001", "B": "11110 10001 10001 11110 10001 10001 11110",
    "C": "01110 10001 10000 10000 10000 10001 01110", "D": "11110 10001 10001 10001 10001 10001 11110",
    "E": "11111 10000 10000 11110 10000 10000 11111", "F": "11111 10000 10000 11110 10000 10000 10000",
    "G": "01111 10000 10000 10011 10001 10001 01111", "H": "10001 10001 10001 11111 10001 10001 10001",
    "I": "01110 00100 00100 00100 00100 00100 01110", "K": "10001 10010 10100 11000 10100 10010 10001",
    "L": "10000 10000 10000 10000 10000 10000 11111", "M": "10001 11011 10101 10101 10001 10001 10001",
    "N": "10001 11001 10101 10011 10001 10001 10001", "O": "01110 10001 10001 10001 10001 10001 01110",
    "P": "11110 10001 10001 11110 10000 10000 10000", "Q": "01110 10001 10001 10001 10101 10010 01101",
    "R": "11110 10001 10001 11110 10100 10010 10001", "S": "01111 10000 10000 01110 00001 00001 11110",
    "T": "11111 00100 00100 00100 00100 00100 00100", "U": "10001 10001 10001 10001 10001 10001 01110",
    "V": "10001 10001 10001 10001 10001 01010 00100", "W": "10001 10001 10001 10101 10101 10101 01010",
    "Y": "10001 10001 01010 00100 00100 00100 00100", "Z": "11111 00001 00010 00100 01000 10000 11111",
    "0": "01110 10011 10101 10101 10101 11001 01110", "3": "11110 00001 00001 01110 00001 00001 11110",
    "5": "11111 10000 11110 00001 00001 10001 01110", "%": "11001 11010 00010 00100 01000 01011 10011",
    " ": "00000 00000 00000 00000 00000 00000 00000", "-": "00000 00000 00000 01110 00000 00000 00000",
}


def text_mask(text: str, px: int) -> np.ndarray:
    """Bool mask (7*px, 6*px*len - px) of ``text`` in a 5x7 font scaled by ``px`` pixels per dot."""
    glyphs = []
    for ch in text.upper():
        rows = _FONT[ch].split()
        g = np.array([[c == "1" for c in r] for r in rows], bool)
        glyphs += [g, np.zeros((7, 1), bool)]
    mask = np.concatenate(glyphs[:-1], 1)
    return np.kron(mask, np.ones((px, px), bool))


def stamp(img: np.ndarray, mask: np.ndarray, centre_rc: tuple[int, int], colour, wrap: bool = True) -> None:
    """Paint ``colour`` into img (h,w,3) where ``mask`` is set, centred at (row, col); columns wrap."""
    h, w = img.shape[:2]
    mh, mw = mask.shape
    r0, c0 = centre_rc[0] - mh // 2, centre_rc[1] - mw // 2
    rows = np.arange(mh) + r0
    cols = (np.arange(mw) + c0) % w if wrap else np.arange(mw) + c0
    ok_r = (rows >= 0) & (rows < h)
    ok_c = (cols >= 0) & (cols < w)
    sub = mask[np.ix_(ok_r, ok_c)]
    region = img[np.ix_(rows[ok_r], cols[ok_c])]
    region[sub] = colour
    img[np.ix_(rows[ok_r], cols[ok_c])] = region


# ---------------------------------------------------------------------------------------------
# Fruit and vegetables (sphere UVs unless stated)

# 256 x 512 texels: at paper resolution (1280x704) a 20 cm object spans ~200 px, so half its
# circumference (256 texels) keeps speckles and stripe edges sharp enough for a point tracker
H, W = 256, 512


@functools.cache
def apple() -> np.ndarray:
    p = sphere_points(H, W)
    red, deep, green = np.array([0.66, 0.06, 0.05]), np.array([0.42, 0.03, 0.04]), np.array([0.7, 0.62, 0.2])
    streak = fbm(p * np.array([6.0, 6.0, 0.7]), seed=11, freq=3.0)  # streaks run pole to pole
    patch = fbm(p, seed=12, freq=1.6)
    img = blend(fill(H, W, red), deep, smoothstep(-0.2, 0.7, streak))
    img = blend(img, green, smoothstep(0.45, 0.9, patch) * 0.4)
    img = blend(img, [0.72, 0.62, 0.22], smoothstep(0.85, 0.97, p[..., 2]) * 0.7)  # yellow-green stem cavity
    img = blend(img, [0.55, 0.6, 0.2], smoothstep(-0.85, -0.98, p[..., 2]))
    speck = dots(p, fibonacci_sphere(1400) + 0.02 * random_unit(1400, 13), 0.014)
    return blend(img, [0.88, 0.62, 0.38], speck * 0.55)


@functools.cache
def orange() -> np.ndarray:
    p = sphere_points(H, W)
    n = fbm(p, seed=21, freq=3.0)
    img = blend(fill(H, W, [0.9, 0.4, 0.02]), [0.8, 0.3, 0.0], smoothstep(0.0, 0.8, n) * 0.7)
    img = blend(img, [0.9, 0.46, 0.03], smoothstep(0.2, -0.8, n) * 0.5)
    img = blend(img, [0.35, 0.45, 0.12], smoothstep(0.985, 0.995, p[..., 2]))  # stem scar
    img = blend(img, [0.55, 0.35, 0.1], smoothstep(-0.99, -0.997, p[..., 2]))  # navel
    speck = dots(p, fibonacci_sphere(2400) + 0.015 * random_unit(2400, 22), 0.012)
    return blend(img, [0.74, 0.3, 0.02], speck * 0.7)


@functools.cache
def lemon() -> np.ndarray:
    p = sphere_points(H, W)
    n = fbm(p, seed=31, freq=3.0)
    img = blend(fill(H, W, [0.93, 0.8, 0.04]), [0.88, 0.7, 0.02], smoothstep(0.1, 0.9, n) * 0.7)
    tips = smoothstep(0.86, 0.99, np.abs(p[..., 2]))
    img = blend(img, [0.66, 0.72, 0.18], tips * 0.9)
    speck = dots(p, fibonacci_sphere(2400) + 0.015 * random_unit(2400, 32), 0.012)
    return blend(img, [0.74, 0.58, 0.03], speck * 0.65)


@functools.cache
def kiwi() -> np.ndarray:
    p = sphere_points(H, W)
    n = fbm(p, seed=41, freq=5.0)
    img = blend(fill(H, W, [0.46, 0.34, 0.17]), [0.36, 0.26, 0.12], smoothstep(-0.4, 0.8, n) * 0.8)
    img = blend(img, [0.55, 0.4, 0.2], smoothstep(0.3, -0.9, fbm(p, seed=44, freq=2.0)) * 0.5)
    img = blend(img, [0.22, 0.14, 0.06], smoothstep(0.95, 0.995, np.abs(p[..., 2])))  # dried ends
    hair = fbm(p, seed=45, freq=40.0, octaves=2)  # fine mottling of the fuzz
    img = blend(img, [0.32, 0.22, 0.1], smoothstep(0.15, 0.7, hair) * 0.5)
    speck = dots(p, fibonacci_sphere(3000) + 0.03 * random_unit(3000, 42), 0.01)
    return blend(img, [0.22, 0.14, 0.06], speck * 0.75)


@functools.cache
def pomegranate() -> np.ndarray:
    p = sphere_points(H, W)
    n = fbm(p, seed=51, freq=2.5)
    img = blend(fill(H, W, [0.62, 0.05, 0.08]), [0.42, 0.02, 0.06], smoothstep(-0.1, 0.8, n))
    img = blend(img, [0.7, 0.3, 0.2], smoothstep(0.5, 0.95, fbm(p, seed=52, freq=1.8)) * 0.4)
    img = blend(img, [0.5, 0.2, 0.12], smoothstep(0.88, 0.97, p[..., 2]))  # towards the crown
    img = blend(img, [0.36, 0.02, 0.05], smoothstep(0.2, 0.8, fbm(p, seed=54, freq=12.0, octaves=3)) * 0.35)
    speck = dots(p, fibonacci_sphere(1800) + 0.03 * random_unit(1800, 53), 0.013)
    img = blend(img, [0.28, 0.02, 0.04], speck * 0.7)
    return blend(img, [0.72, 0.42, 0.3], dots(p, random_unit(600, 55), 0.008) * 0.6)  # pale freckles


@functools.cache
def pear() -> np.ndarray:
    p = sphere_points(H, W)
    n = fbm(p, seed=61, freq=2.0)
    img = blend(fill(H, W, [0.72, 0.78, 0.22]), [0.86, 0.8, 0.28], smoothstep(-0.2, 0.8, n))
    img = blend(img, [0.78, 0.38, 0.15], smoothstep(0.55, 0.95, fbm(p, seed=62, freq=1.2)) * 0.6)  # blush
    img = blend(img, [0.55, 0.42, 0.2], smoothstep(0.85, 0.97, p[..., 2]) * 0.7)  # russet at the neck
    speck = dots(p, fibonacci_sphere(1200) + 0.02 * random_unit(1200, 63), 0.014)
    return blend(img, [0.5, 0.38, 0.16], speck * 0.75)


@functools.cache
def mango() -> np.ndarray:
    # revolved about z then turned so z becomes the long x axis; blush on the +x side of the profile
    p = sphere_points(H, W)
    blush = smoothstep(-0.4, 0.8, p[..., 0] + 0.35 * p[..., 2] + 0.25 * fbm(p, seed=71, freq=2.0))
    img = blend(fill(H, W, [0.42, 0.58, 0.14]), [0.92, 0.6, 0.1], smoothstep(-0.9, 0.0, p[..., 0] + 0.4 * p[..., 2]))
    img = blend(img, [0.82, 0.12, 0.12], blush)
    speck = dots(p, fibonacci_sphere(2000) + 0.02 * random_unit(2000, 72), 0.011)
    return blend(img, [0.9, 0.82, 0.45], speck * 0.7)


@functools.cache
def banana() -> np.ndarray:
    """Sweep UVs: u around the tube, v along it (tips at 0 and 1)."""
    u, v = uv_grid(H, W)
    p = np.stack([np.cos(2 * np.pi * u), np.sin(2 * np.pi * u), v * 6.0], -1)
    n = fbm(p, seed=81, freq=2.0)
    img = blend(fill(H, W, [0.92, 0.78, 0.16]), [0.85, 0.68, 0.08], smoothstep(0.0, 0.9, n) * 0.7)
    img = blend(img, [0.62, 0.7, 0.18], smoothstep(0.2, 0.0, v) * 0.8)  # green towards the stalk
    ends = np.maximum(smoothstep(0.07, 0.015, v), smoothstep(0.94, 0.985, v))
    img = blend(img, [0.18, 0.12, 0.05], ends)
    ridges = np.abs(np.cos(2.5 * 2 * np.pi * u))  # faint ridge lines
    img = blend(img, [0.75, 0.6, 0.12], smoothstep(0.97, 1.0, ridges) * 0.5)
    rng = np.random.default_rng(83)
    ang, along = rng.uniform(0, 2 * np.pi, 160), rng.uniform(0.6, 5.4, 160)
    speck = dots(p, np.stack([np.cos(ang), np.sin(ang), along], 1), 0.08)  # sugar spots
    return blend(img, [0.4, 0.25, 0.08], speck * 0.85)


@functools.cache
def watermelon() -> np.ndarray:
    p = sphere_points(H, W)
    u, _ = uv_grid(H, W)
    warp = 0.35 * fbm(p, seed=91, freq=3.0) + 0.15 * fbm(p, seed=92, freq=9.0)
    jag = fbm(p, seed=94, freq=28.0, octaves=3)  # ragged "flame" edges of the stripes
    stripe = np.cos(16 * 2 * np.pi * u + 2.5 * warp + 1.1 * jag)
    # rind: pale-mid green with broad dark green stripes (a photo's rind averages about (60, 110, 45) sRGB)
    light = blend(fill(H, W, [0.3, 0.5, 0.15]), [0.42, 0.58, 0.2], smoothstep(0.0, 0.8, fbm(p, seed=95, freq=6.0)))
    img = blend(light, [0.05, 0.2, 0.05], smoothstep(-0.45, -0.1, stripe))
    veins = smoothstep(0.35, 0.75, fbm(p * np.array([1.0, 1.0, 0.3]), seed=96, freq=14.0))  # mottled veins
    img = blend(img, [0.16, 0.36, 0.1], veins * 0.6)
    img = blend(img, [0.72, 0.7, 0.35], smoothstep(0.7, 0.92, -p[..., 1] + 0.2 * fbm(p, seed=93, freq=2.0))
                * 0.6)  # small yellowish ground spot
    speck = dots(p, fibonacci_sphere(2500) + 0.02 * random_unit(2500, 97), 0.012)
    img = blend(img, [0.55, 0.66, 0.3], speck * 0.5)
    return blend(img, [0.3, 0.3, 0.12], smoothstep(0.97, 0.995, np.abs(p[..., 2])))


@functools.cache
def peach() -> np.ndarray:
    p = sphere_points(H, W)
    blush = smoothstep(-0.5, 0.7, p[..., 0] + 0.3 * fbm(p, seed=101, freq=2.5))
    img = blend(fill(H, W, [0.9, 0.64, 0.3]), [0.84, 0.26, 0.16], blush)
    img = blend(img, [0.65, 0.12, 0.12], smoothstep(0.5, 0.95, p[..., 0] + 0.2 * fbm(p, seed=102, freq=5.0)) * 0.6)
    img = blend(img, [0.78, 0.3, 0.16], smoothstep(0.3, 0.8, fbm(p, seed=104, freq=14.0, octaves=3)) * 0.15)
    speck = dots(p, fibonacci_sphere(2000) + 0.02 * random_unit(2000, 103), 0.011)
    return blend(img, [0.62, 0.16, 0.1], speck * 0.6)


@functools.cache
def tomato() -> np.ndarray:
    p = sphere_points(H, W)
    n = fbm(p, seed=111, freq=2.5)
    img = blend(fill(H, W, [0.8, 0.08, 0.04]), [0.64, 0.04, 0.03], smoothstep(0.0, 0.9, n) * 0.7)
    img = blend(img, [0.9, 0.36, 0.06], smoothstep(0.6, 0.95, p[..., 2]) * 0.45)  # orange shoulders
    img = blend(img, [0.6, 0.03, 0.02], smoothstep(0.2, 0.8, fbm(p, seed=113, freq=14.0, octaves=3)) * 0.4)
    return blend(img, [0.9, 0.58, 0.4], dots(p, fibonacci_sphere(1500) + 0.03 * random_unit(1500, 112), 0.01) * 0.55)


@functools.cache
def coconut() -> np.ndarray:
    p = sphere_points(H, W)
    u, v = uv_grid(H, W)
    rng = np.random.default_rng(121)
    fibres = np.zeros((H, W))
    for k in range(5):  # many thin fibres running pole to pole with random wobble
        freq = rng.uniform(60, 140)
        fibres += np.sin(2 * np.pi * freq * u + 3.0 * fbm(p, seed=122 + k, freq=2.0) + rng.uniform(0, 6.28))
    fibres /= 2.2
    img = blend(fill(H, W, [0.42, 0.27, 0.14]), [0.22, 0.13, 0.06], smoothstep(-0.3, 0.6, fibres))
    img = blend(img, [0.62, 0.46, 0.28], smoothstep(0.6, 1.2, fibres) * 0.8)
    img = blend(img, [0.3, 0.2, 0.1], smoothstep(0.3, 0.9, fbm(p, seed=131, freq=1.5)) * 0.5)
    eyes = np.array([[np.cos(a) * 0.25, np.sin(a) * 0.25, 0.968] for a in (0.0, 2.1, 4.2)])
    return blend(img, [0.09, 0.05, 0.03], dots(p, eyes, 0.09, soft=0.4))


@functools.cache
def duck() -> np.ndarray:
    """Rubber duck body (sphere UVs, +x forward): yellow with moulded wings and a warmer belly."""
    p = sphere_points(H, W)
    img = blend(fill(H, W, [0.94, 0.76, 0.06]), [0.9, 0.62, 0.04], smoothstep(-0.3, -0.8, p[..., 2]))
    ell = ((p[..., 0] + 0.12) / 0.5) ** 2 + ((p[..., 2] - 0.1) / 0.38) ** 2
    side = np.abs(p[..., 1]) > 0.45
    img = blend(img, [0.88, 0.6, 0.04], ((ell < 1.0) & (ell > 0.8) & side).astype(float))
    feathers = side & (ell < 0.8) & (np.abs(np.sin(9 * (p[..., 0] + 0.5 * p[..., 2]))) < 0.12) & (p[..., 0] < 0.1)
    return blend(img, [0.88, 0.62, 0.04], feathers.astype(float))


# ---------------------------------------------------------------------------------------------
# Balls


@functools.cache
def baseball() -> np.ndarray:
    p = sphere_points(H, W)
    img = blend(fill(H, W, [0.8, 0.78, 0.71]), [0.7, 0.68, 0.6], smoothstep(0.2, 0.9, fbm(p, seed=141, freq=3.0)))
    d, s = curve_frame(p, seam_curve(0.75))
    img = blend(img, [0.7, 0.68, 0.6], 1 - smoothstep(0.006, 0.014, np.abs(d)))  # seam groove
    spacing = 2 * np.pi * 1.0 * 1.0 / 54  # ~108 stitches per ball, half per side period
    ad = np.abs(d)
    phase = (s + 0.9 * ad) / spacing
    stitch = (np.abs(phase - np.round(phase)) < 0.16) & (ad > 0.015) & (ad < 0.075)
    return blend(img, [0.78, 0.06, 0.06], stitch.astype(float))


@functools.cache
def tennis_ball() -> np.ndarray:
    p = sphere_points(H, W)
    n = fbm(p, seed=151, freq=6.0)
    img = blend(fill(H, W, [0.78, 0.88, 0.16]), [0.66, 0.78, 0.1], smoothstep(-0.3, 0.9, n) * 0.8)
    d, _ = curve_frame(p, seam_curve(0.68))
    return blend(img, [0.88, 0.88, 0.82], 1 - smoothstep(0.035, 0.05, np.abs(d)))


@functools.cache
def cricket_ball() -> np.ndarray:
    h, w = 256, 512
    p = sphere_points(h, w)
    u, _ = uv_grid(h, w)
    img = blend(fill(h, w, [0.52, 0.04, 0.05]), [0.36, 0.02, 0.03], smoothstep(0.1, 0.9, fbm(p, seed=161, freq=3.0)))
    z = p[..., 2]
    img = blend(img, [0.5, 0.04, 0.04], (np.abs(z) < 0.15).astype(float))  # raised seam band
    img = blend(img, [0.3, 0.02, 0.02], (np.abs(z) < 0.012).astype(float))  # central groove
    phase = u * 180
    dash = np.abs(phase - np.round(phase)) < 0.32
    for offset in (0.035, 0.08, 0.125):
        for sign in (-1, 1):
            img = blend(img, [0.88, 0.85, 0.76], ((np.abs(z - sign * offset) < 0.014) & dash).astype(float))
    quarter = (np.abs(p[..., 0]) < 0.012) & (np.abs(z) > 0.2)  # quarter seams
    img = blend(img, [0.82, 0.72, 0.6], (quarter & (np.abs(np.sin(z * 90)) > 0.3)).astype(float))
    logo = np.array([[0.0, 0.82, 0.55]])
    logo /= np.linalg.norm(logo)
    return blend(img, [0.85, 0.68, 0.25], dots(p, logo, 0.22, soft=0.1) * (1 - dots(p, logo, 0.17, soft=0.1)))


@functools.cache
def bouncy_ball() -> np.ndarray:
    p = sphere_points(H, W)
    ang = np.arctan2(p[..., 1], p[..., 0]) + 3.0 * p[..., 2] + 0.6 * fbm(p, seed=171, freq=1.5)
    band = np.sin(3 * ang)
    img = blend(fill(H, W, [0.95, 0.1, 0.55]), [0.1, 0.6, 0.95], smoothstep(-0.2, 0.2, band))
    img = blend(img, [1.0, 0.85, 0.1], smoothstep(0.75, 0.9, np.sin(3 * ang + 1.0)))
    glitter = dots(p, random_unit(900, 172), 0.012, soft=0.3)
    return blend(img, [1.0, 1.0, 1.0], glitter * 0.7)


@functools.cache
def rugby_ball() -> np.ndarray:
    """Revolved about z (later the long x axis); four panels meet at the tips."""
    p = sphere_points(H, W)
    u, v = uv_grid(H, W)
    img = blend(fill(H, W, [0.86, 0.85, 0.8]), [0.76, 0.75, 0.7], smoothstep(0.3, 0.9, fbm(p, seed=181, freq=4.0)))
    panel = (4 * u) % 1.0
    img = blend(img, [0.12, 0.16, 0.42], ((np.abs(v - 0.28) < 0.045) | (np.abs(v - 0.72) < 0.045)).astype(float))
    img = blend(img, [0.85, 0.12, 0.12], ((np.abs(v - 0.35) < 0.015) | (np.abs(v - 0.65) < 0.015)).astype(float))
    seam = np.minimum(panel, 1 - panel) * 4  # 0 at panel boundaries
    img = blend(img, [0.35, 0.35, 0.33], 1 - smoothstep(0.015, 0.04, seam))
    lace = (u > 0.235) & (u < 0.265) & (np.abs(v - 0.5) < 0.12) & (((v * 90) % 1.0) < 0.5)
    img = blend(img, [1.0, 1.0, 1.0], lace.astype(float))
    mask = text_mask("RUGBY", H // 32)
    stamp(img, mask, (int(H * 0.5), int(W * 0.625)), [0.12, 0.16, 0.42])
    stamp(img, text_mask("PRO", H // 32), (int(H * 0.5), int(W * 0.875)), [0.85, 0.12, 0.12])
    return img


# ---------------------------------------------------------------------------------------------
# Cans and bottles (cylinder UVs: u = angle / 2 pi, v = height fraction)


@functools.cache
def energy_can() -> np.ndarray:
    h, w = 256, 256
    u, v = uv_grid(h, w)
    blue, silver = np.array([0.06, 0.14, 0.55]), np.array([0.8, 0.82, 0.86])
    diamonds = ((np.floor(u * 24) + np.floor(v * 16)) % 2).astype(float)
    img = blend(fill(h, w, silver), [0.64, 0.67, 0.74], diamonds * 0.8)
    img = blend(img, blue, (v > 0.52).astype(float))
    img = blend(img, blue, ((v < 0.12)).astype(float))
    for centre_u in (0.25, 0.75):  # red sun emblem with a yellow ring, twice around the can
        du = (u - centre_u) * 2 * np.pi * 0.5
        dv = (v - 0.55) * 2.55
        r = np.hypot(du, dv)
        img = blend(img, [0.98, 0.8, 0.1], (r < 0.22).astype(float))
        img = blend(img, [0.86, 0.08, 0.1], (r < 0.17).astype(float))
        stamp(img, text_mask("VOLT", 4), (int(h * (1 - 0.8)), int(w * centre_u)), [0.98, 0.8, 0.1])
        stamp(img, text_mask("ENERGY", 3), (int(h * (1 - 0.34)), int(w * centre_u)), [0.06, 0.14, 0.55])
    return img


@functools.cache
def soda_can() -> np.ndarray:
    h, w = 256, 256
    u, v = uv_grid(h, w)
    img = fill(h, w, [0.78, 0.04, 0.06])
    wave = 0.5 + 0.12 * np.sin(2 * np.pi * 2 * u) + 0.03 * np.sin(2 * np.pi * 7 * u)
    img = blend(img, [0.98, 0.97, 0.95], (np.abs(v - wave) < 0.035).astype(float))
    img = blend(img, [0.2, 0.2, 0.22], (np.abs(v - wave - 0.06) < 0.01).astype(float))
    img = blend(img, [0.98, 0.97, 0.95], ((v > 0.9) | (v < 0.08)).astype(float))
    for centre_u in (0.12, 0.62):
        stamp(img, text_mask("FIZZ", 5), (int(h * (1 - 0.72)), int(w * centre_u)), [0.98, 0.97, 0.95])
        stamp(img, text_mask("COLA", 5), (int(h * (1 - 0.27)), int(w * centre_u)), [0.98, 0.85, 0.2])
    return img


@functools.cache
def food_can_label() -> np.ndarray:
    h, w = 256, 256
    u, v = uv_grid(h, w)
    img = fill(h, w, [0.9, 0.85, 0.7])
    img = blend(img, [0.1, 0.42, 0.18], ((v > 0.86) | (v < 0.14)).astype(float))
    img = blend(img, [0.85, 0.68, 0.2], ((np.abs(v - 0.86) < 0.012) | (np.abs(v - 0.14) < 0.012)).astype(float))
    for centre_u in (0.2, 0.7):
        du = (u - centre_u) * 2 * np.pi * 0.5 * 0.68
        dv = (v - 0.45)
        r = np.hypot(du, dv)
        img = blend(img, [0.82, 0.1, 0.06], (r < 0.16).astype(float))  # a tomato on the label
        img = blend(img, [0.95, 0.45, 0.35], (np.hypot(du + 0.05, dv - 0.06) < 0.04).astype(float) * 0.7)
        img = blend(img, [0.15, 0.5, 0.15], (np.hypot(du, dv - 0.16) < 0.035).astype(float))
        stamp(img, text_mask("TOMATO", 3), (int(h * (1 - 0.73)), int(w * centre_u)), [0.7, 0.08, 0.05])
        stamp(img, text_mask("SOUP", 4), (int(h * (1 - 0.22)), int(w * centre_u)), [0.15, 0.15, 0.15])
    bars = (u > 0.42) & (u < 0.5) & (v > 0.25) & (v < 0.6) & (((v * 60) % 1.0) < 0.45)  # barcode side
    img = blend(img, [0.1, 0.1, 0.1], bars.astype(float) * ((u * 300 % 1.0) < 0.6))
    return img


@functools.cache
def bottle_label() -> np.ndarray:
    h, w = 256, 512
    u, v = uv_grid(h, w)
    img = fill(h, w, [0.1, 0.45, 0.85])
    wave = 0.45 + 0.1 * np.sin(2 * np.pi * 3 * u)
    img = blend(img, [0.88, 0.92, 0.95], (v < wave).astype(float))
    img = blend(img, [0.35, 0.75, 0.95], (np.abs(v - wave) < 0.04).astype(float))
    for centre_u in (0.25, 0.75):
        stamp(img, text_mask("AQUA", 8), (int(h * (1 - 0.72)), int(w * centre_u)), [1.0, 1.0, 1.0])
        stamp(img, text_mask("SPRING", 5), (int(h * (1 - 0.25)), int(w * centre_u)), [0.1, 0.3, 0.7])
    return img


# ---------------------------------------------------------------------------------------------
# Cube atlases: 3x2 tiles in the face order +x, -x, +y, -y, +z, -z (see _mesh.rounded_box)

DIE_PIPS = {"+x": 2, "-x": 5, "+y": 3, "-y": 4, "+z": 1, "-z": 6}  # opposite faces sum to 7
_FACE_ORDER = ("+x", "-x", "+y", "-y", "+z", "-z")
_PIP_LAYOUT = {
    1: [(0.5, 0.5)], 2: [(0.27, 0.27), (0.73, 0.73)], 3: [(0.27, 0.27), (0.5, 0.5), (0.73, 0.73)],
    4: [(0.27, 0.27), (0.73, 0.27), (0.27, 0.73), (0.73, 0.73)],
    5: [(0.27, 0.27), (0.73, 0.27), (0.27, 0.73), (0.73, 0.73), (0.5, 0.5)],
    6: [(0.27, 0.27), (0.27, 0.5), (0.27, 0.73), (0.73, 0.27), (0.73, 0.5), (0.73, 0.73)],
}


def _atlas_tiles(tile: int):
    """Yield (face name, row slice, col slice, tu (tile,tile), tv (tile,tile)) of a 3x2 atlas."""
    t = (np.arange(tile) + 0.5) / tile
    tu, tv = np.meshgrid(t, 1 - t)  # tv = 1 at the top row of a tile
    for i, face in enumerate(_FACE_ORDER):
        col, row = i % 3, i // 3
        yield face, slice(row * tile, (row + 1) * tile), slice(col * tile, (col + 1) * tile), tu, tv


@functools.cache
def die() -> np.ndarray:
    tile = 96
    img = fill(2 * tile, 3 * tile, [0.82, 0.81, 0.78])
    for face, rs, cs, tu, tv in _atlas_tiles(tile):
        n = DIE_PIPS[face]
        pip = np.zeros_like(tu)
        for pu, pv in _PIP_LAYOUT[n]:
            r = 0.11 if n > 1 else 0.15
            pip = np.maximum(pip, 1 - smoothstep(r * 0.85, r, np.hypot(tu - pu, tv - pv)))
        colour = [0.04, 0.04, 0.05]
        img[rs, cs] = blend(img[rs, cs], colour, pip)
    return img


CUBE_COLOURS = {"+z": [0.88, 0.88, 0.86], "-z": [0.95, 0.8, 0.0], "+x": [0.8, 0.05, 0.08],
                "-x": [1.0, 0.42, 0.0], "+y": [0.0, 0.3, 0.8], "-y": [0.0, 0.62, 0.28]}


@functools.cache
def puzzle_cube() -> np.ndarray:
    tile = 96
    img = fill(2 * tile, 3 * tile, [0.02, 0.02, 0.02])
    for face, rs, cs, tu, tv in _atlas_tiles(tile):
        # tile coordinates span the whole face; the outer 4% is the rounded edge
        fu, fv = (tu - 0.04) / 0.92 * 3, (tv - 0.04) / 0.92 * 3
        cu, cv = fu - np.floor(fu) - 0.5, fv - np.floor(fv) - 0.5
        inside = (fu > 0) & (fu < 3) & (fv > 0) & (fv < 3)
        corner = np.maximum(np.abs(cu), np.abs(cv))
        rounded = np.hypot(np.maximum(np.abs(cu) - 0.3, 0), np.maximum(np.abs(cv) - 0.3, 0))
        sticker = inside & (corner < 0.42) & (rounded < 0.12)
        img[rs, cs] = blend(img[rs, cs], CUBE_COLOURS[face], sticker.astype(float))
    return img


# ---------------------------------------------------------------------------------------------
# Decor: wall art, the butterfly mural, rug patterns


def _butterfly(shape_h: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """An RGBA-ish butterfly sprite: (colour (s,s,3), alpha (s,s)) with four wing lobes and a body."""
    rng = np.random.default_rng(seed)
    s = shape_h
    y, x = np.mgrid[0:s, 0:s] / (s - 1) * 2 - 1  # [-1, 1], y down
    ax = np.abs(x)
    palette = [([0.98, 0.55, 0.05], [0.1, 0.05, 0.02]), ([0.2, 0.45, 0.95], [0.05, 0.05, 0.15]),
               ([0.95, 0.85, 0.15], [0.15, 0.1, 0.05]), ([0.9, 0.2, 0.45], [0.2, 0.05, 0.1]),
               ([0.35, 0.8, 0.75], [0.05, 0.15, 0.15]), ([0.98, 0.98, 0.95], [0.1, 0.1, 0.1])]
    main, edge = palette[int(rng.integers(len(palette)))]
    upper = ((ax - 0.45) / 0.5) ** 2 + ((y + 0.3) / 0.55) ** 2 < 1
    lower = ((ax - 0.32) / 0.33) ** 2 + ((y - 0.38) / 0.42) ** 2 < 1
    wing = (upper | lower) & (ax > 0.05)
    rim = wing & ~((((ax - 0.45) / 0.4) ** 2 + ((y + 0.3) / 0.45) ** 2 < 1) |
                   (((ax - 0.32) / 0.24) ** 2 + ((y - 0.38) / 0.32) ** 2 < 1))
    spots = ((((ax - 0.55) / 0.1) ** 2 + ((y + 0.35) / 0.1) ** 2 < 1)
             | (((ax - 0.3) / 0.07) ** 2 + ((y - 0.45) / 0.07) ** 2 < 1))
    body = (ax < 0.06) & (np.abs(y) < 0.7)
    col = np.zeros((s, s, 3))
    col[wing] = main
    col[rim] = edge
    col[wing & spots] = [0.98, 0.98, 0.95]
    col[body] = [0.08, 0.06, 0.05]
    return col, (wing | body).astype(float)


@functools.cache
def butterfly_mural(h: int = 512, w: int = 1536) -> np.ndarray:
    """Pale sky wall with leafy vines and 46 butterflies of six palettes, varied size and tilt: two rows of
    large ones low on the wall (0.35-1.6 m up a 2.8 m wall), smaller ones anywhere."""
    from scipy import ndimage

    u, v = uv_grid(h, w)
    cu, cv = uv_grid(h // 8, w // 8)  # the soft background tone is smooth: paint it coarse, then zoom
    p = np.stack([np.cos(2 * np.pi * cu) * 3, np.sin(2 * np.pi * cu) * 3, cv * 3], -1)
    tone = ndimage.zoom(smoothstep(-0.5, 0.8, fbm(p, seed=191, freq=1.0, octaves=2)), 8, order=1)
    img = blend(fill(h, w, [0.86, 0.93, 0.9]), [0.95, 0.92, 0.82], tone[:h, :w])
    for k in range(7):  # swaying green vines, painted in a narrow band of columns
        x0 = (k + 0.5) / 7 + 0.03 * np.sin(k)
        c0, c1 = max(0, int((x0 - 0.05) * w)), min(w, int((x0 + 0.05) * w))
        uu, vv = u[:, c0:c1], v[:, c0:c1]
        path = x0 + 0.03 * np.sin(vv * 9 + k)
        band = img[:, c0:c1]
        band[np.abs(uu - path) < 0.0025] = [0.35, 0.6, 0.35]
        leaves = (np.abs(uu - path - 0.008 * np.sign(np.sin(vv * 60))) < 0.006) & (np.sin(vv * 60 + k) > 0.6)
        band[leaves] = [0.42, 0.7, 0.4]
    rng = np.random.default_rng(192)
    # two staggered rows of large butterflies at ~0.35-1.6 m up a 2.8 m wall (where the benchmark cameras
    # look), then smaller ones anywhere
    n_row = 14
    for k in range(2 * n_row + 18):
        low = k < 2 * n_row
        size = int(rng.integers(64, 104)) if low else int(rng.integers(36, 72))
        col, alpha = _butterfly(size, 300 + k)
        angle = rng.uniform(-0.5, 0.5)
        # rotate the sprite by nearest-neighbour lookup
        yy, xx = np.mgrid[0:size, 0:size] - (size - 1) / 2
        sx = np.clip(np.round(np.cos(angle) * xx + np.sin(angle) * yy + (size - 1) / 2), 0, size - 1).astype(int)
        sy = np.clip(np.round(-np.sin(angle) * xx + np.cos(angle) * yy + (size - 1) / 2), 0, size - 1).astype(int)
        col, alpha = col[sy, sx], alpha[sy, sx]
        if low:
            row, i = divmod(k, n_row)
            centre_r = h * (0.5 if row == 0 else 0.76) + rng.uniform(-0.05, 0.05) * h
            centre_c = (i + 0.5 * row + rng.uniform(0.2, 0.8)) * w / n_row
            r0 = int(np.clip(centre_r - size / 2, 0, h - size))
            c0 = int(np.clip(centre_c - size / 2, 0, w - size))
        else:
            r0, c0 = int(rng.integers(0, h - size)), int(rng.integers(0, w - size))
        region = img[r0:r0 + size, c0:c0 + size]
        img[r0:r0 + size, c0:c0 + size] = region * (1 - alpha[..., None]) + col * alpha[..., None]
    return img


@functools.cache
def abstract_art(seed: int, palette: tuple[tuple[float, float, float], ...], h: int = 256, w: int = 320) -> np.ndarray:
    """Framed-print content: overlapping soft colour fields and arcs from ``palette``."""
    rng = np.random.default_rng(seed)
    u, v = uv_grid(h, w)
    img = fill(h, w, palette[0])
    for k in range(7):
        c = palette[1 + k % (len(palette) - 1)]
        cu, cv, r = rng.uniform(0.1, 0.9), rng.uniform(0.1, 0.9), rng.uniform(0.12, 0.35)
        d = np.hypot((u - cu) * w / h, v - cv)
        if k % 3 == 2:
            img = blend(img, c, (np.abs(d - r) < 0.02).astype(float))
        else:
            img = blend(img, c, 1 - smoothstep(r - 0.01, r, d))
    return img


@functools.cache
def rug_pattern(seed: int, colours: tuple[tuple[float, float, float], ...], h: int = 256, w: int = 384) -> np.ndarray:
    """A bordered rug: field colour, medallion diamonds and a patterned border. UVs span the rug."""
    u, v = uv_grid(h, w)
    field, border, accent, dark = (np.asarray(c, float) for c in colours)
    img = fill(h, w, field)
    edge = np.minimum(np.minimum(u, 1 - u) * w / h, np.minimum(v, 1 - v))
    img = blend(img, border, (edge < 0.14).astype(float))
    img = blend(img, dark, (np.abs(edge - 0.14) < 0.008).astype(float))
    img = blend(img, accent, ((edge < 0.12) & (edge > 0.04) & (np.sin(u * 90) * np.sin(v * 60) > 0.3)).astype(float))
    du, dv = np.abs(u - 0.5) * w / h, np.abs(v - 0.5)
    img = blend(img, accent, ((du + dv < 0.3) & (du + dv > 0.2)).astype(float))
    img = blend(img, dark, ((du + dv < 0.12)).astype(float))
    for cu in (0.25, 0.75):
        dd = np.abs(u - cu) * w / h + np.abs(v - 0.5)
        img = blend(img, border, ((dd < 0.1) & (dd > 0.06)).astype(float))
    p = np.stack([u * 20, v * 14, np.zeros_like(u)], -1)
    return img * (0.93 + 0.07 * fbm(p, seed=seed, freq=1.0, octaves=2))[..., None]


@functools.cache
def pinboard(seed: int, h: int = 192, w: int = 288) -> np.ndarray:
    """A cork board with pinned notes, photos and postcards (scene decor)."""
    rng = np.random.default_rng(seed)
    grain = rng.uniform(-0.06, 0.06, (h, w))
    img = fill(h, w, [0.66, 0.48, 0.3]) * (1 + grain[..., None])
    colours = ([0.98, 0.9, 0.35], [0.95, 0.6, 0.65], [0.55, 0.8, 0.9], [0.97, 0.97, 0.95], [0.6, 0.85, 0.55])
    for k in range(14):
        ph, pw = int(rng.integers(h // 6, h // 3)), int(rng.integers(w // 9, w // 4))
        r0, c0 = int(rng.integers(4, h - ph - 4)), int(rng.integers(4, w - pw - 4))
        if k % 3 == 0:  # a photo: white border round a two-tone scene
            img[r0:r0 + ph, c0:c0 + pw] = [0.96, 0.96, 0.94]
            sky, land = rng.uniform(0.2, 0.9, 3), rng.uniform(0.1, 0.6, 3)
            m = ph // 2
            img[r0 + 3:r0 + m, c0 + 3:c0 + pw - 3] = sky
            img[r0 + m:r0 + ph - 6, c0 + 3:c0 + pw - 3] = land
        else:  # a note with a few lines of writing
            img[r0:r0 + ph, c0:c0 + pw] = colours[k % len(colours)]
            for line in range(r0 + 5, r0 + ph - 3, 5):
                img[line, c0 + 3:c0 + pw - int(rng.integers(3, max(4, pw // 2)))] = [0.25, 0.25, 0.3]
        pin = colours[int(rng.integers(len(colours)))] if k % 2 else [0.85, 0.15, 0.12]
        img[max(r0 - 1, 0):r0 + 3, c0 + pw // 2 - 2:c0 + pw // 2 + 2] = pin
    return np.clip(img, 0.0, 1.0)
