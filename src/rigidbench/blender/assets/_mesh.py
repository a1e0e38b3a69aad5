"""Numpy mesh parts (vertices, polygons, per-corner UVs, material slots) and their bpy conversion.

Every generator returns a ``Part`` in metres. Parts are joined, transformed and fitted in numpy
and turned into one bpy mesh at the end, which keeps object building to a few milliseconds.
UV conventions: surfaces of revolution use u = angle / 2 pi about their axis and v = position
along the axis (0 at the start of the profile, 1 at its end); boxes use metric projections.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np


@dataclass
class Part:
    """A polygon mesh: vertices (V,3) m, polygons as flat corner indices + sizes, UV per corner."""

    vertices: np.ndarray  # (V,3) float64
    corners: np.ndarray  # (C,) int64 vertex index of each polygon corner, polygons in order
    sizes: np.ndarray  # (F,) int64 corners per polygon
    uvs: np.ndarray  # (C,2) float64
    materials: np.ndarray  # (F,) int64 material slot per polygon
    smooth: np.ndarray = field(default=None)  # (F,) bool smooth shading per polygon

    def __post_init__(self) -> None:
        if self.smooth is None:
            self.smooth = np.ones(len(self.sizes), bool)

    def with_material(self, slot: int) -> "Part":
        """Same part with every polygon in material ``slot``."""
        return Part(self.vertices, self.corners, self.sizes, self.uvs, np.full(len(self.sizes), slot), self.smooth)

    def flat(self) -> "Part":
        """Same part with flat shading (hard edges, e.g. boxes)."""
        return Part(self.vertices, self.corners, self.sizes, self.uvs, self.materials, np.zeros(len(self.sizes), bool))

    def transformed(self, matrix: np.ndarray | None = None, offset=(0.0, 0.0, 0.0)) -> "Part":
        """Vertices mapped by ``matrix`` (3,3) then shifted by ``offset`` (m)."""
        v = self.vertices if matrix is None else self.vertices @ np.asarray(matrix, float).T
        return Part(v + np.asarray(offset, float), self.corners, self.sizes, self.uvs, self.materials, self.smooth)

    def scaled(self, factors) -> "Part":
        """Vertices scaled per axis by ``factors`` (3,)."""
        return Part(self.vertices * np.asarray(factors, float), self.corners, self.sizes, self.uvs, self.materials,
                    self.smooth)


def rot_x(deg: float) -> np.ndarray:
    """(3,3) rotation about +x by ``deg`` degrees."""
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(deg: float) -> np.ndarray:
    """(3,3) rotation about +y by ``deg`` degrees."""
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(deg: float) -> np.ndarray:
    """(3,3) rotation about +z by ``deg`` degrees."""
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


Z_TO_X = rot_y(90.0)  # maps a z-axis surface of revolution onto the +x long axis (z -> x, x -> -z)


def join(parts: Sequence[Part]) -> Part:
    """One part holding all ``parts`` (indices offset; materials and UVs kept)."""
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
    return Part(np.concatenate([p.vertices for p in parts]),
                np.concatenate([p.corners + o for p, o in zip(parts, offsets)]),
                np.concatenate([p.sizes for p in parts]),
                np.concatenate([p.uvs for p in parts]),
                np.concatenate([p.materials for p in parts]),
                np.concatenate([p.smooth for p in parts]))


def weld(part: Part, tol_m: float = 1e-7) -> Part:
    """Merge vertices closer than ``tol_m`` (grid-rounded); corner UVs are untouched."""
    keys = np.round(part.vertices / tol_m).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    return Part(part.vertices[first], inverse.reshape(-1)[part.corners], part.sizes, part.uvs, part.materials,
                part.smooth)


def bbox(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """vertices: (V,3). Returns (lo, hi) corners, each (3,)."""
    return vertices.min(0), vertices.max(0)


def fit(part: Part, size_m) -> Part:
    """Centre the bounding box on the origin and scale each axis so it equals ``size_m`` (3,)."""
    lo, hi = bbox(part.vertices)
    extent = np.where(hi - lo > 0, hi - lo, 1.0)
    v = (part.vertices - (lo + hi) / 2) / extent * np.asarray(size_m, float)
    return Part(v, part.corners, part.sizes, part.uvs, part.materials, part.smooth)


# ---------------------------------------------------------------------------------------------
# Generators


def revolve(profile_r: np.ndarray, profile_z: np.ndarray, segments: int = 32,
            radial: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
            v_coords: np.ndarray | None = None) -> Part:
    """Surface of revolution about +z. profile_r, profile_z: (K,) m from bottom to top.

    A profile point with r == 0 at either end becomes a pole (triangle fan); ``radial(v, phi)``
    ((K,1),(1,S) -> (K,S)) multiplies the radius, e.g. for lobes, creases or dimples. UV: u =
    phi / 2 pi, v = ``v_coords`` (default: normalised arc length of the profile).
    """
    r = np.asarray(profile_r, float)
    z = np.asarray(profile_z, float)
    if v_coords is None:
        arc = np.r_[0.0, np.cumsum(np.hypot(np.diff(r), np.diff(z)))]
        v_coords = arc / arc[-1]
    v_coords = np.asarray(v_coords, float)
    bottom_pole, top_pole = r[0] <= 1e-12, r[-1] <= 1e-12
    ring_idx = np.arange(len(r))[int(bottom_pole): len(r) - int(top_pole)]
    phi = 2 * np.pi * np.arange(segments) / segments
    scale = np.ones((len(r), segments)) if radial is None else \
        np.broadcast_to(radial(v_coords[:, None], phi[None, :]), (len(r), segments))
    rr = r[ring_idx, None] * scale[ring_idx]
    ring_verts = np.stack([rr * np.cos(phi), rr * np.sin(phi), np.repeat(z[ring_idx, None], segments, 1)], -1)
    verts = [ring_verts.reshape(-1, 3)]
    n_rings = len(ring_idx)
    corners, uvs = [], []
    j = np.arange(segments)
    u0, u1 = j / segments, (j + 1) / segments
    for k in range(n_rings - 1):  # quads between ring k and k+1, counter-clockwise seen from outside
        a, b = k * segments + j, k * segments + (j + 1) % segments
        c, d = a + segments, b + segments
        corners.append(np.stack([a, b, d, c], 1))
        vk, vk1 = v_coords[ring_idx[k]], v_coords[ring_idx[k + 1]]
        uvs.append(np.stack([np.stack([u0, np.full_like(u0, vk)], 1), np.stack([u1, np.full_like(u0, vk)], 1),
                             np.stack([u1, np.full_like(u0, vk1)], 1), np.stack([u0, np.full_like(u0, vk1)], 1)], 1))
    quads = (np.concatenate(corners).reshape(-1) if corners else np.zeros(0, np.int64))
    quad_uv = np.concatenate(uvs).reshape(-1, 2) if uvs else np.zeros((0, 2))
    sizes = [np.full(len(quads) // 4, 4)]
    all_corners, all_uvs = [quads], [quad_uv]
    n_verts = n_rings * segments
    if bottom_pole:
        pole = n_verts
        verts.append(np.array([[0.0, 0.0, z[0]]]))
        n_verts += 1
        tri = np.stack([np.full(segments, pole), (j + 1) % segments, j], 1)
        um = (j + 0.5) / segments
        tri_uv = np.stack([np.stack([um, np.full_like(um, v_coords[0])], 1),
                           np.stack([u1, np.full_like(um, v_coords[1])], 1),
                           np.stack([u0, np.full_like(um, v_coords[1])], 1)], 1)
        all_corners.append(tri.reshape(-1))
        all_uvs.append(tri_uv.reshape(-1, 2))
        sizes.append(np.full(segments, 3))
    if top_pole:
        pole = n_verts
        verts.append(np.array([[0.0, 0.0, z[-1]]]))
        last = (n_rings - 1) * segments
        tri = np.stack([last + j, last + (j + 1) % segments, np.full(segments, pole)], 1)
        um = (j + 0.5) / segments
        tri_uv = np.stack([np.stack([u0, np.full_like(um, v_coords[-2])], 1),
                           np.stack([u1, np.full_like(um, v_coords[-2])], 1),
                           np.stack([um, np.full_like(um, v_coords[-1])], 1)], 1)
        all_corners.append(tri.reshape(-1))
        all_uvs.append(tri_uv.reshape(-1, 2))
        sizes.append(np.full(segments, 3))
    size_arr = np.concatenate(sizes).astype(np.int64)
    return Part(np.concatenate(verts), np.concatenate(all_corners).astype(np.int64), size_arr,
                np.concatenate(all_uvs), np.zeros(len(size_arr), np.int64))


def sphere_profile(rings: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Unit-diameter sphere profile from the south to the north pole: (r, z), each (rings+1,)."""
    theta = np.linspace(0.0, np.pi, rings + 1)
    r = 0.5 * np.sin(theta)
    r[0] = r[-1] = 0.0
    return r, -0.5 * np.cos(theta)


def sphere(segments: int = 32, rings: int = 16, radial=None) -> Part:
    """Unit-diameter sphere about +z, v from the south pole (0) to the north pole (1)."""
    r, z = sphere_profile(rings)
    return revolve(r, z, segments, radial, v_coords=np.linspace(0.0, 1.0, rings + 1))


def cylinder(radius_m: float, height_m: float, segments: int = 24, caps: bool = True) -> Part:
    """Capped cylinder along +z from z=0 to ``height_m``."""
    if caps:
        r = np.array([0.0, radius_m, radius_m, 0.0])
        z = np.array([0.0, 0.0, height_m, height_m])
        part = revolve(r, z, segments)
        part.smooth = np.abs(part.sizes - 4) == 0  # side smooth, caps flat
        return part
    return revolve(np.array([radius_m, radius_m]), np.array([0.0, height_m]), segments)


def sweep(centres: np.ndarray, radii: np.ndarray, up: np.ndarray | None = None, segments: int = 12,
          cross: Callable[[np.ndarray], np.ndarray] | None = None, caps: bool = True) -> Part:
    """Tube along a polyline. centres: (K,3) m; radii: (K,) m; ``cross(angle)`` scales the section.

    UV: u = angle / 2 pi around the tube, v = normalised arc length. Ends are closed by fans.
    """
    centres = np.asarray(centres, float)
    tangents = np.gradient(centres, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    ref = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, float)
    normals = np.cross(ref, tangents)
    bad = np.linalg.norm(normals, axis=1) < 1e-6
    normals[bad] = np.cross([1.0, 0.0, 0.0], tangents[bad])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    binormals = np.cross(tangents, normals)
    ang = 2 * np.pi * np.arange(segments) / segments
    shape = np.ones(segments) if cross is None else cross(ang)
    ring = (np.cos(ang) * shape)[None, :, None] * normals[:, None, :] + \
        (np.sin(ang) * shape)[None, :, None] * binormals[:, None, :]
    verts = centres[:, None, :] + np.asarray(radii, float)[:, None, None] * ring
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(centres, axis=0), axis=1))]
    v = arc / arc[-1]
    K = len(centres)
    j = np.arange(segments)
    corners, uvs = [], []
    for k in range(K - 1):
        a, b = k * segments + j, k * segments + (j + 1) % segments
        corners.append(np.stack([a, b, b + segments, a + segments], 1))
        uvs.append(np.stack([np.stack([j / segments, np.full(segments, v[k])], 1),
                             np.stack([(j + 1) / segments, np.full(segments, v[k])], 1),
                             np.stack([(j + 1) / segments, np.full(segments, v[k + 1])], 1),
                             np.stack([j / segments, np.full(segments, v[k + 1])], 1)], 1))
    flat_verts = verts.reshape(-1, 3)
    all_c = [np.concatenate(corners).reshape(-1)]
    all_uv = [np.concatenate(uvs).reshape(-1, 2)]
    sizes = [np.full((K - 1) * segments, 4)]
    if caps:
        start, end = len(flat_verts), len(flat_verts) + 1
        flat_verts = np.vstack([flat_verts, centres[0], centres[-1]])
        last = (K - 1) * segments
        all_c += [np.stack([np.full(segments, start), (j + 1) % segments, j], 1).reshape(-1),
                  np.stack([np.full(segments, end), last + j, last + (j + 1) % segments], 1).reshape(-1)]
        all_uv += [np.zeros((3 * segments, 2)), np.ones((3 * segments, 2))]
        sizes += [np.full(segments, 3), np.full(segments, 3)]
    size_arr = np.concatenate(sizes).astype(np.int64)
    return Part(flat_verts, np.concatenate(all_c).astype(np.int64), size_arr, np.concatenate(all_uv),
                np.zeros(len(size_arr), np.int64))


_CUBE_FACES = (  # (normal axis, sign, u axis, v axis) so that u x v = outward normal
    (0, 1, 1, 2), (0, -1, 2, 1), (1, 1, 2, 0), (1, -1, 0, 2), (2, 1, 0, 1), (2, -1, 1, 0))


def rounded_box(size_m, radius_m: float, flat_steps: int = 3, round_steps: int = 3,
                atlas: bool = True) -> Part:
    """Box of ``size_m`` (3,) with edges rounded by ``radius_m``; one grid per face, welded.

    With ``atlas`` each face's UVs fill one tile of a 3x2 atlas in the order +x, -x, +y, -y, +z,
    -z (columns left to right, then the second row), u/v following the face grid; otherwise UVs
    are metric (1 unit = 1 m) planar projections.
    """
    half = np.asarray(size_m, float) / 2
    radius = float(min(radius_m, *(half * 0.999)))
    parts = []
    for fi, (axis, sign, ua, va) in enumerate(_CUBE_FACES):
        def coords(h):
            inner = h - radius
            band = inner + radius * np.sin(np.linspace(0, np.pi / 2, round_steps + 1))[1:]  # dense near edge
            flat = np.linspace(-inner, inner, flat_steps + 1)
            return np.r_[-band[::-1], flat, band]
        us, vs = coords(half[ua]), coords(half[va])
        U, V = np.meshgrid(us, vs, indexing="ij")
        p = np.zeros(U.shape + (3,))
        p[..., axis] = sign * half[axis]
        p[..., ua] = U
        p[..., va] = V
        inner = half - radius
        clamped = np.clip(p, -inner, inner)
        d = p - clamped
        n = np.linalg.norm(d, axis=-1, keepdims=True)
        p = clamped + d / np.where(n > 0, n, 1) * radius
        nu, nv = len(us), len(vs)
        idx = np.arange(nu * nv).reshape(nu, nv)
        a, b, c, dd = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
        quads = np.stack([a, b, c, dd], -1).reshape(-1, 4)
        if atlas:
            tu = (U - us[0]) / (us[-1] - us[0])
            tv = (V - vs[0]) / (vs[-1] - vs[0])
            col, row = fi % 3, fi // 3
            uv_grid = np.stack([(col + tu) / 3.0, (1 - row) * 0.5 + tv * 0.5], -1)
        else:
            uv_grid = np.stack([U, V], -1)
        uv_flat = uv_grid.reshape(-1, 2)
        parts.append(Part(p.reshape(-1, 3), quads.reshape(-1).astype(np.int64), np.full(len(quads), 4),
                          uv_flat[quads.reshape(-1)], np.zeros(len(quads), np.int64)))
    return weld(join(parts), tol_m=1e-9)


def box(size_m, offset_m=(0.0, 0.0, 0.0), uv_offset_m=(0.0, 0.0, 0.0)) -> Part:
    """Axis-aligned box of ``size_m`` (3,) centred at ``offset_m``; metric planar UVs, flat shaded.

    UVs are the two in-plane coordinates (m) of each face, shifted by ``uv_offset_m`` so adjacent
    boxes continue one texture (e.g. world-aligned floor boards).
    """
    half = np.asarray(size_m, float) / 2
    o = np.asarray(offset_m, float)
    verts, corners, uvs = [], [], []
    for axis, sign, ua, va in _CUBE_FACES:
        quad = []
        for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
            p = np.zeros(3)
            p[axis] = sign * half[axis]
            p[ua], p[va] = su * half[ua], sv * half[va]
            quad.append(p + o)
        base = len(verts)
        verts += quad
        corners += [base, base + 1, base + 2, base + 3]
        for q in quad:
            w = q + np.asarray(uv_offset_m, float)
            # keep a consistent in-plane orientation: horizontal faces use (x, y), walls use (x|y, z)
            uvs.append((w[0], w[1]) if axis == 2 else ((w[1], w[2]) if axis == 0 else (w[0], w[2])))
    return Part(np.array(verts), np.array(corners, np.int64), np.full(6, 4), np.array(uvs, float),
                np.zeros(6, np.int64), np.zeros(6, bool))


def polygon_prism(outline_xy: np.ndarray, z0: float, z1: float) -> Part:
    """Vertical prism over a convex outline (N,2) m between heights z0 < z1; metric UVs, flat shaded."""
    outline = np.asarray(outline_xy, float)
    n = len(outline)
    bottom = np.c_[outline, np.full(n, z0)]
    top = np.c_[outline, np.full(n, z1)]
    verts = np.vstack([bottom, top])
    j = np.arange(n)
    sides = np.stack([j, (j + 1) % n, n + (j + 1) % n, n + j], 1)
    edge_len = np.linalg.norm(outline[(j + 1) % n] - outline[j], axis=1)
    s0 = np.r_[0.0, np.cumsum(edge_len)[:-1]]
    side_uv = np.stack([np.stack([s0, np.full(n, z0)], 1), np.stack([s0 + edge_len, np.full(n, z0)], 1),
                        np.stack([s0 + edge_len, np.full(n, z1)], 1), np.stack([s0, np.full(n, z1)], 1)], 1)
    corners = np.concatenate([sides.reshape(-1), n + j, j[::-1]])
    uvs = np.vstack([side_uv.reshape(-1, 2), outline, outline[::-1]])
    sizes = np.r_[np.full(n, 4), n, n]
    return Part(verts, corners.astype(np.int64), sizes.astype(np.int64), uvs, np.zeros(n + 2, np.int64),
                np.zeros(n + 2, bool))


def grid_plane(x_edges: np.ndarray, y_edges: np.ndarray, keep: np.ndarray, z: float) -> Part:
    """Horizontal quads on the cells of a rectilinear grid where ``keep`` (nx-1, ny-1) is True; metric UVs."""
    quads, verts, uvs = [], [], []
    for i in range(len(x_edges) - 1):
        for j in range(len(y_edges) - 1):
            if not keep[i, j]:
                continue
            x0, x1, y0, y1 = x_edges[i], x_edges[i + 1], y_edges[j], y_edges[j + 1]
            base = len(verts)
            verts += [(x0, y0, z), (x1, y0, z), (x1, y1, z), (x0, y1, z)]
            uvs += [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
            quads.append([base, base + 1, base + 2, base + 3])
    q = np.array(quads, np.int64).reshape(-1)
    return Part(np.array(verts, float).reshape(-1, 3), q, np.full(len(quads), 4, np.int64), np.array(uvs, float),
                np.zeros(len(quads), np.int64), np.zeros(len(quads), bool))


# ---------------------------------------------------------------------------------------------
# bpy conversion


def to_object(part: Part, name: str, materials: Sequence, collection=None, location=(0.0, 0.0, 0.0),
              rotation_z_deg: float = 0.0):
    """Create a bpy mesh object from ``part`` with material slots ``materials``, linked to ``collection``."""
    import bpy

    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(part.vertices))
    mesh.vertices.foreach_set("co", part.vertices.astype(np.float32).reshape(-1))
    mesh.loops.add(len(part.corners))
    mesh.loops.foreach_set("vertex_index", part.corners.astype(np.int32))
    mesh.polygons.add(len(part.sizes))
    starts = np.r_[0, np.cumsum(part.sizes)[:-1]].astype(np.int32)
    mesh.polygons.foreach_set("loop_start", starts)
    mesh.polygons.foreach_set("material_index", part.materials.astype(np.int32))
    mesh.polygons.foreach_set("use_smooth", part.smooth.astype(bool))
    uv = mesh.uv_layers.new(name="UVMap")
    uv.data.foreach_set("uv", part.uvs.astype(np.float32).reshape(-1))
    mesh.update(calc_edges=True)
    for mat in materials:
        mesh.materials.append(mat)
    obj = bpy.data.objects.new(name, mesh)
    obj.location = location
    obj.rotation_euler = (0.0, 0.0, float(np.radians(rotation_z_deg)))
    (collection or bpy.context.scene.collection).objects.link(obj)
    return obj
