"""Wall items slide beside windows (blender.assets.scenes.slide_clear), checked on hand-made walls."""

import pytest

from rigidbench.blender.assets.scenes import slide_clear


def test_an_item_clear_of_every_window_stays_where_it_was_put():
    assert slide_clear(1.0, 0.4, 8.0, [(3.0, 5.0)], margin_m=0.1) == 1.0


def test_an_item_over_a_window_moves_to_the_nearer_side():
    # window 3-5 m on an 8 m wall; a 0.8 m item centred at 3.4 m goes left (centre 2.5), at 4.8 m right (5.5)
    assert slide_clear(3.4, 0.4, 8.0, [(3.0, 5.0)], margin_m=0.1) == pytest.approx(2.5)
    assert slide_clear(4.8, 0.4, 8.0, [(3.0, 5.0)], margin_m=0.1) == pytest.approx(5.5)


def test_a_side_without_room_is_skipped_and_windows_on_both_sides_are_respected():
    # the left side has 0.9 m for a 1.6 m item; it goes right of the window, clear of the second window
    assert slide_clear(1.5, 0.8, 10.0, [(1.0, 3.0), (6.0, 7.5)], margin_m=0.1) == pytest.approx(3.9)
    # between two windows 1.5 m apart, a 1.2 m item centred over the first lands in the gap (centre 3.7)
    assert slide_clear(2.6, 0.6, 10.0, [(1.0, 3.0), (4.5, 6.0)], margin_m=0.1) == pytest.approx(3.7)


def test_no_place_beside_the_window_leaves_the_item_out():
    # a 4.85 m wall with a 2.6 m window in the middle: 1.125 m each side, too little for a 1.6 m bookcase
    assert slide_clear(1.45, 0.8, 4.85, [(1.125, 3.725)], margin_m=0.1) is None
    assert slide_clear(0.97, 0.45, 4.85, [(1.125, 3.725)], margin_m=0.1) == pytest.approx(0.575)
