"""The pure parts of the camera clearance check and background preference (docs/camera.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rigidbench.blender.camera import box_distance, choose_view, item_kind, summarise_view, view_grid_uv


def test_view_grid_covers_the_image_at_cell_centres():
    uv = view_grid_uv(4, 2, 1280.0, 704.0)
    assert uv.shape == (8, 2)
    np.testing.assert_allclose(sorted(set(uv[:, 0])), [160.0, 480.0, 800.0, 1120.0])
    np.testing.assert_allclose(sorted(set(uv[:, 1])), [176.0, 528.0])


def test_box_distance_is_zero_inside_and_euclidean_outside():
    lo, hi = np.zeros(3), np.ones(3)
    assert box_distance([0.5, 0.5, 0.5], lo, hi) == 0.0
    assert box_distance([2.0, 0.5, 0.5], lo, hi) == pytest.approx(1.0)
    assert box_distance([4.0, 5.0, 0.5], lo, hi) == pytest.approx(5.0)  # (3, 4) off the corner edge


def test_summarise_view_counts_near_hits_above_the_top_only():
    # near = 2 m, support top at z = 0.8: ten rays, hand-classified
    d = [1.0, 1.0, 1.0, 1.0, 3.0, 3.0, 3.0, 3.0, math.inf, 1.5]
    z = [1.5, 0.5, 1.5, 1.2, 1.5, 1.5, 0.81, 1.0, -math.inf, 2.0]
    k = ["structure",  # a wall beside the camera: obstructs
         "furnishing",  # below the top face (the support's own cabinet front): ignored
         "actor",  # an actor is never an obstruction
         "furnishing",  # a chair in front of the action: obstructs
         "furnishing",  # a sofa behind the action: furnished background
         "structure",  # the back wall: background, not furnishing
         "furnishing",  # just at the top face (within ABOVE_TOP_M): ignored
         "furnishing",  # furnished background
         "none",  # sky
         "structure"]  # another near wall: obstructs
    view = summarise_view(np.array(d), np.array(z), k, near_m=2.0, top_z_m=0.8)
    assert view.obstruction == pytest.approx(3 / 10)
    assert view.furnishing == pytest.approx(2 / 10)


def test_item_kind_strips_the_scene_prefix():
    assert item_kind("modern_loft_wall_north_004", "modern_loft") == "structure"
    assert item_kind("beach_gazebo_sea_012", "beach_gazebo") == "structure"
    assert item_kind("beach_gazebo_shore_003", "beach_gazebo") == "structure"  # the wet-sand band
    assert item_kind("support_counter", "modern_loft") == "structure"
    assert item_kind("modern_loft_sofa_007", "modern_loft") == "furnishing"
    # a scene id containing a structure word does not make its furniture structure
    assert item_kind("floor_show_sofa_003", "floor_show") == "furnishing"


def test_choose_view_prefers_furnishing_only_among_views_that_see_the_actors_well():
    # (furnishing, relative azimuth, visibility) in seeded order
    accepted = [(0.10, -30.0, 1.00),  # sees everything, a little furniture behind
                (0.40, 0.0, 0.55),  # a furnished background but half the actors hidden (the 00027 case)
                (0.25, 15.0, 0.92),  # within 0.1 of the best: the most furnished of the eligible views
                (0.25, 30.0, 0.95)]  # a tie on furnishing: the earlier view keeps it
    assert choose_view(accepted, visibility_margin=0.1) == (0.25, 15.0, 0.92)
    # with no margin only the best-seeing view is eligible; with an unbounded one the old rule returns
    assert choose_view(accepted, visibility_margin=0.0) == (0.10, -30.0, 1.00)
    assert choose_view(accepted, visibility_margin=1.0) == (0.40, 0.0, 0.55)


def test_choose_view_needs_a_view():
    with pytest.raises(ValueError, match="at least one"):
        choose_view([], visibility_margin=0.1)
