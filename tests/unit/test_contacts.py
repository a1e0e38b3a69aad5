"""Mesh-proximity contacts on hand-placed unit cubes and a sphere (numpy only)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rigidbench.blender.assets.standin import box, object_mesh
from rigidbench.groundtruth.contacts import (contact_pairs, convex_hull, detect_contacts, farthest_points,
                                             pair_contact, quat_to_matrix)

TOL = 0.003
I3 = np.eye(3)


@pytest.fixture(scope="module")
def cube():
    return convex_hull(box().vertices)  # unit cube centred on the origin


def test_cube_hull_has_six_planes_and_eight_vertices(cube):
    assert len(cube.vertices) == 8
    assert len(cube.normals) == 6  # twelve triangles merged into six faces
    assert np.allclose(np.sort(cube.offsets), 0.5)
    assert cube.radius_m == pytest.approx(math.sqrt(3) / 2)


@pytest.mark.parametrize("gap_m, touching", [(0.0, True), (0.002, True), (0.0029, True), (0.0031, False),
                                             (0.01, False), (-0.001, True)])
def test_stacked_cubes_touch_iff_within_tolerance(cube, gap_m, touching):
    hit = pair_contact(cube, I3, np.array([0.0, 0.0, 1.0 + gap_m]), cube, I3, np.zeros(3), TOL, 5)
    assert (hit is not None) == touching
    if touching:
        points, normals, dist = hit
        assert np.allclose(dist, gap_m, atol=1e-12)
        assert np.allclose(normals, [0.0, 0.0, 1.0])  # from b (below) towards a (above)
        assert np.allclose(points[:, 2], 0.5 + gap_m / 2)  # midway across the gap
        assert len(points) <= 5


def test_normals_point_from_b_to_a_when_roles_swap(cube):
    points, normals, _ = pair_contact(cube, I3, np.zeros(3), cube, I3, np.array([0.0, 0.0, 1.001]), TOL, 5)
    assert np.allclose(normals, [0.0, 0.0, -1.0])
    side = pair_contact(cube, I3, np.array([-1.002, 0.0, 0.0]), cube, I3, np.zeros(3), TOL, 5)
    assert np.allclose(side[1], [-1.0, 0.0, 0.0])


def test_face_contact_keeps_at_most_five_spread_points(cube):
    points, normals, dist = pair_contact(cube, I3, np.array([0.0, 0.0, 1.001]), cube, I3, np.zeros(3), TOL, 5)
    # Face on face: the four corners of each cube are candidates (eight, coincident in pairs).
    assert 4 <= len(points) <= 5
    corners = {(round(x, 6), round(y, 6)) for x, y in points[:, :2]}
    assert corners == {(sx, sy) for sx in (-0.5, 0.5) for sy in (-0.5, 0.5)}


def test_rotated_cube_corner_on_face(cube):
    # Rotate the upper cube so a single corner points down, then lower it onto the lower cube.
    tilt = math.atan(math.sqrt(2))
    qa = np.array([math.cos(tilt / 2), math.sin(tilt / 2) / math.sqrt(2), -math.sin(tilt / 2) / math.sqrt(2), 0.0])
    ra = quat_to_matrix(qa)
    lowest = (cube.vertices @ ra.T)[:, 2].min()
    assert lowest == pytest.approx(-math.sqrt(3) / 2)
    pos = np.array([0.0, 0.0, 0.5 - lowest + 0.001])
    points, normals, dist = pair_contact(cube, ra, pos, cube, I3, np.zeros(3), TOL, 5)
    assert len(points) == 1
    assert np.allclose(points[0], [0.0, 0.0, 0.5005])
    assert dist[0] == pytest.approx(0.001)
    assert pair_contact(cube, ra, pos + [0, 0, 0.0025], cube, I3, np.zeros(3), TOL, 5) is None


def test_sphere_resting_on_box_touches_at_its_bottom():
    sphere = convex_hull(object_mesh("ellipsoid", (0.08, 0.08, 0.08)).vertices)
    slab = convex_hull(box().fitted((1.0, 1.0, 0.05)).vertices)
    points, normals, dist = pair_contact(sphere, I3, np.array([0.2, 0.1, 0.025 + 0.04 + 0.001]), slab, I3,
                                         np.zeros(3), TOL, 5)
    assert 1 <= len(points) <= 5
    assert np.allclose(normals, [0.0, 0.0, 1.0])
    assert np.all(np.linalg.norm(points[:, :2] - [0.2, 0.1], axis=1) < 0.02)
    assert dist.min() == pytest.approx(0.001, abs=1e-9)


def test_farthest_points_spreads_out():
    pts = np.array([[0.0, 0, 0], [0.01, 0, 0], [1.0, 0, 0], [0.5, 0, 0], [0.99, 0, 0]])
    assert list(farthest_points(pts, 3, start=0)) == [0, 2, 3]
    assert len(farthest_points(pts[:2], 5)) == 2


def test_contact_pairs_skip_passive_pairs():
    assert contact_pairs(["passive", "active", "active", "passive"]) == [(1, 2), (1, 0), (1, 3), (2, 0), (2, 3)]


def test_detect_contacts_over_frames(cube):
    # Body a falls onto b: gaps 0.1, 0.01, 0.002, 0.0 across four frames.
    gaps = np.array([0.1, 0.01, 0.002, 0.0])
    pos = np.zeros((2, 4, 3))
    pos[0, :, 2] = 1.0 + gaps
    quat = np.zeros((2, 4, 4))
    quat[..., 0] = 1.0
    contacts = detect_contacts(["a", "b"], [cube, cube], pos, quat, [(0, 1)], TOL, 5)
    assert [c.frame for c in contacts] == [2, 3]
    assert all(c.a == "a" and c.b == "b" for c in contacts)
    assert np.allclose(contacts[0].distances_m, 0.002)
    assert np.allclose(contacts[1].normals, [0.0, 0.0, 1.0])
