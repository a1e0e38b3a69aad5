"""The gallery's event frames, picks and drawing (rigidbench.report.gallery)."""

from __future__ import annotations

import io
from collections import namedtuple

import numpy as np
import pytest
from PIL import Image

from rigidbench.groundtruth.trajectory import Contact, Trajectory
from rigidbench.report import gallery as G

FPS, G_M_S2 = 24.0, 9.81


def bouncing_ball(h0=0.6, radius=0.03, e=0.5, frames=49):
    """Analytic drop and bounces of a ball (restitution e); returns (trajectory, contacts, t_contact, t_apex)."""
    t = np.arange(frames) / FPS
    t1 = np.sqrt(2 * h0 / G_M_S2)
    v1 = e * G_M_S2 * t1
    t2 = t1 + 2 * v1 / G_M_S2
    z = np.where(t < t1, h0 - 0.5 * G_M_S2 * t ** 2, 0.0)
    up = (t >= t1) & (t < t2)
    z[up] = v1 * (t[up] - t1) - 0.5 * G_M_S2 * (t[up] - t1) ** 2
    z = np.maximum(z, 0.0) + radius  # after the second landing it lies still (crude, fine here)
    pos = np.zeros((1, frames, 3))
    pos[0, :, 2] = z
    quat = np.tile([1.0, 0, 0, 0], (1, frames, 1))
    traj = Trajectory(("ball",), ("active",), FPS, pos, quat)
    # Bullet reports the touch in the frame after the impact instant, and again once the ball lands for good
    touching = [int(np.ceil(t1 * FPS))] + [f for f in range(frames) if t[f] >= t2]
    contacts = [Contact(int(f), "ball", "support", ((0, 0, 0),), ((0, 0, 1),), (0.0,)) for f in touching]
    return traj, contacts, t1, t1 + v1 / G_M_S2


def test_bounce_events_are_release_contact_apex_and_rest():
    traj, contacts, t1, t_apex = bouncing_ball()
    events = G.event_frames(traj, contacts, 49)
    assert [e.label for e in events] == ["release", "first contact", "rebound apex", "at rest"]
    assert events[0].frame == 0
    assert events[1].frame == int(np.ceil(t1 * FPS))
    assert abs(events[2].frame - t_apex * FPS) <= 1.0  # the sampled apex is within a frame of the analytic one
    assert events[3].frame > events[2].frame
    assert np.all(np.linalg.norm(traj.linear_velocity_m_s[0, events[3].frame:], axis=-1) < G.REST_SPEED_M_S)


def test_a_bounce_between_frames_counts_as_the_first_contact():
    # the contact test sees only the second landing; the first impact falls between two frames
    traj, contacts, t1, t_apex = bouncing_ball()
    late = [c for c in contacts if c.frame > int(np.ceil(t1 * FPS))]
    events = G.event_frames(traj, late, 49)
    assert [e.label for e in events] == ["release", "first contact", "rebound apex", "at rest"]
    assert events[1].frame == int(np.ceil(t1 * FPS)) == G.first_bounce(traj, 49)
    assert abs(events[2].frame - t_apex * FPS) <= 1.0


def test_contact_between_actors_is_preferred_and_initial_contacts_ignored():
    frames = 30
    pos = np.zeros((2, frames, 3))
    pos[0, :, 0] = np.minimum(np.arange(frames), 12) * 0.01  # a slides and stops at frame 12
    quat = np.tile([1.0, 0, 0, 0], (2, frames, 1))
    traj = Trajectory(("a", "b"), ("active", "active"), FPS, pos, quat)
    c = lambda f, x, y: Contact(f, x, y, ((0, 0, 0),), ((0, 0, 1),), (0.0,))  # noqa: E731
    contacts = [c(f, "a", "ramp_a") for f in range(frames)] + [c(5, "a", "support"), c(9, "a", "b")]
    assert G.first_new_contact(traj, contacts, frames) == 9
    events = G.event_frames(traj, contacts, frames)
    assert [(e.frame, e.label) for e in events] == [(0, "release"), (9, "first contact"), (13, "at rest")]


def test_a_clip_that_never_settles_ends_on_its_last_frame():
    frames = 20
    pos = np.zeros((1, frames, 3))
    pos[0, :, 0] = np.arange(frames) * 0.05
    traj = Trajectory(("a",), ("active",), FPS, pos, np.tile([1.0, 0, 0, 0], (1, frames, 1)))
    assert G.rest_frame(traj, frames) is None
    assert [(e.frame, e.label) for e in G.event_frames(traj, [], frames)] == [(0, "release"), (9, "in motion"),
                                                                              (19, "last frame")]


Row = namedtuple("Row", "sample_id task scene")


def test_picks_cover_every_task_and_scene_with_different_examples():
    tasks, scenes = ["t0", "t1", "t2"], ["s0", "s1", "s2", "s3"]
    rows = [Row(f"{i:05d}", tasks[i % 3], scenes[(i // 3) % 4]) for i in range(36)]
    by_task, by_scene = G.pick_examples(rows, tasks, scenes)
    assert set(by_task) == set(tasks) and set(by_scene) == set(scenes)
    ids = [r.sample_id for r in [*by_task.values(), *by_scene.values()]]
    assert len(ids) == len(set(ids))
    assert all(r.task == t for t, r in by_task.items()) and all(r.scene == s for s, r in by_scene.items())
    assert len({r.task for r in by_scene.values()}) == 3  # the scene sheets rotate through the tasks


def test_marker_subset_keeps_a_few_per_actor():
    actor_index = np.array([0] * 100 + [1] * 5 + [2] * 40)
    keep = G.marker_subset(actor_index, per_actor=8)
    counts = np.bincount(actor_index[keep])
    assert list(counts) == [8, 5, 8]


def test_outline_is_the_mask_border():
    m = np.zeros((10, 10), bool)
    m[2:8, 3:7] = True
    edge = G.outline(m)
    assert edge[2, 3] and edge[7, 6] and not edge[5, 5] and not edge[0, 0]


def test_sheet_draws_outlines_and_hollow_markers_and_fits_the_budget():
    rng = np.random.default_rng(0)
    T, H, W = 5, 88, 160
    frames = {t: (rng.random((H, W, 3)) * 60 + 100).astype(np.uint8) for t in (0, 4)}
    masks = np.zeros((T, 1, H, W), bool)
    masks[:, 0, 30:60, 60:100] = True
    depth = np.full((T, H, W), 3.0, np.float32)
    depth[:, 30:60, 60:100] = 1.5
    tracks = np.tile(np.array([[80.0, 45.0]]), (1, T, 1))
    vis = np.ones((1, T), bool)
    events = [G.Event(0, "release"), G.Event(4, "at rest")]
    img = G.example_sheet(frames, events, masks, depth, tracks, vis, np.array([0]), 24.0, "title", ["ball"],
                          cell_width=320)
    arr = np.asarray(img)
    assert arr.shape[1] == 2 * 320 + 6
    # masks and depth kept for the event frames only (as the gallery script stores them) draw the same sheet
    sparse = G.example_sheet(frames, events, {t: masks[t] for t in (0, 4)}, {t: depth[t] for t in (0, 4)}, tracks,
                             vis, np.array([0]), 24.0, "title", ["ball"], cell_width=320)
    np.testing.assert_array_equal(np.asarray(sparse), arr)
    blue = np.all(arr == G.actor_colours(1)[0], axis=-1)
    assert blue.sum() > 50  # outlines and markers in the actor's colour
    cell = G.annotate(frames[0], masks[0], tracks, vis, np.array([0]), 0, (320, 176))
    centre = np.asarray(cell)[90, 160]
    assert not np.array_equal(centre, G.actor_colours(1)[0])  # the marker is hollow: its centre is the frame
    data = G.encode_under(img, 60_000)
    assert len(data) <= 60_000 and Image.open(io.BytesIO(data)).format == "JPEG"
    with pytest.raises(ValueError):
        G.encode_under(img, 100)
