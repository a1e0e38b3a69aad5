"""Colour management and side naming of rendered bundles (issue 18).

A lemon rendered at the `test` preset must come out lemon yellow, not the cream that Blender's default
AgX view transform makes of it; in ramp_collision the bundle must say, from the camera's point of
view, which (neutrally named) ramp is on the left of the image.
"""

from __future__ import annotations

import colorsys
import dataclasses

import numpy as np
import pytest

from fixtures.blender import requires_bpy
from fixtures.scenes import free_fall_spec, ramp_collision_spec

from rigidbench.config import registry as load_registry
from rigidbench.groundtruth import bundle as B

pytestmark = [pytest.mark.integration, requires_bpy]


@pytest.fixture(scope="module")
def reg():
    return load_registry()


def _render(reg, spec, path, frames=1):
    from rigidbench.blender.render import render_spec

    preset = dataclasses.replace(reg.preset("test"), frames=frames)
    return B.Sample(render_spec(spec, reg, preset, path, device="cpu", threads=2))


def test_lemon_is_saturated_yellow(reg, tmp_path):
    """Photo lemon ~ (240, 220, 60) sRGB: hue ~53 deg, HSV saturation ~0.75. At the preview preset
    AgX gave (216, 192, 140): hue 41, HSV saturation 0.35; Standard (242, 228, 99): hue 54, 0.59.
    At the test preset (2 samples) Standard gives about (186, 176, 71): hue 55, 0.62."""
    s = _render(reg, free_fall_spec(reg, asset="lemon", drop_m=0.0), tmp_path / "lemon")
    cm = s.metadata["render"]["color_management"]
    assert cm["view_transform"] == "Standard" and cm["look"] == "None"
    mask = s.masks[0, 0]
    assert mask.sum() > 30
    r, g, b = s.frame(0)[mask].astype(float).mean(0) / 255
    hue, sat, _ = colorsys.rgb_to_hsv(r, g, b)
    assert 45 <= hue * 360 <= 65, (hue * 360, (r, g, b))
    assert sat >= 0.5, (sat, (r, g, b))
    assert b < 0.6 * min(r, g), (r, g, b)  # yellow, not cream


@pytest.mark.parametrize("azimuth_deg", [270.0])  # (at 90 deg the hand-built layout hides ramp_a at frame 0)
def test_ramp_sides_follow_the_camera(reg, tmp_path, azimuth_deg):
    spec = dataclasses.replace(ramp_collision_spec(reg), azimuth_candidates_deg=(azimuth_deg,))
    s = _render(reg, spec, tmp_path / "ramps")
    sides = s.metadata["image_sides"]
    assert "camera view" in sides["convention"]
    names = list(s.actor_names) if hasattr(s, "actor_names") else list(s.metadata["actor_names"])
    mean_x = {}
    cols = np.arange(s.resolution[0])
    for k, n in enumerate(names):
        m = s.masks[0, k]
        assert m.any(), n
        mean_x[n] = float((m * cols[None, :]).sum() / m.sum())
    a, b = sorted(("ramp_a", "ramp_b"), key=mean_x.get)  # a: the ramp more to the left in the image
    assert sides["actors"][a] == "left" and sides["actors"][b] == "right", (sides, mean_x)
    assert {sides["actors"]["ramp_a"], sides["actors"]["ramp_b"]} == {"left", "right"}
    # each object starts on the same side as its ramp
    assert sides["actors"]["orange_0"] == sides["actors"]["ramp_a"]
    assert sides["actors"]["apple_1"] == sides["actors"]["ramp_b"]
