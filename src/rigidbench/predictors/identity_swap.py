"""``identity-swap``: the actors keep their shape and motion but take on another object's appearance.

The reference example is re-simulated and re-rendered (same spec, camera, seed, preset and device
kind, see ``counterfactuals.render_counterfactual``) with every active actor dressed in the
materials of a donor object (``DONORS``: a fixed table chosen so each donor looks clearly different
from its recipient; objects outside the table take the next object id in sorted order). Each
material slot k of the actor takes the donor's slot k mod n. Geometry is untouched, so masks,
depth and point tracks are exactly the reference's.

Severity s blends the swapped appearance into the actor pixels: at frames t >= 1, pixels inside
the union of the reference's active-actor masks become (1 - s) reference + s swapped (rounded);
every other pixel, and all of frame 0 (the conditioning frame), stay the reference. At s = 0 the
prediction is the reference itself and nothing is rendered.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..blender.overrides import RenderOverrides
from ..config import Registry, registry as packaged_registry
from ..errors import PredictionError
from ..groundtruth.bundle import Sample
from .counterfactuals import render_counterfactual, scratch_bundle_dir
from .image_space import reference

log = logging.getLogger(__name__)

#: recipient object id -> donor object id (primary colours and patterns far apart).
DONORS: dict[str, str] = {
    "apple": "lemon", "banana": "kiwi", "baseball": "cricket_ball", "bouncy_ball": "coconut",
    "coconut": "tennis_ball", "cricket_ball": "baseball", "food_can": "watermelon", "kiwi": "orange",
    "large_dice": "pomegranate", "lemon": "apple", "mango": "large_dice", "orange": "large_dice",
    "peach": "tennis_ball", "pear": "tomato", "plastic_bottle": "red_bull_can", "pomegranate": "large_dice",
    "red_bull_can": "watermelon", "rubiks_cube": "orange", "rugby_ball": "bouncy_ball", "soda_can": "coconut",
    "tennis_ball": "cricket_ball", "tomato": "pear", "toy_duck": "rubiks_cube", "watermelon": "tomato",
}


def donor_for(asset: str, object_ids) -> str:
    """The donor object id for ``asset``: ``DONORS`` when both are configured, else the next id in sorted order."""
    ids = sorted(object_ids)
    donor = DONORS.get(asset)
    if donor in ids and donor != asset:
        return donor
    others = [i for i in ids if i != asset]
    if not others:
        raise ValueError(f"object '{asset}' has no other configured object to lend it an appearance")
    return next((i for i in others if i > asset), others[0])


def blend_inside_masks(reference: np.ndarray, swapped: np.ndarray, masks: np.ndarray, severity: float) -> np.ndarray:
    """reference, swapped: (T,H,W,3) uint8; masks (T,A,H,W) bool. Returns (T,H,W,3) uint8: the reference with
    (1 - s) reference + s swapped inside the union of the masks at frames t >= 1."""
    out = reference.copy()
    inside = masks.any(axis=1)
    inside[0] = False
    mixed = np.rint((1.0 - severity) * reference[inside].astype(np.float64)
                    + severity * swapped[inside].astype(np.float64))
    out[inside] = np.clip(mixed, 0, 255).astype(np.uint8)
    return out


def swapped_overrides(sample, registry):
    """RenderOverrides dressing each active actor of ``sample`` in its donor's materials."""
    bodies = {b.name: b for b in sample.spec.bodies}
    names = [sample.actor_names[a] for a in sample.active_indices]
    return RenderOverrides(materials_from={n: donor_for(bodies[n].asset, registry.objects) for n in names})


def prediction_from_swapped(sample, swapped, severity: float):
    """A Prediction of reference ``sample`` blended with the rendered swapped bundle ``swapped`` at ``severity``."""
    if not np.array_equal(swapped.masks, sample.masks):
        raise PredictionError(f"example {sample.sample_id}: the re-rendered actors do not cover the reference's "
                                  "pixels (the re-simulation diverged); cannot swap appearance in place")
    pred = reference(sample, 0.0)
    pred.frames = blend_inside_masks(pred.frames, swapped.frames, pred.state.masks, float(severity))
    return pred


def identity_swap(sample, severity: float, bundle_dir: str | Path | None = None, registry: Registry | None = None,
                  scratch_dir: str | Path | None = None):
    """Actors shown with their donors' appearance, blended in with weight ``severity`` from frame 1 on."""
    if severity == 0:
        return reference(sample, 0.0)
    reg = registry if registry is not None else packaged_registry()
    overrides = swapped_overrides(sample, reg)
    log.info("example %s: rendering actors with donor materials %s", sample.sample_id, dict(overrides.materials_from))
    if bundle_dir is not None:
        path = render_counterfactual(sample, sample.spec, reg, bundle_dir, overrides)
        return prediction_from_swapped(sample, Sample(path), severity)
    with scratch_bundle_dir(sample.sample_id, scratch_dir) as tmp:  # inside the run's output folder
        path = render_counterfactual(sample, sample.spec, reg, tmp / sample.sample_id, overrides)
        return prediction_from_swapped(sample, Sample(path), severity)


__all__ = ["DONORS", "donor_for", "blend_inside_masks", "swapped_overrides", "prediction_from_swapped",
           "identity_swap"]
